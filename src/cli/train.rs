//! `zrak train`: a new run, or a resumed one, trained to its limits with
//! a progress bar, checkpoints and held-out evaluations.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use anyhow::bail;
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use zrak::engine::{EngineKind, choose_engine};
use zrak::field::ModelKind;
use zrak::field::common::{LossKind, Sampling};
use zrak::field::mlp::Precision;
use zrak::interrupt::{
    note, say, {self},
};
use zrak::train::log::MetricsLog;
use zrak::train::run::{Limits, RunFolder, Schedule, run};
use zrak::train::trainer::Trainer;

use super::run_config::{
    RunConfig, build_trainer, check_same_scene, load_run_scene, read_run_config, restore_run,
    scene_key, settle_camera_refinement, start_run_folder,
};
use super::{KernelsLine, PhotographSwitches, SpaceChoice, parse_duration, photograph_lines};
use zrak::scene::photographs::PhotographAnalysis;

#[derive(Args, Debug)]
pub struct TrainArgs {
    /// A scene folder, or `demo` for the built-in demo scene. With
    /// `--resume` it may be left out (the run knows its scene).
    #[arg(required_unless_present = "resume")]
    scene: Option<String>,
    // What the run is made of comes from its `run.json` when resuming, so
    // these conflict with `--resume` instead of being silently ignored
    // (clap does not count a default value as given).
    #[arg(long, value_enum, default_value_t = ModelKind::Ngp, conflicts_with = "resume")]
    model: ModelKind,
    /// The sampler: the occupancy grid, the paper's stratified +
    /// importance sampling (NeRF, Mip-NeRF) or proposal fields in the
    /// contracted space (Instant-NGP). Default: proposal fields on an
    /// unbounded scene where the model has them, else the occupancy grid.
    #[arg(long, value_enum, conflicts_with = "resume")]
    sampling: Option<Sampling>,
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
    loss: Option<LossKind>,
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
    /// What the scene is treated as: a bounded object, unbounded, or a
    /// forward-facing capture; auto leaves it to the scene analysis
    /// (`zrak info` prints its choice and why). When resuming, the run's
    /// own.
    #[arg(long, value_enum, default_value_t = SpaceChoice::Auto, conflicts_with = "resume")]
    space: SpaceChoice,
    /// Per-image appearance and camera refinement: auto leaves each to the
    /// analysis of the photographs (`zrak info` prints its choices and
    /// why). When resuming, the run's own.
    #[command(flatten)]
    photographs: PhotographSwitches,
}

impl TrainArgs {
    fn limits(&self) -> Limits {
        Limits {
            steps: self.steps,
            seconds: self.time,
        }
    }
}

pub fn train(args: TrainArgs) -> anyhow::Result<()> {
    if args.steps.is_none() && args.time.is_none() && args.resume.is_none() {
        bail!("give --steps N or --time DURATION (e.g. --time 10m)");
    }
    let (folder, config, trainer) = match &args.resume {
        Some(dir) => resume_run(&args, dir)?,
        None => start_run(&args)?,
    };
    train_to_limits(&args, &folder, &config, trainer)
}

/// Opens a run folder to continue: its lock, its own `run.json` and
/// checkpoint, and its log cut back to the checkpoint's step.
fn resume_run(args: &TrainArgs, dir: &Path) -> anyhow::Result<(RunFolder, RunConfig, Trainer)> {
    // The lock first: a run another zrak is training must not be read
    // half-way or continued twice.
    if args.photographs != PhotographSwitches::default() {
        bail!(
            "--appearance and --refine-cameras are the run's own when resuming (its run.json \
             records them)"
        );
    }
    let folder = RunFolder::resume(dir).map_err(anyhow::Error::msg)?;
    if let Some(scene) = &args.scene {
        check_same_scene(scene, &read_run_config(&folder)?.scene, dir)?;
    }
    let (config, trainer) = restore_run(&folder, args.engine, args.precision)?;
    check_resume_limits(args.limits(), &trainer, dir)?;
    note(&format!(
        "resuming at step {} ({:.0} s trained)",
        trainer.step, trainer.train_seconds
    ));
    // Log lines past the checkpoint (written after it, before the run
    // stopped) describe steps that will be trained again.
    let dropped = MetricsLog::truncate_after(&folder.metrics_path(), trainer.step)
        .map_err(anyhow::Error::msg)?;
    if dropped > 0 {
        note(&format!(
            "{}: dropped {dropped} lines logged after the checkpoint's step {}",
            folder.metrics_path().display(),
            trainer.step
        ));
    }
    Ok((folder, config, trainer))
}

/// The `run.json` of a new run made as `args` say.
fn new_run_config(args: &TrainArgs, scene: &str) -> RunConfig {
    RunConfig {
        scene: scene_key(scene),
        model: args.model,
        downscale: args.downscale,
        loss: args.loss.unwrap_or_else(|| args.model.default_loss()),
        seed: args.seed,
        // Chosen once the scene is loaded (see `start_run`).
        sampling: args.sampling.unwrap_or(Sampling::Occupancy),
        engine: args.engine,
        batch_samples: None,
        precision: args.precision.unwrap_or_else(Precision::best_available),
        training_scales: args.training_scales,
        space: None,
        space_overridden: false,
        photographs: PhotographAnalysis::default(),
    }
}

/// The space a scene is treated as, in one line: what and why.
fn describe_space(scene: &zrak::scene::Scene) -> String {
    let analysis = &scene.space;
    format!(
        "scene space: {} ({})",
        analysis.space,
        analysis
            .reasons
            .first()
            .map_or("no reason given", String::as_str)
    )
}

/// What training says of the scene's masks: how many frames have one and
/// what they leave out of training and of the held-out PSNR, and a warning
/// for each training view whose mask hides every pixel (it is skipped).
fn mask_notes(scene: &zrak::scene::Scene) -> Vec<String> {
    let Some(masks) = scene.describe_masks() else {
        return Vec::new();
    };
    let mut lines = vec![format!(
        "masks: {masks}; the held-out PSNR is over the pixels that count"
    )];
    lines.extend(scene.fully_masked_training_views().iter().map(|frame| {
        format!(
            "warning: the mask of {} hides every pixel; that view is skipped",
            frame.image_path.display()
        )
    }));
    lines
}

/// Starts a new run in `--out`: the model is built first, and the folder
/// made (or, with --force, the old run moved aside) only once it is.
fn start_run(args: &TrainArgs) -> anyhow::Result<(RunFolder, RunConfig, Trainer)> {
    let (Some(dir), Some(scene_arg)) = (&args.out, args.scene.as_deref()) else {
        bail!("give SCENE and --out RUN to start a run, or --resume RUN to continue one");
    };
    // A folder holding a run or anything else is refused before anything
    // loads, so a refused command leaves nothing behind.
    check_out_is_not_the_scene(dir, scene_arg)?;
    RunFolder::check_out(dir, args.force).map_err(anyhow::Error::msg)?;
    let mut config = new_run_config(args, scene_arg);
    let scene = args.space.apply(load_run_scene(
        scene_arg,
        args.downscale,
        args.training_scales,
    )?);
    config.record_space(&scene);
    note(&describe_space(&scene));
    config.sampling = args
        .model
        .choose_sampling(args.sampling, scene.space.space)
        .map_err(anyhow::Error::msg)?;
    if args.sampling.is_none() {
        let (_, why) = args.model.sampling_for(scene.space.space);
        note(&format!("sampler: {} ({why})", config.sampling.name()));
    }
    if let Some(problem) = scene.training_problem() {
        bail!("{scene_arg}: nothing to train: {problem}");
    }
    config.photographs = args.photographs.analyse(&scene);
    for line in photograph_lines(&config.photographs) {
        note(&line);
    }
    for line in mask_notes(&scene) {
        note(&line);
    }
    let choice = choose_engine(args.engine)?;
    note(&choice.reason);
    let trainer = build_trainer(&config, Arc::new(scene), choice)?;
    if let Some(line) = settle_camera_refinement(&mut config, &trainer) {
        note(&line);
    }
    let (folder, aside) = RunFolder::create_new(dir, args.force).map_err(anyhow::Error::msg)?;
    if let Some(aside) = aside {
        note(&format!(
            "moved the {} in {} aside to {}",
            if aside.was_run {
                "run that was"
            } else {
                "files that were"
            },
            dir.display(),
            aside.to.display()
        ));
    }
    start_run_folder(&folder, &config)?;
    Ok((folder, config, trainer))
}

/// Refuses an `--out` that is the scene folder or a folder holding it:
/// the run's files would go among the scene's, and `--force` would move
/// the scene itself aside. Both are compared as the system resolves them
/// (links and `..` followed); a run folder inside the scene folder is
/// allowed.
fn check_out_is_not_the_scene(out: &Path, scene: &str) -> anyhow::Result<()> {
    if scene == "demo" {
        return Ok(());
    }
    // A scene that does not resolve is said to be missing when it loads.
    let Ok(scene_dir) = std::fs::canonicalize(scene) else {
        return Ok(());
    };
    let scene_dir = if scene_dir.is_file() {
        scene_dir
            .parent()
            .map(Path::to_path_buf)
            .unwrap_or(scene_dir)
    } else {
        scene_dir
    };
    let out_resolved = resolved_even_if_missing(out);
    if scene_dir == out_resolved {
        bail!(
            "--out {} is the scene folder {scene}: the run's files would go among the scene's \
             (and --force would move the scene aside); give --out a folder of its own, e.g. \
             {}-run",
            out.display(),
            scene.trim_end_matches('/')
        );
    }
    if scene_dir.starts_with(&out_resolved) {
        bail!(
            "--out {} holds the scene folder {scene}: the run's files would go beside the \
             scene's (and --force would move the scene aside); give --out a folder of its own",
            out.display()
        );
    }
    Ok(())
}

/// `path` with links and `..` resolved as far as it exists (the rest
/// joined on as given), absolute.
fn resolved_even_if_missing(path: &Path) -> PathBuf {
    if let Ok(resolved) = std::fs::canonicalize(path) {
        return resolved;
    }
    let absolute = std::path::absolute(path).unwrap_or_else(|_| path.to_path_buf());
    match (absolute.parent(), absolute.file_name()) {
        (Some(parent), Some(name)) => resolved_even_if_missing(parent).join(name),
        _ => absolute,
    }
}

/// Refuses a resume whose limit the run has already reached: it would
/// train nothing and say it had finished.
fn check_resume_limits(limits: Limits, trainer: &Trainer, dir: &Path) -> anyhow::Result<()> {
    if trainer.step == u32::MAX {
        bail!(
            "the run in {} is at step {}, the last step zrak counts (32 bits): it cannot be \
             continued; evaluate or render it as it is, or start a new run with --out",
            dir.display(),
            trainer.step
        );
    }
    if let Some(steps) = limits.steps
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
    if let Some(seconds) = limits.seconds
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

/// Trains until a limit or an interrupt, with a progress bar, writing
/// checkpoints and evaluations into the run folder.
fn train_to_limits(
    args: &TrainArgs,
    folder: &RunFolder,
    config: &RunConfig,
    mut trainer: Trainer,
) -> anyhow::Result<()> {
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
    if let Some(appearance) = zrak::train::eval::describe_appearance(trainer.model.as_ref()) {
        note(&appearance);
    }
    let limits = args.limits();
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
        folder,
        &serde_json::to_value(config)?,
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
        note(&format!(
            "interrupted at step {} ({:.1} s trained); checkpoint written to {}\n\
             continue with: zrak train --resume {}{}",
            trainer.step,
            trainer.train_seconds,
            folder.checkpoint_path().display(),
            folder.dir.display(),
            resume_limit(args.limits()),
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

/// The limit to repeat in the command that continues an interrupted run
/// (the steps when both were given: they are what `--steps` counted to).
fn resume_limit(limits: Limits) -> String {
    match (limits.steps, limits.seconds) {
        (Some(steps), _) => format!(" --steps {steps}"),
        (None, Some(seconds)) => format!(" --time {seconds}s"),
        (None, None) => String::new(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cli::parse_args;
    use clap::error::ErrorKind;

    fn refused(args: &[&str]) -> clap::Error {
        match parse_args::<TrainArgs>(args) {
            Ok(_) => panic!("`zrak train {}` was accepted", args.join(" ")),
            Err(error) => error,
        }
    }

    #[test]
    fn a_new_run_gets_the_papers_defaults() {
        let args: TrainArgs = parse_args(&["demo", "--out", "RUN", "--steps", "10"]).unwrap();
        assert_eq!(args.scene.as_deref(), Some("demo"));
        assert_eq!(args.out, Some(PathBuf::from("RUN")));
        assert_eq!(args.steps, Some(10));
        assert_eq!(args.time, None);
        assert_eq!(args.model, ModelKind::Ngp);
        assert_eq!(args.sampling, None);
        assert_eq!(args.engine, None);
        assert_eq!(args.downscale, 1);
        assert_eq!(args.loss, None);
        assert_eq!(args.seed, 0);
        assert_eq!(args.checkpoint_every, 120.0);
        assert_eq!(args.eval_every, 30.0);
        assert_eq!(args.training_scales, 1);
        assert_eq!(args.precision, None);
        assert!(!args.force);
        // The loss left out is the model's own.
        let config = new_run_config(&args, "demo");
        assert_eq!(config.loss, LossKind::Huber);
        assert_eq!(config.scene, "demo");
        let args: TrainArgs =
            parse_args(&["demo", "--out", "RUN", "--time", "1m", "--model", "nerf"]).unwrap();
        assert_eq!(new_run_config(&args, "demo").loss, LossKind::L2);
    }

    #[test]
    fn every_flag_of_a_new_run_is_read() {
        let args: TrainArgs = parse_args(&[
            "scene",
            "--out",
            "RUN",
            "--model",
            "mipnerf",
            "--sampling",
            "paper",
            "--engine",
            "cpu",
            "--time",
            "90s",
            "--downscale",
            "2",
            "--loss",
            "huber",
            "--seed",
            "3",
            "--force",
            "--checkpoint-every",
            "30s",
            "--eval-every",
            "5",
            "--training-scales",
            "4",
            "--precision",
            "f32",
        ])
        .unwrap();
        assert_eq!(args.model, ModelKind::MipNerf);
        assert_eq!(args.sampling, Some(Sampling::Paper));
        assert_eq!(args.engine, Some(EngineKind::Cpu));
        assert_eq!(args.time, Some(90.0));
        assert_eq!(args.downscale, 2);
        assert_eq!(args.loss, Some(LossKind::Huber));
        assert_eq!(args.seed, 3);
        assert!(args.force);
        assert_eq!(args.checkpoint_every, 30.0);
        assert_eq!(args.eval_every, 5.0);
        assert_eq!(args.training_scales, 4);
        assert_eq!(args.precision, Some(Precision::F32));
        let config = new_run_config(&args, "demo");
        assert_eq!(
            (config.model, config.loss, config.training_scales),
            (ModelKind::MipNerf, LossKind::Huber, 4)
        );
        assert_eq!(config.engine, Some(EngineKind::Cpu));
        assert_eq!(config.precision, Precision::F32);
        let args: TrainArgs = parse_args(&["s", "--out", "R", "--loss", "l2"]).unwrap();
        assert_eq!(args.loss, Some(LossKind::L2));
    }

    #[test]
    fn a_resume_needs_only_the_run_folder() {
        let args: TrainArgs = parse_args(&["--resume", "RUN"]).unwrap();
        assert_eq!(args.resume, Some(PathBuf::from("RUN")));
        assert_eq!((args.scene, args.out), (None, None));
        // The limit and the engine may change on the way.
        let args: TrainArgs = parse_args(&[
            "--resume",
            "RUN",
            "--time",
            "20m",
            "--engine",
            "gpu",
            "--precision",
            "mixed",
        ])
        .unwrap();
        assert_eq!(args.time, Some(1200.0));
        assert_eq!(args.engine, Some(EngineKind::Gpu));
        assert_eq!(args.precision, Some(Precision::Mixed));
        // SCENE may be given, to be checked against the run's.
        let args: TrainArgs = parse_args(&["demo", "--resume", "RUN"]).unwrap();
        assert_eq!(args.scene.as_deref(), Some("demo"));
    }

    #[test]
    fn what_a_resumed_run_is_made_of_cannot_be_given_again() {
        for (flag, value) in [
            ("--model", Some("nerf")),
            ("--sampling", Some("paper")),
            ("--downscale", Some("2")),
            ("--loss", Some("l2")),
            ("--seed", Some("1")),
            ("--training-scales", Some("2")),
            ("--out", Some("OTHER")),
            ("--force", None),
        ] {
            let mut args = vec!["--resume", "RUN", flag];
            args.extend(value);
            let error = refused(&args);
            assert_eq!(error.kind(), ErrorKind::ArgumentConflict, "{flag}: {error}");
            let message = error.to_string();
            assert!(
                message.contains(flag) && message.contains("--resume <RESUME>"),
                "{flag}: {message}"
            );
        }
    }

    #[test]
    fn a_new_run_needs_a_scene_and_an_out_folder() {
        let error = refused(&["--out", "RUN", "--steps", "1"]);
        assert_eq!(error.kind(), ErrorKind::MissingRequiredArgument);
        assert!(error.to_string().contains("<SCENE>"), "{error}");
        let error = refused(&["demo", "--steps", "1"]);
        assert_eq!(error.kind(), ErrorKind::MissingRequiredArgument);
        assert!(error.to_string().contains("--out <OUT>"), "{error}");
    }

    #[test]
    fn training_scales_are_one_to_eight() {
        for scales in ["0", "9"] {
            let error = refused(&["demo", "--out", "R", "--training-scales", scales]);
            assert_eq!(error.kind(), ErrorKind::ValueValidation);
            assert!(error.to_string().contains("1..=8"), "{error}");
        }
        let args: TrainArgs =
            parse_args(&["demo", "--out", "R", "--training-scales", "8"]).unwrap();
        assert_eq!(args.training_scales, 8);
    }

    #[test]
    fn durations_and_values_are_checked_as_they_are_read() {
        let error = refused(&["demo", "--out", "R", "--time", "soon"]);
        assert_eq!(error.kind(), ErrorKind::ValueValidation);
        assert!(
            error
                .to_string()
                .contains("`soon` is not a duration like 90s, 10m or 1h"),
            "{error}"
        );
        let error = refused(&["demo", "--out", "R", "--checkpoint-every", "0s"]);
        assert!(
            error.to_string().contains("must be a positive duration"),
            "{error}"
        );
        let error = refused(&["demo", "--out", "R", "--model", "gaussians"]);
        assert_eq!(error.kind(), ErrorKind::InvalidValue);
        assert!(
            error
                .to_string()
                .contains("[possible values: ngp, nerf, mipnerf]"),
            "{error}"
        );
        let error = refused(&["demo", "--out", "R", "--loss", "l1"]);
        assert_eq!(error.kind(), ErrorKind::InvalidValue);
        assert!(error.to_string().contains("huber, l2"), "{error}");
    }

    #[test]
    fn an_interrupted_run_is_continued_with_its_own_limit() {
        let limits = |steps, seconds| Limits { steps, seconds };
        assert_eq!(resume_limit(limits(Some(500), None)), " --steps 500");
        assert_eq!(resume_limit(limits(None, Some(600.0))), " --time 600s");
        assert_eq!(resume_limit(limits(Some(500), Some(600.0))), " --steps 500");
        assert_eq!(resume_limit(limits(None, None)), "");
    }
}
