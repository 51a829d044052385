// Compositing intervals from sorted samples, the last one ending at far,
// one invocation per ray, as `engine::cpu::sampling::intervals_to_far`.

@group(0) @binding(1) var<storage, read> t: array<f32>;
@group(0) @binding(2) var<storage, read> far: array<f32>;
@group(0) @binding(3) var<storage, read_write> dt: array<f32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let r = ray_index(id);
    if (r >= params.rays) {
        return;
    }
    let n = params.samples;
    let o = r * n;
    for (var i = 0u; i + 1u < n; i++) {
        dt[o + i] = t[o + i + 1u] - t[o + i];
    }
    dt[o + n - 1u] = max(far[r] - t[o + n - 1u], 0.0);
}
