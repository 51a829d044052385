use super::*;
use crate::engine::cpu::composite::{
    OutputGradients, RaySamples, {self as reference},
};
use crate::field::common::MarchConfig;

/// A deterministic pseudo-random sequence in [0, 1).
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

/// An owned batch.
#[derive(Clone, Debug)]
struct Batch {
    density: Vec<f64>,
    rgb: Vec<f64>,
    dt: Vec<f64>,
    t: Vec<f64>,
    ray_offsets: Vec<u32>,
    background: Vec<f64>,
}

impl Batch {
    /// Rays with the given sample counts; each ray gets its own density
    /// scale from `scales`, so the batch mixes near-empty and saturating
    /// rays.
    fn random(seed: u64, counts: &[usize], scales: &[f64]) -> Self {
        let total: usize = counts.iter().sum();
        let r = sequence(seed, 6 * total + 3 * counts.len());
        let mut ray_offsets = vec![0u32];
        let (mut density, mut dt, mut t) = (Vec::new(), Vec::new(), Vec::new());
        let mut s = 0;
        for (ray, &n) in counts.iter().enumerate() {
            let mut far = 2.0;
            for _ in 0..n {
                let d = 0.01 + 0.05 * r[s];
                dt.push(d);
                t.push(far + 0.5 * d);
                far += d;
                density.push(scales[ray % scales.len()] * r[total + s]);
                s += 1;
            }
            ray_offsets.push(s as u32);
        }
        Self {
            density,
            rgb: r[2 * total..5 * total].to_vec(),
            dt,
            t,
            ray_offsets,
            background: r[6 * total..6 * total + 3 * counts.len()].to_vec(),
        }
    }

    fn view(&self) -> RayBatch<'_, f64> {
        RayBatch {
            density: &self.density,
            rgb: &self.rgb,
            dt: &self.dt,
            t: &self.t,
            ray_offsets: &self.ray_offsets,
            background: &self.background,
        }
    }

    fn rays(&self) -> usize {
        self.ray_offsets.len() - 1
    }

    fn forward(&self, min_transmittance: f64) -> Forward {
        let rays = self.rays();
        let mut out = Forward {
            rgb: vec![f64::NAN; 3 * rays],
            opacity: vec![f64::NAN; rays],
            depth: vec![f64::NAN; rays],
            used: vec![u32::MAX; rays],
        };
        composite_forward(
            &self.view(),
            min_transmittance,
            CompositeOutputs {
                rgb: &mut out.rgb,
                opacity: &mut out.opacity,
                depth: &mut out.depth,
                samples_used: &mut out.used,
            },
        );
        out
    }

    fn backward(&self, min_transmittance: f64, d_rgb: &[f64]) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
        self.backward_with(min_transmittance, d_rgb, None)
    }

    fn backward_with(
        &self,
        min_transmittance: f64,
        d_rgb: &[f64],
        distortion: Option<Distortion<f64>>,
    ) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
        let n = self.density.len();
        // NaN-filled, so a slot the backward forgets to write shows up.
        let mut d_density = vec![f64::NAN; n];
        let mut d_colour = vec![f64::NAN; 3 * n];
        let mut d_background = vec![f64::NAN; 3 * self.rays()];
        composite_backward(
            &self.view(),
            min_transmittance,
            d_rgb,
            distortion,
            CompositeGradients {
                density: &mut d_density,
                rgb: &mut d_colour,
                background: Some(&mut d_background),
            },
        );
        (d_density, d_colour, d_background)
    }
}

struct Forward {
    rgb: Vec<f64>,
    opacity: Vec<f64>,
    depth: Vec<f64>,
    used: Vec<u32>,
}

/// Varied sample counts, zeros included.
fn counts(n: usize, seed: u64) -> Vec<usize> {
    sequence(seed, n)
        .iter()
        .enumerate()
        .map(|(i, x)| if i % 17 == 0 { 0 } else { (x * 60.0) as usize })
        .collect()
}

const PAPER_CUT: f64 = MarchConfig::PAPER.min_transmittance as f64;

#[test]
fn samples_before_cut_matches_the_forward_pass() {
    let counts = counts(300, 21);
    let batch = Batch::random(3, &counts, &[0.5, 5.0, 40.0, 300.0, 1e4]);
    for min_transmittance in [0.0, PAPER_CUT] {
        let out = batch.forward(min_transmittance);
        let mut used = vec![u32::MAX; batch.rays()];
        samples_before_cut(
            &batch.density,
            &batch.dt,
            &batch.ray_offsets,
            min_transmittance,
            &mut used,
        );
        assert_eq!(used, out.used);
    }
}

#[test]
fn agrees_with_the_single_ray_reference() {
    // Enough samples (~9000) that the batch is split across threads.
    let counts = counts(300, 5);
    let batch = Batch::random(7, &counts, &[0.5, 5.0, 40.0, 300.0, 1e4]);
    let d_rgb: Vec<f64> = sequence(11, 3 * batch.rays())
        .iter()
        .map(|x| 2.0 * x - 1.0)
        .collect();
    for min_transmittance in [0.0, PAPER_CUT] {
        let out = batch.forward(min_transmittance);
        let (d_density, d_colour, d_background) = batch.backward(min_transmittance, &d_rgb);
        let mut truncated_rays = 0;
        for ray in 0..batch.rays() {
            let all = batch.ray_offsets[ray] as usize..batch.ray_offsets[ray + 1] as usize;
            let used = out.used[ray] as usize;
            assert!(used <= all.len());
            if min_transmittance == 0.0 {
                assert_eq!(used, all.len(), "no cut without a threshold");
            }
            truncated_rays += usize::from(used < all.len());
            // The reference on the samples the ray used.
            let kept = all.start..all.start + used;
            let colour: Vec<[f64; 3]> = kept
                .clone()
                .map(|s| [batch.rgb[3 * s], batch.rgb[3 * s + 1], batch.rgb[3 * s + 2]])
                .collect();
            let samples = RaySamples {
                density: &batch.density[kept.clone()],
                colour: &colour,
                delta: &batch.dt[kept.clone()],
                t: &batch.t[kept.clone()],
            };
            let background = [
                batch.background[3 * ray],
                batch.background[3 * ray + 1],
                batch.background[3 * ray + 2],
            ];
            let want = reference::composite(&samples, background);
            // Same operations in the same order: identical up to the
            // compiler's freedom, which Rust does not use (no FMA
            // contraction), so 1e-15 relative is already generous.
            let close = |a: f64, b: f64| (a - b).abs() <= 1e-15 * a.abs().max(b.abs()).max(1.0);
            for c in 0..3 {
                assert!(close(out.rgb[3 * ray + c], want.colour[c]), "ray {ray}");
            }
            assert!(close(out.opacity[ray], want.opacity) && close(out.depth[ray], want.depth));
            // The cut is where transmittance first drops below the
            // threshold.
            if used < all.len() {
                assert!(want.final_transmittance < min_transmittance);
                let mut before = vec![0.0; used];
                let t_before_last = if used > 0 {
                    reference::weights(
                        &RaySamples {
                            density: &samples.density[..used - 1],
                            colour: &colour[..used - 1],
                            delta: &samples.delta[..used - 1],
                            t: &samples.t[..used - 1],
                        },
                        &mut before,
                    )
                } else {
                    1.0
                };
                assert!(t_before_last >= min_transmittance);
            }
            let grad = OutputGradients {
                colour: [d_rgb[3 * ray], d_rgb[3 * ray + 1], d_rgb[3 * ray + 2]],
                opacity: 0.0,
                depth: 0.0,
            };
            let want_grad = reference::composite_backward(&samples, background, &grad);
            for (k, s) in kept.clone().enumerate() {
                assert!(
                    close(d_density[s], want_grad.density[k]),
                    "ray {ray} sample {k}"
                );
                for c in 0..3 {
                    assert!(close(d_colour[3 * s + c], want_grad.colour[k][c]));
                }
            }
            for s in kept.end..all.end {
                assert_eq!(d_density[s], 0.0);
                assert_eq!(&d_colour[3 * s..3 * s + 3], &[0.0; 3]);
            }
            for c in 0..3 {
                assert!(close(d_background[3 * ray + c], want_grad.background[c]));
            }
        }
        if min_transmittance > 0.0 {
            // The dense rays must exercise the cut, or this test says
            // nothing about it.
            assert!(truncated_rays > 50, "only {truncated_rays} rays were cut");
        }
    }
}

/// A scalar loss on the batch's colours, plus the distortion loss if
/// asked (from the reference on each ray's samples before the cut), for
/// finite differences.
fn loss(batch: &Batch, weights: &[f64], distortion: Option<Distortion<f64>>) -> f64 {
    let out = batch.forward(PAPER_CUT);
    let colour: f64 = out.rgb.iter().zip(weights).map(|(c, w)| c * w).sum();
    let Some(d) = distortion else {
        return colour;
    };
    let mut w = vec![0.0; batch.density.len()];
    sample_weights(&batch.view(), PAPER_CUT, &mut w);
    let scaled = |v: &[f64]| v.iter().map(|x| x * d.distance_scale).collect::<Vec<_>>();
    let (s, delta) = (scaled(&batch.t), scaled(&batch.dt));
    let spread: f64 = (0..batch.rays())
        .map(|r| {
            let samples = batch.ray_offsets[r] as usize..batch.ray_offsets[r + 1] as usize;
            reference::distortion(&w[samples.clone()], &s[samples.clone()], &delta[samples])
        })
        .sum();
    colour + d.weight_per_ray * spread
}

#[test]
fn gradients_match_central_differences_with_the_cut() {
    gradients_match_central_differences(None);
}

#[test]
fn gradients_with_the_distortion_loss_match_central_differences() {
    // λ′ large enough that the distortion term is as large as the
    // colour term's gradients (a weak λ′ would pass with a wrong
    // distortion gradient inside the tolerance).
    gradients_match_central_differences(Some(Distortion {
        weight_per_ray: 0.7,
        distance_scale: 0.4,
    }));
}

fn gradients_match_central_differences(distortion: Option<Distortion<f64>>) {
    let counts = [0usize, 1, 3, 12, 30, 30, 45, 8];
    // Scales from near-empty rays to rays cut after a few samples.
    let batch = Batch::random(3, &counts, &[0.5, 30.0, 150.0, 2000.0]);
    let weights: Vec<f64> = sequence(9, 3 * batch.rays())
        .iter()
        .map(|x| 2.0 * x - 1.0)
        .collect();
    let base = batch.forward(PAPER_CUT);
    let cut_rays = (0..batch.rays())
        .filter(|&r| (base.used[r] as usize) < counts[r])
        .count();
    assert!(
        cut_rays >= 3,
        "the test needs rays that are cut: {cut_rays}"
    );
    let (d_density, d_colour, d_background) = batch.backward_with(PAPER_CUT, &weights, distortion);

    // Central differences with h ≤ 1e-6: truncation O(h²|L'''|) and
    // rounding O(ε|L|/h) ≈ 1e-10 in f64, far below the 1e-6 relative
    // bound (absolute floor 1e-9 for gradients that cancel to ~0).
    // Each perturbation must leave every ray's cut where it was,
    // because the function being differentiated is the truncated one;
    // the margin to the threshold here is orders of magnitude larger
    // than the change in T a perturbation of 1e-6 causes.
    let check = |perturb: &dyn Fn(&mut Batch, f64), analytic: f64, h: f64, what: &str| {
        let mut plus = batch.clone();
        let mut minus = batch.clone();
        perturb(&mut plus, h);
        perturb(&mut minus, -h);
        assert_eq!(
            plus.forward(PAPER_CUT).used,
            base.used,
            "{what}: the cut moved"
        );
        assert_eq!(
            minus.forward(PAPER_CUT).used,
            base.used,
            "{what}: the cut moved"
        );
        let numeric =
            (loss(&plus, &weights, distortion) - loss(&minus, &weights, distortion)) / (2.0 * h);
        let error = (analytic - numeric).abs() / analytic.abs().max(numeric.abs()).max(1e-3);
        assert!(
            error < 1e-6,
            "{what}: analytic {analytic:e}, numeric {numeric:e}"
        );
    };
    for s in 0..batch.density.len() {
        let h = (0.5 * batch.density[s]).min(1e-6);
        check(
            &|b, h| b.density[s] += h,
            d_density[s],
            h,
            &format!("σ[{s}]"),
        );
        for c in 0..3 {
            check(
                &|b, h| b.rgb[3 * s + c] += h,
                d_colour[3 * s + c],
                1e-6,
                &format!("c[{s}][{c}]"),
            );
        }
    }
    for (i, &analytic) in d_background.iter().enumerate() {
        check(
            &|b, h| b.background[i] += h,
            analytic,
            1e-6,
            &format!("bg[{i}]"),
        );
    }
}

#[test]
fn the_distortion_loss_drains_fog_the_colour_loss_cannot_see() {
    // One ray: a faint fog over 40 samples, then a surface; fog,
    // surface and target all grey, so every split of the weight between
    // fog and surface renders the target and the colour loss has no
    // gradient to choose. Gradient descent on log-densities (as the
    // fields parametrise σ) with the distortion loss moves the weight
    // into the surface; without it the fog stays.
    let n = 60;
    let dt = vec![0.05; n];
    let t: Vec<f64> = (0..n).map(|i| 2.0 + 0.05 * (i as f64 + 0.5)).collect();
    let initial: Vec<f64> = (0..n)
        .map(|i| {
            if (40..44).contains(&i) {
                100f64.ln()
            } else {
                0.2f64.ln()
            }
        })
        .collect();
    let target = [0.5; 3];
    // The ray with densities exp(log_density), grey, over black.
    let grey_ray = |log_density: &[f64]| Batch {
        density: log_density.iter().map(|x| x.exp()).collect(),
        rgb: vec![0.5; 3 * n],
        dt: dt.clone(),
        t: t.clone(),
        ray_offsets: vec![0, n as u32],
        background: vec![0.0; 3],
    };
    let fog_weight = |log_density: &[f64], distortion: Option<Distortion<f64>>, steps: usize| {
        let mut log_density = log_density.to_vec();
        // Fog samples have ∂L/∂x = σ δ ∂L/∂τ ≈ 0.01 ∂L/∂τ: a step of
        // 100 moves them at a rate of order one per step.
        for _ in 0..steps {
            let batch = grey_ray(&log_density);
            let out = batch.forward(PAPER_CUT);
            let d_rgb: Vec<f64> = (0..3).map(|c| (out.rgb[c] - target[c]) / 3.0).collect();
            let (d_density, _, _) = batch.backward_with(PAPER_CUT, &d_rgb, distortion);
            for ((x, sigma), d) in log_density.iter_mut().zip(&batch.density).zip(d_density) {
                *x -= 100.0 * sigma * d;
            }
        }
        let batch = grey_ray(&log_density);
        let mut w = vec![0.0; n];
        sample_weights(&batch.view(), PAPER_CUT, &mut w);
        let colour = batch.forward(PAPER_CUT).rgb[0];
        (w[..40].iter().sum::<f64>(), colour)
    };
    let (fog_before, _) = fog_weight(&initial, None, 0);
    // 1 − e^{−40 · 0.2 · 0.05} = 1 − e^{−0.4}.
    assert!((fog_before - (1.0 - (-0.4f64).exp())).abs() < 1e-9);
    let (fog_plain, colour_plain) = fog_weight(&initial, None, 300);
    let (fog_drained, colour_drained) = fog_weight(
        &initial,
        Some(Distortion {
            weight_per_ray: 0.1,
            distance_scale: 1.0 / 3.0,
        }),
        300,
    );
    // Measured: 0.33 stays 0.33 without the loss, falls to 0.04 with it.
    assert!((fog_plain - fog_before).abs() < 1e-3, "{fog_plain}");
    assert!(fog_drained < 0.25 * fog_before, "{fog_drained}");
    for colour in [colour_plain, colour_drained] {
        assert!((colour - 0.5).abs() < 1e-3, "{colour}");
    }
}

#[test]
fn cut_follows_instant_ngp() {
    // One opaque first sample: T₀ = 1 is used, T₁ = e^{-100} is not.
    let batch = Batch {
        density: vec![100.0, 1.0, 1.0],
        rgb: vec![0.2, 0.4, 0.6, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0],
        dt: vec![1.0; 3],
        t: vec![0.5, 1.5, 2.5],
        ray_offsets: vec![0, 3],
        background: vec![1.0; 3],
    };
    let out = batch.forward(PAPER_CUT);
    assert_eq!(out.used, [1]);
    let (d_density, d_colour, _) = batch.backward(PAPER_CUT, &[1.0, 1.0, 1.0]);
    assert_eq!(&d_density[1..], &[0.0, 0.0]);
    assert_eq!(&d_colour[3..], &[0.0; 6]);
    // Transmittance exp(−Σ) drops below 1e-4 after Σ τ > ln 1e4 ≈ 9.21:
    // with τ = 1 per sample, sample 9 sees e^{-9} ≈ 1.2e-4 (used) and
    // sample 10 sees e^{-10} ≈ 4.5e-5 (cut).
    let n = 20;
    let batch = Batch {
        density: vec![1.0; n],
        rgb: vec![0.5; 3 * n],
        dt: vec![1.0; n],
        t: (0..n).map(|i| i as f64).collect(),
        ray_offsets: vec![0, n as u32],
        background: vec![0.0; 3],
    };
    let out = batch.forward(PAPER_CUT);
    assert_eq!(out.used, [10]);
    // The cut changes the colour by at most T_cut · (colour + bg).
    let full = batch.forward(0.0);
    assert!((out.rgb[0] - full.rgb[0]).abs() <= (-10f64).exp() * 0.5 + 1e-15);
    assert!((out.opacity[0] - (1.0 - (-10f64).exp())).abs() < 1e-15);
}

#[test]
fn empty_rays_and_huge_densities_stay_finite() {
    let batch = Batch {
        density: vec![1e30, 3.0, 0.0, -2.0, 1e-30],
        rgb: vec![0.5; 15],
        dt: vec![0.1; 5],
        t: vec![1.0, 2.0, 3.0, 4.0, 5.0],
        ray_offsets: vec![0, 0, 2, 2, 5, 5],
        background: vec![
            0.25, 0.5, 0.75, 1.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.3, 0.3, 0.3, 0.1, 0.2, 0.3,
        ],
    };
    let out = batch.forward(PAPER_CUT);
    // Rays without samples are their background, fully transparent.
    assert_eq!(&out.rgb[0..3], &[0.25, 0.5, 0.75]);
    assert_eq!(&out.rgb[12..15], &[0.1, 0.2, 0.3]);
    assert_eq!((out.opacity[0], out.depth[0], out.used[0]), (0.0, 0.0, 0));
    // An infinitely thick first sample takes everything.
    assert_eq!(out.used[1], 1);
    assert_eq!(&out.rgb[3..6], &[0.5; 3]);
    assert_eq!(out.opacity[1], 1.0);
    assert!(
        out.rgb
            .iter()
            .chain(&out.opacity)
            .chain(&out.depth)
            .all(|x| x.is_finite())
    );
    let d_rgb = vec![1.0; 15];
    let (d_density, d_colour, d_background) = batch.backward(PAPER_CUT, &d_rgb);
    assert!(
        d_density
            .iter()
            .chain(&d_colour)
            .chain(&d_background)
            .all(|x| x.is_finite())
    );
    assert_eq!(&d_background[0..3], &[1.0; 3]);
    // The negative density is clamped to empty space, without gradient.
    assert_eq!(d_density[3], 0.0);
}

#[test]
fn f32_matches_f64() {
    // The engines run f32; it must agree with the f64 path to f32
    // rounding. Per ray, the errors are those of ~60 sums of products
    // and exps, each ~1e-7 relative, so 1e-5 absolute on values in
    // [0, 1] (and relative to the size of the terms for gradients).
    let counts = counts(200, 21);
    let batch = Batch::random(23, &counts, &[1.0, 30.0, 300.0]);
    let d_rgb: Vec<f64> = sequence(29, 3 * batch.rays())
        .iter()
        .map(|x| 2.0 * x - 1.0)
        .collect();
    let want = batch.forward(PAPER_CUT);
    let (want_density, want_colour, _) = batch.backward(PAPER_CUT, &d_rgb);
    let to32 = |v: &[f64]| v.iter().map(|&x| x as f32).collect::<Vec<f32>>();
    let (density, rgb, dt, t, background) = (
        to32(&batch.density),
        to32(&batch.rgb),
        to32(&batch.dt),
        to32(&batch.t),
        to32(&batch.background),
    );
    let view = RayBatch {
        density: &density,
        rgb: &rgb,
        dt: &dt,
        t: &t,
        ray_offsets: &batch.ray_offsets,
        background: &background,
    };
    let rays = batch.rays();
    let (mut out_rgb, mut opacity, mut depth, mut used) = (
        vec![0f32; 3 * rays],
        vec![0f32; rays],
        vec![0f32; rays],
        vec![0u32; rays],
    );
    composite_forward(
        &view,
        MarchConfig::PAPER.min_transmittance,
        CompositeOutputs {
            rgb: &mut out_rgb,
            opacity: &mut opacity,
            depth: &mut depth,
            samples_used: &mut used,
        },
    );
    let n = density.len();
    let (mut d_density, mut d_colour) = (vec![0f32; n], vec![0f32; 3 * n]);
    composite_backward(
        &view,
        MarchConfig::PAPER.min_transmittance,
        &to32(&d_rgb),
        None,
        CompositeGradients {
            density: &mut d_density,
            rgb: &mut d_colour,
            background: None,
        },
    );
    // A cut can move by one sample only where T is within f32 rounding
    // (~1e-6 relative) of the threshold: rare.
    let moved = (0..rays).filter(|&r| used[r] != want.used[r]).count();
    assert!(moved <= rays / 100, "{moved} cuts moved");
    for ray in 0..rays {
        if used[ray] != want.used[ray] {
            continue;
        }
        for c in 0..3 {
            assert!((out_rgb[3 * ray + c] as f64 - want.rgb[3 * ray + c]).abs() < 1e-5);
        }
        assert!((opacity[ray] as f64 - want.opacity[ray]).abs() < 1e-5);
        let samples = batch.ray_offsets[ray] as usize..batch.ray_offsets[ray + 1] as usize;
        for s in samples {
            // ∂L/∂σ is δ (Tg − behind) with both terms ≤ 3 in size.
            assert!(
                (d_density[s] as f64 - want_density[s]).abs() < 1e-5 * (1.0 + batch.dt[s] * 3.0)
            );
            for c in 0..3 {
                assert!((d_colour[3 * s + c] as f64 - want_colour[3 * s + c]).abs() < 1e-5);
            }
        }
    }
}
