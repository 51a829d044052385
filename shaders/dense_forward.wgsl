// One dense layer forward: y = act(x Wᵀ + b) for every row x, W out × in
// row-major at layer.weight_offset of the parameter buffer. BLOCK × BLOCK
// tiles of (rows × outputs), 4 × 4 per thread (dense_common.wgsl); x and W
// are staged k-major, so both are transposed on the way in.

@group(0) @binding(0) var<uniform> layer: Layer;
@group(0) @binding(1) var<storage, read> params: array<f32>;
@group(0) @binding(2) var<storage, read> input: array<f32>;
@group(0) @binding(3) var<storage, read_write> output: array<f32>;

var<workgroup> x_tile: array<vec4<f32>, 256>; // [k][row / 4]
var<workgroup> w_tile: array<vec4<f32>, 256>; // [k][output / 4]

@compute @workgroup_size(256)
fn main(
    @builtin(local_invocation_index) thread: u32,
    @builtin(workgroup_id) workgroup: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
) {
    let first_row = row_tile(workgroup, groups) * BLOCK;
    let first_out = workgroup.x * BLOCK;
    // Loading: a row of x (and of W) per four threads, four k each.
    let load_line = thread / 4u;
    let load_k = (thread % 4u) * 4u;
    let x_row = first_row + load_line;
    let w_row = first_out + load_line;
    // Computing: rows 4 ty .. 4 ty + 3, outputs 4 tx .. 4 tx + 3.
    let tx = thread % QUADS;
    let ty = thread / QUADS;
    var acc = array<vec4<f32>, 4>();
    for (var k0 = 0u; k0 < layer.in_width; k0 += DEPTH) {
        for (var j = 0u; j < 4u; j++) {
            let kk = load_k + j;
            let k = k0 + kk;
            var x = 0.0;
            if (x_row < layer.rows && k < layer.in_width) {
                x = input[x_row * layer.in_width + k];
            }
            x_tile[kk * QUADS + load_line / 4u][load_line % 4u] = x;
            var w = 0.0;
            if (w_row < layer.out_width && k < layer.in_width) {
                w = params[layer.weight_offset + w_row * layer.in_width + k];
            }
            w_tile[kk * QUADS + load_line / 4u][load_line % 4u] = w;
        }
        workgroupBarrier();
        for (var kk = 0u; kk < DEPTH; kk++) {
            let a = x_tile[kk * QUADS + ty];
            let b = w_tile[kk * QUADS + tx];
            acc[0] += a.x * b;
            acc[1] += a.y * b;
            acc[2] += a.z * b;
            acc[3] += a.w * b;
        }
        workgroupBarrier();
    }
    for (var j = 0u; j < 4u; j++) {
        let out = first_out + 4u * tx + j;
        if (out >= layer.out_width) {
            break;
        }
        var bias = 0.0;
        if (layer.bias_offset != NO_BIAS) {
            bias = params[layer.bias_offset + out];
        }
        for (var i = 0u; i < 4u; i++) {
            let row = first_row + 4u * ty + i;
            if (row < layer.rows) {
                output[row * layer.out_width + out] =
                    activate(acc[i][j] + bias, layer.activation, layer.exp_clamp);
            }
        }
    }
}
