//! Volume rendering by quadrature along one ray, forward and backward.
//!
//! For samples with densities σᵢ, colours cᵢ and interval lengths δᵢ
//! (Max 1995; NeRF, Mildenhall et al. 2020, eq. 3; the reference thesis,
//! eq. 2.6):
//!
//! ```text
//! τᵢ = σᵢ δᵢ          αᵢ = 1 − exp(−τᵢ)
//! Tᵢ = exp(−Σ_{j<i} τⱼ)  wᵢ = Tᵢ αᵢ = Tᵢ − Tᵢ₊₁
//! colour  = Σ wᵢ cᵢ + T_N · background
//! opacity = Σ wᵢ = 1 − T_N
//! depth   = Σ wᵢ tᵢ      (expected depth; divide by opacity for the
//!                         depth of the surface the ray hit)
//! ```
//!
//! Stability: αᵢ uses `exp_m1`, so τ down to 1e-12 keeps full precision;
//! transmittance is exp of a running sum rather than a running product of
//! (1 − α), so no factor rounds to exactly 1 and no product drifts; and the
//! opacity is taken as 1 − T_N, which makes Σwᵢ ≤ 1 hold by construction.
//!
//! Generic over `f32` and `f64`: the engines run `f32`, gradient checks run
//! `f64`.

use num_traits::Float;

/// What compositing one ray gives.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Composited<F> {
    pub colour: [F; 3],
    /// Σ wᵢ, in [0, 1].
    pub opacity: F,
    /// Σ wᵢ tᵢ.
    pub depth: F,
    /// T_N, the transmittance left after the last sample; the background's
    /// weight.
    pub final_transmittance: F,
}

/// Samples along one ray, in order of increasing distance.
#[derive(Debug, Clone, Copy)]
pub struct RaySamples<'a, F> {
    pub density: &'a [F],
    pub colour: &'a [[F; 3]],
    /// Interval length δᵢ of each sample.
    pub delta: &'a [F],
    /// Distance tᵢ of each sample along the ray, for depth.
    pub t: &'a [F],
}

impl<F: Float> RaySamples<'_, F> {
    fn len(&self) -> usize {
        debug_assert!(
            self.colour.len() == self.density.len()
                && self.delta.len() == self.density.len()
                && self.t.len() == self.density.len()
        );
        self.density.len()
    }

    /// τᵢ = σᵢ δᵢ, with negative densities (never produced by the fields'
    /// activations, but possible from a raw input) treated as empty space.
    fn optical_depth(&self, i: usize) -> F {
        (self.density[i] * self.delta[i]).max(F::zero())
    }
}

/// Per-sample weights wᵢ (written into `weights`) and the final
/// transmittance T_N.
pub fn weights<F: Float>(samples: &RaySamples<F>, weights: &mut [F]) -> F {
    let mut accumulated = F::zero();
    for (i, w) in weights.iter_mut().enumerate().take(samples.len()) {
        let tau = samples.optical_depth(i);
        let transmittance = (-accumulated).exp();
        *w = transmittance * -(-tau).exp_m1();
        accumulated = accumulated + tau;
    }
    (-accumulated).exp()
}

/// Composites one ray over `background`.
pub fn composite<F: Float>(samples: &RaySamples<F>, background: [F; 3]) -> Composited<F> {
    let mut colour = [F::zero(); 3];
    let mut depth = F::zero();
    let mut accumulated = F::zero();
    for i in 0..samples.len() {
        let tau = samples.optical_depth(i);
        let weight = (-accumulated).exp() * -(-tau).exp_m1();
        for (c, sample_c) in colour.iter_mut().zip(samples.colour[i]) {
            *c = *c + weight * sample_c;
        }
        depth = depth + weight * samples.t[i];
        accumulated = accumulated + tau;
    }
    let final_transmittance = (-accumulated).exp();
    for (c, b) in colour.iter_mut().zip(background) {
        *c = *c + final_transmittance * b;
    }
    Composited {
        colour,
        opacity: F::one() - final_transmittance,
        depth,
        final_transmittance,
    }
}

/// Gradients of a loss with respect to compositing's outputs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OutputGradients<F> {
    pub colour: [F; 3],
    pub opacity: F,
    pub depth: F,
}

/// Gradients of the loss with respect to compositing's inputs.
#[derive(Debug, Clone, PartialEq)]
pub struct InputGradients<F> {
    pub density: Vec<F>,
    pub colour: Vec<[F; 3]>,
    pub background: [F; 3],
}

/// The analytic backward pass of [`composite`].
///
/// Every output is Σ wᵢ vᵢ + T_N v_bg for a per-sample value v (colour
/// channel, 1 for opacity, tᵢ for depth), so with gᵢ = ∂L/∂output · vᵢ folded
/// into one scalar per sample:
///
/// ```text
/// ∂wᵢ/∂τₖ = Tₖ₊₁ (i = k),  −wᵢ (i > k),  0 (i < k);   ∂T_N/∂τₖ = −T_N
/// ∂L/∂τₖ = Tₖ₊₁ gₖ − (Σ_{i>k} wᵢ gᵢ + T_N g_bg)
/// ∂L/∂σₖ = δₖ ∂L/∂τₖ
/// ```
///
/// The bracket (what lies behind sample k) is accumulated from the back of
/// the ray, so no large total is subtracted from (which would cancel
/// catastrophically once the ray is opaque).
pub fn composite_backward<F: Float>(
    samples: &RaySamples<F>,
    background: [F; 3],
    grad: &OutputGradients<F>,
) -> InputGradients<F> {
    let n = samples.len();
    let mut weight = vec![F::zero(); n];
    let final_transmittance = weights(samples, &mut weight);

    let folded = |c: [F; 3], t: F| {
        grad.colour[0] * c[0]
            + grad.colour[1] * c[1]
            + grad.colour[2] * c[2]
            + grad.opacity
            + grad.depth * t
    };
    let background_value = grad.colour[0] * background[0]
        + grad.colour[1] * background[1]
        + grad.colour[2] * background[2];

    let mut density = vec![F::zero(); n];
    let mut colour = vec![[F::zero(); 3]; n];
    let mut behind = final_transmittance * background_value;
    // T_{k+1}, walked backwards: T_N at the end, then T_k = T_{k+1} + w_k.
    // Recomputed from the running sum instead, to stay exact when a sample
    // is opaque (T_{k+1} = 0 would not give back T_k).
    let mut accumulated_before: Vec<F> = Vec::with_capacity(n);
    let mut running = F::zero();
    for k in 0..n {
        accumulated_before.push(running);
        running = running + samples.optical_depth(k);
    }
    for k in (0..n).rev() {
        let transmittance_after = (-(accumulated_before[k] + samples.optical_depth(k))).exp();
        let g = folded(samples.colour[k], samples.t[k]);
        let d_tau = transmittance_after * g - behind;
        // Negative densities were clamped to empty space: no gradient flows.
        density[k] = if samples.density[k] * samples.delta[k] >= F::zero() {
            samples.delta[k] * d_tau
        } else {
            F::zero()
        };
        colour[k] = grad.colour.map(|gc| weight[k] * gc);
        behind = behind + weight[k] * g;
    }
    InputGradients {
        density,
        colour,
        background: grad.colour.map(|gc| final_transmittance * gc),
    }
}

/// Mip-NeRF 360's distortion loss on one ray (Barron et al. 2022, eq. 15):
///
/// ```text
/// L = Σᵢ Σⱼ wᵢ wⱼ |sᵢ − sⱼ| + ⅓ Σᵢ wᵢ² δᵢ
/// ```
///
/// for samples at distances `s` (the intervals' midpoints, sorted) with
/// lengths `delta` and weights `weights`. It is smallest when the weight
/// sits in one short stretch of the ray, so it drains the thin fog a field
/// spreads between the cameras and the surfaces behind it (fog too faint to
/// end a ray, too dense for the occupancy grid to skip). The double sum is
/// taken in O(n) with running sums over the sorted samples:
/// Σᵢⱼ wᵢwⱼ|sᵢ − sⱼ| = 2 Σᵢ wᵢ (sᵢ Σ_{j<i} wⱼ − Σ_{j<i} wⱼ sⱼ).
pub fn distortion<F: Float>(weights: &[F], s: &[F], delta: &[F]) -> F {
    let two = F::one() + F::one();
    let third = F::one() / (two + F::one());
    let (mut weight_before, mut moment_before) = (F::zero(), F::zero());
    let mut loss = F::zero();
    for ((&w, &s), &d) in weights.iter().zip(s).zip(delta) {
        loss = loss + two * w * (s * weight_before - moment_before) + third * w * w * d;
        weight_before = weight_before + w;
        moment_before = moment_before + w * s;
    }
    loss
}

/// ∂L/∂wₖ of [`distortion`] into `gradient`:
///
/// ```text
/// ∂L/∂wₖ = 2 Σⱼ wⱼ |sₖ − sⱼ| + ⅔ wₖ δₖ
///        = 2 (sₖ W_<k − S_<k + S_>k − sₖ W_>k) + ⅔ wₖ δₖ
/// ```
///
/// with W and S the sums of wⱼ and wⱼ sⱼ before and after k.
pub fn distortion_gradient<F: Float>(weights: &[F], s: &[F], delta: &[F], gradient: &mut [F]) {
    let two = F::one() + F::one();
    let two_thirds = two / (two + F::one());
    let (mut weight_after, mut moment_after) = (F::zero(), F::zero());
    for ((&w, &s), _) in weights.iter().zip(s).zip(delta) {
        weight_after = weight_after + w;
        moment_after = moment_after + w * s;
    }
    let (mut weight_before, mut moment_before) = (F::zero(), F::zero());
    for (((&w, &s), &d), g) in weights.iter().zip(s).zip(delta).zip(gradient.iter_mut()) {
        weight_after = weight_after - w;
        moment_after = moment_after - w * s;
        *g = two * (s * weight_before - moment_before + moment_after - s * weight_after)
            + two_thirds * w * d;
        weight_before = weight_before + w;
        moment_before = moment_before + w * s;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A deterministic pseudo-random sequence in [0, 1) for test inputs.
    fn sequence(seed: u64, n: usize) -> Vec<f64> {
        let mut state = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (0..n)
            .map(|_| {
                state = state
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                (state >> 11) as f64 / (1u64 << 53) as f64
            })
            .collect()
    }

    #[derive(Clone)]
    struct Ray {
        density: Vec<f64>,
        colour: Vec<[f64; 3]>,
        delta: Vec<f64>,
        t: Vec<f64>,
        background: [f64; 3],
    }

    impl Ray {
        fn random(seed: u64, n: usize, density_scale: f64) -> Self {
            let r = sequence(seed, 6 * n + 3);
            let delta: Vec<f64> = (0..n).map(|i| 0.01 + 0.05 * r[i]).collect();
            let mut t = Vec::with_capacity(n);
            let mut far = 2.0;
            for d in &delta {
                t.push(far + 0.5 * d);
                far += d;
            }
            Self {
                density: (0..n).map(|i| density_scale * r[n + i]).collect(),
                colour: (0..n)
                    .map(|i| [r[2 * n + i], r[3 * n + i], r[4 * n + i]])
                    .collect(),
                delta,
                t,
                background: [r[6 * n], r[6 * n + 1], r[6 * n + 2]],
            }
        }

        fn samples(&self) -> RaySamples<'_, f64> {
            RaySamples {
                density: &self.density,
                colour: &self.colour,
                delta: &self.delta,
                t: &self.t,
            }
        }
    }

    /// A scalar loss that uses every output with distinct weights.
    const LOSS_COLOUR: [f64; 3] = [0.7, -1.3, 0.4];
    const LOSS_OPACITY: f64 = 0.9;
    const LOSS_DEPTH: f64 = -0.35;

    fn loss(ray: &Ray) -> f64 {
        let out = composite(&ray.samples(), ray.background);
        (0..3).map(|c| LOSS_COLOUR[c] * out.colour[c]).sum::<f64>()
            + LOSS_OPACITY * out.opacity
            + LOSS_DEPTH * out.depth
    }

    /// The error relative to the larger magnitude, with magnitudes below
    /// 1e-3 measured against 1e-3 (so the absolute floor is 1e-9 at a 1e-6
    /// bound).
    fn relative_error(analytic: f64, numeric: f64) -> f64 {
        (analytic - numeric).abs() / analytic.abs().max(numeric.abs()).max(1e-3)
    }

    #[test]
    fn gradients_match_central_differences() {
        // Densities from near-empty to near-opaque rays.
        for (seed, density_scale) in [(1, 0.5), (2, 20.0), (3, 150.0)] {
            let ray = Ray::random(seed, 24, density_scale);
            let grad = OutputGradients {
                colour: LOSS_COLOUR,
                opacity: LOSS_OPACITY,
                depth: LOSS_DEPTH,
            };
            let analytic = composite_backward(&ray.samples(), ray.background, &grad);
            // Central differences with h = 1e-5 have O(h²) ≈ 1e-10 truncation
            // error and O(ε·|L|/h) ≈ 1e-11 rounding error in f64; the
            // relative bound is 1e-6, with an absolute floor of 1e-9 for
            // gradients that cancel to near zero, where any relative
            // measure is rounding noise.
            let mut worst = 0f64;
            for k in 0..ray.density.len() {
                // Stay clear of the clamp at σ = 0.
                let h = (0.5 * ray.density[k]).min(1e-5);
                let mut plus = ray.clone();
                let mut minus = ray.clone();
                plus.density[k] += h;
                minus.density[k] -= h;
                let numeric = (loss(&plus) - loss(&minus)) / (2.0 * h);
                worst = worst.max(relative_error(analytic.density[k], numeric));
                for c in 0..3 {
                    let h = 1e-5;
                    let mut plus = ray.clone();
                    let mut minus = ray.clone();
                    plus.colour[k][c] += h;
                    minus.colour[k][c] -= h;
                    let numeric = (loss(&plus) - loss(&minus)) / (2.0 * h);
                    worst = worst.max(relative_error(analytic.colour[k][c], numeric));
                }
            }
            for c in 0..3 {
                let h = 1e-5;
                let mut plus = ray.clone();
                let mut minus = ray.clone();
                plus.background[c] += h;
                minus.background[c] -= h;
                let numeric = (loss(&plus) - loss(&minus)) / (2.0 * h);
                worst = worst.max(relative_error(analytic.background[c], numeric));
            }
            assert!(
                worst < 1e-6,
                "density scale {density_scale}: worst relative error {worst:e}"
            );
        }
    }

    #[test]
    fn extreme_optical_depths_stay_finite_and_bounded() {
        for tau in [1e-12, 1e-8, 1e-3, 1.0, 30.0, 1e3, 1e4] {
            for n in [1usize, 2, 7, 64] {
                let density = vec![tau; n];
                let colour = vec![[0.2, 0.5, 0.8]; n];
                let delta = vec![1.0; n];
                let t: Vec<f64> = (0..n).map(|i| i as f64 + 0.5).collect();
                let samples = RaySamples {
                    density: &density,
                    colour: &colour,
                    delta: &delta,
                    t: &t,
                };
                let mut w = vec![0.0; n];
                let final_t = weights(&samples, &mut w);
                assert!(
                    w.iter().all(|w| w.is_finite() && (0.0..=1.0).contains(w)),
                    "tau {tau}: {w:?}"
                );
                let sum: f64 = w.iter().sum();
                assert!(sum <= 1.0 + 1e-12, "tau {tau}, n {n}: Σw = {sum}");
                assert!((sum + final_t - 1.0).abs() < 1e-12);
                let out = composite(&samples, [1.0; 3]);
                assert!(
                    out.colour
                        .iter()
                        .all(|c| c.is_finite() && (0.0..=1.0).contains(c))
                );
                assert!((0.0..=1.0).contains(&out.opacity) && out.depth.is_finite());
                // The smallest τ must not be lost to rounding: α ≈ τ.
                if tau == 1e-12 && n == 1 {
                    assert!((w[0] - 1e-12).abs() < 1e-22, "{}", w[0]);
                }
                let grad = OutputGradients {
                    colour: [1.0, -1.0, 0.5],
                    opacity: 1.0,
                    depth: 0.1,
                };
                let g = composite_backward(&samples, [1.0; 3], &grad);
                assert!(g.density.iter().all(|x| x.is_finite()));
                assert!(g.colour.iter().flatten().all(|x| x.is_finite()));
            }
        }
        // The same in f32, where 1 − exp(−τ) would round to 0 without expm1.
        let density = [1e-12f32, 1e4, 1e4];
        let colour = [[0.3f32; 3]; 3];
        let delta = [1.0f32; 3];
        let t = [0.5f32, 1.5, 2.5];
        let samples = RaySamples {
            density: &density,
            colour: &colour,
            delta: &delta,
            t: &t,
        };
        let mut w = [0f32; 3];
        weights(&samples, &mut w);
        assert!(w[0] > 0.0 && w[0] < 2e-12 && (w[1] - 1.0).abs() < 1e-6 && w[2] == 0.0);
    }

    #[test]
    fn empty_ray_is_background() {
        let samples: RaySamples<f64> = RaySamples {
            density: &[],
            colour: &[],
            delta: &[],
            t: &[],
        };
        let out = composite(&samples, [0.25, 0.5, 0.75]);
        assert_eq!(out.colour, [0.25, 0.5, 0.75]);
        assert_eq!(
            (out.opacity, out.depth, out.final_transmittance),
            (0.0, 0.0, 1.0)
        );
        let grad = OutputGradients {
            colour: [1.0, 2.0, 3.0],
            opacity: 1.0,
            depth: 1.0,
        };
        let g = composite_backward(&samples, [0.25, 0.5, 0.75], &grad);
        assert!(g.density.is_empty() && g.colour.is_empty());
        assert_eq!(g.background, [1.0, 2.0, 3.0]);
    }

    #[test]
    fn constant_density_slab_matches_closed_form() {
        // A slab of constant density σ and colour c from t0 to t0 + L, split
        // into N equal intervals. Quadrature is exact for piecewise-constant
        // media, so colour and opacity match the closed form to rounding:
        // opacity = 1 − e^{−σL}, colour = c (1 − e^{−σL}) + bg e^{−σL}.
        let (sigma, length, t0, n) = (1.7f64, 2.0f64, 1.0f64, 400usize);
        let delta = vec![length / n as f64; n];
        let t: Vec<f64> = (0..n)
            .map(|i| t0 + (i as f64 + 0.5) * length / n as f64)
            .collect();
        let density = vec![sigma; n];
        let colour = vec![[0.9, 0.4, 0.1]; n];
        let background = [1.0, 1.0, 1.0];
        let samples = RaySamples {
            density: &density,
            colour: &colour,
            delta: &delta,
            t: &t,
        };
        let out = composite(&samples, background);
        let absorbed = 1.0 - (-sigma * length).exp();
        assert!((out.opacity - absorbed).abs() < 1e-14);
        for c in 0..3 {
            let want = colour[0][c] * absorbed + background[c] * (1.0 - absorbed);
            assert!((out.colour[c] - want).abs() < 1e-14);
        }
        // Expected depth in closed form: ∫ t σ e^{−σ(t−t0)} dt over the slab
        // = t0·A + (1 − e^{−σL}(1 + σL))/σ with A = 1 − e^{−σL}. Midpoint
        // positions make the quadrature second-order accurate: the error is
        // O(δ²) ≈ (L/N)² = 2.5e-5 relative, so 1e-4 bounds it.
        let want_depth =
            t0 * absorbed + (1.0 - (-sigma * length).exp() * (1.0 + sigma * length)) / sigma;
        assert!(
            ((out.depth - want_depth) / want_depth).abs() < 1e-4,
            "{} vs {want_depth}",
            out.depth
        );
    }

    /// The double sum of [`distortion`] as written in the paper, O(n²).
    fn distortion_brute_force(weights: &[f64], s: &[f64], delta: &[f64]) -> f64 {
        let mut loss = 0.0;
        for i in 0..weights.len() {
            for j in 0..weights.len() {
                loss += weights[i] * weights[j] * (s[i] - s[j]).abs();
            }
            loss += weights[i] * weights[i] * delta[i] / 3.0;
        }
        loss
    }

    #[test]
    fn distortion_matches_the_double_sum_and_closed_forms() {
        for (seed, density_scale) in [(4, 0.5), (5, 20.0), (6, 150.0)] {
            let ray = Ray::random(seed, 40, density_scale);
            let mut w = vec![0.0; 40];
            weights(&ray.samples(), &mut w);
            let fast = distortion(&w, &ray.t, &ray.delta);
            let slow = distortion_brute_force(&w, &ray.t, &ray.delta);
            // The same terms summed in another order: f64 rounding of ~40²
            // terms of size ≤ 3, far below 1e-12.
            assert!((fast - slow).abs() < 1e-12, "{fast} against {slow}");
            assert!(fast > 0.0);
        }
        // One sample holding all the weight: only its own interval counts.
        assert!(
            (distortion(&[0.0, 0.8, 0.0], &[1.0, 2.0, 3.0], &[0.1, 0.3, 0.1]) - 0.064).abs()
                < 1e-15
        );
        // Two halves a distance 2 apart: 2 · ½ · ½ · 2 + ⅓ (¼ · 0.1 + ¼ · 0.2).
        let two_peaks = distortion(&[0.5, 0.5], &[1.0, 3.0], &[0.1, 0.2]);
        assert!((two_peaks - (1.0 + 0.025)).abs() < 1e-15);
    }

    #[test]
    fn distortion_gradient_matches_central_differences() {
        for (seed, density_scale) in [(7, 0.5), (8, 20.0)] {
            let ray = Ray::random(seed, 30, density_scale);
            let mut w = vec![0.0; 30];
            weights(&ray.samples(), &mut w);
            let mut analytic = vec![f64::NAN; 30];
            distortion_gradient(&w, &ray.t, &ray.delta, &mut analytic);
            // L is quadratic in w: central differences are exact up to
            // rounding, O(ε|L|/h) ≈ 1e-11 at h = 1e-5.
            for k in 0..w.len() {
                let h = 1e-5;
                let (mut plus, mut minus) = (w.clone(), w.clone());
                plus[k] += h;
                minus[k] -= h;
                let numeric = (distortion_brute_force(&plus, &ray.t, &ray.delta)
                    - distortion_brute_force(&minus, &ray.t, &ray.delta))
                    / (2.0 * h);
                assert!(
                    relative_error(analytic[k], numeric) < 1e-6,
                    "w[{k}]: analytic {}, numeric {numeric}",
                    analytic[k]
                );
            }
        }
    }
}
