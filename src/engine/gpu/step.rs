//! What every model driver on the `gpu` engine does with its rays, whatever
//! its sampler and field: the per-ray buffers of a batch and their upload,
//! and compositing → loss → compositing's backward pass, recorded into one
//! command encoder. The recipe driver ([`super::model::GpuModel`]) calls
//! these for every level it composites.

use std::ops::Range;

use super::composite::{
    CompositeGradientBuffers, CompositeOutputBuffers, GpuComposite, RayBatchBuffers,
};
use super::kernel::{MapRequest, Recorder, staging_buffer, zeroed_storage_buffer};
use super::loss::{GpuLoss, LossBuffers};
use super::timing::{PendingTimes, StageClock};
use crate::engine::gpu::GpuContext;
use crate::engine::shared::composite::Distortion;
use crate::field::common::LossKind;
use crate::model::StageTimes;
use crate::model::batch::RayBatch;

/// Buffers that hold one value (or colour) per ray of a batch.
pub struct RayBuffers {
    /// Rays the buffers hold.
    pub capacity: usize,
    /// R × 3, world space.
    pub origins: wgpu::Buffer,
    /// R × 3, unit length.
    pub directions: wgpu::Buffer,
    /// R cone radii at unit distance (Mip-NeRF's frustums).
    pub radii: wgpu::Buffer,
    /// R training images (u32), whose appearance vectors the rays' samples
    /// take in a model with appearance embeddings.
    pub images: wgpu::Buffer,
    /// R × 3 target colours, composited on the ray's background.
    pub targets: wgpu::Buffer,
    /// R × 3.
    pub backgrounds: wgpu::Buffer,
    /// R × 3 composited colours.
    pub rgb: wgpu::Buffer,
    pub opacity: wgpu::Buffer,
    pub depth: wgpu::Buffer,
    /// Samples before each ray's cut (u32).
    pub samples_used: wgpu::Buffer,
    /// R × 3: ∂loss/∂colour.
    pub d_rgb: wgpu::Buffer,
    /// Each ray's share of the mean loss.
    pub ray_loss: wgpu::Buffer,
    /// R × 3 (compositing writes it; training ignores it).
    pub d_background: wgpu::Buffer,
    /// One f32: the mean loss of the last [`record_composite_and_loss`].
    pub loss_total: wgpu::Buffer,
}

impl RayBuffers {
    pub fn new(context: &GpuContext, capacity: usize) -> Self {
        let f = |label: &str, n: usize| zeroed_storage_buffer::<f32>(context, label, n);
        Self {
            capacity,
            origins: f("ray origins", 3 * capacity),
            directions: f("ray directions", 3 * capacity),
            radii: f("ray radii", capacity),
            images: zeroed_storage_buffer::<u32>(context, "ray images", capacity),
            targets: f("ray targets", 3 * capacity),
            backgrounds: f("ray backgrounds", 3 * capacity),
            rgb: f("ray rgb", 3 * capacity),
            opacity: f("ray opacity", capacity),
            depth: f("ray depth", capacity),
            samples_used: zeroed_storage_buffer::<u32>(context, "ray samples used", capacity),
            d_rgb: f("d ray rgb", 3 * capacity),
            ray_loss: f("ray loss", capacity),
            d_background: f("d ray background", 3 * capacity),
            loss_total: f("loss total", 1),
        }
    }

    /// Bytes on the device.
    pub fn bytes(&self) -> usize {
        self.capacity * 4 * (3 * 7 + 6) + 4
    }

    /// Writes rays `rays` of `batch` (origins, directions, cone radii,
    /// targets, backgrounds and, where the batch names them, training
    /// images) to the start of the buffers; the queue applies the
    /// writes before its next submission. `scratch` is reused between
    /// calls.
    pub fn upload(
        &self,
        context: &GpuContext,
        batch: &RayBatch,
        rays: Range<usize>,
        scratch: &mut Vec<f32>,
    ) {
        assert!(
            rays.len() <= self.capacity,
            "{} rays exceed the buffers' {}",
            rays.len(),
            self.capacity
        );
        if rays.is_empty() {
            return;
        }
        let queue = &context.queue;
        for (vectors, buffer) in [
            (&batch.origins, &self.origins),
            (&batch.directions, &self.directions),
        ] {
            scratch.clear();
            scratch.extend(vectors[rays.clone()].iter().flat_map(|v| v.to_array()));
            queue.write_buffer(buffer, 0, bytemuck::cast_slice(scratch));
        }
        for (colours, buffer) in [
            (&batch.targets, &self.targets),
            (&batch.backgrounds, &self.backgrounds),
        ] {
            queue.write_buffer(buffer, 0, bytemuck::cast_slice(&colours[rays.clone()]));
        }
        if let Some(images) = batch.images.get(rays.clone()) {
            queue.write_buffer(&self.images, 0, bytemuck::cast_slice(images));
        }
        self.upload_radii(
            context,
            batch.radii.get(rays.clone()).unwrap_or(&[]),
            rays.len(),
        );
    }

    /// Writes `count` cone radii to the start of the radii buffer: `radii`,
    /// or zeros where it is shorter (a batch made without cones: each ray is
    /// then a line, its frustums segments with no width).
    pub fn upload_radii(&self, context: &GpuContext, radii: &[f32], count: usize) {
        let count = count.min(self.capacity);
        if count == 0 {
            return;
        }
        let queue = &context.queue;
        if radii.len() >= count {
            queue.write_buffer(&self.radii, 0, bytemuck::cast_slice(&radii[..count]));
        } else {
            let mut padded = radii.to_vec();
            padded.resize(count, 0.0);
            queue.write_buffer(&self.radii, 0, bytemuck::cast_slice(&padded));
        }
    }

    /// The compositing input of `samples`' σ, colours, intervals, distances
    /// and per-ray offsets, over these rays' backgrounds.
    pub fn batch<'a>(
        &'a self,
        samples: SampleBuffers<'a>,
        ray_count: usize,
    ) -> RayBatchBuffers<'a> {
        RayBatchBuffers {
            density: samples.sigma,
            rgb: samples.rgb,
            dt: samples.dt,
            t: samples.t,
            ray_offsets: samples.ray_offsets,
            background: &self.backgrounds,
            ray_count,
        }
    }
}

/// The per-sample values compositing reads.
#[derive(Debug, Clone, Copy)]
pub struct SampleBuffers<'a> {
    /// S densities (activated).
    pub sigma: &'a wgpu::Buffer,
    /// S × 3 colours.
    pub rgb: &'a wgpu::Buffer,
    /// S interval lengths.
    pub dt: &'a wgpu::Buffer,
    /// S distances along the ray.
    pub t: &'a wgpu::Buffer,
    /// R + 1 offsets (u32).
    pub ray_offsets: &'a wgpu::Buffer,
}

/// Where a level's per-sample gradients go.
#[derive(Debug, Clone, Copy)]
pub struct SampleGradientBuffers<'a> {
    /// S: ∂loss/∂σ.
    pub sigma: &'a wgpu::Buffer,
    /// S × 3: ∂loss/∂colour.
    pub rgb: &'a wgpu::Buffer,
}

/// How a level is composited and scored: compositing stops where the
/// transmittance falls below `min_transmittance`; the loss is `loss`, its
/// gradient scaled by `gradient_weight`; with the distortion loss if
/// asked.
#[derive(Debug, Clone, Copy)]
pub struct LevelLoss {
    pub min_transmittance: f32,
    pub loss: LossKind,
    pub gradient_weight: f32,
    pub distortion: Option<Distortion<f32>>,
}

/// The compositing and loss kernels.
pub struct CompositeAndLoss<'a> {
    pub composite: &'a GpuComposite,
    pub loss: &'a GpuLoss,
}

impl CompositeAndLoss<'_> {
    /// Records compositing of `ray_count` rays from `samples` over the
    /// rays' backgrounds (into `rays.rgb`, `opacity`, `depth`,
    /// `samples_used`), the loss against `rays.targets` (its mean into
    /// `rays.loss_total`, its gradient times the level's weight into
    /// `rays.d_rgb`), and compositing's backward pass into `gradients`,
    /// as `level` says.
    pub fn record(
        &self,
        rec: &mut Recorder,
        rays: &RayBuffers,
        samples: SampleBuffers,
        ray_count: usize,
        level: LevelLoss,
        gradients: SampleGradientBuffers,
    ) {
        let LevelLoss {
            min_transmittance,
            loss,
            gradient_weight,
            distortion,
        } = level;
        let batch = rays.batch(samples, ray_count);
        self.composite.record_forward(
            rec,
            &batch,
            min_transmittance,
            &CompositeOutputBuffers {
                rgb: &rays.rgb,
                opacity: &rays.opacity,
                depth: &rays.depth,
                samples_used: &rays.samples_used,
            },
        );
        self.loss.record_weighted(
            rec,
            loss,
            &LossBuffers {
                predicted: &rays.rgb,
                target: &rays.targets,
                gradient: &rays.d_rgb,
                ray_loss: &rays.ray_loss,
                total: &rays.loss_total,
                ray_count,
            },
            gradient_weight,
        );
        self.composite.record_backward(
            rec,
            &batch,
            min_transmittance,
            &rays.d_rgb,
            distortion,
            &CompositeGradientBuffers {
                density: gradients.sigma,
                rgb: gradients.rgb,
                background: &rays.d_background,
            },
        );
    }
}

/// What a step computed on the device and the host reports: the mean loss
/// and the time of each stage.
#[derive(Debug, Clone, Copy)]
pub struct StepResults {
    pub loss: f32,
    pub times: StageTimes,
}

/// How a driver reads a step's loss and stage times back.
///
/// At once, a step waits for the device twice: for the march's counters,
/// which size everything after it, and for the loss at the end; the device
/// idles while the host records between them. Read a step late (the
/// default), the loss and times of step N are taken right after step N + 1's
/// march read-back, which has waited for the device anyway: one blocking
/// read-back per step, and each step reports the previous step's loss and
/// times (the first step, having none before it, waits for its own, and
/// the second reports the first's again).
pub struct StepReadback {
    loss_staging: wgpu::Buffer,
    late: bool,
    pending: Option<(MapRequest, PendingTimes)>,
    /// Results read at once, to report again as the next step's previous.
    repeat: Option<StepResults>,
}

impl StepReadback {
    pub fn new(context: &GpuContext) -> Self {
        Self {
            loss_staging: staging_buffer(context, "step loss read-back", 4),
            late: true,
            pending: None,
            repeat: None,
        }
    }

    /// Read each step's results at once (tests that compare a step with
    /// the cpu engine's), or a step late.
    pub fn set_late(&mut self, late: bool) {
        self.late = late;
    }

    pub fn is_late(&self) -> bool {
        self.late
    }

    /// The previous step's results, if a late read is pending. Call after
    /// this step's blocking read-back (so nothing waits) and before
    /// submitting this step's [`Self::record`].
    pub fn take_previous(&mut self, context: &GpuContext) -> Option<StepResults> {
        let repeat = self.repeat.take();
        self.pending
            .take()
            .map(|(loss, times)| StepResults {
                loss: loss.take::<f32>(context)[0],
                times: times.take(context),
            })
            .or(repeat)
    }

    /// Records the step's loss copy and the clock's resolve, last in the
    /// step's final encoder.
    pub fn record(&self, rec: &mut Recorder, clock: &StageClock, loss_total: &wgpu::Buffer) {
        clock.resolve(rec);
        rec.encoder
            .copy_buffer_to_buffer(loss_total, 0, &self.loss_staging, 0, 4);
    }

    /// After submitting the encoder holding [`Self::record`]: the results
    /// to report for this step, this step's own when read at once, else
    /// `previous` (from [`Self::take_previous`]) while this step's wait for
    /// the next.
    pub fn finish(
        &mut self,
        context: &GpuContext,
        clock: &StageClock,
        previous: Option<StepResults>,
    ) -> StepResults {
        let loss = MapRequest::new(&self.loss_staging, 4);
        let times = clock.read_later();
        match previous {
            Some(previous) if self.late => {
                self.pending = Some((loss, times));
                previous
            }
            _ => {
                let own = StepResults {
                    loss: loss.take::<f32>(context)[0],
                    times: times.take(context),
                };
                self.repeat = self.late.then_some(own);
                own
            }
        }
    }
}
