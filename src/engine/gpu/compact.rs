//! σ-first compaction of a marched batch on the device: given each ray's
//! samples before its cut (from compositing the σ pass's densities), a
//! prefix sum of those counts places the samples kept, and two gathers
//! (`shaders/compact_*.wgsl`) copy each one's inputs (position, direction,
//! covariance diagonal) and compositing values (step, distance, σ) from the
//! march's arrays, rays in order and samples in order within each ray. The
//! forward and backward passes then run on the kept samples only, as the
//! cpu engine's marched step does after its σ pass.
//!
//! How many samples are kept is known on the device only until the step's
//! march read-back: the gathers are dispatched over the march's capacity and
//! read the count from the prefix sum's counter, so the whole compaction
//! goes into the same submission as the march and adds no wait.

use super::kernel::{Kernel, Recorder, uniform_buffer, zeroed_storage_buffer};
use super::march::{GpuMarch, PrefixSum, block_sums_len, dispatch_grid, source};
use crate::engine::gpu::{GpuContext, GpuError};

/// Threads per workgroup of the gathers.
const WORKGROUP: u32 = 64;

const COMMON: &str = include_str!("../../../shaders/compact_common.wgsl");

/// `shaders/compact_common.wgsl`'s `Params`.
#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct CompactUniforms {
    ray_count: u32,
    row_stride: u32,
    with_variances: u32,
    _pad: u32,
}

/// The compiled gathers.
pub struct GpuCompaction {
    vectors: Kernel,
    scalars: Kernel,
}

/// Where a compacted batch lives: sized for `rays` rays and at most
/// `capacity` samples (the march's).
pub struct CompactedSamples {
    /// rays + 1 offsets (u32) into the compacted arrays.
    pub ray_offsets: wgpu::Buffer,
    /// [samples kept, rays] (u32), written by the prefix sum.
    pub counters: wgpu::Buffer,
    block_sums: wgpu::Buffer,
    /// capacity × 3: the field's positions.
    pub positions: wgpu::Buffer,
    /// capacity × 3.
    pub directions: wgpu::Buffer,
    /// Frustum recipes: capacity × 3 (else one float, unused).
    pub variances: wgpu::Buffer,
    pub dt: wgpu::Buffer,
    pub t: wgpu::Buffer,
    /// σ of the σ pass.
    pub sigma: wgpu::Buffer,
    /// What the gather reads for variances without frustums (one float;
    /// a buffer cannot be bound for reading and writing in one pass).
    no_variances: wgpu::Buffer,
    rays: usize,
    capacity: usize,
}

impl CompactedSamples {
    pub fn new(context: &GpuContext, rays: usize, capacity: usize, frustums: bool) -> Self {
        let f = |label: &str, n: usize| zeroed_storage_buffer::<f32>(context, label, n);
        let u = |label: &str, n: usize| zeroed_storage_buffer::<u32>(context, label, n);
        Self {
            ray_offsets: u("compacted offsets", rays + 1),
            counters: u("compacted counters", 2),
            block_sums: u("compacted block sums", block_sums_len(rays)),
            positions: f("compacted positions", 3 * capacity),
            directions: f("compacted directions", 3 * capacity),
            variances: f(
                "compacted variances",
                if frustums { 3 * capacity } else { 1 },
            ),
            dt: f("compacted dt", capacity),
            t: f("compacted t", capacity),
            sigma: f("compacted sigma", capacity),
            no_variances: f("no variances", 1),
            rays,
            capacity,
        }
    }

    /// Bytes on the device.
    pub fn bytes(&self) -> usize {
        4 * (self.rays + 4 + block_sums_len(self.rays) + 9 * self.capacity)
            + self.variances.size() as usize
    }
}

/// The march's samples a compaction reads (`capacity` of each; the
/// variances only for frustum recipes).
#[derive(Debug, Clone, Copy)]
pub struct MarchedInputs<'a> {
    /// rays + 1 offsets of the march.
    pub ray_offsets: &'a wgpu::Buffer,
    /// Each ray's samples before its cut (u32).
    pub samples_used: &'a wgpu::Buffer,
    /// The field's positions (× 3).
    pub positions: &'a wgpu::Buffer,
    pub directions: &'a wgpu::Buffer,
    pub variances: Option<&'a wgpu::Buffer>,
    pub dt: &'a wgpu::Buffer,
    pub t: &'a wgpu::Buffer,
    /// σ of the σ pass.
    pub sigma: &'a wgpu::Buffer,
}

impl GpuCompaction {
    pub fn new(context: &GpuContext) -> Result<Self, GpuError> {
        let gather =
            |name: &str, entry: &str| Kernel::new(context, name, &source(&[COMMON, entry]), "main");
        Ok(Self {
            vectors: gather(
                "compact_vectors",
                include_str!("../../../shaders/compact_vectors.wgsl"),
            )?,
            scalars: gather(
                "compact_scalars",
                include_str!("../../../shaders/compact_scalars.wgsl"),
            )?,
        })
    }

    /// Records the prefix sum alone: the samples before the cut of `rays`
    /// rays, counted in `used`, into `out.ray_offsets`, and their total into
    /// `out.counters[0]`.
    pub fn record_count(
        &self,
        rec: &mut Recorder,
        march: &GpuMarch,
        used: &wgpu::Buffer,
        rays: usize,
        out: &CompactedSamples,
    ) {
        assert!(rays <= out.rays, "{rays} rays exceed {}", out.rays);
        march.record_prefix_sum(
            rec,
            PrefixSum {
                counts: used,
                offsets: &out.ray_offsets,
                block_sums: &out.block_sums,
                counters: &out.counters,
            },
            rays,
        );
    }

    /// Records the compaction of `rays` rays: the prefix sum of their
    /// samples before the cut into `out.ray_offsets` and `out.counters`,
    /// then the gathers.
    pub fn record(
        &self,
        rec: &mut Recorder,
        march: &GpuMarch,
        rays: usize,
        from: MarchedInputs,
        out: &CompactedSamples,
    ) {
        let context = rec.context;
        self.record_count(rec, march, from.samples_used, rays, out);
        if rays == 0 {
            return;
        }
        let (groups, row_stride) = dispatch_grid(out.capacity, WORKGROUP);
        let uniforms = CompactUniforms {
            ray_count: rays as u32,
            row_stride,
            with_variances: from.variances.is_some() as u32,
            _pad: 0,
        };
        let uniform = uniform_buffer(context, "compaction params", &uniforms);
        let head = [&uniform, &out.ray_offsets, from.ray_offsets, &out.counters];
        // Without frustums the variance bindings are one-float
        // placeholders, never read.
        let variances = from.variances.unwrap_or(&out.no_variances);
        self.vectors.record(
            rec,
            &[
                head.as_slice(),
                &[
                    from.positions,
                    from.directions,
                    variances,
                    &out.positions,
                    &out.directions,
                    &out.variances,
                ],
            ]
            .concat(),
            groups,
        );
        self.scalars.record(
            rec,
            &[
                head.as_slice(),
                &[from.dt, from.t, from.sigma, &out.dt, &out.t, &out.sigma],
            ]
            .concat(),
            groups,
        );
    }
}

/// The uniforms as the shaders declare them (`engine::gpu::mirror`).
#[cfg(test)]
mod uniform_mirrors {
    use super::*;
    use crate::engine::gpu::mirror::assert_mirrors;

    #[test]
    fn compactuniforms_of_compact_common_mirror_the_shader() {
        assert_mirrors!(
            include_str!("../../../shaders/compact_common.wgsl"),
            "Params",
            CompactUniforms,
            [ray_count, row_stride, with_variances]
        );
    }
}
