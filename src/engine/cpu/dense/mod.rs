//! Dense layers: small multilayer perceptrons over a batch of rows, forward
//! and backward, at a high fraction of the machine's FLOP/s.
//!
//! A layer computes `y = act(x Wᵀ + b)` for every row `x` of the batch.
//!
//! # Parameter layout
//!
//! All parameters of an MLP live in one flat `&[f32]`, layer after layer.
//! Layer k contributes its weight matrix W_k, `out × in` row-major (row o
//! holds the weights into output o, as in PyTorch's `nn.Linear` and in
//! tiny-cuda-nn), followed by its bias b_k (`out` values) when the layout has
//! biases. [`MlpLayout::weight_offset`] and [`MlpLayout::bias_offset`] give
//! the positions; gradients use the same layout.
//!
//! # How it is computed
//!
//! Rows are processed in blocks of [`BLOCK`] through every layer at once, so a
//! block's activations stay in L1/L2 between layers (the CPU counterpart of
//! tiny-cuda-nn's fully fused MLP). Each layer product is a register-tiled
//! kernel: a tile of up to 8 rows × 64 columns of accumulators is held in
//! vector registers while the reduction runs, one broadcast of `x` and one
//! vector load of the (transposed, packed) weights per step. The same kernel
//! computes the three products of a layer:
//!
//! ```text
//! forward      Y  = X  · Wᵀ       (rows × out, reduce over in)
//! backward     dX = G  · W        (rows × in,  reduce over out)
//!              dW += Gᵀ · X       (out × in,   reduce over rows)
//! ```
//!
//! with `G = dY ⊙ act'(Y)`, bias and activation fused into the tile's
//! epilogue, and `act'` of the layer below fused into dX's epilogue. A
//! forward layer with at most four outputs (σ alone, RGB) is a dot product
//! per row and output instead (`narrow_layer`). The
//! weight-gradient reduction over the batch is split into a fixed number of
//! row chunks that depends only on the batch size, each summed into its own
//! partial gradient, and the partials are added in chunk order: results are
//! bit-identical from run to run and for any number of threads.
//!
//! Kernels exist for AVX-512, AVX2+FMA and portable Rust, chosen at run time
//! (see [`backend`]).
//!
//! Why not a GEMM crate: measured on the development machine (Zen 4, per
//! CPU-second), the `gemm` crate reaches 88-94 GFLOP/s on whole-batch
//! products of these shapes but 58 on the 64-row blocks that keep a block
//! in cache across layers, 75 on the weight-gradient reduction and 18 on the
//! 64 → 3 output layer; these kernels do 86-102 on the fused forward blocks
//! (inference), 80-90 on the backward pass, with bias, activation and
//! activation derivative fused into the products.

use std::ops::Range;

use num_traits::Float;
use rayon::prelude::*;

use crate::field::ngp::{DENSITY_EXP_CLAMP, HashGridConfig, NetworkConfig};
use crate::rng::Pcg32;

mod bf16;
mod peak;
pub use bf16::round_to_bf16;
pub use peak::{arithmetic_peak_gflops, measure_peak_gflops};

/// Rows carried through all layers together. 64 rows of a 64-wide layer are
/// 16 KiB: input, output and gradient blocks of one layer fit in L1.
pub const BLOCK: usize = 64;

/// The batch is split into at most this many chunks for the weight-gradient
/// reduction (each chunk owns one partial gradient). 32 keeps both cores busy
/// with room for imbalance while the partials stay small (32 × 25 KiB for
/// the Instant-NGP colour network).
const MAX_CHUNKS: usize = 32;

/// Rows per parallel task in the forward pass, where no reduction constrains
/// the split.
const FORWARD_CHUNK: usize = 16 * BLOCK;

/// A task's scratch, in BLOCK × max-width units: two buffers the layers
/// of a block alternate between, and one for the mixed-precision kernels'
/// bf16 pairs of a block (at most BLOCK × max-width words).
const SCRATCH_BLOCKS: usize = 3;

/// An element-wise activation.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Activation {
    None,
    Relu,
    Sigmoid,
    /// exp with the input clamped to ≤ [`DENSITY_EXP_CLAMP`]; the gradient
    /// is zero above the clamp.
    ClampedExp,
}

impl Activation {
    pub fn apply<F: Float>(self, x: F) -> F {
        match self {
            Activation::None => x,
            Activation::Relu => x.max(F::zero()),
            Activation::Sigmoid => F::one() / (F::one() + (-x).exp()),
            Activation::ClampedExp => x.min(exp_clamp()).exp(),
        }
    }

    /// The derivative at the input that produced the output `y`. Every
    /// activation here can be differentiated from its output, so the
    /// backward pass needs only the stored outputs: ReLU y > 0; sigmoid
    /// y (1 − y); the clamped exponential y below exp(clamp) and 0 at it
    /// (an input within rounding of the clamp counts as clamped).
    pub fn derivative_from_output<F: Float>(self, y: F) -> F {
        match self {
            Activation::None => F::one(),
            Activation::Relu => {
                if y > F::zero() {
                    F::one()
                } else {
                    F::zero()
                }
            }
            Activation::Sigmoid => y * (F::one() - y),
            Activation::ClampedExp => {
                if y < exp_clamp::<F>().exp() {
                    y
                } else {
                    F::zero()
                }
            }
        }
    }

    /// True where the kernels apply it with scalar code after the vector
    /// epilogue (exp is not vectorised; these sit on narrow output layers).
    fn is_transcendental(self) -> bool {
        matches!(self, Activation::Sigmoid | Activation::ClampedExp)
    }
}

fn exp_clamp<F: Float>() -> F {
    F::from(DENSITY_EXP_CLAMP).expect("representable")
}

/// The arithmetic of a network's matrix products.
#[derive(
    Debug,
    Clone,
    Copy,
    PartialEq,
    Eq,
    Default,
    clap::ValueEnum,
    serde::Serialize,
    serde::Deserialize,
)]
#[serde(rename_all = "lowercase")]
pub enum Precision {
    /// Products and sums in f32.
    #[default]
    F32,
    /// Mixed-precision training: the operands of every product (weights,
    /// activations, gradients) rounded to bf16, the products summed in f32;
    /// master weights, bias, activations, gradient sums and the optimiser
    /// stay f32. Runs on the processor's bf16 dot-product instructions
    /// where it has them ([`mixed_kernels_available`]), in f32 elsewhere.
    Mixed,
}

impl Precision {
    pub fn name(self) -> &'static str {
        match self {
            Precision::F32 => "f32",
            Precision::Mixed => "mixed",
        }
    }

    /// What the precision computes, in words.
    pub fn describe(self) -> &'static str {
        match self {
            Precision::F32 => "f32 products and sums",
            Precision::Mixed => "mixed (bf16 products summed in f32, the rest f32)",
        }
    }

    /// What runs here when this is asked for: mixed falls back to f32
    /// on processors without bf16 kernels.
    pub fn kernels_here(self) -> Self {
        backend_for(self).precision()
    }

    /// Mixed where this processor has bf16 kernels, else f32: what a
    /// user gets without asking.
    pub fn best_available() -> Self {
        if mixed_kernels_available() {
            Precision::Mixed
        } else {
            Precision::F32
        }
    }
}

/// The shape of an MLP: `widths[0]` inputs, `widths.len() − 2` hidden layers,
/// `widths[last]` outputs.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct MlpLayout {
    pub widths: Vec<usize>,
    /// Activation after every layer but the last.
    pub hidden: Activation,
    /// Activation after the last layer.
    pub output: Activation,
    /// Whether every layer has a bias.
    pub bias: bool,
    /// How the products are computed (f32 unless asked otherwise).
    pub precision: Precision,
}

impl MlpLayout {
    pub fn new(widths: Vec<usize>, hidden: Activation, output: Activation, bias: bool) -> Self {
        assert!(
            widths.len() >= 2,
            "an MLP needs an input and an output width"
        );
        assert!(
            widths.iter().all(|&w| w > 0),
            "zero-width layer in {widths:?}"
        );
        Self {
            widths,
            hidden,
            output,
            bias,
            precision: Precision::F32,
        }
    }

    /// The same network with its products computed at `precision`.
    pub fn with_precision(mut self, precision: Precision) -> Self {
        self.precision = precision;
        self
    }

    /// The kernels this network runs on here.
    pub fn kernels(&self) -> Backend {
        backend_for(self.precision)
    }

    /// Instant-NGP's density network: hash features → hidden ReLU layers →
    /// the density output (linear; the first output is log-density, the
    /// caller applies the exponential). No biases, as in tiny-cuda-nn's
    /// fully fused MLP.
    pub fn ngp_density(network: &NetworkConfig, grid: &HashGridConfig) -> Self {
        let mut widths = vec![grid.output_width()];
        widths.extend(std::iter::repeat_n(
            network.density_hidden_width,
            network.density_hidden_layers,
        ));
        widths.push(network.density_output_width);
        Self::new(widths, Activation::Relu, Activation::None, false)
    }

    /// Instant-NGP's colour network: density outputs and spherical
    /// harmonics → hidden ReLU layers → RGB through a sigmoid; no biases.
    pub fn ngp_colour(network: &NetworkConfig) -> Self {
        let mut widths = vec![network.density_output_width + network.sh_coefficients()];
        widths.extend(std::iter::repeat_n(
            network.colour_hidden_width,
            network.colour_hidden_layers,
        ));
        widths.push(3);
        Self::new(widths, Activation::Relu, Activation::Sigmoid, false)
    }

    pub fn layers(&self) -> usize {
        self.widths.len() - 1
    }

    pub fn input_width(&self) -> usize {
        self.widths[0]
    }

    pub fn output_width(&self) -> usize {
        *self.widths.last().expect("at least two widths")
    }

    pub fn activation(&self, layer: usize) -> Activation {
        if layer + 1 == self.layers() {
            self.output
        } else {
            self.hidden
        }
    }

    fn layer_params(&self, layer: usize) -> usize {
        let (i, o) = (self.widths[layer], self.widths[layer + 1]);
        o * i + if self.bias { o } else { 0 }
    }

    /// Where layer `layer`'s weights (`out × in` row-major) start.
    pub fn weight_offset(&self, layer: usize) -> usize {
        (0..layer).map(|l| self.layer_params(l)).sum()
    }

    /// Where layer `layer`'s bias starts, if the layout has biases.
    pub fn bias_offset(&self, layer: usize) -> Option<usize> {
        self.bias
            .then(|| self.weight_offset(layer) + self.widths[layer] * self.widths[layer + 1])
    }

    pub fn param_count(&self) -> usize {
        (0..self.layers()).map(|l| self.layer_params(l)).sum()
    }

    /// Multiply-adds per row of one forward pass.
    pub fn macs_per_row(&self) -> usize {
        self.widths.windows(2).map(|w| w[0] * w[1]).sum()
    }

    /// Initial parameters: weights uniform in ±√(6 / (in + out)) (Glorot &
    /// Bengio 2010, "Xavier uniform", which tiny-cuda-nn's MLPs use),
    /// biases zero.
    pub fn init_params(&self, seed: u64) -> Vec<f32> {
        let mut rng = Pcg32::new(seed, 0x006d_6c70);
        let mut params = vec![0.0; self.param_count()];
        for layer in 0..self.layers() {
            let (i, o) = (self.widths[layer], self.widths[layer + 1]);
            let scale = (6.0 / (i + o) as f32).sqrt();
            let start = self.weight_offset(layer);
            for w in &mut params[start..start + i * o] {
                *w = (2.0 * rng.next_f32() - 1.0) * scale;
            }
        }
        params
    }

    fn max_width(&self) -> usize {
        *self.widths.iter().max().expect("non-empty")
    }
}

/// Scratch for one MLP at up to `capacity` rows: every layer's outputs (kept
/// by the forward pass for the backward pass), the transposed weights, and
/// the per-chunk partial gradients. Made once and reused across steps.
pub struct MlpWorkspace {
    widths: Vec<usize>,
    capacity: usize,
    /// Output of layer l, rows × widths[l + 1].
    activations: Vec<Vec<f32>>,
    /// Wᵀ of every layer (in × out row-major), layer after layer.
    packed: Vec<f32>,
    /// MAX_CHUNKS partial parameter gradients.
    partials: Vec<f32>,
    /// Per chunk: two BLOCK × max-width gradient buffers, then the
    /// mixed-precision kernels' bf16 pairs (BLOCK × max-width words).
    scratch: Vec<f32>,
    /// The weights as bf16 pairs for the mixed-precision kernels (empty
    /// until they run).
    pairs: bf16::PairedWeights,
}

impl MlpWorkspace {
    pub fn new(layout: &MlpLayout, capacity: usize) -> Self {
        let chunks = MAX_CHUNKS;
        Self {
            widths: layout.widths.clone(),
            capacity,
            activations: layout.widths[1..]
                .iter()
                .map(|&w| vec![0.0; capacity * w])
                .collect(),
            packed: vec![0.0; layout.macs_per_row()],
            partials: vec![0.0; chunks * layout.param_count()],
            scratch: vec![0.0; chunks * SCRATCH_BLOCKS * BLOCK * layout.max_width()],
            pairs: bf16::PairedWeights::default(),
        }
    }

    pub fn capacity(&self) -> usize {
        self.capacity
    }

    /// Bytes held (for memory accounting).
    pub fn bytes(&self) -> usize {
        4 * (self.activations.iter().map(Vec::capacity).sum::<usize>()
            + self.packed.capacity()
            + self.partials.capacity()
            + self.scratch.capacity()
            + self.pairs.words())
    }

    /// Grows the workspace to hold `rows` rows (never shrinks).
    pub fn reserve(&mut self, rows: usize) {
        if rows > self.capacity {
            self.capacity = rows;
            for (a, &w) in self.activations.iter_mut().zip(&self.widths[1..]) {
                a.resize(rows * w, 0.0);
            }
        }
    }

    /// Outputs of layer `layer` (after its activation) from the last forward
    /// pass, rows × width.
    pub fn activations(&self, layer: usize) -> &[f32] {
        &self.activations[layer]
    }

    fn check(&self, layout: &MlpLayout, rows: usize) {
        assert_eq!(
            self.widths, layout.widths,
            "workspace made for another layout"
        );
        assert!(
            rows <= self.capacity,
            "{rows} rows exceed the workspace's {}",
            self.capacity
        );
    }
}

/// Which vector kernels run.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Backend {
    /// bf16 pair products (`vdpbf16ps`) for the layer products, AVX-512
    /// for the rest: [`Precision::Mixed`].
    Avx512Bf16,
    Avx512,
    Avx2,
    Portable,
}

impl Backend {
    pub fn precision(self) -> Precision {
        match self {
            Backend::Avx512Bf16 => Precision::Mixed,
            _ => Precision::F32,
        }
    }
}

/// Whether this processor runs [`Precision::Mixed`] on bf16 kernels
/// (AVX512-BF16: AMD Zen 4 and later, Intel Cooper Lake and Sapphire
/// Rapids and later).
#[cfg(target_arch = "x86_64")]
pub fn mixed_kernels_available() -> bool {
    static DETECTED: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *DETECTED.get_or_init(|| {
        backend() == Backend::Avx512
            && is_x86_feature_detected!("avx512bw")
            && is_x86_feature_detected!("avx512vl")
            && is_x86_feature_detected!("avx512bf16")
    })
}

#[cfg(not(target_arch = "x86_64"))]
pub fn mixed_kernels_available() -> bool {
    false
}

/// The kernels a network at `precision` runs on here.
pub fn backend_for(precision: Precision) -> Backend {
    match precision {
        Precision::Mixed if mixed_kernels_available() => Backend::Avx512Bf16,
        _ => backend(),
    }
}

/// The best f32 kernels this CPU supports.
pub fn backend() -> Backend {
    static DETECTED: std::sync::OnceLock<Backend> = std::sync::OnceLock::new();
    *DETECTED.get_or_init(|| {
        #[cfg(target_arch = "x86_64")]
        {
            if is_x86_feature_detected!("avx512f")
                && is_x86_feature_detected!("avx2")
                && is_x86_feature_detected!("fma")
            {
                return Backend::Avx512;
            }
            if is_x86_feature_detected!("avx2") && is_x86_feature_detected!("fma") {
                return Backend::Avx2;
            }
        }
        Backend::Portable
    })
}

/// Forward pass over `rows` rows of `input` (rows × in), keeping every
/// layer's output in `workspace` for [`mlp_backward`], and writing the last
/// layer's into `output` (rows × out).
pub fn mlp_forward(
    layout: &MlpLayout,
    params: &[f32],
    input: &[f32],
    rows: usize,
    workspace: &mut MlpWorkspace,
    output: &mut [f32],
) {
    forward_with(
        layout.kernels(),
        layout,
        params,
        input,
        rows,
        workspace,
        output,
    );
}

/// Backward pass of the last [`mlp_forward`] on the same `input`:
/// accumulates (`+=`) the parameter gradients into `d_params` and, when
/// asked, writes (`=`) the gradient with respect to the input into
/// `d_input` (rows × in). `d_output` is rows × out.
#[allow(clippy::too_many_arguments)]
pub fn mlp_backward(
    layout: &MlpLayout,
    params: &[f32],
    input: &[f32],
    rows: usize,
    workspace: &mut MlpWorkspace,
    d_output: &[f32],
    d_params: &mut [f32],
    d_input: Option<&mut [f32]>,
) {
    let columns = 0..layout.input_width();
    backward_with(
        layout.kernels(),
        layout,
        params,
        input,
        rows,
        workspace,
        d_output,
        d_params,
        d_input.map(|d| (d, columns)),
    );
}

/// [`mlp_backward`] with the input gradient of only some input columns:
/// `d_input` is rows × `columns.len()`. The colour network needs the
/// gradient of its density-feature columns but not of its direction
/// encoding, and skipping those saves their share of the last product.
#[allow(clippy::too_many_arguments)]
pub fn mlp_backward_columns(
    layout: &MlpLayout,
    params: &[f32],
    input: &[f32],
    rows: usize,
    workspace: &mut MlpWorkspace,
    d_output: &[f32],
    d_params: &mut [f32],
    d_input: &mut [f32],
    columns: Range<usize>,
) {
    backward_with(
        layout.kernels(),
        layout,
        params,
        input,
        rows,
        workspace,
        d_output,
        d_params,
        Some((d_input, columns)),
    );
}

/// Forward pass without keeping activations (for rendering): only `output`
/// is written. Bit-identical to [`mlp_forward`]'s output.
pub fn mlp_inference(
    layout: &MlpLayout,
    params: &[f32],
    input: &[f32],
    rows: usize,
    output: &mut [f32],
) {
    let columns = layout.output_width();
    inference_with(
        layout.kernels(),
        layout,
        params,
        input,
        rows,
        output,
        columns,
    );
}

/// [`mlp_inference`] computing only the first `columns` outputs of the last
/// layer: `output` is rows × `columns`. Instant-NGP's density queries need
/// output 0 (log-density) of the density network's 16, one dot product in
/// place of 16. Each computed output is bit-identical to [`mlp_forward`]'s.
pub fn mlp_inference_leading(
    layout: &MlpLayout,
    params: &[f32],
    input: &[f32],
    rows: usize,
    output: &mut [f32],
    columns: usize,
) {
    assert!(
        (1..=layout.output_width()).contains(&columns),
        "{columns} leading outputs of {}",
        layout.output_width()
    );
    inference_with(
        layout.kernels(),
        layout,
        params,
        input,
        rows,
        output,
        columns,
    );
}

fn check_sizes(layout: &MlpLayout, params: &[f32], input: &[f32], rows: usize, output_len: usize) {
    assert_eq!(params.len(), layout.param_count(), "parameter count");
    assert!(
        input.len() >= rows * layout.input_width(),
        "input holds fewer than {rows} rows"
    );
    assert!(
        output_len >= rows * layout.output_width(),
        "output holds fewer than {rows} rows"
    );
}

fn pack_transposed(layout: &MlpLayout, params: &[f32], packed: &mut [f32]) {
    let mut at = 0;
    for layer in 0..layout.layers() {
        let (i, o) = (layout.widths[layer], layout.widths[layer + 1]);
        let w = &params[layout.weight_offset(layer)..][..i * o];
        let dst = &mut packed[at..at + i * o];
        for (row, weights) in w.chunks_exact(i).enumerate() {
            for (col, &x) in weights.iter().enumerate() {
                dst[col * o + row] = x;
            }
        }
        at += i * o;
    }
}

/// The layers' pointers into `params`, the transposed weights `packed`
/// and, for the mixed-precision kernels, the weights as bf16 pairs.
fn net<'a>(
    layout: &'a MlpLayout,
    params: &'a [f32],
    packed: &'a [f32],
    pairs: &'a bf16::PairedWeights,
) -> Net<'a> {
    let mut layers = Vec::with_capacity(layout.layers());
    let mut at = 0;
    for layer in 0..layout.layers() {
        let (i, o) = (layout.widths[layer], layout.widths[layer + 1]);
        let w_off = layout.weight_offset(layer);
        let b_off = layout.bias_offset(layer);
        let (wt_pairs, w_pairs) = pairs.layer(layer);
        layers.push(Layer {
            inw: i,
            outw: o,
            w: params[w_off..].as_ptr(),
            wt: packed.get(at..).map_or(std::ptr::null(), <[f32]>::as_ptr),
            wt_pairs,
            w_pairs,
            bias: b_off.map_or(std::ptr::null(), |b| params[b..].as_ptr()),
            w_off,
            b_off,
        });
        at += i * o;
    }
    Net {
        layers,
        hidden: layout.hidden,
        output: layout.output,
        _params: std::marker::PhantomData,
    }
}

fn forward_with(
    backend: Backend,
    layout: &MlpLayout,
    params: &[f32],
    input: &[f32],
    rows: usize,
    workspace: &mut MlpWorkspace,
    output: &mut [f32],
) {
    check_sizes(layout, params, input, rows, output.len());
    workspace.check(layout, rows);
    if backend == Backend::Avx512Bf16 {
        workspace.pairs.pack_forward(layout, params);
    } else {
        pack_transposed(layout, params, &mut workspace.packed);
    }
    let net = net(layout, params, &workspace.packed, &workspace.pairs);
    let max_width = layout.max_width();
    let job = ForwardJob {
        net: &net,
        max_width,
        input: input.as_ptr(),
        activations: workspace
            .activations
            .iter_mut()
            .map(|a| SendPtr(a.as_mut_ptr()))
            .collect(),
        output: SendPtr(output.as_mut_ptr()),
    };
    let tasks = rows.div_ceil(FORWARD_CHUNK);
    (0..tasks).into_par_iter().for_each_init(
        || vec![0.0f32; SCRATCH_BLOCKS * BLOCK * max_width],
        |scratch, t| {
            let range = t * FORWARD_CHUNK..((t + 1) * FORWARD_CHUNK).min(rows);
            // SAFETY: tasks write disjoint row ranges of the activations
            // and output, whose sizes were checked above; the scratch is
            // the task's own.
            unsafe { dispatch::forward(backend, &job, range, scratch.as_mut_ptr()) }
        },
    );
}

fn inference_with(
    backend: Backend,
    layout: &MlpLayout,
    params: &[f32],
    input: &[f32],
    rows: usize,
    output: &mut [f32],
    out_columns: usize,
) {
    // Sized for the leading columns: the full width stands in for the check.
    let output_rows = output.len() / out_columns;
    check_sizes(
        layout,
        params,
        input,
        rows,
        output_rows * layout.output_width(),
    );
    let mut packed = Vec::new();
    let mut pairs = bf16::PairedWeights::default();
    if backend == Backend::Avx512Bf16 {
        pairs.pack_forward(layout, params);
    } else {
        packed.resize(layout.macs_per_row(), 0.0);
        pack_transposed(layout, params, &mut packed);
    }
    let net = net(layout, params, &packed, &pairs);
    let job = InferenceJob {
        net: &net,
        max_width: layout.max_width(),
        input: input.as_ptr(),
        output: SendPtr(output.as_mut_ptr()),
        out_columns,
    };
    let scratch_len = SCRATCH_BLOCKS * BLOCK * layout.max_width();
    let tasks = rows.div_ceil(FORWARD_CHUNK);
    (0..tasks).into_par_iter().for_each_init(
        || vec![0.0f32; scratch_len],
        |scratch, t| {
            let range = t * FORWARD_CHUNK..((t + 1) * FORWARD_CHUNK).min(rows);
            // SAFETY: disjoint output rows per task; scratch is the task's own.
            unsafe { dispatch::inference(backend, &job, range, scratch.as_mut_ptr()) }
        },
    );
}

/// The row chunks of the weight-gradient reduction: a function of the row
/// count only, so the summation order never depends on the thread count.
fn backward_chunks(rows: usize) -> (usize, usize) {
    let blocks = rows.div_ceil(BLOCK).max(1);
    let chunks = blocks.min(MAX_CHUNKS);
    let chunk_rows = blocks.div_ceil(chunks) * BLOCK;
    (rows.div_ceil(chunk_rows).max(1), chunk_rows)
}

#[allow(clippy::too_many_arguments)]
fn backward_with(
    backend: Backend,
    layout: &MlpLayout,
    params: &[f32],
    input: &[f32],
    rows: usize,
    workspace: &mut MlpWorkspace,
    d_output: &[f32],
    d_params: &mut [f32],
    d_input: Option<(&mut [f32], Range<usize>)>,
) {
    check_sizes(layout, params, input, rows, d_output.len());
    workspace.check(layout, rows);
    assert_eq!(d_params.len(), params.len(), "gradient count");
    if let Some((d, columns)) = &d_input {
        assert!(
            columns.start < columns.end && columns.end <= layout.input_width(),
            "input columns {columns:?} of {}",
            layout.input_width()
        );
        assert!(
            d.len() >= rows * columns.len(),
            "d_input holds fewer than {rows} rows"
        );
    }
    if rows == 0 {
        return;
    }
    // The forward pass packed Wᵀ; the backward pass uses W itself (or, in
    // mixed precision, W's pairs of rows), but `net` wants a slice to
    // point into.
    if backend == Backend::Avx512Bf16 {
        workspace.pairs.pack_backward(layout, params);
    }
    let net = net(layout, params, &workspace.packed, &workspace.pairs);
    let n_params = layout.param_count();
    let max_width = layout.max_width();
    let (chunks, chunk_rows) = backward_chunks(rows);
    let job = BackwardJob {
        net: &net,
        input: input.as_ptr(),
        activations: workspace.activations.iter().map(|a| a.as_ptr()).collect(),
        d_output: d_output.as_ptr(),
        d_input_columns: d_input.as_ref().map_or(0..0, |(_, c)| c.clone()),
        d_input: SendPtr(d_input.map_or(std::ptr::null_mut(), |(d, _)| d.as_mut_ptr())),
        n_params,
        max_width,
    };
    let partials = SendPtr(workspace.partials.as_mut_ptr());
    let scratch = SendPtr(workspace.scratch.as_mut_ptr());
    (0..chunks).into_par_iter().for_each(|c| {
        let range = c * chunk_rows..((c + 1) * chunk_rows).min(rows);
        // SAFETY: chunk c owns partial c, scratch c and the d_input rows of
        // its range.
        unsafe {
            let partial = partials.get().add(c * n_params);
            let g = scratch.get().add(c * SCRATCH_BLOCKS * BLOCK * max_width);
            dispatch::backward(backend, &job, range, partial, g)
        }
    });
    // Chunk partials added in chunk order, in parallel over parameters.
    let partials = &workspace.partials;
    d_params
        .par_chunks_mut(1024)
        .enumerate()
        .for_each(|(s, out)| {
            let start = s * 1024;
            for c in 0..chunks {
                let p = &partials[c * n_params + start..][..out.len()];
                for (d, x) in out.iter_mut().zip(p) {
                    *d += x;
                }
            }
        });
}

// ---------------------------------------------------------------------------
// Kernels.

/// A raw pointer that rayon tasks may share; every use says why the accesses
/// are disjoint.
#[derive(Clone, Copy)]
struct SendPtr(*mut f32);
unsafe impl Send for SendPtr {}
unsafe impl Sync for SendPtr {}
impl SendPtr {
    fn get(self) -> *mut f32 {
        self.0
    }
}

#[derive(Clone, Copy)]
struct Layer {
    inw: usize,
    outw: usize,
    /// W, out × in.
    w: *const f32,
    /// Wᵀ, in × out (f32 kernels only).
    wt: *const f32,
    /// Wᵀ as bf16 pairs along `in`: ⌈in/2⌉ × out words (mixed-precision
    /// kernels only, else null).
    wt_pairs: *const u32,
    /// W as bf16 pairs along `out`: ⌈out/2⌉ × in words (mixed-precision
    /// backward only, else null).
    w_pairs: *const u32,
    /// Null without biases.
    bias: *const f32,
    w_off: usize,
    b_off: Option<usize>,
}

struct Net<'a> {
    layers: Vec<Layer>,
    hidden: Activation,
    output: Activation,
    _params: std::marker::PhantomData<&'a [f32]>,
}

// SAFETY: the pointers are read-only views of slices borrowed for 'a.
unsafe impl Sync for Net<'_> {}

impl Net<'_> {
    fn act(&self, layer: usize) -> Activation {
        if layer + 1 == self.layers.len() {
            self.output
        } else {
            self.hidden
        }
    }
}

struct ForwardJob<'a> {
    net: &'a Net<'a>,
    max_width: usize,
    input: *const f32,
    activations: Vec<SendPtr>,
    output: SendPtr,
}
unsafe impl Sync for ForwardJob<'_> {}

struct InferenceJob<'a> {
    net: &'a Net<'a>,
    max_width: usize,
    input: *const f32,
    output: SendPtr,
    /// The leading outputs of the last layer that are computed (rows ×
    /// out_columns in `output`).
    out_columns: usize,
}
unsafe impl Sync for InferenceJob<'_> {}

struct BackwardJob<'a> {
    net: &'a Net<'a>,
    input: *const f32,
    activations: Vec<*const f32>,
    d_output: *const f32,
    /// Null when the input gradient is not wanted.
    d_input: SendPtr,
    /// The input columns whose gradient is wanted.
    d_input_columns: Range<usize>,
    n_params: usize,
    max_width: usize,
}
unsafe impl Sync for BackwardJob<'_> {}

/// What a tile does with its accumulators.
#[derive(Clone, Copy)]
enum Epi {
    Store,
    Accumulate,
    /// c = act(acc + bias); bias may be null.
    Forward {
        bias: *const f32,
        act: Activation,
    },
    /// c = acc ⊙ act'(y), y laid out like c with row stride y_m.
    Backward {
        act: Activation,
        y: *const f32,
        y_m: usize,
    },
}

/// `c[i, j] ⊕= Σ_k a[i·a_m + k·a_k] · b[k·b_k + j]` for i < m, j < n.
struct Gemm {
    m: usize,
    n: usize,
    k: usize,
    a: *const f32,
    a_m: usize,
    a_k: usize,
    b: *const f32,
    b_k: usize,
    c: *mut f32,
    c_m: usize,
    epi: Epi,
}

/// A vector instruction set, as the kernels see it.
trait Lanes {
    type V: Copy;
    type M: Copy;
    /// f32 lanes per vector.
    const N: usize;
    /// Vectors per tile row: a panel is N · NV_MAX columns.
    const NV_MAX: usize;
    unsafe fn zero() -> Self::V;
    unsafe fn splat(x: f32) -> Self::V;
    /// The first min(n, N) lanes.
    unsafe fn mask(n: usize) -> Self::M;
    unsafe fn load(p: *const f32, m: Self::M) -> Self::V;
    unsafe fn store(p: *mut f32, v: Self::V, m: Self::M);
    /// a · b + c
    unsafe fn fma(a: Self::V, b: Self::V, c: Self::V) -> Self::V;
    unsafe fn add(a: Self::V, b: Self::V) -> Self::V;
    unsafe fn relu(x: Self::V) -> Self::V;
    /// g where y > 0, else 0.
    unsafe fn relu_gate(g: Self::V, y: Self::V) -> Self::V;
    /// Copies n floats with stores that bypass the caches where the
    /// instruction set has them.
    unsafe fn stream_copy(dst: *mut f32, src: *const f32, n: usize) {
        unsafe { std::ptr::copy_nonoverlapping(src, dst, n) }
    }
    /// Orders streaming stores before what follows (the end of a task).
    unsafe fn store_fence() {}
    /// The sum of the lanes.
    unsafe fn sum(v: Self::V) -> f32;
}

/// Copies `$n` floats, the part of `$dst` aligned to `$align` bytes in
/// `$step`-float pieces through `$stream` and the rest with plain stores.
/// A macro, not a function taking a closure: a closure is compiled without
/// the caller's vector extensions, so the streaming intrinsic inside it
/// became a function call per 64 bytes (1% of a training step).
macro_rules! stream_with {
    ($dst:expr, $src:expr, $n:expr, $align:expr, $step:expr, |$d:ident, $s:ident| $stream:expr) => {{
        let (dst, src, n): (*mut f32, *const f32, usize) = ($dst, $src, $n);
        let head = (($align - dst as usize % $align) % $align / 4).min(n);
        std::ptr::copy_nonoverlapping(src, dst, head);
        let mut i = head;
        while i + $step <= n {
            let ($d, $s) = (dst.add(i), src.add(i));
            $stream;
            i += $step;
        }
        std::ptr::copy_nonoverlapping(src.add(i), dst.add(i), n - i);
    }};
}

#[cfg(target_arch = "x86_64")]
mod x86 {
    use super::Lanes;
    use std::arch::x86_64::*;

    pub struct Avx512;
    impl Lanes for Avx512 {
        type V = __m512;
        type M = __mmask16;
        const N: usize = 16;
        const NV_MAX: usize = 4;
        #[inline(always)]
        unsafe fn zero() -> __m512 {
            unsafe { _mm512_setzero_ps() }
        }
        #[inline(always)]
        unsafe fn splat(x: f32) -> __m512 {
            unsafe { _mm512_set1_ps(x) }
        }
        #[inline(always)]
        unsafe fn mask(n: usize) -> __mmask16 {
            if n >= 16 {
                0xffff
            } else {
                ((1u32 << n) - 1) as u16
            }
        }
        #[inline(always)]
        unsafe fn load(p: *const f32, m: __mmask16) -> __m512 {
            unsafe { _mm512_maskz_loadu_ps(m, p) }
        }
        #[inline(always)]
        unsafe fn store(p: *mut f32, v: __m512, m: __mmask16) {
            unsafe { _mm512_mask_storeu_ps(p, m, v) }
        }
        #[inline(always)]
        unsafe fn fma(a: __m512, b: __m512, c: __m512) -> __m512 {
            unsafe { _mm512_fmadd_ps(a, b, c) }
        }
        #[inline(always)]
        unsafe fn add(a: __m512, b: __m512) -> __m512 {
            unsafe { _mm512_add_ps(a, b) }
        }
        #[inline(always)]
        unsafe fn relu(x: __m512) -> __m512 {
            unsafe { _mm512_max_ps(x, _mm512_setzero_ps()) }
        }
        #[inline(always)]
        unsafe fn relu_gate(g: __m512, y: __m512) -> __m512 {
            unsafe {
                _mm512_maskz_mov_ps(_mm512_cmp_ps_mask::<_CMP_GT_OQ>(y, _mm512_setzero_ps()), g)
            }
        }
        #[inline(always)]
        unsafe fn sum(v: __m512) -> f32 {
            unsafe { _mm512_reduce_add_ps(v) }
        }
        #[inline(always)]
        unsafe fn stream_copy(dst: *mut f32, src: *const f32, n: usize) {
            unsafe {
                stream_with!(dst, src, n, 64, 16, |d, s| _mm512_stream_ps(
                    d,
                    _mm512_loadu_ps(s)
                ))
            }
        }
        #[inline(always)]
        unsafe fn store_fence() {
            unsafe { _mm_sfence() }
        }
    }

    pub struct Avx2;
    /// Lane masks for maskload: 8 all-ones then 8 zeros, read at 8 − n.
    static MASKS: [i32; 16] = [-1, -1, -1, -1, -1, -1, -1, -1, 0, 0, 0, 0, 0, 0, 0, 0];
    impl Lanes for Avx2 {
        type V = __m256;
        /// The lane count and its mask: full vectors use plain loads.
        type M = (usize, __m256i);
        const N: usize = 8;
        const NV_MAX: usize = 2;
        #[inline(always)]
        unsafe fn zero() -> __m256 {
            unsafe { _mm256_setzero_ps() }
        }
        #[inline(always)]
        unsafe fn splat(x: f32) -> __m256 {
            unsafe { _mm256_set1_ps(x) }
        }
        #[inline(always)]
        unsafe fn mask(n: usize) -> (usize, __m256i) {
            let n = n.min(8);
            unsafe {
                (
                    n,
                    _mm256_loadu_si256(MASKS.as_ptr().add(8 - n) as *const __m256i),
                )
            }
        }
        #[inline(always)]
        unsafe fn load(p: *const f32, m: (usize, __m256i)) -> __m256 {
            unsafe {
                if m.0 == 8 {
                    _mm256_loadu_ps(p)
                } else {
                    _mm256_maskload_ps(p, m.1)
                }
            }
        }
        #[inline(always)]
        unsafe fn store(p: *mut f32, v: __m256, m: (usize, __m256i)) {
            unsafe {
                if m.0 == 8 {
                    _mm256_storeu_ps(p, v)
                } else {
                    _mm256_maskstore_ps(p, m.1, v)
                }
            }
        }
        #[inline(always)]
        unsafe fn fma(a: __m256, b: __m256, c: __m256) -> __m256 {
            unsafe { _mm256_fmadd_ps(a, b, c) }
        }
        #[inline(always)]
        unsafe fn add(a: __m256, b: __m256) -> __m256 {
            unsafe { _mm256_add_ps(a, b) }
        }
        #[inline(always)]
        unsafe fn relu(x: __m256) -> __m256 {
            unsafe { _mm256_max_ps(x, _mm256_setzero_ps()) }
        }
        #[inline(always)]
        unsafe fn relu_gate(g: __m256, y: __m256) -> __m256 {
            unsafe { _mm256_and_ps(g, _mm256_cmp_ps::<_CMP_GT_OQ>(y, _mm256_setzero_ps())) }
        }
        #[inline(always)]
        unsafe fn sum(v: __m256) -> f32 {
            unsafe {
                let quad = _mm_add_ps(_mm256_castps256_ps128(v), _mm256_extractf128_ps::<1>(v));
                let pair = _mm_add_ps(quad, _mm_movehl_ps(quad, quad));
                _mm_cvtss_f32(_mm_add_ss(pair, _mm_movehdup_ps(pair)))
            }
        }
        #[inline(always)]
        unsafe fn stream_copy(dst: *mut f32, src: *const f32, n: usize) {
            unsafe {
                stream_with!(dst, src, n, 32, 8, |d, s| _mm256_stream_ps(
                    d,
                    _mm256_loadu_ps(s)
                ))
            }
        }
        #[inline(always)]
        unsafe fn store_fence() {
            unsafe { _mm_sfence() }
        }
    }
}

/// Plain Rust, 8 lanes as an array; the compiler vectorises what it can.
struct Portable;
impl Lanes for Portable {
    type V = [f32; 8];
    type M = usize;
    const N: usize = 8;
    const NV_MAX: usize = 2;
    #[inline(always)]
    unsafe fn zero() -> [f32; 8] {
        [0.0; 8]
    }
    #[inline(always)]
    unsafe fn splat(x: f32) -> [f32; 8] {
        [x; 8]
    }
    #[inline(always)]
    unsafe fn mask(n: usize) -> usize {
        n.min(8)
    }
    #[inline(always)]
    unsafe fn load(p: *const f32, m: usize) -> [f32; 8] {
        let mut v = [0.0; 8];
        if m == 8 {
            unsafe { std::ptr::copy_nonoverlapping(p, v.as_mut_ptr(), 8) };
        } else {
            for (j, x) in v.iter_mut().enumerate().take(m) {
                *x = unsafe { *p.add(j) };
            }
        }
        v
    }
    #[inline(always)]
    unsafe fn store(p: *mut f32, v: [f32; 8], m: usize) {
        for (j, x) in v.iter().enumerate().take(m) {
            unsafe { *p.add(j) = *x };
        }
    }
    #[inline(always)]
    unsafe fn fma(a: [f32; 8], b: [f32; 8], c: [f32; 8]) -> [f32; 8] {
        std::array::from_fn(|j| a[j] * b[j] + c[j])
    }
    #[inline(always)]
    unsafe fn add(a: [f32; 8], b: [f32; 8]) -> [f32; 8] {
        std::array::from_fn(|j| a[j] + b[j])
    }
    #[inline(always)]
    unsafe fn relu(x: [f32; 8]) -> [f32; 8] {
        x.map(|x| x.max(0.0))
    }
    #[inline(always)]
    unsafe fn relu_gate(g: [f32; 8], y: [f32; 8]) -> [f32; 8] {
        std::array::from_fn(|j| if y[j] > 0.0 { g[j] } else { 0.0 })
    }
    #[inline(always)]
    unsafe fn sum(v: [f32; 8]) -> f32 {
        v.iter().sum()
    }
}

/// Rows per register tile for a tile NV vectors wide: as many as the
/// register file holds with the NV weight vectors and one broadcast
/// (AVX-512: 32 registers; AVX2: 16).
macro_rules! with_tile_rows {
    ($nv:expr, $body:ident, $($args:expr),*) => {
        match $nv {
            1 => $body::<L, 1, 8>($($args),*),
            2 => $body::<L, 2, 6>($($args),*),
            3 => $body::<L, 3, 4>($($args),*),
            _ => $body::<L, 4, 4>($($args),*),
        }
    };
}

#[inline(always)]
unsafe fn gemm<L: Lanes>(g: &Gemm) {
    let panel = L::N * L::NV_MAX;
    let mut j0 = 0;
    while j0 < g.n {
        let nj = (g.n - j0).min(panel);
        unsafe { with_tile_rows!(nj.div_ceil(L::N), panel_rows, g, j0, nj) };
        j0 += panel;
    }
}

#[inline(always)]
unsafe fn panel_rows<L: Lanes, const NV: usize, const MR: usize>(g: &Gemm, j0: usize, nj: usize) {
    let mut masks = [unsafe { L::mask(0) }; NV];
    for (v, m) in masks.iter_mut().enumerate() {
        *m = unsafe { L::mask(nj - v * L::N) };
    }
    let mut i = 0;
    while i + MR <= g.m {
        unsafe { tile::<L, MR, NV>(g, i, j0, nj, &masks) };
        i += MR;
    }
    unsafe {
        match g.m - i {
            0 => {}
            1 => tile::<L, 1, NV>(g, i, j0, nj, &masks),
            2 if MR > 2 => tile::<L, 2, NV>(g, i, j0, nj, &masks),
            3 if MR > 3 => tile::<L, 3, NV>(g, i, j0, nj, &masks),
            4 if MR > 4 => tile::<L, 4, NV>(g, i, j0, nj, &masks),
            5 if MR > 5 => tile::<L, 5, NV>(g, i, j0, nj, &masks),
            6 if MR > 6 => tile::<L, 6, NV>(g, i, j0, nj, &masks),
            7 if MR > 7 => tile::<L, 7, NV>(g, i, j0, nj, &masks),
            _ => unreachable!("remainders are below MR ≤ 8"),
        }
    }
}

#[inline(always)]
unsafe fn tile<L: Lanes, const R: usize, const NV: usize>(
    g: &Gemm,
    i0: usize,
    j0: usize,
    nj: usize,
    masks: &[L::M; NV],
) {
    unsafe {
        let mut acc = [[L::zero(); NV]; R];
        let mut a = g.a.add(i0 * g.a_m);
        let mut b = g.b.add(j0);
        for _ in 0..g.k {
            let mut bv = [L::zero(); NV];
            for v in 0..NV {
                bv[v] = L::load(b.add(v * L::N), masks[v]);
            }
            for (r, acc_r) in acc.iter_mut().enumerate() {
                let av = L::splat(*a.add(r * g.a_m));
                for v in 0..NV {
                    acc_r[v] = L::fma(av, bv[v], acc_r[v]);
                }
            }
            a = a.add(g.a_k);
            b = b.add(g.b_k);
        }
        let destination = Destination {
            c: g.c,
            c_m: g.c_m,
            epi: g.epi,
        };
        epilogue::<L, R, NV>(destination, i0, j0, nj, masks, &acc);
    }
}

/// Where a tile's results go and what is done to them on the way.
#[derive(Clone, Copy)]
struct Destination {
    c: *mut f32,
    c_m: usize,
    epi: Epi,
}

#[inline(always)]
unsafe fn epilogue<L: Lanes, const R: usize, const NV: usize>(
    g: Destination,
    i0: usize,
    j0: usize,
    nj: usize,
    masks: &[L::M; NV],
    acc: &[[L::V; NV]; R],
) {
    unsafe {
        for (r, acc_r) in acc.iter().enumerate() {
            let c = g.c.add((i0 + r) * g.c_m + j0);
            for v in 0..NV {
                let p = c.add(v * L::N);
                let m = masks[v];
                let x = acc_r[v];
                match g.epi {
                    Epi::Store => L::store(p, x, m),
                    Epi::Accumulate => L::store(p, L::add(L::load(p, m), x), m),
                    Epi::Forward { bias, act } => {
                        let x = if bias.is_null() {
                            x
                        } else {
                            L::add(x, L::load(bias.add(j0 + v * L::N), m))
                        };
                        let x = if act == Activation::Relu {
                            L::relu(x)
                        } else {
                            x
                        };
                        L::store(p, x, m);
                    }
                    Epi::Backward { act, y, y_m } => {
                        let x = if act == Activation::Relu {
                            L::relu_gate(x, L::load(y.add((i0 + r) * y_m + j0 + v * L::N), m))
                        } else {
                            x
                        };
                        L::store(p, x, m);
                    }
                }
            }
        }
        match g.epi {
            Epi::Forward { act, .. } if act.is_transcendental() => {
                for r in 0..R {
                    let c = g.c.add((i0 + r) * g.c_m + j0);
                    for j in 0..nj {
                        *c.add(j) = act.apply(*c.add(j));
                    }
                }
            }
            Epi::Backward { act, y, y_m } if act.is_transcendental() => {
                for r in 0..R {
                    let c = g.c.add((i0 + r) * g.c_m + j0);
                    let y = y.add((i0 + r) * y_m + j0);
                    for j in 0..nj {
                        *c.add(j) *= act.derivative_from_output(*y.add(j));
                    }
                }
            }
            _ => {}
        }
    }
}

/// Layers with at most this many outputs (computed) go through
/// [`narrow_layer`] instead of a register tile.
const NARROW_COLUMNS: usize = 4;

/// `c = act(x Wᵀ + b)` for a layer with few outputs (σ alone, RGB): one
/// dot product per row and output along W's contiguous rows. A register
/// tile would spend a whole vector of lanes on each of these 1–3 columns;
/// on lego_400 this made the σ-only inference of a training batch ~1.8×
/// faster.
/// The sum runs in a different order than the tile's, so outputs differ
/// from a tile's in the last bits.
#[inline(always)]
unsafe fn narrow_layer<L: Lanes>(
    layer: &Layer,
    x: *const f32,
    nb: usize,
    n: usize,
    act: Activation,
    c: *mut f32,
) {
    let k = layer.inw;
    unsafe {
        for r in 0..nb {
            let row = x.add(r * k);
            for j in 0..n {
                let weights = layer.w.add(j * k);
                let mut acc = L::zero();
                let mut i = 0;
                while i < k {
                    let m = L::mask(k - i);
                    acc = L::fma(L::load(row.add(i), m), L::load(weights.add(i), m), acc);
                    i += L::N;
                }
                let mut y = L::sum(acc);
                if !layer.bias.is_null() {
                    y += *layer.bias.add(j);
                }
                *c.add(r * n + j) = act.apply(y);
            }
        }
    }
}

/// Where a block's layers go: a trait with methods inlined into the kernels
/// rather than closures, which are compiled without the kernels' vector
/// extensions (their streaming stores became out-of-line calls).
trait BlockSink {
    /// Where layer `l` writes its block.
    unsafe fn destination(&self, l: usize) -> *mut f32;
    /// Called once layer `l` wrote its block at `block`.
    unsafe fn after(&self, l: usize, block: *const f32);
}

/// How a layer's three products are computed: in f32 on lanes `L`
/// ([`F32Products`]) or from bf16 pairs ([`bf16::Bf16Products`]). The
/// block loops above and below are written once over this.
trait Products {
    /// The lanes of everything but the products (narrow layers, copies).
    type L: Lanes;

    /// `c = epi(a Wᵀ)` for `nb` rows of `a` (row stride `layer.inw`), the
    /// first `n` outputs (row stride `n`). `pairs` is scratch for BLOCK ×
    /// max-width words.
    unsafe fn forward(
        layer: &Layer,
        a: *const f32,
        nb: usize,
        n: usize,
        out: Destination,
        pairs: *mut u32,
    );

    /// `dW += Gᵀ X` over `nb` rows: `g` is nb × out, `x` nb × in, `dw`
    /// out × in.
    unsafe fn weight_gradient(
        layer: &Layer,
        g: *const f32,
        x: *const f32,
        nb: usize,
        dw: *mut f32,
        pairs: *mut u32,
    );

    /// `c = epi(G W[:, first..first + n])` for `nb` rows of `g` (nb × out).
    #[allow(clippy::too_many_arguments)]
    unsafe fn input_gradient(
        layer: &Layer,
        g: *const f32,
        nb: usize,
        first: usize,
        n: usize,
        out: Destination,
        pairs: *mut u32,
    );
}

/// The products in f32 with the register-tiled [`gemm`].
struct F32Products<L>(std::marker::PhantomData<L>);

impl<L: Lanes> Products for F32Products<L> {
    type L = L;

    #[inline(always)]
    unsafe fn forward(
        layer: &Layer,
        a: *const f32,
        nb: usize,
        n: usize,
        out: Destination,
        _: *mut u32,
    ) {
        unsafe {
            gemm::<L>(&Gemm {
                m: nb,
                n,
                k: layer.inw,
                a,
                a_m: layer.inw,
                a_k: 1,
                b: layer.wt,
                b_k: layer.outw,
                c: out.c,
                c_m: out.c_m,
                epi: out.epi,
            })
        }
    }

    #[inline(always)]
    unsafe fn weight_gradient(
        layer: &Layer,
        g: *const f32,
        x: *const f32,
        nb: usize,
        dw: *mut f32,
        _: *mut u32,
    ) {
        // Rows of dW are outputs; the reduction runs over the block's rows.
        unsafe {
            gemm::<L>(&Gemm {
                m: layer.outw,
                n: layer.inw,
                k: nb,
                a: g,
                a_m: 1,
                a_k: layer.outw,
                b: x,
                b_k: layer.inw,
                c: dw,
                c_m: layer.inw,
                epi: Epi::Accumulate,
            })
        }
    }

    #[inline(always)]
    unsafe fn input_gradient(
        layer: &Layer,
        g: *const f32,
        nb: usize,
        first: usize,
        n: usize,
        out: Destination,
        _: *mut u32,
    ) {
        unsafe {
            gemm::<L>(&Gemm {
                m: nb,
                n,
                k: layer.outw,
                a: g,
                a_m: layer.outw,
                a_k: 1,
                b: layer.w.add(first),
                b_k: layer.inw,
                c: out.c,
                c_m: out.c_m,
                epi: out.epi,
            })
        }
    }
}

/// One block of `nb` rows through every layer; layer l writes to
/// `sink.destination(l)` with row stride equal to its width, except the
/// last layer, which computes and writes only its first `last_columns`
/// outputs.
#[inline(always)]
unsafe fn forward_block<P: Products>(
    net: &Net,
    x: *const f32,
    nb: usize,
    last_columns: usize,
    sink: &impl BlockSink,
    pairs: *mut u32,
) {
    let mut a = x;
    let last = net.layers.len() - 1;
    for (l, layer) in net.layers.iter().enumerate() {
        let c = unsafe { sink.destination(l) };
        let n = if l == last { last_columns } else { layer.outw };
        if n <= NARROW_COLUMNS {
            unsafe { narrow_layer::<P::L>(layer, a, nb, n, net.act(l), c) };
            unsafe { sink.after(l, c) };
            a = c;
            continue;
        }
        let out = Destination {
            c,
            c_m: n,
            epi: Epi::Forward {
                bias: layer.bias,
                act: net.act(l),
            },
        };
        unsafe { P::forward(layer, a, nb, n, out, pairs) };
        unsafe { sink.after(l, c) };
        a = c;
    }
}

/// The training forward pass: each block runs through the layers in the
/// task's scratch (in L1/L2), and every layer's block is then streamed to
/// the workspace with non-temporal stores. The workspace is far larger than
/// the caches and is only read again by the backward pass, so writing around
/// the caches saves the read-for-ownership of every line.
#[inline(always)]
unsafe fn forward_rows<P: Products>(job: &ForwardJob, rows: Range<usize>, scratch: *mut f32) {
    let net = job.net;
    let in_w = net.layers[0].inw;
    let last = net.layers.len() - 1;
    let out_w = net.layers[last].outw;
    let half = BLOCK * job.max_width;
    let pairs = unsafe { scratch.add(2 * half) }.cast::<u32>();
    let mut r0 = rows.start;
    while r0 < rows.end {
        let nb = (rows.end - r0).min(BLOCK);
        let sink = TrainingSink::<P::L> {
            job,
            scratch,
            half,
            r0,
            nb,
            last,
            out_w,
            lanes: std::marker::PhantomData,
        };
        unsafe { forward_block::<P>(net, job.input.add(r0 * in_w), nb, out_w, &sink, pairs) };
        r0 += nb;
    }
    unsafe { P::L::store_fence() };
}

/// The training forward pass's blocks: computed in the scratch, streamed
/// to the workspace, the last layer also copied to the output.
struct TrainingSink<'a, L> {
    job: &'a ForwardJob<'a>,
    scratch: *mut f32,
    half: usize,
    r0: usize,
    nb: usize,
    last: usize,
    out_w: usize,
    lanes: std::marker::PhantomData<L>,
}

impl<L: Lanes> BlockSink for TrainingSink<'_, L> {
    #[inline(always)]
    unsafe fn destination(&self, l: usize) -> *mut f32 {
        unsafe { self.scratch.add((l % 2) * self.half) }
    }

    #[inline(always)]
    unsafe fn after(&self, l: usize, block: *const f32) {
        let (job, r0, nb) = (self.job, self.r0, self.nb);
        let w = job.net.layers[l].outw;
        unsafe {
            L::stream_copy(job.activations[l].get().add(r0 * w), block, nb * w);
            if l == self.last {
                std::ptr::copy_nonoverlapping(
                    block,
                    job.output.get().add(r0 * self.out_w),
                    nb * self.out_w,
                );
            }
        }
    }
}

/// The inference pass's blocks: hidden layers in the scratch, the last
/// straight into the output.
struct InferenceSink {
    output: *mut f32,
    scratch: *mut f32,
    half: usize,
    last: usize,
}

impl BlockSink for InferenceSink {
    #[inline(always)]
    unsafe fn destination(&self, l: usize) -> *mut f32 {
        if l == self.last {
            self.output
        } else {
            unsafe { self.scratch.add((l % 2) * self.half) }
        }
    }

    #[inline(always)]
    unsafe fn after(&self, _: usize, _: *const f32) {}
}

#[inline(always)]
unsafe fn inference_rows<P: Products>(job: &InferenceJob, rows: Range<usize>, scratch: *mut f32) {
    let net = job.net;
    let in_w = net.layers[0].inw;
    let last = net.layers.len() - 1;
    let out_w = job.out_columns;
    let half = BLOCK * job.max_width;
    let pairs = unsafe { scratch.add(2 * half) }.cast::<u32>();
    let mut r0 = rows.start;
    while r0 < rows.end {
        let nb = (rows.end - r0).min(BLOCK);
        let sink = InferenceSink {
            output: unsafe { job.output.get().add(r0 * out_w) },
            scratch,
            half,
            last,
        };
        unsafe { forward_block::<P>(net, job.input.add(r0 * in_w), nb, out_w, &sink, pairs) };
        r0 += nb;
    }
}

#[inline(always)]
unsafe fn backward_rows<P: Products>(
    job: &BackwardJob,
    rows: Range<usize>,
    partial: *mut f32,
    scratch: *mut f32,
) {
    let net = job.net;
    let layers = &net.layers;
    let last = layers.len() - 1;
    let out_w = layers[last].outw;
    let in_w = layers[0].inw;
    let half = BLOCK * job.max_width;
    let pairs = unsafe { scratch.add(2 * half) }.cast::<u32>();
    unsafe {
        std::ptr::write_bytes(partial, 0, job.n_params);
        let mut r0 = rows.start;
        while r0 < rows.end {
            let nb = (rows.end - r0).min(BLOCK);
            // Two gradient buffers alternate; `g` (read) never aliases the
            // one being written.
            let buffers = [scratch, scratch.add(half)];
            let mut next = 0;
            // G = dY ⊙ act'(Y) for the last layer; a linear output uses dY
            // as it is.
            let act = net.output;
            let dy = job.d_output.add(r0 * out_w);
            let mut g: *const f32 = if act == Activation::None {
                dy
            } else {
                let y = job.activations[last].add(r0 * out_w);
                let into = buffers[1];
                let n = nb * out_w;
                if act == Activation::Relu {
                    // A wide ReLU output (NeRF's trunk before the skip):
                    // in vectors, as the hidden layers' gates are.
                    let mut i = 0;
                    while i < n {
                        let m = P::L::mask(n - i);
                        let gate =
                            P::L::relu_gate(P::L::load(dy.add(i), m), P::L::load(y.add(i), m));
                        P::L::store(into.add(i), gate, m);
                        i += P::L::N;
                    }
                } else {
                    for i in 0..n {
                        *into.add(i) = *dy.add(i) * act.derivative_from_output(*y.add(i));
                    }
                }
                into
            };
            for l in (0..layers.len()).rev() {
                let layer = layers[l];
                let x = if l == 0 {
                    job.input.add(r0 * in_w)
                } else {
                    job.activations[l - 1].add(r0 * layer.inw)
                };
                P::weight_gradient(&layer, g, x, nb, partial.add(layer.w_off), pairs);
                if let Some(b_off) = layer.b_off {
                    let db = partial.add(b_off);
                    for r in 0..nb {
                        for o in 0..layer.outw {
                            *db.add(o) += *g.add(r * layer.outw + o);
                        }
                    }
                }
                // dX = G W, times act' of the layer below (its G), or
                // stored as the input gradient.
                // (destination, epilogue, first column, columns)
                let epi_dst = if l > 0 {
                    Some((
                        buffers[next],
                        Epi::Backward {
                            act: net.hidden,
                            y: job.activations[l - 1].add(r0 * layer.inw),
                            y_m: layer.inw,
                        },
                        0,
                        layer.inw,
                    ))
                } else if !job.d_input.get().is_null() {
                    let columns = &job.d_input_columns;
                    Some((
                        job.d_input.get().add(r0 * columns.len()),
                        Epi::Store,
                        columns.start,
                        columns.len(),
                    ))
                } else {
                    None
                };
                if let Some((c, epi, first, n)) = epi_dst {
                    let out = Destination { c, c_m: n, epi };
                    P::input_gradient(&layer, g, nb, first, n, out, pairs);
                }
                g = buffers[next];
                next ^= 1;
            }
            r0 += nb;
        }
    }
}

/// Entry points compiled once per instruction set, so the generic kernels
/// above are inlined with that set enabled.
mod dispatch {
    use super::*;

    macro_rules! entry_points {
        ($module:ident, $products:ty, $($features:literal)?) => {
            pub mod $module {
                #[allow(unused_imports)]
                #[cfg(target_arch = "x86_64")]
                use super::super::x86::*;
                use super::super::*;

                $(#[target_feature(enable = $features)])?
                pub unsafe fn forward(job: &ForwardJob, rows: Range<usize>, scratch: *mut f32) {
                    unsafe { forward_rows::<$products>(job, rows, scratch) }
                }
                $(#[target_feature(enable = $features)])?
                pub unsafe fn inference(job: &InferenceJob, rows: Range<usize>, scratch: *mut f32) {
                    unsafe { inference_rows::<$products>(job, rows, scratch) }
                }
                $(#[target_feature(enable = $features)])?
                pub unsafe fn backward(
                    job: &BackwardJob,
                    rows: Range<usize>,
                    partial: *mut f32,
                    scratch: *mut f32,
                ) {
                    unsafe { backward_rows::<$products>(job, rows, partial, scratch) }
                }
                /// The f32 product alone (the peak measurement).
                $(#[target_feature(enable = $features)])?
                pub unsafe fn gemm(g: &Gemm) {
                    unsafe { super::super::gemm::<<$products as Products>::L>(g) }
                }
            }
        };
    }

    #[cfg(target_arch = "x86_64")]
    entry_points!(
        avx512bf16,
        bf16::Bf16Products,
        "avx512f,avx512vl,avx512bw,avx512bf16,avx2,fma"
    );
    #[cfg(target_arch = "x86_64")]
    entry_points!(avx512, F32Products<Avx512>, "avx512f,avx512vl,avx2,fma");
    #[cfg(target_arch = "x86_64")]
    entry_points!(avx2, F32Products<Avx2>, "avx2,fma");
    entry_points!(portable, F32Products<Portable>,);

    macro_rules! route {
        ($backend:expr, $f:ident($($arg:expr),*)) => {
            match $backend {
                #[cfg(target_arch = "x86_64")]
                Backend::Avx512Bf16 => unsafe { avx512bf16::$f($($arg),*) },
                #[cfg(target_arch = "x86_64")]
                Backend::Avx512 => unsafe { avx512::$f($($arg),*) },
                #[cfg(target_arch = "x86_64")]
                Backend::Avx2 => unsafe { avx2::$f($($arg),*) },
                _ => unsafe { portable::$f($($arg),*) },
            }
        };
    }

    /// # Safety
    /// `backend` must be supported by this CPU (see [`backend`]), and the
    /// job's pointers valid for `rows`.
    pub unsafe fn forward(
        backend: Backend,
        job: &ForwardJob,
        rows: Range<usize>,
        scratch: *mut f32,
    ) {
        route!(backend, forward(job, rows, scratch))
    }
    pub unsafe fn inference(
        backend: Backend,
        job: &InferenceJob,
        rows: Range<usize>,
        scratch: *mut f32,
    ) {
        route!(backend, inference(job, rows, scratch))
    }
    pub unsafe fn backward(
        backend: Backend,
        job: &BackwardJob,
        rows: Range<usize>,
        partial: *mut f32,
        scratch: *mut f32,
    ) {
        route!(backend, backward(job, rows, partial, scratch))
    }
    pub unsafe fn gemm(backend: Backend, g: &Gemm) {
        route!(backend, gemm(g))
    }
}

// ---------------------------------------------------------------------------
// Reference.

/// The forward pass in plain loops, generic over the float type: the
/// reference the fast kernels and the gpu engine are tested against, and
/// what finite differences run on in f64. Returns every layer's output.
pub fn reference_forward<F: Float>(
    layout: &MlpLayout,
    params: &[F],
    input: &[F],
    rows: usize,
) -> Vec<Vec<F>> {
    let mut outputs: Vec<Vec<F>> = Vec::with_capacity(layout.layers());
    for layer in 0..layout.layers() {
        let (iw, ow) = (layout.widths[layer], layout.widths[layer + 1]);
        let x = if layer == 0 {
            input
        } else {
            &outputs[layer - 1][..]
        };
        let w = &params[layout.weight_offset(layer)..][..iw * ow];
        let act = layout.activation(layer);
        let mut y = vec![F::zero(); rows * ow];
        for r in 0..rows {
            for o in 0..ow {
                let mut s = layout
                    .bias_offset(layer)
                    .map_or(F::zero(), |b| params[b + o]);
                for i in 0..iw {
                    s = s + w[o * iw + i] * x[r * iw + i];
                }
                y[r * ow + o] = act.apply(s);
            }
        }
        outputs.push(y);
    }
    outputs
}

/// The backward pass in plain loops: (parameter gradients, input gradient).
pub fn reference_backward<F: Float>(
    layout: &MlpLayout,
    params: &[F],
    input: &[F],
    rows: usize,
    outputs: &[Vec<F>],
    d_output: &[F],
) -> (Vec<F>, Vec<F>) {
    let mut d_params = vec![F::zero(); params.len()];
    let last = layout.layers() - 1;
    let mut g: Vec<F> = d_output[..rows * layout.output_width()]
        .iter()
        .zip(&outputs[last])
        .map(|(&d, &y)| d * layout.output.derivative_from_output(y))
        .collect();
    for layer in (0..layout.layers()).rev() {
        let (iw, ow) = (layout.widths[layer], layout.widths[layer + 1]);
        let x = if layer == 0 {
            input
        } else {
            &outputs[layer - 1][..]
        };
        let w_off = layout.weight_offset(layer);
        for r in 0..rows {
            for o in 0..ow {
                let go = g[r * ow + o];
                for i in 0..iw {
                    d_params[w_off + o * iw + i] =
                        d_params[w_off + o * iw + i] + go * x[r * iw + i];
                }
                if let Some(b) = layout.bias_offset(layer) {
                    d_params[b + o] = d_params[b + o] + go;
                }
            }
        }
        let mut dx = vec![F::zero(); rows * iw];
        for r in 0..rows {
            for i in 0..iw {
                let mut s = F::zero();
                for o in 0..ow {
                    s = s + g[r * ow + o] * params[w_off + o * iw + i];
                }
                dx[r * iw + i] = if layer > 0 {
                    s * layout.hidden.derivative_from_output(x[r * iw + i])
                } else {
                    s
                };
            }
        }
        g = dx;
    }
    (d_params, g)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn random(seed: u64, n: usize, scale: f32) -> Vec<f32> {
        let mut rng = Pcg32::new(seed, 7);
        (0..n)
            .map(|_| (2.0 * rng.next_f32() - 1.0) * scale)
            .collect()
    }

    fn to_f64(x: &[f32]) -> Vec<f64> {
        x.iter().map(|&v| v as f64).collect()
    }

    fn available_backends() -> Vec<Backend> {
        let mut all = vec![Backend::Portable];
        #[cfg(target_arch = "x86_64")]
        {
            if is_x86_feature_detected!("avx2") && is_x86_feature_detected!("fma") {
                all.push(Backend::Avx2);
            }
            if is_x86_feature_detected!("avx512f")
                && is_x86_feature_detected!("avx2")
                && is_x86_feature_detected!("fma")
            {
                all.push(Backend::Avx512);
            }
        }
        all
    }

    #[test]
    fn layout_offsets_and_counts() {
        let layout = MlpLayout::new(vec![3, 5, 2], Activation::Relu, Activation::None, true);
        assert_eq!(layout.weight_offset(0), 0);
        assert_eq!(layout.bias_offset(0), Some(15));
        assert_eq!(layout.weight_offset(1), 20);
        assert_eq!(layout.bias_offset(1), Some(30));
        assert_eq!(layout.param_count(), 32);
        let ngp = NetworkConfig::PAPER;
        let density = MlpLayout::ngp_density(&ngp, &HashGridConfig::paper(1.0));
        assert_eq!(density.widths, vec![32, 64, 16]);
        assert_eq!(density.param_count(), 32 * 64 + 64 * 16);
        let colour = MlpLayout::ngp_colour(&ngp);
        assert_eq!(colour.widths, vec![32, 64, 64, 3]);
        assert_eq!(colour.bias_offset(0), None);
    }

    #[test]
    fn init_is_xavier_uniform() {
        let layout = MlpLayout::new(vec![32, 64, 16], Activation::Relu, Activation::None, true);
        let p = layout.init_params(3);
        let bound0 = (6.0f32 / 96.0).sqrt();
        let w0 = &p[..32 * 64];
        assert!(w0.iter().all(|w| w.abs() <= bound0));
        // Uniform on ±a has variance a²/3; over 2048 draws the sample
        // variance has a relative standard deviation of about 2.5%, so 10%
        // is four of them.
        let var = w0.iter().map(|w| (w * w) as f64).sum::<f64>() / w0.len() as f64;
        let want = (bound0 * bound0 / 3.0) as f64;
        assert!((var / want - 1.0).abs() < 0.1, "{var} vs {want}");
        assert!(
            p[layout.bias_offset(0).unwrap()..][..64]
                .iter()
                .all(|&b| b == 0.0)
        );
        assert_eq!(p, layout.init_params(3));
        assert_ne!(p, layout.init_params(4));
    }

    /// L = Σ c ⊙ output with fixed random weights c, so ∂L/∂output = c.
    fn loss(layout: &MlpLayout, params: &[f64], input: &[f64], rows: usize, c: &[f64]) -> f64 {
        let out = reference_forward(layout, params, input, rows);
        out[layout.layers() - 1]
            .iter()
            .zip(c)
            .map(|(y, c)| y * c)
            .sum()
    }

    #[test]
    fn reference_gradients_match_central_differences() {
        let cases = [
            MlpLayout::new(
                vec![5, 7, 6, 4],
                Activation::Relu,
                Activation::Sigmoid,
                true,
            ),
            MlpLayout::new(vec![4, 6, 3], Activation::Relu, Activation::None, false),
            MlpLayout::new(
                vec![3, 5, 2],
                Activation::Sigmoid,
                Activation::ClampedExp,
                true,
            ),
        ];
        for (case, layout) in cases.iter().enumerate() {
            let rows = 6;
            let params = to_f64(&random(10 + case as u64, layout.param_count(), 0.8));
            let input = to_f64(&random(20 + case as u64, rows * layout.input_width(), 1.0));
            let c = to_f64(&random(30 + case as u64, rows * layout.output_width(), 1.0));
            let outputs = reference_forward(layout, &params, &input, rows);
            // ReLU has a kink at 0: a central difference straddling it is
            // wrong. With h = 1e-5 and every pre-activation at least 1e-3
            // from 0 (checked), no difference straddles one.
            let h = 1e-5;
            let min_pre = min_abs_hidden_pre_activation(layout, &params, &input, rows);
            assert!(
                min_pre > 1e-3,
                "case {case}: a pre-activation at {min_pre:e} makes the test invalid"
            );
            let (d_params, d_input) =
                reference_backward(layout, &params, &input, rows, &outputs, &c);
            // Central differences: truncation h²/6·L''' ≈ 2e-11·|L'''|,
            // rounding ε·|L|/h ≈ 2e-11·|L| in f64, with |L|, |L'''| of order
            // 1-10 here. 1e-7 relative, with magnitudes below 1e-2 measured
            // against 1e-2 (an absolute floor of 1e-9), is far above that
            // and far below any wrong or missing term.
            let rel = |a: f64, b: f64| (a - b).abs() / a.abs().max(b.abs()).max(1e-2);
            let mut worst = 0f64;
            for j in 0..params.len() {
                let mut p = params.clone();
                p[j] += h;
                let plus = loss(layout, &p, &input, rows, &c);
                p[j] -= 2.0 * h;
                let minus = loss(layout, &p, &input, rows, &c);
                worst = worst.max(rel(d_params[j], (plus - minus) / (2.0 * h)));
            }
            for j in 0..input.len() {
                let mut x = input.clone();
                x[j] += h;
                let plus = loss(layout, &params, &x, rows, &c);
                x[j] -= 2.0 * h;
                let minus = loss(layout, &params, &x, rows, &c);
                worst = worst.max(rel(d_input[j], (plus - minus) / (2.0 * h)));
            }
            assert!(worst < 1e-7, "case {case}: worst relative error {worst:e}");
        }
    }

    /// The smallest |pre-activation| of any hidden unit over the batch.
    fn min_abs_hidden_pre_activation(
        layout: &MlpLayout,
        params: &[f64],
        input: &[f64],
        rows: usize,
    ) -> f64 {
        let outputs = reference_forward(layout, params, input, rows);
        let mut min = f64::INFINITY;
        for layer in 0..layout.layers() - 1 {
            let (iw, ow) = (layout.widths[layer], layout.widths[layer + 1]);
            let x = if layer == 0 {
                input
            } else {
                &outputs[layer - 1][..]
            };
            let w = &params[layout.weight_offset(layer)..];
            for r in 0..rows {
                for o in 0..ow {
                    let mut s = layout.bias_offset(layer).map_or(0.0, |b| params[b + o]);
                    for i in 0..iw {
                        s += w[o * iw + i] * x[r * iw + i];
                    }
                    min = min.min(s.abs());
                }
            }
        }
        min
    }

    /// max |a − b| over the tensor, relative to max |b|.
    fn max_relative(a: &[f32], b: &[f64]) -> f64 {
        assert_eq!(a.len(), b.len());
        let scale = b.iter().fold(0f64, |m, x| m.max(x.abs())).max(1e-30);
        a.iter()
            .zip(b)
            .fold(0f64, |m, (&x, &y)| m.max((x as f64 - y).abs()))
            / scale
    }

    #[test]
    fn kernels_match_the_reference_on_every_backend() {
        let cases = [
            // Instant-NGP's shapes.
            (
                MlpLayout::new(vec![32, 64, 16], Activation::Relu, Activation::None, false),
                1000,
            ),
            (
                MlpLayout::new(
                    vec![32, 64, 64, 3],
                    Activation::Relu,
                    Activation::Sigmoid,
                    false,
                ),
                777,
            ),
            // Widths that are not multiples of any vector width, biases,
            // and more rows than one chunk per block.
            (
                MlpLayout::new(
                    vec![37, 21, 70, 5],
                    Activation::Relu,
                    Activation::ClampedExp,
                    true,
                ),
                2500,
            ),
            (
                MlpLayout::new(vec![3, 130, 1], Activation::Sigmoid, Activation::None, true),
                130,
            ),
            (
                MlpLayout::new(vec![8, 8], Activation::Relu, Activation::Relu, true),
                1,
            ),
        ];
        // Every remainder of rows below a tile's height (8 for one vector
        // column, 6 for two, 4 for more), for each panel width.
        let sweep = (1..=17).flat_map(|rows| {
            [
                (
                    MlpLayout::new(vec![20, 40, 7], Activation::Relu, Activation::None, true),
                    rows,
                ),
                (
                    MlpLayout::new(
                        vec![9, 33, 50, 16],
                        Activation::Relu,
                        Activation::Sigmoid,
                        false,
                    ),
                    64 + rows,
                ),
            ]
        });
        let cases: Vec<(MlpLayout, usize)> = cases.into_iter().chain(sweep).collect();
        for backend in available_backends() {
            for (case, (layout, rows)) in cases.iter().enumerate() {
                let rows = *rows;
                let params = random(100 + case as u64, layout.param_count(), 0.5);
                let input = random(200 + case as u64, rows * layout.input_width(), 1.0);
                let d_out = random(300 + case as u64, rows * layout.output_width(), 1.0);
                let mut ws = MlpWorkspace::new(layout, rows);
                let mut out = vec![0.0; rows * layout.output_width()];
                forward_with(backend, layout, &params, &input, rows, &mut ws, &mut out);
                // Start from nonzero gradients to check that they accumulate.
                let mut d_params = vec![1.0f32; params.len()];
                let mut d_input = vec![f32::NAN; input.len()];
                backward_with(
                    backend,
                    layout,
                    &params,
                    &input,
                    rows,
                    &mut ws,
                    &d_out,
                    &mut d_params,
                    Some((&mut d_input, 0..layout.input_width())),
                );

                let (p64, x64) = (to_f64(&params), to_f64(&input));
                let want = reference_forward(layout, &p64, &x64, rows);
                let (want_dp, want_dx) =
                    reference_backward(layout, &p64, &x64, rows, &want, &to_f64(&d_out));
                let want_dp: Vec<f64> = want_dp.iter().map(|g| g + 1.0).collect();
                // Each value is a sum of at most 130 products per layer (the
                // weight gradients: of 2500 rows) in f32 against f64: the
                // worst-case bound n·ε·Σ|terms| is loose; with random signs
                // the error grows like √n·ε ≈ 60·6e-8 ≈ 4e-6 of the
                // tensor's scale for the weight gradients and less for the
                // rest. 2e-5 holds that with margin and fails on any wrong
                // index, missing term or wrong activation.
                let tol = 2e-5;
                for (l, y) in want.iter().enumerate() {
                    let e = max_relative(&ws.activations(l)[..rows * layout.widths[l + 1]], y);
                    assert!(e < tol, "{backend:?} case {case} layer {l} forward: {e:e}");
                }
                let e = max_relative(&out, &want[layout.layers() - 1]);
                assert!(e < tol, "{backend:?} case {case} output: {e:e}");
                let e = max_relative(&d_params, &want_dp);
                assert!(e < tol, "{backend:?} case {case} d_params: {e:e}");
                let e = max_relative(&d_input, &want_dx);
                assert!(e < tol, "{backend:?} case {case} d_input: {e:e}");

                let out_w = layout.output_width();
                let mut inferred = vec![0.0; out.len()];
                inference_with(backend, layout, &params, &input, rows, &mut inferred, out_w);
                assert_eq!(
                    inferred, out,
                    "{backend:?} case {case}: inference differs from forward"
                );
                // Only the first output: column 0 of the full forward pass,
                // summed by the narrow kernel where the full pass used a tile
                // (outputs wider than NARROW_COLUMNS), so equal to rounding.
                let mut first = vec![0.0; rows];
                inference_with(backend, layout, &params, &input, rows, &mut first, 1);
                let column: Vec<f64> = want[layout.layers() - 1]
                    .chunks_exact(out_w)
                    .map(|r| r[0])
                    .collect();
                let e = max_relative(&first, &column);
                assert!(e < tol, "{backend:?} case {case} leading output: {e:e}");
                if out_w <= NARROW_COLUMNS {
                    let same: Vec<f32> = out.chunks_exact(out_w).map(|r| r[0]).collect();
                    assert_eq!(first, same, "{backend:?} case {case}: leading output");
                }
            }
        }
    }

    #[test]
    fn backward_is_deterministic_and_skips_unwanted_input_gradient() {
        let layout = MlpLayout::new(
            vec![32, 64, 64, 3],
            Activation::Relu,
            Activation::Sigmoid,
            false,
        );
        let rows = 5000;
        let params = layout.init_params(9);
        let input = random(1, rows * 32, 1.0);
        let d_out = random(2, rows * 3, 1.0);
        let mut ws = MlpWorkspace::new(&layout, rows);
        let mut out = vec![0.0; rows * 3];
        mlp_forward(&layout, &params, &input, rows, &mut ws, &mut out);
        let mut first = vec![0.0; params.len()];
        mlp_backward(
            &layout, &params, &input, rows, &mut ws, &d_out, &mut first, None,
        );
        // On a pool of one thread, the summation order must be the same.
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .unwrap();
        let second = pool.install(|| {
            let mut d = vec![0.0; params.len()];
            mlp_backward(
                &layout, &params, &input, rows, &mut ws, &d_out, &mut d, None,
            );
            d
        });
        assert_eq!(first, second);
        assert!(first.iter().any(|&g| g != 0.0));

        // The gradient of some input columns only equals those columns of
        // the full input gradient, bit for bit (each element is the same
        // sum in the same order), and the parameter gradients are the same.
        let mut full = vec![0.0; rows * 32];
        let mut d_full = vec![0.0; params.len()];
        mlp_backward(
            &layout,
            &params,
            &input,
            rows,
            &mut ws,
            &d_out,
            &mut d_full,
            Some(&mut full),
        );
        let mut part = vec![0.0; rows * 16];
        let mut d_part = vec![0.0; params.len()];
        mlp_backward_columns(
            &layout,
            &params,
            &input,
            rows,
            &mut ws,
            &d_out,
            &mut d_part,
            &mut part,
            3..19,
        );
        assert_eq!(d_part, d_full);
        for r in 0..rows {
            assert_eq!(
                part[r * 16..(r + 1) * 16],
                full[r * 32 + 3..r * 32 + 19],
                "row {r}"
            );
        }
    }

    #[test]
    fn activations_and_their_derivatives() {
        assert_eq!(Activation::Relu.apply(-2.0f64), 0.0);
        assert_eq!(Activation::Sigmoid.apply(0.0f64), 0.5);
        assert_eq!(
            Activation::ClampedExp.apply(100.0f32),
            DENSITY_EXP_CLAMP.exp()
        );
        assert!(
            Activation::Sigmoid.apply(-1e4f32) == 0.0 && Activation::Sigmoid.apply(1e4f32) == 1.0
        );
        let clamp = DENSITY_EXP_CLAMP as f64;
        assert_eq!(
            Activation::ClampedExp
                .derivative_from_output(Activation::ClampedExp.apply(clamp + 1.0)),
            0.0
        );
        // Away from kinks and the clamp, the derivative from the output
        // matches a central difference (f64, h = 1e-6: error ≈ 1e-10).
        for act in [
            Activation::None,
            Activation::Relu,
            Activation::Sigmoid,
            Activation::ClampedExp,
        ] {
            for x in [-3.0, -0.5, 0.25, 2.0, clamp - 1.0] {
                let h = 1e-6;
                let numeric = (act.apply(x + h) - act.apply(x - h)) / (2.0 * h);
                let analytic = act.derivative_from_output(act.apply(x));
                assert!(
                    (numeric - analytic).abs() <= 1e-7 * numeric.abs().max(1.0),
                    "{act:?} at {x}"
                );
            }
        }
    }

    /// User + system CPU seconds of this process so far (Linux; 0 elsewhere).
    fn process_cpu_seconds() -> f64 {
        let stat = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
        // Fields after the parenthesised command name; utime and stime are
        // the 14th and 15th fields overall, in clock ticks of 1/100 s.
        let rest = stat.rsplit(')').next().unwrap_or("");
        let f: Vec<&str> = rest.split_whitespace().collect();
        let field = |i: usize| f.get(i).and_then(|x| x.parse::<f64>().ok()).unwrap_or(0.0);
        (field(11) + field(12)) / 100.0
    }

    /// GFLOP/s of the Instant-NGP networks at 2^18 rows. Run with
    /// `cargo test --release --lib dense::tests::throughput -- --ignored --nocapture`.
    #[test]
    #[ignore]
    fn throughput() {
        let rows = crate::field::ngp::SAMPLES_PER_BATCH;
        let ngp = NetworkConfig::PAPER;
        eprintln!(
            "backend {:?}, threads {}",
            backend(),
            rayon::current_num_threads()
        );
        eprintln!("peak (1024³ SGEMM): {:.0} GFLOP/s", measure_peak_gflops());
        let layouts = [
            (
                "density",
                MlpLayout::ngp_density(&ngp, &HashGridConfig::paper(1.0)),
            ),
            ("colour", MlpLayout::ngp_colour(&ngp)),
            ("nerf 8×256", {
                let mut w = vec![63];
                w.extend([256; 8]);
                w.push(4);
                MlpLayout::new(w, Activation::Relu, Activation::None, true)
            }),
        ];
        let mut total = [0.0f64; 3];
        for (name, layout) in &layouts {
            let params = layout.init_params(1);
            let input = random(1, rows * layout.input_width(), 1.0);
            let d_out = random(2, rows * layout.output_width(), 1.0);
            let mut ws = MlpWorkspace::new(layout, rows);
            let mut out = vec![0.0; rows * layout.output_width()];
            let mut d_params = vec![0.0; params.len()];
            let mut d_input = vec![0.0; input.len()];
            // Wall time and this process's CPU time (the machine is shared:
            // CPU seconds show what the kernels do per core-second even when
            // other processes take cores away).
            let median = |f: &mut dyn FnMut()| {
                f();
                let mut t: Vec<(f64, f64)> = (0..7)
                    .map(|_| {
                        let (s, c) = (std::time::Instant::now(), process_cpu_seconds());
                        f();
                        (s.elapsed().as_secs_f64(), process_cpu_seconds() - c)
                    })
                    .collect();
                t.sort_by(|a, b| a.0.total_cmp(&b.0));
                let cpu = t.iter().map(|x| x.1).sum::<f64>() / t.len() as f64;
                (t[3].0, cpu)
            };
            let (fwd, fwd_cpu) =
                median(&mut || mlp_forward(layout, &params, &input, rows, &mut ws, &mut out));
            let (inf, inf_cpu) =
                median(&mut || mlp_inference(layout, &params, &input, rows, &mut out));
            let (bwd, bwd_cpu) = median(&mut || {
                mlp_backward(
                    layout,
                    &params,
                    &input,
                    rows,
                    &mut ws,
                    &d_out,
                    &mut d_params,
                    Some(&mut d_input),
                )
            });
            let flop = 2.0 * (layout.macs_per_row() * rows) as f64;
            eprintln!(
                "{name:>11}: forward {:.1} ms ({:.0} GFLOP/s; {:.0} per CPU-second), inference {:.1} ms ({:.0} GFLOP/s; {:.0} per CPU-second), \
                 backward {:.1} ms ({:.0} GFLOP/s; {:.0} per CPU-second)",
                fwd * 1e3,
                flop / fwd / 1e9,
                flop / fwd_cpu / 1e9,
                inf * 1e3,
                flop / inf / 1e9,
                flop / inf_cpu / 1e9,
                bwd * 1e3,
                2.0 * flop / bwd / 1e9,
                2.0 * flop / bwd_cpu / 1e9,
            );
            if name != &"nerf 8×256" {
                total[0] += fwd;
                total[1] += bwd;
                total[2] += flop * 3.0;
            }
        }
        let step = total[0] + total[1];
        eprintln!(
            "NGP networks forward+backward: {:.1} ms per 2^18 samples = {:.1} M samples/s ({:.0} GFLOP/s)",
            step * 1e3,
            rows as f64 / step / 1e6,
            total[2] / step / 1e9
        );
    }
}
