//! The models the thread trains: a slot per model built (its trainer, the
//! steps not yet reported, what its pixels cost), which of them trains
//! (the active one, or the one whose turn it is), and the turns.

use std::collections::VecDeque;
use std::time::{Duration, Instant};

use crate::field::ModelKind;
use crate::field::common::LossKind;
use crate::metrics::psnr_from_mse;
use crate::model::{StageTimes, StepStats};
use crate::scene::Frame;
use crate::session::progressive::ChunkPacer;
use crate::session::protocol::{InTurn, TrainingStats};
use crate::session::schedule::{EVAL_SHARE, MIN_EVAL_PIXELS, RenderCost};
use crate::train::trainer::Trainer;

/// How long one chunk of rays should take: well under the ~100 ms a command
/// may wait.
const CHUNK_TARGET: Duration = Duration::from_millis(40);

/// Stats go out at most this often (ten times a second), aggregated over
/// the steps in between.
const STATS_INTERVAL: Duration = Duration::from_millis(100);

/// The speed figures (ms/step, samples/s) are medians over the steps of
/// this many of the last training seconds: a report covers a step or two
/// (a step of the viewer's cpu batch takes ~0.2 s), so a mean over it
/// showed the one step that also updated the occupancy grid at four times
/// the others' time.
const RECENT_TRAINING_SECONDS: f64 = 5.0;

/// The speed figures keep at least this many steps, however long they
/// took, so one long step is outvoted even when steps are slow.
const MIN_RECENT_STEPS: usize = 5;

/// At most this many steps are kept (fast gpu steps take a millisecond).
const MAX_RECENT_STEPS: usize = 1024;

/// While the camera moves, training gets at most 1/(1 + this) of wall time:
/// after a step of d seconds, the next waits d × this. A step cannot be
/// interrupted, so a coarse frame may wait behind one (tens of ms with the
/// viewer's cpu batch); waiting instead for a pause between requests would
/// stop training for as long as the user drags.
const MOVING_IDLE_PER_STEP: f64 = 3.0;

/// Models trained in turn at equal shares of training time.
///
/// Each model trains until it has had one more slice than it had finished
/// turns since the turns began, then the next model in order takes over.
/// A step cannot be cut short, so a turn runs a little past its slice; the
/// next turn's end is counted from the turns' start, not from where that
/// turn ended, so the overshoot never adds up: every model's training
/// time stays within one slice and one step of every other's.
#[derive(Debug, Clone)]
pub struct Turns {
    models: Vec<ModelKind>,
    slice_seconds: f64,
    /// Each model's training seconds when the turns began.
    base: Vec<f64>,
    /// Turns each model has finished.
    finished: Vec<u32>,
    current: usize,
}

impl Turns {
    /// Turns among `settings.models` (at least one), starting with the
    /// first; `trained` gives a model's training seconds so far.
    pub fn new(settings: &InTurn, trained: impl Fn(ModelKind) -> f64) -> Self {
        Self {
            base: settings.models.iter().map(|&m| trained(m)).collect(),
            finished: vec![0; settings.models.len()],
            models: settings.models.clone(),
            slice_seconds: settings.slice_seconds.max(1e-3),
            current: 0,
        }
    }

    pub fn settings(&self) -> InTurn {
        InTurn {
            models: self.models.clone(),
            slice_seconds: self.slice_seconds,
        }
    }

    /// The model whose turn it is.
    pub fn current(&self) -> ModelKind {
        self.models[self.current]
    }

    /// The model to train next, moving on to the next model when the
    /// current one has had its slice; `trained` gives a model's training
    /// seconds so far.
    pub fn model_to_train(&mut self, trained: impl Fn(ModelKind) -> f64) -> ModelKind {
        // Bounded: after a round every model has a slice left to train.
        for _ in 0..self.models.len() {
            let i = self.current;
            let since = trained(self.models[i]) - self.base[i];
            if since < f64::from(self.finished[i] + 1) * self.slice_seconds {
                break;
            }
            self.finished[i] += 1;
            self.current = (i + 1) % self.models.len();
        }
        self.current()
    }
}

/// A step of [`RecentSteps`].
#[derive(Debug, Clone, Copy, PartialEq)]
struct RecentStep {
    /// The model's training seconds when the step ended.
    ended_at: f64,
    seconds: f64,
    samples: usize,
}

/// Training speed a report shows: medians over the last training seconds.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) struct StepRate {
    /// The median step time, in milliseconds.
    pub(super) ms_per_step: f64,
    /// The steps' mean samples per step over the median step time.
    pub(super) samples_per_second: f64,
}

/// A model's steps of the last [`RECENT_TRAINING_SECONDS`] training
/// seconds. Measured on the training clock (each step's own time), so
/// time the thread spends not training (paused, rendering, waiting for
/// commands) neither counts in a step nor ages the steps kept.
#[derive(Debug, Default)]
pub(super) struct RecentSteps {
    steps: VecDeque<RecentStep>,
}

impl RecentSteps {
    /// A step of `seconds` that trained `samples` and ended at `ended_at`
    /// training seconds.
    pub(super) fn add(&mut self, ended_at: f64, seconds: f64, samples: usize) {
        if self
            .steps
            .back()
            .is_some_and(|last| ended_at < last.ended_at)
        {
            // The training clock went back (a checkpoint was loaded): the
            // steps kept were another model's.
            self.steps.clear();
        }
        self.steps.push_back(RecentStep {
            ended_at,
            seconds,
            samples,
        });
        while self.steps.len() > MAX_RECENT_STEPS
            || (self.steps.len() > MIN_RECENT_STEPS
                && self.steps[0].ended_at < ended_at - RECENT_TRAINING_SECONDS)
        {
            self.steps.pop_front();
        }
    }

    /// The median step time and the samples per second it gives; `None`
    /// before any step.
    pub(super) fn rate(&self) -> Option<StepRate> {
        if self.steps.is_empty() {
            return None;
        }
        let mut seconds: Vec<f64> = self.steps.iter().map(|s| s.seconds).collect();
        seconds.sort_by(f64::total_cmp);
        let n = seconds.len();
        let median = if n % 2 == 1 {
            seconds[n / 2]
        } else {
            0.5 * (seconds[n / 2 - 1] + seconds[n / 2])
        };
        let samples_per_step = self.steps.iter().map(|s| s.samples as f64).sum::<f64>() / n as f64;
        Some(StepRate {
            ms_per_step: 1000.0 * median,
            samples_per_second: if median > 0.0 {
                samples_per_step / median
            } else {
                0.0
            },
        })
    }
}

/// Steps since the last stats event, to be reported as one.
#[derive(Debug, Default)]
pub(super) struct StatsWindow {
    steps: u32,
    rays: usize,
    samples: usize,
    /// Samples before the rays' cuts, while every step of the window
    /// reported them.
    composited: Option<usize>,
    /// Σ loss × rays, so the mean is over every ray of the window.
    loss_times_rays: f64,
    times: StageTimes,
}

impl StatsWindow {
    /// Adds a step.
    pub(super) fn add(&mut self, stats: &StepStats) {
        self.composited = match (self.steps, self.composited, stats.samples_composited) {
            (0, _, now) => now,
            (_, Some(sum), Some(now)) => Some(sum + now),
            _ => None,
        };
        self.steps += 1;
        self.rays += stats.rays;
        self.samples += stats.samples;
        self.loss_times_rays += stats.loss as f64 * stats.rays as f64;
        self.times.add(&stats.times);
    }

    /// The window's steps as one report of `model` (trained with `loss`,
    /// now at `step` after `train_seconds`, holding `memory_bytes`, training
    /// at `rate`), without a held-out PSNR; `None` when it holds no step.
    pub(super) fn stats(
        &self,
        model: ModelKind,
        loss: LossKind,
        step: u32,
        train_seconds: f64,
        memory_bytes: usize,
        rate: StepRate,
    ) -> Option<TrainingStats> {
        if self.steps == 0 {
            return None;
        }
        let steps = self.steps as f64;
        let mean_loss = if self.rays > 0 {
            self.loss_times_rays / self.rays as f64
        } else {
            f64::NAN
        };
        // L2 is the mean squared error over rays × channels, so its PSNR is
        // exact; Huber is not an MSE and has no honest PSNR.
        let batch_psnr = match loss {
            LossKind::L2 => Some(psnr_from_mse(mean_loss) as f32),
            LossKind::Huber => None,
        };
        let per = |seconds: f64| seconds / steps;
        let t = self.times;
        Some(TrainingStats {
            model,
            step,
            train_seconds,
            loss: mean_loss as f32,
            batch_psnr,
            val_psnr: None,
            ms_per_step: rate.ms_per_step as f32,
            samples_per_ray: if self.rays > 0 {
                self.samples as f32 / self.rays as f32
            } else {
                0.0
            },
            composited_per_ray: self.composited.map(|n| n as f32 / self.rays.max(1) as f32),
            samples_per_second: rate.samples_per_second as f32,
            memory_bytes,
            times: StageTimes::from_fn(|stage| per(t[stage])),
        })
    }
}

/// One model's training on the current scene.
pub(super) struct ModelSlot {
    pub(super) kind: ModelKind,
    pub(super) trainer: Trainer,
    /// The loss the model trains with (a loaded checkpoint brings its own).
    pub(super) loss: LossKind,
    window: StatsWindow,
    /// The steps the speed figures are medians over.
    recent: RecentSteps,
    last_stats: Option<Instant>,
    /// Training seconds at which the next held-out evaluation is due.
    next_val_at: f64,
    /// A held-out PSNR not yet reported.
    pending_val: Option<f32>,
    /// The last stats sent, re-sent with a held-out PSNR that completes
    /// when no step was taken since.
    last_report: Option<TrainingStats>,
    /// Changes whenever the field does (step, reset, load), so the view
    /// knows when what it shows is out of date.
    pub(super) revision: u64,
    /// The step last saved or loaded (0 for a fresh model): a model past
    /// it has training that only memory holds.
    pub(super) saved_step: u32,
    /// Sizes the chunks of rays this model renders (its rays cost their
    /// own: a NeRF ray ~50 of Instant-NGP's).
    pub(super) pacer: ChunkPacer,
    /// What a pixel of this model costs to render, over whole levels.
    pub(super) cost: RenderCost,
    /// What a pixel of the held-out evaluation costs: its views frame the
    /// scene as the training views do, so more of their pixels cross it
    /// than a viewport's.
    pub(super) eval_cost: RenderCost,
}

impl ModelSlot {
    /// One training step; returns its stats.
    fn step(&mut self, revision: u64) -> StepStats {
        let before = self.trainer.train_seconds;
        let stats = self.trainer.step();
        self.window.add(&stats);
        let ended_at = self.trainer.train_seconds;
        self.recent.add(ended_at, ended_at - before, stats.samples);
        if stats.rays > 0 {
            self.cost.follow_march(f64::from(stats.samples_per_ray()));
            self.eval_cost
                .follow_march(f64::from(stats.samples_per_ray()));
        }
        self.revision = revision;
        stats
    }

    /// Whether the stats of the steps since the last report are due.
    fn report_due(&self) -> bool {
        self.last_stats
            .is_none_or(|sent| sent.elapsed() >= STATS_INTERVAL)
    }

    /// The pixels of the held-out evaluation due now, if one is: as many as
    /// fit in the evaluation's share of the training time until the next
    /// one (`every` training seconds), at this model's cost. Counts the
    /// next one from here.
    fn evaluation_due(&mut self, frames: &[Frame], every: f64) -> Option<usize> {
        if self.trainer.train_seconds < self.next_val_at || frames.is_empty() {
            return None;
        }
        self.next_val_at = self.trainer.train_seconds + every;
        let all: usize = frames
            .iter()
            .map(|f| f.camera.intrinsics.width as usize * f.camera.intrinsics.height as usize)
            .sum();
        let cost = self
            .eval_cost
            .seconds_per_pixel()
            .or(self.cost.seconds_per_pixel());
        let pixels = cost.map_or(MIN_EVAL_PIXELS, |cost| (EVAL_SHARE * every / cost) as usize);
        Some(pixels.clamp(MIN_EVAL_PIXELS.min(all), all.max(1)))
    }

    /// A finished held-out evaluation: `psnr` over `pixels` pixels that
    /// took `seconds`; reported with the next stats.
    pub(super) fn evaluated(&mut self, psnr: f32, pixels: usize, seconds: f64) {
        self.eval_cost.record(pixels, seconds);
        self.pending_val = Some(psnr);
    }

    /// The stats of the steps since the last report, with a held-out PSNR
    /// not yet reported; with no step since, only a new held-out PSNR is
    /// worth sending (on the last report's figures).
    pub(super) fn take_report(&mut self) -> Option<TrainingStats> {
        let window = std::mem::take(&mut self.window);
        let trainer = &self.trainer;
        let stats = self.recent.rate().and_then(|rate| {
            window.stats(
                self.kind,
                self.loss,
                trainer.step,
                trainer.train_seconds,
                trainer.model.memory_bytes(),
                rate,
            )
        });
        let Some(stats) = stats else {
            let (Some(val_psnr), Some(last)) = (self.pending_val.take(), self.last_report) else {
                return None;
            };
            return Some(TrainingStats {
                step: self.trainer.step,
                train_seconds: self.trainer.train_seconds,
                val_psnr: Some(val_psnr),
                ..last
            });
        };
        self.last_stats = Some(Instant::now());
        self.last_report = Some(stats);
        Some(TrainingStats {
            val_psnr: self.pending_val.take(),
            ..stats
        })
    }
}

/// What a training step did, for the worker's accounts.
pub(super) struct StepDone {
    pub(super) model: ModelKind,
    pub(super) stats: StepStats,
    /// The held-out evaluation due after it, in pixels.
    pub(super) evaluation_pixels: Option<usize>,
    /// Its stats are due to be reported.
    pub(super) report_due: bool,
}

/// The models built on the current scene and which of them trains.
pub(super) struct Training {
    slots: Vec<ModelSlot>,
    /// The model shown, and trained when the models take no turns.
    pub(super) active: ModelKind,
    /// When set, the models take turns at training instead of the active
    /// model training alone.
    turns: Option<Turns>,
    pub(super) running: bool,
    /// When the last training step ended and how long it took, to keep
    /// training light while the camera moves.
    last_step: Option<(Instant, f64)>,
    next_revision: u64,
}

impl Training {
    pub(super) fn new(active: ModelKind) -> Self {
        Self {
            slots: Vec::new(),
            active,
            turns: None,
            running: false,
            last_step: None,
            next_revision: 0,
        }
    }

    pub(super) fn slots(&self) -> &[ModelSlot] {
        &self.slots
    }

    pub(super) fn slots_mut(&mut self) -> &mut [ModelSlot] {
        &mut self.slots
    }

    pub(super) fn slot(&self, kind: ModelKind) -> Option<&ModelSlot> {
        self.slots.iter().find(|s| s.kind == kind)
    }

    pub(super) fn slot_mut(&mut self, kind: ModelKind) -> Option<&mut ModelSlot> {
        self.slots.iter_mut().find(|s| s.kind == kind)
    }

    /// The active model's slot.
    pub(super) fn shown(&self) -> Option<&ModelSlot> {
        self.slot(self.active)
    }

    pub(super) fn shown_mut(&mut self) -> Option<&mut ModelSlot> {
        self.slot_mut(self.active)
    }

    /// The model that trains: the one whose turn it is, else the active one.
    pub(super) fn trainee(&self) -> ModelKind {
        self.turns.as_ref().map_or(self.active, Turns::current)
    }

    /// Whether training runs and its model was built.
    pub(super) fn can_train(&self) -> bool {
        self.running && self.slot(self.trainee()).is_some()
    }

    pub(super) fn turns(&self) -> Option<InTurn> {
        self.turns.as_ref().map(Turns::settings)
    }

    fn revision(&mut self) -> u64 {
        self.next_revision += 1;
        self.next_revision
    }

    /// A slot for `trainer`, whose first held-out evaluation is due after
    /// `val_every` training seconds.
    pub(super) fn new_slot(
        &mut self,
        kind: ModelKind,
        trainer: Trainer,
        loss: LossKind,
        val_every: f64,
    ) -> ModelSlot {
        let saved_step = trainer.step;
        ModelSlot {
            kind,
            next_val_at: trainer.train_seconds + val_every,
            trainer,
            loss,
            window: StatsWindow::default(),
            recent: RecentSteps::default(),
            last_stats: None,
            pending_val: None,
            last_report: None,
            revision: self.revision(),
            saved_step,
            pacer: ChunkPacer::new(CHUNK_TARGET),
            cost: RenderCost::default(),
            eval_cost: RenderCost::default(),
        }
    }

    /// Adds `slot`, replacing the slot of its model if there is one.
    pub(super) fn install(&mut self, slot: ModelSlot) {
        match self.slot_mut(slot.kind) {
            Some(existing) => *existing = slot,
            None => self.slots.push(slot),
        }
    }

    pub(super) fn add(&mut self, slot: ModelSlot) {
        self.slots.push(slot);
    }

    /// Drops every model and the turns among them (another scene was
    /// opened); true when there were turns.
    pub(super) fn clear(&mut self) -> bool {
        self.slots.clear();
        self.turns.take().is_some()
    }

    /// Training seconds of `kind`'s model (0 when it has none).
    pub(super) fn trained_seconds(&self, kind: ModelKind) -> f64 {
        self.slot(kind).map_or(0.0, |s| s.trainer.train_seconds)
    }

    /// Makes `models` take turns of `slice_seconds`, or stops the turns
    /// (`None`).
    pub(super) fn set_turns(&mut self, turns: Option<InTurn>) {
        self.turns = turns.map(|settings| Turns::new(&settings, |kind| self.trained_seconds(kind)));
    }

    /// Starts the turns afresh after a model was reset or loaded, so that
    /// its new training time does not count as a share it had or owes.
    pub(super) fn rebase_turns(&mut self) {
        if let Some(turns) = &self.turns {
            let settings = turns.settings();
            self.turns = Some(Turns::new(&settings, |kind| self.trained_seconds(kind)));
        }
    }

    /// Moves the turns on if the current model has had its slice; returns
    /// the model whose turn ended.
    pub(super) fn pass_turn(&mut self) -> Option<ModelKind> {
        let slots = &self.slots;
        let turns = self.turns.as_mut()?;
        let before = turns.current();
        let now = turns.model_to_train(|kind| {
            slots
                .iter()
                .find(|s| s.kind == kind)
                .map_or(0.0, |s| s.trainer.train_seconds)
        });
        (now != before).then_some(before)
    }

    /// One step of the model that trains, if it was built; `every` is the
    /// training seconds between held-out evaluations, which are due only
    /// when `can_evaluate` (there are views to score and none runs).
    pub(super) fn step(
        &mut self,
        val_frames: &[Frame],
        every: f64,
        can_evaluate: bool,
    ) -> Option<StepDone> {
        let revision = self.revision();
        let model = self.trainee();
        let slot = self.slot_mut(model)?;
        let stats = slot.step(revision);
        let evaluation_pixels = if can_evaluate {
            slot.evaluation_due(val_frames, every)
        } else {
            None
        };
        Some(StepDone {
            model,
            stats,
            evaluation_pixels,
            report_due: slot.report_due(),
        })
    }

    /// The last step ended now and took `seconds`.
    pub(super) fn stepped(&mut self, seconds: f64) {
        self.last_step = Some((Instant::now(), seconds));
    }

    /// How long the next step waits while the camera moves, at `now`: its
    /// part of the wall time is 1/(1 + [`MOVING_IDLE_PER_STEP`]).
    pub(super) fn wait_while_moving(&self, now: Instant) -> Duration {
        self.last_step.map_or(Duration::ZERO, |(ended, seconds)| {
            Duration::from_secs_f64(seconds * MOVING_IDLE_PER_STEP)
                .saturating_sub(now.saturating_duration_since(ended))
        })
    }

    /// Whether a step is due while the camera moves, at `now`.
    pub(super) fn step_due_while_moving(&self, now: Instant) -> bool {
        self.last_step.is_none_or(|(ended, seconds)| {
            now.saturating_duration_since(ended).as_secs_f64() >= seconds * MOVING_IDLE_PER_STEP
        })
    }
}

#[cfg(test)]
#[path = "training_tests.rs"]
mod tests;
