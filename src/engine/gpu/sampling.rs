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

use super::kernel::{Kernel, Recorder, float_range, pieces, rows_per_piece, uniform_buffer};
use super::march::{CPU_ARITHMETIC, GpuRays, dispatch_grid, source};
use crate::engine::gpu::{GpuContext, GpuError};
use crate::engine::shared::sampling::stratified_step;

/// Threads per workgroup of every sampling kernel.
const WORKGROUP: u32 = 64;

pub(crate) const COMMON: &str = include_str!("../../../shaders/sample_common.wgsl");

/// `SampleParams` in `shaders/sample_common.wgsl`.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct SampleUniforms {
    pub rays: u32,
    pub ray_base: u32,
    pub row_stride: u32,
    pub samples: u32,
    pub bins: u32,
    pub seed: u32,
    pub use_jitter: u32,
    pub zero: u32,
    pub step: f32,
    pub inverse_count: f32,
    pub padding: f32,
    pub _pad: u32,
}

/// `Params` in `shaders/sample_to_world.wgsl`.
#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct ToWorldUniforms {
    count: u32,
    row_stride: u32,
    scale: f32,
    _pad0: u32,
    offset: [f32; 3],
    _pad1: u32,
}

/// Each ray's bounds: R distances each, where its samples start and end.
#[derive(Debug, Clone, Copy)]
pub struct RayBounds<'a> {
    pub near: &'a wgpu::Buffer,
    pub far: &'a wgpu::Buffer,
}

/// A piecewise-constant pdf per ray: `bins` bins between R × (`bins` + 1)
/// sorted `edges`, weighted by R × `bins` `weights`, each raised by
/// `padding`.
#[derive(Debug, Clone, Copy)]
pub struct Pdf<'a> {
    pub edges: &'a wgpu::Buffer,
    pub weights: &'a wgpu::Buffer,
    pub bins: usize,
    pub padding: f32,
}

/// R rows of `per_ray` values each, sorted within each row.
#[derive(Debug, Clone, Copy)]
pub struct SortedRows<'a> {
    pub values: &'a wgpu::Buffer,
    pub per_ray: usize,
}

/// A level's samples and their compositing weights, R × M each.
#[derive(Debug, Clone, Copy)]
pub struct WeightedSamples<'a> {
    pub t: &'a wgpu::Buffer,
    pub weights: &'a wgpu::Buffer,
}

/// Points along rays, R × N × 3 each: positions and unit directions.
#[derive(Debug, Clone, Copy)]
pub struct SamplePoints<'a> {
    pub positions: &'a wgpu::Buffer,
    pub directions: &'a wgpu::Buffer,
}

/// The compiled sampling kernels.
pub struct GpuSampling {
    stratified: Kernel,
    pdf: Kernel,
    merge: Kernel,
    blur: Kernel,
    intervals: Kernel,
    points: Kernel,
    bins: Kernel,
    to_world: Kernel,
}

impl GpuSampling {
    pub fn new(context: &GpuContext) -> Result<Self, GpuError> {
        let kernel = |name: &str, entry: &str| {
            Kernel::new(
                context,
                name,
                &source(&[COMMON, CPU_ARITHMETIC, entry]),
                "main",
            )
        };
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
            points: kernel(
                "sample_points",
                include_str!("../../../shaders/sample_points.wgsl"),
            )?,
            bins: kernel(
                "sample_bins",
                include_str!("../../../shaders/sample_bins.wgsl"),
            )?,
            // Its own uniform: not prepended with sample_common.wgsl.
            to_world: Kernel::new(
                context,
                "sample_to_world",
                include_str!("../../../shaders/sample_to_world.wgsl"),
                "main",
            )?,
        })
    }

    /// Records `kernel` over `rays` rays, a piece of rays at a time when the
    /// widest per-ray binding (`widest` floats per ray) would pass the
    /// device's storage-binding limit. `bind` gives the piece's storage
    /// bindings, after the uniform.
    pub(crate) fn record_rays<'a>(
        rec: &mut Recorder,
        kernel: &Kernel,
        rays: usize,
        widest: usize,
        template: SampleUniforms,
        bind: impl Fn(&std::ops::Range<usize>) -> Vec<wgpu::BufferBinding<'a>>,
    ) {
        let context = rec.context;
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
            kernel.record_bindings(rec, &bindings, groups);
        }
    }

    /// Records [`crate::engine::cpu::sampling::stratified`]: `bounds` to
    /// `t_out` (R × N).
    pub fn record_stratified(
        &self,
        rec: &mut Recorder,
        bounds: RayBounds,
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
        Self::record_rays(rec, &self.stratified, rays, n, template, |p| {
            vec![
                float_range(bounds.near, p.start, p.len()),
                float_range(bounds.far, p.start, p.len()),
                float_range(t_out, n * p.start, n * p.len()),
            ]
        });
    }

    /// Records [`crate::engine::cpu::sampling::sample_pdf`]: `count` draws
    /// from `pdf` to `out` (R × count).
    pub fn record_sample_pdf(
        &self,
        rec: &mut Recorder,
        pdf: Pdf,
        rays: usize,
        count: usize,
        jitter: Option<u32>,
        out: &wgpu::Buffer,
    ) {
        let Pdf {
            edges,
            weights,
            bins,
            padding,
        } = pdf;
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
        Self::record_rays(rec, &self.pdf, rays, widest, template, |p| {
            vec![
                float_range(edges, (bins + 1) * p.start, (bins + 1) * p.len()),
                float_range(weights, bins * p.start, bins * p.len()),
                float_range(out, count * p.start, count * p.len()),
            ]
        });
    }

    /// Records [`crate::engine::cpu::sampling::merge_sorted`]: `a` (R × Na)
    /// and `b` (R × Nb) to `out` (R × (Na + Nb)).
    pub fn record_merge_sorted(
        &self,
        rec: &mut Recorder,
        a: SortedRows,
        b: SortedRows,
        rays: usize,
        out: &wgpu::Buffer,
    ) {
        let (na, nb) = (a.per_ray, b.per_ray);
        let n = na + nb;
        if n == 0 || rays == 0 {
            return;
        }
        let template = SampleUniforms {
            samples: na as u32,
            bins: nb as u32,
            ..Default::default()
        };
        Self::record_rays(rec, &self.merge, rays, n, template, |p| {
            vec![
                float_range(a.values, na * p.start, na * p.len()),
                float_range(b.values, nb * p.start, nb * p.len()),
                float_range(out, n * p.start, n * p.len()),
            ]
        });
    }

    /// Records [`crate::engine::cpu::sampling::blur_weights`]: R × B to
    /// R × B.
    pub fn record_blur_weights(
        &self,
        rec: &mut Recorder,
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
        Self::record_rays(rec, &self.blur, rays, bins, template, |p| {
            vec![
                float_range(weights, bins * p.start, bins * p.len()),
                float_range(out, bins * p.start, bins * p.len()),
            ]
        });
    }

    /// Records [`crate::engine::cpu::sampling::intervals_to_far`]: `t`
    /// (R × N) and `far` (R) to `dt_out` (R × N).
    pub fn record_intervals_to_far(
        &self,
        rec: &mut Recorder,
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
        Self::record_rays(rec, &self.intervals, rays, n, template, |p| {
            vec![
                float_range(t, n * p.start, n * p.len()),
                float_range(far, p.start, p.len()),
                float_range(dt_out, n * p.start, n * p.len()),
            ]
        });
    }

    /// Records the positions o + t·d and directions of `samples_per_ray`
    /// samples at distances `t` (R × N) along `on` (R rays), as the cpu
    /// model's `points_along_rays`.
    pub fn record_points(
        &self,
        rec: &mut Recorder,
        on: GpuRays,
        t: &wgpu::Buffer,
        rays: usize,
        samples_per_ray: usize,
        out: SamplePoints,
    ) {
        let n = samples_per_ray;
        if n == 0 || rays == 0 {
            return;
        }
        let template = SampleUniforms {
            samples: n as u32,
            ..Default::default()
        };
        Self::record_rays(rec, &self.points, rays, 3 * n, template, |p| {
            vec![
                float_range(on.origins, 3 * p.start, 3 * p.len()),
                float_range(on.directions, 3 * p.start, 3 * p.len()),
                float_range(t, n * p.start, n * p.len()),
                float_range(out.positions, 3 * n * p.start, 3 * n * p.len()),
                float_range(out.directions, 3 * n * p.start, 3 * n * p.len()),
            ]
        });
    }

    /// Records the bins of NeRF's importance sampling from the previous
    /// level's `samples_per_ray` (M ≥ 3) sorted samples and their weights
    /// (`previous`): `edges_out` (R × (M − 1)) are the midpoints between
    /// samples, `bin_weights_out` (R × (M − 2)) the weights of the interior
    /// samples, as the cpu model's `importance_samples` gives
    /// [`crate::engine::cpu::sampling::sample_pdf`].
    pub fn record_importance_bins(
        &self,
        rec: &mut Recorder,
        previous: WeightedSamples,
        rays: usize,
        samples_per_ray: usize,
        edges_out: &wgpu::Buffer,
        bin_weights_out: &wgpu::Buffer,
    ) {
        let m = samples_per_ray;
        assert!(m >= 3, "importance sampling needs three samples per ray");
        if rays == 0 {
            return;
        }
        let template = SampleUniforms {
            samples: m as u32,
            ..Default::default()
        };
        Self::record_rays(rec, &self.bins, rays, m, template, |p| {
            vec![
                float_range(previous.t, m * p.start, m * p.len()),
                float_range(previous.weights, m * p.start, m * p.len()),
                float_range(edges_out, (m - 1) * p.start, (m - 1) * p.len()),
                float_range(bin_weights_out, (m - 2) * p.start, (m - 2) * p.len()),
            ]
        });
    }

    /// Records world positions of `count` unit-cube positions (n × 3 each)
    /// under `mapping`, as the cpu model's `to_world`.
    pub fn record_to_world(
        &self,
        rec: &mut Recorder,
        mapping: &crate::scene::UnitCubeMapping,
        unit: &wgpu::Buffer,
        count: usize,
        world_out: &wgpu::Buffer,
    ) {
        if count == 0 {
            return;
        }
        let context = rec.context;
        for piece in pieces(count, rows_per_piece(context, 3, 1)) {
            let (groups, row_stride) = dispatch_grid(piece.len(), WORKGROUP);
            let uniform = ToWorldUniforms {
                count: piece.len() as u32,
                row_stride,
                scale: mapping.scale,
                _pad0: 0,
                offset: mapping.offset.to_array(),
                _pad1: 0,
            };
            let uniform = uniform_buffer(context, "sample to world", &uniform);
            self.to_world.record_bindings(
                rec,
                &[
                    uniform.as_entire_buffer_binding(),
                    float_range(unit, 3 * piece.start, 3 * piece.len()),
                    float_range(world_out, 3 * piece.start, 3 * piece.len()),
                ],
                groups,
            );
        }
    }
}

/// The uniforms as the shaders declare them (`engine::gpu::mirror`).
#[cfg(test)]
mod uniform_mirrors {
    use super::*;
    use crate::engine::gpu::mirror::assert_mirrors;

    #[test]
    fn sampleuniforms_of_sample_common_mirror_the_shader() {
        assert_mirrors!(
            include_str!("../../../shaders/sample_common.wgsl"),
            "SampleParams",
            SampleUniforms,
            [
                rays,
                ray_base,
                row_stride,
                samples,
                bins,
                seed,
                use_jitter,
                zero,
                step,
                inverse_count,
                padding
            ]
        );
    }
    #[test]
    fn toworlduniforms_of_sample_to_world_mirror_the_shader() {
        assert_mirrors!(
            include_str!("../../../shaders/sample_to_world.wgsl"),
            "Params",
            ToWorldUniforms,
            [count, row_stride, scale, offset]
        );
    }
}
