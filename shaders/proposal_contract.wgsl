// World positions into a contracted field's inputs, in place, one
// invocation per point, as the cpu model's `InputMap`: contracted (mode 0,
// NeRF's and Mip-NeRF's fields) or contracted onto [0, 1]³ (mode 1, hash
// grids).

@group(0) @binding(1) var<storage, read_write> positions: array<f32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let i = invocation(id);
    if (i >= params.count) {
        return;
    }
    let world = vec3<f32>(positions[3u * i], positions[3u * i + 1u], positions[3u * i + 2u]);
    var p: vec3<f32>;
    if (params.mode == 0u) {
        p = contract(to_frame(world));
    } else {
        p = to_unit_cube(world);
    }
    positions[3u * i] = p.x;
    positions[3u * i + 1u] = p.y;
    positions[3u * i + 2u] = p.z;
}
