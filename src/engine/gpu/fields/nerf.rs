//! NeRF's field on the `gpu` engine: the math and parameter layout of
//! [`crate::engine::cpu::fields::nerf::NerfField`] (Mildenhall et al. 2020,
//! figure 7), as gpu stages recorded into one command encoder:
//!
//! ```text
//! positions ─ frequency ─► γ(x) ─ dense A ─► h ──┐
//!                           └─────────────────────┴ concat ─► [h | γ(x)]
//! [h | γ(x)] ─ dense B ─► [σ_raw | feature] ─ density ─► σ
//! directions ─ frequency ─► γ(d) ─┐
//! [σ_raw | feature] ──────────────┴ concat (feature columns) ─► [feature | γ(d)]
//! [feature | γ(d) | appearance] ─ dense C ─► RGB (sigmoid, widened by the padding)
//! ```
//!
//! The appearance columns are there where the shape has per-image
//! embeddings ([`crate::engine::gpu::appearance`]).
//!
//! Mip-NeRF is the same field with other constants (its `NerfShape`): the
//! position encoding is the integrated one when the samples come with
//! covariances (frustums), σ a shifted softplus, the colour widened
//! (`shaders/nerf_colour_padding.wgsl`).
//!
//! The parameters are one flat buffer `[A | B | C]` (then the appearance
//! embeddings, where the shape has them), each network's
//! `MlpLayout` in the cpu engine's layout; the dense kernels read each
//! network at its offset in that buffer and accumulate its gradients at the
//! same offset of the gradient buffer ([`GpuDense::record_forward`]), so
//! nothing is copied in or out. The small kernels between the networks are
//! `shaders/nerf_concat.wgsl` (row-wise concatenation of column ranges) and
//! `shaders/nerf_density*.wgsl` (σ's activation and its backward).
//!
//! Every per-row buffer is bound a piece of rows at a time when it exceeds
//! the device's storage-binding limit, as the dense and encoding stages do.

use std::ops::Range;

use crate::engine::gpu::appearance::{GpuAppearance, GpuAppearanceTable};
use crate::engine::gpu::dense::{GpuDense, GpuMlpWorkspace, MlpGradients};
use crate::engine::gpu::fields::{FieldInputs, FieldOutputs};
use crate::engine::gpu::frequency::GpuFrequency;
use crate::engine::gpu::kernel::{
    Columns, FloatsAt, Kernel, Recorder, float_range, pieces, read_buffer, rows_per_piece,
    storage_buffer, uniform_buffer, zeroed_storage_buffer,
};
use crate::engine::gpu::march::dispatch_grid;
use crate::engine::gpu::{GpuContext, GpuError};
use crate::field::appearance::AppearanceShape;
use crate::field::nerf::{DensityActivation, NerfShape};

/// Threads per workgroup of the nerf_* kernels.
const WORKGROUP: u32 = 64;

pub(super) const DENSITY_COMMON: &str =
    include_str!("../../../../shaders/nerf_density_common.wgsl");

/// `Params` in shaders/nerf_concat.wgsl.
#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct ConcatUniform {
    rows: u32,
    row_stride: u32,
    left_stride: u32,
    left_start: u32,
    left_width: u32,
    right_stride: u32,
    right_start: u32,
    right_width: u32,
    output_stride: u32,
    output_start: u32,
    _pad: [u32; 2],
}

/// `Params` in shaders/nerf_colour_padding.wgsl.
#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct PaddingUniform {
    count: u32,
    row_stride: u32,
    scale: f32,
    offset: f32,
    zero: u32,
    _pad: [u32; 3],
}

/// `Params` in shaders/nerf_density_common.wgsl.
#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
pub(super) struct DensityUniform {
    pub(super) rows: u32,
    pub(super) row_stride: u32,
    pub(super) raw_stride: u32,
    pub(super) feature_width: u32,
    pub(super) colour_stride: u32,
    pub(super) activation: u32,
    pub(super) shift: f32,
    pub(super) _pad: u32,
}

/// The compiled kernels a NeRF field records.
pub struct GpuNerfKernels {
    dense: GpuDense,
    frequency: GpuFrequency,
    concat: Kernel,
    density: Kernel,
    density_backward: Kernel,
    colour_padding: Kernel,
}

impl GpuNerfKernels {
    pub fn new(context: &GpuContext) -> Result<Self, GpuError> {
        let density = |name: &str, source: &str| {
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
            concat: Kernel::new(
                context,
                "nerf_concat",
                include_str!("../../../../shaders/nerf_concat.wgsl"),
                "main",
            )?,
            density: density(
                "nerf_density",
                include_str!("../../../../shaders/nerf_density.wgsl"),
            )?,
            density_backward: density(
                "nerf_density_backward",
                include_str!("../../../../shaders/nerf_density_backward.wgsl"),
            )?,
            colour_padding: Kernel::new(
                context,
                "nerf_colour_padding",
                include_str!("../../../../shaders/nerf_colour_padding.wgsl"),
                "main",
            )?,
        })
    }
}

/// NeRF's field on the `gpu` engine, with buffers for up to `capacity`
/// rows (samples). It keeps the activations of the last
/// [`Self::record_forward`] for [`Self::record_backward`].
pub struct GpuNerfField {
    shape: NerfShape,
    kernels: GpuNerfKernels,
    capacity: usize,
    a: GpuMlpWorkspace,
    b: GpuMlpWorkspace,
    c: GpuMlpWorkspace,
    /// γ(x), rows × position encoding width.
    encoded_position: wgpu::Buffer,
    /// [h | γ(x)], trunk B's input.
    trunk_b_in: wgpu::Buffer,
    /// γ(d), rows × direction encoding width.
    encoded_direction: wgpu::Buffer,
    /// [feature | γ(d) | appearance], the colour network's input.
    colour_in: wgpu::Buffer,
    // Gradients with respect to the same matrices.
    d_colour_in: wgpu::Buffer,
    d_trunk_b_out: wgpu::Buffer,
    d_trunk_b_in: wgpu::Buffer,
    d_trunk_a_out: wgpu::Buffer,
    /// ∂L/∂(the sigmoid's output), when the colour is widened (else one
    /// float, unused).
    d_colour: wgpu::Buffer,
    /// The appearance embeddings' kernels, where the shape has them.
    appearance: Option<GpuAppearanceTable>,
    /// Rows of the last recorded forward pass whose activations are still
    /// held (None after [`Self::record_density`], which overwrites them).
    forward_rows: Option<usize>,
    /// Where the field's parameters start in the buffers it is given (a
    /// model keeps several fields in one flat buffer), in f32s.
    param_offset: usize,
}

impl GpuNerfField {
    /// A field of `shape` for batches of up to `capacity_rows` samples
    /// (compiles its kernels).
    pub fn new(
        context: &GpuContext,
        shape: &NerfShape,
        capacity_rows: usize,
    ) -> Result<Self, GpuError> {
        let capacity = capacity_rows.max(1);
        let width = shape.trunk_a.output_width();
        let enc = shape.position.output_width();
        let colour_width = shape.colour.input_width();
        let f = |label: &str, n: usize| zeroed_storage_buffer::<f32>(context, label, n);
        Ok(Self {
            kernels: GpuNerfKernels::new(context)?,
            a: GpuMlpWorkspace::new(context, &shape.trunk_a, capacity),
            b: GpuMlpWorkspace::new(context, &shape.trunk_b, capacity),
            c: GpuMlpWorkspace::new(context, &shape.colour, capacity),
            encoded_position: f("nerf encoded position", capacity * enc),
            trunk_b_in: f("nerf trunk B input", capacity * (width + enc)),
            encoded_direction: f(
                "nerf encoded direction",
                capacity * shape.direction.output_width(),
            ),
            colour_in: f("nerf colour input", capacity * colour_width),
            d_colour_in: f("nerf d colour input", capacity * colour_width),
            d_trunk_b_out: f("nerf d trunk B output", capacity * (width + 1)),
            d_trunk_b_in: f("nerf d trunk B input", capacity * (width + enc)),
            d_trunk_a_out: f("nerf d trunk A output", capacity * width),
            d_colour: f(
                "nerf d colour",
                if shape.colour_padding != 0.0 {
                    3 * capacity
                } else {
                    1
                },
            ),
            appearance: shape
                .appearance
                .map(|table| GpuAppearanceTable::new(context, table, capacity))
                .transpose()?,
            forward_rows: None,
            param_offset: 0,
            shape: shape.clone(),
            capacity,
        })
    }

    pub fn shape(&self) -> &NerfShape {
        &self.shape
    }

    pub fn capacity(&self) -> usize {
        self.capacity
    }

    /// Parameters of the field, `[A | B | C]` and the appearance
    /// embeddings.
    pub fn param_count(&self) -> usize {
        self.shape.appearance_range().end
    }

    /// Reads the field's parameters (and writes its gradients) from f32
    /// `offset` of the buffers passed to the `record_*` methods on, instead
    /// of from their start.
    pub fn set_param_offset(&mut self, offset: usize) {
        self.param_offset = offset;
    }

    /// Where A, B and C sit in the buffers the field is given (as the cpu
    /// field lays them out, from [`Self::set_param_offset`]).
    fn ranges(&self) -> [Range<usize>; 3] {
        let s = &self.shape;
        let o = self.param_offset;
        let a = o + s.trunk_a.param_count();
        let b = a + s.trunk_b.param_count();
        let c = b + s.colour.param_count();
        [o..a, a..b, b..c]
    }

    fn width(&self) -> usize {
        self.shape.trunk_a.output_width()
    }

    fn check_rows(&self, rows: usize) {
        assert!(
            rows <= self.capacity,
            "{rows} rows exceed the field's capacity of {}",
            self.capacity
        );
    }

    /// Records `output`'s columns = [left columns | right columns] for
    /// `rows` rows.
    fn record_concat<'a>(
        &self,
        rec: &mut Recorder,
        left: Columns<'a>,
        right: Columns<'a>,
        output: Columns<'a>,
        rows: usize,
    ) {
        let context = rec.context;
        let out_w = left.width + right.width;
        assert_eq!(output.width, out_w, "the concatenation's columns");
        assert!(
            output.start + out_w <= output.stride,
            "columns overrun the row"
        );
        let widest = left.stride.max(right.stride).max(output.stride);
        for piece in pieces(rows, rows_per_piece(context, widest, 1)) {
            let (groups, row_stride) = dispatch_grid(piece.len() * out_w, WORKGROUP);
            let uniform = ConcatUniform {
                rows: piece.len() as u32,
                row_stride,
                left_stride: left.stride as u32,
                left_start: left.start as u32,
                left_width: left.width as u32,
                right_stride: right.stride as u32,
                right_start: right.start as u32,
                right_width: right.width as u32,
                output_stride: output.stride as u32,
                output_start: output.start as u32,
                _pad: [0; 2],
            };
            let uniform = uniform_buffer(context, "nerf concat", &uniform);
            let bind = |m: &Columns<'a>| {
                float_range(m.buffer, m.stride * piece.start, m.stride * piece.len())
            };
            self.kernels.concat.record_bindings(
                rec,
                &[
                    uniform.as_entire_buffer_binding(),
                    bind(&left),
                    bind(&right),
                    bind(&output),
                ],
                groups,
            );
        }
    }

    /// The uniform of the density kernels for a piece of `rows` rows
    /// dispatched as `count` invocations.
    fn density_uniform(&self, rows: usize, count: usize) -> ([u32; 3], DensityUniform) {
        let (groups, row_stride) = dispatch_grid(count, WORKGROUP);
        let width = self.width();
        let (activation, shift) = match self.shape.density {
            DensityActivation::Relu => (0, 0.0),
            DensityActivation::ShiftedSoftplus { shift } => (1, shift),
        };
        let uniform = DensityUniform {
            rows: rows as u32,
            row_stride,
            raw_stride: (width + 1) as u32,
            feature_width: width as u32,
            colour_stride: self.shape.colour.input_width() as u32,
            activation,
            shift,
            _pad: 0,
        };
        (groups, uniform)
    }

    /// Records σ = activation(σ_raw) from trunk B's output.
    fn record_sigma(&self, rec: &mut Recorder, sigma_out: &wgpu::Buffer, rows: usize) {
        let context = rec.context;
        let raw_w = self.width() + 1;
        for piece in pieces(rows, rows_per_piece(context, raw_w, 1)) {
            let (groups, uniform) = self.density_uniform(piece.len(), piece.len());
            let uniform = uniform_buffer(context, "nerf density", &uniform);
            self.kernels.density.record_bindings(
                rec,
                &[
                    uniform.as_entire_buffer_binding(),
                    float_range(self.b.output(), raw_w * piece.start, raw_w * piece.len()),
                    float_range(sigma_out, piece.start, piece.len()),
                ],
                groups,
            );
        }
    }

    /// Records the position encoding (integrated, damped by `variances`,
    /// when they are given), trunk A, the skip concatenation and trunk B:
    /// trunk B's output [σ_raw | feature] is then in `b.output()`.
    fn record_trunk(
        &self,
        rec: &mut Recorder,
        params: &wgpu::Buffer,
        positions: &wgpu::Buffer,
        variances: Option<&wgpu::Buffer>,
        rows: usize,
    ) {
        let k = &self.kernels;
        let [ra, rb, _] = self.ranges();
        let (width, enc) = (self.width(), self.shape.position.output_width());
        k.frequency.record(
            rec,
            &self.shape.position,
            positions,
            variances,
            rows as u32,
            &self.encoded_position,
        );
        k.dense.record_forward(
            rec,
            FloatsAt {
                buffer: params,
                offset: ra.start,
            },
            &self.encoded_position,
            &self.a,
            rows,
        );
        // The skip: h first, then γ(x), as the cpu field orders it.
        self.record_concat(
            rec,
            Columns::all(self.a.output(), width),
            Columns::all(&self.encoded_position, enc),
            Columns::all(&self.trunk_b_in, width + enc),
            rows,
        );
        k.dense.record_forward(
            rec,
            FloatsAt {
                buffer: params,
                offset: rb.start,
            },
            &self.trunk_b_in,
            &self.b,
            rows,
        );
    }

    /// Records the forward pass over `rows` samples `inputs` (Gaussians,
    /// Mip-NeRF's frustums, where they have variances): σ and colour into
    /// `out`, from `params` (the field's flat parameters `[A | B | C]`, as
    /// the cpu field). Keeps the activations for [`Self::record_backward`].
    pub fn record_forward(
        &mut self,
        rec: &mut Recorder,
        params: &wgpu::Buffer,
        inputs: FieldInputs,
        appearance: GpuAppearance,
        rows: usize,
        out: FieldOutputs,
    ) {
        let FieldInputs {
            positions,
            variances,
            directions,
        } = inputs;
        let FieldOutputs {
            sigma: sigma_out,
            rgb: rgb_out,
        } = out;
        self.check_rows(rows);
        self.record_trunk(rec, params, positions, variances, rows);
        self.record_sigma(rec, sigma_out, rows);
        let [_, _, rc] = self.ranges();
        let (width, enc_dir) = (self.width(), self.shape.direction.output_width());
        let k = &self.kernels;
        k.frequency.record(
            rec,
            &self.shape.direction,
            directions,
            None,
            rows as u32,
            &self.encoded_direction,
        );
        // The colour input: trunk B's output without its σ column, then γ(d),
        // then the appearance vector where the field has embeddings.
        let colour_width = self.shape.colour.input_width();
        self.record_concat(
            rec,
            Columns {
                buffer: self.b.output(),
                stride: width + 1,
                start: 1,
                width,
            },
            Columns::all(&self.encoded_direction, enc_dir),
            Columns {
                buffer: &self.colour_in,
                stride: colour_width,
                start: 0,
                width: width + enc_dir,
            },
            rows,
        );
        if let Some(table) = self.appearance.as_mut() {
            let at = FloatsAt {
                buffer: params,
                offset: self.param_offset + self.shape.appearance_range().start,
            };
            let columns = Columns {
                buffer: &self.colour_in,
                stride: colour_width,
                start: width + enc_dir,
                width: table.shape().width,
            };
            table.record_forward(rec, at, appearance, rows, columns);
        }
        k.dense.record_forward(
            rec,
            FloatsAt {
                buffer: params,
                offset: rc.start,
            },
            &self.colour_in,
            &self.c,
            rows,
        );
        // The colour network's output stays in its workspace (its backward
        // pass reads it for the sigmoid's derivative); the caller gets a
        // copy, 12 bytes a row, widened when the shape says so.
        let padding = self.shape.colour_padding;
        if padding != 0.0 {
            self.record_padding(rec, self.c.output(), rgb_out, rows, padding);
        } else if rows > 0 {
            rec.encoder
                .copy_buffer_to_buffer(self.c.output(), 0, rgb_out, 0, 12 * rows as u64);
        }
        self.forward_rows = Some(rows);
    }

    /// Records `out` = `x` · (1 + 2p) − `offset` over `rows` × 3 values: the
    /// colour's widening (offset p) or its backward (offset 0), with the
    /// scale rounded as the cpu rounds it.
    fn record_padding(
        &self,
        rec: &mut Recorder,
        x: &wgpu::Buffer,
        out: &wgpu::Buffer,
        rows: usize,
        offset: f32,
    ) {
        let context = rec.context;
        let scale = 1.0 + 2.0 * self.shape.colour_padding;
        for piece in pieces(rows, rows_per_piece(context, 3, 1)) {
            let (groups, row_stride) = dispatch_grid(3 * piece.len(), WORKGROUP);
            let uniform = PaddingUniform {
                count: 3 * piece.len() as u32,
                row_stride,
                scale,
                offset,
                zero: 0,
                _pad: [0; 3],
            };
            let uniform = uniform_buffer(context, "nerf colour padding", &uniform);
            self.kernels.colour_padding.record_bindings(
                rec,
                &[
                    uniform.as_entire_buffer_binding(),
                    float_range(x, 3 * piece.start, 3 * piece.len()),
                    float_range(out, 3 * piece.start, 3 * piece.len()),
                ],
                groups,
            );
        }
    }

    /// Records the backward pass of the last [`Self::record_forward`] (same
    /// `params` and `rows`), given ∂L/∂σ (`d_sigma`, rows) and ∂L/∂colour
    /// (`d_rgb`, rows × 3): **adds** (+=) the parameter gradient into
    /// `gradients` (the field's layout `[A | B | C]`), as the cpu field's
    /// `backward` does; clear it first for a plain gradient. Positions and
    /// directions get no gradient.
    pub fn record_backward(
        &self,
        rec: &mut Recorder,
        params: &wgpu::Buffer,
        d_sigma: &wgpu::Buffer,
        d_rgb: &wgpu::Buffer,
        rows: usize,
        gradients: &wgpu::Buffer,
    ) {
        let context = rec.context;
        assert_eq!(
            self.forward_rows,
            Some(rows),
            "backward needs the activations of a forward pass over the same {rows} rows"
        );
        let [ra, rb, rc] = self.ranges();
        let (width, enc) = (self.width(), self.shape.position.output_width());
        let k = &self.kernels;
        // Through the colour's widening: a constant factor.
        let d_rgb = if self.shape.colour_padding != 0.0 {
            self.record_padding(rec, d_rgb, &self.d_colour, rows, 0.0);
            &self.d_colour
        } else {
            d_rgb
        };
        // Colour network. Its input gradient includes γ(d)'s columns, which
        // nothing uses (γ(d) has no parameters): 27 of 283 columns in the
        // paper's shape, computed rather than adding a column-range option
        // to the dense kernels.
        k.dense.record_backward(
            rec,
            FloatsAt {
                buffer: params,
                offset: rc.start,
            },
            &self.colour_in,
            &self.c,
            MlpGradients {
                output: d_rgb,
                params: gradients,
                input: Some(&self.d_colour_in),
            },
            rows,
        );
        let colour_w = self.shape.colour.input_width();
        if let Some(table) = &self.appearance {
            let d_appearance = Columns {
                buffer: &self.d_colour_in,
                stride: colour_w,
                start: width + self.shape.direction.output_width(),
                width: table.shape().width,
            };
            let at = FloatsAt {
                buffer: gradients,
                offset: self.param_offset + self.shape.appearance_range().start,
            };
            table.record_backward(rec, d_appearance, rows, at);
        }
        // [∂L/∂σ_raw | ∂L/∂feature] for trunk B's output.
        let raw_w = width + 1;
        for piece in pieces(rows, rows_per_piece(context, raw_w.max(colour_w), 1)) {
            let (groups, uniform) = self.density_uniform(piece.len(), piece.len() * raw_w);
            let uniform = uniform_buffer(context, "nerf density backward", &uniform);
            let bind = |buffer, w: usize| float_range(buffer, w * piece.start, w * piece.len());
            k.density_backward.record_bindings(
                rec,
                &[
                    uniform.as_entire_buffer_binding(),
                    bind(self.b.output(), raw_w),
                    bind(d_sigma, 1),
                    bind(&self.d_colour_in, colour_w),
                    bind(&self.d_trunk_b_out, raw_w),
                ],
                groups,
            );
        }
        k.dense.record_backward(
            rec,
            FloatsAt {
                buffer: params,
                offset: rb.start,
            },
            &self.trunk_b_in,
            &self.b,
            MlpGradients {
                output: &self.d_trunk_b_out,
                params: gradients,
                input: Some(&self.d_trunk_b_in),
            },
            rows,
        );
        // The skip's gradient: trunk A's output is the first `width` columns
        // of trunk B's input; the γ(x) columns are dropped (no parameters).
        // The same buffer is bound as the (empty) right-hand side.
        self.record_concat(
            rec,
            Columns {
                buffer: &self.d_trunk_b_in,
                stride: width + enc,
                start: 0,
                width,
            },
            Columns {
                buffer: &self.d_trunk_b_in,
                stride: width + enc,
                start: 0,
                width: 0,
            },
            Columns::all(&self.d_trunk_a_out, width),
            rows,
        );
        k.dense.record_backward(
            rec,
            FloatsAt {
                buffer: params,
                offset: ra.start,
            },
            &self.encoded_position,
            &self.a,
            MlpGradients {
                output: &self.d_trunk_a_out,
                params: gradients,
                input: None,
            },
            rows,
        );
    }

    /// Records σ alone at `rows` `positions` (Gaussians with `variances`
    /// when given) into `sigma_out` (for the occupancy grid). Trunk B is evaluated in full although only its
    /// first output is used (its last layer is about a quarter of B in
    /// the paper's shape). Overwrites the activations a forward pass kept:
    /// record it outside a forward/backward pair.
    pub fn record_density(
        &mut self,
        rec: &mut Recorder,
        params: &wgpu::Buffer,
        positions: &wgpu::Buffer,
        variances: Option<&wgpu::Buffer>,
        rows: usize,
        sigma_out: &wgpu::Buffer,
    ) {
        self.check_rows(rows);
        self.forward_rows = None;
        self.record_trunk(rec, params, positions, variances, rows);
        self.record_sigma(rec, sigma_out, rows);
    }

    /// Uploads, runs the forward pass and reads back (σ, rgb) (for tests
    /// and tools).
    pub fn forward_once(
        &mut self,
        context: &GpuContext,
        params: &[f32],
        inputs: FieldInputs<[f32]>,
    ) -> (Vec<f32>, Vec<f32>) {
        let rows = inputs.positions.len() / 3;
        let buffers = self.upload(context, params, inputs);
        let mut rec = Recorder::new(context);
        self.record_forward(
            &mut rec,
            &buffers.params,
            buffers.inputs(),
            GpuAppearance::Mean,
            rows,
            buffers.outputs(),
        );
        rec.submit();
        (
            read_buffer(context, &buffers.sigma, rows),
            read_buffer(context, &buffers.rgb, 3 * rows),
        )
    }

    /// Uploads, runs forward and backward (into a cleared gradient), and
    /// reads back (σ, rgb, parameter gradient).
    pub fn forward_backward_once(
        &mut self,
        context: &GpuContext,
        params: &[f32],
        inputs: FieldInputs<[f32]>,
        d_sigma: &[f32],
        d_rgb: &[f32],
    ) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
        let rows = inputs.positions.len() / 3;
        assert!(
            d_sigma.len() == rows && d_rgb.len() == 3 * rows,
            "gradients of {rows} samples"
        );
        let buffers = self.upload(context, params, inputs);
        let d_sigma = storage_buffer(context, "nerf d sigma", d_sigma);
        let d_rgb = storage_buffer(context, "nerf d rgb", d_rgb);
        let gradients = zeroed_storage_buffer::<f32>(context, "nerf gradients", params.len());
        let mut rec = Recorder::new(context);
        rec.encoder.clear_buffer(&gradients, 0, None);
        self.record_forward(
            &mut rec,
            &buffers.params,
            buffers.inputs(),
            GpuAppearance::Mean,
            rows,
            buffers.outputs(),
        );
        self.record_backward(
            &mut rec,
            &buffers.params,
            &d_sigma,
            &d_rgb,
            rows,
            &gradients,
        );
        rec.submit();
        (
            read_buffer(context, &buffers.sigma, rows),
            read_buffer(context, &buffers.rgb, 3 * rows),
            read_buffer(context, &gradients, params.len()),
        )
    }

    /// Uploads and runs [`Self::record_density`], reading σ back.
    pub fn density_once(
        &mut self,
        context: &GpuContext,
        params: &[f32],
        positions: &[f32],
        variances: Option<&[f32]>,
    ) -> Vec<f32> {
        let rows = positions.len() / 3;
        let inputs = FieldInputs {
            positions,
            variances,
            directions: &[],
        };
        let buffers = self.upload(context, params, inputs);
        let mut rec = Recorder::new(context);
        self.record_density(
            &mut rec,
            &buffers.params,
            &buffers.positions,
            buffers.variances.as_ref(),
            rows,
            &buffers.sigma,
        );
        rec.submit();
        read_buffer(context, &buffers.sigma, rows)
    }

    fn upload(
        &self,
        context: &GpuContext,
        params: &[f32],
        inputs: FieldInputs<[f32]>,
    ) -> OnceBuffers {
        let FieldInputs {
            positions,
            variances,
            directions,
        } = inputs;
        let rows = positions.len() / 3;
        assert_eq!(positions.len(), 3 * rows, "positions are not rows of 3");
        assert!(
            variances.is_none_or(|v| v.len() == positions.len()),
            "variances and positions differ in size"
        );
        assert!(
            directions.is_empty() || directions.len() == positions.len(),
            "directions and positions differ in size"
        );
        assert_eq!(params.len(), self.param_count(), "parameter count");
        assert_eq!(
            self.param_offset, 0,
            "the *_once helpers take the field's own parameters"
        );
        OnceBuffers {
            params: storage_buffer(context, "nerf params", params),
            positions: storage_buffer(context, "nerf positions", positions),
            variances: variances.map(|v| storage_buffer(context, "nerf variances", v)),
            directions: storage_buffer(context, "nerf directions", directions),
            sigma: zeroed_storage_buffer::<f32>(context, "nerf sigma", rows),
            rgb: zeroed_storage_buffer::<f32>(context, "nerf rgb", 3 * rows),
        }
    }
}

impl super::GpuField for GpuNerfField {
    fn param_count(&self) -> usize {
        GpuNerfField::param_count(self)
    }

    fn set_param_offset(&mut self, offset: usize) {
        GpuNerfField::set_param_offset(self, offset)
    }

    fn capacity(&self) -> usize {
        self.capacity
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
        GpuNerfField::record_forward(self, rec, params, inputs, appearance, rows, out)
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
        GpuNerfField::record_backward(self, rec, params, d_sigma, d_rgb, rows, gradients)
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
        GpuNerfField::record_density(self, rec, params, positions, variances, rows, sigma_out)
    }

    fn macs_per_sample(&self) -> usize {
        self.shape.macs_per_sample()
    }

    fn density_macs_per_sample(&self) -> usize {
        self.shape.density_macs_per_sample()
    }

    fn workspace_bytes(&self) -> usize {
        let buffers = [
            &self.encoded_position,
            &self.trunk_b_in,
            &self.encoded_direction,
            &self.colour_in,
            &self.d_colour_in,
            &self.d_trunk_b_out,
            &self.d_trunk_b_in,
            &self.d_trunk_a_out,
            &self.d_colour,
        ];
        buffers.iter().map(|b| b.size() as usize).sum::<usize>()
            + self.a.bytes()
            + self.b.bytes()
            + self.c.bytes()
            + self
                .appearance
                .as_ref()
                .map_or(0, GpuAppearanceTable::bytes)
    }
}

/// Buffers of the `*_once` helpers.
struct OnceBuffers {
    params: wgpu::Buffer,
    positions: wgpu::Buffer,
    variances: Option<wgpu::Buffer>,
    directions: wgpu::Buffer,
    sigma: wgpu::Buffer,
    rgb: wgpu::Buffer,
}

impl OnceBuffers {
    fn inputs(&self) -> FieldInputs<'_> {
        FieldInputs {
            positions: &self.positions,
            variances: self.variances.as_ref(),
            directions: &self.directions,
        }
    }

    fn outputs(&self) -> FieldOutputs<'_> {
        FieldOutputs {
            sigma: &self.sigma,
            rgb: &self.rgb,
        }
    }
}

/// The uniforms as the shaders declare them (`engine::gpu::mirror`).
#[cfg(test)]
mod uniform_mirrors {
    use super::*;
    use crate::engine::gpu::mirror::assert_mirrors;

    #[test]
    fn concatuniform_of_nerf_concat_mirror_the_shader() {
        assert_mirrors!(
            include_str!("../../../../shaders/nerf_concat.wgsl"),
            "Params",
            ConcatUniform,
            [
                rows,
                row_stride,
                left_stride,
                left_start,
                left_width,
                right_stride,
                right_start,
                right_width,
                output_stride,
                output_start
            ]
        );
    }
    #[test]
    fn paddinguniform_of_nerf_colour_padding_mirror_the_shader() {
        assert_mirrors!(
            include_str!("../../../../shaders/nerf_colour_padding.wgsl"),
            "Params",
            PaddingUniform,
            [count, row_stride, scale, offset, zero]
        );
    }
    #[test]
    fn densityuniform_of_nerf_density_common_mirror_the_shader() {
        assert_mirrors!(
            include_str!("../../../../shaders/nerf_density_common.wgsl"),
            "Params",
            DensityUniform,
            [
                rows,
                row_stride,
                raw_stride,
                feature_width,
                colour_stride,
                activation,
                shift
            ]
        );
    }
}
