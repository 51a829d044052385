//! What both engines' model drivers share, host-side and engine-neutral:
//! what a model is called and which sampler its checkpoints were trained
//! with, the rays' near and far bounds, the size of a batch and of the
//! paper sampler's chunks, the seeds of each chunk's jitter, and the
//! inputs a field gets for samples marched through the grid when
//! rendering (world positions, or frustum Gaussians). The `cpu` engine's
//! `CpuModel` and the `gpu` engine's `GpuModel` both call these, so the two
//! see the same rays, seeds and samples.

use std::ops::Range;

use glam::Vec3;
use rayon::prelude::*;

use super::batch_sizer::BatchSizer;
use super::frustum::frustum_gaussian;
use super::march::{GridSamples, mix32};
use super::occupancy::{GridPace, OccupancyGrid};
use crate::field::common::{
    BatchSize, MarchConfig, OccupancyConfig, RayBounds, Recipe, SamplerKind,
};
use crate::field::params::ParamLayout;
use crate::scene::{Aabb, UnitCubeMapping};

/// Rays per chunk of the paper's sampler: 256 rays × 192 fine samples is
/// 49k rows of activations (~0.5 GB for NeRF's networks).
pub const RAYS_PER_CHUNK: usize = 256;

/// Rows per rayon task in the element-wise passes.
const ROWS_PER_TASK: usize = 4096;

/// Names and settings that identify a model built on either engine's
/// driver.
#[derive(Debug, Clone)]
pub struct ModelIdentity {
    /// Shown to the user, e.g. "NeRF".
    pub name: &'static str,
    /// Stored in checkpoints, e.g. "nerf".
    pub key: &'static str,
    /// The sampler's name, stored in checkpoints ("paper", "occupancy"),
    /// for models with a choice of samplers.
    pub sampling: Option<&'static str>,
}

/// A buffer resized to `n` values, all zero: what every output here is
/// written into.
fn set_len(v: &mut Vec<f32>, n: usize) {
    v.truncate(n);
    v.resize(n, 0.0);
}

/// What a model says it is: "NeRF (occupancy sampling, cpu)",
/// "Instant-NGP (gpu)".
pub fn describe(identity: &ModelIdentity, engine: &str) -> String {
    match identity.sampling {
        Some(sampling) => format!("{} ({sampling} sampling, {engine})", identity.name),
        None => format!("{} ({engine})", identity.name),
    }
}

/// Refuses a checkpoint trained with another sampler than `identity`'s.
pub(crate) fn check_sampling(
    header: &super::state::ModelHeader,
    identity: &ModelIdentity,
) -> Result<(), String> {
    let saved = header.sampling.as_deref();
    if saved == identity.sampling {
        return Ok(());
    }
    let name = |s: Option<&str>| s.map_or("its model's only".to_string(), str::to_string);
    Err(format!(
        "the checkpoint was trained with {} sampling, this model uses {}",
        name(saved),
        name(identity.sampling)
    ))
}

/// Near and far bounds of each ray (R × 3 origins and directions) under
/// `bounds`, `scene_box` being the scene's box.
pub fn ray_bounds(
    bounds: RayBounds,
    scene_box: &Aabb,
    origins: &[f32],
    directions: &[f32],
    near: &mut Vec<f32>,
    far: &mut Vec<f32>,
) {
    let rays = origins.len() / 3;
    set_len(near, rays);
    set_len(far, rays);
    for r in 0..rays {
        let (n, f) = match bounds {
            RayBounds::Fixed { near, far } => (near, far),
            RayBounds::SceneBox => scene_box
                .intersect(
                    Vec3::from_slice(&origins[3 * r..]),
                    Vec3::from_slice(&directions[3 * r..]),
                    0.0,
                )
                // A ray that misses the box gets an empty interval:
                // every sample at its origin with zero length, so it
                // shows the background.
                .unwrap_or((0.0, 0.0)),
        };
        near[r] = n;
        far[r] = f.max(n);
    }
}

/// The seed of the random sample positions of `level` for the rays of
/// chunk `chunk` (of [`RAYS_PER_CHUNK`] rays by default) in the step seeded `step_seed`:
/// each chunk and level draws its own jitter, the same on either engine.
pub fn chunk_jitter_seed(step_seed: u32, chunk: usize, level: usize) -> u32 {
    mix32(step_seed ^ mix32((chunk * 8 + level) as u32))
}

/// The variance per axis at which a frustum field is asked for the density
/// of a grid cell as a whole: that of a uniform distribution over the finest
/// cascade's cell (side²/12), so the grid sees what the frustums that fill
/// such a cell see, not the alias of the highest frequencies at one point.
pub fn grid_cell_variance(grid: &OccupancyGrid, mapping: &UnitCubeMapping) -> f32 {
    let cell = 1.0 / (grid.geometry().cells_per_unit(0) * mapping.scale);
    cell * cell / 12.0
}

/// World Gaussians (means and covariance diagonals, n × 3 each) of samples
/// marched through the grid for rendering: as in training, each sample
/// stands for the frustum of its step, centred on it. `origins`,
/// `directions` and cone `radii` are the rendered rays' (a missing radius
/// is 0: a ray without a cone).
pub fn grid_sample_gaussians(
    samples: &GridSamples,
    origins: &[Vec3],
    directions: &[Vec3],
    radii: &[f32],
    world: &mut Vec<f32>,
    variances: &mut Vec<f32>,
) {
    let n = samples.t.len();
    set_len(world, 3 * n);
    set_len(variances, 3 * n);
    for (i, ((&t, &dt), &r)) in samples
        .t
        .iter()
        .zip(samples.dt)
        .zip(samples.rays)
        .enumerate()
    {
        let r = r as usize;
        let (mean, variance) = frustum_gaussian(
            origins[r],
            directions[r],
            radii.get(r).copied().unwrap_or(0.0),
            (t - 0.5 * dt).max(0.0),
            t + 0.5 * dt,
        );
        world[3 * i..3 * i + 3].copy_from_slice(&mean.to_array());
        variances[3 * i..3 * i + 3].copy_from_slice(&variance.to_array());
    }
}

/// Rays for the next batch of a model that sizes its batches as
/// `batch_size` says (by samples, through the sizer's estimate of samples
/// per ray).
pub fn rays_for_batch(batch_size: BatchSize, sizer: &BatchSizer) -> usize {
    match batch_size {
        BatchSize::Rays(rays) => rays,
        BatchSize::Samples(_) => sizer.rays(),
    }
}

/// A batch's size in its own unit (`batch_of` keeps a driver's batch in
/// the recipe's unit, so two batches of one driver compare).
fn batch_units(batch: BatchSize) -> u64 {
    match batch {
        BatchSize::Rays(n) | BatchSize::Samples(n) => n as u64,
    }
}

/// Which pass finds where each marched ray becomes opaque (its cut), for a
/// field whose forward pass costs `forward_macs` multiply-adds a sample and
/// whose σ alone costs `density_macs`, when the last step's rays used
/// `used_fraction` of their marched samples. After a ray's cut no sample's
/// colour is read and every gradient through it is zero, so the cut needs
/// σ of every marched sample; two ways to find it:
///
/// - σ first (`true`): a σ-only pass over every marched sample, then the
///   forward and backward passes on the samples before the cut only (the
///   compaction of instant-ngp);
/// - forward first (`false`): the forward pass over every marched sample
///   finds the cut as it goes, and the backward pass runs on them all,
///   zero past the cut.
///
/// Per marched sample the first costs D + 3F·u and the second 3F (D the σ
/// pass, F the forward pass, u the share used; the backward pass is twice
/// the forward), so forward first wins above u = 1 − D/3F: 0.72 for NeRF's
/// field, whose rays on a Blender object use 90–100 % of their samples.
/// A field that cannot find the cut in its forward pass
/// (`may_find_cut_in_forward` false) always goes σ first. Both engines
/// decide with this, so they take the same passes.
pub fn sigma_first(
    may_find_cut_in_forward: bool,
    forward_macs: usize,
    density_macs: usize,
    used_fraction: f64,
) -> bool {
    !may_find_cut_in_forward
        || used_fraction <= 1.0 - density_macs as f64 / (3 * forward_macs) as f64
}

/// What a field of world positions takes for samples marched through the
/// grid for rendering: for a recipe of `frustums`, each sample's Gaussian
/// ([`grid_sample_gaussians`]: means into `world`, covariance diagonals
/// into `variances`); else its position mapped to the world.
#[allow(clippy::too_many_arguments)]
pub fn grid_sample_inputs(
    samples: &GridSamples,
    frustums: bool,
    mapping: &UnitCubeMapping,
    origins: &[Vec3],
    directions: &[Vec3],
    radii: &[f32],
    world: &mut Vec<f32>,
    variances: &mut Vec<f32>,
) {
    if frustums {
        grid_sample_gaussians(samples, origins, directions, radii, world, variances);
    } else {
        to_world(mapping, samples.positions, world);
    }
}

/// Unit-cube positions (n × 3) to world positions.
pub fn to_world(mapping: &UnitCubeMapping, unit: &[f32], world: &mut Vec<f32>) {
    set_len(world, unit.len());
    let (scale, offset) = (mapping.scale, mapping.offset.to_array());
    world
        .par_chunks_mut(3 * ROWS_PER_TASK)
        .zip(unit.par_chunks(3 * ROWS_PER_TASK))
        .for_each(|(w, u)| {
            for (w, u) in w.chunks_exact_mut(3).zip(u.chunks_exact(3)) {
                for c in 0..3 {
                    w[c] = (u[c] - offset[c]) / scale;
                }
            }
        });
}

/// What both engines' drivers hold alike: the model's identity and
/// recipe, its parameters' layout and where each field's sit, and the size
/// of its batches. The drivers answer `describe`, `rays_for_next_batch` and
/// `centre_crop` from it, and build their occupancy grid with it.
#[derive(Debug, Clone)]
pub struct DriverCore {
    pub identity: ModelIdentity,
    pub recipe: Recipe,
    /// Every field's parts, one after the other: what Adam updates how.
    pub layout: ParamLayout,
    /// Where each field's parameters sit in the flat vector.
    pub ranges: Vec<Range<usize>>,
    /// Rays per batch for fixed-count levels, or samples per batch for
    /// marched ones.
    pub batch_size: BatchSize,
    pub batch_sizer: BatchSizer,
    /// The batch the occupancy grid's intervals count steps of: this
    /// driver's own, or, for the viewer, the one `zrak train` takes on the
    /// engine (see [`GridPace`]).
    pub grid_batch: BatchSize,
}

impl DriverCore {
    /// `batch_size` replaces the recipe's batch (tests and the viewer ask
    /// for smaller ones); `grid_batch` is the one the occupancy grid's
    /// intervals count steps of (`None`: the recipe's).
    pub fn new(
        identity: ModelIdentity,
        recipe: Recipe,
        layout: ParamLayout,
        ranges: Vec<Range<usize>>,
        batch_size: Option<BatchSize>,
        grid_batch: Option<BatchSize>,
    ) -> Self {
        let grid_batch = grid_batch.unwrap_or(recipe.batch);
        let batch_size = batch_size.unwrap_or(recipe.batch);
        let batch_sizer = BatchSizer::new(match batch_size {
            BatchSize::Samples(samples) => samples,
            BatchSize::Rays(rays) => rays,
        });
        Self {
            identity,
            recipe,
            layout,
            ranges,
            batch_size,
            batch_sizer,
            grid_batch,
        }
    }

    /// Whether the recipe's one level marches through the occupancy grid.
    pub fn marches(&self) -> bool {
        self.recipe.levels[0].sampler == SamplerKind::Occupancy
    }

    /// The occupancy grid of a recipe that marches through one, for a scene
    /// of `mapping`. The grid stores σ · step with σ per world unit, the
    /// step being Instant-NGP's smallest (√3/1024 of the unit cube)
    /// whatever this recipe marches with: the occupancy threshold (0.01)
    /// then means the same density for every model. Its updates query
    /// σ in chunks of a batch's samples.
    pub fn occupancy_grid(&self, mapping: &UnitCubeMapping) -> Option<OccupancyGrid> {
        self.marches().then(|| {
            let mut grid = OccupancyGrid::new(
                self.recipe.occupancy,
                OccupancyConfig::cascades(mapping.aabb_scale),
                MarchConfig::PAPER.step / mapping.scale,
            );
            if let BatchSize::Samples(samples) = self.batch_size {
                grid.chunk = samples;
            }
            grid.pace = GridPace {
                step_batch: batch_units(self.batch_size),
                recipe_batch: batch_units(self.grid_batch),
            };
            grid
        })
    }

    /// What the model says it is: "NeRF (occupancy sampling, cpu)".
    pub fn describe(&self, engine: &str) -> String {
        describe(&self.identity, engine)
    }

    /// Rays for the next batch.
    pub fn rays_for_next_batch(&self) -> usize {
        rays_for_batch(self.batch_size, &self.batch_sizer)
    }

    /// The share of the image's centre that rays are drawn from at `step`.
    pub fn centre_crop(&self, step: u32) -> Option<f32> {
        self.recipe.centre_crop_at(step)
    }
}
