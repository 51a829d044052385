//! Batched volume rendering on the GPU (`shaders/composite_forward.wgsl`,
//! `shaders/composite_backward.wgsl`): one invocation per ray, the same
//! maths, layout and early termination as
//! [`crate::engine::cpu::composite_batch`]; and each sample's weight
//! (`shaders/composite_weights.wgsl`), which importance sampling draws from.
//! `shaders/volume_common.wgsl` is prepended to each kernel.

use super::kernel::{
    Kernel, Recorder, read_buffer, storage_buffer, uniform_buffer, zeroed_storage_buffer,
};
use crate::engine::gpu::{GpuContext, GpuError};
use crate::engine::shared::composite::{Distortion, RayBatch};

pub(crate) const VOLUME_COMMON: &str = include_str!("../../../shaders/volume_common.wgsl");

/// Threads per workgroup in the compositing kernels.
const WORKGROUP: u32 = 64;
/// Workgroups per dispatch dimension (wgpu's default limit; adapters may
/// allow more, none allow less).
const MAX_GROUPS_PER_DIMENSION: u32 = 65535;

/// The dispatch for `count` invocations at `workgroup` per group, as a 2-D
/// grid when one dimension is not enough, and the invocations per row of
/// that grid (kernels index `id.x + id.y · row_stride`).
pub(crate) fn grid(count: usize, workgroup: u32) -> ([u32; 3], u32) {
    let groups = u32::try_from(count.div_ceil(workgroup as usize))
        .expect("dispatch too large")
        .max(1);
    let rows = groups.div_ceil(MAX_GROUPS_PER_DIMENSION);
    let columns = groups.div_ceil(rows);
    ([columns, rows, 1], columns * workgroup)
}

#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct Params {
    ray_count: u32,
    row_stride: u32,
    min_transmittance: f32,
    /// λ′ of the distortion loss (0: none).
    distortion_weight: f32,
    distance_scale: f32,
    _pad: [u32; 3],
}

/// A batch of rays on the GPU, in the layout of [`RayBatch`].
#[derive(Debug, Clone, Copy)]
pub struct RayBatchBuffers<'a> {
    /// S densities (activated).
    pub density: &'a wgpu::Buffer,
    /// S × 3 colours (after the sigmoid).
    pub rgb: &'a wgpu::Buffer,
    /// S interval lengths.
    pub dt: &'a wgpu::Buffer,
    /// S distances along the ray.
    pub t: &'a wgpu::Buffer,
    /// R + 1 offsets (u32).
    pub ray_offsets: &'a wgpu::Buffer,
    /// R × 3 background colours.
    pub background: &'a wgpu::Buffer,
    /// R.
    pub ray_count: usize,
}

/// Where the forward pass writes, per ray.
#[derive(Debug, Clone, Copy)]
pub struct CompositeOutputBuffers<'a> {
    /// R × 3.
    pub rgb: &'a wgpu::Buffer,
    /// R.
    pub opacity: &'a wgpu::Buffer,
    /// R.
    pub depth: &'a wgpu::Buffer,
    /// R (u32).
    pub samples_used: &'a wgpu::Buffer,
}

/// Where the backward pass writes.
#[derive(Debug, Clone, Copy)]
pub struct CompositeGradientBuffers<'a> {
    /// S: ∂L/∂σ.
    pub density: &'a wgpu::Buffer,
    /// S × 3: ∂L/∂c.
    pub rgb: &'a wgpu::Buffer,
    /// R × 3: ∂L/∂background (always written; training may ignore it).
    pub background: &'a wgpu::Buffer,
}

/// What [`GpuComposite::forward`] reads back.
#[derive(Debug, Clone, PartialEq)]
pub struct ForwardResult {
    pub rgb: Vec<f32>,
    pub opacity: Vec<f32>,
    pub depth: Vec<f32>,
    pub samples_used: Vec<u32>,
}

/// What [`GpuComposite::backward`] reads back.
#[derive(Debug, Clone, PartialEq)]
pub struct BackwardResult {
    pub density: Vec<f32>,
    pub rgb: Vec<f32>,
    pub background: Vec<f32>,
}

/// The compiled compositing kernels.
pub struct GpuComposite {
    forward: Kernel,
    backward: Kernel,
    weights: Kernel,
}

impl GpuComposite {
    pub fn new(context: &GpuContext) -> Result<Self, GpuError> {
        let kernel = |name: &str, source: &str| {
            Kernel::new(context, name, &format!("{VOLUME_COMMON}\n{source}"), "main")
        };
        Ok(Self {
            forward: kernel(
                "composite_forward",
                include_str!("../../../shaders/composite_forward.wgsl"),
            )?,
            backward: kernel(
                "composite_backward",
                include_str!("../../../shaders/composite_backward.wgsl"),
            )?,
            weights: kernel(
                "composite_weights",
                include_str!("../../../shaders/composite_weights.wgsl"),
            )?,
        })
    }

    /// Records each sample's weight Tᵢ (1 − e^{−σᵢ dtᵢ}) into `weights` (S),
    /// zero from each ray's cut on, as
    /// [`crate::engine::cpu::composite_batch::sample_weights`].
    pub fn record_weights(
        &self,
        rec: &mut Recorder,
        batch: &RayBatchBuffers,
        min_transmittance: f32,
        weights: &wgpu::Buffer,
    ) {
        let context = rec.context;
        let (uniform, groups) = Self::params(context, batch.ray_count, min_transmittance);
        self.weights.record(
            rec,
            &[
                &uniform,
                batch.density,
                batch.dt,
                batch.ray_offsets,
                weights,
            ],
            groups,
        );
    }

    /// Uploads `batch`, records [`Self::record_weights`] and reads the
    /// weights back (tests and tools).
    pub fn weights(
        &self,
        context: &GpuContext,
        batch: &RayBatch<f32>,
        min_transmittance: f32,
    ) -> Vec<f32> {
        let uploaded = Upload::new(context, batch);
        let samples = batch.sample_count();
        let weights = zeroed_storage_buffer::<f32>(context, "composite weights", samples);
        let mut rec = Recorder::new(context);
        self.record_weights(
            &mut rec,
            &uploaded.buffers(batch.ray_count()),
            min_transmittance,
            &weights,
        );
        rec.submit();
        read_buffer(context, &weights, samples)
    }

    fn params(
        context: &GpuContext,
        ray_count: usize,
        min_transmittance: f32,
    ) -> (wgpu::Buffer, [u32; 3]) {
        Self::params_with(context, ray_count, min_transmittance, None)
    }

    fn params_with(
        context: &GpuContext,
        ray_count: usize,
        min_transmittance: f32,
        distortion: Option<Distortion<f32>>,
    ) -> (wgpu::Buffer, [u32; 3]) {
        let (groups, row_stride) = grid(ray_count, WORKGROUP);
        let params = Params {
            ray_count: ray_count as u32,
            row_stride,
            min_transmittance,
            distortion_weight: distortion.map_or(0.0, |d| d.weight_per_ray),
            distance_scale: distortion.map_or(0.0, |d| d.distance_scale),
            _pad: [0; 3],
        };
        (uniform_buffer(context, "composite params", &params), groups)
    }

    /// Records the forward pass: colour, opacity, depth and samples used
    /// per ray.
    pub fn record_forward(
        &self,
        rec: &mut Recorder,
        batch: &RayBatchBuffers,
        min_transmittance: f32,
        out: &CompositeOutputBuffers,
    ) {
        let context = rec.context;
        let (uniform, groups) = Self::params(context, batch.ray_count, min_transmittance);
        self.forward.record(
            rec,
            &[
                &uniform,
                batch.density,
                batch.rgb,
                batch.dt,
                batch.t,
                batch.ray_offsets,
                batch.background,
                out.rgb,
                out.opacity,
                out.depth,
                out.samples_used,
            ],
            groups,
        );
    }

    /// Records the backward pass for ∂L/∂rgb per ray (R × 3 in `d_rgb`),
    /// with the distortion loss if asked.
    /// Every sample of every ray is written (zero after a ray's cut).
    pub fn record_backward(
        &self,
        rec: &mut Recorder,
        batch: &RayBatchBuffers,
        min_transmittance: f32,
        d_rgb: &wgpu::Buffer,
        distortion: Option<Distortion<f32>>,
        gradients: &CompositeGradientBuffers,
    ) {
        let context = rec.context;
        let (uniform, groups) =
            Self::params_with(context, batch.ray_count, min_transmittance, distortion);
        self.backward.record(
            rec,
            &[
                &uniform,
                batch.density,
                batch.rgb,
                batch.dt,
                batch.ray_offsets,
                batch.background,
                d_rgb,
                gradients.density,
                gradients.rgb,
                gradients.background,
                batch.t,
            ],
            groups,
        );
    }

    /// Uploads `batch`, runs the forward pass and reads it back (tests and
    /// tools).
    pub fn forward(
        &self,
        context: &GpuContext,
        batch: &RayBatch<f32>,
        min_transmittance: f32,
    ) -> ForwardResult {
        let uploaded = Upload::new(context, batch);
        let rays = batch.ray_count();
        let rgb = zeroed_storage_buffer::<f32>(context, "composite rgb", 3 * rays);
        let opacity = zeroed_storage_buffer::<f32>(context, "composite opacity", rays);
        let depth = zeroed_storage_buffer::<f32>(context, "composite depth", rays);
        let samples_used = zeroed_storage_buffer::<u32>(context, "composite samples used", rays);
        let mut rec = Recorder::new(context);
        self.record_forward(
            &mut rec,
            &uploaded.buffers(rays),
            min_transmittance,
            &CompositeOutputBuffers {
                rgb: &rgb,
                opacity: &opacity,
                depth: &depth,
                samples_used: &samples_used,
            },
        );
        rec.submit();
        ForwardResult {
            rgb: read_buffer(context, &rgb, 3 * rays),
            opacity: read_buffer(context, &opacity, rays),
            depth: read_buffer(context, &depth, rays),
            samples_used: read_buffer(context, &samples_used, rays),
        }
    }

    /// Uploads `batch` and `d_rgb`, runs the backward pass and reads the
    /// gradients back (tests and tools).
    pub fn backward(
        &self,
        context: &GpuContext,
        batch: &RayBatch<f32>,
        min_transmittance: f32,
        d_rgb: &[f32],
        distortion: Option<Distortion<f32>>,
    ) -> BackwardResult {
        let uploaded = Upload::new(context, batch);
        let rays = batch.ray_count();
        let samples = batch.sample_count();
        assert!(d_rgb.len() >= 3 * rays);
        let d_rgb = storage_buffer(context, "composite d_rgb", &d_rgb[..3 * rays]);
        let density = zeroed_storage_buffer::<f32>(context, "composite d_density", samples);
        let rgb = zeroed_storage_buffer::<f32>(context, "composite d_colour", 3 * samples);
        let background = zeroed_storage_buffer::<f32>(context, "composite d_background", 3 * rays);
        let mut rec = Recorder::new(context);
        self.record_backward(
            &mut rec,
            &uploaded.buffers(rays),
            min_transmittance,
            &d_rgb,
            distortion,
            &CompositeGradientBuffers {
                density: &density,
                rgb: &rgb,
                background: &background,
            },
        );
        rec.submit();
        BackwardResult {
            density: read_buffer(context, &density, samples),
            rgb: read_buffer(context, &rgb, 3 * samples),
            background: read_buffer(context, &background, 3 * rays),
        }
    }
}

/// A [`RayBatch`] copied to the GPU.
struct Upload {
    density: wgpu::Buffer,
    rgb: wgpu::Buffer,
    dt: wgpu::Buffer,
    t: wgpu::Buffer,
    ray_offsets: wgpu::Buffer,
    background: wgpu::Buffer,
}

impl Upload {
    fn new(context: &GpuContext, batch: &RayBatch<f32>) -> Self {
        let samples = batch.sample_count();
        let rays = batch.ray_count();
        Self {
            density: storage_buffer(context, "composite density", &batch.density[..samples]),
            rgb: storage_buffer(context, "composite rgb in", &batch.rgb[..3 * samples]),
            dt: storage_buffer(context, "composite dt", &batch.dt[..samples]),
            t: storage_buffer(context, "composite t", &batch.t[..samples]),
            ray_offsets: storage_buffer(context, "composite ray offsets", batch.ray_offsets),
            background: storage_buffer(
                context,
                "composite background",
                &batch.background[..3 * rays],
            ),
        }
    }

    fn buffers(&self, ray_count: usize) -> RayBatchBuffers<'_> {
        RayBatchBuffers {
            density: &self.density,
            rgb: &self.rgb,
            dt: &self.dt,
            t: &self.t,
            ray_offsets: &self.ray_offsets,
            background: &self.background,
            ray_count,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn grid_covers_every_invocation_within_the_limits() {
        for count in [
            0usize,
            1,
            63,
            64,
            65,
            65535 * 64,
            65535 * 64 + 1,
            16_787_456,
            40_000_000,
        ] {
            for workgroup in [64u32, 256] {
                let ([x, y, z], row_stride) = grid(count, workgroup);
                assert!(x <= MAX_GROUPS_PER_DIMENSION && y <= MAX_GROUPS_PER_DIMENSION && z == 1);
                assert_eq!(row_stride, x * workgroup);
                let covered = x as usize * y as usize * workgroup as usize;
                assert!(covered >= count, "{count}: {covered}");
                // Less than one row of waste.
                assert!(
                    covered < count.max(1) + row_stride as usize,
                    "{count}: {covered}"
                );
            }
        }
    }
}

/// The uniforms as the shaders declare them (`engine::gpu::mirror`).
#[cfg(test)]
mod uniform_mirrors {
    use super::*;
    use crate::engine::gpu::mirror::assert_mirrors;

    // The forward pass and the weights read the leading fields only.
    #[test]
    fn params_of_composite_forward_mirror_the_shader() {
        assert_mirrors!(
            include_str!("../../../shaders/composite_forward.wgsl"),
            "Params",
            Params,
            [
                ray_count,
                row_stride,
                min_transmittance,
                distortion_weight,
                distance_scale
            ],
            prefix
        );
    }
    #[test]
    fn params_of_composite_backward_mirror_the_shader() {
        assert_mirrors!(
            include_str!("../../../shaders/composite_backward.wgsl"),
            "Params",
            Params,
            [
                ray_count,
                row_stride,
                min_transmittance,
                distortion_weight,
                distance_scale
            ]
        );
    }
    #[test]
    fn params_of_composite_weights_mirror_the_shader() {
        assert_mirrors!(
            include_str!("../../../shaders/composite_weights.wgsl"),
            "Params",
            Params,
            [
                ray_count,
                row_stride,
                min_transmittance,
                distortion_weight,
                distance_scale
            ],
            prefix
        );
    }
}
