// Sample positions o + t·d and their directions, `samples` per ray, one
// invocation per ray, as the cpu engine's `points_along_rays` in
// `engine::cpu::model` (the product rounded before the sum, as the cpu).

@group(0) @binding(1) var<storage, read> origins: array<f32>;
@group(0) @binding(2) var<storage, read> directions: array<f32>;
@group(0) @binding(3) var<storage, read> t: array<f32>;
@group(0) @binding(4) var<storage, read_write> positions: array<f32>;
@group(0) @binding(5) var<storage, read_write> sample_directions: array<f32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let r = ray_index(id);
    if (r >= params.rays) {
        return;
    }
    let n = params.samples;
    for (var k = 0u; k < n; k++) {
        let s = r * n + k;
        for (var c = 0u; c < 3u; c++) {
            let d = directions[3u * r + c];
            positions[3u * s + c] = origins[3u * r + c] + unfused(t[s] * d);
            sample_directions[3u * s + c] = d;
        }
    }
}
