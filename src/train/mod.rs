//! The training loop: batches, schedules, the optimiser, the occupancy grid,
//! evaluation, checkpoints and events.

pub mod batch;
pub mod checkpoint;
pub mod eval;
pub mod log;
pub mod model;
pub mod run;
pub mod trainer;

use crate::engine::{EngineChoice, EngineKind};
use crate::field::ModelKind;
use crate::field::ngp::LossKind;
use crate::scene::Scene;
use model::RadianceModel;

/// Settings every model takes.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ModelSettings {
    pub seed: u64,
    pub loss: LossKind,
    /// Samples per training batch; `None` keeps the model's paper default
    /// (2^18 for Instant-NGP). The viewer asks for fewer on the cpu engine,
    /// so a step, and the wait of a command behind it, stays short.
    pub batch_samples: Option<usize>,
}

/// A fresh model of `kind` for `scene` on the chosen engine.
pub fn build_model(
    kind: ModelKind,
    engine: EngineChoice,
    scene: &Scene,
    settings: &ModelSettings,
) -> Result<Box<dyn RadianceModel>, String> {
    match (kind, engine.kind) {
        (ModelKind::Ngp, EngineKind::Cpu) => {
            let samples = settings
                .batch_samples
                .unwrap_or(crate::field::ngp::SAMPLES_PER_BATCH);
            Ok(Box::new(
                crate::engine::cpu::ngp::CpuNgp::with_batch_samples(
                    scene,
                    settings.seed,
                    settings.loss,
                    samples,
                ),
            ))
        }
        (ModelKind::Ngp, EngineKind::Gpu) => {
            let context = engine
                .gpu
                .ok_or("the gpu engine was chosen without a gpu context")?;
            let samples = settings
                .batch_samples
                .unwrap_or(crate::field::ngp::SAMPLES_PER_BATCH);
            crate::engine::gpu::ngp::GpuNgp::with_batch_samples(
                context,
                scene,
                settings.seed,
                settings.loss,
                samples,
            )
            .map(|model| Box::new(model) as Box<dyn RadianceModel>)
            .map_err(|e| format!("building Instant-NGP on the gpu engine: {e}"))
        }
    }
}
