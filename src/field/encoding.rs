//! The shapes of the input encodings, as both engines and the checkpoints
//! see them: the multiresolution hash grid's levels and where their entries
//! sit ([`HashGridLayout`], Müller et al. 2022, section 3), the frequency
//! encoding's width ([`FrequencyEncoding`], NeRF's γ and Mip-NeRF's IPE)
//! and the spherical-harmonics degrees ([`SH_MAX_DEGREE`]). The encodings
//! themselves are computed by each engine's stages (`engine::cpu::hash_grid`,
//! `frequency`, `sh` and their `engine::gpu` twins), which document the
//! formulas and the output layouts.

use crate::rng::splitmix64;

// The multiresolution hash grid.

/// A multiresolution hash encoding's settings (Müller et al. 2022,
/// section 3 and table 1; Instant-NGP's values are in `ngp.rs`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HashGridConfig {
    /// L, the number of resolution levels.
    pub levels: u32,
    /// F, features per table entry.
    pub features_per_level: u32,
    /// log2 of T, the entries per level.
    pub log2_table_size: u32,
    /// N_min, the coarsest grid resolution.
    pub base_resolution: u32,
    /// N_max, the finest grid resolution.
    pub finest_resolution: u32,
    /// Entries start uniform in ±this (paper, section 4: U(−1e-4, 1e-4)).
    pub init_range: f32,
    /// Side of the cube the grid spans, centred on the unit cube's centre:
    /// the scene's box (side aabb_scale). Positions are mapped from it onto
    /// the grid's [0, 1]³, as the testbed's `warp_position` maps its aabb,
    /// so N_max = 2048 · aabb_scale across the box is 2048 per unit-cube
    /// length on every scene.
    pub extent: f32,
}

impl HashGridConfig {
    /// How a unit-cube position x reaches the grid: (x − box_min) ·
    /// inverse_extent, returned as (box_min, inverse_extent) in f64 for each
    /// engine to round to its own precision ((0, 1) for the unit cube, which
    /// leaves x as it is).
    pub fn box_mapping(&self) -> (f64, f64) {
        let extent = self.extent as f64;
        (0.5 - 0.5 * extent, 1.0 / extent)
    }

    /// b = exp((ln N_max − ln N_min) / (L − 1)) (paper, eq. 3).
    pub fn growth_factor(&self) -> f64 {
        if self.levels <= 1 {
            return 1.0;
        }
        (((self.finest_resolution as f64).ln() - (self.base_resolution as f64).ln())
            / (self.levels - 1) as f64)
            .exp()
    }

    /// Encoded width: L · F.
    pub fn output_width(&self) -> usize {
        (self.levels * self.features_per_level) as usize
    }

    pub fn table_size(&self) -> usize {
        1 << self.log2_table_size
    }
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
    /// Starting parameters: each uniform in ±`init_range` (paper, section
    /// 4), from a counter-based generator, so the result depends only on
    /// `seed` and not on the number of threads.
    pub fn init_params(&self, seed: u64) -> Vec<f32> {
        use rayon::prelude::*;
        let range = self.config().init_range;
        let key = splitmix64(seed ^ 0x6861_7368_6772_6964); // "hashgrid"
        let mut params = vec![0.0f32; self.param_count()];
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

// The frequency encoding.

/// The most frequencies supported: 2^31 is the largest scale, and ½·4^31 =
/// 2^61 still fits comfortably in f32, so every scale is an exact f32.
pub const MAX_FREQUENCIES: u32 = 32;

/// Frequencies 2^0 … 2^(frequencies−1) of each of 3 input coordinates.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FrequencyEncoding {
    pub frequencies: u32,
    pub include_input: bool,
}

impl FrequencyEncoding {
    /// Values per row: the 3 inputs when included, and a sine and a cosine
    /// per coordinate and frequency.
    pub const fn output_width(&self) -> usize {
        3 * self.include_input as usize + 6 * self.frequencies as usize
    }
}

// Spherical harmonics.

/// The highest degree supported (bands l ≤ 3).
pub const SH_MAX_DEGREE: u32 = 4;

/// Number of coefficients for `degree`.
pub fn sh_coefficients(degree: u32) -> usize {
    (degree * degree) as usize
}
