// Backward of nerf_density.wgsl and of the feature's copy into the colour
// input: the gradient of trunk B's output [σ_raw | feature] is
// [∂L/∂σ · dσ/d raw | the colour input's gradient in its feature columns]
// (the chain rule; the direction encoding's columns have no parameters
// behind them and are dropped). One invocation per output element.

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> raw: array<f32>;
@group(0) @binding(2) var<storage, read> d_sigma: array<f32>;
@group(0) @binding(3) var<storage, read> d_colour_input: array<f32>;
@group(0) @binding(4) var<storage, read_write> d_raw: array<f32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let i = id.x + id.y * params.row_stride;
    if (i >= params.rows * params.raw_stride) {
        return;
    }
    let r = i / params.raw_stride;
    let j = i % params.raw_stride;
    if (j == 0u) {
        d_raw[i] = d_sigma[r] * density_derivative(raw[i]);
    } else {
        d_raw[i] = d_colour_input[r * params.colour_stride + j - 1u];
    }
}
