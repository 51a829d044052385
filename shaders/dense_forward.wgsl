// One dense layer forward: y = act(x Wᵀ + b) for every row x, W out × in
// row-major at layer.weight_offset of the parameter buffer. 16 × 16 tiles of
// (rows × outputs), the reduction over inputs staged through workgroup
// memory 16 at a time.

@group(0) @binding(0) var<uniform> layer: Layer;
@group(0) @binding(1) var<storage, read> params: array<f32>;
@group(0) @binding(2) var<storage, read> input: array<f32>;
@group(0) @binding(3) var<storage, read_write> output: array<f32>;

var<workgroup> x_tile: array<array<f32, 16>, 16>; // [row][k]
var<workgroup> w_tile: array<array<f32, 16>, 16>; // [output][k]

@compute @workgroup_size(16, 16)
fn main(
    @builtin(local_invocation_id) local: vec3<u32>,
    @builtin(workgroup_id) workgroup: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
) {
    let first_row = row_tile(workgroup, groups) * TILE;
    let first_out = workgroup.x * TILE;
    let row = first_row + local.y;
    let out = first_out + local.x;
    var sum = 0.0;
    for (var k0 = 0u; k0 < layer.in_width; k0 += TILE) {
        let k = k0 + local.x;
        var x = 0.0;
        if (row < layer.rows && k < layer.in_width) {
            x = input[row * layer.in_width + k];
        }
        x_tile[local.y][local.x] = x;
        let w_row = first_out + local.y;
        var w = 0.0;
        if (w_row < layer.out_width && k < layer.in_width) {
            w = params[layer.weight_offset + w_row * layer.in_width + k];
        }
        w_tile[local.y][local.x] = w;
        workgroupBarrier();
        for (var j = 0u; j < TILE; j++) {
            sum += x_tile[local.y][j] * w_tile[local.x][j];
        }
        workgroupBarrier();
    }
    if (row < layer.rows && out < layer.out_width) {
        if (layer.bias_offset != NO_BIAS) {
            sum += params[layer.bias_offset + out];
        }
        output[row * layer.out_width + out] = activate(sum, layer.activation, layer.exp_clamp);
    }
}
