//! Throughput of the cpu engine's stages on training-sized batches: the
//! dense layers, the hash grid, the march, compositing and the optimiser.
//! Each was an ignored test of its module until issue 44 kept `src/` to
//! tests that assert.

use glam::Vec3;
use zrak::engine::cpu::composite_batch::{
    CompositeGradients, CompositeOutputs, composite_backward, composite_forward,
};
use zrak::engine::cpu::dense::{
    InputGradient, MlpGradients, MlpWorkspace, backend, measure_peak_gflops, mlp_backward,
    mlp_forward, mlp_inference,
};
use zrak::engine::cpu::hash_grid::{encode_backward_with_scratch, encode_with_scratch};
use zrak::engine::cpu::march::{MarchWorkspace, march};
use zrak::engine::shared::adam::Adam;
use zrak::engine::shared::batch_sizer::BatchSizer;
use zrak::engine::shared::composite::RayBatch;
use zrak::engine::shared::march::{MarchParams, MarchedSamples};
use zrak::engine::shared::occupancy::OccupancyGrid;
use zrak::field::common::{MarchConfig, OptimiserConfig};
use zrak::field::encoding::{HashGridConfig, HashGridLayout};
use zrak::field::mlp::{Activation, MlpLayout, NetworkConfig};
use zrak::field::ngp::SAMPLES_PER_BATCH;
use zrak::rng::Pcg32;
use zrak::scene::UnitCubeMapping;

/// `n` values drawn uniformly from [-scale, scale).
fn random(rng: &mut Pcg32, n: usize, scale: f32) -> Vec<f32> {
    (0..n)
        .map(|_| (2.0 * rng.next_f32() - 1.0) * scale)
        .collect()
}

/// The CPU time of all this process's threads so far, in seconds: the
/// first field of each thread's schedstat is its time on a CPU, in
/// nanoseconds (Linux; 0 elsewhere). On a shared machine it says what the
/// code costs per core-second even when other work takes cores away.
fn process_cpu_seconds() -> f64 {
    let Ok(tasks) = std::fs::read_dir("/proc/self/task") else {
        return 0.0;
    };
    let mut total = 0u64;
    for task in tasks.flatten() {
        if let Ok(stat) = std::fs::read_to_string(task.path().join("schedstat")) {
            total += stat
                .split_whitespace()
                .next()
                .and_then(|v| v.parse::<u64>().ok())
                .unwrap_or(0);
        }
    }
    total as f64 * 1e-9
}

/// Wall and CPU seconds of one call of `f`.
fn timed(f: &mut dyn FnMut()) -> (f64, f64) {
    let (start, cpu) = (std::time::Instant::now(), process_cpu_seconds());
    f();
    (start.elapsed().as_secs_f64(), process_cpu_seconds() - cpu)
}

/// GFLOP/s of the Instant-NGP networks (and NeRF's 8 × 256 trunk) at 2^18
/// rows, forward, inference and backward. Run with
/// `cargo bench --bench probes -- cpu_dense_throughput`.
pub fn cpu_dense_throughput() {
    let rows = SAMPLES_PER_BATCH;
    let ngp = NetworkConfig::PAPER;
    eprintln!(
        "backend {:?}, threads {}",
        backend(),
        rayon::current_num_threads()
    );
    eprintln!("peak (1024³ SGEMM): {:.0} GFLOP/s", measure_peak_gflops());
    let layouts = [
        (
            "density",
            MlpLayout::ngp_density(&ngp, &HashGridConfig::paper(1.0)),
        ),
        ("colour", MlpLayout::ngp_colour(&ngp)),
        ("nerf 8×256", {
            let mut w = vec![63];
            w.extend([256; 8]);
            w.push(4);
            MlpLayout::new(w, Activation::Relu, Activation::None, true)
        }),
    ];
    let mut rng = Pcg32::new(1, 7);
    let mut total = [0.0f64; 3];
    for (name, layout) in &layouts {
        let params = layout.init_params(1);
        let input = random(&mut rng, rows * layout.input_width(), 1.0);
        let d_out = random(&mut rng, rows * layout.output_width(), 1.0);
        let mut ws = MlpWorkspace::new(layout, rows);
        let mut out = vec![0.0; rows * layout.output_width()];
        let mut d_params = vec![0.0; params.len()];
        let mut d_input = vec![0.0; input.len()];
        // The median of seven runs' wall time, and their mean CPU time.
        let median = |f: &mut dyn FnMut()| {
            f();
            let mut t: Vec<(f64, f64)> = (0..7).map(|_| timed(f)).collect();
            t.sort_by(|a, b| a.0.total_cmp(&b.0));
            let cpu = t.iter().map(|x| x.1).sum::<f64>() / t.len() as f64;
            (t[3].0, cpu)
        };
        let (fwd, fwd_cpu) =
            median(&mut || mlp_forward(layout, &params, &input, rows, &mut ws, &mut out));
        let (inf, inf_cpu) = median(&mut || mlp_inference(layout, &params, &input, rows, &mut out));
        let (bwd, bwd_cpu) = median(&mut || {
            mlp_backward(
                layout,
                &params,
                &input,
                rows,
                &mut ws,
                MlpGradients {
                    output: &d_out,
                    params: &mut d_params,
                    input: Some(InputGradient::every_column(&mut d_input, layout)),
                },
            )
        });
        let flop = 2.0 * (layout.macs_per_row() * rows) as f64;
        eprintln!(
            "{name:>11}: forward {:.1} ms ({:.0} GFLOP/s; {:.0} per CPU-second), inference {:.1} ms ({:.0} GFLOP/s; {:.0} per CPU-second), \
             backward {:.1} ms ({:.0} GFLOP/s; {:.0} per CPU-second)",
            fwd * 1e3,
            flop / fwd / 1e9,
            flop / fwd_cpu / 1e9,
            inf * 1e3,
            flop / inf / 1e9,
            flop / inf_cpu / 1e9,
            bwd * 1e3,
            2.0 * flop / bwd / 1e9,
            2.0 * flop / bwd_cpu / 1e9,
        );
        if name != &"nerf 8×256" {
            total[0] += fwd;
            total[1] += bwd;
            total[2] += flop * 3.0;
        }
    }
    let step = total[0] + total[1];
    eprintln!(
        "NGP networks forward+backward: {:.1} ms per 2^18 samples = {:.1} M samples/s ({:.0} GFLOP/s)",
        step * 1e3,
        rows as f64 / step / 1e6,
        total[2] / step / 1e9
    );
}

/// The hash grid's forward and backward pass on a training batch of 2^18
/// samples, scattered and along marched rays, on the paper's grid and, to
/// show what the arithmetic alone costs, on one whose tables fit in L1.
/// Run with `cargo bench --bench probes -- cpu_hash_grid_throughput`.
pub fn cpu_hash_grid_throughput() {
    let mut rng = Pcg32::new(1, 5);
    let mut position = || [rng.next_f32(), rng.next_f32(), rng.next_f32()];
    let scattered: Vec<[f32; 3]> = (0..SAMPLES_PER_BATCH).map(|_| position()).collect();
    // Rays of 64 consecutive samples at the paper's step, as the ray
    // marcher emits them.
    let step = MarchConfig::PAPER.step;
    let mut marched = Vec::with_capacity(SAMPLES_PER_BATCH);
    let mut rng = Pcg32::new(2, 5);
    while marched.len() < SAMPLES_PER_BATCH {
        let origin = Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32());
        let d = Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32()) * 2.0 - 1.0;
        let d = d / d.length();
        for k in 0..64 {
            let p = (origin + k as f32 * step * d).clamp(Vec3::ZERO, Vec3::ONE);
            marched.push(p.to_array());
        }
    }
    for log2_table_size in [19, 10] {
        let layout = HashGridLayout::new(&HashGridConfig {
            log2_table_size,
            ..HashGridConfig::paper(1.0)
        });
        let params = layout.init_params(1);
        let width = layout.output_width();
        let d_out = random(&mut rng, SAMPLES_PER_BATCH * width, 1.0);
        let mut out = vec![0.0f32; SAMPLES_PER_BATCH * width];
        let mut d_params = vec![0.0f32; layout.param_count()];
        let mut scratch = Vec::new();
        for (name, positions) in [("scattered", &scattered), ("marched", &marched)] {
            // The best of seven runs, wall and CPU time each: on a shared
            // machine other work only ever slows a run down.
            let (mut forward, mut backward) = ((f64::MAX, f64::MAX), (f64::MAX, f64::MAX));
            let best = |a: (f64, f64), b: (f64, f64)| (a.0.min(b.0), a.1.min(b.1));
            for _ in 0..7 {
                let f = timed(&mut || {
                    encode_with_scratch(&layout, &params, positions, &mut out, &mut scratch)
                });
                forward = best(forward, f);
                let b = timed(&mut || {
                    encode_backward_with_scratch(
                        &layout,
                        positions,
                        &d_out,
                        &mut d_params,
                        &mut scratch,
                    )
                });
                backward = best(backward, b);
            }
            let n = SAMPLES_PER_BATCH as f64 / 1e6;
            println!(
                "T = 2^{log2_table_size}, {name}: forward {:.2} M samples/s ({:.2} M per cpu-second), \
                 backward {:.2} M samples/s ({:.2} M per cpu-second), {} threads",
                n / forward.0,
                n / forward.1,
                n / backward.0,
                n / backward.1,
                rayon::current_num_threads()
            );
        }
    }
}

/// `n` rays from a sphere of radius 4 (one in eight from inside radius
/// 1.2) towards points of the box ±1.2: training rays around a Blender
/// scene, some starting inside it.
fn random_rays(n: usize, seed: u64) -> (Vec<f32>, Vec<f32>) {
    let mut rng = Pcg32::new(seed, 3);
    let mut origins = Vec::with_capacity(3 * n);
    let mut directions = Vec::with_capacity(3 * n);
    for i in 0..n {
        let z = 2.0 * rng.next_f32() - 1.0;
        let phi = std::f32::consts::TAU * rng.next_f32();
        let r = (1.0 - z * z).sqrt();
        let radius = if i % 8 == 0 {
            1.2 * rng.next_f32()
        } else {
            4.0
        };
        let origin = radius * Vec3::new(r * phi.cos(), r * phi.sin(), z);
        let target = Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32()) * 2.4 - 1.2;
        let direction = (target - origin).normalize();
        origins.extend_from_slice(&origin.to_array());
        directions.extend_from_slice(&direction.to_array());
    }
    (origins, directions)
}

/// The cpu march on a lego-like grid (a ball of radius 0.35 occupied),
/// batches sized to 2^18 samples, on one thread and on all. Run with
/// `cargo bench --bench probes -- cpu_march_throughput`.
pub fn cpu_march_throughput() {
    const BLENDER: UnitCubeMapping = UnitCubeMapping::BLENDER;
    let mut grid = OccupancyGrid::for_scene(&BLENDER);
    let geometry = grid.geometry();
    for (i, v) in grid.values_mut().iter_mut().enumerate() {
        let centre = geometry.cell_centre(geometry.cell_at(i));
        *v = if centre.distance(Vec3::splat(0.5)) < 0.35 {
            1.0
        } else {
            0.0
        };
    }
    grid.build_bitfield();
    println!("occupancy {:.1}%", 100.0 * grid.occupancy_fraction());
    let mut sizer = BatchSizer::new(SAMPLES_PER_BATCH);
    let mut workspace = MarchWorkspace::default();
    let mut out = MarchedSamples::default();
    let (origins, directions) = random_rays(1 << 18, 77);
    for _ in 0..10 {
        let rays = sizer.rays();
        let stats = march(
            &grid,
            &origins[..3 * rays],
            &directions[..3 * rays],
            &MarchParams::training(BLENDER, 1),
            &mut workspace,
            &mut out,
        );
        sizer.record(rays, stats.samples);
    }
    let rays = sizer.rays();
    // The machine is shared: the fastest of many batches is the figure
    // least disturbed by other work.
    let mut run = |label: &str| {
        let mut best = f64::INFINITY;
        let mut samples = 0;
        let cpu_before = process_cpu_seconds();
        for i in 0..60 {
            let started = std::time::Instant::now();
            samples = march(
                &grid,
                &origins[..3 * rays],
                &directions[..3 * rays],
                &MarchParams::training(BLENDER, i),
                &mut workspace,
                &mut out,
            )
            .samples;
            best = best.min(started.elapsed().as_secs_f64());
        }
        let cpu = process_cpu_seconds() - cpu_before;
        println!(
            "{label}: {rays} rays, {samples} samples ({:.1}/ray), {:.2} ms per batch: {:.2} M rays/s, \
             {:.1} M samples/s; {:.1} M samples per cpu-second",
            samples as f64 / rays as f64,
            1e3 * best,
            rays as f64 / best / 1e6,
            samples as f64 / best / 1e6,
            60.0 * samples as f64 / cpu / 1e6,
        );
    };
    rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap()
        .install(|| run("1 thread"));
    run(&format!("{} threads", rayon::current_num_threads()));
}

/// Compositing, forward and backward, of a training batch of 2^18 samples
/// in rays of 1 to 128 samples (about 64 on average), a third of them
/// dense enough to be cut early. Run with
/// `cargo bench --bench probes -- cpu_composite_throughput`.
pub fn cpu_composite_throughput() {
    let samples = SAMPLES_PER_BATCH;
    let mut rng = Pcg32::new(1, 9);
    let mut ray_offsets = vec![0u32];
    let (mut density, mut dt, mut t) = (Vec::new(), Vec::new(), Vec::new());
    // Each ray's density scale, in turn: near-empty to saturating.
    let scales = [1.0, 10.0, 100.0];
    while density.len() < samples {
        let n = (1 + (rng.next_f32() * 127.0) as usize).min(samples - density.len());
        let scale = scales[(ray_offsets.len() - 1) % scales.len()];
        let mut far = 2.0;
        for _ in 0..n {
            let d = 0.01 + 0.05 * rng.next_f32();
            dt.push(d);
            t.push(far + 0.5 * d);
            far += d;
            density.push(scale * rng.next_f32());
        }
        ray_offsets.push(density.len() as u32);
    }
    let rays = ray_offsets.len() - 1;
    let rgb: Vec<f32> = (0..3 * samples).map(|_| rng.next_f32()).collect();
    let background: Vec<f32> = (0..3 * rays).map(|_| rng.next_f32()).collect();
    let view = RayBatch {
        density: &density,
        rgb: &rgb,
        dt: &dt,
        t: &t,
        ray_offsets: &ray_offsets,
        background: &background,
    };
    let (mut out_rgb, mut opacity, mut depth, mut used) = (
        vec![0f32; 3 * rays],
        vec![0f32; rays],
        vec![0f32; rays],
        vec![0u32; rays],
    );
    let (mut d_density, mut d_colour) = (vec![0f32; samples], vec![0f32; 3 * samples]);
    let d_rgb = vec![0.1f32; 3 * rays];
    let cut = MarchConfig::PAPER.min_transmittance;
    let mut run = || {
        composite_forward(
            &view,
            cut,
            CompositeOutputs {
                rgb: &mut out_rgb,
                opacity: &mut opacity,
                depth: &mut depth,
                samples_used: &mut used,
            },
        );
        composite_backward(
            &view,
            cut,
            &d_rgb,
            None,
            CompositeGradients {
                density: &mut d_density,
                rgb: &mut d_colour,
                background: None,
            },
        );
    };
    run();
    let repeats = 20;
    let start = std::time::Instant::now();
    for _ in 0..repeats {
        run();
    }
    let seconds = start.elapsed().as_secs_f64() / repeats as f64;
    println!(
        "composite forward+backward: {samples} samples, {rays} rays in {:.2} ms: {:.1} M samples/s ({} threads)",
        seconds * 1e3,
        samples as f64 / seconds / 1e6,
        rayon::current_num_threads()
    );
}

/// The optimiser on Instant-NGP's parameter count (16 levels of 2^19
/// entries of 2 features, and the networks), with every gradient set, with
/// a quarter of the hash entries' (about what a batch touches at the fine
/// levels), and with half of the hash entries' blocks empty (the fine
/// levels away from surfaces: a block without gradient is skipped after
/// one read). Run with `cargo bench --bench probes -- cpu_adam_throughput`.
pub fn cpu_adam_throughput() {
    let hash = 16 * (1 << 19) * 2;
    let network = 10_240;
    let n = hash + network;
    let mut params = vec![0.0f32; n];
    let mut rng = Pcg32::new(1, 4);
    let r: Vec<f32> = (0..4096).map(|_| rng.next_f32()).collect();
    let dense: Vec<f32> = (0..n).map(|i| r[i % 4096] - 0.5).collect();
    let sparse: Vec<f32> = (0..n)
        .map(|i| {
            if i < network || i % 4 == 0 {
                dense[i]
            } else {
                0.0
            }
        })
        .collect();
    let blocks: Vec<f32> = (0..n)
        .map(|i| {
            if i < network || (i / zrak::engine::shared::adam::BLOCK).is_multiple_of(2) {
                dense[i]
            } else {
                0.0
            }
        })
        .collect();
    let config = OptimiserConfig::PAPER;
    let mut adam = Adam::new(n);
    for (name, gradients) in [
        ("dense", &dense),
        ("1/4 of hash entries", &sparse),
        ("1/2 of hash blocks", &blocks),
    ] {
        adam.step(&config, 0..network, &mut params, gradients);
        let steps = 10;
        let start = std::time::Instant::now();
        for _ in 0..steps {
            adam.step(&config, 0..network, &mut params, gradients);
        }
        let seconds = start.elapsed().as_secs_f64() / steps as f64;
        println!(
            "adam ({name}): {n} params in {:.2} ms, {:.0} Mparams/s",
            seconds * 1e3,
            n as f64 / seconds / 1e6
        );
    }
}
