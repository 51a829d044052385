//! A model on the `cpu` engine as a composition of stages: per level a
//! sampler (occupancy-grid marching, stratified, or importance sampling of
//! the previous level's weights), a field, compositing and the loss; then
//! one Adam step over every field's parameters. NeRF is this driver with
//! its field ([`super::fields::nerf`]) and recipe ([`crate::field::nerf`]).
//!
//! Two ways through a step, chosen by the first level's sampler:
//!
//! - **Grid marching** (one level): the rays march through the occupancy
//!   grid; σ of every marched sample finds where each ray becomes opaque
//!   (transmittance below the march's threshold), and only the samples
//!   before that point go through the field's forward and backward passes
//!   (the compaction of instant-ngp). The grid is refreshed from the
//!   field's density on its own schedule.
//! - **Stratified then importance** (the paper's): every ray gets the same
//!   number of samples per level, so rays are processed in chunks of
//!   [`RAYS_PER_CHUNK`], each chunk's levels forward and backward in turn,
//!   gradients accumulating: the activations of a 1024-ray batch of 256
//!   samples each would not fit in memory at once.
//!
//! Parameters live in one flat vector, field after field, updated by one
//! Adam with every parameter dense (no sparse entries, no weight decay
//! unless the recipe's optimiser has it).

use std::ops::Range;
use std::time::Instant;

use glam::Vec3;
use rayon::prelude::*;

use super::composite_batch::{
    CompositeGradients, CompositeOutputs, {self},
};
use super::fields::{Appearance, AppearanceShape, Field, Gradient, gather_rows, set_len};
use super::frustum::{contracted_frustum_gaussians, frustum_gaussians};
use super::loss::loss_and_gradient;
use super::march::{MarchWorkspace, march};
use super::sampling;
use crate::engine::crop::{crop_densities, crop_ray_bounds};
use crate::engine::shared::adam::Adam;
use crate::engine::shared::camera_refinement::CameraRefinement;
use crate::engine::shared::composite::Distortion;
use crate::engine::shared::march::{
    GridSamples, MarchParams, MarchedSamples, mix_seed, render_through_grid,
};
use crate::engine::shared::occupancy::OccupancyGrid;
use crate::engine::shared::state::{CameraState, ModelHeader, ModelState, check_appearance};
use crate::field::common::{BatchSize, Coordinates, LossKind, SampleShape, SamplerKind};
use crate::field::contraction::Contraction;
use crate::field::params::ParamLayout;
use crate::model::batch::RayBatch;
use crate::model::checkpoint::Checkpoint;
use crate::model::{
    PointQuery, RadianceModel, RenderRays, RenderedPixel, Stage, StageTimes, StepStats,
};
use crate::scene::{Aabb, Scene, UnitCubeMapping};

mod fixed;
mod marched;
mod samplers;

use super::fields::fields_for;
use crate::engine::request::ModelRequest;
use crate::engine::shared::driver::*;
use fixed::*;
use samplers::{LevelSampler, level_sampler};

/// Buffers of one level of a step, reused between steps.
#[derive(Default)]
struct LevelBuffers {
    /// Per ray (fixed-count levels): sample distances and intervals.
    t: Vec<f32>,
    dt: Vec<f32>,
    /// Frustum levels: each ray's interval edges (one more than samples).
    edges: Vec<f32>,
    positions: Vec<f32>,
    /// Frustum levels: each sample's covariance diagonal.
    variances: Vec<f32>,
    directions: Vec<f32>,
    ray_offsets: Vec<u32>,
    sigma: Vec<f32>,
    rgb: Vec<f32>,
    weights: Vec<f32>,
    d_sigma: Vec<f32>,
    d_rgb: Vec<f32>,
}

/// Buffers of a step.
#[derive(Default)]
struct StepBuffers {
    origins: Vec<f32>,
    directions: Vec<f32>,
    marched: MarchedSamples,
    march: MarchWorkspace,
    world: Vec<f32>,
    sigma_marched: Vec<f32>,
    /// σ from the field's forward pass on the used samples (compositing
    /// uses the cut pass's), or on every marched sample when the forward
    /// pass finds the cut.
    sigma_forward: Vec<f32>,
    /// Colours of every marched sample, and the gradients of every marched
    /// sample's σ and colour (zero past the cut), when the forward pass
    /// finds the cut.
    rgb_marched: Vec<f32>,
    d_sigma_marched: Vec<f32>,
    d_rgb_marched: Vec<f32>,
    /// Cone radius at unit distance of each ray.
    radii: Vec<f32>,
    /// Frustum recipes: covariance diagonals of the marched samples.
    variances_marched: Vec<f32>,
    source: Vec<u32>,
    levels: Vec<LevelBuffers>,
    sampling: SamplingScratch,
    proposal: ProposalScratch,
    targets: Vec<f32>,
    backgrounds: Vec<f32>,
    rays: RayScratch,
    gradients: Vec<f32>,
    /// Camera refinement: each ray's training image, the field's input
    /// gradients (per sample) and each ray's gradients (R × 3).
    images: Vec<u32>,
    /// The last march's figures while samples are held
    /// ([`CpuModel::hold_samples`]): later steps reuse its samples.
    held_march: Option<crate::engine::shared::march::MarchStats>,
    d_positions: Vec<f32>,
    d_sample_directions: Vec<f32>,
    d_origins: Vec<f32>,
    d_directions: Vec<f32>,
    /// Each ray's training image, and each sample's (models with
    /// appearance embeddings).
    ray_images: Vec<u32>,
    sample_images: Vec<u32>,
}

/// A model on the `cpu` engine built from a recipe and its fields.
pub struct CpuModel {
    /// Identity, recipe, layout and batch, as the gpu driver holds them.
    core: DriverCore,
    fields: Vec<Box<dyn Field>>,
    params: Vec<f32>,
    adam: Adam,
    /// The occupancy grid, for recipes that march through one.
    grid: Option<OccupancyGrid>,
    mapping: UnitCubeMapping,
    bounds: Aabb,
    loss: LossKind,
    seed: u64,
    buffers: StepBuffers,
    /// Sample distances kept per (chunk, level) while samples are held
    /// (see [`Self::hold_samples`]).
    held_samples: Option<std::collections::HashMap<(usize, usize), Vec<f32>>>,
    /// Rays per chunk of fixed-count levels ([`RAYS_PER_CHUNK`] unless a
    /// test asks for fewer).
    rays_per_chunk: usize,
    /// The share of the marched samples that lay before their ray's cut in
    /// the last marched step: it chooses how the next step finds the cut
    /// (see [`Self::marched_step`]). Kept in checkpoints, so a resumed run
    /// chooses as the uninterrupted one did.
    used_fraction: f64,
    /// What rendering keeps ([`RadianceModel::set_crop`]).
    crop: Option<crate::scene::crop::CropBox>,
    /// The sampler of each fixed-count level (none for a recipe that
    /// marches through the occupancy grid).
    samplers: Vec<Box<dyn LevelSampler>>,
    /// Per level: a twin of its field ([`Field::twin`]) where an earlier
    /// proposal level evaluates the same field, so each round keeps its
    /// own activations until the proposals' backward passes; `None` where
    /// the level uses the field itself.
    twins: Vec<Option<Box<dyn Field>>>,
    /// The training images' pose corrections, where the settings ask for
    /// them and the model can learn them (see [`Self::refine_cameras`]).
    refinement: Option<CameraRefinement>,
    /// The training image whose appearance vector renders use (`None`:
    /// the mean of them all), for models with appearance embeddings.
    render_appearance: Option<usize>,
}

impl CpuModel {
    /// The model `request` asks for, on the `cpu` engine: its fields of
    /// the requested shape, with the settings' precision.
    pub fn build(request: &ModelRequest, scene: &Scene) -> Self {
        let plan = request.plan(scene, None);
        let precision = request.settings.precision;
        let shapes: Vec<_> = plan
            .shapes
            .into_iter()
            .map(|shape| shape.with_precision(precision))
            .collect();
        let fields = fields_for(&shapes);
        let settings = &request.settings;
        let mut model = Self::new(
            plan.core,
            plan.params,
            fields,
            scene,
            settings.seed,
            settings.loss,
        );
        if settings.refine_cameras {
            model.refine_cameras(scene.train.len());
        }
        model
    }

    /// Learns a pose correction for each of `images` training images with
    /// the field, where the model can: a recipe that marches through the
    /// occupancy grid, whose field gives its inputs' gradient (Instant-NGP).
    /// Elsewhere the cameras stay as given; returns whether they are
    /// refined.
    pub fn refine_cameras(&mut self, images: usize) -> bool {
        let level = self.core.recipe.levels[0];
        let refined = self.core.marches() && self.fields[level.field].keep_input_gradients(true);
        self.refinement = refined.then(|| CameraRefinement::new(images));
        refined
    }

    /// The pose corrections being learned, if any.
    pub fn camera_refinement(&self) -> Option<&CameraRefinement> {
        self.refinement.as_ref()
    }

    /// The pose corrections, writable (gradient checks).
    pub fn camera_refinement_mut(&mut self) -> Option<&mut CameraRefinement> {
        self.refinement.as_mut()
    }

    /// A fresh model of `core`'s recipe from `params` (laid out as its
    /// ranges): `fields[i]` is the field levels name by index `i`.
    pub fn new(
        core: DriverCore,
        params: Vec<f32>,
        fields: Vec<Box<dyn Field>>,
        scene: &Scene,
        seed: u64,
        loss: LossKind,
    ) -> Self {
        let recipe = &core.recipe;
        assert_eq!(fields.len(), recipe.fields, "the recipe's field count");
        assert!(
            recipe.levels.iter().all(|l| l.field < fields.len()),
            "a level names a missing field"
        );
        assert_eq!(
            params.len(),
            core.layout.len(),
            "the initial parameters' count"
        );
        let marches = core.marches();
        // Fixed-count levels: one sampler each (none when marching).
        let samplers: Vec<Box<dyn LevelSampler>> = if marches {
            Vec::new()
        } else {
            recipe
                .levels
                .iter()
                .map(|l| {
                    level_sampler(l.sampler, recipe.samples, recipe.contraction).unwrap_or_else(
                        || {
                            panic!(
                                "{:?} does not sample {:?}: importance sampling adds points, \
                                 resampling draws frustums, the proposal levels need a \
                                 contraction, and only a first and only level marches",
                                l.sampler, recipe.samples
                            )
                        },
                    )
                })
                .collect()
        };
        assert!(
            fields.iter().all(|f| f.coordinates() == Coordinates::World)
                || recipe.samples == SampleShape::Points,
            "a field of unit-cube positions takes points (frustums are placed in world units)"
        );
        assert!(
            recipe.levels.iter().filter(|l| !l.colour).all(|p| recipe
                .levels
                .iter()
                .all(|l| l.field != p.field || !l.colour)),
            "a proposal level's field serves proposal levels only: their backward passes wait \
             for the final level"
        );
        // A proposal field that serves several rounds (Mip-NeRF 360's)
        // evaluates each after the first through a twin, with activations
        // of its own: the rounds' backward passes all follow the final
        // level, each on its own round's activations, adding to the one
        // gradient of the shared parameters.
        let twins = recipe
            .levels
            .iter()
            .enumerate()
            .map(|(index, level)| {
                let shared = recipe.levels[..index]
                    .iter()
                    .any(|earlier| earlier.field == level.field);
                (!level.colour && shared).then(|| {
                    fields[level.field].twin().unwrap_or_else(|| {
                        panic!(
                            "field {} serves several proposal rounds but has no twin",
                            level.field
                        )
                    })
                })
            })
            .collect();
        let mapping = scene.unit_cube;
        let grid = core.occupancy_grid(&mapping);
        Self {
            adam: Adam::new(params.len()),
            params,
            fields,
            grid,
            mapping,
            bounds: scene.bounds,
            loss,
            seed,
            buffers: StepBuffers::default(),
            rays_per_chunk: RAYS_PER_CHUNK,
            core,
            held_samples: None,
            // Early training has no ray opaque before its last sample.
            used_fraction: 1.0,
            crop: None,
            samplers,
            twins,
            refinement: None,
            render_appearance: None,
        }
    }

    /// The table of appearance embeddings of the fields that give colour,
    /// if they have one.
    fn appearance(&self) -> Option<AppearanceShape> {
        self.fields.iter().find_map(|field| field.appearance())
    }

    /// The appearance renders use: [`Appearance::Mean`] or the chosen
    /// training image's.
    fn rendered_appearance(&self) -> Appearance<'static> {
        match self.render_appearance {
            None => Appearance::Mean,
            Some(image) => Appearance::Image(image as u32),
        }
    }

    /// The field that evaluates level `level` (of field `field`) in a
    /// step: its twin where it has one, else the field.
    fn level_field<'a>(
        fields: &'a mut [Box<dyn Field>],
        twins: &'a mut [Option<Box<dyn Field>>],
        level: usize,
        field: usize,
    ) -> &'a mut dyn Field {
        match twins.get_mut(level) {
            Some(Some(twin)) => twin.as_mut(),
            _ => fields[field].as_mut(),
        }
    }

    /// Sets the share of marched samples the last step used, which orders
    /// the next marched step's passes (σ first below 1 − D/3F, forward
    /// first above: see [`Self::marched_step`]); tests take either order
    /// with it. Each marched step sets it again.
    pub fn assume_used_fraction(&mut self, fraction: f64) {
        self.used_fraction = fraction;
    }

    /// While held, each fixed-count level reuses the sample distances it
    /// drew first, whatever the parameters are since. No gradient flows
    /// through where the importance and resampled levels put their samples
    /// (NeRF, section 5.2; Mip-NeRF's `stop_level_grad`), so a finite
    /// difference of the loss matches the step's gradient only with the
    /// samples held still. A marched step holds its samples' distances
    /// along their rays, so a gradient check of the cameras moves the
    /// samples with their rays, as the gradient does.
    pub fn hold_samples(&mut self, hold: bool) {
        self.held_samples = hold.then(Default::default);
        self.buffers.held_march = None;
    }

    /// Processes fixed-count levels in chunks of `rays` (at least 1)
    /// instead of [`RAYS_PER_CHUNK`]: the chunk index seeds the jitter, so
    /// tests of a gpu model with smaller chunks set the same here.
    pub fn set_rays_per_chunk(&mut self, rays: usize) {
        self.rays_per_chunk = rays.max(1);
    }

    pub fn params(&self) -> &[f32] {
        &self.params
    }

    /// The sample distances level `level` drew for the last chunk of the
    /// last fixed-count step: each ray's interval edges for a level of
    /// intervals, else its points' t (tests compare engines with them).
    pub fn level_distances(&self, level: usize) -> &[f32] {
        let buffers = &self.buffers.levels[level];
        if self.samplers[level].draws_intervals() {
            &buffers.edges
        } else {
            &buffers.t
        }
    }

    /// Parameters, writable (for gradient checks).
    pub fn params_mut(&mut self) -> &mut [f32] {
        &mut self.params
    }

    /// The gradient written by the last [`Self::forward_backward`].
    pub fn gradients(&self) -> &[f32] {
        &self.buffers.gradients
    }

    pub fn occupancy(&self) -> Option<&OccupancyGrid> {
        self.grid.as_ref()
    }

    /// The occupancy grid, writable (tests of empty grids).
    pub fn occupancy_mut(&mut self) -> Option<&mut OccupancyGrid> {
        self.grid.as_mut()
    }

    /// Where each field sits in the parameter vector.
    pub fn parameter_ranges(&self) -> &[Range<usize>] {
        &self.core.ranges
    }

    /// Every part of the parameters by name, with how Adam updates it.
    pub fn layout(&self) -> &ParamLayout {
        &self.core.layout
    }

    /// σ at unit-cube positions (n × 3) from the first level's field, as
    /// the occupancy grid's updates see it: for probes of where the field
    /// holds density.
    pub fn densities(&self, positions: &[f32]) -> Vec<f32> {
        let field = &self.fields[self.core.recipe.levels[0].field];
        let params = &self.params[self.core.ranges[self.core.recipe.levels[0].field].clone()];
        let mut world = Vec::new();
        let positions = match field.coordinates() {
            Coordinates::UnitCube => positions,
            Coordinates::World => {
                to_world(&self.mapping, positions, &mut world);
                &world[..]
            }
        };
        let mut sigma = vec![0f32; positions.len() / 3];
        field.density(params, positions, None, &mut sigma);
        sigma
    }

    /// How world positions become `field`'s inputs in this model.
    fn input_map(&self, field: &dyn Field) -> InputMap {
        InputMap {
            coordinates: field.coordinates(),
            mapping: self.mapping,
            contraction: self.core.recipe.contraction,
        }
    }

    /// Whether the share of samples used orders the next marched step's
    /// passes (see [`Self::marched_step`]).
    fn chooses_pass_order(&self) -> bool {
        self.grid.is_some()
            && self.fields[self.core.recipe.levels[0].field].may_find_cut_in_forward()
    }

    /// The side of the box the first field's encoding spans, where its
    /// checkpoint must match it.
    fn grid_extent(&self) -> Option<f32> {
        self.fields[self.core.recipe.levels[0].field].grid_extent()
    }

    /// Multiply-adds per sample of each level's field, forward.
    pub fn macs_per_sample(&self) -> Vec<usize> {
        self.core
            .recipe
            .levels
            .iter()
            .map(|l| self.fields[l.field].macs_per_sample())
            .collect()
    }

    /// Near and far bounds of each ray (R × 3 origins and directions).
    fn ray_bounds(
        &self,
        origins: &[f32],
        directions: &[f32],
        near: &mut Vec<f32>,
        far: &mut Vec<f32>,
    ) {
        ray_bounds(
            self.core.recipe.bounds,
            &self.bounds,
            origins,
            directions,
            near,
            far,
        );
    }

    /// Evaluates `batch` and writes the gradient of the loss with respect
    /// to every parameter (see [`Self::gradients`]), without changing any
    /// parameter. Optimiser and grid times are zero in the result.
    pub fn forward_backward(&mut self, batch: &RayBatch, step: u32) -> StepStats {
        let b = &mut self.buffers;
        b.origins.clear();
        b.directions.clear();
        b.targets.clear();
        b.backgrounds.clear();
        b.radii.clear();
        if self.core.recipe.samples == SampleShape::ConicalFrustums {
            assert_eq!(batch.radii.len(), batch.len(), "a cone radius per ray");
            b.radii.extend_from_slice(&batch.radii);
        }
        for r in 0..batch.len() {
            b.origins.extend_from_slice(&batch.origins[r].to_array());
            b.directions
                .extend_from_slice(&batch.directions[r].to_array());
            b.targets.extend_from_slice(&batch.targets[r]);
            b.backgrounds.extend_from_slice(&batch.backgrounds[r]);
        }
        if let Some(refinement) = &self.refinement {
            b.images.clear();
            b.images.extend_from_slice(&batch.images);
            // Rays of no image (a batch built without them) keep their pose.
            b.images.resize(batch.len(), u32::MAX);
            refinement.apply(&b.images, &mut b.origins, &mut b.directions);
        }
        b.ray_images.clear();
        if let Some(table) = self.fields.iter().find_map(|field| field.appearance()) {
            assert_eq!(
                batch.images.len(),
                batch.len(),
                "a model with appearance embeddings trains on rays that name their image"
            );
            assert!(
                batch
                    .images
                    .iter()
                    .all(|&image| (image as usize) < table.images),
                "a ray's image beyond the {} with embeddings",
                table.images
            );
            b.ray_images.extend_from_slice(&batch.images);
        }
        set_len(&mut b.gradients, self.params.len());
        if self.core.recipe.levels[0].sampler == SamplerKind::Occupancy {
            self.marched_step(step)
        } else {
            self.fixed_step(step)
        }
    }
}

impl RadianceModel for CpuModel {
    fn cpu_kernels(&self) -> Option<crate::model::CpuKernels> {
        self.fields
            .first()
            .map(|field| field.kernels())
            .map(|kernels| crate::model::CpuKernels {
                name: format!("{kernels:?}"),
                precision: kernels.precision().describe(),
            })
    }

    fn describe(&self) -> String {
        self.core.describe("cpu")
    }

    fn rays_for_next_batch(&self) -> usize {
        self.core.rays_for_next_batch()
    }

    fn centre_crop(&self, step: u32) -> Option<f32> {
        self.core.centre_crop(step)
    }

    fn step(&mut self, batch: &RayBatch, step: u32) -> StepStats {
        let clock = Instant::now();
        if self.grid.as_ref().is_some_and(|g| g.is_due(step)) {
            self.update_grid(step);
        }
        let grid_update = clock.elapsed().as_secs_f64();
        let mut stats = self.forward_backward(batch, step);
        stats.times[Stage::GridUpdate] = grid_update;
        let clock = Instant::now();
        self.adam.step_layout(
            &self.core.recipe.optimiser,
            &self.core.layout,
            &mut self.params,
            &self.buffers.gradients,
        );
        if let Some(refinement) = &mut self.refinement {
            refinement.step();
        }
        stats.times[Stage::Optimiser] = clock.elapsed().as_secs_f64();
        stats
    }

    fn render(&self, rays: RenderRays, out: &mut [RenderedPixel]) {
        let (origins, directions) = (rays.origins, rays.directions);
        let flat = |v: &[Vec3]| v.iter().flat_map(|x| x.to_array()).collect::<Vec<f32>>();
        match &self.grid {
            Some(grid) => {
                let level = self.core.recipe.levels[0];
                let field = &self.fields[level.field];
                let params = &self.params[self.core.ranges[level.field].clone()];
                let mapping = self.mapping;
                let frustums = self.core.recipe.samples == SampleShape::ConicalFrustums;
                let unit_cube = field.coordinates() == Coordinates::UnitCube;
                let (mut world, mut variances) = (Vec::new(), Vec::new());
                let appearance = self.rendered_appearance();
                render_through_grid(
                    grid,
                    &self.mapping,
                    origins,
                    directions,
                    rays.background,
                    &self.core.recipe.march,
                    field.inference_rows(),
                    |samples: &GridSamples, sigma, rgb| {
                        if unit_cube {
                            field.radiance(
                                params,
                                samples.positions,
                                None,
                                samples.directions,
                                appearance,
                                sigma,
                                rgb,
                            );
                            if let Some(crop) = &self.crop {
                                crop_densities(crop, &mapping, samples.positions, sigma);
                            }
                            return;
                        }
                        grid_sample_inputs(
                            samples,
                            frustums,
                            &mapping,
                            origins,
                            directions,
                            rays.radii,
                            &mut world,
                            &mut variances,
                        );
                        field.radiance(
                            params,
                            &world,
                            frustums.then_some(&variances[..]),
                            samples.directions,
                            appearance,
                            sigma,
                            rgb,
                        );
                        if let Some(crop) = &self.crop {
                            crop_densities(crop, &mapping, samples.positions, sigma);
                        }
                    },
                    out,
                );
            }
            None => self.render_fixed(
                &flat(origins),
                &flat(directions),
                rays.radii,
                rays.background,
                out,
            ),
        }
    }

    fn density_at(&self, query: PointQuery, sigma: &mut [f32]) -> Result<(), String> {
        let (positions, footprint) = (query.positions, query.footprint);
        let level = *self.core.recipe.levels.last().expect("a recipe has levels");
        let field = &self.fields[level.field];
        let params = &self.params[self.core.ranges[level.field].clone()];
        // A cube of side s as a Gaussian of the same variance per axis,
        // s²/12 (that of a uniform distribution over the side).
        let frustums = self.core.recipe.samples == SampleShape::ConicalFrustums;
        let variance = footprint * footprint / 12.0;
        let inputs = self.input_map(field.as_ref());
        let (mut world, mut variances) = (Vec::new(), Vec::new());
        for (points, sigma) in positions
            .chunks(field.inference_rows())
            .zip(sigma.chunks_mut(field.inference_rows()))
        {
            inputs.fill(
                points,
                frustums.then_some(variance),
                &mut world,
                &mut variances,
            );
            field.density(params, &world, frustums.then_some(&variances[..]), sigma);
            // Nothing in cells the occupancy grid marks empty, as the
            // renderer sees it (see the Instant-NGP model's `density_at`).
            if let Some(grid) = &self.grid {
                for (s, p) in sigma.iter_mut().zip(points) {
                    if !grid.occupied_at(self.mapping.to_unit(*p)) {
                        *s = 0.0;
                    }
                }
            }
        }
        Ok(())
    }

    fn colour_at(&self, query: PointQuery, rgb: &mut [f32]) -> Result<(), String> {
        let (positions, directions) = (query.positions, query.directions);
        let footprint = query.footprint;
        let level = *self.core.recipe.levels.last().expect("a recipe has levels");
        let field = &self.fields[level.field];
        let params = &self.params[self.core.ranges[level.field].clone()];
        let frustums = self.core.recipe.samples == SampleShape::ConicalFrustums;
        let variance = footprint * footprint / 12.0;
        let inputs = self.input_map(field.as_ref());
        let (mut world, mut flat_directions, mut variances, mut sigma) =
            (Vec::new(), Vec::new(), Vec::new(), Vec::new());
        for ((points, directions), rgb) in positions
            .chunks(field.inference_rows())
            .zip(directions.chunks(field.inference_rows()))
            .zip(rgb.chunks_mut(3 * field.inference_rows()))
        {
            inputs.fill(
                points,
                frustums.then_some(variance),
                &mut world,
                &mut variances,
            );
            flat_directions.clear();
            flat_directions.extend(directions.iter().flat_map(|d| d.to_array()));
            set_len(&mut sigma, points.len());
            field.radiance(
                params,
                &world,
                frustums.then_some(&variances[..]),
                &flat_directions,
                self.rendered_appearance(),
                &mut sigma,
                rgb,
            );
        }
        Ok(())
    }

    fn set_crop(&mut self, crop: Option<crate::scene::crop::CropBox>) -> Result<(), String> {
        self.crop = crop;
        Ok(())
    }

    fn camera_corrections(&self) -> Option<Vec<f32>> {
        self.refinement.as_ref().map(|r| r.values().to_vec())
    }

    fn appearance_images(&self) -> Option<usize> {
        self.appearance().map(|table| table.images)
    }

    fn render_with_fitted_appearance(
        &mut self,
        fit: &RayBatch,
        rays: RenderRays,
        out: &mut [RenderedPixel],
    ) -> Result<(), String> {
        use crate::field::appearance::{FIT_LEARNING_RATE, FIT_RAYS, FIT_STEPS};
        let Some(table) = self.appearance() else {
            return Err(format!("{} has no appearance embeddings", self.describe()));
        };
        if fit.is_empty() {
            return Err("no rays to fit the appearance to".into());
        }
        // Each field with a table (NeRF's coarse and fine fields both have
        // one): its table is its last part; row 0 holds the fitted vector
        // while the view is fitted and drawn, and is put back after.
        let rows: Vec<Range<usize>> = self
            .fields
            .iter()
            .zip(self.core.ranges.iter())
            .filter(|(field, _)| field.appearance().is_some())
            .map(|(_, range)| {
                let start = range.end - table.param_count();
                start..start + table.width
            })
            .collect();
        let saved: Vec<Vec<f32>> = rows
            .iter()
            .map(|r| self.params[r.clone()].to_vec())
            .collect();
        for row in &rows {
            let whole = row.start..row.start + table.param_count();
            let mean = table.mean(&self.params[whole]);
            self.params[row.clone()].copy_from_slice(&mean);
        }
        // The view is no training image: no training camera's correction.
        let refinement = self.refinement.take();
        let (mut first, mut second) = (
            vec![0f32; rows.len() * table.width],
            vec![0f32; rows.len() * table.width],
        );
        let mut rng = crate::rng::Pcg32::new(0x6e65_7266_7721, 0);
        let mut batch = RayBatch::default();
        for step in 0..FIT_STEPS {
            batch.origins.clear();
            batch.directions.clear();
            batch.targets.clear();
            batch.backgrounds.clear();
            batch.radii.clear();
            batch.images.clear();
            for _ in 0..FIT_RAYS.min(fit.len()) {
                let r = rng.below(fit.len() as u32) as usize;
                batch.origins.push(fit.origins[r]);
                batch.directions.push(fit.directions[r]);
                batch.targets.push(fit.targets[r]);
                batch.backgrounds.push(fit.backgrounds[r]);
                batch.radii.push(fit.radii.get(r).copied().unwrap_or(0.0));
                batch.images.push(0);
            }
            self.forward_backward(&batch, step);
            // Adam on the vector alone (torch's β and ε), no bias
            // correction needed past its first steps: applied anyway.
            let t = (step + 1) as i32;
            let (b1, b2) = (0.9f32, 0.999f32);
            for (k, row) in rows.iter().enumerate() {
                for i in 0..table.width {
                    let g = self.buffers.gradients[row.start + i];
                    let (m, v) = (
                        &mut first[k * table.width + i],
                        &mut second[k * table.width + i],
                    );
                    *m = b1 * *m + (1.0 - b1) * g;
                    *v = b2 * *v + (1.0 - b2) * g * g;
                    let m_hat = *m / (1.0 - b1.powi(t));
                    let v_hat = *v / (1.0 - b2.powi(t));
                    self.params[row.start + i] -= FIT_LEARNING_RATE * m_hat / (v_hat.sqrt() + 1e-8);
                }
            }
        }
        self.refinement = refinement;
        let chosen = self.render_appearance.replace(0);
        self.render(rays, out);
        self.render_appearance = chosen;
        for (row, values) in rows.iter().zip(saved) {
            self.params[row.clone()].copy_from_slice(&values);
        }
        Ok(())
    }

    fn set_render_appearance(&mut self, image: Option<usize>) -> Result<(), String> {
        let Some(table) = self.appearance() else {
            return Err(format!("{} has no appearance embeddings", self.describe()));
        };
        if let Some(image) = image.filter(|&image| image >= table.images) {
            return Err(format!(
                "no training image {image}: the model has embeddings of {}",
                table.images
            ));
        }
        self.render_appearance = image;
        Ok(())
    }

    fn save(&self) -> Checkpoint {
        ModelState {
            header: ModelHeader {
                model: self.core.identity.key.into(),
                loss: self.loss,
                seed: self.seed,
                adam_step: self.adam.step,
                samples_per_ray: self.core.batch_sizer.samples_per_ray(),
                param_count: self.params.len(),
                sampling: self.core.identity.sampling.map(Into::into),
                // Only where it chooses the next step's order.
                used_fraction: self.chooses_pass_order().then_some(self.used_fraction),
                grid_extent: self.grid_extent(),
                appearance_images: self.appearance().map(|table| table.images),
            },
            params: self.params.clone(),
            adam: self.adam.clone(),
            occupancy: self.grid.as_ref().map(|g| g.values().to_vec()),
            cameras: self.refinement.as_ref().map(|r| CameraState {
                values: r.values().to_vec(),
                adam: r.adam().clone(),
            }),
        }
        .into_checkpoint()
    }

    fn load(&mut self, checkpoint: &Checkpoint) -> Result<(), String> {
        check_appearance(checkpoint, self.appearance().map(|table| table.images))?;
        let state = ModelState::from_checkpoint(
            checkpoint,
            self.core.identity.key,
            self.params.len(),
            self.grid.as_ref().map(|g| g.values().len()),
            self.refinement.as_ref().map(|r| r.values().len()),
        )?;
        check_sampling(&state.header, &self.core.identity)?;
        if let Some(extent) = self.grid_extent() {
            state.header.check_grid_extent(extent)?;
        }
        self.params = state.params;
        self.adam = state.adam;
        if let (Some(refinement), Some(cameras)) = (self.refinement.as_mut(), state.cameras) {
            refinement.set_values(&cameras.values, Some(cameras.adam));
        }
        if let (Some(grid), Some(values)) = (self.grid.as_mut(), &state.occupancy) {
            grid.values_mut().copy_from_slice(values);
            grid.build_bitfield();
        }
        self.core
            .batch_sizer
            .set_samples_per_ray(state.header.samples_per_ray);
        self.used_fraction = state.header.used_fraction.unwrap_or(1.0);
        self.loss = state.header.loss;
        self.seed = state.header.seed;
        Ok(())
    }

    fn memory_bytes(&self) -> usize {
        let b = &self.buffers;
        let mut floats = self.params.len() * 5
            + self.grid.as_ref().map_or(0, |g| g.values().len())
            + [
                &b.origins,
                &b.directions,
                &b.world,
                &b.sigma_marched,
                &b.gradients,
                &b.marched.positions,
                &b.marched.directions,
                &b.marched.dt,
                &b.marched.t,
            ]
            .iter()
            .map(|v| v.capacity())
            .sum::<usize>();
        for lb in &b.levels {
            floats += [
                &lb.t,
                &lb.dt,
                &lb.positions,
                &lb.directions,
                &lb.sigma,
                &lb.rgb,
                &lb.weights,
                &lb.d_sigma,
                &lb.d_rgb,
            ]
            .iter()
            .map(|v| v.capacity())
            .sum::<usize>();
        }
        floats * 4
            + self
                .fields
                .iter()
                .map(|f| f.workspace_bytes())
                .sum::<usize>()
    }
}

/// Each sample's training image into `out`, its ray's of `ray_images`
/// (ray r owns samples `ray_offsets[r]..ray_offsets[r + 1]`); nothing where
/// `ray_images` is empty (a model without appearance embeddings).
fn sample_images(ray_images: &[u32], ray_offsets: &[u32], out: &mut Vec<u32>) {
    out.clear();
    if ray_images.is_empty() {
        return;
    }
    for (r, ends) in ray_offsets.windows(2).enumerate() {
        out.extend(std::iter::repeat_n(
            ray_images[r],
            (ends[1] - ends[0]) as usize,
        ));
    }
}

/// The appearance of a training pass's samples: each its ray's image where
/// the model has embeddings (`images` not empty), else none.
fn training_appearance(images: &[u32]) -> Appearance<'_> {
    if images.is_empty() {
        Appearance::None
    } else {
        Appearance::PerSample(images)
    }
}

/// How world positions become a field's inputs: through the recipe's
/// contraction where it has one (into the contracted cube, or its [0, 1]³
/// image for a field of unit-cube positions), else as they are or in the
/// scene's unit cube (Instant-NGP's hash grid).
#[derive(Debug, Clone, Copy)]
pub(super) struct InputMap {
    coordinates: Coordinates,
    mapping: UnitCubeMapping,
    contraction: Option<Contraction>,
}

impl InputMap {
    pub(super) fn position(&self, world: Vec3) -> [f32; 3] {
        match (self.contraction, self.coordinates) {
            (Some(c), Coordinates::UnitCube) => c.to_unit_cube(world).to_array(),
            (Some(c), Coordinates::World) => c.contract_world(world).to_array(),
            (None, Coordinates::World) => world.to_array(),
            (None, Coordinates::UnitCube) => self.mapping.to_unit(world).to_array(),
        }
    }

    /// The field's inputs for world `points`: their positions, and with
    /// `variance`, each point as a Gaussian of that variance per world axis
    /// (a query's footprint), whose covariance diagonal goes through the
    /// contraction's linearisation where there is one (Mip-NeRF 360, eq. 9).
    pub(super) fn fill(
        &self,
        points: &[Vec3],
        variance: Option<f32>,
        positions: &mut Vec<f32>,
        variances: &mut Vec<f32>,
    ) {
        positions.clear();
        variances.clear();
        for &p in points {
            match (variance, self.contraction) {
                (Some(v), Some(c)) => {
                    let (mean, covariance) =
                        c.contract_world_gaussian(p, glam::Mat3::from_diagonal(Vec3::splat(v)));
                    positions.extend(mean.to_array());
                    variances.extend(covariance.diagonal().to_array());
                }
                (variance, _) => {
                    positions.extend(self.position(p));
                    if let Some(v) = variance {
                        variances.extend([v; 3]);
                    }
                }
            }
        }
    }

    /// Maps world positions (n × 3) in place.
    pub(super) fn map_in_place(&self, positions: &mut [f32]) {
        if self.contraction.is_none() && self.coordinates == Coordinates::World {
            return;
        }
        positions.par_chunks_mut(3 * 1024).for_each(|chunk| {
            for p in chunk.chunks_exact_mut(3) {
                p.copy_from_slice(&self.position(Vec3::from_slice(p)));
            }
        });
    }
}
