// A fixed-count level's frustums (Mip-NeRF), one invocation per ray, as the
// cpu model's `sample_level` for conical frustums: each ray's `samples` + 1
// interval edges give `samples` frustums; for each, the interval's
// midpoint and length (for compositing), the Gaussian's mean and
// covariance diagonal (the field's input) and the ray's direction.

@group(0) @binding(1) var<storage, read> origins: array<f32>;
@group(0) @binding(2) var<storage, read> directions: array<f32>;
@group(0) @binding(3) var<storage, read> radii: array<f32>;
@group(0) @binding(4) var<storage, read> edges: array<f32>;
@group(0) @binding(5) var<storage, read_write> t: array<f32>;
@group(0) @binding(6) var<storage, read_write> dt: array<f32>;
@group(0) @binding(7) var<storage, read_write> means: array<f32>;
@group(0) @binding(8) var<storage, read_write> variances: array<f32>;
@group(0) @binding(9) var<storage, read_write> sample_directions: array<f32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let r = ray_index(id);
    if (r >= params.rays) {
        return;
    }
    let n = params.samples;
    let o = vec3<f32>(origins[3u * r], origins[3u * r + 1u], origins[3u * r + 2u]);
    let d = vec3<f32>(directions[3u * r], directions[3u * r + 1u], directions[3u * r + 2u]);
    let radius = radii[r];
    for (var k = 0u; k < n; k++) {
        let t0 = edges[r * (n + 1u) + k];
        let t1 = edges[r * (n + 1u) + k + 1u];
        let s = r * n + k;
        t[s] = 0.5 * (t0 + t1);
        dt[s] = t1 - t0;
        let g = frustum_gaussian(o, d, radius, t0, t1);
        for (var c = 0u; c < 3u; c++) {
            means[3u * s + c] = g.mean[c];
            variances[3u * s + c] = g.variance[c];
            sample_directions[3u * s + c] = d[c];
        }
    }
}
