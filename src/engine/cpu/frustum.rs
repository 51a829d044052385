//! Mip-NeRF's conical frustums as Gaussians for a batch of samples on the
//! `cpu` engine. The formulas, one frustum at a time, are in
//! [`crate::engine::shared::frustum`] (both engines use them) and are
//! re-exported here.
//!
//! No gradient flows into the frustums (sample positions are not learned),
//! so only the forward pass exists.

use glam::Vec3;
use rayon::prelude::*;

use crate::engine::shared::frustum::{frustum_gaussian, frustum_gaussian_full};
use crate::field::contraction::Contraction;

/// Samples per rayon task.
const SAMPLES_PER_TASK: usize = 4096;

/// Gaussians of many frustums: frustum i lies on ray `rays[i]` (origins,
/// unit directions and cone radii per ray) between `starts[i]` and
/// `ends[i]`. Writes means and covariance diagonals (n × 3 each).
#[allow(clippy::too_many_arguments)]
pub fn frustum_gaussians(
    origins: &[f32],
    directions: &[f32],
    radii: &[f32],
    rays: &[u32],
    starts: &[f32],
    ends: &[f32],
    means: &mut [f32],
    variances: &mut [f32],
) {
    each_frustum(
        origins,
        directions,
        radii,
        rays,
        starts,
        ends,
        means,
        variances,
        frustum_gaussian,
    );
}

/// [`frustum_gaussians`] in `contraction`'s contracted space: each
/// frustum's full Gaussian through the contraction's linearisation at its
/// mean (Mip-NeRF 360, eq. 9–10: mean contract(μ), covariance J Σ Jᵀ),
/// and the diagonal of that covariance, which the integrated encoding
/// takes (multinerf's `lift_and_diagonalize` takes the diagonal too, in
/// its own basis).
#[allow(clippy::too_many_arguments)]
pub fn contracted_frustum_gaussians(
    origins: &[f32],
    directions: &[f32],
    radii: &[f32],
    rays: &[u32],
    starts: &[f32],
    ends: &[f32],
    contraction: &Contraction,
    means: &mut [f32],
    variances: &mut [f32],
) {
    each_frustum(
        origins,
        directions,
        radii,
        rays,
        starts,
        ends,
        means,
        variances,
        |origin, direction, radius, t0, t1| {
            let (mean, covariance) = frustum_gaussian_full(origin, direction, radius, t0, t1);
            let (mean, covariance) = contraction.contract_world_gaussian(mean, covariance);
            (mean, covariance.diagonal())
        },
    );
}

/// Writes `gaussian`'s mean and covariance diagonal of every frustum.
#[allow(clippy::too_many_arguments)]
fn each_frustum(
    origins: &[f32],
    directions: &[f32],
    radii: &[f32],
    rays: &[u32],
    starts: &[f32],
    ends: &[f32],
    means: &mut [f32],
    variances: &mut [f32],
    gaussian: impl Fn(Vec3, Vec3, f32, f32, f32) -> (Vec3, Vec3) + Sync,
) {
    let n = rays.len();
    assert!(
        starts.len() == n && ends.len() == n && means.len() == 3 * n && variances.len() == 3 * n,
        "frustum buffers of {n} samples"
    );
    means
        .par_chunks_mut(3 * SAMPLES_PER_TASK)
        .zip(variances.par_chunks_mut(3 * SAMPLES_PER_TASK))
        .enumerate()
        .for_each(|(task, (means, variances))| {
            let first = task * SAMPLES_PER_TASK;
            for (i, (mean, variance)) in means
                .chunks_exact_mut(3)
                .zip(variances.chunks_exact_mut(3))
                .enumerate()
            {
                let s = first + i;
                let r = rays[s] as usize;
                let (m, v) = gaussian(
                    Vec3::from_slice(&origins[3 * r..]),
                    Vec3::from_slice(&directions[3 * r..]),
                    radii[r],
                    starts[s],
                    ends[s],
                );
                mean.copy_from_slice(&m.to_array());
                variance.copy_from_slice(&v.to_array());
            }
        });
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::shared::frustum::frustum_moments;

    /// Mean and variances of the frustum by numerical integration in f64:
    /// the cone's cross-section at distance t is a disc of radius r·t, its
    /// area ∝ t², so along the axis the density is ∝ t² on [t₀, t₁], and a
    /// disc of radius ρ has variance ρ²/4 along each perpendicular
    /// direction.
    fn integrated(t0: f64, t1: f64, radius: f64) -> (f64, f64, f64) {
        let steps = 200_000;
        let h = (t1 - t0) / steps as f64;
        let (mut mass, mut first, mut second, mut radial) = (0.0, 0.0, 0.0, 0.0);
        // Midpoint rule: error O(h²) relative, far below the tolerances.
        for i in 0..steps {
            let t = t0 + (i as f64 + 0.5) * h;
            let w = t * t * h;
            mass += w;
            first += w * t;
            second += w * t * t;
            radial += w * (radius * t).powi(2) / 4.0;
        }
        let mean = first / mass;
        (mean, second / mass - mean * mean, radial / mass)
    }

    #[test]
    fn moments_match_numerical_integration() {
        // Thin and thick, near and far, starting at the apex.
        let cases = [
            (2.0, 2.01, 0.0015),
            (2.0, 6.0, 0.0015),
            (0.05, 0.06, 0.01),
            (5.9, 5.9001, 0.0015),
            (0.0, 1.0, 0.3),
            (0.0, 1e-3, 1.0),
            (1.0, 3.0, 100.0),
        ];
        for (t0, t1, r) in cases {
            let m = frustum_moments(t0 as f32, t1 as f32, r as f32);
            let (mean, var_t, var_r) = integrated(t0, t1, r);
            // f32 holds ~7 digits: the mean to a few ulps of t₁; each
            // variance to 1e-4 of itself (the formulas' terms are of the
            // variance's own size, no cancellation) or an absolute floor of
            // a few ulps of t₁² for the near-zero axial variance of the
            // thinnest intervals.
            let ulp = (t1 * t1 * 4.0 * f32::EPSILON as f64).max(1e-30);
            assert!(
                (m.t_mean as f64 - mean).abs() <= 4.0 * f32::EPSILON as f64 * t1.max(1e-6),
                "mean of [{t0}, {t1}]: {} vs {mean}",
                m.t_mean
            );
            assert!(
                (m.t_variance as f64 - var_t).abs() <= 1e-4 * var_t + ulp,
                "axial variance of [{t0}, {t1}]: {} vs {var_t}",
                m.t_variance
            );
            assert!(
                (m.radial_variance as f64 - var_r).abs() <= 1e-4 * var_r + ulp * r * r,
                "radial variance of [{t0}, {t1}] r {r}: {} vs {var_r}",
                m.radial_variance
            );
        }
    }

    #[test]
    fn degenerate_frustums_are_finite() {
        for (t0, t1) in [(0.0, 0.0), (3.0, 3.0), (0.0, 1e-30), (1e-30, 1e-30)] {
            for radius in [1e-8, 1.5e-3, 1e2] {
                let m = frustum_moments(t0, t1, radius);
                assert!(
                    m.t_mean.is_finite() && m.t_variance >= 0.0 && m.radial_variance >= 0.0,
                    "[{t0}, {t1}] r {radius}: {m:?}"
                );
                assert!(m.t_variance.is_finite() && m.radial_variance.is_finite());
                // A zero-length interval is a point: its mean is that point,
                // the axial variance 0, the radial one the disc's (r t)²/4.
                if t0 == t1 {
                    assert_eq!(m.t_mean, t0);
                    assert_eq!(m.t_variance, 0.0);
                    let disc = radius * radius * t0 * t0 / 4.0;
                    assert!((m.radial_variance - disc).abs() <= 1e-6 * disc + 1e-37);
                }
            }
        }
    }

    /// Each frustum's warped Gaussian against Monte Carlo points of the
    /// frustum itself (uniform in the cone between t₀ and t₁: density ∝ t²
    /// along the axis, uniform over the disc of radius r·t) pushed through
    /// the contraction: the mean and the covariance's diagonal. Two errors
    /// separate them. The Gaussian's moments are the frustum's exactly,
    /// but the linearisation drops the map's second-order terms: with a
    /// spread σ at distance ρ from the centre they move the mean by
    /// ~σ²/ρ² of ρ·|J| (≤ 0.2 % of the spread for these frustums, σ/ρ ≤
    /// 0.05) and the variance by ~(σ/ρ)² (≤ 0.3 %). The estimates from
    /// 100,000 points are off by ~1/√100000 = 0.3 % of the spread (mean)
    /// and ~√(0.8/100000) ≈ 0.3 % of the variance for distributions as
    /// light-tailed as these (a uniform's kurtosis is 1.8): 5 % of the
    /// spread and 3 % of each variance hold both, several times over,
    /// while a covariance left unwarped (Σ without J) misses the far
    /// frustums' variances by far more: J scales them by ~(2/ρ)² across
    /// the ray from the centre and ~1/ρ⁴ along it (at ρ = 10, factors of
    /// 25 and 10⁴).
    #[test]
    fn contracted_frustums_match_monte_carlo_points_through_the_contraction() {
        use crate::field::contraction::{ContractionNorm, contract};
        let contraction = Contraction {
            centre: Vec3::new(0.5, -1.0, 0.25),
            radius: 2.0,
            norm: ContractionNorm::L2,
        };
        let mut state = 17u64;
        let mut uniform = move || {
            state = crate::rng::splitmix64(state);
            ((state >> 11) as f64 + 0.5) / (1u64 << 53) as f64
        };
        // Origin, direction, cone radius, interval: inside the unit ball
        // (left as it is), just beyond it, far out, and very far out with a
        // wide cone, along different directions.
        let origin = Vec3::new(0.6, -0.8, 0.3);
        let cases = [
            (Vec3::new(1.0, 0.2, -0.1), 0.01, 0.5, 0.6),
            (Vec3::new(-0.3, 1.0, 0.4), 0.02, 3.0, 3.3),
            (Vec3::new(0.2, -0.5, 1.0), 0.01, 20.0, 21.0),
            (Vec3::new(-1.0, -0.7, 0.2), 0.05, 300.0, 330.0),
        ];
        for (direction, radius, t0, t1) in cases {
            let direction = direction.normalize();
            let mut means = [0f32; 3];
            let mut variances = [0f32; 3];
            contracted_frustum_gaussians(
                &origin.to_array(),
                &direction.to_array(),
                &[radius],
                &[0],
                &[t0],
                &[t1],
                &contraction,
                &mut means,
                &mut variances,
            );
            let (mean, variance) = (Vec3::from_array(means), Vec3::from_array(variances));
            // A basis across the ray.
            let across = direction.any_orthonormal_pair();
            let n = 100_000;
            let (t0d, t1d) = (t0 as f64, t1 as f64);
            let mut sum = [0f64; 3];
            let mut square = [0f64; 3];
            for _ in 0..n {
                let t = (t0d.powi(3) + uniform() * (t1d.powi(3) - t0d.powi(3))).cbrt();
                let rho = radius as f64 * t * uniform().sqrt();
                let angle = std::f64::consts::TAU * uniform();
                let point = origin
                    + direction * t as f32
                    + across.0 * (rho * angle.cos()) as f32
                    + across.1 * (rho * angle.sin()) as f32;
                let warped = contract(contraction.to_frame(point), contraction.norm);
                for axis in 0..3 {
                    sum[axis] += warped[axis] as f64;
                    square[axis] += (warped[axis] as f64).powi(2);
                }
            }
            let spread = variance.max_element().sqrt() as f64;
            for axis in 0..3 {
                let sample_mean = sum[axis] / n as f64;
                let sample_variance = square[axis] / n as f64 - sample_mean * sample_mean;
                assert!(
                    (sample_mean - mean[axis] as f64).abs() < 0.05 * spread,
                    "[{t0}, {t1}] axis {axis}: mean {sample_mean} vs {}",
                    mean[axis]
                );
                let v = variance[axis] as f64;
                assert!(
                    (sample_variance - v).abs() < 0.03 * v,
                    "[{t0}, {t1}] axis {axis}: variance {sample_variance:e} vs {v:e}"
                );
            }
            // Inside the unit ball the map is the frame's scaling alone:
            // the world Gaussian's diagonal over radius².
            if t1 < 1.0 {
                let (world_mean, world_variance) =
                    frustum_gaussian(origin, direction, radius, t0, t1);
                let scale = contraction.radius * contraction.radius;
                assert!((mean - contraction.to_frame(world_mean)).length() < 1e-6);
                assert!((variance - world_variance / scale).length() < 1e-6 * variance.length());
            }
        }
    }

    #[test]
    fn world_gaussian_follows_the_direction() {
        // Along +x: the axial variance on x, the radial on y and z.
        let (mean, var) = frustum_gaussian(Vec3::new(1.0, 2.0, 3.0), Vec3::X, 0.1, 2.0, 4.0);
        let m = frustum_moments(2.0, 4.0, 0.1);
        assert!((mean - Vec3::new(1.0 + m.t_mean, 2.0, 3.0)).length() < 1e-6);
        assert_eq!(
            var,
            Vec3::new(m.t_variance, m.radial_variance, m.radial_variance)
        );
        // A diagonal direction splits both among the axes; the total
        // variance (trace) is σ_t² + 2 σ_r² whatever the direction.
        let d = Vec3::new(1.0, 2.0, -2.0).normalize();
        let (_, var) = frustum_gaussian(Vec3::ZERO, d, 0.1, 2.0, 4.0);
        let trace = m.t_variance + 2.0 * m.radial_variance;
        assert!(((var.x + var.y + var.z) - trace).abs() < 1e-5 * trace);
    }
}
