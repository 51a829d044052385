//! Dense layers on the GPU: the same MLPs, parameter layout and activations as
//! [`crate::engine::cpu::dense`], one layer per dispatch.
//!
//! Per layer, forward is one kernel (`dense_forward.wgsl`: 64 × 64 tiles of
//! rows × outputs, 4 × 4 per thread, bias and activation fused). Backward
//! is up to three: `dense_backward_weights.wgsl` sums Gᵀx over chunks of
//! rows into partial sums (one workgroup per 64 × 64 tile of the weight
//! matrix and chunk),
//! `dense_reduce.wgsl` adds the partials in chunk order into the gradients
//! (`+=`), and `dense_backward_input.wgsl` computes G W for the layer below.
//! G = dy ⊙ act'(y) is formed on load by both. No atomics: the results are
//! deterministic.
//!
//! Storage bindings are limited (128 MiB on lavapipe and many GPUs). A
//! 2^18 × 64 f32 activation is 64 MiB and fits; larger ones (2^18 rows ×
//! 256 wide = 256 MiB) are split by rows: the kernels address rows relative
//! to the binding, so the same dispatches run over pieces of rows that fit
//! the limit, each binding its rows of the same buffers (offsets multiples
//! of 64 rows, so 256-byte aligned).
//!
//! A network's parameters may sit at an offset inside a larger flat buffer
//! (a model's `[network A | network B | …]`): the `record_*` functions take
//! that offset in f32s ([`FloatsAt`]) and add it to the layer's weight and
//! bias offsets in the uniform, so nothing is copied and the parameter
//! gradients land at the same offset of the gradient buffer. Backward, each piece writes its
//! weight-gradient partial sums after the previous piece's (pieces start
//! on chunk boundaries) and one reduction adds them all in chunk order:
//! the gradients are bit for bit those of the unsplit batch. The partials
//! adapt their chunk size to stay under the limit.

use super::kernel::{
    FloatsAt, Kernel, Recorder, float_range, groups_for, pieces, read_buffer, rows_per_piece,
    storage_buffer, uniform_buffer, zeroed_storage_buffer,
};
use crate::engine::gpu::{GpuContext, GpuError};
use crate::field::mlp::{Activation, DENSITY_EXP_CLAMP, MlpLayout};

const COMMON: &str = include_str!("../../../shaders/dense_common.wgsl");
/// Each workgroup computes a BLOCK × BLOCK tile of its result
/// (dense_common.wgsl).
const BLOCK: usize = 64;
/// Rows the weight-gradient kernel steps through at a time: a chunk of rows
/// is a multiple of it.
const DEPTH: usize = 16;
/// Rows per weight-gradient partial sum, at least: 16 tiles of rows per
/// workgroup keeps the partials small (2^18 rows → 1024 partials of a
/// 64 × 64 matrix, 16 MiB) while giving a GPU thousands of workgroups.
const MIN_ROWS_PER_CHUNK: usize = 256;
/// One dispatch dimension holds at most this many workgroups (WebGPU's and
/// wgpu's default limit).
const MAX_GROUPS_PER_DIMENSION: u32 = 65535;

/// The uniform every dense kernel reads (`Layer` in dense_common.wgsl).
#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct LayerUniform {
    rows: u32,
    in_width: u32,
    out_width: u32,
    activation: u32,
    weight_offset: u32,
    bias_offset: u32,
    rows_per_chunk: u32,
    chunks: u32,
    exp_clamp: f32,
    first_chunk: u32,
    _pad: [u32; 2],
}

const NO_BIAS: u32 = u32::MAX;

fn activation_code(a: Activation) -> u32 {
    match a {
        Activation::None => 0,
        Activation::Relu => 1,
        Activation::Sigmoid => 2,
        Activation::ClampedExp => 3,
    }
}

/// The compiled dense-layer kernels.
pub struct GpuDense {
    forward: Kernel,
    backward_input: Kernel,
    backward_weights: Kernel,
    reduce: Kernel,
}

/// Activations kept between forward and backward, gradient ping-pong
/// buffers and the weight-gradient partials, for one layout at up to
/// `capacity` rows.
pub struct GpuMlpWorkspace {
    layout: MlpLayout,
    capacity: usize,
    activations: Vec<wgpu::Buffer>,
    gradients: [wgpu::Buffer; 2],
    partials: wgpu::Buffer,
    /// Partial sums the partials buffer holds per layer (fixed at creation).
    max_chunks: usize,
}

impl GpuMlpWorkspace {
    /// Bytes of the workspace's buffers on the device.
    pub fn bytes(&self) -> usize {
        let buffers = self
            .activations
            .iter()
            .chain(&self.gradients)
            .chain([&self.partials]);
        buffers.map(|b| b.size() as usize).sum()
    }

    pub fn new(context: &GpuContext, layout: &MlpLayout, capacity: usize) -> Self {
        let limit = context.storage_binding_limit() as usize;
        let max_width = *layout.widths.iter().max().expect("widths");
        let largest_matrix = (0..layout.layers())
            .map(|l| layout.widths[l + 1] * (layout.widths[l] + 1))
            .max()
            .expect("layers");
        let wanted = capacity.div_ceil(MIN_ROWS_PER_CHUNK).max(1);
        let max_chunks = wanted.min((limit / 4 / largest_matrix).max(1));
        Self {
            layout: layout.clone(),
            capacity,
            activations: layout.widths[1..]
                .iter()
                .enumerate()
                .map(|(l, &w)| {
                    zeroed_storage_buffer::<f32>(
                        context,
                        &format!("dense activations {l}"),
                        capacity * w,
                    )
                })
                .collect(),
            gradients: [0, 1].map(|i| {
                zeroed_storage_buffer::<f32>(
                    context,
                    &format!("dense gradients {i}"),
                    capacity * max_width,
                )
            }),
            partials: zeroed_storage_buffer::<f32>(
                context,
                "dense partials",
                max_chunks * largest_matrix,
            ),
            max_chunks,
        }
    }

    pub fn capacity(&self) -> usize {
        self.capacity
    }

    /// Outputs of layer `layer` after its activation, rows × width.
    pub fn activations(&self, layer: usize) -> &wgpu::Buffer {
        &self.activations[layer]
    }

    /// The network's output, rows × output width.
    pub fn output(&self) -> &wgpu::Buffer {
        self.activations.last().expect("layers")
    }

    /// Rows per partial sum and the number of partials for `rows` rows.
    fn chunking(&self, rows: usize) -> (usize, usize) {
        let per = rows
            .div_ceil(self.max_chunks)
            .max(MIN_ROWS_PER_CHUNK)
            .next_multiple_of(DEPTH);
        (per, rows.div_ceil(per).max(1))
    }
}

/// The gradients of a network's backward pass: the one given, of its
/// `output` (rows × output width); the parameters' (`params`, added to at
/// the parameters' offset); and its `input`'s (rows × input width), written
/// when asked for.
#[derive(Debug, Clone, Copy)]
pub struct MlpGradients<'a> {
    pub output: &'a wgpu::Buffer,
    pub params: &'a wgpu::Buffer,
    pub input: Option<&'a wgpu::Buffer>,
}

impl GpuDense {
    pub fn new(context: &GpuContext) -> Result<Self, GpuError> {
        let kernel = |name: &str, source: &str| {
            Kernel::new(context, name, &format!("{COMMON}\n{source}"), "main")
        };
        Ok(Self {
            forward: kernel(
                "dense_forward",
                include_str!("../../../shaders/dense_forward.wgsl"),
            )?,
            backward_input: kernel(
                "dense_backward_input",
                include_str!("../../../shaders/dense_backward_input.wgsl"),
            )?,
            backward_weights: kernel(
                "dense_backward_weights",
                include_str!("../../../shaders/dense_backward_weights.wgsl"),
            )?,
            reduce: kernel(
                "dense_reduce",
                include_str!("../../../shaders/dense_reduce.wgsl"),
            )?,
        })
    }

    /// `params_offset`: where the network's parameters (and gradients)
    /// start in the bound buffers, in f32s.
    fn uniform(
        layout: &MlpLayout,
        layer: usize,
        rows: usize,
        chunking: (usize, usize),
        params_offset: usize,
    ) -> LayerUniform {
        let offset =
            |at: usize| u32::try_from(params_offset + at).expect("parameter offsets fit in u32");
        LayerUniform {
            rows: rows as u32,
            in_width: layout.widths[layer] as u32,
            out_width: layout.widths[layer + 1] as u32,
            activation: activation_code(layout.activation(layer)),
            weight_offset: offset(layout.weight_offset(layer)),
            bias_offset: layout.bias_offset(layer).map_or(NO_BIAS, offset),
            rows_per_chunk: chunking.0 as u32,
            chunks: chunking.1 as u32,
            exp_clamp: DENSITY_EXP_CLAMP,
            first_chunk: 0,
            _pad: [0; 2],
        }
    }

    /// Workgroups for `columns` BLOCK-wide column tiles over `rows` rows,
    /// the row tiles folded into y and z.
    fn row_groups(columns: usize, rows: usize) -> [u32; 3] {
        let tiles = groups_for(rows, BLOCK as u32);
        let z = tiles.div_ceil(MAX_GROUPS_PER_DIMENSION);
        [groups_for(columns, BLOCK as u32), tiles.div_ceil(z), z]
    }

    /// Records the forward pass of every layer, the network's parameters
    /// at `params`; each layer's output lands in
    /// `workspace.activations(l)`, the network's in `workspace.output()`.
    pub fn record_forward(
        &self,
        rec: &mut Recorder,
        params: FloatsAt,
        input: &wgpu::Buffer,
        workspace: &GpuMlpWorkspace,
        rows: usize,
    ) {
        let context = rec.context;
        assert!(
            rows <= workspace.capacity,
            "{rows} rows exceed the workspace's {}",
            workspace.capacity
        );
        let layout = &workspace.layout;
        for layer in 0..layout.layers() {
            let x = if layer == 0 {
                input
            } else {
                &workspace.activations[layer - 1]
            };
            let y = &workspace.activations[layer];
            // Layer `layer`: y = act(x Wᵀ + b).
            let (in_w, out_w) = (layout.widths[layer], layout.widths[layer + 1]);
            for piece in pieces(rows, rows_per_piece(context, in_w.max(out_w), 1)) {
                let uniform = uniform_buffer(
                    context,
                    "dense layer",
                    &Self::uniform(layout, layer, piece.len(), (0, 0), params.offset),
                );
                self.forward.record_bindings(
                    rec,
                    &[
                        uniform.as_entire_buffer_binding(),
                        params.buffer.as_entire_buffer_binding(),
                        float_range(x, in_w * piece.start, in_w * piece.len()),
                        float_range(y, out_w * piece.start, out_w * piece.len()),
                    ],
                    Self::row_groups(out_w, piece.len()),
                );
            }
        }
    }

    /// Records the backward pass of the last recorded forward pass on the
    /// same `input` and `params`: accumulates (`+=`) parameter gradients
    /// into `gradients.params` (at the parameters' offset) and writes the
    /// input gradient into `gradients.input` when given.
    pub fn record_backward(
        &self,
        rec: &mut Recorder,
        params: FloatsAt,
        input: &wgpu::Buffer,
        workspace: &GpuMlpWorkspace,
        gradients: MlpGradients,
        rows: usize,
    ) {
        let context = rec.context;
        let FloatsAt {
            buffer: params,
            offset: params_offset,
        } = params;
        let MlpGradients {
            output: d_output,
            params: d_params,
            input: d_input,
        } = gradients;
        assert!(
            rows <= workspace.capacity,
            "{rows} rows exceed the workspace's {}",
            workspace.capacity
        );
        let layout = &workspace.layout;
        let (rows_per_chunk, chunks) = workspace.chunking(rows);
        // Pieces of whole chunks whose rows of every matrix bound below
        // (input, output and their gradients) fit one binding.
        let max_width = *layout.widths.iter().max().expect("widths");
        let per = rows_per_piece(context, max_width, rows_per_chunk);
        let mut d_y = d_output;
        for layer in (0..layout.layers()).rev() {
            let (in_w, out_w) = (layout.widths[layer], layout.widths[layer + 1]);
            let x = if layer == 0 {
                input
            } else {
                &workspace.activations[layer - 1]
            };
            let y = &workspace.activations[layer];
            let columns = in_w + usize::from(layout.bias);
            let piece_uniform = |piece: &std::ops::Range<usize>| {
                let mut uniform = Self::uniform(
                    layout,
                    layer,
                    piece.len(),
                    (rows_per_chunk, piece.len().div_ceil(rows_per_chunk).max(1)),
                    params_offset,
                );
                uniform.first_chunk = (piece.start / rows_per_chunk) as u32;
                uniform
            };
            for piece in pieces(rows, per) {
                let uniform = piece_uniform(&piece);
                let bound = uniform_buffer(context, "dense layer", &uniform);
                self.backward_weights.record_bindings(
                    rec,
                    &[
                        bound.as_entire_buffer_binding(),
                        float_range(d_y, out_w * piece.start, out_w * piece.len()),
                        float_range(y, out_w * piece.start, out_w * piece.len()),
                        float_range(x, in_w * piece.start, in_w * piece.len()),
                        workspace.partials.as_entire_buffer_binding(),
                    ],
                    // The bias column is summed by the first column tile.
                    [
                        groups_for(in_w, BLOCK as u32),
                        groups_for(out_w, BLOCK as u32),
                        uniform.chunks,
                    ],
                );
            }
            let uniform = uniform_buffer(
                context,
                "dense layer",
                &Self::uniform(layout, layer, rows, (rows_per_chunk, chunks), params_offset),
            );
            self.reduce.record(
                rec,
                &[&uniform, &workspace.partials, d_params],
                [groups_for(out_w * columns, 64), 1, 1],
            );
            let d_x = if layer > 0 {
                Some(&workspace.gradients[layer % 2])
            } else {
                d_input
            };
            if let Some(d_x) = d_x {
                for piece in pieces(rows, per) {
                    let uniform = uniform_buffer(context, "dense layer", &piece_uniform(&piece));
                    self.backward_input.record_bindings(
                        rec,
                        &[
                            uniform.as_entire_buffer_binding(),
                            params.as_entire_buffer_binding(),
                            float_range(d_y, out_w * piece.start, out_w * piece.len()),
                            float_range(y, out_w * piece.start, out_w * piece.len()),
                            float_range(d_x, in_w * piece.start, in_w * piece.len()),
                        ],
                        Self::row_groups(in_w, piece.len()),
                    );
                }
                d_y = d_x;
            }
        }
    }

    /// Uploads, runs the forward pass and reads back every layer's output
    /// (for tests and tools).
    pub fn forward_once(
        &self,
        context: &GpuContext,
        layout: &MlpLayout,
        params: &[f32],
        input: &[f32],
        rows: usize,
    ) -> Vec<Vec<f32>> {
        let workspace = GpuMlpWorkspace::new(context, layout, rows);
        let params_buffer = storage_buffer(context, "params", params);
        let input_buffer = storage_buffer(context, "input", &input[..rows * layout.input_width()]);
        let mut rec = Recorder::new(context);
        self.record_forward(
            &mut rec,
            FloatsAt::start(&params_buffer),
            &input_buffer,
            &workspace,
            rows,
        );
        rec.submit();
        (0..layout.layers())
            .map(|l| {
                read_buffer(
                    context,
                    &workspace.activations[l],
                    rows * layout.widths[l + 1],
                )
            })
            .collect()
    }

    /// Uploads, runs forward and backward, and reads back (outputs of every
    /// layer, parameter gradients, input gradient).
    pub fn forward_backward_once(
        &self,
        context: &GpuContext,
        layout: &MlpLayout,
        params: &[f32],
        input: &[f32],
        rows: usize,
        d_output: &[f32],
    ) -> (Vec<Vec<f32>>, Vec<f32>, Vec<f32>) {
        let workspace = GpuMlpWorkspace::new(context, layout, rows);
        let params_buffer = storage_buffer(context, "params", params);
        let input_buffer = storage_buffer(context, "input", &input[..rows * layout.input_width()]);
        let d_output_buffer = storage_buffer(
            context,
            "d_output",
            &d_output[..rows * layout.output_width()],
        );
        let d_params = zeroed_storage_buffer::<f32>(context, "d_params", params.len());
        let d_input = zeroed_storage_buffer::<f32>(context, "d_input", rows * layout.input_width());
        let mut rec = Recorder::new(context);
        rec.encoder.clear_buffer(&d_params, 0, None);
        self.record_forward(
            &mut rec,
            FloatsAt::start(&params_buffer),
            &input_buffer,
            &workspace,
            rows,
        );
        self.record_backward(
            &mut rec,
            FloatsAt::start(&params_buffer),
            &input_buffer,
            &workspace,
            MlpGradients {
                output: &d_output_buffer,
                params: &d_params,
                input: Some(&d_input),
            },
            rows,
        );
        rec.submit();
        let outputs = (0..layout.layers())
            .map(|l| {
                read_buffer(
                    context,
                    &workspace.activations[l],
                    rows * layout.widths[l + 1],
                )
            })
            .collect();
        (
            outputs,
            read_buffer(context, &d_params, params.len()),
            read_buffer(context, &d_input, rows * layout.input_width()),
        )
    }
}

/// The uniforms as the shaders declare them (`engine::gpu::mirror`).
#[cfg(test)]
mod uniform_mirrors {
    use super::*;
    use crate::engine::gpu::mirror::assert_mirrors;

    #[test]
    fn layeruniform_of_dense_common_mirror_the_shader() {
        assert_mirrors!(
            include_str!("../../../shaders/dense_common.wgsl"),
            "Layer",
            LayerUniform,
            [
                rows,
                in_width,
                out_width,
                activation,
                weight_offset,
                bias_offset,
                rows_per_chunk,
                chunks,
                exp_clamp,
                first_chunk
            ]
        );
    }
}
