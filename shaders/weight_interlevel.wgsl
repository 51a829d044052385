// The interlevel loss (Mip-NeRF 360, eq. 13) of a proposal level against
// the final level's weights (held still), one invocation per ray, as
// `engine::cpu::weight_losses::interlevel` with its edges in s: each final
// interval's bound is the proposal weight of the intervals that overlap it;
// the excess of its weight over the bound, squared over the weight, is the
// loss, and −2·excess/(w + ε)·scale the gradient on each of those proposal
// weights (a difference array over the proposal's intervals, then its
// running sum). `samples` is the final level's intervals per ray, `bins`
// the proposal's.

@group(0) @binding(1) var<storage, read> fine_edges: array<f32>;
@group(0) @binding(2) var<storage, read> fine_weights: array<f32>;
@group(0) @binding(3) var<storage, read> edges: array<f32>;
@group(0) @binding(4) var<storage, read> weights: array<f32>;
// R × (bins + 1) scratch: each ray's running sum of proposal weights.
@group(0) @binding(5) var<storage, read_write> cumulative: array<f32>;
@group(0) @binding(6) var<storage, read_write> d_weights: array<f32>;
@group(0) @binding(7) var<storage, read_write> ray_loss: array<f32>;

// multinerf's ε: f32's machine epsilon.
const INTERLEVEL_EPSILON: f32 = 1.1920929e-7;

// The proposal edges (of `count` + 1 at `base`) whose s satisfies
// s ≤ x (`inclusive`) or s < x: how many, as Rust's `partition_point`.
fn edges_below(base: u32, count: u32, x: f32, inclusive: bool) -> u32 {
    var lo = 0u;
    var hi = count + 1u;
    while (lo < hi) {
        let mid = (lo + hi) / 2u;
        let s = spacing_of(edges[base + mid]);
        if (s < x || (inclusive && s == x)) {
            lo = mid + 1u;
        } else {
            hi = mid;
        }
    }
    return lo;
}

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let r = invocation(id);
    if (r >= params.count) {
        return;
    }
    let n = params.samples;
    let m = params.bins;
    let c = r * (m + 1u);
    let base = r * (m + 1u);
    cumulative[c] = 0.0;
    for (var j = 0u; j < m; j++) {
        cumulative[c + j + 1u] = cumulative[c + j] + max(weights[r * m + j], 0.0);
        d_weights[r * m + j] = 0.0;
    }
    var total = 0.0;
    for (var i = 0u; i < n; i++) {
        let lo = spacing_of(fine_edges[r * (n + 1u) + i]);
        let hi = spacing_of(fine_edges[r * (n + 1u) + i + 1u]);
        let at_or_below = edges_below(base, m, lo, true);
        let first = min(max(at_or_below, 1u) - 1u, m);
        let end = max(min(edges_below(base, m, hi, false), m), first);
        let bound = cumulative[c + end] - cumulative[c + first];
        let w = fine_weights[r * n + i];
        let excess = max(w - bound, 0.0);
        if (excess > 0.0) {
            let denominator = w + INTERLEVEL_EPSILON;
            total += excess * excess / denominator;
            let g = -2.0 * excess / denominator * params.scale;
            // The difference array's entry m is never summed.
            if (first < m) {
                d_weights[r * m + first] += g;
            }
            if (end < m) {
                d_weights[r * m + end] -= g;
            }
        }
    }
    var running = 0.0;
    for (var j = 0u; j < m; j++) {
        running += d_weights[r * m + j];
        d_weights[r * m + j] = running;
    }
    ray_loss[r] = total;
}
