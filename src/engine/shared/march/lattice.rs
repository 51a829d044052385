//! The lattice of one ray and the walk along it through the grid: where
//! both engines' marches put their samples.

use super::*;

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

#[cfg(test)]
mod tests;
