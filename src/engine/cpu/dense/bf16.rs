//! Mixed-precision layer products on processors with AVX512-BF16
//! (`vdpbf16ps`: AMD Zen 4 and later, Intel Cooper Lake, Sapphire Rapids
//! and later).
//!
//! `vdpbf16ps` multiplies 16 pairs of bf16 values by 16 other pairs and
//! adds each pair's two products to an f32 lane: twice the multiply-adds
//! of an f32 FMA per instruction. A product `C = A · B` therefore reads
//! both operands as *pairs along the reduction*: a 32-bit word holds two
//! consecutive reduction terms, low half first. Each of a layer's three
//! products gets its operands in that form:
//!
//! ```text
//! forward  Y  = X · Wᵀ   X's rows as pairs of columns     Wᵀ as pairs of rows (packed per step)
//! backward dX = G · W    G's rows as pairs of columns     W as pairs of rows (packed per step)
//!          dW += Gᵀ · X  G's and X's pairs of rows, interleaved column by column
//! ```
//!
//! The block's operands are converted just before each product (one
//! conversion per element against a layer width of multiply-adds), with
//! round-to-nearest-even; sums, bias, activations, their derivatives and
//! everything outside the products stay f32, as in mixed-precision
//! training on GPUs. The register tiles and their fused epilogue are the
//! f32 kernels' own.

use crate::field::mlp::MlpLayout;

/// The weights of every layer as bf16 pairs, packed once per pass.
///
/// Each layer's pairs are a matrix of words with its row count and row
/// stride rounded up to `align` (1 for `vdpbf16ps`, [`amx::TILE`] for the
/// tile registers) and zeros in the padding, and the words end with
/// `2 · align` zero words of slack: the tile kernels read whole tiles
/// past a product's last column.
#[derive(Default)]
pub(super) struct PairedWeights {
    /// Per layer, Wᵀ as pairs along `in`: ⌈in/2⌉ × out words.
    forward: Vec<u32>,
    forward_at: Vec<(usize, usize)>,
    /// Per layer, W as pairs along `out`: ⌈out/2⌉ × in words.
    backward: Vec<u32>,
    backward_at: Vec<(usize, usize)>,
}

/// Layer `l`'s weights as bf16 pairs: where its words start in the
/// packed buffer, and their row stride.
type PairedAt = (usize, usize);

impl PairedWeights {
    /// Words held (for memory accounting; a word is 4 bytes).
    pub(super) fn words(&self) -> usize {
        self.forward.capacity() + self.backward.capacity()
    }

    /// Packs Wᵀ of every layer for the forward product.
    pub(super) fn pack_forward(&mut self, layout: &MlpLayout, params: &[f32], align: usize) {
        // Word (p, j) holds W[j, 2p] and W[j, 2p + 1].
        pack(
            layout,
            params,
            align,
            true,
            &mut self.forward,
            &mut self.forward_at,
        );
    }

    /// Packs W of every layer for the input-gradient product.
    pub(super) fn pack_backward(&mut self, layout: &MlpLayout, params: &[f32], align: usize) {
        // Word (p, c) holds W[2p, c] and W[2p + 1, c].
        pack(
            layout,
            params,
            align,
            false,
            &mut self.backward,
            &mut self.backward_at,
        );
    }

    /// Layer `l`'s packed Wᵀ and W with their row strides, null where not
    /// packed.
    pub(super) fn layer(&self, l: usize) -> [(*const u32, usize); 2] {
        let at = |words: &[u32], offsets: &[PairedAt]| {
            offsets
                .get(l)
                .map_or((std::ptr::null(), 0), |&(at, stride)| {
                    (words[at..].as_ptr(), stride)
                })
        };
        [
            at(&self.forward, &self.forward_at),
            at(&self.backward, &self.backward_at),
        ]
    }
}

/// Every layer's W (`transposed`: Wᵀ) as rows of pairs along its
/// reduction, padded to `align` as [`PairedWeights`] describes. Every word
/// is written, padding included, so a buffer packed for another alignment
/// before leaves nothing behind.
fn pack(
    layout: &MlpLayout,
    params: &[f32],
    align: usize,
    transposed: bool,
    words: &mut Vec<u32>,
    offsets: &mut Vec<PairedAt>,
) {
    offsets.clear();
    let mut total = 0;
    for l in 0..layout.layers() {
        let (i, o) = (layout.widths[l], layout.widths[l + 1]);
        let (reduced, columns) = if transposed { (i, o) } else { (o, i) };
        let stride = columns.next_multiple_of(align);
        offsets.push((total, stride));
        total += reduced.div_ceil(2).next_multiple_of(align) * stride;
    }
    let slack = if align > 1 { 2 * align } else { 0 };
    words.resize(total + slack, 0);
    words[total..].fill(0);
    for (l, &(at, stride)) in offsets.iter().enumerate() {
        let (i, o) = (layout.widths[l], layout.widths[l + 1]);
        let w = &params[layout.weight_offset(l)..][..i * o];
        // W[r, c] with r < o, c < i; the reduction runs over c for Wᵀ.
        let (reduced, columns) = if transposed { (i, o) } else { (o, i) };
        let value = |reduction: usize, column: usize| {
            if reduction >= reduced {
                0.0
            } else if transposed {
                w[column * i + reduction]
            } else {
                w[reduction * i + column]
            }
        };
        let rows = reduced.div_ceil(2).next_multiple_of(align);
        let dst = &mut words[at..at + rows * stride];
        for (p, row) in dst.chunks_exact_mut(stride).enumerate() {
            for (j, word) in row.iter_mut().enumerate() {
                *word = if j < columns {
                    pair(value(2 * p, j), value(2 * p + 1, j))
                } else {
                    0
                };
            }
        }
    }
}

/// `x` rounded to bf16 (to nearest, ties to even), as the top 16 bits of
/// its f32 pattern. NaN stays NaN (quiet).
pub fn bf16_bits(x: f32) -> u32 {
    let bits = x.to_bits();
    if x.is_nan() {
        (bits >> 16) | 0x40
    } else {
        (bits + 0x7fff + ((bits >> 16) & 1)) >> 16
    }
}

/// `x` rounded to bf16 and back: the value the products see.
pub fn round_to_bf16(x: f32) -> f32 {
    f32::from_bits(bf16_bits(x) << 16)
}

/// Two values as one word of bf16 pair, `lo` in the low half.
fn pair(lo: f32, hi: f32) -> u32 {
    bf16_bits(lo) | (bf16_bits(hi) << 16)
}

#[cfg(target_arch = "x86_64")]
pub(super) use kernels::Bf16Products;

#[cfg(target_arch = "x86_64")]
pub(super) mod amx;

#[cfg(target_arch = "x86_64")]
mod kernels {
    use std::arch::x86_64::*;

    use super::super::x86::Avx512;
    use super::super::{Destination, Epi, Layer, Products, epilogue};

    /// `c[i, j] ⊕= Σ_p a(i, p) · b(p, j)` for i < m, j < n, p < pairs,
    /// where a(i, p) at `a[i·a_m + p·a_k]` and b(p, j) at `b[p·b_k + j]`
    /// are words of two bf16 values and `·` is their two-term dot
    /// product.
    struct PairGemm {
        m: usize,
        n: usize,
        pairs: usize,
        a: *const u32,
        a_m: usize,
        a_k: usize,
        b: *const u32,
        b_k: usize,
        out: Destination,
    }

    /// Columns per panel: two vectors of 16 lanes, so a tile is 8 rows
    /// (16 accumulators) and a panel of the weights for a 256-wide input
    /// (128 pairs × 32 columns, 16 KiB) stays in L1 while the tiles go
    /// down the rows. Measured on Zen 4 against the f32 kernels' 64
    /// columns × 4 rows: NeRF's networks 343 against 335 GFLOP/s, the
    /// weight-gradient product gaining most; 12 rows or 48 columns gained
    /// nothing more.
    const PANEL: usize = 32;

    /// `g`'s product, panel by panel.
    ///
    /// # Safety
    /// AVX512-BF16 (with AVX-512F, VL and BW) must be enabled, and for
    /// i < m, p < pairs and j < n: the word `a[i·a_m + p·a_k]` readable,
    /// `b[p·b_k + j]` readable, and `g.out` as [`epilogue`] needs it for
    /// rows below m and columns below n. The panels and tiles below rely
    /// on the same for their part of `g`.
    #[inline(always)]
    unsafe fn pair_gemm(g: &PairGemm) {
        let mut j0 = 0;
        while j0 < g.n {
            let nj = (g.n - j0).min(PANEL);
            // SAFETY: columns j0..j0 + nj are within n, nj ≤ 16 · NV, and
            // the caller keeps the rest of the contract.
            unsafe {
                match nj.div_ceil(16) {
                    1 => panel::<1, 8>(g, j0, nj),
                    _ => panel::<2, 8>(g, j0, nj),
                }
            }
            j0 += PANEL;
        }
    }

    /// # Safety
    /// As [`pair_gemm`]'s, with `j0 + nj ≤ g.n` and `nj ≤ 16 · NV`.
    #[inline(always)]
    unsafe fn panel<const NV: usize, const MR: usize>(g: &PairGemm, j0: usize, nj: usize) {
        let mut masks = [0u16; NV];
        for (v, m) in masks.iter_mut().enumerate() {
            *m = mask(nj - v * 16);
        }
        let mut i = 0;
        while i + MR <= g.m {
            // SAFETY: rows i..i + MR are within m, the masks select the
            // panel's nj columns, and the caller keeps the rest.
            unsafe { tile::<MR, NV>(g, i, j0, nj, &masks) };
            i += MR;
        }
        // SAFETY: as above, for the last m − i < MR rows.
        unsafe {
            match g.m - i {
                0 => {}
                1 => tile::<1, NV>(g, i, j0, nj, &masks),
                2 if MR > 2 => tile::<2, NV>(g, i, j0, nj, &masks),
                3 if MR > 3 => tile::<3, NV>(g, i, j0, nj, &masks),
                4 if MR > 4 => tile::<4, NV>(g, i, j0, nj, &masks),
                5 if MR > 5 => tile::<5, NV>(g, i, j0, nj, &masks),
                6 if MR > 6 => tile::<6, NV>(g, i, j0, nj, &masks),
                7 if MR > 7 => tile::<7, NV>(g, i, j0, nj, &masks),
                _ => unreachable!("remainders are below MR ≤ 8"),
            }
        }
    }

    /// # Safety
    /// As [`pair_gemm`]'s, with rows `i0..i0 + R` within m, columns
    /// `j0..j0 + nj` within n, and `masks[v]` selecting those of vector v.
    #[inline(always)]
    unsafe fn tile<const R: usize, const NV: usize>(
        g: &PairGemm,
        i0: usize,
        j0: usize,
        nj: usize,
        masks: &[__mmask16; NV],
    ) {
        // SAFETY: the loads read a's words of rows i0 + r < m and b's
        // columns the masks select, at pairs p < g.pairs; the epilogue
        // writes the same rows and columns of `g.out`: all within this
        // function's contract.
        unsafe {
            let mut acc = [[_mm512_setzero_ps(); NV]; R];
            let mut a = g.a.add(i0 * g.a_m);
            let mut b = g.b.add(j0);
            for _ in 0..g.pairs {
                let mut bv = [_mm512_setzero_si512(); NV];
                for v in 0..NV {
                    bv[v] = _mm512_maskz_loadu_epi32(masks[v], b.add(v * 16).cast());
                }
                for (r, acc_r) in acc.iter_mut().enumerate() {
                    let av = as_bf16(_mm512_set1_epi32(*a.add(r * g.a_m) as i32));
                    for v in 0..NV {
                        acc_r[v] = _mm512_dpbf16_ps(acc_r[v], av, as_bf16(bv[v]));
                    }
                }
                a = a.add(g.a_k);
                b = b.add(g.b_k);
            }
            epilogue::<Avx512, R, NV>(g.out, i0, j0, nj, masks, &acc);
        }
    }

    /// 32 bf16 values as the bits they are stored in, and back.
    #[inline(always)]
    fn as_bf16(words: __m512i) -> __m512bh {
        // SAFETY: both are 64 bytes of plain data.
        unsafe { std::mem::transmute::<__m512i, __m512bh>(words) }
    }

    #[inline(always)]
    fn as_words(halves: __m512bh) -> __m512i {
        // SAFETY: both are 64 bytes of plain data.
        unsafe { std::mem::transmute::<__m512bh, __m512i>(halves) }
    }

    #[inline(always)]
    pub(super) fn mask(n: usize) -> __mmask16 {
        if n >= 16 {
            0xffff
        } else {
            ((1u32 << n) - 1) as u16
        }
    }

    /// Each of `rows` rows of `cols` floats (row stride `stride`) as
    /// ⌈cols/2⌉ words of consecutive bf16 pairs (row stride
    /// `dst_stride`), an odd row's last word padded with zero.
    ///
    /// # Safety
    /// AVX512-BF16 (with AVX-512F) must be enabled, the rows' floats
    /// readable and their words writable.
    #[inline(always)]
    pub(super) unsafe fn rows_to_pairs(
        src: *const f32,
        rows: usize,
        cols: usize,
        stride: usize,
        dst: *mut u32,
        dst_stride: usize,
    ) {
        // SAFETY: the masked loads read columns j + t < cols of row r, the
        // masked store writes words below ⌈cols/2⌉ of row r; within the
        // contract.
        unsafe {
            for r in 0..rows {
                let s = src.add(r * stride);
                let d = dst.add(r * dst_stride);
                let mut j = 0;
                while j < cols {
                    let left = cols - j;
                    let lo = _mm512_maskz_loadu_ps(mask(left), s.add(j));
                    let hi = _mm512_maskz_loadu_ps(mask(left.saturating_sub(16)), s.add(j + 16));
                    // Lanes 0-15 from `lo`, 16-31 from `hi`: the row's
                    // order, so word t holds columns 2t and 2t + 1.
                    let words = as_words(_mm512_cvtne2ps_pbh(hi, lo));
                    _mm512_mask_storeu_epi32(
                        d.add(j / 2).cast(),
                        mask(left.min(32).div_ceil(2)),
                        words,
                    );
                    j += 32;
                }
            }
        }
    }

    /// The halfword order that turns `_mm512_cvtne2ps_pbh(second, first)`
    /// into words of (first, second) pairs, lane by lane. Halfword t of a
    /// converted pair of vectors is lane t of the first (t < 16) or lane
    /// t − 16 of the second: take 0, 16, 1, 17, ….
    pub(super) static PAIR_ZIP: [u16; 32] = {
        let mut zip = [0u16; 32];
        let mut t = 0;
        while t < 16 {
            zip[2 * t] = t as u16;
            zip[2 * t + 1] = t as u16 + 16;
            t += 1;
        }
        zip
    };

    /// Rows 2p and 2p + 1 of `rows` rows of `cols` floats (row stride
    /// `stride`) as one row of `cols` words: word (p, c) holds the two
    /// rows' column c, the second zero past the last row.
    ///
    /// # Safety
    /// AVX512-BF16 (with AVX-512F and BW) must be enabled, the rows'
    /// floats readable and ⌈rows/2⌉ rows of `cols` words writable at
    /// `dst`.
    #[inline(always)]
    pub(super) unsafe fn interleave_row_pairs(
        src: *const f32,
        rows: usize,
        cols: usize,
        stride: usize,
        dst: *mut u32,
    ) {
        // SAFETY: PAIR_ZIP is 64 bytes; the masked loads read columns
        // c + t < cols of rows 2p and (when it exists) 2p + 1 < rows, the
        // masked store the same columns of word row p < ⌈rows/2⌉.
        unsafe {
            let zip = _mm512_loadu_si512(PAIR_ZIP.as_ptr().cast());
            for p in 0..rows.div_ceil(2) {
                let first = src.add(2 * p * stride);
                let second = 2 * p + 1 < rows;
                let d = dst.add(p * cols);
                let mut c = 0;
                while c < cols {
                    let m = mask(cols - c);
                    let lo = _mm512_maskz_loadu_ps(m, first.add(c));
                    let hi = if second {
                        _mm512_maskz_loadu_ps(m, first.add(stride + c))
                    } else {
                        _mm512_setzero_ps()
                    };
                    let halves = as_words(_mm512_cvtne2ps_pbh(hi, lo));
                    let words = _mm512_permutexvar_epi16(zip, halves);
                    _mm512_mask_storeu_epi32(d.add(c).cast(), m, words);
                    c += 16;
                }
            }
        }
    }

    /// The products from bf16 pairs with `vdpbf16ps`.
    pub struct Bf16Products;

    impl Products for Bf16Products {
        type L = Avx512;

        #[inline(always)]
        unsafe fn forward(
            layer: &Layer,
            a: *const f32,
            nb: usize,
            n: usize,
            out: Destination,
            pairs: *mut u32,
        ) {
            let k = layer.inw.div_ceil(2);
            // SAFETY: the block's nb ≤ BLOCK rows as pairs, nb × ⌈inw/2⌉
            // words, fit the pairs' scratch; the weights are Wᵀ's pairs,
            // ⌈inw/2⌉ rows of outw ≥ n words, `wt_pairs_stride` apart (the
            // trait's contract).
            unsafe {
                rows_to_pairs(a, nb, layer.inw, layer.inw, pairs, k);
                pair_gemm(&PairGemm {
                    m: nb,
                    n,
                    pairs: k,
                    a: pairs,
                    a_m: k,
                    a_k: 1,
                    b: layer.wt_pairs,
                    b_k: layer.wt_pairs_stride,
                    out,
                });
            }
        }

        #[inline(always)]
        unsafe fn weight_gradient(
            layer: &Layer,
            g: *const f32,
            x: *const f32,
            nb: usize,
            dw: *mut f32,
            pairs: *mut u32,
        ) {
            let k = nb.div_ceil(2);
            // SAFETY: G's and X's pairs of rows, ⌈nb/2⌉ × (outw + inw)
            // words, fit the pairs' scratch (scratch_floats); dW is outw ×
            // inw (the trait's contract).
            unsafe {
                let g_pairs = pairs;
                let x_pairs = pairs.add(k * layer.outw);
                interleave_row_pairs(g, nb, layer.outw, layer.outw, g_pairs);
                interleave_row_pairs(x, nb, layer.inw, layer.inw, x_pairs);
                pair_gemm(&PairGemm {
                    m: layer.outw,
                    n: layer.inw,
                    pairs: k,
                    a: g_pairs,
                    a_m: 1,
                    a_k: layer.outw,
                    b: x_pairs,
                    b_k: layer.inw,
                    out: Destination {
                        c: dw,
                        c_m: layer.inw,
                        epi: Epi::Accumulate,
                    },
                });
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
            pairs: *mut u32,
        ) {
            let k = layer.outw.div_ceil(2);
            // SAFETY: G's nb ≤ BLOCK rows as pairs fit the pairs' scratch;
            // the weights are W's pairs, ⌈outw/2⌉ rows of inw words
            // `w_pairs_stride` apart, of which columns first..first + n
            // ≤ inw are read (the trait's contract).
            unsafe {
                rows_to_pairs(g, nb, layer.outw, layer.outw, pairs, k);
                pair_gemm(&PairGemm {
                    m: nb,
                    n,
                    pairs: k,
                    a: pairs,
                    a_m: k,
                    a_k: 1,
                    b: layer.w_pairs.add(first),
                    b_k: layer.w_pairs_stride,
                    out,
                });
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use std::io::Write;

    use super::super::*;
    use super::*;
    use crate::rng::Pcg32;

    fn random(seed: u64, n: usize, scale: f32) -> Vec<f32> {
        let mut rng = Pcg32::new(seed, 11);
        (0..n)
            .map(|_| (2.0 * rng.next_f32() - 1.0) * scale)
            .collect()
    }

    fn rounded(x: &[f32]) -> Vec<f64> {
        x.iter().map(|&v| round_to_bf16(v) as f64).collect()
    }

    /// Largest |a − b| over the largest |b|.
    fn max_relative(a: &[f32], b: &[f64]) -> f64 {
        assert_eq!(a.len(), b.len());
        let scale = b.iter().fold(0f64, |m, x| m.max(x.abs())).max(1e-30);
        a.iter()
            .zip(b)
            .fold(0f64, |m, (&x, &y)| m.max((x as f64 - y).abs()))
            / scale
    }

    /// True where the bf16 kernels can run; otherwise says by name, on the
    /// terminal (past the test harness's capture), that they were skipped.
    fn bf16_kernels_here(test: &str) -> bool {
        if mixed_kernels_available() {
            return true;
        }
        let _ = writeln!(
            std::io::stderr(),
            "SKIPPED {test}: the bf16 kernels (Avx512Bf16) need AVX512-BF16, which this processor lacks"
        );
        false
    }

    /// The mixed-precision kernels this processor runs: `vdpbf16ps`, and
    /// the tile kernels where it has them (their weight gradient is
    /// `vdpbf16ps`'s, the other two products their own).
    fn mixed_backends() -> Vec<Backend> {
        let mut all = vec![Backend::Avx512Bf16];
        if tile_kernels_available() {
            all.push(Backend::AmxBf16);
        }
        all
    }

    /// The parameters of layer `l` of `layout` as a one-layer network's,
    /// weights rounded to bf16 when `round_weights`, biases as they are.
    fn layer_params(layout: &MlpLayout, params: &[f32], l: usize, round_weights: bool) -> Vec<f64> {
        let (i, o) = (layout.widths[l], layout.widths[l + 1]);
        let w = &params[layout.weight_offset(l)..][..i * o];
        let mut p: Vec<f64> = if round_weights {
            rounded(w)
        } else {
            w.iter().map(|&v| v as f64).collect()
        };
        if let Some(b) = layout.bias_offset(l) {
            p.extend(params[b..b + o].iter().map(|&v| v as f64));
        }
        p
    }

    #[test]
    fn rounding_to_bf16_is_to_nearest_with_ties_to_even() {
        // bf16 keeps 8 significant bits: 1 + 2⁻⁷ is representable, 1 + 2⁻⁸
        // is a tie between 1 (even) and 1 + 2⁻⁷ (odd).
        assert_eq!(round_to_bf16(1.0 + 2f32.powi(-7)), 1.0 + 2f32.powi(-7));
        assert_eq!(round_to_bf16(1.0 + 2f32.powi(-8)), 1.0);
        assert_eq!(
            round_to_bf16(1.0 + 3.0 * 2f32.powi(-8)),
            1.0 + 2f32.powi(-6)
        );
        assert_eq!(
            round_to_bf16(1.0 + 2f32.powi(-8) + 2f32.powi(-20)),
            1.0 + 2f32.powi(-7)
        );
        assert_eq!(round_to_bf16(-3.0), -3.0);
        assert_eq!(round_to_bf16(f32::INFINITY), f32::INFINITY);
        assert_eq!(round_to_bf16(f32::MAX), f32::INFINITY);
        assert!(round_to_bf16(f32::NAN).is_nan());
        // Within half a unit of the last place everywhere else.
        for x in random(5, 10_000, 1e3) {
            let r = round_to_bf16(x);
            assert!((r - x).abs() <= x.abs() * 2f32.powi(-8), "{x} → {r}");
        }
    }

    /// Every layer's product equals the f64 sum of the products of its
    /// bf16-rounded operands (weights, and the layer's input as the
    /// kernels stored it), up to the f32 summation's rounding: the bf16
    /// kernels round the operands exactly as [`round_to_bf16`], multiply
    /// exactly and sum in f32. A layer with at most four outputs is
    /// computed in f32 without rounding (the narrow kernel).
    #[test]
    fn mixed_forward_layers_equal_sums_of_rounded_operands() {
        if !bf16_kernels_here("mixed_forward_layers_equal_sums_of_rounded_operands") {
            return;
        }
        let cases = [
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
            // NeRF's odd widths: 63 inputs, the 319-wide skip, a 257 output.
            (
                MlpLayout::new(vec![63, 256, 256], Activation::Relu, Activation::Relu, true),
                130,
            ),
            (
                MlpLayout::new(
                    vec![319, 256, 257],
                    Activation::Relu,
                    Activation::None,
                    true,
                ),
                67,
            ),
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
                MlpLayout::new(vec![8, 8], Activation::Relu, Activation::Relu, true),
                1,
            ),
        ];
        let sweep = (1..=17).map(|rows| {
            (
                MlpLayout::new(
                    vec![9, 33, 50, 16],
                    Activation::Relu,
                    Activation::Sigmoid,
                    false,
                ),
                64 + rows,
            )
        });
        for (case, (layout, rows)) in cases.into_iter().chain(sweep).enumerate() {
            for backend in mixed_backends() {
                let params = random(100 + case as u64, layout.param_count(), 0.5);
                let input = random(200 + case as u64, rows * layout.input_width(), 1.0);
                let mut ws = MlpWorkspace::new(&layout, rows);
                let mut out = vec![0.0; rows * layout.output_width()];
                forward_with(backend, &layout, &params, &input, rows, &mut ws, &mut out);
                for l in 0..layout.layers() {
                    let (i, o) = (layout.widths[l], layout.widths[l + 1]);
                    let x = if l == 0 {
                        &input[..]
                    } else {
                        &ws.activations(l - 1)[..rows * i]
                    };
                    let act = layout.activation(l);
                    let single = MlpLayout::new(vec![i, o], act, act, layout.bias);
                    let narrow = o <= NARROW_COLUMNS;
                    let x64: Vec<f64> = if narrow {
                        x.iter().map(|&v| v as f64).collect()
                    } else {
                        rounded(x)
                    };
                    let p64 = layer_params(&layout, &params, l, !narrow);
                    let want = reference_forward(&single, &p64, &x64, rows).remove(0);
                    // Sums of ≤ 319 products in f32: ~√319 · 6e-8 ≈ 1e-6 of the
                    // scale with random signs; a wrongly rounded operand would
                    // be off by up to 2⁻⁸ ≈ 4e-3 of its term.
                    let e = max_relative(&ws.activations(l)[..rows * o], &want);
                    assert!(
                        e < 2e-5,
                        "{backend:?} case {case} ({:?}) layer {l}: {e:e}",
                        layout.widths
                    );
                }
                assert_eq!(&out[..], &ws.activations(layout.layers() - 1)[..out.len()]);
                let mut inferred = vec![0.0; out.len()];
                let out_w = layout.output_width();
                inference_with(
                    backend,
                    &layout,
                    &params,
                    &input,
                    rows,
                    &mut inferred,
                    out_w,
                );
                assert_eq!(
                    inferred, out,
                    "{backend:?} case {case}: inference differs from forward"
                );
            }
        }
    }

    /// One layer's backward pass: with a linear or ReLU output, G = dY ⊙
    /// act'(Y) is exact in f32, so dW, dX (and db, summed in f32) equal
    /// the f64 sums over bf16-rounded G, X and W up to f32 summation.
    #[test]
    fn mixed_backward_of_a_layer_equals_sums_of_rounded_operands() {
        if !bf16_kernels_here("mixed_backward_of_a_layer_equals_sums_of_rounded_operands") {
            return;
        }
        let cases = [
            (vec![63, 256], Activation::Relu, 2500),
            (vec![319, 257], Activation::None, 131),
            (vec![20, 3], Activation::None, 65),
            (vec![256, 1], Activation::Relu, 1),
            (vec![33, 50], Activation::Relu, 64),
        ];
        for (case, (widths, act, rows)) in cases.into_iter().enumerate() {
            for backend in mixed_backends() {
                let layout = MlpLayout::new(widths.clone(), act, act, true);
                let (i, o) = (layout.widths[0], layout.widths[1]);
                let params = random(10 + case as u64, layout.param_count(), 0.5);
                let input = random(20 + case as u64, rows * i, 1.0);
                let d_out = random(30 + case as u64, rows * o, 1.0);
                let mut ws = MlpWorkspace::new(&layout, rows);
                let mut out = vec![0.0; rows * o];
                forward_with(backend, &layout, &params, &input, rows, &mut ws, &mut out);
                let mut d_params = vec![1.0f32; params.len()];
                let mut d_input = vec![f32::NAN; input.len()];
                backward_with(
                    backend,
                    &layout,
                    &params,
                    &input,
                    rows,
                    &mut ws,
                    MlpGradients {
                        output: &d_out,
                        params: &mut d_params,
                        input: Some(InputGradient {
                            values: &mut d_input,
                            columns: 0..i,
                        }),
                    },
                );
                let g: Vec<f32> = d_out
                    .iter()
                    .zip(&out)
                    .map(|(&d, &y)| d * act.derivative_from_output(y))
                    .collect();
                let (g16, x16, w16) = (rounded(&g), rounded(&input), rounded(&params[..i * o]));
                let mut want_dw = vec![1.0f64; i * o];
                let mut want_db = vec![1.0f64; o];
                let mut want_dx = vec![0.0f64; rows * i];
                for r in 0..rows {
                    for k in 0..o {
                        want_db[k] += g[r * o + k] as f64;
                        for c in 0..i {
                            want_dw[k * i + c] += g16[r * o + k] * x16[r * i + c];
                            want_dx[r * i + c] += g16[r * o + k] * w16[k * i + c];
                        }
                    }
                }
                // Sums of up to 2500 terms in f32 (in row chunks): √2500 · 6e-8
                // ≈ 3e-6 of the scale with random signs.
                let e = max_relative(&d_params[..i * o], &want_dw);
                assert!(e < 2e-5, "{backend:?} case {case} dW: {e:e}");
                let e = max_relative(&d_params[i * o..], &want_db);
                assert!(e < 2e-5, "{backend:?} case {case} db: {e:e}");
                let e = max_relative(&d_input, &want_dx);
                assert!(e < 2e-5, "{backend:?} case {case} dX: {e:e}");
            }
        }
    }

    /// Whole networks. The backward pass, given the forward pass the
    /// kernels stored, equals f64 sums over bf16-rounded operands layer by
    /// layer (G, X and W rounded in every product, db and the activation
    /// derivatives in full precision), up to f32 summation: 1e-4 of the
    /// scale leaves room for the f32 rounding of five layers (~1e-6 each)
    /// and for the rare operand that rounds the other way because f32 and
    /// f64 differ in its last bits (2⁻⁸ of one term). The output is
    /// compared with the exact f64 network: each operand is within 2⁻⁹ of
    /// its value, so with random signs a layer's sum stays within a few
    /// 2⁻⁸ of its scale; 2 % bounds that for these depths. Both fail on a
    /// wrong index, pair or layout (errors of order one).
    #[test]
    fn mixed_networks_equal_sums_of_rounded_operands() {
        if !bf16_kernels_here("mixed_networks_equal_sums_of_rounded_operands") {
            return;
        }
        let cases = [
            (
                MlpLayout::new(
                    vec![63, 256, 256, 256, 256, 256],
                    Activation::Relu,
                    Activation::Relu,
                    true,
                ),
                300,
            ),
            (
                MlpLayout::new(
                    vec![319, 256, 256, 256, 257],
                    Activation::Relu,
                    Activation::None,
                    true,
                ),
                129,
            ),
            (
                MlpLayout::new(
                    vec![283, 128, 3],
                    Activation::Relu,
                    Activation::Sigmoid,
                    true,
                ),
                200,
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
            (
                MlpLayout::new(
                    vec![37, 21, 70, 5],
                    Activation::Relu,
                    Activation::None,
                    true,
                ),
                65,
            ),
        ];
        for (case, (layout, rows)) in cases.into_iter().enumerate() {
            let layout = layout.with_precision(Precision::Mixed);
            let params = layout.init_params(40 + case as u64);
            let input = random(50 + case as u64, rows * layout.input_width(), 1.0);
            let d_out = random(60 + case as u64, rows * layout.output_width(), 1.0);
            let mut ws = MlpWorkspace::new(&layout, rows);
            let mut out = vec![0.0; rows * layout.output_width()];
            mlp_forward(&layout, &params, &input, rows, &mut ws, &mut out);
            let mut d_params = vec![0.0f32; params.len()];
            let mut d_input = vec![0.0f32; input.len()];
            mlp_backward(
                &layout,
                &params,
                &input,
                rows,
                &mut ws,
                MlpGradients {
                    output: &d_out,
                    params: &mut d_params,
                    input: Some(InputGradient::every_column(&mut d_input, &layout)),
                },
            );

            let to64 = |x: &[f32]| x.iter().map(|&v| v as f64).collect::<Vec<_>>();
            let want = reference_forward(&layout, &to64(&params), &to64(&input), rows);
            let e = max_relative(&out, &want[layout.layers() - 1]);
            assert!(e < 2e-2, "case {case} output: {e:e}");

            let mut want_dp = vec![0.0f64; params.len()];
            let last = layout.layers() - 1;
            let mut g: Vec<f64> = d_out
                .iter()
                .zip(&ws.activations(last)[..d_out.len()])
                .map(|(&d, &y)| d as f64 * layout.output.derivative_from_output(y as f64))
                .collect();
            let mut want_dx = Vec::new();
            for l in (0..layout.layers()).rev() {
                let (i, o) = (layout.widths[l], layout.widths[l + 1]);
                let x = if l == 0 {
                    &input[..]
                } else {
                    &ws.activations(l - 1)[..rows * i]
                };
                let (g16, x16) = (
                    rounded(&g.iter().map(|&v| v as f32).collect::<Vec<_>>()),
                    rounded(x),
                );
                let w16 = rounded(&params[layout.weight_offset(l)..][..i * o]);
                let w_off = layout.weight_offset(l);
                let mut dx = vec![0.0f64; rows * i];
                for r in 0..rows {
                    for k in 0..o {
                        if let Some(b) = layout.bias_offset(l) {
                            want_dp[b + k] += g[r * o + k];
                        }
                        let gk = g16[r * o + k];
                        for c in 0..i {
                            want_dp[w_off + k * i + c] += gk * x16[r * i + c];
                            dx[r * i + c] += gk * w16[k * i + c];
                        }
                    }
                }
                if l > 0 {
                    g = dx
                        .iter()
                        .zip(x)
                        .map(|(&d, &y)| d * layout.hidden.derivative_from_output(y as f64))
                        .collect();
                } else {
                    want_dx = dx;
                }
            }
            let e = max_relative(&d_params, &want_dp);
            assert!(e < 1e-4, "case {case} d_params: {e:e}");
            // An input gradient sums only a layer's width of terms, so a
            // term whose G rounds the other way (G's f32 sum and the
            // reference's f64 sum differ in the last bits, ~1e-7, which
            // crosses a bf16 rounding boundary for ~1e-7 / 2⁻⁹ ≈ 5e-5 of
            // the operands: tens of the 77k here) moves it by 2⁻⁸ of that
            // term, up to ~2⁻⁸ / √256 ≈ 2.4e-4 of the scale each: 5e-3.
            let e = max_relative(&d_input, &want_dx);
            assert!(e < 5e-3, "case {case} d_input: {e:e}");

            // Not f32 in disguise: rounding shows.
            let f32_layout = layout.clone().with_precision(Precision::F32);
            let mut f32_out = vec![0.0; out.len()];
            mlp_inference(&f32_layout, &params, &input, rows, &mut f32_out);
            assert_ne!(
                f32_out, out,
                "case {case}: mixed precision gave f32's result"
            );
        }
    }
}
