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
}

/// A fresh model of `kind` for `scene` on the chosen engine.
pub fn build_model(
    kind: ModelKind,
    engine: EngineChoice,
    scene: &Scene,
    settings: &ModelSettings,
) -> Result<Box<dyn RadianceModel>, String> {
    match (kind, engine.kind) {
        (ModelKind::Ngp, EngineKind::Cpu) => Ok(Box::new(crate::engine::cpu::ngp::CpuNgp::new(
            scene,
            settings.seed,
            settings.loss,
        ))),
        (ModelKind::Ngp, EngineKind::Gpu) => {
            let context = engine
                .gpu
                .ok_or("the gpu engine was chosen without a gpu context")?;
            crate::engine::gpu::ngp::GpuNgp::new(context, scene, settings.seed, settings.loss)
                .map(|model| Box::new(model) as Box<dyn RadianceModel>)
                .map_err(|e| format!("building Instant-NGP on the gpu engine: {e}"))
        }
    }
}
