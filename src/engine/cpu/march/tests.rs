use glam::Vec3;

use super::*;
use crate::engine::cpu::composite::{RaySamples, composite};
use crate::engine::shared::batch_sizer::BatchSizer;
use crate::engine::shared::occupancy::mix64;
use crate::field::common::{MarchConfig, OccupancyConfig};
/// Instant-NGP's batch (paper, section 5.4), which the sizer is tested at.
const SAMPLES_PER_BATCH: usize = 1 << 18;
use crate::scene::{Aabb, UnitCubeMapping};

const BLENDER: UnitCubeMapping = UnitCubeMapping::BLENDER;

fn uniform(key: u64) -> f32 {
    (mix64(key) >> 40) as f32 / (1u64 << 24) as f32
}

fn grid_with(cascades: u32, occupied: impl Fn(usize, Vec3) -> bool) -> OccupancyGrid {
    let mut grid = OccupancyGrid::for_scene(&BLENDER);
    if cascades != grid.geometry().cascades {
        grid = OccupancyGrid::new(OccupancyConfig::PAPER, cascades, MarchConfig::PAPER.step);
    }
    let geometry = grid.geometry();
    for (i, v) in grid.values_mut().iter_mut().enumerate() {
        let cell = geometry.cell_at(i);
        let centre = geometry.cell_centre(cell);
        *v = if occupied(i, centre) { 1.0 } else { 0.0 };
    }
    grid.build_bitfield();
    grid
}

/// Blocks of 8³ cells are empty, sparse, half or full, then each cell
/// is drawn: empty stretches for the skip and scattered cells for its
/// boundaries.
fn random_grid(cascades: u32, seed: u64) -> OccupancyGrid {
    let res = OccupancyConfig::PAPER.resolution as usize;
    grid_with(cascades, |i, _| {
        let local = i % (res * res * res);
        let (x, y, z) = (
            local % res / 8,
            local / res % res / 8,
            local / (res * res) / 8,
        );
        let block = (i / (res * res * res)) * 4096 + x + 16 * (y + 16 * z);
        let p = [0.0, 0.03, 0.5, 1.0][(mix64(seed ^ block as u64) % 4) as usize];
        uniform(seed.wrapping_add(1) ^ mix64(i as u64)) < p
    })
}

/// Rays from a sphere of radius 4 (world) at points near the centre,
/// and some starting inside the box.
fn random_rays(n: usize, seed: u64) -> (Vec<f32>, Vec<f32>) {
    let mut origins = Vec::with_capacity(3 * n);
    let mut directions = Vec::with_capacity(3 * n);
    let u = |i: usize, j: u64| uniform(seed ^ mix64((i as u64) * 16 + j));
    for i in 0..n {
        let z = 2.0 * u(i, 0) - 1.0;
        let phi = std::f32::consts::TAU * u(i, 1);
        let r = (1.0 - z * z).sqrt();
        let radius = if i % 8 == 0 { 1.2 * u(i, 2) } else { 4.0 };
        let origin = radius * Vec3::new(r * phi.cos(), r * phi.sin(), z);
        let target = Vec3::new(u(i, 3), u(i, 4), u(i, 5)) * 2.4 - 1.2;
        let direction = (target - origin).normalize();
        origins.extend_from_slice(&origin.to_array());
        directions.extend_from_slice(&direction.to_array());
    }
    (origins, directions)
}

/// The lattice indices a march that tests every lattice point finds.
fn naive(marcher: &Marcher, ray: &RayMarch, max: u32) -> Vec<u32> {
    let mut out = Vec::new();
    let mut k = 0;
    while ray.s(k) <= ray.s_exit && (out.len() as u32) < max {
        if marcher.is_sample(ray, k) {
            out.push(k);
        }
        k += 1;
    }
    out
}

fn march_one(
    grid: &OccupancyGrid,
    origin: Vec3,
    direction: Vec3,
    params: &MarchParams,
) -> MarchedSamples {
    let mut out = MarchedSamples::default();
    march(
        grid,
        &origin.to_array(),
        &direction.to_array(),
        params,
        &mut MarchWorkspace::default(),
        &mut out,
    );
    out
}

fn all_finite(out: &MarchedSamples) -> bool {
    [&out.positions, &out.directions, &out.dt, &out.t]
        .iter()
        .all(|v| v.iter().all(|x| x.is_finite()))
}

#[test]
fn rays_that_miss_give_no_samples() {
    let grid = grid_with(1, |_, _| true);
    let params = MarchParams::training(BLENDER, 3);
    // The box spans ±0.5/0.33 ≈ ±1.515 in world units.
    for (origin, direction) in [
        (Vec3::new(0.0, 3.0, 4.0), -Vec3::Z),
        (Vec3::new(0.0, 0.0, 4.0), Vec3::Z),
        (Vec3::new(1.6, 0.0, 4.0), -Vec3::Z),
        (Vec3::new(0.0, 0.0, 4.0), Vec3::ZERO),
        (Vec3::new(f32::NAN, 0.0, 4.0), -Vec3::Z),
    ] {
        let out = march_one(&grid, origin, direction, &params);
        assert_eq!(out.ray_offsets, vec![0, 0], "{origin} {direction}");
        assert_eq!(out.sample_count(), 0);
    }
}

#[test]
fn all_occupied_gives_evenly_spaced_samples_over_the_chord() {
    let grid = grid_with(1, |_, _| true);
    let dt = MarchConfig::PAPER.step;
    for seed in 0..20u32 {
        let (origins, directions) = random_rays(1, seed as u64 + 100);
        let origin = Vec3::from_slice(&origins);
        let direction = Vec3::from_slice(&directions);
        let params = MarchParams::training(BLENDER, seed);
        let out = march_one(&grid, origin, direction, &params);
        assert!(all_finite(&out));
        let unit = BLENDER.to_unit(origin);
        let Some((t0, t1)) = Aabb::new(Vec3::ZERO, Vec3::ONE).intersect(unit, direction, 0.0)
        else {
            assert_eq!(out.sample_count(), 0);
            continue;
        };
        // Lattice points u·dt, (u+1)·dt, … up to the chord: there are
        // floor(chord/dt − u) + 1, capped at 1024; rounding of the chord
        // can move the last one across the exit, hence ±1.
        let u = jitter(seed, 0);
        let expected = (((t1 - t0) / dt - u).floor() as i64 + 1).min(1024);
        let n = out.sample_count() as i64;
        assert!(
            (n - expected).abs() <= 1,
            "seed {seed}: {n} samples, chord says {expected}"
        );
        // Even spacing: consecutive positions dt·d apart (positions
        // are < 2 in magnitude, so each carries ≤ 2 ulps ≈ 2.4e-7 of
        // rounding), t in world steps of dt / 0.33.
        for i in 1..out.sample_count() {
            for a in 0..3 {
                let step = out.positions[3 * i + a] - out.positions[3 * i - 3 + a];
                assert!((step - dt * direction[a]).abs() < 1e-6);
            }
            assert!((out.t[i] - out.t[i - 1] - dt / 0.33).abs() < 2e-6);
            assert_eq!(out.dt[i], dt / 0.33);
        }
        // The first sample sits u·dt past the entry.
        assert!((out.t[0] - (t0 + u * dt) / 0.33).abs() < 2e-6);
        let first = Vec3::from_slice(&out.positions[..3]);
        assert!(
            (first - (unit + direction * (t0 + u * dt)))
                .abs()
                .max_element()
                < 1e-6
        );
    }
}

#[test]
fn rays_starting_inside_and_axis_parallel_rays() {
    let grid = grid_with(1, |_, _| true);
    let dt = MarchConfig::PAPER.step;
    let params = MarchParams::rendering(BLENDER);
    // From the centre along +x: samples at k·dt for k·dt ≤ 0.5, the
    // exit; 0.5 / (√3/1024) = 295.6, so k = 0..=295.
    let out = march_one(&grid, Vec3::ZERO, Vec3::X, &params);
    assert_eq!(out.sample_count(), 296);
    assert!(all_finite(&out));
    assert_eq!(out.t[0], 0.0);
    assert_eq!(&out.positions[..3], &[0.5, 0.5, 0.5]);
    for i in 0..296 {
        // y and z stay exactly 0.5: the direction's zero components add
        // exact zeros.
        assert_eq!(out.positions[3 * i + 1], 0.5);
        assert_eq!(out.positions[3 * i + 2], 0.5);
        assert!((out.positions[3 * i] - (0.5 + i as f32 * dt)).abs() < 1e-6);
    }

    // From outside along −z, on the cell boundary x = y = 0.5: the whole
    // chord of length 1 gives floor(1/dt) + 1 = 592 samples.
    let out = march_one(&grid, Vec3::new(0.0, 0.0, 4.0), -Vec3::Z, &params);
    assert_eq!(out.sample_count(), 592);
    assert!(all_finite(&out));
    assert!((out.t[0] - (4.0 - 0.5 / 0.33)).abs() < 1e-5);
    // Along a face of the box (x = 1 in unit coordinates): the closed
    // box holds it, clamped into the last column of cells.
    let face = BLENDER.to_world(Vec3::new(1.0, 0.25, 0.5));
    let out = march_one(&grid, Vec3::new(face.x, face.y, 4.0), -Vec3::Z, &params);
    assert_eq!(out.sample_count(), 592);
    assert!(out.positions.chunks(3).all(|p| p[0] == 1.0));

    // Axis-parallel through a grid where only the cells with z index
    // 100 are occupied: the march skips to that slab and samples it:
    // z in [100/128, 101/128) from the entry at z = 1 holds the lattice
    // points k with 27/128 < k·dt ≤ 28/128, i.e. 124.7 < k ≤ 129.3.
    let res = 128;
    let grid = grid_with(1, |i, _| i / (res * res) == 100);
    let out = march_one(&grid, Vec3::new(0.1, -0.2, 4.0), -Vec3::Z, &params);
    assert_eq!(out.sample_count(), 5);
    assert!((out.t[0] - (4.0 - 0.5 / 0.33 + 125.0 * dt / 0.33)).abs() < 1e-5);
    for p in out.positions.chunks(3) {
        assert!((100.0 / 128.0..101.0 / 128.0).contains(&p[2]), "{p:?}");
    }
}

#[test]
fn an_empty_grid_gives_no_samples() {
    let grid = grid_with(1, |_, _| false);
    let (origins, directions) = random_rays(500, 1);
    let mut out = MarchedSamples::default();
    let stats = march(
        &grid,
        &origins,
        &directions,
        &MarchParams::training(BLENDER, 1),
        &mut MarchWorkspace::default(),
        &mut out,
    );
    assert_eq!(stats.samples, 0);
    assert_eq!(out.ray_offsets, vec![0; 501]);
}

#[test]
fn skipping_gives_exactly_the_naive_samples() {
    for (cascades, aabb_scale, seed) in [(1, 1.0, 5u64), (1, 1.0, 6), (2, 2.0, 7), (3, 3.0, 8)] {
        let grid = random_grid(cascades, seed);
        let mapping = UnitCubeMapping {
            aabb_scale,
            ..BLENDER
        };
        let params = MarchParams::training(mapping, seed as u32);
        let (origins, directions) = random_rays(400, seed);
        let mut out = MarchedSamples::default();
        march(
            &grid,
            &origins,
            &directions,
            &params,
            &mut MarchWorkspace::default(),
            &mut out,
        );
        assert!(all_finite(&out));
        // The march jumped over empty blocks: the grid has both kinds.
        let mut coarse = Vec::new();
        assert!(coarse_occupancy(
            &grid.geometry(),
            grid.bitfield(),
            &mut coarse
        ));
        let occupied_blocks: u32 = coarse.iter().map(|w| w.count_ones()).sum();
        let blocks = grid.values().len() / (COARSE * COARSE * COARSE) as usize;
        assert!(occupied_blocks > 0 && (occupied_blocks as usize) < blocks);
        let marcher = Marcher::new(&grid, &params.config, &mapping);
        let mut total_naive = 0;
        for r in 0..400 {
            let origin = Vec3::from_slice(&origins[3 * r..3 * r + 3]);
            let direction = Vec3::from_slice(&directions[3 * r..3 * r + 3]);
            let expected = match marcher.prepare(origin, direction, jitter(seed as u32, r as u32)) {
                Some(ray) => naive(&marcher, &ray, 1024)
                    .into_iter()
                    .map(|k| ray.position(k))
                    .collect::<Vec<_>>(),
                None => Vec::new(),
            };
            total_naive += expected.len();
            let got: Vec<Vec3> = out.positions[3 * out.ray(r).start..3 * out.ray(r).end]
                .chunks(3)
                .map(Vec3::from_slice)
                .collect();
            assert_eq!(got, expected, "ray {r}, {cascades} cascades");
            for p in &got {
                assert!(grid.occupied_at(*p));
            }
        }
        assert_eq!(out.sample_count(), total_naive);
        // The grid is neither empty nor full, so skipping was exercised.
        assert!(total_naive > 1000, "{total_naive}");
    }
}

#[test]
fn per_ray_limit_budget_and_thread_count_independence() {
    let grid = random_grid(1, 21);
    let (origins, directions) = random_rays(300, 21);
    let params = MarchParams::training(BLENDER, 4);
    let mut full = MarchedSamples::default();
    march(
        &grid,
        &origins,
        &directions,
        &params,
        &mut MarchWorkspace::default(),
        &mut full,
    );

    // One thread gives the same bits.
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap();
    let mut single = MarchedSamples::default();
    pool.install(|| {
        march(
            &grid,
            &origins,
            &directions,
            &params,
            &mut MarchWorkspace::default(),
            &mut single,
        )
    });
    assert_eq!(full, single);

    // At most 10 samples per ray: the first 10 of each.
    let limited_params = MarchParams {
        config: MarchConfig {
            max_steps: 10,
            ..MarchConfig::PAPER
        },
        ..params
    };
    let mut limited = MarchedSamples::default();
    march(
        &grid,
        &origins,
        &directions,
        &limited_params,
        &mut MarchWorkspace::default(),
        &mut limited,
    );
    for r in 0..300 {
        let (a, b) = (full.ray(r), limited.ray(r));
        assert_eq!(b.len(), a.len().min(10));
        assert_eq!(
            limited.positions[3 * b.start..3 * b.end],
            full.positions[3 * a.start..3 * a.start + 3 * b.len()]
        );
    }

    // A budget of half the samples keeps a prefix of the rays, whole.
    let budget = full.sample_count() / 2;
    let mut workspace = MarchWorkspace::default();
    let mut cut = MarchedSamples::default();
    let stats = march(
        &grid,
        &origins,
        &directions,
        &MarchParams {
            sample_budget: budget,
            ..params
        },
        &mut workspace,
        &mut cut,
    );
    assert!(stats.rays_kept < 300);
    assert_whole_ray_prefix(&full, &cut, &stats, budget);
    // The workspace is reusable: marching again with it matches.
    let mut again = MarchedSamples::default();
    march(
        &grid,
        &origins,
        &directions,
        &params,
        &mut workspace,
        &mut again,
    );
    assert_eq!(again, full);
}

/// `cut`, marched with a sample budget, holds the first whole rays of
/// the unlimited march `full` and nothing else: the next ray would have
/// gone over `budget`, and every later ray has no samples.
fn assert_whole_ray_prefix(
    full: &MarchedSamples,
    cut: &MarchedSamples,
    stats: &MarchStats,
    budget: usize,
) {
    let kept = stats.rays_kept;
    assert!(stats.samples <= budget);
    assert_eq!(full.ray_offsets[kept] as usize, stats.samples);
    assert!(full.ray_offsets[kept + 1] as usize > budget);
    assert_eq!(cut.ray_offsets[..=kept], full.ray_offsets[..=kept]);
    assert!(
        cut.ray_offsets[kept..]
            .iter()
            .all(|&o| o as usize == stats.samples)
    );
    assert_eq!(cut.positions[..], full.positions[..3 * stats.samples]);
    assert_eq!(cut.t[..], full.t[..stats.samples]);
}

#[test]
fn rays_past_the_budget_are_not_walked_and_nothing_else_changes() {
    // Many waves of blocks, and a budget met within the second wave.
    let rays = 5 * WAVE_BLOCKS * RAYS_PER_BLOCK;
    let grid = random_grid(1, 5);
    let (origins, directions) = random_rays(rays, 5);
    let params = MarchParams::training(BLENDER, 9);
    let mut full = MarchedSamples::default();
    march(
        &grid,
        &origins,
        &directions,
        &params,
        &mut MarchWorkspace::default(),
        &mut full,
    );
    let budget = full.ray_offsets[WAVE_BLOCKS * RAYS_PER_BLOCK + 100] as usize + 1;
    let mut workspace = MarchWorkspace::default();
    let mut cut = MarchedSamples::default();
    let stats = march(
        &grid,
        &origins,
        &directions,
        &MarchParams {
            sample_budget: budget,
            ..params
        },
        &mut workspace,
        &mut cut,
    );
    assert_eq!(stats.rays, rays);
    assert_whole_ray_prefix(&full, &cut, &stats, budget);
    // Only the first two waves were walked.
    let walked = workspace.rays.iter().filter(|r| r.is_some()).count();
    assert!(
        walked <= 2 * WAVE_BLOCKS * RAYS_PER_BLOCK,
        "{walked} rays walked"
    );
}

#[test]
fn rendering_with_early_stop_matches_full_compositing() {
    // A ball of radius 0.3 in the unit cube; inside it density 400
    // (world units), so rays through it turn opaque within ~0.1.
    let ball = |p: Vec3| p.distance(Vec3::splat(0.5)) < 0.3;
    let grid = grid_with(1, |_, centre| centre.distance(Vec3::splat(0.5)) < 0.31);
    let field = |p: &[f32], d: &[f32], sigma: &mut [f32], rgb: &mut [f32]| {
        for i in 0..sigma.len() {
            let q = Vec3::from_slice(&p[3 * i..3 * i + 3]);
            sigma[i] = if ball(q) { 400.0 * q.x } else { 0.0 };
            rgb[3 * i] = q.x;
            rgb[3 * i + 1] = d[3 * i + 1].abs();
            rgb[3 * i + 2] = 0.25;
        }
    };
    let (origins, directions) = random_rays(200, 33);
    let background = [1.0, 0.5, 0.0];
    let n = 200;
    let (mut colour, mut depth, mut opacity) = (vec![0.0; 3 * n], vec![0.0; n], vec![0.0; n]);
    let mut evaluated = 0;
    march_and_composite(
        &grid,
        GridRendering {
            mapping: &BLENDER,
            config: &MarchConfig::PAPER,
            background,
            chunk_samples: 1000,
        },
        &origins,
        &directions,
        |samples: &GridSamples, s: &mut [f32], c: &mut [f32]| {
            evaluated += s.len();
            field(samples.positions, samples.directions, s, c)
        },
        CompositedRays {
            colour: &mut colour,
            depth: &mut depth,
            opacity: &mut opacity,
        },
    );

    // Reference: every sample, composited by the reference stage.
    let mut out = MarchedSamples::default();
    march(
        &grid,
        &origins,
        &directions,
        &MarchParams::rendering(BLENDER),
        &mut MarchWorkspace::default(),
        &mut out,
    );
    let s = out.sample_count();
    let (mut sigma, mut rgb) = (vec![0.0; s], vec![0.0; 3 * s]);
    field(&out.positions, &out.directions, &mut sigma, &mut rgb);
    let rgb3: Vec<[f32; 3]> = rgb.chunks(3).map(|c| [c[0], c[1], c[2]]).collect();
    let mut opaque = 0;
    for r in 0..n {
        let range = out.ray(r);
        let want = composite(
            &RaySamples {
                density: &sigma[range.clone()],
                colour: &rgb3[range.clone()],
                delta: &out.dt[range.clone()],
                t: &out.t[range.clone()],
            },
            background,
        );
        // What the early stop leaves out weighs at most T < 1e-4 (times
        // colours ≤ 1, or depths ≤ 8 world units), plus f32 rounding
        // of sums over a few hundred terms.
        for c in 0..3 {
            assert!(
                (colour[3 * r + c] - want.colour[c]).abs() < 1e-4 + 1e-5,
                "ray {r}"
            );
        }
        assert!((opacity[r] - want.opacity).abs() < 1e-4 + 1e-5);
        assert!((depth[r] - want.depth).abs() < 8e-4 + 1e-4);
        opaque += (want.opacity > 0.999) as usize;
    }
    // Many rays hit the opaque ball; stopping them early saves work.
    assert!(opaque > 50, "{opaque}");
    assert!(evaluated < s * 3 / 4, "evaluated {evaluated} of {s}");
}

#[test]
fn batch_sizer_converges_to_the_target() {
    let mut sizer = BatchSizer::new(SAMPLES_PER_BATCH);
    assert_eq!(sizer.rays(), 4096);
    // A scene where rays average `mean` samples (uniform 0..2·mean):
    // after ~30 steps (0.8^30 ≈ 1e-3 of the start left) batches hold
    // the target to within the granularity (256 rays) and the noise of
    // the mean over thousands of rays (< 2%).
    let mut step = 0u64;
    let mut run = |sizer: &mut BatchSizer, mean: f32, steps: usize| {
        for _ in 0..steps {
            let rays = sizer.rays();
            let samples: f32 = (0..rays)
                .map(|r| 2.0 * mean * uniform(step * 1_000_000 + r as u64))
                .sum();
            sizer.record(rays, samples as usize);
            step += 1;
        }
        let rays = sizer.rays();
        let expected = SAMPLES_PER_BATCH as f32 / mean;
        assert!(
            (rays as f32 - expected).abs() <= 0.02 * expected + 256.0,
            "mean {mean}: {rays} rays, want {expected}"
        );
        assert_eq!(rays % 256, 0);
    };
    run(&mut sizer, 40.0, 30);
    // The grid empties as training goes on: fewer samples per ray.
    run(&mut sizer, 12.0, 30);
    run(&mut sizer, 90.0, 30);
    // An empty grid: no samples, the batch grows to its cap.
    for _ in 0..100 {
        sizer.record(sizer.rays(), 0);
    }
    assert_eq!(sizer.rays(), SAMPLES_PER_BATCH);
}
