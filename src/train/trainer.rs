//! One model training on one scene: batches in, steps out, with the
//! counters a checkpoint needs to resume exactly.

use std::sync::Arc;
use std::time::Instant;

use serde::{Deserialize, Serialize};

use crate::rng::Pcg32;
use crate::scene::Scene;

use crate::model::batch::{RayBatch, TrainingBackground, sample_rays_cropped, training_background};
use crate::model::checkpoint::Checkpoint;
use crate::model::{RadianceModel, StepStats};
use crate::scene::identity::SceneIdentity;

/// Random streams of a step, so each purpose draws independently.
const BATCH_STREAM: u64 = 1;

/// What the trainer itself stores in a checkpoint's header, beside the
/// model's own state.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct TrainerState {
    pub step: u32,
    pub train_seconds: f64,
    pub seed: u64,
    pub scene: SceneIdentity,
}

pub struct Trainer {
    pub model: Box<dyn RadianceModel>,
    pub scene: Arc<Scene>,
    /// Steps taken so far; the next step has this number.
    pub step: u32,
    /// Seconds spent inside steps (evaluation and checkpoints excluded).
    pub train_seconds: f64,
    pub seed: u64,
    background: TrainingBackground,
    batch: RayBatch,
}

impl Trainer {
    pub fn new(model: Box<dyn RadianceModel>, scene: Arc<Scene>, seed: u64) -> Self {
        let background = training_background(&scene);
        Self {
            model,
            scene,
            step: 0,
            train_seconds: 0.0,
            seed,
            background,
            batch: RayBatch::default(),
        }
    }

    /// One training step: a fresh batch drawn from (seed, step), then the
    /// model's update.
    pub fn step(&mut self) -> StepStats {
        let started = Instant::now();
        let mut rng = Pcg32::for_step(self.seed, self.step as u64, BATCH_STREAM);
        let rays = self.model.rays_for_next_batch();
        sample_rays_cropped(
            &self.scene.train,
            rays,
            self.background,
            self.model.centre_crop(self.step),
            &mut rng,
            &mut self.batch,
        );
        let stats = self.model.step(&self.batch, self.step);
        self.step += 1;
        self.train_seconds += started.elapsed().as_secs_f64();
        stats
    }

    pub fn state(&self) -> TrainerState {
        TrainerState {
            step: self.step,
            train_seconds: self.train_seconds,
            seed: self.seed,
            scene: SceneIdentity::of(&self.scene),
        }
    }

    /// The model's checkpoint with the trainer's state and `extra` (the
    /// run's configuration) added to its header.
    pub fn checkpoint(&self, extra: serde_json::Value) -> Checkpoint {
        let mut checkpoint = self.model.save();
        let model_header = std::mem::take(&mut checkpoint.header);
        checkpoint.header = serde_json::json!({
            "trainer": self.state(),
            "model": model_header,
            "run": extra,
        });
        checkpoint
    }

    /// Restores a checkpoint, refusing one made on another scene.
    pub fn restore(&mut self, checkpoint: &Checkpoint) -> Result<(), String> {
        let state: TrainerState = serde_json::from_value(checkpoint.header["trainer"].clone())
            .map_err(|e| format!("checkpoint header has no trainer state: {e}"))?;
        let here = SceneIdentity::of(&self.scene);
        if state.scene != here {
            return Err(format!(
                "the checkpoint was trained on scene {}, not on {}",
                state.scene, here
            ));
        }
        let mut model_part = checkpoint.clone();
        model_part.header = checkpoint.header["model"].clone();
        self.model.load(&model_part)?;
        self.step = state.step;
        self.train_seconds = state.train_seconds;
        self.seed = state.seed;
        Ok(())
    }
}
