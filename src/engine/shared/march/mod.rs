//! Ray marching through the occupancy grid, as both engines march:
//! Instant-NGP's sample generation (Müller et al. 2022, appendix E.1;
//! instant-ngp testbed). What is here runs on the host and is the same for
//! either engine: the march's parameters and seeds, the lattice of a ray
//! ([`Lattice`], cones) and the walk along it ([`Marcher`], in
//! `lattice.rs`), the grid's coarse occupancy and skip margin, the batch's
//! samples and statistics, and the render loop that marches and
//! composites in rounds (`render.rs`). The `cpu` engine's batch march
//! (`engine::cpu::march::march`) and the `gpu` engine's kernels
//! (`engine::gpu::march`) produce the samples described here.
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
use crate::field::common::MarchConfig;
use crate::model::RenderedPixel;
use crate::scene::{Aabb, UnitCubeMapping};

mod lattice;
mod render;

pub use lattice::{Cone, Lattice, Marcher, cone_for};
pub use render::{
    CompositedRays, GridRendering, GridSamples, march_and_composite, mix_seed, render_through_grid,
};

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
