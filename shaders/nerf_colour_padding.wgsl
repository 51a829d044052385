// Mip-NeRF's widened colour (reference `rgb_padding`, see
// src/engine/cpu/fields/nerf.rs `NerfShape::colour_padding`), one invocation
// per value: y = x · scale − offset. Forward: x the sigmoid's output,
// scale 1 + 2p, offset p. Backward: x ∂L/∂colour, scale 1 + 2p, offset 0
// (the map is affine, so its derivative is the constant scale).

struct Params {
    count: u32,
    row_stride: u32,
    scale: f32,
    offset: f32,
    // Always 0: XOR-ing the product with it keeps it rounded before the
    // subtraction (no fused multiply-add), as the cpu rounds it.
    zero: u32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> x: array<f32>;
@group(0) @binding(2) var<storage, read_write> y: array<f32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let i = id.x + id.y * params.row_stride;
    if (i >= params.count) {
        return;
    }
    let product = bitcast<f32>(bitcast<u32>(x[i] * params.scale) ^ params.zero);
    y[i] = product - params.offset;
}
