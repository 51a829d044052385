//! The gpu march against the cpu engine on lavapipe: the same samples
//! (the kernels repeat the cpu's arithmetic operation for operation, with
//! fused multiply-adds prevented) and the same offsets. The gpu driver
//! updates its occupancy grid with the cpu engine's code on the host
//! (`ngp_gpu::occupancy_update_matches_the_cpu_engine`).

use zrak::engine::cpu::march::{MarchWorkspace, march};
use zrak::engine::gpu::GpuContext;
use zrak::engine::gpu::march::GpuMarch;
use zrak::engine::shared::march::{MarchParams, MarchStats, MarchedSamples};
use zrak::engine::shared::occupancy::{OccupancyGrid, mix64};
use zrak::field::common::{MarchConfig, OccupancyConfig};
use zrak::scene::UnitCubeMapping;

use crate::common::march::{rays, uniform};

/// Blocks of 8³ cells empty, sparse, half or full, each cell then drawn.
fn random_grid(cascades: u32, seed: u64) -> OccupancyGrid {
    let mut grid = OccupancyGrid::new(OccupancyConfig::PAPER, cascades, MarchConfig::PAPER.step);
    let res = OccupancyConfig::PAPER.resolution as usize;
    for (i, v) in grid.values_mut().iter_mut().enumerate() {
        let local = i % (res * res * res);
        let (x, y, z) = (
            local % res / 8,
            local / res % res / 8,
            local / (res * res) / 8,
        );
        let block = (i / (res * res * res)) * 4096 + x + 16 * (y + 16 * z);
        let p = [0.0, 0.03, 0.5, 1.0][(mix64(seed ^ block as u64) % 4) as usize];
        *v = if uniform(seed.wrapping_add(1) ^ mix64(i as u64)) < p {
            1.0
        } else {
            0.0
        };
    }
    grid.build_bitfield();
    grid
}

fn cpu_march(
    grid: &OccupancyGrid,
    origins: &[f32],
    directions: &[f32],
    params: &MarchParams,
) -> (MarchedSamples, MarchStats) {
    let mut out = MarchedSamples::default();
    let stats = march(
        grid,
        origins,
        directions,
        params,
        &mut MarchWorkspace::default(),
        &mut out,
    );
    (out, stats)
}

fn assert_same_samples(cpu: &MarchedSamples, gpu: &MarchedSamples, label: &str) {
    assert_eq!(cpu.ray_offsets, gpu.ray_offsets, "{label}: offsets");
    assert_eq!(cpu.sample_count(), gpu.sample_count(), "{label}");
    // The kernels repeat the cpu's operations one for one (no fma), so
    // positions agree to the bit on lavapipe; 1e-5 leaves room for a GPU
    // whose division is not correctly rounded (WGSL allows 2.5 ulp), which
    // moves a ray's entry point by ~1e-7.
    let mut worst = 0f32;
    for (i, (a, b)) in cpu.positions.iter().zip(&gpu.positions).enumerate() {
        assert!(
            (a - b).abs() <= 1e-5,
            "{label}: position {i}: cpu {a} gpu {b}"
        );
        worst = worst.max((a - b).abs());
    }
    assert_eq!(
        cpu.directions, gpu.directions,
        "{label}: directions are copied"
    );
    // A sample's step is the fixed step times a power of two (cone steps
    // on large scenes), exact on both engines.
    assert_eq!(cpu.dt, gpu.dt, "{label}: dt");
    for (i, (a, b)) in cpu.t.iter().zip(&gpu.t).enumerate() {
        assert!(
            (a - b).abs() <= 1e-5 * a.abs().max(1.0),
            "{label}: t {i}: cpu {a} gpu {b}"
        );
    }
    eprintln!(
        "{label}: {} samples, largest position difference {worst:e}",
        cpu.sample_count()
    );
}

#[test]
fn march_matches_cpu() {
    let _cores = crate::common::shared();
    let context = GpuContext::new().expect("lavapipe or a GPU");
    let gpu = GpuMarch::new(&context).unwrap();
    // (cascades, aabb_scale, seed, jitter, cone angle, distance of the
    // random rays' origins in multiples of 4 world units): Blender scenes
    // with the fixed step; larger boxes with the fixed step and with cone
    // steps, from inside the box (entry at distance 0, octave 0) and from
    // far outside it (entry in a later octave, the first stretch shorter
    // than an octave).
    for (cascades, aabb_scale, seed, jitter, cone_angle, distance) in [
        (1, 1.0, 1u64, true, 1.0 / 256.0, 1.0),
        (1, 1.0, 2, false, 1.0 / 256.0, 1.0),
        (3, 3.0, 3, true, 0.0, 1.0),
        (3, 3.0, 4, true, 1.0 / 256.0, 1.0),
        (3, 3.0, 5, false, 1.0 / 256.0, 6.0),
        (4, 8.0, 6, true, 1.0 / 256.0, 1.0),
    ] {
        let grid = random_grid(cascades, seed);
        let mapping = UnitCubeMapping {
            aabb_scale,
            ..UnitCubeMapping::BLENDER
        };
        let mut params = if jitter {
            MarchParams::training(mapping, seed as u32 * 7)
        } else {
            MarchParams::rendering(mapping)
        };
        params.config.cone_angle = cone_angle;
        let (mut origins, directions) = rays(400, seed);
        // The seven hard-case rays stay where they are.
        for o in &mut origins[21..] {
            *o *= distance;
        }
        let (cpu, cpu_stats) = cpu_march(&grid, &origins, &directions, &params);
        let (marched, stats) = gpu.march(
            &context,
            &grid,
            &origins,
            &directions,
            &params,
            cpu.sample_count() + 10,
        );
        assert_eq!(stats, cpu_stats);
        // The hard cases: the axis-parallel rays and the one from the
        // centre get samples; the zero direction gets none, nor do the ray
        // passing 3 world units off centre and the one pointing away from
        // z = 4, unless the box is 3 times larger (half side 1.5 / 0.33 ≈
        // 4.5) and holds their origins.
        for r in 0..4 {
            assert!(!marched.ray(r).is_empty(), "ray {r}");
        }
        assert_eq!(marched.ray(4).is_empty(), aabb_scale == 1.0);
        assert_eq!(marched.ray(5).is_empty(), aabb_scale == 1.0);
        assert!(marched.ray(6).is_empty());
        assert!(cpu.sample_count() > 10_000, "{}", cpu.sample_count());
        if cone_angle > 0.0 && aabb_scale > 1.0 {
            // Steps grow along the rays: at least three sizes of step.
            let mut steps = cpu.dt.clone();
            steps.sort_by(f32::total_cmp);
            steps.dedup();
            assert!(steps.len() >= 3, "{steps:?}");
        }
        assert_same_samples(
            &cpu,
            &marched,
            &format!("{cascades} cascades, seed {seed}, cone angle {cone_angle}"),
        );
    }
}

#[test]
fn budget_and_sample_limit_match_cpu() {
    let _cores = crate::common::shared();
    let context = GpuContext::new().expect("lavapipe or a GPU");
    let gpu = GpuMarch::new(&context).unwrap();
    let grid = random_grid(1, 11);
    let (origins, directions) = rays(300, 11);
    let full = MarchParams::training(UnitCubeMapping::BLENDER, 5);
    let (all, _) = cpu_march(&grid, &origins, &directions, &full);
    let params = MarchParams {
        sample_budget: all.sample_count() / 3,
        config: MarchConfig {
            max_steps: 100,
            ..MarchConfig::PAPER
        },
        ..full
    };
    let (cpu, cpu_stats) = cpu_march(&grid, &origins, &directions, &params);
    assert!(cpu_stats.rays_kept < cpu_stats.rays);
    let (marched, stats) = gpu.march(
        &context,
        &grid,
        &origins,
        &directions,
        &params,
        all.sample_count(),
    );
    assert_eq!(stats, cpu_stats);
    assert_same_samples(&cpu, &marched, "budget");

    // A capacity below the budget acts as the budget.
    let (capped, capped_stats) = gpu.march(
        &context,
        &grid,
        &origins,
        &directions,
        &full,
        cpu.sample_count(),
    );
    assert!(capped_stats.samples <= cpu.sample_count());
    let (cpu_capped, cpu_capped_stats) = cpu_march(
        &grid,
        &origins,
        &directions,
        &MarchParams {
            sample_budget: cpu.sample_count(),
            ..full
        },
    );
    assert_eq!(capped_stats, cpu_capped_stats);
    assert_same_samples(&cpu_capped, &capped, "capacity");
}

#[test]
fn prefix_sum_over_many_blocks() {
    let _cores = crate::common::shared();
    // 150 000 rays: 293 scan blocks, so the block totals take two tiles of
    // the single-workgroup step and its carry. At most 3 samples per ray
    // keeps the write small.
    let context = GpuContext::new().expect("lavapipe or a GPU");
    let gpu = GpuMarch::new(&context).unwrap();
    let grid = random_grid(1, 21);
    let (origins, directions) = rays(150_000, 21);
    let params = MarchParams {
        config: MarchConfig {
            max_steps: 3,
            ..MarchConfig::PAPER
        },
        ..MarchParams::training(UnitCubeMapping::BLENDER, 9)
    };
    let (cpu, cpu_stats) = cpu_march(&grid, &origins, &directions, &params);
    let (marched, stats) = gpu.march(
        &context,
        &grid,
        &origins,
        &directions,
        &params,
        cpu.sample_count(),
    );
    assert_eq!(stats, cpu_stats);
    assert_same_samples(&cpu, &marched, "150 000 rays");
}

/// σ-first compaction: rays whose samples before the cut are counted keep
/// those samples, rays in order and samples in order within each ray; empty
/// rays, rays that keep nothing and rays that keep everything among them,
/// with more rays than a scan block holds (the binary search and the
/// prefix sum across blocks).
#[test]
fn compaction_keeps_each_rays_samples_before_its_cut_in_order() {
    let _cores = crate::common::shared();
    use zrak::engine::gpu::compact::{CompactedSamples, GpuCompaction, MarchedInputs};
    use zrak::engine::gpu::kernel::{Recorder, read_buffer, storage_buffer};

    let context = crate::common::gpu_context();
    let rays = 700;
    // Marched samples per ray 0..=5 and, of those, used 0..=all.
    let marched: Vec<u32> = (0..rays).map(|r| (mix64(r as u64) % 6) as u32).collect();
    let used: Vec<u32> = marched
        .iter()
        .enumerate()
        .map(|(r, &n)| (mix64(r as u64 ^ 0x5eed) % (n as u64 + 1)) as u32)
        .collect();
    let mut offsets = vec![0u32];
    for &n in &marched {
        offsets.push(offsets.last().unwrap() + n);
    }
    let samples = *offsets.last().unwrap() as usize;
    // Every value names its sample and component.
    let values = |components: usize, tag: f32| -> Vec<f32> {
        (0..samples * components).map(|i| tag + i as f32).collect()
    };
    let (positions, directions, variances) = (values(3, 0.0), values(3, 1e5), values(3, 2e5));
    let (dt, t, sigma) = (values(1, 3e5), values(1, 4e5), values(1, 5e5));
    let buffer = |data: &[f32], label: &str| storage_buffer(&context, label, data);
    let march = GpuMarch::new(&context).unwrap();
    let compaction = GpuCompaction::new(&context).unwrap();
    let out = CompactedSamples::new(&context, rays, samples, true);
    let offsets_buffer = storage_buffer(&context, "offsets", &offsets);
    let used_buffer = storage_buffer(&context, "used", &used);
    let inputs = [
        buffer(&positions, "positions"),
        buffer(&directions, "directions"),
        buffer(&variances, "variances"),
        buffer(&dt, "dt"),
        buffer(&t, "t"),
        buffer(&sigma, "sigma"),
    ];
    let mut rec = Recorder::new(&context);
    compaction.record(
        &mut rec,
        &march,
        rays,
        MarchedInputs {
            ray_offsets: &offsets_buffer,
            samples_used: &used_buffer,
            positions: &inputs[0],
            directions: &inputs[1],
            variances: Some(&inputs[2]),
            dt: &inputs[3],
            t: &inputs[4],
            sigma: &inputs[5],
        },
        &out,
    );
    rec.submit();

    // The same on the host.
    let kept: Vec<usize> = (0..rays)
        .flat_map(|r| offsets[r] as usize..(offsets[r] + used[r]) as usize)
        .collect();
    let gather = |data: &[f32], components: usize| -> Vec<f32> {
        kept.iter()
            .flat_map(|&s| data[components * s..components * (s + 1)].iter().copied())
            .collect()
    };
    let mut compact_offsets = vec![0u32];
    for &n in &used {
        compact_offsets.push(compact_offsets.last().unwrap() + n);
    }
    let n = kept.len();
    assert!(n > 300 && n < samples, "{n} of {samples}");
    assert_eq!(
        read_buffer::<u32>(&context, &out.counters, 1)[0] as usize,
        n
    );
    assert_eq!(
        read_buffer::<u32>(&context, &out.ray_offsets, rays + 1),
        compact_offsets
    );
    for (name, buffer, data, components) in [
        ("positions", &out.positions, &positions, 3),
        ("directions", &out.directions, &directions, 3),
        ("variances", &out.variances, &variances, 3),
        ("dt", &out.dt, &dt, 1),
        ("t", &out.t, &t, 1),
        ("sigma", &out.sigma, &sigma, 1),
    ] {
        assert_eq!(
            read_buffer::<f32>(&context, buffer, components * n),
            gather(data, components),
            "{name}"
        );
    }
}
