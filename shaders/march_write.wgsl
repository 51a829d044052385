// Pass 3 of the march: each ray walks again and writes its samples at its
// offset (`march_common.wgsl` is prepended). Rays over the budget have an
// empty range and write nothing.

@group(0) @binding(0) var<uniform> params: MarchParams;
@group(0) @binding(1) var<storage, read> bitfield: array<u32>;
@group(0) @binding(2) var<storage, read> origins: array<f32>;
@group(0) @binding(3) var<storage, read> directions: array<f32>;
@group(0) @binding(4) var<storage, read> ray_offsets: array<u32>;
@group(0) @binding(5) var<storage, read_write> out_positions: array<f32>;
@group(0) @binding(6) var<storage, read_write> out_directions: array<f32>;
@group(0) @binding(7) var<storage, read_write> out_dt: array<f32>;
@group(0) @binding(8) var<storage, read_write> out_t: array<f32>;

// The ray's first sample goes to `base`, set by `main` before its walk.
var<private> base: u32;

fn emit_sample(m: RayMarch, n: u32, k: u32, s: f32) {
    let index = base + n;
    let p = lattice_position(m, s);
    out_positions[3u * index] = p.x;
    out_positions[3u * index + 1u] = p.y;
    out_positions[3u * index + 2u] = p.z;
    out_directions[3u * index] = m.direction.x;
    out_directions[3u * index + 1u] = m.direction.y;
    out_directions[3u * index + 2u] = m.direction.z;
    out_dt[index] = params.world_dt * lattice_step_scale(m, lattice_coordinate(m, k));
    out_t[index] = (m.t_enter + s) * params.inverse_scale;
}

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let ray = id.x + id.y * params.row_stride;
    if (ray >= params.ray_count) {
        return;
    }
    base = ray_offsets[ray];
    let limit = ray_offsets[ray + 1u] - base;
    if (limit == 0u) {
        return;
    }
    let m = prepare(ray);
    if (!m.hit) {
        return;
    }
    var k = 0u;
    walk(m, &k, limit);
}
