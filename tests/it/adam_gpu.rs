//! The gpu Adam step against the cpu engine's on lavapipe.

use zrak::engine::gpu::GpuContext;
use zrak::engine::gpu::adam::GpuAdam;
use zrak::engine::gpu::kernel::{Recorder, read_buffer, storage_buffer};
use zrak::engine::shared::adam::Adam;
use zrak::field::common::OptimiserConfig;
use zrak::rng::Pcg32;

const PAPER: OptimiserConfig = OptimiserConfig::PAPER;

/// Gradients for one step: a quarter exactly zero (sparse hash entries,
/// and dead network units), some of 1e-30 (issue 3's hard case: g² flushes
/// to zero, so the step is lr·m̂/ε, tiny), the rest from 1e-6 to 1e2 with
/// both signs. Every 97th index (from 5) never has a gradient and every
/// 89th only ever sees ±1e-30. No subnormals: WGSL lets a GPU flush them to zero, which
/// would turn a tiny gradient into a skipped entry on one engine only.
fn gradients(n: usize, step: u64) -> Vec<f32> {
    let mut rng = Pcg32::new(100 + step, 5);
    (0..n)
        .map(|i| {
            let kind = rng.next_f32();
            let sign = if rng.next_f32() < 0.5 { -1.0 } else { 1.0 };
            if i % 97 == 5 {
                0.0
            } else if i % 89 == 0 {
                sign * 1e-30
            } else if kind < 0.25 {
                0.0
            } else if kind < 0.35 {
                sign * 1e-30
            } else {
                sign * 10f32.powf(-6.0 + 8.0 * rng.next_f32())
            }
        })
        .collect()
}

/// Runs `steps` Adam steps on both engines from the same start and
/// compares every array. Returns the gpu's parameters and state.
fn compare(
    context: &GpuContext,
    n: usize,
    network: std::ops::Range<usize>,
    steps: u64,
) -> (Vec<f32>, Adam) {
    let mut rng = Pcg32::new(1, 1);
    let initial: Vec<f32> = (0..n)
        .map(|i| {
            if i % 11 == 0 {
                0.0
            } else {
                2.0 * rng.next_f32() - 1.0
            }
        })
        .collect();

    let mut cpu_params = initial.clone();
    let mut cpu = Adam::new(n);
    let mut gpu = GpuAdam::new(context, n).expect("the kernel compiles");
    let gpu_params = storage_buffer(context, "params", &initial);
    let mut rec = Recorder::new(context);
    let mut gradient_buffers = Vec::new();
    for step in 0..steps {
        let g = gradients(n, step);
        cpu.step(&PAPER, network.clone(), &mut cpu_params, &g);
        // All steps in one submission, as a training loop would chain them.
        gradient_buffers.push(storage_buffer(context, "gradients", &g));
        gpu.record_step(
            &mut rec,
            &PAPER,
            network.clone(),
            &gpu_params,
            gradient_buffers.last().unwrap(),
        );
    }
    rec.submit();
    let params: Vec<f32> = read_buffer(context, &gpu_params, n);
    let state = gpu.read_state(context);
    assert_eq!(state.step, cpu.step);

    // Both engines evaluate the same f32 expressions; they may differ by
    // the GPU fusing a multiply-add (½ ulp) and by WGSL's division and
    // square root (2.5 ulp each instead of correctly rounded). Per step
    // that is ≤ ~8 ulp ≈ 5e-7 relative on each quantity; m, v and the
    // norms carry earlier steps' differences forward damped by β < 1, so
    // after a few steps they stay within ~3e-6. 1e-5 relative bounds it.
    let relative =
        |gpu: f32, cpu: f32| (gpu as f64 - cpu as f64).abs() / (cpu as f64).abs().max(1e-30);
    let worst = (0..n)
        .map(|i| relative(state.m[i], cpu.m[i]).max(relative(state.v[i], cpu.v[i])))
        .fold(0f64, f64::max);
    let differing = (0..n).filter(|&i| params[i] != cpu_params[i]).count();
    eprintln!("worst m, v difference {worst:e}; parameters not bit-identical: {differing} of {n}");
    for i in 0..n {
        assert!(
            relative(state.m[i], cpu.m[i]) <= 1e-5,
            "m[{i}]: gpu {} cpu {}",
            state.m[i],
            cpu.m[i]
        );
        assert!(
            relative(state.v[i], cpu.v[i]) <= 1e-5 || state.v[i] == cpu.v[i],
            "v[{i}]"
        );
        assert!(
            relative(state.m_norm[i], cpu.m_norm[i]) <= 1e-5 || cpu.m_norm[i] == 0.0,
            "m_norm[{i}]"
        );
        assert!(
            relative(state.v_norm[i], cpu.v_norm[i]) <= 1e-5 || cpu.v_norm[i] == 0.0,
            "v_norm[{i}]"
        );
        // The parameter's change (each step's of size ≤ lr) to 1e-5 of
        // itself, plus the rounding of p itself: half an ulp per step.
        let moved_gpu = params[i] as f64 - initial[i] as f64;
        let moved_cpu = cpu_params[i] as f64 - initial[i] as f64;
        let ulp = (initial[i].abs().max(params[i].abs()) as f64) * f32::EPSILON as f64;
        assert!(
            (moved_gpu - moved_cpu).abs() <= 1e-5 * moved_cpu.abs() + steps as f64 * ulp,
            "p[{i}]: moved gpu {moved_gpu:e} cpu {moved_cpu:e}"
        );
        // Entries outside the network that never had a gradient are
        // bitwise untouched on both engines.
        if cpu.m_norm[i] == 0.0 {
            assert!(!network.contains(&i));
            assert_eq!((params[i], state.m[i], state.v[i]), (initial[i], 0.0, 0.0));
        }
        assert!(params[i].is_finite() && state.m[i].is_finite() && state.v[i].is_finite());
    }
    (params, state)
}

#[test]
fn adam_matches_cpu_over_several_steps() {
    let _cores = crate::common::shared();
    let context = GpuContext::new().expect("CI installs mesa-vulkan-drivers, so an adapter exists");
    // Network weights in the middle, hash entries on both sides; a count
    // that is not a multiple of the workgroup.
    let n = 20_000 + 13;
    let steps = 6;
    let network = 5_000..9_000;
    let (params, state) = compare(&context, n, network.clone(), steps);

    // Hash entries without gradient stayed as they were (checked in
    // `compare`); entries touched only at some steps have norms that show
    // how many updates they had.
    let untouched = (0..n).filter(|&i| state.m_norm[i] == 0.0).count();
    let partly = (0..n)
        .filter(|&i| !network.contains(&i) && state.m_norm[i] > 0.0)
        .filter(|&i| (state.m_norm[i] - (1.0 - PAPER.beta1.powi(steps as i32))).abs() > 1e-3)
        .count();
    assert!(
        untouched > 100 && partly > 1000,
        "untouched {untouched}, partly {partly}"
    );
    // A parameter that starts at 0 and only ever sees ±1e-30 moves by
    // lr · |m̂|/ε ≤ 1e-17 per step: finite and tiny, on both engines.
    let mut tiny = 0;
    for i in (0..n).step_by(11 * 89).filter(|i| !network.contains(i)) {
        tiny += 1;
        assert!(
            params[i] != 0.0 && params[i].abs() <= steps as f32 * 1.01e-17,
            "{i}: {}",
            params[i]
        );
    }
    assert!(tiny > 10);
}

#[test]
fn adam_resumes_from_a_cpu_state() {
    let _cores = crate::common::shared();
    // A checkpointed cpu state continues on the gpu as it would on the cpu.
    let context = GpuContext::new().expect("an adapter exists");
    let n = 3000;
    let network = 0..1000;
    let mut params: Vec<f32> = (0..n).map(|i| (i as f32 * 0.37).sin()).collect();
    let mut cpu = Adam::new(n);
    for step in 0..3 {
        cpu.step(&PAPER, network.clone(), &mut params, &gradients(n, step));
    }
    let mut gpu = GpuAdam::from_state(&context, &cpu).expect("the kernel compiles");
    assert_eq!(gpu.read_state(&context), cpu);
    let buffer = storage_buffer(&context, "params", &params);
    let g = gradients(n, 3);
    let g_buffer = storage_buffer(&context, "gradients", &g);
    let mut rec = Recorder::new(&context);
    gpu.record_step(&mut rec, &PAPER, network.clone(), &buffer, &g_buffer);
    rec.submit();
    let before = params.clone();
    cpu.step(&PAPER, network, &mut params, &g);
    let gpu_params: Vec<f32> = read_buffer(&context, &buffer, n);
    for i in 0..n {
        let moved_gpu = gpu_params[i] as f64 - before[i] as f64;
        let moved_cpu = params[i] as f64 - before[i] as f64;
        let ulp = before[i].abs().max(params[i].abs()) as f64 * f32::EPSILON as f64;
        assert!(
            (moved_gpu - moved_cpu).abs() <= 1e-5 * moved_cpu.abs() + ulp,
            "{i}"
        );
    }
    assert_eq!(gpu.step, 4);
}

#[test]
fn adam_covers_instant_ngp_sized_parameter_sets() {
    let _cores = crate::common::shared();
    // 16 levels × 2^19 entries × 2 features + the networks: more than
    // 65535 workgroups of 256, so the dispatch is a 2-D grid. One step;
    // every parameter must have moved as on the cpu (checked on a sample
    // of indices across the whole range, including the last).
    let context = GpuContext::new().expect("an adapter exists");
    let network = 10_240;
    let n = 16 * (1 << 19) * 2 + network;
    assert!(n > 65535 * 256);
    let initial: Vec<f32> = (0..n).map(|i| ((i % 1000) as f32 - 500.0) * 1e-4).collect();
    let g: Vec<f32> = (0..n)
        .map(|i| {
            if i % 7 == 0 {
                0.0
            } else {
                ((i % 13) as f32 - 6.5) * 1e-3
            }
        })
        .collect();
    let mut gpu = GpuAdam::new(&context, n).expect("the kernel compiles");
    let params = storage_buffer(&context, "params", &initial);
    let gradients = storage_buffer(&context, "gradients", &g);
    let mut rec = Recorder::new(&context);
    let start = std::time::Instant::now();
    gpu.record_step(&mut rec, &PAPER, 0..network, &params, &gradients);
    rec.submit();
    let result: Vec<f32> = read_buffer(&context, &params, n);
    eprintln!(
        "gpu adam over {n} parameters (with read-back): {:?}",
        start.elapsed()
    );
    let mut cpu_params = initial.clone();
    Adam::new(n).step(&PAPER, 0..network, &mut cpu_params, &g);
    let lr = PAPER.learning_rate as f64;
    for i in (0..n)
        .step_by(997)
        .chain([n - 1, n - 2, 65535 * 256, 65535 * 256 - 1])
    {
        let moved_gpu = result[i] as f64 - initial[i] as f64;
        let moved_cpu = cpu_params[i] as f64 - initial[i] as f64;
        // A first step moves by lr·sign(g), or not at all for g = 0.
        assert!(
            (moved_gpu - moved_cpu).abs() <= 1e-5 * lr,
            "{i}: gpu {moved_gpu:e} cpu {moved_cpu:e}"
        );
        if i >= network && g[i] == 0.0 {
            assert_eq!(result[i], initial[i]);
        }
    }
}
