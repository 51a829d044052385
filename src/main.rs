//! The `zrak` command line.

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::Arc;
use std::time::Instant;

use anyhow::{Context, bail};
use clap::{Args, Parser, Subcommand};
use indicatif::{ProgressBar, ProgressStyle};
use serde::{Deserialize, Serialize};
use zrak::app::protocol::SceneSource;
use zrak::app::viewer::ViewerOptions;
use zrak::engine::cpu::dense::{Precision, backend_for};
use zrak::engine::{EngineKind, choose_engine};
use zrak::field::ModelKind;
use zrak::field::nerf::Sampling;
use zrak::field::ngp::{LossKind, OccupancyConfig};
use zrak::interrupt::{self, note, say};
use zrak::render::export::{ExportSettings, export_turntable};
use zrak::render::path::Turntable;
use zrak::render::{RenderMode, render_pixels, to_image};
use zrak::scene::demo::{self, DemoConfig};
use zrak::scene::{Camera, Frame, LoadOptions, Scene, Split};
use zrak::train::eval::{SplitScores, evaluate_split_until};
use zrak::train::log::MetricsLog;
use zrak::train::run::{Limits, RunFolder, Schedule, load_checkpoint, run};
use zrak::train::trainer::Trainer;
use zrak::train::{ModelSettings, build_model};

/// `println!` that never panics: a failed write to standard output (a full
/// disk, `> /dev/full`) is kept and reported when the command ends, as an
/// error with a non-zero status, instead of a panic.
macro_rules! println {
    () => {
        zrak::interrupt::print_line(format_args!(""))
    };
    ($($arg:tt)*) => {
        zrak::interrupt::print_line(format_args!($($arg)*))
    };
}

mod cli;
use cli::quality::bench_quality;

/// Train neural radiance fields (NeRF, Mip-NeRF, Instant-NGP) while you watch.
#[derive(Parser)]
#[command(name = "zrak", version, about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Option<Command>,
}

#[derive(Subcommand)]
enum Command {
    /// Print a scene's splits, resolution, intrinsics and bounds.
    Info {
        /// A folder in the NeRF-synthetic layout, with a transforms.json, or with a COLMAP model.
        scene: PathBuf,
        /// Integer image downscale, as training would load it.
        #[arg(long, default_value_t = 1)]
        downscale: u32,
    },
    /// Write the built-in demo scene to a folder in the NeRF-synthetic layout.
    Demo {
        /// The folder to write (created if missing).
        #[arg(long)]
        out: PathBuf,
        /// Width and height of every image, in pixels.
        #[arg(long, default_value_t = DemoConfig::default().size)]
        size: u32,
        /// Number of training views (val and test get a tenth each, at least one).
        #[arg(long, default_value_t = DemoConfig::default().train_views)]
        views: usize,
        /// The large-extent variant: an opaque backdrop sphere around the
        /// objects, aabb_scale 8, written as an instant-ngp transforms.json.
        #[arg(long)]
        large: bool,
        /// Write into a folder that is not empty, replacing the scene's
        /// files there (others are left alone).
        #[arg(long)]
        force: bool,
    },
    /// Convert a COLMAP model (sparse/0 and images/) into an instant-ngp /
    /// nerfstudio transforms.json, centred and scaled as zrak loads it.
    Convert {
        /// A folder with sparse/0/cameras.bin and images.bin (or .txt) and images/.
        colmap: PathBuf,
        /// The transforms.json to write (an existing file is kept unless
        /// --force).
        #[arg(long)]
        out: PathBuf,
        /// Replace an existing --out file (never one of the model's own).
        #[arg(long)]
        force: bool,
    },
    /// Train a model on a scene, writing checkpoints and metrics to a run folder.
    Train(TrainArgs),
    /// Score a trained run on a split: per-image and mean PSNR and SSIM on white.
    Eval {
        /// The run folder written by `zrak train`.
        run: PathBuf,
        #[arg(long, value_enum, default_value_t = SplitArg::Val)]
        split: SplitArg,
        /// Force an engine (default: the run's own choice rules).
        #[arg(long, value_enum)]
        engine: Option<EngineKind>,
        /// Evaluate at 1/N of the views' resolution: intrinsics scaled, the
        /// photographs area-averaged (Mip-NeRF's multiscale protocol: how
        /// much a model aliases when it sees the scene from further away).
        #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=64))]
        downscale: u32,
    },
    /// Render views of a trained run to PNG files.
    Render(RenderArgs),
    /// Benchmarks that print figures (throughput per stage, peak memory).
    #[command(subcommand)]
    Bench(BenchCommand),
    /// Open the viewer window and train while you watch (the default).
    View(ViewArgs),
}

#[derive(Args)]
struct ViewArgs {
    /// A scene folder (default: the built-in demo scene).
    scene: Option<PathBuf>,
    /// Default: gpu on a real GPU, cpu otherwise.
    #[arg(long, value_enum)]
    engine: Option<EngineKind>,
    #[arg(long, value_enum, default_value_t = ModelKind::Ngp)]
    model: ModelKind,
    /// NeRF's sampler: the occupancy grid (default) or the paper's
    /// stratified + importance sampling.
    #[arg(long, value_enum, default_value_t = Sampling::Occupancy)]
    sampling: Sampling,
    /// Save a PNG of the window to this path (after --screenshot-after).
    #[arg(long)]
    screenshot: Option<PathBuf>,
    /// Seconds after opening to take the screenshot.
    #[arg(long, default_value_t = 5.0, requires = "screenshot")]
    screenshot_after: f64,
    /// Close the window by itself after this many seconds.
    #[arg(long)]
    quit_after: Option<f64>,
    /// On exit, write per-frame times (UI update, time between frames; camera
    /// moving or still; median and 95th percentile) as JSON to this path.
    #[arg(long)]
    frame_log: Option<PathBuf>,
    /// Orbit the camera by itself, as if dragged (to measure a moving camera).
    #[arg(long)]
    auto_orbit: bool,
    /// How the cpu engine computes the networks' products: f32, or mixed
    /// (bf16 products, f32 sums, on processors with AVX512-BF16). Default:
    /// mixed where the processor has bf16 kernels, else f32.
    #[arg(long, value_enum)]
    precision: Option<Precision>,
    /// How many of the runs kept on closing (File → Recent runs) stay on
    /// disk: the newest; older ones are removed when another is kept.
    #[arg(long, default_value_t = zrak::train::kept::DEFAULT_KEPT_RUNS)]
    keep_runs: usize,
}

#[derive(Subcommand)]
enum BenchCommand {
    /// GFLOP/s of NeRF's dense networks (forward, backward) against the
    /// machine's measured f32 matrix-multiply peak.
    Dense {
        /// Rows (samples) per pass.
        #[arg(long, default_value_t = 16384)]
        rows: usize,
        #[arg(long, default_value_t = 5)]
        repeats: usize,
    },
    /// Training-step throughput per stage on a scene (default: lego_400 when
    /// present beside the checkout, else the demo scene).
    Throughput(ThroughputArgs),
    /// The gpu engine on this machine's GPU: the adapter, its limits and
    /// features; a self-check of each model against the cpu engine (one
    /// training step and one render, with the parity tests' tolerances);
    /// then each model's stage times for a training step. Exits with
    /// status 1 if a check fails.
    Gpu(GpuBenchArgs),
    /// The accuracy-versus-time experiment: trains each model on each scene
    /// for a budget of training time, scores PSNR and SSIM at marks along
    /// the way, and writes results.json, results.csv, report.md and plots
    /// into --out. Run it again to continue an interrupted experiment.
    Quality(QualityArgs),
}

#[derive(Args)]
struct ThroughputArgs {
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
}

#[derive(Args)]
struct GpuBenchArgs {
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
}

#[derive(Args)]
struct QualityArgs {
    /// Scene folders, or `demo` for the built-in demo scene.
    #[arg(required = true)]
    scenes: Vec<String>,
    /// The models, comma-separated.
    #[arg(
        long,
        value_enum,
        value_delimiter = ',',
        default_value = "ngp,nerf,mipnerf"
    )]
    models: Vec<ModelKind>,
    /// NeRF's and Mip-NeRF's samplers, comma-separated: each of those models
    /// runs once with each (Instant-NGP has only the occupancy grid).
    #[arg(long, value_enum, value_delimiter = ',', default_value = "occupancy")]
    sampling: Vec<Sampling>,
    /// Training time per model and scene, evaluation excluded: `90s`, `10m`.
    #[arg(long, value_parser = parse_duration, default_value = "10m")]
    budget: f64,
    /// Training times to score at, comma-separated (default: 1/20, 1/10,
    /// 1/5, 1/2 and all of the budget, i.e. 30s,1m,2m,5m,10m for 10m).
    #[arg(long, value_parser = parse_duration, value_delimiter = ',')]
    marks: Option<Vec<f64>>,
    /// The split scored (the papers use test; the NeRF-synthetic folders in
    /// ../shared have only train and val).
    #[arg(long, value_enum, default_value_t = SplitArg::Test)]
    split: SplitArg,
    /// Score every N-th view of the split, from the first (1: all views).
    #[arg(long, default_value_t = zrak::bench::quality::DEFAULT_EVERY,
          value_parser = clap::value_parser!(usize))]
    every: usize,
    /// Score 1/N² of each view's pixels, chosen by --eval-pixels, so that
    /// NeRF's slow renders stay affordable (1: every pixel).
    #[arg(long, default_value_t = zrak::bench::quality::DEFAULT_EVAL_DOWNSCALE)]
    eval_downscale: u32,
    /// tiles: full-resolution tiles, one from each block of N×N (estimates
    /// the full-resolution scores the papers report); downscaled: the whole
    /// view at 1/N resolution against area-averaged photographs (Mip-NeRF's
    /// multiscale protocol, which penalises aliasing).
    #[arg(long, value_enum, default_value_t = zrak::bench::quality::EvalPixels::Tiles)]
    eval_pixels: zrak::bench::quality::EvalPixels,
    /// Integer image downscale for training.
    #[arg(long, default_value_t = 1)]
    downscale: u32,
    /// Default: gpu on a real GPU, cpu otherwise.
    #[arg(long, value_enum)]
    engine: Option<EngineKind>,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Samples per training batch (default: each model's own, the papers'
    /// batches). Smaller batches make shorter steps, e.g. for a quick look;
    /// the figures then are not the papers' recipe.
    #[arg(long, value_parser = clap::value_parser!(u64).range(1..))]
    batch_samples: Option<u64>,
    /// PSNR targets in dB for the time-to-quality columns, comma-separated.
    #[arg(long, value_delimiter = ',', default_value = "25,30,33")]
    targets: Vec<f64>,
    /// The experiment's folder (created; one holding an experiment with the
    /// same settings is continued).
    #[arg(long)]
    out: PathBuf,
    /// How the cpu engine computes the networks' products: f32, or mixed
    /// (bf16 products, f32 sums, on processors with AVX512-BF16). Default:
    /// mixed where the processor has bf16 kernels, else f32.
    #[arg(long, value_enum)]
    precision: Option<Precision>,
}

#[derive(Args)]
struct TrainArgs {
    /// A scene folder, or `demo` for the built-in demo scene. With
    /// `--resume` it may be left out (the run knows its scene).
    #[arg(required_unless_present = "resume")]
    scene: Option<String>,
    // What the run is made of comes from its `run.json` when resuming, so
    // these conflict with `--resume` instead of being silently ignored
    // (clap does not count a default value as given).
    #[arg(long, value_enum, default_value_t = ModelKind::Ngp, conflicts_with = "resume")]
    model: ModelKind,
    /// NeRF's sampler: the occupancy grid (default) or the paper's
    /// stratified + importance sampling.
    #[arg(long, value_enum, default_value_t = Sampling::Occupancy, conflicts_with = "resume")]
    sampling: Sampling,
    /// Default: gpu on a real GPU, cpu otherwise; when resuming, the run's
    /// own choice (this overrides it: checkpoints move between engines).
    #[arg(long, value_enum)]
    engine: Option<EngineKind>,
    /// Stop after this many steps (counted from the start of the run).
    #[arg(long)]
    steps: Option<u32>,
    /// Stop after this much training time: `90s`, `10m`, `1h`.
    #[arg(long, value_parser = parse_duration)]
    time: Option<f64>,
    /// Integer image downscale.
    #[arg(long, default_value_t = 1, conflicts_with = "resume")]
    downscale: u32,
    /// Default: Huber for Instant-NGP (instant-ngp's config), L2 for NeRF
    /// (the paper's).
    #[arg(long, value_enum, conflicts_with = "resume")]
    loss: Option<LossArg>,
    #[arg(long, default_value_t = 0, conflicts_with = "resume")]
    seed: u64,
    /// The run folder (created; must be writable; one holding a run is
    /// refused unless --force).
    #[arg(long, required_unless_present = "resume")]
    out: Option<PathBuf>,
    /// Continue the run in this folder from its checkpoint.
    #[arg(long, conflicts_with = "out")]
    resume: Option<PathBuf>,
    /// Start a new run in an --out folder that holds one: the old run's
    /// folder is moved aside to OUT.old (renamed; nothing is deleted).
    #[arg(long, conflicts_with = "resume")]
    force: bool,
    /// Wall time between checkpoints: `30s`, `2m`. The first comes
    /// sooner, after 10 s of training (or this interval, if shorter), so a
    /// run killed early still keeps its start.
    #[arg(long, value_parser = parse_duration, default_value = "2m")]
    checkpoint_every: f64,
    /// Training seconds between held-out evaluations.
    #[arg(long, default_value_t = 30.0)]
    eval_every: f64,
    /// Train on every view at this many sizes: full, ½, ¼, … (Mip-NeRF's
    /// multiscale Blender protocol: 4), each size an equal share of the
    /// rays.
    #[arg(long, default_value_t = 1, conflicts_with = "resume",
          value_parser = clap::value_parser!(u32).range(1..=8))]
    training_scales: u32,
    /// How the cpu engine computes the networks' products: f32, or mixed
    /// (bf16 products, f32 sums, on processors with AVX512-BF16). Default:
    /// mixed where the processor has bf16 kernels, else f32; when
    /// resuming, the run's own (this overrides it).
    #[arg(long, value_enum)]
    precision: Option<Precision>,
}

#[derive(Args)]
struct RenderArgs {
    /// The run folder written by `zrak train`.
    run: PathBuf,
    /// Render the camera of this view of `--split`.
    #[arg(long, conflicts_with = "turntable")]
    view: Option<usize>,
    #[arg(long, value_enum, default_value_t = SplitArg::Val)]
    split: SplitArg,
    /// Render a turntable of this many frames.
    #[arg(long)]
    turntable: Option<usize>,
    /// Turntable elevation in degrees.
    #[arg(long, default_value_t = 30.0)]
    elevation: f32,
    /// Turntable radius (default: the training cameras' mean distance).
    #[arg(long)]
    radius: Option<f32>,
    /// Turntable image size in pixels (default: the training images').
    #[arg(long)]
    size: Option<u32>,
    /// Also write the turntable as an animated GIF (`turntable.gif`).
    #[arg(long)]
    gif: bool,
    #[arg(long, value_enum, default_value_t = RenderMode::Rgb)]
    mode: RenderMode,
    /// Output folder (created if missing; images already there are kept
    /// unless --force).
    #[arg(long)]
    out: PathBuf,
    #[arg(long, value_enum)]
    engine: Option<EngineKind>,
    /// Replace images of the same names already in --out.
    #[arg(long)]
    force: bool,
}

#[derive(Clone, Copy, clap::ValueEnum)]
enum SplitArg {
    Train,
    Val,
    Test,
}

impl From<SplitArg> for Split {
    fn from(value: SplitArg) -> Self {
        match value {
            SplitArg::Train => Split::Train,
            SplitArg::Val => Split::Val,
            SplitArg::Test => Split::Test,
        }
    }
}

#[derive(Clone, Copy, clap::ValueEnum)]
enum LossArg {
    Huber,
    L2,
}

/// What a run folder records about how it was made (`run.json`), so eval,
/// render and resume rebuild the same scene and model.
#[derive(Debug, Clone, Serialize, Deserialize)]
struct RunConfig {
    /// The scene folder, or "demo".
    scene: String,
    model: ModelKind,
    downscale: u32,
    loss: LossKind,
    seed: u64,
    /// NeRF's sampler (absent in runs made before NeRF existed).
    #[serde(default = "default_sampling")]
    sampling: Sampling,
    /// The engine asked for with `--engine` (`None`: chosen by the
    /// machine's adapter), so eval, render and resume choose the same way
    /// (absent in runs made before it was recorded).
    #[serde(default)]
    engine: Option<EngineKind>,
    /// Samples per training batch when not the model's paper batch (runs
    /// of `bench quality --batch-samples`; absent otherwise).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    batch_samples: Option<usize>,
    /// How the cpu engine computed the networks' products (absent in runs
    /// made before mixed precision existed: those trained in f32).
    #[serde(default)]
    precision: Precision,
    /// Sizes of every training view trained on (1: the views as they are;
    /// see `Scene::with_training_scales`).
    #[serde(default = "single_scale", skip_serializing_if = "is_single_scale")]
    training_scales: u32,
}

fn single_scale() -> u32 {
    1
}

fn is_single_scale(scales: &u32) -> bool {
    *scales == 1
}

fn default_sampling() -> Sampling {
    Sampling::Occupancy
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    // Training keeps SIGPIPE ignored and prints without panicking, so that
    // a closed pipe (`zrak train … 2>&1 | head`) never ends it before its
    // checkpoint is written; the viewer has windows, not pipes, to care
    // about; every other command only prints and may end with its reader.
    if !matches!(
        cli.command,
        Some(Command::Train(_))
            | Some(Command::Bench(BenchCommand::Quality(_)))
            | Some(Command::View(_))
            | None
    ) {
        interrupt::end_quietly_on_closed_pipe();
    }
    let on_interrupt = match &cli.command {
        Some(Command::Train(_)) => Some("finishing the current step, then writing the checkpoint"),
        Some(Command::Eval { .. }) => Some("finishing the current view"),
        Some(Command::Render(_)) => Some("finishing the current frame"),
        Some(Command::Bench(BenchCommand::Throughput(_))) => {
            Some("finishing the current step, then reporting the steps measured")
        }
        Some(Command::View(_)) | None => {
            Some("closing the window, keeping every model trained since its last save")
        }
        Some(Command::Bench(BenchCommand::Quality(_))) => Some(
            "finishing the current step or scored view, then writing the checkpoint and \
             the report so far",
        ),
        _ => None,
    };
    if let Some(what_happens) = on_interrupt
        && let Err(error) = interrupt::install(what_happens)
    {
        interrupt::note(&format!("error: {error}"));
        return ExitCode::FAILURE;
    }
    let result = match cli.command {
        Some(Command::Info { scene, downscale }) => info(&scene, downscale),
        Some(Command::Demo {
            out,
            size,
            views,
            large,
            force,
        }) => write_demo(&out, size, views, large, force),
        Some(Command::Convert { colmap, out, force }) => convert(&colmap, &out, force),
        Some(Command::Train(args)) => train(args),
        Some(Command::Eval {
            run,
            split,
            engine,
            downscale,
        }) => eval(&run, split.into(), engine, downscale),
        Some(Command::Render(args)) => render(args),
        Some(Command::Bench(BenchCommand::Throughput(args))) => bench_throughput(args),
        Some(Command::Bench(BenchCommand::Gpu(args))) => bench_gpu(args),
        Some(Command::Bench(BenchCommand::Quality(args))) => bench_quality(args),
        Some(Command::Bench(BenchCommand::Dense { rows, repeats })) => {
            bench_dense(rows, repeats);
            Ok(())
        }
        Some(Command::View(args)) => view(args),
        None => view(ViewArgs {
            scene: None,
            engine: None,
            model: ModelKind::Ngp,
            sampling: Sampling::Occupancy,
            screenshot: None,
            screenshot_after: 5.0,
            quit_after: None,
            frame_log: None,
            auto_orbit: false,
            precision: None,
            keep_runs: zrak::train::kept::DEFAULT_KEPT_RUNS,
        }),
    };
    // What the command printed did not all arrive: the work is done (and
    // saved), but the output is incomplete, which the status must say.
    let result = match (result, interrupt::stdout_error()) {
        (Ok(()), Some(error)) => Err(anyhow::anyhow!(error)),
        (result, _) => result,
    };
    match result {
        // The command has said what it kept; the status tells scripts it
        // did not run to its end.
        Ok(()) if interrupt::requested() => ExitCode::from(interrupt::EXIT_STATUS),
        Ok(()) => ExitCode::SUCCESS,
        Err(error) => {
            interrupt::note(&format!("error: {error:#}"));
            ExitCode::FAILURE
        }
    }
}

fn parse_duration(text: &str) -> Result<f64, String> {
    let text = text.trim();
    // The unit is the letters at the end, so that a number in exponent
    // form (`1e3s`) keeps its `e`.
    let number = text.trim_end_matches(|c: char| c.is_ascii_alphabetic());
    let (number, unit) = match &text[number.len()..] {
        "" => (number, "s"),
        unit => (number, unit),
    };
    let value: f64 = number
        .trim()
        .parse()
        .map_err(|_| format!("`{text}` is not a duration like 90s, 10m or 1h"))?;
    let scale = match unit {
        "s" => 1.0,
        "m" | "min" => 60.0,
        "h" => 3600.0,
        _ => return Err(format!("`{text}`: unknown unit `{unit}` (use s, m or h)")),
    };
    if !(value > 0.0 && value.is_finite()) {
        return Err(format!("`{text}` must be a positive duration"));
    }
    Ok(value * scale)
}

fn load_scene(scene: &str, downscale: u32) -> anyhow::Result<Scene> {
    if scene == "demo" {
        anyhow::ensure!(downscale >= 1, "--downscale must be at least 1");
        let mut config = DemoConfig::default();
        anyhow::ensure!(
            downscale <= config.size,
            "--downscale {downscale} leaves no pixels of the demo scene's {size}×{size} \
             views: give at most {size}",
            size = config.size
        );
        config.size /= downscale;
        return Ok(demo::build(&config));
    }
    Ok(Scene::load(Path::new(scene), LoadOptions { downscale })?)
}

fn info(path: &Path, downscale: u32) -> anyhow::Result<()> {
    let started = Instant::now();
    let scene = Scene::load(path, LoadOptions { downscale })?;
    print_info(&scene);
    println!("loaded in {:.2} s", started.elapsed().as_secs_f64());
    Ok(())
}

/// `path` as it will be once written: its canonical form when it exists
/// (through any link), else its folder's canonical form and its name.
fn canonical_destination(path: &Path) -> PathBuf {
    if let Ok(canonical) = std::fs::canonicalize(path) {
        return canonical;
    }
    let parent = path
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    match (std::fs::canonicalize(parent), path.file_name()) {
        (Ok(folder), Some(name)) => folder.join(name),
        _ => path.to_path_buf(),
    }
}

/// Refuses an output file that is one of the COLMAP model's own files or
/// photographs: `convert` must never destroy what it reads.
fn check_not_colmap_input(colmap: &Path, out: &Path) -> anyhow::Result<()> {
    let destination = canonical_destination(out);
    if let Some(model) = zrak::scene::colmap::find_model_folder(colmap) {
        let model = std::fs::canonicalize(&model).unwrap_or(model);
        let is_model_file = destination.parent() == Some(model.as_path())
            && destination.file_name().is_some_and(|name| {
                ["cameras", "images", "points3D"].iter().any(|stem| {
                    ["bin", "txt"]
                        .iter()
                        .any(|ext| name.to_string_lossy() == format!("{stem}.{ext}"))
                })
            });
        if is_model_file {
            bail!(
                "{}: that is the COLMAP model's own {} (convert reads it); give --out \
                 another path, e.g. {}",
                out.display(),
                destination
                    .file_name()
                    .unwrap_or_default()
                    .to_string_lossy(),
                colmap.join("transforms.json").display()
            );
        }
    }
    let images = std::fs::canonicalize(colmap.join("images")).ok();
    if let Some(images) = images
        && destination.starts_with(&images)
    {
        bail!(
            "{}: that is inside the model's photographs folder {}; give --out another path",
            out.display(),
            images.display()
        );
    }
    Ok(())
}

fn convert(colmap: &Path, out: &Path, force: bool) -> anyhow::Result<()> {
    check_not_colmap_input(colmap, out)?;
    if out.is_dir() {
        bail!(
            "{}: is a folder; give the path of the file to write, e.g. {}",
            out.display(),
            out.join("transforms.json").display()
        );
    }
    if zrak::files::exists_at_all(out) && !force {
        bail!(
            "{} already exists; give --force to replace it, or another --out",
            out.display()
        );
    }
    let converted = zrak::scene::colmap::convert(colmap)?;
    let out_folder = out
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    // Image paths relative to the output's folder need both in the same
    // form; an absolute path is written otherwise.
    let absolute = |p: &Path| std::fs::canonicalize(p).unwrap_or_else(|_| p.to_path_buf());
    let mut absolute_images = converted.clone();
    for image in &mut absolute_images.images {
        image.image_path = absolute(&image.image_path);
    }
    let json = zrak::scene::colmap::transforms_json(&absolute_images, &absolute(out_folder));
    let text = serde_json::to_string_pretty(&json)?;
    zrak::files::write_bytes_atomically(out, text.as_bytes())
        .with_context(|| format!("{}: cannot write", out.display()))?;
    println!(
        "wrote {} ({} frames, centre [{:.4}, {:.4}, {:.4}] and scale {:.5} applied, aabb_scale {})",
        out.display(),
        converted.images.len(),
        converted.centre.x,
        converted.centre.y,
        converted.centre.z,
        converted.scale,
        converted.unit_cube.aabb_scale
    );
    Ok(())
}

/// The largest image side the commands that render accept: a frame is
/// rendered whole in memory (16384² pixels take ~4 GB as they render).
const MAX_IMAGE_SIDE: u32 = 16384;

/// Bytes a view of `width` × `height` takes while it is rendered and
/// written: the rendered pixels (colour, depth, opacity: 5 floats) and the
/// 8-bit image, with the PNG encoder's copy.
fn render_bytes_per_view(width: u32, height: u32) -> u64 {
    width as u64 * height as u64 * (5 * 4 + 2 * 4)
}

fn demo_config(size: u32, views: usize) -> anyhow::Result<DemoConfig> {
    anyhow::ensure!(
        (8..=MAX_IMAGE_SIDE).contains(&size),
        "--size must be 8 to {MAX_IMAGE_SIDE} pixels, got {size}"
    );
    anyhow::ensure!(
        (1..=100_000).contains(&views),
        "--views must be 1 to 100000, got {views}"
    );
    let held_out = (views / 10).max(1);
    // Every view's photograph is held in memory (4 bytes a pixel) and
    // rendered on every thread at once.
    let pixels = size as u64 * size as u64;
    let bytes = (views + 2 * held_out) as u64 * pixels * 4
        + rayon::current_num_threads() as u64 * render_bytes_per_view(size, size);
    zrak::files::check_memory(
        &format!(
            "the demo scene at --size {size} with {} views",
            views + 2 * held_out
        ),
        bytes,
    )
    .map_err(anyhow::Error::msg)?;
    Ok(DemoConfig {
        size,
        train_views: views,
        val_views: held_out,
        test_views: held_out,
    })
}

fn write_demo(out: &Path, size: u32, views: usize, large: bool, force: bool) -> anyhow::Result<()> {
    let config = demo_config(size, views)?;
    if !force {
        match std::fs::read_dir(out) {
            Ok(mut entries) => {
                if entries.next().is_some() {
                    bail!(
                        "{} is not empty; give another --out, or --force to write the demo \
                         scene's files over those of the same names there",
                        out.display()
                    );
                }
            }
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
            Err(_) if zrak::files::exists_at_all(out) => bail!(
                "{}: cannot write the demo scene there: {}",
                out.display(),
                zrak::files::describe_not_a_folder(out)
            ),
            Err(_) => {}
        }
    }
    let started = Instant::now();
    if large {
        demo::write_large(&config, out).context("writing the large demo scene")?;
    } else {
        demo::write(&config, out).context("writing the demo scene")?;
    }
    println!(
        "wrote the demo scene to {} ({} / {} / {} views at {size}×{size}) in {:.2} s",
        out.display(),
        config.train_views,
        config.val_views,
        config.test_views,
        started.elapsed().as_secs_f64()
    );
    Ok(())
}

/// Opens the viewer window on the demo scene or a folder.
fn view(args: ViewArgs) -> anyhow::Result<()> {
    for (flag, value) in [
        ("--screenshot-after", Some(args.screenshot_after)),
        ("--quit-after", args.quit_after),
    ] {
        if let Some(value) = value {
            anyhow::ensure!(
                value.is_finite() && value >= 0.0,
                "{flag} must be a number of seconds ≥ 0, got {value}"
            );
        }
    }
    zrak::app::viewer::run(ViewerOptions {
        source: match args.scene {
            Some(folder) => SceneSource::Folder(folder),
            None => SceneSource::Demo,
        },
        engine: args.engine,
        model: args.model,
        sampling: args.sampling,
        screenshot: args.screenshot,
        screenshot_after: args.screenshot_after,
        quit_after: args.quit_after,
        frame_log: args.frame_log,
        auto_orbit: args.auto_orbit,
        precision: args.precision.unwrap_or_else(Precision::best_available),
        kept_runs: args.keep_runs,
    })
}

fn print_info(scene: &Scene) {
    let source = if scene.root.as_os_str().is_empty() {
        "built in".to_string()
    } else {
        scene.root.display().to_string()
    };
    println!("scene       {} ({:?}, {source})", scene.name, scene.format);
    let counts: Vec<String> = Split::ALL
        .iter()
        .map(|&s| format!("{} {}", s.name(), scene.split(s).len()))
        .collect();
    println!("frames      {}", counts.join(", "));
    let Some(first) = scene.frames().next() else {
        return;
    };
    let k = first.camera.intrinsics;
    println!(
        "images      {}×{}, {}",
        k.width,
        k.height,
        if scene.has_alpha {
            "RGBA"
        } else {
            "RGB (no alpha)"
        }
    );
    println!(
        "intrinsics  fx {:.4}  fy {:.4}  cx {:.3}  cy {:.3}  (field of view {:.2}° × {:.2}°)",
        k.fx,
        k.fy,
        k.cx,
        k.cy,
        k.fov_x().to_degrees(),
        k.fov_y().to_degrees()
    );
    if k.lens != zrak::scene::Lens::Pinhole {
        println!("lens        {}", k.lens.describe());
    }
    let b = scene.bounds;
    println!(
        "bounds      [{:.3}, {:.3}, {:.3}] to [{:.3}, {:.3}, {:.3}]",
        b.min.x, b.min.y, b.min.z, b.max.x, b.max.y, b.max.z
    );
    let m = scene.unit_cube;
    println!(
        "unit cube   scale {}  offset [{}, {}, {}]  aabb_scale {}",
        m.scale, m.offset.x, m.offset.y, m.offset.z, m.aabb_scale
    );
    if let Some((near, far)) = scene.seen_depth_range() {
        println!("near/far    {near:.3} to {far:.3} (where camera rays cross the bounds)");
    }
}

fn read_run_config(folder: &RunFolder) -> anyhow::Result<RunConfig> {
    let path = folder.config_path();
    let text = std::fs::read_to_string(&path)
        .with_context(|| format!("{}: cannot read the run's configuration", path.display()))?;
    serde_json::from_str(&text)
        .with_context(|| format!("{}: malformed run configuration", path.display()))
}

/// Rebuilds a run's scene and model and restores its checkpoint.
fn restore_run(
    folder: &RunFolder,
    engine: Option<EngineKind>,
    precision: Option<Precision>,
) -> anyhow::Result<(RunConfig, Trainer)> {
    let mut config = read_run_config(folder)?;
    if let Some(precision) = precision {
        config.precision = precision;
    }
    let scene = Arc::new(
        load_scene(&config.scene, config.downscale)?.with_training_scales(config.training_scales),
    );
    let choice = choose_engine(engine.or(config.engine))?;
    note(&choice.reason);
    let mut trainer = build_trainer(&config, scene, choice)?;
    restore_checkpoint(folder, &mut trainer)?;
    Ok((config, trainer))
}

/// A fresh trainer of the run's model on `scene` (loaded as the run says).
fn build_trainer(
    config: &RunConfig,
    scene: Arc<Scene>,
    choice: zrak::engine::EngineChoice,
) -> anyhow::Result<Trainer> {
    let model = build_model(
        config.model,
        choice,
        &scene,
        &ModelSettings {
            seed: config.seed,
            loss: config.loss,
            batch_samples: config.batch_samples,
            sampling: config.sampling,
            precision: config.precision,
        },
    )
    .map_err(anyhow::Error::msg)?;
    Ok(Trainer::new(model, scene, config.seed))
}

/// Restores the run folder's checkpoint into `trainer`.
fn restore_checkpoint(folder: &RunFolder, trainer: &mut Trainer) -> anyhow::Result<()> {
    let checkpoint = load_checkpoint(folder).map_err(anyhow::Error::msg)?;
    trainer
        .restore(&checkpoint)
        .map_err(|e| anyhow::anyhow!("{}: {e}", folder.checkpoint_path().display()))
}

/// Writes a new run's `run.json` and clears any earlier log: a fresh run
/// starts a fresh history. (A folder holding a checkpoint never gets here:
/// [`RunFolder::create_new`] refuses it or moves it aside.)
fn start_run_folder(folder: &RunFolder, config: &RunConfig) -> anyhow::Result<()> {
    zrak::files::write_bytes_atomically(
        &folder.config_path(),
        serde_json::to_string_pretty(config)?.as_bytes(),
    )
    .with_context(|| format!("{}: cannot write", folder.config_path().display()))?;
    let _ = std::fs::remove_file(folder.metrics_path());
    Ok(())
}

/// Refuses a resume whose limit the run has already reached: it would
/// train nothing and say it had finished.
fn check_resume_limits(args: &TrainArgs, trainer: &Trainer, dir: &Path) -> anyhow::Result<()> {
    if let Some(steps) = args.steps
        && steps <= trainer.step
    {
        bail!(
            "the run in {} is already at step {}; --steps counts from the run's start, so \
             --steps {steps} leaves nothing to train: give more than {}",
            dir.display(),
            trainer.step,
            trainer.step
        );
    }
    if let Some(seconds) = args.time
        && seconds <= trainer.train_seconds
    {
        bail!(
            "the run in {} has already trained {:.1} s; --time counts from the run's start, \
             so --time {seconds}s leaves nothing to train: give more than {:.0}s",
            dir.display(),
            trainer.train_seconds,
            trainer.train_seconds.ceil()
        );
    }
    Ok(())
}

/// Refuses `--training-scales` asking for sizes the views are too small
/// to have (each size halves the last; below one pixel there is none).
fn check_training_scales(scene: &Scene, scales: u32) -> anyhow::Result<()> {
    let smallest_side = scene
        .photographed_training_views()
        .iter()
        .map(|f| f.camera.intrinsics.width.min(f.camera.intrinsics.height))
        .min()
        .unwrap_or(0);
    if scales > 1 && smallest_side > 0 {
        // Sizes full, ½, … while a side keeps at least one pixel.
        let possible = u32::BITS - smallest_side.leading_zeros();
        if scales > possible {
            bail!(
                "--training-scales {scales} needs views of at least {} pixels a side (the \
                 smallest size is 1/{}); the smallest here is {smallest_side}: give at most {possible}",
                1u64 << (scales - 1),
                1u64 << (scales - 1)
            );
        }
    }
    Ok(())
}

/// How `run.json` names a scene: `demo`, or the folder's absolute path, so
/// a run can be resumed, evaluated and rendered from any working folder.
fn scene_key(scene: &str) -> String {
    if scene == "demo" {
        "demo".into()
    } else {
        std::fs::canonicalize(scene)
            .unwrap_or_else(|_| PathBuf::from(scene))
            .display()
            .to_string()
    }
}

/// A SCENE given with `--resume` must be the run's own: a checkpoint only
/// continues on the scene it was trained on.
fn check_same_scene(given: &str, recorded: &str, run: &Path) -> anyhow::Result<()> {
    let key = scene_key(given);
    if key != recorded {
        bail!(
            "the run in {} was trained on `{recorded}`, not on `{key}`: leave SCENE out to \
             continue it on its own scene, or give --out instead of --resume to start a new run",
            run.display()
        );
    }
    Ok(())
}

fn train(args: TrainArgs) -> anyhow::Result<()> {
    if args.steps.is_none() && args.time.is_none() && args.resume.is_none() {
        bail!("give --steps N or --time DURATION (e.g. --time 10m)");
    }
    let (folder, config, mut trainer) = if let Some(dir) = &args.resume {
        // The lock first: a run another zrak is training must not be read
        // half-way or continued twice.
        let folder = RunFolder::resume(dir).map_err(anyhow::Error::msg)?;
        if let Some(scene) = &args.scene {
            check_same_scene(scene, &read_run_config(&folder)?.scene, dir)?;
        }
        let (config, trainer) = restore_run(&folder, args.engine, args.precision)?;
        check_resume_limits(&args, &trainer, dir)?;
        note(&format!(
            "resuming at step {} ({:.0} s trained)",
            trainer.step, trainer.train_seconds
        ));
        // Log lines past the checkpoint (written after it, before the run
        // stopped) describe steps that will be trained again.
        let dropped = MetricsLog::truncate_after(&folder.metrics_path(), trainer.step)
            .with_context(|| format!("{}: cannot trim the log", folder.metrics_path().display()))?;
        if dropped > 0 {
            note(&format!(
                "{}: dropped {dropped} lines logged after the checkpoint's step {}",
                folder.metrics_path().display(),
                trainer.step
            ));
        }
        (folder, config, trainer)
    } else {
        let (Some(dir), Some(scene_arg)) = (&args.out, args.scene.as_deref()) else {
            bail!("give SCENE and --out RUN to start a run, or --resume RUN to continue one");
        };
        // A folder holding a run is refused before anything loads; the
        // folder is made (or, with --force, the old run moved aside) only
        // once the new run is known to start, so a refused command leaves
        // nothing behind.
        if !args.force {
            RunFolder::refuse_if_holds_run(dir).map_err(anyhow::Error::msg)?;
        }
        let config = RunConfig {
            scene: scene_key(scene_arg),
            model: args.model,
            downscale: args.downscale,
            loss: match args.loss {
                Some(LossArg::Huber) => LossKind::Huber,
                Some(LossArg::L2) => LossKind::L2,
                None => args.model.default_loss(),
            },
            seed: args.seed,
            sampling: args.sampling,
            engine: args.engine,
            batch_samples: None,
            precision: args.precision.unwrap_or_else(Precision::best_available),
            training_scales: args.training_scales,
        };
        let scene = load_scene(scene_arg, args.downscale)?;
        check_training_scales(&scene, args.training_scales)?;
        let scene = Arc::new(scene.with_training_scales(args.training_scales));
        if let Some(problem) = scene.training_problem() {
            bail!("{scene_arg}: nothing to train: {problem}");
        }
        let choice = choose_engine(args.engine)?;
        note(&choice.reason);
        let trainer = build_trainer(&config, scene, choice)?;
        let (folder, aside) = RunFolder::create_new(dir, args.force).map_err(anyhow::Error::msg)?;
        if let Some(aside) = aside {
            note(&format!(
                "moved the run that was in {} aside to {}",
                dir.display(),
                aside.display()
            ));
        }
        start_run_folder(&folder, &config)?;
        (folder, config, trainer)
    };
    if let Some(kernels) = trainer.model.cpu_kernels() {
        note(&KernelsLine(kernels).to_string());
    }
    note(&format!(
        "training {} on {} ({} views, {}×{})",
        trainer.model.describe(),
        trainer.scene.name,
        trainer.scene.train.len(),
        trainer.scene.resolution().map_or(0, |r| r.0),
        trainer.scene.resolution().map_or(0, |r| r.1),
    ));
    let limits = Limits {
        steps: args.steps,
        seconds: args.time,
    };
    let bar = match (limits.steps, limits.seconds) {
        (Some(steps), _) => ProgressBar::new(steps as u64),
        (None, Some(seconds)) => ProgressBar::new(seconds.ceil() as u64),
        (None, None) => ProgressBar::new_spinner(),
    };
    bar.set_style(
        ProgressStyle::with_template("{bar:30} {pos}/{len} {msg}").expect("valid template"),
    );
    let by_steps = limits.steps.is_some();
    let started = Instant::now();
    let schedule = Schedule {
        eval_every_seconds: args.eval_every,
        checkpoint_every_seconds: args.checkpoint_every,
        ..Schedule::default()
    };
    let psnr = run(
        &mut trainer,
        limits,
        schedule,
        &folder,
        &serde_json::to_value(&config)?,
        interrupt::flag(),
        |p| {
            bar.set_position(if by_steps {
                p.trainer.step as u64
            } else {
                p.trainer.train_seconds as u64
            });
            bar.set_message(format!(
                "step {} | loss {:.5} | psnr {} | {:.0} samples/ray | {:.2} M samples/s | {:.0} s",
                p.trainer.step,
                p.stats.loss,
                p.psnr.map_or("-".into(), |v| format!("{v:.2}")),
                p.stats.samples_per_ray(),
                p.samples_per_second / 1e6,
                started.elapsed().as_secs_f64(),
            ));
        },
    )
    .map_err(anyhow::Error::msg)?;
    if interrupt::requested() {
        bar.abandon();
        let limit = match (args.steps, args.time) {
            (Some(steps), _) => format!(" --steps {steps}"),
            (None, Some(seconds)) => format!(" --time {seconds}s"),
            (None, None) => String::new(),
        };
        note(&format!(
            "interrupted at step {} ({:.1} s trained); checkpoint written to {}\n\
             continue with: zrak train --resume {}{limit}",
            trainer.step,
            trainer.train_seconds,
            folder.checkpoint_path().display(),
            folder.dir.display(),
        ));
        return Ok(());
    }
    bar.finish();
    say(&format!(
        "trained {} steps in {:.1} s; held-out PSNR {}; run folder {}",
        trainer.step,
        trainer.train_seconds,
        psnr.map_or("-".into(), |v| format!("{v:.2} dB")),
        folder.dir.display()
    ));
    Ok(())
}

fn eval(
    run_dir: &Path,
    split: Split,
    engine: Option<EngineKind>,
    downscale: u32,
) -> anyhow::Result<()> {
    let folder = RunFolder::open(run_dir).map_err(anyhow::Error::msg)?;
    let (_, trainer) = restore_run(&folder, engine, None)?;
    let frames = trainer.scene.split(split);
    if frames.is_empty() {
        bail!("the scene has no {} views", split.name());
    }
    let smaller: Vec<Frame>;
    let frames = if downscale > 1 {
        smaller = frames.iter().map(|f| f.downscaled(downscale)).collect();
        if smaller
            .iter()
            .any(|f| f.camera.intrinsics.width == 0 || f.camera.intrinsics.height == 0)
        {
            bail!(
                "the {} views are smaller than {downscale} pixels",
                split.name()
            );
        }
        println!("at 1/{downscale} of the views' resolution");
        &smaller[..]
    } else {
        frames
    };
    println!("{:>5}  {:>8}  {:>7}  image", "view", "PSNR", "SSIM");
    let scores: SplitScores = evaluate_split_until(
        trainer.model.as_ref(),
        split.name(),
        frames,
        interrupt::flag(),
        |v| {
            println!(
                "{:>5}  {:>8.3}  {:>7.4}  {}",
                v.index, v.psnr, v.ssim, v.image
            );
        },
    );
    if interrupt::requested() {
        // A mean over some of the views is not the split's score: it is
        // shown, but not written where a finished evaluation goes.
        println!(
            "{:>5}  {:>8.3}  {:>7.4}  (interrupted: {} of {} views; nothing written)",
            "mean",
            scores.mean_psnr,
            scores.mean_ssim,
            scores.views.len(),
            frames.len()
        );
        return Ok(());
    }
    if let Some(view) = scores.views.iter().find(|v| v.psnr.is_nan()) {
        bail!(
            "view {} of the {} split ({}) renders colours that are not numbers: the model in \
             {} is broken (its training diverged); nothing written",
            view.index,
            split.name(),
            view.image,
            folder.dir.display()
        );
    }
    println!(
        "{:>5}  {:>8.3}  {:>7.4}",
        "mean", scores.mean_psnr, scores.mean_ssim
    );
    let window = zrak::metrics::SSIM_WINDOW as u32;
    let small = frames
        .iter()
        .filter(|f| f.camera.intrinsics.width < window || f.camera.intrinsics.height < window)
        .count();
    if small > 0 {
        note(&format!(
            "SSIM is NaN for {small} of the {} views: they are smaller than its {window}×{window} \
             window (give a smaller --downscale, or read PSNR alone)",
            frames.len()
        ));
    }
    let suffix = if downscale > 1 {
        format!("_d{downscale}")
    } else {
        String::new()
    };
    let path = folder
        .dir
        .join(format!("eval_{}{suffix}.json", split.name()));
    zrak::files::write_bytes_atomically(&path, serde_json::to_string_pretty(&scores)?.as_bytes())
        .with_context(|| format!("{}: cannot write", path.display()))?;
    println!("step {}; written to {}", trainer.step, path.display());
    Ok(())
}

/// The largest turntable: 10⁵ frames (over an hour of video at 25 frames a
/// second); the frames' cameras are placed up front.
const MAX_TURNTABLE_FRAMES: usize = 100_000;

/// Refuses render settings that could never finish or would abort on an
/// allocation, before the run loads; then images of the same names in
/// --out, unless --force.
fn check_render_args(args: &RenderArgs) -> anyhow::Result<()> {
    if let Some(frames) = args.turntable {
        anyhow::ensure!(
            (1..=MAX_TURNTABLE_FRAMES).contains(&frames),
            "--turntable must be 1 to {MAX_TURNTABLE_FRAMES} frames, got {frames}"
        );
    }
    if let Some(size) = args.size {
        anyhow::ensure!(
            (1..=MAX_IMAGE_SIDE).contains(&size),
            "--size must be 1 to {MAX_IMAGE_SIDE} pixels, got {size}"
        );
        // One frame renders at a time; the GIF encoder keeps a copy of it.
        let bytes = render_bytes_per_view(size, size)
            + if args.gif {
                size as u64 * size as u64 * 8
            } else {
                0
            };
        zrak::files::check_memory(&format!("a {size}×{size} frame"), bytes)
            .map_err(anyhow::Error::msg)?;
    }
    anyhow::ensure!(
        args.elevation.is_finite(),
        "--elevation must be a number of degrees, got {}",
        args.elevation
    );
    if let Some(radius) = args.radius {
        anyhow::ensure!(
            radius.is_finite() && radius > 0.0,
            "--radius must be a positive distance, got {radius}"
        );
    }
    if args.force {
        return Ok(());
    }
    let outputs: Vec<PathBuf> = match (args.view, args.turntable) {
        (Some(view), None) => vec![
            args.out
                .join(format!("{}_{view:03}.png", Split::from(args.split).name())),
        ],
        (None, Some(frames)) => {
            let settings = ExportSettings {
                turntable: Turntable {
                    frames,
                    ..Turntable::default()
                },
                mode: args.mode,
                out_dir: args.out.clone(),
                write_gif: args.gif,
            };
            let mut paths: Vec<PathBuf> = (0..frames).map(|i| settings.frame_path(i)).collect();
            if args.gif {
                paths.push(settings.gif_path());
            }
            paths
        }
        _ => Vec::new(),
    };
    let existing: Vec<&PathBuf> = outputs
        .iter()
        .filter(|p| zrak::files::exists_at_all(p))
        .collect();
    if let Some(first) = existing.first() {
        bail!(
            "{} already exists{}; give --force to replace this render's files, or another --out",
            first.display(),
            match existing.len() {
                1 => String::new(),
                n => format!(" (and {} more of the files this render writes)", n - 1),
            }
        );
    }
    Ok(())
}

fn render(args: RenderArgs) -> anyhow::Result<()> {
    check_render_args(&args)?;
    let folder = RunFolder::open(&args.run).map_err(anyhow::Error::msg)?;
    let (_, trainer) = restore_run(&folder, args.engine, None)?;
    let scene = &trainer.scene;
    if args.size.is_none()
        && let Some((width, height)) = scene.resolution()
    {
        zrak::files::check_memory(
            &format!("a {width}×{height} frame"),
            render_bytes_per_view(width, height),
        )
        .map_err(anyhow::Error::msg)?;
    }
    let cameras: Vec<(String, Camera)> = match (args.view, args.turntable) {
        (Some(view), None) => {
            anyhow::ensure!(!args.gif, "--gif goes with --turntable FRAMES, not --view");
            let split: Split = args.split.into();
            let frames = scene.split(split);
            let frame = frames.get(view).with_context(|| {
                format!(
                    "the {} split has {} views; there is no view {view}",
                    split.name(),
                    frames.len()
                )
            })?;
            vec![(format!("{}_{view:03}", split.name()), frame.camera)]
        }
        (None, Some(frames)) => {
            anyhow::ensure!(frames >= 1, "--turntable needs at least one frame");
            let settings = ExportSettings {
                turntable: Turntable {
                    frames,
                    elevation_degrees: args.elevation,
                    radius: args.radius,
                    size: args.size.map(|s| (s, s)),
                },
                mode: args.mode,
                out_dir: args.out.clone(),
                write_gif: args.gif,
            };
            let bar = ProgressBar::new(frames as u64);
            let mut frames_done = 0;
            let exported = export_turntable(
                trainer.model.as_ref(),
                scene,
                settings,
                interrupt::flag(),
                &mut |done, _| {
                    frames_done = done;
                    bar.set_position(done as u64);
                },
            );
            if interrupt::requested() {
                bar.abandon();
                note(&format!(
                    "interrupted after {frames_done} of {frames} frames; those are in {} \
                     (no GIF)",
                    args.out.display()
                ));
                return Ok(());
            }
            let written = exported.map_err(anyhow::Error::msg)?;
            bar.finish();
            println!("wrote {} files to {}", written.len(), args.out.display());
            return Ok(());
        }
        _ => bail!("give --view N or --turntable FRAMES"),
    };
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("{}: cannot create the output folder", args.out.display()))?;
    let depth_range = scene.depth_range();
    let bar = ProgressBar::new(cameras.len() as u64);
    for (name, camera) in &cameras {
        let pixels = render_pixels(trainer.model.as_ref(), camera, [1.0; 3]);
        let k = camera.intrinsics;
        let image = to_image(&pixels, k.width, k.height, args.mode, depth_range);
        let path = args.out.join(format!("{name}.png"));
        image.save_png(&path)?;
        bar.inc(1);
    }
    bar.finish();
    println!("wrote {} images to {}", cameras.len(), args.out.display());
    Ok(())
}

/// The kernels and precision a cpu model computes with, as one line.
struct KernelsLine(zrak::engine::cpu::dense::Backend);

impl std::fmt::Display for KernelsLine {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "kernels              {:?}, {} threads; precision: {}",
            self.0,
            rayon::current_num_threads(),
            self.0.precision().describe()
        )
    }
}

/// NeRF's networks in f32 and, where the processor has bf16 kernels, in
/// mixed precision, one after the other in one run, against the machine's
/// f32 matrix-multiply rate and its multiply-add ceilings.
fn bench_dense(rows: usize, repeats: usize) {
    use zrak::engine::cpu::dense::{arithmetic_peak_gflops, measure_peak_gflops};
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
}

/// Samples per batch when a bench runs the gpu engine on a software
/// adapter: NeRF's 16 rays with the paper's sampler, ~14 G FLOP a step
/// (its paper-size batch, ~1 T FLOP, would take many minutes a step at
/// lavapipe's few GFLOP/s), Instant-NGP's 1/64 of its 2^18; seconds on
/// lavapipe. There the bench is a correctness run.
const SOFTWARE_GPU_SAMPLES: usize = 1 << 12;

/// Unmeasured steps before a throughput measurement: past the occupancy
/// grid's warm-up (its first 256 steps update every cell, twice the work of
/// a later update) and a few more, so the figures are those of most of a
/// run; 1 on a software adapter, where a gpu step takes minutes.
fn default_warmup(model: ModelKind, sampling: Sampling, software_gpu: bool) -> usize {
    match model {
        _ if software_gpu => 1,
        ModelKind::Ngp => OccupancyConfig::PAPER.warmup_steps as usize + 32,
        // Past the grid's warm-up too, with the occupancy sampler; the
        // paper's sampler has no grid, and a few steps settle its caches.
        ModelKind::Nerf | ModelKind::MipNerf => match sampling {
            Sampling::Occupancy => zrak::field::nerf::OCCUPANCY.warmup_steps as usize + 16,
            Sampling::Paper => 2,
        },
    }
}

/// The benches' scene when none is given: lego_400 when present beside the
/// checkout, else the demo scene.
fn default_bench_scene() -> String {
    zrak::bench::default_scene_path()
        .map(|p| p.display().to_string())
        .unwrap_or_else(|| "demo".into())
}

fn bench_gpu(args: GpuBenchArgs) -> anyhow::Result<()> {
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
        let scene = Arc::new(load_scene(&scene_name, 1)?);
        for &model in &args.models {
            if interrupt::requested() {
                break;
            }
            say(&format!("\n{} on {}:", model.name(), scene.name));
            // A context of its own per model, so its counters are its own.
            let choice = gpu_choice.share()?;
            let counters = choice.gpu.as_ref().map(|gpu| gpu.counters.clone());
            let engine_line = choice.reason.clone();
            let settings = ModelSettings {
                seed: 0,
                loss: model.default_loss(),
                batch_samples: software.then_some(SOFTWARE_GPU_SAMPLES),
                sampling: Sampling::Occupancy,
                precision: Precision::F32,
            };
            let built =
                build_model(model, choice, &scene, &settings).map_err(anyhow::Error::msg)?;
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
    model: &dyn zrak::train::model::RadianceModel,
    context: &zrak::engine::gpu::GpuContext,
    scene: &Scene,
) -> Option<f64> {
    let renderer = model.texture_render()?;
    let frame = scene.val.first().or(scene.train.first())?;
    let (width, height) = (1280, 720);
    let camera = Camera::new(
        zrak::scene::camera::Intrinsics::from_fov_x(width, height, frame.camera.intrinsics.fov_x()),
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

fn bench_throughput(args: ThroughputArgs) -> anyhow::Result<()> {
    let ThroughputArgs {
        scene,
        engine,
        downscale,
        model,
        sampling,
        warmup,
        steps,
        precision,
    } = args;
    let precision = precision.unwrap_or_else(Precision::best_available);
    let scene_name = scene.unwrap_or_else(default_bench_scene);
    let scene = Arc::new(load_scene(&scene_name, downscale)?);
    let choice = choose_engine(engine)?;
    let engine_line = choice.reason.clone();
    let counters = choice.gpu.as_ref().map(|gpu| gpu.counters.clone());
    let software_gpu =
        choice.kind == EngineKind::Gpu && choice.gpu.as_ref().is_some_and(|gpu| gpu.is_software());
    let warmup = warmup.unwrap_or_else(|| default_warmup(model, sampling, software_gpu));
    let batch_samples = software_gpu.then_some(SOFTWARE_GPU_SAMPLES);
    let settings = ModelSettings {
        seed: 0,
        loss: model.default_loss(),
        batch_samples,
        sampling,
        precision,
    };
    let model = build_model(model, choice, &scene, &settings).map_err(anyhow::Error::msg)?;
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
