//! A model on the `gpu` engine as a composition of stages, driven by the
//! same [`Recipe`] as the cpu engine's [`crate::engine::cpu::model::CpuModel`]:
//! per level a sampler (stratified, importance sampling of the previous
//! level's weights merged with its samples, or Mip-NeRF's resampling of
//! frustums), a field, compositing and the loss; then one Adam step over
//! every field's parameters, each part as the parameter layout says (a
//! hash table sparsely, networks densely, with or without weight decay).
//! NeRF is this driver with [`super::fields::nerf::GpuNerfField`] and the
//! recipe of [`crate::field::nerf`]; Mip-NeRF is the same driver and field
//! with the recipe of [`crate::field::mipnerf`] (one field for both
//! levels); Instant-NGP is this driver with
//! [`super::fields::ngp::GpuNgpField`] (unit-cube positions) and
//! Instant-NGP's recipe.
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
//! - rays go in chunks of [`RAYS_PER_CHUNK`], as on the cpu (the chunk
//!   index seeds its jitter, [`chunk_jitter_seed`]), each chunk one submission:
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
//! ([`SamplerKind::Occupancy`]) keeps the grid's values on the host with
//! the cpu engine's update code, its
//! bitfield on the device, the march ([`GpuMarch`]) and everything after
//! it on the device, σ first or forward first as the cpu engine chooses
//! (see [`GpuModel::run_marched`]).

use std::ops::Range;
use std::sync::Mutex;
use std::time::Instant;

use glam::Vec3;

use super::adam::GpuAdam;
use super::appearance::GpuAppearance;
use super::compact::{CompactedSamples, GpuCompaction, MarchedInputs};
use super::composite::{CompositeOutputBuffers, GpuComposite};
use super::fields::{GpuField, fields_for};
use super::frustum::{FrustumRays, FrustumSamples, GpuFrustums, MarchedIntervals};
use super::kernel::{
    MapRequest, Recorder, read_buffer, read_mapped, staging_buffer, storage_buffer,
    zeroed_storage_buffer,
};
use super::loss::GpuLoss;
use super::march::{GpuGrid, GpuMarch, GpuMarchBuffers, GpuRays};
use super::proposal::GpuProposal;
use super::render::{RenderBuffers, RenderKernels, check_target};
use super::sampling::GpuSampling;
use super::step::{
    CompositeAndLoss, RayBuffers, SampleBuffers, SampleGradientBuffers, StepReadback, StepResults,
};
use super::timing::{StageClock, StageTiming};
use crate::engine::crop::{crop_densities, crop_ray_bounds};
use crate::engine::gpu::{GpuContext, GpuError};
use crate::engine::request::ModelRequest;
use crate::engine::shared::driver::{
    DriverCore, RAYS_PER_CHUNK, check_sampling, chunk_jitter_seed, grid_cell_variance,
    grid_sample_inputs, ray_bounds, sigma_first, to_world,
};
use crate::engine::shared::march::{GridSamples, MarchParams, mix_seed, render_through_grid};
use crate::engine::shared::occupancy::OccupancyGrid;
use crate::engine::shared::state::{ModelHeader, ModelState, check_appearance};
use crate::field::appearance::AppearanceShape;
use crate::field::common::{BatchSize, Coordinates, LossKind, Recipe, SampleShape, SamplerKind};
use crate::model::batch::RayBatch;
use crate::model::checkpoint::Checkpoint;
use crate::model::pixels::{render_pixels, to_image};
use crate::model::{
    PointQuery, RadianceModel, RenderMode, RenderRays, RenderedPixel, Stage, StepStats,
    TextureRender,
};
use crate::scene::crop::CropBox;
use crate::scene::{Aabb, Camera, Scene, UnitCubeMapping};

mod levels;
mod marched;
mod points;
mod samplers;
mod walk;

use samplers::{LevelSampler, LevelSampling, level_sampler};

/// How a recipe's samples are placed.
enum Plan {
    /// One level marching through the occupancy grid.
    Marched,
    /// Fixed-count levels: each one's sampler and samples per ray.
    Fixed(Vec<(Box<dyn LevelSampler>, usize)>),
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
    let mut levels: Vec<(Box<dyn LevelSampler>, usize)> = Vec::with_capacity(recipe.levels.len());
    for (i, level) in recipe.levels.iter().enumerate() {
        let sampler = level_sampler(level.sampler, recipe.samples, recipe.contraction)
            .map_err(|why| format!("level {i}: {why}"))?;
        // An importance level evaluates the previous level's samples and
        // its own; a resampled level only its own frustums.
        let n = sampler
            .samples_per_ray(levels.last().map(|(_, n)| *n))
            .map_err(|why| format!("level {i}: {why}"))?;
        if n == 0 {
            return Err(format!("level {i} has no samples"));
        }
        levels.push((sampler, n));
    }
    Ok(Plan::Fixed(levels))
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
    /// The march's two counters, the samples kept after the cut by this
    /// step's σ-first compaction, and those of the last step that went
    /// forward first (measured after it, read with this step's counters).
    counters_staging: wgpu::Buffer,
    compaction: GpuCompaction,
    /// The share of its marched samples the last measured step used
    /// (before each ray's cut), which chooses σ first or forward first
    /// ([`sigma_first`]).
    used_fraction: f64,
    /// The marched samples of the last step that went forward first, whose
    /// used samples are counted on the device after its compositing.
    forward_first_samples: Option<usize>,
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
    /// The samples before each ray's cut, σ first.
    compacted: CompactedSamples,
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
            compacted: CompactedSamples::new(context, rays, samples, frustums),
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
            + self.compacted.bytes()
    }
}

/// Buffers of one level for one chunk of rays.
struct LevelBuffers {
    per_ray: usize,
    /// Levels of intervals (frustums, the proposal sampler's): each ray's
    /// per_ray + 1 interval edges (else one float, unused).
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
    fn new(context: &GpuContext, per_ray: usize, frustums: bool, intervals: bool) -> Self {
        let n = RAYS_PER_CHUNK * per_ray;
        let f = |label: &str, count: usize| zeroed_storage_buffer::<f32>(context, label, count);
        let offsets: Vec<u32> = (0..=RAYS_PER_CHUNK)
            .map(|r| u32::try_from(r * per_ray).expect("a chunk's samples fit in u32"))
            .collect();
        let edges = if intervals {
            RAYS_PER_CHUNK * (per_ray + 1)
        } else {
            1
        };
        let variances = if frustums { 3 * n } else { 1 };
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
        /// Rays of the whole batch (the losses on weights are per ray of
        /// it, as on the cpu).
        batch_rays: usize,
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
    /// Per level: a second instance of its field where an earlier proposal
    /// level evaluates the same field (as the cpu's twins), so each round
    /// keeps its own activations until the proposals' backward passes.
    twins: Vec<Option<Box<dyn GpuField>>>,
    /// The losses on weights (proposal sampler): their gradient on a
    /// level's weights (R × the widest level), the kernels' scratch
    /// (R × (the widest level + 1)), and each ray's interlevel loss.
    d_weights: wgpu::Buffer,
    weight_scratch: wgpu::Buffer,
    weight_ray_loss: wgpu::Buffer,
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
    proposal: GpuProposal,
}

/// A model on the `gpu` engine built from a recipe and its fields.
pub struct GpuModel {
    context: GpuContext,
    /// Identity, recipe, layout and batch, as the cpu driver holds them.
    core: DriverCore,
    /// The sampler of each fixed-count level (none for a recipe that
    /// marches through the occupancy grid).
    samplers: Vec<Box<dyn LevelSampler>>,
    stages: Stages,
    param_count: usize,
    /// Every field's parameters, one after the other (the cpu's layout).
    params: wgpu::Buffer,
    /// Their gradient, same layout.
    gradients: wgpu::Buffer,
    adam: GpuAdam,
    work: Mutex<Work>,
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
    /// The device render walk's kernels, for a recipe that marches points
    /// (`walk.rs`).
    render: Option<RenderKernels>,
    /// Buffers of the last texture render, kept for the next frame of the
    /// same size.
    render_buffers: Mutex<Option<RenderBuffers>>,
    /// The training image whose appearance vector renders use (`None`:
    /// the mean of them all), for models with appearance embeddings.
    render_appearance: Option<usize>,
}

impl GpuModel {
    /// The model `request` asks for, on the `gpu` engine with the
    /// context's device: the same initial parameters, layout and
    /// checkpoints as on the `cpu` engine. Where the recipe's batch is in
    /// samples and the settings name none, the model's batch for this
    /// engine (its row's `gpu_batch_samples`).
    pub fn build(
        context: GpuContext,
        request: &ModelRequest,
        scene: &Scene,
    ) -> Result<Self, String> {
        let plan = request.plan(scene, request.kind.spec().gpu_batch_samples);
        let shapes = plan.shapes;
        let settings = &request.settings;
        Self::new(
            context,
            plan.core,
            plan.params,
            |context, index, capacity| fields_for(context, &shapes[index], capacity),
            scene,
            settings.seed,
            settings.loss,
        )
    }

    /// A model of `core`'s recipe for `scene`, starting from `params` (laid
    /// out as its ranges, field after field: the cpu model's initial
    /// parameters for the same seed). `make_field(i, capacity)` builds
    /// field `i` for passes of up to `capacity` samples.
    pub fn new(
        context: GpuContext,
        core: DriverCore,
        params: Vec<f32>,
        mut make_field: impl FnMut(&GpuContext, usize, usize) -> Result<Box<dyn GpuField>, GpuError>,
        scene: &Scene,
        seed: u64,
        loss: LossKind,
    ) -> Result<Self, String> {
        let recipe = &core.recipe;
        let ranges = &core.ranges;
        let layout = &core.layout;
        let batch_size = core.batch_size;
        let plan = plan(recipe)?;
        let marches = matches!(plan, Plan::Marched);
        let (samplers, per_ray): (Vec<_>, Vec<_>) = match plan {
            Plan::Fixed(levels) => levels.into_iter().unzip(),
            Plan::Marched => (Vec::new(), Vec::new()),
        };
        // A marched batch is sized in samples; its buffers hold that many.
        let marched_samples = match (marches, batch_size) {
            (true, BatchSize::Samples(samples)) => Some(samples.max(1)),
            (true, BatchSize::Rays(_)) => {
                return Err("marching through the occupancy grid needs a batch in samples".into());
            }
            (false, _) => None,
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
        if params.len() != param_count || layout.len() != param_count {
            return Err(format!(
                "{} initial parameters and a layout of {} for fields of {param_count}",
                params.len(),
                layout.len()
            ));
        }
        // As `CpuModel::new`: fixed-count levels and frustums are placed in
        // world units, or contracted (onto the unit cube for a hash grid).
        let marches_points = recipe.samples == SampleShape::Points && marches;
        let contracted_points =
            recipe.samples == SampleShape::Points && recipe.contraction.is_some();
        if !marches_points
            && !contracted_points
            && fields
                .iter()
                .any(|f| f.coordinates() == Coordinates::UnitCube)
        {
            return Err(
                "a field of unit-cube positions takes marched points (fixed-count \
                        levels and frustums are placed in world units)"
                    .into(),
            );
        }
        // The widest importance bins and sample sets, and resampling's
        // blurred weights (the previous level's, in the bin weights).
        let mut edges = 1;
        let mut bins = 1;
        let mut fine = 1;
        for (i, sampler) in samplers.iter().enumerate() {
            let needs = sampler.scratch_per_ray(if i == 0 { 0 } else { per_ray[i - 1] });
            edges = edges.max(RAYS_PER_CHUNK * needs.edges);
            bins = bins.max(RAYS_PER_CHUNK * needs.bins);
            fine = fine.max(RAYS_PER_CHUNK * needs.fine);
        }
        let frustums = recipe.samples == SampleShape::ConicalFrustums;
        let f = |label: &str, n: usize| zeroed_storage_buffer::<f32>(ctx, label, n);
        if recipe
            .levels
            .iter()
            .filter(|l| !l.colour)
            .any(|p| recipe.levels.iter().any(|l| l.field == p.field && l.colour))
        {
            return Err(
                "a proposal level's field serves proposal levels only: their backward passes \
                 wait for the final level"
                    .into(),
            );
        }
        // A proposal field that serves several rounds evaluates each after
        // the first through a second instance of itself, reading the same
        // parameters and adding to the same gradient.
        let mut twins = Vec::with_capacity(recipe.levels.len());
        for (index, level) in recipe.levels.iter().enumerate() {
            let shared = recipe.levels[..index]
                .iter()
                .any(|earlier| earlier.field == level.field);
            twins.push(if !level.colour && shared {
                let mut twin =
                    make_field(ctx, level.field, RAYS_PER_CHUNK * per_ray[index]).map_err(gpu)?;
                twin.set_param_offset(ranges[level.field].start);
                Some(twin)
            } else {
                None
            });
        }
        let widest = per_ray.iter().copied().max().unwrap_or(1);
        let intervals: Vec<bool> = samplers.iter().map(|s| s.draws_intervals()).collect();
        let mut work = Work {
            fields,
            rays: RayBuffers::new(ctx, RAYS_PER_CHUNK),
            near: f("ray near", RAYS_PER_CHUNK),
            far: f("ray far", RAYS_PER_CHUNK),
            levels: per_ray
                .iter()
                .zip(&intervals)
                .map(|(&n, &intervals)| LevelBuffers::new(ctx, n, frustums, intervals))
                .collect(),
            edges: f("importance edges", edges),
            bin_weights: f("importance bin weights", bins),
            fine_t: f("importance samples", fine),
            twins,
            d_weights: f("d weights", RAYS_PER_CHUNK * widest),
            weight_scratch: f("weight loss scratch", RAYS_PER_CHUNK * (widest + 1)),
            weight_ray_loss: f("interlevel loss per ray", RAYS_PER_CHUNK),
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
            proposal: GpuProposal::new(ctx).map_err(gpu)?,
        };
        let mapping = scene.unit_cube;
        let grid = match (marched_samples, core.occupancy_grid(&mapping)) {
            (Some(samples), Some(grid)) => {
                work.marched = Some(MarchedBuffers::new(
                    ctx,
                    core.batch_sizer.max_rays,
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
                        size: 16,
                        usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                        mapped_at_creation: false,
                    }),
                    compaction: GpuCompaction::new(ctx).map_err(gpu)?,
                    used_fraction: 1.0,
                    forward_first_samples: None,
                })
            }
            _ => None,
        };
        Ok(Self {
            adam: GpuAdam::new(ctx, param_count).map_err(gpu)?,
            params: storage_buffer(ctx, "model params", &params),
            gradients: f("model gradients", param_count),
            param_count,
            stages,
            work: Mutex::new(work),
            bounds: scene.bounds,
            loss,
            seed,
            rays_per_chunk: RAYS_PER_CHUNK,
            grid,
            pending_grid: None,
            depth_range: scene.depth_range(),
            crop: None,
            render: marches
                .then(|| RenderKernels::new(ctx))
                .transpose()
                .map_err(gpu)?,
            render_buffers: Mutex::new(None),
            render_appearance: None,
            core,
            samplers,
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

    /// Whether marched steps choose between σ first and forward first by
    /// the share of samples used (as `CpuModel`'s: fields that may find the
    /// cut in their forward pass); the choice is saved with a checkpoint.
    fn chooses_pass_order(&self) -> bool {
        self.grid.is_some()
            && self.work().fields[self.core.recipe.levels[0].field].may_find_cut_in_forward()
    }

    /// Marched steps choose σ first or forward first as if the last step
    /// had used `fraction` of its samples (tests compare both orders), as
    /// `CpuModel::assume_used_fraction`.
    pub fn assume_used_fraction(&mut self, fraction: f64) {
        if let Some(grid) = self.grid.as_mut() {
            grid.used_fraction = fraction;
            grid.forward_first_samples = None;
        }
    }

    pub fn context(&self) -> &GpuContext {
        &self.context
    }

    /// Reads the parameters back.
    pub fn params(&self) -> Vec<f32> {
        read_buffer(&self.context, &self.params, self.param_count)
    }

    /// Reads back the sample distances level `level` drew for the last
    /// chunk (of `rays` rays) of the last fixed-count step, as
    /// `CpuModel::level_distances`: interval edges or points' t.
    pub fn level_distances(&self, level: usize, rays: usize) -> Vec<f32> {
        let work = self.work();
        let buffers = &work.levels[level];
        if self.samplers[level].draws_intervals() {
            read_buffer(&self.context, &buffers.edges, rays * (buffers.per_ray + 1))
        } else {
            read_buffer(&self.context, &buffers.t, rays * buffers.per_ray)
        }
    }

    /// Reads back the gradient of the last step or
    /// [`Self::forward_backward`], in the parameters' layout.
    pub fn gradients(&self) -> Vec<f32> {
        read_buffer(&self.context, &self.gradients, self.param_count)
    }

    /// Near and far depth that depth images map to white and black (the
    /// scene's, as the `render` command uses).
    pub fn depth_range(&self) -> (f32, f32) {
        self.depth_range
    }

    /// How the stages of a step are timed: GPU timestamps where the device
    /// has them (the default), else the wall clock with a wait at each
    /// stage boundary.
    pub fn stage_timing(&self) -> StageTiming {
        self.work().clock.timing()
    }

    /// Chooses how stages are timed ([`StageTiming::Timestamps`] falls back
    /// to the wall clock on a device without timestamps).
    pub fn set_stage_timing(&mut self, timing: StageTiming) {
        self.work().clock = StageClock::new(&self.context, timing);
    }

    /// The occupancy grid, for a recipe that marches through one.
    pub fn occupancy(&self) -> Option<&OccupancyGrid> {
        self.grid.as_ref().map(|g| &g.grid)
    }

    /// Where each field sits in the parameters.
    pub fn parameter_ranges(&self) -> &[Range<usize>] {
        &self.core.ranges
    }

    /// Evaluates `batch` and leaves the gradient of the loss in the
    /// gradient buffer ([`Self::gradients`]) without changing any
    /// parameter, as `CpuModel::forward_backward`.
    pub fn forward_backward(&mut self, batch: &RayBatch, step: u32) -> StepStats {
        self.work().clock.reset();
        self.run(batch, step, false)
    }

    /// The side of the box the first level's field's encoding spans, where
    /// its checkpoint must match it.
    fn grid_extent(&self) -> Option<f32> {
        self.work().fields[self.core.recipe.levels[0].field].grid_extent()
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
            self.core.recipe.bounds,
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

    /// The table of appearance embeddings of the fields that give colour,
    /// if they have one.
    fn appearance(&self) -> Option<AppearanceShape> {
        self.work()
            .fields
            .iter()
            .find_map(|field| field.appearance())
    }

    /// The appearance renders use: the mean or the chosen training
    /// image's.
    fn rendered_appearance(&self) -> GpuAppearance<'static> {
        GpuAppearance::rendered(self.render_appearance)
    }

    /// One step on `batch`; with `optimise`, Adam updates the parameters.
    fn run(&mut self, batch: &RayBatch, step: u32, optimise: bool) -> StepStats {
        if let Some(table) = self.appearance() {
            // As the cpu engine: the rays must name images that have
            // vectors (the device would read some other row).
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
        }
        if self.grid.is_some() {
            self.run_marched(batch, step, optimise)
        } else {
            self.run_fixed(batch, step, optimise)
        }
    }
}

/// A recipe that marches through the grid (Instant-NGP; NeRF and Mip-NeRF
/// with the occupancy sampler) is drawn on the device (`walk.rs`). The
/// paper's samplers composite each ray's samples on the host, so their view reaches the texture as one upload of the finished
/// pixels: the image `render::to_image(render_pixels(..))` makes, byte for
/// byte. The viewer draws every model on the gpu engine the same way, from
/// a texture on the model's device.
impl TextureRender for GpuModel {
    fn render_to_texture(
        &self,
        camera: &Camera,
        mode: RenderMode,
        background: [f32; 3],
        target: &wgpu::Texture,
    ) -> Result<(), String> {
        if self.walks_on_device() {
            return self
                .walk_to_texture(camera, mode, background, target)
                .map_err(|e| e.to_string());
        }
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
        self.core.describe("gpu")
    }

    fn rays_for_next_batch(&self) -> usize {
        self.core.rays_for_next_batch()
    }

    fn centre_crop(&self, step: u32) -> Option<f32> {
        self.core.centre_crop(step)
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
            stats.times[Stage::GridUpdate] = grid_update;
        }
        stats
    }

    fn set_read_back_late(&mut self, late: bool) {
        self.work().readback.set_late(late);
    }

    fn render(&self, view: RenderRays, out: &mut [RenderedPixel]) {
        let (origins, directions, radii) = (view.origins, view.directions, view.radii);
        if let Some(grid) = &self.grid {
            render_through_grid(
                &grid.grid,
                &grid.mapping,
                origins,
                directions,
                view.background,
                &self.core.recipe.march,
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
        let backgrounds = view.background.repeat(RAYS_PER_CHUNK);
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
            let mut rec = Recorder::new(ctx);
            self.record_levels(work, &mut rec, count, |_| None, &Purpose::Inference, false);
            rec.submit();
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

    fn appearance_images(&self) -> Option<usize> {
        self.appearance().map(|table| table.images)
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

    fn density_at(&self, query: PointQuery, sigma: &mut [f32]) -> Result<(), String> {
        self.evaluate_points(query.positions, query.footprint, sigma, None);
        Ok(())
    }

    fn colour_at(&self, query: PointQuery, rgb: &mut [f32]) -> Result<(), String> {
        let mut sigma = vec![0.0; query.positions.len()];
        let colour = Some((query.directions, rgb));
        self.evaluate_points(query.positions, query.footprint, &mut sigma, colour);
        Ok(())
    }

    fn save(&self) -> Checkpoint {
        let adam = self.adam.read_state(&self.context);
        ModelState {
            header: ModelHeader {
                model: self.core.identity.key.into(),
                loss: self.loss,
                seed: self.seed,
                adam_step: adam.step,
                samples_per_ray: self.core.batch_sizer.samples_per_ray(),
                param_count: self.param_count,
                sampling: self.core.identity.sampling.map(Into::into),
                used_fraction: self
                    .chooses_pass_order()
                    .then(|| self.grid.as_ref().map(|g| g.used_fraction))
                    .flatten(),
                grid_extent: self.grid_extent(),
                appearance_images: self.appearance().map(|table| table.images),
            },
            params: self.params(),
            adam,
            occupancy: self.grid.as_ref().map(|g| g.grid.values().to_vec()),
            // The gpu engine does not refine cameras yet.
            cameras: None,
        }
        .into_checkpoint()
    }

    fn load(&mut self, checkpoint: &Checkpoint) -> Result<(), String> {
        check_appearance(checkpoint, self.appearance().map(|table| table.images))?;
        let state = ModelState::from_checkpoint(
            checkpoint,
            self.core.identity.key,
            self.param_count,
            self.grid.as_ref().map(|g| g.grid.values().len()),
            None,
        )?;
        check_sampling(&state.header, &self.core.identity)?;
        if let Some(extent) = self.grid_extent() {
            state.header.check_grid_extent(extent)?;
        }
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
        self.core
            .batch_sizer
            .set_samples_per_ray(state.header.samples_per_ray);
        self.loss = state.header.loss;
        self.seed = state.header.seed;
        if let Some(grid) = self.grid.as_mut() {
            grid.used_fraction = state.header.used_fraction.unwrap_or(1.0);
            grid.forward_first_samples = None;
        }
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
            + [
                &work.edges,
                &work.bin_weights,
                &work.fine_t,
                &work.d_weights,
                &work.weight_scratch,
                &work.weight_ray_loss,
            ]
            .iter()
            .map(|b| b.size() as usize)
            .sum::<usize>()
            + work
                .twins
                .iter()
                .flatten()
                .map(|f| f.workspace_bytes())
                .sum::<usize>()
    }
}
