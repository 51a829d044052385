//! Instant-NGP's field on the `gpu` engine: the math and parameter layout
//! of [`crate::engine::cpu::fields::ngp::NgpField`] as gpu stages recorded
//! into one command encoder:
//!
//! ```text
//! position ─ hash grid ─► features ─ density MLP ─► raw ─ ngp_density ─► σ
//!                                                     └───────────────► [raw | SH(d) | appearance] ─ colour MLP ─► RGB
//! ```
//!
//! The parameters are one flat buffer `[hash grid | density | colour]`,
//! then the appearance embeddings where the shape has them; the
//! hash kernels and the dense kernels read each part at its offset of the
//! model's buffer and accumulate its gradient at the same offset of the
//! gradient buffer, so nothing is copied in or out. Positions are the unit
//! cube's, as marched.

use crate::engine::gpu::appearance::GpuAppearanceTable;
use crate::engine::gpu::dense::{GpuDense, GpuMlpWorkspace, MlpGradients};
use crate::engine::gpu::fields::{FieldInputs, FieldOutputs, GpuAppearance, GpuField};
use crate::engine::gpu::hash_grid::GpuHashGrid;
use crate::engine::gpu::kernel::{
    Columns, FloatsAt, Kernel, Recorder, float_range, pieces, rows_per_piece, uniform_buffer,
    zeroed_storage_buffer,
};
use crate::engine::gpu::march::dispatch_grid;
use crate::engine::gpu::sh::GpuSh;
use crate::engine::gpu::{GpuContext, GpuError};
use crate::field::appearance::AppearanceShape;
use crate::field::common::Coordinates;
use crate::field::encoding::sh_coefficients;
use crate::field::mlp::DENSITY_EXP_CLAMP;
use crate::field::ngp::NgpShape;

/// Threads per workgroup of the activation kernels.
const WORKGROUP: u32 = 64;

/// `Params` in shaders/ngp_density*.wgsl.
#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct ActivationUniforms {
    count: u32,
    row_stride: u32,
    density_width: u32,
    colour_width: u32,
    exp_clamp: f32,
    density_scale: f32,
    _pad: [u32; 2],
}

/// Instant-NGP's field on the `gpu` engine, with buffers for up to
/// `capacity` rows (samples). It keeps what the last forward pass computed
/// for the backward pass, and reads the positions and σ of that pass from
/// the buffers it was given then (a driver leaves them as they were until
/// the backward pass, as it does within a step).
pub struct GpuNgpField {
    shape: NgpShape,
    capacity: usize,
    hash: GpuHashGrid,
    dense: GpuDense,
    sh: GpuSh,
    activate: Kernel,
    activate_backward: Kernel,
    encoded: wgpu::Buffer,
    colour_input: wgpu::Buffer,
    density: GpuMlpWorkspace,
    colour: GpuMlpWorkspace,
    d_colour_input: wgpu::Buffer,
    d_density_out: wgpu::Buffer,
    d_encoded: wgpu::Buffer,
    /// The appearance embeddings' kernels, where the shape has them.
    appearance: Option<GpuAppearanceTable>,
    /// The positions and σ of the last forward pass (handles to the
    /// driver's buffers).
    forward_inputs: Option<(wgpu::Buffer, wgpu::Buffer)>,
    /// Where the field's parameters start in the model's buffers, in f32s.
    param_offset: usize,
}

impl GpuNgpField {
    /// A field of `shape` for passes of up to `capacity_rows` samples
    /// (compiles its kernels).
    pub fn new(
        context: &GpuContext,
        shape: &NgpShape,
        capacity_rows: usize,
    ) -> Result<Self, GpuError> {
        let capacity = capacity_rows.max(1);
        let f = |label: &str, n: usize| zeroed_storage_buffer::<f32>(context, label, n);
        let density_width = shape.density.output_width();
        let colour_width = shape.colour.input_width();
        let grid_width = shape.grid.output_width();
        Ok(Self {
            hash: GpuHashGrid::new(context, &shape.grid, true)?,
            dense: GpuDense::new(context)?,
            sh: GpuSh::new(context)?,
            activate: Kernel::new(
                context,
                "ngp_density",
                include_str!("../../../../shaders/ngp_density.wgsl"),
                "forward",
            )?,
            activate_backward: Kernel::new(
                context,
                "ngp_density_backward",
                include_str!("../../../../shaders/ngp_density_backward.wgsl"),
                "backward",
            )?,
            encoded: f("ngp encoded", capacity * grid_width),
            colour_input: f("ngp colour input", capacity * colour_width),
            density: GpuMlpWorkspace::new(context, &shape.density, capacity),
            colour: GpuMlpWorkspace::new(context, &shape.colour, capacity),
            d_colour_input: f("ngp d colour input", capacity * colour_width),
            d_density_out: f("ngp d density out", capacity * density_width),
            d_encoded: f("ngp d encoded", capacity * grid_width),
            appearance: shape
                .appearance
                .map(|table| GpuAppearanceTable::new(context, table, capacity))
                .transpose()?,
            forward_inputs: None,
            param_offset: 0,
            shape: shape.clone(),
            capacity,
        })
    }

    pub fn shape(&self) -> &NgpShape {
        &self.shape
    }

    fn density_offset(&self) -> usize {
        self.param_offset + self.shape.density_range().start
    }

    fn colour_offset(&self) -> usize {
        self.param_offset + self.shape.colour_range().start
    }

    /// The appearance columns of the colour network's input (or of its
    /// gradient, `buffer`): after the density outputs and the spherical
    /// harmonics.
    fn appearance_columns<'a>(&self, buffer: &'a wgpu::Buffer, width: usize) -> Columns<'a> {
        Columns {
            buffer,
            stride: self.shape.colour.input_width(),
            start: self.shape.density.output_width()
                + sh_coefficients(self.shape.network.sh_degree),
            width,
        }
    }

    /// Where the appearance embeddings start in `buffer` (the model's
    /// parameters or their gradient).
    fn appearance_at<'a>(&self, buffer: &'a wgpu::Buffer) -> FloatsAt<'a> {
        FloatsAt {
            buffer,
            offset: self.param_offset + self.shape.appearance_range().start,
        }
    }

    /// Records the density activation over `count` samples (forward: σ
    /// into `sigma` and the raw outputs into the colour input; backward:
    /// the raw outputs' gradient from σ's and the colour input's), a piece
    /// of samples at a time when the per-sample matrices exceed one storage
    /// binding.
    fn record_activation(
        &self,
        rec: &mut Recorder,
        count: usize,
        sigma: &wgpu::Buffer,
        d_sigma: Option<&wgpu::Buffer>,
    ) {
        let context = rec.context;
        let density_width = self.shape.density.output_width();
        let colour_width = self.shape.colour.input_width();
        let per = rows_per_piece(context, density_width.max(colour_width), 1);
        for piece in pieces(count, per) {
            let (groups, row_stride) = dispatch_grid(piece.len(), WORKGROUP);
            let uniforms = ActivationUniforms {
                count: piece.len() as u32,
                row_stride,
                density_width: density_width as u32,
                colour_width: colour_width as u32,
                exp_clamp: DENSITY_EXP_CLAMP,
                density_scale: self.shape.density_scale,
                _pad: [0; 2],
            };
            let uniform = uniform_buffer(context, "ngp activation", &uniforms);
            let rows = |buffer, width: usize| {
                float_range(buffer, width * piece.start, width * piece.len())
            };
            match d_sigma {
                Some(d_sigma) => self.activate_backward.record_bindings(
                    rec,
                    &[
                        uniform.as_entire_buffer_binding(),
                        rows(self.density.output(), density_width),
                        rows(sigma, 1),
                        rows(d_sigma, 1),
                        rows(&self.d_colour_input, colour_width),
                        rows(&self.d_density_out, density_width),
                    ],
                    groups,
                ),
                None => self.activate.record_bindings(
                    rec,
                    &[
                        uniform.as_entire_buffer_binding(),
                        rows(self.density.output(), density_width),
                        rows(sigma, 1),
                        rows(&self.colour_input, colour_width),
                    ],
                    groups,
                ),
            }
        }
    }

    /// Records the encoding and the density network at `rows` positions:
    /// σ into `sigma_out`, the raw outputs into the colour input.
    fn record_density_network(
        &self,
        rec: &mut Recorder,
        params: &wgpu::Buffer,
        positions: &wgpu::Buffer,
        rows: usize,
        sigma_out: &wgpu::Buffer,
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
            FloatsAt {
                buffer: params,
                offset: self.density_offset(),
            },
            &self.encoded,
            &self.density,
            rows,
        );
        self.record_activation(rec, rows, sigma_out, None);
    }
}

impl GpuField for GpuNgpField {
    fn param_count(&self) -> usize {
        self.shape.param_count()
    }

    fn set_param_offset(&mut self, offset: usize) {
        // Any offset: the hash grid binds its table from the aligned offset
        // below it (after a proposal sampler's fields, it is not aligned).
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

    fn appearance(&self) -> Option<AppearanceShape> {
        self.shape.appearance
    }

    fn record_forward(
        &mut self,
        rec: &mut Recorder,
        params: &wgpu::Buffer,
        inputs: FieldInputs,
        appearance: GpuAppearance,
        rows: usize,
        out: FieldOutputs,
    ) {
        self.record_density_network(rec, params, inputs.positions, rows, out.sigma);
        let sh_degree = self.shape.network.sh_degree;
        self.sh.record_encode(
            rec,
            sh_degree,
            inputs.directions,
            rows,
            Columns {
                buffer: &self.colour_input,
                stride: self.shape.colour.input_width(),
                start: self.shape.density.output_width(),
                width: sh_coefficients(sh_degree),
            },
        );
        if let Some(table) = &self.appearance {
            let columns = self.appearance_columns(&self.colour_input, table.shape().width);
            let at = self.appearance_at(params);
            let table = self.appearance.as_mut().expect("checked above");
            table.record_forward(rec, at, appearance, rows, columns);
        }
        self.dense.record_forward(
            rec,
            FloatsAt {
                buffer: params,
                offset: self.colour_offset(),
            },
            &self.colour_input,
            &self.colour,
            rows,
        );
        // The colours where the driver reads them (a copy, not a dispatch).
        if rows > 0 {
            rec.encoder.copy_buffer_to_buffer(
                self.colour.output(),
                0,
                out.rgb,
                0,
                12 * rows as u64,
            );
        }
        self.forward_inputs = Some((inputs.positions.clone(), out.sigma.clone()));
    }

    fn record_backward(
        &self,
        rec: &mut Recorder,
        params: &wgpu::Buffer,
        d_sigma: &wgpu::Buffer,
        d_rgb: &wgpu::Buffer,
        rows: usize,
        gradients: &wgpu::Buffer,
    ) {
        let (positions, sigma) = self
            .forward_inputs
            .as_ref()
            .expect("a forward pass before the backward pass");
        // The networks' gradients land at their parameters' offsets of the
        // flat gradient buffer.
        self.dense.record_backward(
            rec,
            FloatsAt {
                buffer: params,
                offset: self.colour_offset(),
            },
            &self.colour_input,
            &self.colour,
            MlpGradients {
                output: d_rgb,
                params: gradients,
                input: Some(&self.d_colour_input),
            },
            rows,
        );
        if let Some(table) = &self.appearance {
            table.record_backward(
                rec,
                self.appearance_columns(&self.d_colour_input, table.shape().width),
                rows,
                self.appearance_at(gradients),
            );
        }
        self.record_activation(rec, rows, sigma, Some(d_sigma));
        self.dense.record_backward(
            rec,
            FloatsAt {
                buffer: params,
                offset: self.density_offset(),
            },
            &self.encoded,
            &self.density,
            MlpGradients {
                output: &self.d_density_out,
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
        self.record_density_network(rec, params, positions, rows, sigma_out);
        // The activations now hold this pass, not a forward pass.
        self.forward_inputs = None;
    }

    fn macs_per_sample(&self) -> usize {
        self.shape.macs_per_sample()
    }

    fn density_macs_per_sample(&self) -> usize {
        self.shape.density_macs_per_sample()
    }

    fn may_find_cut_in_forward(&self) -> bool {
        // As the cpu twin (which reuses the σ pass's hash features) and as
        // instant-ngp, which always compacts: here the σ pass recomputes
        // the encoding, but both engines take the same passes.
        false
    }

    fn workspace_bytes(&self) -> usize {
        [
            &self.encoded,
            &self.colour_input,
            &self.d_colour_input,
            &self.d_density_out,
            &self.d_encoded,
        ]
        .iter()
        .map(|b| b.size() as usize)
        .sum::<usize>()
            + self.density.bytes()
            + self.colour.bytes()
            + self
                .appearance
                .as_ref()
                .map_or(0, GpuAppearanceTable::bytes)
    }
}

/// The uniforms as the shaders declare them (`engine::gpu::mirror`).
#[cfg(test)]
mod uniform_mirrors {
    use super::*;
    use crate::engine::gpu::mirror::assert_mirrors;

    #[test]
    fn activationuniforms_of_ngp_density_mirror_the_shader() {
        assert_mirrors!(
            include_str!("../../../../shaders/ngp_density.wgsl"),
            "Params",
            ActivationUniforms,
            [
                count,
                row_stride,
                density_width,
                colour_width,
                exp_clamp,
                density_scale
            ]
        );
    }
    #[test]
    fn activationuniforms_of_ngp_density_backward_mirror_the_shader() {
        assert_mirrors!(
            include_str!("../../../../shaders/ngp_density_backward.wgsl"),
            "Params",
            ActivationUniforms,
            [
                count,
                row_stride,
                density_width,
                colour_width,
                exp_clamp,
                density_scale
            ]
        );
    }
}
