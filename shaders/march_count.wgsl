// Pass 1 of the march: samples per ray (`march_common.wgsl` is prepended).

@group(0) @binding(0) var<uniform> params: MarchParams;
@group(0) @binding(1) var<storage, read> bitfield: array<u32>;
@group(0) @binding(2) var<storage, read> origins: array<f32>;
@group(0) @binding(3) var<storage, read> directions: array<f32>;
@group(0) @binding(4) var<storage, read_write> counts: array<u32>;

// Counting writes nothing.
fn emit_sample(m: RayMarch, n: u32, k: u32, s: f32) {}

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let ray = id.x + id.y * params.row_stride;
    if (ray >= params.ray_count) {
        return;
    }
    let m = prepare(ray);
    var emitted = 0u;
    if (m.hit) {
        var k = 0u;
        emitted = walk(m, &k, params.max_samples).emitted;
    }
    counts[ray] = emitted;
}
