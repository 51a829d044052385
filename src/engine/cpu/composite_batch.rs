//! Volume rendering for a whole batch of rays at once, forward and backward,
//! with instant-ngp's early ray termination.
//!
//! The maths is that of [`super::composite`] (the single-ray reference),
//! restated in a loop that allocates nothing and runs rayon over blocks of
//! rays. The arithmetic is the reference's, operation for operation, so on
//! the samples a ray uses the two agree to the last bit (tested).
//!
//! # Early termination is part of the model
//!
//! As in instant-ngp (testbed: `composite_kernel_nerf`), a ray stops
//! accumulating at the first sample whose transmittance
//! Tᵢ = exp(−Σ_{j<i} τⱼ) is below `min_transmittance`
//! (`MarchConfig::PAPER.min_transmittance` = 1e-4). That sample and all
//! after it get zero weight and zero gradient, and the background is weighted by
//! the transmittance at the cut. The function computed here (and
//! differentiated, and checked against finite differences) is therefore
//! "composite the first `samples_used` samples", which differs from the
//! untruncated sum by at most T_cut · (|colour| + |background|) < 1e-4 per
//! channel for colours in [0, 1]. Pass `min_transmittance = 0` for the plain
//! quadrature.
//!
//! # Layout
//!
//! Samples are flattened: sample `s` has density `density[s]`, colour
//! `rgb[3s..3s+3]`, interval `dt[s]` and distance `t[s]`; ray `r` owns
//! samples `ray_offsets[r]..ray_offsets[r+1]` and has its background at
//! `background[3r..3r+3]`. Per-ray outputs are `rgb[3r..3r+3]`,
//! `opacity[r]`, `depth[r]`, `samples_used[r]`.

use std::ops::Range;

use num_traits::Float;

/// Rays are processed serially in blocks of at most this many samples
/// (or a single ray if it is longer): small enough that 2^18 samples give
/// rayon ~128 pieces to balance over the cores, large enough that the
/// splitting costs nothing next to the work.
const LEAF_SAMPLES: usize = 2048;

use crate::engine::shared::composite::{Distortion, RayBatch};

impl<F> RayBatch<'_, F> {
    /// Panics on inconsistent lengths or decreasing offsets: either would
    /// make the unchecked-looking slicing below index the wrong samples.
    fn validate(&self) {
        assert!(
            !self.ray_offsets.is_empty(),
            "ray_offsets needs R + 1 entries"
        );
        let rays = self.ray_count();
        let samples = self.sample_count();
        assert!(
            self.ray_offsets.windows(2).all(|w| w[0] <= w[1]),
            "ray_offsets must be non-decreasing"
        );
        assert!(
            self.density.len() >= samples,
            "density: {} < {samples} samples",
            self.density.len()
        );
        assert!(
            self.rgb.len() >= 3 * samples,
            "rgb: {} < 3 × {samples}",
            self.rgb.len()
        );
        assert!(
            self.dt.len() >= samples,
            "dt: {} < {samples} samples",
            self.dt.len()
        );
        assert!(
            self.t.len() >= samples,
            "t: {} < {samples} samples",
            self.t.len()
        );
        assert!(
            self.background.len() >= 3 * rays,
            "background: {} < 3 × {rays} rays",
            self.background.len()
        );
    }

    fn samples_of(&self, rays: &Range<usize>) -> Range<usize> {
        self.ray_offsets[rays.start] as usize..self.ray_offsets[rays.end] as usize
    }
}

/// Where the forward pass writes, per ray.
#[derive(Debug)]
pub struct CompositeOutputs<'a, F> {
    /// R × 3: Σ wᵢ cᵢ + T_cut · background.
    pub rgb: &'a mut [F],
    /// R: Σ wᵢ = 1 − T_cut.
    pub opacity: &'a mut [F],
    /// R: Σ wᵢ tᵢ (expected depth, not divided by opacity).
    pub depth: &'a mut [F],
    /// R: samples before the cut (the ray's whole count if T never fell
    /// below the threshold).
    pub samples_used: &'a mut [u32],
}

/// Where the backward pass writes.
#[derive(Debug)]
pub struct CompositeGradients<'a, F> {
    /// S: ∂L/∂σ per sample (zero after the cut).
    pub density: &'a mut [F],
    /// S × 3: ∂L/∂c per sample (zero after the cut).
    pub rgb: &'a mut [F],
    /// R × 3: ∂L/∂background, if wanted (training with random backgrounds
    /// does not need it).
    pub background: Option<&'a mut [F]>,
}

/// τ = σ δ with negative densities treated as empty space (as the
/// reference does).
#[inline(always)]
fn optical_depth<F: Float>(density: F, dt: F) -> F {
    (density * dt).max(F::zero())
}

/// Composites every ray of `batch` over its background.
pub fn composite_forward<F: Float + Send + Sync>(
    batch: &RayBatch<F>,
    min_transmittance: F,
    out: CompositeOutputs<F>,
) {
    batch.validate();
    let rays = batch.ray_count();
    assert!(out.rgb.len() >= 3 * rays && out.opacity.len() >= rays);
    assert!(out.depth.len() >= rays && out.samples_used.len() >= rays);
    forward_block(
        batch,
        min_transmittance,
        0..rays,
        &mut out.rgb[..3 * rays],
        &mut out.opacity[..rays],
        &mut out.depth[..rays],
        &mut out.samples_used[..rays],
    );
}

/// The samples each ray uses, written to `used` (R), from the densities and
/// intervals alone: the cut of [`composite_forward`], found with the same
/// arithmetic, so `composite_forward` on the batch gives the same counts.
/// Training uses it to evaluate colours and gradients only where they
/// matter: after the cut, a sample's colour is never read and every
/// gradient through it is zero.
pub fn samples_before_cut<F: Float + Send + Sync>(
    density: &[F],
    dt: &[F],
    ray_offsets: &[u32],
    min_transmittance: F,
    used: &mut [u32],
) {
    use rayon::prelude::*;
    let rays = ray_offsets.len().saturating_sub(1);
    assert!(used.len() >= rays, "used: {} < {rays} rays", used.len());
    let samples = ray_offsets.last().map_or(0, |&n| n as usize);
    assert!(density.len() >= samples && dt.len() >= samples);
    // 64 rays of ~50 samples per task, as the leaves of the forward pass.
    const RAYS_PER_TASK: usize = 64;
    used[..rays]
        .par_chunks_mut(RAYS_PER_TASK)
        .enumerate()
        .for_each(|(task, used)| {
            for (local, count) in used.iter_mut().enumerate() {
                let ray = task * RAYS_PER_TASK + local;
                let (start, end) = (ray_offsets[ray] as usize, ray_offsets[ray + 1] as usize);
                let mut accumulated = F::zero();
                let mut n = end - start;
                for s in start..end {
                    if (-accumulated).exp() < min_transmittance {
                        n = s - start;
                        break;
                    }
                    accumulated = accumulated + optical_depth(density[s], dt[s]);
                }
                *count = n as u32;
            }
        });
}

/// The weight wᵢ = Tᵢ (1 − e^(−τᵢ)) of every sample in [`composite_forward`]
/// (zero from each ray's cut on), with the same arithmetic: the
/// importance sampler draws from them.
pub fn sample_weights<F: Float + Send + Sync>(
    batch: &RayBatch<F>,
    min_transmittance: F,
    weights: &mut [F],
) {
    use rayon::prelude::*;
    batch.validate();
    let samples = batch.sample_count();
    assert!(
        weights.len() >= samples,
        "weights: {} < {samples}",
        weights.len()
    );
    let rays = batch.ray_count();
    // One task per block of rays; each writes its own rays' samples.
    const RAYS_PER_TASK: usize = 64;
    let blocks: Vec<(usize, usize)> = (0..rays)
        .step_by(RAYS_PER_TASK)
        .map(|r| (r, (r + RAYS_PER_TASK).min(rays)))
        .collect();
    let base = batch.ray_offsets[0] as usize;
    let mut pieces: Vec<&mut [F]> = Vec::with_capacity(blocks.len());
    let mut rest = &mut weights[base..samples];
    for &(start, end) in &blocks {
        let len = (batch.ray_offsets[end] - batch.ray_offsets[start]) as usize;
        let (piece, tail) = rest.split_at_mut(len);
        pieces.push(piece);
        rest = tail;
    }
    pieces
        .into_par_iter()
        .zip(blocks)
        .for_each(|(piece, (start, end))| {
            let first = batch.ray_offsets[start] as usize;
            for ray in start..end {
                let samples = batch.samples_of(&(ray..ray + 1));
                let mut accumulated = F::zero();
                let mut cut = false;
                for s in samples {
                    let transmittance = (-accumulated).exp();
                    cut = cut || transmittance < min_transmittance;
                    let w = &mut piece[s - first];
                    if cut {
                        *w = F::zero();
                        continue;
                    }
                    let tau = optical_depth(batch.density[s], batch.dt[s]);
                    *w = transmittance * -(-tau).exp_m1();
                    accumulated = accumulated + tau;
                }
            }
        });
}

/// Splits the rays in two until a block is small, then composites it. The
/// output slices cover exactly `rays`.
fn forward_block<F: Float + Send + Sync>(
    batch: &RayBatch<F>,
    min_transmittance: F,
    rays: Range<usize>,
    rgb: &mut [F],
    opacity: &mut [F],
    depth: &mut [F],
    used: &mut [u32],
) {
    if rays.len() > 1 && batch.samples_of(&rays).len() > LEAF_SAMPLES {
        let mid = rays.start + rays.len() / 2;
        let k = mid - rays.start;
        let (rgb_a, rgb_b) = rgb.split_at_mut(3 * k);
        let (opacity_a, opacity_b) = opacity.split_at_mut(k);
        let (depth_a, depth_b) = depth.split_at_mut(k);
        let (used_a, used_b) = used.split_at_mut(k);
        rayon::join(
            || {
                forward_block(
                    batch,
                    min_transmittance,
                    rays.start..mid,
                    rgb_a,
                    opacity_a,
                    depth_a,
                    used_a,
                )
            },
            || {
                forward_block(
                    batch,
                    min_transmittance,
                    mid..rays.end,
                    rgb_b,
                    opacity_b,
                    depth_b,
                    used_b,
                )
            },
        );
        return;
    }
    for (local, ray) in rays.enumerate() {
        let samples = batch.samples_of(&(ray..ray + 1));
        let start = samples.start;
        let mut colour = [F::zero(); 3];
        let mut ray_depth = F::zero();
        let mut accumulated = F::zero();
        let mut count = samples.len();
        for s in samples {
            let transmittance = (-accumulated).exp();
            if transmittance < min_transmittance {
                count = s - start;
                break;
            }
            let tau = optical_depth(batch.density[s], batch.dt[s]);
            let weight = transmittance * -(-tau).exp_m1();
            for (c, sample_c) in colour.iter_mut().zip(&batch.rgb[3 * s..3 * s + 3]) {
                *c = *c + weight * *sample_c;
            }
            ray_depth = ray_depth + weight * batch.t[s];
            accumulated = accumulated + tau;
        }
        let final_transmittance = (-accumulated).exp();
        for c in 0..3 {
            rgb[3 * local + c] = colour[c] + final_transmittance * batch.background[3 * ray + c];
        }
        opacity[local] = F::one() - final_transmittance;
        depth[local] = ray_depth;
        used[local] = count as u32;
    }
}

/// The backward pass of [`composite_forward`] for a loss on the colours:
/// given ∂L/∂rgb per ray (R × 3), writes ∂L/∂σ and ∂L/∂c per sample and,
/// if asked, ∂L/∂background per ray.
///
/// The forward walk is redone here (it is two transcendental functions per
/// sample, cheaper than storing and reading back per-sample state), with
/// the same arithmetic, so it finds the same cut as the forward pass did.
/// As in the reference, with gₖ = ∂L/∂rgb · cₖ:
///
/// ```text
/// ∂L/∂τₖ = Tₖ₊₁ gₖ − (Σ_{k<i<cut} wᵢ gᵢ + T_cut ∂L/∂rgb · background)
/// ```
///
/// with the bracket summed from the back of the ray. Tₖ for the ray is
/// kept in `gradients.density` between the two walks, so nothing is
/// allocated.
///
/// With `distortion`, gₖ gains ∂L_dist/∂wₖ (the formula above holds for any
/// loss on the weights): λ′ (2 (sₖ W_<k − S_<k + S_>k − sₖ W_>k) + ⅔ wₖ δₖ),
/// where W_<k = 1 − Tₖ and W_>k = Tₖ₊₁ − T_cut come from the
/// transmittances already at hand and S (the sums of wⱼ sⱼ) from one more
/// running sum in the forward walk.
pub fn composite_backward<F: Float + Send + Sync>(
    batch: &RayBatch<F>,
    min_transmittance: F,
    d_rgb: &[F],
    distortion: Option<Distortion<F>>,
    gradients: CompositeGradients<F>,
) {
    batch.validate();
    let rays = batch.ray_count();
    let samples = batch.sample_count();
    assert!(
        d_rgb.len() >= 3 * rays,
        "d_rgb: {} < 3 × {rays} rays",
        d_rgb.len()
    );
    assert!(gradients.density.len() >= samples && gradients.rgb.len() >= 3 * samples);
    let first = batch.ray_offsets[0] as usize;
    let background = gradients.background.map(|b| {
        assert!(b.len() >= 3 * rays);
        &mut b[..3 * rays]
    });
    backward_block(
        batch,
        min_transmittance,
        d_rgb,
        distortion,
        0..rays,
        CompositeGradients {
            density: &mut gradients.density[first..samples],
            rgb: &mut gradients.rgb[3 * first..3 * samples],
            background,
        },
    );
}

/// As [`forward_block`]: the gradients' density and colour cover exactly
/// the samples of `rays`, their background exactly the rays.
fn backward_block<F: Float + Send + Sync>(
    batch: &RayBatch<F>,
    min_transmittance: F,
    d_rgb: &[F],
    distortion: Option<Distortion<F>>,
    rays: Range<usize>,
    gradients: CompositeGradients<F>,
) {
    let CompositeGradients {
        density: d_density,
        rgb: d_colour,
        background: d_background,
    } = gradients;
    let block = batch.samples_of(&rays);
    if rays.len() > 1 && block.len() > LEAF_SAMPLES {
        let mid = rays.start + rays.len() / 2;
        let k = batch.ray_offsets[mid] as usize - block.start;
        let (density_a, density_b) = d_density.split_at_mut(k);
        let (colour_a, colour_b) = d_colour.split_at_mut(3 * k);
        let (background_a, background_b) = match d_background {
            Some(b) => {
                let (a, b) = b.split_at_mut(3 * (mid - rays.start));
                (Some(a), Some(b))
            }
            None => (None, None),
        };
        rayon::join(
            || {
                backward_block(
                    batch,
                    min_transmittance,
                    d_rgb,
                    distortion,
                    rays.start..mid,
                    CompositeGradients {
                        density: density_a,
                        rgb: colour_a,
                        background: background_a,
                    },
                )
            },
            || {
                backward_block(
                    batch,
                    min_transmittance,
                    d_rgb,
                    distortion,
                    mid..rays.end,
                    CompositeGradients {
                        density: density_b,
                        rgb: colour_b,
                        background: background_b,
                    },
                )
            },
        );
        return;
    }
    let mut d_background = d_background;
    for (local_ray, ray) in rays.enumerate() {
        let samples = batch.samples_of(&(ray..ray + 1));
        let local = samples.start - block.start..samples.end - block.start;
        let grad = [d_rgb[3 * ray], d_rgb[3 * ray + 1], d_rgb[3 * ray + 2]];
        let transmittance_before = &mut d_density[local.clone()];

        // Forward: Tₖ into the density gradient's slots, the cut, and for
        // the distortion loss Σ wₖ sₖ.
        let mut accumulated = F::zero();
        let mut used = samples.len();
        let mut moment_total = F::zero();
        for (k, s) in samples.clone().enumerate() {
            let transmittance = (-accumulated).exp();
            if transmittance < min_transmittance {
                used = k;
                break;
            }
            transmittance_before[k] = transmittance;
            let tau = optical_depth(batch.density[s], batch.dt[s]);
            if let Some(d) = distortion {
                let weight = transmittance * -(-tau).exp_m1();
                moment_total = moment_total + weight * (batch.t[s] * d.distance_scale);
            }
            accumulated = accumulated + tau;
        }
        let final_transmittance = (-accumulated).exp();
        transmittance_before[used..].fill(F::zero());
        d_colour[3 * (local.start + used)..3 * local.end].fill(F::zero());

        // Backward. Tₖ₊₁ is the Tₖ read one step earlier (the same float
        // the reference gets as exp of the same running sum), T_cut for the
        // last sample used.
        let background = &batch.background[3 * ray..3 * ray + 3];
        let mut behind = final_transmittance
            * (grad[0] * background[0] + grad[1] * background[1] + grad[2] * background[2]);
        let mut transmittance_after = final_transmittance;
        let mut moment_after = F::zero();
        for k in (0..used).rev() {
            let s = samples.start + k;
            let transmittance = transmittance_before[k];
            let tau = optical_depth(batch.density[s], batch.dt[s]);
            let weight = transmittance * -(-tau).exp_m1();
            let c = &batch.rgb[3 * s..3 * s + 3];
            let mut g = grad[0] * c[0] + grad[1] * c[1] + grad[2] * c[2];
            if let Some(d) = distortion {
                let distance = batch.t[s] * d.distance_scale;
                let weight_before = F::one() - transmittance;
                let weight_after = transmittance_after - final_transmittance;
                let moment_before = moment_total - moment_after - weight * distance;
                let spread = distance * weight_before - moment_before + moment_after
                    - distance * weight_after;
                let two = F::one() + F::one();
                let own = two / (two + F::one()) * weight * (batch.dt[s] * d.distance_scale);
                g = g + d.weight_per_ray * (two * spread + own);
                moment_after = moment_after + weight * distance;
            }
            let d_tau = transmittance_after * g - behind;
            // Negative densities were clamped to empty space: no gradient.
            transmittance_before[k] = if batch.density[s] * batch.dt[s] >= F::zero() {
                batch.dt[s] * d_tau
            } else {
                F::zero()
            };
            let out = &mut d_colour[3 * (local.start + k)..3 * (local.start + k) + 3];
            for (o, gc) in out.iter_mut().zip(grad) {
                *o = weight * gc;
            }
            behind = behind + weight * g;
            transmittance_after = transmittance;
        }
        if let Some(d_background) = d_background.as_deref_mut() {
            for c in 0..3 {
                d_background[3 * local_ray + c] = final_transmittance * grad[c];
            }
        }
    }
}

#[cfg(test)]
mod tests;
