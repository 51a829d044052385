// Writes each row's appearance vector into its columns of the colour
// network's input. One invocation per written value.

@group(0) @binding(1) var<storage, read> table: array<f32>;
@group(0) @binding(2) var<storage, read> images: array<u32>;
@group(0) @binding(3) var<storage, read_write> input: array<f32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let i = id.x + id.y * params.row_stride;
    if (i >= params.rows * params.width) {
        return;
    }
    let r = i / params.width;
    let j = i % params.width;
    var image = params.image;
    if (params.one_image == 0u) {
        image = images[r];
    }
    input[r * params.stride + params.column + j] = table[params.table_base + image * params.width + j];
}
