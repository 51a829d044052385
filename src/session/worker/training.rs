//! Training on the worker's thread: steps, the stats sent from them, the
//! held-out evaluation sized to its share, and models trained in turns.

use super::*;

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

impl StatsWindow {
    pub(super) fn add(&mut self, stats: &StepStats, seconds: f64) {
        self.composited = match (self.steps, self.composited, stats.samples_composited) {
            (0, _, now) => now,
            (_, Some(sum), Some(now)) => Some(sum + now),
            _ => None,
        };
        self.steps += 1;
        self.seconds += seconds;
        self.rays += stats.rays;
        self.samples += stats.samples;
        self.loss_times_rays += stats.loss as f64 * stats.rays as f64;
        self.times.add(&stats.times);
    }
}

impl ValJob {
    /// About `pixels` pixels spread evenly over `frames`.
    pub(super) fn new(model: ModelKind, frames: &[Frame], pixels: usize) -> Self {
        let per_view = pixels.div_ceil(frames.len().max(1));
        let mut chosen = Vec::new();
        for (view, frame) in frames.iter().enumerate() {
            let k = frame.camera.intrinsics;
            chosen.extend(
                pixel_grid(k.width, k.height, per_view)
                    .into_iter()
                    .map(|(x, y)| (view, x, y)),
            );
        }
        Self {
            model,
            pixels: chosen,
            done: 0,
            squared: vec![0.0; frames.len()],
            counts: vec![0; frames.len()],
            seconds: 0.0,
        }
    }

    pub(super) fn is_done(&self) -> bool {
        self.done >= self.pixels.len()
    }

    /// Renders and scores up to `max_rays` more pixels.
    pub(super) fn render_chunk(
        &mut self,
        model: &dyn RadianceModel,
        frames: &[Frame],
        max_rays: usize,
    ) {
        let end = (self.done + max_rays.max(1)).min(self.pixels.len());
        let chunk = &self.pixels[self.done..end];
        let rays: Vec<_> = chunk
            .iter()
            .map(|&(view, x, y)| frames[view].camera.pixel_ray(x, y))
            .collect();
        let mut out = vec![RenderedPixel::default(); chunk.len()];
        model.render(RayColumns::of(&rays).over(WHITE), &mut out);
        for (&(view, x, y), pixel) in chunk.iter().zip(&out) {
            let truth = frames[view].image.rgb_over(x, y, WHITE);
            self.squared[view] += pixel
                .rgb
                .iter()
                .zip(&truth)
                .map(|(&p, &t)| ((p - t) as f64).powi(2))
                .sum::<f64>();
            self.counts[view] += 1;
        }
        self.done = end;
    }

    /// The mean over views of each view's PSNR.
    pub(super) fn mean_psnr(&self) -> f64 {
        let scored: Vec<f64> = self
            .squared
            .iter()
            .zip(&self.counts)
            .filter(|&(_, &n)| n > 0)
            .map(|(&squared, &n)| psnr_from_mse(squared / (3 * n) as f64))
            .collect();
        if scored.is_empty() {
            return f64::NAN;
        }
        scored.iter().sum::<f64>() / scored.len() as f64
    }
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

impl Worker {
    /// Starts or stops the models' taking turns. Models that cannot be
    /// built are left out (and reported); fewer than two leave the active
    /// model training alone.
    pub(super) fn set_turns(&mut self, settings: Option<InTurn>) -> Result<(), UiGone> {
        self.flush_stats(self.trainee())?;
        self.val_job = None;
        self.turns = None;
        if let Some(settings) = settings {
            let mut models = Vec::new();
            for &kind in &settings.models {
                self.ensure_slot(kind)?;
                if self.slot(kind).is_some() && !models.contains(&kind) {
                    models.push(kind);
                }
            }
            if models.len() >= 2 {
                self.turns = Some(Turns::new(
                    &InTurn {
                        models,
                        slice_seconds: settings.slice_seconds,
                    },
                    |kind| self.trained_seconds(kind),
                ));
            } else {
                self.send(Event::Error(
                    "taking turns needs at least two models that can be built".into(),
                ))?;
            }
        }
        self.send(Event::InTurn(self.turns.as_ref().map(Turns::settings)))
    }

    /// Training seconds of `kind`'s model (0 when it has none).
    pub(super) fn trained_seconds(&self, kind: ModelKind) -> f64 {
        self.slot(kind).map_or(0.0, |s| s.trainer.train_seconds)
    }

    /// Starts the turns afresh after a model was reset or loaded, so that
    /// its new training time does not count as a share it had or owes.
    pub(super) fn rebase_turns(&mut self) {
        if let Some(turns) = &self.turns {
            let settings = turns.settings();
            self.turns = Some(Turns::new(&settings, |kind| self.trained_seconds(kind)));
        }
    }

    /// Moves the turns on if the current model has had its slice, sending
    /// the stats of the model whose turn ended.
    pub(super) fn take_turn(&mut self) -> Result<(), UiGone> {
        let slots = &self.slots;
        let Some(turns) = self.turns.as_mut() else {
            return Ok(());
        };
        let before = turns.current();
        let now = turns.model_to_train(|kind| {
            slots
                .iter()
                .find(|s| s.kind == kind)
                .map_or(0.0, |s| s.trainer.train_seconds)
        });
        if now != before {
            self.flush_stats(before)?;
        }
        Ok(())
    }

    pub(super) fn train_unit(&mut self) -> Result<(), UiGone> {
        self.train_step(false)
    }

    /// One step of the model that trains (the active one, or the one whose
    /// turn it is); `report` sends its stats at once.
    pub(super) fn train_step(&mut self, report: bool) -> Result<(), UiGone> {
        self.take_turn()?;
        let revision = self.revision();
        let every = self.options.val_every_train_seconds;
        let active = self.trainee();
        let Some(slot) = self.slots.iter_mut().find(|s| s.kind == active) else {
            return Ok(());
        };
        let started = Instant::now();
        let before = slot.trainer.train_seconds;
        let stats = slot.trainer.step();
        slot.window.add(&stats, slot.trainer.train_seconds - before);
        if stats.rays > 0 {
            slot.cost.follow_march(f64::from(stats.samples_per_ray()));
            slot.eval_cost
                .follow_march(f64::from(stats.samples_per_ray()));
        }
        slot.revision = revision;
        if slot.trainer.train_seconds >= slot.next_val_at
            && !self.val_frames.is_empty()
            && self.val_job.is_none()
        {
            slot.next_val_at = slot.trainer.train_seconds + every;
            // As many pixels as fit in the evaluation's share of the
            // training time until the next one, at this model's cost.
            let all: usize = self
                .val_frames
                .iter()
                .map(|f| f.camera.intrinsics.width as usize * f.camera.intrinsics.height as usize)
                .sum();
            let cost = slot
                .eval_cost
                .seconds_per_pixel()
                .or(slot.cost.seconds_per_pixel());
            let pixels = cost.map_or(MIN_EVAL_PIXELS, |cost| (EVAL_SHARE * every / cost) as usize);
            let pixels = pixels.clamp(MIN_EVAL_PIXELS.min(all), all.max(1));
            self.val_job = Some(ValJob::new(active, &self.val_frames, pixels));
        }
        let seconds = started.elapsed().as_secs_f64();
        self.last_step = Some((Instant::now(), seconds));
        if self.view.as_ref().is_none_or(|v| !v.moving()) {
            self.ledger.record_training(seconds);
        }
        self.trace.training_seconds += seconds;
        self.trace.grid_update_seconds += stats.times[Stage::GridUpdate];
        self.trace.steps += 1;
        let due = slot
            .last_stats
            .is_none_or(|sent| sent.elapsed() >= STATS_INTERVAL);
        if report || due {
            self.flush_stats(active)?;
        }
        Ok(())
    }

    /// Sends the stats of the steps since the last report, if any.
    pub(super) fn flush_stats(&mut self, kind: ModelKind) -> Result<(), UiGone> {
        let Some(slot) = self.slots.iter_mut().find(|s| s.kind == kind) else {
            return Ok(());
        };
        let window = std::mem::take(&mut slot.window);
        if window.steps == 0 {
            // No step since the last report: only a new held-out PSNR is
            // worth sending.
            let (Some(val_psnr), Some(last)) = (slot.pending_val.take(), slot.last_report) else {
                return Ok(());
            };
            let stats = TrainingStats {
                step: slot.trainer.step,
                train_seconds: slot.trainer.train_seconds,
                val_psnr: Some(val_psnr),
                ..last
            };
            return self.outbox.send(Event::Stats(stats));
        }
        slot.last_stats = Some(Instant::now());
        let steps = window.steps as f64;
        let loss = if window.rays > 0 {
            window.loss_times_rays / window.rays as f64
        } else {
            f64::NAN
        };
        // L2 is the mean squared error over rays × channels, so its PSNR is
        // exact; Huber is not an MSE and has no honest PSNR.
        let batch_psnr = match slot.loss {
            LossKind::L2 => Some(psnr_from_mse(loss) as f32),
            LossKind::Huber => None,
        };
        let per = |seconds: f64| seconds / steps;
        let t = window.times;
        let stats = TrainingStats {
            model: kind,
            step: slot.trainer.step,
            train_seconds: slot.trainer.train_seconds,
            loss: loss as f32,
            batch_psnr,
            val_psnr: slot.pending_val.take(),
            ms_per_step: (1000.0 * per(window.seconds)) as f32,
            samples_per_ray: if window.rays > 0 {
                window.samples as f32 / window.rays as f32
            } else {
                0.0
            },
            composited_per_ray: window
                .composited
                .map(|n| n as f32 / window.rays.max(1) as f32),
            samples_per_second: if window.seconds > 0.0 {
                (window.samples as f64 / window.seconds) as f32
            } else {
                0.0
            },
            memory_bytes: slot.trainer.model.memory_bytes(),
            times: StageTimes::from_fn(|stage| per(t[stage])),
        };
        slot.last_report = Some(TrainingStats {
            val_psnr: None,
            ..stats
        });
        self.outbox.send(Event::Stats(stats))
    }

    /// Renders one chunk of the held-out evaluation; reports the mean PSNR
    /// when the last pixel is scored.
    pub(super) fn evaluate_unit(&mut self) -> Result<(), UiGone> {
        let Some(job) = self.val_job.as_mut() else {
            return Ok(());
        };
        let Some(slot) = self.slots.iter_mut().find(|s| s.kind == job.model) else {
            self.val_job = None;
            return Ok(());
        };
        let started = Instant::now();
        let before = job.done;
        job.render_chunk(
            slot.trainer.model.as_ref(),
            &self.val_frames,
            slot.pacer.chunk_rays(),
        );
        let seconds = started.elapsed().as_secs_f64();
        slot.pacer.record(job.done - before, seconds);
        job.seconds += seconds;
        // Evaluation is the view's kind of work in the balance.
        if self.view.as_ref().is_none_or(|v| !v.moving()) {
            self.ledger.record_other(seconds);
        }
        self.trace.evaluation_seconds += seconds;
        if !job.is_done() {
            return Ok(());
        }
        self.trace.evaluations += 1;
        slot.eval_cost.record(job.pixels.len(), job.seconds);
        slot.pending_val = Some(job.mean_psnr() as f32);
        let kind = job.model;
        self.val_job = None;
        self.flush_stats(kind)
    }
}
