//! Mip-NeRF's conical frustums as Gaussians (Barron et al. 2021, section 3.1
//! and appendix A; reference `mip.py`, `conical_frustum_to_gaussian` and
//! `lift_gaussian`), one frustum at a time: the formulas both engines use.
//! The `cpu` engine's batch of them is `engine::cpu::frustum`; the `gpu`
//! engine's kernel (`engine::gpu::frustum`) repeats these operations.
//!
//! A pixel's cone has its apex at the camera and radius `r·t` at distance
//! `t`. The part of it between `t₀` and `t₁` is approximated by the Gaussian
//! with the frustum's mean and covariance. With t_μ = (t₀ + t₁)/2 and
//! t_δ = (t₁ − t₀)/2, the moments along the axis and across it are
//!
//! ```text
//! μ_t  = t_μ + 2 t_μ t_δ² / (3 t_μ² + t_δ²)
//! σ_t² = t_δ²/3 − (4/15) t_δ⁴ (12 t_μ² − t_δ²) / (3 t_μ² + t_δ²)²
//! σ_r² = r² (t_μ²/4 + (5/12) t_δ² − (4/15) t_δ⁴ / (3 t_μ² + t_δ²))
//! ```
//!
//! the paper's stable form: written with the centre and half-width instead
//! of t₀ and t₁, no term cancels catastrophically when the interval is thin
//! and far away, which the direct moment formulas (ratios of differences of
//! t⁵ and t³) do in floating point. In world space, the mean is o + μ_t d
//! and the covariance's diagonal σ_t² d∘d + σ_r² (1 − d∘d) for a unit
//! direction d (the diagonal of σ_t² ddᵀ + σ_r² (I − ddᵀ)): the
//! integrated encoding only needs the diagonal.
//!
//! No gradient flows into the frustums (sample positions are not learned),
//! so only the forward pass exists.

use glam::{Mat3, Vec3};

/// Moments of one frustum along and across the cone's axis.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FrustumMoments {
    /// Mean distance along the axis.
    pub t_mean: f32,
    /// Variance along the axis.
    pub t_variance: f32,
    /// Variance across the axis, per perpendicular direction.
    pub radial_variance: f32,
}

/// The moments of the frustum of a cone of radius `radius` at unit distance
/// between distances `t0` ≤ `t1` (both ≥ 0).
///
/// A frustum of zero extent (t₀ = t₁ = 0, the apex) has all of its moments
/// at the apex: the mean is 0 and both variances 0. Elsewhere the formulas'
/// denominator 3 t_μ² + t_δ² is positive.
pub fn frustum_moments(t0: f32, t1: f32, radius: f32) -> FrustumMoments {
    let mid = 0.5 * (t0 + t1);
    let half = 0.5 * (t1 - t0);
    let (mid2, half2) = (mid * mid, half * half);
    let denominator = 3.0 * mid2 + half2;
    // Also catches NaN from non-finite distances.
    if denominator.is_nan() || denominator <= 0.0 {
        return FrustumMoments {
            t_mean: mid,
            t_variance: 0.0,
            radial_variance: 0.0,
        };
    }
    let half4_over = half2 * half2 / denominator;
    let t_mean = mid + 2.0 * mid * half2 / denominator;
    // Both variances are non-negative in exact arithmetic; rounding may not
    // keep them so for vanishing widths, and the encoding takes a square
    // root's worth of them.
    let t_variance =
        (half2 / 3.0 - (4.0 / 15.0) * half4_over * (12.0 * mid2 - half2) / denominator).max(0.0);
    let radial_variance =
        (radius * radius * (mid2 / 4.0 + (5.0 / 12.0) * half2 - (4.0 / 15.0) * half4_over))
            .max(0.0);
    FrustumMoments {
        t_mean,
        t_variance,
        radial_variance,
    }
}

/// The world-space Gaussian of a frustum: mean o + μ_t d and the diagonal
/// of its covariance, for a unit `direction` d.
pub fn frustum_gaussian(
    origin: Vec3,
    direction: Vec3,
    radius: f32,
    t0: f32,
    t1: f32,
) -> (Vec3, Vec3) {
    let m = frustum_moments(t0, t1, radius);
    let along = direction * direction;
    let variance = along * m.t_variance + (Vec3::ONE - along).max(Vec3::ZERO) * m.radial_variance;
    (origin + direction * m.t_mean, variance)
}

/// The world-space Gaussian of a frustum with its full covariance,
/// σ_t² ddᵀ + σ_r² (I − ddᵀ) for a unit `direction` d (Mip-NeRF, eq. 7;
/// reference `lift_gaussian` with `diag=False`): what a non-linear map of
/// space (Mip-NeRF 360's contraction) carries through its Jacobian, where
/// the integrated encoding alone needs only the diagonal.
pub fn frustum_gaussian_full(
    origin: Vec3,
    direction: Vec3,
    radius: f32,
    t0: f32,
    t1: f32,
) -> (Vec3, Mat3) {
    let m = frustum_moments(t0, t1, radius);
    let d = direction;
    let outer = Mat3::from_cols(d * d.x, d * d.y, d * d.z);
    let covariance = outer * m.t_variance + (Mat3::IDENTITY - outer) * m.radial_variance;
    (origin + d * m.t_mean, covariance)
}
