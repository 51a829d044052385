//! Mip-NeRF (Barron, Mildenhall, Tancik, Hedman, Martin-Brualla, Srinivasan
//! 2021, "Mip-NeRF: A Multiscale Representation for Anti-Aliasing Neural
//! Radiance Fields"): every constant of the model, with where it comes
//! from. "Paper" is the ICCV paper; "reference" is google/mipnerf, whose
//! `internal/models.py` (`MipNerfModel`, `MLP`), `internal/mip.py`,
//! `internal/utils.py` (`Config`) and `configs/blender.gin` hold the
//! defaults the paper's Blender results were trained with.
//!
//! The network is NeRF's (8 × 256 with the skip, a 128-wide colour branch);
//! what changes is what it is given (the integrated encoding of a conical
//! frustum instead of the encoding of a point), that one network serves both
//! levels, and the sampling, activations, loss weights and schedule below.

use super::common::{
    BatchSize, Level, LrSchedule, OptimiserConfig, RayBounds, Recipe, SampleShape, SamplerKind,
};
use super::encoding::FrequencyEncoding;
use super::nerf::{
    NerfShape, {self},
};
use crate::field::common::Sampling;

/// Frequencies of the integrated position encoding: 2⁰ … 2¹⁵ (reference
/// `min_deg_point` 0, `max_deg_point` 16). No raw input: the reference's
/// `integrated_pos_enc` has none, and the damping would not apply to it.
pub const POSITION_FREQUENCIES: u32 = 16;
/// Frequencies of the view-direction encoding, with the raw direction kept
/// (reference `deg_view` 4, `pos_enc(..., append_identity=True)`).
pub const DIRECTION_FREQUENCIES: u32 = 4;

/// σ = softplus(raw + bias) (reference `density_activation` softplus,
/// `density_bias` −1): starting below zero keeps fresh networks nearly
/// transparent.
pub const DENSITY_BIAS: f32 = -1.0;
/// RGB = sigmoid(raw) · (1 + 2p) − p (reference `rgb_padding` 0.001): the
/// colour can reach 0 and 1 without the raw output running off to infinity.
pub const RGB_PADDING: f32 = 0.001;

/// Intervals per ray at each level (reference `num_samples` 128,
/// `num_levels` 2; paper, section 4).
pub const SAMPLES_PER_LEVEL: usize = 128;
/// Added to the blurred coarse weights before resampling (reference
/// `resample_padding` 0.01).
pub const RESAMPLE_PADDING: f32 = 0.01;
/// The coarse level's loss counts a tenth (paper, equation 9: λ = 0.1;
/// reference `coarse_loss_mult`).
pub const COARSE_LOSS_WEIGHT: f32 = 0.1;

/// Rays per batch with the paper's sampler. The reference trains with 4096
/// (`Config.batch_size`) for a million steps on accelerators; zrak uses
/// NeRF's 1024 (its `N_rand`) so that the two models' steps cost the same
/// per sample and compare at equal time.
pub const PAPER_RAYS_PER_BATCH: usize = 1024;

/// Adam with flax's defaults (β 0.9, 0.999, ε 1e-8; the reference's
/// `flax.optim.Adam(config.lr_init)`), no weight decay (`weight_decay_mult`
/// 0), learning rate 5e-4 → 5e-6 log-linearly over 10⁶ steps with a
/// 2500-step warm-up from 0.01 of the rate (`lr_init`, `lr_final`,
/// `max_steps`, `lr_delay_steps`, `lr_delay_mult`). The reference clips
/// gradients only when `grad_max_norm` or `grad_max_val` is set; both are 0
/// in its Blender configuration, so there is no clipping.
pub const OPTIMISER: OptimiserConfig = OptimiserConfig {
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

/// Mip-NeRF with the proposal sampler, as Mip-NeRF 360 trains it: its
/// levels (`nerf::proposal_levels`) on conical frustums, each frustum's
/// Gaussian carried through the contraction's linearisation (Mip-NeRF 360,
/// eq. 9–10), with its optimiser ([`nerf::MIPNERF360_OPTIMISER`]).
pub fn proposal_recipe(scene: &crate::scene::Scene) -> Recipe {
    nerf::proposal_levels(
        scene,
        SampleShape::ConicalFrustums,
        nerf::MIPNERF360_OPTIMISER,
    )
}

/// Mip-NeRF as trained with `sampling`: the paper's two levels of one
/// network, or one level marched through NeRF's occupancy grid (the same
/// network cost per sample, so the same grid, step and batch as NeRF's);
/// the proposal sampler's is [`proposal_recipe`].
/// Blender scenes sample between the reference's near and far planes (2 and
/// 6, `Config.near` / `far`, NeRF's); other scenes inside their box.
pub fn recipe(sampling: Sampling, blender_scene: bool) -> Recipe {
    let bounds = if blender_scene {
        RayBounds::Fixed {
            near: nerf::BLENDER_NEAR,
            far: nerf::BLENDER_FAR,
        }
    } else {
        RayBounds::SceneBox
    };
    let (levels, batch) = match sampling {
        Sampling::Paper => (
            vec![
                Level {
                    sampler: SamplerKind::Stratified {
                        count: SAMPLES_PER_LEVEL,
                    },
                    field: 0,
                    loss_weight: COARSE_LOSS_WEIGHT,
                    colour: true,
                },
                Level {
                    sampler: SamplerKind::Resample {
                        count: SAMPLES_PER_LEVEL,
                        padding: RESAMPLE_PADDING,
                    },
                    field: 0,
                    loss_weight: 1.0,
                    colour: true,
                },
            ],
            BatchSize::Rays(PAPER_RAYS_PER_BATCH),
        ),
        Sampling::Occupancy => (
            vec![Level {
                sampler: SamplerKind::Occupancy,
                field: 0,
                loss_weight: 1.0,
                colour: true,
            }],
            BatchSize::Samples(nerf::OCCUPANCY_SAMPLES_PER_BATCH),
        ),
        Sampling::Proposal => unreachable!("the proposal sampler's recipe is `proposal_recipe`"),
    };
    Recipe {
        levels,
        fields: 1,
        samples: SampleShape::ConicalFrustums,
        batch,
        bounds,
        optimiser: OPTIMISER,
        march: nerf::MARCH,
        occupancy: nerf::OCCUPANCY,
        // The reference has no centre crop (no `precrop_iters`).
        // No distortion loss in the paper.
        distortion: 0.0,
        centre_crop: None,
        contraction: None,
        interlevel: 0.0,
    }
}

impl NerfShape {
    /// Mip-NeRF's field: NeRF's networks on the integrated encoding of
    /// each frustum's Gaussian, σ = softplus(raw − 1), colour widened by
    /// 0.001 (the constants above).
    pub fn mipnerf() -> Self {
        Self::new(
            FrequencyEncoding {
                frequencies: POSITION_FREQUENCIES,
                include_input: false,
            },
            FrequencyEncoding {
                frequencies: DIRECTION_FREQUENCIES,
                include_input: true,
            },
            nerf::TRUNK_WIDTH,
            nerf::TRUNK_LAYERS,
            nerf::SKIP_AFTER_LAYERS,
            nerf::COLOUR_HIDDEN_WIDTH,
            nerf::DensityActivation::ShiftedSoftplus {
                shift: -DENSITY_BIAS,
            },
        )
        .with_colour_padding(RGB_PADDING)
    }
}
