// Distances along rays to the spacing coordinate s (mode 0) or back
// (mode 1), in place, one invocation per value: the proposal samplers
// stratify and resample in s (engine/cpu/model/samplers.rs).

@group(0) @binding(1) var<storage, read_write> values: array<f32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let i = invocation(id);
    if (i >= params.count) {
        return;
    }
    if (params.mode == 0u) {
        values[i] = spacing_of(values[i]);
    } else {
        values[i] = distance_of(values[i]);
    }
}
