//! `zrak bench quality`: the command-line side of the accuracy-versus-time
//! experiment (the library's `bench::quality` and `bench::report` do the
//! measuring and the writing): loading the scenes, building or resuming
//! each cell's trainer, the progress bar, interrupts.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::{Context, bail};
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use zrak::bench::quality::{
    CellOutcome, CellProgress, CellRecord, CellSpec, DEFAULT_EVAL_DOWNSCALE, DEFAULT_EVERY,
    EvalPixels, PROTOCOL_FILE, Protocol, RUNS_FOLDER, cells_for,
};
use zrak::bench::report::{
    CellResult, EngineInfo, REPORT_MD, Results, SceneEntry, Settings, machine, write_outputs,
};
use zrak::bench::table::{Table, format_mark, format_seconds};
use zrak::engine::{EngineKind, choose_engine};
use zrak::field::ModelKind;
use zrak::field::common::Sampling;
use zrak::field::mlp::Precision;
use zrak::interrupt::{
    note, say, {self},
};
use zrak::scene::{Scene, Split};
use zrak::train::run::RunFolder;
use zrak::train::trainer::Trainer;

use super::run_config::{
    RunConfig, build_trainer, read_run_config, restore_checkpoint, scene_key, start_run_folder,
};
use super::{PhotographSwitches, SpaceChoice, load_scene, parse_duration};

#[derive(Args, Debug)]
pub struct QualityArgs {
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
    #[arg(long, value_enum, default_value_t = Split::Test)]
    split: Split,
    /// Score every N-th view of the split, from the first (1: all views).
    #[arg(long, default_value_t = DEFAULT_EVERY,
          value_parser = clap::value_parser!(usize))]
    every: usize,
    /// Score 1/N² of each view's pixels, chosen by --eval-pixels, so that
    /// NeRF's slow renders stay affordable (1: every pixel).
    #[arg(long, default_value_t = DEFAULT_EVAL_DOWNSCALE)]
    eval_downscale: u32,
    /// tiles: full-resolution tiles, one from each block of N×N (estimates
    /// the full-resolution scores the papers report); downscaled: the whole
    /// view at 1/N resolution against area-averaged photographs (Mip-NeRF's
    /// multiscale protocol, which penalises aliasing).
    #[arg(long, value_enum, default_value_t = EvalPixels::Tiles)]
    eval_pixels: EvalPixels,
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
    /// What every scene is treated as: a bounded object, unbounded, or a
    /// forward-facing capture; auto leaves it to the scene analysis.
    #[arg(long, value_enum, default_value_t = SpaceChoice::Auto)]
    space: SpaceChoice,
    /// Per-image appearance and camera refinement in every cell: auto
    /// leaves each to the analysis of each scene's photographs.
    #[command(flatten)]
    photographs: PhotographSwitches,
}

/// A scene of the experiment, loaded once for all its cells.
struct LoadedScene {
    name: String,
    /// As given on the command line (`demo` or a folder).
    argument: String,
    scene: Arc<Scene>,
}

/// The short name a scene goes by in folders and the report.
fn scene_name(argument: &str) -> String {
    if argument == "demo" {
        return "demo".into();
    }
    let path = Path::new(argument);
    let canonical = std::fs::canonicalize(path).unwrap_or_else(|_| path.to_path_buf());
    canonical
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| argument.to_string())
}

/// Creates `dir` and checks that files can be written there, before any
/// training, so a bad `--out` fails at once.
fn create_output_folder(dir: &Path) -> anyhow::Result<()> {
    std::fs::create_dir_all(dir)
        .with_context(|| format!("{}: cannot create the experiment folder", dir.display()))?;
    let probe = dir.join(".zrak-write-test");
    std::fs::write(&probe, b"")
        .with_context(|| format!("{}: the experiment folder is not writable", dir.display()))?;
    let _ = std::fs::remove_file(probe);
    Ok(())
}

/// Refuses a folder holding an experiment made with other settings (its
/// scores would not compare); says whether the folder holds this one's
/// settings already.
fn check_folder(dir: &Path, protocol: &Protocol) -> anyhow::Result<bool> {
    let path = dir.join(PROTOCOL_FILE);
    match std::fs::read_to_string(&path) {
        Ok(text) => {
            let recorded: Protocol = serde_json::from_str(&text)
                .with_context(|| format!("{}: not an experiment's settings", path.display()))?;
            if &recorded != protocol {
                bail!(
                    "{} holds an experiment with other settings ({}); give another --out, \
                     or the same --budget, --marks, --split, --every, --eval-downscale, \
                     --eval-pixels, \
                     --downscale, --seed and --batch-samples to continue it",
                    dir.display(),
                    describe_protocol(&recorded)
                );
            }
            Ok(true)
        }
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(false),
        Err(e) => Err(e).with_context(|| format!("{}: cannot read", path.display())),
    }
}

/// Records the protocol in the experiment's folder, once every check has
/// passed: a refused command must leave nothing that would block its
/// corrected re-run.
fn record_protocol(dir: &Path, protocol: &Protocol) -> anyhow::Result<()> {
    let path = dir.join(PROTOCOL_FILE);
    zrak::files::write_bytes_atomically(&path, serde_json::to_string_pretty(protocol)?.as_bytes())
        .with_context(|| format!("{}: cannot write", path.display()))
}

fn describe_protocol(p: &Protocol) -> String {
    format!(
        "budget {}, marks {}, split {}, every {}, eval downscale {} ({:?}), downscale {}, \
         seed {}, batch {}",
        format_mark(p.budget_seconds),
        p.marks_seconds
            .iter()
            .map(|&m| format_mark(m))
            .collect::<Vec<_>>()
            .join(","),
        p.split,
        p.every,
        p.eval_downscale,
        p.eval_pixels,
        p.downscale,
        p.seed,
        p.batch_samples
            .map_or("each model's own".to_string(), |n| format!("{n} samples"))
    )
}

/// The command as typed, to print in the report and to resume with.
fn command_line() -> String {
    let words: Vec<String> = std::env::args()
        .enumerate()
        .map(|(i, w)| if i == 0 { "zrak".to_string() } else { w })
        .map(|w| {
            if w.is_empty() || w.contains(|c: char| c.is_whitespace() || "'\"$`\\".contains(c)) {
                format!("'{}'", w.replace('\'', "'\\''"))
            } else {
                w
            }
        })
        .collect();
    words.join(" ")
}

/// How one cell's run folder is set up.
fn run_config(cell: &CellSpec, scene: &LoadedScene, args: &QualityArgs) -> RunConfig {
    let mut config = RunConfig {
        scene: scene_key(&scene.argument),
        model: cell.model,
        downscale: args.downscale,
        loss: cell.model.default_loss(),
        seed: args.seed,
        sampling: cell.sampling,
        engine: args.engine,
        batch_samples: args.batch_samples.map(|n| n as usize),
        precision: precision(args),
        training_scales: 1,
        space: None,
        space_overridden: false,
        photographs: args.photographs.analyse(&scene.scene),
    };
    config.record_space(&scene.scene);
    config
}

/// The experiment's precision: as asked, else mixed where the processor
/// has bf16 kernels.
fn precision(args: &QualityArgs) -> Precision {
    args.precision.unwrap_or_else(Precision::best_available)
}

pub fn bench_quality(args: QualityArgs) -> anyhow::Result<()> {
    let split = args.split;
    let marks = args.marks.clone();
    let protocol = Protocol::new(
        args.budget,
        marks.as_deref(),
        split.name(),
        args.every,
        args.eval_downscale,
        args.downscale,
        args.seed,
    )
    .map_err(anyhow::Error::msg)?
    .with_eval_pixels(args.eval_pixels)
    .with_batch_samples(args.batch_samples.map(|n| n as usize));
    if let Some(bad) = args.targets.iter().find(|t| !(t.is_finite() && **t > 0.0)) {
        bail!("--targets: {bad} is not a PSNR in dB (give positive numbers, e.g. 25,30,33)");
    }
    create_output_folder(&args.out)?;
    // One experiment command per folder at a time; each cell's run folder
    // is locked too, against `zrak train --resume` of it meanwhile.
    let _lock = zrak::train::lock::RunLock::acquire(&args.out).map_err(anyhow::Error::msg)?;
    let protocol_recorded = check_folder(&args.out, &protocol)?;

    // Every scene loads (and has the split) before anything trains.
    let mut scenes: Vec<LoadedScene> = Vec::new();
    for argument in &args.scenes {
        let name = scene_name(argument);
        if let Some(other) = scenes.iter().find(|s| s.name == name) {
            bail!(
                "the scenes `{}` and `{argument}` are both called {name}: their cells would \
                 share run folders; give them folders of different names",
                other.argument
            );
        }
        let scene = args.space.apply(
            load_scene(argument, args.downscale)
                .with_context(|| format!("{argument}: cannot load the scene"))?,
        );
        if let Some(problem) = scene.training_problem() {
            bail!("{argument}: nothing to train: {problem}");
        }
        let frames = scene.split(split);
        if frames.is_empty() {
            bail!(
                "{argument}: the scene has no {} views to score; choose another with --split \
                 (the NeRF-synthetic folders in ../shared have train and val)",
                split.name()
            );
        }
        protocol
            .views(frames)
            .map_err(|e| anyhow::anyhow!("{argument}: {e}"))?;
        scenes.push(LoadedScene {
            name,
            argument: argument.clone(),
            scene: Arc::new(scene),
        });
    }
    let names: Vec<String> = scenes.iter().map(|s| s.name.clone()).collect();
    let cells = cells_for(&names, &args.models, &args.sampling);

    let choice = choose_engine(args.engine)?;
    note(&choice.reason);
    let engine = EngineInfo {
        engine: choice.kind.name().to_string(),
        description: choice.reason.clone(),
        kernels: match choice.kind {
            EngineKind::Cpu => format!(
                "{:?} ({} threads)",
                zrak::engine::cpu::dense::backend_for(precision(&args)),
                rayon::current_num_threads()
            ),
            EngineKind::Gpu => "WGSL compute shaders".to_string(),
        },
        precision: match choice.kind {
            EngineKind::Cpu => precision(&args).kernels_here().describe().to_string(),
            EngineKind::Gpu => Precision::F32.describe().to_string(),
        },
    };
    let runs = args.out.join(RUNS_FOLDER);

    // Each unfinished cell's model is built once up front, so that a
    // combination the engine cannot run fails now, not after hours.
    let mut records: Vec<Option<CellRecord>> = Vec::new();
    for cell in &cells {
        let folder = runs.join(cell.folder_name());
        let record = CellRecord::load(&folder).map_err(anyhow::Error::msg)?;
        if let Some(record) = &record
            && record.protocol != protocol
        {
            bail!(
                "{}: scored under other settings ({}) than this experiment's",
                CellRecord::path(&folder).display(),
                describe_protocol(&record.protocol)
            );
        }
        if !record.as_ref().is_some_and(CellRecord::finished) {
            let scene = &scenes
                .iter()
                .find(|s| s.name == cell.scene)
                .expect("loaded");
            let config = run_config(cell, scene, &args);
            build_trainer(&config, scene.scene.clone(), choice.share()?)
                .with_context(|| format!("{} on {}", cell.label(), cell.scene))?;
        }
        records.push(record);
    }
    if !protocol_recorded {
        record_protocol(&args.out, &protocol)?;
    }

    let budget = protocol.budget_seconds;
    let total = budget * cells.len() as f64;
    let trained_before: f64 = records
        .iter()
        .flatten()
        .map(|r| r.marks.last().map_or(0.0, |m| m.train_seconds.min(budget)))
        .sum();
    let bar = ProgressBar::new(total.ceil() as u64);
    bar.set_style(
        ProgressStyle::with_template(
            "{bar:30} {percent:>3}% of the training | {msg} | about {eta} left",
        )
        .expect("valid template"),
    );
    bar.set_position(trained_before as u64);
    bar.reset_eta();

    let settings = |scenes: &[LoadedScene]| Settings {
        protocol: protocol.clone(),
        models: args.models.clone(),
        samplings: args.sampling.clone(),
        scenes: scenes
            .iter()
            .map(|s| {
                let count = s.scene.split(split).len();
                SceneEntry {
                    name: s.name.clone(),
                    source: scene_key(&s.argument),
                    split_views: count,
                    scored: protocol.describe_views(count),
                }
            })
            .collect(),
        targets_db: args.targets.clone(),
        background: "white".to_string(),
        command: command_line(),
    };
    let write_report = |records: &[Option<CellRecord>]| -> anyhow::Result<PathBuf> {
        let results: Vec<CellResult> = cells
            .iter()
            .zip(records)
            .filter_map(|(cell, record)| {
                let record = record.as_ref()?;
                // Relative to the experiment's folder, which may move.
                Some(CellResult::new(
                    cell,
                    record,
                    &Path::new(RUNS_FOLDER).join(cell.folder_name()),
                    &args.targets,
                ))
            })
            .collect();
        let results = Results::new(machine(), engine.clone(), settings(&scenes), results);
        write_outputs(&args.out, &results).map_err(anyhow::Error::msg)?;
        Ok(args.out.join(REPORT_MD))
    };

    for (index, cell) in cells.iter().enumerate() {
        if records[index].as_ref().is_some_and(CellRecord::finished) {
            continue;
        }
        let scene = scenes
            .iter()
            .find(|s| s.name == cell.scene)
            .expect("loaded");
        let folder_path = runs.join(cell.folder_name());
        let folder = RunFolder::create(&folder_path).map_err(anyhow::Error::msg)?;
        let config = run_config(cell, scene, &args);
        let mut trainer = open_cell(&folder, &config, scene, choice.share()?)?;
        let mut record = records[index].take().unwrap_or_else(|| CellRecord {
            protocol: protocol.clone(),
            scene: cell.scene.clone(),
            model: cell.model,
            sampling: cell.sampling,
            engine: engine.description.clone(),
            marks: Vec::new(),
        });
        let views = protocol
            .views(scene.scene.split(split))
            .map_err(anyhow::Error::msg)?;
        let done_before = index as f64 * budget;
        let label = format!("{} · {}", cell.scene, cell.label());
        let outcome = zrak::bench::quality::run_cell(
            &mut trainer,
            &mut record,
            &folder,
            &serde_json::to_value(&config)?,
            &views,
            interrupt::flag(),
            |progress| match progress {
                CellProgress::Training {
                    mark,
                    train_seconds,
                    step,
                    samples_per_second,
                } => {
                    bar.set_position((done_before + train_seconds.min(budget)) as u64);
                    bar.set_message(format!(
                        "{label} · training to {} · step {step} · {:.2} M samples/s",
                        format_mark(protocol.marks_seconds[mark]),
                        samples_per_second / 1e6
                    ));
                }
                CellProgress::Scoring {
                    mark,
                    view,
                    views,
                    psnr,
                } => bar.set_message(format!(
                    "{label} · scoring at {}: view {view} of {views} ({psnr:.2} dB)",
                    format_mark(protocol.marks_seconds[mark])
                )),
            },
        );
        records[index] = Some(record);
        let outcome = match outcome {
            Ok(outcome) => outcome,
            Err(error) => {
                bar.abandon();
                // What was scored so far is kept in the report.
                let _ = write_report(&records);
                bail!("{} on {}: {error}", cell.label(), cell.scene);
            }
        };
        let report = write_report(&records)?;
        if outcome == CellOutcome::Interrupted {
            bar.abandon();
            note(&format!(
                "interrupted during {} on {} (step {}, {:.1} s trained); the checkpoint \
                 and every mark scored are kept, and {} holds the results so far.\n\
                 continue with: {}",
                cell.label(),
                cell.scene,
                trainer.step,
                trainer.train_seconds,
                report.display(),
                command_line()
            ));
            return Ok(());
        }
        let last = records[index]
            .as_ref()
            .and_then(|r| r.marks.last())
            .map_or(f64::NAN, |m| m.psnr);
        bar.suspend(|| {
            note(&format!(
                "{} on {}: {:.2} dB after {} of training",
                cell.label(),
                cell.scene,
                last,
                format_seconds(budget)
            ))
        });
    }
    bar.finish_with_message("done");
    let report = write_report(&records)?;
    say(&summary(&cells, &records, &args.targets));
    say(&format!(
        "wrote {} (and results.json, results.csv, the plots) in {}",
        report.display(),
        args.out.display()
    ));
    Ok(())
}

/// The trainer of a cell: resumed from its checkpoint when one is there,
/// else new (its `run.json` written and any old log cleared).
fn open_cell(
    folder: &RunFolder,
    config: &RunConfig,
    scene: &LoadedScene,
    choice: zrak::engine::EngineChoice,
) -> anyhow::Result<Trainer> {
    if folder.checkpoint_path().is_file() {
        let recorded = read_run_config(folder)?;
        // A run from before spaces were recorded matches any.
        let same_space = recorded.space.is_none() || recorded.space == config.space;
        if (
            recorded.model,
            recorded.sampling,
            &recorded.scene,
            recorded.downscale,
            recorded.seed,
        ) != (
            config.model,
            config.sampling,
            &config.scene,
            config.downscale,
            config.seed,
        ) || !same_space
        {
            bail!(
                "{}: the run there is not this cell's (another model, sampler, scene, \
                 downscale, seed or scene space); move it away or give another --out",
                folder.dir.display()
            );
        }
        let mut trainer = build_trainer(config, scene.scene.clone(), choice)?;
        restore_checkpoint(folder, &mut trainer)?;
        return Ok(trainer);
    }
    let trainer = build_trainer(config, scene.scene.clone(), choice)?;
    start_run_folder(folder, config)?;
    Ok(trainer)
}

/// A few lines for the terminal: each cell's last score and the time to
/// each target.
fn summary(cells: &[CellSpec], records: &[Option<CellRecord>], targets: &[f64]) -> String {
    let mut headers = vec!["scene".to_string(), "model".to_string(), "PSNR".to_string()];
    headers.extend(targets.iter().map(|t| format!("to {t:.0} dB")));
    let mut table = Table::new(headers);
    for (cell, record) in cells.iter().zip(records) {
        let Some(record) = record else { continue };
        let curve = record.curve();
        let mut row = vec![
            cell.scene.clone(),
            cell.label(),
            record
                .marks
                .last()
                .map_or("—".into(), |m| format!("{:.2}", m.psnr)),
        ];
        row.extend(
            targets
                .iter()
                .map(|&t| zrak::bench::table::time_to_reach(&curve, t).describe()),
        );
        table.push(row);
    }
    table.to_markdown()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cli::parse_args;

    #[test]
    fn scene_names_come_from_folders() {
        assert_eq!(scene_name("demo"), "demo");
        assert_eq!(scene_name("/data/nerf_synthetic/lego_400"), "lego_400");
        assert_eq!(scene_name("/data/nerf_synthetic/lego_400/"), "lego_400");
    }

    #[test]
    fn the_experiment_defaults_to_ten_minutes_of_each_model_scored_on_test() {
        let args: QualityArgs = parse_args(&["demo", "--out", "DIR"]).unwrap();
        assert_eq!(args.scenes, ["demo"]);
        assert_eq!(args.out, PathBuf::from("DIR"));
        assert_eq!(args.models, ModelKind::ALL);
        assert_eq!(args.sampling, [Sampling::Occupancy]);
        assert_eq!(args.budget, 600.0);
        assert_eq!(args.marks, None);
        assert_eq!(args.split, Split::Test);
        assert_eq!(args.every, DEFAULT_EVERY);
        assert_eq!(args.eval_downscale, DEFAULT_EVAL_DOWNSCALE);
        assert_eq!(args.eval_pixels, EvalPixels::Tiles);
        assert_eq!((args.downscale, args.seed), (1, 0));
        assert_eq!((args.engine, args.batch_samples), (None, None));
        assert_eq!(args.targets, [25.0, 30.0, 33.0]);
        assert_eq!(precision(&args), Precision::best_available());
    }

    #[test]
    fn lists_and_durations_are_comma_separated() {
        let args: QualityArgs = parse_args(&[
            "a",
            "b",
            "--out",
            "DIR",
            "--models",
            "nerf,mipnerf",
            "--sampling",
            "occupancy,paper",
            "--budget",
            "90s",
            "--marks",
            "30s,1m,1.5m",
            "--targets",
            "20,27.5",
            "--batch-samples",
            "1024",
            "--split",
            "val",
        ])
        .unwrap();
        assert_eq!(args.scenes, ["a", "b"]);
        assert_eq!(args.models, [ModelKind::Nerf, ModelKind::MipNerf]);
        assert_eq!(args.sampling, [Sampling::Occupancy, Sampling::Paper]);
        assert_eq!(args.budget, 90.0);
        assert_eq!(args.marks, Some(vec![30.0, 60.0, 90.0]));
        assert_eq!(args.targets, [20.0, 27.5]);
        assert_eq!(args.batch_samples, Some(1024));
        assert_eq!(args.split, Split::Val);
    }

    #[test]
    fn an_experiment_needs_scenes_a_folder_and_a_positive_batch() {
        use clap::error::ErrorKind;
        let error = parse_args::<QualityArgs>(&["--out", "DIR"]).unwrap_err();
        assert_eq!(error.kind(), ErrorKind::MissingRequiredArgument);
        assert!(error.to_string().contains("<SCENES>..."), "{error}");
        let error = parse_args::<QualityArgs>(&["demo"]).unwrap_err();
        assert_eq!(error.kind(), ErrorKind::MissingRequiredArgument);
        assert!(error.to_string().contains("--out <OUT>"), "{error}");
        let error =
            parse_args::<QualityArgs>(&["demo", "--out", "D", "--batch-samples", "0"]).unwrap_err();
        assert_eq!(error.kind(), ErrorKind::ValueValidation);
        assert!(error.to_string().contains("1.."), "{error}");
        let error =
            parse_args::<QualityArgs>(&["demo", "--out", "D", "--marks", "1m,later"]).unwrap_err();
        assert!(
            error.to_string().contains("`later` is not a duration"),
            "{error}"
        );
    }

    #[test]
    fn each_cell_runs_as_the_experiment_says() {
        let args: QualityArgs = parse_args(&[
            "demo",
            "--out",
            "D",
            "--downscale",
            "2",
            "--seed",
            "5",
            "--engine",
            "cpu",
            "--batch-samples",
            "4096",
            "--precision",
            "f32",
            "--space",
            "unbounded",
        ])
        .unwrap();
        let cell = CellSpec {
            scene: "demo".into(),
            model: ModelKind::Nerf,
            sampling: Sampling::Paper,
        };
        let scene = LoadedScene {
            name: "demo".into(),
            argument: "demo".into(),
            scene: Arc::new(args.space.apply(load_scene("demo", 16).unwrap())),
        };
        let config = run_config(&cell, &scene, &args);
        assert_eq!(config.scene, "demo");
        assert_eq!(
            (config.model, config.sampling),
            (ModelKind::Nerf, Sampling::Paper)
        );
        assert_eq!(config.loss, ModelKind::Nerf.default_loss());
        assert_eq!((config.downscale, config.seed), (2, 5));
        assert_eq!(config.engine, Some(EngineKind::Cpu));
        assert_eq!(config.batch_samples, Some(4096));
        assert_eq!(config.precision, Precision::F32);
        assert_eq!(config.training_scales, 1);
        assert_eq!(config.space, Some(zrak::scene::SceneSpace::Unbounded));
        assert!(config.space_overridden);
    }
}
