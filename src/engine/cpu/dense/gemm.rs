//! The GEMM kernels: tiles of rows by vectors of columns, their epilogues
//! (bias, activation, the streamed store), and the narrow layers; generic
//! over the lanes of an instruction set.

use super::*;

/// Plain Rust, 8 lanes as an array; the compiler vectorises what it can.
pub(super) struct Portable;
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
        // SAFETY: `p` is readable for the first m ≤ 8 lanes (the `Lanes`
        // contract), and these read no more.
        unsafe {
            if m == 8 {
                std::ptr::copy_nonoverlapping(p, v.as_mut_ptr(), 8);
            } else {
                for (j, x) in v.iter_mut().enumerate().take(m) {
                    *x = *p.add(j);
                }
            }
        }
        v
    }
    #[inline(always)]
    unsafe fn store(p: *mut f32, v: [f32; 8], m: usize) {
        for (j, x) in v.iter().enumerate().take(m) {
            // SAFETY: j < m, and `p` is writable for the first m lanes (the
            // `Lanes` contract).
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

/// `g`'s product, tile by tile.
///
/// # Safety
/// `L`'s instruction set must be enabled (the [`Lanes`] contract), and the
/// memory `g` describes valid: for i < m, p < k and j < n, `a` readable
/// at `i·a_m + p·a_k`, `b` at `p·b_k + j`, `c` writable (and, to
/// accumulate, readable) at `i·c_m + j`, a forward bias readable at j and
/// a backward `y` at `i·y_m + j`. The tiles below, each a part of `g`,
/// rely on the same.
#[inline(always)]
pub(super) unsafe fn gemm<L: Lanes>(g: &Gemm) {
    let panel = L::N * L::NV_MAX;
    let mut j0 = 0;
    while j0 < g.n {
        let nj = (g.n - j0).min(panel);
        // SAFETY: columns j0..j0 + nj are within n, and the caller keeps
        // the rest of the contract.
        unsafe { with_tile_rows!(nj.div_ceil(L::N), panel_rows, g, j0, nj) };
        j0 += panel;
    }
}

/// The tiles of columns `j0..j0 + nj` (nj ≤ NV vectors), MR rows at a
/// time, then the remaining rows.
///
/// # Safety
/// As [`gemm`]'s, with `j0 + nj ≤ g.n` and `nj ≤ NV · L::N`.
#[inline(always)]
pub(super) unsafe fn panel_rows<L: Lanes, const NV: usize, const MR: usize>(
    g: &Gemm,
    j0: usize,
    nj: usize,
) {
    // SAFETY: `L`'s instructions are enabled (this function's contract).
    let mut masks = [unsafe { L::mask(0) }; NV];
    for (v, m) in masks.iter_mut().enumerate() {
        // SAFETY: as above; v · N < nj, since NV = ⌈nj / N⌉.
        *m = unsafe { L::mask(nj - v * L::N) };
    }
    let mut i = 0;
    while i + MR <= g.m {
        // SAFETY: rows i..i + MR are within m, the masks cover exactly the
        // panel's nj columns, and the caller keeps the rest of the contract.
        unsafe { tile::<L, MR, NV>(g, i, j0, nj, &masks) };
        i += MR;
    }
    // SAFETY: as above, for the last m − i < MR rows.
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

/// Rows `i0..i0 + R` by columns `j0..j0 + nj` of `g`'s product, held in
/// R × NV vector registers through the reduction.
///
/// # Safety
/// As [`gemm`]'s, with the rows within m, the columns within n, and
/// `masks[v]` selecting the lanes of columns j0 + v·N… below j0 + nj.
#[inline(always)]
pub(super) unsafe fn tile<L: Lanes, const R: usize, const NV: usize>(
    g: &Gemm,
    i0: usize,
    j0: usize,
    nj: usize,
    masks: &[L::M; NV],
) {
    // SAFETY: every load reads a's rows i0 + r < m at reduction steps
    // p < k, and b's columns the masks select (below n) at those steps;
    // the epilogue's contract is part of this function's.
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
pub(super) struct Destination {
    pub(super) c: *mut f32,
    pub(super) c_m: usize,
    pub(super) epi: Epi,
}

/// Writes a tile's accumulators to rows `i0..i0 + R`, columns
/// `j0..j0 + nj` of `g.c`, through `g.epi`.
///
/// # Safety
/// `L`'s instructions must be enabled, `g.c` writable (and, to
/// accumulate, readable) at `(i0 + r)·c_m + j` for r < R and j < j0 + nj,
/// with `masks[v]` selecting the lanes of columns j0 + v·N… below
/// j0 + nj; a forward bias readable at those columns, a backward `y` at
/// `(i0 + r)·y_m + j`.
#[inline(always)]
pub(super) unsafe fn epilogue<L: Lanes, const R: usize, const NV: usize>(
    g: Destination,
    i0: usize,
    j0: usize,
    nj: usize,
    masks: &[L::M; NV],
    acc: &[[L::V; NV]; R],
) {
    // SAFETY: every access is at a row below i0 + R and, vector by vector,
    // at the columns the masks select, or, in the scalar loops, at columns
    // j0..j0 + nj: all inside this function's contract.
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
pub(super) const NARROW_COLUMNS: usize = 4;

/// `c = act(x Wᵀ + b)` for a layer with few outputs (σ alone, RGB): one
/// dot product per row and output along W's contiguous rows. A register
/// tile would spend a whole vector of lanes on each of these 1–3 columns;
/// on lego_400 this made the σ-only inference of a training batch ~1.8×
/// faster.
/// The sum runs in a different order than the tile's, so outputs differ
/// from a tile's in the last bits.
///
/// # Safety
/// `L`'s instructions must be enabled; `x` readable for `nb` rows of
/// `layer.inw`, `c` writable for `nb` rows of `n`, n ≤ `layer.outw`, and
/// the layer's W (and bias, where not null) readable.
#[inline(always)]
pub(super) unsafe fn narrow_layer<L: Lanes>(
    layer: &Layer,
    x: *const f32,
    nb: usize,
    n: usize,
    act: Activation,
    c: *mut f32,
) {
    let k = layer.inw;
    // SAFETY: rows r < nb of x and c, W's rows j < n ≤ outw, and within a
    // row the lanes `mask(k − i)` selects, all below k: inside this
    // function's contract.
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
