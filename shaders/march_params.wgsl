// The uniform every march kernel reads (`engine::gpu::march::MarchUniforms`
// on the Rust side); prepended to each march shader.

struct MarchParams {
    offset: vec3<f32>,
    scale: f32,
    box_min: f32,
    box_max: f32,
    dt: f32,
    inverse_dt: f32,
    margin: f32,
    ray_count: u32,
    row_stride: u32,
    resolution: u32,
    cascades: u32,
    max_samples: u32,
    jitter_seed: u32,
    use_jitter: u32,
    // Always 0. XOR-ing a product with it hides the product from the
    // shader compiler, which may otherwise fuse a·b + c into one fma and
    // round once where the cpu rounds twice; a position one ulp off can
    // land in the neighbouring cell.
    zero: u32,
    budget: u32,
    element_count: u32,
    block_count: u32,
    world_dt: f32,
    inverse_scale: f32,
    // Cone stepping (`engine::cpu::march::Cone`), read when use_cone is 1:
    // lattice points per octave (1 / cone angle), the distance A = dt / c
    // where octave 1 starts and its inverse, and the octave whose step is
    // the largest.
    use_cone: u32,
    points_per_octave: f32,
    octave_start: f32,
    inverse_octave_start: f32,
    last_octave: i32,
}
