// Concatenates columns of two row-major matrices row by row (NeRF's field,
// src/engine/gpu/fields/nerf.rs): columns output_start .. of output row r
// (rows of output_stride) are
//   [left[r, left_start .. left_start + left_width] |
//    right[r, right_start .. right_start + right_width]].
// The field uses it for the skip input [h | γ(x)], for the colour input
// [feature | γ(d)] (the feature is trunk B's output without its σ column;
// the appearance columns after them are another kernel's),
// and, with right_width 0, to take the first columns of an input gradient.
// One invocation per output element.

struct Params {
    rows: u32,
    // Invocations per row of the dispatch grid.
    row_stride: u32,
    left_stride: u32,
    left_start: u32,
    left_width: u32,
    right_stride: u32,
    right_start: u32,
    right_width: u32,
    output_stride: u32,
    output_start: u32,
    _pad1: u32,
    _pad2: u32,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> left: array<f32>;
@group(0) @binding(2) var<storage, read> right: array<f32>;
@group(0) @binding(3) var<storage, read_write> output: array<f32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let width = params.left_width + params.right_width;
    let i = id.x + id.y * params.row_stride;
    if (i >= params.rows * width) {
        return;
    }
    let r = i / width;
    let j = i % width;
    let o = r * params.output_stride + params.output_start + j;
    if (j < params.left_width) {
        output[o] = left[r * params.left_stride + params.left_start + j];
    } else {
        output[o] = right[r * params.right_stride + params.right_start + j - params.left_width];
    }
}
