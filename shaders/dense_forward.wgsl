@group(0) @binding(0) var<uniform> layer: Layer;
@group(0) @binding(1) var<storage, read> params: array<f32>;
@group(0) @binding(2) var<storage, read> input: array<f32>;
@group(0) @binding(3) var<storage, read_write> output: array<f32>;

@compute @workgroup_size(16, 16)
fn main(
    @builtin(local_invocation_id) local: vec3<u32>,
    @builtin(workgroup_id) workgroup: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
) {
    let row = row_tile(workgroup, groups) * TILE + local.y;
    let out = workgroup.x * TILE + local.x;
    if (row >= layer.rows || out >= layer.out_width) {
        return;
    }
    var sum = 0.0;
    let x0 = row * layer.in_width;
    let w0 = layer.weight_offset + out * layer.in_width;
    for (var k = 0u; k < layer.in_width; k++) {
        sum += input[x0 + k] * params[w0 + k];
    }
    if (layer.bias_offset != NO_BIAS) {
        sum += params[layer.bias_offset + out];
    }
    output[row * layer.out_width + out] = activate(sum, layer.activation, layer.exp_clamp);
}
