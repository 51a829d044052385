//! Sample generation along rays for NeRF and Mip-NeRF on the GPU
//! (`shaders/sample_*.wgsl`): the operations of
//! [`crate::engine::cpu::sampling`], with the same buffer layouts (R rays ×
//! N samples, row-major per ray), recorded into a command encoder.
//!
//! One invocation per ray: a ray's work is O(N + B) with N, B ≤ a few
//! hundred, and a batch has thousands of rays. The kernels repeat the cpu's
//! arithmetic operation for operation, with the same random numbers
//! ([`crate::engine::cpu::sampling::uniform`]) and fused multiply-adds
//! prevented, so stratified samples, merges, blurs and intervals match the
//! cpu bit for bit, and inverse-CDF samples fall in the same bins, at most a
//! few ulps of the bin width apart (WGSL's division is accurate to 2.5 ulp;
//! on lavapipe they are bit-equal too). Two limits to the parity: the blur
//! takes finite weights (WGSL leaves `max` of a NaN to the implementation),
//! and a pdf whose padded total is within a factor `count` of f32's smallest
//! normal number can meet a GPU that flushes subnormal products to zero.
//! Rays beyond one storage binding go a piece at a time.

use super::context::{GpuContext, GpuError};
use super::kernel::{Kernel, float_range, pieces, rows_per_piece, uniform_buffer};
use super::march::{dispatch_grid, source};
use crate::engine::cpu::sampling::stratified_step;

/// Threads per workgroup of every sampling kernel.
const WORKGROUP: u32 = 64;

const COMMON: &str = include_str!("../../../shaders/sample_common.wgsl");

/// `SampleParams` in `shaders/sample_common.wgsl`.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, bytemuck::Pod, bytemuck::Zeroable)]
struct SampleUniforms {
    rays: u32,
    ray_base: u32,
    row_stride: u32,
    samples: u32,
    bins: u32,
    seed: u32,
    use_jitter: u32,
    zero: u32,
    step: f32,
    inverse_count: f32,
    padding: f32,
    _pad: u32,
}

/// The compiled sampling kernels.
pub struct GpuSampling {
    stratified: Kernel,
    pdf: Kernel,
    merge: Kernel,
    blur: Kernel,
    intervals: Kernel,
}

impl GpuSampling {
    pub fn new(context: &GpuContext) -> Result<Self, GpuError> {
        let kernel =
            |name: &str, entry: &str| Kernel::new(context, name, &source(&[COMMON, entry]), "main");
        Ok(Self {
            stratified: kernel(
                "sample_stratified",
                include_str!("../../../shaders/sample_stratified.wgsl"),
            )?,
            pdf: kernel(
                "sample_pdf",
                include_str!("../../../shaders/sample_pdf.wgsl"),
            )?,
            merge: kernel(
                "sample_merge",
                include_str!("../../../shaders/sample_merge.wgsl"),
            )?,
            blur: kernel(
                "sample_blur",
                include_str!("../../../shaders/sample_blur.wgsl"),
            )?,
            intervals: kernel(
                "sample_intervals",
                include_str!("../../../shaders/sample_intervals.wgsl"),
            )?,
        })
    }

    /// Records `kernel` over `rays` rays, a piece of rays at a time when the
    /// widest per-ray binding (`widest` floats per ray) would pass the
    /// device's storage-binding limit. `bind` gives the piece's storage
    /// bindings, after the uniform.
    fn record_rays<'a>(
        context: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        kernel: &Kernel,
        rays: usize,
        widest: usize,
        template: SampleUniforms,
        bind: impl Fn(&std::ops::Range<usize>) -> Vec<wgpu::BufferBinding<'a>>,
    ) {
        for piece in pieces(rays, rows_per_piece(context, widest, 1)) {
            let (groups, row_stride) = dispatch_grid(piece.len(), WORKGROUP);
            let params = SampleUniforms {
                rays: piece.len() as u32,
                ray_base: u32::try_from(piece.start).expect("ray index fits in u32"),
                row_stride,
                ..template
            };
            let uniform = uniform_buffer(context, &kernel.name, &params);
            let mut bindings = vec![uniform.as_entire_buffer_binding()];
            bindings.extend(bind(&piece));
            kernel.record_bindings(context, encoder, &bindings, groups);
        }
    }

    /// Records [`crate::engine::cpu::sampling::stratified`]: `near`, `far`
    /// (R each) to `t_out` (R × N).
    #[allow(clippy::too_many_arguments)]
    pub fn record_stratified(
        &self,
        context: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        near: &wgpu::Buffer,
        far: &wgpu::Buffer,
        rays: usize,
        samples_per_ray: usize,
        jitter: Option<u32>,
        t_out: &wgpu::Buffer,
    ) {
        let n = samples_per_ray;
        if n == 0 || rays == 0 {
            return;
        }
        let template = SampleUniforms {
            samples: n as u32,
            seed: jitter.unwrap_or(0),
            use_jitter: jitter.is_some() as u32,
            step: stratified_step(n),
            ..Default::default()
        };
        Self::record_rays(context, encoder, &self.stratified, rays, n, template, |p| {
            vec![
                float_range(near, p.start, p.len()),
                float_range(far, p.start, p.len()),
                float_range(t_out, n * p.start, n * p.len()),
            ]
        });
    }

    /// Records [`crate::engine::cpu::sampling::sample_pdf`]: `edges`
    /// (R × (B + 1)) and `weights` (R × B) to `out` (R × count).
    #[allow(clippy::too_many_arguments)]
    pub fn record_sample_pdf(
        &self,
        context: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        edges: &wgpu::Buffer,
        weights: &wgpu::Buffer,
        rays: usize,
        bins: usize,
        padding: f32,
        count: usize,
        jitter: Option<u32>,
        out: &wgpu::Buffer,
    ) {
        assert!(bins > 0, "a pdf needs at least one bin");
        assert!(
            padding.is_finite() && padding >= 0.0,
            "padding {padding} must be finite and ≥ 0"
        );
        if count == 0 || rays == 0 {
            return;
        }
        let template = SampleUniforms {
            samples: count as u32,
            bins: bins as u32,
            seed: jitter.unwrap_or(0),
            use_jitter: jitter.is_some() as u32,
            inverse_count: 1.0 / count as f32,
            padding,
            ..Default::default()
        };
        let widest = count.max(bins + 1);
        Self::record_rays(context, encoder, &self.pdf, rays, widest, template, |p| {
            vec![
                float_range(edges, (bins + 1) * p.start, (bins + 1) * p.len()),
                float_range(weights, bins * p.start, bins * p.len()),
                float_range(out, count * p.start, count * p.len()),
            ]
        });
    }

    /// Records [`crate::engine::cpu::sampling::merge_sorted`]: `a` (R × Na)
    /// and `b` (R × Nb) to `out` (R × (Na + Nb)).
    #[allow(clippy::too_many_arguments)]
    pub fn record_merge_sorted(
        &self,
        context: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        a: &wgpu::Buffer,
        na: usize,
        b: &wgpu::Buffer,
        nb: usize,
        rays: usize,
        out: &wgpu::Buffer,
    ) {
        let n = na + nb;
        if n == 0 || rays == 0 {
            return;
        }
        let template = SampleUniforms {
            samples: na as u32,
            bins: nb as u32,
            ..Default::default()
        };
        Self::record_rays(context, encoder, &self.merge, rays, n, template, |p| {
            vec![
                float_range(a, na * p.start, na * p.len()),
                float_range(b, nb * p.start, nb * p.len()),
                float_range(out, n * p.start, n * p.len()),
            ]
        });
    }

    /// Records [`crate::engine::cpu::sampling::blur_weights`]: R × B to
    /// R × B.
    pub fn record_blur_weights(
        &self,
        context: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        weights: &wgpu::Buffer,
        rays: usize,
        bins: usize,
        out: &wgpu::Buffer,
    ) {
        if bins == 0 || rays == 0 {
            return;
        }
        let template = SampleUniforms {
            samples: bins as u32,
            ..Default::default()
        };
        Self::record_rays(context, encoder, &self.blur, rays, bins, template, |p| {
            vec![
                float_range(weights, bins * p.start, bins * p.len()),
                float_range(out, bins * p.start, bins * p.len()),
            ]
        });
    }

    /// Records [`crate::engine::cpu::sampling::intervals_to_far`]: `t`
    /// (R × N) and `far` (R) to `dt_out` (R × N).
    #[allow(clippy::too_many_arguments)]
    pub fn record_intervals_to_far(
        &self,
        context: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        t: &wgpu::Buffer,
        far: &wgpu::Buffer,
        rays: usize,
        samples_per_ray: usize,
        dt_out: &wgpu::Buffer,
    ) {
        let n = samples_per_ray;
        if n == 0 || rays == 0 {
            return;
        }
        let template = SampleUniforms {
            samples: n as u32,
            ..Default::default()
        };
        Self::record_rays(context, encoder, &self.intervals, rays, n, template, |p| {
            vec![
                float_range(t, n * p.start, n * p.len()),
                float_range(far, p.start, p.len()),
                float_range(dt_out, n * p.start, n * p.len()),
            ]
        });
    }
}
