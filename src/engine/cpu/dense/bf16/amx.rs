//! Mixed-precision layer products on Intel's matrix units (AMX-BF16:
//! Sapphire Rapids and later Xeons).
//!
//! `tdpbf16ps` multiplies a tile of 16 rows × 16 bf16 pairs by a tile of
//! 16 pair rows × 16 columns and adds the 16 × 16 sums of pair products to
//! an f32 tile: 8,192 multiply-adds per instruction, against 32 for
//! `vdpbf16ps`. Its operands are the bf16 kernels' own pair words
//! ([`super::bf16`]): A as rows of pairs along the reduction, B as rows
//! of pairs, a column per word. A tile row is 64 bytes, so the reduction
//! is taken 16 pairs at a time and each operand is padded with zero pairs
//! to a multiple of 16 (zero pairs add nothing to a sum); rows and columns
//! past the product's edge are computed and thrown away.
//!
//! The forward product (`X · Wᵀ`) and the input-gradient product (`G · W`)
//! read X or G as rows of pairs and the weights as pair rows, the layout
//! the tiles want. The weight-gradient product (`Gᵀ · X`) reduces over the
//! block's rows, which both operands store across rows: X's pairs of rows
//! are B as they are, and G's pairs of rows are transposed into A, 16 × 16
//! words at a time in vector registers (four rounds of swapping the
//! off-diagonal halves of ever smaller blocks).
//!
//! A block of up to 32 rows × 32 columns is four f32 tiles (tmm0–3); its
//! two A tiles (tmm4, 5) and two B tiles (tmm6, 7) are reloaded for each
//! 16 pairs of the reduction. The f32 tiles are stored to the stack and go
//! through the f32 kernels' epilogue (bias, activation, derivative gate).
//!
//! Linux hands a process the 8 KiB of tile registers only on request
//! (`arch_prctl(ARCH_REQ_XCOMP_PERM, XFEATURE_XTILEDATA)`, Linux 5.16);
//! where it refuses, or elsewhere, the `vdpbf16ps` kernels run instead.
//! The instructions are written as inline assembly: Rust has no stable
//! intrinsics for them.

use std::arch::asm;
use std::arch::x86_64::*;

use super::super::x86::Avx512;
use super::super::{Destination, Epi, Lanes, Layer, Products, epilogue};
use super::kernels::{PAIR_ZIP, interleave_row_pairs, mask};

/// Pairs of the reduction in one A tile row, and rows or columns of a tile.
pub(in super::super) const TILE: usize = 16;

/// Whether the processor has AMX-BF16 and the kernel lets this process use
/// the tile registers (asked once).
pub(in super::super) fn available() -> bool {
    static GRANTED: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *GRANTED.get_or_init(|| {
        // CPUID leaf 7, sub-leaf 0, EDX: bit 22 AMX-BF16, bit 24 AMX-TILE
        // (Intel SDM vol. 2A, CPUID).
        let leaf7 = __cpuid_count(7, 0);
        let has_amx = leaf7.edx & (1 << 22) != 0 && leaf7.edx & (1 << 24) != 0;
        has_amx && tile_data_permitted()
    })
}

#[cfg(target_os = "linux")]
fn tile_data_permitted() -> bool {
    // arch/x86/include/uapi/asm/prctl.h and the XSAVE feature number of
    // the tile data (Linux's Documentation/arch/x86/xstate.rst).
    const ARCH_REQ_XCOMP_PERM: libc::c_long = 0x1023;
    const XFEATURE_XTILEDATA: libc::c_long = 18;
    // SAFETY: a request for a permission; no memory is passed.
    unsafe {
        libc::syscall(
            libc::SYS_arch_prctl,
            ARCH_REQ_XCOMP_PERM,
            XFEATURE_XTILEDATA,
        ) == 0
    }
}

#[cfg(not(target_os = "linux"))]
fn tile_data_permitted() -> bool {
    false
}

/// The tile shapes, loaded by `ldtilecfg`: palette 1, every one of the
/// eight tiles 16 rows of 64 bytes (Intel SDM vol. 1, 18.2: bytes 16–31
/// the bytes per row of tiles 0–7, bytes 48–55 their rows).
#[repr(C, align(64))]
struct TileConfig([u8; 64]);

static TILE_CONFIG: TileConfig = {
    let mut bytes = [0u8; 64];
    bytes[0] = 1;
    let mut tile = 0;
    while tile < 8 {
        bytes[16 + 2 * tile] = 64;
        bytes[48 + tile] = TILE as u8;
        tile += 1;
    }
    TileConfig(bytes)
};

/// `out[i, j] ⊕= Σ_p a(i, p) · b(p, j)` for i < m, j < n, p < pairs,
/// where a(i, p) is the word `a[i·a_stride + p]`, b(p, j) the word
/// `b[p·b_stride + j]`, and `·` the two-term dot product of their bf16
/// halves. `pairs` is a multiple of [`TILE`]; rows of `a` up to m rounded
/// up to 16, and columns of `b` up to n rounded up to 32, must be
/// readable (their products are thrown away).
struct TileGemm {
    m: usize,
    n: usize,
    pairs: usize,
    a: *const u32,
    a_stride: usize,
    b: *const u32,
    b_stride: usize,
    out: Destination,
}

/// `g`'s product on the tile registers.
///
/// # Safety
/// [`available`] must have returned true, AVX-512F (for the epilogue) be
/// enabled, `g.pairs` be a multiple of [`TILE`], the words [`TileGemm`]
/// names readable (rows of `a` up to m rounded up to 16, columns of `b`
/// up to n rounded up to 32, over all `pairs`), and `g.out` as
/// [`epilogue`] needs it for rows below m and columns below n.
#[inline(always)]
unsafe fn tile_gemm(g: &TileGemm) {
    debug_assert!(g.pairs.is_multiple_of(TILE));
    // SAFETY: this process may use the tile registers (`available`), so
    // `ldtilecfg` of a valid palette-1 configuration (TILE_CONFIG, 64
    // bytes, 64-byte aligned) and `tilerelease` are sound; every block
    // lies within m and n, as `block` requires.
    unsafe {
        asm!("ldtilecfg [{}]", in(reg) &TILE_CONFIG, options(nostack, readonly));
        // Column panels outside, rows inside: a panel of B (32 columns of
        // up to 160 pairs, 20 KiB) stays in L1 while the row blocks pass.
        let mut j0 = 0;
        while j0 < g.n {
            let cols = (g.n - j0).min(2 * TILE);
            let mut i0 = 0;
            while i0 < g.m {
                let rows = (g.m - i0).min(2 * TILE);
                match (rows > TILE, cols > TILE) {
                    (true, true) => block::<2, 2>(g, i0, j0, rows, cols),
                    (true, false) => block::<2, 1>(g, i0, j0, rows, cols),
                    (false, true) => block::<1, 2>(g, i0, j0, rows, cols),
                    (false, false) => block::<1, 1>(g, i0, j0, rows, cols),
                }
                i0 += 2 * TILE;
            }
            j0 += 2 * TILE;
        }
        asm!("tilerelease", options(nostack, nomem));
    }
}

/// 64-byte aligned f32 tiles as stored from the tile registers.
#[repr(C, align(64))]
struct Stored([f32; 4 * TILE * TILE]);

/// One block of `rows` ≤ 16·MR rows and `cols` ≤ 16·NC columns at
/// (i0, j0): f32 tile r·2 + c holds rows i0 + 16r…, columns j0 + 16c….
///
/// # Safety
/// As [`tile_gemm`]'s, with the tile configuration loaded, rows
/// `i0..i0 + rows` within m and columns `j0..j0 + cols` within n.
#[inline(always)]
unsafe fn block<const MR: usize, const NC: usize>(
    g: &TileGemm,
    i0: usize,
    j0: usize,
    rows: usize,
    cols: usize,
) {
    let a_row_bytes = 4 * g.a_stride;
    let b_row_bytes = 4 * g.b_stride;
    // SAFETY: the tiles are configured as 16 rows of 64 bytes. The A loads
    // read 16 words of rows i0..i0 + 16·MR (within m rounded up to 16, as
    // MR = 2 only when rows > 16), the B loads 16 words of columns
    // j0..j0 + 16·NC (within n rounded up to 32) of 16 pair rows, at
    // pairs below g.pairs: all readable by the contract. The stores write
    // 16 rows of 64 bytes at 128-byte row strides inside `stored` (32 × 32
    // floats), and the epilogue reads back only rows < rows and columns
    // the masks select, which those stores wrote, and writes rows and
    // columns of the block, within the contract.
    unsafe {
        asm!("tilezero tmm0", options(nostack, nomem));
        if NC == 2 {
            asm!("tilezero tmm1", options(nostack, nomem));
        }
        if MR == 2 {
            asm!("tilezero tmm2", options(nostack, nomem));
            if NC == 2 {
                asm!("tilezero tmm3", options(nostack, nomem));
            }
        }
        let mut a = g.a.add(i0 * g.a_stride);
        let mut b = g.b.add(j0);
        for _ in 0..g.pairs / TILE {
            asm!("tileloadd tmm4, [{p} + {s} * 1]", p = in(reg) a, s = in(reg) a_row_bytes,
                options(nostack, readonly));
            if MR == 2 {
                asm!("tileloadd tmm5, [{p} + {s} * 1]", p = in(reg) a.add(TILE * g.a_stride),
                    s = in(reg) a_row_bytes, options(nostack, readonly));
            }
            asm!("tileloadd tmm6, [{p} + {s} * 1]", p = in(reg) b, s = in(reg) b_row_bytes,
                options(nostack, readonly));
            if NC == 2 {
                asm!("tileloadd tmm7, [{p} + {s} * 1]", p = in(reg) b.add(TILE),
                    s = in(reg) b_row_bytes, options(nostack, readonly));
            }
            asm!("tdpbf16ps tmm0, tmm4, tmm6", options(nostack, nomem));
            if NC == 2 {
                asm!("tdpbf16ps tmm1, tmm4, tmm7", options(nostack, nomem));
            }
            if MR == 2 {
                asm!("tdpbf16ps tmm2, tmm5, tmm6", options(nostack, nomem));
                if NC == 2 {
                    asm!("tdpbf16ps tmm3, tmm5, tmm7", options(nostack, nomem));
                }
            }
            a = a.add(TILE);
            b = b.add(TILE * g.b_stride);
        }
        // The block as 32 rows of 32 floats.
        // Left uninitialised: the stores below write every float the
        // epilogue reads (rows < 16·MR, columns < 16·NC).
        let mut stored = std::mem::MaybeUninit::<Stored>::uninit();
        let c = stored.as_mut_ptr().cast::<f32>();
        let row_bytes = 4 * 2 * TILE;
        asm!("tilestored [{p} + {s} * 1], tmm0", p = in(reg) c, s = in(reg) row_bytes,
            options(nostack));
        if NC == 2 {
            asm!("tilestored [{p} + {s} * 1], tmm1", p = in(reg) c.add(TILE), s = in(reg) row_bytes,
                options(nostack));
        }
        if MR == 2 {
            asm!("tilestored [{p} + {s} * 1], tmm2", p = in(reg) c.add(2 * TILE * TILE),
                s = in(reg) row_bytes, options(nostack));
            if NC == 2 {
                asm!("tilestored [{p} + {s} * 1], tmm3", p = in(reg) c.add(2 * TILE * TILE + TILE),
                    s = in(reg) row_bytes, options(nostack));
            }
        }
        let mut masks = [0; NC];
        for (v, mask) in masks.iter_mut().enumerate() {
            *mask = Avx512::mask(cols.saturating_sub(v * TILE));
        }
        for r in 0..rows {
            let mut acc = [[Avx512::zero(); NC]; 1];
            for (v, lane) in acc[0].iter_mut().enumerate() {
                *lane = Avx512::load(c.add(r * 2 * TILE + v * TILE), masks[v]);
            }
            epilogue::<Avx512, 1, NC>(g.out, i0 + r, j0, cols, &masks, &acc);
        }
    }
}

/// Each of `rows` rows of `cols` floats (row stride `cols`) as ⌈cols/2⌉
/// bf16 pair words, then zero words up to `stride`, the row stride of
/// `dst`.
///
/// # Safety
/// AVX512-BF16 (with AVX-512F) must be enabled, `src` readable for the
/// rows, `dst` writable for `rows` rows of `stride ≥ ⌈cols/2⌉` words.
#[inline(always)]
unsafe fn rows_to_padded_pairs(
    src: *const f32,
    rows: usize,
    cols: usize,
    dst: *mut u32,
    stride: usize,
) {
    // SAFETY: rows_to_pairs writes words below ⌈cols/2⌉ of each row, the
    // zeros the rest of the row up to `stride`: within the contract.
    unsafe {
        super::kernels::rows_to_pairs(src, rows, cols, cols, dst, stride);
        let words = cols.div_ceil(2);
        for r in 0..rows {
            std::ptr::write_bytes(dst.add(r * stride + words), 0, stride - words);
        }
    }
}

/// [`TILE`]-aligned pair count for a reduction over `width` values.
pub(in super::super) fn padded_pairs(width: usize) -> usize {
    width.div_ceil(2).next_multiple_of(TILE)
}

/// Index vectors of `_mm512_permutex2var_epi32` for the four rounds of a
/// 16 × 16 transpose: round `r` swaps the off-diagonal `s × s` blocks of
/// every `2s × 2s` block (s = 8 >> r). Of rows a = i and b = i + s (bit s
/// of i clear), the new row i keeps a's columns with bit s clear and takes
/// b's columns s to the left; the new row i + s takes a's columns s to the
/// right and keeps b's.
static TRANSPOSE_ROUNDS: [[[u32; 16]; 2]; 4] = {
    let mut rounds = [[[0u32; 16]; 2]; 4];
    let mut r = 0;
    while r < 4 {
        let s = 8 >> r;
        let mut j = 0;
        while j < 16 {
            let (upper, lower) = if j & s == 0 {
                (j, j + s)
            } else {
                (16 + j - s, 16 + j)
            };
            rounds[r][0][j] = upper as u32;
            rounds[r][1][j] = lower as u32;
            j += 1;
        }
        r += 1;
    }
    rounds
};

/// Transposes 16 rows of 16 words in place.
///
/// # Safety
/// AVX-512F must be enabled.
#[inline(always)]
unsafe fn transpose(rows: &mut [__m512i; TILE]) {
    // SAFETY: AVX-512F is enabled (the contract); the loads read the 64
    // bytes of a round's index vector.
    unsafe {
        for (r, round) in TRANSPOSE_ROUNDS.iter().enumerate() {
            let s = 8 >> r;
            let upper = _mm512_loadu_si512(round[0].as_ptr().cast());
            let lower = _mm512_loadu_si512(round[1].as_ptr().cast());
            for i in 0..TILE {
                if i & s == 0 {
                    let (a, b) = (rows[i], rows[i + s]);
                    rows[i] = _mm512_permutex2var_epi32(a, upper, b);
                    rows[i + s] = _mm512_permutex2var_epi32(a, lower, b);
                }
            }
        }
    }
}

/// Gᵀ as rows of pairs: for `rows` rows of `cols` floats (row stride
/// `cols`), word (c, p) of `dst` (row stride `pairs`, a multiple of 16;
/// ⌈cols/16⌉·16 rows) holds G[2p, c] and G[2p + 1, c], zero past the
/// last row or column.
///
/// # Safety
/// AVX512-BF16 (with AVX-512F and BW) must be enabled, `src` readable for
/// `rows` rows of `cols` floats, `pairs` ≥ ⌈rows/2⌉ a multiple of 16, and
/// `dst` writable for ⌈cols/16⌉·16 rows of `pairs` words.
#[inline(always)]
unsafe fn transposed_row_pairs(
    src: *const f32,
    rows: usize,
    cols: usize,
    dst: *mut u32,
    pairs: usize,
) {
    // SAFETY: the masked loads read columns c0 + t < cols of rows
    // 2p + 1 < rows or 2p < rows; the stores write 16 words at
    // (c0 + t)·pairs + p0, with c0 + t < ⌈cols/16⌉·16 and p0 + 16 ≤ pairs;
    // `transmute` reinterprets 64 bytes of plain data.
    unsafe {
        let zip = _mm512_loadu_si512(PAIR_ZIP.as_ptr().cast());
        let used = rows.div_ceil(2);
        for c0 in (0..cols).step_by(TILE) {
            let m = mask(cols - c0);
            for p0 in (0..pairs).step_by(TILE) {
                let mut words = [_mm512_setzero_si512(); TILE];
                for (t, word) in words.iter_mut().enumerate() {
                    let p = p0 + t;
                    if p >= used {
                        break;
                    }
                    let first = src.add(2 * p * cols + c0);
                    let lo = _mm512_maskz_loadu_ps(m, first);
                    let hi = if 2 * p + 1 < rows {
                        _mm512_maskz_loadu_ps(m, first.add(cols))
                    } else {
                        _mm512_setzero_ps()
                    };
                    let halves =
                        std::mem::transmute::<__m512bh, __m512i>(_mm512_cvtne2ps_pbh(hi, lo));
                    *word = _mm512_permutexvar_epi16(zip, halves);
                }
                // Row t held pair p0 + t of columns c0…; now row t holds
                // column c0 + t's pairs p0….
                transpose(&mut words);
                for (t, word) in words.iter().enumerate() {
                    _mm512_storeu_si512(dst.add((c0 + t) * pairs + p0).cast(), *word);
                }
            }
        }
    }
}

/// Weights as rows of bf16 pair words, `stride` words apart.
#[derive(Clone, Copy)]
struct PairRows {
    words: *const u32,
    stride: usize,
}

/// The forward and input-gradient products: `nb` rows of `width` floats
/// at `a`, as padded pairs in `pairs`, times `n` columns of the weights'
/// pair rows.
///
/// # Safety
/// [`tile_gemm`]'s, with the weights packed as [`super::PairedWeights`]
/// packs them for the tiles (16-aligned rows and stride, zero slack past
/// the end) and `pairs` the scratch [`super::super::scratch_floats`] sets
/// aside for them.
#[inline(always)]
unsafe fn rows_times_paired_weights(
    a: *const f32,
    nb: usize,
    width: usize,
    weights: PairRows,
    n: usize,
    out: Destination,
    pairs: *mut u32,
) {
    let k = padded_pairs(width);
    // SAFETY: up to BLOCK rows (nb rounded up to 16, as the A tiles read)
    // of k = ⌈width/2⌉ rounded up to 16 words fit the scratch's
    // 2 · BLOCK · (max-width + 16) words; the weights hold k pair rows of
    // `weights.stride` ≥ n words and slack for the last tile's columns.
    unsafe {
        rows_to_padded_pairs(a, nb, width, pairs, k);
        tile_gemm(&TileGemm {
            m: nb,
            n,
            pairs: k,
            a: pairs,
            a_stride: k,
            b: weights.words,
            b_stride: weights.stride,
            out,
        });
    }
}

/// The three products on the tile registers.
pub struct AmxProducts;

impl Products for AmxProducts {
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
        // SAFETY: the trait's contract, with Wᵀ packed for the tiles.
        unsafe {
            rows_times_paired_weights(
                a,
                nb,
                layer.inw,
                PairRows {
                    words: layer.wt_pairs,
                    stride: layer.wt_pairs_stride,
                },
                n,
                out,
                pairs,
            )
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
        let k = padded_pairs(nb);
        let used = nb.div_ceil(2);
        // SAFETY: A (outw rounded up to 16 rows of k ≤ 32 words) and B (k
        // rows of inw words and 32 words of slack) fit the pairs' scratch,
        // 2 · BLOCK · (max-width + 16) words (scratch_floats); the tile
        // loads read A's rows below outw rounded up to 16 and B's columns
        // below inw rounded up to 32, inside the slack; dW is outw × inw.
        unsafe {
            // A: Gᵀ's pairs, outw (rounded up to 16) rows of k words; B:
            // X's pairs of rows, k rows of inw words, zero rows past the
            // block's last pair and 32 zero words of slack.
            let a = pairs;
            let b = pairs.add(layer.outw.next_multiple_of(TILE) * k);
            transposed_row_pairs(g, nb, layer.outw, a, k);
            interleave_row_pairs(x, nb, layer.inw, layer.inw, b);
            std::ptr::write_bytes(
                b.add(used * layer.inw),
                0,
                (k - used) * layer.inw + 2 * TILE,
            );
            tile_gemm(&TileGemm {
                m: layer.outw,
                n: layer.inw,
                pairs: k,
                a,
                a_stride: k,
                b,
                b_stride: layer.inw,
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
        // SAFETY: the trait's contract, with W packed for the tiles;
        // columns first..first + n are within its inw.
        unsafe {
            rows_times_paired_weights(
                g,
                nb,
                layer.outw,
                PairRows {
                    words: layer.w_pairs.add(first),
                    stride: layer.w_pairs_stride,
                },
                n,
                out,
                pairs,
            )
        }
    }
}

/// `tdpbf16ps` on registers only, four independent tiles: the ceiling of
/// the products above. Returns the FLOP done and a value read from the
/// tiles.
///
/// # Safety
/// [`available`] must have returned true.
pub(in super::super) unsafe fn tile_chains(iterations: usize, seed: f32) -> (f64, f32) {
    let a = [super::pair(seed, 0.25); TILE * TILE];
    let b = [super::pair(1e-3, -1e-3); TILE * TILE];
    let mut stored = Stored([0.0; 4 * TILE * TILE]);
    // SAFETY: this process may use the tile registers (the contract); the
    // loads read 16 rows of 64 bytes of `a` and `b` (256 words each), the
    // store writes 16 rows of 64 bytes into `stored` (4 KiB).
    unsafe {
        asm!("ldtilecfg [{}]", in(reg) &TILE_CONFIG, options(nostack, readonly));
        asm!(
            "tilezero tmm0",
            "tilezero tmm1",
            "tilezero tmm2",
            "tilezero tmm3",
            options(nostack, nomem)
        );
        asm!("tileloadd tmm4, [{p} + {s} * 1]", "tileloadd tmm5, [{p} + {s} * 1]",
            p = in(reg) a.as_ptr(), s = in(reg) 64usize, options(nostack, readonly));
        asm!("tileloadd tmm6, [{p} + {s} * 1]", "tileloadd tmm7, [{p} + {s} * 1]",
            p = in(reg) b.as_ptr(), s = in(reg) 64usize, options(nostack, readonly));
        for _ in 0..iterations {
            asm!(
                "tdpbf16ps tmm0, tmm4, tmm6",
                "tdpbf16ps tmm1, tmm4, tmm7",
                "tdpbf16ps tmm2, tmm5, tmm6",
                "tdpbf16ps tmm3, tmm5, tmm7",
                options(nostack, nomem)
            );
        }
        asm!("tilestored [{p} + {s} * 1], tmm3", p = in(reg) stored.0.as_mut_ptr(),
            s = in(reg) 64usize, options(nostack));
        asm!("tilerelease", options(nostack, nomem));
    }
    // Four instructions of 16 × 16 outputs × 32 products, each a
    // multiply-add.
    let flop = (4 * 2 * TILE * TILE * 2 * TILE * iterations) as f64;
    (flop, stored.0[..TILE * TILE].iter().sum())
}

#[cfg(test)]
mod tests {
    use std::io::Write;

    use super::super::super::Backend;
    use super::super::round_to_bf16;
    use super::*;
    use crate::rng::Pcg32;

    /// True where `backend` runs; otherwise says by name, on the terminal
    /// (past the test harness's capture), that the test was skipped.
    fn runs_here(backend: Backend, needs: &str, test: &str) -> bool {
        if backend.runs_here() {
            return true;
        }
        let _ = writeln!(
            std::io::stderr(),
            "SKIPPED {test}: {needs}, which this processor (or its kernel) lacks"
        );
        false
    }

    fn random(seed: u64, n: usize) -> Vec<f32> {
        let mut rng = Pcg32::new(seed, 13);
        (0..n).map(|_| 2.0 * rng.next_f32() - 1.0).collect()
    }

    /// A pair of quiet NaNs: what the operands hold past the product's
    /// rows and columns, which the tiles compute and must throw away.
    const NAN_PAIR: u32 = 0x7fc0_7fc0;

    /// `tile_gemm` with the instructions its epilogue and conversions are
    /// compiled for, as the `amxbf16` entry points enable them.
    ///
    /// # Safety
    /// [`tile_gemm`]'s.
    #[target_feature(enable = "avx512f,avx512vl,avx512bw,avx512bf16,avx2,fma")]
    unsafe fn product(g: &TileGemm) {
        // SAFETY: the caller keeps tile_gemm's contract; the instructions
        // it inlines are enabled here.
        unsafe { tile_gemm(g) }
    }

    /// The tile product `C = A · B` of f32 matrices given as bf16 pairs,
    /// stored (`C = A · B`) and accumulated onto ones (`C = 1 + A · B`),
    /// against references from the f32 operands in f64:
    ///
    /// - the exact sum of the bf16-rounded operands' products: `tdpbf16ps`
    ///   multiplies bf16 values exactly (8 × 8 significant bits fit f32's
    ///   24) and sums in f32, so each output is within
    ///   (terms + 2) · 2⁻²⁴ · Σ|a·b| of it, whatever the order of the sum;
    /// - the product of the f32 operands themselves: rounding to bf16
    ///   moves each operand by at most 2⁻⁸ of itself, so each product by
    ///   at most (2 · 2⁻⁸ + 2⁻¹⁶)|a·b|, and each output by that much of
    ///   Σ|a·b| on top of the summation's error.
    ///
    /// A wrong row, column, pair or tile is off by the order of Σ|a·b|.
    /// The shapes cover every block shape (one or two row and column
    /// tiles), rows and columns past a tile's edge, reductions of one pair
    /// to several tiles, and odd widths (a zero half in the last pair).
    #[test]
    fn tile_products_match_f32_products_within_bf16_rounding() {
        if !runs_here(
            Backend::AmxBf16,
            "the tile kernels need AMX-BF16, AMX-TILE, the kernel's permission to use the tile data, and AVX512-BF16",
            "tile_products_match_f32_products_within_bf16_rounding",
        ) {
            return;
        }
        let shapes = [
            (1, 1, 1),
            (16, 16, 32),
            (17, 33, 33),
            (32, 32, 64),
            (33, 17, 31),
            (64, 70, 257),
            (45, 256, 320),
            (5, 3, 2),
        ];
        for (case, &(m, n, width)) in shapes.iter().enumerate() {
            let a = random(10 + case as u64, m * width);
            let b = random(20 + case as u64, width * n);
            // A: m rows (then NaN rows up to a multiple of 16) of `pairs`
            // words; B: `pairs` rows of n words (then NaN columns up to
            // the stride, a multiple of 16, and 32 words of NaN slack).
            let pairs = padded_pairs(width);
            let value = |x: &[f32], at: usize, within: bool| if within { x[at] } else { 0.0 };
            let rows = m.next_multiple_of(TILE);
            let mut a_words = vec![NAN_PAIR; rows * pairs];
            for i in 0..m {
                for p in 0..pairs {
                    let c = 2 * p;
                    a_words[i * pairs + p] = super::super::pair(
                        value(&a, i * width + c, c < width),
                        value(&a, i * width + c + 1, c + 1 < width),
                    );
                }
            }
            let stride = n.next_multiple_of(TILE);
            let mut b_words = vec![NAN_PAIR; pairs * stride + 2 * TILE];
            for p in 0..pairs {
                for j in 0..n {
                    let r = 2 * p;
                    b_words[p * stride + j] = super::super::pair(
                        value(&b, r * n + j, r < width),
                        value(&b, (r + 1) * n + j, r + 1 < width),
                    );
                }
            }
            for epi in [Epi::Store, Epi::Accumulate] {
                let start = if matches!(epi, Epi::Store) { 0.0 } else { 1.0 };
                let mut c = vec![start; m * n];
                let g = TileGemm {
                    m,
                    n,
                    pairs,
                    a: a_words.as_ptr(),
                    a_stride: pairs,
                    b: b_words.as_ptr(),
                    b_stride: stride,
                    out: Destination {
                        c: c.as_mut_ptr(),
                        c_m: n,
                        epi,
                    },
                };
                // SAFETY: the tile kernels run here (checked above); A has
                // m rounded up to 16 rows of `pairs` (a multiple of 16)
                // words, B `pairs` rows of n rounded up to 16 words and 32
                // words of slack, and C is m × n.
                unsafe { product(&g) };
                for i in 0..m {
                    for j in 0..n {
                        let (mut exact, mut rounded, mut magnitude) = (0f64, 0f64, 0f64);
                        for k in 0..width {
                            let (x, y) = (a[i * width + k], b[k * n + j]);
                            exact += x as f64 * y as f64;
                            rounded += round_to_bf16(x) as f64 * round_to_bf16(y) as f64;
                            magnitude += (x as f64 * y as f64).abs();
                        }
                        let got = c[i * n + j] as f64 - start as f64;
                        let summation =
                            (width + 2) as f64 * 2f64.powi(-24) * (magnitude + start as f64);
                        let rounding = (2.0 * 2f64.powi(-8) + 2f64.powi(-16)) * magnitude;
                        assert!(
                            (got - rounded).abs() <= summation,
                            "{m}×{width}·{width}×{n} {}: C[{i}, {j}] = {got}, the rounded \
                             operands' sum {rounded}",
                            if start == 0.0 {
                                "stored"
                            } else {
                                "accumulated"
                            },
                        );
                        assert!(
                            (got - exact).abs() <= rounding + summation,
                            "{m}×{width}·{width}×{n}: C[{i}, {j}] = {got}, the f32 \
                             operands' sum {exact}, beyond bf16 rounding's {rounding}",
                        );
                    }
                }
            }
        }
    }

    /// `transposed_row_pairs` against the words written out one by one:
    /// word (c, p) holds G[2p, c] (low half) and G[2p + 1, c], zero past
    /// the last row, and the rows past the last column are zero too. Exact:
    /// both round the same f32 values to bf16. Runs wherever AVX512-BF16
    /// does (the transpose is vector code, not tiles).
    #[test]
    fn transposed_row_pairs_are_the_pairs_of_each_column() {
        if !runs_here(
            Backend::Avx512Bf16,
            "the transpose of the tile kernels' weight gradient needs AVX512-BF16",
            "transposed_row_pairs_are_the_pairs_of_each_column",
        ) {
            return;
        }
        #[target_feature(enable = "avx512f,avx512vl,avx512bw,avx512bf16,avx2,fma")]
        unsafe fn transpose_here(g: &[f32], rows: usize, cols: usize, dst: &mut [u32]) {
            let pairs = padded_pairs(rows);
            assert_eq!(g.len(), rows * cols);
            assert_eq!(dst.len(), cols.next_multiple_of(TILE) * pairs);
            // SAFETY: the instructions are enabled here (the caller checked
            // the processor has them); `g` holds rows × cols floats and
            // `dst` ⌈cols/16⌉·16 rows of `pairs` words (asserted above).
            unsafe { transposed_row_pairs(g.as_ptr(), rows, cols, dst.as_mut_ptr(), pairs) }
        }
        for (case, &(rows, cols)) in [(1, 1), (2, 16), (3, 17), (31, 64), (64, 16), (64, 257)]
            .iter()
            .enumerate()
        {
            let g = random(30 + case as u64, rows * cols);
            let pairs = padded_pairs(rows);
            let mut got = vec![NAN_PAIR; cols.next_multiple_of(TILE) * pairs];
            // SAFETY: the processor has AVX512-BF16 (checked above).
            unsafe { transpose_here(&g, rows, cols, &mut got) };
            for c in 0..cols.next_multiple_of(TILE) {
                for p in 0..pairs {
                    let at = |r: usize| {
                        if r < rows && c < cols {
                            g[r * cols + c]
                        } else {
                            0.0
                        }
                    };
                    let want = super::super::pair(at(2 * p), at(2 * p + 1));
                    assert_eq!(got[c * pairs + p], want, "{rows} × {cols}: word ({c}, {p})");
                }
            }
        }
    }
}
