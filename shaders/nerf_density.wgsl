// NeRF's σ: the density activation of the first column of trunk B's output
// [σ_raw | feature]. One invocation per row. Activations in
// nerf_density_common.wgsl.

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> raw: array<f32>;
@group(0) @binding(2) var<storage, read_write> sigma: array<f32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let r = id.x + id.y * params.row_stride;
    if (r >= params.rows) {
        return;
    }
    sigma[r] = density(raw[r * params.raw_stride]);
}
