//! The `cpu` engine's batch march: every ray of a training batch marched
//! through the occupancy grid on the lattice of
//! [`crate::engine::shared::march`] (which describes the march and holds
//! the lattice, the walk, the seeds and the render loop both engines use),
//! in two passes over blocks of rays.
//!
//! Output, for R rays: positions (S × 3, unit cube), directions (S × 3,
//! world unit vectors), dt and t per sample in world units (for
//! compositing), and ray_offsets (R + 1).

use glam::Vec3;
use rayon::prelude::*;

use crate::engine::shared::occupancy::OccupancyGrid;

// What both engines use, under the paths the cpu engine has always named
// it by.
use crate::engine::shared::march::*;

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

#[cfg(test)]
mod tests;
