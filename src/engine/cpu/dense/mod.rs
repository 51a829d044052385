//! Dense layers: small multilayer perceptrons over a batch of rows, forward
//! and backward, at a high fraction of the machine's FLOP/s.
//!
//! A layer computes `y = act(x Wᵀ + b)` for every row `x` of the batch.
//!
//! # Parameter layout
//!
//! As [`crate::field::mlp`] describes: one flat `&[f32]`, layer after
//! layer, each layer's `out × in` row-major weights then its bias. The
//! shape ([`MlpLayout`]), the activations and the precision are
//! engine-neutral and live there; they are re-exported here under the
//! paths this stage has always named them by.
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

/// A task's scratch, in floats, for a network at most `max_width` wide:
/// two BLOCK × max-width buffers the layers of a block alternate between,
/// then the mixed-precision kernels' bf16 pairs of a block. BLOCK ×
/// max-width words hold a block's pairs; the tile kernels pad rows and
/// columns to multiples of 16 and, for the weight gradient, hold both
/// operands' pairs: twice BLOCK × (max-width + 16) words hold them all.
fn scratch_floats(max_width: usize) -> usize {
    2 * BLOCK * max_width + 2 * BLOCK * (max_width + 16)
}

use crate::field::mlp::{Activation, MlpLayout, Precision};

impl Activation {
    /// True where the kernels apply it with scalar code after the vector
    /// epilogue (exp is not vectorised; these sit on narrow output layers).
    fn is_transcendental(self) -> bool {
        matches!(self, Activation::Sigmoid | Activation::ClampedExp)
    }
}

impl Precision {
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

impl MlpLayout {
    /// The kernels this network runs on here.
    pub fn kernels(&self) -> Backend {
        backend_for(self.precision)
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
            scratch: vec![0.0; chunks * scratch_floats(layout.max_width())],
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
    /// bf16 pair products on Intel's matrix units (`tdpbf16ps`) for the
    /// layer products, AVX-512 for the rest: [`Precision::Mixed`].
    AmxBf16,
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
            Backend::AmxBf16 | Backend::Avx512Bf16 => Precision::Mixed,
            _ => Precision::F32,
        }
    }

    /// Whether this processor has the instructions these kernels are
    /// compiled for (see `dispatch`), which makes running them sound;
    /// `ZRAK_CPU_KERNELS` ([`crate::isa`]) chooses among those that do.
    pub fn runs_here(self) -> bool {
        #[cfg(target_arch = "x86_64")]
        {
            let avx2 = is_x86_feature_detected!("avx2") && is_x86_feature_detected!("fma");
            let avx512 =
                avx2 && is_x86_feature_detected!("avx512f") && is_x86_feature_detected!("avx512vl");
            let bf16 = avx512
                && is_x86_feature_detected!("avx512bw")
                && is_x86_feature_detected!("avx512bf16");
            match self {
                Backend::AmxBf16 => bf16 && bf16::amx::available(),
                Backend::Avx512Bf16 => bf16,
                Backend::Avx512 => avx512,
                Backend::Avx2 => avx2,
                Backend::Portable => true,
            }
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            self == Backend::Portable
        }
    }

    /// The multiple the mixed-precision kernels pad the weights' bf16
    /// pairs to (rows and row stride).
    fn pair_alignment(self) -> usize {
        match self {
            #[cfg(target_arch = "x86_64")]
            Backend::AmxBf16 => bf16::amx::TILE,
            _ => 1,
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

/// Whether this processor has Intel's bf16 matrix units (AMX-BF16) and
/// lets zrak use them (see [`bf16::amx`]).
#[cfg(target_arch = "x86_64")]
pub fn tile_kernels_available() -> bool {
    mixed_kernels_available() && bf16::amx::available()
}

#[cfg(not(target_arch = "x86_64"))]
pub fn tile_kernels_available() -> bool {
    false
}

/// The kernels a network at `precision` runs on here.
pub fn backend_for(precision: Precision) -> Backend {
    match precision {
        Precision::Mixed if tile_kernels_available() => Backend::AmxBf16,
        Precision::Mixed if mixed_kernels_available() => Backend::Avx512Bf16,
        _ => backend(),
    }
}

/// The best f32 kernels this CPU supports (within `ZRAK_CPU_KERNELS`,
/// [`crate::isa`]).
pub fn backend() -> Backend {
    static DETECTED: std::sync::OnceLock<Backend> = std::sync::OnceLock::new();
    *DETECTED.get_or_init(|| {
        #[cfg(target_arch = "x86_64")]
        {
            if crate::isa::avx512() {
                return Backend::Avx512;
            }
            if crate::isa::avx2_fma() {
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

/// The gradients of a backward pass: the one it starts from, with respect
/// to the network's output, and those it writes.
pub struct MlpGradients<'a> {
    /// With respect to the output, rows × out.
    pub output: &'a [f32],
    /// With respect to the parameters, accumulated (`+=`).
    pub params: &'a mut [f32],
    /// With respect to the input, written (`=`) where wanted.
    pub input: Option<InputGradient<'a>>,
}

/// Where a backward pass writes the gradient with respect to its input.
pub struct InputGradient<'a> {
    /// rows × `columns.len()`.
    pub values: &'a mut [f32],
    /// The input columns whose gradient is written. The colour network
    /// needs the gradient of its density-feature columns but not of its
    /// direction encoding, and skipping those saves their share of the
    /// last product.
    pub columns: Range<usize>,
}

impl<'a> InputGradient<'a> {
    /// The gradient of every input column of `layout`: rows × in.
    pub fn every_column(values: &'a mut [f32], layout: &MlpLayout) -> Self {
        Self {
            values,
            columns: 0..layout.input_width(),
        }
    }
}

/// Backward pass of the last [`mlp_forward`] on the same `input`, from
/// and into `gradients`.
pub fn mlp_backward(
    layout: &MlpLayout,
    params: &[f32],
    input: &[f32],
    rows: usize,
    workspace: &mut MlpWorkspace,
    gradients: MlpGradients,
) {
    backward_with(
        layout.kernels(),
        layout,
        params,
        input,
        rows,
        workspace,
        gradients,
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
        let [(wt_pairs, wt_pairs_stride), (w_pairs, w_pairs_stride)] = pairs.layer(layer);
        layers.push(Layer {
            inw: i,
            outw: o,
            w: params[w_off..].as_ptr(),
            wt: packed.get(at..).map_or(std::ptr::null(), <[f32]>::as_ptr),
            wt_pairs,
            wt_pairs_stride,
            w_pairs,
            w_pairs_stride,
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
    assert!(backend.runs_here(), "{backend:?} kernels on this processor");
    check_sizes(layout, params, input, rows, output.len());
    workspace.check(layout, rows);
    if backend.precision() == Precision::Mixed {
        workspace
            .pairs
            .pack_forward(layout, params, backend.pair_alignment());
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
        || vec![0.0f32; scratch_floats(max_width)],
        |scratch, t| {
            let range = t * FORWARD_CHUNK..((t + 1) * FORWARD_CHUNK).min(rows);
            // SAFETY: `backend` runs here (asserted above). The job points
            // into `input`, `params` and the workspace's buffers, whose
            // sizes were checked above for `rows` rows and this layout
            // (`net` packed the weights the backend reads); tasks write
            // disjoint row ranges of the activations and output, and the
            // scratch, `scratch_floats(max_width)` long, is the task's own.
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
    assert!(backend.runs_here(), "{backend:?} kernels on this processor");
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
    if backend.precision() == Precision::Mixed {
        pairs.pack_forward(layout, params, backend.pair_alignment());
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
    let scratch_len = scratch_floats(layout.max_width());
    let tasks = rows.div_ceil(FORWARD_CHUNK);
    (0..tasks).into_par_iter().for_each_init(
        || vec![0.0f32; scratch_len],
        |scratch, t| {
            let range = t * FORWARD_CHUNK..((t + 1) * FORWARD_CHUNK).min(rows);
            // SAFETY: `backend` runs here (asserted above); `input`,
            // `params` and `output` hold `rows` rows of this layout
            // (checked above) and `net` packed the weights the backend
            // reads; tasks write disjoint output rows, and the scratch,
            // `scratch_len` long, is the task's own.
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

fn backward_with(
    backend: Backend,
    layout: &MlpLayout,
    params: &[f32],
    input: &[f32],
    rows: usize,
    workspace: &mut MlpWorkspace,
    gradients: MlpGradients,
) {
    assert!(backend.runs_here(), "{backend:?} kernels on this processor");
    let MlpGradients {
        output: d_output,
        params: d_params,
        input: d_input,
    } = gradients;
    check_sizes(layout, params, input, rows, d_output.len());
    workspace.check(layout, rows);
    assert_eq!(d_params.len(), params.len(), "gradient count");
    if let Some(InputGradient { values, columns }) = &d_input {
        assert!(
            columns.start < columns.end && columns.end <= layout.input_width(),
            "input columns {columns:?} of {}",
            layout.input_width()
        );
        assert!(
            values.len() >= rows * columns.len(),
            "d_input holds fewer than {rows} rows"
        );
    }
    if rows == 0 {
        return;
    }
    // The forward pass packed Wᵀ; the backward pass uses W itself (or, in
    // mixed precision, W's pairs of rows), but `net` wants a slice to
    // point into.
    if backend.precision() == Precision::Mixed {
        workspace
            .pairs
            .pack_backward(layout, params, backend.pair_alignment());
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
        d_input_columns: d_input.as_ref().map_or(0..0, |d| d.columns.clone()),
        d_input: SendPtr(d_input.map_or(std::ptr::null_mut(), |d| d.values.as_mut_ptr())),
        n_params,
        max_width,
    };
    let partials = SendPtr(workspace.partials.as_mut_ptr());
    let scratch = SendPtr(workspace.scratch.as_mut_ptr());
    (0..chunks).into_par_iter().for_each(|c| {
        let range = c * chunk_rows..((c + 1) * chunk_rows).min(rows);
        // SAFETY: `backend` runs here (asserted above) and every buffer
        // the job points into holds `rows` rows of this layout (checked
        // above; the activations are the forward pass's). c < chunks ≤
        // MAX_CHUNKS, the number of partials and scratches the workspace
        // holds; chunk c owns partial c, scratch c and the d_input rows of
        // its range.
        unsafe {
            let partial = partials.get().add(c * n_params);
            let g = scratch.get().add(c * scratch_floats(max_width));
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
// SAFETY: a SendPtr is an address; dereferencing it is unsafe, and each
// dereference says why no other thread accesses the same floats.
unsafe impl Send for SendPtr {}
// SAFETY: as for Send: sharing the address reads nothing through it.
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
    /// kernels only, else null), rows `wt_pairs_stride` words apart.
    wt_pairs: *const u32,
    wt_pairs_stride: usize,
    /// W as bf16 pairs along `out`: ⌈out/2⌉ × in words (mixed-precision
    /// backward only, else null), rows `w_pairs_stride` words apart.
    w_pairs: *const u32,
    w_pairs_stride: usize,
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
// SAFETY: `input` is read only, and the tasks that share a job write
// disjoint rows of the activations and output (forward_with).
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
// SAFETY: `input` is read only, and the tasks that share a job write
// disjoint rows of the output (inference_with).
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
// SAFETY: everything but `d_input` is read only, and the tasks that share
// a job write disjoint rows of `d_input` (backward_with).
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
///
/// # Safety
/// Every method is unsafe for one reason: it may be called only where the
/// implementation's instruction set is enabled, that is from code inlined
/// into one of [`dispatch`]'s entry points compiled for it and reached
/// only for a [`Backend`] that [`Backend::runs_here`]. A method that takes
/// a pointer also needs it valid, for reads (`load`) or writes (`store`),
/// for the first lanes its mask selects; the other lanes are not touched.
/// `stream_copy` needs `n` floats readable at `src` and writable at `dst`,
/// the two not overlapping.
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
        // SAFETY: `n` floats are readable at `src` and writable at `dst`,
        // the two not overlapping (the trait's contract).
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
mod x86;

mod gemm;
mod rows;

use gemm::*;
use rows::*;

mod dispatch;

mod reference;

pub use reference::{reference_backward, reference_forward};
#[cfg(test)]
mod tests;
