// Hash encoding forward: encoded[s · width + l · F + f] = Σ_c w_c ·
// table[(index_c) · F + f]. Appended to hash_common.wgsl.

@group(0) @binding(2) var<storage, read> table: array<f32>;
@group(0) @binding(3) var<storage, read> positions: array<f32>;
@group(0) @binding(4) var<storage, read_write> encoded: array<f32>;

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
        // Corners summed in order 0..7, as on the cpu.
        var sum = 0.0;
        for (var c = 0u; c < 8u; c++) {
            sum += corner.weight[c] * table[corner.index[c] * features + f - params.table_base];
        }
        encoded[row + f] = sum;
    }
}
