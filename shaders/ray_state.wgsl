// What the render kernels (render_walk, render_composite, render_compact,
// render_image; prepended to each) keep per pixel between rounds: eight
// 4-byte words (`engine::gpu::render::STATE_WORDS`).

struct RayState {
    // The next lattice index to look at.
    k: u32,
    // Samples composited so far.
    emitted: u32,
    // 1 once the ray needs no more samples.
    done: u32,
    optical_depth: f32,
    depth: f32,
    r: f32,
    g: f32,
    b: f32,
}
