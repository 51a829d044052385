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

use super::adam::Adam;
use super::composite_batch::Distortion;
use super::composite_batch::{self, CompositeGradients, CompositeOutputs};
use super::fields::{Coordinates, Field, Gradient, gather_rows, set_len};
use super::frustum::{frustum_gaussian, frustum_gaussians};
use super::loss::loss_and_gradient;
use super::march::{
    BatchSizer, GridSamples, MarchParams, MarchWorkspace, MarchedSamples, march, mix_seed, mix32,
    render_through_grid,
};
use super::occupancy::OccupancyGrid;
use super::sampling;
use super::state::{ModelHeader, ModelState};
use crate::engine::crop::{crop_densities, crop_ray_bounds};
use crate::field::common::{BatchSize, RayBounds, Recipe, SampleShape, SamplerKind};
use crate::field::ngp::LossKind;
use crate::field::params::ParamLayout;
use crate::model::batch::RayBatch;
use crate::model::checkpoint::Checkpoint;
use crate::model::{RadianceModel, RenderedPixel, StageTimes, StepStats};
use crate::scene::{Aabb, Scene, UnitCubeMapping};

/// Rays per chunk of the paper's sampler: 256 rays × 192 fine samples is
/// 49k rows of activations (~0.5 GB for NeRF's networks).
pub const RAYS_PER_CHUNK: usize = 256;

/// Rows per rayon task in the element-wise passes.
const ROWS_PER_TASK: usize = 4096;

/// Names and settings that identify a model built on this driver.
#[derive(Debug, Clone)]
pub struct ModelIdentity {
    /// Shown to the user, e.g. "NeRF".
    pub name: &'static str,
    /// Stored in checkpoints, e.g. "nerf".
    pub key: &'static str,
    /// The sampler's name, stored in checkpoints ("paper", "occupancy"),
    /// for models with a choice of samplers.
    pub sampling: Option<&'static str>,
}

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
    targets: Vec<f32>,
    backgrounds: Vec<f32>,
    rays: RayScratch,
    gradients: Vec<f32>,
}

/// A model on the `cpu` engine built from a recipe and its fields.
pub struct CpuModel {
    identity: ModelIdentity,
    recipe: Recipe,
    fields: Vec<Box<dyn Field>>,
    ranges: Vec<Range<usize>>,
    /// Every field's parts, one after the other: what Adam updates how.
    layout: ParamLayout,
    params: Vec<f32>,
    adam: Adam,
    /// The occupancy grid, for recipes that march through one.
    grid: Option<OccupancyGrid>,
    batch_sizer: BatchSizer,
    mapping: UnitCubeMapping,
    bounds: Aabb,
    loss: LossKind,
    seed: u64,
    buffers: StepBuffers,
    /// Rays per batch for fixed-size batches, or samples per batch for
    /// marched ones.
    batch_size: BatchSize,
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
}

impl CpuModel {
    /// A fresh model: `fields[i]` is the field levels name by index `i`.
    /// `batch_size` replaces the recipe's batch (tests and the viewer ask
    /// for smaller ones).
    pub fn new(
        identity: ModelIdentity,
        recipe: Recipe,
        fields: Vec<Box<dyn Field>>,
        scene: &Scene,
        seed: u64,
        loss: LossKind,
        batch_size: Option<BatchSize>,
    ) -> Self {
        assert_eq!(fields.len(), recipe.fields, "the recipe's field count");
        assert!(
            recipe.levels.iter().all(|l| l.field < fields.len()),
            "a level names a missing field"
        );
        assert!(
            recipe.levels.iter().all(|l| match l.sampler {
                SamplerKind::Importance { .. } => recipe.samples == SampleShape::Points,
                SamplerKind::Resample { .. } => recipe.samples == SampleShape::ConicalFrustums,
                _ => true,
            }),
            "importance sampling adds points; resampling draws frustums"
        );
        let (params, ranges) = init_field_params(&fields, seed);
        let layout = model_layout(&fields);
        assert!(
            fields.iter().all(|f| f.coordinates() == Coordinates::World)
                || (recipe.samples == SampleShape::Points
                    && recipe.levels[0].sampler == SamplerKind::Occupancy),
            "a field of unit-cube positions takes marched points (fixed-count levels and \
             frustums are placed in world units)"
        );
        let marches = recipe.levels[0].sampler == SamplerKind::Occupancy;
        let mapping = scene.unit_cube;
        let grid = marches.then(|| {
            let mut grid = OccupancyGrid::new(
                recipe.occupancy,
                crate::field::ngp::OccupancyConfig::cascades(mapping.aabb_scale),
                // The grid stores σ · step with σ per world unit, the step
                // being Instant-NGP's smallest (√3/1024 of the unit cube)
                // whatever this recipe marches with: the occupancy threshold
                // (0.01) then means the same density for every model.
                crate::field::ngp::MarchConfig::PAPER.step / mapping.scale,
            );
            if let BatchSize::Samples(samples) = batch_size.unwrap_or(recipe.batch) {
                grid.chunk = samples;
            }
            grid
        });
        let batch_size = batch_size.unwrap_or(recipe.batch);
        let batch_sizer = BatchSizer::new(match batch_size {
            BatchSize::Samples(samples) => samples,
            BatchSize::Rays(rays) => rays,
        });
        Self {
            identity,
            adam: Adam::new(params.len()),
            params,
            ranges,
            layout,
            fields,
            grid,
            batch_sizer,
            mapping,
            bounds: scene.bounds,
            loss,
            seed,
            buffers: StepBuffers::default(),
            batch_size,
            rays_per_chunk: RAYS_PER_CHUNK,
            recipe,
            held_samples: None,
            // Early training has no ray opaque before its last sample.
            used_fraction: 1.0,
            crop: None,
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
    /// samples held still.
    pub fn hold_samples(&mut self, hold: bool) {
        self.held_samples = hold.then(Default::default);
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
        &self.ranges
    }

    /// Every part of the parameters by name, with how Adam updates it.
    pub fn layout(&self) -> &ParamLayout {
        &self.layout
    }

    /// σ at unit-cube positions (n × 3) from the first level's field, as
    /// the occupancy grid's updates see it: for probes of where the field
    /// holds density.
    pub fn densities(&self, positions: &[f32]) -> Vec<f32> {
        let field = &self.fields[self.recipe.levels[0].field];
        let params = &self.params[self.ranges[self.recipe.levels[0].field].clone()];
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

    /// Whether the share of samples used orders the next marched step's
    /// passes (see [`Self::marched_step`]).
    fn chooses_pass_order(&self) -> bool {
        self.grid.is_some() && self.fields[self.recipe.levels[0].field].may_find_cut_in_forward()
    }

    /// The side of the box the first field's encoding spans, where its
    /// checkpoint must match it.
    fn grid_extent(&self) -> Option<f32> {
        self.fields[self.recipe.levels[0].field].grid_extent()
    }

    /// Multiply-adds per sample of each level's field, forward.
    pub fn macs_per_sample(&self) -> Vec<usize> {
        self.recipe
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
            self.recipe.bounds,
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
        if self.recipe.samples == SampleShape::ConicalFrustums {
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
        set_len(&mut b.gradients, self.params.len());
        if self.recipe.levels[0].sampler == SamplerKind::Occupancy {
            self.marched_step(step)
        } else {
            self.fixed_step(step)
        }
    }

    /// A step through the occupancy grid (one level).
    fn marched_step(&mut self, step: u32) -> StepStats {
        let mut times = StageTimes::default();
        let level = self.recipe.levels[0];
        let field_range = self.ranges[level.field].clone();
        let grid = self.grid.as_ref().expect("marching recipes have a grid");
        let b = &mut self.buffers;
        let rays = b.origins.len() / 3;

        let clock = Instant::now();
        let budget = match self.batch_size {
            BatchSize::Samples(samples) => samples,
            BatchSize::Rays(_) => usize::MAX,
        };
        let params = MarchParams {
            config: self.recipe.march,
            mapping: self.mapping,
            jitter_seed: Some(mix_seed(self.seed, step)),
            sample_budget: budget,
        };
        let marched = march(
            grid,
            &b.origins,
            &b.directions,
            &params,
            &mut b.march,
            &mut b.marched,
        );
        self.batch_sizer.record(marched.rays_kept, marched.samples);
        let kept = marched.rays_kept;
        let s = marched.samples;
        let field = &self.fields[level.field];
        let unit_cube = field.coordinates() == Coordinates::UnitCube;
        if !unit_cube {
            to_world(&self.mapping, &b.marched.positions, &mut b.world);
        }
        let frustums = self.recipe.samples == SampleShape::ConicalFrustums;
        if frustums {
            // Each marched sample stands for the frustum of its step,
            // centred on it.
            let m = &b.marched;
            let scratch = &mut b.sampling;
            scratch.starts.clear();
            scratch.ends.clear();
            scratch.rays.clear();
            for r in 0..kept {
                for i in m.ray(r) {
                    scratch.starts.push((m.t[i] - 0.5 * m.dt[i]).max(0.0));
                    scratch.ends.push(m.t[i] + 0.5 * m.dt[i]);
                    scratch.rays.push(r as u32);
                }
            }
            set_len(&mut b.variances_marched, 3 * s);
            frustum_gaussians(
                &b.origins,
                &b.directions,
                &b.radii,
                &scratch.rays,
                &scratch.starts,
                &scratch.ends,
                &mut b.world,
                &mut b.variances_marched,
            );
        }
        times.march = clock.elapsed().as_secs_f64();

        // Where each ray becomes opaque (its cut) needs σ of every marched
        // sample; after it a sample's colour is never read and every
        // gradient through it is zero. Two ways to find it, chosen by the
        // share of samples the last step used:
        // - σ first: a σ-only pass over every marched sample, then the
        //   forward and backward passes on the samples before the cut;
        // - forward first: the forward pass over every marched sample finds
        //   the cut as it goes, and the backward pass runs on them all,
        //   zero past the cut.
        // Per marched sample the first costs D + 3F·u and the second 3F
        // multiply-adds (D the σ pass, F the forward pass, u the share
        // used; the backward is twice the forward), so forward first wins
        // above u = 1 − D/3F: 0.72 for NeRF's field, whose rays on a
        // Blender object use 90–100 % of their samples.
        // Both passes are counted as the networks' forward time (the
        // encodings are part of the field here).
        let clock = Instant::now();
        let (forward_macs, density_macs) =
            (field.macs_per_sample(), field.density_macs_per_sample());
        let forward_first = field.may_find_cut_in_forward()
            && self.used_fraction > 1.0 - density_macs as f64 / (3 * forward_macs) as f64;
        let field_params = &self.params[field_range.clone()];
        // The field's positions: unit-cube ones as marched, or world ones.
        let positions = if unit_cube {
            &b.marched.positions
        } else {
            &b.world
        };
        let min_transmittance = self.recipe.march.min_transmittance;
        if forward_first {
            set_len(&mut b.sigma_forward, s);
            set_len(&mut b.rgb_marched, 3 * s);
            self.fields[level.field].forward(
                field_params,
                positions,
                frustums.then_some(&b.variances_marched[..]),
                &b.marched.directions,
                &mut b.sigma_forward,
                &mut b.rgb_marched,
            );
            set_len(&mut b.rays.samples_used, kept);
            composite_batch::samples_before_cut(
                &b.sigma_forward,
                &b.marched.dt,
                &b.marched.ray_offsets[..kept + 1],
                min_transmittance,
                &mut b.rays.samples_used,
            );
        } else {
            set_len(&mut b.sigma_marched, s);
            self.fields[level.field].density_for_cut(
                field_params,
                positions,
                frustums.then_some(&b.variances_marched[..]),
                &mut b.sigma_marched,
            );
            set_len(&mut b.rays.samples_used, kept);
            composite_batch::samples_before_cut(
                &b.sigma_marched,
                &b.marched.dt,
                &b.marched.ray_offsets[..kept + 1],
                min_transmittance,
                &mut b.rays.samples_used,
            );
        }
        if b.levels.is_empty() {
            b.levels.push(LevelBuffers::default());
        }
        let lb = &mut b.levels[0];
        b.source.clear();
        lb.ray_offsets.clear();
        lb.ray_offsets.push(0);
        for (r, &count) in b.rays.samples_used.iter().enumerate() {
            let first = b.marched.ray_offsets[r];
            b.source.extend(first..first + count);
            lb.ray_offsets.push(b.source.len() as u32);
        }
        let u = b.source.len();
        gather_rows(&b.marched.dt, 1, &b.source, &mut lb.dt);
        gather_rows(&b.marched.t, 1, &b.source, &mut lb.t);
        if forward_first {
            gather_rows(&b.sigma_forward, 1, &b.source, &mut lb.sigma);
            gather_rows(&b.rgb_marched, 3, &b.source, &mut lb.rgb);
        } else {
            gather_rows(positions, 3, &b.source, &mut lb.positions);
            gather_rows(&b.marched.directions, 3, &b.source, &mut lb.directions);
            if frustums {
                gather_rows(&b.variances_marched, 3, &b.source, &mut lb.variances);
            }
            // Compositing uses the σ the cut was found with, so it stops
            // exactly where the cut said (the forward pass may differ from
            // the σ-only inference in the last bits).
            set_len(&mut b.sigma_forward, u);
            set_len(&mut lb.rgb, 3 * u);
            self.fields[level.field].forward_before_cut(
                field_params,
                &b.source,
                &lb.positions,
                frustums.then_some(&lb.variances[..]),
                &lb.directions,
                &mut b.sigma_forward,
                &mut lb.rgb,
            );
            gather_rows(&b.sigma_marched, 1, &b.source, &mut lb.sigma);
        }
        times.networks_forward = clock.elapsed().as_secs_f64();

        let clock = Instant::now();
        let distortion = (self.recipe.distortion > 0.0 && kept > 0).then(|| Distortion {
            weight_per_ray: self.recipe.distortion / kept as f32,
            distance_scale: self.mapping.diagonal_scale(),
        });
        let loss = composite_and_loss(
            lb,
            &b.targets[..3 * kept],
            &b.backgrounds[..3 * kept],
            min_transmittance,
            self.loss,
            level.loss_weight,
            distortion,
            &mut b.rays,
        );
        times.composite = clock.elapsed().as_secs_f64();

        let clock = Instant::now();
        // The one field's backward pass writes its gradient; any other
        // field's is zero.
        for (i, range) in self.ranges.iter().enumerate() {
            if i != level.field {
                b.gradients[range.clone()].fill(0.0);
            }
        }
        if forward_first {
            // The used samples' gradients back in their marched rows.
            set_len(&mut b.d_sigma_marched, s);
            set_len(&mut b.d_rgb_marched, 3 * s);
            b.d_sigma_marched.fill(0.0);
            b.d_rgb_marched.fill(0.0);
            for (k, &i) in b.source.iter().enumerate() {
                let i = i as usize;
                b.d_sigma_marched[i] = lb.d_sigma[k];
                b.d_rgb_marched[3 * i..3 * i + 3].copy_from_slice(&lb.d_rgb[3 * k..3 * k + 3]);
            }
            self.fields[level.field].backward(
                field_params,
                &b.d_sigma_marched,
                &b.d_rgb_marched,
                &mut b.gradients[field_range],
                Gradient::Overwrite,
            );
        } else {
            self.fields[level.field].backward(
                field_params,
                &lb.d_sigma,
                &lb.d_rgb,
                &mut b.gradients[field_range],
                Gradient::Overwrite,
            );
        }
        times.networks_backward = clock.elapsed().as_secs_f64();
        if s > 0 {
            self.used_fraction = u as f64 / s as f64;
        }

        let network_flops = if forward_first {
            6.0 * (forward_macs * s) as f64
        } else {
            // σ of every marched sample, then forward (2 FLOP a
            // multiply-add) and backward (twice the forward) of the used.
            2.0 * (density_macs * s) as f64 + 6.0 * (forward_macs * u) as f64
        };
        StepStats {
            loss: loss as f32,
            level_losses: [loss as f32, 0.0],
            rays: if rays == 0 { 0 } else { kept },
            samples: s,
            samples_composited: Some(u),
            times,
            network_flops,
        }
    }

    /// A step of fixed-count levels (stratified, then importance), in
    /// chunks of rays.
    fn fixed_step(&mut self, step: u32) -> StepStats {
        let mut times = StageTimes::default();
        let rays = self.buffers.origins.len() / 3;
        // Chunks and levels add to the gradient.
        self.buffers.gradients.fill(0.0);
        let mut loss = 0.0f64;
        let mut level_losses = [0f32; 2];
        let mut samples = 0usize;
        let mut network_flops = 0f64;
        let (mut near, mut far) = (Vec::new(), Vec::new());
        {
            let b = &self.buffers;
            self.ray_bounds(&b.origins, &b.directions, &mut near, &mut far);
        }
        let step_seed = mix_seed(self.seed, step);
        let per_chunk = self.rays_per_chunk;
        for (chunk, start) in (0..rays).step_by(per_chunk).enumerate() {
            let end = (start + per_chunk).min(rays);
            let chunk_rays = end - start;
            // Each chunk and level draws its own jitter.
            let seed_of = |level: usize| chunk_jitter_seed(step_seed, chunk, level);
            let share = chunk_rays as f32 / rays as f32;
            for level_index in 0..self.recipe.levels.len() {
                let level = self.recipe.levels[level_index];
                let clock = Instant::now();
                self.sample_level(
                    (chunk, level_index),
                    start..end,
                    &near[start..end],
                    &far[start..end],
                    Some(seed_of(level_index)),
                );
                times.march += clock.elapsed().as_secs_f64();

                let clock = Instant::now();
                let b = &mut self.buffers;
                let lb = &mut b.levels[level_index];
                let n = lb.t.len();
                samples += n;
                network_flops += 6.0 * (self.fields[level.field].macs_per_sample() * n) as f64;
                let field_range = self.ranges[level.field].clone();
                let field_params = &self.params[field_range.clone()];
                set_len(&mut lb.sigma, n);
                set_len(&mut lb.rgb, 3 * n);
                let variances = (self.recipe.samples == SampleShape::ConicalFrustums)
                    .then_some(&lb.variances[..]);
                self.fields[level.field].forward(
                    field_params,
                    &lb.positions,
                    variances,
                    &lb.directions,
                    &mut lb.sigma,
                    &mut lb.rgb,
                );
                times.networks_forward += clock.elapsed().as_secs_f64();

                let clock = Instant::now();
                let level_loss = composite_and_loss(
                    lb,
                    &b.targets[3 * start..3 * end],
                    &b.backgrounds[3 * start..3 * end],
                    0.0,
                    self.loss,
                    level.loss_weight * share,
                    None,
                    &mut b.rays,
                );
                loss += level_loss * (level.loss_weight * share) as f64;
                if let Some(l) = level_losses.get_mut(level_index) {
                    *l += (level_loss * share as f64) as f32;
                }
                times.composite += clock.elapsed().as_secs_f64();

                let clock = Instant::now();
                self.fields[level.field].backward(
                    field_params,
                    &lb.d_sigma,
                    &lb.d_rgb,
                    &mut b.gradients[field_range],
                    Gradient::Add,
                );
                times.networks_backward += clock.elapsed().as_secs_f64();
            }
        }
        StepStats {
            loss: loss as f32,
            level_losses,
            rays,
            samples,
            samples_composited: None,
            times,
            network_flops,
        }
    }

    /// Fills level `level`'s samples for rays `rays` of the step's buffers
    /// (see [`sample_level`]).
    fn sample_level(
        &mut self,
        (chunk, level): (usize, usize),
        rays: Range<usize>,
        near: &[f32],
        far: &[f32],
        jitter: Option<u32>,
    ) {
        let held = self
            .held_samples
            .as_ref()
            .and_then(|held| held.get(&(chunk, level)));
        let b = &mut self.buffers;
        while b.levels.len() <= level {
            b.levels.push(LevelBuffers::default());
        }
        let (before, rest) = b.levels.split_at_mut(level);
        let radii = if b.radii.is_empty() {
            &[][..]
        } else {
            &b.radii[rays.clone()]
        };
        sample_level(
            self.recipe.levels[level].sampler,
            self.recipe.samples,
            before.last(),
            RaysOfChunk {
                origins: &b.origins[3 * rays.start..3 * rays.end],
                directions: &b.directions[3 * rays.start..3 * rays.end],
                radii,
                near,
                far,
            },
            jitter,
            held.map(|d| &d[..]),
            &mut b.sampling,
            &mut rest[0],
        );
        if let Some(held) = self.held_samples.as_mut() {
            let lb = &self.buffers.levels[level];
            let distances = match self.recipe.samples {
                SampleShape::Points => &lb.t,
                SampleShape::ConicalFrustums => &lb.edges,
            };
            held.entry((chunk, level))
                .or_insert_with(|| distances.clone());
        }
    }

    fn update_grid(&mut self, step: u32) {
        let Some(grid) = self.grid.as_mut() else {
            return;
        };
        let level = self.recipe.levels[0];
        let field = &self.fields[level.field];
        let params = &self.params[self.ranges[level.field].clone()];
        let mapping = self.mapping;
        let mut world = Vec::new();
        let frustums = self.recipe.samples == SampleShape::ConicalFrustums;
        let cell_variance = grid_cell_variance(grid, &mapping);
        let mut variances = Vec::new();
        let unit_cube = field.coordinates() == Coordinates::UnitCube;
        grid.update(step, self.seed, |positions, sigma| {
            if unit_cube {
                field.density(params, positions, None, sigma);
                return;
            }
            to_world(&mapping, positions, &mut world);
            if frustums {
                set_len(&mut variances, world.len());
                variances.fill(cell_variance);
            }
            field.density(params, &world, frustums.then_some(&variances[..]), sigma);
        });
    }

    /// Renders rays with the paper's levels (no jitter), in chunks.
    fn render_fixed(
        &self,
        origins: &[f32],
        directions: &[f32],
        radii: &[f32],
        background: [f32; 3],
        out: &mut [RenderedPixel],
    ) {
        let rays = origins.len() / 3;
        let (mut near, mut far) = (Vec::new(), Vec::new());
        self.ray_bounds(origins, directions, &mut near, &mut far);
        if let Some(crop) = &self.crop {
            crop_ray_bounds(crop, origins, directions, &mut near, &mut far);
        }
        let mut scratch = SamplingScratch::default();
        let mut levels = [LevelBuffers::default(), LevelBuffers::default()];
        let mut pixels = RayScratch::default();
        let frustums = self.recipe.samples == SampleShape::ConicalFrustums;
        for start in (0..rays).step_by(RAYS_PER_CHUNK) {
            let end = (start + RAYS_PER_CHUNK).min(rays);
            let count = end - start;
            let backgrounds = background.repeat(count);
            for (index, level) in self.recipe.levels.iter().enumerate() {
                let (before, rest) = levels.split_at_mut(index);
                let lb = &mut rest[0];
                sample_level(
                    level.sampler,
                    self.recipe.samples,
                    before.last(),
                    RaysOfChunk {
                        origins: &origins[3 * start..3 * end],
                        directions: &directions[3 * start..3 * end],
                        radii: if frustums { &radii[start..end] } else { &[] },
                        near: &near[start..end],
                        far: &far[start..end],
                    },
                    None,
                    None,
                    &mut scratch,
                    lb,
                );
                let n = lb.t.len();
                set_len(&mut lb.sigma, n);
                set_len(&mut lb.rgb, 3 * n);
                self.fields[level.field].radiance(
                    &self.params[self.ranges[level.field].clone()],
                    &lb.positions,
                    frustums.then_some(&lb.variances[..]),
                    &lb.directions,
                    &mut lb.sigma,
                    &mut lb.rgb,
                );
                composite_level(lb, &backgrounds, 0.0, &mut pixels);
            }
            for (i, pixel) in out[start..end].iter_mut().enumerate() {
                *pixel = RenderedPixel {
                    rgb: [
                        pixels.rgb[3 * i],
                        pixels.rgb[3 * i + 1],
                        pixels.rgb[3 * i + 2],
                    ],
                    opacity: pixels.opacity[i],
                    depth: pixels.depth[i],
                };
            }
        }
    }
}

/// The rays of a chunk, as fixed-count sampling needs them.
struct RaysOfChunk<'a> {
    /// R × 3 each.
    origins: &'a [f32],
    directions: &'a [f32],
    /// R cone radii (frustum recipes only; empty otherwise).
    radii: &'a [f32],
    near: &'a [f32],
    far: &'a [f32],
}

/// Scratch of sampling a level, reused.
#[derive(Default)]
struct SamplingScratch {
    edges: Vec<f32>,
    inner_weights: Vec<f32>,
    blurred: Vec<f32>,
    fine_t: Vec<f32>,
    /// Frustums: each sample's interval and ray.
    starts: Vec<f32>,
    ends: Vec<f32>,
    rays: Vec<u32>,
}

/// Fills `lb` with a fixed-count level's samples for the rays of `chunk`:
/// distances `t` and intervals `dt` for compositing, the field's inputs
/// (positions, frustum covariances, directions) and the ray offsets.
///
/// Points (NeRF): stratified points, or the previous level's points merged
/// with importance samples of its weights; each interval runs to the next
/// point (the last one to far). Frustums (Mip-NeRF): `count` + 1 interval
/// edges, stratified or resampled from the previous level's edges and
/// blurred weights; each sample is the Gaussian of the frustum between
/// consecutive edges, at the interval's midpoint for compositing.
/// `held`, where given, replaces the drawn distances (points or edges).
#[allow(clippy::too_many_arguments)]
fn sample_level(
    sampler: SamplerKind,
    shape: SampleShape,
    previous: Option<&LevelBuffers>,
    chunk: RaysOfChunk,
    jitter: Option<u32>,
    held: Option<&[f32]>,
    scratch: &mut SamplingScratch,
    lb: &mut LevelBuffers,
) {
    let count = chunk.near.len();
    let per_ray = match (shape, sampler, held) {
        (SampleShape::Points, _, Some(t)) => {
            lb.t.clear();
            lb.t.extend_from_slice(t);
            t.len() / count.max(1)
        }
        (SampleShape::ConicalFrustums, _, Some(edges)) => {
            lb.edges.clear();
            lb.edges.extend_from_slice(edges);
            (edges.len() / count.max(1)).saturating_sub(1)
        }
        _ => sample_distances(sampler, shape, previous, &chunk, jitter, scratch, lb),
    };

    lb.ray_offsets.clear();
    lb.ray_offsets
        .extend((0..=count).map(|r| (r * per_ray) as u32));
    match shape {
        SampleShape::Points => {
            set_len(&mut lb.dt, count * per_ray);
            sampling::intervals_to_far(&lb.t, chunk.far, per_ray, &mut lb.dt);
            points_along_rays(
                chunk.origins,
                chunk.directions,
                &lb.t,
                per_ray,
                &mut lb.positions,
                &mut lb.directions,
            );
        }
        SampleShape::ConicalFrustums => {
            let n = count * per_ray;
            scratch.starts.clear();
            scratch.ends.clear();
            scratch.rays.clear();
            for (r, edges) in lb.edges.chunks_exact(per_ray + 1).enumerate() {
                for pair in edges.windows(2) {
                    scratch.starts.push(pair[0]);
                    scratch.ends.push(pair[1]);
                    scratch.rays.push(r as u32);
                }
            }
            set_len(&mut lb.t, n);
            set_len(&mut lb.dt, n);
            for (i, (&t0, &t1)) in scratch.starts.iter().zip(&scratch.ends).enumerate() {
                lb.t[i] = 0.5 * (t0 + t1);
                lb.dt[i] = t1 - t0;
            }
            set_len(&mut lb.positions, 3 * n);
            set_len(&mut lb.variances, 3 * n);
            frustum_gaussians(
                chunk.origins,
                chunk.directions,
                chunk.radii,
                &scratch.rays,
                &scratch.starts,
                &scratch.ends,
                &mut lb.positions,
                &mut lb.variances,
            );
            set_len(&mut lb.directions, 3 * n);
            for (d, &r) in lb.directions.chunks_exact_mut(3).zip(&scratch.rays) {
                d.copy_from_slice(&chunk.directions[3 * r as usize..][..3]);
            }
        }
    }
}

/// Draws a fixed-count level's sample distances into `lb` (points into
/// `t`, frustum edges into `edges`; see [`sample_level`]) and returns the
/// samples per ray.
fn sample_distances(
    sampler: SamplerKind,
    shape: SampleShape,
    previous: Option<&LevelBuffers>,
    chunk: &RaysOfChunk,
    jitter: Option<u32>,
    scratch: &mut SamplingScratch,
    lb: &mut LevelBuffers,
) -> usize {
    let count = chunk.near.len();
    match (shape, sampler) {
        (SampleShape::Points, SamplerKind::Stratified { count: n }) => {
            set_len(&mut lb.t, count * n);
            sampling::stratified(chunk.near, chunk.far, n, jitter, &mut lb.t);
            n
        }
        (SampleShape::Points, SamplerKind::Importance { count: n, padding }) => {
            let previous = previous.expect("importance sampling follows a level");
            let m = previous.t.len() / count.max(1);
            importance_samples(
                &previous.t,
                &previous.weights,
                m,
                n,
                padding,
                jitter,
                &mut scratch.edges,
                &mut scratch.inner_weights,
                &mut scratch.fine_t,
            );
            set_len(&mut lb.t, count * (m + n));
            sampling::merge_sorted(&previous.t, m, &scratch.fine_t, n, &mut lb.t);
            m + n
        }
        (SampleShape::ConicalFrustums, SamplerKind::Stratified { count: n }) => {
            set_len(&mut lb.edges, count * (n + 1));
            sampling::stratified(chunk.near, chunk.far, n + 1, jitter, &mut lb.edges);
            n
        }
        (SampleShape::ConicalFrustums, SamplerKind::Resample { count: n, padding }) => {
            let previous = previous.expect("resampling follows a level");
            let m = previous.weights.len() / count.max(1);
            set_len(&mut scratch.blurred, previous.weights.len());
            sampling::blur_weights(&previous.weights, m.max(1), &mut scratch.blurred);
            set_len(&mut lb.edges, count * (n + 1));
            sampling::sample_pdf(
                &previous.edges,
                &scratch.blurred,
                m,
                padding,
                n + 1,
                jitter,
                &mut lb.edges,
            );
            n
        }
        (shape, sampler) => unreachable!("{sampler:?} does not sample {shape:?}"),
    }
}

/// Composites a level's samples (σ, rgb, dt, t, ray offsets in `lb`) over
/// the rays' backgrounds, each ray stopping where its transmittance falls
/// below `min_transmittance`: the pixels into `pixels`, the per-sample
/// weights into `lb.weights` (for the next level).
fn composite_level(
    lb: &mut LevelBuffers,
    backgrounds: &[f32],
    min_transmittance: f32,
    pixels: &mut RayScratch,
) {
    let rays = lb.ray_offsets.len() - 1;
    let batch = composite_batch::RayBatch {
        density: &lb.sigma,
        rgb: &lb.rgb,
        dt: &lb.dt,
        t: &lb.t,
        ray_offsets: &lb.ray_offsets,
        background: backgrounds,
    };
    set_len(&mut lb.weights, lb.sigma.len());
    composite_batch::sample_weights(&batch, min_transmittance, &mut lb.weights);
    set_len(&mut pixels.rgb, 3 * rays);
    set_len(&mut pixels.opacity, rays);
    set_len(&mut pixels.depth, rays);
    set_len(&mut pixels.samples_used, rays);
    composite_batch::composite_forward(
        &batch,
        min_transmittance,
        CompositeOutputs {
            rgb: &mut pixels.rgb,
            opacity: &mut pixels.opacity,
            depth: &mut pixels.depth,
            samples_used: &mut pixels.samples_used,
        },
    );
}

/// The parameters of `fields` laid out one after the other, each from its
/// own seed ([`Field::init_seed`]), and where each sits. Both engines start
/// a model from these, so a model starts identical on either.
pub fn init_field_params<F: AsRef<dyn Field>>(
    fields: &[F],
    seed: u64,
) -> (Vec<f32>, Vec<Range<usize>>) {
    let mut params = Vec::new();
    let mut ranges = Vec::new();
    for (i, field) in fields.iter().enumerate() {
        let field = field.as_ref();
        let start = params.len();
        params.extend(field.init_params(field.init_seed(seed, i)));
        assert_eq!(params.len() - start, field.param_count(), "field {i}");
        ranges.push(start..params.len());
    }
    (params, ranges)
}

/// The parts of `fields`' parameters one after the other (named "field
/// i: …" where there are several fields).
pub fn model_layout<F: AsRef<dyn Field>>(fields: &[F]) -> ParamLayout {
    let mut layout = ParamLayout::new();
    for (i, field) in fields.iter().enumerate() {
        let prefix = if fields.len() > 1 {
            format!("field {i}: ")
        } else {
            String::new()
        };
        layout.append(&field.as_ref().layout(), &prefix);
    }
    layout
}

/// What a model says it is: "NeRF (occupancy sampling, cpu)",
/// "Instant-NGP (gpu)".
pub fn describe(identity: &ModelIdentity, engine: &str) -> String {
    match identity.sampling {
        Some(sampling) => format!("{} ({sampling} sampling, {engine})", identity.name),
        None => format!("{} ({engine})", identity.name),
    }
}

/// Refuses a checkpoint trained with another sampler than `identity`'s.
pub(crate) fn check_sampling(
    header: &super::state::ModelHeader,
    identity: &ModelIdentity,
) -> Result<(), String> {
    let saved = header.sampling.as_deref();
    if saved == identity.sampling {
        return Ok(());
    }
    let name = |s: Option<&str>| s.map_or("its model's only".to_string(), str::to_string);
    Err(format!(
        "the checkpoint was trained with {} sampling, this model uses {}",
        name(saved),
        name(identity.sampling)
    ))
}

/// Near and far bounds of each ray (R × 3 origins and directions) under
/// `bounds`, `scene_box` being the scene's box.
pub fn ray_bounds(
    bounds: RayBounds,
    scene_box: &Aabb,
    origins: &[f32],
    directions: &[f32],
    near: &mut Vec<f32>,
    far: &mut Vec<f32>,
) {
    let rays = origins.len() / 3;
    set_len(near, rays);
    set_len(far, rays);
    for r in 0..rays {
        let (n, f) = match bounds {
            RayBounds::Fixed { near, far } => (near, far),
            RayBounds::SceneBox => scene_box
                .intersect(
                    Vec3::from_slice(&origins[3 * r..]),
                    Vec3::from_slice(&directions[3 * r..]),
                    0.0,
                )
                // A ray that misses the box gets an empty interval:
                // every sample at its origin with zero length, so it
                // shows the background.
                .unwrap_or((0.0, 0.0)),
        };
        near[r] = n;
        far[r] = f.max(n);
    }
}

/// The seed of the random sample positions of `level` for the rays of
/// chunk `chunk` (of [`RAYS_PER_CHUNK`] rays by default) in the step seeded `step_seed`:
/// each chunk and level draws its own jitter, the same on either engine.
pub fn chunk_jitter_seed(step_seed: u32, chunk: usize, level: usize) -> u32 {
    mix32(step_seed ^ mix32((chunk * 8 + level) as u32))
}

/// Per-ray values of compositing and the loss, reused between levels and
/// steps.
#[derive(Default)]
struct RayScratch {
    rgb: Vec<f32>,
    opacity: Vec<f32>,
    depth: Vec<f32>,
    /// Samples before each ray's cut.
    samples_used: Vec<u32>,
    d_rgb: Vec<f32>,
}

/// Composites a level's samples (σ, rgb, dt, t, ray offsets in `lb`) over
/// the rays' backgrounds, writes the per-sample weights into `lb.weights`,
/// and the gradients of `scale` × (mean loss against `targets`) with
/// respect to σ and colour into `lb.d_sigma` and `lb.d_rgb`. Returns the
/// mean loss (unscaled).
#[allow(clippy::too_many_arguments)]
fn composite_and_loss(
    lb: &mut LevelBuffers,
    targets: &[f32],
    backgrounds: &[f32],
    min_transmittance: f32,
    loss_kind: LossKind,
    scale: f32,
    distortion: Option<Distortion<f32>>,
    scratch: &mut RayScratch,
) -> f64 {
    composite_level(lb, backgrounds, min_transmittance, scratch);
    let rays = lb.ray_offsets.len() - 1;
    let n = lb.sigma.len();
    set_len(&mut scratch.d_rgb, 3 * rays);
    let loss = loss_and_gradient(loss_kind, &scratch.rgb, targets, &mut scratch.d_rgb);
    if scale != 1.0 {
        for g in scratch.d_rgb.iter_mut() {
            *g *= scale;
        }
    }
    set_len(&mut lb.d_sigma, n);
    set_len(&mut lb.d_rgb, 3 * n);
    let batch = composite_batch::RayBatch {
        density: &lb.sigma,
        rgb: &lb.rgb,
        dt: &lb.dt,
        t: &lb.t,
        ray_offsets: &lb.ray_offsets,
        background: backgrounds,
    };
    composite_batch::composite_backward(
        &batch,
        min_transmittance,
        &scratch.d_rgb,
        distortion,
        CompositeGradients {
            density: &mut lb.d_sigma,
            rgb: &mut lb.d_rgb,
            background: None,
        },
    );
    loss
}

/// Importance samples for each ray from the previous level's `m` sorted
/// samples `t` and their weights (NeRF's `sample_pdf` on the midpoints of
/// the coarse samples with the weights of the interior samples: the first
/// and last samples have no bin of their own between midpoints).
#[allow(clippy::too_many_arguments)]
fn importance_samples(
    t: &[f32],
    weights: &[f32],
    m: usize,
    count: usize,
    padding: f32,
    jitter: Option<u32>,
    edges: &mut Vec<f32>,
    inner: &mut Vec<f32>,
    out: &mut Vec<f32>,
) {
    assert!(m >= 3, "importance sampling needs three samples per ray");
    let rays = t.len() / m;
    set_len(edges, rays * (m - 1));
    set_len(inner, rays * (m - 2));
    for r in 0..rays {
        let t = &t[r * m..(r + 1) * m];
        for (e, pair) in edges[r * (m - 1)..(r + 1) * (m - 1)]
            .iter_mut()
            .zip(t.windows(2))
        {
            *e = 0.5 * (pair[0] + pair[1]);
        }
        inner[r * (m - 2)..(r + 1) * (m - 2)].copy_from_slice(&weights[r * m + 1..(r + 1) * m - 1]);
    }
    set_len(out, rays * count);
    sampling::sample_pdf(edges, inner, m - 2, padding, count, jitter, out);
}

/// Positions o + t·d (world) and directions of `per_ray` samples per ray.
fn points_along_rays(
    origins: &[f32],
    directions: &[f32],
    t: &[f32],
    per_ray: usize,
    positions: &mut Vec<f32>,
    dirs: &mut Vec<f32>,
) {
    let n = t.len();
    set_len(positions, 3 * n);
    set_len(dirs, 3 * n);
    if per_ray == 0 {
        return;
    }
    positions
        .par_chunks_mut(3 * per_ray)
        .zip(dirs.par_chunks_mut(3 * per_ray))
        .zip(t.par_chunks(per_ray))
        .enumerate()
        .for_each(|(r, ((p, d), t))| {
            let o = Vec3::from_slice(&origins[3 * r..]);
            let dir = Vec3::from_slice(&directions[3 * r..]);
            for (k, &t) in t.iter().enumerate() {
                p[3 * k..3 * k + 3].copy_from_slice(&(o + t * dir).to_array());
                d[3 * k..3 * k + 3].copy_from_slice(&dir.to_array());
            }
        });
}

/// The variance per axis at which a frustum field is asked for the density
/// of a grid cell as a whole: that of a uniform distribution over the finest
/// cascade's cell (side²/12), so the grid sees what the frustums that fill
/// such a cell see, not the alias of the highest frequencies at one point.
pub fn grid_cell_variance(grid: &OccupancyGrid, mapping: &UnitCubeMapping) -> f32 {
    let cell = 1.0 / (grid.geometry().cells_per_unit(0) * mapping.scale);
    cell * cell / 12.0
}

/// World Gaussians (means and covariance diagonals, n × 3 each) of samples
/// marched through the grid for rendering: as in training, each sample
/// stands for the frustum of its step, centred on it. `origins`,
/// `directions` and cone `radii` are the rendered rays' (a missing radius
/// is 0: a ray without a cone).
pub fn grid_sample_gaussians(
    samples: &GridSamples,
    origins: &[Vec3],
    directions: &[Vec3],
    radii: &[f32],
    world: &mut Vec<f32>,
    variances: &mut Vec<f32>,
) {
    let n = samples.t.len();
    set_len(world, 3 * n);
    set_len(variances, 3 * n);
    for (i, ((&t, &dt), &r)) in samples
        .t
        .iter()
        .zip(samples.dt)
        .zip(samples.rays)
        .enumerate()
    {
        let r = r as usize;
        let (mean, variance) = frustum_gaussian(
            origins[r],
            directions[r],
            radii.get(r).copied().unwrap_or(0.0),
            (t - 0.5 * dt).max(0.0),
            t + 0.5 * dt,
        );
        world[3 * i..3 * i + 3].copy_from_slice(&mean.to_array());
        variances[3 * i..3 * i + 3].copy_from_slice(&variance.to_array());
    }
}

/// Unit-cube positions (n × 3) to world positions.
pub fn to_world(mapping: &UnitCubeMapping, unit: &[f32], world: &mut Vec<f32>) {
    set_len(world, unit.len());
    let (scale, offset) = (mapping.scale, mapping.offset.to_array());
    world
        .par_chunks_mut(3 * ROWS_PER_TASK)
        .zip(unit.par_chunks(3 * ROWS_PER_TASK))
        .for_each(|(w, u)| {
            for (w, u) in w.chunks_exact_mut(3).zip(u.chunks_exact(3)) {
                for c in 0..3 {
                    w[c] = (u[c] - offset[c]) / scale;
                }
            }
        });
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
        describe(&self.identity, "cpu")
    }

    fn rays_for_next_batch(&self) -> usize {
        match self.batch_size {
            BatchSize::Rays(rays) => rays,
            BatchSize::Samples(_) => self.batch_sizer.rays(),
        }
    }

    fn centre_crop(&self, step: u32) -> Option<f32> {
        self.recipe
            .centre_crop
            .and_then(|(steps, fraction)| (step < steps).then_some(fraction))
    }

    fn step(&mut self, batch: &RayBatch, step: u32) -> StepStats {
        let clock = Instant::now();
        if self.grid.as_ref().is_some_and(|g| g.is_due(step)) {
            self.update_grid(step);
        }
        let grid_update = clock.elapsed().as_secs_f64();
        let mut stats = self.forward_backward(batch, step);
        stats.times.grid_update = grid_update;
        let clock = Instant::now();
        self.adam.step_layout(
            &self.recipe.optimiser,
            &self.layout,
            &mut self.params,
            &self.buffers.gradients,
        );
        stats.times.optimiser = clock.elapsed().as_secs_f64();
        stats
    }

    fn render(
        &self,
        origins: &[Vec3],
        directions: &[Vec3],
        radii: &[f32],
        background: [f32; 3],
        out: &mut [RenderedPixel],
    ) {
        let flat = |v: &[Vec3]| v.iter().flat_map(|x| x.to_array()).collect::<Vec<f32>>();
        match &self.grid {
            Some(grid) => {
                let level = self.recipe.levels[0];
                let field = &self.fields[level.field];
                let params = &self.params[self.ranges[level.field].clone()];
                let mapping = self.mapping;
                let frustums = self.recipe.samples == SampleShape::ConicalFrustums;
                let unit_cube = field.coordinates() == Coordinates::UnitCube;
                let (mut world, mut variances) = (Vec::new(), Vec::new());
                render_through_grid(
                    grid,
                    &self.mapping,
                    origins,
                    directions,
                    background,
                    &self.recipe.march,
                    field.inference_rows(),
                    |samples: &GridSamples, sigma, rgb| {
                        if unit_cube {
                            field.radiance(
                                params,
                                samples.positions,
                                None,
                                samples.directions,
                                sigma,
                                rgb,
                            );
                            if let Some(crop) = &self.crop {
                                crop_densities(crop, &mapping, samples.positions, sigma);
                            }
                            return;
                        }
                        if frustums {
                            grid_sample_gaussians(
                                samples,
                                origins,
                                directions,
                                radii,
                                &mut world,
                                &mut variances,
                            );
                        } else {
                            to_world(&mapping, samples.positions, &mut world);
                        }
                        field.radiance(
                            params,
                            &world,
                            frustums.then_some(&variances[..]),
                            samples.directions,
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
            None => self.render_fixed(&flat(origins), &flat(directions), radii, background, out),
        }
    }

    fn density_at(
        &self,
        positions: &[Vec3],
        footprint: f32,
        sigma: &mut [f32],
    ) -> Result<(), String> {
        let level = *self.recipe.levels.last().expect("a recipe has levels");
        let field = &self.fields[level.field];
        let params = &self.params[self.ranges[level.field].clone()];
        // A cube of side s as a Gaussian of the same variance per axis,
        // s²/12 (that of a uniform distribution over the side).
        let frustums = self.recipe.samples == SampleShape::ConicalFrustums;
        let variance = footprint * footprint / 12.0;
        let (mut world, mut variances) = (Vec::new(), Vec::new());
        for (points, sigma) in positions
            .chunks(field.inference_rows())
            .zip(sigma.chunks_mut(field.inference_rows()))
        {
            world.clear();
            world.extend(
                points
                    .iter()
                    .flat_map(|&p| field_position(field.as_ref(), &self.mapping, p)),
            );
            if frustums {
                variances.clear();
                variances.resize(world.len(), variance);
            }
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

    fn colour_at(
        &self,
        positions: &[Vec3],
        directions: &[Vec3],
        footprint: f32,
        rgb: &mut [f32],
    ) -> Result<(), String> {
        let level = *self.recipe.levels.last().expect("a recipe has levels");
        let field = &self.fields[level.field];
        let params = &self.params[self.ranges[level.field].clone()];
        let frustums = self.recipe.samples == SampleShape::ConicalFrustums;
        let variance = footprint * footprint / 12.0;
        let (mut world, mut flat_directions, mut variances, mut sigma) =
            (Vec::new(), Vec::new(), Vec::new(), Vec::new());
        for ((points, directions), rgb) in positions
            .chunks(field.inference_rows())
            .zip(directions.chunks(field.inference_rows()))
            .zip(rgb.chunks_mut(3 * field.inference_rows()))
        {
            world.clear();
            world.extend(
                points
                    .iter()
                    .flat_map(|&p| field_position(field.as_ref(), &self.mapping, p)),
            );
            flat_directions.clear();
            flat_directions.extend(directions.iter().flat_map(|d| d.to_array()));
            if frustums {
                variances.clear();
                variances.resize(world.len(), variance);
            }
            set_len(&mut sigma, points.len());
            field.radiance(
                params,
                &world,
                frustums.then_some(&variances[..]),
                &flat_directions,
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

    fn save(&self) -> Checkpoint {
        ModelState {
            header: ModelHeader {
                model: self.identity.key.into(),
                loss: self.loss,
                seed: self.seed,
                adam_step: self.adam.step,
                samples_per_ray: self.batch_sizer.samples_per_ray(),
                param_count: self.params.len(),
                sampling: self.identity.sampling.map(Into::into),
                // Only where it chooses the next step's order.
                used_fraction: self.chooses_pass_order().then_some(self.used_fraction),
                grid_extent: self.grid_extent(),
            },
            params: self.params.clone(),
            adam: self.adam.clone(),
            occupancy: self.grid.as_ref().map(|g| g.values().to_vec()),
        }
        .into_checkpoint()
    }

    fn load(&mut self, checkpoint: &Checkpoint) -> Result<(), String> {
        let state = ModelState::from_checkpoint(
            checkpoint,
            self.identity.key,
            self.params.len(),
            self.grid.as_ref().map(|g| g.values().len()),
        )?;
        check_sampling(&state.header, &self.identity)?;
        if let Some(extent) = self.grid_extent() {
            state.header.check_grid_extent(extent)?;
        }
        self.params = state.params;
        self.adam = state.adam;
        if let (Some(grid), Some(values)) = (self.grid.as_mut(), &state.occupancy) {
            grid.values_mut().copy_from_slice(values);
            grid.build_bitfield();
        }
        self.batch_sizer
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

/// A world position as `field` takes it: in the world, or in the unit cube
/// (Instant-NGP's hash grid).
fn field_position(field: &dyn Field, mapping: &UnitCubeMapping, world: Vec3) -> [f32; 3] {
    match field.coordinates() {
        Coordinates::World => world.to_array(),
        Coordinates::UnitCube => mapping.to_unit(world).to_array(),
    }
}
