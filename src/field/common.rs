//! Settings of stages that every model uses, with each model's values in
//! its own file (`ngp.rs`, `nerf.rs`, `mipnerf.rs`).

/// Loss on pixel colours (`--loss huber|l2` on the command line).
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, serde::Serialize, serde::Deserialize,
)]
pub enum LossKind {
    /// Huber with δ = 0.1: instant-ngp's default for NeRF (config "loss").
    Huber,
    L2,
}

/// Huber's δ (config "loss": Huber; tiny-cuda-nn's default, also used by
/// JNeRF's port).
pub const HUBER_DELTA: f32 = 0.1;

/// Where a model with a choice of samplers (NeRF, Mip-NeRF) puts its
/// samples.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "lowercase")]
pub enum Sampling {
    /// The paper's: 64 stratified samples for a coarse network, 128 more
    /// from its weights for a fine network, on every ray.
    Paper,
    /// Instant-NGP's occupancy grid (zrak's default): samples only in
    /// occupied cells, at a fixed step, until the ray is opaque; one network.
    Occupancy,
    /// Proposal density fields (Mip-NeRF 360, section 2.1; nerfstudio's
    /// nerfacto; nerfacc's `ngp_prop`): in the scene's contracted space,
    /// small density-only fields place samples per ray (Instant-NGP: 256
    /// then 96; NeRF and Mip-NeRF: 64 then 64), each level resampled from
    /// the one before, and the full field evaluates a few (48; 32):
    /// unbounded scenes at a fixed, small count per ray.
    Proposal,
}

impl Sampling {
    pub fn name(self) -> &'static str {
        match self {
            Sampling::Paper => "paper",
            Sampling::Occupancy => "occupancy",
            Sampling::Proposal => "proposal",
        }
    }
}

/// How rays march through the occupancy grid (Instant-NGP, appendix E.1;
/// each model's values in its own file).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MarchConfig {
    /// Step length in unit-cube coordinates: √3 / 1024 (testbed:
    /// MIN_CONE_STEPSIZE for the Blender scenes, cone angle 0).
    pub step: f32,
    /// At most this many samples per ray (testbed: NERF_STEPS()).
    pub max_steps: u32,
    /// Stop marching once transmittance falls below this (testbed: 1e-4).
    pub min_transmittance: f32,
    /// For scenes with aabb_scale > 1, the step grows to this fraction of
    /// the distance from the camera (testbed: `cone_angle_constant` 1/256,
    /// used when aabb_scale > 1; Blender scenes keep the fixed step). See
    /// `engine::shared::march::Lattice`.
    pub cone_angle: f32,
}

/// The occupancy grid's settings (Instant-NGP, appendix E.2; each model's
/// values in its own file).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OccupancyConfig {
    /// Cells per side of each cascade.
    pub resolution: u32,
    /// EMA decay of the stored density per update.
    pub decay: f32,
    /// A cell is occupied where its optical thickness (σ · smallest step)
    /// exceeds min(this, mean over the grid) (testbed:
    /// NERF_MIN_OPTICAL_THICKNESS).
    pub min_optical_thickness: f32,
    /// Steps between grid updates.
    pub update_interval: u32,
    /// During the first this many steps every cell is updated; afterwards
    /// a random quarter plus a quarter drawn from occupied cells.
    pub warmup_steps: u32,
}

impl OccupancyConfig {
    /// Cascades needed to cover aabb_scale: each doubles the extent
    /// (paper, appendix E.2: K = 1 + ceil(log2(aabb_scale))).
    pub fn cascades(aabb_scale: f32) -> u32 {
        1 + aabb_scale.max(1.0).log2().ceil() as u32
    }
}

/// Where the positions a field is given live.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Coordinates {
    /// World units (NeRF, Mip-NeRF: their encodings' frequencies are per
    /// world unit).
    World,
    /// The scene's unit cube, where the occupancy grid marches (Instant-NGP:
    /// its hash grid spans a box around the unit cube, and marched samples
    /// reach it without a round trip through world units).
    UnitCube,
}

/// How the learning rate changes with the optimiser's step count.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum LrSchedule {
    /// From `start` on, the rate is multiplied by
    /// base^⌊(step − start) / interval⌋ (Instant-NGP).
    Stepwise {
        start: u32,
        interval: u32,
        base: f32,
    },
    /// rate · (final/rate)^(step / steps): exponential decay that reaches
    /// `final_rate` at `steps` and keeps decaying after (NeRF,
    /// `run_nerf.py`: lrate · 0.1^(step / (lrate_decay · 1000))).
    Exponential { final_rate: f32, steps: u32 },
    /// Log-linear from the rate to `final_rate` at `steps` (held there
    /// after), times a warm-up factor that rises from `warmup_multiplier`
    /// to 1 along a quarter sine over the first `warmup_steps` (Mip-NeRF,
    /// `math.learning_rate_decay`).
    LogLinearWithWarmup {
        final_rate: f32,
        steps: u32,
        warmup_steps: u32,
        warmup_multiplier: f32,
    },
}

/// Adam and its schedule.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OptimiserConfig {
    pub learning_rate: f32,
    pub beta1: f32,
    pub beta2: f32,
    pub epsilon: f32,
    /// L2 regularisation on network weights only, not on hash entries.
    pub l2_weights: f32,
    pub schedule: LrSchedule,
}

impl OptimiserConfig {
    /// The learning rate at `step`.
    pub fn learning_rate_at(&self, step: u32) -> f32 {
        match self.schedule {
            LrSchedule::Stepwise {
                start,
                interval,
                base,
            } => {
                if step < start {
                    return self.learning_rate;
                }
                let decays = (step - start) / interval.max(1);
                self.learning_rate * base.powi(decays as i32)
            }
            LrSchedule::Exponential { final_rate, steps } => {
                // In f64: the exponent's small steps would round away in f32
                // over hundreds of thousands of steps.
                let ratio = final_rate as f64 / self.learning_rate as f64;
                let progress = step as f64 / steps.max(1) as f64;
                (self.learning_rate as f64 * ratio.powf(progress)) as f32
            }
            LrSchedule::LogLinearWithWarmup {
                final_rate,
                steps,
                warmup_steps,
                warmup_multiplier,
            } => {
                let warmup = if warmup_steps == 0 {
                    1.0
                } else {
                    let progress = (step as f64 / warmup_steps as f64).min(1.0);
                    let m = warmup_multiplier as f64;
                    m + (1.0 - m) * (0.5 * std::f64::consts::PI * progress).sin()
                };
                let progress = (step as f64 / steps.max(1) as f64).min(1.0);
                let log_rate = (self.learning_rate as f64).ln() * (1.0 - progress)
                    + (final_rate as f64).ln() * progress;
                (warmup * log_rate.exp()) as f32
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exponential_decay_reaches_its_final_rate() {
        let config = OptimiserConfig {
            learning_rate: 5e-4,
            beta1: 0.9,
            beta2: 0.999,
            epsilon: 1e-7,
            l2_weights: 0.0,
            schedule: LrSchedule::Exponential {
                final_rate: 5e-5,
                steps: 500_000,
            },
        };
        assert_eq!(config.learning_rate_at(0), 5e-4);
        let half = config.learning_rate_at(250_000);
        // Half way in log space: √(5e-4 · 5e-5).
        assert!((half - (5e-4f32 * 5e-5).sqrt()).abs() < 1e-9, "{half}");
        assert!((config.learning_rate_at(500_000) - 5e-5).abs() < 1e-10);
        assert!(config.learning_rate_at(1_000_000) < 5e-5);
    }

    #[test]
    fn log_linear_schedule_warms_up_then_decays() {
        let config = OptimiserConfig {
            learning_rate: 5e-4,
            beta1: 0.9,
            beta2: 0.999,
            epsilon: 1e-8,
            l2_weights: 0.0,
            schedule: LrSchedule::LogLinearWithWarmup {
                final_rate: 5e-6,
                steps: 1_000_000,
                warmup_steps: 2500,
                warmup_multiplier: 0.01,
            },
        };
        let close = |a: f32, b: f64| ((a as f64 - b) / b).abs() < 1e-5;
        // Step 0: the warm-up's multiplier times the initial rate.
        assert!(close(config.learning_rate_at(0), 5e-6));
        // Half way through the warm-up: sin(π/4) of the way to 1, with the
        // log-linear decay of 1250 steps (a factor 100^(−1250/1e6)).
        let decay = 100f64.powf(-1250.0 / 1e6);
        let warm = 0.01 + 0.99 * (std::f64::consts::FRAC_PI_4).sin();
        assert!(close(config.learning_rate_at(1250), 5e-4 * warm * decay));
        // Half way in log space at 500k: √(5e-4 · 5e-6) = 5e-5.
        assert!(close(config.learning_rate_at(500_000), 5e-5));
        assert!(close(config.learning_rate_at(1_000_000), 5e-6));
        assert!(close(config.learning_rate_at(2_000_000), 5e-6));
    }
}

/// Where a level of a model puts its samples along each ray.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum SamplerKind {
    /// Marching through the occupancy grid: samples only in occupied cells,
    /// at a fixed step, until the ray is opaque.
    Occupancy,
    /// `count` stratified samples between the ray's near and far bounds.
    Stratified { count: usize },
    /// `count` samples drawn from the previous level's weights (inverse
    /// CDF, `padding` added to each weight), evaluated together with the
    /// previous level's samples.
    Importance { count: usize, padding: f32 },
    /// Mip-NeRF's resampling: `count` intervals drawn afresh from the
    /// previous level's intervals, whose weights are blurred (2-tap max,
    /// 2-tap average) and padded by `padding` first; they replace the
    /// previous level's intervals instead of joining them.
    Resample { count: usize, padding: f32 },
    /// `count` intervals between `count` + 1 edges stratified in the
    /// spacing coordinate s of the recipe's contraction (linear inside its
    /// unit ball, linear in disparity beyond; `field::contraction`), from
    /// the ray's near to its far bound: a proposal sampler's first level.
    SpacedIntervals { count: usize },
    /// `count` intervals whose edges are drawn from the previous level's
    /// intervals and weights in s (inverse CDF, `padding` added to each
    /// weight, no blur): the proposal sampler's later levels (nerfstudio's
    /// `PDFSampler`, `histogram_padding` 0.01).
    ProposalResample { count: usize, padding: f32 },
}

impl SamplerKind {
    /// Samples per ray a level of this sampler evaluates after a level of
    /// `previous` (0 before the first): an importance level evaluates the
    /// previous level's samples and its own, the others only their own;
    /// the occupancy grid's march has no fixed count (0).
    pub fn samples_evaluated(self, previous: usize) -> usize {
        match self {
            SamplerKind::Stratified { count }
            | SamplerKind::Resample { count, .. }
            | SamplerKind::SpacedIntervals { count }
            | SamplerKind::ProposalResample { count, .. } => count,
            SamplerKind::Importance { count, .. } => previous + count,
            SamplerKind::Occupancy => 0,
        }
    }
}

/// What a sample stands for, which decides what the field is given.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SampleShape {
    /// A point on the ray (NeRF, Instant-NGP).
    Points,
    /// The conical frustum of the pixel's cone between two distances, given
    /// to the field as its Gaussian's mean and diagonal covariance
    /// (Mip-NeRF). Fixed-count levels then sample interval edges: `count`
    /// intervals take `count + 1` edges.
    ConicalFrustums,
}

/// One level of a model: a sampler and the field that evaluates its
/// samples, with the weight of its loss.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Level {
    pub sampler: SamplerKind,
    /// Index of the model's field this level evaluates.
    pub field: usize,
    pub loss_weight: f32,
    /// Whether the level composites colour and is trained by the loss on
    /// pixels. A proposal level computes density only: its weights place
    /// the next level's samples, and the interlevel loss trains it.
    pub colour: bool,
}

impl Level {
    /// A level that composites colour, with its loss weight.
    pub const fn radiance(sampler: SamplerKind, field: usize, loss_weight: f32) -> Self {
        Self {
            sampler,
            field,
            loss_weight,
            colour: true,
        }
    }

    /// A density-only proposal level (no loss on pixels).
    pub const fn proposal(sampler: SamplerKind, field: usize) -> Self {
        Self {
            sampler,
            field,
            loss_weight: 0.0,
            colour: false,
        }
    }
}

/// How big a training batch is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BatchSize {
    /// A fixed number of rays.
    Rays(usize),
    /// As many rays as fill this many samples (grid marching, where rays
    /// hold very different numbers of samples).
    Samples(usize),
}

/// Where sampling along a ray starts and ends.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum RayBounds {
    /// The same near and far distance for every ray (NeRF's Blender scenes).
    Fixed { near: f32, far: f32 },
    /// Where the ray enters and leaves the scene's box.
    SceneBox,
}

/// What the engines build for a model: its levels, fields, batch and schedule.
#[derive(Debug, Clone, PartialEq)]
pub struct Recipe {
    pub levels: Vec<Level>,
    /// Number of separate networks (the levels index them).
    pub fields: usize,
    pub samples: SampleShape,
    pub batch: BatchSize,
    pub bounds: RayBounds,
    pub optimiser: OptimiserConfig,
    pub march: MarchConfig,
    pub occupancy: OccupancyConfig,
    /// λ of the distortion loss (Mip-NeRF 360, Barron et al. 2022, eq. 15)
    /// on a level marched through the occupancy grid (see
    /// `engine::shared::composite::Distortion`), or on the final level of a
    /// proposal sampler (in its spacing coordinate s), per ray of the
    /// batch; 0 for none.
    pub distortion: f32,
    /// (steps, fraction): rays come from the central `fraction` of each
    /// image during the first `steps` steps.
    pub centre_crop: Option<(u32, f32)>,
    /// Where samples become the fields' inputs through the scene's
    /// contraction (unbounded scenes), its frame and norm; `None` keeps
    /// world or unit-cube positions.
    pub contraction: Option<super::contraction::Contraction>,
    /// λ of the interlevel loss (Mip-NeRF 360, eq. 13) that trains each
    /// proposal level to bound the final level's weights; 0 without
    /// proposal levels.
    pub interlevel: f32,
}

impl Recipe {
    /// The central fraction of each image that step `step`'s rays come
    /// from, while the recipe crops to the centre.
    pub fn centre_crop_at(&self, step: u32) -> Option<f32> {
        self.centre_crop
            .and_then(|(steps, fraction)| (step < steps).then_some(fraction))
    }
}
