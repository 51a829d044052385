//! The proposal sampler's density-only fields on the `gpu` engine, the
//! twins of the cpu engine's `fields/density.rs` (Instant-NGP's proposal
//! grids) and `fields/nerf_density.rs` (Mip-NeRF 360's proposal MLP), with
//! their parameter layouts, from the stages the full fields use:
//!
//! ```text
//! position ─ hash grid ─► features ─ dense (ReLU 16, clamped exp) ─► σ
//! position ─ γ (or the integrated encoding) ─ dense (4 × 256 ReLU) ─► raw ─ softplus(raw − 1) ─► σ
//! ```
//!
//! They have no colour: a proposal level composites weights only, and
//! their colour output is zero. Each keeps the activations of its last
//! forward pass for the backward pass; a field that serves several
//! proposal rounds is built once per round (the driver's twins), so each
//! round's backward pass finds its own activations.

use crate::engine::gpu::dense::{GpuDense, GpuMlpWorkspace, MlpGradients};
use crate::engine::gpu::fields::nerf::{DENSITY_COMMON, DensityUniform};
use crate::engine::gpu::fields::{FieldInputs, FieldOutputs, GpuAppearance, GpuField};
use crate::engine::gpu::frequency::GpuFrequency;
use crate::engine::gpu::hash_grid::GpuHashGrid;
use crate::engine::gpu::kernel::{
    FloatsAt, Kernel, Recorder, float_range, uniform_buffer, zeroed_storage_buffer,
};
use crate::engine::gpu::march::dispatch_grid;
use crate::engine::gpu::{GpuContext, GpuError};
use crate::field::common::Coordinates;
use crate::field::nerf::{DensityActivation, NerfDensityShape};
use crate::field::ngp::DensityShape;

/// Threads per workgroup of the density kernels.
const WORKGROUP: u32 = 64;

/// Clears the colours a density-only field does not have.
fn clear_colours(rec: &mut Recorder, rows: usize, out: FieldOutputs) {
    rec.encoder.clear_buffer(out.rgb, 0, Some(12 * rows as u64));
}

/// `Params` in shaders/density_scale.wgsl.
#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct ScaleUniform {
    count: u32,
    row_stride: u32,
    scale: f32,
    _pad: u32,
}

/// An Instant-NGP proposal level's field on the `gpu` engine: a small hash
/// grid of unit-cube (contracted) positions, one hidden layer, σ through
/// the clamped exponential (the network's output activation).
pub struct GpuDensityField {
    shape: DensityShape,
    capacity: usize,
    hash: GpuHashGrid,
    dense: GpuDense,
    network: GpuMlpWorkspace,
    /// σ = `density_scale` · y of the network's outputs y, and back.
    scale: Kernel,
    /// ∂L/∂y of the network's outputs.
    d_output: wgpu::Buffer,
    encoded: wgpu::Buffer,
    d_encoded: wgpu::Buffer,
    /// The positions of the last forward pass (a handle to the driver's
    /// buffer, unchanged until the backward pass).
    forward_positions: Option<wgpu::Buffer>,
    param_offset: usize,
}

impl GpuDensityField {
    pub fn new(
        context: &GpuContext,
        shape: &DensityShape,
        capacity_rows: usize,
    ) -> Result<Self, GpuError> {
        let capacity = capacity_rows.max(1);
        let width = shape.grid.output_width();
        Ok(Self {
            hash: GpuHashGrid::new(context, &shape.grid, true)?,
            dense: GpuDense::new(context)?,
            network: GpuMlpWorkspace::new(context, &shape.density, capacity),
            scale: Kernel::new(
                context,
                "density_scale",
                include_str!("../../../../shaders/density_scale.wgsl"),
                "main",
            )?,
            d_output: zeroed_storage_buffer::<f32>(context, "density d output", capacity),
            encoded: zeroed_storage_buffer::<f32>(context, "density encoded", capacity * width),
            d_encoded: zeroed_storage_buffer::<f32>(context, "density d encoded", capacity * width),
            forward_positions: None,
            param_offset: 0,
            shape: shape.clone(),
            capacity,
        })
    }

    fn network_at<'a>(&self, buffer: &'a wgpu::Buffer) -> FloatsAt<'a> {
        FloatsAt {
            buffer,
            offset: self.param_offset + self.shape.density_range().start,
        }
    }

    /// `to` = `density_scale` · `from` over `rows` floats.
    fn record_scale(
        &self,
        rec: &mut Recorder,
        from: &wgpu::Buffer,
        to: &wgpu::Buffer,
        rows: usize,
    ) {
        if rows == 0 {
            return;
        }
        let (groups, row_stride) = dispatch_grid(rows, WORKGROUP);
        let uniform = ScaleUniform {
            count: rows as u32,
            row_stride,
            scale: self.shape.density_scale,
            _pad: 0,
        };
        let uniform = uniform_buffer(rec.context, "density scale", &uniform);
        self.scale.record_bindings(
            rec,
            &[
                uniform.as_entire_buffer_binding(),
                float_range(from, 0, rows),
                float_range(to, 0, rows),
            ],
            groups,
        );
    }

    /// The encoding and the network at `rows` positions: σ is then the
    /// network's output times the shape's `density_scale`.
    fn record_network(
        &self,
        rec: &mut Recorder,
        params: &wgpu::Buffer,
        positions: &wgpu::Buffer,
        rows: usize,
    ) {
        assert!(rows <= self.capacity, "{rows} rows of {}", self.capacity);
        self.hash.record_encode_at(
            rec,
            FloatsAt {
                buffer: params,
                offset: self.param_offset,
            },
            positions,
            &self.encoded,
            rows,
        );
        self.dense.record_forward(
            rec,
            self.network_at(params),
            &self.encoded,
            &self.network,
            rows,
        );
    }
}

impl GpuField for GpuDensityField {
    fn param_count(&self) -> usize {
        self.shape.param_count()
    }

    fn set_param_offset(&mut self, offset: usize) {
        self.param_offset = offset;
    }

    fn capacity(&self) -> usize {
        self.capacity
    }

    fn coordinates(&self) -> Coordinates {
        Coordinates::UnitCube
    }

    fn grid_extent(&self) -> Option<f32> {
        Some(self.shape.grid.config().extent)
    }

    fn record_forward(
        &mut self,
        rec: &mut Recorder,
        params: &wgpu::Buffer,
        inputs: FieldInputs,
        _appearance: GpuAppearance,
        rows: usize,
        out: FieldOutputs,
    ) {
        self.record_network(rec, params, inputs.positions, rows);
        self.record_scale(rec, self.network.output(), out.sigma, rows);
        if rows > 0 {
            clear_colours(rec, rows, out);
        }
        self.forward_positions = Some(inputs.positions.clone());
    }

    fn record_backward(
        &self,
        rec: &mut Recorder,
        params: &wgpu::Buffer,
        d_sigma: &wgpu::Buffer,
        _d_rgb: &wgpu::Buffer,
        rows: usize,
        gradients: &wgpu::Buffer,
    ) {
        let positions = self
            .forward_positions
            .as_ref()
            .expect("a forward pass before the backward pass");
        self.record_scale(rec, d_sigma, &self.d_output, rows);
        self.dense.record_backward(
            rec,
            self.network_at(params),
            &self.encoded,
            &self.network,
            MlpGradients {
                output: &self.d_output,
                params: gradients,
                input: Some(&self.d_encoded),
            },
            rows,
        );
        self.hash.record_backward_at(
            rec,
            positions,
            &self.d_encoded,
            FloatsAt {
                buffer: gradients,
                offset: self.param_offset,
            },
            rows,
        );
    }

    fn record_density(
        &mut self,
        rec: &mut Recorder,
        params: &wgpu::Buffer,
        positions: &wgpu::Buffer,
        _variances: Option<&wgpu::Buffer>,
        rows: usize,
        sigma_out: &wgpu::Buffer,
    ) {
        self.record_network(rec, params, positions, rows);
        self.record_scale(rec, self.network.output(), sigma_out, rows);
        self.forward_positions = None;
    }

    fn macs_per_sample(&self) -> usize {
        self.shape.density.macs_per_row()
    }

    fn density_macs_per_sample(&self) -> usize {
        self.shape.density.macs_per_row()
    }

    fn workspace_bytes(&self) -> usize {
        (self.encoded.size() + self.d_encoded.size()) as usize + self.network.bytes()
    }
}

/// A NeRF or Mip-NeRF proposal level's field on the `gpu` engine: the
/// position encoding of the full field (integrated where the samples are
/// frustums), one network, σ = softplus(raw − 1).
pub struct GpuNerfDensityField {
    shape: NerfDensityShape,
    capacity: usize,
    dense: GpuDense,
    frequency: GpuFrequency,
    density: Kernel,
    density_backward: Kernel,
    network: GpuMlpWorkspace,
    encoded: wgpu::Buffer,
    d_raw: wgpu::Buffer,
    /// Rows of the last forward pass whose activations are still held.
    forward_rows: Option<usize>,
    param_offset: usize,
}

impl GpuNerfDensityField {
    pub fn new(
        context: &GpuContext,
        shape: &NerfDensityShape,
        capacity_rows: usize,
    ) -> Result<Self, GpuError> {
        let capacity = capacity_rows.max(1);
        let kernel = |name: &str, source: &str| {
            Kernel::new(
                context,
                name,
                &format!("{DENSITY_COMMON}\n{source}"),
                "main",
            )
        };
        Ok(Self {
            dense: GpuDense::new(context)?,
            frequency: GpuFrequency::new(context)?,
            density: kernel(
                "nerf_density",
                include_str!("../../../../shaders/nerf_density.wgsl"),
            )?,
            density_backward: kernel(
                "nerf_density_backward",
                include_str!("../../../../shaders/nerf_density_backward.wgsl"),
            )?,
            network: GpuMlpWorkspace::new(context, &shape.network, capacity),
            encoded: zeroed_storage_buffer::<f32>(
                context,
                "proposal encoded position",
                capacity * shape.position.output_width(),
            ),
            d_raw: zeroed_storage_buffer::<f32>(context, "proposal d raw", capacity),
            forward_rows: None,
            param_offset: 0,
            shape: shape.clone(),
            capacity,
        })
    }

    /// The density kernels' uniform over `rows` rows of one raw column.
    fn density_uniform(&self, rows: usize) -> ([u32; 3], DensityUniform) {
        let (groups, row_stride) = dispatch_grid(rows, WORKGROUP);
        let (activation, shift) = match self.shape.density {
            DensityActivation::Relu => (0, 0.0),
            DensityActivation::ShiftedSoftplus { shift } => (1, shift),
        };
        (
            groups,
            DensityUniform {
                rows: rows as u32,
                row_stride,
                raw_stride: 1,
                feature_width: 0,
                colour_stride: 1,
                activation,
                shift,
                _pad: 0,
            },
        )
    }

    /// The encoding, the network and σ at `rows` samples.
    fn record_sigma(
        &mut self,
        rec: &mut Recorder,
        params: &wgpu::Buffer,
        positions: &wgpu::Buffer,
        variances: Option<&wgpu::Buffer>,
        rows: usize,
        sigma_out: &wgpu::Buffer,
    ) {
        assert!(rows <= self.capacity, "{rows} rows of {}", self.capacity);
        if rows == 0 {
            return;
        }
        self.frequency.record(
            rec,
            &self.shape.position,
            positions,
            variances,
            rows as u32,
            &self.encoded,
        );
        self.dense.record_forward(
            rec,
            FloatsAt {
                buffer: params,
                offset: self.param_offset,
            },
            &self.encoded,
            &self.network,
            rows,
        );
        let (groups, uniform) = self.density_uniform(rows);
        let uniform = uniform_buffer(rec.context, "proposal density", &uniform);
        self.density.record_bindings(
            rec,
            &[
                uniform.as_entire_buffer_binding(),
                float_range(self.network.output(), 0, rows),
                float_range(sigma_out, 0, rows),
            ],
            groups,
        );
    }
}

impl GpuField for GpuNerfDensityField {
    fn param_count(&self) -> usize {
        self.shape.network.param_count()
    }

    fn set_param_offset(&mut self, offset: usize) {
        self.param_offset = offset;
    }

    fn capacity(&self) -> usize {
        self.capacity
    }

    fn record_forward(
        &mut self,
        rec: &mut Recorder,
        params: &wgpu::Buffer,
        inputs: FieldInputs,
        _appearance: GpuAppearance,
        rows: usize,
        out: FieldOutputs,
    ) {
        self.record_sigma(
            rec,
            params,
            inputs.positions,
            inputs.variances,
            rows,
            out.sigma,
        );
        if rows > 0 {
            rec.encoder.clear_buffer(out.rgb, 0, Some(12 * rows as u64));
        }
        self.forward_rows = Some(rows);
    }

    fn record_backward(
        &self,
        rec: &mut Recorder,
        params: &wgpu::Buffer,
        d_sigma: &wgpu::Buffer,
        _d_rgb: &wgpu::Buffer,
        rows: usize,
        gradients: &wgpu::Buffer,
    ) {
        assert_eq!(
            self.forward_rows,
            Some(rows),
            "backward needs the activations of a forward pass over the same {rows} rows"
        );
        if rows == 0 {
            return;
        }
        let (groups, uniform) = self.density_uniform(rows);
        let uniform = uniform_buffer(rec.context, "proposal density backward", &uniform);
        // One raw column: the colour input's gradient is never read (bound
        // to satisfy the kernel's layout).
        self.density_backward.record_bindings(
            rec,
            &[
                uniform.as_entire_buffer_binding(),
                float_range(self.network.output(), 0, rows),
                float_range(d_sigma, 0, rows),
                float_range(d_sigma, 0, rows),
                float_range(&self.d_raw, 0, rows),
            ],
            groups,
        );
        self.dense.record_backward(
            rec,
            FloatsAt {
                buffer: params,
                offset: self.param_offset,
            },
            &self.encoded,
            &self.network,
            MlpGradients {
                output: &self.d_raw,
                params: gradients,
                input: None,
            },
            rows,
        );
    }

    fn record_density(
        &mut self,
        rec: &mut Recorder,
        params: &wgpu::Buffer,
        positions: &wgpu::Buffer,
        variances: Option<&wgpu::Buffer>,
        rows: usize,
        sigma_out: &wgpu::Buffer,
    ) {
        self.record_sigma(rec, params, positions, variances, rows, sigma_out);
        self.forward_rows = None;
    }

    fn macs_per_sample(&self) -> usize {
        self.shape.macs_per_sample()
    }

    fn density_macs_per_sample(&self) -> usize {
        self.shape.macs_per_sample()
    }

    fn workspace_bytes(&self) -> usize {
        (self.encoded.size() + self.d_raw.size()) as usize + self.network.bytes()
    }
}

/// The uniform as the shader declares it (`engine::gpu::mirror`).
#[cfg(test)]
mod uniform_mirrors {
    use super::*;
    use crate::engine::gpu::mirror::assert_mirrors;

    #[test]
    fn scaleuniform_of_density_scale_mirrors_the_shader() {
        assert_mirrors!(
            include_str!("../../../../shaders/density_scale.wgsl"),
            "Params",
            ScaleUniform,
            [count, row_stride, scale]
        );
    }
}
