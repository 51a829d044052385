//! The viewer's training thread. It owns the scene and one trainer per
//! model, trains the active model, renders the viewport progressively, and
//! answers the UI's [`Command`]s with [`Event`]s over channels that never
//! block the UI.
//!
//! The loop works in small units (one training step, one chunk of rays or
//! band of rows, one export frame, one chunk of a held-out evaluation) and
//! reads every pending command between units, so a command waits at most
//! one unit. How the units share the time is [`super::schedule`]'s: the
//! first level of a new camera is drawn at once; while the camera rests,
//! training gets its share of the time, the view is refreshed at the finest
//! level whose render fits the budget, and the held-out evaluation takes a
//! small share of its own. Where the time went is sent as
//! [`Event::Schedule`] every second.
//!
//! The thread's state is in parts that own their data: the scene
//! (`scene.rs`), the models and their turns (`training.rs`), the view and
//! its share of the time (`view.rs`), the export and the held-out
//! evaluation (`jobs.rs`, `export_jobs.rs`), and the trace of where the
//! time went (`trace.rs`). `Worker` keeps the channels and routes each
//! command to the parts it concerns; saving and loading checkpoints, which
//! concern most of them, are its own (`saving.rs`).

use std::path::PathBuf;
use std::sync::mpsc::{
    Receiver, RecvTimeoutError, Sender, TryRecvError, {self},
};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use crate::engine::cpu::dense::backend_for;
use crate::engine::gpu::GpuContext;
use crate::engine::request::{ModelRequest, ModelSettings};
use crate::engine::{EngineChoice, EngineKind, build, choose_engine};
use crate::field::common::{LossKind, Sampling};
use crate::field::mlp::Precision;
use crate::field::nerf::NerfShape;
use crate::field::{FieldShape, ModelKind};
use crate::model::{RadianceModel, Stage};
use crate::scene::crop::CropBox;
use crate::scene::demo::{
    DemoConfig, {self},
};
use crate::scene::{Scene, SceneSpace};
use crate::session::protocol::{Command, Event, InTurn, SceneSource};
use crate::train::trainer::Trainer;

mod export_jobs;
mod export_mesh;
mod jobs;
mod saving;
mod scene;
mod trace;
mod training;
mod view;

use export_jobs::ExportOrder;
use jobs::{Evaluation, Jobs};
use scene::{SceneState, load_scene, with_chosen_space};
use trace::Trace;
pub use training::Turns;
use training::{ModelSlot, Training};
use view::Viewing;

pub type RepaintCallback = Box<dyn Fn() + Send>;

/// The viewer's training batch of `kind`, in samples, where the model's
/// recipe would make a step too long to wait behind (its
/// [`crate::field::ViewerBatch`]); `None` keeps the recipe's.
fn viewer_batch_samples(
    kind: ModelKind,
    engine: EngineKind,
    software_gpu: bool,
    sampling: Sampling,
) -> Option<usize> {
    let batch = kind.spec().viewer_batch;
    let paper_sampler = sampling == Sampling::Paper && kind.has_paper_sampler();
    match engine {
        EngineKind::Cpu if paper_sampler => batch.slow.or(batch.cpu),
        EngineKind::Cpu => batch.cpu,
        EngineKind::Gpu if software_gpu => batch.slow,
        EngineKind::Gpu => None,
    }
}

/// How the thread trains and measures; [`Default`] is what the viewer uses.
pub struct WorkerOptions {
    pub seed: u64,
    /// The loss every model trains with; `None` gives each model its own
    /// default ([`ModelKind::default_loss`]).
    pub loss: Option<LossKind>,
    /// Samples per training batch; `None` picks by engine and sampler: the
    /// model's [`crate::field::ViewerBatch`].
    pub batch_samples: Option<usize>,
    /// The sampler asked for: each model that has it trains with it, the
    /// others (and every model with `None`) with the one the scene's space
    /// calls for ([`ModelKind::sampling_for`]).
    pub sampling: Option<Sampling>,
    /// The networks of NeRF and Mip-NeRF; `None` gives each its paper's.
    /// Tests give small ones, so that a software gpu adapter runs them.
    pub nerf_shape: Option<NerfShape>,
    /// How the cpu engine computes the networks' products (f32 unless
    /// asked: the viewer asks for the processor's best).
    pub precision: Precision,
    /// The scene [`SceneSource::Demo`] builds.
    pub demo: DemoConfig,
    /// What every scene opened is treated as (`zrak view --space`);
    /// `None` leaves it to the scene analysis.
    pub space: Option<SceneSpace>,
    /// Per-image appearance and camera refinement for every scene opened
    /// (`zrak view --appearance`, `--refine-cameras`; auto: as each scene's
    /// photographs call for).
    pub photographs: crate::scene::photographs::Switches,
    /// Training seconds between held-out PSNR evaluations, for every
    /// model. Each evaluation scores a grid of pixels spread over the
    /// held-out views, as many as fit in [`EVAL_SHARE`] of this time at
    /// the model's measured render cost (at least [`MIN_EVAL_PIXELS`]), as
    /// `zrak train` sizes its evaluations.
    pub val_every_train_seconds: f64,
    /// Held-out views per evaluation.
    pub val_views: usize,
    pub repaint: Option<RepaintCallback>,
    /// A device made elsewhere (the window's own) for the gpu engine,
    /// instead of one of its own; the automatic choice still takes
    /// the cpu engine when it is a software adapter. When the gpu engine
    /// trains on it, the view is drawn into textures on this device and
    /// sent as [`Event::GpuFrame`] (the window draws them without a copy
    /// through the CPU), except for requests that need the pixels.
    pub gpu_device: Option<GpuContext>,
    /// Where the thread keeps, when it stops, every model trained since it
    /// was last saved or loaded: one run folder each (`checkpoint.zrak` and
    /// `run.json`), which `zrak train --resume`, `eval` and `render` and
    /// the viewer's checkpoint loading reopen. `None` keeps nothing (the
    /// default, so tests never write into the user's data folder; the
    /// viewer gives [`default_autosave_folder`]).
    pub autosave: Option<PathBuf>,
    /// How many kept runs stay under `autosave` (the newest); older ones
    /// are removed after each close that keeps one.
    pub kept_runs: usize,
}

/// `$XDG_DATA_HOME/zrak/runs`, else `~/.local/share/zrak/runs`.
pub fn default_autosave_folder() -> Option<PathBuf> {
    let data = std::env::var_os("XDG_DATA_HOME")
        .filter(|v| !v.is_empty())
        .map(PathBuf::from)
        .or_else(|| {
            std::env::var_os("HOME")
                .filter(|v| !v.is_empty())
                .map(|home| PathBuf::from(home).join(".local").join("share"))
        })?;
    Some(data.join("zrak").join("runs"))
}

impl Default for WorkerOptions {
    fn default() -> Self {
        Self {
            seed: 0,
            loss: None,
            batch_samples: None,
            sampling: None,
            nerf_shape: None,
            precision: Precision::F32,
            demo: DemoConfig::default(),
            space: None,
            photographs: Default::default(),
            val_every_train_seconds: 5.0,
            // As `zrak train` (`Schedule::eval_views`).
            val_views: 3,
            repaint: None,
            gpu_device: None,
            autosave: None,
            kept_runs: crate::train::kept::DEFAULT_KEPT_RUNS,
        }
    }
}

type SharedRepaint = Arc<Mutex<Option<RepaintCallback>>>;

/// The UI's handle on the training thread.
pub struct TrainingWorker {
    commands: Sender<Command>,
    events: Receiver<Event>,
    repaint: SharedRepaint,
    thread: Option<JoinHandle<()>>,
}

impl TrainingWorker {
    /// Starts the thread with [`WorkerOptions::default`].
    pub fn spawn(
        source: SceneSource,
        engine: Option<EngineKind>,
        model: ModelKind,
    ) -> TrainingWorker {
        Self::spawn_with(source, engine, model, WorkerOptions::default())
    }

    /// Starts the thread "zrak-training". It chooses the engine (`None`:
    /// automatically), loads `source` (the demo scene when that fails) and
    /// builds `model`, then waits for commands; training starts with
    /// [`Command::Start`].
    pub fn spawn_with(
        source: SceneSource,
        engine: Option<EngineKind>,
        model: ModelKind,
        mut options: WorkerOptions,
    ) -> TrainingWorker {
        let (command_sender, command_receiver) = mpsc::channel();
        let (event_sender, event_receiver) = mpsc::channel();
        let repaint: SharedRepaint = Arc::new(Mutex::new(options.repaint.take()));
        let outbox = Outbox {
            events: event_sender.clone(),
            repaint: repaint.clone(),
        };
        let spawned = std::thread::Builder::new()
            .name("zrak-training".into())
            .spawn(move || {
                let crash_report = outbox.clone();
                let run = std::panic::catch_unwind(std::panic::AssertUnwindSafe(move || {
                    // Err means the UI is gone: nothing left to tell.
                    let _ = Worker::start(command_receiver, outbox, options, source, engine, model)
                        .and_then(Worker::run);
                }));
                if let Err(panic) = run {
                    let what = panic
                        .downcast_ref::<String>()
                        .map(String::as_str)
                        .or_else(|| panic.downcast_ref::<&str>().copied())
                        .unwrap_or("unknown cause");
                    let _ = crash_report.send(Event::Error(format!(
                        "the training thread stopped after an internal error: {what}"
                    )));
                }
            });
        let thread = match spawned {
            Ok(thread) => Some(thread),
            Err(e) => {
                let _ = event_sender.send(Event::Error(format!(
                    "cannot start the training thread: {e}"
                )));
                None
            }
        };
        TrainingWorker {
            commands: command_sender,
            events: event_receiver,
            repaint,
            thread,
        }
    }

    /// Sets (or replaces) the callback run after every event.
    pub fn set_repaint(&self, repaint: RepaintCallback) {
        if let Ok(mut slot) = self.repaint.lock() {
            *slot = Some(repaint);
        }
    }

    /// Queues a command; never blocks. Commands to a thread that has ended
    /// are dropped (its last event said why).
    pub fn send(&self, command: Command) {
        let _ = self.commands.send(command);
    }

    /// The next event, if one is waiting; never blocks.
    pub fn try_recv(&self) -> Option<Event> {
        self.events.try_recv().ok()
    }

    /// The next event, waiting at most `timeout` (for tests and headless
    /// use; the UI uses [`Self::try_recv`]).
    pub fn recv_timeout(&self, timeout: Duration) -> Option<Event> {
        self.events.recv_timeout(timeout).ok()
    }

    /// True while the thread runs (it ends on shutdown, when the handle is
    /// dropped, or after an internal error it reported).
    pub fn is_alive(&self) -> bool {
        self.thread.as_ref().is_some_and(|t| !t.is_finished())
    }

    /// Asks the thread to stop and waits for it (at most the current unit
    /// of work: one training step, chunk or export frame).
    pub fn shutdown(mut self) {
        self.send(Command::Shutdown);
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

impl Drop for TrainingWorker {
    /// Dropping the handle stops the thread without waiting for it (closing
    /// the channels would stop it too, after its current unit of work).
    fn drop(&mut self) {
        let _ = self.commands.send(Command::Shutdown);
    }
}

/// The UI dropped its handle: the thread ends.
#[derive(Debug)]
struct UiGone;

#[derive(Clone)]
struct Outbox {
    events: Sender<Event>,
    repaint: SharedRepaint,
}

impl Outbox {
    fn send(&self, event: Event) -> Result<(), UiGone> {
        self.events.send(event).map_err(|_| UiGone)?;
        if let Ok(repaint) = self.repaint.lock()
            && let Some(repaint) = repaint.as_ref()
        {
            repaint();
        }
        Ok(())
    }
}

/// The engine every model of this thread runs on.
struct Engine {
    kind: EngineKind,
    gpu: Option<GpuContext>,
}

impl Engine {
    /// A choice for [`build_model`], sharing the device.
    fn choice(&self) -> Result<EngineChoice, String> {
        Ok(EngineChoice {
            kind: self.kind,
            gpu: self.gpu.as_ref().map(share_context).transpose()?,
            reason: String::new(),
        })
    }
}

/// Another context on the same device: every model of the thread shares
/// it (wgpu handles are reference-counted clones).
fn share_context(context: &GpuContext) -> Result<GpuContext, String> {
    GpuContext::from_existing(
        &context.adapter,
        context.device.clone(),
        context.queue.clone(),
    )
    .map_err(|e| format!("the gpu engine: {e}"))
}

/// The engine to train on: as [`choose_engine`], but on `device` when the
/// window made one, so the engine can draw into its textures.
fn choose_engine_on(
    requested: Option<EngineKind>,
    device: Option<GpuContext>,
) -> Result<EngineChoice, String> {
    let Some(context) = device else {
        return choose_engine(requested).map_err(|e| e.to_string());
    };
    Ok(match requested {
        Some(EngineKind::Cpu) => choose_engine(Some(EngineKind::Cpu)).map_err(|e| e.to_string())?,
        Some(EngineKind::Gpu) => EngineChoice {
            kind: EngineKind::Gpu,
            reason: format!("gpu engine on {} (requested)", context.describe()),
            gpu: Some(context),
        },
        // The same rule as `choose_engine`: a software adapter trains far
        // slower than the cpu engine (docs/design.md, "Two engines, one
        // contract").
        None if context.is_software() => EngineChoice {
            kind: EngineKind::Cpu,
            reason: format!(
                "cpu engine: the only adapter is {}, a software rasteriser",
                context.describe()
            ),
            gpu: None,
        },
        None => EngineChoice {
            kind: EngineKind::Gpu,
            reason: format!("gpu engine on {}", context.describe()),
            gpu: Some(context),
        },
    })
}

/// What the loop does next.
enum Work {
    /// Draw the view: a whole level, or one chunk of rays.
    Render {
        whole_level: bool,
    },
    Export,
    Evaluate,
    Train,
    /// Nothing to do until a command arrives or the time passes.
    Wait(Option<Duration>),
}

enum Flow {
    Continue,
    Stop,
}

/// How often the loop looks for a loaded scene when it has nothing else to
/// do (it looks after every unit of work otherwise).
const SCENE_POLL: Duration = Duration::from_millis(20);

/// The thread's state: its inbox and outbox, what it was started with, and
/// the parts that own the rest. The worker routes each command to the parts
/// it concerns and picks the next unit of work.
struct Worker {
    inbox: Receiver<Command>,
    outbox: Outbox,
    options: WorkerOptions,
    engine: Engine,
    scene: SceneState,
    training: Training,
    viewing: Viewing,
    jobs: Jobs,
    trace: Trace,
}

impl Worker {
    fn start(
        inbox: Receiver<Command>,
        outbox: Outbox,
        mut options: WorkerOptions,
        source: SceneSource,
        requested_engine: Option<EngineKind>,
        model: ModelKind,
    ) -> Result<Worker, UiGone> {
        let device = options.gpu_device.take();
        let display_device = device.is_some();
        let (engine, description) = match choose_engine_on(requested_engine, device) {
            Ok(choice) => {
                let description = describe_engine(&choice, options.precision);
                (
                    Engine {
                        kind: choice.kind,
                        gpu: choice.gpu,
                    },
                    description,
                )
            }
            Err(e) => {
                outbox.send(Event::Error(format!(
                    "the gpu engine is not available ({e}); training on the cpu engine"
                )))?;
                let cpu = choose_engine(Some(EngineKind::Cpu)).map_err(|_| UiGone)?;
                let description = describe_engine(&cpu, options.precision);
                (
                    Engine {
                        kind: EngineKind::Cpu,
                        gpu: None,
                    },
                    description,
                )
            }
        };
        outbox.send(Event::Engine {
            kind: engine.kind,
            description,
        })?;

        // The first scene: the one asked for, else the demo so that the
        // viewer always has something to show.
        let (scene, source) = match load_scene(&source, &options.demo) {
            Ok(scene) => (scene, source),
            Err(error) => {
                outbox.send(Event::SceneFailed { source, error })?;
                (demo::build(&options.demo), SceneSource::Demo)
            }
        };
        let scene = SceneState::new(
            source,
            with_chosen_space(scene, options.space),
            options.val_views,
            options.photographs,
        );
        // `choose_engine_on` keeps the given device only for the gpu engine.
        let textures_shared =
            display_device && engine.kind == EngineKind::Gpu && engine.gpu.is_some();
        let mut worker = Worker {
            inbox,
            outbox,
            options,
            engine,
            scene,
            training: Training::new(model),
            viewing: Viewing::new(textures_shared),
            jobs: Jobs::default(),
            trace: Trace::new(Instant::now()),
        };
        worker.send(Event::SceneLoaded(worker.scene.info()))?;
        worker.ensure_slot(model)?;
        worker.send(Event::ModelSelected(model))?;
        worker.send(Event::Running(false))?;
        Ok(worker)
    }

    fn send(&self, event: Event) -> Result<(), UiGone> {
        self.outbox.send(event)
    }

    /// Works until told to stop or the UI is gone, then keeps what has
    /// not been saved.
    fn run(mut self) -> Result<(), UiGone> {
        let result = self.work();
        self.autosave();
        result
    }

    fn work(&mut self) -> Result<(), UiGone> {
        loop {
            self.poll_scene_load()?;
            loop {
                match self.inbox.try_recv() {
                    Ok(command) => {
                        if let Flow::Stop = self.handle(command)? {
                            return Ok(());
                        }
                    }
                    Err(TryRecvError::Empty) => break,
                    Err(TryRecvError::Disconnected) => return Ok(()),
                }
            }
            if let Some(trace) = self.trace.take_if_due(Instant::now()) {
                self.send(Event::Schedule(trace))?;
            }
            let mut work = self.next_work();
            if let Work::Wait(timeout) = &mut work
                && self.scene.is_loading()
            {
                *timeout = Some(timeout.map_or(SCENE_POLL, |t| t.min(SCENE_POLL)));
            }
            if let Work::Wait(timeout) = &mut work
                && let Some(due) = self.trace.wake_within(Instant::now())
            {
                // Wake to send what was done before the wait.
                *timeout = Some(timeout.map_or(due, |t| t.min(due)));
            }
            match work {
                Work::Render { whole_level } => self.viewing.render_unit(
                    whole_level,
                    self.training.shown_mut(),
                    self.engine.gpu.as_ref(),
                    &mut self.trace.time,
                    &self.outbox,
                )?,
                Work::Export => self.jobs.export_unit(&self.training, &self.outbox)?,
                Work::Evaluate => self.evaluate_unit()?,
                Work::Train => self.train_step(false)?,
                Work::Wait(timeout) => {
                    let waited = Instant::now();
                    let received = match timeout {
                        None => Some(self.inbox.recv().map_err(|_| UiGone)?),
                        Some(timeout) => match self.inbox.recv_timeout(timeout) {
                            Ok(command) => Some(command),
                            Err(RecvTimeoutError::Timeout) => None,
                            Err(RecvTimeoutError::Disconnected) => return Ok(()),
                        },
                    };
                    self.trace.time.idle_seconds += waited.elapsed().as_secs_f64();
                    if let Some(command) = received
                        && let Flow::Stop = self.handle(command)?
                    {
                        return Ok(());
                    }
                }
            }
        }
    }

    fn next_work(&mut self) -> Work {
        let training = self.training.can_train() && !self.jobs.exporting();
        let now = Instant::now();
        let mut wake_after: Option<Duration> = None;
        // While the camera moves, training still gets its share: a camera
        // that moves on every frame (a long drag, `--auto-orbit`) brings a
        // new coarse frame to render before the last one is done, and
        // letting every such frame go first stopped training altogether.
        let step_due_while_moving = training && self.training.step_due_while_moving(now);
        let mut refine = false;
        if let Some(view) = self.viewing.pending(self.training.shown()) {
            let moving = view.moving_for.is_some();
            if view.first_level && !(moving && step_due_while_moving) {
                // A new camera (or model): its first level at once.
                return Work::Render { whole_level: true };
            }
            match view.moving_for {
                // Refine only once the camera rests.
                Some(grace_left) => wake_after = Some(grace_left),
                None => refine = true,
            }
        }
        if refine && !training && !self.jobs.exporting() {
            return Work::Render { whole_level: false };
        }
        if let Some(job) = &self.jobs.evaluation {
            if self.training.slot(job.model).is_some() && job.model == self.training.trainee() {
                return Work::Evaluate;
            }
            // Its model no longer trains: evaluate again when due.
            self.jobs.evaluation = None;
        }
        if refine && !self.viewing.training_due() {
            return Work::Render { whole_level: false };
        }
        if self.jobs.exporting() {
            if refine {
                return Work::Render { whole_level: false };
            }
            return Work::Export;
        }
        if training {
            if self.viewing.camera_moving() {
                let wait = self.training.wait_while_moving(now);
                if !wait.is_zero() {
                    return Work::Wait(Some(wake_after.map_or(wait, |w| w.min(wait))));
                }
            }
            return Work::Train;
        }
        Work::Wait(wake_after)
    }

    /// The sampler `kind` trains with here: the one asked for where the
    /// model has it, else the one the scene's space calls for.
    fn sampling_of(&self, kind: ModelKind) -> Sampling {
        let space = self.scene.scene.space.space;
        kind.choose_sampling(self.options.sampling, space)
            .unwrap_or_else(|_| kind.sampling_for(space).0)
    }

    /// A fresh trainer of `kind` on the current scene and engine.
    fn build_trainer(&self, kind: ModelKind) -> Result<Trainer, String> {
        let sampling = self.sampling_of(kind);
        let settings = ModelSettings {
            seed: self.options.seed,
            loss: self.options.loss.unwrap_or(kind.default_loss()),
            batch_samples: self.options.batch_samples.or_else(|| {
                let software_gpu = self.engine.gpu.as_ref().is_some_and(|g| g.is_software());
                viewer_batch_samples(kind, self.engine.kind, software_gpu, sampling)
            }),
            sampling,
            precision: self.options.precision,
            refine_cameras: self.scene.photographs.refine_cameras.on,
            appearance: self.scene.photographs.appearance.on,
        };
        let engine = self.engine.choice()?;
        let mut model = build_viewer_model(
            kind,
            engine,
            &self.scene.scene,
            &settings,
            self.options.nerf_shape.as_ref(),
        )?;
        // The crop box was checked with the models of this engine already.
        let _ = model.set_crop(self.scene.crop);
        if model.appearance_images().is_some() {
            // An image beyond the model's table leaves it on the mean.
            let _ = model.set_render_appearance(self.scene.render_appearance);
        }
        Ok(Trainer::new(
            model,
            self.scene.scene.clone(),
            self.options.seed,
        ))
    }

    /// A slot for a trainer of `kind` fresh from [`Self::build_trainer`]
    /// or a checkpoint, trained with `loss`.
    fn new_slot(&mut self, kind: ModelKind, trainer: Trainer, loss: LossKind) -> ModelSlot {
        self.training
            .new_slot(kind, trainer, loss, self.options.val_every_train_seconds)
    }

    /// The loss `kind` trains with when no checkpoint says otherwise.
    fn loss_of(&self, kind: ModelKind) -> LossKind {
        self.options.loss.unwrap_or(kind.default_loss())
    }

    /// Builds `kind`'s model on first use. Failure is reported and leaves
    /// no slot.
    fn ensure_slot(&mut self, kind: ModelKind) -> Result<(), UiGone> {
        if self.training.slot(kind).is_some() {
            return Ok(());
        }
        match self.build_trainer(kind) {
            Ok(trainer) => {
                let slot = self.new_slot(kind, trainer, self.loss_of(kind));
                self.training.add(slot);
                Ok(())
            }
            Err(e) => self.send(Event::Error(e)),
        }
    }

    fn handle(&mut self, command: Command) -> Result<Flow, UiGone> {
        match command {
            Command::OpenScene(source) => self.open_scene(source)?,
            Command::Start => {
                self.ensure_slot(self.training.trainee())?;
                self.training.running = self.training.slot(self.training.trainee()).is_some();
                self.send(Event::Running(self.training.running))?;
            }
            Command::Pause => {
                self.training.running = false;
                self.flush_stats(self.training.trainee())?;
                self.send(Event::Running(false))?;
            }
            Command::StepOnce => {
                self.ensure_slot(self.training.trainee())?;
                if self.training.slot(self.training.trainee()).is_some() {
                    self.train_step(true)?;
                }
            }
            Command::TrainInTurn(settings) => self.set_turns(settings)?,
            Command::Reset => self.reset()?,
            Command::SelectModel(kind) => {
                if kind != self.training.active {
                    self.flush_stats(self.training.active)?;
                }
                self.ensure_slot(kind)?;
                if self.training.slot(kind).is_some() {
                    self.training.active = kind;
                    self.viewing.restart();
                }
                self.send(Event::ModelSelected(self.training.active))?;
            }
            Command::SetBalance(balance) => self.viewing.set_balance(balance),
            Command::Render(request) => {
                self.viewing
                    .set_view(request, self.training.shown(), &self.outbox)?
            }
            Command::SaveCheckpoint(path) => self.save_checkpoint(&path)?,
            Command::LoadCheckpoint(path) => self.load_checkpoint(&path)?,
            Command::ExportTurntable(settings) => {
                self.start_export(ExportOrder::Turntable(settings))?
            }
            Command::ExportCameraPath(order) => {
                self.start_export(ExportOrder::CameraPath(order))?
            }
            Command::ExportMesh(order) => self.start_export(ExportOrder::Mesh(order))?,
            Command::ExportPoints(order) => self.start_export(ExportOrder::Points(order))?,
            Command::SetCrop(crop) => self.set_crop(crop)?,
            Command::SetAppearance(image) => self.set_appearance(image),
            Command::CancelExport => {
                if self.jobs.stop_export() {
                    self.send(Event::ExportFinished(
                        Err("the export was cancelled".into()),
                    ))?;
                }
            }
            Command::Shutdown => return Ok(Flow::Stop),
        }
        Ok(Flow::Continue)
    }

    /// Starts loading `source` on its own thread; training and rendering
    /// go on with the current scene until it has loaded. A later request
    /// replaces an unfinished one (whose result is then dropped).
    fn open_scene(&mut self, source: SceneSource) -> Result<(), UiGone> {
        match self.scene.start_loading(source.clone(), self.options.demo) {
            Ok(()) => Ok(()),
            Err(error) => self.send(Event::SceneFailed { source, error }),
        }
    }

    /// Installs the scene being loaded, if it is ready.
    fn poll_scene_load(&mut self) -> Result<(), UiGone> {
        let Some((source, result)) = self.scene.poll_loaded() else {
            return Ok(());
        };
        let scene = match result {
            Ok(scene) => with_chosen_space(scene, self.options.space),
            Err(error) => return self.send(Event::SceneFailed { source, error }),
        };
        if self.jobs.stop_export() {
            self.send(Event::ExportFinished(Err(
                "the export stopped: another scene was opened".into(),
            )))?;
        }
        self.scene.install(source, scene, self.options.val_views);
        let had_turns = self.training.clear();
        self.jobs.evaluation = None;
        if had_turns {
            // The models of the old scene are gone; the user starts the
            // turns again on the new one.
            self.send(Event::InTurn(None))?;
        }
        // The camera belongs to the old scene; the UI sends a new one.
        self.viewing.forget_camera();
        self.send(Event::SceneLoaded(self.scene.info()))?;
        self.ensure_slot(self.training.active)?;
        if self.training.shown().is_none() && self.training.running {
            self.training.running = false;
            self.send(Event::Running(false))?;
        }
        Ok(())
    }

    fn reset(&mut self) -> Result<(), UiGone> {
        let kind = self.training.active;
        let trainer = match self.build_trainer(kind) {
            Ok(trainer) => trainer,
            Err(e) => return self.send(Event::Error(e)),
        };
        let slot = self.new_slot(kind, trainer, self.loss_of(kind));
        self.training.install(slot);
        self.jobs.evaluation = None;
        self.training.rebase_turns();
        self.viewing.restart();
        Ok(())
    }

    /// Starts or stops the models' taking turns. Models that cannot be
    /// built are left out (and reported); fewer than two leave the active
    /// model training alone.
    fn set_turns(&mut self, settings: Option<InTurn>) -> Result<(), UiGone> {
        self.flush_stats(self.training.trainee())?;
        self.jobs.evaluation = None;
        self.training.set_turns(None);
        if let Some(settings) = settings {
            let mut models = Vec::new();
            for &kind in &settings.models {
                self.ensure_slot(kind)?;
                if self.training.slot(kind).is_some() && !models.contains(&kind) {
                    models.push(kind);
                }
            }
            if models.len() >= 2 {
                self.training.set_turns(Some(InTurn {
                    models,
                    slice_seconds: settings.slice_seconds,
                }));
            } else {
                self.send(Event::Error(
                    "taking turns needs at least two models that can be built".into(),
                ))?;
            }
        }
        self.send(Event::InTurn(self.training.turns()))
    }

    /// One step of the model that trains (the active one, or the one whose
    /// turn it is); `report` sends its stats at once.
    fn train_step(&mut self, report: bool) -> Result<(), UiGone> {
        if let Some(ended) = self.training.pass_turn() {
            // The stats of the model whose turn ended.
            self.flush_stats(ended)?;
        }
        let started = Instant::now();
        let can_evaluate = self.jobs.evaluation.is_none();
        let Some(step) = self.training.step(
            &self.scene.val_frames,
            self.options.val_every_train_seconds,
            can_evaluate,
        ) else {
            return Ok(());
        };
        if let Some(pixels) = step.evaluation_pixels {
            self.jobs.evaluation =
                Some(Evaluation::new(step.model, &self.scene.val_frames, pixels));
        }
        let seconds = started.elapsed().as_secs_f64();
        self.training.stepped(seconds);
        self.viewing.record_training(seconds);
        let trace = &mut self.trace.time;
        trace.training_seconds += seconds;
        trace.grid_update_seconds += step.stats.times[Stage::GridUpdate];
        trace.steps += 1;
        if report || step.report_due {
            self.flush_stats(step.model)?;
        }
        Ok(())
    }

    /// Sends the stats of `kind`'s steps since the last report, if any.
    fn flush_stats(&mut self, kind: ModelKind) -> Result<(), UiGone> {
        match self
            .training
            .slot_mut(kind)
            .and_then(ModelSlot::take_report)
        {
            Some(stats) => self.send(Event::Stats(stats)),
            None => Ok(()),
        }
    }

    /// Renders one chunk of the held-out evaluation; reports the mean PSNR
    /// when the last pixel is scored.
    fn evaluate_unit(&mut self) -> Result<(), UiGone> {
        let Some(job) = self.jobs.evaluation.as_mut() else {
            return Ok(());
        };
        let Some(slot) = self.training.slot_mut(job.model) else {
            self.jobs.evaluation = None;
            return Ok(());
        };
        let (seconds, done) = job.render_unit(slot, &self.scene.val_frames);
        let kind = job.model;
        // Evaluation is the view's kind of work in the balance.
        self.viewing.record_other(seconds);
        self.trace.time.evaluation_seconds += seconds;
        if !done {
            return Ok(());
        }
        self.trace.time.evaluations += 1;
        self.jobs.evaluation = None;
        self.flush_stats(kind)
    }

    fn start_export(&mut self, order: ExportOrder) -> Result<(), UiGone> {
        let step = self.training.shown().map_or(0, |slot| slot.trainer.step);
        let event = self.jobs.start_export(
            &self.scene.scene,
            order,
            self.training.active,
            self.scene.crop,
            step,
        );
        self.send(event)
    }

    /// Sets the crop box on every model (and on those built later); a
    /// model that refuses it (the gpu engine may) keeps rendering the whole
    /// scene, and the refusal goes to the window.
    /// Every model with appearance embeddings draws with `image`'s vector
    /// (or the mean); so do the models built later on this scene.
    fn set_appearance(&mut self, image: Option<usize>) {
        self.scene.render_appearance = image;
        for slot in self.training.slots_mut() {
            if slot.trainer.model.appearance_images().is_some() {
                let _ = slot.trainer.model.set_render_appearance(image);
            }
        }
        self.viewing.restart();
    }

    fn set_crop(&mut self, crop: Option<CropBox>) -> Result<(), UiGone> {
        let crop = match crop.map(|c| c.check().map(|()| c)).transpose() {
            Ok(crop) => crop,
            Err(problem) => {
                return self.send(Event::CropSet {
                    crop: self.scene.crop,
                    refused: Some(problem),
                });
            }
        };
        let refused = self
            .training
            .slots_mut()
            .iter_mut()
            .find_map(|slot| slot.trainer.model.set_crop(crop).err());
        if refused.is_some() {
            // Every model back to the whole scene, so that they agree.
            for slot in self.training.slots_mut() {
                let _ = slot.trainer.model.set_crop(None);
            }
        }
        self.scene.crop = if refused.is_some() { None } else { crop };
        self.viewing.restart();
        self.send(Event::CropSet {
            crop: self.scene.crop,
            refused,
        })
    }
}

/// A fresh model of `kind` on the worker's engine: tests give NeRF-shaped
/// fields ([`WorkerOptions::nerf_shape`]) a small shape of their own.
fn build_viewer_model(
    kind: ModelKind,
    engine: EngineChoice,
    scene: &Scene,
    settings: &ModelSettings,
    nerf_shape: Option<&NerfShape>,
) -> Result<Box<dyn RadianceModel>, String> {
    // The viewer's batch is smaller than `zrak train`'s on the cpu engine
    // and lavapipe: counted in steps, its grid updates took a third to a
    // half of its training time (issue 45).
    let request = ModelRequest::new(kind, *settings).with_grid_paced_by_samples();
    let request = match (nerf_shape, (kind.spec().shape)(scene, settings.sampling)) {
        (Some(shape), FieldShape::Nerf(_)) => request.with_shape(shape.clone()),
        _ => request,
    };
    build(&request, engine, scene).map_err(|e| e.to_string())
}

/// The engine in one line for the stats panel: the choice's reason (which
/// names the adapter), and for the cpu engine its thread count.
fn describe_engine(choice: &EngineChoice, precision: Precision) -> String {
    match choice.kind {
        EngineKind::Gpu => choice.reason.clone(),
        EngineKind::Cpu => format!(
            "{}; {} threads; {:?} kernels, {} precision",
            choice.reason,
            rayon::current_num_threads(),
            backend_for(precision),
            precision.kernels_here().name()
        ),
    }
}

#[cfg(test)]
mod tests;
