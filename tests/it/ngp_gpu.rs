//! Instant-NGP on the gpu engine (lavapipe) against the cpu engine: one
//! whole training step from the same state, the occupancy update, and a
//! checkpoint moved from the gpu engine to the cpu engine.

use crate::common;

use std::ops::Range;
use std::sync::Arc;
use std::time::Instant;

use common::{batch, relative, relative_norm};
use glam::Vec3;
use zrak::engine::build_gpu;
use zrak::engine::cpu::model::CpuModel;
use zrak::engine::gpu::model::GpuModel;
use zrak::engine::gpu::timing::StageTiming;
use zrak::field::ModelKind;
use zrak::field::common::{LossKind, Recipe};
use zrak::field::ngp::NgpShape;
use zrak::model::{RadianceModel, Stage};
use zrak::scene::Scene;

/// 2^12 samples per batch: a few dozen rays through a sparse grid.
const BATCH_SAMPLES: usize = 1 << 12;
const SEED: u64 = 5;

fn small_scene() -> Arc<Scene> {
    common::small_scene(32)
}

fn models(scene: &Scene) -> (CpuModel, GpuModel) {
    let recipe = zrak::field::ngp::recipe(scene.unit_cube.aabb_scale);
    models_of_shape(scene, NgpShape::for_scene(scene), recipe)
}

/// As [`models`], with an occupancy grid of 32³ cells instead of the
/// paper's 128³: for tests that count what a step does, not what it
/// computes, where lavapipe would spend most of their time evaluating the
/// warm-up's grid updates (every cell, every 16 steps).
fn models_with_coarse_grid(scene: &Scene) -> (CpuModel, GpuModel) {
    let mut recipe = zrak::field::ngp::recipe(scene.unit_cube.aabb_scale);
    recipe.occupancy.resolution = 32;
    models_of_shape(scene, NgpShape::for_scene(scene), recipe)
}

fn models_of_shape(scene: &Scene, shape: NgpShape, recipe: Recipe) -> (CpuModel, GpuModel) {
    let cpu = CpuModel::build(
        &crate::common::request(ModelKind::Ngp, SEED, LossKind::Huber, Some(BATCH_SAMPLES))
            .with_shape(shape.clone())
            .with_recipe(recipe.clone()),
        scene,
    );
    let context = common::gpu_context();
    let mut gpu = build_gpu(
        context,
        &crate::common::request(ModelKind::Ngp, SEED, LossKind::Huber, Some(BATCH_SAMPLES))
            .with_shape(shape)
            .with_recipe(recipe),
        scene,
    )
    .expect("gpu model");
    // Each step's own loss and the cpu's order of grid updates, to compare
    // step by step.
    gpu.set_read_back_late(false);
    (cpu, gpu)
}

/// Gives both models the same sparse grid (through a checkpoint of the
/// cpu model, which also checks that one loads into the other): occupied
/// inside a ball around the centre, so rays get ~20 samples and ~170 fit
/// the budget, instead of the untrained grid's ~1000 samples for 4 rays.
fn share_ball_grid(cpu: &mut CpuModel, gpu: &mut GpuModel) {
    {
        let grid = cpu.occupancy_mut().expect("Instant-NGP has a grid");
        let geometry = grid.geometry();
        for (i, v) in grid.values_mut().iter_mut().enumerate() {
            let cell = geometry.cell_at(i);
            let centre = geometry.cell_centre(cell);
            *v = if (centre - Vec3::splat(0.5)).length() < 0.2 {
                1.0
            } else {
                0.0
            };
        }
        grid.build_bitfield();
    }
    gpu.load(&cpu.save()).unwrap();
    assert_eq!(
        gpu.occupancy().unwrap().bitfield(),
        cpu.occupancy().unwrap().bitfield()
    );
}

#[test]
fn one_training_step_matches_the_cpu_engine() {
    let _cores = crate::common::shared();
    let scene = small_scene();
    let (mut cpu, mut gpu) = models(&scene);
    // The same initial parameters, bit for bit (the same seeds per part).
    assert!(gpu.params() == cpu.params(), "initial parameters differ");

    share_ball_grid(&mut cpu, &mut gpu);

    let rays = batch(&scene, 256, 17);
    // Step 1: no occupancy update is due, so both march the grid above.
    let step = 1;
    let before = cpu.params().to_vec();

    // Gradients first (no parameter changes).
    let cpu_stats = cpu.forward_backward(&rays, step);
    let clock = Instant::now();
    let gpu_stats = gpu.forward_backward(&rays, step);
    println!(
        "gpu forward + backward without Adam: {:.1} ms",
        clock.elapsed().as_secs_f64() * 1e3
    );
    assert_eq!(gpu_stats.samples, cpu_stats.samples);
    assert_eq!(gpu_stats.rays, cpu_stats.rays);
    assert!(cpu_stats.rays >= 20, "{cpu_stats:?}");
    // Both go σ first, and compact to the same samples before the cut.
    assert!(gpu_stats.samples_composited.is_some(), "{gpu_stats:?}");
    assert_eq!(gpu_stats.samples_composited, cpu_stats.samples_composited);
    let cpu_gradient = cpu.gradients().to_vec();
    let gpu_gradient = gpu.gradients();
    let ranges: Vec<(String, Range<usize>)> = cpu
        .layout()
        .parts()
        .iter()
        .map(|part| (part.name.clone(), part.range.clone()))
        .collect();
    for (name, range) in &ranges {
        let error = relative_norm(&gpu_gradient[range.clone()], &cpu_gradient[range.clone()]);
        println!("gradient of the {name}: relative error {error:.2e}");
        // Each stage matches the cpu within 1e-4 (tests/*_gpu.rs); the
        // chain multiplies a handful of such factors, and the norm is
        // dominated by the large, well-conditioned entries.
        assert!(error < 1e-4, "{name}: {error:e}");
    }

    // The whole step.
    let cpu_stats = cpu.step(&rays, step);
    let clock = Instant::now();
    let gpu_stats = gpu.step(&rays, step);
    let ms = clock.elapsed().as_secs_f64() * 1e3;
    println!("gpu step times: {:?}", gpu_stats.times);
    println!(
        "gpu step: {ms:.1} ms for {} samples, {} rays ({:.0} samples/s); loss cpu {} gpu {}",
        gpu_stats.samples,
        gpu_stats.rays,
        gpu_stats.samples as f64 / (ms / 1e3),
        cpu_stats.loss,
        gpu_stats.loss
    );
    // The loss is a mean of a few hundred per-channel terms computed by
    // the same formulas in f32: agreement to ~1e-6, 1e-4 is a wide margin
    // that still catches any wrong sample, ray or weight.
    assert!(
        relative(gpu_stats.loss, cpu_stats.loss) < 1e-4,
        "loss: gpu {} cpu {}",
        gpu_stats.loss,
        cpu_stats.loss
    );

    let cpu_after = cpu.params();
    let gpu_after = gpu.params();
    let (mut changed, mut mismatched, mut mismatched_at_tiny) = (0usize, 0usize, 0usize);
    for (name, range) in &ranges {
        let largest = range
            .clone()
            .map(|i| cpu_gradient[i].abs())
            .fold(0f32, f32::max);
        for i in range.clone() {
            if cpu_after[i] == before[i] && gpu_after[i] == before[i] {
                continue;
            }
            changed += 1;
            // Adam's first step moves each parameter by lr · g/|g| (plus
            // rounding); the two engines' updates agree to f32 rounding
            // unless the gradient differs in sign.
            if relative(gpu_after[i], cpu_after[i]) > 1e-3 {
                mismatched += 1;
                // A sign can only differ where the gradient is at the level
                // of summation-order noise: a sum of many terms whose f32
                // rounding (≈ 1e-7 of their magnitudes) is comparable to
                // the sum itself. 1e-4 of the range's largest gradient is
                // still hundreds of times above that noise, so anything
                // above it must agree.
                if cpu_gradient[i].abs() <= 1e-4 * largest {
                    mismatched_at_tiny += 1;
                } else {
                    panic!(
                        "{name}[{}]: gpu {} cpu {} (before {}, gradient cpu {} gpu {})",
                        i - range.start,
                        gpu_after[i],
                        cpu_after[i],
                        before[i],
                        cpu_gradient[i],
                        gpu_gradient[i]
                    );
                }
            }
        }
    }
    println!(
        "parameters changed: {changed}; beyond 1e-3: {mismatched} (all with |g| ≤ 1e-4 · max: \
         {mismatched_at_tiny})"
    );
    assert!(changed > 1000, "{changed}");
    // Near-zero gradients are rare: at most 0.1% of the changed parameters.
    assert!(mismatched * 1000 <= changed, "{mismatched} of {changed}");
}

/// Every stage of a step reports its time, from GPU timestamps where the
/// device has them (lavapipe does) and from the wall clock otherwise; the
/// timing does not change what the step computes.
#[test]
fn a_step_reports_the_time_of_each_stage() {
    let _cores = crate::common::shared();
    let scene = small_scene();
    let (mut cpu, mut gpu) = models(&scene);
    share_ball_grid(&mut cpu, &mut gpu);
    let rays = batch(&scene, 256, 17);
    let has_timestamps = gpu
        .context()
        .features
        .contains(wgpu::Features::TIMESTAMP_QUERY);
    assert_eq!(
        gpu.stage_timing() == StageTiming::Timestamps,
        has_timestamps
    );
    let mut losses = Vec::new();
    for timing in [StageTiming::Timestamps, StageTiming::WallClock] {
        gpu.set_stage_timing(timing);
        // Step 1 has no occupancy update; forward_backward changes nothing,
        // so both timings see the same work.
        let stats = gpu.forward_backward(&rays, 1);
        losses.push(stats.loss);
        println!("{timing:?}: {:?}", stats.times);
        let t = stats.times;
        for (name, seconds) in t.named() {
            assert!(seconds.is_finite() && seconds >= 0.0, "{name}: {seconds}");
        }
        // Stages with real work take some time on any clock.
        for stage in [
            Stage::March,
            Stage::NetworksForward,
            Stage::NetworksBackward,
        ] {
            assert!(t[stage] > 0.0, "{timing:?}: {} took no time", stage.name());
        }
    }
    assert_eq!(losses[0].to_bits(), losses[1].to_bits());
}

#[test]
fn a_gpu_checkpoint_renders_the_same_pixels_on_the_cpu_engine() {
    let _cores = crate::common::shared();
    let scene = small_scene();
    let (mut cpu, mut gpu) = models(&scene);
    share_ball_grid(&mut cpu, &mut gpu);
    let rays = batch(&scene, 256, 23);
    // A checkpoint of the gpu model, loaded into the cpu model, renders
    // the same pixels on both.
    gpu.step(&rays, 1);
    let checkpoint = gpu.save();
    cpu.load(&checkpoint).unwrap();
    assert!(cpu.params() == gpu.params().as_slice());
    assert_eq!(
        cpu.occupancy().unwrap().values(),
        gpu.occupancy().unwrap().values()
    );
    let from_cpu = common::render_first_val_view(&cpu, &scene);
    let from_gpu = common::render_first_val_view(&gpu, &scene);
    let mut worst = 0f32;
    for (a, b) in from_gpu.iter().zip(&from_cpu) {
        for (x, y) in a.rgb.iter().zip(&b.rgb).chain([(&a.opacity, &b.opacity)]) {
            worst = worst.max((x - y).abs());
        }
    }
    println!("render: largest colour/opacity difference {worst:.2e}");
    // Colours and opacity lie in [0, 1]: an absolute 1e-4 is the 1e-4
    // relative of a stage test at full scale; early termination at
    // transmittance 1e-4 can move a ray's cut by one sample, worth at most
    // ~1e-4 of colour.
    assert!(worst <= 1e-4, "{worst:e}");

    // And back: the cpu's checkpoint loads into the gpu model.
    gpu.load(&cpu.save()).unwrap();
    assert!(gpu.params() == cpu.params());
}

/// The grid's full update at step 0 on both engines, on a grid of 32³
/// cells instead of the paper's 128³ (32 thousand density evaluations
/// instead of 2 million, seconds on lavapipe instead of 1.5 minutes; the
/// update's code does not depend on the resolution).
#[test]
fn occupancy_update_matches_the_cpu_engine() {
    let _cores = crate::common::shared();
    let scene = small_scene();
    let mut recipe = zrak::field::ngp::recipe(scene.unit_cube.aabb_scale);
    recipe.occupancy.resolution = 32;
    let shape = || zrak::field::ngp::NgpShape::for_scene(&scene);
    let mut cpu = CpuModel::build(
        &crate::common::request(ModelKind::Ngp, SEED, LossKind::Huber, Some(BATCH_SAMPLES))
            .with_shape(shape())
            .with_recipe(recipe.clone()),
        &scene,
    );
    let mut gpu = build_gpu(
        common::gpu_context(),
        &crate::common::request(ModelKind::Ngp, SEED, LossKind::Huber, Some(BATCH_SAMPLES))
            .with_shape(shape())
            .with_recipe(recipe),
        &scene,
    )
    .expect("gpu model");
    gpu.set_read_back_late(false);
    // 32³ cells per cascade.
    assert_eq!(cpu.occupancy().unwrap().values().len() % (32 * 32 * 32), 0);
    let rays = batch(&scene, 256, 23);

    // Step 0 updates every cell of the grid first, with densities from
    // each engine's own networks.
    cpu.step(&rays, 0);
    let clock = Instant::now();
    gpu.step(&rays, 0);
    println!(
        "gpu step 0 with the full grid update: {:.0} ms",
        clock.elapsed().as_secs_f64() * 1e3
    );
    let (c, g) = (cpu.occupancy().unwrap(), gpu.occupancy().unwrap());
    let error = relative_norm(g.values(), c.values());
    let flipped: u32 = g
        .bitfield()
        .iter()
        .zip(c.bitfield())
        .map(|(a, b)| (a ^ b).count_ones())
        .sum();
    println!(
        "occupancy after step 0: relative error {error:.2e}, {flipped} of {} cells differ \
         (occupied: cpu {}, gpu {})",
        c.values().len(),
        c.occupied_count(),
        g.occupied_count()
    );
    // Densities through the same encode and network, each stage within
    // 1e-4 of the cpu.
    assert!(error < 1e-4, "{error:e}");
    // At the start all densities are ≈ exp(0) within ~1e-4, and the
    // threshold is their mean, so cells within f32 noise of it may land on
    // either side: allow 1% of the cells.
    assert!((flipped as usize) * 100 <= c.values().len(), "{flipped}");
}

/// A training step waits for the device once (for the march's counters,
/// which size the rest of the step); its loss, stage times and grid update
/// come back with the next step's wait. Steps 1 to 17 include step 16's
/// grid update; step 0 has no earlier step and waits for its own loss.
#[test]
fn a_step_waits_for_the_device_once() {
    let _cores = crate::common::shared();
    let scene = small_scene();
    let (mut cpu, mut gpu) = models_with_coarse_grid(&scene);
    share_ball_grid(&mut cpu, &mut gpu);
    gpu.set_read_back_late(true);
    let counters = gpu.context().counters.clone();
    let counts = common::readbacks_per_step(&mut gpu, &counters, &scene, 0..18);
    println!("blocking read-backs per step {counts:?}");
    assert_eq!(counts[0], 2, "the first step waits for its loss too");
    assert!(counts[1..].iter().all(|&n| n == 1), "{counts:?}");
}
