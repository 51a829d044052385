// Instant-NGP's density activation between the two networks (the cpu
// engine's loops in `engine::cpu::ngp`): σ = scale · exp(min(x₀, clamp)) of the
// density network's first output, and the whole raw output row copied into
// the first columns of the colour network's input; backward, the colour
// input's gradient copied back plus ∂L/∂σ · σ on x₀ where the clamp was
// not active. One invocation per sample.

struct Params {
    count: u32,
    // Invocations per row of the dispatch grid.
    row_stride: u32,
    // Density network output width (16) and colour input width (32).
    density_width: u32,
    colour_width: u32,
    exp_clamp: f32,
    // The shape's `density_scale` (field/ngp.rs).
    density_scale: f32,
    _pad1: u32,
    _pad2: u32,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> density_out: array<f32>;
@group(0) @binding(2) var<storage, read_write> sigma: array<f32>;
@group(0) @binding(3) var<storage, read_write> colour_input: array<f32>;

@compute @workgroup_size(64)
fn forward(@builtin(global_invocation_id) id: vec3<u32>) {
    let s = id.x + id.y * params.row_stride;
    if (s >= params.count) {
        return;
    }
    let row = s * params.density_width;
    sigma[s] = params.density_scale * exp(min(density_out[row], params.exp_clamp));
    let out = s * params.colour_width;
    for (var j = 0u; j < params.density_width; j++) {
        colour_input[out + j] = density_out[row + j];
    }
}
