//! What the training loop, the renderer and the viewer need from a model on
//! an engine. Each (model, engine) pair implements it; nothing above this
//! trait knows which one it drives.

use glam::Vec3;

use crate::scene::Camera;

pub mod batch;
pub mod checkpoint;
pub mod pixels;

use batch::RayBatch;
use checkpoint::Checkpoint;

/// A stage of a training step, as both engines time it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stage {
    March,
    Encode,
    NetworksForward,
    Composite,
    NetworksBackward,
    EncodeBackward,
    Optimiser,
    GridUpdate,
}

impl Stage {
    /// Every stage, in the order of a step (the grid's update, every 16
    /// steps, last).
    pub const ALL: [Stage; 8] = [
        Stage::March,
        Stage::Encode,
        Stage::NetworksForward,
        Stage::Composite,
        Stage::NetworksBackward,
        Stage::EncodeBackward,
        Stage::Optimiser,
        Stage::GridUpdate,
    ];

    /// The stage's name in reports and the viewer.
    pub fn name(self) -> &'static str {
        match self {
            Stage::March => "march",
            Stage::Encode => "encode",
            Stage::NetworksForward => "networks forward",
            Stage::Composite => "composite + loss",
            Stage::NetworksBackward => "networks backward",
            Stage::EncodeBackward => "encode backward",
            Stage::Optimiser => "optimiser",
            Stage::GridUpdate => "grid update",
        }
    }
}

/// Seconds spent in each stage of one training step: a table indexed by
/// [`Stage`] (`times[Stage::March]`), so a new stage is a variant, not a
/// field to add in every place that sums, scales or names the times.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct StageTimes([f64; Stage::ALL.len()]);

impl std::ops::Index<Stage> for StageTimes {
    type Output = f64;

    fn index(&self, stage: Stage) -> &f64 {
        &self.0[stage as usize]
    }
}

impl std::ops::IndexMut<Stage> for StageTimes {
    fn index_mut(&mut self, stage: Stage) -> &mut f64 {
        &mut self.0[stage as usize]
    }
}

impl StageTimes {
    /// The table of `seconds(stage)` for every stage.
    pub fn from_fn(mut seconds: impl FnMut(Stage) -> f64) -> Self {
        Self(Stage::ALL.map(&mut seconds))
    }

    pub fn total(&self) -> f64 {
        self.0.iter().sum()
    }

    pub fn named(&self) -> [(&'static str, f64); Stage::ALL.len()] {
        Stage::ALL.map(|stage| (stage.name(), self[stage]))
    }

    pub fn add(&mut self, other: &StageTimes) {
        for stage in Stage::ALL {
            self[stage] += other[stage];
        }
    }
}

/// What one training step did.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct StepStats {
    /// Mean loss over the batch's rays.
    pub loss: f32,
    /// The mean loss of each of the first two levels (coarse, fine) before
    /// their weights, for models with levels; the first is the whole loss
    /// for single-level models that report it.
    pub level_losses: [f32; 2],
    pub rays: usize,
    /// Samples the networks were evaluated on.
    pub samples: usize,
    /// Of those, the samples before the rays' cuts (transmittance below
    /// 1e-4), which compositing weighs and the backward passes run on:
    /// instant-ngp's testbed calls these per ray "samples/ray", after
    /// compaction. Reported by steps that compact (the gpu engine's σ-first
    /// steps) or count them on the host (every cpu engine step).
    pub samples_composited: Option<usize>,
    /// Samples of a proposal sampler's density-only levels (not counted in
    /// [`Self::samples`], which are the full field's).
    pub proposal_samples: usize,
    /// The interlevel loss that trained the proposal levels (0 without).
    pub proposal_loss: f32,
    pub times: StageTimes,
    /// Floating-point operations of the networks' forward and backward
    /// passes in this step, for models that count them (0 otherwise).
    pub network_flops: f64,
}

impl StepStats {
    pub fn samples_per_ray(&self) -> f32 {
        if self.rays == 0 {
            0.0
        } else {
            self.samples as f32 / self.rays as f32
        }
    }

    /// [`Self::proposal_samples`] per ray, where a proposal sampler ran.
    pub fn proposal_samples_per_ray(&self) -> Option<f32> {
        (self.proposal_samples > 0).then(|| self.proposal_samples as f32 / self.rays.max(1) as f32)
    }

    /// [`Self::samples_composited`] per ray.
    pub fn composited_per_ray(&self) -> Option<f32> {
        self.samples_composited.map(|n| {
            if self.rays == 0 {
                0.0
            } else {
                n as f32 / self.rays as f32
            }
        })
    }
}

/// The loss of a step of fixed levels (stratified, then importance or
/// resampled), summed alike on both engines: each chunk's mean loss at a
/// level counts with its share of the batch's rays, and with the level's
/// weight in the total.
#[derive(Debug, Clone, Copy, Default)]
pub struct LevelLossSum {
    loss: f64,
    level_losses: [f32; 2],
}

impl LevelLossSum {
    /// Adds a chunk's mean loss `value` at level `level` (of weight
    /// `loss_weight`), the chunk holding `share` of the batch's rays.
    pub fn add(&mut self, level: usize, loss_weight: f32, share: f32, value: f64) {
        self.loss += value * (loss_weight * share) as f64;
        if let Some(l) = self.level_losses.get_mut(level) {
            *l += (value * share as f64) as f32;
        }
    }

    /// The step's stats. Every sample of a fixed level is composited, so
    /// none is counted apart.
    pub fn into_stats(
        self,
        rays: usize,
        samples: usize,
        times: StageTimes,
        network_flops: f64,
    ) -> StepStats {
        StepStats {
            loss: self.loss as f32,
            level_losses: self.level_losses,
            rays,
            samples,
            samples_composited: None,
            proposal_samples: 0,
            proposal_loss: 0.0,
            times,
            network_flops,
        }
    }
}

/// Rays to render, as [`RadianceModel::render`] takes them: world origins,
/// unit directions and cone radii at unit distance
/// ([`crate::scene::Ray::radius`], which models of cones (Mip-NeRF) read
/// and the others ignore), composited over `background`.
#[derive(Debug, Clone, Copy)]
pub struct RenderRays<'a> {
    pub origins: &'a [Vec3],
    pub directions: &'a [Vec3],
    pub radii: &'a [f32],
    pub background: [f32; 3],
}

/// A list of rays as the columns [`RenderRays`] borrows.
#[derive(Debug, Clone, Default)]
pub struct RayColumns {
    pub origins: Vec<Vec3>,
    pub directions: Vec<Vec3>,
    pub radii: Vec<f32>,
}

impl RayColumns {
    pub fn of(rays: &[crate::scene::Ray]) -> Self {
        Self {
            origins: rays.iter().map(|r| r.origin).collect(),
            directions: rays.iter().map(|r| r.direction).collect(),
            radii: rays.iter().map(|r| r.radius()).collect(),
        }
    }

    /// The rays, composited over `background`.
    pub fn over(&self, background: [f32; 3]) -> RenderRays<'_> {
        RenderRays {
            origins: &self.origins,
            directions: &self.directions,
            radii: &self.radii,
            background,
        }
    }
}

/// World positions at which a model is asked for σ or colour (for meshes),
/// each standing for a cube of side `footprint` (world units), which
/// models of cones (Mip-NeRF) integrate over and the others ignore; colour
/// is seen along unit `directions` (one per position; σ ignores them, and
/// they may be empty there).
#[derive(Debug, Clone, Copy)]
pub struct PointQuery<'a> {
    pub positions: &'a [Vec3],
    pub directions: &'a [Vec3],
    pub footprint: f32,
}

/// One rendered pixel.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct RenderedPixel {
    pub rgb: [f32; 3],
    pub opacity: f32,
    /// Expected depth Σ wᵢ tᵢ along the unit direction (world units).
    pub depth: f32,
}

/// What an image shows.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, serde::Serialize, serde::Deserialize,
)]
pub enum RenderMode {
    Rgb,
    /// Depth of the surface hit (expected depth over opacity), near = white.
    Depth,
    Opacity,
}

/// What a model on the gpu engine offers besides [`RadianceModel`]: drawing
/// a view into a texture on its device (the viewer shows it from there),
/// and how its stages are timed.
pub trait TextureRender {
    /// Draws `camera`'s view in `mode` over `background` into `target`
    /// (RGBA8, the camera's size, on the model's device).
    fn render_to_texture(
        &self,
        camera: &Camera,
        mode: RenderMode,
        background: [f32; 3],
        target: &wgpu::Texture,
    ) -> Result<(), String>;

    /// How the per-stage times were measured, for the benchmark.
    fn stage_timing_note(&self) -> String;
}

/// Which vector kernels a model on the cpu engine runs, in words.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CpuKernels {
    /// `AmxBf16`, `Avx512Bf16`, `Avx512`, `Avx2` or `Portable`.
    pub name: String,
    /// How the networks' products are computed.
    pub precision: &'static str,
}

/// A model being trained on one engine.
pub trait RadianceModel: Send {
    /// e.g. "Instant-NGP (cpu)".
    fn describe(&self) -> String;

    /// How many rays the next batch should hold (models that adapt the
    /// batch to a sample budget change it as training goes).
    fn rays_for_next_batch(&self) -> usize;

    /// During early steps some models draw rays from the central part of
    /// each image only: the fraction of width and height, or `None` for the
    /// whole image.
    fn centre_crop(&self, _step: u32) -> Option<f32> {
        None
    }

    /// One optimisation step on `batch`; `step` counts from 0 and seeds
    /// every random choice inside the step.
    fn step(&mut self, batch: &RayBatch, step: u32) -> StepStats;

    /// Inference: composites each ray over its background, a pixel per
    /// ray into `out`.
    fn render(&self, rays: RenderRays, out: &mut [RenderedPixel]);

    /// Everything needed to resume bit for bit: parameters, optimiser state,
    /// grids, counters. The header holds small values as JSON.
    fn save(&self) -> Checkpoint;

    /// Restores what [`Self::save`] wrote.
    fn load(&mut self, checkpoint: &Checkpoint) -> Result<(), String>;

    /// Bytes held by parameters, optimiser state and workspaces.
    fn memory_bytes(&self) -> usize;

    /// Texture rendering, for models whose engine has a device.
    fn texture_render(&self) -> Option<&dyn TextureRender> {
        None
    }

    /// On the gpu engine: read each step's loss, stage times and occupancy
    /// update back at once (`false`: the step's own figures and the cpu
    /// engine's order of updates, at two or three waits for the device a
    /// step), or a step late (`true`, the default: one wait a step, each
    /// step reporting the previous one's loss and times, a grid update used
    /// from the step after). The cpu engine reads nothing back.
    fn set_read_back_late(&mut self, _late: bool) {}

    /// The vector kernels of a model on the cpu engine (`None` on the gpu
    /// engine), for the log.
    fn cpu_kernels(&self) -> Option<CpuKernels> {
        None
    }

    /// σ (per world unit) at `points`: for meshes. Models of levels answer
    /// with their finest field.
    fn density_at(&self, _points: PointQuery, _sigma: &mut [f32]) -> Result<(), String> {
        Err(format!(
            "{} cannot be asked for its density at points; give --engine cpu",
            self.describe()
        ))
    }

    /// Colour (linear 0 to 1, n × 3) at `points`, seen along their
    /// directions: for the colours of a mesh's vertices.
    fn colour_at(&self, _points: PointQuery, _rgb: &mut [f32]) -> Result<(), String> {
        Err(format!(
            "{} cannot be asked for its colour at points; give --engine cpu",
            self.describe()
        ))
    }

    /// The pose corrections camera refinement learned, six values per
    /// training image (a rotation vector, then a translation: see
    /// `engine::shared::camera_refinement`); `None` when the model does not
    /// refine its cameras.
    fn camera_corrections(&self) -> Option<Vec<f32>> {
        None
    }

    /// Training images with an appearance vector of their own, for a
    /// model with appearance embeddings (`None` without).
    fn appearance_images(&self) -> Option<usize> {
        None
    }

    /// The appearance [`Self::render`] draws with: the training image
    /// `image`'s vector, or the mean of them all (`None`, the default: a
    /// view that is no training image's, as held-out views are evaluated).
    fn set_render_appearance(&mut self, image: Option<usize>) -> Result<(), String> {
        let _ = image;
        Err(format!("{} has no appearance embeddings", self.describe()))
    }

    /// NeRF in the Wild's protocol for a view that is no training image's
    /// (Martin-Brualla et al. 2021, section 6): the appearance vector that
    /// best explains `fit` (rays of the view's left half, with their
    /// targets), found with the field held still, then `rays` (its right
    /// half) rendered with it. Nothing the model keeps changes.
    fn render_with_fitted_appearance(
        &mut self,
        fit: &batch::RayBatch,
        rays: RenderRays,
        out: &mut [RenderedPixel],
    ) -> Result<(), String> {
        let _ = (fit, rays, out);
        Err(format!(
            "{} cannot fit a held-out view's appearance (models with appearance embeddings on \
             the cpu engine can)",
            self.describe()
        ))
    }

    /// Limits what [`Self::render`] shows to a crop box (`None`: the whole
    /// scene): samples outside it have no density, so the background shows
    /// through.
    fn set_crop(&mut self, crop: Option<crate::scene::crop::CropBox>) -> Result<(), String> {
        match crop {
            None => Ok(()),
            Some(_) => Err(format!(
                "{} does not render with a crop box; give --engine cpu",
                self.describe()
            )),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `Stage::ALL` lists every stage once, in the order of their slots,
    /// so each stage reads and writes its own slot of the table.
    #[test]
    fn each_stage_has_its_own_slot_of_the_table() {
        for (slot, stage) in Stage::ALL.into_iter().enumerate() {
            assert_eq!(stage as usize, slot, "{stage:?}");
        }
        let times = StageTimes::from_fn(|stage| 1.0 + stage as usize as f64);
        let mut twice = times;
        twice.add(&times);
        for (stage, (name, seconds)) in Stage::ALL.into_iter().zip(times.named()) {
            assert_eq!((name, seconds), (stage.name(), 1.0 + stage as usize as f64));
            assert_eq!(twice[stage], 2.0 * seconds);
        }
        // 1 + 2 + … + 8.
        assert_eq!(times.total(), 36.0);
    }
}
