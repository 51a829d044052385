//! Mip-NeRF's conical frustums as Gaussians on the GPU
//! (`shaders/frustum_common.wgsl` and its two kernels): the forward pass of
//! [`crate::engine::cpu::frustum`], same formulas, same operation order,
//! same layouts, recorded into a command encoder.
//!
//! Three kernels, one per way a model places its samples:
//!
//! - [`GpuFrustums::record_edges`], for fixed-count levels: each ray's
//!   N + 1 interval edges (stratified, or resampled from the previous
//!   level) become N frustums, as the cpu model's `sample_level`;
//! - [`GpuFrustums::record_marched`], for samples marched through the
//!   occupancy grid: each sample stands for the frustum of its step, centred
//!   on it, as the cpu model's marched step;
//! - [`GpuFrustums::record_walked`], for the samples of the viewer's device
//!   walk (`engine::gpu::model::walk`): the same frustums, for slots of a
//!   round's rays rather than a compacted batch.
//!
//! Only a forward pass: no gradient flows into the frustums. The loss
//! reaches the network's parameters through the integrated encoding of the
//! Gaussians, but the Gaussians themselves are functions of the rays and of
//! the sample distances, which nothing learns (Mip-NeRF's reference stops
//! the gradient through the resampled distances, `stop_level_grad`), so
//! neither this stage nor the encoding has a backward pass.
//!
//! The kernels repeat the cpu's f32 operations with products kept apart
//! from the sums they feed; the only operations WGSL may round differently
//! are the divisions (2.5 ulp), so the two engines agree to a few ulps (on
//! lavapipe, bit for bit: see `tests/it/sampling_gpu.rs`).

use super::kernel::{Kernel, Recorder, float_range};
use super::march::{CPU_ARITHMETIC, source};
use super::sampling::{COMMON, GpuSampling, SampleUniforms};
use crate::engine::gpu::{GpuContext, GpuError};

const FRUSTUM_COMMON: &str = include_str!("../../../shaders/frustum_common.wgsl");

/// The rays the frustums lie on, R of each: origins and unit directions
/// (R × 3, world space) and the cone radius at unit distance (R).
#[derive(Debug, Clone, Copy)]
pub struct FrustumRays<'a> {
    pub origins: &'a wgpu::Buffer,
    pub directions: &'a wgpu::Buffer,
    pub radii: &'a wgpu::Buffer,
}

/// What a fixed-count level's frustums give, S = R × N samples: each
/// interval's midpoint `t` and length `dt` (S each, for compositing), the
/// Gaussians' `means` and covariance diagonals `variances` and the samples'
/// `directions` (S × 3 each, the field's inputs).
#[derive(Debug, Clone, Copy)]
pub struct FrustumSamples<'a> {
    pub t: &'a wgpu::Buffer,
    pub dt: &'a wgpu::Buffer,
    pub means: &'a wgpu::Buffer,
    pub variances: &'a wgpu::Buffer,
    pub directions: &'a wgpu::Buffer,
}

/// Samples marched through the occupancy grid, as
/// [`super::march::GpuMarchBuffers`] holds them: R + 1 offsets (u32), and
/// per sample the distance `t` and step `dt` (world units).
#[derive(Debug, Clone, Copy)]
pub struct MarchedIntervals<'a> {
    pub ray_offsets: &'a wgpu::Buffer,
    pub t: &'a wgpu::Buffer,
    pub dt: &'a wgpu::Buffer,
    /// Samples in the arrays (the march's count).
    pub samples: usize,
}

/// The Gaussians of S frustums: means and covariance diagonals, S × 3
/// each (the field's inputs).
#[derive(Debug, Clone, Copy)]
pub struct Gaussians<'a> {
    pub means: &'a wgpu::Buffer,
    pub variances: &'a wgpu::Buffer,
}

/// A round of the render walk's samples: `per_ray` slots per ray of the
/// round, each slot's distance `t` and step `dt` (world units).
#[derive(Debug, Clone, Copy)]
pub struct WalkedIntervals<'a> {
    pub t: &'a wgpu::Buffer,
    pub dt: &'a wgpu::Buffer,
    pub per_ray: usize,
}

/// The compiled frustum kernels.
pub struct GpuFrustums {
    edges: Kernel,
    marched: Kernel,
    walked: Kernel,
}

impl GpuFrustums {
    pub fn new(context: &GpuContext) -> Result<Self, GpuError> {
        let kernel = |name: &str, entry: &str| {
            Kernel::new(
                context,
                name,
                &source(&[COMMON, CPU_ARITHMETIC, FRUSTUM_COMMON, entry]),
                "main",
            )
        };
        Ok(Self {
            edges: kernel(
                "sample_frustums",
                include_str!("../../../shaders/sample_frustums.wgsl"),
            )?,
            marched: kernel(
                "sample_marched_frustums",
                include_str!("../../../shaders/sample_marched_frustums.wgsl"),
            )?,
            walked: kernel(
                "render_frustums",
                include_str!("../../../shaders/render_frustums.wgsl"),
            )?,
        })
    }

    /// Records the frustums between consecutive `edges` (R × (N + 1),
    /// sorted per ray) of `rays` rays, `samples_per_ray` = N each, into
    /// `out`, as [`crate::engine::cpu::frustum::frustum_gaussians`] over
    /// the cpu model's fixed-count level. Rays beyond one storage binding go
    /// a piece at a time.
    pub fn record_edges(
        &self,
        rec: &mut Recorder,
        on: FrustumRays,
        edges: &wgpu::Buffer,
        rays: usize,
        samples_per_ray: usize,
        out: FrustumSamples,
    ) {
        let n = samples_per_ray;
        if n == 0 || rays == 0 {
            return;
        }
        let template = SampleUniforms {
            samples: n as u32,
            ..Default::default()
        };
        GpuSampling::record_rays(rec, &self.edges, rays, 3 * n, template, |p| {
            let per = |buffer, width: usize| float_range(buffer, width * p.start, width * p.len());
            vec![
                per(on.origins, 3),
                per(on.directions, 3),
                per(on.radii, 1),
                per(edges, n + 1),
                per(out.t, n),
                per(out.dt, n),
                per(out.means, 3 * n),
                per(out.variances, 3 * n),
                per(out.directions, 3 * n),
            ]
        });
    }

    /// Records the Gaussians of the frustums the first `rays` rays' marched
    /// samples stand for, into `out` (S = `marched.samples`). The
    /// per-sample arrays are bound whole (the model sizes its batch to one
    /// binding); the rays a piece at a time.
    pub fn record_marched(
        &self,
        rec: &mut Recorder,
        on: FrustumRays,
        marched: MarchedIntervals,
        rays: usize,
        out: Gaussians,
    ) {
        let s = marched.samples;
        if rays == 0 || s == 0 {
            return;
        }
        let template = SampleUniforms::default();
        GpuSampling::record_rays(rec, &self.marched, rays, 3, template, |p| {
            vec![
                float_range(on.origins, 3 * p.start, 3 * p.len()),
                float_range(on.directions, 3 * p.start, 3 * p.len()),
                float_range(on.radii, p.start, p.len()),
                // Each ray reads its own offset and the next.
                float_range(marched.ray_offsets, p.start, p.len() + 1),
                float_range(marched.t, 0, s),
                float_range(marched.dt, 0, s),
                float_range(out.means, 0, 3 * s),
                float_range(out.variances, 0, 3 * s),
            ]
        });
    }

    /// Records the Gaussians of the frustums a round of the render walk's
    /// samples stand for: `round_rays` rays of `on` (the view's), listed by
    /// index in `ray_list`, ray i of the round at slots i·`per_ray`.. of
    /// `walked`; into `out` (3 per slot each), as
    /// [`crate::engine::shared::driver::grid_sample_gaussians`] on the host.
    pub fn record_walked(
        &self,
        rec: &mut Recorder,
        on: FrustumRays,
        ray_list: wgpu::BufferBinding,
        round_rays: usize,
        walked: WalkedIntervals,
        out: Gaussians,
    ) {
        let per_ray = walked.per_ray;
        let slots = round_rays * per_ray;
        if slots == 0 {
            return;
        }
        let template = SampleUniforms {
            samples: per_ray as u32,
            ..Default::default()
        };
        // Each slot is one invocation; every binding is whole, so a piece
        // of slots finds its own through `ray_base`.
        GpuSampling::record_rays(rec, &self.walked, slots, 3, template, |_| {
            vec![
                on.origins.as_entire_buffer_binding(),
                on.directions.as_entire_buffer_binding(),
                on.radii.as_entire_buffer_binding(),
                ray_list.clone(),
                float_range(walked.t, 0, slots),
                float_range(walked.dt, 0, slots),
                float_range(out.means, 0, 3 * slots),
                float_range(out.variances, 0, 3 * slots),
            ]
        });
    }
}
