// σ = scale · y of a density network's outputs y (forward), and
// ∂L/∂y = scale · ∂L/∂σ (backward): field/ngp.rs, `DensityShape::
// density_scale`. One invocation per row.

struct Params {
    count: u32,
    // Invocations per row of the dispatch grid.
    row_stride: u32,
    scale: f32,
    _pad: u32,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> from_values: array<f32>;
@group(0) @binding(2) var<storage, read_write> to_values: array<f32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let i = id.x + id.y * params.row_stride;
    if (i >= params.count) {
        return;
    }
    to_values[i] = params.scale * from_values[i];
}
