//! Camera refinement's settings: nerfacto's per-image pose correction
//! (nerfstudio's `CameraOptimizer`, mode "SO3xR3"). Why a pose can be
//! learned with the field at all: BARF (Lin et al. 2021) shows that the
//! photometric loss's gradient with respect to a camera's pose points
//! towards the registration wherever the field is smooth enough to compare
//! neighbouring views, which a coarse-to-fine field is early in training.

use super::common::{LrSchedule, OptimiserConfig};

/// Adam for the pose corrections, as nerfacto trains them: the optimiser
/// group "camera_opt" of nerfstudio's `method_configs.py` (nerfstudio 1.x),
/// `AdamOptimizerConfig(lr=1e-3, eps=1e-15)` with
/// `ExponentialDecaySchedulerConfig(lr_final=1e-4, max_steps=5000)`, whose
/// rate is log-linear from lr to lr_final over max_steps and stays at
/// lr_final after; β are torch's defaults (0.9, 0.999); no weight decay
/// (nerfstudio 1.x replaced the earlier `weight_decay=1e-2` with the
/// penalties below).
pub const CAMERA_OPTIMISER: OptimiserConfig = OptimiserConfig {
    learning_rate: 1e-3,
    beta1: 0.9,
    beta2: 0.999,
    epsilon: 1e-15,
    l2_weights: 0.0,
    schedule: LrSchedule::LogLinearWithWarmup {
        final_rate: 1e-4,
        steps: 5000,
        warmup_steps: 0,
        warmup_multiplier: 1.0,
    },
};

/// The penalty on each correction's translation and rotation, added to
/// the loss as the weight times the mean over images of the vector's
/// length (nerfstudio `CameraOptimizerConfig.trans_l2_penalty` = 1e-2,
/// `rot_l2_penalty` = 1e-3, `CameraOptimizer.get_loss_dict`): it keeps
/// corrections the images do not ask for at zero.
pub const TRANSLATION_PENALTY: f32 = 1e-2;
pub const ROTATION_PENALTY: f32 = 1e-3;
