// The uniform of the occupancy kernels (`engine::gpu::march::OccupancyUniforms`
// on the Rust side); prepended to each occupancy shader.

struct OccupancyParams {
    // Cells of all cascades.
    cell_count: u32,
    // Cells of one cascade; the mean is taken over cascade 0's.
    cells_per_cascade: u32,
    word_count: u32,
    partial_count: u32,
    min_optical_thickness: f32,
    // Invocations per row of a 2-D dispatch.
    row_stride: u32,
    decay: f32,
    // The smallest march step; cascade k measures optical thickness with
    // min_step · 2^k.
    min_step: f32,
    sample_count: u32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
}
