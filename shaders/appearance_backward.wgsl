// The backward pass of appearance_write.wgsl: each row's gradient in its
// appearance columns added to its table row, with atomic adds, since many
// rows share an image. Appended to appearance_common.wgsl and to one of
// hash_accumulate_float.wgsl / hash_accumulate_cas.wgsl, which define
// `GradientCell` and `add_gradient`. One invocation per value.

@group(0) @binding(1) var<storage, read> images: array<u32>;
@group(0) @binding(2) var<storage, read> d_input: array<f32>;
@group(0) @binding(3) var<storage, read_write> d_params: array<GradientCell>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let i = id.x + id.y * params.row_stride;
    if (i >= params.rows * params.width) {
        return;
    }
    let r = i / params.width;
    let j = i % params.width;
    let gradient = d_input[r * params.stride + params.column + j];
    // Zero contributions change nothing: skip the atomics.
    if (gradient == 0.0) {
        return;
    }
    var image = params.image;
    if (params.one_image == 0u) {
        image = images[r];
    }
    add_gradient(params.table_base + image * params.width + j, gradient);
}
