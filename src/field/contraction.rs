//! Scene contraction (Barron et al. 2022, "Mip-NeRF 360", section 2.2):
//! the whole of space warped into a ball (or cube) of radius 2 so that a
//! field of bounded extent can hold an unbounded scene, the far field at a
//! resolution that falls with distance as a camera near the centre sees it.
//!
//! Positions are first moved into the scene's *contraction frame*:
//! x = (p − centre) / radius, where the cameras and the content they circle
//! lie within ‖x‖ ≤ 1. Then (eq. 10)
//!
//! ```text
//! contract(x) = x                          for ‖x‖ ≤ 1
//!               (2 − 1/‖x‖) · x/‖x‖        for ‖x‖ > 1
//! ```
//!
//! which is continuous at ‖x‖ = 1 (both give x) and maps infinity to the
//! sphere of radius 2. The norm is the L2 norm for NeRF and Mip-NeRF (the
//! paper's) and the L∞ norm for hash grids (nerfstudio's
//! `SceneContraction(order=inf)`): the contracted space is then the cube
//! [−2, 2]³, which a grid tiles without the corners a ball leaves empty.
//!
//! **The Jacobian.** Outside the unit ball, write r = ‖x‖ and
//! contract(x) = s(r)·x with s(r) = (2 − 1/r)/r = 2/r − 1/r². Then
//! J = s(r)·I + s′(r)·x·(∇r)ᵀ, s′(r) = −2/r² + 2/r³, with ∇r = x/r for
//! L2 and ∇r = sign(x_k)·e_k for L∞ (k the axis of the largest |x_k|).
//!
//! **Gaussians** (Mip-NeRF's frustums) go through the map's linearisation
//! at their mean, as Mip-NeRF 360 does (eq. 9 and section 2.2): mean
//! contract(μ), covariance J Σ Jᵀ.
//!
//! **Spacing along rays.** Samples are placed uniformly in
//! s = g(t) with g(t) = t/2 for t < 1 and 1 − 1/(2t) beyond (t in the
//! frame's units): linear inside the unit ball, linear in disparity 1/t
//! outside, so the far field, which contraction squeezes, gets few samples
//! (Mip-NeRF 360, section 2.3, eq. 11 with g = 1/x beyond the ball;
//! nerfstudio's `UniformLinDispPiecewiseSampler`). g is continuous and
//! increasing, with g(1) = ½ and g(∞) = 1.

use glam::{Mat3, Vec3};

/// The norm whose unit ball contraction leaves as it is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum ContractionNorm {
    /// The ball: Mip-NeRF 360's, for NeRF's and Mip-NeRF's encodings.
    L2,
    /// The cube: for hash grids (nerfstudio's nerfacto).
    LInf,
}

/// The contraction of one scene: its frame and norm.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Contraction {
    /// The frame's origin, in world units.
    pub centre: Vec3,
    /// World units per unit of the frame: the content within this
    /// distance of the centre is left as it is.
    pub radius: f32,
    pub norm: ContractionNorm,
}

impl Contraction {
    /// The frame around camera positions: centred on their mean, with a
    /// radius that holds every camera (in the norm's sense), so the
    /// cameras and what they circle are left unwarped (nerfstudio's
    /// pose normalisation to the unit cube does the same).
    pub fn around_cameras(positions: &[Vec3], norm: ContractionNorm) -> Self {
        let count = positions.len().max(1) as f32;
        let centre = positions.iter().copied().sum::<Vec3>() / count;
        let radius = positions
            .iter()
            .map(|&p| norm.of(p - centre))
            .fold(0.0f32, f32::max);
        Self {
            centre,
            radius: if radius > 1e-6 { radius } else { 1.0 },
            norm,
        }
    }

    /// A world position in the frame's units.
    pub fn to_frame(&self, world: Vec3) -> Vec3 {
        (world - self.centre) / self.radius
    }

    /// A world position contracted: in the ball (or cube) of radius 2.
    pub fn contract_world(&self, world: Vec3) -> Vec3 {
        contract(self.to_frame(world), self.norm)
    }

    /// A world position contracted and the cube [−2, 2]³ mapped onto
    /// [0, 1]³, where a hash grid of extent 1 takes it (nerfstudio's
    /// `(x + 2) / 4`).
    pub fn to_unit_cube(&self, world: Vec3) -> Vec3 {
        self.contract_world(world) * 0.25 + Vec3::splat(0.5)
    }

    /// A world Gaussian (mean, covariance) in the frame's units and through
    /// the contraction's linearisation at its mean ([`contract_gaussian`]):
    /// Mip-NeRF 360's frustums in contracted space (eq. 9–10).
    pub fn contract_world_gaussian(&self, mean: Vec3, covariance: Mat3) -> (Vec3, Mat3) {
        let scale = 1.0 / (self.radius * self.radius);
        contract_gaussian(self.to_frame(mean), covariance * scale, self.norm)
    }

    /// A world distance along a ray in the frame's units.
    pub fn to_frame_distance(&self, t: f32) -> f32 {
        t / self.radius
    }

    /// The spacing coordinate s of a world distance t (see the module).
    pub fn spacing_of(&self, t: f32) -> f32 {
        spacing(self.to_frame_distance(t))
    }

    /// The world distance of spacing coordinate s.
    pub fn distance_of(&self, s: f32) -> f32 {
        inverse_spacing(s) * self.radius
    }
}

impl ContractionNorm {
    pub fn of(self, x: Vec3) -> f32 {
        match self {
            ContractionNorm::L2 => x.length(),
            ContractionNorm::LInf => x.abs().max_element(),
        }
    }

    /// ∇‖x‖ for x ≠ 0.
    fn gradient(self, x: Vec3) -> Vec3 {
        match self {
            ContractionNorm::L2 => x / x.length(),
            ContractionNorm::LInf => {
                let a = x.abs();
                let axis = if a.x >= a.y && a.x >= a.z {
                    0
                } else if a.y >= a.z {
                    1
                } else {
                    2
                };
                let mut g = Vec3::ZERO;
                g[axis] = x[axis].signum();
                g
            }
        }
    }
}

/// contract(x) in the frame's units (module doc, eq. 10).
pub fn contract(x: Vec3, norm: ContractionNorm) -> Vec3 {
    let r = norm.of(x);
    if r <= 1.0 {
        return x;
    }
    x * ((2.0 - 1.0 / r) / r)
}

/// The Jacobian of [`contract`] at x (the identity inside the unit ball).
pub fn jacobian(x: Vec3, norm: ContractionNorm) -> Mat3 {
    let r = norm.of(x);
    if r <= 1.0 {
        return Mat3::IDENTITY;
    }
    let s = 2.0 / r - 1.0 / (r * r);
    let ds = -2.0 / (r * r) + 2.0 / (r * r * r);
    let g = norm.gradient(x);
    // J = s·I + s′·x gᵀ: glam's matrices are column-major, so column j is
    // s·e_j + s′·g_j·x.
    Mat3::from_cols(
        Vec3::X * s + x * (ds * g.x),
        Vec3::Y * s + x * (ds * g.y),
        Vec3::Z * s + x * (ds * g.z),
    )
}

/// A Gaussian (mean, covariance, in the frame's units) through the
/// contraction's linearisation at its mean.
pub fn contract_gaussian(mean: Vec3, covariance: Mat3, norm: ContractionNorm) -> (Vec3, Mat3) {
    let j = jacobian(mean, norm);
    (contract(mean, norm), j * covariance * j.transpose())
}

/// g(t): t/2 inside the unit ball, 1 − 1/(2t) beyond (module doc).
pub fn spacing(t: f32) -> f32 {
    if t < 1.0 {
        0.5 * t.max(0.0)
    } else {
        1.0 - 0.5 / t
    }
}

/// g⁻¹(s) for s in [0, 1): 2s up to ½, 1/(2 − 2s) beyond; s ≥ 1 is
/// infinitely far, returned as f32::MAX so sums stay finite-checked.
pub fn inverse_spacing(s: f32) -> f32 {
    if s < 0.5 {
        2.0 * s.max(0.0)
    } else if s < 1.0 {
        1.0 / (2.0 - 2.0 * s)
    } else {
        f32::MAX
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const NORMS: [ContractionNorm; 2] = [ContractionNorm::L2, ContractionNorm::LInf];

    /// Points spread over several octaves of distance and all directions.
    fn points() -> Vec<Vec3> {
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let mut next = move || {
            state = crate::rng::splitmix64(state);
            (state >> 40) as f32 / (1u64 << 24) as f32
        };
        (0..400)
            .map(|_| {
                let direction = Vec3::new(next() - 0.5, next() - 0.5, next() - 0.5).normalize();
                direction * 10f32.powf(3.0 * next() - 1.0)
            })
            .collect()
    }

    #[test]
    fn contraction_is_continuous_at_the_unit_sphere_and_bounded_by_two() {
        for norm in NORMS {
            for p in points() {
                let on_sphere = p / norm.of(p);
                // Just inside and just outside the sphere: both are the
                // point itself to first order (the factor (2 − 1/r)/r is
                // 1 − (r − 1)² + …), so they are 2ε·|x| apart (|x| up to √3
                // on the L∞ sphere), not more.
                let inside = contract(on_sphere * (1.0 - 1e-4), norm);
                let outside = contract(on_sphere * (1.0 + 1e-4), norm);
                let apart = (inside - outside).length();
                assert!(apart < 2.1e-4 * on_sphere.length(), "{norm:?} {p}: {apart}");
                let c = contract(p, norm);
                assert!(norm.of(c) < 2.0 + 1e-5, "{norm:?}: {c} from {p}");
            }
            let far = contract(Vec3::new(1e9, 3e8, -2e8), norm);
            assert!((norm.of(far) - 2.0).abs() < 1e-5, "{norm:?} {far}");
        }
    }

    #[test]
    fn jacobian_matches_finite_differences() {
        for norm in NORMS {
            for p in points() {
                let r = norm.of(p);
                // Central differences in f64 of the f32 map would be noisy;
                // a step of 1e-3·r keeps rounding (~1e-7/1e-3) and the
                // truncation (~h²·|f'''|, f''' ~ 1/r³) below 1e-3 relative.
                // Points where the L∞ norm's largest axis is nearly tied have
                // a kink within the step: skip those.
                if norm == ContractionNorm::LInf {
                    let mut a = p.abs().to_array();
                    a.sort_by(|x, y| y.partial_cmp(x).unwrap());
                    if a[0] - a[1] < 2e-3 * r {
                        continue;
                    }
                }
                if (r - 1.0).abs() < 2e-3 * r {
                    continue;
                }
                let h = 1e-3 * r;
                let j = jacobian(p, norm);
                for axis in 0..3 {
                    let mut e = Vec3::ZERO;
                    e[axis] = h;
                    let numeric = (contract(p + e, norm) - contract(p - e, norm)) / (2.0 * h);
                    let analytic = j.col(axis);
                    let scale = analytic.length().max(1e-3);
                    assert!(
                        (numeric - analytic).length() < 2e-3 * scale,
                        "{norm:?} at {p}, axis {axis}: {numeric} vs {analytic}"
                    );
                }
            }
        }
    }

    /// The warped Gaussian's mean and covariance against those of Monte
    /// Carlo samples pushed through the contraction. The linearisation is
    /// exact as the Gaussian shrinks: with a standard deviation of 1 % of
    /// the distance, second-order terms move the mean by ~(σ/r)² ≈ 1e-4 of
    /// r and the covariance by ~σ/r ≈ 1 %; the sample estimates' own error
    /// with 40,000 samples is ~1/√40000 = 0.5 % of each entry's scale.
    #[test]
    fn warped_gaussian_matches_monte_carlo_samples() {
        let mut state = 7u64;
        let mut normal = move || {
            // Box–Muller from two uniforms.
            state = crate::rng::splitmix64(state);
            let u1 = ((state >> 11) as f64 + 0.5) / (1u64 << 53) as f64;
            state = crate::rng::splitmix64(state);
            let u2 = (state >> 11) as f64 / (1u64 << 53) as f64;
            ((-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()) as f32
        };
        for norm in NORMS {
            for mean in [
                Vec3::new(0.3, -0.2, 0.1),
                Vec3::new(2.5, 0.7, -0.4),
                Vec3::new(-6.0, 2.0, 9.0),
            ] {
                let r = norm.of(mean);
                let sigma = 0.01 * r;
                // An anisotropic covariance: L Lᵀ with L lower-triangular.
                let l = Mat3::from_cols(
                    Vec3::new(1.0, 0.4, -0.2) * sigma,
                    Vec3::new(0.0, 0.6, 0.3) * sigma,
                    Vec3::new(0.0, 0.0, 0.5) * sigma,
                );
                let covariance = l * l.transpose();
                let (warped_mean, warped_cov) = contract_gaussian(mean, covariance, norm);
                let n = 40_000;
                let samples: Vec<Vec3> = (0..n)
                    .map(|_| contract(mean + l * Vec3::new(normal(), normal(), normal()), norm))
                    .collect();
                let sample_mean = samples.iter().copied().sum::<Vec3>() / n as f32;
                let mut sample_cov = Mat3::ZERO;
                for s in &samples {
                    let d = *s - sample_mean;
                    sample_cov += Mat3::from_cols(d * d.x, d * d.y, d * d.z);
                }
                sample_cov *= 1.0 / (n - 1) as f32;
                let spread = warped_cov.diagonal_max_sqrt();
                assert!(
                    (sample_mean - warped_mean).length() < 0.02 * spread + 1e-4 * r,
                    "{norm:?} {mean}: mean {sample_mean} vs {warped_mean}"
                );
                let scale = spread * spread;
                for (a, b) in sample_cov
                    .to_cols_array()
                    .into_iter()
                    .zip(warped_cov.to_cols_array())
                {
                    assert!(
                        (a - b).abs() < 0.04 * scale,
                        "{norm:?} {mean}: covariance {sample_cov} vs {warped_cov}"
                    );
                }
            }
        }
    }

    #[test]
    fn spacing_is_linear_then_disparity_and_inverts() {
        assert_eq!(spacing(0.0), 0.0);
        assert!((spacing(1.0) - 0.5).abs() < 1e-7);
        assert!((spacing(0.999_999) - 0.5).abs() < 1e-6);
        assert!((spacing(1e30) - 1.0).abs() < 1e-7);
        // Beyond the ball, equal steps of s are equal steps of disparity:
        // 1/t = 2 − 2s.
        for t in [1.5f32, 3.0, 40.0] {
            assert!((1.0 / t - (2.0 - 2.0 * spacing(t))).abs() < 1e-6);
        }
        for t in [0.0f32, 0.2, 0.99, 1.0, 1.7, 12.0, 300.0] {
            let back = inverse_spacing(spacing(t));
            assert!((back - t).abs() <= 1e-4 * t.max(1.0), "{t} → {back}");
        }
        let frame = Contraction {
            centre: Vec3::ZERO,
            radius: 4.0,
            norm: ContractionNorm::L2,
        };
        assert!((frame.distance_of(frame.spacing_of(10.0)) - 10.0).abs() < 1e-4);
    }

    #[test]
    fn frame_around_cameras_holds_every_camera() {
        let cameras = [
            Vec3::new(1.0, 2.0, 3.0),
            Vec3::new(3.0, 2.0, 3.0),
            Vec3::new(2.0, 4.0, 3.0),
            Vec3::new(2.0, 0.0, 3.0),
        ];
        for norm in NORMS {
            let frame = Contraction::around_cameras(&cameras, norm);
            assert_eq!(frame.centre, Vec3::new(2.0, 2.0, 3.0));
            let largest = cameras
                .iter()
                .map(|&c| norm.of(frame.to_frame(c)))
                .fold(0.0, f32::max);
            assert!((largest - 1.0).abs() < 1e-6, "{norm:?} {largest}");
            // Cameras are inside the unwarped region.
            for &c in &cameras {
                assert!((frame.contract_world(c) - frame.to_frame(c)).length() < 1e-6);
            }
        }
    }

    trait DiagonalSpread {
        fn diagonal_max_sqrt(&self) -> f32;
    }

    impl DiagonalSpread for Mat3 {
        fn diagonal_max_sqrt(&self) -> f32 {
            self.x_axis.x.max(self.y_axis.y).max(self.z_axis.z).sqrt()
        }
    }
}
