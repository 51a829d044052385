//! The fixed-count levels' samplers on the gpu engine, behind one seam:
//! the twin of the cpu engine's `engine/cpu/model/samplers.rs`.
//!
//! A recipe names each level's sampler ([`SamplerKind`], engine-neutral
//! data); [`level_sampler`] is the one place that turns a name into the
//! kernels that draw, and the driver only asks a sampler how many samples
//! per ray it makes, what scratch it needs, and to record itself. Each
//! sampler writes a level's distances along the rays on the device:
//! points' `t` (NeRF) or frustums' edges (Mip-NeRF), from the rays' bounds
//! or from the level before.

use super::LevelBuffers;
use crate::engine::gpu::kernel::Recorder;
use crate::engine::gpu::proposal::GpuProposal;
use crate::engine::gpu::sampling::{GpuSampling, Pdf, RayBounds, SortedRows, WeightedSamples};
use crate::field::common::{SampleShape, SamplerKind};
use crate::field::contraction::Contraction;

/// What a level's sampler reads and writes on the device, for a chunk of
/// `rays` rays.
pub(super) struct LevelSampling<'a> {
    pub(super) rays: usize,
    pub(super) bounds: RayBounds<'a>,
    /// The level before, with its weights (none for a first level).
    pub(super) previous: Option<&'a LevelBuffers>,
    /// Scratch: importance sampling's bin edges, bin weights (or
    /// resampling's blurred weights), and new samples.
    pub(super) edges: &'a wgpu::Buffer,
    pub(super) bin_weights: &'a wgpu::Buffer,
    pub(super) fine_t: &'a wgpu::Buffer,
    /// The level's own buffers: `t` for points, `edges` for frustums and
    /// intervals.
    pub(super) out: &'a LevelBuffers,
    /// The spacing coordinate's kernels (the proposal levels').
    pub(super) proposal: &'a GpuProposal,
}

/// Per-ray floats of the shared sampling scratch a level needs.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub(super) struct ScratchPerRay {
    pub(super) edges: usize,
    pub(super) bins: usize,
    pub(super) fine: usize,
}

/// Draws a fixed-count level's sample distances on the device.
pub(super) trait LevelSampler: Send + Sync {
    /// Samples per ray the level evaluates after a level of `previous`
    /// (none: it is the first), or why it cannot follow it.
    fn samples_per_ray(&self, previous: Option<usize>) -> Result<usize, String>;

    /// The scratch the level needs after a level of `previous` samples per
    /// ray.
    fn scratch_per_ray(&self, _previous: usize) -> ScratchPerRay {
        ScratchPerRay::default()
    }

    /// Whether it draws intervals (each ray's samples + 1 edges into
    /// `edges`) rather than points into `t` (as the cpu twin's).
    fn draws_intervals(&self) -> bool;

    /// Records the draw. `jitter` seeds the random offsets (`None`: the
    /// deterministic positions).
    fn record(
        &self,
        rec: &mut Recorder,
        sampling: &GpuSampling,
        level: LevelSampling,
        jitter: Option<u32>,
    );
}

/// The sampler that draws a level named `kind` of a recipe whose samples
/// are `shape`, or why there is none.
pub(super) fn level_sampler(
    kind: SamplerKind,
    shape: SampleShape,
    contraction: Option<Contraction>,
) -> Result<Box<dyn LevelSampler>, String> {
    let frustums = shape == SampleShape::ConicalFrustums;
    let spacing = || {
        contraction.ok_or_else(|| {
            "the proposal sampler's levels space their samples by the scene's contraction, \
             which the recipe does not have"
                .to_string()
        })
    };
    Ok(match kind {
        SamplerKind::Stratified { count } => Box::new(Stratified { count, frustums }),
        SamplerKind::Importance { .. } if frustums => {
            return Err("it adds importance points to frustums: frustum levels resample".into());
        }
        SamplerKind::Importance { count, padding } => Box::new(Importance { count, padding }),
        SamplerKind::Resample { .. } if !frustums => {
            return Err("it resamples frustums, but the recipe's samples are points".into());
        }
        SamplerKind::Resample { count, padding } => Box::new(Resample { count, padding }),
        SamplerKind::Occupancy => {
            return Err(
                "it marches through the occupancy grid, which only a first and only level can"
                    .into(),
            );
        }
        SamplerKind::SpacedIntervals { count } => Box::new(SpacedIntervals {
            count,
            contraction: spacing()?,
        }),
        SamplerKind::ProposalResample { count, padding } => Box::new(ProposalResample {
            count,
            padding,
            contraction: spacing()?,
        }),
    })
}

/// `count` stratified points, or `count` frustums between `count` + 1
/// stratified edges, from near to far.
struct Stratified {
    count: usize,
    frustums: bool,
}

impl LevelSampler for Stratified {
    fn samples_per_ray(&self, _previous: Option<usize>) -> Result<usize, String> {
        Ok(self.count)
    }

    fn draws_intervals(&self) -> bool {
        self.frustums
    }

    fn record(
        &self,
        rec: &mut Recorder,
        sampling: &GpuSampling,
        level: LevelSampling,
        jitter: Option<u32>,
    ) {
        sampling.record_stratified(
            rec,
            level.bounds,
            level.rays,
            self.count + self.frustums as usize,
            jitter,
            if self.frustums {
                &level.out.edges
            } else {
                &level.out.t
            },
        );
    }
}

/// NeRF's fine level: `count` points drawn from the previous level's
/// weights (padded by `padding`), merged with that level's points.
struct Importance {
    count: usize,
    padding: f32,
}

impl LevelSampler for Importance {
    fn samples_per_ray(&self, previous: Option<usize>) -> Result<usize, String> {
        match previous {
            Some(previous) if previous >= 3 => Ok(previous + self.count),
            Some(_) => Err(
                "it samples the previous level's weights, which needs three samples per ray".into(),
            ),
            None => Err("the first level cannot be an importance level".into()),
        }
    }

    fn draws_intervals(&self) -> bool {
        false
    }

    fn scratch_per_ray(&self, previous: usize) -> ScratchPerRay {
        ScratchPerRay {
            edges: previous - 1,
            bins: previous - 2,
            fine: self.count,
        }
    }

    fn record(
        &self,
        rec: &mut Recorder,
        sampling: &GpuSampling,
        level: LevelSampling,
        jitter: Option<u32>,
    ) {
        let previous = level.previous.expect("checked by samples_per_ray");
        let m = previous.per_ray;
        sampling.record_importance_bins(
            rec,
            WeightedSamples {
                t: &previous.t,
                weights: &previous.weights,
            },
            level.rays,
            m,
            level.edges,
            level.bin_weights,
        );
        sampling.record_sample_pdf(
            rec,
            Pdf {
                edges: level.edges,
                weights: level.bin_weights,
                bins: m - 2,
                padding: self.padding,
            },
            level.rays,
            self.count,
            jitter,
            level.fine_t,
        );
        sampling.record_merge_sorted(
            rec,
            SortedRows {
                values: &previous.t,
                per_ray: m,
            },
            SortedRows {
                values: level.fine_t,
                per_ray: self.count,
            },
            level.rays,
            &level.out.t,
        );
    }
}

/// Mip-NeRF's second level: `count` + 1 edges drawn afresh from the
/// previous level's edges and its weights, blurred and padded by
/// `padding` (the cpu engine's `ResampledEdges`).
struct Resample {
    count: usize,
    padding: f32,
}

impl LevelSampler for Resample {
    fn samples_per_ray(&self, previous: Option<usize>) -> Result<usize, String> {
        match previous {
            Some(_) => Ok(self.count),
            None => Err("the first level cannot be a resampled level".into()),
        }
    }

    fn draws_intervals(&self) -> bool {
        true
    }

    fn scratch_per_ray(&self, previous: usize) -> ScratchPerRay {
        ScratchPerRay {
            bins: previous,
            ..ScratchPerRay::default()
        }
    }

    fn record(
        &self,
        rec: &mut Recorder,
        sampling: &GpuSampling,
        level: LevelSampling,
        jitter: Option<u32>,
    ) {
        let previous = level.previous.expect("checked by samples_per_ray");
        let m = previous.per_ray;
        sampling.record_blur_weights(rec, &previous.weights, level.rays, m, level.bin_weights);
        sampling.record_sample_pdf(
            rec,
            Pdf {
                edges: &previous.edges,
                weights: level.bin_weights,
                bins: m,
                padding: self.padding,
            },
            level.rays,
            self.count + 1,
            jitter,
            &level.out.edges,
        );
    }
}

/// A proposal sampler's first level: `count` intervals whose `count` + 1
/// edges are stratified in the contraction's spacing coordinate s between
/// each ray's near and far bounds (the cpu engine's `SpacedIntervals`: the
/// same stratified kernel, so the same jitter, on the bounds in s).
struct SpacedIntervals {
    count: usize,
    contraction: Contraction,
}

impl LevelSampler for SpacedIntervals {
    fn samples_per_ray(&self, _previous: Option<usize>) -> Result<usize, String> {
        Ok(self.count)
    }

    fn scratch_per_ray(&self, _previous: usize) -> ScratchPerRay {
        // Each ray's near and far bound in s.
        ScratchPerRay {
            edges: 1,
            fine: 1,
            ..ScratchPerRay::default()
        }
    }

    fn draws_intervals(&self) -> bool {
        true
    }

    fn record(
        &self,
        rec: &mut Recorder,
        sampling: &GpuSampling,
        level: LevelSampling,
        jitter: Option<u32>,
    ) {
        let rays = level.rays;
        if rays == 0 {
            return;
        }
        let bytes = 4 * rays as u64;
        let (near, far) = (level.edges, level.fine_t);
        rec.encoder
            .copy_buffer_to_buffer(level.bounds.near, 0, near, 0, bytes);
        rec.encoder
            .copy_buffer_to_buffer(level.bounds.far, 0, far, 0, bytes);
        for bound in [near, far] {
            level
                .proposal
                .record_spacing(rec, &self.contraction, bound, rays, false);
        }
        sampling.record_stratified(
            rec,
            RayBounds { near, far },
            rays,
            self.count + 1,
            jitter,
            &level.out.edges,
        );
        level.proposal.record_spacing(
            rec,
            &self.contraction,
            &level.out.edges,
            rays * (self.count + 1),
            true,
        );
    }
}

/// A proposal sampler's later levels: `count` + 1 edges drawn from the
/// previous level's intervals and weights in s (padded by `padding`, not
/// blurred), mapped back to distances (the cpu engine's
/// `ProposalResample`).
struct ProposalResample {
    count: usize,
    padding: f32,
    contraction: Contraction,
}

impl LevelSampler for ProposalResample {
    fn samples_per_ray(&self, previous: Option<usize>) -> Result<usize, String> {
        match previous {
            Some(_) => Ok(self.count),
            None => Err("the first level cannot be a proposal resampling level".into()),
        }
    }

    fn scratch_per_ray(&self, previous: usize) -> ScratchPerRay {
        // The previous level's edges in s.
        ScratchPerRay {
            edges: previous + 1,
            ..ScratchPerRay::default()
        }
    }

    fn draws_intervals(&self) -> bool {
        true
    }

    fn record(
        &self,
        rec: &mut Recorder,
        sampling: &GpuSampling,
        level: LevelSampling,
        jitter: Option<u32>,
    ) {
        let previous = level.previous.expect("checked by samples_per_ray");
        let (rays, m) = (level.rays, previous.per_ray);
        if rays == 0 {
            return;
        }
        let edges = rays * (m + 1);
        rec.encoder
            .copy_buffer_to_buffer(&previous.edges, 0, level.edges, 0, 4 * edges as u64);
        level
            .proposal
            .record_spacing(rec, &self.contraction, level.edges, edges, false);
        sampling.record_sample_pdf(
            rec,
            Pdf {
                edges: level.edges,
                weights: &previous.weights,
                bins: m,
                padding: self.padding,
            },
            rays,
            self.count + 1,
            jitter,
            &level.out.edges,
        );
        level.proposal.record_spacing(
            rec,
            &self.contraction,
            &level.out.edges,
            rays * (self.count + 1),
            true,
        );
    }
}

#[cfg(test)]
mod tests {
    use super::super::{Plan, plan};
    use crate::field::common::{Recipe, SamplerKind, Sampling};

    /// Each level's samples per ray, or the plan's refusal.
    fn per_ray(recipe: &Recipe) -> Result<Vec<usize>, String> {
        match plan(recipe)? {
            Plan::Fixed(levels) => Ok(levels.iter().map(|(_, n)| *n).collect()),
            Plan::Marched => Ok(Vec::new()),
        }
    }

    #[test]
    fn the_papers_levels_evaluate_their_samples_per_ray() {
        // NeRF: 64 stratified points, then the fine network on those 64
        // and 128 importance samples (Mildenhall et al. 2020, section 5.3).
        let nerf = crate::field::nerf::recipe(Sampling::Paper, true);
        assert_eq!(per_ray(&nerf), Ok(vec![64, 64 + 128]));
        // Mip-NeRF: 128 stratified frustums, then 128 resampled ones that
        // replace them (Barron et al. 2021, section 4; reference
        // `num_samples`).
        let mipnerf = crate::field::mipnerf::recipe(Sampling::Paper, true);
        assert_eq!(per_ray(&mipnerf), Ok(vec![128, 128]));
        let marched = crate::field::nerf::recipe(Sampling::Occupancy, true);
        assert!(matches!(plan(&marched), Ok(Plan::Marched)));
    }

    /// The proposal sampler's levels: 256 then 96 proposal intervals, then
    /// 48 of the full field (Instant-NGP's counts, nerfacc's `ngp_prop`),
    /// each its own; without a contraction to space them by, refused.
    #[test]
    fn the_proposal_levels_evaluate_their_intervals_and_need_a_contraction() {
        use crate::field::common::Level;
        use crate::field::contraction::{Contraction, ContractionNorm};
        let mut recipe = crate::field::nerf::recipe(Sampling::Paper, true);
        recipe.levels = vec![
            Level::proposal(SamplerKind::SpacedIntervals { count: 256 }, 0),
            Level::proposal(
                SamplerKind::ProposalResample {
                    count: 96,
                    padding: 0.01,
                },
                0,
            ),
            Level::radiance(
                SamplerKind::ProposalResample {
                    count: 48,
                    padding: 0.01,
                },
                1,
                1.0,
            ),
        ];
        let without = per_ray(&recipe).expect_err("refused");
        assert!(
            without.starts_with("level 0: the proposal sampler's levels space their samples"),
            "{without}"
        );
        recipe.contraction = Some(Contraction {
            centre: glam::Vec3::ZERO,
            radius: 1.0,
            norm: ContractionNorm::L2,
        });
        assert_eq!(per_ray(&recipe), Ok(vec![256, 96, 48]));
        recipe.levels.swap(0, 1);
        let first = per_ray(&recipe).expect_err("refused");
        assert!(
            first.starts_with("level 0: the first level cannot be a proposal resampling"),
            "{first}"
        );
    }

    #[test]
    fn levels_that_no_sampler_draws_are_refused_by_level() {
        let nerf = crate::field::nerf::recipe(Sampling::Paper, true);
        let mipnerf = crate::field::mipnerf::recipe(Sampling::Paper, true);
        let with = |recipe: &Recipe, level: usize, sampler: SamplerKind| {
            let mut recipe = recipe.clone();
            recipe.levels[level].sampler = sampler;
            per_ray(&recipe).expect_err("refused")
        };
        // Each paper's second level, put where the other paper's goes.
        let (importance, resample) = (nerf.levels[1].sampler, mipnerf.levels[1].sampler);
        let refusals = [
            (
                with(&mipnerf, 1, importance),
                "level 1: it adds importance points",
            ),
            (with(&nerf, 1, resample), "level 1: it resamples frustums"),
            (
                with(&nerf, 0, importance),
                "level 0: the first level cannot be an importance",
            ),
            (
                with(&mipnerf, 0, resample),
                "level 0: the first level cannot be a resampled",
            ),
            (
                with(&nerf, 1, SamplerKind::Occupancy),
                "level 1: it marches",
            ),
            (
                with(&nerf, 0, SamplerKind::Stratified { count: 2 }),
                "level 1: it samples the previous level's weights, which needs three",
            ),
            (
                with(&nerf, 0, SamplerKind::Stratified { count: 0 }),
                "level 0 has no samples",
            ),
        ];
        for (message, expected) in refusals {
            assert!(
                message.starts_with(expected),
                "{message:?}, not {expected:?}"
            );
        }
    }
}
