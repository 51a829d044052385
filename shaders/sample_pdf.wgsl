// Inverse-CDF sampling of a piecewise-constant pdf, one invocation per ray:
// the two passes of `engine::cpu::sampling::sample_pdf` (see there for the
// reasoning), operation for operation. The bin of each sample comes from
// additions, multiplications and comparisons only, which WGSL rounds as the
// cpu does, so both engines pick the same bin; the position inside it
// differs at most by the division's 2.5 ulp.

@group(0) @binding(1) var<storage, read> edges: array<f32>;
@group(0) @binding(2) var<storage, read> weights: array<f32>;
@group(0) @binding(3) var<storage, read_write> samples: array<f32>;

// Finite, positive and normal weights count; everything else is zero. Read
// from the bits, so no compiler assumption about NaN can change it.
fn padded_weight(w: f32) -> f32 {
    let bits = bitcast<u32>(w);
    let exponent = (bits >> 23u) & 0xffu;
    var v = 0.0;
    if ((bits >> 31u) == 0u && exponent != 0u && exponent != 255u) {
        v = w;
    }
    return v + params.padding;
}

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let r = ray_index(id);
    if (r >= params.rays) {
        return;
    }
    let bins = params.bins;
    let count = params.samples;
    let e = r * (bins + 1u);
    let w = r * bins;
    let ray = params.ray_base + r;

    var total = 0.0;
    var last = 0u;
    for (var i = 0u; i < bins; i++) {
        let v = padded_weight(weights[w + i]);
        total += v;
        if (v > 0.0) {
            last = i;
        }
    }
    // No mass, or a sum past f32::MAX: equal mass per bin.
    let equal = !(total > 0.0 && total <= 3.4028235e38);
    if (equal) {
        total = f32(bins);
        last = bins - 1u;
    }

    var bin = 0u;
    var below = 0.0;
    var above = 1.0;
    if (!equal) {
        above = padded_weight(weights[w]);
    }
    var previous = edges[e];
    for (var k = 0u; k < count; k++) {
        var xi = 0.5;
        if (params.use_jitter != 0u) {
            xi = uniform01(params.seed, ray, k);
        }
        let target_mass = ((f32(k) + xi) * params.inverse_count) * total;
        while (bin < last && above <= target_mass) {
            bin += 1u;
            below = above;
            var v = 1.0;
            if (!equal) {
                v = padded_weight(weights[w + bin]);
            }
            above = below + v;
        }
        let mass = above - below;
        var fraction = 1.0;
        if (mass > 0.0) {
            fraction = min((target_mass - below) / mass, 1.0);
        }
        let lo = edges[e + bin];
        let hi = edges[e + bin + 1u];
        let t = max(min(lo + unfused((hi - lo) * fraction), hi), previous);
        samples[r * count + k] = t;
        previous = t;
    }
}
