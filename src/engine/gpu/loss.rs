//! The photometric loss on the GPU (`shaders/loss_gradient.wgsl`,
//! `shaders/loss_sum.wgsl`): per-ray value and gradient, then the batch
//! mean, as [`crate::engine::cpu::loss`].

use super::composite::grid;
use super::kernel::{
    Kernel, Recorder, read_buffer, storage_buffer, uniform_buffer, zeroed_storage_buffer,
};
use crate::engine::gpu::{GpuContext, GpuError};
use crate::field::common::{HUBER_DELTA, LossKind};

/// Threads per workgroup in loss_gradient.wgsl.
const WORKGROUP: u32 = 64;

#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct GradientParams {
    ray_count: u32,
    row_stride: u32,
    kind: u32,
    huber_delta: f32,
    scale: f32,
    gradient_weight: f32,
    _pad: [u32; 2],
}

#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct SumParams {
    count: u32,
    _pad: [u32; 3],
}

/// Where the loss pass reads and writes.
#[derive(Debug, Clone, Copy)]
pub struct LossBuffers<'a> {
    /// R × 3 rendered colours.
    pub predicted: &'a wgpu::Buffer,
    /// R × 3 target colours (already composited on the ray's background).
    pub target: &'a wgpu::Buffer,
    /// R × 3: ∂(mean loss)/∂predicted.
    pub gradient: &'a wgpu::Buffer,
    /// R: each ray's share of the mean (sums to the mean).
    pub ray_loss: &'a wgpu::Buffer,
    /// One f32: the mean loss over rays × channels.
    pub total: &'a wgpu::Buffer,
    pub ray_count: usize,
}

/// The compiled loss kernels.
pub struct GpuLoss {
    gradient: Kernel,
    sum: Kernel,
}

impl GpuLoss {
    pub fn new(context: &GpuContext) -> Result<Self, GpuError> {
        Ok(Self {
            gradient: Kernel::new(
                context,
                "loss_gradient",
                include_str!("../../../shaders/loss_gradient.wgsl"),
                "main",
            )?,
            sum: Kernel::new(
                context,
                "loss_sum",
                include_str!("../../../shaders/loss_sum.wgsl"),
                "main",
            )?,
        })
    }

    /// Records the gradient, the per-ray losses and their sum.
    pub fn record(&self, rec: &mut Recorder, kind: LossKind, buffers: &LossBuffers) {
        self.record_weighted(rec, kind, buffers, 1.0);
    }

    /// As [`Self::record`], the gradient multiplied by `gradient_weight`
    /// (a level's loss weight times the chunk's share of the batch's rays);
    /// the loss values stay the plain mean.
    pub fn record_weighted(
        &self,
        rec: &mut Recorder,
        kind: LossKind,
        buffers: &LossBuffers,
        gradient_weight: f32,
    ) {
        let context = rec.context;
        let rays = buffers.ray_count;
        let (groups, row_stride) = grid(rays, WORKGROUP);
        let params = GradientParams {
            ray_count: rays as u32,
            row_stride,
            kind: match kind {
                LossKind::Huber => 0,
                LossKind::L2 => 1,
            },
            huber_delta: HUBER_DELTA,
            scale: if rays == 0 {
                0.0
            } else {
                1.0 / (3 * rays) as f32
            },
            gradient_weight,
            _pad: [0; 2],
        };
        let uniform = uniform_buffer(context, "loss params", &params);
        self.gradient.record(
            rec,
            &[
                &uniform,
                buffers.predicted,
                buffers.target,
                buffers.gradient,
                buffers.ray_loss,
            ],
            groups,
        );
        let sum_params = SumParams {
            count: rays as u32,
            _pad: [0; 3],
        };
        let sum_uniform = uniform_buffer(context, "loss sum params", &sum_params);
        self.sum.record(
            rec,
            &[&sum_uniform, buffers.ray_loss, buffers.total],
            [1, 1, 1],
        );
    }

    /// Records the sum of the first `count` of `values` into `total[0]`
    /// (one f32), as the loss's sum over rays.
    pub fn record_sum(
        &self,
        rec: &mut Recorder,
        values: &wgpu::Buffer,
        count: usize,
        total: &wgpu::Buffer,
    ) {
        let sum_params = SumParams {
            count: count as u32,
            _pad: [0; 3],
        };
        let sum_uniform = uniform_buffer(rec.context, "sum params", &sum_params);
        self.sum
            .record(rec, &[&sum_uniform, values, total], [1, 1, 1]);
    }

    /// Uploads, runs and reads back the mean loss and its gradient (tests
    /// and tools).
    pub fn loss_and_gradient(
        &self,
        context: &GpuContext,
        kind: LossKind,
        predicted: &[f32],
        target: &[f32],
    ) -> (f32, Vec<f32>) {
        assert!(predicted.len() == target.len() && predicted.len().is_multiple_of(3));
        let rays = predicted.len() / 3;
        let predicted_buffer = storage_buffer(context, "loss predicted", predicted);
        let target_buffer = storage_buffer(context, "loss target", target);
        let gradient = zeroed_storage_buffer::<f32>(context, "loss gradient", 3 * rays);
        let ray_loss = zeroed_storage_buffer::<f32>(context, "loss per ray", rays);
        let total = zeroed_storage_buffer::<f32>(context, "loss total", 1);
        let mut rec = Recorder::new(context);
        self.record(
            &mut rec,
            kind,
            &LossBuffers {
                predicted: &predicted_buffer,
                target: &target_buffer,
                gradient: &gradient,
                ray_loss: &ray_loss,
                total: &total,
                ray_count: rays,
            },
        );
        rec.submit();
        (
            read_buffer::<f32>(context, &total, 1)[0],
            read_buffer(context, &gradient, 3 * rays),
        )
    }
}

/// The uniforms as the shaders declare them (`engine::gpu::mirror`).
#[cfg(test)]
mod uniform_mirrors {
    use super::*;
    use crate::engine::gpu::mirror::assert_mirrors;

    #[test]
    fn gradientparams_of_loss_gradient_mirror_the_shader() {
        assert_mirrors!(
            include_str!("../../../shaders/loss_gradient.wgsl"),
            "Params",
            GradientParams,
            [
                ray_count,
                row_stride,
                kind,
                huber_delta,
                scale,
                gradient_weight
            ]
        );
    }
    #[test]
    fn sumparams_of_loss_sum_mirror_the_shader() {
        assert_mirrors!(
            include_str!("../../../shaders/loss_sum.wgsl"),
            "Params",
            SumParams,
            [count]
        );
    }
}
