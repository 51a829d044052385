// Mip-NeRF's conical frustum as a Gaussian: the formulas, their source
// (Barron et al. 2021, section 3.1 and appendix A; reference mip.py
// `conical_frustum_to_gaussian`, `lift_gaussian`) and why this stable form
// is used are in src/engine/cpu/frustum.rs. Prepended (after
// sample_common.wgsl and cpu_arithmetic.wgsl, whose `unfused` keeps each product rounded before the
// sum it feeds, as the cpu rounds it) to the frustum kernels. Every
// operation is the cpu's, in the cpu's order, so the two engines differ
// only where WGSL's division is allowed to (2.5 ulp).

struct Gaussian {
    mean: vec3<f32>,
    // The diagonal of the covariance.
    variance: vec3<f32>,
}

fn unfused3(x: vec3<f32>) -> vec3<f32> {
    return bitcast<vec3<f32>>(bitcast<vec3<u32>>(x) ^ vec3<u32>(params.zero));
}

// The frustum's moments along its ray: the mean distance, the variance
// along the ray and the variance across it (x, y, z of the result).
fn frustum_moments(radius: f32, t0: f32, t1: f32) -> vec3<f32> {
    let mid = 0.5 * (t0 + t1);
    let half = 0.5 * (t1 - t0);
    let mid2 = mid * mid;
    let half2 = half * half;
    let denominator = unfused(3.0 * mid2) + half2;
    var t_mean = mid;
    var t_variance = 0.0;
    var radial_variance = 0.0;
    // A frustum of zero extent at the apex (denominator 0) is a point
    // there, as on the cpu. Written as a positive test, so that a NaN
    // (which WGSL need not preserve) also takes the point's branch.
    if (denominator > 0.0) {
        let half4_over = half2 * half2 / denominator;
        t_mean = mid + 2.0 * mid * half2 / denominator;
        // (4/15 and 5/12 are constant expressions: evaluated exactly and
        // rounded once to f32, the same bits as the cpu's f32 division.)
        t_variance = max(
            half2 / 3.0 - (4.0 / 15.0) * half4_over * (unfused(12.0 * mid2) - half2) / denominator,
            0.0,
        );
        radial_variance = max(
            radius * radius * (mid2 / 4.0 + unfused((5.0 / 12.0) * half2) - unfused((4.0 / 15.0) * half4_over)),
            0.0,
        );
    }
    return vec3<f32>(t_mean, t_variance, radial_variance);
}

// The frustum of the cone of radius `radius` at unit distance around the
// unit direction `d` from `o`, between distances t0 <= t1.
fn frustum_gaussian(o: vec3<f32>, d: vec3<f32>, radius: f32, t0: f32, t1: f32) -> Gaussian {
    let moments = frustum_moments(radius, t0, t1);
    let t_mean = moments.x;
    let t_variance = moments.y;
    let radial_variance = moments.z;
    let along = d * d;
    var g: Gaussian;
    g.mean = o + unfused3(d * t_mean);
    g.variance = unfused3(along * t_variance) + unfused3(max(vec3<f32>(1.0) - along, vec3<f32>(0.0)) * radial_variance);
    return g;
}
