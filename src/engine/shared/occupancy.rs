//! Instant-NGP's occupancy grid (Müller et al. 2022, appendix E.2; instant-ngp
//! testbed): which cells of the unit cube hold anything, so ray marching can
//! skip empty space.
//!
//! Geometry. Cascade k (0 ≤ k < K) is the cube of side 2^k centred at
//! (0.5, 0.5, 0.5), split into `resolution`³ cells; cascade 0 is the unit
//! cube itself. A position belongs to the finest cascade that contains it
//! (the testbed's `mip_from_pos`): cascade k holds max|p − 0.5| < 2^(k−1),
//! the outermost cascade takes everything beyond. Cells are laid out
//! x-fastest, `x + res·(y + res·z)`, cascade after cascade; the bitfield has
//! one bit per cell in u32 words in the same order (the gpu shaders read the
//! same words).
//!
//! Values. Each cell stores an optical thickness, σ times the smallest march
//! step scaled by the cascade (√3/1024 · 2^k), as an EMA: at every update all
//! cells decay by 0.95 and each freshly sampled cell takes
//! max(decayed, σ_new · step) (the testbed's `ema_grid_samples_nerf` after its
//! max-splat). A cell is occupied where its value exceeds
//! min(0.01, mean of the values of cascade 0) (testbed `grid_to_bitfield`,
//! NERF_MIN_OPTICAL_THICKNESS). Cells no update has reached since the grid
//! was made or [`OccupancyGrid::mark_untrained`] hold [`UNTRAINED`] and count
//! as occupied, so training starts with every ray sampled everywhere.
//!
//! Updates (every 16 steps, the caller asks [`OccupancyGrid::is_due`]; the
//! viewer's smaller batch counts steps of `zrak train`'s, see
//! [`GridPace`]): during the first 256 steps every cell of every cascade is
//! sampled once; afterwards
//! a quarter of each cascade's cells (distinct, at random) plus as many draws
//! (with replacement) from the cells that are occupied before the update.
//! Each sample evaluates the density at a uniformly random point inside its
//! cell. When the grid holds no occupied cell at all (a bad step drove every
//! density to zero), the update samples every cell again, as during warm-up,
//! so the grid recovers wherever the density has risen.

use glam::Vec3;
use rayon::prelude::*;

use crate::field::common::{MarchConfig, OccupancyConfig};

/// Density evaluations per call of the density function unless the driver
/// sets its batch's size: 2^18, Instant-NGP's batch (paper, section 5.4).
const DEFAULT_CHUNK: usize = 1 << 18;
use crate::scene::UnitCubeMapping;

/// The stored value of a cell that no update has sampled yet. Real values are
/// optical thicknesses, never negative, so any negative value means this.
pub const UNTRAINED: f32 = -1.0;

/// How many cells, in which cascades: everything needed to map a position
/// to its cell. Small and `Copy`, for hot loops.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct GridGeometry {
    /// Cells per side of each cascade (even, so cascade k−1 covers whole
    /// cells of cascade k).
    pub resolution: u32,
    /// K, the number of cascades.
    pub cascades: u32,
}

/// A cell: its cascade and integer coordinates inside that cascade.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Cell {
    pub cascade: u32,
    pub xyz: [u32; 3],
}

impl GridGeometry {
    pub fn new(resolution: u32, cascades: u32) -> Self {
        assert!(
            resolution >= 2 && resolution.is_multiple_of(2),
            "the occupancy grid needs an even resolution, got {resolution}"
        );
        assert!(
            (1..=16).contains(&cascades),
            "1 to 16 cascades, got {cascades}"
        );
        Self {
            resolution,
            cascades,
        }
    }

    pub fn cells_per_cascade(&self) -> usize {
        (self.resolution as usize).pow(3)
    }

    pub fn cell_count(&self) -> usize {
        self.cells_per_cascade() * self.cascades as usize
    }

    /// u32 words of the bitfield.
    pub fn bitfield_words(&self) -> usize {
        self.cell_count().div_ceil(32)
    }

    /// Half the side of the outermost cascade plus the offset 0.5: no
    /// coordinate inside the grid is larger in magnitude.
    pub fn max_coordinate(&self) -> f32 {
        0.5 + (1u32 << (self.cascades - 1)) as f32
    }

    /// The finest cascade containing `p`: the exponent e of
    /// max|p − 0.5| = m · 2^e with m in [0.5, 1) (frexp) gives cascade e + 1,
    /// clamped to the grid. Read from the float's bits, as the shaders do, so
    /// both engines agree exactly on points lying on a cascade's face (those
    /// belong to the coarser cascade).
    #[inline(always)]
    pub fn cascade_of(&self, p: Vec3) -> u32 {
        if self.cascades == 1 {
            return 0;
        }
        let q = (p - Vec3::splat(0.5)).abs();
        let m = q.x.max(q.y).max(q.z);
        let exponent = ((m.to_bits() >> 23) & 0xff) as i32 - 126;
        (exponent + 1).clamp(0, self.cascades as i32 - 1) as u32
    }

    /// Cells per unit length in `cascade`: res / 2^cascade (a power of two
    /// times res, so scaling by it is exact).
    #[inline(always)]
    pub fn cells_per_unit(&self, cascade: u32) -> f32 {
        self.resolution as f32 * power_of_two(-(cascade as i32))
    }

    /// The side of a cell of `cascade`: 2^cascade / res.
    #[inline(always)]
    pub fn cell_size(&self, cascade: u32) -> f32 {
        power_of_two(cascade as i32) / self.resolution as f32
    }

    /// The cell holding `p`. Points outside the outermost cascade, on its
    /// far faces, or not finite map to the nearest valid cell: the index is
    /// always inside the grid.
    #[inline(always)]
    pub fn cell_of(&self, p: Vec3) -> Cell {
        let cascade = self.cascade_of(p);
        let scale = self.cells_per_unit(cascade);
        let half = (self.resolution / 2) as f32;
        let top = self.resolution as i32 - 1;
        // `as i32` truncates towards zero and saturates (NaN gives 0); after
        // the clamp that equals floor for every input.
        let index = |x: f32| (((x - 0.5) * scale + half) as i32).clamp(0, top) as u32;
        Cell {
            cascade,
            xyz: [index(p.x), index(p.y), index(p.z)],
        }
    }

    /// Index of `cell` into the value array and the bitfield.
    #[inline(always)]
    pub fn linear_index(&self, cell: Cell) -> usize {
        let res = self.resolution as usize;
        let [x, y, z] = cell.xyz.map(|v| v as usize);
        cell.cascade as usize * self.cells_per_cascade() + x + res * (y + res * z)
    }

    /// The cell at `index` (inverse of [`Self::linear_index`]).
    pub fn cell_at(&self, index: usize) -> Cell {
        let res = self.resolution as usize;
        let per = self.cells_per_cascade();
        let local = index % per;
        Cell {
            cascade: (index / per) as u32,
            xyz: [
                (local % res) as u32,
                ((local / res) % res) as u32,
                (local / (res * res)) as u32,
            ],
        }
    }

    /// The lower corner of `cell` in unit coordinates; the cell's side is
    /// 1 / [`Self::cells_per_unit`].
    #[inline(always)]
    pub fn cell_min(&self, cell: Cell) -> Vec3 {
        let size = self.cell_size(cell.cascade);
        let half = (self.resolution / 2) as f32;
        let corner = |c: u32| (c as f32 - half) * size + 0.5;
        Vec3::new(
            corner(cell.xyz[0]),
            corner(cell.xyz[1]),
            corner(cell.xyz[2]),
        )
    }

    /// The centre of `cell` in unit coordinates.
    #[inline(always)]
    pub fn cell_centre(&self, cell: Cell) -> Vec3 {
        self.cell_min(cell) + Vec3::splat(0.5 * self.cell_size(cell.cascade))
    }
}

/// 2^e for small e, exactly, without a division or a libm call.
#[inline(always)]
fn power_of_two(e: i32) -> f32 {
    f32::from_bits(((127 + e) as u32) << 23)
}

/// Whether bit `index` is set.
#[inline(always)]
pub fn bit_is_set(bitfield: &[u32], index: usize) -> bool {
    (bitfield[index >> 5] >> (index & 31)) & 1 != 0
}

/// What one update did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct UpdateReport {
    /// Density evaluations made.
    pub samples: usize,
    /// Whether every cell was sampled (warm-up, or recovery from an empty
    /// grid).
    pub full: bool,
}

/// How often a driver's steps update the grid. The recipe's
/// `update_interval` and `warmup_steps` count steps of a reference batch:
/// the driver's own (every driver but the viewer's), or the one `zrak
/// train` takes on the engine (the viewer's, asked for with
/// `ModelRequest::with_grid_paced_by_samples`), which then updates after
/// as many samples
/// as those steps would train, not after as many of its own steps: a step
/// of a quarter batch updates every 64 steps instead of 16, and warms up
/// for 1024 steps instead of 256. Samples are counted as batches: step n
/// has trained n times its batch, so pacing needs no state beyond the
/// step (a model resumed at another batch counts its earlier steps at the
/// new one).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct GridPace {
    /// What a step of this driver trains (samples, or rays for a recipe
    /// that counts its batch in rays).
    pub step_batch: u64,
    /// What a step of the batch the recipe's intervals count trains, in the
    /// same unit.
    pub recipe_batch: u64,
}

impl GridPace {
    /// Steps of the batch the recipe's intervals count: the grid updates
    /// on the steps it always did.
    pub const RECIPE: Self = Self {
        step_batch: 1,
        recipe_batch: 1,
    };

    /// Whether a grid of `config` is updated at step `step`: the first
    /// step (0), and the first step after the samples trained reach each
    /// further multiple of `update_interval` recipe batches (the previous
    /// step's batch reached it).
    pub fn is_due(&self, config: &OccupancyConfig, step: u32) -> bool {
        let batch = self.step_batch.max(1);
        let every = u64::from(config.update_interval) * self.recipe_batch;
        match (u64::from(step) * batch).checked_rem(every) {
            Some(past) => past < batch,
            // No interval: the first step only, as `is_multiple_of(0)` says.
            None => step == 0,
        }
    }

    /// Whether step `step` is still in the warm-up of a grid of `config`
    /// (`warmup_steps` recipe batches).
    pub fn warming_up(&self, config: &OccupancyConfig, step: u32) -> bool {
        u64::from(step) * self.step_batch.max(1)
            < u64::from(config.warmup_steps) * self.recipe_batch
    }
}

/// The occupancy grid: stored optical thicknesses, the occupancy bitfield
/// built from them, and reusable workspaces for updates.
#[derive(Debug, Clone)]
pub struct OccupancyGrid {
    config: OccupancyConfig,
    geometry: GridGeometry,
    /// The smallest march step in unit coordinates (√3/1024 for the paper).
    min_step: f32,
    values: Vec<f32>,
    bitfield: Vec<u32>,
    threshold: f32,
    occupied: usize,
    /// Density evaluations per call of the density function.
    pub chunk: usize,
    /// How the driver's steps count towards the recipe's intervals.
    pub pace: GridPace,
    // Workspaces, kept between updates so updates do not allocate.
    sample_cells: Vec<u32>,
    sample_positions: Vec<f32>,
    sample_density: Vec<f32>,
    occupied_list: Vec<u32>,
    /// Bitmap of the uniformly chosen cells of one cascade.
    chosen: Vec<u32>,
    /// Draws per entry of `occupied_list`.
    draws: Vec<u32>,
}

impl OccupancyGrid {
    /// A grid with every cell untrained (all occupied).
    pub fn new(config: OccupancyConfig, cascades: u32, min_step: f32) -> Self {
        let geometry = GridGeometry::new(config.resolution, cascades);
        let mut grid = Self {
            config,
            geometry,
            min_step,
            values: vec![UNTRAINED; geometry.cell_count()],
            bitfield: vec![0; geometry.bitfield_words()],
            threshold: config.min_optical_thickness,
            occupied: 0,
            chunk: DEFAULT_CHUNK,
            pace: GridPace::RECIPE,
            sample_cells: Vec::new(),
            sample_positions: Vec::new(),
            sample_density: Vec::new(),
            occupied_list: Vec::new(),
            chosen: Vec::new(),
            draws: Vec::new(),
        };
        grid.build_bitfield();
        grid
    }

    /// The paper's grid for a scene: 128³ cells, as many cascades as its
    /// aabb_scale needs, optical thickness measured with √3/1024 steps.
    pub fn for_scene(mapping: &UnitCubeMapping) -> Self {
        Self::new(
            OccupancyConfig::PAPER,
            OccupancyConfig::cascades(mapping.aabb_scale),
            MarchConfig::PAPER.step,
        )
    }

    /// A grid holding `values` (e.g. from a checkpoint), bitfield rebuilt.
    pub fn from_values(
        config: OccupancyConfig,
        cascades: u32,
        min_step: f32,
        values: Vec<f32>,
    ) -> Self {
        let mut grid = Self::new(config, cascades, min_step);
        assert_eq!(
            values.len(),
            grid.values.len(),
            "occupancy values of the wrong size"
        );
        grid.values = values;
        grid.build_bitfield();
        grid
    }

    pub fn config(&self) -> &OccupancyConfig {
        &self.config
    }

    pub fn geometry(&self) -> GridGeometry {
        self.geometry
    }

    pub fn min_step(&self) -> f32 {
        self.min_step
    }

    /// Stored optical thicknesses ([`UNTRAINED`] where never sampled).
    pub fn values(&self) -> &[f32] {
        &self.values
    }

    /// Direct access for tests and checkpoints; call
    /// [`Self::build_bitfield`] after changing values.
    pub fn values_mut(&mut self) -> &mut [f32] {
        &mut self.values
    }

    /// One bit per cell, see the module documentation for the order.
    pub fn bitfield(&self) -> &[u32] {
        &self.bitfield
    }

    /// The threshold the bitfield was built with: min(0.01, mean).
    pub fn threshold(&self) -> f32 {
        self.threshold
    }

    pub fn occupied_count(&self) -> usize {
        self.occupied
    }

    /// Occupied cells over all cells, in [0, 1].
    pub fn occupancy_fraction(&self) -> f32 {
        self.occupied as f32 / self.values.len() as f32
    }

    pub fn is_occupied(&self, cell: Cell) -> bool {
        bit_is_set(&self.bitfield, self.geometry.linear_index(cell))
    }

    /// Whether the cell holding `p` (unit coordinates) is occupied.
    pub fn occupied_at(&self, p: Vec3) -> bool {
        self.is_occupied(self.geometry.cell_of(p))
    }

    /// Forgets every stored value: all cells untrained, hence occupied.
    pub fn mark_untrained(&mut self) {
        self.values.fill(UNTRAINED);
        self.build_bitfield();
    }

    /// Whether the grid is updated at training step `step` (every
    /// `update_interval` steps of the recipe's batch, starting with step 0;
    /// see [`GridPace`]).
    pub fn is_due(&self, step: u32) -> bool {
        self.pace.is_due(&self.config, step)
    }

    /// The mean stored value over the sampled cells of cascade 0 (the
    /// testbed averages the finest cascade only); `None` before any sample.
    pub fn mean(&self) -> Option<f32> {
        let cells = &self.values[..self.geometry.cells_per_cascade()];
        // Partial sums over fixed chunks, added in order: the same bits
        // whatever the number of threads (a rayon reduce would add in an
        // order that depends on work stealing).
        let partials: Vec<(f64, usize)> = cells
            .par_chunks(1 << 14)
            .map(|chunk| {
                chunk.iter().fold((0.0f64, 0usize), |(s, n), &v| {
                    if v >= 0.0 {
                        (s + v as f64, n + 1)
                    } else {
                        (s, n)
                    }
                })
            })
            .collect();
        let (sum, count) = partials
            .iter()
            .fold((0.0, 0), |a, b| (a.0 + b.0, a.1 + b.1));
        (count > 0).then(|| (sum / count as f64) as f32)
    }

    /// Rebuilds the threshold and the bitfield from the stored values.
    pub fn build_bitfield(&mut self) {
        let limit = self.config.min_optical_thickness;
        self.threshold = self.mean().map_or(limit, |mean| mean.min(limit));
        let threshold = self.threshold;
        let values = &self.values;
        self.occupied = self
            .bitfield
            .par_iter_mut()
            .enumerate()
            .map(|(w, word)| {
                let start = w * 32;
                let end = (start + 32).min(values.len());
                let mut bits = 0u32;
                for (i, &v) in values[start..end].iter().enumerate() {
                    // Untrained cells (negative) are occupied.
                    bits |= ((v < 0.0 || v > threshold) as u32) << i;
                }
                *word = bits;
                bits.count_ones() as usize
            })
            .sum();
    }

    /// Updates the grid at training step `step` with `density`, which maps a
    /// batch of unit-cube positions (row-major n × 3) to densities σ (n).
    /// `seed` makes the choice of cells and of points inside them
    /// reproducible; the same (seed, step) gives the same update.
    pub fn update<D>(&mut self, step: u32, seed: u64, mut density: D) -> UpdateReport
    where
        D: FnMut(&[f32], &mut [f32]),
    {
        let report = self.plan_update(step, seed);
        let mut sigma = std::mem::take(&mut self.sample_density);
        sigma.resize(report.samples, 0.0);
        let chunk = self.chunk.max(1);
        for (positions, sigma) in self
            .sample_positions
            .chunks(3 * chunk)
            .zip(sigma.chunks_mut(chunk))
        {
            density(positions, sigma);
        }
        self.apply_update(&sigma);
        self.sample_density = sigma;
        report
    }

    /// The first half of [`Self::update`], for engines that evaluate the
    /// density elsewhere (the gpu): chooses the cells and the points inside
    /// them, readable from [`Self::update_cells`] and
    /// [`Self::update_positions`] until [`Self::apply_update`].
    pub fn plan_update(&mut self, step: u32, seed: u64) -> UpdateReport {
        let full = self.pace.warming_up(&self.config, step) || self.occupied == 0;
        let key = mix64(seed ^ mix64(step as u64 ^ 0x6f63_6375_7061_6e63));
        self.choose_cells(full, key);
        self.sample_points(key);
        UpdateReport {
            samples: self.sample_cells.len(),
            full,
        }
    }

    /// The cells (linear indices) the planned update samples, one per
    /// sample; a cell may appear more than once.
    pub fn update_cells(&self) -> &[u32] {
        &self.sample_cells
    }

    /// The points (n × 3, unit cube) the planned update samples.
    pub fn update_positions(&self) -> &[f32] {
        &self.sample_positions
    }

    /// The second half of [`Self::update`]: the EMA with the densities at
    /// the planned points, then the bitfield.
    pub fn apply_update(&mut self, sigma: &[f32]) {
        assert_eq!(
            sigma.len(),
            self.sample_cells.len(),
            "one density per planned sample"
        );
        let decay = self.config.decay;
        self.values.par_iter_mut().for_each(|v| {
            if *v >= 0.0 {
                *v *= decay;
            }
        });
        let per = self.geometry.cells_per_cascade();
        for (&cell, &sigma) in self.sample_cells.iter().zip(sigma) {
            let cascade = cell as usize / per;
            let tau = optical_thickness(sigma, self.cascade_step(cascade as u32));
            let v = &mut self.values[cell as usize];
            *v = if *v < 0.0 { tau } else { v.max(tau) };
        }
        self.build_bitfield();
    }

    /// The step the optical thickness of `cascade` is measured with: the
    /// smallest march step scaled by the cascade's cell size, 2^cascade,
    /// about the cone step a ray takes there. The instant-ngp paper
    /// (appendix E.2) and its testbed (`splat_grid_samples_nerf_max_nearest_neighbor`,
    /// `level = 0`) measure every cascade with the smallest step, a σ
    /// threshold 2^cascade times higher in the outer cascades. Measured on
    /// the large demo (2 minutes, cpu, mixed precision) while the hash grid
    /// spanned only the unit cube, not since: that sparser grid
    /// marched 390 samples per ray and composited 118 against 440 and 194,
    /// but scored 23.5 dB on the held-out views against 25.3 (25.4 against
    /// 25.8 on the training views): the cells it skips hold the thin
    /// density the walls are made of at that stage of training. Object
    /// scenes (one cascade) are not affected.
    pub fn cascade_step(&self, cascade: u32) -> f32 {
        self.min_step * (1u32 << cascade) as f32
    }

    /// Fills `sample_cells` with the cells to sample, in ascending cell
    /// order within each half of each cascade: neighbouring samples then
    /// read neighbouring hash-table entries and grid values, which made
    /// an update ~1.3× faster on lego_400 than taking the cells in the
    /// order they were drawn (the draws, and so the update, are the same).
    fn choose_cells(&mut self, full: bool, key: u64) {
        let per = self.geometry.cells_per_cascade();
        self.sample_cells.clear();
        if full {
            self.sample_cells.extend(0..self.values.len() as u32);
            return;
        }
        let quarter = per / 4;
        for cascade in 0..self.geometry.cascades as usize {
            let base = cascade * per;
            let cascade_key = mix64(key ^ (cascade as u64 + 1).wrapping_mul(0x9e37_79b9_7f4a_7c15));
            // A quarter of the cells, distinct: i ↦ (a·i + b) mod N is a
            // bijection when gcd(a, N) = 1, so its first N/4 images are
            // distinct cells, and a random (a, b) makes them a random-looking
            // quarter without an N-sized shuffle. They are marked in a
            // bitmap and read back in order.
            let mut a = (mix64(cascade_key ^ 1) % per as u64) | 1;
            while gcd(a, per as u64) != 1 {
                a = (a + 2) % per as u64;
            }
            let b = mix64(cascade_key ^ 2) % per as u64;
            self.chosen.clear();
            self.chosen.resize(per.div_ceil(32), 0);
            for i in 0..quarter as u64 {
                let local = ((a * i + b) % per as u64) as usize;
                self.chosen[local / 32] |= 1 << (local % 32);
            }
            for (w, &word) in self.chosen.iter().enumerate() {
                let mut bits = word;
                while bits != 0 {
                    let local = w * 32 + bits.trailing_zeros() as usize;
                    self.sample_cells.push((base + local) as u32);
                    bits &= bits - 1;
                }
            }

            // As many draws from the cells occupied before this update
            // (with replacement), counted per occupied cell and read back in
            // order.
            self.occupied_list.clear();
            let words = &self.bitfield[base / 32..(base + per).div_ceil(32)];
            for (w, &word) in words.iter().enumerate() {
                let mut bits = word;
                while bits != 0 {
                    let index = base / 32 * 32 + w * 32 + bits.trailing_zeros() as usize;
                    if (base..base + per).contains(&index) {
                        self.occupied_list.push(index as u32);
                    }
                    bits &= bits - 1;
                }
            }
            if !self.occupied_list.is_empty() {
                let len = self.occupied_list.len() as u64;
                self.draws.clear();
                self.draws.resize(self.occupied_list.len(), 0);
                for i in 0..quarter as u64 {
                    self.draws[(mix64(cascade_key ^ mix64(i + 3)) % len) as usize] += 1;
                }
                for (&cell, &count) in self.occupied_list.iter().zip(&self.draws) {
                    for _ in 0..count {
                        self.sample_cells.push(cell);
                    }
                }
            }
        }
    }

    /// A uniformly random point inside each chosen cell.
    fn sample_points(&mut self, key: u64) {
        let geometry = self.geometry;
        let n = self.sample_cells.len();
        self.sample_positions.resize(3 * n, 0.0);
        self.sample_positions
            .par_chunks_mut(3)
            .zip(self.sample_cells.par_iter())
            .enumerate()
            .for_each(|(i, (out, &cell))| {
                let cell = geometry.cell_at(cell as usize);
                let size = geometry.cell_size(cell.cascade);
                let corner = geometry.cell_min(cell);
                let r = mix64(key ^ mix64(i as u64));
                // 21 random bits per axis, in [0, 1).
                let u =
                    |shift: u32| ((r >> shift) & 0x1f_ffff) as f32 * (1.0 / (1u32 << 21) as f32);
                out[0] = corner.x + u(0) * size;
                out[1] = corner.y + u(21) * size;
                out[2] = corner.z + u(42) * size;
            });
    }
}

/// σ · step, with a density that is negative or NaN (a broken network)
/// counted as empty space, never as a value that poisons the mean.
fn optical_thickness(sigma: f32, step: f32) -> f32 {
    let tau = sigma * step;
    if tau > 0.0 { tau.min(f32::MAX) } else { 0.0 }
}

fn gcd(mut a: u64, mut b: u64) -> u64 {
    while b != 0 {
        (a, b) = (b, a % b);
    }
    a
}

/// A 64-bit mixing function (the SplitMix64 finaliser, Steele, Lea and
/// Flood 2014): counter-based randomness, so updates are reproducible and
/// independent of thread scheduling.
#[inline]
pub fn mix64(mut x: u64) -> u64 {
    x = x.wrapping_add(0x9e37_79b9_7f4a_7c15);
    x = (x ^ (x >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    x = (x ^ (x >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    x ^ (x >> 31)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::HashSet;

    const STEP: f32 = 0.01;

    fn small(resolution: u32, cascades: u32) -> OccupancyGrid {
        let config = OccupancyConfig {
            resolution,
            ..OccupancyConfig::PAPER
        };
        OccupancyGrid::new(config, cascades, STEP)
    }

    fn cells_of(grid: &OccupancyGrid, positions: &[f32]) -> Vec<usize> {
        positions
            .chunks(3)
            .map(|p| {
                grid.geometry()
                    .linear_index(grid.geometry().cell_of(Vec3::from_slice(p)))
            })
            .collect()
    }

    #[test]
    fn faces_and_cell_boundaries_map_to_valid_cells() {
        let g = GridGeometry::new(128, 1);
        // Every cell boundary k/128 is exact in f32 and belongs to cell k;
        // the far face 1 belongs to the last cell.
        for k in 0..=128u32 {
            let x = k as f32 / 128.0;
            let cell = g.cell_of(Vec3::new(x, 0.5, 1.0 - x));
            assert_eq!(cell.xyz, [k.min(127), 64, (128 - k).min(127)], "x = {x}");
            assert_eq!(cell.cascade, 0);
        }
        // Outside, and not finite: clamped into the grid.
        for p in [
            Vec3::splat(-0.3),
            Vec3::splat(1.7),
            Vec3::new(f32::NAN, f32::INFINITY, f32::NEG_INFINITY),
        ] {
            let cell = g.cell_of(p);
            assert!(cell.xyz.iter().all(|&c| c < 128), "{p:?} → {cell:?}");
            assert!(g.linear_index(cell) < g.cell_count());
        }
        assert_eq!(g.cell_of(Vec3::splat(-0.3)).xyz, [0; 3]);
        assert_eq!(g.cell_of(Vec3::splat(1.7)).xyz, [127; 3]);

        // Three cascades: cascade 1 spans [-0.5, 1.5), cascade 2 [-1.5, 2.5).
        let g = GridGeometry::new(128, 3);
        let c = |x: f32| g.cell_of(Vec3::new(x, 0.5, 0.5));
        assert_eq!((c(0.999_999).cascade, c(0.999_999).xyz[0]), (0, 127));
        // The face of cascade 0 belongs to cascade 1: (1 − 0.5)·64 + 64 = 96.
        assert_eq!((c(1.0).cascade, c(1.0).xyz[0]), (1, 96));
        // So does the near face 0: cascade 0 is the open cube, (0 − 0.5)·64 + 64 = 32.
        assert_eq!((c(0.0).cascade, c(0.0).xyz[0]), (1, 32));
        assert_eq!((c(1e-6).cascade, c(1e-6).xyz[0]), (0, 0));
        assert_eq!((c(-0.5).cascade, c(-0.5).xyz[0]), (2, 32));
        assert_eq!((c(1.5).cascade, c(1.5).xyz[0]), (2, 96));
        assert_eq!((c(2.5).cascade, c(2.5).xyz[0]), (2, 127));
        assert_eq!((c(-7.0).cascade, c(-7.0).xyz[0]), (2, 0));
        // Cell corners invert the mapping: the corner of a cell maps to it.
        for index in [
            0,
            1,
            128 * 128 * 128 - 1,
            128 * 128 * 128 + 5 * 128 + 77,
            g.cell_count() - 1,
        ] {
            let cell = g.cell_at(index);
            assert_eq!(g.linear_index(cell), index);
            let centre = g.cell_centre(cell);
            if cell.cascade == 0 || centre.cmplt(Vec3::ZERO).any() || centre.cmpgt(Vec3::ONE).any()
            {
                assert_eq!(g.cell_of(centre), cell, "{index}");
            }
        }
    }

    /// Dense in the half x < 0.5, empty elsewhere: after an update some
    /// cells are occupied and others not.
    fn half_dense(positions: &[f32], sigma: &mut [f32]) {
        for (p, s) in positions.chunks(3).zip(sigma) {
            *s = if p[0] < 0.5 { 1000.0 } else { 0.0 };
        }
    }

    /// At the recipe's batch the grid updates on exactly the steps it did
    /// when it counted steps (every `update_interval`, warm-up for
    /// `warmup_steps`), whatever the batch's size.
    #[test]
    fn at_the_recipes_batch_updates_fall_on_the_same_steps_as_before() {
        let config = OccupancyConfig::PAPER;
        for batch in [1, 1 << 14, 1 << 18] {
            let pace = GridPace {
                step_batch: batch,
                recipe_batch: batch,
            };
            for step in 0..10_000 {
                assert_eq!(
                    pace.is_due(&config, step),
                    step.is_multiple_of(config.update_interval),
                    "step {step}, batch {batch}"
                );
                assert_eq!(
                    pace.warming_up(&config, step),
                    step < config.warmup_steps,
                    "step {step}, batch {batch}"
                );
            }
        }
        let mut grid = small(4, 1);
        assert_eq!(grid.pace, GridPace::RECIPE);
        grid.update(0, 1, half_dense);
        assert!(grid.plan_update(255, 1).full);
        assert!(!grid.plan_update(256, 1).full);
    }

    /// A step of a quarter of the recipe's batch updates a quarter as
    /// often per step (every 64 steps instead of 16) and warms up for four
    /// times the steps, the same samples; a batch that does not divide the
    /// recipe's updates at the step whose batch reaches each interval's
    /// samples.
    #[test]
    fn a_quarter_batch_updates_a_quarter_as_often_per_step() {
        let config = OccupancyConfig::PAPER;
        let quarter = GridPace {
            step_batch: 1 << 16,
            recipe_batch: 1 << 18,
        };
        let due: Vec<u32> = (0..6400).filter(|&s| quarter.is_due(&config, s)).collect();
        let full_batch = (0..6400)
            .filter(|&s| GridPace::RECIPE.is_due(&config, s))
            .count();
        assert_eq!(due.len() * 4, full_batch);
        assert!(due.iter().all(|s| s.is_multiple_of(64)), "{due:?}");
        assert_eq!(&due[..3], &[0, 64, 128]);
        assert!(quarter.warming_up(&config, 1023));
        assert!(!quarter.warming_up(&config, 1024));

        // 3 samples a step against 16 × 4 a period: 64 samples are
        // trained by step 21 (63 to 66), 128 by step 42, 192 by step 63,
        // so the steps after those update.
        let thirds = GridPace {
            step_batch: 3,
            recipe_batch: 4,
        };
        let due: Vec<u32> = (0..65).filter(|&s| thirds.is_due(&config, s)).collect();
        assert_eq!(due, [0, 22, 43, 64]);

        // A driver's grid follows its pace in `plan_update`'s warm-up.
        let mut grid = small(4, 1);
        grid.pace = quarter;
        grid.update(0, 1, half_dense);
        assert!(grid.plan_update(1023, 1).full);
        assert!(!grid.plan_update(1024, 1).full);
        assert!(grid.is_due(64) && !grid.is_due(16));
    }

    #[test]
    fn a_new_grid_is_all_occupied_and_mark_untrained_restores_that() {
        let mut grid = small(8, 2);
        assert_eq!(grid.occupied_count(), 2 * 512);
        assert_eq!(grid.occupancy_fraction(), 1.0);
        grid.update(0, 1, |_, sigma| sigma.fill(0.0));
        assert_eq!(grid.occupied_count(), 0);
        assert_eq!(grid.occupancy_fraction(), 0.0);
        grid.mark_untrained();
        assert_eq!(grid.occupancy_fraction(), 1.0);
        assert!(grid.values().iter().all(|&v| v == UNTRAINED));
    }

    #[test]
    fn warm_up_samples_every_cell_once_inside_it_and_scales_by_cascade() {
        let mut grid = small(4, 2);
        let mut seen = Vec::new();
        let report = grid.update(0, 7, |p, sigma| {
            seen.extend_from_slice(p);
            sigma.fill(2.0);
        });
        assert!(report.full);
        assert_eq!(report.samples, 128);
        // Sample i lies inside cell i: each cell exactly once. (The cells of
        // cascade 1 that overlap cascade 0 are sampled too, as in the
        // testbed, though marching reads cascade 0 there.)
        let geometry = grid.geometry();
        for (i, p) in seen.chunks(3).enumerate() {
            let cell = geometry.cell_at(i);
            let lo = geometry.cell_min(cell);
            let hi = lo + Vec3::splat(1.0 / geometry.cells_per_unit(cell.cascade));
            let p = Vec3::from_slice(p);
            assert!(
                p.cmpge(lo).all() && p.cmplt(hi).all(),
                "sample {i} at {p} outside {lo}..{hi}"
            );
        }
        // τ = σ · step · 2^cascade, exactly (powers of two).
        assert!(grid.values()[..64].iter().all(|&v| v == 2.0 * STEP));
        assert!(grid.values()[64..].iter().all(|&v| v == 4.0 * STEP));
    }

    #[test]
    fn ema_threshold_and_bitfield_follow_the_rule() {
        let mut grid = small(4, 1);
        // First update: σ = 2 in cells with x < 2, σ = 0.5 elsewhere.
        let sigma_a = |p: &[f32], s: &mut [f32]| {
            for (p, s) in p.chunks(3).zip(s) {
                *s = if p[0] < 0.5 { 2.0 } else { 0.5 };
            }
        };
        grid.update(0, 3, sigma_a);
        let (high, low) = (2.0 * STEP, 0.5 * STEP);
        let mean = 0.5 * (high + low); // 0.0125 > 0.01
        assert!((grid.mean().unwrap() - mean).abs() < 1e-9);
        // min(0.01, 0.0125) = 0.01: only the σ = 2 cells (τ = 0.02) pass.
        assert_eq!(grid.threshold(), 0.01);
        assert_eq!(grid.occupied_count(), 32);
        for index in 0..64 {
            let cell = grid.geometry().cell_at(index);
            assert_eq!(grid.is_occupied(cell), cell.xyz[0] < 2);
        }

        // Second update (still warm-up): σ = 0 in the left half, 1 on the
        // right. Left: max(0.02 · 0.95, 0) = 0.019; right: max(0.005 · 0.95,
        // 0.01) = 0.01.
        grid.update(16, 3, |p, s| {
            for (p, s) in p.chunks(3).zip(s) {
                *s = if p[0] < 0.5 { 0.0 } else { 1.0 };
            }
        });
        for index in 0..64 {
            let cell = grid.geometry().cell_at(index);
            let want = if cell.xyz[0] < 2 {
                high * 0.95
            } else {
                (low * 0.95).max(STEP)
            };
            assert_eq!(grid.values()[index], want);
        }
        // Mean (0.019 + 0.01)/2 = 0.0145 → threshold 0.01; 0.01 does not
        // exceed 0.01.
        assert_eq!(grid.threshold(), 0.01);
        assert_eq!(grid.occupied_count(), 32);

        // Small values: mean below 0.01 becomes the threshold.
        let mut grid = small(4, 1);
        grid.update(0, 3, |p, s| {
            for (p, s) in p.chunks(3).zip(s) {
                *s = if p[1] < 0.25 { 0.3 } else { 0.1 };
            }
        });
        // A quarter at 0.003, the rest 0.001: mean 0.0015.
        assert!((grid.threshold() - 0.0015).abs() < 1e-9);
        assert_eq!(grid.occupied_count(), 16);
    }

    #[test]
    fn after_warm_up_a_quarter_plus_a_quarter_from_occupied_cells() {
        let mut grid = small(8, 1);
        // Warm-up: only the five cells with x = y = z... a few chosen
        // cells are dense.
        let dense: HashSet<usize> = [0, 9, 100, 300, 511].into_iter().collect();
        let geometry = grid.geometry();
        let field = |p: &[f32], s: &mut [f32]| {
            for (p, s) in p.chunks(3).zip(s) {
                let index = geometry.linear_index(geometry.cell_of(Vec3::from_slice(p)));
                *s = if dense.contains(&index) { 5.0 } else { 0.0 };
            }
        };
        grid.update(0, 11, field);
        assert_eq!(grid.occupied_count(), 5);
        let before = grid.values().to_vec();

        let mut seen = Vec::new();
        let report = grid.update(256, 11, |p, s| {
            seen.extend_from_slice(p);
            s.fill(0.0);
        });
        assert!(!report.full);
        assert_eq!(report.samples, 128 + 128);
        let cells = cells_of(&grid, &seen);
        let uniform: HashSet<usize> = cells[..128].iter().copied().collect();
        assert_eq!(
            uniform.len(),
            128,
            "the uniform quarter holds distinct cells"
        );
        assert!(
            cells[128..].iter().all(|c| dense.contains(c)),
            "drawn from occupied cells"
        );
        // Every occupied cell is drawn at least once in 128 draws from 5
        // (a miss has probability 5·(4/5)^128 ≈ 2e-12).
        let drawn: HashSet<usize> = cells[128..].iter().copied().collect();
        assert_eq!(drawn, dense);
        // With σ = 0 everywhere every cell just decays.
        for (v, b) in grid.values().iter().zip(&before) {
            assert_eq!(*v, b * 0.95);
        }
        // Reproducible: the same seed and step draw the same points.
        let mut again = OccupancyGrid::from_values(*grid.config(), 1, STEP, before);
        let mut seen_again = Vec::new();
        again.update(256, 11, |p, s| {
            seen_again.extend_from_slice(p);
            s.fill(0.0);
        });
        assert_eq!(seen, seen_again);
    }

    #[test]
    fn untrained_cells_stay_occupied_until_sampled() {
        let mut grid = small(8, 1);
        grid.update(0, 5, |_, s| s.fill(1.0));
        grid.mark_untrained();
        let report = grid.update(512, 5, |_, s| s.fill(0.0));
        assert!(!report.full);
        // The sampled cells now hold 0 (not occupied); the others are still
        // untrained, hence occupied.
        let sampled = grid.values().iter().filter(|&&v| v == 0.0).count();
        assert!(sampled >= 128, "{sampled}");
        assert_eq!(grid.occupied_count(), 512 - sampled);
        assert!(grid.values().iter().all(|&v| v == 0.0 || v == UNTRAINED));
    }

    #[test]
    fn an_empty_grid_recovers_where_density_rises() {
        let mut grid = small(8, 1);
        // A bad step: every density zero (or NaN, counted as zero).
        grid.update(0, 9, |_, s| s.fill(f32::NAN));
        assert_eq!(grid.occupied_count(), 0);
        assert!(grid.values().iter().all(|&v| v == 0.0));
        // Long after warm-up, density rises in a ball of radius 0.25: the
        // empty grid triggers a full update and the ball is occupied again.
        let ball = |p: &[f32]| Vec3::from_slice(p).distance(Vec3::splat(0.5)) < 0.25;
        let report = grid.update(4096, 9, |p, s| {
            for (p, s) in p.chunks(3).zip(s) {
                *s = if ball(p) { 3.0 } else { 0.0 };
            }
        });
        assert!(report.full);
        assert_eq!(report.samples, 512);
        // Cells sampled at a point in the ball hold 0.03 > min(0.01, mean).
        let in_ball = grid.values().iter().filter(|&&v| v > 0.0).count();
        assert!(in_ball > 0);
        assert_eq!(grid.occupied_count(), in_ball);
        // The centre cells are certainly in the ball.
        assert!(grid.occupied_at(Vec3::splat(0.5)));
        assert!(!grid.occupied_at(Vec3::splat(0.05)));
    }
}
