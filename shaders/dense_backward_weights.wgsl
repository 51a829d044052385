// One dense layer backward, weight gradients, first pass: each workgroup sums
// Gᵀ x over one chunk of layer.rows_per_chunk rows for a BLOCK × BLOCK tile
// of (outputs × inputs), 4 × 4 per thread (dense_common.wgsl), G = dy ⊙
// act'(y), and writes that partial sum; the bias gradient (the sum of G over
// the rows, column in_width) is summed on the way by the threads that hold
// the first inputs of the first column tile. dense_reduce.wgsl adds the
// partials of all chunks in chunk order. Nothing is atomic, so the result
// is deterministic.
//
// partials[(chunk · out_width + o) · columns + i], columns = in_width (+ 1
// with a bias).

@group(0) @binding(0) var<uniform> layer: Layer;
@group(0) @binding(1) var<storage, read> d_output: array<f32>;
@group(0) @binding(2) var<storage, read> output: array<f32>;
@group(0) @binding(3) var<storage, read> input: array<f32>;
@group(0) @binding(4) var<storage, read_write> partials: array<f32>;

var<workgroup> g_tile: array<vec4<f32>, 256>; // [row][o / 4]
var<workgroup> x_tile: array<vec4<f32>, 256>; // [row][input / 4]

@compute @workgroup_size(256)
fn main(
    @builtin(local_invocation_index) thread: u32,
    @builtin(workgroup_id) workgroup: vec3<u32>,
) {
    let has_bias = layer.bias_offset != NO_BIAS;
    let columns = layer.in_width + select(0u, 1u, has_bias);
    let first_in = workgroup.x * BLOCK;
    let first_out = workgroup.y * BLOCK;
    let chunk = workgroup.z;
    let chunk_start = chunk * layer.rows_per_chunk;
    let chunk_end = min(chunk_start + layer.rows_per_chunk, layer.rows);
    // Loading: a row per sixteen threads, four outputs (and four inputs)
    // each, stored as they lie in memory.
    let load_r = thread / QUADS;
    let load_o = first_out + (thread % QUADS) * 4u;
    let load_in = first_in + (thread % QUADS) * 4u;
    // Computing: outputs 4 ty .. 4 ty + 3, inputs 4 tx .. 4 tx + 3.
    let tx = thread % QUADS;
    let ty = thread / QUADS;
    let sums_bias = has_bias && workgroup.x == 0u && tx == 0u;
    var acc = array<vec4<f32>, 4>();
    var bias = vec4<f32>();
    for (var r0 = chunk_start; r0 < chunk_end; r0 += DEPTH) {
        let r = r0 + load_r;
        var g = vec4<f32>();
        var x = vec4<f32>();
        if (r < chunk_end) {
            for (var j = 0u; j < 4u; j++) {
                let o = load_o + j;
                if (o < layer.out_width) {
                    let at = r * layer.out_width + o;
                    g[j] = d_output[at] * activation_derivative(output[at], layer.activation, layer.exp_clamp);
                }
                let i = load_in + j;
                if (i < layer.in_width) {
                    x[j] = input[r * layer.in_width + i];
                }
            }
        }
        g_tile[thread] = g;
        x_tile[thread] = x;
        workgroupBarrier();
        for (var rr = 0u; rr < DEPTH; rr++) {
            let a = g_tile[rr * QUADS + ty];
            let b = x_tile[rr * QUADS + tx];
            acc[0] += a.x * b;
            acc[1] += a.y * b;
            acc[2] += a.z * b;
            acc[3] += a.w * b;
            if (sums_bias) {
                bias += a;
            }
        }
        workgroupBarrier();
    }
    let base = layer.first_chunk + chunk;
    for (var i = 0u; i < 4u; i++) {
        let o = first_out + 4u * ty + i;
        if (o >= layer.out_width) {
            break;
        }
        let line = (base * layer.out_width + o) * columns;
        for (var j = 0u; j < 4u; j++) {
            let input = first_in + 4u * tx + j;
            if (input < layer.in_width) {
                partials[line + input] = acc[i][j];
            }
        }
        if (sums_bias) {
            partials[line + layer.in_width] = bias[i];
        }
    }
}
