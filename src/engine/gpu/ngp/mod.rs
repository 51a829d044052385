//! Instant-NGP on the `gpu` engine: the gpu stages chained into a training
//! step, with the parameter layout, initial values, checkpoint format and
//! random choices of Instant-NGP on the `cpu` engine (its field,
//! [`crate::engine::cpu::fields::ngp::NgpField`], on `CpuModel`), so a model moves
//! between engines through a checkpoint.
//!
//! A training step is two submissions. The first uploads the rays and
//! marches them against the occupancy bitfield; its only read-back is the
//! march's two counters (samples, rays kept), which size every later
//! dispatch and the loss's mean. The second records everything else into
//! one command encoder (encode, density network, exp, spherical harmonics,
//! colour network, composite, loss, every backward stage, Adam) and reads
//! back the mean loss.
//!
//! The occupancy grid's values and the choice of cells stay on the cpu
//! ([`OccupancyGrid::plan_update`] / [`OccupancyGrid::apply_update`], the
//! same code and random choices as the cpu engine); the densities at the
//! planned points are evaluated on the gpu in one submission and read back
//! (every 16 steps), and the rebuilt bitfield is uploaded.
//!
//! Each stage of a step is timed ([`StageClock`]): by GPU timestamps at the
//! stage boundaries inside the submissions where the device has
//! `TIMESTAMP_QUERY`, else by the wall clock with a wait at each boundary.
//!
//! [`RadianceModel::render`] marches on the cpu with early termination
//! (`march_and_composite`, the cpu engine's own loop) and evaluates each
//! round of samples on the gpu, returning pixels to the host.
//! [`GpuNgp::render_to_texture`] runs the same rounds on the gpu
//! (`super::render`) and writes the image into a texture the viewer draws,
//! with nothing read back but each round's count of rays still marching.

use std::ops::Range;
use std::sync::Mutex;
use std::time::Instant;

use glam::Vec3;

use super::adam::GpuAdam;
use super::composite::GpuComposite;
use super::context::{GpuContext, GpuError};
use super::dense::{GpuDense, GpuMlpWorkspace};
use super::hash_grid::GpuHashGrid;
use super::kernel::{
    Kernel, MapRequest, float_range, pieces, read_buffer, read_mapped, rows_per_piece,
    staging_buffer, storage_buffer, uniform_buffer, zeroed_storage_buffer,
};
use super::loss::GpuLoss;
use super::march::{GpuGrid, GpuMarch, GpuMarchBuffers, GpuRays, dispatch_grid};
use super::render::{
    CompactUniforms, CompositeUniforms, ImageUniforms, RAY_GROUP_ALIGN, RenderBuffers,
    RenderKernels, check_target,
};
use super::sh::GpuSh;
use super::step::{
    self, CompositeAndLoss, RayBuffers, SampleGradientBuffers, StepReadback, StepResults,
};
use super::timing::{Stage, StageClock, StageTiming};
use crate::engine::cpu::composite_batch::Distortion;
use crate::engine::cpu::fields::ngp::NgpShape;
use crate::engine::cpu::march::{BatchSizer, MarchParams, Marcher};
use crate::engine::cpu::march::{mix_seed, render_through_grid};
use crate::engine::cpu::occupancy::OccupancyGrid;
use crate::engine::cpu::state::{ModelHeader, ModelState};
use crate::engine::crop::crop_densities;
use crate::field::ngp::{
    DENSITY_EXP_CLAMP, LossKind, MarchConfig, OccupancyConfig, OptimiserConfig, SAMPLES_PER_BATCH,
};
use crate::model::RenderMode;
use crate::model::batch::RayBatch;
use crate::model::checkpoint::Checkpoint;
use crate::model::{RadianceModel, RenderedPixel, StepStats, TextureRender};
use crate::scene::crop::CropBox;
use crate::scene::{Camera, Scene};

/// Threads per workgroup of the activation kernels.
const WORKGROUP: u32 = 64;

mod render;

/// `Params` in shaders/ngp_density*.wgsl.
#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct ActivationUniforms {
    count: u32,
    row_stride: u32,
    density_width: u32,
    colour_width: u32,
    exp_clamp: f32,
    _pad: [u32; 3],
}

/// Per-sample buffers, sized once for the batch's sample budget.
struct SampleBuffers {
    encoded: wgpu::Buffer,
    sigma: wgpu::Buffer,
    colour_input: wgpu::Buffer,
    density: GpuMlpWorkspace,
    colour: GpuMlpWorkspace,
    d_sigma: wgpu::Buffer,
    d_rgb: wgpu::Buffer,
    d_colour_input: wgpu::Buffer,
    d_density_out: wgpu::Buffer,
    d_encoded: wgpu::Buffer,
}

/// The compiled kernels of every stage.
struct Stages {
    hash: GpuHashGrid,
    dense: GpuDense,
    sh: GpuSh,
    march: GpuMarch,
    composite: GpuComposite,
    loss: GpuLoss,
    activate: Kernel,
    activate_backward: Kernel,
    render: RenderKernels,
}

/// Instant-NGP trained by the `gpu` engine.
pub struct GpuNgp {
    context: GpuContext,
    shape: NgpShape,
    stages: Stages,
    adam: GpuAdam,
    /// All parameters, `[hash grid | density MLP | colour MLP]`.
    params: wgpu::Buffer,
    /// Their gradient, same layout.
    gradients: wgpu::Buffer,
    grid: OccupancyGrid,
    bitfield: wgpu::Buffer,
    march_out: GpuMarchBuffers,
    rays: RayBuffers,
    samples: SampleBuffers,
    /// Mappable copy of the march's counters.
    counters_staging: wgpu::Buffer,
    /// The loss and stage times of each step.
    readback: StepReadback,
    /// Densities of an occupancy update read a step late
    /// ([`StepReadback`]): applied once the step's march read-back has
    /// waited for them.
    pending_grid: Option<MapRequest>,
    batch_sizer: BatchSizer,
    optimiser: OptimiserConfig,
    loss: LossKind,
    seed: u64,
    /// Samples per batch; every per-sample buffer holds this many.
    batch_samples: usize,
    /// Flattened rays of the current batch (reused).
    scratch: Vec<f32>,
    /// Times each training step's stages (taken out while a step runs).
    clock: Option<StageClock>,
    /// Buffers of the last [`GpuNgp::render_to_texture`], kept for the
    /// next frame of the same size.
    render_buffers: Mutex<Option<RenderBuffers>>,
    /// Near and far depth of depth images ([`Scene::depth_range`]).
    depth_range: (f32, f32),
    /// What rendering keeps ([`RadianceModel::set_crop`]).
    crop: Option<CropBox>,
}

impl GpuNgp {
    pub fn new(
        context: GpuContext,
        scene: &Scene,
        seed: u64,
        loss: LossKind,
    ) -> Result<Self, GpuError> {
        Self::with_batch_samples(context, scene, seed, loss, SAMPLES_PER_BATCH)
    }

    /// A model whose batches hold `batch_samples` samples (tests use few).
    /// The parameters start as the cpu engine's do for the same seed.
    pub fn with_batch_samples(
        context: GpuContext,
        scene: &Scene,
        seed: u64,
        loss: LossKind,
        batch_samples: usize,
    ) -> Result<Self, GpuError> {
        Self::with_shape(
            context,
            NgpShape::for_scene(scene),
            scene.depth_range(),
            seed,
            loss,
            batch_samples,
        )
    }

    /// [`Self::with_batch_samples`] with parts of another size than the
    /// paper's (as `train::cpu_ngp_with_shape`); `depth_range` is the scene's
    /// ([`Scene::depth_range`]), for depth images.
    pub fn with_shape(
        context: GpuContext,
        shape: NgpShape,
        depth_range: (f32, f32),
        seed: u64,
        loss: LossKind,
        batch_samples: usize,
    ) -> Result<Self, GpuError> {
        // The wide per-sample matrices (encodings, activations) and the
        // parameter arrays are bound a piece at a time when they exceed the
        // storage-binding limit; the march's and compositing's per-sample
        // arrays (at most 3 f32 per sample) are bound whole, as their
        // samples are addressed through per-ray offsets.
        let narrow = 12 * batch_samples.max(1) as u64;
        let limit = context.storage_binding_limit();
        if narrow > limit {
            return Err(GpuError::BindingTooLarge {
                what: format!("a batch of {batch_samples} samples (3 f32 per sample)"),
                bytes: narrow,
                limit,
            });
        }
        // The cpu engine's initial values (a test checks that both engines
        // start identical).
        let params = shape.init_params(seed);
        let grid = OccupancyGrid::new(
            OccupancyConfig::PAPER,
            OccupancyConfig::cascades(shape.mapping.aabb_scale),
            MarchConfig::PAPER.step / shape.mapping.scale,
        );
        let ctx = &context;
        let stages = Stages {
            hash: GpuHashGrid::new(ctx, &shape.grid, true)?,
            dense: GpuDense::new(ctx)?,
            sh: GpuSh::new(ctx)?,
            march: GpuMarch::new(ctx)?,
            composite: GpuComposite::new(ctx)?,
            loss: GpuLoss::new(ctx)?,
            activate: Kernel::new(
                ctx,
                "ngp_density",
                include_str!("../../../../shaders/ngp_density.wgsl"),
                "forward",
            )?,
            activate_backward: Kernel::new(
                ctx,
                "ngp_density_backward",
                include_str!("../../../../shaders/ngp_density_backward.wgsl"),
                "backward",
            )?,
            render: RenderKernels::new(ctx)?,
        };
        let capacity = batch_samples.max(1);
        let f = |label: &str, n: usize| zeroed_storage_buffer::<f32>(ctx, label, n);
        let density_width = shape.density.output_width();
        let colour_width = shape.colour.input_width();
        let grid_width = shape.grid.output_width();
        let samples = SampleBuffers {
            encoded: f("ngp encoded", capacity * grid_width),
            sigma: f("ngp sigma", capacity),
            colour_input: f("ngp colour input", capacity * colour_width),
            density: GpuMlpWorkspace::new(ctx, &shape.density, capacity),
            colour: GpuMlpWorkspace::new(ctx, &shape.colour, capacity),
            d_sigma: f("ngp d sigma", capacity),
            d_rgb: f("ngp d rgb", 3 * capacity),
            d_colour_input: f("ngp d colour input", capacity * colour_width),
            d_density_out: f("ngp d density out", capacity * density_width),
            d_encoded: f("ngp d encoded", capacity * grid_width),
        };
        let batch_sizer = BatchSizer::new(batch_samples);
        let ray_capacity = batch_sizer.max_rays;
        let staging = |label: &str, bytes: u64| {
            ctx.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size: bytes,
                usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            })
        };
        let model = Self {
            adam: GpuAdam::new(ctx, params.len())?,
            params: storage_buffer(ctx, "ngp params", &params),
            gradients: f("ngp gradients", params.len()),
            bitfield: storage_buffer(ctx, "ngp occupancy bitfield", grid.bitfield()),
            grid,
            march_out: GpuMarchBuffers::new(ctx, ray_capacity, capacity),
            rays: RayBuffers::new(ctx, ray_capacity),
            samples,
            counters_staging: staging("ngp counters read-back", 8),
            readback: StepReadback::new(ctx),
            pending_grid: None,
            batch_sizer,
            optimiser: OptimiserConfig::PAPER,
            loss,
            seed,
            batch_samples,
            scratch: Vec::new(),
            clock: Some(StageClock::new(ctx, StageTiming::Timestamps)),
            render_buffers: Mutex::new(None),
            depth_range,
            crop: None,
            stages,
            shape,
            context,
        };
        Ok(model)
    }

    pub fn context(&self) -> &GpuContext {
        &self.context
    }

    /// How the stages of a step are timed: GPU timestamps where the device
    /// has them (the default), else the wall clock with a wait at each
    /// stage boundary.
    pub fn stage_timing(&self) -> StageTiming {
        self.clock
            .as_ref()
            .map_or(StageTiming::WallClock, StageClock::timing)
    }

    /// How stage times are measured, in words for reports.
    pub fn stage_timing_note(&self) -> String {
        self.stage_timing().note()
    }

    /// Chooses how stages are timed ([`StageTiming::Timestamps`] falls back
    /// to the wall clock on a device without timestamps).
    pub fn set_stage_timing(&mut self, timing: StageTiming) {
        self.clock = Some(StageClock::new(&self.context, timing));
    }

    pub fn occupancy(&self) -> &OccupancyGrid {
        &self.grid
    }

    /// Reads the parameters back.
    pub fn params(&self) -> Vec<f32> {
        read_buffer(&self.context, &self.params, self.shape.param_count())
    }

    /// Reads back the gradient of the last step or
    /// [`Self::forward_backward`], in the parameters' layout.
    pub fn gradients(&self) -> Vec<f32> {
        read_buffer(&self.context, &self.gradients, self.shape.param_count())
    }

    fn density_range(&self) -> Range<usize> {
        let start = self.shape.grid.param_count();
        start..start + self.shape.density.param_count()
    }

    fn colour_range(&self) -> Range<usize> {
        let start = self.density_range().end;
        start..start + self.shape.colour.param_count()
    }

    /// Marches, evaluates and composites `batch` and leaves the gradient
    /// of the mean loss in the gradient buffer ([`Self::gradients`])
    /// without changing any parameter, as `CpuModel::forward_backward`.
    pub fn forward_backward(&mut self, batch: &RayBatch, step: u32) -> StepStats {
        if let Some(clock) = self.clock.as_mut() {
            clock.reset();
        }
        self.run(batch, step, false)
    }

    /// Reads each step's loss, stage times and occupancy update back at
    /// once (`false`: two or three waits for the device per step, each
    /// step's own figures, the cpu engine's order of updates) or a step
    /// late (`true`, the default: one wait per step; see
    /// [`StepReadback`]).
    pub fn set_read_back_late(&mut self, late: bool) {
        self.readback.set_late(late);
    }

    /// Records the density activation over `count` samples (forward, or
    /// with `backward` its gradient), a piece of samples at a time when the
    /// per-sample matrices exceed one storage binding.
    fn record_activation(&self, encoder: &mut wgpu::CommandEncoder, count: usize, backward: bool) {
        let ctx = &self.context;
        let b = &self.samples;
        let density_width = self.shape.density.output_width();
        let colour_width = self.shape.colour.input_width();
        let per = rows_per_piece(ctx, density_width.max(colour_width), 1);
        for piece in pieces(count, per) {
            let (groups, row_stride) = dispatch_grid(piece.len(), WORKGROUP);
            let uniforms = ActivationUniforms {
                count: piece.len() as u32,
                row_stride,
                density_width: density_width as u32,
                colour_width: colour_width as u32,
                exp_clamp: DENSITY_EXP_CLAMP,
                _pad: [0; 3],
            };
            let uniform = uniform_buffer(ctx, "ngp activation", &uniforms);
            let rows = |buffer, width: usize| {
                float_range(buffer, width * piece.start, width * piece.len())
            };
            if backward {
                self.stages.activate_backward.record_bindings(
                    ctx,
                    encoder,
                    &[
                        uniform.as_entire_buffer_binding(),
                        rows(b.density.output(), density_width),
                        rows(&b.sigma, 1),
                        rows(&b.d_sigma, 1),
                        rows(&b.d_colour_input, colour_width),
                        rows(&b.d_density_out, density_width),
                    ],
                    groups,
                );
            } else {
                self.stages.activate.record_bindings(
                    ctx,
                    encoder,
                    &[
                        uniform.as_entire_buffer_binding(),
                        rows(b.density.output(), density_width),
                        rows(&b.sigma, 1),
                        rows(&b.colour_input, colour_width),
                    ],
                    groups,
                );
            }
        }
    }

    /// Records the field at the `count` positions (and directions) in the
    /// march buffers: σ into `samples.sigma`, and with `colour` the colour
    /// network's output into `samples.colour.output()`. The networks read
    /// their parameters where they lie in the flat buffer.
    fn record_field(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        count: usize,
        colour: bool,
        mut clock: Option<&mut StageClock>,
    ) {
        let ctx = &self.context;
        let mut mark = |encoder: &mut wgpu::CommandEncoder, stage| {
            if let Some(clock) = clock.as_deref_mut() {
                clock.mark(ctx, encoder, stage);
            }
        };
        let s = &self.stages;
        let b = &self.samples;
        s.hash.record_encode(
            ctx,
            encoder,
            &self.params,
            &self.march_out.positions,
            &b.encoded,
            count,
        );
        mark(encoder, Stage::Encode);
        s.dense.record_forward_at(
            ctx,
            encoder,
            &self.params,
            self.density_range().start,
            &b.encoded,
            &b.density,
            count,
        );
        self.record_activation(encoder, count, false);
        mark(encoder, Stage::NetworksForward);
        if colour {
            let density_width = self.shape.density.output_width();
            s.sh.record_encode(
                ctx,
                encoder,
                self.shape.network.sh_degree,
                &self.march_out.directions,
                &b.colour_input,
                count,
                self.shape.colour.input_width(),
                density_width,
            );
            mark(encoder, Stage::Encode);
            s.dense.record_forward_at(
                ctx,
                encoder,
                &self.params,
                self.colour_range().start,
                &b.colour_input,
                &b.colour,
                count,
            );
            mark(encoder, Stage::NetworksForward);
        }
    }

    /// Uploads the batch's rays, targets and backgrounds, growing the ray
    /// buffers if the batch holds more rays than any before.
    fn upload_rays(&mut self, batch: &RayBatch) {
        let rays = batch.len();
        if rays > self.rays.capacity {
            self.rays = RayBuffers::new(&self.context, rays);
            self.march_out = GpuMarchBuffers::new(&self.context, rays, self.batch_samples.max(1));
        }
        self.rays
            .upload(&self.context, batch, 0..rays, &mut self.scratch);
    }

    /// One step on `batch`; with `optimise`, Adam updates the parameters.
    fn run(&mut self, batch: &RayBatch, step: u32, optimise: bool) -> StepStats {
        let rays = batch.len();
        let mut clock = self
            .clock
            .take()
            .unwrap_or_else(|| StageClock::new(&self.context, StageTiming::Timestamps));

        // Submission 1: the march, and its counters read back.
        self.upload_rays(batch);
        let (samples, kept) = if rays == 0 {
            (0, 0)
        } else {
            let params = MarchParams {
                config: MarchConfig::paper_or_environment(),
                sample_budget: self.batch_samples,
                ..MarchParams::training(self.shape.mapping, mix_seed(self.seed, step))
            };
            self.march_out.ray_count = rays;
            let mut encoder = self
                .context
                .device
                .create_command_encoder(&Default::default());
            clock.restart(&self.context, &mut encoder);
            self.stages.march.record(
                &self.context,
                &mut encoder,
                GpuGrid {
                    geometry: self.grid.geometry(),
                    bitfield: &self.bitfield,
                },
                GpuRays {
                    origins: &self.rays.origins,
                    directions: &self.rays.directions,
                },
                &params,
                &self.march_out,
            );
            clock.mark(&self.context, &mut encoder, Stage::March);
            encoder.copy_buffer_to_buffer(
                &self.march_out.counters,
                0,
                &self.counters_staging,
                0,
                8,
            );
            self.context.queue.submit([encoder.finish()]);
            let counters: Vec<u32> = read_mapped(&self.context, &self.counters_staging, 2);
            (counters[0] as usize, counters[1] as usize)
        };
        let previous = self.readback.take_previous(&self.context);
        // The samples are those of the kept rays (the rest are past the
        // budget), so they are what a ray holds on average.
        self.batch_sizer.record(kept, samples);

        // Submission 2: forward, loss, backward and Adam.
        let ctx = &self.context;
        let mut encoder = ctx.device.create_command_encoder(&Default::default());
        clock.restart(ctx, &mut encoder);
        encoder.clear_buffer(&self.gradients, 0, None);
        self.record_field(&mut encoder, samples, true, Some(&mut clock));
        let s = &self.stages;
        let b = &self.samples;
        let r = &self.rays;
        let distortion_weight = crate::field::ngp::distortion_weight(self.shape.mapping.aabb_scale);
        let distortion = (distortion_weight > 0.0 && kept > 0).then(|| Distortion {
            weight_per_ray: distortion_weight / kept as f32,
            distance_scale: self.shape.mapping.diagonal_scale(),
        });
        CompositeAndLoss {
            composite: &s.composite,
            loss: &s.loss,
        }
        .record(
            ctx,
            &mut encoder,
            r,
            step::SampleBuffers {
                sigma: &b.sigma,
                rgb: b.colour.output(),
                dt: &self.march_out.dt,
                t: &self.march_out.t,
                ray_offsets: &self.march_out.ray_offsets,
            },
            kept,
            MarchConfig::PAPER.min_transmittance,
            self.loss,
            1.0,
            distortion,
            SampleGradientBuffers {
                sigma: &b.d_sigma,
                rgb: &b.d_rgb,
            },
        );
        clock.mark(ctx, &mut encoder, Stage::Composite);
        // The networks' gradients land at their parameters' offsets of the
        // flat gradient buffer.
        s.dense.record_backward_at(
            ctx,
            &mut encoder,
            &self.params,
            self.colour_range().start,
            &b.colour_input,
            &b.colour,
            &b.d_rgb,
            &self.gradients,
            Some(&b.d_colour_input),
            samples,
        );
        self.record_activation(&mut encoder, samples, true);
        s.dense.record_backward_at(
            ctx,
            &mut encoder,
            &self.params,
            self.density_range().start,
            &b.encoded,
            &b.density,
            &b.d_density_out,
            &self.gradients,
            Some(&b.d_encoded),
            samples,
        );
        clock.mark(ctx, &mut encoder, Stage::NetworksBackward);
        // The grid's range starts at 0, so the flat gradient buffer is the
        // hash backward's own layout.
        s.hash.record_backward(
            ctx,
            &mut encoder,
            &self.march_out.positions,
            &b.d_encoded,
            &self.gradients,
            samples,
        );
        clock.mark(ctx, &mut encoder, Stage::EncodeBackward);
        if optimise {
            let weights = self.density_range().start..self.shape.param_count();
            self.adam.record_step(
                ctx,
                &mut encoder,
                &self.optimiser,
                weights,
                &self.params,
                &self.gradients,
            );
        }
        clock.mark(ctx, &mut encoder, Stage::Optimiser);
        self.readback
            .record(&mut encoder, &clock, &self.rays.loss_total);
        ctx.queue.submit([encoder.finish()]);
        let StepResults { loss, times } = self.readback.finish(ctx, &clock, previous);
        self.clock = Some(clock);

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

    /// The occupancy update of `step`: cells and points chosen on the cpu,
    /// densities evaluated on the gpu (in chunks of the sample budget, all
    /// in one submission) and read back, the EMA and bitfield on the cpu,
    /// the bitfield uploaded. Read a step late, the densities come back
    /// with the step's march read-back and the new bitfield is used from
    /// the next step on ([`Self::apply_pending_grid_update`]).
    fn update_grid(&mut self, step: u32) {
        let report = self.grid.plan_update(step, self.seed);
        let n = report.samples;
        let ctx = &self.context;
        let positions = storage_buffer(
            ctx,
            "ngp grid update positions",
            self.grid.update_positions(),
        );
        let all_sigma = zeroed_storage_buffer::<f32>(ctx, "ngp grid update sigma", n);
        let mut encoder = ctx.device.create_command_encoder(&Default::default());
        let late = self.readback.is_late();
        if late && let Some(clock) = self.clock.as_mut() {
            clock.restart(ctx, &mut encoder);
        }
        let chunk = self.batch_samples.max(1);
        for start in (0..n).step_by(chunk) {
            let count = chunk.min(n - start);
            encoder.copy_buffer_to_buffer(
                &positions,
                12 * start as u64,
                &self.march_out.positions,
                0,
                12 * count as u64,
            );
            self.record_field(&mut encoder, count, false, None);
            encoder.copy_buffer_to_buffer(
                &self.samples.sigma,
                0,
                &all_sigma,
                4 * start as u64,
                4 * count as u64,
            );
        }
        if late {
            if let Some(clock) = self.clock.as_mut() {
                clock.mark(ctx, &mut encoder, Stage::GridUpdate);
            }
            let staging = staging_buffer(ctx, "ngp grid update read-back", 4 * n as u64);
            encoder.copy_buffer_to_buffer(&all_sigma, 0, &staging, 0, 4 * n as u64);
            ctx.queue.submit([encoder.finish()]);
            self.pending_grid = Some(MapRequest::new(&staging, 4 * n as u64));
            return;
        }
        ctx.queue.submit([encoder.finish()]);
        let sigma: Vec<f32> = read_buffer(ctx, &all_sigma, n);
        self.apply_grid_update(&sigma);
    }

    /// Applies densities read a step late by [`Self::update_grid`], once
    /// the device is done with them.
    fn apply_pending_grid_update(&mut self) {
        if let Some(request) = self.pending_grid.take() {
            let sigma: Vec<f32> = request.take(&self.context);
            self.apply_grid_update(&sigma);
        }
    }

    fn apply_grid_update(&mut self, sigma: &[f32]) {
        self.grid.apply_update(sigma);
        self.context.queue.write_buffer(
            &self.bitfield,
            0,
            bytemuck::cast_slice(self.grid.bitfield()),
        );
    }

    /// World positions in the unit cube, flat (n × 3).
    fn unit_positions(&self, positions: &[Vec3]) -> Vec<f32> {
        positions
            .iter()
            .flat_map(|&p| self.shape.mapping.to_unit(p).to_array())
            .collect()
    }

    /// σ and colour at `positions` / `directions` (n × 3), evaluated on
    /// the gpu in chunks of the sample budget.
    fn radiance(&self, positions: &[f32], directions: &[f32], sigma: &mut [f32], rgb: &mut [f32]) {
        let ctx = &self.context;
        let chunk = self.batch_samples.max(1);
        for (((p, d), sigma), rgb) in positions
            .chunks(3 * chunk)
            .zip(directions.chunks(3 * chunk))
            .zip(sigma.chunks_mut(chunk))
            .zip(rgb.chunks_mut(3 * chunk))
        {
            let count = sigma.len();
            ctx.queue
                .write_buffer(&self.march_out.positions, 0, bytemuck::cast_slice(p));
            ctx.queue
                .write_buffer(&self.march_out.directions, 0, bytemuck::cast_slice(d));
            let mut encoder = ctx.device.create_command_encoder(&Default::default());
            self.record_field(&mut encoder, count, true, None);
            ctx.queue.submit([encoder.finish()]);
            sigma.copy_from_slice(&read_buffer::<f32>(ctx, &self.samples.sigma, count));
            rgb.copy_from_slice(&read_buffer::<f32>(
                ctx,
                self.samples.colour.output(),
                3 * count,
            ));
        }
    }

    /// Near and far depth that depth images map to white and black (by
    /// default the scene's, as the `render` command uses).
    pub fn depth_range(&self) -> (f32, f32) {
        self.depth_range
    }

    pub fn set_depth_range(&mut self, near: f32, far: f32) {
        self.depth_range = (near, far);
    }
}

impl RadianceModel for GpuNgp {
    fn describe(&self) -> String {
        "Instant-NGP (gpu)".into()
    }

    fn texture_render(&self) -> Option<&dyn TextureRender> {
        Some(self)
    }

    fn rays_for_next_batch(&self) -> usize {
        self.batch_sizer.rays()
    }

    fn step(&mut self, batch: &RayBatch, step: u32) -> StepStats {
        if let Some(clock) = self.clock.as_mut() {
            clock.reset();
        }
        let clock = Instant::now();
        if self.grid.is_due(step) {
            self.update_grid(step);
        }
        let grid_update = clock.elapsed().as_secs_f64();
        let mut stats = self.run(batch, step, true);
        if self.readback.is_late() {
            // The update's device time is among the stage times; the host
            // applies its densities while the device runs the step.
            self.apply_pending_grid_update();
        } else {
            stats.times.grid_update = grid_update;
        }
        stats
    }

    fn set_read_back_late(&mut self, late: bool) {
        GpuNgp::set_read_back_late(self, late);
    }

    fn render(
        &self,
        origins: &[Vec3],
        directions: &[Vec3],
        _radii: &[f32],
        background: [f32; 3],
        out: &mut [RenderedPixel],
    ) {
        render_through_grid(
            &self.grid,
            &self.shape.mapping,
            origins,
            directions,
            background,
            &MarchConfig::paper_or_environment(),
            self.batch_samples.max(1),
            |samples, sigma, rgb| {
                self.radiance(samples.positions, samples.directions, sigma, rgb);
                if let Some(crop) = &self.crop {
                    crop_densities(crop, &self.shape.mapping, samples.positions, sigma);
                }
            },
            out,
        );
    }

    fn set_crop(&mut self, crop: Option<CropBox>) -> Result<(), String> {
        self.crop = crop;
        Ok(())
    }

    /// As the cpu engine answers it: the field's σ, zero in cells the
    /// occupancy grid marks empty (where rendering never looks).
    fn density_at(
        &self,
        positions: &[Vec3],
        _footprint: f32,
        sigma: &mut [f32],
    ) -> Result<(), String> {
        let unit = self.unit_positions(positions);
        // σ does not depend on the direction; any unit vector will do.
        let directions = [0.0, 0.0, 1.0].repeat(positions.len());
        let mut rgb = vec![0.0; 3 * positions.len()];
        self.radiance(&unit, &directions, sigma, &mut rgb);
        for (s, p) in sigma.iter_mut().zip(unit.chunks_exact(3)) {
            if !self.grid.occupied_at(Vec3::from_slice(p)) {
                *s = 0.0;
            }
        }
        Ok(())
    }

    fn colour_at(
        &self,
        positions: &[Vec3],
        directions: &[Vec3],
        _footprint: f32,
        rgb: &mut [f32],
    ) -> Result<(), String> {
        let unit = self.unit_positions(positions);
        let directions: Vec<f32> = directions.iter().flat_map(|d| d.to_array()).collect();
        let mut sigma = vec![0.0; positions.len()];
        self.radiance(&unit, &directions, &mut sigma, rgb);
        Ok(())
    }

    fn save(&self) -> Checkpoint {
        let adam = self.adam.read_state(&self.context);
        ModelState {
            header: ModelHeader {
                model: "ngp".into(),
                loss: self.loss,
                seed: self.seed,
                adam_step: adam.step,
                samples_per_ray: self.batch_sizer.samples_per_ray(),
                param_count: self.shape.param_count(),
                sampling: None,
                used_fraction: None,
                grid_extent: Some(self.shape.grid.config().extent),
            },
            params: self.params(),
            adam,
            occupancy: Some(self.grid.values().to_vec()),
        }
        .into_checkpoint()
    }

    fn load(&mut self, checkpoint: &Checkpoint) -> Result<(), String> {
        let state = ModelState::from_checkpoint(
            checkpoint,
            "ngp",
            self.shape.param_count(),
            Some(self.grid.values().len()),
        )?;
        state
            .header
            .check_grid_extent(self.shape.grid.config().extent)?;
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
        if let Some(occupancy) = &state.occupancy {
            self.grid.values_mut().copy_from_slice(occupancy);
        }
        self.grid.build_bitfield();
        queue.write_buffer(
            &self.bitfield,
            0,
            bytemuck::cast_slice(self.grid.bitfield()),
        );
        self.batch_sizer
            .set_samples_per_ray(state.header.samples_per_ray);
        self.loss = state.header.loss;
        self.seed = state.header.seed;
        Ok(())
    }

    fn memory_bytes(&self) -> usize {
        let params = self.shape.param_count();
        // Parameters, gradients and Adam's four arrays on the gpu.
        let flat = params * 4 * 6;
        // Per-sample floats: march (3 + 3 + 1 + 1), encoded and its
        // gradient, σ and its gradient, colour input and its gradient,
        // density output gradient, colour gradient, and the two networks'
        // activations and gradient ping-pong buffers.
        let widths = |w: &[usize]| -> usize {
            let max = *w.iter().max().unwrap_or(&0);
            w[1..].iter().sum::<usize>() + 2 * max
        };
        let per_sample = 8
            + 2 * self.shape.grid.output_width()
            + 2
            + 2 * self.shape.colour.input_width()
            + self.shape.density.output_width()
            + 3
            + widths(&self.shape.density.widths)
            + widths(&self.shape.colour.widths);
        flat + per_sample * 4 * self.batch_samples
            + self.rays.bytes()
            + self.grid.values().len() * 4
            + self.grid.bitfield().len() * 4
    }
}

impl TextureRender for GpuNgp {
    fn render_to_texture(
        &self,
        camera: &Camera,
        mode: RenderMode,
        background: [f32; 3],
        target: &wgpu::Texture,
    ) -> Result<(), String> {
        GpuNgp::render_to_texture(self, camera, mode, background, target).map_err(|e| e.to_string())
    }

    fn stage_timing_note(&self) -> String {
        GpuNgp::stage_timing_note(self)
    }
}

/// The uniforms as the shaders declare them (`engine::gpu::mirror`).
#[cfg(test)]
mod uniform_mirrors {
    use super::*;
    use crate::engine::gpu::mirror::assert_mirrors;

    #[test]
    fn activationuniforms_of_ngp_density_mirror_the_shader() {
        assert_mirrors!(
            include_str!("../../../../shaders/ngp_density.wgsl"),
            "Params",
            ActivationUniforms,
            [count, row_stride, density_width, colour_width, exp_clamp]
        );
    }
    #[test]
    fn activationuniforms_of_ngp_density_backward_mirror_the_shader() {
        assert_mirrors!(
            include_str!("../../../../shaders/ngp_density_backward.wgsl"),
            "Params",
            ActivationUniforms,
            [count, row_stride, density_width, colour_width, exp_clamp]
        );
    }
}
