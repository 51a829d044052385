// One dense layer backward, input gradient: dx = G W with
// G = dy ⊙ act'(y), per row. 16 × 16 tiles of (rows × inputs), the
// reduction over outputs staged through workgroup memory.

@group(0) @binding(0) var<uniform> layer: Layer;
@group(0) @binding(1) var<storage, read> params: array<f32>;
@group(0) @binding(2) var<storage, read> d_output: array<f32>;
@group(0) @binding(3) var<storage, read> output: array<f32>;
@group(0) @binding(4) var<storage, read_write> d_input: array<f32>;

var<workgroup> g_tile: array<array<f32, 16>, 16>; // [row][o]
var<workgroup> w_tile: array<array<f32, 16>, 16>; // [o][input]

@compute @workgroup_size(16, 16)
fn main(
    @builtin(local_invocation_id) local: vec3<u32>,
    @builtin(workgroup_id) workgroup: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
) {
    let first_row = row_tile(workgroup, groups) * TILE;
    let first_in = workgroup.x * TILE;
    let row = first_row + local.y;
    let i = first_in + local.x;
    var sum = 0.0;
    for (var o0 = 0u; o0 < layer.out_width; o0 += TILE) {
        let o = o0 + local.x;
        var g = 0.0;
        if (row < layer.rows && o < layer.out_width) {
            let at = row * layer.out_width + o;
            g = d_output[at] * activation_derivative(output[at], layer.activation, layer.exp_clamp);
        }
        g_tile[local.y][local.x] = g;
        let w_out = o0 + local.y;
        var w = 0.0;
        if (w_out < layer.out_width && i < layer.in_width) {
            w = params[layer.weight_offset + w_out * layer.in_width + i];
        }
        w_tile[local.y][local.x] = w;
        workgroupBarrier();
        for (var j = 0u; j < TILE; j++) {
            sum += g_tile[local.y][j] * w_tile[j][local.x];
        }
        workgroupBarrier();
    }
    if (row < layer.rows && i < layer.in_width) {
        d_input[row * layer.in_width + i] = sum;
    }
}
