// Mip-NeRF's 2-tap max, 2-tap blur of the weights before resampling (mip.py
// `resample_along_rays`), one invocation per ray, as
// `engine::cpu::sampling::blur_weights`.

@group(0) @binding(1) var<storage, read> weights: array<f32>;
@group(0) @binding(2) var<storage, read_write> blurred: array<f32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let r = ray_index(id);
    if (r >= params.rays) {
        return;
    }
    let bins = params.samples;
    let o = r * bins;
    for (var i = 0u; i < bins; i++) {
        let left = weights[o + max(i, 1u) - 1u];
        let right = weights[o + min(i + 1u, bins - 1u)];
        let w = weights[o + i];
        blurred[o + i] = 0.5 * (max(left, w) + max(w, right));
    }
}
