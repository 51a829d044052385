//! The training loop: batches, schedules, the optimiser, the occupancy grid,
//! evaluation, checkpoints and events.

pub mod eval;
pub mod kept;
pub mod lock;
pub mod log;
pub mod run;
pub mod trainer;

// The model layer's modules, under their former paths (the app, the
// command line and the tests still name them so).
pub use crate::model::{self, batch, checkpoint};

use crate::engine::cpu::dense::Precision;
use crate::engine::{EngineChoice, EngineKind};
use crate::field::ModelKind;
use crate::field::nerf::Sampling;
use crate::field::ngp::LossKind;
use crate::model::RadianceModel;
use crate::scene::Scene;

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
    /// How the cpu engine computes the networks' products (the gpu engine
    /// computes in f32).
    pub precision: Precision,
}

/// How a model is built on each engine: the only place a model meets the
/// engines' drivers, one row per model in [`BUILDERS`], so a new model is
/// its field files and a row here and in [`crate::field::MODELS`], not an
/// arm in every `match`.
pub struct ModelBuilder {
    pub kind: ModelKind,
    /// The model on the `cpu` engine.
    pub cpu: fn(&Scene, &ModelSettings) -> Box<dyn RadianceModel>,
    /// The model on the `gpu` engine, sharing the context's device.
    pub gpu: GpuBuilder,
}

/// Builds a model on the `gpu` engine with the context's device, or says
/// why it cannot.
pub type GpuBuilder = fn(
    crate::engine::gpu::GpuContext,
    &Scene,
    &ModelSettings,
) -> Result<Box<dyn RadianceModel>, String>;

/// Every model's builders, in [`ModelKind`]'s order.
pub const BUILDERS: [ModelBuilder; crate::field::MODELS.len()] = [
    ModelBuilder {
        kind: ModelKind::Ngp,
        cpu: |scene, settings| Box::new(cpu_ngp(scene, settings)),
        gpu: |context, scene, settings| {
            let shape = crate::engine::cpu::fields::ngp::NgpShape::for_scene(scene);
            let (seed, loss, batch) = (settings.seed, settings.loss, settings.batch_samples);
            gpu_ngp_with_shape(context, scene, shape, seed, loss, batch)
                .map(|model| Box::new(model) as Box<dyn RadianceModel>)
        },
    },
    ModelBuilder {
        kind: ModelKind::Nerf,
        cpu: |scene, settings| Box::new(cpu_nerf(scene, settings)),
        gpu: |context, scene, settings| {
            gpu_nerf(context, scene, settings)
                .map(|model| Box::new(model) as Box<dyn RadianceModel>)
        },
    },
    ModelBuilder {
        kind: ModelKind::MipNerf,
        cpu: |scene, settings| {
            let shape = crate::engine::cpu::fields::nerf::NerfShape::mipnerf();
            Box::new(cpu_mipnerf_with_shape(scene, settings, &shape))
        },
        gpu: |context, scene, settings| {
            let shape = crate::engine::cpu::fields::nerf::NerfShape::mipnerf();
            gpu_mipnerf_with_shape(context, scene, settings, &shape)
                .map(|model| Box::new(model) as Box<dyn RadianceModel>)
        },
    },
];

impl ModelBuilder {
    /// The row of `kind` in [`BUILDERS`].
    pub fn of(kind: ModelKind) -> &'static ModelBuilder {
        &BUILDERS[kind as usize]
    }
}

/// A fresh model of `kind` for `scene` on the chosen engine.
pub fn build_model(
    kind: ModelKind,
    engine: EngineChoice,
    scene: &Scene,
    settings: &ModelSettings,
) -> Result<Box<dyn RadianceModel>, String> {
    let builder = ModelBuilder::of(kind);
    match engine.kind {
        EngineKind::Cpu => Ok((builder.cpu)(scene, settings)),
        EngineKind::Gpu => {
            let context = engine
                .gpu
                .ok_or("the gpu engine was chosen without a gpu context")?;
            (builder.gpu)(context, scene, settings)
                .map_err(|e| format!("building {} on the gpu engine: {e}", kind.name()))
        }
    }
}

/// Instant-NGP on the `cpu` engine: its field ([`NgpShape`], the networks'
/// products at the settings' precision) on the generic driver with its
/// recipe. `batch_samples` replaces the paper's 2^18 samples per batch.
///
/// [`NgpShape`]: crate::engine::cpu::fields::ngp::NgpShape
pub fn cpu_ngp(scene: &Scene, settings: &ModelSettings) -> crate::engine::cpu::model::CpuModel {
    let shape = crate::engine::cpu::fields::ngp::NgpShape::for_scene(scene)
        .with_precision(settings.precision);
    cpu_ngp_with_shape(
        scene,
        shape,
        settings.seed,
        settings.loss,
        settings.batch_samples,
    )
}

/// [`cpu_ngp`] with parts of another size than the paper's (tests use a
/// small hash table, as they use small NeRF networks).
pub fn cpu_ngp_with_shape(
    scene: &Scene,
    shape: crate::engine::cpu::fields::ngp::NgpShape,
    seed: u64,
    loss: LossKind,
    batch_samples: Option<usize>,
) -> crate::engine::cpu::model::CpuModel {
    let recipe = crate::field::ngp::recipe(scene.unit_cube.aabb_scale);
    cpu_ngp_with_recipe(scene, shape, recipe, seed, loss, batch_samples)
}

/// [`cpu_ngp_with_shape`] with another recipe than the paper's (tests use
/// a coarser occupancy grid).
pub fn cpu_ngp_with_recipe(
    scene: &Scene,
    shape: crate::engine::cpu::fields::ngp::NgpShape,
    recipe: crate::field::common::Recipe,
    seed: u64,
    loss: LossKind,
    batch_samples: Option<usize>,
) -> crate::engine::cpu::model::CpuModel {
    use crate::engine::cpu::fields::Field;
    use crate::engine::cpu::fields::ngp::NgpField;
    let fields: Vec<Box<dyn Field>> = vec![Box::new(NgpField::new(shape))];
    crate::engine::cpu::model::CpuModel::new(
        ngp_identity(),
        recipe,
        fields,
        scene,
        seed,
        loss,
        batch_samples.map(crate::field::common::BatchSize::Samples),
    )
}

/// Instant-NGP on the `gpu` engine: its field
/// ([`crate::engine::gpu::fields::ngp::GpuNgpField`]) on the generic driver
/// with its recipe, the gpu twin of [`cpu_ngp_with_shape`] (the same
/// initial parameters, layout and checkpoints).
pub fn gpu_ngp_with_shape(
    context: crate::engine::gpu::GpuContext,
    scene: &Scene,
    shape: crate::engine::cpu::fields::ngp::NgpShape,
    seed: u64,
    loss: LossKind,
    batch_samples: Option<usize>,
) -> Result<crate::engine::gpu::model::GpuModel, String> {
    let recipe = crate::field::ngp::recipe(scene.unit_cube.aabb_scale);
    gpu_ngp_with_recipe(context, scene, shape, recipe, seed, loss, batch_samples)
}

/// [`gpu_ngp_with_shape`] with another recipe than the paper's (tests use
/// a coarser occupancy grid).
pub fn gpu_ngp_with_recipe(
    context: crate::engine::gpu::GpuContext,
    scene: &Scene,
    shape: crate::engine::cpu::fields::ngp::NgpShape,
    recipe: crate::field::common::Recipe,
    seed: u64,
    loss: LossKind,
    batch_samples: Option<usize>,
) -> Result<crate::engine::gpu::model::GpuModel, String> {
    use crate::engine::cpu::fields::Field;
    use crate::engine::cpu::fields::ngp::NgpField;
    use crate::engine::gpu::fields::GpuField;
    use crate::engine::gpu::fields::ngp::GpuNgpField;
    let cpu_fields: Vec<Box<dyn Field>> = vec![Box::new(NgpField::new(shape.clone()))];
    let (params, ranges) = crate::engine::cpu::model::init_field_params(&cpu_fields, seed);
    let layout = crate::engine::cpu::model::model_layout(&cpu_fields);
    crate::engine::gpu::model::GpuModel::new(
        context,
        ngp_identity(),
        recipe,
        params,
        ranges,
        layout,
        |context, _, capacity| {
            GpuNgpField::new(context, &shape, capacity).map(|f| Box::new(f) as Box<dyn GpuField>)
        },
        scene,
        seed,
        loss,
        batch_samples.map(crate::field::common::BatchSize::Samples),
    )
}

/// Instant-NGP on the `gpu` engine with the paper's parts, batches of
/// `batch_samples` samples (tests use few).
pub fn gpu_ngp(
    context: crate::engine::gpu::GpuContext,
    scene: &Scene,
    seed: u64,
    loss: LossKind,
    batch_samples: usize,
) -> Result<crate::engine::gpu::model::GpuModel, String> {
    gpu_ngp_with_shape(
        context,
        scene,
        crate::engine::cpu::fields::ngp::NgpShape::for_scene(scene),
        seed,
        loss,
        Some(batch_samples),
    )
}

/// What Instant-NGP's models are called, in the viewer and in checkpoints.
pub fn ngp_identity() -> crate::engine::cpu::model::ModelIdentity {
    crate::engine::cpu::model::ModelIdentity {
        name: ModelKind::Ngp.name(),
        key: ModelKind::Ngp.key(),
        sampling: None,
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
    let recipe = nerf_recipe(scene, settings);
    cpu_model_of_nerf_fields(nerf_identity(settings), recipe, scene, settings, shape)
}

/// Mip-NeRF on the `cpu` engine with networks of `shape` (the paper's is
/// [`crate::engine::cpu::fields::nerf::NerfShape::mipnerf`]).
pub fn cpu_mipnerf_with_shape(
    scene: &Scene,
    settings: &ModelSettings,
    shape: &crate::engine::cpu::fields::nerf::NerfShape,
) -> crate::engine::cpu::model::CpuModel {
    cpu_model_of_nerf_fields(
        mipnerf_identity(settings),
        mipnerf_recipe(scene, settings),
        scene,
        settings,
        shape,
    )
}

/// A model of the recipe's levels over fields of NeRF's shape (NeRF and
/// Mip-NeRF are such models; tests build them with other recipes too).
pub fn cpu_model_of_nerf_fields(
    identity: crate::engine::cpu::model::ModelIdentity,
    recipe: crate::field::common::Recipe,
    scene: &Scene,
    settings: &ModelSettings,
    shape: &crate::engine::cpu::fields::nerf::NerfShape,
) -> crate::engine::cpu::model::CpuModel {
    use crate::engine::cpu::fields::Field;
    use crate::engine::cpu::fields::nerf::NerfField;
    let fields: Vec<Box<dyn Field>> = (0..recipe.fields)
        .map(|_| {
            let shape = shape.clone().with_precision(settings.precision);
            Box::new(NerfField::new(shape)) as Box<dyn Field>
        })
        .collect();
    let batch = batch_of(&recipe, settings);
    crate::engine::cpu::model::CpuModel::new(
        identity,
        recipe,
        fields,
        scene,
        settings.seed,
        settings.loss,
        batch,
    )
}

/// NeRF on the `gpu` engine, with the cpu engine's recipe, parameters and
/// checkpoints (see [`cpu_nerf`]).
pub fn gpu_nerf(
    context: crate::engine::gpu::GpuContext,
    scene: &Scene,
    settings: &ModelSettings,
) -> Result<crate::engine::gpu::model::GpuModel, String> {
    gpu_nerf_with_shape(
        context,
        scene,
        settings,
        &crate::engine::cpu::fields::nerf::NerfShape::paper(),
    )
}

/// [`gpu_nerf`] with networks of another size (tests use small ones).
pub fn gpu_nerf_with_shape(
    context: crate::engine::gpu::GpuContext,
    scene: &Scene,
    settings: &ModelSettings,
    shape: &crate::engine::cpu::fields::nerf::NerfShape,
) -> Result<crate::engine::gpu::model::GpuModel, String> {
    gpu_model_of_nerf_fields(
        context,
        nerf_identity(settings),
        nerf_recipe(scene, settings),
        scene,
        settings,
        shape,
    )
}

/// Mip-NeRF on the `gpu` engine with networks of `shape`, with the cpu
/// engine's recipe, parameters and checkpoints (see
/// [`cpu_mipnerf_with_shape`]).
pub fn gpu_mipnerf_with_shape(
    context: crate::engine::gpu::GpuContext,
    scene: &Scene,
    settings: &ModelSettings,
    shape: &crate::engine::cpu::fields::nerf::NerfShape,
) -> Result<crate::engine::gpu::model::GpuModel, String> {
    gpu_model_of_nerf_fields(
        context,
        mipnerf_identity(settings),
        mipnerf_recipe(scene, settings),
        scene,
        settings,
        shape,
    )
}

/// A gpu model of the recipe's levels over fields of NeRF's shape, the gpu
/// twin of [`cpu_model_of_nerf_fields`].
pub fn gpu_model_of_nerf_fields(
    context: crate::engine::gpu::GpuContext,
    identity: crate::engine::cpu::model::ModelIdentity,
    recipe: crate::field::common::Recipe,
    scene: &Scene,
    settings: &ModelSettings,
    shape: &crate::engine::cpu::fields::nerf::NerfShape,
) -> Result<crate::engine::gpu::model::GpuModel, String> {
    use crate::engine::cpu::fields::Field;
    use crate::engine::cpu::fields::nerf::NerfField;
    use crate::engine::gpu::fields::GpuField;
    use crate::engine::gpu::fields::nerf::GpuNerfField;
    // The cpu fields give the initial parameters (the same for the same
    // seed on either engine); they hold no workspace until used.
    let cpu_fields: Vec<Box<dyn Field>> = (0..recipe.fields)
        .map(|_| Box::new(NerfField::new(shape.clone())) as Box<dyn Field>)
        .collect();
    let (params, ranges) = crate::engine::cpu::model::init_field_params(&cpu_fields, settings.seed);
    let layout = crate::engine::cpu::model::model_layout(&cpu_fields);
    let batch = batch_of(&recipe, settings).or_else(|| {
        matches!(recipe.batch, crate::field::common::BatchSize::Samples(_)).then_some(
            crate::field::common::BatchSize::Samples(
                crate::field::nerf::GPU_OCCUPANCY_SAMPLES_PER_BATCH,
            ),
        )
    });
    crate::engine::gpu::model::GpuModel::new(
        context,
        identity,
        recipe,
        params,
        ranges,
        layout,
        |context, _, capacity| {
            GpuNerfField::new(context, shape, capacity).map(|f| Box::new(f) as Box<dyn GpuField>)
        },
        scene,
        settings.seed,
        settings.loss,
        batch,
    )
}

/// NeRF's recipe for `scene` with the settings' sampler.
pub fn nerf_recipe(scene: &Scene, settings: &ModelSettings) -> crate::field::nerf::Recipe {
    crate::field::nerf::recipe(
        settings.sampling,
        scene.format == crate::scene::SceneFormat::Blender,
    )
}

/// Mip-NeRF's recipe for `scene` with the settings' sampler.
pub fn mipnerf_recipe(scene: &Scene, settings: &ModelSettings) -> crate::field::common::Recipe {
    crate::field::mipnerf::recipe(
        settings.sampling,
        scene.format == crate::scene::SceneFormat::Blender,
    )
}

/// What Mip-NeRF's models are called, in the viewer and in checkpoints.
pub fn mipnerf_identity(settings: &ModelSettings) -> crate::engine::cpu::model::ModelIdentity {
    crate::engine::cpu::model::ModelIdentity {
        name: ModelKind::MipNerf.name(),
        key: ModelKind::MipNerf.key(),
        sampling: Some(settings.sampling.name()),
    }
}

/// What NeRF's models are called, in the viewer and in checkpoints.
pub fn nerf_identity(settings: &ModelSettings) -> crate::engine::cpu::model::ModelIdentity {
    crate::engine::cpu::model::ModelIdentity {
        name: ModelKind::Nerf.name(),
        key: ModelKind::Nerf.key(),
        sampling: Some(settings.sampling.name()),
    }
}

/// The batch a `batch_samples` setting asks for: about that many samples
/// per step with either sampler (with the paper's, each level evaluates
/// its own samples, and importance samples join the previous level's).
fn batch_of(
    recipe: &crate::field::common::Recipe,
    settings: &ModelSettings,
) -> Option<crate::field::common::BatchSize> {
    use crate::field::common::BatchSize;
    let mut per_ray = 0;
    let mut level_samples = 0;
    for level in &recipe.levels {
        level_samples = level.sampler.samples_evaluated(level_samples);
        per_ray += level_samples;
    }
    settings
        .batch_samples
        .map(|samples| match settings.sampling {
            Sampling::Occupancy => BatchSize::Samples(samples),
            Sampling::Paper => BatchSize::Rays((samples / per_ray.max(1)).max(1)),
        })
}

#[cfg(test)]
mod builder_tests {
    use super::*;

    #[test]
    fn every_model_has_its_builders_in_its_row() {
        assert_eq!(BUILDERS.len(), ModelKind::ALL.len());
        for (index, kind) in ModelKind::ALL.into_iter().enumerate() {
            assert_eq!(BUILDERS[index].kind, kind, "row {index}");
            assert_eq!(ModelBuilder::of(kind).kind, kind);
        }
    }
}
