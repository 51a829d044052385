// Rendering: the rays still marching after a round, gathered into the next
// round's list. Their order varies from run to run (an atomic counter); no
// ray's result depends on it.

// `RayState` comes from ray_state.wgsl.

struct Params {
    count: u32,
    row_stride: u32,
    _pad0: u32,
    _pad1: u32,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> ray_list: array<u32>;
@group(0) @binding(2) var<storage, read> states: array<RayState>;
@group(0) @binding(3) var<storage, read_write> next_ray_list: array<u32>;
@group(0) @binding(4) var<storage, read_write> next_count: atomic<u32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let i = id.x + id.y * params.row_stride;
    if (i >= params.count) {
        return;
    }
    let ray = ray_list[i];
    if (states[ray].done == 0u) {
        next_ray_list[atomicAdd(&next_count, 1u)] = ray;
    }
}
