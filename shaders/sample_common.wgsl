// Shared by the sampling kernels (`shaders/sample_*.wgsl`, prepended to
// each): their uniform (`engine::gpu::sampling::SampleUniforms` on the Rust
// side) and the random numbers of `engine::cpu::sampling::uniform`.
// Rays are processed a piece at a time; `ray_base` is the batch index of the
// piece's first ray, so the hash sees the same ray index as the cpu's.

struct SampleParams {
    rays: u32,
    ray_base: u32,
    // Invocations per row of a 2-D dispatch (past 65535 workgroups).
    row_stride: u32,
    // Samples per ray: N (stratified, intervals), count (pdf), Na (merge),
    // bins (blur).
    samples: u32,
    // Bins per ray (pdf), Nb (merge).
    bins: u32,
    seed: u32,
    use_jitter: u32,
    // Always 0: XOR-ing a product with it hides the product from the
    // shader compiler, which may otherwise fuse a·b + c into one fma and
    // round once where the cpu rounds twice (as in march_params.wgsl).
    zero: u32,
    // 1/(N − 1) for the stratified linspace, computed on the host.
    step: f32,
    // 1/count for the pdf's u, computed on the host (WGSL's division is
    // accurate to 2.5 ulp only).
    inverse_count: f32,
    padding: f32,
    _pad: u32,
}

@group(0) @binding(0) var<uniform> params: SampleParams;

// `unfused` and `mix32` come from cpu_arithmetic.wgsl.

// `engine::cpu::sampling::uniform` (a WGSL function cannot be called
// `uniform`, an address space): 24 bits, exact in f32, in [0, 1).
fn uniform01(seed: u32, ray: u32, index: u32) -> f32 {
    let h = mix32(mix32(seed ^ mix32(ray + 0x9e3779b9u)) ^ index);
    return f32(h >> 8u) * (1.0 / 16777216.0);
}

fn ray_index(id: vec3<u32>) -> u32 {
    return id.x + id.y * params.row_stride;
}
