//! Losses on a ray's compositing weights rather than its colour, and the
//! way their gradients reach the densities: what trains a proposal
//! sampler (Mip-NeRF 360, Barron et al. 2022, sections 2.1 and 3).
//!
//! A ray's samples are intervals [s_i, s_{i+1}] of the spacing coordinate
//! s (see `field::contraction`), each with the weight w_i = T_i·(1 − e^{−σ_i δ_i})
//! compositing gave it (δ_i its length in world units,
//! T_i = exp(−Σ_{j<i} σ_j δ_j)).
//!
//! **Interlevel loss** (eq. 13). A proposal level's weights ŵ over its own
//! intervals must bound the final level's: for each final interval, the
//! proposal weight of every proposal interval that overlaps it, summed,
//! bound(i) = Σ_{j overlaps i} ŵ_j, must be at least w_i. The loss is
//! Σ_i max(0, w_i − bound(i))² / (w_i + ε), with the final weights held
//! still (no gradient flows into the final level through it), so only the
//! proposal learns; its gradient on ŵ_j is −2·max(0, w_i − bound(i))/(w_i + ε)
//! summed over the final intervals i that j overlaps. ε is f32's machine
//! epsilon (multinerf's `lossfun_outer`).
//!
//! **Distortion loss** (eq. 15). Σ_{i,j} w_i w_j |m_i − m_j| + ⅓ Σ_i w_i² δs_i
//! with m_i the interval's midpoint and δs_i its length in s: it pulls each
//! ray's weight into as short a stretch as it can. With the midpoints in
//! order the double sum is 2 Σ_i w_i (m_i W_i − M_i), W_i = Σ_{j<i} w_j and
//! M_i = Σ_{j<i} w_j m_j, so loss and gradient take one pass each way.
//!
//! **From weights to densities.** ∂w_i/∂σ_k is −δ_k w_i for i > k,
//! δ_k T_{k+1} for i = k and 0 before: a gradient g on the weights gives
//! ∂L/∂σ_k = δ_k (T_{k+1} g_k − Σ_{i>k} g_i w_i).

use rayon::prelude::*;

/// ε of the interlevel loss's denominator (multinerf: f32's machine epsilon).
const INTERLEVEL_EPSILON: f32 = f32::EPSILON;

/// Per-ray intervals and weights of one level: `edges` R × (n + 1) sorted
/// in s per ray, `weights` R × n.
#[derive(Debug, Clone, Copy)]
pub struct Intervals<'a> {
    pub edges: &'a [f32],
    pub weights: &'a [f32],
}

impl Intervals<'_> {
    fn per_ray(&self, rays: usize) -> usize {
        self.weights.len() / rays.max(1)
    }
}

/// The interlevel loss of `proposal` against `fine` (held still), summed
/// over the `rays` rays; `scale` × its gradient with respect to the
/// proposal's weights is added to `d_proposal_weights`.
pub fn interlevel(
    fine: Intervals,
    proposal: Intervals,
    rays: usize,
    scale: f32,
    d_proposal_weights: &mut [f32],
) -> f64 {
    let n = fine.per_ray(rays);
    let m = proposal.per_ray(rays);
    assert_eq!(d_proposal_weights.len(), rays * m);
    if m == 0 {
        return 0.0;
    }
    d_proposal_weights
        .par_chunks_mut(m)
        .enumerate()
        .map_init(
            || (vec![0f32; m + 1], vec![0f32; m + 1]),
            |(cumulative, difference), (r, d)| {
                let fine_edges = &fine.edges[r * (n + 1)..][..n + 1];
                let fine_weights = &fine.weights[r * n..][..n];
                let edges = &proposal.edges[r * (m + 1)..][..m + 1];
                let weights = &proposal.weights[r * m..][..m];
                cumulative[0] = 0.0;
                for j in 0..m {
                    cumulative[j + 1] = cumulative[j] + weights[j].max(0.0);
                }
                difference.fill(0.0);
                let mut total = 0f64;
                for i in 0..n {
                    let (first, end) = overlapping(edges, fine_edges[i], fine_edges[i + 1]);
                    let bound = cumulative[end] - cumulative[first];
                    let w = fine_weights[i];
                    let excess = (w - bound).max(0.0);
                    if excess > 0.0 {
                        let denominator = w + INTERLEVEL_EPSILON;
                        total += (excess * excess / denominator) as f64;
                        let g = -2.0 * excess / denominator * scale;
                        difference[first] += g;
                        difference[end] -= g;
                    }
                }
                let mut running = 0.0;
                for (j, d) in d.iter_mut().enumerate() {
                    running += difference[j];
                    *d += running;
                }
                total
            },
        )
        .sum()
}

/// The proposal intervals [first, end) that overlap (lo, hi): those whose
/// span reaches past lo and starts before hi (multinerf's `inner_outer`
/// with the outer bound: the last edge at or below lo, the first at or
/// above hi).
fn overlapping(edges: &[f32], lo: f32, hi: f32) -> (usize, usize) {
    let m = edges.len() - 1;
    // Edges at or below lo: the interval starting at the last of them is
    // the first to overlap.
    let at_or_below = edges.partition_point(|&e| e <= lo);
    let first = at_or_below.saturating_sub(1).min(m);
    // The first edge at or above hi ends the last overlapping interval.
    let end = edges.partition_point(|&e| e < hi).min(m);
    (first, end.max(first))
}

/// The distortion loss of each ray's intervals, summed over `rays`;
/// `scale` × its gradient with respect to the weights is added to
/// `d_weights`.
pub fn distortion(intervals: Intervals, rays: usize, scale: f32, d_weights: &mut [f32]) -> f64 {
    let n = intervals.per_ray(rays);
    assert_eq!(d_weights.len(), rays * n);
    if n == 0 {
        return 0.0;
    }
    d_weights
        .par_chunks_mut(n)
        .enumerate()
        .map(|(r, d)| {
            let edges = &intervals.edges[r * (n + 1)..][..n + 1];
            let weights = &intervals.weights[r * n..][..n];
            let total_weight: f64 = weights.iter().map(|&w| w as f64).sum();
            let total_moment: f64 = weights
                .iter()
                .zip(edges.windows(2))
                .map(|(&w, e)| w as f64 * 0.5 * (e[0] + e[1]) as f64)
                .sum();
            let (mut before, mut moment_before) = (0f64, 0f64);
            let mut loss = 0f64;
            for i in 0..n {
                let w = weights[i] as f64;
                let mid = 0.5 * (edges[i] + edges[i + 1]) as f64;
                let width = (edges[i + 1] - edges[i]) as f64;
                loss += 2.0 * w * (mid * before - moment_before) + w * w * width / 3.0;
                let (after, moment_after) = (
                    total_weight - before - w,
                    total_moment - moment_before - w * mid,
                );
                // ∂/∂w_i: its pairs with the earlier intervals and with the
                // later ones, and its own interval's term.
                let gradient = 2.0 * (mid * before - moment_before)
                    + 2.0 * (moment_after - mid * after)
                    + 2.0 * w * width / 3.0;
                d[i] += (gradient * scale as f64) as f32;
                before += w;
                moment_before += w * mid;
            }
            loss
        })
        .sum()
}

/// Adds to `d_sigma` the gradient that `d_weights` (the loss's gradient on
/// each sample's compositing weight) gives the densities, for rays of
/// `per_ray` samples with densities `sigma`, world lengths `dt` and
/// weights `weights` (module doc).
pub fn weights_to_densities(
    sigma: &[f32],
    dt: &[f32],
    weights: &[f32],
    d_weights: &[f32],
    per_ray: usize,
    d_sigma: &mut [f32],
) {
    if per_ray == 0 {
        return;
    }
    d_sigma
        .par_chunks_mut(per_ray)
        .zip(sigma.par_chunks(per_ray))
        .zip(dt.par_chunks(per_ray))
        .zip(weights.par_chunks(per_ray))
        .zip(d_weights.par_chunks(per_ray))
        .for_each_init(
            || vec![0f64; per_ray],
            |suffix, ((((d_sigma, sigma), dt), weights), d_weights)| {
                // Σ_{i>k} g_i w_i, from the back.
                let mut later = 0f64;
                for k in (0..per_ray).rev() {
                    suffix[k] = later;
                    later += d_weights[k] as f64 * weights[k] as f64;
                }
                let mut optical_depth = 0f64;
                for k in 0..per_ray {
                    optical_depth += sigma[k].max(0.0) as f64 * dt[k] as f64;
                    let transmittance_after = (-optical_depth).exp();
                    d_sigma[k] += (dt[k] as f64
                        * (transmittance_after * d_weights[k] as f64 - suffix[k]))
                        as f32;
                }
            },
        );
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Weights of densities over intervals (as compositing computes them).
    fn weights_of(sigma: &[f64], dt: &[f64]) -> Vec<f64> {
        let mut transmittance = 1.0;
        sigma
            .iter()
            .zip(dt)
            .map(|(&s, &d)| {
                let alpha = 1.0 - (-s * d).exp();
                let w = transmittance * alpha;
                transmittance *= 1.0 - alpha;
                w
            })
            .collect()
    }

    #[test]
    fn a_proposal_that_bounds_the_final_weights_has_no_interlevel_loss() {
        // The final level's intervals lie inside the proposal's, and each
        // proposal interval holds at least the final weight inside it.
        let proposal_edges = [0.0, 0.25, 0.5, 0.75, 1.0];
        let proposal_weights = [0.1, 0.5, 0.3, 0.1];
        let fine_edges = [0.05, 0.2, 0.3, 0.45, 0.55, 0.9];
        let fine_weights = [0.05, 0.2, 0.3, 0.3, 0.1];
        let mut d = [0f32; 4];
        let loss = interlevel(
            Intervals {
                edges: &fine_edges,
                weights: &fine_weights,
            },
            Intervals {
                edges: &proposal_edges,
                weights: &proposal_weights,
            },
            1,
            1.0,
            &mut d,
        );
        assert_eq!(loss, 0.0);
        assert_eq!(d, [0.0; 4]);
        // A final weight above its bound: [0.3, 0.45] lies in the proposal's
        // second interval alone (0.5), so 0.8 exceeds it by 0.3.
        let fine_weights = [0.05, 0.2, 0.8, 0.3, 0.1];
        let loss = interlevel(
            Intervals {
                edges: &fine_edges,
                weights: &fine_weights,
            },
            Intervals {
                edges: &proposal_edges,
                weights: &proposal_weights,
            },
            1,
            1.0,
            &mut d,
        );
        let expected = 0.3f64 * 0.3 / (0.8 + f32::EPSILON as f64);
        assert!((loss - expected).abs() < 1e-6, "{loss} vs {expected}");
        // Only the interval that bounds it is pushed up.
        assert!(
            d[1] < 0.0 && d[0] == 0.0 && d[2] == 0.0 && d[3] == 0.0,
            "{d:?}"
        );
    }

    #[test]
    fn interlevel_gradient_matches_finite_differences() {
        let proposal_edges = [0.0f32, 0.1, 0.3, 0.35, 0.6, 0.8, 1.0];
        let proposal_weights = [0.05f32, 0.1, 0.3, 0.05, 0.2, 0.1];
        let fine_edges = [0.02f32, 0.12, 0.2, 0.33, 0.4, 0.5, 0.7, 0.95];
        let fine_weights = [0.1f32, 0.2, 0.25, 0.3, 0.15, 0.05, 0.3];
        let loss_at = |weights: &[f32]| {
            let mut unused = vec![0f32; weights.len()];
            interlevel(
                Intervals {
                    edges: &fine_edges,
                    weights: &fine_weights,
                },
                Intervals {
                    edges: &proposal_edges,
                    weights,
                },
                1,
                1.0,
                &mut unused,
            )
        };
        let mut d = vec![0f32; proposal_weights.len()];
        let base = interlevel(
            Intervals {
                edges: &fine_edges,
                weights: &fine_weights,
            },
            Intervals {
                edges: &proposal_edges,
                weights: &proposal_weights,
            },
            1,
            1.0,
            &mut d,
        );
        assert!(base > 0.0);
        // The loss is piecewise quadratic in ŵ; a step of 1e-3 stays on one
        // piece here (every excess is > 0.01 or 0 by a margin), so central
        // differences are exact up to f32 rounding (~1e-7 / 1e-3).
        let h = 1e-3;
        for j in 0..proposal_weights.len() {
            let (mut up, mut down) = (proposal_weights, proposal_weights);
            up[j] += h;
            down[j] -= h;
            let numeric = (loss_at(&up) - loss_at(&down)) / (2.0 * h as f64);
            assert!(
                (numeric - d[j] as f64).abs() < 2e-3 * (1.0 + numeric.abs()),
                "ŵ_{j}: {numeric} vs {}",
                d[j]
            );
        }
    }

    #[test]
    fn distortion_matches_its_double_sum_and_finite_differences() {
        let edges = [0.1f32, 0.2, 0.25, 0.5, 0.55, 0.9];
        let weights = [0.1f32, 0.4, 0.2, 0.25, 0.05];
        let direct = |weights: &[f32]| {
            let mids: Vec<f64> = edges
                .windows(2)
                .map(|e| 0.5 * (e[0] + e[1]) as f64)
                .collect();
            let mut total = 0.0;
            for i in 0..weights.len() {
                for j in 0..weights.len() {
                    total += weights[i] as f64 * weights[j] as f64 * (mids[i] - mids[j]).abs();
                }
                total += (weights[i] as f64).powi(2) * (edges[i + 1] - edges[i]) as f64 / 3.0;
            }
            total
        };
        let mut d = [0f32; 5];
        let loss = distortion(
            Intervals {
                edges: &edges,
                weights: &weights,
            },
            1,
            1.0,
            &mut d,
        );
        assert!((loss - direct(&weights)).abs() < 1e-9, "{loss}");
        // The loss is quadratic in w: central differences are exact up to
        // rounding.
        let h = 1e-3;
        for k in 0..weights.len() {
            let (mut up, mut down) = (weights, weights);
            up[k] += h;
            down[k] -= h;
            let numeric = (direct(&up) - direct(&down)) / (2.0 * h as f64);
            assert!(
                (numeric - d[k] as f64).abs() < 1e-4,
                "w_{k}: {numeric} vs {}",
                d[k]
            );
        }
    }

    #[test]
    fn density_gradient_of_weights_matches_finite_differences() {
        let sigma = [0.5f64, 2.0, 0.1, 4.0, 1.0];
        let dt = [0.1f64, 0.3, 0.2, 0.15, 0.4];
        let g = [0.3f64, -1.0, 0.5, 2.0, -0.7];
        let objective = |sigma: &[f64]| -> f64 {
            weights_of(sigma, &dt)
                .iter()
                .zip(&g)
                .map(|(w, g)| w * g)
                .sum()
        };
        let weights: Vec<f32> = weights_of(&sigma, &dt).iter().map(|&w| w as f32).collect();
        let mut d_sigma = [0f32; 5];
        weights_to_densities(
            &sigma.map(|s| s as f32),
            &dt.map(|d| d as f32),
            &weights,
            &g.map(|g| g as f32),
            5,
            &mut d_sigma,
        );
        // Smooth in σ: central differences of step 1e-5 in f64 are exact to
        // ~1e-9; the analytic side is f32 (~1e-7 relative).
        for k in 0..5 {
            let (mut up, mut down) = (sigma, sigma);
            up[k] += 1e-5;
            down[k] -= 1e-5;
            let numeric = (objective(&up) - objective(&down)) / 2e-5;
            assert!(
                (numeric - d_sigma[k] as f64).abs() < 1e-5 * (1.0 + numeric.abs()),
                "σ_{k}: {numeric} vs {}",
                d_sigma[k]
            );
        }
    }
}
