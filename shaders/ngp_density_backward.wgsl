// Backward of shaders/ngp_density.wgsl: ∂L/∂(density output) is the colour
// input's gradient in its first columns, plus ∂L/∂σ · dσ/dx₀ on x₀, where
// dσ/dx₀ = σ below the clamp and 0 at or above it (the clamp is decided on
// the raw x₀, which is what the cpu engine's σ ≥ exp(clamp) test amounts
// to). One invocation per sample.

struct Params {
    count: u32,
    row_stride: u32,
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
@group(0) @binding(2) var<storage, read> sigma: array<f32>;
@group(0) @binding(3) var<storage, read> d_sigma: array<f32>;
@group(0) @binding(4) var<storage, read> d_colour_input: array<f32>;
@group(0) @binding(5) var<storage, read_write> d_density_out: array<f32>;

@compute @workgroup_size(64)
fn backward(@builtin(global_invocation_id) id: vec3<u32>) {
    let s = id.x + id.y * params.row_stride;
    if (s >= params.count) {
        return;
    }
    let row = s * params.density_width;
    let input = s * params.colour_width;
    for (var j = 0u; j < params.density_width; j++) {
        d_density_out[row + j] = d_colour_input[input + j];
    }
    if (density_out[row] < params.exp_clamp) {
        d_density_out[row] += d_sigma[s] * sigma[s];
    }
}
