// Mip-NeRF's samples in the viewer's device walk (after sample_common.wgsl
// and frustum_common.wgsl): each sample a round of `render_walk.wgsl`
// wrote stands for the frustum of its step, centred on it,
// [max(t − dt/2, 0), t + dt/2], as in a training step
// (`sample_marched_frustums.wgsl`) and the host's render
// (`grid_sample_gaussians`). One invocation per sample slot of the round:
// ray i of the round owns slots i·samples .. (i + 1)·samples, and is ray
// ray_list[i] of the view. Slots a ray did not fill this round get a
// Gaussian too, from what they held before; compositing reads only the
// slots the walk wrote.

@group(0) @binding(1) var<storage, read> origins: array<f32>;
@group(0) @binding(2) var<storage, read> directions: array<f32>;
@group(0) @binding(3) var<storage, read> radii: array<f32>;
@group(0) @binding(4) var<storage, read> ray_list: array<u32>;
@group(0) @binding(5) var<storage, read> t: array<f32>;
@group(0) @binding(6) var<storage, read> dt: array<f32>;
@group(0) @binding(7) var<storage, read_write> means: array<f32>;
@group(0) @binding(8) var<storage, read_write> variances: array<f32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    // `rays` counts the piece's slots here, `ray_base` its first slot.
    if (ray_index(id) >= params.rays) {
        return;
    }
    let s = params.ray_base + ray_index(id);
    let r = ray_list[s / params.samples];
    let o = vec3<f32>(origins[3u * r], origins[3u * r + 1u], origins[3u * r + 2u]);
    let d = vec3<f32>(directions[3u * r], directions[3u * r + 1u], directions[3u * r + 2u]);
    // Half of dt is exact, so no product here can be fused.
    let half = 0.5 * dt[s];
    let g = frustum_gaussian(o, d, radii[r], max(t[s] - half, 0.0), t[s] + half);
    for (var c = 0u; c < 3u; c++) {
        means[3u * s + c] = g.mean[c];
        variances[3u * s + c] = g.variance[c];
    }
}
