// One dense layer backward, input gradient: dx = G W with
// G = dy ⊙ act'(y), per row. BLOCK × BLOCK tiles of (rows × inputs), 4 × 4
// per thread (dense_common.wgsl), the reduction over outputs staged through
// workgroup memory: G transposed on the way in, W's rows as they are.

@group(0) @binding(0) var<uniform> layer: Layer;
@group(0) @binding(1) var<storage, read> params: array<f32>;
@group(0) @binding(2) var<storage, read> d_output: array<f32>;
@group(0) @binding(3) var<storage, read> output: array<f32>;
@group(0) @binding(4) var<storage, read_write> d_input: array<f32>;

var<workgroup> g_tile: array<vec4<f32>, 256>; // [o][row / 4]
var<workgroup> w_tile: array<vec4<f32>, 256>; // [o][input / 4]

@compute @workgroup_size(256)
fn main(
    @builtin(local_invocation_index) thread: u32,
    @builtin(workgroup_id) workgroup: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
) {
    let first_row = row_tile(workgroup, groups) * BLOCK;
    let first_in = workgroup.x * BLOCK;
    // Loading G: a row per four threads, four outputs each.
    let g_row = first_row + thread / 4u;
    let g_o = (thread % 4u) * 4u;
    // Loading W: an output per sixteen threads, four inputs each.
    let w_o = thread / QUADS;
    let w_in = first_in + (thread % QUADS) * 4u;
    let tx = thread % QUADS;
    let ty = thread / QUADS;
    var acc = array<vec4<f32>, 4>();
    for (var o0 = 0u; o0 < layer.out_width; o0 += DEPTH) {
        for (var j = 0u; j < 4u; j++) {
            let oo = g_o + j;
            let o = o0 + oo;
            var g = 0.0;
            if (g_row < layer.rows && o < layer.out_width) {
                let at = g_row * layer.out_width + o;
                g = d_output[at] * activation_derivative(output[at], layer.activation, layer.exp_clamp);
            }
            g_tile[oo * QUADS + (thread / 4u) / 4u][(thread / 4u) % 4u] = g;
        }
        var w = vec4<f32>();
        let o = o0 + w_o;
        if (o < layer.out_width) {
            let base = layer.weight_offset + o * layer.in_width;
            for (var j = 0u; j < 4u; j++) {
                if (w_in + j < layer.in_width) {
                    w[j] = params[base + w_in + j];
                }
            }
        }
        w_tile[w_o * QUADS + thread % QUADS] = w;
        workgroupBarrier();
        for (var oo = 0u; oo < DEPTH; oo++) {
            let a = g_tile[oo * QUADS + ty];
            let b = w_tile[oo * QUADS + tx];
            acc[0] += a.x * b;
            acc[1] += a.y * b;
            acc[2] += a.z * b;
            acc[3] += a.w * b;
        }
        workgroupBarrier();
    }
    for (var i = 0u; i < 4u; i++) {
        let row = first_row + 4u * ty + i;
        if (row >= layer.rows) {
            break;
        }
        for (var j = 0u; j < 4u; j++) {
            let input = first_in + 4u * tx + j;
            if (input < layer.in_width) {
                d_input[row * layer.in_width + input] = acc[i][j];
            }
        }
    }
}
