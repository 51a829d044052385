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
use crate::engine::gpu::sampling::{GpuSampling, Pdf, RayBounds, SortedRows, WeightedSamples};
use crate::field::common::{SampleShape, SamplerKind};

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
    /// The level's own buffers: `t` for points, `edges` for frustums.
    pub(super) out: &'a LevelBuffers,
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
) -> Result<Box<dyn LevelSampler>, String> {
    let frustums = shape == SampleShape::ConicalFrustums;
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
        SamplerKind::SpacedIntervals { .. } | SamplerKind::ProposalResample { .. } => {
            return Err(
                "the proposal sampler is not on the gpu engine yet: use --engine cpu, or \
                 --sampling occupancy"
                    .into(),
            );
        }
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
