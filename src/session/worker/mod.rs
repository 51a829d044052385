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

use std::path::{Path, PathBuf};
use std::sync::mpsc::{self, Receiver, RecvTimeoutError, Sender, TryRecvError};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use crate::engine::cpu::dense::{Precision, backend_for};
use crate::engine::cpu::fields::nerf::NerfShape;
use crate::engine::gpu::GpuContext;
use crate::engine::gpu::render::render_target;
use crate::engine::{EngineChoice, EngineKind, choose_engine};
use crate::field::ModelKind;
use crate::field::nerf::Sampling;
use crate::field::ngp::LossKind;
use crate::metrics::WHITE;
use crate::metrics::psnr::psnr_from_mse;
use crate::render::export::{ExportSettings, TurntableExport};
use crate::scene::demo::{self, DemoConfig};
use crate::scene::{Camera, Frame, LoadOptions, Scene};
use crate::train::checkpoint::Checkpoint;
use crate::train::eval::{pixel_grid, spread_views};
use crate::train::model::{RadianceModel, RayColumns, RenderedPixel, Stage, StageTimes, StepStats};
use crate::train::trainer::Trainer;
use crate::train::{ModelSettings, build_model};

use super::progressive::{ChunkPacer, LevelRender, draw_band_to_texture, level_camera};
use super::protocol::{
    Balance, Command, Event, GpuFrame, InTurn, RenderRequest, RenderedFrame, SceneInfo,
    SceneSource, TrainingStats,
};
use super::schedule::{
    EVAL_SHARE, Ledger, MIN_EVAL_PIXELS, RenderCost, ScheduleTrace, TRACE_INTERVAL, first_level,
    next_finer_level, refresh_budget,
};

mod export_jobs;
mod export_mesh;
mod saving;
mod training;
mod view;

use crate::scene::crop::CropBox;
use export_jobs::{ExportJob, ExportOrder};
pub use training::Turns;
use view::TexturePool;

pub type RepaintCallback = Box<dyn Fn() + Send>;

/// Stats go out at most this often (ten times a second), aggregated over
/// the steps in between.
const STATS_INTERVAL: Duration = Duration::from_millis(100);

/// How long one chunk of rays should take: well under the ~100 ms a command
/// may wait.
const CHUNK_TARGET: Duration = Duration::from_millis(40);

/// A moving request counts as moving for this long after it arrived: the UI
/// sends one per frame while the user drags, so a gap this long means the
/// camera came to rest even if no resting request followed.
const MOVING_GRACE: Duration = Duration::from_millis(300);

/// While the camera moves, training gets at most 1/(1 + this) of wall time:
/// after a step of d seconds, the next waits d × this. A step cannot be
/// interrupted, so a coarse frame may wait behind one (tens of ms with the
/// viewer's cpu batch); waiting instead for a pause between requests would
/// stop training for as long as the user drags.
const MOVING_IDLE_PER_STEP: f64 = 3.0;

/// The largest training share honoured while a view still refines: at 1.0
/// the viewport would never sharpen.
const MAX_TRAINING_SHARE: f32 = 0.95;

/// Textures the gpu engine's view is drawn into, kept for reuse (levels of
/// several sizes, two of each size that is shown).
const MAX_KEPT_TEXTURES: usize = 8;

/// The largest viewport side accepted (8K); anything above is a bad
/// request, refused before it allocates gigabytes of pixels.
const MAX_VIEWPORT_SIDE: u32 = 8_192;

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
    /// NeRF's sampler.
    pub sampling: Sampling,
    /// The networks of NeRF and Mip-NeRF; `None` gives each its paper's.
    /// Tests give small ones, so that a software gpu adapter runs them.
    pub nerf_shape: Option<NerfShape>,
    /// How the cpu engine computes the networks' products (f32 unless
    /// asked: the viewer asks for the processor's best).
    pub precision: Precision,
    /// The scene [`SceneSource::Demo`] builds.
    pub demo: DemoConfig,
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
            sampling: Sampling::Occupancy,
            nerf_shape: None,
            precision: Precision::F32,
            demo: DemoConfig::default(),
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

/// Steps since the last stats event, to be reported as one.
#[derive(Default)]
struct StatsWindow {
    steps: u32,
    seconds: f64,
    rays: usize,
    samples: usize,
    /// Samples before the rays' cuts, while every step of the window
    /// reported them.
    composited: Option<usize>,
    /// Σ loss × rays, so the mean is over every ray of the window.
    loss_times_rays: f64,
    times: StageTimes,
}

/// One model's training on the current scene.
struct ModelSlot {
    kind: ModelKind,
    trainer: Trainer,
    /// The loss the model trains with (a loaded checkpoint brings its own).
    loss: LossKind,
    window: StatsWindow,
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
    revision: u64,
    /// The step last saved or loaded (0 for a fresh model): a model past
    /// it has training that only memory holds.
    saved_step: u32,
    /// Sizes the chunks of rays this model renders (its rays cost their
    /// own: a NeRF ray ~50 of Instant-NGP's).
    pacer: ChunkPacer,
    /// What a pixel of this model costs to render, over whole levels.
    cost: RenderCost,
    /// What a pixel of the held-out evaluation costs: its views frame the
    /// scene as the training views do, so more of their pixels cross it
    /// than a viewport's.
    eval_cost: RenderCost,
}

/// What the viewport asked for and how far it has been drawn.
struct View {
    request: RenderRequest,
    received: Instant,
    /// The level being drawn.
    job: Option<LevelJob>,
    /// The last finished level of this camera and model (re-sent when the
    /// same camera is requested again).
    shown: Option<Shown>,
}

/// A finished level on screen.
struct Shown {
    picture: Picture,
    /// The model revision the level began from.
    revision: u64,
    downscale: u32,
}

/// A level of the view being drawn.
struct LevelJob {
    downscale: u32,
    /// The model drawn, its step and training seconds when the level began.
    model: ModelKind,
    step: u32,
    train_seconds: f64,
    revision: u64,
    /// Render seconds spent on it so far.
    seconds: f64,
    /// Whether it may be sent before its last row over the rest of the
    /// picture on screen (a redraw of that level, or a finer level over it).
    over_shown: bool,
    /// Whether the rows not drawn yet hold the picture on screen (copied
    /// when the level is first sent unfinished).
    holds_shown_rest: bool,
    /// Render seconds spent on it when it was last sent unfinished.
    seconds_at_last_send: f64,
    draw: LevelDraw,
}

enum LevelDraw {
    /// Chunks of rays composited on the host, sent as pixels.
    Pixels(LevelRender),
    /// Bands of rows drawn by the gpu engine into a texture on the
    /// window's device.
    Texture(TextureLevel),
}

/// A level drawn into a texture band by band, so that a level slower
/// than a unit of work (NeRF on lavapipe: seconds) never holds the thread.
struct TextureLevel {
    camera: Camera,
    texture: wgpu::Texture,
    /// Rows above this one are drawn.
    next_row: u32,
}

/// A finished frame of the view, as sent.
enum Picture {
    /// Pixels read back to the CPU (the cpu engine, or a request that
    /// needs the pixels).
    Pixels(RenderedFrame),
    /// A texture on the device shared with the window.
    Texture(GpuFrame),
}

/// A held-out evaluation in progress: a grid of pixels spread over each
/// held-out view, rendered in chunks like the view so that commands are
/// not held up by a slow model, scored view by view (per-view PSNR, then
/// the mean, as `train::eval::mean_psnr_sampled` scores for `zrak
/// train`). Training waits until it is done, so the PSNR belongs to one
/// step.
struct ValJob {
    model: ModelKind,
    /// (held-out view, column, row) of every pixel to score, view by view.
    pixels: Vec<(usize, u32, u32)>,
    /// Pixels rendered so far.
    done: usize,
    /// Per view: Σ squared error over the three channels, and pixels.
    squared: Vec<f64>,
    counts: Vec<usize>,
    /// Render seconds so far.
    seconds: f64,
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

struct Worker {
    inbox: Receiver<Command>,
    outbox: Outbox,
    options: WorkerOptions,
    engine: Engine,
    source: SceneSource,
    scene: Arc<Scene>,
    /// The held-out views of the scene, downscaled for quick evaluation.
    val_frames: Vec<Frame>,
    slots: Vec<ModelSlot>,
    active: ModelKind,
    /// When set, the models take turns at training instead of the active
    /// model training alone.
    turns: Option<Turns>,
    running: bool,
    balance: Balance,
    view: Option<View>,
    export: Option<ExportJob>,
    /// What every model renders and exports (`None`: the whole scene).
    crop: Option<CropBox>,
    val_job: Option<ValJob>,
    /// When the last training step ended and how long it took, to keep
    /// training light while the camera moves.
    last_step: Option<(Instant, f64)>,
    next_revision: u64,
    /// Training's part of the time while the camera rests.
    ledger: Ledger,
    /// Where the time went since `trace_started`, sent every
    /// [`TRACE_INTERVAL`].
    trace: ScheduleTrace,
    trace_started: Instant,
    /// True when the engine trains on the window's own device
    /// ([`WorkerOptions::gpu_device`]): the view is then drawn into
    /// textures there.
    textures_shared: bool,
    /// Textures the view's levels and bands are drawn into.
    textures: TexturePool,
    /// A scene being loaded on a thread of its own, so that reading and
    /// decoding a large one never stalls training or rendering.
    loading: Option<SceneLoad>,
}

/// A scene load under way: what was asked for, and where the result comes.
struct SceneLoad {
    source: SceneSource,
    result: Receiver<Result<Scene, String>>,
}

/// How often the loop looks for a loaded scene when it has nothing else to
/// do (it looks after every unit of work otherwise).
const SCENE_POLL: Duration = Duration::from_millis(20);

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
        let scene = Arc::new(scene);
        let val_frames = held_out_views(&scene, options.val_views);
        // `choose_engine_on` keeps the given device only for the gpu engine.
        let textures_shared =
            display_device && engine.kind == EngineKind::Gpu && engine.gpu.is_some();
        let mut worker = Worker {
            inbox,
            outbox,
            options,
            engine,
            source,
            scene,
            val_frames,
            slots: Vec::new(),
            active: model,
            turns: None,
            running: false,
            balance: Balance::default(),
            view: None,
            export: None,
            crop: None,
            val_job: None,
            last_step: None,
            next_revision: 0,
            ledger: Ledger::default(),
            trace: ScheduleTrace::default(),
            trace_started: Instant::now(),
            textures_shared,
            textures: TexturePool::default(),
            loading: None,
        };
        worker.send(Event::SceneLoaded(SceneInfo {
            scene: worker.scene.clone(),
            source: worker.source.clone(),
        }))?;
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
            self.send_trace_if_due()?;
            let mut work = self.next_work();
            if let (Work::Wait(timeout), Some(_)) = (&mut work, &self.loading) {
                *timeout = Some(timeout.map_or(SCENE_POLL, |t| t.min(SCENE_POLL)));
            }
            if let Work::Wait(timeout) = &mut work
                && !self.trace.only_idle()
            {
                // Wake to send what was done before the wait.
                let due = TRACE_INTERVAL.saturating_sub(self.trace_started.elapsed());
                *timeout = Some(timeout.map_or(due, |t| t.min(due)));
            }
            match work {
                Work::Render { whole_level } => self.render_unit(whole_level)?,
                Work::Export => self.export_unit()?,
                Work::Evaluate => self.evaluate_unit()?,
                Work::Train => self.train_unit()?,
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
                    self.trace.idle_seconds += waited.elapsed().as_secs_f64();
                    if let Some(command) = received
                        && let Flow::Stop = self.handle(command)?
                    {
                        return Ok(());
                    }
                }
            }
        }
    }

    /// Sends where the time went, once a [`TRACE_INTERVAL`] has passed
    /// (nothing when the thread only waited).
    fn send_trace_if_due(&mut self) -> Result<(), UiGone> {
        let elapsed = self.trace_started.elapsed();
        if elapsed < TRACE_INTERVAL {
            return Ok(());
        }
        let mut trace = std::mem::take(&mut self.trace);
        trace.wall_seconds = elapsed.as_secs_f64();
        self.trace_started = Instant::now();
        if trace.only_idle() {
            return Ok(());
        }
        self.send(Event::Schedule(trace))
    }

    fn training_share(&self) -> f64 {
        self.balance.training_share.clamp(0.0, MAX_TRAINING_SHARE) as f64
    }

    fn training_active(&self) -> bool {
        self.running && self.export.is_none() && self.slot(self.trainee()).is_some()
    }

    /// The model that trains: the one whose turn it is, else the active one.
    fn trainee(&self) -> ModelKind {
        self.turns.as_ref().map_or(self.active, Turns::current)
    }

    fn next_work(&mut self) -> Work {
        let training = self.training_active();
        let share = self.training_share();
        let mut wake_after: Option<Duration> = None;
        // While the camera moves, training still gets its share: a camera
        // that moves on every frame (a long drag, `--auto-orbit`) brings a
        // new coarse frame to render before the last one is done, and
        // letting every such frame go first stopped training altogether.
        let step_due_while_moving = training
            && self.last_step.is_none_or(|(ended, seconds)| {
                ended.elapsed().as_secs_f64() >= seconds * MOVING_IDLE_PER_STEP
            });
        let view_has_work =
            self.view.as_ref().is_some_and(|v| v.job.is_some()) || self.next_level().is_some();
        let mut refine = false;
        if let Some(view) = self.view.as_ref()
            && view_has_work
        {
            if view.shown.is_none() && !(view.moving() && step_due_while_moving) {
                // A new camera (or model): its first level at once.
                return Work::Render { whole_level: true };
            }
            if view.moving() {
                // Refine only once the camera rests.
                wake_after = Some(MOVING_GRACE.saturating_sub(view.received.elapsed()));
            } else {
                refine = true;
            }
        }
        if refine && !training && self.export.is_none() {
            return Work::Render { whole_level: false };
        }
        if let Some(job) = &self.val_job {
            if self.slot(job.model).is_some() && job.model == self.trainee() {
                return Work::Evaluate;
            }
            // Its model no longer trains: evaluate again when due.
            self.val_job = None;
        }
        if refine && !self.ledger.training_due(share) {
            return Work::Render { whole_level: false };
        }
        if self.export.is_some() {
            if refine {
                return Work::Render { whole_level: false };
            }
            return Work::Export;
        }
        if training {
            if self.view.as_ref().is_some_and(|v| v.moving()) {
                let wait = self.last_step.map_or(Duration::ZERO, |(ended, seconds)| {
                    Duration::from_secs_f64(seconds * MOVING_IDLE_PER_STEP)
                        .saturating_sub(ended.elapsed())
                });
                if !wait.is_zero() {
                    return Work::Wait(Some(wake_after.map_or(wait, |w| w.min(wait))));
                }
            }
            return Work::Train;
        }
        Work::Wait(wake_after)
    }

    fn slot(&self, kind: ModelKind) -> Option<&ModelSlot> {
        self.slots.iter().find(|s| s.kind == kind)
    }

    fn slot_mut(&mut self, kind: ModelKind) -> Option<&mut ModelSlot> {
        self.slots.iter_mut().find(|s| s.kind == kind)
    }

    fn revision(&mut self) -> u64 {
        self.next_revision += 1;
        self.next_revision
    }

    /// A fresh trainer of `kind` on the current scene and engine.
    fn build_trainer(&self, kind: ModelKind) -> Result<Trainer, String> {
        let settings = ModelSettings {
            seed: self.options.seed,
            loss: self.options.loss.unwrap_or(kind.default_loss()),
            batch_samples: self.options.batch_samples.or_else(|| {
                let software_gpu = self.engine.gpu.as_ref().is_some_and(|g| g.is_software());
                viewer_batch_samples(kind, self.engine.kind, software_gpu, self.options.sampling)
            }),
            sampling: self.options.sampling,
            precision: self.options.precision,
        };
        let engine = self.engine.choice()?;
        let mut model: Box<dyn RadianceModel> =
            match (&self.options.nerf_shape, kind, engine.gpu) {
                (Some(shape), ModelKind::Nerf, None) => Box::new(
                    crate::train::cpu_nerf_with_shape(&self.scene, &settings, shape),
                ),
                (Some(shape), ModelKind::MipNerf, None) => Box::new(
                    crate::train::cpu_mipnerf_with_shape(&self.scene, &settings, shape),
                ),
                (Some(shape), ModelKind::Nerf, Some(gpu)) if engine.kind == EngineKind::Gpu => {
                    Box::new(crate::train::gpu_nerf_with_shape(
                        gpu,
                        &self.scene,
                        &settings,
                        shape,
                    )?)
                }
                (Some(shape), ModelKind::MipNerf, Some(gpu)) if engine.kind == EngineKind::Gpu => {
                    Box::new(crate::train::gpu_mipnerf_with_shape(
                        gpu,
                        &self.scene,
                        &settings,
                        shape,
                    )?)
                }
                (_, _, gpu) => build_model(
                    kind,
                    EngineChoice {
                        kind: engine.kind,
                        gpu,
                        reason: engine.reason,
                    },
                    &self.scene,
                    &settings,
                )?,
            };
        // The crop box was checked with the models of this engine already.
        let _ = model.set_crop(self.crop);
        Ok(Trainer::new(model, self.scene.clone(), self.options.seed))
    }

    fn new_slot(&mut self, kind: ModelKind, trainer: Trainer, loss: LossKind) -> ModelSlot {
        let saved_step = trainer.step;
        ModelSlot {
            kind,
            next_val_at: trainer.train_seconds + self.options.val_every_train_seconds,
            trainer,
            loss,
            window: StatsWindow::default(),
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

    /// Builds `kind`'s model on first use. Failure is reported and leaves
    /// no slot.
    fn ensure_slot(&mut self, kind: ModelKind) -> Result<(), UiGone> {
        if self.slot(kind).is_some() {
            return Ok(());
        }
        match self.build_trainer(kind) {
            Ok(trainer) => {
                let slot = self.new_slot(
                    kind,
                    trainer,
                    self.options.loss.unwrap_or(kind.default_loss()),
                );
                self.slots.push(slot);
                Ok(())
            }
            Err(e) => self.send(Event::Error(e)),
        }
    }

    fn handle(&mut self, command: Command) -> Result<Flow, UiGone> {
        match command {
            Command::OpenScene(source) => self.open_scene(source)?,
            Command::Start => {
                self.ensure_slot(self.trainee())?;
                self.running = self.slot(self.trainee()).is_some();
                self.send(Event::Running(self.running))?;
            }
            Command::Pause => {
                self.running = false;
                self.flush_stats(self.trainee())?;
                self.send(Event::Running(false))?;
            }
            Command::StepOnce => {
                self.ensure_slot(self.trainee())?;
                if self.slot(self.trainee()).is_some() {
                    self.train_step(true)?;
                }
            }
            Command::TrainInTurn(settings) => self.set_turns(settings)?,
            Command::Reset => self.reset()?,
            Command::SelectModel(kind) => {
                if kind != self.active {
                    self.flush_stats(self.active)?;
                }
                self.ensure_slot(kind)?;
                if self.slot(kind).is_some() {
                    self.active = kind;
                    if let Some(view) = self.view.as_mut() {
                        view.restart();
                    }
                }
                self.send(Event::ModelSelected(self.active))?;
            }
            Command::SetBalance(balance) => {
                let share = if balance.training_share.is_finite() {
                    balance.training_share.clamp(0.0, 1.0)
                } else {
                    Balance::default().training_share
                };
                self.balance = Balance {
                    training_share: share,
                };
            }
            Command::Render(request) => self.set_view(request)?,
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
            Command::CancelExport => {
                if self.export.take().is_some() {
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
        let (sender, receiver) = mpsc::channel();
        let demo = self.options.demo;
        let to_load = source.clone();
        let spawned = std::thread::Builder::new()
            .name("zrak-scene-loading".into())
            .spawn(move || {
                // The receiver may be gone (another scene was asked for).
                let _ = sender.send(load_scene(&to_load, &demo));
            });
        match spawned {
            Ok(_) => {
                self.loading = Some(SceneLoad {
                    source,
                    result: receiver,
                });
                Ok(())
            }
            Err(e) => self.send(Event::SceneFailed {
                source,
                error: format!("cannot start loading the scene: {e}"),
            }),
        }
    }

    /// Installs the scene being loaded, if it is ready.
    fn poll_scene_load(&mut self) -> Result<(), UiGone> {
        let Some(load) = self.loading.take() else {
            return Ok(());
        };
        let result = match load.result.try_recv() {
            Ok(result) => result,
            Err(TryRecvError::Empty) => {
                self.loading = Some(load);
                return Ok(());
            }
            Err(TryRecvError::Disconnected) => {
                Err("loading the scene stopped after an internal error".to_string())
            }
        };
        let source = load.source;
        let scene = match result {
            Ok(scene) => scene,
            Err(error) => return self.send(Event::SceneFailed { source, error }),
        };
        if self.export.take().is_some() {
            self.send(Event::ExportFinished(Err(
                "the export stopped: another scene was opened".into(),
            )))?;
        }
        self.scene = Arc::new(scene);
        self.crop = None; // the old scene's box; the window clears its own
        self.source = source;
        self.val_frames = held_out_views(&self.scene, self.options.val_views);
        self.slots.clear();
        self.val_job = None;
        if self.turns.take().is_some() {
            // The models of the old scene are gone; the user starts the
            // turns again on the new one.
            self.send(Event::InTurn(None))?;
        }
        // The camera belongs to the old scene; the UI sends a new one.
        self.view = None;
        self.send(Event::SceneLoaded(SceneInfo {
            scene: self.scene.clone(),
            source: self.source.clone(),
        }))?;
        self.ensure_slot(self.active)?;
        if self.slot(self.active).is_none() && self.running {
            self.running = false;
            self.send(Event::Running(false))?;
        }
        Ok(())
    }

    fn reset(&mut self) -> Result<(), UiGone> {
        let kind = self.active;
        let trainer = match self.build_trainer(kind) {
            Ok(trainer) => trainer,
            Err(e) => return self.send(Event::Error(e)),
        };
        let slot = self.new_slot(
            kind,
            trainer,
            self.options.loss.unwrap_or(kind.default_loss()),
        );
        match self.slot_mut(kind) {
            Some(existing) => *existing = slot,
            None => self.slots.push(slot),
        }
        self.val_job = None;
        self.rebase_turns();
        if let Some(view) = self.view.as_mut() {
            view.restart();
        }
        Ok(())
    }
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

fn load_scene(source: &SceneSource, demo_config: &DemoConfig) -> Result<Scene, String> {
    let scene = match source {
        SceneSource::Demo => demo::build(demo_config),
        SceneSource::Folder(path) => {
            Scene::load(path, LoadOptions::default()).map_err(|e| e.to_string())?
        }
    };
    if scene.train.is_empty() {
        let place = match source {
            SceneSource::Demo => PathBuf::from("demo"),
            SceneSource::Folder(path) => path.clone(),
        };
        return Err(format!(
            "{}: the scene has no training views to learn from",
            place.display()
        ));
    }
    Ok(scene)
}

/// Up to `count` held-out views (val, else test, else train), spread over
/// the split as `zrak train` chooses them.
fn held_out_views(scene: &Scene, count: usize) -> Vec<Frame> {
    let frames = [&scene.val, &scene.test, &scene.train]
        .into_iter()
        .find(|frames| !frames.is_empty())
        .map_or(&[][..], |frames| frames.as_slice());
    spread_views(frames, count).into_iter().cloned().collect()
}

#[cfg(test)]
mod tests;
