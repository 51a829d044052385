// The backward pass of the mean (appearance_mean.wgsl): the gradient of
// the mean vector, divided by the images, added to every row of the
// table's gradient. One invocation per table value.

@group(0) @binding(1) var<storage, read> d_mean: array<f32>;
@group(0) @binding(2) var<storage, read_write> d_table: array<f32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let i = id.x + id.y * params.row_stride;
    if (i >= params.images * params.width) {
        return;
    }
    d_table[params.table_base + i] += d_mean[i % params.width] / f32(params.images);
}
