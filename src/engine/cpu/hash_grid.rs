//! Multiresolution hash encoding (Müller, Evans, Schied, Keller 2022,
//! "Instant Neural Graphics Primitives with a Multiresolution Hash
//! Encoding", section 3), forward and backward.
//!
//! Level l has resolution N_l = ⌊N_min · b^l⌋. A position x ∈ [0,1]³ is
//! scaled by N_l; its cell is ⌊x · N_l⌋ and the level's grid has N_l + 1
//! vertices per side. A level whose (N_l + 1)³ vertices fit in T entries
//! indexes them densely (x + y·(N_l+1) + z·(N_l+1)²) and stores exactly that
//! many entries; a finer level hashes its vertices into T entries with
//! (x·π₁ ⊕ y·π₂ ⊕ z·π₃) mod T. The F features of the 8 corners of the cell
//! are interpolated trilinearly.
//!
//! Parameter layout: one flat array, level after level (level 0 first), each
//! level `entries × F` with an entry's F features adjacent, so one corner is
//! one small contiguous read. Output layout: S × (L·F) row-major, level 0's
//! features first in each row.
//!
//! Positions are unit-cube coordinates, mapped from the grid's box (side
//! `extent` around the unit cube's centre, the scene's box) onto [0,1]³.
//! Positions outside it (rounding in the world → unit-cube mapping can
//! leave a sample a few ulps outside) are clamped to the box, per axis, so
//! they take the value on the nearest face; a NaN coordinate is read as 0.
//! Clamped coordinates get zero gradient with respect to position, which
//! this stage does not compute anyway.
//!
//! Generic over `f32` and `f64` ([`Real`]): the engine runs `f32`, gradient
//! checks run `f64`.
//!
//! Speed (measured by the ignored `throughput` test): the paper's hashed
//! tables are 4 MiB per level, 44 MiB in all, so a sample-by-sample walk
//! through all levels misses the caches on nearly every corner. Instead
//! each pass sweeps one level at a time over the whole batch, so only that
//! level's table is being read and it stays in the last-level cache; the
//! level's features go to a level-major scratch buffer that one blocked
//! transposition turns into rows. Within a sweep, samples go in groups of
//! 16: their corners are computed by loops the compiler vectorises (built
//! for AVX2 or AVX-512 when the CPU has them) and their table entries are
//! prefetched while the group before is gathered.

use num_traits::Float;
use rayon::prelude::*;

/// π₁, π₂, π₃ of the spatial hash (paper, section 3, eq. 4). π₁ = 1 keeps
/// neighbouring x in neighbouring entries, which helps the cache.
pub const HASH_PRIMES: [u32; 3] = [1, 2_654_435_761, 805_459_861];

/// The spatial hash before the reduction mod T, with wrapping 32-bit
/// multiplication as in the paper's implementation.
#[inline(always)]
pub fn spatial_hash(x: u32, y: u32, z: u32) -> u32 {
    x.wrapping_mul(HASH_PRIMES[0]) ^ y.wrapping_mul(HASH_PRIMES[1]) ^ z.wrapping_mul(HASH_PRIMES[2])
}

use crate::field::encoding::{HashGridLayout, LevelLayout};

/// The floating-point types the stage runs in.
pub trait Real: Float + Send + Sync + 'static {
    fn from_index(value: u32) -> Self;
    /// Truncation toward zero, which is floor for the values callers pass.
    /// Unlike `as`, it does not saturate, so it vectorises (cvttps2dq).
    ///
    /// # Safety
    /// `self` must be finite and in [0, 2^31).
    unsafe fn truncate_index(self) -> u32;
}

impl Real for f32 {
    #[inline(always)]
    fn from_index(value: u32) -> Self {
        // Through i32, which converts in one instruction on every x86-64
        // (indices stay below 2^31).
        value as i32 as f32
    }
    #[inline(always)]
    unsafe fn truncate_index(self) -> u32 {
        // SAFETY: the caller guarantees 0 ≤ self < 2^31, so the value fits.
        unsafe { self.to_int_unchecked::<i32>() as u32 }
    }
}

impl Real for f64 {
    #[inline(always)]
    fn from_index(value: u32) -> Self {
        value as i32 as f64
    }
    #[inline(always)]
    unsafe fn truncate_index(self) -> u32 {
        // SAFETY: the caller guarantees 0 ≤ self < 2^31, so the value fits.
        unsafe { self.to_int_unchecked::<i32>() as u32 }
    }
}

/// What the inner loops need of one level, converted once.
#[derive(Clone, Copy)]
struct LevelMath<T> {
    /// The grid's box: a position x maps to (x − box_min) / extent in
    /// [0, 1] (0 and 1 when the box is the unit cube, leaving x as it is).
    box_min: T,
    inverse_extent: T,
    scale: T,
    /// N_l − 1: the cell of a coordinate exactly on the far face.
    last_cell: u32,
    /// (N_l + 1) and (N_l + 1)², the dense strides.
    stride_y: u32,
    stride_z: u32,
    /// T − 1; T is a power of two, so mod T is a mask.
    mask: u32,
}

/// Samples whose corners are computed together: the arithmetic runs as
/// vector loops over the group, and the group's table reads are prefetched
/// while the previous group is gathered.
const GROUP: usize = 16;

/// The 8 corners of each sample of a group: entry indices relative to the
/// level and trilinear weights. Corner c is offset by (c & 1, (c >> 1) & 1,
/// c >> 2) from the cell's lowest vertex.
#[derive(Clone, Copy)]
struct Corners<T> {
    index: [[u32; GROUP]; 8],
    weight: [[T; GROUP]; 8],
}

impl<T: Real> Corners<T> {
    fn new() -> Self {
        Self {
            index: [[0; GROUP]; 8],
            weight: [[T::zero(); GROUP]; 8],
        }
    }
}

impl<T: Real> LevelMath<T> {
    fn new(layout: &HashGridLayout, level: &LevelLayout) -> Self {
        let side = level.resolution + 1;
        let (box_min, inverse_extent) = layout.config().box_mapping();
        let real = |v: f64| T::from(v).expect("a finite box");
        Self {
            box_min: real(box_min),
            inverse_extent: real(inverse_extent),
            scale: T::from_index(level.resolution),
            last_cell: level.resolution - 1,
            stride_y: side,
            stride_z: if level.dense { side * side } else { 0 },
            mask: (layout.config().table_size() - 1) as u32,
        }
    }

    /// Fills `corners` for up to [`GROUP`] positions (a shorter group leaves
    /// the rest describing the origin).
    #[inline(always)]
    fn corners<const DENSE: bool>(&self, positions: &[[T; 3]], corners: &mut Corners<T>) {
        match positions.try_into() {
            Ok(full) => self.group_corners::<DENSE>(full, corners),
            Err(_) => {
                let mut padded = [[T::zero(); 3]; GROUP];
                padded[..positions.len()].copy_from_slice(positions);
                self.group_corners::<DENSE>(&padded, corners)
            }
        }
    }

    /// The corners of a full group. Every loop runs over the whole group
    /// with no early exit, so it compiles to vector instructions.
    #[inline(always)]
    fn group_corners<const DENSE: bool>(
        &self,
        positions: &[[T; 3]; GROUP],
        corners: &mut Corners<T>,
    ) {
        // Per axis and sample: the index term of the lower and upper vertex
        // (times the prime, or the dense stride) and their weights.
        let mut term = [[[0u32; GROUP]; 2]; 3];
        let mut weight = [[[T::zero(); GROUP]; 2]; 3];
        let multiplier = if DENSE {
            [1, self.stride_y, self.stride_z]
        } else {
            HASH_PRIMES
        };
        for k in 0..GROUP {
            for axis in 0..3 {
                // Compare-and-select rather than max/min, whose NaN rules do
                // not vectorise; `x > 0` is false for NaN, which so becomes 0.
                let x = (positions[k][axis] - self.box_min) * self.inverse_extent;
                let x = if x > T::zero() { x } else { T::zero() };
                let x = if x < T::one() { x } else { T::one() };
                let scaled = x * self.scale;
                // scaled ≥ 0, so truncation is floor; x = 1 lands in the last
                // cell with fraction 1 rather than one cell beyond the grid.
                // SAFETY: x ∈ [0, 1] (NaN was mapped to 0) and N_l < 2^31.
                let cell = unsafe { scaled.truncate_index() }.min(self.last_cell);
                let frac = scaled - T::from_index(cell);
                term[axis][0][k] = cell.wrapping_mul(multiplier[axis]);
                term[axis][1][k] = (cell + 1).wrapping_mul(multiplier[axis]);
                weight[axis][0][k] = T::one() - frac;
                weight[axis][1][k] = frac;
            }
        }
        for c in 0..8 {
            let (i, j, l) = (c & 1, (c >> 1) & 1, c >> 2);
            for k in 0..GROUP {
                let (x, y, z) = (term[0][i][k], term[1][j][k], term[2][l][k]);
                corners.index[c][k] = if DENSE {
                    x + y + z
                } else {
                    (x ^ y ^ z) & self.mask
                };
                corners.weight[c][k] = weight[0][i][k] * weight[1][j][k] * weight[2][l][k];
            }
        }
    }
}

/// Samples per rayon task inside one level's sweep and per block of the
/// transposition (a block of 512 rows of L·F = 32 is 64 KiB).
const TASK: usize = 2048;
const TRANSPOSE_BLOCK: usize = 512;

/// Runs `$body` with `$f` and `$d` bound to constants for the feature count
/// and indexing of the level at hand, so the inner loops are compiled for
/// each combination.
macro_rules! with_level_constants {
    ($features:expr, $dense:expr, $f:ident, $d:ident, $body:block) => {
        match ($features, $dense) {
            (1, true) => {
                const $f: usize = 1;
                const $d: bool = true;
                $body
            }
            (1, false) => {
                const $f: usize = 1;
                const $d: bool = false;
                $body
            }
            (2, true) => {
                const $f: usize = 2;
                const $d: bool = true;
                $body
            }
            (2, false) => {
                const $f: usize = 2;
                const $d: bool = false;
                $body
            }
            (4, true) => {
                const $f: usize = 4;
                const $d: bool = true;
                $body
            }
            (4, false) => {
                const $f: usize = 4;
                const $d: bool = false;
                $body
            }
            (8, true) => {
                const $f: usize = 8;
                const $d: bool = true;
                $body
            }
            (8, false) => {
                const $f: usize = 8;
                const $d: bool = false;
                $body
            }
            _ => unreachable!("HashGridLayout::new admits only supported feature counts"),
        }
    };
}

/// Encodes `positions` into `out` (S × L·F, row-major). Allocates its
/// working memory; [`encode_with_scratch`] reuses it across calls.
pub fn encode<T: Real>(layout: &HashGridLayout, params: &[T], positions: &[[T; 3]], out: &mut [T]) {
    encode_with_scratch(layout, params, positions, out, &mut Vec::new());
}

/// [`encode`] with a reusable buffer (grown to S × L·F values).
///
/// Levels are swept one after another over the whole batch, both cores on
/// the same level: the level's table (4 MiB when hashed) is then the only
/// large thing read and stays in the last-level cache, where a batch of 2^18
/// samples reads each of its lines about 16 times; interleaving levels per
/// sample instead cycles through all 48 MiB and misses nearly always. Each
/// sweep writes its level's features contiguously into `scratch` (level
/// major), and one blocked transposition makes the rows: writing 8 bytes
/// into every 128-byte row of `out` per level would move the whole output
/// through memory 16 times.
pub fn encode_with_scratch<T: Real>(
    layout: &HashGridLayout,
    params: &[T],
    positions: &[[T; 3]],
    out: &mut [T],
    scratch: &mut Vec<T>,
) {
    let width = layout.output_width();
    let features = layout.features();
    let samples = positions.len();
    assert_eq!(params.len(), layout.param_count(), "params");
    assert_eq!(out.len(), samples * width, "out must be S × L·F");
    if samples == 0 {
        return;
    }
    if scratch.len() < samples * width {
        scratch.resize(samples * width, T::zero());
    }
    let scratch = &mut scratch[..samples * width];
    for (level, level_out) in layout
        .levels()
        .iter()
        .zip(scratch.chunks_exact_mut(samples * features))
    {
        let math = LevelMath::<T>::new(layout, level);
        let table = &params[level.offset * features..][..level.entries * features];
        level_out
            .par_chunks_mut(TASK * features)
            .zip(positions.par_chunks(TASK))
            .for_each(|(level_out, positions)| {
                with_level_constants!(features, level.dense, F, DENSE, {
                    if !x86_gather::forward_level::<T, F, DENSE>(&math, table, positions, level_out)
                    {
                        forward_level::<T, F, DENSE>(&math, table, positions, level_out)
                    }
                })
            });
    }
    with_level_constants!(features, true, F, _D, {
        level_major_to_rows::<T, F>(scratch, out, samples)
    });
}

/// Adds ∂loss/∂params to `d_params`, given ∂loss/∂out in `d_out` (S × L·F).
/// Allocates its working memory; [`encode_backward_with_scratch`] reuses it.
pub fn encode_backward<T: Real>(
    layout: &HashGridLayout,
    positions: &[[T; 3]],
    d_out: &[T],
    d_params: &mut [T],
) {
    encode_backward_with_scratch(layout, positions, d_out, d_params, &mut Vec::new());
}

/// [`encode_backward`] with a reusable buffer (grown to S × L·F values).
///
/// No races and no per-thread copies of the table: each rayon task owns one
/// level's slice of `d_params` and walks all samples, so the level's
/// gradient table stays in the last-level cache for its whole sweep. `d_out`
/// is first transposed to level-major order in `scratch`, so that each task
/// reads its column contiguously instead of 8 bytes of every 128-byte row.
pub fn encode_backward_with_scratch<T: Real>(
    layout: &HashGridLayout,
    positions: &[[T; 3]],
    d_out: &[T],
    d_params: &mut [T],
    scratch: &mut Vec<T>,
) {
    backward_sweeps(layout, positions, d_out, d_params, scratch, false);
}

/// [`encode_backward_with_scratch`] that writes (`=`) ∂loss/∂params into
/// `d_params` instead of adding to it: each level's task clears its slice
/// of the gradient just before its sweep, in parallel and while the slice
/// is about to be in cache anyway, in place of a serial clearing pass over
/// the whole table beforehand.
pub fn encode_gradient_with_scratch<T: Real>(
    layout: &HashGridLayout,
    positions: &[[T; 3]],
    d_out: &[T],
    d_params: &mut [T],
    scratch: &mut Vec<T>,
) {
    backward_sweeps(layout, positions, d_out, d_params, scratch, true);
}

fn backward_sweeps<T: Real>(
    layout: &HashGridLayout,
    positions: &[[T; 3]],
    d_out: &[T],
    d_params: &mut [T],
    scratch: &mut Vec<T>,
    overwrite: bool,
) {
    let width = layout.output_width();
    let features = layout.features();
    let samples = positions.len();
    assert_eq!(d_params.len(), layout.param_count(), "d_params");
    assert_eq!(d_out.len(), samples * width, "d_out must be S × L·F");
    if samples == 0 {
        if overwrite {
            d_params.fill(T::zero());
        }
        return;
    }
    if scratch.len() < samples * width {
        scratch.resize(samples * width, T::zero());
    }
    let scratch = &mut scratch[..samples * width];
    with_level_constants!(features, true, F, _D, {
        rows_to_level_major::<T, F>(d_out, scratch, samples)
    });
    let mut tasks: Vec<(&LevelLayout, &[T], &mut [T])> = Vec::with_capacity(layout.levels().len());
    let mut rest = d_params;
    for (level, level_d_out) in layout
        .levels()
        .iter()
        .zip(scratch.chunks_exact(samples * features))
    {
        let (d_table, tail) = rest.split_at_mut(level.entries * features);
        tasks.push((level, level_d_out, d_table));
        rest = tail;
    }
    // Finest levels first: they cost the most (cache misses), and starting
    // them early keeps every core busy to the end.
    tasks.reverse();
    tasks
        .into_par_iter()
        .with_max_len(1)
        .for_each(|(level, level_d_out, d_table)| {
            if overwrite {
                d_table.fill(T::zero());
            }
            let math = LevelMath::<T>::new(layout, level);
            with_level_constants!(features, level.dense, F, DENSE, {
                backward_level::<T, F, DENSE>(&math, d_table, positions, level_d_out)
            })
        });
}

/// The gradient with respect to the positions (written, S × 3) of a loss
/// whose gradient with respect to the features is `d_out` (S × L·F), for
/// camera refinement. Each level's features are the trilinear blend
/// Σ_c w_c f_c of its cell's corners, whose weights are products of
/// (1 − u) or u per axis with u the position's fraction in the cell, so
/// ∂/∂u_a flips the sign of axis a's factor and drops it, and ∂u_a/∂x_a =
/// N_l / extent. A coordinate clamped onto the box's face has no
/// gradient. One sample at a time over every level: it runs only when
/// cameras are refined, beside a backward pass that costs far more.
pub fn position_gradient<T: Real>(
    layout: &HashGridLayout,
    params: &[T],
    positions: &[[T; 3]],
    d_out: &[T],
    d_positions: &mut [[T; 3]],
) {
    let width = layout.output_width();
    let features = layout.features();
    assert_eq!(params.len(), layout.param_count(), "params");
    assert_eq!(
        d_out.len(),
        positions.len() * width,
        "d_out must be S × L·F"
    );
    assert_eq!(
        d_positions.len(),
        positions.len(),
        "a gradient per position"
    );
    let levels: Vec<(LevelMath<T>, &[T])> = layout
        .levels()
        .iter()
        .map(|level| {
            let table = &params[level.offset * features..][..level.entries * features];
            (LevelMath::<T>::new(layout, level), table)
        })
        .collect();
    let dense: Vec<bool> = layout.levels().iter().map(|l| l.dense).collect();
    d_positions
        .par_chunks_mut(TASK)
        .zip(positions.par_chunks(TASK))
        .zip(d_out.par_chunks(TASK * width))
        .for_each(|((d_positions, positions), d_out)| {
            for ((d_position, position), d_row) in d_positions
                .iter_mut()
                .zip(positions)
                .zip(d_out.chunks_exact(width))
            {
                let mut sum = [T::zero(); 3];
                for (l, (math, table)) in levels.iter().enumerate() {
                    let d_features = &d_row[l * features..][..features];
                    let multiplier = if dense[l] {
                        [1, math.stride_y, math.stride_z]
                    } else {
                        HASH_PRIMES
                    };
                    let mut term = [[0u32; 2]; 3];
                    let mut weight = [[T::zero(); 2]; 3];
                    let mut slope = [T::zero(); 3];
                    for axis in 0..3 {
                        let x = (position[axis] - math.box_min) * math.inverse_extent;
                        let inside = x > T::zero() && x < T::one();
                        let x = if x > T::zero() { x } else { T::zero() };
                        let x = if x < T::one() { x } else { T::one() };
                        let scaled = x * math.scale;
                        // SAFETY: x ∈ [0, 1] (NaN was mapped to 0) and N_l < 2^31.
                        let cell = unsafe { scaled.truncate_index() }.min(math.last_cell);
                        let frac = scaled - T::from_index(cell);
                        term[axis] = [
                            cell.wrapping_mul(multiplier[axis]),
                            (cell + 1).wrapping_mul(multiplier[axis]),
                        ];
                        weight[axis] = [T::one() - frac, frac];
                        if inside {
                            slope[axis] = math.scale * math.inverse_extent;
                        }
                    }
                    for c in 0..8 {
                        let bits = [c & 1, (c >> 1) & 1, c >> 2];
                        let (x, y, z) = (term[0][bits[0]], term[1][bits[1]], term[2][bits[2]]);
                        let index = if dense[l] {
                            x + y + z
                        } else {
                            (x ^ y ^ z) & math.mask
                        } as usize;
                        let entry = &table[index * features..][..features];
                        let along = entry
                            .iter()
                            .zip(d_features)
                            .fold(T::zero(), |acc, (&f, &g)| acc + f * g);
                        for axis in 0..3 {
                            let sign = if bits[axis] == 1 { T::one() } else { -T::one() };
                            let others = (0..3)
                                .filter(|&a| a != axis)
                                .fold(T::one(), |acc, a| acc * weight[a][bits[a]]);
                            sum[axis] = sum[axis] + sign * others * along * slope[axis];
                        }
                    }
                }
                *d_position = sum;
            }
        });
}

/// `out` (S × L·F rows) from `level_major` (L × S × F).
fn level_major_to_rows<T: Real, const F: usize>(level_major: &[T], out: &mut [T], samples: usize) {
    let levels = level_major.len() / (samples * F);
    let width = levels * F;
    out.par_chunks_mut(TRANSPOSE_BLOCK * width)
        .enumerate()
        .for_each(|(block, out)| {
            let first = block * TRANSPOSE_BLOCK;
            for (l, level) in level_major.chunks_exact(samples * F).enumerate() {
                let level = &level[first * F..];
                for (row, value) in out.chunks_exact_mut(width).zip(level.chunks_exact(F)) {
                    row[l * F..(l + 1) * F].copy_from_slice(value);
                }
            }
        });
}

/// `level_major` (L × S × F) from `rows` (S × L·F).
fn rows_to_level_major<T: Real, const F: usize>(rows: &[T], level_major: &mut [T], samples: usize) {
    let levels = level_major.len() / (samples * F);
    let width = levels * F;
    // Each task fills one block of samples in every level: split each
    // level's column into blocks and hand task b the b-th block of each.
    let mut blocks: Vec<Vec<&mut [T]>> = (0..samples.div_ceil(TRANSPOSE_BLOCK))
        .map(|_| Vec::with_capacity(levels))
        .collect();
    for level in level_major.chunks_exact_mut(samples * F) {
        for (block, column) in blocks.iter_mut().zip(level.chunks_mut(TRANSPOSE_BLOCK * F)) {
            block.push(column);
        }
    }
    blocks
        .into_par_iter()
        .zip(rows.par_chunks(TRANSPOSE_BLOCK * width))
        .for_each(|(mut columns, rows)| {
            for (l, column) in columns.iter_mut().enumerate() {
                for (value, row) in column.chunks_exact_mut(F).zip(rows.chunks_exact(width)) {
                    value.copy_from_slice(&row[l * F..(l + 1) * F]);
                }
            }
        });
}

/// Asks for the cache line holding `base[index]` ahead of its use, so the
/// misses of a group overlap with the work on the previous one. Only the
/// address is used: a prefetch never faults and never reads into a value.
#[inline(always)]
fn prefetch<T>(base: *const T, index: usize) {
    #[cfg(target_arch = "x86_64")]
    {
        use core::arch::x86_64::{_MM_HINT_T0, _mm_prefetch};
        // SAFETY: prefetching is a hint; any address is allowed.
        unsafe { _mm_prefetch::<_MM_HINT_T0>(base.wrapping_add(index) as *const i8) };
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (base, index);
}

/// Visits the samples of `positions` group by group, with each group's
/// corners computed, and their entries of the table at `base` prefetched,
/// while the group before is visited. `visit` gets the group's first
/// sample, its length and its corners.
#[inline(always)]
fn for_each_group<T: Real, const F: usize, const DENSE: bool>(
    math: &LevelMath<T>,
    base: *const T,
    positions: &[[T; 3]],
    mut visit: impl FnMut(usize, usize, &Corners<T>),
) {
    let mut corners = [Corners::new(), Corners::new()];
    let mut groups = positions.chunks(GROUP);
    let Some(first) = groups.next() else { return };
    math.corners::<DENSE>(first, &mut corners[0]);
    let mut len = first.len();
    let mut start = 0;
    let mut current = 0;
    loop {
        let upcoming = groups.next();
        if let Some(group) = upcoming {
            let next = &mut corners[1 - current];
            math.corners::<DENSE>(group, next);
            for index in &next.index {
                for &i in &index[..group.len()] {
                    prefetch(base, i as usize * F);
                }
            }
        }
        visit(start, len, &corners[current]);
        let Some(group) = upcoming else { return };
        start += len;
        len = group.len();
        current = 1 - current;
    }
}

/// One level's features for `positions`, into `out` (S × F).
#[inline(always)]
fn forward_level_portable<T: Real, const F: usize, const DENSE: bool>(
    math: &LevelMath<T>,
    table: &[T],
    positions: &[[T; 3]],
    out: &mut [T],
) {
    for_each_group::<T, F, DENSE>(math, table.as_ptr(), positions, |start, len, corners| {
        let out = &mut out[start * F..(start + len) * F];
        for (k, value) in out.chunks_exact_mut(F).enumerate() {
            let mut sum = [T::zero(); F];
            for c in 0..8 {
                let entry: &[T; F] = table[corners.index[c][k] as usize * F..][..F]
                    .try_into()
                    .unwrap();
                for f in 0..F {
                    sum[f] = sum[f] + corners.weight[c][k] * entry[f];
                }
            }
            value.copy_from_slice(&sum);
        }
    });
}

/// Adds one level's gradient for `positions`, given `d_out` (S × F).
#[inline(always)]
fn backward_level_portable<T: Real, const F: usize, const DENSE: bool>(
    math: &LevelMath<T>,
    d_table: &mut [T],
    positions: &[[T; 3]],
    d_out: &[T],
) {
    for_each_group::<T, F, DENSE>(math, d_table.as_ptr(), positions, |start, len, corners| {
        let d_out = &d_out[start * F..(start + len) * F];
        for (k, gradient) in d_out.chunks_exact(F).enumerate() {
            for c in 0..8 {
                let entry: &mut [T; F] = (&mut d_table[corners.index[c][k] as usize * F..][..F])
                    .try_into()
                    .unwrap();
                for f in 0..F {
                    entry[f] = entry[f] + corners.weight[c][k] * gradient[f];
                }
            }
        }
    });
}

/// Defines `$name`, which runs `$portable` compiled for the widest vector
/// extension the CPU has: the crate is built for baseline x86-64 (SSE2), and
/// the corner arithmetic of a group vectorises much better with AVX2 or
/// AVX-512. Results are bit-identical on every path: nothing is contracted
/// into fused multiply-adds.
macro_rules! dispatch_by_isa {
    ($name:ident, $avx2:ident, $avx512:ident, $portable:ident, ($($arg:ident: $ty:ty),*)) => {
        #[inline(always)]
        fn $name<T: Real, const F: usize, const DENSE: bool>($($arg: $ty),*) {
            #[cfg(target_arch = "x86_64")]
            {
                if crate::isa::avx512() {
                    // SAFETY: the CPU has the features the function is compiled for.
                    return unsafe { $avx512::<T, F, DENSE>($($arg),*) };
                }
                if crate::isa::avx2_fma() {
                    // SAFETY: as above.
                    return unsafe { $avx2::<T, F, DENSE>($($arg),*) };
                }
            }
            $portable::<T, F, DENSE>($($arg),*)
        }

        #[cfg(target_arch = "x86_64")]
        #[target_feature(enable = "avx2,fma,bmi1,bmi2")]
        fn $avx2<T: Real, const F: usize, const DENSE: bool>($($arg: $ty),*) {
            $portable::<T, F, DENSE>($($arg),*)
        }

        #[cfg(target_arch = "x86_64")]
        #[target_feature(enable = "avx512f,avx512vl,avx512dq,avx512bw,avx2,fma,bmi1,bmi2")]
        fn $avx512<T: Real, const F: usize, const DENSE: bool>($($arg: $ty),*) {
            $portable::<T, F, DENSE>($($arg),*)
        }
    };
}

dispatch_by_isa!(forward_level, forward_level_avx2, forward_level_avx512, forward_level_portable, (
    math: &LevelMath<T>,
    table: &[T],
    positions: &[[T; 3]],
    out: &mut [T]
));

dispatch_by_isa!(backward_level, backward_level_avx2, backward_level_avx512, backward_level_portable, (
    math: &LevelMath<T>,
    d_table: &mut [T],
    positions: &[[T; 3]],
    d_out: &[T]
));

/// The forward sweep of one level with AVX-512 gathers, for the paper's
/// case (f32, F = 2): one gather fetches a corner's feature pair for 8
/// samples. The same multiplications and additions, in the same order, as
/// [`forward_level_portable`] (sum = 0, then + wᶜ·eᶜ for c = 0..8, nothing
/// fused), so the bits are the same; the portable loop spends most of its
/// instructions moving single values.
mod x86_gather {
    use super::{Corners, GROUP, LevelMath, Real, prefetch};

    /// Runs the sweep if this CPU and these types have the gather path;
    /// false means the caller runs the general one.
    #[inline(always)]
    pub fn forward_level<T: Real, const F: usize, const DENSE: bool>(
        math: &LevelMath<T>,
        table: &[T],
        positions: &[[T; 3]],
        out: &mut [T],
    ) -> bool {
        #[cfg(target_arch = "x86_64")]
        {
            use std::any::TypeId;
            if F == 2 && TypeId::of::<T>() == TypeId::of::<f32>() && crate::isa::avx512() {
                // SAFETY: T is f32 (checked above), so the casts change
                // nothing but the static type; the CPU has AVX-512F/VL.
                unsafe {
                    let math = &*(math as *const LevelMath<T> as *const LevelMath<f32>);
                    let table =
                        std::slice::from_raw_parts(table.as_ptr() as *const f32, table.len());
                    let positions = std::slice::from_raw_parts(
                        positions.as_ptr() as *const [f32; 3],
                        positions.len(),
                    );
                    let out =
                        std::slice::from_raw_parts_mut(out.as_mut_ptr() as *mut f32, out.len());
                    forward_f32x2::<DENSE>(math, table, positions, out);
                }
                return true;
            }
        }
        let _ = (math, table, positions, out);
        false
    }

    /// As `for_each_group` with the gather of a full group written out,
    /// so everything runs with AVX-512 enabled.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f,avx512vl,avx512dq,avx512bw,avx2,fma,bmi1,bmi2")]
    fn forward_f32x2<const DENSE: bool>(
        math: &LevelMath<f32>,
        table: &[f32],
        positions: &[[f32; 3]],
        out: &mut [f32],
    ) {
        const F: usize = 2;
        assert_eq!(out.len(), positions.len() * F);
        let base = table.as_ptr();
        let mut corners = [Corners::new(), Corners::new()];
        let mut groups = positions.chunks(GROUP);
        let Some(first) = groups.next() else { return };
        math.corners::<DENSE>(first, &mut corners[0]);
        let mut len = first.len();
        let mut start = 0;
        let mut current = 0;
        loop {
            let upcoming = groups.next();
            if let Some(group) = upcoming {
                let next = &mut corners[1 - current];
                math.corners::<DENSE>(group, next);
                for index in &next.index {
                    for &i in &index[..group.len()] {
                        prefetch(base, i as usize * F);
                    }
                }
            }
            let group = &corners[current];
            let out = &mut out[start * F..(start + len) * F];
            if len == GROUP {
                // SAFETY: the indices are entries of the level (LevelMath
                // keeps them below the level's entry count), so every
                // gathered pair lies inside `table`; `out` holds 32 values.
                unsafe { gather_group(base, group, out.as_mut_ptr()) };
            } else {
                for (k, value) in out.chunks_exact_mut(F).enumerate() {
                    let mut sum = [0.0f32; F];
                    for c in 0..8 {
                        let entry = &table[group.index[c][k] as usize * F..][..F];
                        for f in 0..F {
                            sum[f] += group.weight[c][k] * entry[f];
                        }
                    }
                    value.copy_from_slice(&sum);
                }
            }
            let Some(group) = upcoming else { return };
            start += len;
            len = group.len();
            current = 1 - current;
        }
    }

    /// The two features of a full group of samples, each the sum over the
    /// eight corners' weights times entries, into `out`.
    ///
    /// # Safety
    /// Every index of `corners` must name a pair of floats inside `table`
    /// (index < entries), and `out` must be writable for 32 floats.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f,avx512vl,avx512dq,avx512bw,avx2,fma")]
    unsafe fn gather_group(table: *const f32, corners: &Corners<f32>, out: *mut f32) {
        use std::arch::x86_64::*;
        const _: () = assert!(GROUP == 16);
        // SAFETY: the instructions are enabled on this function; the
        // unaligned loads read the 16 indices and weights of a corner
        // (GROUP = 16), the gathers 8-byte pairs at indices inside
        // `table`, and the stores write `out`'s 32 floats: the contract.
        unsafe {
            // Lane j of the low (high) half takes weight j / 2 (8 + j / 2):
            // each weight is repeated for the two features of its sample.
            let dup_lo = _mm512_set_epi32(7, 7, 6, 6, 5, 5, 4, 4, 3, 3, 2, 2, 1, 1, 0, 0);
            let dup_hi =
                _mm512_set_epi32(15, 15, 14, 14, 13, 13, 12, 12, 11, 11, 10, 10, 9, 9, 8, 8);
            let pairs = table as *const f64;
            let mut lo = _mm512_setzero_ps();
            let mut hi = _mm512_setzero_ps();
            for c in 0..8 {
                let index = _mm512_loadu_si512(corners.index[c].as_ptr() as *const __m512i);
                let index_lo = _mm512_castsi512_si256(index);
                let index_hi = _mm512_extracti64x4_epi64::<1>(index);
                let entries_lo = _mm512_castpd_ps(_mm512_i32gather_pd::<8>(index_lo, pairs));
                let entries_hi = _mm512_castpd_ps(_mm512_i32gather_pd::<8>(index_hi, pairs));
                let weight = _mm512_loadu_ps(corners.weight[c].as_ptr());
                let weight_lo = _mm512_permutexvar_ps(dup_lo, weight);
                let weight_hi = _mm512_permutexvar_ps(dup_hi, weight);
                lo = _mm512_add_ps(lo, _mm512_mul_ps(weight_lo, entries_lo));
                hi = _mm512_add_ps(hi, _mm512_mul_ps(weight_hi, entries_hi));
            }
            _mm512_storeu_ps(out, lo);
            _mm512_storeu_ps(out.add(16), hi);
        }
    }
}

#[cfg(test)]
mod tests;
