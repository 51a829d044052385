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
use crate::field::nerf::Sampling;
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
    /// NeRF's sampler (the other models have one sampler each).
    pub sampling: Sampling,
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
        (ModelKind::Nerf, EngineKind::Cpu) => Ok(Box::new(cpu_nerf(scene, settings))),
        (ModelKind::Nerf, EngineKind::Gpu) => {
            Err("NeRF is not yet built on the gpu engine: use --engine cpu".into())
        }
        (ModelKind::MipNerf, EngineKind::Cpu) => Ok(Box::new(cpu_mipnerf_with_shape(
            scene,
            settings,
            &crate::engine::cpu::fields::nerf::NerfShape::mipnerf(),
        ))),
        (ModelKind::MipNerf, EngineKind::Gpu) => {
            Err("Mip-NeRF is not yet built on the gpu engine: use --engine cpu".into())
        }
    }
}

/// NeRF on the `cpu` engine: the paper's field, one per level of the
/// recipe. A `batch_samples` setting keeps the samples per batch near it
/// with either sampler (the paper's evaluates 64 + 192 samples per ray).
pub fn cpu_nerf(scene: &Scene, settings: &ModelSettings) -> crate::engine::cpu::model::CpuModel {
    cpu_nerf_with_shape(
        scene,
        settings,
        &crate::engine::cpu::fields::nerf::NerfShape::paper(),
    )
}

/// [`cpu_nerf`] with networks of another size (tests use small ones).
pub fn cpu_nerf_with_shape(
    scene: &Scene,
    settings: &ModelSettings,
    shape: &crate::engine::cpu::fields::nerf::NerfShape,
) -> crate::engine::cpu::model::CpuModel {
    use crate::field::nerf;
    let recipe = nerf::recipe(
        settings.sampling,
        scene.format == crate::scene::SceneFormat::Blender,
    );
    cpu_model_of_nerf_fields("NeRF", "nerf", recipe, scene, settings, shape)
}

/// Mip-NeRF on the `cpu` engine with networks of `shape` (the paper's is
/// [`crate::engine::cpu::fields::nerf::NerfShape::mipnerf`]).
pub fn cpu_mipnerf_with_shape(
    scene: &Scene,
    settings: &ModelSettings,
    shape: &crate::engine::cpu::fields::nerf::NerfShape,
) -> crate::engine::cpu::model::CpuModel {
    let recipe = crate::field::mipnerf::recipe(
        settings.sampling,
        scene.format == crate::scene::SceneFormat::Blender,
    );
    cpu_model_of_nerf_fields("Mip-NeRF", "mipnerf", recipe, scene, settings, shape)
}

/// A model of the recipe's levels over fields of NeRF's shape.
fn cpu_model_of_nerf_fields(
    name: &'static str,
    key: &'static str,
    recipe: crate::field::common::Recipe,
    scene: &Scene,
    settings: &ModelSettings,
    shape: &crate::engine::cpu::fields::nerf::NerfShape,
) -> crate::engine::cpu::model::CpuModel {
    use crate::engine::cpu::fields::Field;
    use crate::engine::cpu::fields::nerf::NerfField;
    use crate::field::common::{BatchSize, SamplerKind};
    let fields: Vec<Box<dyn Field>> = (0..recipe.fields)
        .map(|_| Box::new(NerfField::new(shape.clone())) as Box<dyn Field>)
        .collect();
    // Samples per ray of the paper's levels: each level evaluates its own
    // samples, and importance samples join the previous level's.
    let mut per_ray = 0;
    let mut level_samples = 0;
    for level in &recipe.levels {
        level_samples = match level.sampler {
            SamplerKind::Stratified { count } | SamplerKind::Resample { count, .. } => count,
            SamplerKind::Importance { count, .. } => level_samples + count,
            SamplerKind::Occupancy => 0,
        };
        per_ray += level_samples;
    }
    let batch = settings
        .batch_samples
        .map(|samples| match settings.sampling {
            Sampling::Occupancy => BatchSize::Samples(samples),
            Sampling::Paper => BatchSize::Rays((samples / per_ray.max(1)).max(1)),
        });
    crate::engine::cpu::model::CpuModel::new(
        crate::engine::cpu::model::ModelIdentity {
            name,
            key,
            sampling: settings.sampling.name(),
        },
        recipe,
        fields,
        scene,
        settings.seed,
        settings.loss,
        batch,
    )
}
