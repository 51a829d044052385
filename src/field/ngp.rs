//! Instant-NGP (Müller, Evans, Schied, Keller 2022, "Instant Neural Graphics
//! Primitives with a Multiresolution Hash Encoding"): every constant of the
//! model, with where it comes from. "Paper" is the paper; "config" is
//! instant-ngp's `configs/nerf/base.json`; "testbed" is instant-ngp's NeRF
//! training code (`src/testbed_nerf.cu`). Also the field's shapes
//! ([`NgpShape`]: the hash grid's levels and the two networks), which both
//! engines build their Instant-NGP field from.

use std::ops::Range;

use super::common::{LrSchedule, MarchConfig, OccupancyConfig, OptimiserConfig};
use super::encoding::HashGridConfig;
use super::mlp::NetworkConfig;

use super::appearance::AppearanceShape;
use super::encoding::HashGridLayout;
use super::mlp::{Activation, MlpLayout, Precision};
use super::params::{APPEARANCE_PART, ParamLayout, Update};
use crate::scene::{Scene, UnitCubeMapping};

impl HashGridConfig {
    /// Table 1 of the paper for NeRF: L = 16, F = 2, T = 2^19, N_min = 16,
    /// N_max = 2048 · aabb_scale (paper, section 5.4).
    pub fn paper(aabb_scale: f32) -> Self {
        Self {
            levels: 16,
            features_per_level: 2,
            log2_table_size: 19,
            base_resolution: 16,
            finest_resolution: (2048.0 * aabb_scale).round() as u32,
            init_range: 1e-4,
            extent: aabb_scale,
        }
    }
}

/// The tiny MLPs (paper, section 5.4; config "network" and "rgb_network").
impl NetworkConfig {
    pub const PAPER: Self = Self {
        density_hidden_width: 64,
        density_hidden_layers: 1,
        density_output_width: 16,
        colour_hidden_width: 64,
        colour_hidden_layers: 2,
        sh_degree: 4,
    };
}

/// Occupancy grid (paper, appendix E.2; testbed).
impl OccupancyConfig {
    pub const PAPER: Self = Self {
        resolution: 128,
        decay: 0.95,
        min_optical_thickness: 0.01,
        update_interval: 16,
        warmup_steps: 256,
    };
}

/// Ray marching (paper, appendix E.1; testbed).
impl MarchConfig {
    pub const PAPER: Self = Self {
        step: 1.732_050_8 / 1024.0,
        max_steps: 1024,
        min_transmittance: 1e-4,
        cone_angle: 1.0 / 256.0,
    };

    /// [`Self::PAPER`], with the cone angle taken from the environment
    /// variable `ZRAK_CONE_ANGLE` when it holds a number (0 marches large
    /// scenes with the fixed step): for measuring what cone stepping buys.
    /// Read once per process.
    pub fn paper_or_environment() -> Self {
        static CONE_ANGLE: std::sync::OnceLock<Option<f32>> = std::sync::OnceLock::new();
        let cone_angle = *CONE_ANGLE.get_or_init(|| {
            std::env::var("ZRAK_CONE_ANGLE")
                .ok()
                .and_then(|v| v.parse::<f32>().ok())
                .filter(|c| c.is_finite() && *c >= 0.0)
        });
        Self {
            cone_angle: cone_angle.unwrap_or(Self::PAPER.cone_angle),
            ..Self::PAPER
        }
    }
}

/// λ of the distortion loss (Mip-NeRF 360, Barron et al. 2022, eq. 15;
/// multinerf's `internal/configs.py`: `distortion_loss_mult` 0.01) for
/// scenes with aabb_scale > 1. Not in instant-ngp: zrak adds it for large
/// scenes, where without it the field keeps a faint fog between the cameras
/// and the walls that rays composite through (measured on the large demo,
/// at step ~500: 337 samples per ray before the cut without it, 192 with
/// it; held-out 24.52 → 24.78 dB at step 600, reached in 692 s instead of
/// 764 s). Distances are fractions of the scene box's diagonal, where
/// multinerf's are of its normalised ray distance.
pub const LARGE_SCENE_DISTORTION: f32 = 0.01;

/// λ of the distortion loss for a scene of this aabb_scale (see
/// `engine::shared::composite::Distortion`): [`LARGE_SCENE_DISTORTION`]
/// for aabb_scale > 1, 0 for the object scenes (which have no fog between
/// camera and object to drain, and train as instant-ngp does). The
/// environment variable `ZRAK_DISTORTION` overrides it when it holds a
/// number, for measuring what the loss buys. Read once per process.
pub fn distortion_weight(aabb_scale: f32) -> f32 {
    static OVERRIDE: std::sync::OnceLock<Option<f32>> = std::sync::OnceLock::new();
    let chosen = OVERRIDE.get_or_init(|| {
        std::env::var("ZRAK_DISTORTION")
            .ok()
            .and_then(|v| v.parse::<f32>().ok())
            .filter(|c| c.is_finite() && *c >= 0.0)
    });
    chosen.unwrap_or(if aabb_scale > 1.0 {
        LARGE_SCENE_DISTORTION
    } else {
        0.0
    })
}

/// The optimiser (config "optimizer": Ema → ExponentialDecay → Adam).
impl OptimiserConfig {
    pub const PAPER: Self = Self {
        learning_rate: 1e-2,
        beta1: 0.9,
        beta2: 0.99,
        epsilon: 1e-15,
        l2_weights: 1e-6,
        schedule: LrSchedule::Stepwise {
            start: 20_000,
            interval: 10_000,
            base: 0.33,
        },
    };
}

/// Samples per training batch (paper, section 5.4: 2^18).
pub const SAMPLES_PER_BATCH: usize = 1 << 18;

/// Instant-NGP as a recipe: one level marching through the occupancy grid
/// (paper, appendix E) with one field (hash grid, density and colour
/// networks), 2^18 samples per batch, Adam with the stepwise decay, and the
/// distortion loss on large scenes ([`distortion_weight`]) for a scene of
/// this aabb_scale.
pub fn recipe(aabb_scale: f32) -> super::common::Recipe {
    use super::common::{BatchSize, Level, RayBounds, Recipe, SampleShape, SamplerKind};
    Recipe {
        levels: vec![Level {
            sampler: SamplerKind::Occupancy,
            field: 0,
            loss_weight: 1.0,
            colour: true,
        }],
        fields: 1,
        samples: SampleShape::Points,
        batch: BatchSize::Samples(SAMPLES_PER_BATCH),
        // Marching finds each ray's span through the grid's cascades; the
        // bounds serve fixed-count levels only.
        bounds: RayBounds::SceneBox,
        optimiser: OptimiserConfig::PAPER,
        march: MarchConfig::paper_or_environment(),
        occupancy: OccupancyConfig::PAPER,
        distortion: distortion_weight(aabb_scale),
        // instant-ngp samples rays from whole images from the start.
        centre_crop: None,
        contraction: None,
        interlevel: 0.0,
    }
}

// The proposal sampler for unbounded scenes (`--sampling proposal`):
// Instant-NGP's field in the contracted cube, with two density-only hash
// grids that place its samples. Not in the Instant-NGP paper; the values
// are nerfstudio's nerfacto (`nerfacto.py`, `NerfactoModelConfig`) and
// nerfacc's `examples/train_ngp_nerf_prop.py`, which both pair
// Instant-NGP's field with Mip-NeRF 360's proposal sampler.

/// Proposal samples per ray, level by level (nerfacto:
/// `num_proposal_samples_per_ray` (256, 96); nerfacc: `num_samples_per_prop`).
pub const PROPOSAL_SAMPLES: [usize; 2] = [256, 96];

/// The full field's samples per ray (nerfacto: `num_nerf_samples_per_ray`;
/// nerfacc: `num_samples`).
pub const PROPOSAL_FIELD_SAMPLES: usize = 48;

/// Padding added to each proposal weight before resampling (nerfstudio's
/// `PDFSampler`, `histogram_padding` 0.01).
pub const PROPOSAL_PADDING: f32 = 0.01;

/// Near and far bounds of every ray in the contraction frame's units
/// (nerfacto: `near_plane` 0.05, `far_plane` 1000).
pub const PROPOSAL_NEAR: f32 = 0.05;
pub const PROPOSAL_FAR: f32 = 1000.0;

/// λ of the interlevel loss (nerfacto: `interlevel_loss_mult` 1.0).
pub const INTERLEVEL_WEIGHT: f32 = 1.0;

/// λ of the distortion loss on the final level, in the spacing
/// coordinate s (nerfacto: `distortion_loss_mult` 0.002).
pub const PROPOSAL_DISTORTION: f32 = 0.002;

/// Rays per batch (nerfacto: `train_num_rays_per_batch` 4096; nerfacc:
/// `init_batch_size` 4096): 196,608 samples of the full field and 1.4 M of
/// the proposals a step, near Instant-NGP's 2^18 of the full field.
pub const PROPOSAL_RAYS_PER_BATCH: usize = 1024;

/// The proposal grids' finest resolutions, level by level (nerfacto's
/// `proposal_net_args_list`: `max_res` 128, then 256).
pub const PROPOSAL_FINEST: [u32; 2] = [128, 256];

/// A proposal field's hash grid (nerfacto's `proposal_net_args_list`: 5
/// levels, 2^17 entries, base resolution 16 (`HashMLPDensityField`'s
/// default), 2 features per level) over the contracted cube.
pub fn proposal_grid(finest_resolution: u32) -> HashGridConfig {
    HashGridConfig {
        levels: 5,
        features_per_level: 2,
        log2_table_size: 17,
        base_resolution: 16,
        finest_resolution,
        init_range: 1e-4,
        extent: 1.0,
    }
}

/// A proposal field's network: one hidden layer of 16 (nerfacto's
/// `proposal_net_args_list`: `hidden_dim` 16, `num_layers` 2 counting the
/// output), σ through the clamped exponential, no biases.
pub const PROPOSAL_HIDDEN_WIDTH: usize = 16;

/// The density at initialisation, relative to the paper's σ = exp(x):
/// σ = 0.01 · exp(x) for the contracted field and its proposal fields
/// (nerfstudio's nerfacto, `average_init_density` 0.01, given to the
/// field and to each proposal field). With the paper's scale every ray of
/// an unbounded scene is opaque a few units from its camera before any
/// step, the far field is hidden behind that fog from the start and the
/// sky settles there; starting nearly empty, the long far intervals (their
/// length grows as 1/(1 − s)) take the sky's weight first and the near
/// content condenses where the views agree. On the unbounded demo after
/// 400 steps: sky 7.6 → 82 units away, 23.0 → 26.9 dB.
pub const PROPOSAL_INIT_DENSITY: f32 = 0.01;

/// Instant-NGP with the proposal sampler, for a scene whose cameras give
/// the contraction's frame: two proposal levels then the full field, all
/// in the contracted cube (L∞, nerfacto's `SceneContraction(order=inf)`),
/// the interlevel and distortion losses, Instant-NGP's optimiser.
pub fn proposal_recipe(scene: &Scene) -> super::common::Recipe {
    use super::common::{BatchSize, Level, RayBounds, Recipe, SampleShape, SamplerKind};
    use super::contraction::{Contraction, ContractionNorm};
    let positions: Vec<glam::Vec3> = scene
        .photographed_training_views()
        .iter()
        .map(|frame| frame.camera.position())
        .collect();
    let contraction = Contraction::around_cameras(&positions, ContractionNorm::LInf);
    let [first, second] = PROPOSAL_SAMPLES;
    Recipe {
        levels: vec![
            Level::proposal(SamplerKind::SpacedIntervals { count: first }, 0),
            Level::proposal(
                SamplerKind::ProposalResample {
                    count: second,
                    padding: PROPOSAL_PADDING,
                },
                1,
            ),
            Level::radiance(
                SamplerKind::ProposalResample {
                    count: PROPOSAL_FIELD_SAMPLES,
                    padding: PROPOSAL_PADDING,
                },
                2,
                1.0,
            ),
        ],
        fields: 3,
        samples: SampleShape::Points,
        batch: BatchSize::Rays(PROPOSAL_RAYS_PER_BATCH),
        bounds: RayBounds::Fixed {
            near: PROPOSAL_NEAR * contraction.radius,
            far: PROPOSAL_FAR * contraction.radius,
        },
        optimiser: OptimiserConfig::PAPER,
        march: MarchConfig::PAPER,
        occupancy: OccupancyConfig::PAPER,
        distortion: PROPOSAL_DISTORTION,
        centre_crop: None,
        contraction: Some(contraction),
        interlevel: INTERLEVEL_WEIGHT,
    }
}

/// A density-only field on a small hash grid: a proposal level's.
#[derive(Debug, Clone)]
pub struct DensityShape {
    pub grid: HashGridLayout,
    pub density: MlpLayout,
    /// σ = `density_scale` · exp(x) of the network's output x.
    pub density_scale: f32,
}

impl DensityShape {
    /// The proposal field whose grid's finest resolution is `finest`.
    pub fn proposal(finest_resolution: u32) -> Self {
        let grid = proposal_grid(finest_resolution);
        Self {
            density: MlpLayout::new(
                vec![grid.output_width(), PROPOSAL_HIDDEN_WIDTH, 1],
                Activation::Relu,
                Activation::ClampedExp,
                false,
            ),
            grid: HashGridLayout::new(&grid),
            density_scale: PROPOSAL_INIT_DENSITY,
        }
    }

    pub fn with_precision(mut self, precision: Precision) -> Self {
        self.density = self.density.with_precision(precision);
        self
    }

    pub fn grid_range(&self) -> Range<usize> {
        0..self.grid.param_count()
    }

    pub fn density_range(&self) -> Range<usize> {
        let start = self.grid.param_count();
        start..start + self.density.param_count()
    }

    pub fn param_count(&self) -> usize {
        self.density_range().end
    }

    /// Initial parameters as Instant-NGP's field's: the grid's entries
    /// uniform in ±1e-4, the network from its own seed.
    pub fn init_params(&self, seed: u64) -> Vec<f32> {
        let mut params = self.grid.init_params(seed);
        params.extend(self.density.init_params(seed ^ 0x64656e73));
        params
    }

    pub fn layout(&self) -> ParamLayout {
        ParamLayout::new()
            .with("hash grid", self.grid.param_count(), Update::Sparse)
            .with(
                "density network",
                self.density.param_count(),
                Update::Dense { l2: true },
            )
    }
}

impl MlpLayout {
    /// Instant-NGP's density network: hash features → hidden ReLU layers →
    /// the density output (linear; the first output is log-density, the
    /// caller applies the exponential). No biases, as in tiny-cuda-nn's
    /// fully fused MLP.
    pub fn ngp_density(network: &NetworkConfig, grid: &HashGridConfig) -> Self {
        let mut widths = vec![grid.output_width()];
        widths.extend(std::iter::repeat_n(
            network.density_hidden_width,
            network.density_hidden_layers,
        ));
        widths.push(network.density_output_width);
        Self::new(widths, Activation::Relu, Activation::None, false)
    }

    /// Instant-NGP's colour network: density outputs and spherical
    /// harmonics → hidden ReLU layers → RGB through a sigmoid; no biases.
    pub fn ngp_colour(network: &NetworkConfig) -> Self {
        let mut widths = vec![network.density_output_width + network.sh_coefficients()];
        widths.extend(std::iter::repeat_n(
            network.colour_hidden_width,
            network.colour_hidden_layers,
        ));
        widths.push(3);
        Self::new(widths, Activation::Relu, Activation::Sigmoid, false)
    }
}

/// The parts of the model that do not change during training: the hash
/// grid's and the networks' shapes, the network constants and the scene's
/// unit-cube mapping. Both engines build Instant-NGP's field from these.
#[derive(Debug, Clone)]
pub struct NgpShape {
    pub grid: HashGridLayout,
    pub density: MlpLayout,
    pub colour: MlpLayout,
    pub network: NetworkConfig,
    pub mapping: UnitCubeMapping,
    /// σ = `density_scale` · exp(x) of the density network's first output
    /// x: 1 as in the paper, [`PROPOSAL_INIT_DENSITY`] in the contracted
    /// space.
    pub density_scale: f32,
    /// Per-image appearance embeddings, appended to the colour network's
    /// input after the spherical harmonics; `None` without.
    pub appearance: Option<AppearanceShape>,
}

impl NgpShape {
    pub fn for_scene(scene: &Scene) -> Self {
        Self::with_grid(scene, HashGridConfig::paper(scene.unit_cube.aabb_scale))
    }

    /// The field in the contracted cube: the grid spans it (extent 1, the
    /// cube mapped onto [0, 1]³) at the paper's N_max 2048, as nerfacto's
    /// (`max_res` 2048, 2^19 entries, 16 levels).
    pub fn contracted(scene: &Scene) -> Self {
        Self {
            density_scale: PROPOSAL_INIT_DENSITY,
            ..Self::with_grid(scene, HashGridConfig::paper(1.0))
        }
    }

    fn with_grid(scene: &Scene, grid_config: HashGridConfig) -> Self {
        let network = NetworkConfig::PAPER;
        Self {
            grid: HashGridLayout::new(&grid_config),
            density: MlpLayout::ngp_density(&network, &grid_config),
            colour: MlpLayout::ngp_colour(&network),
            network,
            mapping: scene.unit_cube,
            density_scale: 1.0,
            appearance: None,
        }
    }

    /// The same field with a vector per training image of `appearance`
    /// in its colour network's input ([16 density outputs | 16 SH |
    /// 32 appearance]), or without (`None`).
    pub fn with_appearance(mut self, appearance: Option<AppearanceShape>) -> Self {
        let network = &self.network;
        self.colour.widths[0] = network.density_output_width
            + network.sh_coefficients()
            + appearance.map_or(0, |a| a.width);
        self.appearance = appearance;
        self
    }

    /// The same model with its networks' products at `precision`.
    pub fn with_precision(mut self, precision: Precision) -> Self {
        self.density = self.density.with_precision(precision);
        self.colour = self.colour.with_precision(precision);
        self
    }

    /// Multiply-adds of the two networks per sample in one forward pass
    /// (the hash encoding's lookups not counted).
    pub fn macs_per_sample(&self) -> usize {
        self.density.macs_per_row() + self.colour.macs_per_row()
    }

    /// Multiply-adds per sample of σ alone: the density network's hidden
    /// layers and its σ output.
    pub fn density_macs_per_sample(&self) -> usize {
        let widths = &self.density.widths;
        widths.windows(2).map(|w| w[0] * w[1]).sum::<usize>()
            - widths[widths.len() - 2] * (widths[widths.len() - 1] - 1)
    }

    pub fn grid_range(&self) -> Range<usize> {
        0..self.grid.param_count()
    }

    pub fn density_range(&self) -> Range<usize> {
        let start = self.grid.param_count();
        start..start + self.density.param_count()
    }

    pub fn colour_range(&self) -> Range<usize> {
        let start = self.density_range().end;
        start..start + self.colour.param_count()
    }

    /// The appearance embeddings, after the colour network (empty without).
    pub fn appearance_range(&self) -> Range<usize> {
        let start = self.colour_range().end;
        start..start + self.appearance.map_or(0, |a| a.param_count())
    }

    pub fn param_count(&self) -> usize {
        self.appearance_range().end
    }

    /// Initial parameters: the grid's entries uniform in ±1e-4 (paper,
    /// section 4), each network from its own seed, the appearance
    /// embeddings from theirs.
    pub fn init_params(&self, seed: u64) -> Vec<f32> {
        let mut params = self.grid.init_params(seed);
        params.extend(self.density.init_params(seed ^ 0x64656e73));
        params.extend(self.colour.init_params(seed ^ 0x636f6c6f));
        if let Some(appearance) = &self.appearance {
            params.extend(appearance.init_params(seed ^ 0x6170_7065));
        }
        assert_eq!(params.len(), self.param_count());
        params
    }

    /// The parameters part by part: the grid sparse, the networks dense
    /// with weight decay, the appearance embeddings dense without.
    pub fn layout(&self) -> ParamLayout {
        let dense = Update::Dense { l2: true };
        let layout = ParamLayout::new()
            .with("hash grid", self.grid.param_count(), Update::Sparse)
            .with("density network", self.density.param_count(), dense)
            .with("colour network", self.colour.param_count(), dense);
        match &self.appearance {
            Some(appearance) => layout.with(
                APPEARANCE_PART,
                appearance.param_count(),
                Update::Dense { l2: false },
            ),
            None => layout,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn growth_factor_reaches_finest_resolution() {
        let grid = HashGridConfig::paper(1.0);
        let b = grid.growth_factor();
        let finest = grid.base_resolution as f64 * b.powi(grid.levels as i32 - 1);
        assert!((finest - 2048.0).abs() < 1e-6);
        // Paper, table 1 footnote: b ≈ 1.38 for N_max 2048, L 16.
        assert!((b - 1.3819).abs() < 1e-3, "{b}");
    }

    #[test]
    fn learning_rate_decays_in_steps() {
        let o = OptimiserConfig::PAPER;
        assert_eq!(o.learning_rate_at(29_999), 1e-2);
        assert!((o.learning_rate_at(30_000) - 3.3e-3).abs() < 1e-9);
        assert!((o.learning_rate_at(39_999) - 3.3e-3).abs() < 1e-9);
        assert!((o.learning_rate_at(40_000) - 1e-2 * 0.33 * 0.33).abs() < 1e-9);
    }

    #[test]
    fn cascades_cover_aabb_scale() {
        assert_eq!(OccupancyConfig::cascades(1.0), 1);
        assert_eq!(OccupancyConfig::cascades(16.0), 5);
        assert_eq!(OccupancyConfig::cascades(3.0), 3);
    }
}
