//! A network's layers over blocks of rows: the forward, inference and
//! backward passes of one worker's rows, generic over how products are
//! taken (f32, or bf16 pairs summed in f32).

use super::*;

/// Where a block's layers go: a trait with methods inlined into the kernels
/// rather than closures, which are compiled without the kernels' vector
/// extensions (their streaming stores became out-of-line calls).
///
/// # Safety
/// Called only by [`forward_block`] on the block the sink was made for,
/// within its caller's contract (the [`dispatch`] module's): the sink's
/// pointers hold that block's rows.
pub(super) trait BlockSink {
    /// Where layer `l` writes its block.
    unsafe fn destination(&self, l: usize) -> *mut f32;
    /// Called once layer `l` wrote its block at `block`.
    unsafe fn after(&self, l: usize, block: *const f32);
}

/// How a layer's three products are computed: in f32 on lanes `L`
/// ([`F32Products`]) or from bf16 pairs ([`bf16::Bf16Products`]). The
/// block loops above and below are written once over this.
///
/// # Safety
/// Every method needs the instructions of its implementation (and of `L`)
/// enabled, the layer's weights in the form it reads (Wᵀ, W, or their
/// bf16 pairs as [`bf16::PairedWeights`] packs them for the backend), the
/// operands readable and the destination writable for the rows and
/// columns it names, and `pairs` writable for the scratch that
/// [`scratch_floats`] sets aside for them.
pub(super) trait Products {
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
pub(super) struct F32Products<L>(std::marker::PhantomData<L>);

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
        // SAFETY: nb rows of `a` (layer.inw wide) and n ≤ outw columns of
        // Wᵀ (outw wide), written through `out`: the trait's contract.
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
        // SAFETY: G is nb × outw, X nb × inw, dW outw × inw (the trait's
        // contract).
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
        // SAFETY: nb rows of G (outw wide); W's columns first..first + n
        // are within its inw (the trait's contract), in rows inw apart.
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
///
/// # Safety
/// The [`dispatch`] module's contract, for a block of `nb` ≤ [`BLOCK`]
/// rows at `x`, with `sink` made for it and `pairs` the task's scratch.
#[inline(always)]
pub(super) unsafe fn forward_block<P: Products>(
    net: &Net,
    x: *const f32,
    nb: usize,
    last_columns: usize,
    sink: &impl BlockSink,
    pairs: *mut u32,
) {
    let mut a = x;
    let last = net.layers.len() - 1;
    // SAFETY: each layer reads the nb rows the layer before it wrote (or
    // x's), and writes nb rows of n ≤ outw columns where the sink says,
    // which holds a layer's block (the sink's contract); the products and
    // the narrow layer get what their contracts ask, within this
    // function's.
    unsafe {
        for (l, layer) in net.layers.iter().enumerate() {
            let c = sink.destination(l);
            let n = if l == last { last_columns } else { layer.outw };
            if n <= NARROW_COLUMNS {
                narrow_layer::<P::L>(layer, a, nb, n, net.act(l), c);
                sink.after(l, c);
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
            P::forward(layer, a, nb, n, out, pairs);
            sink.after(l, c);
            a = c;
        }
    }
}

/// The training forward pass: each block runs through the layers in the
/// task's scratch (in L1/L2), and every layer's block is then streamed to
/// the workspace with non-temporal stores. The workspace is far larger than
/// the caches and is only read again by the backward pass, so writing around
/// the caches saves the read-for-ownership of every line.
///
/// # Safety
/// The [`dispatch`] module's contract.
#[inline(always)]
pub(super) unsafe fn forward_rows<P: Products>(
    job: &ForwardJob,
    rows: Range<usize>,
    scratch: *mut f32,
) {
    let net = job.net;
    let in_w = net.layers[0].inw;
    let last = net.layers.len() - 1;
    let out_w = net.layers[last].outw;
    let half = BLOCK * job.max_width;
    // SAFETY: the scratch holds two blocks of `half` floats, then the
    // pairs (scratch_floats); each block of rows r0..r0 + nb lies within
    // `rows`, which the job's input, activations and output hold (the
    // module's contract), and its sink writes only that block's rows.
    unsafe {
        let pairs = scratch.add(2 * half).cast::<u32>();
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
            forward_block::<P>(net, job.input.add(r0 * in_w), nb, out_w, &sink, pairs);
            r0 += nb;
        }
        P::L::store_fence();
    }
}

/// The training forward pass's blocks: computed in the scratch, streamed
/// to the workspace, the last layer also copied to the output.
pub(super) struct TrainingSink<'a, L> {
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
        // SAFETY: the scratch starts with two halves of BLOCK × max-width
        // floats (scratch_floats), which layers alternate between.
        unsafe { self.scratch.add((l % 2) * self.half) }
    }

    #[inline(always)]
    unsafe fn after(&self, l: usize, block: *const f32) {
        let (job, r0, nb) = (self.job, self.r0, self.nb);
        let w = job.net.layers[l].outw;
        // SAFETY: rows r0..r0 + nb of layer l's activations (and of the
        // output) belong to this task's rows, which they hold (the
        // dispatch module's contract); the block is in the scratch, apart
        // from both.
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
pub(super) struct InferenceSink {
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
            // SAFETY: the scratch starts with two halves of BLOCK ×
            // max-width floats (scratch_floats), which layers alternate
            // between.
            unsafe { self.scratch.add((l % 2) * self.half) }
        }
    }

    #[inline(always)]
    unsafe fn after(&self, _: usize, _: *const f32) {}
}

/// # Safety
/// The [`dispatch`] module's contract.
#[inline(always)]
pub(super) unsafe fn inference_rows<P: Products>(
    job: &InferenceJob,
    rows: Range<usize>,
    scratch: *mut f32,
) {
    let net = job.net;
    let in_w = net.layers[0].inw;
    let last = net.layers.len() - 1;
    let out_w = job.out_columns;
    let half = BLOCK * job.max_width;
    // SAFETY: the scratch holds two blocks of `half` floats, then the
    // pairs (scratch_floats); each block of rows r0..r0 + nb lies within
    // `rows`, which the job's input and output hold (the module's
    // contract).
    unsafe {
        let pairs = scratch.add(2 * half).cast::<u32>();
        let mut r0 = rows.start;
        while r0 < rows.end {
            let nb = (rows.end - r0).min(BLOCK);
            let sink = InferenceSink {
                output: job.output.get().add(r0 * out_w),
                scratch,
                half,
                last,
            };
            forward_block::<P>(net, job.input.add(r0 * in_w), nb, out_w, &sink, pairs);
            r0 += nb;
        }
    }
}

/// # Safety
/// The [`dispatch`] module's contract.
#[inline(always)]
pub(super) unsafe fn backward_rows<P: Products>(
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
    // SAFETY: `partial` holds the parameter count, the scratch two blocks
    // of `half` floats and then the pairs (scratch_floats), and every
    // block r0..r0 + nb lies within `rows`, which the job's input,
    // activations, output gradient and input gradient hold (the module's
    // contract). Within a block, G is read from one scratch half (or
    // d_output) while the other is written, and each product gets the
    // rows and columns of the layer it names.
    unsafe {
        let pairs = scratch.add(2 * half).cast::<u32>();
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
