// Marched samples as frustums (Mip-NeRF through the occupancy grid), one
// invocation per ray, as the cpu model's marched step: each sample stands
// for the frustum of its step centred on it, [max(t − dt/2, 0), t + dt/2].
// Writes each sample's Gaussian (mean and covariance diagonal) in world
// space. `ray_offsets` are the march's: the samples of ray r are
// ray_offsets[r] .. ray_offsets[r + 1] of the (whole-bound) sample arrays.

@group(0) @binding(1) var<storage, read> origins: array<f32>;
@group(0) @binding(2) var<storage, read> directions: array<f32>;
@group(0) @binding(3) var<storage, read> radii: array<f32>;
@group(0) @binding(4) var<storage, read> ray_offsets: array<u32>;
@group(0) @binding(5) var<storage, read> t: array<f32>;
@group(0) @binding(6) var<storage, read> dt: array<f32>;
@group(0) @binding(7) var<storage, read_write> means: array<f32>;
@group(0) @binding(8) var<storage, read_write> variances: array<f32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let r = ray_index(id);
    if (r >= params.rays) {
        return;
    }
    let o = vec3<f32>(origins[3u * r], origins[3u * r + 1u], origins[3u * r + 2u]);
    let d = vec3<f32>(directions[3u * r], directions[3u * r + 1u], directions[3u * r + 2u]);
    let radius = radii[r];
    for (var s = ray_offsets[r]; s < ray_offsets[r + 1u]; s++) {
        // Half of dt is exact, so no product here can be fused.
        let half = 0.5 * dt[s];
        let g = frustum_gaussian(o, d, radius, max(t[s] - half, 0.0), t[s] + half);
        for (var c = 0u; c < 3u; c++) {
            means[3u * s + c] = g.mean[c];
            variances[3u * s + c] = g.variance[c];
        }
    }
}
