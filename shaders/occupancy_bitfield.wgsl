// The occupancy bitfield: one invocation per u32 word of 32 cells; a cell
// is occupied when untrained (negative marker) or above the threshold.

@group(0) @binding(0) var<uniform> params: OccupancyParams;
@group(0) @binding(1) var<storage, read> values: array<f32>;
@group(0) @binding(2) var<storage, read> threshold: array<f32>;
@group(0) @binding(3) var<storage, read_write> bitfield: array<u32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let word = id.x + id.y * params.row_stride;
    if (word >= params.word_count) {
        return;
    }
    let t = threshold[0];
    var bits = 0u;
    for (var i = 0u; i < 32u; i++) {
        let cell = word * 32u + i;
        if (cell < params.cell_count) {
            let v = values[cell];
            if (v < 0.0 || v > t) {
                bits |= 1u << i;
            }
        }
    }
    bitfield[word] = bits;
}
