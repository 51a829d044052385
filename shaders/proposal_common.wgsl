// Shared by the proposal sampler's kernels (proposal_*.wgsl and
// weight_*.wgsl, prepended to each, before cpu_arithmetic.wgsl and
// contraction.wgsl): their uniform (`engine::gpu::proposal::ProposalUniforms`
// on the Rust side).

struct ProposalParams {
    // Rays (per-ray kernels) or values (element-wise kernels).
    count: u32,
    // Invocations per row of a 2-D dispatch.
    row_stride: u32,
    // Samples (intervals) per ray of the level, and of the proposal level
    // the interlevel loss trains.
    samples: u32,
    bins: u32,
    // The contraction's norm: 0 L2, 1 L∞.
    norm: u32,
    // What an element-wise kernel computes (see each kernel).
    mode: u32,
    // Always 0 (cpu_arithmetic.wgsl's `unfused`).
    zero: u32,
    // The factor of a loss's gradient.
    scale: f32,
    // The contraction's frame: world units per unit, and its origin.
    radius: f32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
    centre: vec3<f32>,
    _pad3: u32,
}

@group(0) @binding(0) var<uniform> params: ProposalParams;

fn invocation(id: vec3<u32>) -> u32 {
    return id.x + id.y * params.row_stride;
}
