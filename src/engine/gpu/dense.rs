//! Dense layers on the GPU: the same MLPs, parameter layout and activations as
//! [`crate::engine::cpu::dense`], one layer per dispatch.
//!
//! Per layer, forward is one kernel (`dense_forward.wgsl`: 16 × 16 tiles of
//! rows × outputs, bias and activation fused). Backward is up to three:
//! `dense_backward_weights.wgsl` sums Gᵀx over chunks of rows into partial
//! sums (one workgroup per 16 × 16 tile of the weight matrix and chunk),
//! `dense_reduce.wgsl` adds the partials in chunk order into the gradients
//! (`+=`), and `dense_backward_input.wgsl` computes G W for the layer below.
//! G = dy ⊙ act'(y) is formed on load by both. No atomics: the results are
//! deterministic.
//!
//! Storage bindings are limited (128 MiB on lavapipe and many GPUs). A
//! 2^18 × 64 f32 activation is 64 MiB and fits; every buffer bound here is
//! checked against the device's limit. A layer whose activations do not fit
//! (2^18 rows × 256 wide = 256 MiB) would be split by rows: the kernels
//! address rows relative to the binding, so the same dispatches run over
//! row ranges of at most limit / (width · 4) rows, each with sub-range
//! bindings (256-byte aligned offsets) of the same buffers, and the weight
//! gradients' chunk partials from all ranges are reduced together. That
//! needs bindings of buffer ranges, which `Kernel::record` does not offer
//! yet; the weight-gradient partials already adapt their chunk size to stay
//! under the limit.

use super::context::{GpuContext, GpuError};
use super::kernel::{
    Kernel, groups_for, read_buffer, storage_buffer, uniform_buffer, zeroed_storage_buffer,
};
use crate::engine::cpu::dense::{Activation, MlpLayout};
use crate::field::ngp::DENSITY_EXP_CLAMP;

const COMMON: &str = include_str!("../../../shaders/dense_common.wgsl");
const TILE: usize = 16;
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
    _pad: [u32; 3],
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
    pub fn new(context: &GpuContext, layout: &MlpLayout, capacity: usize) -> Self {
        let limit = context.limits.max_storage_buffer_binding_size as usize;
        let max_width = *layout.widths.iter().max().expect("widths");
        for &w in &layout.widths {
            check_binding(limit, capacity * w, "an activation");
        }
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
            .next_multiple_of(TILE);
        (per, rows.div_ceil(per).max(1))
    }
}

fn check_binding(limit: usize, floats: usize, what: &str) {
    assert!(
        floats * 4 <= limit,
        "{what} of {} MiB exceeds the {} MiB storage-binding limit: split the batch by rows",
        (floats * 4) >> 20,
        limit >> 20
    );
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

    fn uniform(
        layout: &MlpLayout,
        layer: usize,
        rows: usize,
        chunking: (usize, usize),
    ) -> LayerUniform {
        LayerUniform {
            rows: rows as u32,
            in_width: layout.widths[layer] as u32,
            out_width: layout.widths[layer + 1] as u32,
            activation: activation_code(layout.activation(layer)),
            weight_offset: layout.weight_offset(layer) as u32,
            bias_offset: layout.bias_offset(layer).map_or(NO_BIAS, |b| b as u32),
            rows_per_chunk: chunking.0 as u32,
            chunks: chunking.1 as u32,
            exp_clamp: DENSITY_EXP_CLAMP,
            _pad: [0; 3],
        }
    }

    /// Workgroups for `columns` 16-wide column tiles over `rows` rows, the
    /// row tiles folded into y and z.
    fn row_groups(columns: usize, rows: usize) -> [u32; 3] {
        let tiles = groups_for(rows, TILE as u32);
        let z = tiles.div_ceil(MAX_GROUPS_PER_DIMENSION);
        [groups_for(columns, TILE as u32), tiles.div_ceil(z), z]
    }

    /// Records layer `layer` forward: `output` = act(`input` Wᵀ + b).
    #[allow(clippy::too_many_arguments)]
    pub fn record_layer_forward(
        &self,
        context: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        layout: &MlpLayout,
        layer: usize,
        params: &wgpu::Buffer,
        input: &wgpu::Buffer,
        output: &wgpu::Buffer,
        rows: usize,
    ) {
        let uniform = uniform_buffer(
            context,
            "dense layer",
            &Self::uniform(layout, layer, rows, (0, 0)),
        );
        self.forward.record(
            context,
            encoder,
            &[&uniform, params, input, output],
            Self::row_groups(layout.widths[layer + 1], rows),
        );
    }

    /// Records the forward pass of every layer; each layer's output lands in
    /// `workspace.activations(l)`, the network's in `workspace.output()`.
    pub fn record_forward(
        &self,
        context: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        params: &wgpu::Buffer,
        input: &wgpu::Buffer,
        workspace: &GpuMlpWorkspace,
        rows: usize,
    ) {
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
            self.record_layer_forward(
                context,
                encoder,
                layout,
                layer,
                params,
                x,
                &workspace.activations[layer],
                rows,
            );
        }
    }

    /// Records the backward pass of the last recorded forward pass on the
    /// same `input`: accumulates (`+=`) parameter gradients into `d_params`
    /// and writes the input gradient into `d_input` when given.
    #[allow(clippy::too_many_arguments)]
    pub fn record_backward(
        &self,
        context: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        params: &wgpu::Buffer,
        input: &wgpu::Buffer,
        workspace: &GpuMlpWorkspace,
        d_output: &wgpu::Buffer,
        d_params: &wgpu::Buffer,
        d_input: Option<&wgpu::Buffer>,
        rows: usize,
    ) {
        assert!(
            rows <= workspace.capacity,
            "{rows} rows exceed the workspace's {}",
            workspace.capacity
        );
        let layout = &workspace.layout;
        let chunking = workspace.chunking(rows);
        let mut d_y = d_output;
        for layer in (0..layout.layers()).rev() {
            let uniform = uniform_buffer(
                context,
                "dense layer",
                &Self::uniform(layout, layer, rows, chunking),
            );
            let (in_w, out_w) = (layout.widths[layer], layout.widths[layer + 1]);
            let x = if layer == 0 {
                input
            } else {
                &workspace.activations[layer - 1]
            };
            let y = &workspace.activations[layer];
            let columns = in_w + usize::from(layout.bias);
            self.backward_weights.record(
                context,
                encoder,
                &[&uniform, d_y, y, x, &workspace.partials],
                [
                    groups_for(columns, TILE as u32),
                    groups_for(out_w, TILE as u32),
                    chunking.1 as u32,
                ],
            );
            self.reduce.record(
                context,
                encoder,
                &[&uniform, &workspace.partials, d_params],
                [groups_for(out_w * columns, 64), 1, 1],
            );
            let d_x = if layer > 0 {
                Some(&workspace.gradients[layer % 2])
            } else {
                d_input
            };
            if let Some(d_x) = d_x {
                self.backward_input.record(
                    context,
                    encoder,
                    &[&uniform, params, d_y, y, d_x],
                    Self::row_groups(in_w, rows),
                );
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
        let mut encoder = context.device.create_command_encoder(&Default::default());
        self.record_forward(
            context,
            &mut encoder,
            &params_buffer,
            &input_buffer,
            &workspace,
            rows,
        );
        context.queue.submit([encoder.finish()]);
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
        let mut encoder = context.device.create_command_encoder(&Default::default());
        encoder.clear_buffer(&d_params, 0, None);
        self.record_forward(
            context,
            &mut encoder,
            &params_buffer,
            &input_buffer,
            &workspace,
            rows,
        );
        self.record_backward(
            context,
            &mut encoder,
            &params_buffer,
            &input_buffer,
            &workspace,
            &d_output_buffer,
            &d_params,
            Some(&d_input),
            rows,
        );
        context.queue.submit([encoder.finish()]);
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
