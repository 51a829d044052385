//! Ray marching through the occupancy grid: Instant-NGP's sample generation
//! (Müller et al. 2022, appendix E.1; instant-ngp testbed).
//!
//! Each ray is mapped into unit-cube coordinates (`unit = world · scale +
//! offset`, so distances along the unit direction scale by `scale` too) and
//! clipped to the scene box (side aabb_scale around 0.5, inside the
//! outermost cascade). Samples lie on a fixed lattice from the entry point
//! e: s_k = (u + k) · dt, position e + s_k · d, with dt = √3/1024 (cone angle
//! 0, the Blender setting) and u a per-ray offset in [0, 1) during training
//! (0 for rendering). A lattice point is a sample when its cell is occupied;
//! at most 1024 samples per ray.
//!
//! The march goes cell by cell, like a DDA: from a lattice point it finds
//! the first lattice point at or beyond its cell's exit face, and either
//! emits every lattice point up to there (occupied cell) or jumps over them
//! (empty cell; the testbed's `advance_to_next_voxel`, which also stays on
//! the lattice). The face is pulled inside the cell by a margin of ~30 ulps
//! of the largest coordinate, well above the few ulps of rounding in the
//! position and the exit distance, so every lattice point emitted or jumped
//! over lies in the cell for certain: the result is exactly the samples of
//! a naive march that looks up every lattice point (a test checks this).
//!
//! Training marches every ray to its sample limit without early termination
//! (there are no densities yet); compositing ignores samples once the
//! transmittance falls below 1e-4. Rendering uses
//! [`march_and_composite`], which evaluates densities in rounds and stops
//! each ray once its transmittance falls below 1e-4.
//!
//! Output, for R rays: positions (S × 3, unit cube), directions (S × 3,
//! world unit vectors), dt and t per sample in world units (for
//! compositing), and ray_offsets (R + 1).

use glam::Vec3;
use rayon::prelude::*;

use super::occupancy::{Cell, GridGeometry, OccupancyGrid, bit_is_set};
use crate::field::ngp::MarchConfig;
use crate::model::RenderedPixel;
use crate::scene::{Aabb, UnitCubeMapping};

/// What a batch march needs besides the grid and the rays.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MarchParams {
    pub config: MarchConfig,
    pub mapping: UnitCubeMapping,
    /// `Some(seed)`: the first sample of ray r sits at [`jitter`]`(seed, r)`
    /// · dt past the entry point, the training setting (vary the seed per
    /// step). `None`: at the entry point, for rendering.
    pub jitter_seed: Option<u32>,
    /// Samples the batch may hold in total. Rays are kept in order while
    /// their samples fit; from the first ray that would overflow on, rays
    /// get no samples (see [`MarchStats::rays_kept`]).
    pub sample_budget: usize,
}

impl MarchParams {
    /// The paper's marching with a random first offset, no budget.
    pub fn training(mapping: UnitCubeMapping, seed: u32) -> Self {
        Self {
            config: MarchConfig::PAPER,
            mapping,
            jitter_seed: Some(seed),
            sample_budget: usize::MAX,
        }
    }

    /// The paper's marching from the entry point, no budget.
    pub fn rendering(mapping: UnitCubeMapping) -> Self {
        Self {
            jitter_seed: None,
            ..Self::training(mapping, 0)
        }
    }
}

/// The murmur3 32-bit finaliser (Appleby): a cheap bijective mixer that the
/// shaders compute identically.
#[inline]
pub fn mix32(mut x: u32) -> u32 {
    x ^= x >> 16;
    x = x.wrapping_mul(0x85eb_ca6b);
    x ^= x >> 13;
    x = x.wrapping_mul(0xc2b2_ae35);
    x ^ (x >> 16)
}

/// The first-sample offset of `ray` under `seed`, uniform in [0, 1) on a
/// 2^-24 grid (exactly representable, so both engines agree bit for bit).
#[inline]
pub fn jitter(seed: u32, ray: u32) -> f32 {
    let h = mix32(seed ^ mix32(ray.wrapping_add(0x9e37_79b9)));
    (h >> 8) as f32 * (1.0 / 16_777_216.0)
}

/// One ray prepared for marching, in unit-cube coordinates.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RayMarch {
    /// Where the ray enters the box (its origin when it starts inside).
    pub entry: Vec3,
    pub direction: Vec3,
    inverse_direction: Vec3,
    /// Distance from the (unit-space) origin to the entry point.
    pub t_enter: f32,
    /// Distance from the entry point to the exit point.
    pub s_exit: f32,
    /// The first-sample offset u, in steps.
    pub jitter: f32,
    /// Where along the ray the lattice points lie.
    pub lattice: Lattice,
}

impl RayMarch {
    /// Distance of lattice point k past the entry point.
    #[inline(always)]
    pub fn s(&self, k: u32) -> f32 {
        self.lattice.s(self.jitter + k as f32, self.t_enter)
    }

    /// Lattice point k.
    #[inline(always)]
    pub fn position(&self, k: u32) -> Vec3 {
        self.entry + self.direction * self.s(k)
    }

    /// The step (unit-cube length) that lattice point k stands for.
    #[inline(always)]
    pub fn step(&self, k: u32) -> f32 {
        self.lattice.step(self.jitter + k as f32)
    }
}

/// The lattice of one ray: distances s(x) past the entry point for the
/// continuous lattice coordinate x = u + k (u the jitter), and the inverse.
///
/// Without a cone angle: s = x · dt, the fixed step.
///
/// With cone angle c (aabb_scale > 1): the step grows with the distance t
/// from the camera, as instant-ngp's cone stepping (step = c · t clamped to
/// [dt, max]), but in whole octaves so that every engine computes the same
/// points with exact operations (multiplications by powers of two, and a
/// float's exponent instead of a logarithm): with A = dt / c, distances
/// below 2A are stepped by dt, and octave j ≥ 1, t in [A·2ʲ, A·2ʲ⁺¹), by
/// dt·2ʲ (= the octave's start distance times c, so the step is between
/// t·c/2 and t·c), up to the octave whose step is the maximum. Each octave
/// is exactly 1/c = 256 lattice points long. The ray starts in the octave
/// of its entry distance with that octave's step, up to the next octave's
/// start.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Lattice {
    /// Step from the entry point to the first octave boundary (the fixed
    /// step without a cone).
    first_step: f32,
    inverse_first_step: f32,
    /// Lattice units from the entry point to that boundary (∞ without a
    /// cone, or when the entry is already in the last octave), and its
    /// length.
    first_units: f32,
    first_length: f32,
    /// The octave the entry point lies in.
    first_octave: i32,
    cone: Cone,
}

/// The cone-stepping constants of a marcher (all in unit-cube lengths).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Cone {
    /// dt, the smallest step, and its inverse.
    min_step: f32,
    inverse_min_step: f32,
    /// A = dt / c: octave j starts at A · 2ʲ (j ≥ 1).
    octave_start: f32,
    inverse_octave_start: f32,
    /// Lattice points per octave, 1/c.
    points_per_octave: f32,
    /// The octave whose step is the largest (the step stops growing).
    last_octave: i32,
}

impl Cone {
    /// Lattice points per octave (1 / cone angle).
    pub fn points_per_octave(&self) -> f32 {
        self.points_per_octave
    }

    /// A = dt / c, where octave 1 starts.
    pub fn octave_start(&self) -> f32 {
        self.octave_start
    }

    pub fn inverse_octave_start(&self) -> f32 {
        self.inverse_octave_start
    }

    /// The octave whose step is the largest.
    pub fn last_octave(&self) -> i32 {
        self.last_octave
    }

    /// The octave of distance t: 0 below 2A, floor(log2(t / A)) above,
    /// at most the last. From the float's exponent, which is exact.
    #[inline(always)]
    fn octave_of(&self, t: f32) -> i32 {
        let v = t * self.inverse_octave_start;
        if v.is_nan() || v < 2.0 {
            return 0;
        }
        let exponent = ((v.to_bits() >> 23) & 0xff) as i32 - 127;
        exponent.min(self.last_octave)
    }
}

/// 2ʲ as an f32, exactly, for |j| < 127.
#[inline(always)]
fn power_of_two(j: i32) -> f32 {
    f32::from_bits(((j + 127) as u32) << 23)
}

impl Lattice {
    /// The fixed-step lattice.
    pub fn fixed(step: f32) -> Self {
        Self {
            first_step: step,
            inverse_first_step: 1.0 / step,
            first_units: f32::INFINITY,
            first_length: f32::INFINITY,
            first_octave: 0,
            cone: Cone {
                min_step: step,
                inverse_min_step: 1.0 / step,
                octave_start: f32::INFINITY,
                inverse_octave_start: 0.0,
                points_per_octave: f32::INFINITY,
                last_octave: 0,
            },
        }
    }

    /// The cone lattice of a ray entering at distance `t_enter`.
    pub fn cone(cone: Cone, t_enter: f32) -> Self {
        let first_octave = cone.octave_of(t_enter);
        let scale = power_of_two(first_octave);
        let first_step = cone.min_step * scale;
        let inverse_first_step = cone.inverse_min_step / scale;
        let (first_units, first_length) = if first_octave >= cone.last_octave {
            (f32::INFINITY, f32::INFINITY)
        } else {
            let boundary = cone.octave_start * power_of_two(first_octave + 1);
            let length = boundary - t_enter;
            (length * inverse_first_step, length)
        };
        Self {
            first_step,
            inverse_first_step,
            first_units,
            first_length,
            first_octave,
            cone,
        }
    }

    /// The octave of lattice coordinate x past the first stretch, and the
    /// lattice coordinate where it starts.
    #[inline(always)]
    fn octave_at(&self, x: f32) -> (i32, f32) {
        let past = x - self.first_units;
        let whole = (past / self.cone.points_per_octave) as i32;
        let octave = (self.first_octave + 1 + whole).min(self.cone.last_octave);
        let start = self.first_units
            + (octave - self.first_octave - 1) as f32 * self.cone.points_per_octave;
        (octave, start)
    }

    /// s(x): distance of lattice coordinate x past the entry point.
    #[inline(always)]
    pub fn s(&self, x: f32, t_enter: f32) -> f32 {
        if x < self.first_units {
            return x * self.first_step;
        }
        let (octave, start) = self.octave_at(x);
        let scale = power_of_two(octave);
        let t = self.cone.octave_start * scale + (x - start) * (self.cone.min_step * scale);
        t - t_enter
    }

    /// The step at lattice coordinate x.
    #[inline(always)]
    pub fn step(&self, x: f32) -> f32 {
        if x < self.first_units {
            return self.first_step;
        }
        self.cone.min_step * power_of_two(self.octave_at(x).0)
    }

    /// The lattice coordinate of distance s past the entry point (the
    /// inverse of [`Self::s`], to rounding).
    #[inline(always)]
    pub fn x(&self, s: f32, t_enter: f32) -> f32 {
        if s.is_nan() || s < self.first_length {
            return s * self.inverse_first_step;
        }
        let t = t_enter + s;
        let octave = self.cone.octave_of(t).max(self.first_octave + 1);
        let scale = power_of_two(octave);
        let start = self.first_units
            + (octave - self.first_octave - 1) as f32 * self.cone.points_per_octave;
        start + (t - self.cone.octave_start * scale) * (self.cone.inverse_min_step / scale)
    }

    /// Whether the step varies along the ray.
    pub fn is_cone(&self) -> bool {
        self.cone.points_per_octave.is_finite()
    }
}

/// Marching over one occupancy grid: the grid's bits and geometry, the step,
/// the box, and the scene's mapping.
#[derive(Debug, Clone, Copy)]
pub struct Marcher<'a> {
    geometry: GridGeometry,
    bitfield: &'a [u32],
    /// One bit per block of [`COARSE`]³ cells, set when any cell of the
    /// block is occupied ([`coarse_occupancy`]); when present, an empty
    /// block is jumped over whole.
    coarse: Option<&'a [u32]>,
    mapping: UnitCubeMapping,
    bounds: Aabb,
    dt: f32,
    /// Cone stepping, for scenes larger than the unit cube.
    cone: Option<Cone>,
    margin: f32,
}

impl<'a> Marcher<'a> {
    pub fn new(grid: &'a OccupancyGrid, config: &MarchConfig, mapping: &UnitCubeMapping) -> Self {
        Self::from_parts(grid.geometry(), grid.bitfield(), config, mapping)
    }

    /// From a bitfield laid out as [`OccupancyGrid::bitfield`].
    pub fn from_parts(
        geometry: GridGeometry,
        bitfield: &'a [u32],
        config: &MarchConfig,
        mapping: &UnitCubeMapping,
    ) -> Self {
        assert_eq!(
            bitfield.len(),
            geometry.bitfield_words(),
            "bitfield of the wrong size"
        );
        let outermost = (1u32 << (geometry.cascades - 1)) as f32;
        let half = 0.5 * mapping.aabb_scale.min(outermost);
        Self {
            geometry,
            bitfield,
            coarse: None,
            mapping: *mapping,
            bounds: Aabb::cube(Vec3::splat(0.5), half),
            dt: config.step,
            cone: cone_for(config, mapping, &geometry),
            margin: skip_margin(&geometry),
        }
    }

    /// Whether steps grow with distance.
    pub fn cones(&self) -> bool {
        self.cone.is_some()
    }

    pub fn dt(&self) -> f32 {
        self.dt
    }

    /// Jumps over empty blocks of cells whole, with `coarse` built by
    /// [`coarse_occupancy`] from this marcher's bitfield. The samples are
    /// the same: a jump lands where the cell-by-cell walk would have
    /// arrived after crossing the block's empty cells.
    pub fn with_coarse(self, coarse: &'a [u32]) -> Self {
        assert_eq!(
            coarse.len(),
            coarse_words(&self.geometry).unwrap_or(usize::MAX),
            "coarse occupancy of the wrong size"
        );
        Self {
            coarse: Some(coarse),
            ..self
        }
    }

    /// The box rays are clipped to, in unit coordinates.
    pub fn bounds(&self) -> Aabb {
        self.bounds
    }

    /// Prepares a world-space ray (unit `direction`); `None` when it misses
    /// the box or is not a valid ray (non-finite, zero direction).
    #[inline]
    pub fn prepare(&self, origin: Vec3, direction: Vec3, jitter: f32) -> Option<RayMarch> {
        if !origin.is_finite() || !direction.is_finite() || direction == Vec3::ZERO {
            return None;
        }
        let origin = self.mapping.to_unit(origin);
        let (t_enter, t_exit) = self.bounds.intersect(origin, direction, 0.0)?;
        let entry = origin + direction * t_enter;
        let inverse = |d: f32| if d == 0.0 { 0.0 } else { 1.0 / d };
        Some(RayMarch {
            entry,
            direction,
            inverse_direction: Vec3::new(
                inverse(direction.x),
                inverse(direction.y),
                inverse(direction.z),
            ),
            t_enter,
            s_exit: t_exit - t_enter,
            jitter,
            lattice: match self.cone {
                None => Lattice::fixed(self.dt),
                Some(cone) => Lattice::cone(cone, t_enter),
            },
        })
    }

    /// Whether lattice point k of `ray` is a sample (its cell is occupied).
    #[inline(always)]
    pub fn is_sample(&self, ray: &RayMarch, k: u32) -> bool {
        let cell = self.geometry.cell_of(ray.position(k));
        bit_is_set(self.bitfield, self.geometry.linear_index(cell))
    }

    /// The first lattice index at or beyond the exit face of `cell` (pulled
    /// in by the margin, see the module documentation): every lattice point
    /// from one inside `cell` up to this one is inside `cell` too.
    #[inline(always)]
    fn exit_index(&self, ray: &RayMarch, cell: Cell) -> u32 {
        let lo = self.geometry.cell_min(cell);
        let size = self.geometry.cell_size(cell.cascade);
        self.box_exit_index(ray, lo, size)
    }

    /// As [`Self::exit_index`] for the block of [`COARSE`]³ cells holding
    /// `cell`. The margin argument is the same: the rounding it covers is
    /// that of positions and distances, not of the box's size.
    #[inline(always)]
    fn block_exit_index(&self, ray: &RayMarch, cell: Cell) -> u32 {
        let first = Cell {
            cascade: cell.cascade,
            xyz: cell.xyz.map(|c| c & !(COARSE - 1)),
        };
        let lo = self.geometry.cell_min(first);
        let size = self.geometry.cell_size(cell.cascade) * COARSE as f32;
        self.box_exit_index(ray, lo, size)
    }

    /// Whether the block of `cell` has an occupied cell (true without a
    /// coarse field).
    #[inline(always)]
    fn block_occupied(&self, cell: Cell) -> bool {
        match self.coarse {
            None => true,
            Some(coarse) => bit_is_set(coarse, block_index(&self.geometry, cell)),
        }
    }

    /// The first lattice index at or beyond the exit face of the box with
    /// lower corner `lo` and side `size`, pulled in by the margin.
    #[inline(always)]
    fn box_exit_index(&self, ray: &RayMarch, lo: Vec3, size: f32) -> u32 {
        let exit = |lo: f32, e: f32, d: f32, inverse: f32| {
            if d > 0.0 {
                (lo + size - self.margin - e) * inverse
            } else if d < 0.0 {
                (lo + self.margin - e) * inverse
            } else {
                f32::INFINITY
            }
        };
        let s_cell = exit(lo.x, ray.entry.x, ray.direction.x, ray.inverse_direction.x)
            .min(exit(
                lo.y,
                ray.entry.y,
                ray.direction.y,
                ray.inverse_direction.y,
            ))
            .min(exit(
                lo.z,
                ray.entry.z,
                ray.direction.z,
                ray.inverse_direction.z,
            ));
        // ceil without the libm call: `as u32` truncates and saturates
        // (negative and NaN give 0, which callers lift past the current
        // index).
        let v = ray.lattice.x(s_cell, ray.t_enter) - ray.jitter;
        let truncated = v as u32;
        truncated.saturating_add(((truncated as f32) < v) as u32)
    }

    /// Walks `ray` from lattice point `*k`, calling `emit(k)` for each
    /// sample, until `limit` samples were emitted or the ray left the box.
    /// `*k` is left at the next lattice point to look at; the result is
    /// true when the ray is finished.
    ///
    /// One cell at a time: the cell of the current lattice point is looked
    /// up once, and every lattice point before its exit index is emitted
    /// (occupied) or jumped over (empty) without further look-ups; with a
    /// coarse field, an empty cell in an empty block jumps to the block's
    /// exit index instead.
    #[inline]
    #[allow(clippy::neg_cmp_op_on_partial_ord)]
    pub fn walk(&self, ray: &RayMarch, k: &mut u32, limit: u32, mut emit: impl FnMut(u32)) -> bool {
        let mut index = *k;
        let mut emitted = 0;
        loop {
            let s = ray.s(index);
            // Not `s > exit`: a NaN distance ends the ray too, as in the
            // gpu engine's `walk` (march_common.wgsl).
            if !(s <= ray.s_exit) {
                *k = index;
                return true;
            }
            if emitted == limit {
                *k = index;
                return false;
            }
            let cell = self.geometry.cell_of(ray.entry + ray.direction * s);
            if !bit_is_set(self.bitfield, self.geometry.linear_index(cell)) {
                let exit = if self.block_occupied(cell) {
                    self.exit_index(ray, cell)
                } else {
                    self.block_exit_index(ray, cell)
                };
                index = exit.max(index.saturating_add(1));
                continue;
            }
            let next = self.exit_index(ray, cell).max(index.saturating_add(1));
            while index < next {
                if !(ray.s(index) <= ray.s_exit) {
                    *k = index;
                    return true;
                }
                if emitted == limit {
                    *k = index;
                    return false;
                }
                emit(index);
                emitted += 1;
                index += 1;
            }
        }
    }

    /// World distance along the ray of lattice point k.
    #[inline(always)]
    pub fn world_t(&self, ray: &RayMarch, k: u32) -> f32 {
        (ray.t_enter + ray.s(k)) * (1.0 / self.mapping.scale)
    }

    /// The step of lattice point k in world units.
    #[inline(always)]
    pub fn world_dt(&self, ray: &RayMarch, k: u32) -> f32 {
        ray.step(k) / self.mapping.scale
    }
}

/// The cone-stepping constants for a scene, or `None` for the fixed step:
/// instant-ngp steps by cone angle only when aabb_scale > 1 (testbed:
/// `cone_angle_constant` 1/256 unless `aabb_scale <= 1`); its largest step
/// is the width of a cell of the coarsest cascade times NERF_STEPS /
/// NERF_GRIDSIZE (`MAX_CONE_STEPSIZE`), dt · 2^(cascades − 1) · 1024 / 128
/// here, a power of two times dt.
pub fn cone_for(
    config: &MarchConfig,
    mapping: &UnitCubeMapping,
    geometry: &GridGeometry,
) -> Option<Cone> {
    if !(mapping.aabb_scale > 1.0 && config.cone_angle > 0.0) {
        return None;
    }
    // Whole octaves need 1/c lattice points each and a power-of-two cap.
    let points_per_octave = (1.0 / config.cone_angle).round();
    let steps_per_grid = (config.max_steps as f32 / geometry.resolution as f32).max(1.0);
    let last_octave = (geometry.cascades as i32 - 1) + steps_per_grid.log2().round() as i32;
    Some(Cone {
        min_step: config.step,
        inverse_min_step: 1.0 / config.step,
        octave_start: config.step * points_per_octave,
        inverse_octave_start: 1.0 / (config.step * points_per_octave),
        points_per_octave,
        last_octave: last_octave.max(0),
    })
}

/// Cells per side of a block of the coarse occupancy.
pub const COARSE: u32 = 4;

/// Words of the coarse occupancy of `geometry`, or `None` when its
/// resolution is not a multiple of 32 (one bitfield word per row of
/// cells is then not 8 whole blocks; marching goes cell by cell).
pub fn coarse_words(geometry: &GridGeometry) -> Option<usize> {
    if !geometry.resolution.is_multiple_of(32) {
        return None;
    }
    let side = (geometry.resolution / COARSE) as usize;
    Some((geometry.cascades as usize * side * side * side).div_ceil(32))
}

#[inline(always)]
fn block_index(geometry: &GridGeometry, cell: Cell) -> usize {
    let side = (geometry.resolution / COARSE) as usize;
    let [x, y, z] = cell.xyz.map(|c| (c / COARSE) as usize);
    cell.cascade as usize * side * side * side + x + side * (y + side * z)
}

/// Fills `coarse` with one bit per block of [`COARSE`]³ cells of
/// `bitfield`, set when any cell of the block is occupied. Returns false
/// (and leaves `coarse` empty) when the geometry has no coarse level.
pub fn coarse_occupancy(geometry: &GridGeometry, bitfield: &[u32], coarse: &mut Vec<u32>) -> bool {
    coarse.clear();
    let Some(words) = coarse_words(geometry) else {
        return false;
    };
    coarse.resize(words, 0);
    let res = geometry.resolution as usize;
    let side = res / COARSE as usize;
    let words_per_row = res / 32;
    for cascade in 0..geometry.cascades as usize {
        for z in 0..res {
            for y in 0..res {
                let row = (cascade * res * res + z * res + y) * words_per_row;
                for (w, &word) in bitfield[row..row + words_per_row].iter().enumerate() {
                    if word == 0 {
                        continue;
                    }
                    for nibble in 0..8 {
                        if (word >> (4 * nibble)) & 0xf != 0 {
                            let bx = w * 8 + nibble;
                            let block = cascade * side * side * side
                                + bx
                                + side * (y / COARSE as usize + side * (z / COARSE as usize));
                            coarse[block >> 5] |= 1 << (block & 31);
                        }
                    }
                }
            }
        }
    }
    true
}

/// How far exit faces are pulled into a cell before a skip: 4e-6 times the
/// largest coordinate is about 33 ulps there, against at most ~10 ulps of
/// rounding in a position, an exit distance and its conversion to a lattice
/// index. A cell is 1/128 wide, so the margin costs nothing measurable.
pub fn skip_margin(geometry: &GridGeometry) -> f32 {
    4e-6 * geometry.max_coordinate()
}

/// The samples of a batch of rays.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct MarchedSamples {
    /// S × 3, unit-cube coordinates.
    pub positions: Vec<f32>,
    /// S × 3, the ray's world direction (unit).
    pub directions: Vec<f32>,
    /// S, the step in world units.
    pub dt: Vec<f32>,
    /// S, distance from the ray's origin in world units.
    pub t: Vec<f32>,
    /// R + 1; ray r owns samples ray_offsets[r]..ray_offsets[r + 1].
    pub ray_offsets: Vec<u32>,
}

impl MarchedSamples {
    pub fn sample_count(&self) -> usize {
        self.dt.len()
    }

    pub fn ray_count(&self) -> usize {
        self.ray_offsets.len().saturating_sub(1)
    }

    pub fn ray(&self, r: usize) -> std::ops::Range<usize> {
        self.ray_offsets[r] as usize..self.ray_offsets[r + 1] as usize
    }
}

/// What a batch march did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct MarchStats {
    pub rays: usize,
    /// Rays that got their samples; the rest were over the budget.
    pub rays_kept: usize,
    pub samples: usize,
}

/// Per-thread scratch of [`march`], kept between calls.
#[derive(Debug, Default)]
pub struct MarchWorkspace {
    blocks: Vec<Vec<u32>>,
    /// The grid's coarse occupancy ([`coarse_occupancy`]), rebuilt per
    /// march (a quarter-millisecond pass over the bitfield).
    coarse: Vec<u32>,
    rays: Vec<Option<RayMarch>>,
    counts: Vec<u32>,
}

/// Rays per parallel task: a few hundred samples of work at least, and
/// enough tasks for rayon to balance rays of very different lengths.
const RAYS_PER_BLOCK: usize = 64;

/// Blocks walked per wave of pass 1 before checking the budget: 2048 rays,
/// a few waves per training batch, each enough work for rayon to balance.
const WAVE_BLOCKS: usize = 32;

/// Grows or shrinks `v` to `n` without rewriting what it already holds.
fn set_len(v: &mut Vec<f32>, n: usize) {
    v.truncate(n);
    v.resize(n, 0.0);
}

/// Marches R rays (`origins`, `directions`: R × 3, world space, unit
/// directions) through `grid` into `out`.
///
/// Two passes, like the gpu: the first walks every ray and keeps only the
/// lattice indices of its samples (4 bytes each) per block of rays; then the
/// counts are scanned into offsets; the second writes each sample's
/// position, direction, t and dt into its final place. The result does not
/// depend on the number of threads.
pub fn march(
    grid: &OccupancyGrid,
    origins: &[f32],
    directions: &[f32],
    params: &MarchParams,
    workspace: &mut MarchWorkspace,
    out: &mut MarchedSamples,
) -> MarchStats {
    assert_eq!(
        origins.len(),
        directions.len(),
        "origins and directions differ in length"
    );
    assert!(origins.len().is_multiple_of(3), "rays are rows of 3 floats");
    let ray_count = origins.len() / 3;
    let mut marcher = Marcher::new(grid, &params.config, &params.mapping);
    if coarse_occupancy(&grid.geometry(), grid.bitfield(), &mut workspace.coarse) {
        marcher = marcher.with_coarse(&workspace.coarse);
    }

    // Pass 1: lattice indices of the samples, per block, in waves of
    // blocks. Rays are kept in order while they fit the budget, so once the
    // rays walked hold more samples than the budget, no later ray can be
    // kept: those are not walked at all (the batch sizer asks for more rays
    // than fit, and walking them was most of the march's time).
    let blocks = ray_count.div_ceil(RAYS_PER_BLOCK);
    if workspace.blocks.len() < blocks {
        workspace.blocks.resize_with(blocks, Vec::new);
    }
    workspace.rays.clear();
    workspace.rays.resize(ray_count, None);
    workspace.counts.clear();
    workspace.counts.resize(ray_count, 0);
    let mut walked_blocks = 0;
    let mut walked_samples = 0usize;
    while walked_blocks < blocks && walked_samples <= params.sample_budget {
        let wave = walked_blocks..(walked_blocks + WAVE_BLOCKS).min(blocks);
        let wave_rays = wave.start * RAYS_PER_BLOCK..(wave.end * RAYS_PER_BLOCK).min(ray_count);
        workspace.blocks[wave.clone()]
            .par_iter_mut()
            .zip(workspace.rays[wave_rays.clone()].par_chunks_mut(RAYS_PER_BLOCK))
            .zip(workspace.counts[wave_rays.clone()].par_chunks_mut(RAYS_PER_BLOCK))
            .enumerate()
            .for_each(|(i, ((indices, rays), counts))| {
                let b = wave.start + i;
                indices.clear();
                for (i, (ray, count)) in rays.iter_mut().zip(counts.iter_mut()).enumerate() {
                    let r = b * RAYS_PER_BLOCK + i;
                    let origin = Vec3::from_slice(&origins[3 * r..3 * r + 3]);
                    let direction = Vec3::from_slice(&directions[3 * r..3 * r + 3]);
                    let u = params
                        .jitter_seed
                        .map_or(0.0, |seed| jitter(seed, r as u32));
                    *ray = marcher.prepare(origin, direction, u);
                    let before = indices.len();
                    if let Some(ray) = ray {
                        let mut k = 0;
                        marcher.walk(ray, &mut k, params.config.max_steps, |k| indices.push(k));
                    }
                    *count = (indices.len() - before) as u32;
                }
            });
        walked_samples += workspace.counts[wave_rays]
            .iter()
            .map(|&c| c as usize)
            .sum::<usize>();
        walked_blocks = wave.end;
    }
    // Blocks not walked hold no samples (their rays are past the budget).
    for indices in &mut workspace.blocks[walked_blocks..blocks] {
        indices.clear();
    }

    // Offsets, keeping rays while they fit the budget.
    out.ray_offsets.clear();
    out.ray_offsets.reserve(ray_count + 1);
    out.ray_offsets.push(0);
    let mut total = 0usize;
    let mut rays_kept = ray_count;
    for (r, &count) in workspace.counts.iter().enumerate() {
        if rays_kept == ray_count && total + count as usize > params.sample_budget {
            rays_kept = r;
        }
        if r < rays_kept {
            total += count as usize;
        }
        out.ray_offsets.push(total as u32);
    }
    assert!(
        total <= u32::MAX as usize,
        "more samples than u32 offsets can hold"
    );

    // Pass 2: write the samples of each block into its own slices.
    set_len(&mut out.positions, 3 * total);
    set_len(&mut out.directions, 3 * total);
    set_len(&mut out.dt, total);
    set_len(&mut out.t, total);
    let mut positions = out.positions.as_mut_slice();
    let mut directions_out = out.directions.as_mut_slice();
    let mut dts = out.dt.as_mut_slice();
    let mut ts = out.t.as_mut_slice();
    let mut tasks = Vec::with_capacity(blocks);
    for b in 0..blocks {
        let first = b * RAYS_PER_BLOCK;
        let last = (first + RAYS_PER_BLOCK).min(ray_count);
        let n = (out.ray_offsets[last] - out.ray_offsets[first]) as usize;
        let (p, rest_p) = positions.split_at_mut(3 * n);
        let (d, rest_d) = directions_out.split_at_mut(3 * n);
        let (dt, rest_dt) = dts.split_at_mut(n);
        let (t, rest_t) = ts.split_at_mut(n);
        (positions, directions_out, dts, ts) = (rest_p, rest_d, rest_dt, rest_t);
        tasks.push((b, p, d, dt, t));
    }
    let inverse_scale = 1.0 / params.mapping.scale;
    let offsets = &out.ray_offsets;
    let rays = &workspace.rays;
    let counts = &workspace.counts;
    let block_indices = &workspace.blocks;
    tasks
        .into_par_iter()
        .for_each(|(b, mut p, mut d, mut dts, mut ts)| {
            let first = b * RAYS_PER_BLOCK;
            let last = (first + RAYS_PER_BLOCK).min(ray_count);
            let mut read = 0usize;
            for r in first..last {
                let count = counts[r] as usize;
                let kept = (offsets[r + 1] - offsets[r]) as usize;
                if let Some(ray) = &rays[r] {
                    let (p_ray, p_rest) = std::mem::take(&mut p).split_at_mut(3 * kept);
                    let (d_ray, d_rest) = std::mem::take(&mut d).split_at_mut(3 * kept);
                    let (dt_ray, dt_rest) = std::mem::take(&mut dts).split_at_mut(kept);
                    let (t_ray, t_rest) = std::mem::take(&mut ts).split_at_mut(kept);
                    (p, d, dts, ts) = (p_rest, d_rest, dt_rest, t_rest);
                    let [ex, ey, ez] = ray.entry.to_array();
                    let [dx, dy, dz] = ray.direction.to_array();
                    for ((((&k, p), d), dt_out), t_out) in block_indices[b][read..read + kept]
                        .iter()
                        .zip(p_ray.chunks_exact_mut(3))
                        .zip(d_ray.chunks_exact_mut(3))
                        .zip(dt_ray.iter_mut())
                        .zip(t_ray.iter_mut())
                    {
                        // The same expression as `RayMarch::position`, so the
                        // positions are the ones pass 1 looked up.
                        let s = ray.s(k);
                        p[0] = ex + dx * s;
                        p[1] = ey + dy * s;
                        p[2] = ez + dz * s;
                        d[0] = dx;
                        d[1] = dy;
                        d[2] = dz;
                        *dt_out = ray.step(k) * inverse_scale;
                        *t_out = (ray.t_enter + s) * inverse_scale;
                    }
                }
                read += count;
            }
        });

    MarchStats {
        rays: ray_count,
        rays_kept,
        samples: total,
    }
}

/// Renders R rays through a field with early termination: densities and
/// colours are evaluated in rounds of about `chunk_samples` samples; each
/// ray stops once its transmittance falls below
/// `config.min_transmittance`, after `config.max_steps` samples, or when
/// it leaves the box. Compositing as in [`super::composite::composite`]
/// (wᵢ = Tᵢ(1 − e^(−σᵢδᵢ)), expected depth Σwᵢtᵢ, background weighted by the
/// final transmittance), so up to the 1e-4 cut-off the result equals
/// marching everything and compositing it.
///
/// `field(samples, density n, rgb n×3)` fills the last two for a round of
/// n [`GridSamples`]. Outputs: `colour` R × 3, `depth` R, `opacity` R (world units for
/// depth).
/// A round of samples handed to the field while rendering through the grid.
pub struct GridSamples<'a> {
    /// n × 3, unit-cube coordinates.
    pub positions: &'a [f32],
    /// n × 3, each sample's ray's unit world direction.
    pub directions: &'a [f32],
    /// n, distance from the ray's origin in world units.
    pub t: &'a [f32],
    /// n, the index of each sample's ray among the rays rendered.
    pub rays: &'a [u32],
    /// n, each sample's step in world units.
    pub dt: &'a [f32],
}

#[allow(clippy::too_many_arguments)]
pub fn march_and_composite<F>(
    grid: &OccupancyGrid,
    origins: &[f32],
    directions: &[f32],
    mapping: &UnitCubeMapping,
    config: &MarchConfig,
    background: [f32; 3],
    chunk_samples: usize,
    mut field: F,
    colour: &mut [f32],
    depth: &mut [f32],
    opacity: &mut [f32],
) where
    F: FnMut(&GridSamples, &mut [f32], &mut [f32]),
{
    let ray_count = origins.len() / 3;
    assert_eq!(directions.len(), 3 * ray_count);
    assert!(
        colour.len() == 3 * ray_count && depth.len() == ray_count && opacity.len() == ray_count
    );
    let marcher = Marcher::new(grid, config, mapping);

    #[derive(Clone, Copy)]
    struct State {
        ray: Option<RayMarch>,
        k: u32,
        emitted: u32,
        optical_depth: f32,
        colour: [f32; 3],
        depth: f32,
    }
    let mut states: Vec<State> = (0..ray_count)
        .into_par_iter()
        .map(|r| State {
            ray: marcher.prepare(
                Vec3::from_slice(&origins[3 * r..3 * r + 3]),
                Vec3::from_slice(&directions[3 * r..3 * r + 3]),
                0.0,
            ),
            k: 0,
            emitted: 0,
            optical_depth: 0.0,
            colour: [0.0; 3],
            depth: 0.0,
        })
        .collect();
    let mut active: Vec<u32> = (0..ray_count as u32)
        .filter(|&r| states[r as usize].ray.is_some())
        .collect();
    let stop_depth = -config.min_transmittance.ln();
    let chunk = chunk_samples.max(1);

    let mut counts: Vec<u32> = Vec::new();
    let mut next: Vec<u32> = Vec::new();
    let mut lattice: Vec<u32> = Vec::new();
    let mut positions: Vec<f32> = Vec::new();
    let mut sample_directions: Vec<f32> = Vec::new();
    let mut sample_t: Vec<f32> = Vec::new();
    let mut sample_rays: Vec<u32> = Vec::new();
    let mut sample_dt: Vec<f32> = Vec::new();
    let mut sigma: Vec<f32> = Vec::new();
    let mut rgb: Vec<f32> = Vec::new();
    let mut finished: Vec<bool> = Vec::new();
    while !active.is_empty() {
        // Few samples per ray while many rays are active (most stop early on
        // opaque surfaces), more once few are left; 4 to 64 per round.
        let per_ray = (chunk / active.len()).clamp(4, 64);
        let group = (chunk / per_ray).max(1);
        for rays in active.chunks(group) {
            counts.resize(rays.len(), 0);
            next.resize(rays.len(), 0);
            lattice.resize(rays.len() * per_ray, 0);
            finished.resize(rays.len(), false);
            // March each ray's next few samples into its own slots.
            counts
                .par_iter_mut()
                .zip(next.par_iter_mut())
                .zip(lattice.par_chunks_mut(per_ray))
                .zip(finished.par_iter_mut())
                .zip(rays.par_iter())
                .for_each(|((((count, next), slots), done), &r)| {
                    let state = &states[r as usize];
                    let ray = state.ray.as_ref().expect("active rays hit the box");
                    let limit = (per_ray as u32).min(config.max_steps - state.emitted);
                    let mut k = state.k;
                    let mut n = 0;
                    *done = marcher.walk(ray, &mut k, limit, |k| {
                        slots[n] = k;
                        n += 1;
                    });
                    *next = k;
                    *count = n as u32;
                });
            let total: usize = counts.iter().map(|&c| c as usize).sum();
            positions.clear();
            sample_directions.clear();
            sample_t.clear();
            sample_rays.clear();
            sample_dt.clear();
            for (i, &r) in rays.iter().enumerate() {
                let ray = states[r as usize].ray.as_ref().expect("active");
                for &k in &lattice[i * per_ray..i * per_ray + counts[i] as usize] {
                    positions.extend_from_slice(&ray.position(k).to_array());
                    sample_directions.extend_from_slice(&ray.direction.to_array());
                    sample_t.push(marcher.world_t(ray, k));
                    sample_rays.push(r);
                    sample_dt.push(marcher.world_dt(ray, k));
                }
            }
            sigma.resize(total, 0.0);
            rgb.resize(3 * total, 0.0);
            if total > 0 {
                let samples = GridSamples {
                    positions: &positions,
                    directions: &sample_directions,
                    t: &sample_t,
                    rays: &sample_rays,
                    dt: &sample_dt,
                };
                field(&samples, &mut sigma, &mut rgb);
            }
            // Composite, in order along each ray, and advance its state.
            let mut offset = 0;
            for (i, &r) in rays.iter().enumerate() {
                let state = &mut states[r as usize];
                let ray = state.ray.expect("active");
                let n = counts[i] as usize;
                for j in 0..n {
                    if state.optical_depth > stop_depth {
                        break;
                    }
                    let k = lattice[i * per_ray + j];
                    let tau = (sigma[offset + j] * marcher.world_dt(&ray, k)).max(0.0);
                    let weight = (-state.optical_depth).exp() * -(-tau).exp_m1();
                    for c in 0..3 {
                        state.colour[c] += weight * rgb[3 * (offset + j) + c];
                    }
                    state.depth += weight * marcher.world_t(&ray, k);
                    state.optical_depth += tau;
                }
                offset += n;
                state.emitted += n as u32;
                state.k = next[i];
                if finished[i]
                    || state.emitted >= config.max_steps
                    || state.optical_depth > stop_depth
                {
                    state.ray = None;
                }
            }
        }
        active.retain(|&r| states[r as usize].ray.is_some());
    }

    for (r, state) in states.iter().enumerate() {
        let transmittance = (-state.optical_depth).exp();
        for c in 0..3 {
            colour[3 * r + c] = state.colour[c] + transmittance * background[c];
        }
        depth[r] = state.depth;
        opacity[r] = 1.0 - transmittance;
    }
}

/// The marching jitter seed of a step (both engines, so they march the
/// same samples).
pub fn mix_seed(seed: u64, step: u32) -> u32 {
    let mixed = (seed ^ 0x6a69_7474).wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ step as u64;
    (mixed ^ (mixed >> 32)) as u32
}

/// Renders rays with early termination through the occupancy grid, with
/// `field` giving σ and colour for each round of samples (see
/// [`march_and_composite`]).
#[allow(clippy::too_many_arguments)]
pub fn render_through_grid(
    grid: &OccupancyGrid,
    mapping: &UnitCubeMapping,
    origins: &[Vec3],
    directions: &[Vec3],
    background: [f32; 3],
    config: &MarchConfig,
    chunk_samples: usize,
    field: impl FnMut(&GridSamples, &mut [f32], &mut [f32]),
    out: &mut [RenderedPixel],
) {
    let n = origins.len();
    let flat = |v: &[Vec3]| v.iter().flat_map(|x| x.to_array()).collect::<Vec<f32>>();
    let (origins, directions) = (flat(origins), flat(directions));
    let mut colour = vec![0f32; 3 * n];
    let mut depth = vec![0f32; n];
    let mut opacity = vec![0f32; n];
    march_and_composite(
        grid,
        &origins,
        &directions,
        mapping,
        config,
        background,
        chunk_samples,
        field,
        &mut colour,
        &mut depth,
        &mut opacity,
    );
    for (i, pixel) in out.iter_mut().enumerate().take(n) {
        *pixel = RenderedPixel {
            rgb: [colour[3 * i], colour[3 * i + 1], colour[3 * i + 2]],
            opacity: opacity[i],
            depth: depth[i],
        };
    }
}

pub use crate::engine::shared::batch_sizer::BatchSizer;

#[cfg(test)]
mod tests;
