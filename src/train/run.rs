//! A training run on disk: the loop with its limits, `metrics.jsonl`,
//! periodic evaluation on held-out views, and checkpoints.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use super::checkpoint::Checkpoint;
use super::eval::{mean_psnr_sampled, spread_views};
use super::log::{LogLine, MetricsLog};
use super::model::StepStats;
use super::trainer::Trainer;

/// File names inside a run folder.
pub const CHECKPOINT_FILE: &str = "checkpoint.zrak";
pub const METRICS_FILE: &str = "metrics.jsonl";
pub const CONFIG_FILE: &str = "run.json";

/// When to stop: whichever limit comes first (steps counted from the start
/// of training, so a resumed run stops at the same step).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Limits {
    pub steps: Option<u32>,
    /// Training seconds (evaluation excluded).
    pub seconds: Option<f64>,
}

impl Limits {
    fn reached(&self, trainer: &Trainer) -> bool {
        self.steps.is_some_and(|s| trainer.step >= s)
            || self.seconds.is_some_and(|s| trainer.train_seconds >= s)
    }
}

/// How often to log, evaluate and checkpoint.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Schedule {
    pub log_every_steps: u32,
    /// Training seconds between evaluations on the held-out views.
    pub eval_every_seconds: f64,
    /// Held-out views rendered for the progress PSNR.
    pub eval_views: usize,
    /// Pixels rendered for the first progress PSNR, over all its views;
    /// later evaluations adapt the count so that they take about
    /// `eval_share` of the training time between two of them.
    pub eval_rays: usize,
    pub eval_share: f64,
    /// Wall seconds between checkpoints.
    pub checkpoint_every_seconds: f64,
}

impl Default for Schedule {
    fn default() -> Self {
        Self {
            log_every_steps: 16,
            eval_every_seconds: 30.0,
            eval_views: 3,
            eval_rays: 1 << 13,
            // Issue 14's bound: at most ~10 % of the wall time.
            eval_share: 0.05,
            checkpoint_every_seconds: 120.0,
        }
    }
}

/// What the loop reports after each step.
pub struct Progress<'a> {
    pub trainer: &'a Trainer,
    pub stats: &'a StepStats,
    /// Samples per second over the steps since the last report.
    pub samples_per_second: f64,
    /// The latest held-out PSNR.
    pub psnr: Option<f64>,
}

/// Where a run keeps its files.
pub struct RunFolder {
    pub dir: PathBuf,
}

impl RunFolder {
    /// Creates the folder (and checks it is writable) before any training,
    /// so a bad `--out` fails at once instead of after the first checkpoint.
    pub fn create(dir: &Path) -> Result<Self, String> {
        std::fs::create_dir_all(dir)
            .map_err(|e| format!("{}: cannot create the run folder: {e}", dir.display()))?;
        let probe = dir.join(".zrak-write-test");
        std::fs::write(&probe, b"")
            .map_err(|e| format!("{}: the run folder is not writable: {e}", dir.display()))?;
        let _ = std::fs::remove_file(probe);
        Ok(Self {
            dir: dir.to_path_buf(),
        })
    }

    /// An existing run folder (for eval, render and resume).
    pub fn open(dir: &Path) -> Result<Self, String> {
        if !dir.is_dir() {
            return Err(format!("{}: no such run folder", dir.display()));
        }
        Ok(Self {
            dir: dir.to_path_buf(),
        })
    }

    pub fn checkpoint_path(&self) -> PathBuf {
        self.dir.join(CHECKPOINT_FILE)
    }

    pub fn metrics_path(&self) -> PathBuf {
        self.dir.join(METRICS_FILE)
    }

    pub fn config_path(&self) -> PathBuf {
        self.dir.join(CONFIG_FILE)
    }
}

/// Trains until `limits` or until `stop` is set (checked between steps, so
/// an interrupt finishes the current step), logging, evaluating and
/// checkpointing on `schedule`, and always writing the checkpoint at the
/// end. `run_config` is stored in every checkpoint's header. Returns the
/// last held-out PSNR.
pub fn run(
    trainer: &mut Trainer,
    limits: Limits,
    schedule: Schedule,
    folder: &RunFolder,
    run_config: &serde_json::Value,
    stop: &AtomicBool,
    mut on_step: impl FnMut(&Progress),
) -> Result<Option<f64>, String> {
    let mut log = MetricsLog::open(&folder.metrics_path())
        .map_err(|e| format!("{}: {e}", folder.metrics_path().display()))?;
    // The held-out views: val, else test, else (a scene with no held-out
    // split) the training views themselves.
    let scene = trainer.scene.clone();
    let held_out_frames = [&scene.val, &scene.test, &scene.train]
        .into_iter()
        .find(|frames| !frames.is_empty())
        .unwrap_or(&scene.train);
    let held_out = spread_views(held_out_frames, schedule.eval_views);

    let wall_start = Instant::now();
    let wall_offset = trainer.train_seconds;
    let mut last_checkpoint = Instant::now();
    let mut next_eval = trainer.train_seconds + schedule.eval_every_seconds;
    let mut psnr = None;
    let mut eval_rays = schedule.eval_rays.max(1);
    let full_views: usize = held_out
        .iter()
        .map(|f| (f.camera.intrinsics.width * f.camera.intrinsics.height) as usize)
        .sum();
    let mut window_samples = 0usize;
    let mut window_seconds = 0f64;
    let mut samples_per_second = 0f64;

    let save = |trainer: &Trainer| -> Result<(), String> {
        trainer
            .checkpoint(run_config.clone())
            .save(&folder.checkpoint_path())
            .map_err(|e| e.to_string())
    };

    while !limits.reached(trainer) && !stop.load(Ordering::SeqCst) {
        let before = trainer.train_seconds;
        let stats = trainer.step();
        window_samples += stats.samples;
        window_seconds += trainer.train_seconds - before;
        let evaluate_now = trainer.train_seconds >= next_eval || limits.reached(trainer);
        let mut evaluated = None;
        if evaluate_now {
            let clock = Instant::now();
            evaluated = Some(mean_psnr_sampled(
                trainer.model.as_ref(),
                &held_out,
                eval_rays,
            ));
            psnr = evaluated;
            // Scale the next evaluation's pixels towards its share of the
            // time, by at most 4× either way (one slow evaluation, e.g. on
            // a busy machine, must not swing it), never past whole views.
            let took = clock.elapsed().as_secs_f64().max(1e-3);
            let wanted = schedule.eval_share * schedule.eval_every_seconds / took;
            eval_rays = ((eval_rays as f64 * wanted.clamp(0.25, 4.0)) as usize)
                .clamp(256.min(full_views), full_views.max(1));
            next_eval = trainer.train_seconds + schedule.eval_every_seconds;
        }
        if trainer.step.is_multiple_of(schedule.log_every_steps) || evaluated.is_some() {
            if window_seconds > 0.0 {
                samples_per_second = window_samples as f64 / window_seconds;
            }
            window_samples = 0;
            window_seconds = 0.0;
            log.write(&LogLine {
                step: trainer.step,
                wall_seconds: wall_offset + wall_start.elapsed().as_secs_f64(),
                train_seconds: trainer.train_seconds,
                loss: stats.loss,
                psnr: evaluated,
                samples_per_ray: stats.samples_per_ray(),
                composited_per_ray: stats.composited_per_ray(),
                samples_per_second,
                rays_per_batch: stats.rays,
            })
            .map_err(|e| format!("{}: {e}", log.path().display()))?;
        }
        on_step(&Progress {
            trainer,
            stats: &stats,
            samples_per_second,
            psnr,
        });
        if last_checkpoint.elapsed().as_secs_f64() >= schedule.checkpoint_every_seconds {
            save(trainer)?;
            last_checkpoint = Instant::now();
        }
    }
    save(trainer)?;
    Ok(psnr)
}

/// Loads a run's checkpoint.
pub fn load_checkpoint(folder: &RunFolder) -> Result<Checkpoint, String> {
    Checkpoint::load(&folder.checkpoint_path()).map_err(|e| e.to_string())
}
