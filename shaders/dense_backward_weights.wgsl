// One dense layer backward, weight gradients, first pass: each workgroup sums
// Gᵀ x over one chunk of layer.rows_per_chunk rows for a 16 × 16 tile of
// (outputs × inputs), G = dy ⊙ act'(y), and writes that partial sum; the
// bias is column in_width, whose input is 1. dense_reduce.wgsl adds the
// partials of all chunks in chunk order. Nothing is atomic, so the result is
// deterministic.
//
// partials[(chunk · out_width + o) · columns + i], columns = in_width (+ 1
// with a bias).

@group(0) @binding(0) var<uniform> layer: Layer;
@group(0) @binding(1) var<storage, read> d_output: array<f32>;
@group(0) @binding(2) var<storage, read> output: array<f32>;
@group(0) @binding(3) var<storage, read> input: array<f32>;
@group(0) @binding(4) var<storage, read_write> partials: array<f32>;

var<workgroup> g_tile: array<array<f32, 16>, 16>; // [row][o]
var<workgroup> x_tile: array<array<f32, 16>, 16>; // [row][input]

@compute @workgroup_size(16, 16)
fn main(
    @builtin(local_invocation_id) local: vec3<u32>,
    @builtin(workgroup_id) workgroup: vec3<u32>,
) {
    let columns = layer.in_width + select(0u, 1u, layer.bias_offset != NO_BIAS);
    let first_in = workgroup.x * TILE;
    let first_out = workgroup.y * TILE;
    let chunk = workgroup.z;
    let chunk_start = chunk * layer.rows_per_chunk;
    let chunk_end = min(chunk_start + layer.rows_per_chunk, layer.rows);
    let i = first_in + local.x;
    let o = first_out + local.y;
    var sum = 0.0;
    for (var r0 = chunk_start; r0 < chunk_end; r0 += TILE) {
        // Thread (y, x) loads row r0 + y: G at output first_out + x and
        // the input at first_in + x.
        let r = r0 + local.y;
        let go = first_out + local.x;
        var g = 0.0;
        if (r < chunk_end && go < layer.out_width) {
            let at = r * layer.out_width + go;
            g = d_output[at] * activation_derivative(output[at], layer.activation, layer.exp_clamp);
        }
        g_tile[local.y][local.x] = g;
        var x = 0.0;
        if (r < chunk_end) {
            if (i < layer.in_width) {
                x = input[r * layer.in_width + i];
            } else if (i == layer.in_width) {
                x = 1.0;
            }
        }
        x_tile[local.y][local.x] = x;
        workgroupBarrier();
        for (var j = 0u; j < TILE; j++) {
            sum += g_tile[j][local.y] * x_tile[j][local.x];
        }
        workgroupBarrier();
    }
    if (o < layer.out_width && i < columns) {
        // Chunks count from layer.first_chunk: a batch bound a piece of rows
        // at a time puts each piece's partials after the previous piece's.
        partials[((layer.first_chunk + chunk) * layer.out_width + o) * columns + i] = sum;
    }
}
