//! `zrak bench dense`, `bench throughput` and `bench gpu`: benchmarks that
//! print figures (`bench quality` has its own module, [`super::quality`]).

use std::sync::Arc;
use std::time::Instant;

use anyhow::Context;
use clap::Args;
use zrak::engine::cpu::dense::backend_for;
use zrak::engine::request::{ModelRequest, ModelSettings};
use zrak::engine::{EngineKind, build, choose_engine};
use zrak::field::ModelKind;
use zrak::field::common::Sampling;
use zrak::field::mlp::Precision;
use zrak::interrupt::{
    note, say, {self},
};
use zrak::model::RenderMode;
use zrak::scene::{Camera, Scene};
use zrak::train::trainer::Trainer;

use super::{KernelsLine, SpaceChoice, load_scene};

#[derive(Args, Debug)]
pub struct DenseArgs {
    /// Rows (samples) per pass.
    #[arg(long, default_value_t = 16384)]
    rows: usize,
    #[arg(long, default_value_t = 5)]
    repeats: usize,
}

#[derive(Args, Debug)]
pub struct ThroughputArgs {
    #[arg(long)]
    scene: Option<String>,
    #[arg(long, value_enum)]
    engine: Option<EngineKind>,
    #[arg(long, default_value_t = 1)]
    downscale: u32,
    #[arg(long, value_enum, default_value_t = ModelKind::Ngp)]
    model: ModelKind,
    /// NeRF's sampler.
    #[arg(long, value_enum, default_value_t = Sampling::Occupancy)]
    sampling: Sampling,
    /// Unmeasured steps first. Default: past the occupancy grid's
    /// warm-up (its first 256 steps update every cell, twice the work
    /// of a later update) plus 32, so the figures are those of most of a
    /// run; 1 on a software adapter, where a gpu step takes minutes.
    #[arg(long)]
    warmup: Option<usize>,
    /// Measured steps.
    #[arg(long, default_value_t = 32)]
    steps: usize,
    /// How the cpu engine computes the networks' products: f32, or mixed
    /// (bf16 products, f32 sums, on processors with AVX512-BF16). Default:
    /// mixed where the processor has bf16 kernels, else f32.
    #[arg(long, value_enum)]
    precision: Option<Precision>,
    /// What the scene is treated as; auto leaves it to the scene analysis.
    #[arg(long, value_enum, default_value_t = SpaceChoice::Auto)]
    space: SpaceChoice,
}

#[derive(Args, Debug)]
pub struct GpuBenchArgs {
    /// The scene the stage times are measured on (default: lego_400 when
    /// present beside the checkout, else the demo scene).
    #[arg(long)]
    scene: Option<String>,
    /// The models, comma-separated.
    #[arg(
        long,
        value_enum,
        value_delimiter = ',',
        default_value = "ngp,nerf,mipnerf"
    )]
    models: Vec<ModelKind>,
    /// Unmeasured steps before the timed ones (default: each model's
    /// occupancy warm-up and a few more, as `bench throughput`).
    #[arg(long)]
    warmup: Option<usize>,
    /// Timed steps per model (0: the self-check only).
    #[arg(long, default_value_t = 16)]
    steps: usize,
    /// What the scene is treated as; auto leaves it to the scene analysis.
    #[arg(long, value_enum, default_value_t = SpaceChoice::Auto)]
    space: SpaceChoice,
}

/// NeRF's networks in f32 and, where the processor has bf16 kernels, in
/// mixed precision, one after the other in one run, against the machine's
/// f32 matrix-multiply rate and its multiply-add ceilings.
pub fn bench_dense(args: DenseArgs) -> anyhow::Result<()> {
    use zrak::engine::cpu::dense::{arithmetic_peak_gflops, measure_peak_gflops};
    let DenseArgs { rows, repeats } = args;
    let gemm_peak = measure_peak_gflops();
    let f32_kernels = backend_for(Precision::F32);
    let f32_ceiling = arithmetic_peak_gflops(f32_kernels);
    println!("threads              {}", rayon::current_num_threads());
    let mut precisions = vec![Precision::F32];
    if Precision::Mixed.kernels_here() == Precision::Mixed {
        precisions.push(Precision::Mixed);
    } else {
        println!("mixed precision      skipped: this processor has no bf16 kernels (AVX512-BF16)");
    }
    for precision in precisions {
        let kernels = backend_for(precision);
        println!("{} ({kernels:?} kernels):", precision.name());
        let figures = zrak::bench::dense_throughput(rows, repeats, precision);
        let (mut flop, mut seconds) = (0.0, 0.0);
        for f in &figures {
            println!(
                "  {:<22} {:?} × {} rows: forward {:>6.1} GFLOP/s ({:.1} ms), backward {:>6.1} GFLOP/s ({:.1} ms)",
                f.name,
                f.widths,
                f.rows,
                f.forward_gflops,
                f.forward_seconds * 1e3,
                f.backward_gflops,
                f.backward_seconds * 1e3
            );
            flop += f.forward_gflops * f.forward_seconds + f.backward_gflops * f.backward_seconds;
            seconds += f.forward_seconds + f.backward_seconds;
        }
        let overall = flop / seconds;
        let ceiling = if kernels == f32_kernels {
            f32_ceiling
        } else {
            arithmetic_peak_gflops(kernels)
        };
        println!(
            "  NeRF networks        {overall:.1} GFLOP/s forward and backward together = {:.0}% of \
             the f32 matrix multiply, {:.0}% of this precision's multiply-add ceiling ({ceiling:.0})",
            100.0 * overall / gemm_peak,
            100.0 * overall / ceiling,
        );
    }
    println!(
        "machine peak         {gemm_peak:.0} GFLOP/s (f32 matrix multiply, best of 5); f32 \
         multiply-add ceiling {f32_ceiling:.0} GFLOP/s (registers only)"
    );
    Ok(())
}

/// Samples per batch when a bench runs the gpu engine on a software
/// adapter: NeRF's 16 rays with the paper's sampler, ~14 G FLOP a step
/// (its paper-size batch, ~1 T FLOP, would take many minutes a step at
/// lavapipe's few GFLOP/s), Instant-NGP's 1/64 of its 2^18; seconds on
/// lavapipe. There the bench is a correctness run.
const SOFTWARE_GPU_SAMPLES: usize = 1 << 12;

/// Unmeasured steps before a throughput measurement: the model's own
/// (past its occupancy grid's warm-up); 2 with the paper's sampler, which
/// has no grid, so a few steps settle its caches; 1 on a software adapter,
/// where a gpu step takes minutes. There the bench is a correctness run.
fn default_warmup(model: ModelKind, sampling: Sampling, software_gpu: bool) -> usize {
    match sampling {
        _ if software_gpu => 1,
        Sampling::Paper if model.has_paper_sampler() => 2,
        _ => model.spec().bench_warmup_steps,
    }
}

/// The benches' scene when none is given: lego_400 when present beside the
/// checkout, else the demo scene.
fn default_bench_scene() -> String {
    zrak::bench::default_scene_path()
        .map(|p| p.display().to_string())
        .unwrap_or_else(|| "demo".into())
}

/// The settings a bench builds `model` with: the model's own loss and
/// batch, except on a software adapter (see [`SOFTWARE_GPU_SAMPLES`]).
fn bench_settings(
    model: ModelKind,
    sampling: Sampling,
    precision: Precision,
    software_gpu: bool,
) -> ModelSettings {
    ModelSettings {
        seed: 0,
        loss: model.default_loss(),
        batch_samples: software_gpu.then_some(SOFTWARE_GPU_SAMPLES),
        sampling,
        precision,
        refine_cameras: false,
        appearance: false,
    }
}

pub fn bench_gpu(args: GpuBenchArgs) -> anyhow::Result<()> {
    use zrak::bench::gpu::{CheckSize, all_passed, check_scene_name, describe_device, self_check};
    // As `--engine gpu` does: a software adapter where the machine has a
    // GPU is refused, naming both.
    let gpu_choice = choose_engine(Some(EngineKind::Gpu))?;
    let context = gpu_choice
        .gpu
        .as_ref()
        .context("the gpu engine's choice has a context")?;
    for (name, value) in describe_device(context) {
        say(&format!("{name:<22} {value}"));
    }
    let software = context.is_software();
    let size = if software {
        CheckSize::SOFTWARE
    } else {
        CheckSize::DEVICE
    };
    say(&format!(
        "\nself-check: each model, one training step and one render from the same state on \
         both engines, {}, held to the parity tests' tolerances",
        check_scene_name(size)
    ));
    let mut checks = Vec::new();
    for &model in &args.models {
        if interrupt::requested() {
            break;
        }
        for check in self_check(context, model, size) {
            say(&format!(
                "  {:<11} {:<22} {}  {} ({})",
                check.model.name(),
                check.what,
                if check.passed { "pass" } else { "FAIL" },
                check.measured,
                check.limit
            ));
            checks.push(check);
        }
    }
    let failed = checks.iter().filter(|c| !c.passed).count();
    say(&format!(
        "self-check: {} of {} checks passed",
        checks.len() - failed,
        checks.len()
    ));

    if args.steps > 0 && !interrupt::requested() {
        let scene_name = args.scene.unwrap_or_else(default_bench_scene);
        let scene = Arc::new(args.space.apply(load_scene(&scene_name, 1)?));
        for &model in &args.models {
            if interrupt::requested() {
                break;
            }
            say(&format!("\n{} on {}:", model.name(), scene.name));
            // A context of its own per model, so its counters are its own.
            let choice = gpu_choice.share()?;
            let counters = choice.gpu.as_ref().map(|gpu| gpu.counters.clone());
            let engine_line = choice.reason.clone();
            let settings = bench_settings(model, Sampling::Occupancy, Precision::F32, software);
            let built = build(&ModelRequest::new(model, settings), choice, &scene)?;
            let mut trainer = Trainer::new(built, scene.clone(), 0);
            let warmup = args
                .warmup
                .unwrap_or_else(|| default_warmup(model, Sampling::Occupancy, software));
            let report = zrak::bench::throughput(
                &mut trainer,
                warmup,
                args.steps,
                interrupt::flag(),
                counters.as_deref(),
            );
            zrak::bench::print_report(&report, &scene, &engine_line);
            // A software rasteriser takes minutes for a 1280 × 720 level of an
            // untrained field: timed on real GPUs only.
            if !software
                && let Some(seconds) =
                    texture_render_seconds(trainer.model.as_ref(), context, &scene)
            {
                say(&format!(
                    "texture render       {:.1} ms per 1280 × 720 level (median of 3, the viewer's \
                     path: rendered on the device into the texture it draws)",
                    seconds * 1e3
                ));
            }
        }
    }
    if !all_passed(&checks) {
        anyhow::bail!(
            "the gpu engine's self-check failed: {failed} of {} checks",
            checks.len()
        );
    }
    Ok(())
}

/// Seconds for `model` to draw a 1280 × 720 view of `scene` into a
/// texture on the device, the viewer's path (median of three), if it can.
fn texture_render_seconds(
    model: &dyn zrak::model::RadianceModel,
    context: &zrak::engine::gpu::GpuContext,
    scene: &Scene,
) -> Option<f64> {
    let renderer = model.texture_render()?;
    let frame = scene.val.first().or(scene.train.first())?;
    let (width, height) = (1280, 720);
    let camera = Camera::new(
        zrak::scene::Intrinsics::from_fov_x(width, height, frame.camera.intrinsics.fov_x()),
        frame.camera.camera_to_world,
    );
    let target = zrak::engine::gpu::render::render_target(&context.device, width, height);
    let mut seconds = Vec::new();
    for _ in 0..3 {
        let clock = Instant::now();
        renderer
            .render_to_texture(&camera, RenderMode::Rgb, [1.0; 3], &target)
            .ok()?;
        context
            .device
            .poll(wgpu::PollType::wait_indefinitely())
            .ok()?;
        seconds.push(clock.elapsed().as_secs_f64());
    }
    seconds.sort_by(f64::total_cmp);
    Some(seconds[1])
}

pub fn bench_throughput(args: ThroughputArgs) -> anyhow::Result<()> {
    let ThroughputArgs {
        scene,
        engine,
        downscale,
        model,
        sampling,
        warmup,
        steps,
        precision,
        space,
    } = args;
    let precision = precision.unwrap_or_else(Precision::best_available);
    let scene_name = scene.unwrap_or_else(default_bench_scene);
    let scene = Arc::new(space.apply(load_scene(&scene_name, downscale)?));
    let choice = choose_engine(engine)?;
    let engine_line = choice.reason.clone();
    let counters = choice.gpu.as_ref().map(|gpu| gpu.counters.clone());
    let software_gpu =
        choice.kind == EngineKind::Gpu && choice.gpu.as_ref().is_some_and(|gpu| gpu.is_software());
    let warmup = warmup.unwrap_or_else(|| default_warmup(model, sampling, software_gpu));
    let settings = bench_settings(model, sampling, precision, software_gpu);
    let batch_samples = settings.batch_samples;
    let model = build(&ModelRequest::new(model, settings), choice, &scene)?;
    let mut trainer = Trainer::new(model, scene.clone(), 0);
    if let Some(samples) = batch_samples {
        println!("software adapter: batches of ~{samples} samples (a correctness run)");
    }
    let peak = zrak::engine::cpu::dense::measure_peak_gflops();
    let report = zrak::bench::throughput(
        &mut trainer,
        warmup,
        steps,
        interrupt::flag(),
        counters.as_deref(),
    );
    if interrupt::requested() {
        if report.steps == 0 {
            note("interrupted before any measured step: nothing to report");
            return Ok(());
        }
        note(&format!(
            "interrupted: the figures below are over {} of {steps} measured steps",
            report.steps
        ));
    }
    zrak::bench::print_report(&report, &scene, &engine_line);
    if let Some(kernels) = trainer.model.cpu_kernels() {
        println!("{}", KernelsLine(kernels));
    }
    println!("machine peak         {peak:.0} GFLOP/s (f32 matrix multiply, best of 5)");
    if let Some(gflops) = report.network_gflops {
        println!(
            "networks at          {:.0} % of the machine peak",
            100.0 * gflops / peak
        );
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cli::parse_args;

    #[test]
    fn bench_defaults() {
        let dense: DenseArgs = parse_args(&[]).unwrap();
        assert_eq!((dense.rows, dense.repeats), (16384, 5));
        let throughput: ThroughputArgs = parse_args(&[]).unwrap();
        assert_eq!(throughput.scene, None);
        assert_eq!(throughput.model, ModelKind::Ngp);
        assert_eq!(throughput.sampling, Sampling::Occupancy);
        assert_eq!((throughput.warmup, throughput.steps), (None, 32));
        assert_eq!(throughput.downscale, 1);
        assert_eq!(throughput.space, SpaceChoice::Auto);
        let gpu: GpuBenchArgs = parse_args(&[]).unwrap();
        assert_eq!(gpu.models, ModelKind::ALL);
        assert_eq!((gpu.warmup, gpu.steps), (None, 16));
        assert_eq!(gpu.space, SpaceChoice::Auto);
        let chosen: ThroughputArgs = parse_args(&["--space", "forward-facing"]).unwrap();
        assert_eq!(chosen.space, SpaceChoice::ForwardFacing);
    }

    #[test]
    fn bench_gpu_takes_its_models_comma_separated() {
        let gpu: GpuBenchArgs = parse_args(&["--models", "mipnerf,ngp", "--steps", "0"]).unwrap();
        assert_eq!(gpu.models, [ModelKind::MipNerf, ModelKind::Ngp]);
        assert_eq!(gpu.steps, 0);
        let error = parse_args::<GpuBenchArgs>(&["--models", "ngp,instant"]).unwrap_err();
        assert_eq!(error.kind(), clap::error::ErrorKind::InvalidValue);
        assert!(error.to_string().contains("'instant'"), "{error}");
    }

    #[test]
    fn warm_up_passes_the_occupancy_grids_own_warm_up() {
        let ngp_grid = zrak::field::common::OccupancyConfig::PAPER.warmup_steps as usize;
        let nerf_grid = zrak::field::nerf::OCCUPANCY.warmup_steps as usize;
        assert_eq!(
            default_warmup(ModelKind::Ngp, Sampling::Occupancy, false),
            ngp_grid + 32
        );
        assert_eq!(
            default_warmup(ModelKind::Nerf, Sampling::Occupancy, false),
            nerf_grid + 16
        );
        assert_eq!(
            default_warmup(ModelKind::MipNerf, Sampling::Occupancy, false),
            nerf_grid + 16
        );
        assert_eq!(default_warmup(ModelKind::Nerf, Sampling::Paper, false), 2);
        // Instant-NGP has no paper sampler: the setting leaves it on its grid.
        assert_eq!(
            default_warmup(ModelKind::Ngp, Sampling::Paper, false),
            ngp_grid + 32
        );
        // On a software adapter a step takes minutes: one is enough.
        for model in ModelKind::ALL {
            assert_eq!(default_warmup(model, Sampling::Occupancy, true), 1);
        }
    }

    #[test]
    fn software_adapters_train_small_batches() {
        let settings = bench_settings(ModelKind::Nerf, Sampling::Paper, Precision::F32, true);
        assert_eq!(settings.batch_samples, Some(SOFTWARE_GPU_SAMPLES));
        assert_eq!(settings.loss, ModelKind::Nerf.default_loss());
        let settings = bench_settings(ModelKind::Ngp, Sampling::Occupancy, Precision::F32, false);
        assert_eq!(settings.batch_samples, None);
        assert_eq!(settings.sampling, Sampling::Occupancy);
    }
}
