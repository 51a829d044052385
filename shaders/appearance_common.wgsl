// Per-image appearance embeddings (src/engine/gpu/appearance.rs): the
// uniform every appearance kernel takes. The table holds `images` rows of
// `width` values; row r of a pass takes the table's row `image_of(r)` in
// columns `column .. column + width` of the colour network's input (rows of
// `stride` values), and its gradient goes back to that row.

struct Params {
    // Rows of the pass (rays for appearance_images.wgsl).
    rows: u32,
    // Invocations per row of the dispatch grid.
    row_stride: u32,
    width: u32,
    images: u32,
    stride: u32,
    column: u32,
    // The row every pass row takes where `one_image` is 1; else each its own
    // (`images` binding).
    image: u32,
    one_image: u32,
    // The table's first value in its binding, which starts at the aligned
    // offset below it.
    table_base: u32,
    _pad1: u32,
    _pad2: u32,
    _pad3: u32,
}

@group(0) @binding(0) var<uniform> params: Params;
