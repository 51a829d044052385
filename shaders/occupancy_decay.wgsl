// Occupancy update, step 1 of 2: every cell sampled before decays
// (testbed `ema_grid_samples_nerf`); untrained cells keep their marker.

@group(0) @binding(0) var<uniform> params: OccupancyParams;
@group(0) @binding(1) var<storage, read_write> values: array<f32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let i = id.x + id.y * params.row_stride;
    if (i >= params.cell_count) {
        return;
    }
    let v = values[i];
    if (v >= 0.0) {
        values[i] = v * params.decay;
    }
}
