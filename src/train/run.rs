//! A training run on disk: the loop with its limits, `metrics.jsonl`,
//! periodic evaluation on held-out views, and checkpoints.

use super::folder_error::{OutFolder, RunFolderError};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use super::eval::{mean_psnr_sampled, spread_views};
use super::lock::RunLock;
use super::log::{LogLine, MetricsLog};
use super::trainer::Trainer;
use crate::model::StepStats;
use crate::model::checkpoint::Checkpoint;

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
    /// Whether training stops here: at a limit, or at the last step a
    /// checkpoint can count (its `u32` step), which no run continues past.
    fn reached(&self, trainer: &Trainer) -> bool {
        self.steps.is_some_and(|s| trainer.step >= s)
            || self.seconds.is_some_and(|s| trainer.train_seconds >= s)
            || trainer.step == u32::MAX
    }
}

/// The largest `run.json` read: zrak writes a few hundred bytes, so a
/// megabyte leaves room for any later field and refuses anything else
/// before it is read.
pub const MAX_RUN_JSON_BYTES: u64 = 1 << 20;

/// The field every `run.json` zrak writes holds (`"saved_by": "zrak"`
/// from the command line, `"viewer"` from the viewer): a folder whose
/// `run.json` has it is a run, even before its first checkpoint, and a
/// `run.json` without it is someone else's file.
pub const RUN_JSON_MARKER: &str = "saved_by";

/// What the command line writes in [`RUN_JSON_MARKER`].
pub const SAVED_BY_COMMAND_LINE: &str = "zrak";

/// A run moved aside by [`RunFolder::create_new`]: where to, and whether
/// it was a zrak run (else a folder of other files).
#[derive(Debug, Clone, PartialEq)]
pub struct MovedAside {
    pub to: PathBuf,
    pub was_run: bool,
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
    /// Wall seconds before the first checkpoint (at most
    /// `checkpoint_every_seconds`): soon, so a run killed in its first
    /// minutes (SIGKILL, a power cut) still keeps most of them.
    pub first_checkpoint_seconds: f64,
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
            first_checkpoint_seconds: 10.0,
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

/// Where a run keeps its files. A folder opened for writing holds its
/// [`RunLock`] for as long as this lives.
pub struct RunFolder {
    pub dir: PathBuf,
    // Held, never read: the lock lasts as long as this value.
    _lock: Option<RunLock>,
}

impl RunFolder {
    /// Creates the folder (and checks it is writable) before any training,
    /// so a bad `--out` fails at once instead of after the first checkpoint,
    /// and takes its lock. A run already there is kept (the caller resumes
    /// it); see [`Self::create_new`] for a folder that must not hold one.
    pub fn create(dir: &Path) -> Result<Self, RunFolderError> {
        std::fs::create_dir_all(dir).map_err(|e| {
            RunFolderError::unusable(
                dir,
                format!(
                    "{}: cannot create the run folder: {}",
                    dir.display(),
                    if e.kind() == std::io::ErrorKind::AlreadyExists || dir.exists() {
                        crate::files::describe_not_a_folder(dir)
                    } else {
                        e.to_string()
                    }
                ),
            )
        })?;
        // Created new (never through a link a stranger left at the name).
        let probe = crate::files::temporary_beside(&dir.join("write-test"));
        std::fs::File::create_new(&probe).map_err(|e| {
            RunFolderError::unusable(
                dir,
                format!("{}: the run folder is not writable: {e}", dir.display()),
            )
        })?;
        let _ = std::fs::remove_file(probe);
        let lock = RunLock::acquire(dir)?;
        Ok(Self {
            dir: dir.to_path_buf(),
            _lock: Some(lock),
        })
    }

    /// A folder for a new run. One that already holds a run, or other
    /// files, is refused, naming the ways on (see [`Self::check_out`]),
    /// unless `replace`: then the whole folder is renamed aside (never
    /// deleted) and where it went is returned beside the new folder.
    pub fn create_new(
        dir: &Path,
        replace: bool,
    ) -> Result<(Self, Option<MovedAside>), RunFolderError> {
        let found = Self::out_folder(dir);
        if let Some(refusal) = refusal_of_out(dir, &found, replace) {
            return Err(refusal);
        }
        if found == OutFolder::Free {
            return Ok((Self::create(dir)?, None));
        }
        let was_run = matches!(found, OutFolder::Run { .. });
        // A run another process is writing must not move under it. A
        // folder with no lock file has no writer (a writer makes it first),
        // and a folder of someone else's files gets none made in it.
        let old_lock = crate::files::exists_at_all(&dir.join(super::lock::LOCK_FILE))
            .then(|| RunLock::acquire(dir))
            .transpose()?;
        let aside =
            free_name_beside(dir).map_err(|message| RunFolderError::unusable(dir, message))?;
        std::fs::rename(dir, &aside).map_err(|e| {
            RunFolderError::unusable(
                dir,
                format!(
                    "{}: cannot move the old {} aside to {}: {e}",
                    dir.display(),
                    if was_run { "run" } else { "folder" },
                    aside.display()
                ),
            )
        })?;
        drop(old_lock);
        Ok((Self::create(dir)?, Some(MovedAside { to: aside, was_run })))
    }

    /// What is at `dir`, given as a new run's folder.
    pub fn out_folder(dir: &Path) -> OutFolder {
        if !crate::files::exists_at_all(dir) {
            return OutFolder::Free;
        }
        match std::fs::metadata(dir) {
            Ok(meta) if meta.is_dir() => {}
            Ok(meta) if meta.is_file() => return OutFolder::NotAFolder("a file".into()),
            _ => return OutFolder::NotAFolder(crate::files::describe_not_a_folder(dir)),
        }
        if Self::holds_run(dir) {
            return OutFolder::Run {
                has_checkpoint: crate::files::exists_at_all(&dir.join(CHECKPOINT_FILE)),
            };
        }
        let entries = match std::fs::read_dir(dir) {
            Ok(entries) => entries,
            Err(e) => return OutFolder::NotAFolder(format!("a folder that cannot be read ({e})")),
        };
        let mut names: Vec<String> = entries
            .flatten()
            .map(|entry| entry.file_name().to_string_lossy().into_owned())
            .filter(|name| name != super::lock::LOCK_FILE)
            .collect();
        if names.is_empty() {
            return OutFolder::Free;
        }
        names.sort();
        let count = names.len();
        names.truncate(3);
        OutFolder::Other { names, count }
    }

    /// Refuses `dir` as a new run's folder when it is not a folder, and,
    /// unless `replace`, when it holds a run or other files: each refusal
    /// names what is there and the ways on.
    pub fn check_out(dir: &Path, replace: bool) -> Result<(), RunFolderError> {
        refusal_of_out(dir, &Self::out_folder(dir), replace).map_or(Ok(()), Err)
    }

    /// A run folder to continue: it must hold a checkpoint, and no other
    /// process may be writing it.
    pub fn resume(dir: &Path) -> Result<Self, RunFolderError> {
        if !dir.is_dir() {
            return Err(RunFolderError::NotFound {
                path: dir.to_path_buf(),
                problem: crate::files::describe_not_a_folder(dir),
            });
        }
        // Checked before the lock, so a folder that is no run gets no
        // lock file; by their kind only (nothing is opened), so a named
        // pipe cannot block.
        let checkpoint = dir.join(CHECKPOINT_FILE);
        match crate::files::check_regular_file(&checkpoint) {
            Ok(()) => {}
            Err(crate::files::Unreadable::NotFound) => {
                return Err(RunFolderError::NoCheckpoint {
                    path: dir.to_path_buf(),
                    file: CHECKPOINT_FILE,
                });
            }
            Err(problem) => {
                return Err(RunFolderError::unusable(
                    &checkpoint,
                    format!("{}: cannot resume from it: {problem}", checkpoint.display()),
                ));
            }
        }
        // The log is appended to: never through a link, never to a pipe.
        let log = dir.join(METRICS_FILE);
        if crate::files::exists_at_all(&log) {
            MetricsLog::check_not_a_link(&log)
                .map_err(|message| RunFolderError::unusable(&log, message))?;
            crate::files::check_regular_file(&log).map_err(|problem| {
                RunFolderError::unusable(
                    &log,
                    format!(
                        "{}: cannot continue the run's log: {problem}; move it away and resume \
                         again",
                        log.display()
                    ),
                )
            })?;
        }
        let lock = RunLock::acquire(dir)?;
        Ok(Self {
            dir: dir.to_path_buf(),
            _lock: Some(lock),
        })
    }

    /// Whether `dir` holds a run: a checkpoint, which training would
    /// replace, or a `run.json` zrak wrote (see [`RUN_JSON_MARKER`]).
    pub fn holds_run(dir: &Path) -> bool {
        crate::files::exists_at_all(&dir.join(CHECKPOINT_FILE))
            || is_zrak_run_json(&dir.join(CONFIG_FILE))
    }

    /// An existing run folder, for reading (eval and render): no lock.
    pub fn open(dir: &Path) -> Result<Self, RunFolderError> {
        if !dir.is_dir() {
            return Err(RunFolderError::NotFound {
                path: dir.to_path_buf(),
                problem: crate::files::describe_not_a_folder(dir),
            });
        }
        Ok(Self {
            dir: dir.to_path_buf(),
            _lock: None,
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
///
/// A step whose loss is not finite stops the run with an error and
/// without a checkpoint: the model has diverged, and the last checkpoint
/// written (if any) is the last good one. A checkpoint holding a
/// non-finite parameter is refused the same way (see [`Checkpoint::save`]).
pub fn run(
    trainer: &mut Trainer,
    limits: Limits,
    schedule: Schedule,
    folder: &RunFolder,
    run_config: &serde_json::Value,
    stop: &AtomicBool,
    mut on_step: impl FnMut(&Progress),
) -> Result<Option<f64>, String> {
    let mut log = MetricsLog::open(&folder.metrics_path())?;
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
    let mut next_checkpoint = schedule
        .first_checkpoint_seconds
        .min(schedule.checkpoint_every_seconds);
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

    // The step of the checkpoint on disk, for a diverged run's message.
    let mut saved_step = folder.checkpoint_path().is_file().then_some(trainer.step);
    let kept = |saved_step: Option<u32>| match saved_step {
        Some(step) => format!(
            "the last good checkpoint ({}, step {step}) is kept",
            folder.checkpoint_path().display()
        ),
        None => "no checkpoint had been written yet".to_string(),
    };
    let save = |trainer: &Trainer, saved_step: &mut Option<u32>| -> Result<(), String> {
        let checkpoint = trainer.checkpoint(run_config.clone());
        if let Some(problem) = checkpoint.non_finite() {
            return Err(format!(
                "training diverged by step {}: the model's {problem}; stopped without saving \
                 it: {}",
                trainer.step,
                kept(*saved_step)
            ));
        }
        checkpoint
            .save(&folder.checkpoint_path())
            .map_err(|e| e.to_string())?;
        *saved_step = Some(trainer.step);
        Ok(())
    };

    while !limits.reached(trainer) && !stop.load(Ordering::SeqCst) {
        let before = trainer.train_seconds;
        let stats = trainer.step();
        if !stats.loss.is_finite() {
            return Err(format!(
                "training diverged at step {}: the loss is {}; stopped: {}",
                trainer.step - 1,
                stats.loss,
                kept(saved_step)
            ));
        }
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
                proposal_samples_per_ray: stats.proposal_samples_per_ray(),
                proposal_loss: (stats.proposal_samples > 0).then_some(stats.proposal_loss),
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
        let elapsed = wall_start.elapsed().as_secs_f64();
        if elapsed >= next_checkpoint {
            save(trainer, &mut saved_step)?;
            next_checkpoint = elapsed + schedule.checkpoint_every_seconds;
        }
    }
    save(trainer, &mut saved_step)?;
    Ok(psnr)
}

/// Loads a run's checkpoint for `model` (the run's model, freshly built):
/// the file's tensors are matched against the model's before any is
/// decoded, and its trainer's step is checked to be one.
pub fn load_checkpoint(
    folder: &RunFolder,
    model: &dyn crate::model::RadianceModel,
) -> Result<Checkpoint, String> {
    let path = folder.checkpoint_path();
    let checkpoint =
        Checkpoint::load_for(&path, &tensors_needed(model)).map_err(|e| e.to_string())?;
    checked_step(&checkpoint.header).map_err(|e| format!("{}: {e}", path.display()))?;
    Ok(checkpoint)
}

/// What `model` holds, by tensor name and length: its own checkpoint's
/// table (the values themselves are dropped at once), which a checkpoint
/// file must match before any of its tensors is decoded.
pub fn tensors_needed(model: &dyn crate::model::RadianceModel) -> Vec<(String, usize)> {
    model
        .save()
        .tensors
        .into_iter()
        .map(|(name, values)| (name, values.len()))
        .collect()
}

/// The step a checkpoint's header records (`trainer.step`), or what is
/// wrong with it, naming the field: a step is a whole number from 0 to
/// 4294967295 (zrak counts steps in 32 bits).
pub fn checked_step(header: &serde_json::Value) -> Result<u32, String> {
    let field = &header["trainer"]["step"];
    let problem = match field {
        serde_json::Value::Null => "is missing".to_string(),
        serde_json::Value::Number(n) => match (n.as_u64(), n.as_i64()) {
            (Some(step), _) => match u32::try_from(step) {
                Ok(step) => return Ok(step),
                Err(_) => format!("is {step}, more than the {} steps zrak counts", u32::MAX),
            },
            (None, Some(negative)) => format!("is {negative}, and a step count cannot be negative"),
            _ => format!("is {n}, not a whole number of steps"),
        },
        other => format!("is {other}, not a number of steps"),
    };
    Err(format!(
        "the checkpoint's `trainer.step` {problem}: the file was not written by zrak as it is \
         (edited or damaged); restore a copy of it, or train the run again"
    ))
}

/// Whether `path` is a `run.json` zrak wrote: a small regular file whose
/// JSON object has [`RUN_JSON_MARKER`]. Anything else (missing, a pipe,
/// too large, another program's JSON) is not.
pub fn is_zrak_run_json(path: &Path) -> bool {
    crate::files::read_regular_bounded(path, MAX_RUN_JSON_BYTES, "a run's settings")
        .ok()
        .and_then(|bytes| serde_json::from_slice::<serde_json::Value>(&bytes).ok())
        .is_some_and(|json| json[RUN_JSON_MARKER].is_string())
}

/// Why `dir` (where `found` is) cannot be a new run's folder, if it
/// cannot: see [`RunFolder::check_out`].
fn refusal_of_out(dir: &Path, found: &OutFolder, replace: bool) -> Option<RunFolderError> {
    let shown = dir.display();
    let message = match found {
        OutFolder::Free => return None,
        OutFolder::NotAFolder(what) if what == "a file" => format!(
            "{shown} is a file, not a folder: --out names the folder a run is written to; \
                 give the name of a new folder (the file is left as it is)"
        ),
        OutFolder::NotAFolder(what) => format!(
            "{shown} cannot be the run folder: it is {what}; remove it or give --out \
                 another folder"
        ),
        _ if replace => return None,
        OutFolder::Run {
            has_checkpoint: true,
        } => format!(
            "{shown} already holds a run{}: give --resume {shown} to continue it, or \
                 --force to move it aside (renamed, nothing deleted) and start a new run there",
            describe_run(dir),
        ),
        OutFolder::Run {
            has_checkpoint: false,
        } => format!(
            "{shown} already holds a run that stopped before its first checkpoint (its \
                 {CONFIG_FILE}, no {CHECKPOINT_FILE}): give --force to move it aside (renamed, \
                 nothing deleted) and start a new run there, or give --out another folder"
        ),
        OutFolder::Other { names, count } => format!(
            "{shown} is not empty and holds no zrak run ({}{}): give --out a new or empty \
                 folder, or --force to move {shown} aside (renamed, nothing deleted) and start \
                 the run in a new {shown}",
            names.join(", "),
            if *count > names.len() {
                format!(" and {} more", count - names.len())
            } else {
                String::new()
            }
        ),
    };
    Some(match found {
        OutFolder::Run { .. } | OutFolder::Other { .. } => RunFolderError::Occupied {
            path: dir.to_path_buf(),
            found: found.clone(),
            message,
        },
        _ => RunFolderError::unusable(dir, message),
    })
}

/// What the run in `dir` is, from its checkpoint's header, as " (step N,
/// MODEL on SCENE)", or nothing when that cannot be read.
fn describe_run(dir: &Path) -> String {
    let Ok(checkpoint) = Checkpoint::load_header(&dir.join(CHECKPOINT_FILE)) else {
        return String::new();
    };
    let step = checkpoint["trainer"]["step"].as_u64();
    let model = checkpoint["run"]["model"].as_str();
    let scene = checkpoint["trainer"]["scene"]["name"].as_str();
    match (step, model, scene) {
        (Some(step), Some(model), Some(scene)) => format!(" (step {step}, {model} on {scene})"),
        (Some(step), _, _) => format!(" (step {step})"),
        _ => String::new(),
    }
}

/// `DIR.old`, else `DIR.old-2`, `DIR.old-3`, …: the first name beside
/// `dir` that nothing has.
fn free_name_beside(dir: &Path) -> Result<PathBuf, String> {
    let name = dir
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .ok_or_else(|| {
            format!(
                "{}: give the run folder by name to move it aside",
                dir.display()
            )
        })?;
    (1..10_000)
        .map(|n| {
            dir.with_file_name(if n == 1 {
                format!("{name}.old")
            } else {
                format!("{name}.old-{n}")
            })
        })
        .find(|candidate| !crate::files::exists_at_all(candidate))
        .ok_or_else(|| {
            format!(
                "{}: no free name to move the old run aside to",
                dir.display()
            )
        })
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use super::*;
    use crate::model::batch::RayBatch;
    use crate::model::{RadianceModel, RenderedPixel};
    use crate::scene::demo::{DemoConfig, build};

    /// A model whose loss (or whose parameters) turns NaN from a given step.
    struct Diverging {
        params: Vec<f32>,
        nan_loss_from: u32,
        nan_params_from: u32,
    }

    impl RadianceModel for Diverging {
        fn describe(&self) -> String {
            "diverging".into()
        }
        fn rays_for_next_batch(&self) -> usize {
            4
        }
        fn step(&mut self, batch: &RayBatch, step: u32) -> StepStats {
            if step >= self.nan_params_from {
                self.params[1] = f32::NAN;
            }
            StepStats {
                loss: if step >= self.nan_loss_from {
                    f32::NAN
                } else {
                    0.5
                },
                rays: batch.len(),
                samples: batch.len(),
                ..StepStats::default()
            }
        }
        fn render(&self, rays: crate::model::RenderRays, out: &mut [RenderedPixel]) {
            for pixel in out {
                pixel.rgb = rays.background;
            }
        }
        fn save(&self) -> Checkpoint {
            Checkpoint {
                header: serde_json::json!({}),
                tensors: vec![("params".into(), self.params.clone())],
            }
        }
        fn load(&mut self, checkpoint: &Checkpoint) -> Result<(), String> {
            self.params = checkpoint.tensor("params").ok_or("no params")?.to_vec();
            Ok(())
        }
        fn memory_bytes(&self) -> usize {
            0
        }
    }

    fn trainer(nan_loss_from: u32, nan_params_from: u32) -> Trainer {
        let scene = Arc::new(build(&DemoConfig {
            size: 8,
            train_views: 2,
            val_views: 1,
            test_views: 1,
        }));
        let model = Diverging {
            params: vec![1.0, 2.0, 3.0],
            nan_loss_from,
            nan_params_from,
        };
        Trainer::new(Box::new(model), scene, 0)
    }

    fn train_to(trainer: &mut Trainer, steps: u32, folder: &RunFolder) -> Result<(), String> {
        run(
            trainer,
            Limits {
                steps: Some(steps),
                seconds: None,
            },
            Schedule::default(),
            folder,
            &serde_json::json!({}),
            &AtomicBool::new(false),
            |_| {},
        )
        .map(|_| ())
    }

    #[test]
    fn a_non_finite_loss_stops_training_and_keeps_the_last_good_checkpoint() {
        let dir = tempfile::tempdir().unwrap();
        let folder = RunFolder::create(dir.path()).unwrap();
        let mut trainer = trainer(5, u32::MAX);
        train_to(&mut trainer, 3, &folder).unwrap();
        let error = train_to(&mut trainer, 10, &folder).unwrap_err();
        assert!(
            error.contains("diverged at step 5")
                && error.contains("the loss is NaN")
                && error.contains("last good checkpoint")
                && error.contains("step 3"),
            "{error}"
        );
        let kept = Checkpoint::load(&folder.checkpoint_path()).unwrap();
        assert_eq!(kept.header["trainer"]["step"], 3);
    }

    #[test]
    fn non_finite_parameters_are_never_saved() {
        let dir = tempfile::tempdir().unwrap();
        let folder = RunFolder::create(dir.path()).unwrap();
        let mut trainer = trainer(u32::MAX, 4);
        train_to(&mut trainer, 2, &folder).unwrap();
        let error = train_to(&mut trainer, 6, &folder).unwrap_err();
        assert!(
            error.contains("diverged by step 6")
                && error.contains("tensor `params` holds NaN at index 1")
                && error.contains("step 2"),
            "{error}"
        );
        let kept = Checkpoint::load(&folder.checkpoint_path()).unwrap();
        assert_eq!(kept.header["trainer"]["step"], 2);
    }

    #[test]
    fn resuming_says_what_is_missing_by_kind() {
        let dir = tempfile::tempdir().unwrap();
        let gone = dir.path().join("gone");
        let error = RunFolder::resume(&gone).err().unwrap();
        assert_eq!(
            error,
            RunFolderError::NotFound {
                path: gone.clone(),
                problem: "folder not found".into()
            }
        );
        assert_eq!(
            error.to_string(),
            format!("{}: no such run folder (folder not found)", gone.display())
        );
        let error = RunFolder::resume(dir.path()).err().unwrap();
        assert_eq!(
            error.to_string(),
            format!(
                "{}: no checkpoint to resume from (no checkpoint.zrak in the folder)",
                dir.path().display()
            )
        );
        assert_eq!(
            error,
            RunFolderError::NoCheckpoint {
                path: dir.path().to_path_buf(),
                file: CHECKPOINT_FILE,
            }
        );
        // No lock file is made in a folder that is no run.
        assert!(!crate::files::exists_at_all(
            &dir.path().join(super::super::lock::LOCK_FILE)
        ));
        std::fs::create_dir(dir.path().join(CHECKPOINT_FILE)).unwrap();
        let error = RunFolder::resume(dir.path()).err().unwrap();
        assert!(
            matches!(error, RunFolderError::Unusable { .. }),
            "{error:?}"
        );
        assert!(
            error
                .to_string()
                .ends_with("checkpoint.zrak: cannot resume from it: a folder, not a file"),
            "{error}"
        );
    }

    #[test]
    fn a_folder_holding_a_run_is_refused_or_moved_aside_never_deleted() {
        let dir = tempfile::tempdir().unwrap();
        let run_dir = dir.path().join("run");
        let folder = RunFolder::create(&run_dir).unwrap();
        train_to(&mut trainer(u32::MAX, u32::MAX), 2, &folder).unwrap();
        // Held by `folder` (this process): even --force must not move it.
        let error = RunFolder::create_new(&run_dir, true).err().unwrap();
        assert!(matches!(error, RunFolderError::Locked { .. }), "{error:?}");
        assert!(
            error.to_string().contains("is using this run folder"),
            "{error}"
        );
        drop(folder);
        let error = RunFolder::create_new(&run_dir, false).err().unwrap();
        assert!(
            matches!(
                error,
                RunFolderError::Occupied {
                    found: OutFolder::Run {
                        has_checkpoint: true
                    },
                    ..
                }
            ),
            "{error:?}"
        );
        let error = error.to_string();
        assert!(
            error.contains("already holds a run (step 2)")
                && error.contains("--resume")
                && error.contains("--force"),
            "{error}"
        );
        let (_new, aside) = RunFolder::create_new(&run_dir, true).unwrap();
        let aside = aside.unwrap();
        assert!(aside.was_run);
        let aside = aside.to;
        assert_eq!(aside, dir.path().join("run.old"));
        let kept = Checkpoint::load(&aside.join(CHECKPOINT_FILE)).unwrap();
        assert_eq!(kept.header["trainer"]["step"], 2);
        assert!(!RunFolder::holds_run(&run_dir));
    }
}
