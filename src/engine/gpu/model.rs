//! A model on the `gpu` engine as a composition of stages, driven by the
//! same [`Recipe`] as the cpu engine's [`crate::engine::cpu::model::CpuModel`]:
//! per level a sampler (stratified, importance sampling of the previous
//! level's weights merged with its samples, or Mip-NeRF's resampling of
//! frustums), a field, compositing and the loss; then one Adam step over
//! every field's parameters. NeRF is this driver with
//! [`super::fields::nerf::GpuNerfField`] and the recipe of
//! [`crate::field::nerf`]; Mip-NeRF is the same driver and field with the
//! recipe of [`crate::field::mipnerf`] (one field for both levels).
//!
//! A recipe of conical frustums ([`SampleShape::ConicalFrustums`]) places
//! interval edges instead of points: stratified edges, or edges resampled
//! from the previous level's blurred weights; the frustum stage
//! ([`GpuFrustums`]) turns each interval into a Gaussian (the field's input,
//! through the integrated encoding) and its midpoint and length
//! (compositing's). Marched samples become the frustums of their steps.
//!
//! The parameter layout, initial values, random choices and checkpoint
//! format are the cpu model's, so a model moves between engines through a
//! checkpoint, and one step on either engine gives the same result up to
//! f32 rounding:
//!
//! - rays go in chunks of the cpu's [`RAYS_PER_CHUNK`] (the chunk index
//!   seeds its jitter, [`chunk_jitter_seed`]), each chunk one submission:
//!   its rays are written to the device, then every level's sampling,
//!   forward pass, compositing, loss and backward pass are recorded, the
//!   gradients adding up in one buffer; the device's memory holds one
//!   chunk's activations, whatever the batch;
//! - each chunk's loss gradient is weighted by the level's loss weight and
//!   the chunk's share of the batch's rays, as the cpu does; each chunk's
//!   and level's mean loss is copied to its own slot and all are read back
//!   once, after the step's last submission (Adam's);
//! - near and far bounds are found on the host, as on the cpu (one box
//!   intersection per ray).
//!
//! No gradient flows through the importance samples' positions (paper,
//! section 5.2): they are computed from the coarse weights, which are
//! values, not part of the backward pass.
//!
//! A recipe whose level marches through the occupancy grid
//! ([`SamplerKind::Occupancy`]) runs as Instant-NGP's gpu driver does: the
//! grid's values on the host with the cpu engine's update code, its
//! bitfield on the device, the march ([`GpuMarch`]) and everything after
//! it on the device (see [`GpuModel::run_marched`] for the one difference
//! from the cpu: no σ-first compaction yet).

use std::ops::Range;
use std::sync::Mutex;
use std::time::Instant;

use glam::Vec3;

use super::adam::GpuAdam;
use super::composite::{CompositeOutputBuffers, GpuComposite};
use super::context::{GpuContext, GpuError};
use super::fields::GpuField;
use super::frustum::{FrustumRays, FrustumSamples, GpuFrustums, MarchedIntervals};
use super::kernel::{
    MapRequest, read_buffer, read_mapped, staging_buffer, storage_buffer, zeroed_storage_buffer,
};
use super::loss::GpuLoss;
use super::march::{GpuGrid, GpuMarch, GpuMarchBuffers, GpuRays};
use super::render::check_target;
use super::sampling::GpuSampling;
use super::step::{
    CompositeAndLoss, RayBuffers, SampleBuffers, SampleGradientBuffers, StepReadback, StepResults,
};
use super::timing::{Stage, StageClock, StageTiming};
use crate::engine::cpu::march::{
    BatchSizer, GridSamples, MarchParams, mix_seed, render_through_grid,
};
use crate::engine::cpu::model::{
    ModelIdentity, RAYS_PER_CHUNK, check_sampling, chunk_jitter_seed, describe, grid_cell_variance,
    grid_sample_gaussians, ray_bounds, to_world,
};
use crate::engine::cpu::occupancy::OccupancyGrid;
use crate::engine::cpu::state::{ModelHeader, ModelState};
use crate::engine::crop::{crop_densities, crop_ray_bounds};
use crate::field::common::{BatchSize, Recipe, SampleShape, SamplerKind};
use crate::field::ngp::LossKind;
use crate::model::batch::RayBatch;
use crate::model::checkpoint::Checkpoint;
use crate::model::pixels::{render_pixels, to_image};
use crate::model::{RadianceModel, RenderMode, RenderedPixel, StepStats, TextureRender};
use crate::scene::Camera;
use crate::scene::crop::CropBox;
use crate::scene::{Aabb, Scene, UnitCubeMapping};

/// How a recipe's samples are placed.
enum Plan {
    /// One level marching through the occupancy grid.
    Marched,
    /// Fixed-count levels, with their samples per ray.
    Fixed(Vec<usize>),
}

/// What the gpu driver makes of `recipe`'s levels, or why it cannot drive
/// them.
fn plan(recipe: &Recipe) -> Result<Plan, String> {
    if recipe.levels.is_empty() {
        return Err("the recipe has no levels".into());
    }
    if recipe.levels[0].sampler == SamplerKind::Occupancy {
        if recipe.levels.len() != 1 {
            return Err("a recipe that marches through the occupancy grid has one level".into());
        }
        return Ok(Plan::Marched);
    }
    samples_per_ray(recipe).map(Plan::Fixed)
}

/// Samples per ray of each fixed-count level of `recipe` (an importance
/// level evaluates the previous level's samples and its own; a resampled
/// level only its own frustums), or why the levels cannot be sampled so.
pub fn samples_per_ray(recipe: &Recipe) -> Result<Vec<usize>, String> {
    let frustums = recipe.samples == SampleShape::ConicalFrustums;
    let mut out: Vec<usize> = Vec::with_capacity(recipe.levels.len());
    for (i, level) in recipe.levels.iter().enumerate() {
        let n = match level.sampler {
            SamplerKind::Stratified { count } => count,
            SamplerKind::Importance { .. } if frustums => {
                return Err(format!(
                    "level {i} adds importance points to frustums: frustum levels resample"
                ));
            }
            SamplerKind::Resample { .. } if !frustums => {
                return Err(format!(
                    "level {i} resamples frustums, but the recipe's samples are points"
                ));
            }
            SamplerKind::Resample { count, .. } => match out.last() {
                Some(_) => count,
                None => return Err("the first level cannot be a resampled level".into()),
            },
            SamplerKind::Importance { count, .. } => match out.last() {
                Some(&previous) if previous >= 3 => previous + count,
                Some(_) => {
                    return Err(format!(
                        "level {i} samples the previous level's weights, which needs three \
                         samples per ray"
                    ));
                }
                None => return Err("the first level cannot be an importance level".into()),
            },
            SamplerKind::Occupancy => {
                return Err(format!(
                    "level {i} marches through the occupancy grid, which only a first and only \
                     level can"
                ));
            }
        };
        if n == 0 {
            return Err(format!("level {i} has no samples"));
        }
        out.push(n);
    }
    if out.is_empty() {
        return Err("the recipe has no levels".into());
    }
    Ok(out)
}

/// The occupancy grid and its marching, for a recipe that marches.
struct Grid {
    /// Values, cell choice and EMA on the host (the cpu engine's code and
    /// random choices); the bitfield on the device.
    grid: OccupancyGrid,
    bitfield: wgpu::Buffer,
    march: GpuMarch,
    mapping: UnitCubeMapping,
    /// Samples per batch: every per-sample buffer holds this many.
    samples: usize,
    counters_staging: wgpu::Buffer,
    /// Frustum recipes: the covariance diagonal the field's density is
    /// asked for at each grid update position (one cell's,
    /// [`grid_cell_variance`], `samples` × 3).
    cell_variances: Option<wgpu::Buffer>,
}

impl Grid {
    /// The EMA of an update's densities on the host, the bitfield rebuilt
    /// and uploaded.
    fn apply(&mut self, context: &GpuContext, sigma: &[f32]) {
        self.grid.apply_update(sigma);
        context.queue.write_buffer(
            &self.bitfield,
            0,
            bytemuck::cast_slice(self.grid.bitfield()),
        );
    }
}

/// Per-sample and per-ray buffers of a marched step.
struct MarchedBuffers {
    out: GpuMarchBuffers,
    rays: RayBuffers,
    /// Marched positions in world space (the field's input): the frustums'
    /// means for a frustum recipe.
    world: wgpu::Buffer,
    /// Frustum recipes: the frustums' covariance diagonals (else one
    /// float, unused).
    variances: wgpu::Buffer,
    sigma: wgpu::Buffer,
    rgb: wgpu::Buffer,
    d_sigma: wgpu::Buffer,
    d_rgb: wgpu::Buffer,
}

impl MarchedBuffers {
    fn new(context: &GpuContext, rays: usize, samples: usize, frustums: bool) -> Self {
        let f = |label: &str, n: usize| zeroed_storage_buffer::<f32>(context, label, n);
        Self {
            out: GpuMarchBuffers::new(context, rays, samples),
            rays: RayBuffers::new(context, rays),
            world: f("marched world positions", 3 * samples),
            variances: f("marched variances", if frustums { 3 * samples } else { 1 }),
            sigma: f("marched sigma", samples),
            rgb: f("marched rgb", 3 * samples),
            d_sigma: f("marched d sigma", samples),
            d_rgb: f("marched d rgb", 3 * samples),
        }
    }

    fn bytes(&self) -> usize {
        // The march's own (positions, directions, t, dt) and ours.
        self.out.capacity * 4 * (3 + 3 + 1 + 1 + 3 + 1 + 3 + 1 + 3)
            + self.variances.size() as usize
            + self.rays.bytes()
    }
}

/// Buffers of one level for one chunk of rays.
struct LevelBuffers {
    per_ray: usize,
    /// Frustum levels: each ray's per_ray + 1 interval edges (else one
    /// float, unused).
    edges: wgpu::Buffer,
    /// Frustum levels: each sample's covariance diagonal (else one float,
    /// unused).
    variances: wgpu::Buffer,
    t: wgpu::Buffer,
    dt: wgpu::Buffer,
    positions: wgpu::Buffer,
    directions: wgpu::Buffer,
    /// r · per_ray for r in 0..=RAYS_PER_CHUNK (u32).
    ray_offsets: wgpu::Buffer,
    sigma: wgpu::Buffer,
    rgb: wgpu::Buffer,
    weights: wgpu::Buffer,
    d_sigma: wgpu::Buffer,
    d_rgb: wgpu::Buffer,
}

impl LevelBuffers {
    fn new(context: &GpuContext, per_ray: usize, frustums: bool) -> Self {
        let n = RAYS_PER_CHUNK * per_ray;
        let f = |label: &str, count: usize| zeroed_storage_buffer::<f32>(context, label, count);
        let offsets: Vec<u32> = (0..=RAYS_PER_CHUNK)
            .map(|r| u32::try_from(r * per_ray).expect("a chunk's samples fit in u32"))
            .collect();
        let (edges, variances) = if frustums {
            (RAYS_PER_CHUNK * (per_ray + 1), 3 * n)
        } else {
            (1, 1)
        };
        Self {
            per_ray,
            edges: f("level edges", edges),
            variances: f("level variances", variances),
            t: f("level t", n),
            dt: f("level dt", n),
            positions: f("level positions", 3 * n),
            directions: f("level directions", 3 * n),
            ray_offsets: storage_buffer(context, "level ray offsets", &offsets),
            sigma: f("level sigma", n),
            rgb: f("level rgb", 3 * n),
            weights: f("level weights", n),
            d_sigma: f("level d sigma", n),
            d_rgb: f("level d rgb", 3 * n),
        }
    }

    fn bytes(&self) -> usize {
        RAYS_PER_CHUNK * self.per_ray * 4 * (1 + 1 + 3 + 3 + 1 + 3 + 1 + 1 + 3)
            + (self.edges.size() + self.variances.size()) as usize
    }
}

/// What a chunk is recorded for.
enum Purpose<'a> {
    /// Loss and backward pass: the chunk's share of the batch's rays, and
    /// where each level's mean loss goes (f32 slot `first_slot + level`).
    Training {
        share: f32,
        losses: &'a wgpu::Buffer,
        first_slot: usize,
    },
    /// Compositing only (rendering).
    Inference,
}

/// The device buffers and fields a step or a render works in (behind a
/// lock, so rendering, which takes `&self`, can use them too).
struct Work {
    fields: Vec<Box<dyn GpuField>>,
    rays: RayBuffers,
    near: wgpu::Buffer,
    far: wgpu::Buffer,
    levels: Vec<LevelBuffers>,
    /// Importance sampling's bin edges, bin weights (or resampling's
    /// blurred weights) and new samples.
    edges: wgpu::Buffer,
    bin_weights: wgpu::Buffer,
    fine_t: wgpu::Buffer,
    scratch: Vec<f32>,
    clock: StageClock,
    /// The loss and stage times of each marched step.
    readback: StepReadback,
    /// For a recipe that marches.
    marched: Option<MarchedBuffers>,
}

/// The compiled stages the driver records.
struct Stages {
    sampling: GpuSampling,
    frustums: GpuFrustums,
    composite: GpuComposite,
    loss: GpuLoss,
}

/// A model on the `gpu` engine built from a recipe and its fields.
pub struct GpuModel {
    context: GpuContext,
    identity: ModelIdentity,
    recipe: Recipe,
    stages: Stages,
    ranges: Vec<Range<usize>>,
    param_count: usize,
    /// Every field's parameters, one after the other (the cpu's layout).
    params: wgpu::Buffer,
    /// Their gradient, same layout.
    gradients: wgpu::Buffer,
    adam: GpuAdam,
    work: Mutex<Work>,
    batch_sizer: BatchSizer,
    batch_size: BatchSize,
    bounds: Aabb,
    loss: LossKind,
    seed: u64,
    /// Rays per chunk: [`RAYS_PER_CHUNK`], or fewer for tests.
    rays_per_chunk: usize,
    /// For a recipe that marches through the occupancy grid.
    grid: Option<Grid>,
    /// Densities of an occupancy update read a step late.
    pending_grid: Option<MapRequest>,
    /// Near and far depth of depth images ([`Scene::depth_range`]).
    depth_range: (f32, f32),
    /// What rendering keeps ([`RadianceModel::set_crop`]).
    crop: Option<CropBox>,
}

impl GpuModel {
    /// A model of `recipe` for `scene`, starting from `params` (laid out as
    /// `ranges`, field after field: the cpu model's initial parameters for
    /// the same seed). `make_field(i, capacity)` builds field `i` for
    /// passes of up to `capacity` samples. `batch_size` replaces the
    /// recipe's batch.
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        context: GpuContext,
        identity: ModelIdentity,
        recipe: Recipe,
        params: Vec<f32>,
        ranges: Vec<Range<usize>>,
        mut make_field: impl FnMut(&GpuContext, usize, usize) -> Result<Box<dyn GpuField>, GpuError>,
        scene: &Scene,
        seed: u64,
        loss: LossKind,
        batch_size: Option<BatchSize>,
    ) -> Result<Self, String> {
        let plan = plan(&recipe)?;
        let per_ray = match &plan {
            Plan::Fixed(per_ray) => per_ray.clone(),
            Plan::Marched => Vec::new(),
        };
        let batch_size = batch_size.unwrap_or(recipe.batch);
        // A marched batch is sized in samples; its buffers hold that many.
        let marched_samples = match (&plan, batch_size) {
            (Plan::Marched, BatchSize::Samples(samples)) => Some(samples.max(1)),
            (Plan::Marched, BatchSize::Rays(_)) => {
                return Err("marching through the occupancy grid needs a batch in samples".into());
            }
            (Plan::Fixed(_), _) => None,
        };
        if let Some(samples) = marched_samples {
            // The march's and compositing's per-sample arrays (at most 3
            // f32 per sample) are bound whole, as in Instant-NGP's driver.
            let bytes = 12 * samples as u64;
            let limit = context.storage_binding_limit();
            if bytes > limit {
                return Err(format!(
                    "a batch of {samples} samples needs {bytes} bytes per binding, more than \
                     the device's {limit}"
                ));
            }
        }
        if ranges.len() != recipe.fields {
            return Err(format!(
                "{} parameter ranges for the recipe's {} fields",
                ranges.len(),
                recipe.fields
            ));
        }
        if let Some(level) = recipe.levels.iter().find(|l| l.field >= recipe.fields) {
            return Err(format!(
                "a level names field {}, of {}",
                level.field, recipe.fields
            ));
        }
        let ctx = &context;
        let gpu = |e: GpuError| e.to_string();
        let mut fields = Vec::with_capacity(recipe.fields);
        for (i, range) in ranges.iter().enumerate() {
            // A field's passes hold one chunk of its busiest level, or a
            // marched batch.
            let most = recipe
                .levels
                .iter()
                .zip(&per_ray)
                .filter(|(l, _)| l.field == i)
                .map(|(_, &n)| n)
                .max()
                .unwrap_or(1);
            let capacity = marched_samples.unwrap_or(RAYS_PER_CHUNK * most);
            let mut field = make_field(ctx, i, capacity).map_err(gpu)?;
            if field.param_count() != range.len() {
                return Err(format!(
                    "field {i} has {} parameters, its range {}",
                    field.param_count(),
                    range.len()
                ));
            }
            field.set_param_offset(range.start);
            fields.push(field);
        }
        let param_count = ranges.last().map_or(0, |r| r.end);
        if params.len() != param_count {
            return Err(format!(
                "{} initial parameters for fields of {param_count}",
                params.len()
            ));
        }
        // The widest importance bins and sample sets, and resampling's
        // blurred weights (the previous level's, in the bin weights).
        let mut edges = 1;
        let mut bins = 1;
        let mut fine = 1;
        for (i, level) in recipe.levels.iter().enumerate() {
            match level.sampler {
                SamplerKind::Importance { count, .. } => {
                    let m = per_ray[i - 1];
                    edges = edges.max(RAYS_PER_CHUNK * (m - 1));
                    bins = bins.max(RAYS_PER_CHUNK * (m - 2));
                    fine = fine.max(RAYS_PER_CHUNK * count);
                }
                SamplerKind::Resample { .. } => bins = bins.max(RAYS_PER_CHUNK * per_ray[i - 1]),
                SamplerKind::Stratified { .. } | SamplerKind::Occupancy => {}
            }
        }
        let frustums = recipe.samples == SampleShape::ConicalFrustums;
        let f = |label: &str, n: usize| zeroed_storage_buffer::<f32>(ctx, label, n);
        let mut work = Work {
            fields,
            rays: RayBuffers::new(ctx, RAYS_PER_CHUNK),
            near: f("ray near", RAYS_PER_CHUNK),
            far: f("ray far", RAYS_PER_CHUNK),
            levels: per_ray
                .iter()
                .map(|&n| LevelBuffers::new(ctx, n, frustums))
                .collect(),
            edges: f("importance edges", edges),
            bin_weights: f("importance bin weights", bins),
            fine_t: f("importance samples", fine),
            scratch: Vec::new(),
            clock: StageClock::new(ctx, StageTiming::Timestamps),
            readback: StepReadback::new(ctx),
            marched: None,
        };
        let stages = Stages {
            sampling: GpuSampling::new(ctx).map_err(gpu)?,
            frustums: GpuFrustums::new(ctx).map_err(gpu)?,
            composite: GpuComposite::new(ctx).map_err(gpu)?,
            loss: GpuLoss::new(ctx).map_err(gpu)?,
        };
        // As the cpu model: the header's samples per ray comes from here.
        let batch_sizer = BatchSizer::new(match batch_size {
            BatchSize::Samples(samples) => samples,
            BatchSize::Rays(rays) => rays,
        });
        let mapping = scene.unit_cube;
        let grid = match marched_samples {
            None => None,
            Some(samples) => {
                // As `CpuModel::new`: the grid stores σ · (Instant-NGP's
                // smallest step) whatever step the recipe marches with.
                let mut grid = OccupancyGrid::new(
                    recipe.occupancy,
                    crate::field::ngp::OccupancyConfig::cascades(mapping.aabb_scale),
                    crate::field::ngp::MarchConfig::PAPER.step / mapping.scale,
                );
                grid.chunk = samples;
                work.marched = Some(MarchedBuffers::new(
                    ctx,
                    batch_sizer.max_rays,
                    samples,
                    frustums,
                ));
                let cell_variances = frustums.then(|| {
                    let variance = grid_cell_variance(&grid, &mapping);
                    storage_buffer(ctx, "grid cell variances", &vec![variance; 3 * samples])
                });
                Some(Grid {
                    cell_variances,
                    bitfield: storage_buffer(ctx, "occupancy bitfield", grid.bitfield()),
                    grid,
                    march: GpuMarch::new(ctx).map_err(gpu)?,
                    mapping,
                    samples,
                    counters_staging: ctx.device.create_buffer(&wgpu::BufferDescriptor {
                        label: Some("march counters read-back"),
                        size: 8,
                        usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                        mapped_at_creation: false,
                    }),
                })
            }
        };
        Ok(Self {
            adam: GpuAdam::new(ctx, param_count).map_err(gpu)?,
            params: storage_buffer(ctx, "model params", &params),
            gradients: f("model gradients", param_count),
            param_count,
            ranges,
            stages,
            work: Mutex::new(work),
            batch_sizer,
            batch_size,
            bounds: scene.bounds,
            loss,
            seed,
            rays_per_chunk: RAYS_PER_CHUNK,
            grid,
            pending_grid: None,
            depth_range: scene.depth_range(),
            crop: None,
            identity,
            recipe,
            context,
        })
    }

    /// Processes rays in chunks of `rays` (1 ..= [`RAYS_PER_CHUNK`], what
    /// the buffers hold) instead of [`RAYS_PER_CHUNK`], as
    /// `CpuModel::set_rays_per_chunk` (tests use small chunks to cover
    /// several chunks with few rays).
    pub fn set_rays_per_chunk(&mut self, rays: usize) -> Result<(), String> {
        if !(1..=RAYS_PER_CHUNK).contains(&rays) {
            return Err(format!(
                "chunks of {rays} rays: the buffers hold 1 to {RAYS_PER_CHUNK}"
            ));
        }
        self.rays_per_chunk = rays;
        Ok(())
    }

    pub fn context(&self) -> &GpuContext {
        &self.context
    }

    /// Reads the parameters back.
    pub fn params(&self) -> Vec<f32> {
        read_buffer(&self.context, &self.params, self.param_count)
    }

    /// Reads back the gradient of the last step or
    /// [`Self::forward_backward`], in the parameters' layout.
    pub fn gradients(&self) -> Vec<f32> {
        read_buffer(&self.context, &self.gradients, self.param_count)
    }

    /// The occupancy grid, for a recipe that marches through one.
    pub fn occupancy(&self) -> Option<&OccupancyGrid> {
        self.grid.as_ref().map(|g| &g.grid)
    }

    /// Where each field sits in the parameters.
    pub fn parameter_ranges(&self) -> &[Range<usize>] {
        &self.ranges
    }

    /// Evaluates `batch` and leaves the gradient of the loss in the
    /// gradient buffer ([`Self::gradients`]) without changing any
    /// parameter, as `CpuModel::forward_backward`.
    pub fn forward_backward(&mut self, batch: &RayBatch, step: u32) -> StepStats {
        self.work().clock.reset();
        self.run(batch, step, false)
    }

    fn work(&self) -> std::sync::MutexGuard<'_, Work> {
        // A panic while recording leaves nothing half-written that a later
        // step reads before overwriting it.
        self.work.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Near and far bounds of `count` rays (flattened origins and
    /// directions), written to the chunk buffers.
    /// Uploads each ray's `[near, far]`, cut to `crop` when rendering with
    /// one (training never crops).
    fn upload_bounds(
        &self,
        work: &mut Work,
        origins: &[f32],
        directions: &[f32],
        crop: Option<&CropBox>,
    ) {
        let (mut near, mut far) = (Vec::new(), Vec::new());
        ray_bounds(
            self.recipe.bounds,
            &self.bounds,
            origins,
            directions,
            &mut near,
            &mut far,
        );
        if let Some(crop) = crop {
            crop_ray_bounds(crop, origins, directions, &mut near, &mut far);
        }
        let queue = &self.context.queue;
        if !near.is_empty() {
            queue.write_buffer(&work.near, 0, bytemuck::cast_slice(&near));
            queue.write_buffer(&work.far, 0, bytemuck::cast_slice(&far));
        }
    }

    /// Records every level of a chunk of `count` rays (already on the
    /// device): sampling, the field's forward pass, and compositing; for
    /// training also the loss and the backward pass. `jitter(level)` seeds
    /// a level's random sample positions (`None`: the deterministic
    /// positions). Marks stage boundaries on `clock` when given.
    fn record_levels(
        &self,
        work: &mut Work,
        encoder: &mut wgpu::CommandEncoder,
        count: usize,
        jitter: impl Fn(usize) -> Option<u32>,
        purpose: &Purpose,
        timed: bool,
    ) {
        let ctx = &self.context;
        let s = &self.stages;
        let Work {
            fields,
            rays,
            near,
            far,
            levels,
            edges,
            bin_weights,
            fine_t,
            clock,
            ..
        } = work;
        let mut mark = |encoder: &mut wgpu::CommandEncoder, stage| {
            if timed {
                clock.mark(ctx, encoder, stage);
            }
        };
        let frustums = self.recipe.samples == SampleShape::ConicalFrustums;
        for (li, level) in self.recipe.levels.iter().enumerate() {
            let (before, rest) = levels.split_at_mut(li);
            let lb = &mut rest[0];
            let per_ray = lb.per_ray;
            let rows = count * per_ray;
            match level.sampler {
                // Frustums: n + 1 edges make n intervals.
                SamplerKind::Stratified { count: n } => s.sampling.record_stratified(
                    ctx,
                    encoder,
                    near,
                    far,
                    count,
                    n + frustums as usize,
                    jitter(li),
                    if frustums { &lb.edges } else { &lb.t },
                ),
                SamplerKind::Resample { count: n, padding } => {
                    // Mip-NeRF: new edges from the previous level's edges
                    // and blurred weights (the cpu's `sample_distances`).
                    let previous = before.last().expect("checked by samples_per_ray");
                    let m = previous.per_ray;
                    s.sampling.record_blur_weights(
                        ctx,
                        encoder,
                        &previous.weights,
                        count,
                        m,
                        bin_weights,
                    );
                    s.sampling.record_sample_pdf(
                        ctx,
                        encoder,
                        &previous.edges,
                        bin_weights,
                        count,
                        m,
                        padding,
                        n + 1,
                        jitter(li),
                        &lb.edges,
                    );
                }
                SamplerKind::Importance { count: n, padding } => {
                    let previous = before.last().expect("checked by samples_per_ray");
                    let m = previous.per_ray;
                    s.sampling.record_importance_bins(
                        ctx,
                        encoder,
                        &previous.t,
                        &previous.weights,
                        count,
                        m,
                        edges,
                        bin_weights,
                    );
                    s.sampling.record_sample_pdf(
                        ctx,
                        encoder,
                        edges,
                        bin_weights,
                        count,
                        m - 2,
                        padding,
                        n,
                        jitter(li),
                        fine_t,
                    );
                    s.sampling.record_merge_sorted(
                        ctx,
                        encoder,
                        &previous.t,
                        m,
                        fine_t,
                        n,
                        count,
                        &lb.t,
                    );
                }
                SamplerKind::Occupancy => unreachable!("refused by samples_per_ray"),
            }
            if frustums {
                s.frustums.record_edges(
                    ctx,
                    encoder,
                    FrustumRays {
                        origins: &rays.origins,
                        directions: &rays.directions,
                        radii: &rays.radii,
                    },
                    &lb.edges,
                    count,
                    per_ray,
                    FrustumSamples {
                        t: &lb.t,
                        dt: &lb.dt,
                        means: &lb.positions,
                        variances: &lb.variances,
                        directions: &lb.directions,
                    },
                );
            } else {
                s.sampling
                    .record_intervals_to_far(ctx, encoder, &lb.t, far, count, per_ray, &lb.dt);
                s.sampling.record_points(
                    ctx,
                    encoder,
                    &rays.origins,
                    &rays.directions,
                    &lb.t,
                    count,
                    per_ray,
                    &lb.positions,
                    &lb.directions,
                );
            }
            mark(encoder, Stage::March);

            let field = &mut fields[level.field];
            field.record_forward(
                ctx,
                encoder,
                &self.params,
                &lb.positions,
                frustums.then_some(&lb.variances),
                &lb.directions,
                rows,
                &lb.sigma,
                &lb.rgb,
            );
            mark(encoder, Stage::NetworksForward);

            let samples = SampleBuffers {
                sigma: &lb.sigma,
                rgb: &lb.rgb,
                dt: &lb.dt,
                t: &lb.t,
                ray_offsets: &lb.ray_offsets,
            };
            // The paper's levels composite every sample (no transmittance
            // cut), as the cpu's fixed-count levels.
            let min_transmittance = 0.0;
            if li + 1 < self.recipe.levels.len() {
                s.composite.record_weights(
                    ctx,
                    encoder,
                    &rays.batch(samples, count),
                    min_transmittance,
                    &lb.weights,
                );
            }
            match purpose {
                Purpose::Training {
                    share,
                    losses,
                    first_slot,
                } => {
                    CompositeAndLoss {
                        composite: &s.composite,
                        loss: &s.loss,
                    }
                    .record(
                        ctx,
                        encoder,
                        rays,
                        samples,
                        count,
                        min_transmittance,
                        self.loss,
                        level.loss_weight * share,
                        None,
                        SampleGradientBuffers {
                            sigma: &lb.d_sigma,
                            rgb: &lb.d_rgb,
                        },
                    );
                    encoder.copy_buffer_to_buffer(
                        &rays.loss_total,
                        0,
                        losses,
                        4 * (first_slot + li) as u64,
                        4,
                    );
                    mark(encoder, Stage::Composite);
                    field.record_backward(
                        ctx,
                        encoder,
                        &self.params,
                        &lb.d_sigma,
                        &lb.d_rgb,
                        rows,
                        &self.gradients,
                    );
                    mark(encoder, Stage::NetworksBackward);
                }
                Purpose::Inference => {
                    s.composite.record_forward(
                        ctx,
                        encoder,
                        &rays.batch(samples, count),
                        min_transmittance,
                        &CompositeOutputBuffers {
                            rgb: &rays.rgb,
                            opacity: &rays.opacity,
                            depth: &rays.depth,
                            samples_used: &rays.samples_used,
                        },
                    );
                }
            }
        }
    }

    /// One step on `batch`; with `optimise`, Adam updates the parameters.
    fn run(&mut self, batch: &RayBatch, step: u32, optimise: bool) -> StepStats {
        if self.grid.is_some() {
            self.run_marched(batch, step, optimise)
        } else {
            self.run_fixed(batch, step, optimise)
        }
    }

    /// A step through the occupancy grid, in two submissions as Instant-NGP's
    /// (`super::ngp`): the march, whose two counters (samples, rays kept)
    /// are read back to size the rest; then the field, compositing with the
    /// march's transmittance cut, the loss, the backward passes and Adam.
    ///
    /// Unlike the cpu model, the field's forward and backward passes run on
    /// every marched sample, not only on those before each ray's cut: the
    /// gradient is the same (compositing's backward pass gives the samples
    /// past the cut zero gradient), the work is larger by the share of
    /// samples past the cut. A σ-first pass and compaction on the device
    /// are not built yet.
    fn run_marched(&mut self, batch: &RayBatch, step: u32, optimise: bool) -> StepStats {
        let ctx = &self.context;
        let grid = self.grid.as_ref().expect("a marched recipe has a grid");
        let level = self.recipe.levels[0];
        let rays = batch.len();
        let mut guard = self.work.lock().unwrap_or_else(|e| e.into_inner());
        let work = &mut *guard;
        let frustums = self.recipe.samples == SampleShape::ConicalFrustums;
        let marched = work.marched.as_mut().expect("a marched recipe has buffers");
        if rays > marched.rays.capacity {
            *marched = MarchedBuffers::new(ctx, rays, grid.samples, frustums);
        }
        marched.rays.upload(ctx, batch, 0..rays, &mut work.scratch);

        // Submission 1: the march and its counters.
        let (samples, kept) = if rays == 0 {
            (0, 0)
        } else {
            marched.out.ray_count = rays;
            let mut encoder = ctx.device.create_command_encoder(&Default::default());
            work.clock.restart(ctx, &mut encoder);
            grid.march.record(
                ctx,
                &mut encoder,
                GpuGrid {
                    geometry: grid.grid.geometry(),
                    bitfield: &grid.bitfield,
                },
                GpuRays {
                    origins: &marched.rays.origins,
                    directions: &marched.rays.directions,
                },
                &MarchParams {
                    config: self.recipe.march,
                    mapping: grid.mapping,
                    jitter_seed: Some(mix_seed(self.seed, step)),
                    sample_budget: grid.samples,
                },
                &marched.out,
            );
            work.clock.mark(ctx, &mut encoder, Stage::March);
            encoder.copy_buffer_to_buffer(&marched.out.counters, 0, &grid.counters_staging, 0, 8);
            ctx.queue.submit([encoder.finish()]);
            let counters: Vec<u32> = read_mapped(ctx, &grid.counters_staging, 2);
            (counters[0] as usize, counters[1] as usize)
        };
        let previous = work.readback.take_previous(ctx);

        // Submission 2: field, compositing, loss, backward, Adam.
        let s = &self.stages;
        let mut encoder = ctx.device.create_command_encoder(&Default::default());
        work.clock.restart(ctx, &mut encoder);
        encoder.clear_buffer(&self.gradients, 0, None);
        if frustums {
            // Each marched sample stands for the frustum of its step,
            // centred on it; its Gaussian's mean replaces the point.
            s.frustums.record_marched(
                ctx,
                &mut encoder,
                FrustumRays {
                    origins: &marched.rays.origins,
                    directions: &marched.rays.directions,
                    radii: &marched.rays.radii,
                },
                MarchedIntervals {
                    ray_offsets: &marched.out.ray_offsets,
                    t: &marched.out.t,
                    dt: &marched.out.dt,
                    samples,
                },
                kept,
                &marched.world,
                &marched.variances,
            );
        } else {
            s.sampling.record_to_world(
                ctx,
                &mut encoder,
                &grid.mapping,
                &marched.out.positions,
                samples,
                &marched.world,
            );
        }
        work.clock.mark(ctx, &mut encoder, Stage::March);
        let field = &mut work.fields[level.field];
        field.record_forward(
            ctx,
            &mut encoder,
            &self.params,
            &marched.world,
            frustums.then_some(&marched.variances),
            &marched.out.directions,
            samples,
            &marched.sigma,
            &marched.rgb,
        );
        work.clock.mark(ctx, &mut encoder, Stage::NetworksForward);
        CompositeAndLoss {
            composite: &s.composite,
            loss: &s.loss,
        }
        .record(
            ctx,
            &mut encoder,
            &marched.rays,
            SampleBuffers {
                sigma: &marched.sigma,
                rgb: &marched.rgb,
                dt: &marched.out.dt,
                t: &marched.out.t,
                ray_offsets: &marched.out.ray_offsets,
            },
            kept,
            self.recipe.march.min_transmittance,
            self.loss,
            level.loss_weight,
            None,
            SampleGradientBuffers {
                sigma: &marched.d_sigma,
                rgb: &marched.d_rgb,
            },
        );
        work.clock.mark(ctx, &mut encoder, Stage::Composite);
        field.record_backward(
            ctx,
            &mut encoder,
            &self.params,
            &marched.d_sigma,
            &marched.d_rgb,
            samples,
            &self.gradients,
        );
        work.clock.mark(ctx, &mut encoder, Stage::NetworksBackward);
        if optimise {
            self.adam.record_step(
                ctx,
                &mut encoder,
                &self.recipe.optimiser,
                0..self.param_count,
                &self.params,
                &self.gradients,
            );
        }
        work.clock.mark(ctx, &mut encoder, Stage::Optimiser);
        work.readback
            .record(&mut encoder, &work.clock, &marched.rays.loss_total);
        ctx.queue.submit([encoder.finish()]);
        let StepResults { loss, times } = work.readback.finish(ctx, &work.clock, previous);
        drop(guard);
        self.batch_sizer.record(kept, samples);
        StepStats {
            loss,
            level_losses: [loss, 0.0],
            rays: if rays == 0 { 0 } else { kept },
            samples,
            samples_composited: None,
            times,
            network_flops: 0.0,
        }
    }

    /// The occupancy update of `step`: cells and points chosen on the host
    /// (the cpu engine's code and random choices), densities evaluated by
    /// the field on the device in chunks of the batch's samples (one
    /// submission) and read back, the EMA and bitfield on the host, the
    /// bitfield uploaded. Read a step late, the densities come back with
    /// the step's march read-back and the new bitfield is used from the
    /// next step on.
    fn update_grid(&mut self, step: u32) {
        let ctx = &self.context;
        let Some(grid) = self.grid.as_mut() else {
            return;
        };
        let report = grid.grid.plan_update(step, self.seed);
        let n = report.samples;
        let mut world = Vec::new();
        to_world(&grid.mapping, grid.grid.update_positions(), &mut world);
        let positions = storage_buffer(ctx, "grid update positions", &world);
        let all_sigma = zeroed_storage_buffer::<f32>(ctx, "grid update sigma", n);
        let mut guard = self.work.lock().unwrap_or_else(|e| e.into_inner());
        let work = &mut *guard;
        let marched = work.marched.as_ref().expect("a marched recipe has buffers");
        let field = &mut work.fields[self.recipe.levels[0].field];
        let mut encoder = ctx.device.create_command_encoder(&Default::default());
        let late = work.readback.is_late();
        if late {
            work.clock.restart(ctx, &mut encoder);
        }
        for start in (0..n).step_by(grid.samples) {
            let count = grid.samples.min(n - start);
            encoder.copy_buffer_to_buffer(
                &positions,
                12 * start as u64,
                &marched.world,
                0,
                12 * count as u64,
            );
            field.record_density(
                ctx,
                &mut encoder,
                &self.params,
                &marched.world,
                grid.cell_variances.as_ref(),
                count,
                &marched.sigma,
            );
            encoder.copy_buffer_to_buffer(
                &marched.sigma,
                0,
                &all_sigma,
                4 * start as u64,
                4 * count as u64,
            );
        }
        if late {
            work.clock.mark(ctx, &mut encoder, Stage::GridUpdate);
            let staging = staging_buffer(ctx, "grid update read-back", 4 * n as u64);
            encoder.copy_buffer_to_buffer(&all_sigma, 0, &staging, 0, 4 * n as u64);
            ctx.queue.submit([encoder.finish()]);
            self.pending_grid = Some(MapRequest::new(&staging, 4 * n as u64));
            return;
        }
        ctx.queue.submit([encoder.finish()]);
        let sigma: Vec<f32> = read_buffer(ctx, &all_sigma, n);
        grid.apply(ctx, &sigma);
    }

    /// Applies densities read a step late by [`Self::update_grid`], once
    /// the device is done with them.
    fn apply_pending_grid_update(&mut self) {
        if let (Some(request), Some(grid)) = (self.pending_grid.take(), self.grid.as_mut()) {
            let sigma: Vec<f32> = request.take(&self.context);
            grid.apply(&self.context, &sigma);
        }
    }

    /// σ and colour of `samples` marched through the grid for rendering
    /// rays `origins`, `directions` (with cone `radii`, for frustums), on
    /// the device in chunks of the batch's samples. The field's inputs are
    /// made on the host (world positions, or the Gaussians of the steps'
    /// frustums, with the cpu engine's code), as rendering on the cpu does.
    fn radiance(
        &self,
        samples: &GridSamples,
        origins: &[Vec3],
        directions: &[Vec3],
        radii: &[f32],
        sigma: &mut [f32],
        rgb: &mut [f32],
    ) {
        let ctx = &self.context;
        let grid = self.grid.as_ref().expect("a marched recipe has a grid");
        let frustums = self.recipe.samples == SampleShape::ConicalFrustums;
        let (mut world, mut variances) = (Vec::new(), Vec::new());
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
            to_world(&grid.mapping, samples.positions, &mut world);
        }
        let mut guard = self.work();
        let work = &mut *guard;
        let marched = work.marched.as_ref().expect("a marched recipe has buffers");
        let field = &mut work.fields[self.recipe.levels[0].field];
        let chunk = grid.samples;
        for (i, ((sigma, rgb), d)) in sigma
            .chunks_mut(chunk)
            .zip(rgb.chunks_mut(3 * chunk))
            .zip(samples.directions.chunks(3 * chunk))
            .enumerate()
        {
            let count = sigma.len();
            let rows = 3 * chunk * i..3 * (chunk * i + count);
            let queue = &ctx.queue;
            queue.write_buffer(
                &marched.world,
                0,
                bytemuck::cast_slice(&world[rows.clone()]),
            );
            queue.write_buffer(&marched.out.directions, 0, bytemuck::cast_slice(d));
            if frustums {
                queue.write_buffer(
                    &marched.variances,
                    0,
                    bytemuck::cast_slice(&variances[rows]),
                );
            }
            let mut encoder = ctx.device.create_command_encoder(&Default::default());
            field.record_forward(
                ctx,
                &mut encoder,
                &self.params,
                &marched.world,
                frustums.then_some(&marched.variances),
                &marched.out.directions,
                count,
                &marched.sigma,
                &marched.rgb,
            );
            ctx.queue.submit([encoder.finish()]);
            sigma.copy_from_slice(&read_buffer::<f32>(ctx, &marched.sigma, count));
            rgb.copy_from_slice(&read_buffer::<f32>(ctx, &marched.rgb, 3 * count));
        }
    }

    /// A step of fixed-count levels, in chunks of rays.
    fn run_fixed(&mut self, batch: &RayBatch, step: u32, optimise: bool) -> StepStats {
        let ctx = &self.context;
        let rays = batch.len();
        let levels = self.recipe.levels.len();
        let per_chunk = self.rays_per_chunk;
        let chunks = rays.div_ceil(per_chunk);
        let losses = zeroed_storage_buffer::<f32>(ctx, "chunk losses", chunks * levels);
        let step_seed = mix_seed(self.seed, step);
        let flat = |v: &[Vec3]| v.iter().flat_map(|x| x.to_array()).collect::<Vec<f32>>();
        let (origins, directions) = (flat(&batch.origins), flat(&batch.directions));
        // The lock of the field alone (not `self.work()`), so Adam's state
        // stays writable below.
        let mut guard = self.work.lock().unwrap_or_else(|e| e.into_inner());
        let work = &mut *guard;
        work.clock.reset();
        let mut samples = 0usize;
        let mut shares = Vec::with_capacity(chunks);
        let mut encoder = ctx.device.create_command_encoder(&Default::default());
        encoder.clear_buffer(&self.gradients, 0, None);
        for chunk in 0..chunks {
            let start = chunk * per_chunk;
            let end = (start + per_chunk).min(rays);
            let count = end - start;
            let share = count as f32 / rays as f32;
            shares.push(share);
            let mut scratch = std::mem::take(&mut work.scratch);
            work.rays.upload(ctx, batch, start..end, &mut scratch);
            work.scratch = scratch;
            self.upload_bounds(
                work,
                &origins[3 * start..3 * end],
                &directions[3 * start..3 * end],
                None,
            );
            work.clock.restart(ctx, &mut encoder);
            self.record_levels(
                work,
                &mut encoder,
                count,
                |level| Some(chunk_jitter_seed(step_seed, chunk, level)),
                &Purpose::Training {
                    share,
                    losses: &losses,
                    first_slot: chunk * levels,
                },
                true,
            );
            samples += work.levels.iter().map(|l| count * l.per_ray).sum::<usize>();
            // One submission per chunk: the next chunk's rays are written
            // into the same buffers before the following submission.
            let recorded = std::mem::replace(
                &mut encoder,
                ctx.device.create_command_encoder(&Default::default()),
            );
            ctx.queue.submit([recorded.finish()]);
        }
        work.clock.restart(ctx, &mut encoder);
        if optimise {
            self.adam.record_step(
                ctx,
                &mut encoder,
                &self.recipe.optimiser,
                0..self.param_count,
                &self.params,
                &self.gradients,
            );
        }
        work.clock.mark(ctx, &mut encoder, Stage::Optimiser);
        work.clock.resolve(&mut encoder);
        ctx.queue.submit([encoder.finish()]);
        let values: Vec<f32> = read_buffer(ctx, &losses, chunks * levels);
        let times = work.clock.read(ctx);
        drop(guard);

        // The cpu's sums: the loss weighted per level and chunk, the level
        // losses per chunk's share.
        let mut loss = 0f64;
        let mut level_losses = [0f32; 2];
        for (chunk, &share) in shares.iter().enumerate() {
            for (li, level) in self.recipe.levels.iter().enumerate() {
                let value = values[chunk * levels + li] as f64;
                loss += value * (level.loss_weight * share) as f64;
                if let Some(l) = level_losses.get_mut(li) {
                    *l += (value * share as f64) as f32;
                }
            }
        }
        StepStats {
            loss: loss as f32,
            level_losses,
            rays,
            samples,
            samples_composited: None,
            times,
            network_flops: 0.0,
        }
    }
}

/// NeRF and Mip-NeRF composite each ray's samples on the host (their
/// marching, or their reads of the composited colours, go through it
/// anyway), so their view reaches the texture as one upload of the
/// finished pixels: the image `render::to_image(render_pixels(..))` makes,
/// byte for byte. The viewer then draws every model on the gpu engine the
/// same way, from a texture on the model's device.
impl TextureRender for GpuModel {
    fn render_to_texture(
        &self,
        camera: &Camera,
        mode: RenderMode,
        background: [f32; 3],
        target: &wgpu::Texture,
    ) -> Result<(), String> {
        let (width, height) = (camera.intrinsics.width, camera.intrinsics.height);
        check_target(target, width, height, wgpu::TextureUsages::COPY_DST)
            .map_err(|e| e.to_string())?;
        let pixels = render_pixels(self, camera, background);
        let image = to_image(&pixels, width, height, mode, self.depth_range);
        self.context.queue.write_texture(
            target.as_image_copy(),
            &image.data,
            wgpu::TexelCopyBufferLayout {
                offset: 0,
                bytes_per_row: Some(4 * width),
                rows_per_image: Some(height),
            },
            target.size(),
        );
        Ok(())
    }

    fn stage_timing_note(&self) -> String {
        self.work().clock.timing().note()
    }
}

impl RadianceModel for GpuModel {
    fn texture_render(&self) -> Option<&dyn TextureRender> {
        Some(self)
    }

    fn describe(&self) -> String {
        describe(&self.identity, "gpu")
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
        self.work().clock.reset();
        let clock = Instant::now();
        if self.grid.as_ref().is_some_and(|g| g.grid.is_due(step)) {
            self.update_grid(step);
        }
        let grid_update = clock.elapsed().as_secs_f64();
        let mut stats = self.run(batch, step, true);
        if self.work().readback.is_late() {
            // The update's device time is among the stage times; the host
            // applies its densities while the device runs the step.
            self.apply_pending_grid_update();
        } else {
            stats.times.grid_update = grid_update;
        }
        stats
    }

    fn set_read_back_late(&mut self, late: bool) {
        self.work().readback.set_late(late);
    }

    fn render(
        &self,
        origins: &[Vec3],
        directions: &[Vec3],
        radii: &[f32],
        background: [f32; 3],
        out: &mut [RenderedPixel],
    ) {
        if let Some(grid) = &self.grid {
            render_through_grid(
                &grid.grid,
                &grid.mapping,
                origins,
                directions,
                background,
                &self.recipe.march,
                grid.samples,
                |samples, sigma, rgb| {
                    self.radiance(samples, origins, directions, radii, sigma, rgb);
                    if let Some(crop) = &self.crop {
                        crop_densities(crop, &grid.mapping, samples.positions, sigma);
                    }
                },
                out,
            );
            return;
        }
        let ctx = &self.context;
        let rays = origins.len().min(directions.len()).min(out.len());
        let flat = |v: &[Vec3]| v.iter().flat_map(|x| x.to_array()).collect::<Vec<f32>>();
        let (origins, directions) = (flat(&origins[..rays]), flat(&directions[..rays]));
        let backgrounds = background.repeat(RAYS_PER_CHUNK);
        let mut guard = self.work();
        let work = &mut *guard;
        ctx.queue.write_buffer(
            &work.rays.backgrounds,
            0,
            bytemuck::cast_slice(&backgrounds),
        );
        let per_chunk = self.rays_per_chunk;
        for start in (0..rays).step_by(per_chunk) {
            let end = (start + per_chunk).min(rays);
            let count = end - start;
            let (o, d) = (
                &origins[3 * start..3 * end],
                &directions[3 * start..3 * end],
            );
            ctx.queue
                .write_buffer(&work.rays.origins, 0, bytemuck::cast_slice(o));
            ctx.queue
                .write_buffer(&work.rays.directions, 0, bytemuck::cast_slice(d));
            work.rays
                .upload_radii(ctx, radii.get(start..end).unwrap_or(&[]), count);
            self.upload_bounds(work, o, d, self.crop.as_ref());
            let mut encoder = ctx.device.create_command_encoder(&Default::default());
            self.record_levels(
                work,
                &mut encoder,
                count,
                |_| None,
                &Purpose::Inference,
                false,
            );
            ctx.queue.submit([encoder.finish()]);
            let rgb: Vec<f32> = read_buffer(ctx, &work.rays.rgb, 3 * count);
            let opacity: Vec<f32> = read_buffer(ctx, &work.rays.opacity, count);
            let depth: Vec<f32> = read_buffer(ctx, &work.rays.depth, count);
            for (i, pixel) in out[start..end].iter_mut().enumerate() {
                *pixel = RenderedPixel {
                    rgb: [rgb[3 * i], rgb[3 * i + 1], rgb[3 * i + 2]],
                    opacity: opacity[i],
                    depth: depth[i],
                };
            }
        }
    }

    fn set_crop(&mut self, crop: Option<CropBox>) -> Result<(), String> {
        self.crop = crop;
        Ok(())
    }

    fn save(&self) -> Checkpoint {
        let adam = self.adam.read_state(&self.context);
        ModelState {
            header: ModelHeader {
                model: self.identity.key.into(),
                loss: self.loss,
                seed: self.seed,
                adam_step: adam.step,
                samples_per_ray: self.batch_sizer.samples_per_ray(),
                param_count: self.param_count,
                sampling: self.identity.sampling.map(Into::into),
                used_fraction: None,
                grid_extent: None,
            },
            params: self.params(),
            adam,
            occupancy: self.grid.as_ref().map(|g| g.grid.values().to_vec()),
        }
        .into_checkpoint()
    }

    fn load(&mut self, checkpoint: &Checkpoint) -> Result<(), String> {
        let state = ModelState::from_checkpoint(
            checkpoint,
            self.identity.key,
            self.param_count,
            self.grid.as_ref().map(|g| g.grid.values().len()),
        )?;
        check_sampling(&state.header, &self.identity)?;
        let queue = &self.context.queue;
        for (values, buffer) in [
            (&state.adam.m, &self.adam.m),
            (&state.adam.v, &self.adam.v),
            (&state.adam.m_norm, &self.adam.m_norm),
            (&state.adam.v_norm, &self.adam.v_norm),
            (&state.params, &self.params),
        ] {
            queue.write_buffer(buffer, 0, bytemuck::cast_slice(values));
        }
        self.adam.step = state.adam.step;
        if let (Some(grid), Some(values)) = (self.grid.as_mut(), &state.occupancy) {
            grid.grid.values_mut().copy_from_slice(values);
            grid.grid.build_bitfield();
            queue.write_buffer(
                &grid.bitfield,
                0,
                bytemuck::cast_slice(grid.grid.bitfield()),
            );
        }
        self.batch_sizer
            .set_samples_per_ray(state.header.samples_per_ray);
        self.loss = state.header.loss;
        self.seed = state.header.seed;
        Ok(())
    }

    fn memory_bytes(&self) -> usize {
        let work = self.work();
        // Parameters, gradients and Adam's four arrays.
        let flat = self.param_count * 4 * 6;
        flat + work
            .fields
            .iter()
            .map(|f| f.workspace_bytes())
            .sum::<usize>()
            + work.levels.iter().map(LevelBuffers::bytes).sum::<usize>()
            + work.rays.bytes()
            + work.marched.as_ref().map_or(0, MarchedBuffers::bytes)
            + self.grid.as_ref().map_or(0, |g| {
                4 * (g.grid.values().len() + g.grid.bitfield().len())
                    + g.cell_variances.as_ref().map_or(0, |b| b.size() as usize)
            })
            + [&work.edges, &work.bin_weights, &work.fine_t]
                .iter()
                .map(|b| b.size() as usize)
                .sum::<usize>()
    }
}
