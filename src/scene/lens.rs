//! Lens distortion: where a real lens puts the image of a direction, and the
//! inverse, which ray generation needs.
//!
//! Both models work in OpenCV's normalised image coordinates: for a point
//! (X, Y, Z) in OpenCV camera axes (x right, y down, z forward), the ideal
//! pinhole image is (x, y) = (X/Z, Y/Z), and the pixel is
//! (fx · x_d + cx, fy · y_d + cy) where (x_d, y_d) is the distorted point.
//! The coefficients are unitless, so they do not change when an image is
//! downscaled.
//!
//! - Radial-tangential (Brown–Conrady, OpenCV's `OPENCV` model and
//!   instant-ngp's / nerfstudio's `k1 k2 k3 k4 p1 p2`): with r² = x² + y²,
//!   radial = 1 + k1 r² + k2 r⁴ + k3 r⁶ + k4 r⁸ (k4 as nerfstudio's
//!   `radial_and_tangential_undistort` uses it; OpenCV's own model has no r⁸
//!   term, so files from OpenCV leave it 0),
//!   x_d = x · radial + 2 p1 x y + p2 (r² + 2 x²),
//!   y_d = y · radial + p1 (r² + 2 y²) + 2 p2 x y.
//! - Fisheye (OpenCV's `fisheye` module, nerfstudio's `OPENCV_FISHEYE`,
//!   instant-ngp's `is_fisheye`): θ = atan(r) is the angle off the optical
//!   axis, θ_d = θ (1 + k1 θ² + k2 θ⁴ + k3 θ⁶ + k4 θ⁸), and
//!   (x_d, y_d) = (θ_d / r) (x, y). Directions up to 90° off axis and
//!   beyond are representable, which the pinhole coordinates are not, so the
//!   inverse of this model gives the angle, not (x, y).
//!
//! The inverses have no closed form: they are Newton iterations in f64 (the
//! 2×2 Jacobian for radial-tangential, the scalar derivative for fisheye),
//! started from the distorted point, stopped when a step moves less than
//! [`UNDISTORT_TOLERANCE`] (1e-12 in normalised units, i.e. below 1e-8 px
//! for any focal length under 10⁴ px) or after [`UNDISTORT_MAX_ITERATIONS`].
//! Only roots where the mapping keeps the orientation it has at the centre
//! count (past a fold, a second root points elsewhere). Where there is no
//! such root (coefficients whose mapping folds over inside the image, far
//! outside the calibrated region), the valid iterate with the smallest
//! residual is used, or the distorted point itself: never a NaN. The ray is
//! then approximate but finite, and [`Lens::undistort`] reports it.

/// A Newton step shorter than this (normalised image units) ends the
/// iteration: converged.
pub const UNDISTORT_TOLERANCE: f64 = 1e-12;

/// Newton iterations at most. Typical lenses converge in 3–6 from the
/// distorted point; 50 leaves room for strong fisheyes near their edge.
pub const UNDISTORT_MAX_ITERATIONS: u32 = 50;

/// A residual below this (normalised units) counts as converged even when
/// the last step was not tiny (rounding keeps Newton wandering by ~1e-16).
const RESIDUAL_TOLERANCE: f64 = 1e-10;

/// The lens model of a camera.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub enum Lens {
    /// An ideal pinhole: no distortion.
    #[default]
    Pinhole,
    /// OpenCV radial-tangential distortion.
    RadialTangential {
        k1: f32,
        k2: f32,
        k3: f32,
        k4: f32,
        p1: f32,
        p2: f32,
    },
    /// OpenCV's equidistant fisheye model.
    Fisheye { k1: f32, k2: f32, k3: f32, k4: f32 },
}

/// Where a pixel's direction lies, from [`Lens::undistort`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Undistorted {
    /// Unit direction in OpenCV camera axes (x right, y down, z forward).
    pub direction: [f64; 3],
    /// Whether the iteration met its tolerance (always true for a pinhole).
    pub converged: bool,
}

impl Lens {
    /// Whether this lens bends nothing (a pinhole, or every coefficient 0).
    pub fn is_pinhole(&self) -> bool {
        match *self {
            Lens::Pinhole => true,
            Lens::RadialTangential {
                k1,
                k2,
                k3,
                k4,
                p1,
                p2,
            } => [k1, k2, k3, k4, p1, p2].iter().all(|&c| c == 0.0),
            // A fisheye with zero coefficients is still equidistant, not a
            // pinhole.
            Lens::Fisheye { .. } => false,
        }
    }

    /// A short description for `zrak info`.
    pub fn describe(&self) -> String {
        match *self {
            Lens::Pinhole => "pinhole".into(),
            Lens::RadialTangential {
                k1,
                k2,
                k3,
                k4,
                p1,
                p2,
            } => format!("radial-tangential k1 {k1} k2 {k2} k3 {k3} k4 {k4} p1 {p1} p2 {p2}"),
            Lens::Fisheye { k1, k2, k3, k4 } => {
                format!("fisheye k1 {k1} k2 {k2} k3 {k3} k4 {k4}")
            }
        }
    }

    /// The distorted normalised image point of the direction `(x, y, z)` in
    /// OpenCV camera axes (z > 0 for a pinhole-like lens; a fisheye also
    /// images directions at and beyond 90°, z ≤ 0, except straight back).
    /// `None` where the lens images nothing.
    pub fn distort_direction(&self, x: f64, y: f64, z: f64) -> Option<(f64, f64)> {
        match *self {
            Lens::Fisheye { k1, k2, k3, k4 } => {
                let r = (x * x + y * y).sqrt();
                if r == 0.0 {
                    return (z > 0.0).then_some((0.0, 0.0));
                }
                let theta = r.atan2(z);
                let theta_d = theta * fisheye_factor([k1, k2, k3, k4].map(f64::from), theta);
                Some((theta_d * x / r, theta_d * y / r))
            }
            _ if z <= 0.0 => None,
            _ => Some(self.distort(x / z, y / z)),
        }
    }

    /// The distorted normalised point of the ideal pinhole point (x, y).
    /// For a fisheye, (x, y) is the pinhole point of a direction in front.
    pub fn distort(&self, x: f64, y: f64) -> (f64, f64) {
        match *self {
            Lens::Pinhole => (x, y),
            Lens::RadialTangential {
                k1,
                k2,
                k3,
                k4,
                p1,
                p2,
            } => {
                let c = RadialTangentialF64::new(k1, k2, k3, k4, p1, p2);
                c.distort(x, y)
            }
            Lens::Fisheye { .. } => self
                .distort_direction(x, y, 1.0)
                .expect("a direction in front always images"),
        }
    }

    /// The direction whose image is the distorted normalised point
    /// (xd, yd): the inverse of [`Self::distort_direction`].
    pub fn undistort(&self, xd: f64, yd: f64) -> Undistorted {
        match *self {
            Lens::Pinhole => Undistorted {
                direction: normalise([xd, yd, 1.0]),
                converged: true,
            },
            Lens::RadialTangential {
                k1,
                k2,
                k3,
                k4,
                p1,
                p2,
            } => {
                let c = RadialTangentialF64::new(k1, k2, k3, k4, p1, p2);
                let (x, y, converged) = c.undistort(xd, yd);
                Undistorted {
                    direction: normalise([x, y, 1.0]),
                    converged,
                }
            }
            Lens::Fisheye { k1, k2, k3, k4 } => {
                let theta_d = (xd * xd + yd * yd).sqrt();
                if theta_d == 0.0 {
                    return Undistorted {
                        direction: [0.0, 0.0, 1.0],
                        converged: true,
                    };
                }
                let (theta, converged) = fisheye_theta([k1, k2, k3, k4].map(f64::from), theta_d);
                let (sin, cos) = theta.sin_cos();
                Undistorted {
                    direction: [sin * xd / theta_d, sin * yd / theta_d, cos],
                    converged,
                }
            }
        }
    }
}

fn normalise(v: [f64; 3]) -> [f64; 3] {
    let length = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    v.map(|c| c / length)
}

/// 1 + k1 θ² + k2 θ⁴ + k3 θ⁶ + k4 θ⁸.
fn fisheye_factor(k: [f64; 4], theta: f64) -> f64 {
    let t2 = theta * theta;
    1.0 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3])))
}

/// Solves θ (1 + k1 θ² + ...) = θ_d for θ by Newton's method from θ_d,
/// within [0, π] (directions beyond straight back do not exist) and where
/// the image radius still grows with θ (past a fold the root would be on
/// the wrong branch). Without a converged root, the valid iterate with the
/// smallest residual, or θ_d itself when there is none.
fn fisheye_theta(k: [f64; 4], theta_d: f64) -> (f64, bool) {
    let mut theta = theta_d.min(std::f64::consts::PI);
    let mut best: Option<(f64, f64)> = None;
    for _ in 0..=UNDISTORT_MAX_ITERATIONS {
        let t2 = theta * theta;
        let residual = theta * fisheye_factor(k, theta) - theta_d;
        // d/dθ of θ + k1 θ³ + k2 θ⁵ + k3 θ⁷ + k4 θ⁹.
        let derivative =
            1.0 + t2 * (3.0 * k[0] + t2 * (5.0 * k[1] + t2 * (7.0 * k[2] + t2 * 9.0 * k[3])));
        if !(residual.is_finite() && derivative.is_finite() && derivative > 1e-15) {
            break;
        }
        if best.is_none_or(|(best_r, _)| residual.abs() < best_r) {
            best = Some((residual.abs(), theta));
        }
        let step = residual / derivative;
        if step.abs() < UNDISTORT_TOLERANCE {
            return (theta, true);
        }
        theta = (theta - step).clamp(0.0, std::f64::consts::PI);
    }
    match best {
        Some((r, theta)) => (theta, r < RESIDUAL_TOLERANCE),
        None => (theta_d.min(std::f64::consts::PI), false),
    }
}

/// The radial-tangential coefficients in f64.
struct RadialTangentialF64 {
    k: [f64; 4],
    p1: f64,
    p2: f64,
}

impl RadialTangentialF64 {
    fn new(k1: f32, k2: f32, k3: f32, k4: f32, p1: f32, p2: f32) -> Self {
        Self {
            k: [k1, k2, k3, k4].map(f64::from),
            p1: p1 as f64,
            p2: p2 as f64,
        }
    }

    fn distort(&self, x: f64, y: f64) -> (f64, f64) {
        let r2 = x * x + y * y;
        let k = &self.k;
        let radial = 1.0 + r2 * (k[0] + r2 * (k[1] + r2 * (k[2] + r2 * k[3])));
        (
            x * radial + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x),
            y * radial + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y,
        )
    }

    /// The Jacobian of [`Self::distort`] at (x, y): [[∂xd/∂x, ∂xd/∂y],
    /// [∂yd/∂x, ∂yd/∂y]].
    fn jacobian(&self, x: f64, y: f64) -> [[f64; 2]; 2] {
        let r2 = x * x + y * y;
        let k = &self.k;
        let radial = 1.0 + r2 * (k[0] + r2 * (k[1] + r2 * (k[2] + r2 * k[3])));
        // d radial / d r².
        let radial_r2 = k[0] + r2 * (2.0 * k[1] + r2 * (3.0 * k[2] + r2 * 4.0 * k[3]));
        let (p1, p2) = (self.p1, self.p2);
        [
            [
                radial + 2.0 * x * x * radial_r2 + 2.0 * p1 * y + 6.0 * p2 * x,
                2.0 * x * y * radial_r2 + 2.0 * p1 * x + 2.0 * p2 * y,
            ],
            [
                2.0 * x * y * radial_r2 + 2.0 * p1 * x + 2.0 * p2 * y,
                radial + 2.0 * y * y * radial_r2 + 6.0 * p1 * y + 2.0 * p2 * x,
            ],
        ]
    }

    /// Newton's method for distort(x, y) = (xd, yd), from (xd, yd). Only
    /// points where the mapping keeps its orientation (a positive Jacobian
    /// determinant, as at the centre) count: past a fold, a root on the far side
    /// would point the ray elsewhere entirely. Without a converged root the
    /// orientation-keeping iterate with the smallest residual is returned,
    /// or (xd, yd) itself when there is none.
    fn undistort(&self, xd: f64, yd: f64) -> (f64, f64, bool) {
        let norm = |a: f64, b: f64| (a * a + b * b).sqrt();
        let (mut x, mut y) = (xd, yd);
        let mut best: Option<(f64, f64, f64)> = None;
        for _ in 0..=UNDISTORT_MAX_ITERATIONS {
            let (dx, dy) = self.distort(x, y);
            let (rx, ry) = (dx - xd, dy - yd);
            let r = norm(rx, ry);
            let [[a, b], [c, d]] = self.jacobian(x, y);
            let determinant = a * d - b * c;
            if !(r.is_finite() && determinant.is_finite() && determinant > 1e-15) {
                break;
            }
            if best.is_none_or(|(best_r, _, _)| r < best_r) {
                best = Some((r, x, y));
            }
            let step_x = (d * rx - b * ry) / determinant;
            let step_y = (a * ry - c * rx) / determinant;
            if norm(step_x, step_y) < UNDISTORT_TOLERANCE {
                return (x, y, true);
            }
            x -= step_x;
            y -= step_y;
        }
        match best {
            Some((r, x, y)) => (x, y, r < RESIDUAL_TOLERANCE),
            None => (xd, yd, false),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A strong but ordinary phone-like lens (coefficients of the order
    /// COLMAP reports for phone captures).
    const RADIAL: Lens = Lens::RadialTangential {
        k1: -0.12,
        k2: 0.05,
        k3: -0.01,
        k4: 0.002,
        p1: 0.001,
        p2: -0.0015,
    };
    const FISHEYE: Lens = Lens::Fisheye {
        k1: 0.05,
        k2: -0.01,
        k3: 0.003,
        k4: -0.0005,
    };

    #[test]
    fn radial_tangential_matches_the_closed_form() {
        let (x, y) = (0.3_f64, -0.2_f64);
        let r2 = x * x + y * y;
        let radial = 1.0 - 0.12 * r2 + 0.05 * r2 * r2 - 0.01 * r2.powi(3) + 0.002 * r2.powi(4);
        let p1 = 0.001_f32 as f64;
        let p2 = -0.0015_f32 as f64;
        let want_x = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x);
        let want_y = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y;
        let (got_x, got_y) = RADIAL.distort(x, y);
        // The coefficients are f32; the formula above uses the decimal
        // values, so agreement is to f32 precision of the coefficients.
        assert!((got_x - want_x).abs() < 1e-8, "{got_x} vs {want_x}");
        assert!((got_y - want_y).abs() < 1e-8, "{got_y} vs {want_y}");
        // Pure k1 on the x axis: x (1 + k1 x²).
        let k1_only = Lens::RadialTangential {
            k1: 0.25,
            k2: 0.0,
            k3: 0.0,
            k4: 0.0,
            p1: 0.0,
            p2: 0.0,
        };
        assert_eq!(k1_only.distort(0.5, 0.0), (0.5 * (1.0 + 0.25 * 0.25), 0.0));
        // Pure p1 at (0, y): y + p1 · 3y².
        let p1_only = Lens::RadialTangential {
            k1: 0.0,
            k2: 0.0,
            k3: 0.0,
            k4: 0.0,
            p1: 0.5,
            p2: 0.0,
        };
        assert_eq!(p1_only.distort(0.0, 0.2), (0.0, 0.2 + 0.5 * 3.0 * 0.04));
    }

    #[test]
    fn fisheye_matches_the_closed_form() {
        // Equidistant (all k zero): the image radius is the angle itself.
        let equidistant = Lens::Fisheye {
            k1: 0.0,
            k2: 0.0,
            k3: 0.0,
            k4: 0.0,
        };
        let (xd, yd) = equidistant.distort(1.0, 0.0);
        assert!((xd - std::f64::consts::FRAC_PI_4).abs() < 1e-15 && yd == 0.0);
        // 90° off axis images at radius π/2; straight back images nowhere.
        let (xd, _) = equidistant.distort_direction(0.0, 1.0, 0.0).unwrap();
        assert!(xd.abs() < 1e-15);
        let (_, yd) = equidistant.distort_direction(0.0, 1.0, 0.0).unwrap();
        assert!((yd - std::f64::consts::FRAC_PI_2).abs() < 1e-15);
        assert_eq!(equidistant.distort_direction(0.0, 0.0, -1.0), None);
        // With coefficients: θ_d = θ (1 + k1 θ² + ...).
        let theta = (0.4_f64 * 0.4 + 0.3 * 0.3).sqrt().atan();
        let k = [0.05_f32, -0.01, 0.003, -0.0005].map(f64::from);
        let t2 = theta * theta;
        let theta_d =
            theta * (1.0 + k[0] * t2 + k[1] * t2 * t2 + k[2] * t2.powi(3) + k[3] * t2.powi(4));
        let (xd, yd) = FISHEYE.distort(0.4, 0.3);
        assert!((xd - theta_d * 0.8).abs() < 1e-14, "{xd}");
        assert!((yd - theta_d * 0.6).abs() < 1e-14, "{yd}");
    }

    /// Distort then undistort, over a grid of image points out to a 60°
    /// half-angle (radial-tangential) and 100° (fisheye): the direction
    /// comes back to 1e-10 (1e-7 px at f = 1000).
    #[test]
    fn undistort_inverts_distort() {
        for lens in [RADIAL, FISHEYE] {
            let reach = if lens == FISHEYE { 100f64 } else { 60f64 }.to_radians();
            for i in -10..=10 {
                for j in -10..=10 {
                    let (ax, ay) = (reach * i as f64 / 10.0, reach * j as f64 / 10.0);
                    let angle = (ax * ax + ay * ay).sqrt();
                    if angle > reach || angle == 0.0 {
                        continue;
                    }
                    let direction = [
                        angle.sin() * ax / angle,
                        angle.sin() * ay / angle,
                        angle.cos(),
                    ];
                    let Some((xd, yd)) =
                        lens.distort_direction(direction[0], direction[1], direction[2])
                    else {
                        panic!("{lens:?} images nothing at {direction:?}");
                    };
                    let back = lens.undistort(xd, yd);
                    assert!(back.converged, "{lens:?} at {direction:?}");
                    for a in 0..3 {
                        assert!(
                            (back.direction[a] - direction[a]).abs() < 1e-10,
                            "{lens:?}: {direction:?} came back as {:?}",
                            back.direction
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn a_folding_lens_reports_no_convergence_and_stays_finite() {
        // k1 = -1 folds the image at r² = 1/3: distorted radii beyond its
        // maximum (2/(3√3) ≈ 0.385) have no preimage.
        let folding = Lens::RadialTangential {
            k1: -1.0,
            k2: 0.0,
            k3: 0.0,
            k4: 0.0,
            p1: 0.0,
            p2: 0.0,
        };
        let result = folding.undistort(0.6, 0.0);
        assert!(!result.converged);
        assert!(result.direction.iter().all(|c| c.is_finite()));
        // Inside the fold it converges.
        assert!(folding.undistort(0.2, 0.1).converged);
    }

    #[test]
    fn zero_coefficients_are_a_pinhole() {
        assert!(Lens::Pinhole.is_pinhole());
        assert!(
            Lens::RadialTangential {
                k1: 0.0,
                k2: 0.0,
                k3: 0.0,
                k4: 0.0,
                p1: 0.0,
                p2: 0.0
            }
            .is_pinhole()
        );
        assert!(!RADIAL.is_pinhole());
        assert!(!FISHEYE.is_pinhole());
    }
}
