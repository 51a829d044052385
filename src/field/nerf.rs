//! NeRF (Mildenhall, Srinivasan, Tancik, Barron, Ramamoorthi, Ng 2020, "NeRF:
//! Representing Scenes as Neural Radiance Fields for View Synthesis"): every
//! constant of the model, with where it comes from. "Paper" is the ECCV
//! paper; "config" is the reference code's `configs/config_lego.txt`;
//! "reference" is its `run_nerf.py` / `run_nerf_helpers.py`. Also the
//! field's shapes ([`NerfShape`]: the encodings, the trunk with its skip,
//! the colour branch and σ's activation, also Mip-NeRF's), which both
//! engines build their NeRF field from.

use super::appearance::AppearanceShape;
use super::common::{
    BatchSize, Level, LrSchedule, MarchConfig, OccupancyConfig, OptimiserConfig, RayBounds, Recipe,
    SampleShape, SamplerKind, Sampling,
};
use super::contraction::{Contraction, ContractionNorm};
use super::encoding::FrequencyEncoding;
use super::mlp::{Activation, MlpLayout, Precision};
use super::params::{APPEARANCE_PART, ParamLayout, Update};

/// Frequencies of the position encoding γ(x): 2⁰ … 2⁹ (paper, section 5.1:
/// L = 10; reference `multires` 10).
pub const POSITION_FREQUENCIES: u32 = 10;
/// Frequencies of the view-direction encoding (paper: L = 4; reference
/// `multires_views` 4).
pub const DIRECTION_FREQUENCIES: u32 = 4;
/// The reference keeps the raw input beside its sines and cosines
/// (`Embedder`, `include_input`), giving 63 and 27 inputs.
pub const ENCODING_INCLUDES_INPUT: bool = true;

/// Layers of the position trunk before σ (paper, figure 7; reference
/// `netdepth` 8).
pub const TRUNK_LAYERS: usize = 8;
/// Width of every trunk layer (reference `netwidth` 256).
pub const TRUNK_WIDTH: usize = 256;
/// The encoded position enters again after this many trunk layers (paper,
/// figure 7: "a skip connection that concatenates this input to the fifth
/// layer's activation"; reference `skips=[4]`).
pub const SKIP_AFTER_LAYERS: usize = 5;
/// The colour branch: the 256-wide feature vector and the encoded
/// direction → one 128-wide ReLU layer → RGB through a sigmoid (paper,
/// figure 7; reference `views_linears`, W // 2).
pub const COLOUR_HIDDEN_WIDTH: usize = 128;

/// Stratified samples per ray for the coarse network (paper, section 5.3:
/// Nc = 64; config `N_samples`).
pub const COARSE_SAMPLES: usize = 64;
/// Samples added from the coarse weights for the fine network (paper: Nf =
/// 128; config `N_importance`).
pub const FINE_SAMPLES: usize = 128;
/// Added to every coarse weight before the inverse-CDF sampling
/// (reference `sample_pdf`: `weights + 1e-5`, "prevent nans").
pub const IMPORTANCE_WEIGHT_PADDING: f32 = 1e-5;

/// Near and far planes of the Blender scenes (reference `load_blender`
/// branch of `run_nerf.py`: near = 2, far = 6).
pub const BLENDER_NEAR: f32 = 2.0;
pub const BLENDER_FAR: f32 = 6.0;

/// Rays per batch with the paper's sampler (config `N_rand` 1024; the paper's
/// 4096 is for its larger runs).
pub const PAPER_RAYS_PER_BATCH: usize = 1024;
/// During the first steps, rays come from the central part of each image
/// only (config `precrop_iters` 500, `precrop_frac` 0.5): on images of an
/// object against an empty background, this keeps the network from settling
/// on the background colour everywhere.
pub const CENTRE_CROP_STEPS: u32 = 500;
pub const CENTRE_CROP_FRACTION: f32 = 0.5;

/// Adam (paper, section 5.3: β₁ 0.9, β₂ 0.999, ε 1e-7, learning rate 5e-4
/// decaying exponentially to 5e-5 over training; config `lrate_decay` 500,
/// i.e. 500k steps for a factor of ten). No weight decay.
pub const OPTIMISER: OptimiserConfig = OptimiserConfig {
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

/// Marching for NeRF's occupancy sampler: twice Instant-NGP's step (2√3/1024
/// of the unit cube, 0.010 world units on a Blender scene). NeRF's
/// network is smooth at that scale (its highest frequency, 2⁹ per world
/// unit, has a period of 0.012), and one sample of the 8 × 256 network
/// costs as much as ~50 of Instant-NGP's, so the step is where the time
/// goes; the paper's own fine samples are ~0.02 apart on average.
pub const MARCH: MarchConfig = MarchConfig {
    step: 2.0 * 1.732_050_8 / 1024.0,
    max_steps: 512,
    min_transmittance: 1e-4,
    // NeRF keeps the fixed step on every scene: its occupancy grid is
    // tuned to it (see the grid's threshold below).
    cone_angle: 0.0,
};

/// The occupancy grid for NeRF: Instant-NGP's rule (EMA 0.95, threshold
/// 0.01 optical thickness, an update every 16 steps, every cell during the
/// first 256 steps) on 64³ cells instead of 128³. A density query of the
/// 8 × 256 network costs ~1.1 M FLOP (σ only), so the full grid would cost
/// 2.3 T FLOP per update, ~15 s here; 64³ cells cost an eighth of that,
/// and a cell of 1/64 of the box (0.05 world units) is still finer than
/// the thinnest parts of the Blender objects' silhouettes need to be
/// skipped around. What share of the time the updates take is printed by
/// `zrak bench throughput --model nerf`.
pub const OCCUPANCY: OccupancyConfig = OccupancyConfig {
    resolution: 64,
    decay: 0.95,
    min_optical_thickness: 0.01,
    update_interval: 16,
    warmup_steps: 256,
};

/// Samples per batch with the occupancy sampler. The paper trains on
/// 1024 rays × 192 samples = 196,608 network evaluations per step; with
/// most of empty space skipped, 2^14 samples hold 700–1000 rays once the
/// grid has tightened (lego: ~20 samples per ray), near the reference's
/// 1024 rays (config `N_rand`), at ~1/12 of the paper's cost per step.
/// Measured on lego_400 (`bench quality`, 10 minutes, mixed precision on
/// a 2-core Zen 4), against 2^15 samples (1400–1800 rays): NeRF 24.76 dB
/// against 23.26, Mip-NeRF 23.21 against 21.36, so twice the steps of
/// half the rays buy more than the larger batches.
pub const OCCUPANCY_SAMPLES_PER_BATCH: usize = 1 << 14;

/// Samples per batch with the occupancy sampler on the `gpu` engine:
/// nerfacc's NeRF on its occupancy grid (`examples/train_mlp_nerf.py`,
/// `target_sample_batch_size = 1 << 16`). The cpu's trade-off above does
/// not carry over: a GPU's step grows far less than in proportion to its
/// samples at these sizes (an H200 ran 2^14 samples of NeRF in 8.0 ms, of
/// which 1.3 ms waited on the host and 2 ms were per-step fixed work).
pub const GPU_OCCUPANCY_SAMPLES_PER_BATCH: usize = 1 << 16;

// The proposal sampler for unbounded scenes (`--sampling proposal`), for
// NeRF and Mip-NeRF: Mip-NeRF 360's (Barron et al. 2022, section 2.1 and
// its appendix). "multinerf" is its code (google-research/multinerf):
// `internal/models.py` (`Model`, `MLP`, `PropMLP`), `internal/configs.py`
// (`Config`) and `configs/360.gin`.

/// Proposal samples per ray, round by round (multinerf `Model`:
/// `num_prop_samples` 64, `num_levels` 3, i.e. two proposal rounds).
pub const PROPOSAL_SAMPLES: [usize; 2] = [64, 64];

/// The full field's samples per ray (multinerf `Model`:
/// `num_nerf_samples` 32).
pub const PROPOSAL_FIELD_SAMPLES: usize = 32;

/// The proposal MLP's layers (multinerf `configs/360.gin`:
/// `PropMLP.net_depth` 4, `PropMLP.disable_rgb`): σ only, from a linear
/// head on the last layer. Its `skip_layer` 4 puts no skip in a 4-layer
/// trunk (the input joins after layer i only where i % 4 = 0 and i > 0).
pub const PROPOSAL_LAYERS: usize = 4;

/// The proposal MLP's width as a fraction of the field's: Mip-NeRF 360's
/// is a quarter of its NeRF MLP's (`PropMLP.net_width` 256 beside
/// `NerfMLP.net_width` 1024), so 64 beside NeRF's and Mip-NeRF's 256. At
/// 256 wide here, its 128 samples a ray took three fifths of a step's
/// multiply-adds (the field's 32 the rest), where Mip-NeRF 360's take a
/// tenth; on gum-desk in 10 minutes NeRF trained 1,154 steps to 19.8 dB.
pub const PROPOSAL_WIDTH_DIVISOR: usize = 4;

/// The proposal MLP's σ = softplus(raw − 1) (multinerf `MLP`:
/// `density_activation` softplus, `density_bias` −1), for NeRF's too:
/// Mip-NeRF 360's proposal MLP, whose σ never stops learning where ReLU's
/// would die.
pub const PROPOSAL_DENSITY: DensityActivation = DensityActivation::ShiftedSoftplus { shift: 1.0 };

/// Near and far bounds of every ray in the contraction frame's units
/// (multinerf `configs/360.gin`: `Config.near` 0.2, `Config.far` 1e6, in
/// its poses normalised to about the unit cube, as the frame here is).
pub const PROPOSAL_NEAR: f32 = 0.2;
pub const PROPOSAL_FAR: f32 = 1e6;

/// λ of the interlevel loss (multinerf `Config.interlevel_loss_mult` 1).
pub const PROPOSAL_INTERLEVEL: f32 = 1.0;

/// λ of the distortion loss on the final level, in the spacing coordinate
/// s (multinerf `Config.distortion_loss_mult` 0.01).
pub const PROPOSAL_DISTORTION: f32 = 0.01;

/// Padding added to each weight before resampling. multinerf has none
/// (`resample_padding` 0) but dilates each proposal's intervals and anneals
/// the weights early in training (`dilation_multiplier`, `anneal_slope`),
/// which the engine's proposal levels do not; nerfstudio's padding of 0.01
/// (`PDFSampler`, `histogram_padding`, also Instant-NGP's here) keeps a
/// share of the samples everywhere in their place.
pub const PROPOSAL_PADDING: f32 = 0.01;

/// Rays per batch on the cpu engine. multinerf trains 16,384 rays a step
/// (`Config.batch_size`) on accelerators; a ray here costs 64 + 64
/// evaluations of the 4 × 64 proposal MLP (~0.02 M multiply-adds each)
/// and 32 of the 8 × 256 field (~0.6 M), ~22 M forward, so 256 rays cost
/// about half what the occupancy sampler's 2^14 samples of the field do
/// (~10 G): a step of a fraction of a second on two cores.
pub const PROPOSAL_RAYS_PER_BATCH: usize = 256;

/// Adam as Mip-NeRF 360 trains its unbounded scenes (multinerf
/// `configs.py`: `lr_init` 2e-3 decaying log-linearly to `lr_final` 2e-5
/// over `max_steps` 250k, after `lr_delay_steps` 512 of warm-up from
/// `lr_delay_mult` 0.01 of the rate; β₁ 0.9, β₂ 0.999, ε 1e-6). Four times
/// NeRF's rate: the proposal recipes train few rays a step for few steps,
/// and the warm-up keeps the first steps, when the proposal weights are
/// still flat, from overshooting. multinerf also clips the gradient's norm
/// (`grad_max_norm` 1e-3), which the engines' Adam does not.
pub const MIPNERF360_OPTIMISER: OptimiserConfig = OptimiserConfig {
    learning_rate: 2e-3,
    beta1: 0.9,
    beta2: 0.999,
    epsilon: 1e-6,
    l2_weights: 0.0,
    schedule: LrSchedule::LogLinearWithWarmup {
        final_rate: 2e-5,
        steps: 250_000,
        warmup_steps: 512,
        warmup_multiplier: 0.01,
    },
};

/// The contraction of `scene` for NeRF's and Mip-NeRF's fields: L2, the
/// ball of Mip-NeRF 360 (eq. 10), its frame around the training cameras.
pub fn proposal_contraction(scene: &crate::scene::Scene) -> Contraction {
    let positions: Vec<glam::Vec3> = scene
        .photographed_training_views()
        .iter()
        .map(|frame| frame.camera.position())
        .collect();
    Contraction::around_cameras(&positions, ContractionNorm::L2)
}

/// Mip-NeRF 360's levels and losses for a model of `samples` with
/// `optimiser`: two rounds of one proposal MLP (field 0; multinerf's one
/// `PropMLP` serves every proposal round) then the full field (field 1),
/// in `scene`'s contracted space.
pub fn proposal_levels(
    scene: &crate::scene::Scene,
    samples: SampleShape,
    optimiser: OptimiserConfig,
) -> Recipe {
    let contraction = proposal_contraction(scene);
    let [first, second] = PROPOSAL_SAMPLES;
    let resample = |count| SamplerKind::ProposalResample {
        count,
        padding: PROPOSAL_PADDING,
    };
    Recipe {
        levels: vec![
            Level::proposal(SamplerKind::SpacedIntervals { count: first }, 0),
            Level::proposal(resample(second), 0),
            Level::radiance(resample(PROPOSAL_FIELD_SAMPLES), 1, 1.0),
        ],
        fields: 2,
        samples,
        batch: BatchSize::Rays(PROPOSAL_RAYS_PER_BATCH),
        bounds: RayBounds::Fixed {
            near: PROPOSAL_NEAR * contraction.radius,
            far: PROPOSAL_FAR * contraction.radius,
        },
        optimiser,
        // Unused: no level marches.
        march: MARCH,
        occupancy: OCCUPANCY,
        distortion: PROPOSAL_DISTORTION,
        // The centre crop is for objects on an empty background; an
        // unbounded scene has content in every pixel (multinerf has none).
        centre_crop: None,
        contraction: Some(contraction),
        interlevel: PROPOSAL_INTERLEVEL,
    }
}

/// NeRF with the proposal sampler: Mip-NeRF 360's levels on points (each
/// interval's midpoint) and its optimiser.
pub fn proposal_recipe(scene: &crate::scene::Scene) -> Recipe {
    proposal_levels(scene, SampleShape::Points, MIPNERF360_OPTIMISER)
}

/// NeRF as trained with `sampling`, the paper's sampler or the occupancy
/// grid (the proposal sampler's is [`proposal_recipe`]: its contraction
/// needs the scene's cameras). Blender scenes sample between the
/// paper's near and far planes; other scenes between the entry and exit of
/// their box.
pub fn recipe(sampling: Sampling, blender_scene: bool) -> Recipe {
    let bounds = if blender_scene {
        RayBounds::Fixed {
            near: BLENDER_NEAR,
            far: BLENDER_FAR,
        }
    } else {
        RayBounds::SceneBox
    };
    let (levels, fields, batch) = match sampling {
        // Paper, section 5.2: a coarse and a fine network, both losses
        // counted equally (section 5.3, equation 6).
        Sampling::Paper => (
            vec![
                Level {
                    sampler: SamplerKind::Stratified {
                        count: COARSE_SAMPLES,
                    },
                    field: 0,
                    loss_weight: 1.0,
                    colour: true,
                },
                Level {
                    sampler: SamplerKind::Importance {
                        count: FINE_SAMPLES,
                        padding: IMPORTANCE_WEIGHT_PADDING,
                    },
                    field: 1,
                    loss_weight: 1.0,
                    colour: true,
                },
            ],
            2,
            BatchSize::Rays(PAPER_RAYS_PER_BATCH),
        ),
        // The grid does the coarse network's job (finding where the
        // content is), so one network remains, as nerfacc trains NeRF
        // with its occupancy estimator.
        Sampling::Occupancy => (
            vec![Level {
                sampler: SamplerKind::Occupancy,
                field: 0,
                loss_weight: 1.0,
                colour: true,
            }],
            1,
            BatchSize::Samples(OCCUPANCY_SAMPLES_PER_BATCH),
        ),
        Sampling::Proposal => unreachable!("the proposal sampler's recipe is `proposal_recipe`"),
    };
    Recipe {
        levels,
        fields,
        samples: SampleShape::Points,
        batch,
        bounds,
        optimiser: OPTIMISER,
        march: MARCH,
        occupancy: OCCUPANCY,
        // No distortion loss in the paper.
        distortion: 0.0,
        centre_crop: Some((CENTRE_CROP_STEPS, CENTRE_CROP_FRACTION)),
        contraction: None,
        interlevel: 0.0,
    }
}

// The field's shapes, which both engines build their networks from.

/// How the raw σ output becomes a density.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum DensityActivation {
    /// max(x, 0) (NeRF reference, `raw2outputs`).
    Relu,
    /// softplus(x − shift) (Mip-NeRF, `density_bias` −1).
    ShiftedSoftplus { shift: f32 },
}

impl DensityActivation {
    pub fn apply(self, x: f32) -> f32 {
        match self {
            DensityActivation::Relu => x.max(0.0),
            DensityActivation::ShiftedSoftplus { shift } => softplus(x - shift),
        }
    }

    /// dσ/dx at the raw input x.
    pub fn derivative(self, x: f32) -> f32 {
        match self {
            DensityActivation::Relu => {
                if x > 0.0 {
                    1.0
                } else {
                    0.0
                }
            }
            DensityActivation::ShiftedSoftplus { shift } => sigmoid(x - shift),
        }
    }
}

/// log(1 + eˣ) without overflow for large x or loss of digits for very
/// negative x.
fn softplus(x: f32) -> f32 {
    if x > 20.0 { x } else { x.exp().ln_1p() }
}

fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}
/// The shapes of a NeRF field.
#[derive(Debug, Clone, PartialEq)]
pub struct NerfShape {
    pub position: FrequencyEncoding,
    pub direction: FrequencyEncoding,
    /// Layers up to the skip.
    pub trunk_a: MlpLayout,
    /// Layers after the skip, ending in [σ_raw | feature].
    pub trunk_b: MlpLayout,
    pub colour: MlpLayout,
    pub density: DensityActivation,
    /// The sigmoid's output widened to [−p, 1 + p]: rgb · (1 + 2p) − p
    /// (Mip-NeRF's `rgb_padding`; 0 for NeRF).
    pub colour_padding: f32,
    /// Per-image appearance embeddings, appended to the colour network's
    /// input after the direction's encoding; `None` without.
    pub appearance: Option<AppearanceShape>,
}

impl NerfShape {
    /// The paper's field (section 5.1, figure 7).
    pub fn paper() -> Self {
        Self::new(
            FrequencyEncoding {
                frequencies: POSITION_FREQUENCIES,
                include_input: ENCODING_INCLUDES_INPUT,
            },
            FrequencyEncoding {
                frequencies: DIRECTION_FREQUENCIES,
                include_input: ENCODING_INCLUDES_INPUT,
            },
            TRUNK_WIDTH,
            TRUNK_LAYERS,
            SKIP_AFTER_LAYERS,
            COLOUR_HIDDEN_WIDTH,
            DensityActivation::Relu,
        )
    }

    /// Where each network's parameters sit: trunk A, trunk B, colour.
    pub fn ranges(&self) -> [std::ops::Range<usize>; 3] {
        let a = self.trunk_a.param_count();
        let b = a + self.trunk_b.param_count();
        let c = b + self.colour.param_count();
        [0..a, a..b, b..c]
    }

    /// The parameters part by part: network weights updated every step,
    /// with the optimiser's weight decay (none in NeRF's and Mip-NeRF's
    /// optimisers).
    pub fn layout(&self) -> ParamLayout {
        let [a, b, c] = self.ranges();
        let dense = Update::Dense { l2: true };
        let layout = ParamLayout::new()
            .with("trunk A", a.len(), dense)
            .with("trunk B", b.len(), dense)
            .with("colour network", c.len(), dense);
        match &self.appearance {
            // No weight decay on the embeddings.
            Some(appearance) => layout.with(
                APPEARANCE_PART,
                appearance.param_count(),
                Update::Dense { l2: false },
            ),
            None => layout,
        }
    }

    /// Initial parameters, each network from its own seed, the appearance
    /// embeddings from theirs.
    pub fn init_params(&self, seed: u64) -> Vec<f32> {
        let mut params = self.trunk_a.init_params(seed ^ 0x7472_756e_6b61);
        params.extend(self.trunk_b.init_params(seed ^ 0x7472_756e_6b62));
        params.extend(self.colour.init_params(seed ^ 0x636f_6c6f));
        if let Some(appearance) = &self.appearance {
            params.extend(appearance.init_params(seed ^ 0x6170_7065));
        }
        params
    }

    /// Multiply-adds of the networks per sample in one forward pass (the
    /// backward pass does twice as many).
    pub fn macs_per_sample(&self) -> usize {
        self.trunk_a.macs_per_row() + self.trunk_b.macs_per_row() + self.colour.macs_per_row()
    }

    /// Multiply-adds per sample of σ alone: trunk A, and trunk B without
    /// the feature columns of its last layer (σ inference computes its
    /// leading output only).
    pub fn density_macs_per_sample(&self) -> usize {
        let width = self.trunk_a.output_width();
        self.trunk_a.macs_per_row() + self.trunk_b.macs_per_row() - width * width
    }

    /// The same field with its networks' products at `precision`.
    pub fn with_precision(mut self, precision: Precision) -> Self {
        self.trunk_a = self.trunk_a.with_precision(precision);
        self.trunk_b = self.trunk_b.with_precision(precision);
        self.colour = self.colour.with_precision(precision);
        self
    }

    pub fn with_colour_padding(mut self, padding: f32) -> Self {
        self.colour_padding = padding;
        self
    }

    /// A field of any size (tests use small ones): `layers` trunk layers of
    /// `width`, the encoded position entering again after `skip_after`.
    pub fn new(
        position: FrequencyEncoding,
        direction: FrequencyEncoding,
        width: usize,
        layers: usize,
        skip_after: usize,
        colour_hidden: usize,
        density: DensityActivation,
    ) -> Self {
        assert!(
            (1..layers).contains(&skip_after),
            "the skip must fall inside the trunk"
        );
        let encoded = position.output_width();
        let mut a = vec![encoded];
        a.extend(std::iter::repeat_n(width, skip_after));
        let mut b = vec![width + encoded];
        b.extend(std::iter::repeat_n(width, layers - skip_after));
        b.push(1 + width);
        Self {
            position,
            direction,
            trunk_a: MlpLayout::new(a, Activation::Relu, Activation::Relu, true),
            trunk_b: MlpLayout::new(b, Activation::Relu, Activation::None, true),
            colour: MlpLayout::new(
                vec![width + direction.output_width(), colour_hidden, 3],
                Activation::Relu,
                Activation::Sigmoid,
                true,
            ),
            density,
            colour_padding: 0.0,
            appearance: None,
        }
    }

    /// The same field with a vector per training image of `appearance`
    /// in its colour network's input ([feature | γ(d) | appearance]), or
    /// without (`None`).
    pub fn with_appearance(mut self, appearance: Option<AppearanceShape>) -> Self {
        self.colour.widths[0] = self.trunk_a.output_width()
            + self.direction.output_width()
            + appearance.map_or(0, |a| a.width);
        self.appearance = appearance;
        self
    }

    /// The appearance embeddings, after the colour network (empty without).
    pub fn appearance_range(&self) -> std::ops::Range<usize> {
        let start = self.ranges()[2].end;
        start..start + self.appearance.map_or(0, |a| a.param_count())
    }
}

/// A density-only NeRF-shaped field: the proposal MLP of Mip-NeRF 360
/// (multinerf `PropMLP`): the position's encoding → ReLU layers → σ, no
/// skip and no colour.
#[derive(Debug, Clone, PartialEq)]
pub struct NerfDensityShape {
    pub position: FrequencyEncoding,
    /// Encoded position → hidden ReLU layers → raw σ (linear).
    pub network: MlpLayout,
    pub density: DensityActivation,
}

impl NerfDensityShape {
    /// `layers` ReLU layers of `width` on `position`'s encoding.
    pub fn new(
        position: FrequencyEncoding,
        width: usize,
        layers: usize,
        density: DensityActivation,
    ) -> Self {
        let mut widths = vec![position.output_width()];
        widths.extend(std::iter::repeat_n(width, layers));
        widths.push(1);
        Self {
            position,
            network: MlpLayout::new(widths, Activation::Relu, Activation::None, true),
            density,
        }
    }

    /// The proposal MLP beside the field `beside`: its position encoding
    /// (points for NeRF, frustums for Mip-NeRF), [`PROPOSAL_LAYERS`] layers
    /// a quarter of the field's width ([`PROPOSAL_WIDTH_DIVISOR`]), σ as
    /// [`PROPOSAL_DENSITY`].
    pub fn proposal(beside: &NerfShape) -> Self {
        let width = beside
            .trunk_a
            .output_width()
            .div_ceil(PROPOSAL_WIDTH_DIVISOR);
        Self::new(beside.position, width, PROPOSAL_LAYERS, PROPOSAL_DENSITY)
    }

    /// One dense network, updated every step (with the optimiser's weight
    /// decay, none in NeRF's and Mip-NeRF's).
    pub fn layout(&self) -> ParamLayout {
        ParamLayout::new().with(
            "proposal network",
            self.network.param_count(),
            Update::Dense { l2: true },
        )
    }

    pub fn init_params(&self, seed: u64) -> Vec<f32> {
        self.network.init_params(seed ^ 0x7072_6f70)
    }

    pub fn macs_per_sample(&self) -> usize {
        self.network.macs_per_row()
    }

    pub fn with_precision(mut self, precision: Precision) -> Self {
        self.network = self.network.with_precision(precision);
        self
    }
}
