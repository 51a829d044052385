// One dense layer backward, weight gradients, second pass: adds the chunk
// partial sums of dense_backward_weights.wgsl in chunk order and accumulates
// (+=) them into the parameter gradients, one thread per weight or bias.

@group(0) @binding(0) var<uniform> layer: Layer;
@group(0) @binding(1) var<storage, read> partials: array<f32>;
@group(0) @binding(2) var<storage, read_write> d_params: array<f32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let has_bias = layer.bias_offset != NO_BIAS;
    let columns = layer.in_width + select(0u, 1u, has_bias);
    let per_chunk = layer.out_width * columns;
    let j = id.x;
    if (j >= per_chunk) {
        return;
    }
    var sum = 0.0;
    for (var c = 0u; c < layer.chunks; c++) {
        sum += partials[c * per_chunk + j];
    }
    let o = j / columns;
    let i = j % columns;
    var at = layer.weight_offset + o * layer.in_width + i;
    if (i == layer.in_width) {
        at = layer.bias_offset + o;
    }
    d_params[at] += sum;
}
