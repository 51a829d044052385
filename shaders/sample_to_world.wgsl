// Marched sample positions from the unit cube to world space, one
// invocation per sample: (u − offset) / scale per axis, as the cpu model's
// `to_world` (the inverse of `UnitCubeMapping`'s world → unit cube).

struct Params {
    count: u32,
    row_stride: u32,
    scale: f32,
    _pad0: u32,
    offset: vec3<f32>,
    _pad1: u32,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> unit: array<f32>;
@group(0) @binding(2) var<storage, read_write> world: array<f32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let i = id.x + id.y * params.row_stride;
    if (i >= params.count) {
        return;
    }
    for (var c = 0u; c < 3u; c++) {
        world[3u * i + c] = (unit[3u * i + c] - params.offset[c]) / params.scale;
    }
}
