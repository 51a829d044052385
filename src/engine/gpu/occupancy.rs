//! The occupancy grid on the GPU (`shaders/occupancy_*.wgsl`): the EMA
//! update with densities evaluated on the GPU, and the bitfield build, the
//! same as [`OccupancyGrid::apply_update`] and
//! [`OccupancyGrid::build_bitfield`]. Choosing the cells and the points
//! inside them stays on the cpu ([`OccupancyGrid::plan_update`]): it is a
//! few milliseconds every 16 steps, and sharing it keeps both engines'
//! random choices identical.

use super::context::{GpuContext, GpuError};
use super::kernel::{Kernel, read_buffer, storage_buffer, uniform_buffer, zeroed_storage_buffer};
use super::march::{dispatch_grid, source};
use crate::engine::shared::occupancy::{GridGeometry, OccupancyGrid};
use crate::field::ngp::OccupancyConfig;

/// Threads per workgroup of the per-element kernels.
const WORKGROUP: u32 = 64;
/// Cells summed per workgroup by `occupancy_mean.wgsl`.
const MEAN_TILE: usize = 4096;

const OCCUPANCY_PARAMS: &str = include_str!("../../../shaders/occupancy_params.wgsl");

/// What the kernels need to know about a grid whose values live on the GPU.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GridDescription {
    pub geometry: GridGeometry,
    pub config: OccupancyConfig,
    /// The smallest march step, see [`OccupancyGrid::min_step`].
    pub min_step: f32,
}

impl GridDescription {
    pub fn of(grid: &OccupancyGrid) -> Self {
        Self {
            geometry: grid.geometry(),
            config: *grid.config(),
            min_step: grid.min_step(),
        }
    }
}

/// `shaders/occupancy_params.wgsl`.
#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct OccupancyUniforms {
    cell_count: u32,
    cells_per_cascade: u32,
    word_count: u32,
    partial_count: u32,
    min_optical_thickness: f32,
    row_stride: u32,
    decay: f32,
    min_step: f32,
    sample_count: u32,
    _pad: [u32; 3],
}

/// The uniforms for a dispatch of `invocations` (one per cell, word or
/// sample) and its workgroups.
fn uniforms(
    context: &GpuContext,
    grid: &GridDescription,
    sample_count: usize,
    invocations: usize,
) -> (wgpu::Buffer, [u32; 3]) {
    let geometry = grid.geometry;
    let (groups, row_stride) = dispatch_grid(invocations, WORKGROUP);
    let uniforms = OccupancyUniforms {
        cell_count: geometry.cell_count() as u32,
        cells_per_cascade: geometry.cells_per_cascade() as u32,
        word_count: geometry.bitfield_words() as u32,
        partial_count: geometry.cells_per_cascade().div_ceil(MEAN_TILE) as u32,
        min_optical_thickness: grid.config.min_optical_thickness,
        row_stride,
        decay: grid.config.decay,
        min_step: grid.min_step,
        sample_count: sample_count as u32,
        _pad: [0; 3],
    };
    (
        uniform_buffer(context, "occupancy params", &uniforms),
        groups,
    )
}

/// Scratch and outputs of [`GpuOccupancy::record_bitfield`].
pub struct GpuBitfieldBuffers {
    /// u32 words, as [`OccupancyGrid::bitfield`].
    pub bitfield: wgpu::Buffer,
    /// One f32: the threshold used.
    pub threshold: wgpu::Buffer,
    partial_sums: wgpu::Buffer,
    partial_counts: wgpu::Buffer,
}

impl GpuBitfieldBuffers {
    pub fn new(context: &GpuContext, geometry: GridGeometry) -> Self {
        let partials = geometry.cells_per_cascade().div_ceil(MEAN_TILE);
        Self {
            bitfield: zeroed_storage_buffer::<u32>(
                context,
                "occupancy bitfield",
                geometry.bitfield_words(),
            ),
            threshold: zeroed_storage_buffer::<f32>(context, "occupancy threshold", 1),
            partial_sums: zeroed_storage_buffer::<f32>(context, "occupancy partial sums", partials),
            partial_counts: zeroed_storage_buffer::<u32>(
                context,
                "occupancy partial counts",
                partials,
            ),
        }
    }
}

/// The compiled occupancy kernels.
pub struct GpuOccupancy {
    decay: Kernel,
    splat: Kernel,
    mean: Kernel,
    threshold: Kernel,
    bitfield: Kernel,
}

impl GpuOccupancy {
    pub fn new(context: &GpuContext) -> Result<Self, GpuError> {
        let kernel = |name: &str, entry: &str| {
            Kernel::new(context, name, &source(&[OCCUPANCY_PARAMS, entry]), "main")
        };
        Ok(Self {
            decay: kernel(
                "occupancy_decay",
                include_str!("../../../shaders/occupancy_decay.wgsl"),
            )?,
            splat: kernel(
                "occupancy_splat",
                include_str!("../../../shaders/occupancy_splat.wgsl"),
            )?,
            mean: kernel(
                "occupancy_mean",
                include_str!("../../../shaders/occupancy_mean.wgsl"),
            )?,
            threshold: kernel(
                "occupancy_threshold",
                include_str!("../../../shaders/occupancy_threshold.wgsl"),
            )?,
            bitfield: kernel(
                "occupancy_bitfield",
                include_str!("../../../shaders/occupancy_bitfield.wgsl"),
            )?,
        })
    }

    /// Records the EMA step of an update: every sampled-before value decays,
    /// then each of the `sample_count` samples (cell index in `cells`, u32;
    /// density in `sigma`, f32) raises its cell to its optical thickness.
    /// `values` is one f32 per cell, as [`OccupancyGrid::values`].
    #[allow(clippy::too_many_arguments)]
    pub fn record_update(
        &self,
        context: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        grid: &GridDescription,
        values: &wgpu::Buffer,
        cells: &wgpu::Buffer,
        sigma: &wgpu::Buffer,
        sample_count: usize,
    ) {
        let (uniform, groups) = uniforms(context, grid, sample_count, grid.geometry.cell_count());
        self.decay
            .record(context, encoder, &[&uniform, values], groups);
        let (uniform, groups) = uniforms(context, grid, sample_count, sample_count);
        self.splat
            .record(context, encoder, &[&uniform, cells, sigma, values], groups);
    }

    /// Records the bitfield build from `values` into `out`: the mean over
    /// cascade 0 in two reduction steps, the threshold
    /// min(min_optical_thickness, mean), then one u32 word per invocation.
    pub fn record_bitfield(
        &self,
        context: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        grid: &GridDescription,
        values: &wgpu::Buffer,
        out: &GpuBitfieldBuffers,
    ) {
        let partials = grid.geometry.cells_per_cascade().div_ceil(MEAN_TILE);
        assert!(
            partials <= 65535,
            "occupancy grid too large for one reduction"
        );
        let (uniform, groups) = uniforms(context, grid, 0, grid.geometry.bitfield_words());
        self.mean.record(
            context,
            encoder,
            &[&uniform, values, &out.partial_sums, &out.partial_counts],
            [partials as u32, 1, 1],
        );
        self.threshold.record(
            context,
            encoder,
            &[
                &uniform,
                &out.partial_sums,
                &out.partial_counts,
                &out.threshold,
            ],
            [1, 1, 1],
        );
        self.bitfield.record(
            context,
            encoder,
            &[&uniform, values, &out.threshold, &out.bitfield],
            groups,
        );
    }

    /// Builds the bitfield of `grid`'s values on the GPU and reads it back
    /// with the threshold (tests and tools).
    pub fn build_bitfield(&self, context: &GpuContext, grid: &OccupancyGrid) -> (Vec<u32>, f32) {
        let description = GridDescription::of(grid);
        let values = storage_buffer(context, "occupancy values", grid.values());
        let out = GpuBitfieldBuffers::new(context, description.geometry);
        let mut encoder = context.device.create_command_encoder(&Default::default());
        self.record_bitfield(context, &mut encoder, &description, &values, &out);
        context.queue.submit([encoder.finish()]);
        let threshold: Vec<f32> = read_buffer(context, &out.threshold, 1);
        (
            read_buffer(
                context,
                &out.bitfield,
                description.geometry.bitfield_words(),
            ),
            threshold[0],
        )
    }

    /// Applies the update `grid` has planned ([`OccupancyGrid::plan_update`])
    /// with densities `sigma` on the GPU, from `grid`'s current values, and
    /// reads back the new values, bitfield and threshold (tests and tools;
    /// `grid` itself is unchanged).
    pub fn apply_update(
        &self,
        context: &GpuContext,
        grid: &OccupancyGrid,
        sigma: &[f32],
    ) -> (Vec<f32>, Vec<u32>, f32) {
        let description = GridDescription::of(grid);
        let count = grid.update_cells().len();
        assert_eq!(sigma.len(), count, "one density per planned sample");
        let values = storage_buffer(context, "occupancy values", grid.values());
        let cells = storage_buffer(context, "occupancy sample cells", grid.update_cells());
        let sigma = storage_buffer(context, "occupancy sample density", sigma);
        let out = GpuBitfieldBuffers::new(context, description.geometry);
        let mut encoder = context.device.create_command_encoder(&Default::default());
        self.record_update(
            context,
            &mut encoder,
            &description,
            &values,
            &cells,
            &sigma,
            count,
        );
        self.record_bitfield(context, &mut encoder, &description, &values, &out);
        context.queue.submit([encoder.finish()]);
        let threshold: Vec<f32> = read_buffer(context, &out.threshold, 1);
        (
            read_buffer(context, &values, description.geometry.cell_count()),
            read_buffer(
                context,
                &out.bitfield,
                description.geometry.bitfield_words(),
            ),
            threshold[0],
        )
    }
}

/// The uniforms as the shaders declare them (`engine::gpu::mirror`).
#[cfg(test)]
mod uniform_mirrors {
    use super::*;
    use crate::engine::gpu::mirror::assert_mirrors;

    #[test]
    fn occupancyuniforms_of_occupancy_params_mirror_the_shader() {
        assert_mirrors!(
            include_str!("../../../shaders/occupancy_params.wgsl"),
            "OccupancyParams",
            OccupancyUniforms,
            [
                cell_count,
                cells_per_cascade,
                word_count,
                partial_count,
                min_optical_thickness,
                row_stride,
                decay,
                min_step,
                sample_count
            ]
        );
    }
}
