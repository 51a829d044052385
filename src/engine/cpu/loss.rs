//! Photometric losses on rendered colours: Huber (instant-ngp's default for
//! NeRF) and L2, value and gradient.
//!
//! Per channel, with d = predicted − target (instant-ngp,
//! `common_device.cuh`: `huber_loss` with α = 0.1, `l2_loss`):
//!
//! ```text
//! Huber:  ½ d² / δ        if |d| ≤ δ      gradient  d / δ
//!         |d| − ½ δ       otherwise                 sign(d)
//! L2:     d²                                        2 d
//! ```
//!
//! This Huber is the usual one divided by δ, so outside the quadratic zone
//! it is an L1 loss with unit slope; both pieces meet with value δ/2 and
//! slope ±1 at |d| = δ, so the loss is C¹. The batch loss is the mean over
//! rays × channels, and the gradient is that of the mean.

use num_traits::Float;
use rayon::prelude::*;

use crate::field::common::{HUBER_DELTA, LossKind};

/// Elements per rayon task: fixed, so the partial sums (and so the loss
/// value) do not depend on how work was stolen.
const CHUNK: usize = 3 * 4096;

/// Loss and derivative for one channel's difference d = predicted − target,
/// before averaging.
#[inline(always)]
pub fn loss_element<F: Float>(kind: LossKind, difference: F) -> (F, F) {
    match kind {
        LossKind::Huber => {
            let delta = F::from(HUBER_DELTA).unwrap();
            let half = F::from(0.5).unwrap();
            if difference.abs() <= delta {
                (half * difference * difference / delta, difference / delta)
            } else {
                (difference.abs() - half * delta, difference.signum())
            }
        }
        LossKind::L2 => (difference * difference, difference + difference),
    }
}

/// The mean loss over rays × channels of `predicted` against `target`
/// (both R × 3), and its gradient with respect to `predicted` written into
/// `gradient` (R × 3). The value is summed in f64. An empty batch has loss
/// 0.
pub fn loss_and_gradient<F: Float + Send + Sync>(
    kind: LossKind,
    predicted: &[F],
    target: &[F],
    gradient: &mut [F],
) -> f64 {
    let n = predicted.len();
    assert!(
        target.len() == n && gradient.len() == n,
        "predicted, target and gradient differ in length"
    );
    assert!(n.is_multiple_of(3), "colours are R × 3");
    if n == 0 {
        return 0.0;
    }
    let scale = F::one() / F::from(n).unwrap();
    let partial: Vec<f64> = gradient
        .par_chunks_mut(CHUNK)
        .zip(predicted.par_chunks(CHUNK).zip(target.par_chunks(CHUNK)))
        .map(|(gradient, (predicted, target))| {
            let mut sum = 0f64;
            for ((g, &p), &t) in gradient.iter_mut().zip(predicted).zip(target) {
                let (value, derivative) = loss_element(kind, p - t);
                sum += value.to_f64().unwrap();
                *g = derivative * scale;
            }
            sum
        })
        .collect();
    partial.iter().sum::<f64>() / n as f64
}

/// The mean loss alone (evaluation, logging).
pub fn loss_value<F: Float>(kind: LossKind, predicted: &[F], target: &[F]) -> f64 {
    assert_eq!(predicted.len(), target.len());
    if predicted.is_empty() {
        return 0.0;
    }
    let sum: f64 = predicted
        .iter()
        .zip(target)
        .map(|(&p, &t)| loss_element(kind, p - t).0.to_f64().unwrap())
        .sum();
    sum / predicted.len() as f64
}

#[cfg(test)]
mod tests {
    use super::*;

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

    const DELTA: f64 = HUBER_DELTA as f64;

    #[test]
    fn gradients_match_central_differences() {
        // Differences spread over both Huber zones: targets in [0, 1],
        // predictions within ±0.4 of them.
        let rays = 50;
        let r = sequence(1, 6 * rays);
        let target: Vec<f64> = r[..3 * rays].to_vec();
        let predicted: Vec<f64> = (0..3 * rays)
            .map(|i| target[i] + 0.8 * (r[3 * rays + i] - 0.5))
            .collect();
        for kind in [LossKind::Huber, LossKind::L2] {
            let mut gradient = vec![f64::NAN; 3 * rays];
            let value = loss_and_gradient(kind, &predicted, &target, &mut gradient);
            assert!((value - loss_value(kind, &predicted, &target)).abs() < 1e-15);
            let mut quadratic = 0;
            for i in 0..3 * rays {
                let d = predicted[i] - target[i];
                // Central differences with h = 1e-7 away from the kink at
                // |d| = δ (only C¹ there): error O(h²) ≈ 1e-14 plus
                // rounding ε|L|/h ≈ 1e-10 against gradients ~1/(3R) ≈ 7e-3,
                // so 1e-6 relative holds with room.
                if (d.abs() - DELTA).abs() < 1e-5 {
                    continue;
                }
                quadratic += usize::from(d.abs() < DELTA);
                let h = 1e-7;
                let mut plus = predicted.clone();
                let mut minus = predicted.clone();
                plus[i] += h;
                minus[i] -= h;
                let numeric = (loss_value(kind, &plus, &target)
                    - loss_value(kind, &minus, &target))
                    / (2.0 * h);
                let error = (gradient[i] - numeric).abs() / gradient[i].abs().max(1e-6);
                assert!(
                    error < 1e-6,
                    "{kind:?} element {i}: {} vs {numeric}",
                    gradient[i]
                );
            }
            assert!(
                quadratic > 10 && quadratic < 3 * rays - 10,
                "both zones covered: {quadratic}"
            );
        }
    }

    #[test]
    fn values_in_closed_form() {
        // One ray: d = (0.05, −0.3, 0).
        let predicted = [0.55f64, 0.2, 0.7];
        let target = [0.5f64, 0.5, 0.7];
        let mut g = [0.0; 3];
        let huber = loss_and_gradient(LossKind::Huber, &predicted, &target, &mut g);
        let d0 = 0.55f64 - 0.5;
        let want = (0.5 * d0 * d0 / DELTA + (0.3 - 0.5 * DELTA)) / 3.0;
        assert!((huber - want).abs() < 1e-15, "{huber} vs {want}");
        assert!((g[0] - d0 / DELTA / 3.0).abs() < 1e-15 && g[1] == -1.0 / 3.0 && g[2] == 0.0);
        let l2 = loss_and_gradient(LossKind::L2, &predicted, &target, &mut g);
        let d1 = 0.2f64 - 0.5;
        assert!((l2 - (d0 * d0 + d1 * d1) / 3.0).abs() < 1e-15);
        assert!((g[1] - 2.0 * d1 / 3.0).abs() < 1e-15);
    }

    #[test]
    fn huber_is_continuous_with_continuous_slope_at_delta() {
        // At |d| = δ the pieces give δ/2 and slope ±1; just either side of
        // δ they must agree to first order: |L(δ+h) − L(δ−h)| ≈ 2h, the
        // slope jump is O(h/δ).
        for sign in [1.0f64, -1.0] {
            let h = 1e-9;
            let (below, slope_below) = loss_element(LossKind::Huber, sign * (DELTA - h));
            let (at, slope_at) = loss_element(LossKind::Huber, sign * DELTA);
            let (above, slope_above) = loss_element(LossKind::Huber, sign * (DELTA + h));
            assert!((at - 0.5 * DELTA).abs() < 1e-17);
            assert!((slope_at - sign).abs() < 1e-15);
            assert!(
                ((above - below) - 2.0 * h).abs() < 1e-15,
                "{}",
                above - below
            );
            assert!((slope_above - slope_below).abs() < 2.0 * h / DELTA + 1e-15);
        }
        // And in f32, the engines' type: values ≈ 0.05 carry rounding of a
        // few ulp (ulp(0.05) ≈ 3.7e-9) against the 2e-7 step in between.
        let (below, _) = loss_element(LossKind::Huber, HUBER_DELTA * (1.0 - 1e-6));
        let (above, _) = loss_element(LossKind::Huber, HUBER_DELTA * (1.0 + 1e-6));
        assert!(
            ((above - below) - 2e-6 * HUBER_DELTA).abs() < 2e-8,
            "{}",
            above - below
        );
    }

    #[test]
    fn large_batches_match_the_serial_sum_in_f32() {
        // Many chunks: the chunked f64 sum equals the serial one to f64
        // rounding, and the gradient is independent of the chunking.
        let n = 3 * 20_000;
        let r = sequence(5, 2 * n);
        let predicted: Vec<f32> = r[..n].iter().map(|&x| x as f32).collect();
        let target: Vec<f32> = r[n..].iter().map(|&x| x as f32).collect();
        let mut gradient = vec![0f32; n];
        for kind in [LossKind::Huber, LossKind::L2] {
            let value = loss_and_gradient(kind, &predicted, &target, &mut gradient);
            let serial = loss_value(kind, &predicted, &target);
            assert!(
                (value - serial).abs() <= 1e-12 * serial,
                "{value} vs {serial}"
            );
            for i in (0..n).step_by(997) {
                let (_, d) = loss_element(kind, predicted[i] - target[i]);
                assert_eq!(gradient[i], d * (1.0 / n as f32));
            }
        }
        assert_eq!(
            loss_and_gradient::<f32>(LossKind::Huber, &[], &[], &mut []),
            0.0
        );
    }
}
