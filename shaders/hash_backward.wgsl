// Hash encoding backward: scatters w_c · d_encoded[s · width + l · F + f]
// into d_params[(index_c) · F + f] with atomic adds, since samples in
// different invocations share entries. Appended to hash_common.wgsl and to
// one of hash_accumulate_float.wgsl / hash_accumulate_cas.wgsl, which
// define GradientCell and add_gradient.

@group(0) @binding(2) var<storage, read> positions: array<f32>;
@group(0) @binding(3) var<storage, read> d_encoded: array<f32>;
@group(0) @binding(4) var<storage, read_write> d_params: array<GradientCell>;

@compute @workgroup_size(64)
fn main(@builtin(workgroup_id) group: vec3<u32>, @builtin(local_invocation_index) lane: u32) {
    let sample = sample_index(group, lane);
    if (sample >= params.count) {
        return;
    }
    let l = params.first_level + group.y;
    let p = vec3<f32>(positions[3u * sample], positions[3u * sample + 1u], positions[3u * sample + 2u]);
    let corner = corners(levels[l], p);
    let features = params.features;
    let row = sample * params.width + l * features;
    for (var f = 0u; f < features; f++) {
        let gradient = d_encoded[row + f];
        // Zero contributions change nothing: skip the atomics (corners on a
        // face have weight 0, and many samples carry no gradient).
        if (gradient == 0.0) {
            continue;
        }
        for (var c = 0u; c < 8u; c++) {
            let contribution = corner.weight[c] * gradient;
            if (contribution != 0.0) {
                add_gradient(corner.index[c] * features + f - params.table_base, contribution);
            }
        }
    }
}
