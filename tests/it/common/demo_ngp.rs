//! Instant-NGP on the demo scene as the learning test trains it, trained
//! once per process: the learning test scores it after
//! [`SHARED_STEPS`], the mesh tests train it on from there. Each test gets
//! its own model, restored from the shared checkpoint; a resumed run
//! matches an uninterrupted one bit for bit
//! (`ngp_cpu::resumed_run_matches_uninterrupted_run`), so a test that
//! trains on gets the model it would have trained from the start.

use std::sync::{Arc, Mutex};

use zrak::engine::cpu::model::CpuModel;
use zrak::engine::request::{ModelRequest, ModelSettings};
use zrak::field::ModelKind;
use zrak::field::common::{LossKind, Sampling};
use zrak::field::mlp::Precision;
use zrak::model::checkpoint::Checkpoint;
use zrak::scene::Scene;
use zrak::scene::demo::{
    DemoConfig, {self},
};
use zrak::train::trainer::Trainer;

/// The steps trained once and shared: the learning test's run.
pub const SHARED_STEPS: u32 = 250;

/// The side of the shared model's views, in pixels.
pub const SIZE: u32 = 64;

/// The shared model's settings: f32 products, seed 0, the Huber loss,
/// 2^16 samples a step, the paper's occupancy grid.
pub const SEED: u64 = 0;
pub const BATCH_SAMPLES: usize = 1 << 16;
pub const LOSS: LossKind = LossKind::Huber;

/// The demo scene as the learning tests train on it: 100 training views
/// of `size` pixels, 5 held out.
pub fn demo_scene(size: u32) -> Arc<Scene> {
    Arc::new(demo::build(&DemoConfig {
        size,
        train_views: 100,
        val_views: 5,
        test_views: 1,
    }))
}

/// The shared model trained to `steps` (at least [`SHARED_STEPS`]): the
/// first [`SHARED_STEPS`] trained by whichever test asks first (the
/// others wait for its checkpoint), the rest by the caller.
pub fn trained(steps: u32) -> Trainer {
    static SHARED: Mutex<Option<Checkpoint>> = Mutex::new(None);
    assert!(
        steps >= SHARED_STEPS,
        "the shared model has {SHARED_STEPS} steps"
    );
    let scene = demo_scene(SIZE);
    let model = CpuModel::build(
        &ModelRequest::new(
            ModelKind::Ngp,
            ModelSettings {
                seed: SEED,
                loss: LOSS,
                batch_samples: Some(BATCH_SAMPLES),
                sampling: Sampling::Occupancy,
                precision: Precision::F32,
                refine_cameras: false,
                appearance: false,
            },
        ),
        &scene,
    );
    let mut trainer = Trainer::new(Box::new(model), scene, SEED);
    {
        let mut shared = SHARED.lock().unwrap_or_else(|e| e.into_inner());
        match &*shared {
            Some(checkpoint) => trainer
                .restore(checkpoint)
                .expect("the shared checkpoint restores"),
            None => {
                while trainer.step < SHARED_STEPS {
                    trainer.step();
                }
                *shared = Some(trainer.checkpoint(serde_json::json!({})));
            }
        }
    }
    while trainer.step < steps {
        trainer.step();
    }
    trainer
}
