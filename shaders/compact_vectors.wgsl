// Compaction, 3-vectors: the field's positions, the directions and (frustum
// recipes) the covariance diagonals (`compact_common.wgsl` is prepended).

@group(0) @binding(4) var<storage, read> positions: array<f32>;
@group(0) @binding(5) var<storage, read> directions: array<f32>;
@group(0) @binding(6) var<storage, read> variances: array<f32>;
@group(0) @binding(7) var<storage, read_write> out_positions: array<f32>;
@group(0) @binding(8) var<storage, read_write> out_directions: array<f32>;
@group(0) @binding(9) var<storage, read_write> out_variances: array<f32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let at = source_of(id);
    if (at.y == 0xffffffffu) {
        return;
    }
    let i = at.x;
    let s = at.y;
    for (var c = 0u; c < 3u; c++) {
        out_positions[3u * i + c] = positions[3u * s + c];
        out_directions[3u * i + c] = directions[3u * s + c];
    }
    if (params.with_variances != 0u) {
        for (var c = 0u; c < 3u; c++) {
            out_variances[3u * i + c] = variances[3u * s + c];
        }
    }
}
