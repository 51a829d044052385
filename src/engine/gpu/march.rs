//! Occupancy-grid ray marching on the GPU (`shaders/march_*.wgsl`): the
//! same samples, in the same order, as [`crate::engine::cpu::march::march`].
//!
//! The march runs in passes, like the cpu engine's: count the samples of
//! each ray (one invocation per ray), an exclusive prefix sum of the counts
//! into ray offsets (blocks of 512 scanned in workgroup memory, the block
//! totals scanned by one workgroup, then added back), the budget applied to
//! the offsets, and a second walk that writes each sample at its offset.
//! Every step is integer arithmetic or a fixed-order walk, so the result is
//! deterministic; no sample's place depends on which invocation ran first.
//!
//! Large scenes (aabb_scale > 1) step by cone angle as the cpu engine does
//! (`engine::shared::march::Lattice`, in whole octaves with exact
//! power-of-two arithmetic), so both engines take the same samples with the same steps;
//! each sample carries its own step.

use super::kernel::{
    Kernel, Recorder, read_buffer, storage_buffer, uniform_buffer, zeroed_storage_buffer,
};
use crate::engine::gpu::{GpuContext, GpuError};
use crate::engine::shared::march::{
    MarchParams, MarchStats, MarchedSamples, cone_for, skip_margin,
};
use crate::engine::shared::occupancy::{GridGeometry, OccupancyGrid};

/// Threads per workgroup of the per-ray and per-element kernels.
const WORKGROUP: u32 = 64;
/// Offsets scanned per workgroup by `march_scan_blocks.wgsl`.
const SCAN_BLOCK: usize = 512;

/// `shaders/march_params.wgsl`.
#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
pub struct MarchUniforms {
    offset: [f32; 3],
    scale: f32,
    box_min: f32,
    box_max: f32,
    dt: f32,
    inverse_dt: f32,
    margin: f32,
    ray_count: u32,
    row_stride: u32,
    resolution: u32,
    cascades: u32,
    max_samples: u32,
    jitter_seed: u32,
    use_jitter: u32,
    zero: u32,
    budget: u32,
    element_count: u32,
    block_count: u32,
    world_dt: f32,
    inverse_scale: f32,
    use_cone: u32,
    points_per_octave: f32,
    octave_start: f32,
    inverse_octave_start: f32,
    last_octave: i32,
    _pad: [u32; 1],
}

/// The dispatch for `count` invocations, 2-D past 65535 workgroups, and the
/// invocations per row (kernels index `id.x + id.y · row_stride`).
pub(crate) fn dispatch_grid(count: usize, workgroup: u32) -> ([u32; 3], u32) {
    const MAX_GROUPS: u32 = 65535;
    let groups = u32::try_from(count.div_ceil(workgroup as usize))
        .expect("dispatch too large")
        .max(1);
    let rows = groups.div_ceil(MAX_GROUPS);
    let columns = groups.div_ceil(rows);
    ([columns, rows, 1], columns * workgroup)
}

pub(crate) fn source(parts: &[&str]) -> String {
    parts.concat()
}

pub(crate) const MARCH_PARAMS: &str = include_str!("../../../shaders/march_params.wgsl");
pub(crate) const MARCH_COMMON: &str = include_str!("../../../shaders/march_common.wgsl");
/// `unfused` and `mix32`, the cpu's arithmetic to the bit, for the march
/// and the sampling kernels.
pub(crate) const CPU_ARITHMETIC: &str = include_str!("../../../shaders/cpu_arithmetic.wgsl");

/// Where a march leaves its samples on the GPU, sized for `ray_count` rays
/// and at most `capacity` samples.
pub struct GpuMarchBuffers {
    /// capacity × 3, unit-cube positions.
    pub positions: wgpu::Buffer,
    /// capacity × 3, world unit directions.
    pub directions: wgpu::Buffer,
    /// capacity, world step.
    pub dt: wgpu::Buffer,
    /// capacity, world distance.
    pub t: wgpu::Buffer,
    /// ray_count + 1 offsets (u32).
    pub ray_offsets: wgpu::Buffer,
    /// [samples kept, rays kept] (u32).
    pub counters: wgpu::Buffer,
    counts: wgpu::Buffer,
    block_sums: wgpu::Buffer,
    pub ray_count: usize,
    pub capacity: usize,
}

impl GpuMarchBuffers {
    pub fn new(context: &GpuContext, ray_count: usize, capacity: usize) -> Self {
        let blocks = block_sums_len(ray_count);
        Self {
            positions: zeroed_storage_buffer::<f32>(context, "march positions", 3 * capacity),
            directions: zeroed_storage_buffer::<f32>(context, "march directions", 3 * capacity),
            dt: zeroed_storage_buffer::<f32>(context, "march dt", capacity),
            t: zeroed_storage_buffer::<f32>(context, "march t", capacity),
            ray_offsets: zeroed_storage_buffer::<u32>(context, "march offsets", ray_count + 1),
            counters: zeroed_storage_buffer::<u32>(context, "march counters", 2),
            counts: zeroed_storage_buffer::<u32>(context, "march counts", ray_count),
            block_sums: zeroed_storage_buffer::<u32>(context, "march block sums", blocks),
            ray_count,
            capacity,
        }
    }
}

/// The buffers of a prefix sum of per-ray counts
/// ([`GpuMarch::record_prefix_sum`]).
#[derive(Debug, Clone, Copy)]
pub struct PrefixSum<'a> {
    /// ray_count u32.
    pub counts: &'a wgpu::Buffer,
    /// ray_count + 1 u32.
    pub offsets: &'a wgpu::Buffer,
    /// [`block_sums_len`] u32.
    pub block_sums: &'a wgpu::Buffer,
    /// 2 u32: [total, rays].
    pub counters: &'a wgpu::Buffer,
}

/// The scan's block totals for `ray_count` counts.
pub fn block_sums_len(ray_count: usize) -> usize {
    (ray_count + 1).div_ceil(SCAN_BLOCK)
}

/// The grid a march reads: its geometry and its bitfield on the GPU.
#[derive(Debug, Clone, Copy)]
pub struct GpuGrid<'a> {
    pub geometry: GridGeometry,
    /// u32 words, laid out as [`OccupancyGrid::bitfield`].
    pub bitfield: &'a wgpu::Buffer,
}

/// The rays of a march on the GPU: R × 3 f32 each, world space, unit
/// directions.
#[derive(Debug, Clone, Copy)]
pub struct GpuRays<'a> {
    pub origins: &'a wgpu::Buffer,
    pub directions: &'a wgpu::Buffer,
}

/// The compiled march kernels.
pub struct GpuMarch {
    count: Kernel,
    scan_blocks: Kernel,
    scan_sums: Kernel,
    scan_add: Kernel,
    clamp: Kernel,
    write: Kernel,
}

impl GpuMarch {
    pub fn new(context: &GpuContext) -> Result<Self, GpuError> {
        let walk = |name: &str, entry: &str| {
            Kernel::new(
                context,
                name,
                &source(&[MARCH_PARAMS, CPU_ARITHMETIC, MARCH_COMMON, entry]),
                "main",
            )
        };
        let scan = |name: &str, entry: &str| {
            Kernel::new(context, name, &source(&[MARCH_PARAMS, entry]), "main")
        };
        Ok(Self {
            count: walk(
                "march_count",
                include_str!("../../../shaders/march_count.wgsl"),
            )?,
            scan_blocks: scan(
                "march_scan_blocks",
                include_str!("../../../shaders/march_scan_blocks.wgsl"),
            )?,
            scan_sums: scan(
                "march_scan_sums",
                include_str!("../../../shaders/march_scan_sums.wgsl"),
            )?,
            scan_add: scan(
                "march_scan_add",
                include_str!("../../../shaders/march_scan_add.wgsl"),
            )?,
            clamp: scan(
                "march_clamp",
                include_str!("../../../shaders/march_clamp.wgsl"),
            )?,
            write: walk(
                "march_write",
                include_str!("../../../shaders/march_write.wgsl"),
            )?,
        })
    }

    /// The uniforms for marching `ray_count` rays with `params` over a grid
    /// of `geometry`, at most `capacity` samples.
    pub fn uniforms(
        geometry: GridGeometry,
        params: &MarchParams,
        ray_count: usize,
        capacity: usize,
    ) -> MarchUniforms {
        let mapping = &params.mapping;
        // As `cpu::march::Marcher::from_parts`.
        let outermost = (1u32 << (geometry.cascades - 1)) as f32;
        let half = 0.5 * mapping.aabb_scale.min(outermost);
        let element_count = ray_count + 1;
        let (_, row_stride) = dispatch_grid(element_count, WORKGROUP);
        let budget = params.sample_budget.min(capacity).min(u32::MAX as usize) as u32;
        let cone = cone_for(&params.config, mapping, &geometry);
        MarchUniforms {
            offset: mapping.offset.to_array(),
            scale: mapping.scale,
            box_min: 0.5 - half,
            box_max: 0.5 + half,
            dt: params.config.step,
            inverse_dt: 1.0 / params.config.step,
            margin: skip_margin(&geometry),
            ray_count: ray_count as u32,
            row_stride,
            resolution: geometry.resolution,
            cascades: geometry.cascades,
            max_samples: params.config.max_steps,
            jitter_seed: params.jitter_seed.unwrap_or(0),
            use_jitter: params.jitter_seed.is_some() as u32,
            zero: 0,
            budget,
            element_count: element_count as u32,
            block_count: element_count.div_ceil(SCAN_BLOCK) as u32,
            world_dt: params.config.step / mapping.scale,
            inverse_scale: 1.0 / mapping.scale,
            use_cone: cone.is_some() as u32,
            points_per_octave: cone.map_or(0.0, |c| c.points_per_octave()),
            octave_start: cone.map_or(0.0, |c| c.octave_start()),
            inverse_octave_start: cone.map_or(0.0, |c| c.inverse_octave_start()),
            last_octave: cone.map_or(0, |c| c.last_octave()),
            _pad: [0; 1],
        }
    }

    /// Records the whole march of `out.ray_count` rays into `rec`.
    pub fn record(
        &self,
        rec: &mut Recorder,
        grid: GpuGrid,
        rays: GpuRays,
        params: &MarchParams,
        out: &GpuMarchBuffers,
    ) {
        let context = rec.context;
        let GpuRays {
            origins,
            directions,
        } = rays;
        let ray_count = out.ray_count;
        let uniforms = Self::uniforms(grid.geometry, params, ray_count, out.capacity);
        assert!(
            (uniforms.block_count as usize) <= 65535,
            "too many rays for one march: {ray_count}"
        );
        let uniform = uniform_buffer(context, "march params", &uniforms);
        let (groups, _) = dispatch_grid(ray_count + 1, WORKGROUP);
        rec.encoder.clear_buffer(&out.counters, 0, None);
        self.count.record(
            rec,
            &[&uniform, grid.bitfield, origins, directions, &out.counts],
            groups,
        );
        self.record_scan(
            rec,
            (&uniform, &uniforms),
            PrefixSum {
                counts: &out.counts,
                offsets: &out.ray_offsets,
                block_sums: &out.block_sums,
                counters: &out.counters,
            },
        );
        self.clamp
            .record(rec, &[&uniform, &out.counters, &out.ray_offsets], groups);
        self.write.record(
            rec,
            &[
                &uniform,
                grid.bitfield,
                origins,
                directions,
                &out.ray_offsets,
                &out.positions,
                &out.directions,
                &out.dt,
                &out.t,
            ],
            groups,
        );
    }

    /// Records the exclusive prefix sum of `ray_count` counts into
    /// `ray_count + 1` offsets, the last being the total, which also goes
    /// to `counters[0]` (cleared here; `counters[1]` gets the number of
    /// rays): the march's scan with no sample budget, for counts made
    /// elsewhere (the samples before each ray's cut).
    pub fn record_prefix_sum(&self, rec: &mut Recorder, sum: PrefixSum, ray_count: usize) {
        let context = rec.context;
        let element_count = ray_count + 1;
        let uniforms = MarchUniforms {
            ray_count: ray_count as u32,
            row_stride: dispatch_grid(element_count, WORKGROUP).1,
            budget: u32::MAX,
            element_count: element_count as u32,
            block_count: element_count.div_ceil(SCAN_BLOCK) as u32,
            ..bytemuck::Zeroable::zeroed()
        };
        assert!(
            (uniforms.block_count as usize) <= 65535,
            "too many rays for one prefix sum: {ray_count}"
        );
        let uniform = uniform_buffer(context, "prefix sum params", &uniforms);
        rec.encoder.clear_buffer(sum.counters, 0, None);
        self.record_scan(rec, (&uniform, &uniforms), sum);
    }

    /// The three passes of the scan, with the march's uniforms.
    fn record_scan(
        &self,
        rec: &mut Recorder,
        (uniform, uniforms): (&wgpu::Buffer, &MarchUniforms),
        sum: PrefixSum,
    ) {
        let (groups, _) = dispatch_grid(uniforms.element_count as usize, WORKGROUP);
        self.scan_blocks.record(
            rec,
            &[uniform, sum.counts, sum.offsets, sum.block_sums],
            [uniforms.block_count, 1, 1],
        );
        self.scan_sums
            .record(rec, &[uniform, sum.block_sums], [1, 1, 1]);
        self.scan_add.record(
            rec,
            &[uniform, sum.block_sums, sum.offsets, sum.counters],
            groups,
        );
    }

    /// Uploads `grid`'s bitfield and the rays, marches, and reads the
    /// samples back (tests and tools). At most `capacity` samples.
    pub fn march(
        &self,
        context: &GpuContext,
        grid: &OccupancyGrid,
        origins: &[f32],
        directions: &[f32],
        params: &MarchParams,
        capacity: usize,
    ) -> (MarchedSamples, MarchStats) {
        assert_eq!(origins.len(), directions.len());
        let ray_count = origins.len() / 3;
        let bitfield = storage_buffer(context, "occupancy bitfield", grid.bitfield());
        let origins = storage_buffer(context, "ray origins", origins);
        let directions = storage_buffer(context, "ray directions", directions);
        let out = GpuMarchBuffers::new(context, ray_count, capacity);
        let mut rec = Recorder::new(context);
        let gpu_grid = GpuGrid {
            geometry: grid.geometry(),
            bitfield: &bitfield,
        };
        let rays = GpuRays {
            origins: &origins,
            directions: &directions,
        };
        self.record(&mut rec, gpu_grid, rays, params, &out);
        rec.submit();
        let counters: Vec<u32> = read_buffer(context, &out.counters, 2);
        let samples = counters[0] as usize;
        let marched = MarchedSamples {
            positions: read_buffer(context, &out.positions, 3 * samples),
            directions: read_buffer(context, &out.directions, 3 * samples),
            dt: read_buffer(context, &out.dt, samples),
            t: read_buffer(context, &out.t, samples),
            ray_offsets: read_buffer(context, &out.ray_offsets, ray_count + 1),
        };
        let stats = MarchStats {
            rays: ray_count,
            rays_kept: counters[1] as usize,
            samples,
        };
        (marched, stats)
    }
}

/// The uniforms as the shaders declare them (`engine::gpu::mirror`).
#[cfg(test)]
mod uniform_mirrors {
    use super::*;
    use crate::engine::gpu::mirror::assert_mirrors;

    #[test]
    fn marchuniforms_of_march_params_mirror_the_shader() {
        assert_mirrors!(
            include_str!("../../../shaders/march_params.wgsl"),
            "MarchParams",
            MarchUniforms,
            [
                offset,
                scale,
                box_min,
                box_max,
                dt,
                inverse_dt,
                margin,
                ray_count,
                row_stride,
                resolution,
                cascades,
                max_samples,
                jitter_seed,
                use_jitter,
                zero,
                budget,
                element_count,
                block_count,
                world_dt,
                inverse_scale,
                use_cone,
                points_per_octave,
                octave_start,
                inverse_octave_start,
                last_octave
            ]
        );
    }
}
