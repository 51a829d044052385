//! What a model is asked for with: its kind, its settings and, for tests
//! and the viewer, a shape or recipe of its own; and what both engines'
//! drivers start from ([`ModelRequest::plan`]). Everything a model needs
//! beyond its fields (its recipe, its paper shape, its name) is its row of
//! [`crate::field::MODELS`]; [`crate::engine::build`] builds it.

use super::shared::driver::{DriverCore, ModelIdentity};
use crate::field::appearance::AppearanceShape;
use crate::field::common::{BatchSize, LossKind, Recipe, Sampling};
use crate::field::mlp::Precision;
use crate::field::{FieldShape, ModelKind, model_layout, model_params};
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
    /// The sampler, for models with a choice (NeRF's and Mip-NeRF's
    /// paper sampler or the occupancy grid); the others ignore it.
    pub sampling: Sampling,
    /// How the cpu engine computes the networks' products (the gpu engine
    /// computes in f32).
    pub precision: Precision,
    /// Learn a pose correction per training image with the field
    /// (`engine::shared::camera_refinement`; the cpu engine, on models
    /// that march through the occupancy grid with a field that gives its
    /// inputs' gradient: Instant-NGP).
    pub refine_cameras: bool,
    /// Whether the fields that give colour learn a vector per training
    /// image (NeRF in the Wild's appearance embeddings,
    /// [`crate::field::appearance`]). Off by default.
    pub appearance: bool,
}

impl ModelSettings {
    /// The model's defaults for `seed`: its paper's loss and batch, its
    /// default sampler, f32 products.
    pub fn of(kind: ModelKind, seed: u64) -> Self {
        Self {
            seed,
            loss: kind.default_loss(),
            batch_samples: None,
            sampling: kind.spec().samplings[0],
            precision: Precision::F32,
            refine_cameras: false,
            appearance: false,
        }
    }
}

/// A model to build: its kind and settings, and where a test or the viewer
/// wants other parts than the paper's, the shape of its fields or its
/// recipe.
#[derive(Debug, Clone)]
pub struct ModelRequest {
    pub kind: ModelKind,
    pub settings: ModelSettings,
    /// The fields' shape; `None` takes the model's for the scene.
    pub shape: Option<FieldShape>,
    /// The stages' recipe; `None` takes the model's for the scene and the
    /// settings' sampler.
    pub recipe: Option<Recipe>,
    /// Whether the occupancy grid's intervals count steps of the batch
    /// `zrak train` takes on the engine (the viewer, whose batch is
    /// smaller, updates after as many samples) rather than this model's
    /// own steps (tests of small batches count their steps, and so do the
    /// engines' parity tests, whose engines' batches differ).
    pub grid_paced_by_samples: bool,
}

impl ModelRequest {
    pub fn new(kind: ModelKind, settings: ModelSettings) -> Self {
        Self {
            kind,
            settings,
            shape: None,
            recipe: None,
            grid_paced_by_samples: false,
        }
    }

    /// The same model with fields of `shape` (tests use small ones).
    pub fn with_shape(mut self, shape: impl Into<FieldShape>) -> Self {
        self.shape = Some(shape.into());
        self
    }

    /// The same model with another recipe (tests use a coarser occupancy
    /// grid, or other levels).
    pub fn with_recipe(mut self, recipe: Recipe) -> Self {
        self.recipe = Some(recipe);
        self
    }

    /// The same model with its occupancy grid updated after as many
    /// samples as the recipe's intervals of `zrak train`'s batch train (see
    /// [`crate::engine::shared::occupancy::GridPace`]).
    pub fn with_grid_paced_by_samples(mut self) -> Self {
        self.grid_paced_by_samples = true;
        self
    }

    /// What both engines' drivers start from, with the fields' shape and
    /// their initial parameters. `engine_batch` is the batch in samples the
    /// engine takes where the recipe's batch is in samples and the settings
    /// name none.
    pub(crate) fn plan(&self, scene: &Scene, engine_batch: Option<usize>) -> ModelPlan {
        let spec = self.kind.spec();
        let settings = &self.settings;
        let recipe = self
            .recipe
            .clone()
            .unwrap_or_else(|| (spec.recipe)(scene, settings.sampling));
        let mut shape = self
            .shape
            .clone()
            .unwrap_or_else(|| (spec.shape)(scene, settings.sampling));
        if settings.appearance {
            // A vector per training view: each is drawn as a ray's image.
            let images = scene.train.len().max(1);
            shape = shape.with_appearance(Some(AppearanceShape::for_images(images)));
        }
        let shapes = shape.for_recipe(&recipe);
        let (params, ranges) = model_params(&shapes, settings.seed);
        let layout = model_layout(&shapes);
        let named = spec.samplings.len() > 1 && spec.unnamed_sampling != Some(settings.sampling);
        let identity = ModelIdentity {
            name: spec.name,
            key: spec.key,
            sampling: named.then(|| settings.sampling.name()),
        };
        let batch = batch_of(&recipe, settings.batch_samples.or(engine_batch));
        // Not paced by samples: the intervals count this model's steps.
        let grid_batch = if self.grid_paced_by_samples {
            batch_of(&recipe, engine_batch).or(Some(recipe.batch))
        } else {
            batch
        };
        ModelPlan {
            core: DriverCore::new(identity, recipe, layout, ranges, batch, grid_batch),
            shapes,
            params,
        }
    }
}

/// A model's parts before an engine builds it.
pub(crate) struct ModelPlan {
    pub core: DriverCore,
    /// Each field's shape, in the recipe's order.
    pub shapes: Vec<FieldShape>,
    pub params: Vec<f32>,
}

/// The batch that `samples` per step ask for, in the recipe's unit: about
/// that many samples per step with either kind of sampler (with fixed
/// counts per ray, each level evaluates its own samples, and importance
/// samples join the previous level's). `None` keeps the recipe's.
fn batch_of(recipe: &Recipe, samples: Option<usize>) -> Option<BatchSize> {
    let samples = samples?;
    Some(match recipe.batch {
        BatchSize::Samples(_) => BatchSize::Samples(samples),
        BatchSize::Rays(_) => {
            let mut per_ray = 0;
            let mut level_samples = 0;
            for level in &recipe.levels {
                level_samples = level.sampler.samples_evaluated(level_samples);
                per_ray += level_samples;
            }
            BatchSize::Rays((samples / per_ray.max(1)).max(1))
        }
    })
}

/// Why a model could not be built.
#[derive(Debug, thiserror::Error)]
pub enum BuildError {
    #[error("the gpu engine was chosen without a gpu context")]
    NoGpuContext,
    #[error("building {model} on the gpu engine: {problem}")]
    Gpu {
        model: &'static str,
        problem: String,
    },
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::field::nerf::GPU_OCCUPANCY_SAMPLES_PER_BATCH;
    use crate::scene::demo::{self, DemoConfig};

    /// The steps of `request`'s plan on an engine of `engine_batch` that
    /// update its occupancy grid, out of the first 300.
    fn update_steps(request: ModelRequest, engine_batch: Option<usize>) -> Vec<u32> {
        let scene = demo::build(&DemoConfig {
            size: 8,
            train_views: 2,
            val_views: 1,
            test_views: 1,
        });
        let plan = request.plan(&scene, engine_batch);
        let grid = plan
            .core
            .occupancy_grid(&scene.unit_cube)
            .expect("an occupancy recipe");
        (0..300).filter(|&step| grid.is_due(step)).collect()
    }

    /// A request of `kind` with its occupancy sampler and `batch_samples`.
    fn request(kind: ModelKind, batch_samples: Option<usize>) -> ModelRequest {
        let settings = ModelSettings {
            batch_samples,
            sampling: Sampling::Occupancy,
            ..ModelSettings::of(kind, 0)
        };
        ModelRequest::new(kind, settings)
    }

    /// `zrak train` (the recipe's batch, or the gpu engine's own) updates
    /// every 16 steps as it always did, paced by samples or not; the
    /// viewer's smaller batches, paced by samples, update after as many
    /// samples, so fewer times per step; a test's small batch, not paced,
    /// still updates every 16 of its steps.
    #[test]
    fn grid_updates_are_paced_by_the_batch_zrak_train_takes() {
        let every = |n: u32| (0..300).step_by(n as usize).collect::<Vec<u32>>();
        let paced = |kind, batch| request(kind, batch).with_grid_paced_by_samples();
        // Instant-NGP on the cpu engine: 2^18, and the viewer's 2^16.
        assert_eq!(update_steps(request(ModelKind::Ngp, None), None), every(16));
        assert_eq!(update_steps(paced(ModelKind::Ngp, None), None), every(16));
        assert_eq!(
            update_steps(paced(ModelKind::Ngp, Some(1 << 16)), None),
            every(64)
        );
        assert_eq!(
            update_steps(request(ModelKind::Ngp, Some(1 << 12)), None),
            every(16)
        );
        // NeRF's occupancy sampler on the gpu engine trains 2^16 samples a
        // step; the viewer on lavapipe 2^12.
        let gpu = Some(GPU_OCCUPANCY_SAMPLES_PER_BATCH);
        assert_eq!(update_steps(request(ModelKind::Nerf, None), gpu), every(16));
        assert_eq!(update_steps(paced(ModelKind::Nerf, None), gpu), every(16));
        assert_eq!(
            update_steps(paced(ModelKind::Nerf, Some(1 << 12)), gpu),
            every(256)
        );
        // On the cpu engine its recipe's 2^14.
        assert_eq!(update_steps(paced(ModelKind::Nerf, None), None), every(16));
    }
}
