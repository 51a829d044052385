// The distortion loss's gradient (Mip-NeRF 360, eq. 15) on each weight of
// a level's intervals in s, times `scale`, one invocation per ray, as
// `engine::cpu::weight_losses::distortion` (in f32 where the cpu sums in
// f64): with the midpoints in order, the double sum's gradient on w_i is
// 2(m_i W_i − M_i) + 2(M'_i − m_i W'_i) + ⅔ w_i δs_i, with W, M the weight
// and moment before i and W′, M′ after it.

@group(0) @binding(1) var<storage, read> edges: array<f32>;
@group(0) @binding(2) var<storage, read> weights: array<f32>;
@group(0) @binding(3) var<storage, read_write> d_weights: array<f32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let r = invocation(id);
    if (r >= params.count) {
        return;
    }
    let n = params.samples;
    let e = r * (n + 1u);
    var total_weight = 0.0;
    var total_moment = 0.0;
    for (var i = 0u; i < n; i++) {
        let w = weights[r * n + i];
        let mid = 0.5 * (spacing_of(edges[e + i]) + spacing_of(edges[e + i + 1u]));
        total_weight += w;
        total_moment += w * mid;
    }
    var before = 0.0;
    var moment_before = 0.0;
    for (var i = 0u; i < n; i++) {
        let w = weights[r * n + i];
        let s0 = spacing_of(edges[e + i]);
        let s1 = spacing_of(edges[e + i + 1u]);
        let mid = 0.5 * (s0 + s1);
        let width = s1 - s0;
        let after = total_weight - before - w;
        let moment_after = total_moment - moment_before - w * mid;
        let gradient = 2.0 * (mid * before - moment_before)
            + 2.0 * (moment_after - mid * after)
            + 2.0 * w * width / 3.0;
        d_weights[r * n + i] = gradient * params.scale;
        before += w;
        moment_before += w * mid;
    }
}
