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

use crate::field::ngp::HashGridConfig;

/// π₁, π₂, π₃ of the spatial hash (paper, section 3, eq. 4). π₁ = 1 keeps
/// neighbouring x in neighbouring entries, which helps the cache.
pub const HASH_PRIMES: [u32; 3] = [1, 2_654_435_761, 805_459_861];

/// The spatial hash before the reduction mod T, with wrapping 32-bit
/// multiplication as in the paper's implementation.
#[inline(always)]
pub fn spatial_hash(x: u32, y: u32, z: u32) -> u32 {
    x.wrapping_mul(HASH_PRIMES[0]) ^ y.wrapping_mul(HASH_PRIMES[1]) ^ z.wrapping_mul(HASH_PRIMES[2])
}

/// Feature counts the stage is compiled for (tiny-cuda-nn supports the same
/// set); the paper uses F = 2.
pub const SUPPORTED_FEATURES: [u32; 4] = [1, 2, 4, 8];

/// Where one level lives in the parameter array.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct LevelLayout {
    /// N_l: cells per side; the grid has N_l + 1 vertices per side.
    pub resolution: u32,
    /// Index of the level's first entry (multiply by F for the first
    /// parameter).
    pub offset: usize,
    /// Entries the level stores: (N_l + 1)³ when dense, T when hashed.
    pub entries: usize,
    /// Dense (one entry per vertex) rather than hashed.
    pub dense: bool,
}

/// The levels of a hash grid and where their entries are.
#[derive(Debug, Clone, PartialEq)]
pub struct HashGridLayout {
    config: HashGridConfig,
    levels: Vec<LevelLayout>,
    entries: usize,
}

impl HashGridLayout {
    pub fn new(config: &HashGridConfig) -> Self {
        assert!(config.levels >= 1, "a hash grid needs at least one level");
        assert!(config.base_resolution >= 1, "N_min must be at least 1");
        assert!(
            SUPPORTED_FEATURES.contains(&config.features_per_level),
            "features per level must be one of {SUPPORTED_FEATURES:?}, got {}",
            config.features_per_level
        );
        assert!(config.log2_table_size <= 31, "T must fit in u32");
        assert!(
            config.extent.is_finite() && config.extent > 0.0,
            "the grid's box must have a positive side, got {}",
            config.extent
        );
        let table_size = config.table_size();
        let growth = config.growth_factor();
        let mut levels = Vec::with_capacity(config.levels as usize);
        let mut offset = 0;
        for l in 0..config.levels {
            // The relative nudge keeps N_min · b^(L−1), which is N_max in exact
            // arithmetic, from flooring to N_max − 1 after rounding.
            let exact = config.base_resolution as f64 * growth.powi(l as i32);
            let resolution = (exact * (1.0 + 1e-12)).floor() as u32;
            let vertices = (resolution as u64 + 1).pow(3);
            let dense = vertices <= table_size as u64;
            let entries = if dense { vertices as usize } else { table_size };
            levels.push(LevelLayout {
                resolution,
                offset,
                entries,
                dense,
            });
            offset += entries;
        }
        Self {
            config: *config,
            levels,
            entries: offset,
        }
    }

    pub fn config(&self) -> &HashGridConfig {
        &self.config
    }

    pub fn levels(&self) -> &[LevelLayout] {
        &self.levels
    }

    pub fn features(&self) -> usize {
        self.config.features_per_level as usize
    }

    /// Entries over all levels.
    pub fn entry_count(&self) -> usize {
        self.entries
    }

    /// Parameters over all levels: entries × F.
    pub fn param_count(&self) -> usize {
        self.entries * self.features()
    }

    /// Encoded width: L · F.
    pub fn output_width(&self) -> usize {
        self.config.output_width()
    }
}

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

/// Starting parameters: each uniform in ±`init_range` (paper, section 4),
/// from a counter-based generator, so the result depends only on `seed` and
/// not on the number of threads.
pub fn init_params(layout: &HashGridLayout, seed: u64) -> Vec<f32> {
    let range = layout.config.init_range;
    let key = splitmix64(seed ^ 0x6861_7368_6772_6964); // "hashgrid"
    let mut params = vec![0.0f32; layout.param_count()];
    params
        .par_chunks_mut(1 << 14)
        .enumerate()
        .for_each(|(chunk, values)| {
            let start = (chunk << 14) as u64;
            for (i, value) in values.iter_mut().enumerate() {
                let bits = splitmix64(key.wrapping_add(start + i as u64));
                // 24 random bits give every f32 in [0, 1) on a 2^-24 grid.
                let unit = (bits >> 40) as f32 * (1.0 / (1u64 << 24) as f32);
                *value = (2.0 * unit - 1.0) * range;
            }
        });
    params
}

/// SplitMix64 (Steele, Lea, Flood 2014): a bijective 64-bit mixer, good
/// enough to turn a counter into independent-looking uniform bits.
fn splitmix64(x: u64) -> u64 {
    let mut z = x.wrapping_add(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
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
        let (box_min, inverse_extent) = layout.config.box_mapping();
        let real = |v: f64| T::from(v).expect("a finite box");
        Self {
            box_min: real(box_min),
            inverse_extent: real(inverse_extent),
            scale: T::from_index(level.resolution),
            last_cell: level.resolution - 1,
            stride_y: side,
            stride_z: if level.dense { side * side } else { 0 },
            mask: (layout.config.table_size() - 1) as u32,
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
        .levels
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
    let mut tasks: Vec<(&LevelLayout, &[T], &mut [T])> = Vec::with_capacity(layout.levels.len());
    let mut rest = d_params;
    for (level, level_d_out) in layout
        .levels
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
                if std::is_x86_feature_detected!("avx512f") && std::is_x86_feature_detected!("avx512vl") {
                    // SAFETY: the CPU has the features the function is compiled for.
                    return unsafe { $avx512::<T, F, DENSE>($($arg),*) };
                }
                if std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma") {
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
            if F == 2
                && TypeId::of::<T>() == TypeId::of::<f32>()
                && std::is_x86_feature_detected!("avx512f")
                && std::is_x86_feature_detected!("avx512vl")
            {
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

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f,avx512vl,avx512dq,avx512bw,avx2,fma")]
    unsafe fn gather_group(table: *const f32, corners: &Corners<f32>, out: *mut f32) {
        use std::arch::x86_64::*;
        const _: () = assert!(GROUP == 16);
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
mod tests {
    use super::*;

    /// A small deterministic stream of uniforms in [0, 1) for tests.
    struct Uniforms(u64);

    impl Uniforms {
        fn next(&mut self) -> f64 {
            self.0 += 1;
            (splitmix64(self.0) >> 11) as f64 / (1u64 << 53) as f64
        }

        fn symmetric(&mut self) -> f64 {
            2.0 * self.next() - 1.0
        }

        fn position(&mut self) -> [f64; 3] {
            [self.next(), self.next(), self.next()]
        }
    }

    /// Three levels, the first dense and the others hashed into a table small
    /// enough that vertices collide: every code path in a few thousand
    /// parameters.
    fn small_config() -> HashGridConfig {
        HashGridConfig {
            levels: 3,
            features_per_level: 2,
            log2_table_size: 8,
            base_resolution: 4,
            finest_resolution: 16,
            init_range: 1.0,
            extent: 1.0,
        }
    }

    fn random_params(layout: &HashGridLayout, seed: u64) -> Vec<f64> {
        let mut u = Uniforms(seed);
        (0..layout.param_count()).map(|_| u.symmetric()).collect()
    }

    /// Coordinates that sit on faces, vertices and cell boundaries of every
    /// level, and a few just inside the faces.
    fn hard_coordinates(layout: &HashGridLayout) -> Vec<f64> {
        let mut values = vec![0.0, 1.0, 0.5, f64::EPSILON, 1.0 - f64::EPSILON, 1e-30];
        for level in layout.levels() {
            let n = level.resolution as f64;
            values.extend([1.0 / n, (n - 1.0) / n, (n / 2.0).floor() / n, 1.0 - 0.5 / n]);
        }
        values
    }

    fn hard_positions(layout: &HashGridLayout) -> Vec<[f64; 3]> {
        let values = hard_coordinates(layout);
        let mut positions = Vec::new();
        for (i, &x) in values.iter().enumerate() {
            for (j, &y) in values.iter().enumerate() {
                let z = values[(i * 7 + j * 3) % values.len()];
                positions.push([x, y, z]);
            }
        }
        positions
    }

    #[test]
    fn hash_matches_hand_computed_values() {
        assert_eq!(spatial_hash(0, 0, 0), 0);
        assert_eq!(spatial_hash(1, 0, 0), 1);
        assert_eq!(spatial_hash(0, 1, 0), 2_654_435_761);
        assert_eq!(spatial_hash(0, 0, 1), 805_459_861);
        // 2 · 2654435761 = 5308871522 wraps to 5308871522 − 2^32.
        assert_eq!(spatial_hash(0, 2, 0), 1_013_904_226);
        // 0x9E3779B1 ⊕ 0x30025795 ⊕ 1 = 0xAE352E25.
        assert_eq!(spatial_hash(1, 1, 1), 0xAE35_2E25);
        // 5·π₂ mod 2^32 = 387276917, 7·π₃ mod 2^32 = 1343251731;
        // 3 ⊕ 387276917 ⊕ 1343251731 = 1191511397, and mod 2^19 = 329061.
        assert_eq!(spatial_hash(3, 5, 7), 1_191_511_397);
        assert_eq!(spatial_hash(3, 5, 7) & ((1 << 19) - 1), 329_061);
    }

    #[test]
    fn paper_layout_has_five_dense_levels() {
        let layout = HashGridLayout::new(&HashGridConfig::paper(1.0));
        let resolutions: Vec<u32> = layout.levels().iter().map(|l| l.resolution).collect();
        // ⌊16 · b^l⌋ with b = 128^(1/15) ≈ 1.3819.
        assert_eq!(
            resolutions,
            [
                16, 22, 30, 42, 58, 80, 111, 153, 212, 294, 406, 561, 776, 1072, 1482, 2048
            ]
        );
        // 59³ = 205379 ≤ 2^19 = 524288 < 81³ = 531441: levels 0-4 are dense.
        let dense: Vec<bool> = layout.levels().iter().map(|l| l.dense).collect();
        assert_eq!(dense, [[true; 5].as_slice(), &[false; 11]].concat());
        let dense_entries =
            17usize.pow(3) + 23usize.pow(3) + 31usize.pow(3) + 43usize.pow(3) + 59usize.pow(3);
        assert_eq!(layout.entry_count(), dense_entries + 11 * (1 << 19));
        assert_eq!(layout.param_count(), 2 * layout.entry_count());
        assert_eq!(layout.output_width(), 32);
        let mut offset = 0;
        for level in layout.levels() {
            assert_eq!(level.offset, offset);
            offset += level.entries;
        }
        // The table stays under a 128 MiB storage binding (64 MiB at most).
        assert!(layout.param_count() * 4 <= 64 << 20);

        // aabb_scale 16: N_max = 32768, b = 2048^(1/15); the finest level must
        // reach N_max exactly although 16 · b^15 rounds to 32767.99…
        let layout = HashGridLayout::new(&HashGridConfig::paper(16.0));
        let levels = layout.levels();
        assert_eq!(levels[15].resolution, 32768);
        // 74³ = 405224 fits, 123³ does not: four dense levels.
        assert_eq!(levels[3].resolution, 73);
        assert_eq!(levels[4].resolution, 122);
        assert!(levels[3].dense && !levels[4].dense);
    }

    #[test]
    fn dense_and_hashed_vertices_read_their_entries() {
        // N = 16, 32, 64: vertex coordinates k/N are exact in binary, so a
        // vertex reads exactly one entry. 17³ ≤ 2^13 < 33³: level 0 dense.
        let config = HashGridConfig {
            levels: 3,
            features_per_level: 2,
            log2_table_size: 13,
            base_resolution: 16,
            finest_resolution: 64,
            init_range: 1.0,
            extent: 1.0,
        };
        let layout = HashGridLayout::new(&config);
        let levels = layout.levels();
        assert_eq!(
            levels
                .iter()
                .map(|l| (l.resolution, l.dense))
                .collect::<Vec<_>>(),
            [(16, true), (32, false), (64, false)]
        );
        let params = random_params(&layout, 3);
        let vertices = [
            [0u32, 0, 0],
            [16, 16, 16],
            [3, 9, 16],
            [16, 0, 5],
            [7, 7, 7],
        ];
        for v in vertices {
            let p = v.map(|c| c as f64 / 16.0);
            let mut out = [0.0; 6];
            encode(&layout, &params, &[p], &mut out);
            for (l, level) in levels.iter().enumerate() {
                let scale = level.resolution / 16;
                let [x, y, z] = v.map(|c| c * scale);
                let side = level.resolution + 1;
                let entry = if level.dense {
                    x + y * side + z * side * side
                } else {
                    spatial_hash(x, y, z) & ((1 << 13) - 1)
                } as usize;
                let want = &params[(level.offset + entry) * 2..][..2];
                assert_eq!(&out[2 * l..2 * l + 2], want, "vertex {v:?}, level {l}");
            }
        }
    }

    /// The corners of one position, through the group code the passes use.
    fn corners_of<T: Real>(math: &LevelMath<T>, dense: bool, p: [T; 3]) -> ([u32; 8], [T; 8]) {
        let mut corners = Corners::new();
        if dense {
            math.corners::<true>(&[p], &mut corners);
        } else {
            math.corners::<false>(&[p], &mut corners);
        }
        (corners.index.map(|i| i[0]), corners.weight.map(|w| w[0]))
    }

    /// The encoding written plainly from the paper's description, one
    /// sample, one level and one corner at a time.
    fn naive_encode(layout: &HashGridLayout, params: &[f64], p: [f64; 3]) -> Vec<f64> {
        let f = layout.features();
        let t = layout.config().table_size();
        let mut out = Vec::new();
        for level in layout.levels() {
            let n = level.resolution as f64;
            let x = p.map(|v| v.clamp(0.0, 1.0) * n);
            let cell = x.map(|v| (v.floor() as u32).min(level.resolution - 1));
            let mut features = vec![0.0; f];
            for dz in 0..2u32 {
                for dy in 0..2u32 {
                    for dx in 0..2u32 {
                        let v = [cell[0] + dx, cell[1] + dy, cell[2] + dz];
                        let weight: f64 = (0..3)
                            .map(|a| {
                                let frac = x[a] - cell[a] as f64;
                                if v[a] > cell[a] { frac } else { 1.0 - frac }
                            })
                            .product();
                        let side = level.resolution as usize + 1;
                        let entry = if level.dense {
                            v[0] as usize + v[1] as usize * side + v[2] as usize * side * side
                        } else {
                            spatial_hash(v[0], v[1], v[2]) as usize % t
                        };
                        for (k, feature) in features.iter_mut().enumerate() {
                            *feature += weight * params[(level.offset + entry) * f + k];
                        }
                    }
                }
            }
            out.extend(features);
        }
        out
    }

    #[test]
    fn encoding_matches_a_plain_transcription_of_the_paper() {
        let layout = HashGridLayout::new(&HashGridConfig::paper(1.0));
        let params: Vec<f64> = init_params(&layout, 12)
            .iter()
            .map(|&p| p as f64 * 1e4)
            .collect();
        let mut u = Uniforms(13);
        let mut positions: Vec<[f64; 3]> = (0..200).map(|_| u.position()).collect();
        positions.extend(hard_positions(&layout).into_iter().step_by(7));
        let width = layout.output_width();
        let mut out = vec![0.0; positions.len() * width];
        encode(&layout, &params, &positions, &mut out);
        for (p, row) in positions.iter().zip(out.chunks_exact(width)) {
            let want = naive_encode(&layout, &params, *p);
            for (l, (a, b)) in row.iter().zip(&want).enumerate() {
                // Same terms, summed in another order and with the weight
                // products associated differently: |θ| ≤ 1, so a few ε.
                assert!((a - b).abs() < 1e-14, "{p:?}, column {l}: {a} vs {b}");
            }
        }
    }

    #[test]
    fn faces_and_cell_boundaries_stay_in_the_table_with_unit_weights() {
        for config in [HashGridConfig::paper(1.0), small_config()] {
            let layout = HashGridLayout::new(&config);
            let positions = hard_positions(&layout);
            for level in layout.levels() {
                let math64 = LevelMath::<f64>::new(&layout, level);
                let math32 = LevelMath::<f32>::new(&layout, level);
                for p in &positions {
                    let (index, weight) = corners_of(&math64, level.dense, *p);
                    let sum: f64 = weight.iter().sum();
                    assert!((sum - 1.0).abs() < 1e-12, "{p:?}: Σw = {sum}");
                    assert!(weight.iter().all(|&w| (0.0..=1.0).contains(&w)));
                    assert!(
                        index.iter().all(|&i| (i as usize) < level.entries),
                        "{p:?}: {index:?}"
                    );

                    let p32 = p.map(|x| x as f32);
                    let (index, weight) = corners_of(&math32, level.dense, p32);
                    let sum: f32 = weight.iter().sum();
                    // Each weight is a product of three factors in [0, 1], each
                    // rounded once: Σw is within a few ulps of 1.
                    assert!((sum - 1.0).abs() < 1e-6, "{p32:?}: Σw = {sum}");
                    assert!(weight.iter().all(|&w| (0.0..=1.0).contains(&w)));
                    assert!(
                        index.iter().all(|&i| (i as usize) < level.entries),
                        "{p32:?}: {index:?}"
                    );
                }
            }
            // The far corner of the box is the last vertex of a dense level.
            let level = layout.levels()[0];
            let (index, weight) =
                corners_of(&LevelMath::<f32>::new(&layout, &level), true, [1.0; 3]);
            assert_eq!(weight[7], 1.0);
            assert_eq!(index[7] as usize, level.entries - 1);
        }
    }

    #[test]
    fn positions_outside_the_box_are_clamped() {
        let layout = HashGridLayout::new(&HashGridConfig::paper(1.0));
        let params = init_params(&layout, 11);
        let width = layout.output_width();
        let cases: [([f32; 3], [f32; 3]); 6] = [
            ([-1e-7, 0.3, 0.7], [0.0, 0.3, 0.7]),
            ([1.0 + 1e-7, 0.3, 1.0 + 2e-7], [1.0, 0.3, 1.0]),
            ([-5.0, 7.0, 0.25], [0.0, 1.0, 0.25]),
            ([f32::NEG_INFINITY, f32::INFINITY, 0.5], [0.0, 1.0, 0.5]),
            ([f32::NAN, 0.5, 0.5], [0.0, 0.5, 0.5]),
            ([0.2, 0.4, -f32::MIN_POSITIVE], [0.2, 0.4, 0.0]),
        ];
        let outside: Vec<[f32; 3]> = cases.iter().map(|c| c.0).collect();
        let inside: Vec<[f32; 3]> = cases.iter().map(|c| c.1).collect();
        let mut a = vec![0.0f32; cases.len() * width];
        let mut b = vec![0.0f32; cases.len() * width];
        encode(&layout, &params, &outside, &mut a);
        encode(&layout, &params, &inside, &mut b);
        assert!(a.iter().all(|v| v.is_finite()));
        assert_eq!(a, b);
    }

    /// A large scene's grid spans its whole box (side aabb_scale around the
    /// unit cube's centre), not the unit cube: a position x encodes as
    /// (x − box_min) / extent does on a unit-cube grid with the same tables,
    /// so points outside the unit cube but inside the box keep their own
    /// features (clamping them to the unit cube's faces made the whole far
    /// field of a large scene an extrusion of those faces), and only points
    /// outside the box are clamped.
    #[test]
    fn a_grid_spans_its_box() {
        let boxed = HashGridConfig::paper(8.0);
        assert_eq!(boxed.extent, 8.0);
        let unit = HashGridConfig {
            extent: 1.0,
            ..boxed
        };
        let (boxed, unit) = (HashGridLayout::new(&boxed), HashGridLayout::new(&unit));
        let params = init_params(&boxed, 3);
        let width = boxed.output_width();
        // Unit-cube coordinates; the box is [−3.5, 4.5]³, and −3.5 + 8k/16 is
        // exactly representable, so the mapped points are exact too.
        let positions: Vec<[f32; 3]> = vec![
            [0.5, 0.5, 0.5],
            [2.0, 0.5, 0.5],
            [3.0, 0.5, 0.5],
            [-3.0, 4.0, 1.25],
            [4.5, -3.5, 4.5],
            [9.0, 0.5, 0.5],
        ];
        let mapped: Vec<[f32; 3]> = positions
            .iter()
            .map(|p| p.map(|x| ((x + 3.5) / 8.0).clamp(0.0, 1.0)))
            .collect();
        let mut from_box = vec![0.0f32; positions.len() * width];
        let mut from_unit = vec![0.0f32; positions.len() * width];
        encode(&boxed, &params, &positions, &mut from_box);
        encode(&unit, &params, &mapped, &mut from_unit);
        assert_eq!(from_box, from_unit);
        let row = |i: usize| &from_box[i * width..(i + 1) * width];
        // Two points past the unit cube's face along x differ (they were
        // equal when the grid spanned the unit cube), as do the centre
        // and a point beyond it.
        assert_ne!(row(1), row(2));
        assert_ne!(row(0), row(1));
        // Past the box's face, the face's value.
        let face = [[4.5f32, 0.5, 0.5]];
        let mut on_face = vec![0.0f32; width];
        encode(&boxed, &params, &face, &mut on_face);
        assert_eq!(row(5), on_face.as_slice());
    }

    /// ⟨encode(θ, p), d_out⟩ as a function of θ.
    fn loss(layout: &HashGridLayout, params: &[f64], positions: &[[f64; 3]], d_out: &[f64]) -> f64 {
        let mut out = vec![0.0; d_out.len()];
        encode(layout, params, positions, &mut out);
        out.iter().zip(d_out).map(|(o, g)| o * g).sum()
    }

    #[test]
    fn gradients_match_central_differences() {
        let layout = HashGridLayout::new(&small_config());
        let mut u = Uniforms(21);
        let mut positions: Vec<[f64; 3]> = (0..40).map(|_| u.position()).collect();
        positions.extend(hard_positions(&layout).into_iter().step_by(17));
        let d_out: Vec<f64> = (0..positions.len() * layout.output_width())
            .map(|_| u.symmetric())
            .collect();
        let mut params = random_params(&layout, 5);
        let mut d_params = vec![0.0; layout.param_count()];
        encode_backward(&layout, &positions, &d_out, &mut d_params);
        let mut touched = 0;
        for i in 0..params.len() {
            // The loss is linear in θ, so a central difference has no
            // truncation error at any step: h = 1 leaves only rounding,
            // about ε · Σ|terms| ≈ 1e-16 · 100.
            let h = 1.0;
            let saved = params[i];
            params[i] = saved + h;
            let plus = loss(&layout, &params, &positions, &d_out);
            params[i] = saved - h;
            let minus = loss(&layout, &params, &positions, &d_out);
            params[i] = saved;
            let numeric = (plus - minus) / (2.0 * h);
            assert!(
                (d_params[i] - numeric).abs() < 1e-9,
                "param {i}: analytic {} numeric {numeric}",
                d_params[i]
            );
            touched += (d_params[i] != 0.0) as usize;
        }
        // The check means something only if many entries got gradient.
        assert!(touched > params.len() / 4, "{touched} of {}", params.len());
    }

    #[test]
    fn gradients_match_central_differences_on_the_paper_grid() {
        let layout = HashGridLayout::new(&HashGridConfig::paper(1.0));
        let mut u = Uniforms(31);
        let mut positions: Vec<[f64; 3]> = (0..12).map(|_| u.position()).collect();
        positions.extend([[0.0; 3], [1.0; 3], [1.0, 0.0, 0.5]]);
        let d_out: Vec<f64> = (0..positions.len() * layout.output_width())
            .map(|_| u.symmetric())
            .collect();
        let mut params: Vec<f64> = init_params(&layout, 2)
            .iter()
            .map(|&p| p as f64 * 1e4)
            .collect();
        let mut d_params = vec![0.0; layout.param_count()];
        encode_backward(&layout, &positions, &d_out, &mut d_params);
        // Every entry that got gradient (all 16 levels, dense and hashed),
        // and as many that got none.
        let touched: Vec<usize> = (0..params.len()).filter(|&i| d_params[i] != 0.0).collect();
        assert!(touched.len() > 8 * 16, "{}", touched.len());
        let count = params.len() as f64;
        let untouched: Vec<usize> = (0..touched.len())
            .map(|_| (u.next() * count) as usize)
            .collect();
        for i in touched.into_iter().chain(untouched) {
            // Linear in θ: h = 1 is exact up to rounding (see above).
            let saved = params[i];
            params[i] = saved + 1.0;
            let plus = loss(&layout, &params, &positions, &d_out);
            params[i] = saved - 1.0;
            let minus = loss(&layout, &params, &positions, &d_out);
            params[i] = saved;
            let numeric = (plus - minus) / 2.0;
            assert!(
                (d_params[i] - numeric).abs() < 1e-9,
                "param {i}: analytic {} numeric {numeric}",
                d_params[i]
            );
        }
    }

    #[test]
    fn gather_path_gives_the_portable_bits() {
        // f32 with F = 2 takes the AVX-512 gather path where the CPU has
        // it; every level must match the portable loop bit for bit, on
        // full groups, a short last group, faces, corners and NaN.
        for config in [HashGridConfig::paper(1.0), small_config()] {
            let layout = HashGridLayout::new(&config);
            let params = init_params(&layout, 3);
            let mut u = Uniforms(41);
            let mut positions: Vec<[f32; 3]> = hard_positions(&layout)
                .iter()
                .map(|p| p.map(|x| x as f32))
                .collect();
            positions.extend((0..1000).map(|_| u.position().map(|x| x as f32)));
            positions.push([f32::NAN, 1.0, -0.5]);
            let n = positions.len();
            assert_ne!(n % GROUP, 0, "a short last group");
            let width = layout.output_width();
            let mut out = vec![0.0f32; n * width];
            encode(&layout, &params, &positions, &mut out);
            for (l, level) in layout.levels().iter().enumerate() {
                let math = LevelMath::<f32>::new(&layout, level);
                let table = &params[level.offset * 2..][..level.entries * 2];
                let mut expected = vec![0.0f32; n * 2];
                if level.dense {
                    forward_level_portable::<f32, 2, true>(&math, table, &positions, &mut expected);
                } else {
                    forward_level_portable::<f32, 2, false>(
                        &math,
                        table,
                        &positions,
                        &mut expected,
                    );
                }
                for (k, pair) in expected.chunks_exact(2).enumerate() {
                    let got = &out[k * width + 2 * l..][..2];
                    assert_eq!(
                        [got[0].to_bits(), got[1].to_bits()],
                        [pair[0].to_bits(), pair[1].to_bits()],
                        "level {l} sample {k}"
                    );
                }
            }
        }
    }

    #[test]
    fn backward_accumulates() {
        let layout = HashGridLayout::new(&small_config());
        let mut u = Uniforms(8);
        let positions: Vec<[f64; 3]> = (0..50).map(|_| u.position()).collect();
        let d_out: Vec<f64> = (0..50 * layout.output_width())
            .map(|_| u.symmetric())
            .collect();
        let mut fresh = vec![0.0; layout.param_count()];
        encode_backward(&layout, &positions, &d_out, &mut fresh);
        let before = random_params(&layout, 9);
        let mut accumulated = before.clone();
        encode_backward(&layout, &positions, &d_out, &mut accumulated);
        for ((b, f), a) in before.iter().zip(&fresh).zip(&accumulated) {
            // Same terms, summed onto a different start: equal up to the
            // rounding of a few dozen additions of O(1) values.
            assert!((a - (b + f)).abs() < 1e-13, "{a} vs {b} + {f}");
        }
        // The writing variant gives the fresh gradient whatever was there.
        let mut written = before.clone();
        encode_gradient_with_scratch(&layout, &positions, &d_out, &mut written, &mut Vec::new());
        assert_eq!(written, fresh);
        let mut empty = before;
        encode_gradient_with_scratch(&layout, &[], &[], &mut empty, &mut Vec::new());
        assert!(empty.iter().all(|&g| g == 0.0));
    }

    /// ⟨encode(θ, p), g⟩ and ⟨θ, backward(g)⟩ (both accumulated in f64), and
    /// the scale of either: ⟨encode(|θ|, p), |g|⟩ = Σ over all terms of
    /// |w · θ · g|, since the weights are ≥ 0.
    fn adjoint_sides<T: Real>(
        layout: &HashGridLayout,
        params: &[T],
        positions: &[[T; 3]],
        d_out: &[T],
    ) -> (f64, f64, f64) {
        let to64 = |x: T| x.to_f64().unwrap();
        let mut out = vec![T::zero(); d_out.len()];
        encode(layout, params, positions, &mut out);
        let forward: f64 = out
            .iter()
            .zip(d_out)
            .map(|(&o, &g)| to64(o) * to64(g))
            .sum();
        let mut d_params = vec![T::zero(); params.len()];
        encode_backward(layout, positions, d_out, &mut d_params);
        let backward: f64 = params
            .iter()
            .zip(&d_params)
            .map(|(&p, &d)| to64(p) * to64(d))
            .sum();
        let abs_params: Vec<T> = params.iter().map(|p| p.abs()).collect();
        encode(layout, &abs_params, positions, &mut out);
        let scale: f64 = out
            .iter()
            .zip(d_out)
            .map(|(&o, &g)| to64(o) * to64(g).abs())
            .sum();
        (forward, backward, scale)
    }

    #[test]
    fn backward_is_the_transpose_of_forward() {
        let layout = HashGridLayout::new(&HashGridConfig::paper(1.0));
        let mut u = Uniforms(99);
        let mut positions: Vec<[f64; 3]> = (0..4096).map(|_| u.position()).collect();
        positions.extend(hard_positions(&layout).into_iter().step_by(5));
        let d_out: Vec<f64> = (0..positions.len() * layout.output_width())
            .map(|_| u.symmetric())
            .collect();
        let params: Vec<f64> = init_params(&layout, 4)
            .iter()
            .map(|&p| p as f64 * 1e4)
            .collect();

        // f64: every output and every gradient entry is a short sum (8 terms;
        // at most a few hundred contributions per coarse entry), so both
        // sides agree to a few hundred ε of the scale.
        let (forward, backward, scale) = adjoint_sides(&layout, &params, &positions, &d_out);
        assert!(scale > 1.0);
        let error = (forward - backward).abs() / scale;
        eprintln!("adjoint identity, f64: {error:e} of the scale");
        assert!(
            error < 1e-12,
            "f64: {forward} vs {backward} (scale {scale}): {error:e}"
        );

        // f32: the same sums rounded to 2^-24 each; random rounding errors
        // partly cancel, but the bound is ~ (contributions per entry) · ε.
        let params32: Vec<f32> = params.iter().map(|&p| p as f32).collect();
        let positions32: Vec<[f32; 3]> = positions.iter().map(|p| p.map(|x| x as f32)).collect();
        let d_out32: Vec<f32> = d_out.iter().map(|&g| g as f32).collect();
        let (forward, backward, scale) = adjoint_sides(&layout, &params32, &positions32, &d_out32);
        let error = (forward - backward).abs() / scale;
        eprintln!("adjoint identity, f32: {error:e} of the scale");
        assert!(
            error < 1e-6,
            "f32: {forward} vs {backward} (scale {scale}): {error:e}"
        );
    }

    #[test]
    fn f32_and_f64_encodings_agree() {
        let layout = HashGridLayout::new(&HashGridConfig::paper(1.0));
        let params = init_params(&layout, 6);
        let params64: Vec<f64> = params.iter().map(|&p| p as f64).collect();
        let mut u = Uniforms(17);
        let positions: Vec<[f32; 3]> = (0..3000).map(|_| u.position().map(|x| x as f32)).collect();
        let positions64: Vec<[f64; 3]> = positions.iter().map(|p| p.map(|x| x as f64)).collect();
        let width = layout.output_width();
        let mut out = vec![0.0f32; positions.len() * width];
        let mut out64 = vec![0.0f64; positions.len() * width];
        encode(&layout, &params, &positions, &mut out);
        encode(&layout, &params64, &positions64, &mut out64);
        for (a, b) in out.iter().zip(&out64) {
            // |θ| ≤ 1e-4 and the weights sum to 1; the f32 fractional part of
            // x · N carries an absolute error up to ε · N_max ≈ 2.4e-4, which
            // moves the output by at most that times the spread of θ.
            assert!(
                (*a as f64 - b).abs() < 1e-4 * 2.4e-4 * 4.0 + 1e-11,
                "{a} vs {b}"
            );
        }
    }

    #[test]
    fn init_is_deterministic_and_in_range() {
        let layout = HashGridLayout::new(&small_config());
        let a = init_params(&layout, 1);
        assert_eq!(a, init_params(&layout, 1));
        assert_ne!(a, init_params(&layout, 2));
        let layout = HashGridLayout::new(&HashGridConfig::paper(1.0));
        let params = init_params(&layout, 1);
        let r = layout.config().init_range;
        assert!(params.iter().all(|&p| p >= -r && p < r));
        let n = params.len() as f64;
        let mean = params.iter().map(|&p| p as f64).sum::<f64>() / n;
        let mean_square = params.iter().map(|&p| (p as f64).powi(2)).sum::<f64>() / n;
        // U(−r, r): mean 0 with standard error r/√(3n) ≈ 1.7e-8; variance r²/3.
        assert!(mean.abs() < 1e-7, "{mean}");
        assert!((mean_square / (r as f64).powi(2) - 1.0 / 3.0).abs() < 1e-3);
    }

    /// Throughput for a training batch of 2^18 samples, on the paper's grid
    /// and, to show what the arithmetic alone costs, on one whose tables fit
    /// in L1. Run with `cargo test --release --lib
    /// hash_grid::tests::throughput -- --ignored --nocapture`; it prints, it
    /// does not assert.
    #[test]
    #[ignore]
    fn throughput() {
        use crate::field::ngp::{MarchConfig, SAMPLES_PER_BATCH};
        let mut u = Uniforms(1);
        let scattered: Vec<[f32; 3]> = (0..SAMPLES_PER_BATCH)
            .map(|_| u.position().map(|x| x as f32))
            .collect();
        // Rays of 64 consecutive samples at the paper's step, as the ray
        // marcher emits them.
        let step = MarchConfig::PAPER.step as f64;
        let mut marched = Vec::with_capacity(SAMPLES_PER_BATCH);
        while marched.len() < SAMPLES_PER_BATCH {
            let origin = u.position();
            let d = [u.symmetric(), u.symmetric(), u.symmetric()];
            let norm = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            for k in 0..64 {
                let t = k as f64 * step / norm;
                marched.push([0, 1, 2].map(|a| (origin[a] + t * d[a]).clamp(0.0, 1.0) as f32));
            }
        }
        for log2_table_size in [19, 10] {
            let layout = HashGridLayout::new(&HashGridConfig {
                log2_table_size,
                ..HashGridConfig::paper(1.0)
            });
            let params = init_params(&layout, 1);
            let width = layout.output_width();
            let d_out: Vec<f32> = (0..SAMPLES_PER_BATCH * width)
                .map(|_| u.symmetric() as f32)
                .collect();
            let mut out = vec![0.0f32; SAMPLES_PER_BATCH * width];
            let mut d_params = vec![0.0f32; layout.param_count()];
            let mut scratch = Vec::new();
            for (name, positions) in [("scattered", &scattered), ("marched", &marched)] {
                let mut forward = Timing::default();
                let mut backward = Timing::default();
                for _ in 0..7 {
                    let start = Timing::now();
                    encode_with_scratch(&layout, &params, positions, &mut out, &mut scratch);
                    forward = forward.best(start.elapsed());
                    let start = Timing::now();
                    encode_backward_with_scratch(
                        &layout,
                        positions,
                        &d_out,
                        &mut d_params,
                        &mut scratch,
                    );
                    backward = backward.best(start.elapsed());
                }
                let n = SAMPLES_PER_BATCH as f64 / 1e6;
                println!(
                    "T = 2^{log2_table_size}, {name}: forward {:.2} M samples/s ({:.2} M per cpu-second), \
                     backward {:.2} M samples/s ({:.2} M per cpu-second), {} threads",
                    n / forward.wall,
                    n / forward.cpu,
                    n / backward.wall,
                    n / backward.cpu,
                    rayon::current_num_threads()
                );
            }
        }
    }

    /// Wall time and the CPU time of all the process's threads, so that a
    /// measurement on a machine shared with other jobs still says what the
    /// code costs.
    #[derive(Clone, Copy)]
    struct Timing {
        wall: f64,
        cpu: f64,
    }

    impl Default for Timing {
        fn default() -> Self {
            Self {
                wall: f64::MAX,
                cpu: f64::MAX,
            }
        }
    }

    impl Timing {
        fn now() -> (std::time::Instant, f64) {
            (std::time::Instant::now(), process_cpu_seconds())
        }

        fn best(self, other: Self) -> Self {
            Self {
                wall: self.wall.min(other.wall),
                cpu: self.cpu.min(other.cpu),
            }
        }
    }

    trait Elapsed {
        fn elapsed(&self) -> Timing;
    }

    impl Elapsed for (std::time::Instant, f64) {
        fn elapsed(&self) -> Timing {
            Timing {
                wall: self.0.elapsed().as_secs_f64(),
                cpu: process_cpu_seconds() - self.1,
            }
        }
    }

    /// The first field of each thread's schedstat is its time on a CPU, in
    /// nanoseconds (Linux only; elsewhere the CPU figure is meaningless).
    fn process_cpu_seconds() -> f64 {
        let Ok(tasks) = std::fs::read_dir("/proc/self/task") else {
            return 0.0;
        };
        let mut total = 0u64;
        for task in tasks.flatten() {
            if let Ok(stat) = std::fs::read_to_string(task.path().join("schedstat")) {
                total += stat
                    .split_whitespace()
                    .next()
                    .and_then(|v| v.parse::<u64>().ok())
                    .unwrap_or(0);
            }
        }
        total as f64 * 1e-9
    }
}
