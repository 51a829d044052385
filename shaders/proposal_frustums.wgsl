// A fixed-count level's frustums in the scene's contracted space
// (Mip-NeRF 360, eq. 9–10), one invocation per ray, as the cpu model's
// `sample_level` with `contracted_frustum_gaussians`: each ray's `samples`
// + 1 interval edges give `samples` frustums; each one's full Gaussian
// (mean o + t̄·d, covariance σ_t² ddᵀ + σ_r² (I − ddᵀ)) in the frame's
// units goes through the contraction's linearisation at its mean: mean
// contract(μ), covariance J Σ Jᵀ, of which the field takes the diagonal.
// Prepended with proposal_common.wgsl, cpu_arithmetic.wgsl,
// contraction.wgsl and frustum_common.wgsl.

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
    let r = invocation(id);
    if (r >= params.count) {
        return;
    }
    let n = params.samples;
    let o = vec3<f32>(origins[3u * r], origins[3u * r + 1u], origins[3u * r + 2u]);
    let d = vec3<f32>(directions[3u * r], directions[3u * r + 1u], directions[3u * r + 2u]);
    let radius = radii[r];
    let outer = mat3x3<f32>(d * d.x, d * d.y, d * d.z);
    let identity = mat3x3<f32>(vec3<f32>(1.0, 0.0, 0.0), vec3<f32>(0.0, 1.0, 0.0), vec3<f32>(0.0, 0.0, 1.0));
    let scale = 1.0 / (params.radius * params.radius);
    for (var k = 0u; k < n; k++) {
        let t0 = edges[r * (n + 1u) + k];
        let t1 = edges[r * (n + 1u) + k + 1u];
        let s = r * n + k;
        t[s] = 0.5 * (t0 + t1);
        dt[s] = t1 - t0;
        let moments = frustum_moments(radius, t0, t1);
        let covariance = (outer * moments.y + (identity - outer) * moments.z) * scale;
        let x = to_frame(o + unfused3(d * moments.x));
        let j = contraction_jacobian(x);
        let warped = j * covariance * transpose(j);
        let mean = contract(x);
        for (var c = 0u; c < 3u; c++) {
            means[3u * s + c] = mean[c];
            variances[3u * s + c] = warped[c][c];
            sample_directions[3u * s + c] = d[c];
        }
    }
}
