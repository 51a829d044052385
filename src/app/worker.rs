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
use crate::train::model::{RadianceModel, RenderedPixel, StageTimes, StepStats};
use crate::train::trainer::Trainer;
use crate::train::{ModelSettings, build_model};

use super::progressive::{ChunkPacer, LevelRender, draw_band_to_texture, level_camera};
use super::protocol::{
    Balance, Command, Event, GpuFrame, InTurn, RenderRequest, RenderedFrame, SceneInfo,
    SceneSource, TrainingStats,
};
use super::schedule::{
    EVAL_SHARE, Ledger, MIN_EVAL_PIXELS, RenderCost, ScheduleTrace, TRACE_INTERVAL, finest_within,
    first_level, next_finer_level, refresh_budget,
};

/// Training batch of the viewer on the cpu engine, in samples: a quarter
/// of Instant-NGP's 2^18, so a step takes ~60 ms rather than ~250 ms on two
/// cores. Commands and render chunks wait behind at most one step, and the
/// view improves in more, smaller steps during the first minute.
pub const CPU_BATCH_SAMPLES: usize = 1 << 16;

/// NeRF's and Mip-NeRF's batch in the viewer with the paper's samplers, or
/// on a software gpu adapter: the paper's 1024 rays × 256 samples of the
/// 8 × 256 network are ~1 T FLOP a step, seconds on two cores (minutes on
/// lavapipe), so 2^12 samples. With the occupancy sampler on the cpu
/// engine they train on their recipe's batch (2^14 samples, ~0.15 s a
/// step on two cores), as `zrak train` does: their occupancy grid is
/// updated every 16 steps whatever the batch, at ~20 steps' cost (64³
/// density queries of the 8 × 256 network), so a quarter of the batch
/// spent half of the viewer's training time on grid updates (measured on
/// lego_400: 21.6 of 42.2 s), twice `zrak train`'s share; and the same
/// batch makes the viewer's steps comparable with `zrak train`'s.
pub const NERF_SMALL_BATCH_SAMPLES: usize = 1 << 12;

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

/// How the thread trains and measures; [`Default`] is what the viewer uses.
pub struct WorkerOptions {
    pub seed: u64,
    /// The loss every model trains with; `None` gives each model its own
    /// default ([`ModelKind::default_loss`]).
    pub loss: Option<LossKind>,
    /// Samples per training batch; `None` picks by engine: see
    /// [`CPU_BATCH_SAMPLES`].
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
    /// A device made elsewhere (the viewer's, from eframe) for the gpu
    /// engine, instead of one of its own; the automatic choice still takes
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
/// viewer made one (eframe's), so the engine can draw into its textures.
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
        // slower than the cpu engine (DESIGN.md).
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

impl StatsWindow {
    fn add(&mut self, stats: &StepStats, seconds: f64) {
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

impl View {
    fn moving(&self) -> bool {
        self.request.moving && self.received.elapsed() < MOVING_GRACE
    }

    /// Starts again from a first level: the model shown changed (another
    /// model, a reset, a loaded checkpoint), so neither the level in
    /// progress nor the refinement so far is of the model now shown. The
    /// window keeps the old picture until the first level comes.
    fn restart(&mut self) {
        self.job = None;
        self.shown = None;
    }
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

impl LevelJob {
    fn pixels(&self) -> usize {
        match &self.draw {
            LevelDraw::Pixels(render) => render.width() as usize * render.height() as usize,
            LevelDraw::Texture(level) => {
                level.camera.intrinsics.width as usize * level.camera.intrinsics.height as usize
            }
        }
    }

    fn is_done(&self) -> bool {
        match &self.draw {
            LevelDraw::Pixels(render) => render.is_done(),
            LevelDraw::Texture(level) => level.next_row >= level.camera.intrinsics.height,
        }
    }

    /// Pixels drawn so far.
    fn drawn(&self) -> usize {
        match &self.draw {
            LevelDraw::Pixels(render) => render.rendered(),
            LevelDraw::Texture(level) => {
                level.next_row as usize * level.camera.intrinsics.width as usize
            }
        }
    }

    /// True when the level, drawn at the rate of its first part, would take
    /// more than twice `budget` render seconds and is not half done: the
    /// cost was misjudged (the cost of a pixel rises early in training,
    /// while the field clears empty space the grid still marches).
    fn overruns(&self, budget: f64) -> bool {
        let (drawn, pixels) = (self.drawn(), self.pixels());
        if drawn == 0 || 2 * drawn >= pixels || self.seconds <= budget {
            return false;
        }
        self.seconds * pixels as f64 / drawn as f64 > 2.0 * budget
    }
}

/// A finished frame of the view, as sent.
enum Picture {
    /// Pixels read back to the CPU (the cpu engine, or a request that
    /// needs the pixels).
    Pixels(RenderedFrame),
    /// A texture on the device shared with the window.
    Texture(GpuFrame),
}

impl Picture {
    /// Whether this picture answers `request` (of the same camera): pixels
    /// are shown in any mode, while a texture holds one mode's colours.
    fn answers(&self, request: &RenderRequest, draws_to_texture: bool) -> bool {
        match self {
            Picture::Pixels(_) => !draws_to_texture,
            Picture::Texture(frame) => draws_to_texture && frame.mode == request.mode,
        }
    }

    /// The picture as the answer to `request`, as an event.
    fn resend(&mut self, request: &RenderRequest) -> Event {
        match self {
            Picture::Pixels(frame) => {
                frame.generation = request.generation;
                frame.mode = request.mode;
                Event::Frame(frame.clone())
            }
            Picture::Texture(frame) => {
                frame.generation = request.generation;
                Event::GpuFrame(frame.clone())
            }
        }
    }
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

impl ValJob {
    /// About `pixels` pixels spread evenly over `frames`.
    fn new(model: ModelKind, frames: &[Frame], pixels: usize) -> Self {
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

    fn is_done(&self) -> bool {
        self.done >= self.pixels.len()
    }

    /// Renders and scores up to `max_rays` more pixels.
    fn render_chunk(&mut self, model: &dyn RadianceModel, frames: &[Frame], max_rays: usize) {
        let end = (self.done + max_rays.max(1)).min(self.pixels.len());
        let chunk = &self.pixels[self.done..end];
        let rays: Vec<_> = chunk
            .iter()
            .map(|&(view, x, y)| frames[view].camera.pixel_ray(x, y))
            .collect();
        let origins: Vec<_> = rays.iter().map(|r| r.origin).collect();
        let directions: Vec<_> = rays.iter().map(|r| r.direction).collect();
        let radii: Vec<_> = rays.iter().map(|r| r.radius()).collect();
        let mut out = vec![RenderedPixel::default(); chunk.len()];
        model.render(&origins, &directions, &radii, WHITE, &mut out);
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
    fn mean_psnr(&self) -> f64 {
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

    /// The level the view should draw next (its downscale), if any: a
    /// first level for a camera or model not yet shown; then, once the
    /// camera rests, finer levels up to the target; then, whenever the
    /// model has changed since the shown level began, the target again.
    /// The target is the finest level whose render fits the refresh
    /// budget while the thread has other work, full resolution otherwise.
    fn next_level(&self) -> Option<u32> {
        let view = self.view.as_ref()?;
        let slot = self.slot(self.active)?;
        let k = view.request.camera.intrinsics;
        let cost = slot.cost.seconds_per_pixel();
        let Some(shown) = &view.shown else {
            return Some(first_level(k.width, k.height, cost));
        };
        if view.moving() {
            // A moving camera gets one level per request.
            return None;
        }
        let busy = self.training_active() || self.export.is_some();
        let target = match (busy, cost) {
            (false, _) => 1,
            (true, Some(per_pixel)) => finest_within(
                k.width,
                k.height,
                per_pixel,
                refresh_budget(self.training_share()),
            ),
            // Only after a first level, which measures the cost.
            (true, None) => shown.downscale,
        };
        if shown.downscale > target
            && let Some(finer) = next_finer_level(k.width, k.height, shown.downscale, target)
        {
            return Some(finer);
        }
        (shown.revision != slot.revision).then_some(target)
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
                match (self.engine.kind, kind, self.options.sampling) {
                    (EngineKind::Cpu, ModelKind::Ngp, _) => Some(CPU_BATCH_SAMPLES),
                    (EngineKind::Cpu, ModelKind::Nerf | ModelKind::MipNerf, Sampling::Paper) => {
                        Some(NERF_SMALL_BATCH_SAMPLES)
                    }
                    (EngineKind::Gpu, ModelKind::Nerf | ModelKind::MipNerf, _) if software_gpu => {
                        Some(NERF_SMALL_BATCH_SAMPLES)
                    }
                    _ => None,
                }
            }),
            sampling: self.options.sampling,
            precision: self.options.precision,
        };
        let engine = self.engine.choice()?;
        let model: Box<dyn RadianceModel> =
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
            Command::ExportTurntable(settings) => self.start_export(settings)?,
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

    /// Starts or stops the models' taking turns. Models that cannot be
    /// built are left out (and reported); fewer than two leave the active
    /// model training alone.
    fn set_turns(&mut self, settings: Option<InTurn>) -> Result<(), UiGone> {
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
    fn trained_seconds(&self, kind: ModelKind) -> f64 {
        self.slot(kind).map_or(0.0, |s| s.trainer.train_seconds)
    }

    /// Starts the turns afresh after a model was reset or loaded, so that
    /// its new training time does not count as a share it had or owes.
    fn rebase_turns(&mut self) {
        if let Some(turns) = &self.turns {
            let settings = turns.settings();
            self.turns = Some(Turns::new(&settings, |kind| self.trained_seconds(kind)));
        }
    }

    /// Moves the turns on if the current model has had its slice, sending
    /// the stats of the model whose turn ended.
    fn take_turn(&mut self) -> Result<(), UiGone> {
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

    fn set_view(&mut self, request: RenderRequest) -> Result<(), UiGone> {
        if let Err(problem) = check_camera(&request.camera) {
            return self.send(Event::Error(format!(
                "render request {} refused: {problem}",
                request.generation
            )));
        }
        let now = Instant::now();
        let to_texture = self.draws_to_texture(&request);
        let same_picture = self.view.as_ref().is_some_and(|v| {
            v.request.camera == request.camera
                && v.shown
                    .as_ref()
                    .is_none_or(|shown| shown.picture.answers(&request, to_texture))
        });
        if same_picture {
            // The same picture (perhaps in another mode, which only changes
            // how pixels are shown): keep what was drawn and continue.
            let view = self.view.as_mut().expect("checked above");
            if view.request.moving && !request.moving {
                // The camera came to rest: the share starts from here, not
                // from the quarter training had while it moved.
                self.ledger = Ledger::default();
            }
            view.request = request;
            view.received = now;
            if let Some(shown) = view.shown.as_mut() {
                let event = shown.picture.resend(&view.request);
                return self.send(event);
            }
            return Ok(());
        }
        // A new camera: the time shared since the last one says nothing
        // about this one's refinement.
        self.ledger = Ledger::default();
        self.view = Some(View {
            request,
            received: now,
            job: None,
            shown: None,
        });
        Ok(())
    }

    /// Draws the view: one chunk of rays or band of rows, or the whole
    /// level it is on.
    fn render_unit(&mut self, whole_level: bool) -> Result<(), UiGone> {
        if self.slot(self.active).is_none() {
            // No model to draw with (its build failed and was reported).
            self.view = None;
            return Ok(());
        }
        if self.view.as_ref().is_some_and(|v| v.job.is_none()) {
            let Some(downscale) = self.next_level() else {
                return Ok(());
            };
            let job = self.start_level(downscale);
            if let Some(view) = self.view.as_mut() {
                view.job = Some(job);
            }
        }
        loop {
            let drawn = self.draw_part()?;
            let done = self
                .view
                .as_ref()
                .and_then(|v| v.job.as_ref())
                .is_none_or(LevelJob::is_done);
            if !drawn || done || !whole_level {
                break;
            }
        }
        let finished = self
            .view
            .as_ref()
            .and_then(|v| v.job.as_ref())
            .is_some_and(LevelJob::is_done);
        if finished {
            return self.finish_level();
        }
        // A level far over its budget while training waits on it is given
        // up for a coarser one, sized by what this one has cost so far;
        // whole levels (a new camera's first) are small and always finish.
        let budget = refresh_budget(self.training_share());
        if !whole_level
            && self.training_active()
            && let (Some(view), Some(slot)) = (
                self.view.as_mut(),
                self.slots.iter_mut().find(|s| s.kind == self.active),
            )
            && view.job.as_ref().is_some_and(|job| job.overruns(budget))
        {
            let job = view.job.take().expect("checked");
            slot.cost.replace(job.drawn(), job.seconds);
        }
        Ok(())
    }

    /// A level of the view at `downscale` of the active model's current
    /// state: into a texture when the window shares the engine's device.
    fn start_level(&mut self, downscale: u32) -> LevelJob {
        let view = self.view.as_ref().expect("a view to draw");
        let camera = level_camera(&view.request.camera, downscale);
        let request_to_texture = self.draws_to_texture(&view.request);
        let slot = self.slot(self.active).expect("checked by the caller");
        let (model, step, train_seconds, revision) = (
            slot.kind,
            slot.trainer.step,
            slot.trainer.train_seconds,
            slot.revision,
        );
        let draw = if request_to_texture {
            let (width, height) = (camera.intrinsics.width, camera.intrinsics.height);
            LevelDraw::Texture(TextureLevel {
                texture: self.texture(width, height),
                camera,
                next_row: 0,
            })
        } else {
            LevelDraw::Pixels(LevelRender::new(&view.request.camera, downscale))
        };
        LevelJob {
            downscale,
            model,
            step,
            train_seconds,
            revision,
            seconds: 0.0,
            draw,
        }
    }

    /// Draws the next chunk or band of the level in progress; false when
    /// there was nothing to draw.
    fn draw_part(&mut self) -> Result<bool, UiGone> {
        let active = self.active;
        let (Some(slot), Some(view)) = (
            self.slots.iter_mut().find(|s| s.kind == active),
            self.view.as_mut(),
        ) else {
            return Ok(false);
        };
        let Some(job) = view.job.as_mut() else {
            return Ok(false);
        };
        let started = Instant::now();
        let (rays, failure) = match &mut job.draw {
            LevelDraw::Pixels(render) => (
                render.render_chunk(slot.trainer.model.as_ref(), slot.pacer.chunk_rays(), WHITE),
                None,
            ),
            LevelDraw::Texture(level) => {
                let context = self.engine.gpu.as_ref();
                match (slot.trainer.model.texture_render(), context) {
                    (Some(gpu), Some(context)) => {
                        let width = level.camera.intrinsics.width.max(1);
                        // Whole rows, as many as the chunk's rays; not
                        // capped as chunks of pixels are (a real GPU draws
                        // a whole level in one band).
                        let rays = slot.pacer.uncapped_chunk_rays();
                        let rows = u32::try_from(rays / width as usize).unwrap_or(u32::MAX);
                        match draw_band(
                            gpu,
                            context,
                            level,
                            rows,
                            view.request.mode,
                            &mut self.textures,
                        ) {
                            Ok(drawn) => ((drawn * width) as usize, None),
                            Err(error) => (0, Some(error)),
                        }
                    }
                    _ => (0, Some("the model cannot draw into textures".to_string())),
                }
            }
        };
        let seconds = started.elapsed().as_secs_f64();
        if let Some(error) = failure {
            // Pixels still work: this level and every later one go through
            // the CPU.
            self.textures_shared = false;
            job.draw = LevelDraw::Pixels(LevelRender::new(&view.request.camera, job.downscale));
            self.send(Event::Error(format!(
                "drawing the view on the gpu failed ({error}); the view now comes \
                 through the CPU"
            )))?;
            return Ok(true);
        }
        slot.pacer.record(rays, seconds);
        job.seconds += seconds;
        let downscale = job.downscale;
        if !view.moving() {
            self.ledger.record_other(seconds);
        }
        self.trace.add_rendering(downscale, seconds, false);
        Ok(true)
    }

    /// Sends the finished level and keeps it as what is shown.
    fn finish_level(&mut self) -> Result<(), UiGone> {
        let active = self.active;
        let (Some(slot), Some(view)) = (
            self.slots.iter_mut().find(|s| s.kind == active),
            self.view.as_mut(),
        ) else {
            return Ok(());
        };
        let Some(job) = view.job.take() else {
            return Ok(());
        };
        slot.cost.record(job.pixels(), job.seconds);
        self.trace.add_rendering(job.downscale, 0.0, true);
        let picture = match job.draw {
            LevelDraw::Pixels(render) => Picture::Pixels(RenderedFrame {
                generation: view.request.generation,
                model: job.model,
                step: job.step,
                train_seconds: job.train_seconds,
                downscale: job.downscale,
                width: render.width(),
                height: render.height(),
                mode: view.request.mode,
                pixels: render.into_pixels(),
            }),
            LevelDraw::Texture(level) => {
                let texture = level.texture;
                self.textures.sent(&texture);
                Picture::Texture(GpuFrame {
                    generation: view.request.generation,
                    model: job.model,
                    step: job.step,
                    train_seconds: job.train_seconds,
                    downscale: job.downscale,
                    width: level.camera.intrinsics.width,
                    height: level.camera.intrinsics.height,
                    mode: view.request.mode,
                    texture,
                })
            }
        };
        let event = match &picture {
            Picture::Pixels(frame) => Event::Frame(frame.clone()),
            Picture::Texture(frame) => Event::GpuFrame(frame.clone()),
        };
        view.shown = Some(Shown {
            picture,
            revision: job.revision,
            downscale: job.downscale,
        });
        self.outbox.send(event)
    }

    /// Whether `request` is answered with a texture on the shared device.
    fn draws_to_texture(&self, request: &RenderRequest) -> bool {
        self.textures_shared
            && !request.needs_pixels
            && self
                .slot(self.active)
                .is_some_and(|s| s.trainer.model.texture_render().is_some())
    }

    /// A `width × height` texture to draw a level into.
    fn texture(&mut self, width: u32, height: u32) -> wgpu::Texture {
        let context = self.engine.gpu.as_ref().expect("textures need the device");
        self.textures.take(context, width, height)
    }

    fn train_unit(&mut self) -> Result<(), UiGone> {
        self.train_step(false)
    }

    /// One step of the model that trains (the active one, or the one whose
    /// turn it is); `report` sends its stats at once.
    fn train_step(&mut self, report: bool) -> Result<(), UiGone> {
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
        self.trace.grid_update_seconds += stats.times.grid_update;
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
    fn flush_stats(&mut self, kind: ModelKind) -> Result<(), UiGone> {
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
            times: StageTimes {
                march: per(t.march),
                encode: per(t.encode),
                networks_forward: per(t.networks_forward),
                composite: per(t.composite),
                networks_backward: per(t.networks_backward),
                encode_backward: per(t.encode_backward),
                optimiser: per(t.optimiser),
                grid_update: per(t.grid_update),
            },
        };
        slot.last_report = Some(TrainingStats {
            val_psnr: None,
            ..stats
        });
        self.outbox.send(Event::Stats(stats))
    }

    /// Renders one chunk of the held-out evaluation; reports the mean PSNR
    /// when the last pixel is scored.
    fn evaluate_unit(&mut self) -> Result<(), UiGone> {
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

    fn save_checkpoint(&mut self, path: &Path) -> Result<(), UiGone> {
        let Some(slot) = self.slot(self.active) else {
            return self.send(Event::Error(format!(
                "{}: no model to save (the {} model was not built)",
                path.display(),
                self.active.name()
            )));
        };
        let scene = match &self.source {
            SceneSource::Demo => "demo".to_string(),
            SceneSource::Folder(folder) => folder.display().to_string(),
        };
        let checkpoint = slot.trainer.checkpoint(serde_json::json!({
            "scene": scene,
            "model": slot.kind,
            "engine": self.engine.kind,
            "loss": slot.loss,
            "saved_by": "viewer",
        }));
        let step = slot.trainer.step;
        match checkpoint.save(path) {
            Ok(()) => {
                if let Some(slot) = self.slot_mut(self.active) {
                    slot.saved_step = step;
                }
                self.send(Event::CheckpointSaved(path.to_path_buf()))
            }
            Err(e) => self.send(Event::Error(e.to_string())),
        }
    }

    /// Keeps every model trained since it was last saved or loaded in a run
    /// folder of its own under [`WorkerOptions::autosave`], and says where
    /// on standard error (the window is closing: nobody reads events).
    ///
    /// Why save rather than ask: the window is closing because the user
    /// asked it to, and a prompt would make closing (and logging out, and
    /// a script's `--quit-after`) wait for an answer; editors and Blender
    /// keep unsaved work silently on quit for the same reason. Minutes of
    /// training cost more to redo than the disk they take.
    fn autosave(&mut self) {
        let Some(base) = self.options.autosave.clone() else {
            return;
        };
        let scene_key = match &self.source {
            SceneSource::Demo => "demo".to_string(),
            SceneSource::Folder(folder) => std::fs::canonicalize(folder)
                .unwrap_or_else(|_| folder.clone())
                .display()
                .to_string(),
        };
        let stamp = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_secs());
        for slot in &self.slots {
            if slot.trainer.step <= slot.saved_step {
                continue;
            }
            // Only plain characters of the scene's name: it may be any
            // folder's name, the run folder's must be a safe one.
            let scene_name: String = self
                .scene
                .name
                .chars()
                .map(|c| {
                    if c.is_alphanumeric() || c == '-' {
                        c
                    } else {
                        '_'
                    }
                })
                .collect();
            let folder = base.join(format!("{scene_name}-{}-{stamp}", slot.kind.key()));
            // The same keys as the command line's run.json, so `zrak train
            // --resume` rebuilds this scene and model.
            let run = serde_json::json!({
                "scene": scene_key,
                "model": slot.kind,
                "downscale": 1,
                "loss": slot.loss,
                "seed": slot.trainer.seed,
                "sampling": self.options.sampling,
                "engine": self.engine.kind,
                "precision": self.options.precision,
                "saved_by": "viewer",
            });
            let saved = std::fs::create_dir_all(&folder)
                .map_err(|e| format!("{}: cannot create the folder: {e}", folder.display()))
                .and_then(|()| {
                    let path = folder.join(crate::train::run::CONFIG_FILE);
                    crate::files::write_bytes_atomically(&path, format!("{run:#}").as_bytes())
                        .map_err(|e| format!("{}: cannot write: {e}", path.display()))
                })
                .and_then(|()| {
                    slot.trainer
                        .checkpoint(run.clone())
                        .save(&folder.join(crate::train::run::CHECKPOINT_FILE))
                        .map_err(|e| e.to_string())
                });
            match saved {
                Ok(()) => crate::interrupt::note(&format!(
                    "zrak view: kept {} at step {} in {}; continue it with \
                     `zrak train --resume {}` or load its checkpoint.zrak in the viewer",
                    slot.kind.name(),
                    slot.trainer.step,
                    folder.display(),
                    folder.display()
                )),
                Err(error) => crate::interrupt::note(&format!(
                    "zrak view: could not keep {} at step {}: {error}",
                    slot.kind.name(),
                    slot.trainer.step
                )),
            }
        }
        for removed in crate::train::kept::prune(&base, self.options.kept_runs) {
            crate::interrupt::note(&format!(
                "zrak view: removed the kept run {} (more than the newest {}; \
                 `zrak view --keep-runs N` keeps more)",
                removed.display(),
                self.options.kept_runs
            ));
        }
    }

    fn load_checkpoint(&mut self, path: &Path) -> Result<(), UiGone> {
        match self.restore_checkpoint(path) {
            Ok((kind, step)) => {
                if kind != self.active {
                    self.active = kind;
                    self.send(Event::ModelSelected(kind))?;
                }
                if let Some(view) = self.view.as_mut() {
                    view.restart();
                }
                self.send(Event::CheckpointLoaded {
                    path: path.to_path_buf(),
                    model: kind,
                    step,
                })
            }
            Err(e) => self.send(Event::Error(e)),
        }
    }

    /// Restores a checkpoint into its model's slot. The state is restored
    /// into a fresh trainer first, so a refused checkpoint changes nothing.
    fn restore_checkpoint(&mut self, path: &Path) -> Result<(ModelKind, u32), String> {
        let checkpoint = Checkpoint::load(path).map_err(|e| e.to_string())?;
        let model_header = &checkpoint.header["model"];
        let kind: ModelKind =
            serde_json::from_value(model_header["model"].clone()).map_err(|_| {
                format!(
                    "{}: the checkpoint does not name a model this zrak knows ({})",
                    path.display(),
                    model_header["model"]
                )
            })?;
        let loss: LossKind = serde_json::from_value(model_header["loss"].clone())
            .unwrap_or(self.options.loss.unwrap_or(kind.default_loss()));
        let mut trainer = self.build_trainer(kind)?;
        trainer
            .restore(&checkpoint)
            .map_err(|e| format!("{}: {e}", path.display()))?;
        let step = trainer.step;
        self.val_job = None;
        let slot = self.new_slot(kind, trainer, loss);
        match self.slot_mut(kind) {
            Some(existing) => *existing = slot,
            None => self.slots.push(slot),
        }
        self.rebase_turns();
        Ok((kind, step))
    }

    fn start_export(&mut self, settings: ExportSettings) -> Result<(), UiGone> {
        if self.export.is_some() {
            return self.send(Event::Error(
                "an export is already running; cancel it first".into(),
            ));
        }
        match ExportJob::start(&self.scene, settings, self.active) {
            Ok(job) => {
                let (done, total) = job.progress();
                self.export = Some(job);
                self.send(Event::ExportProgress { done, total })
            }
            Err(e) => self.send(Event::ExportFinished(Err(e))),
        }
    }

    /// Renders one export frame; training waits while an export runs.
    fn export_unit(&mut self) -> Result<(), UiGone> {
        let Some(mut job) = self.export.take() else {
            return Ok(());
        };
        let Some(slot) = self.slot(job.model) else {
            return self.send(Event::ExportFinished(Err(format!(
                "the export stopped: the {} model is gone",
                job.model.name()
            ))));
        };
        match job.render_next(slot.trainer.model.as_ref()) {
            Ok(more) => {
                let (done, total) = job.progress();
                self.send(Event::ExportProgress { done, total })?;
                if more {
                    self.export = Some(job);
                    Ok(())
                } else {
                    self.send(Event::ExportFinished(job.finish()))
                }
            }
            Err(e) => self.send(Event::ExportFinished(Err(e))),
        }
    }
}

/// Textures the view is drawn into, kept for reuse: level sizes change
/// with the camera and the model's cost, and bands come in a few sizes.
#[derive(Default)]
struct TexturePool {
    /// Least recently used first.
    kept: Vec<wgpu::Texture>,
    /// The textures of the last two frames sent: the window may still
    /// show either, so neither is drawn into.
    sent: [Option<wgpu::Texture>; 2],
}

impl TexturePool {
    /// A `width × height` texture no frame the window may still show
    /// holds: a kept one, else a new one.
    fn take(&mut self, context: &GpuContext, width: u32, height: u32) -> wgpu::Texture {
        let sent = &self.sent;
        let free = self.kept.iter().position(|t| {
            (t.width(), t.height()) == (width, height) && !sent.iter().flatten().any(|s| s == t)
        });
        let texture = match free {
            Some(index) => self.kept.remove(index),
            None => render_target(&context.device, width, height),
        };
        self.kept.push(texture.clone());
        if self.kept.len() > MAX_KEPT_TEXTURES
            && let Some(oldest) = self
                .kept
                .iter()
                .position(|t| !self.sent.iter().flatten().any(|s| s == t))
        {
            self.kept.remove(oldest);
        }
        texture
    }

    /// `texture` went to the window in a frame.
    fn sent(&mut self, texture: &wgpu::Texture) {
        self.sent = [Some(texture.clone()), self.sent[0].take()];
    }
}

/// Draws up to `rows` more rows of `level` (at least one) and returns how
/// many: the whole level at once when one band covers it, else through a
/// texture of the band's size ([`draw_band_to_texture`]).
fn draw_band(
    gpu: &dyn crate::train::model::TextureRender,
    context: &GpuContext,
    level: &mut TextureLevel,
    rows: u32,
    mode: crate::render::RenderMode,
    textures: &mut TexturePool,
) -> Result<u32, String> {
    let k = level.camera.intrinsics;
    let rows = rows.clamp(1, k.height.saturating_sub(level.next_row).max(1));
    if level.next_row == 0 && rows == k.height {
        gpu.render_to_texture(&level.camera, mode, WHITE, &level.texture)?;
    } else {
        let band = textures.take(context, k.width, rows);
        draw_band_to_texture(
            gpu,
            context,
            &level.camera,
            level.next_row,
            mode,
            WHITE,
            &band,
            &level.texture,
        )?;
    }
    level.next_row += rows;
    Ok(rows)
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

/// Why a camera cannot be rendered, if it cannot.
fn check_camera(camera: &Camera) -> Result<(), String> {
    let k = camera.intrinsics;
    if k.width == 0 || k.height == 0 || k.width > MAX_VIEWPORT_SIDE || k.height > MAX_VIEWPORT_SIDE
    {
        return Err(format!(
            "the viewport is {}×{} pixels (each side must be 1 to {MAX_VIEWPORT_SIDE})",
            k.width, k.height
        ));
    }
    let focal_ok = [k.fx, k.fy].iter().all(|f| f.is_finite() && *f > 0.0);
    let centre_ok = k.cx.is_finite() && k.cy.is_finite();
    if !focal_ok || !centre_ok {
        return Err(format!(
            "the intrinsics are not usable (fx {}, fy {}, cx {}, cy {})",
            k.fx, k.fy, k.cx, k.cy
        ));
    }
    if !camera
        .camera_to_world
        .to_cols_array()
        .iter()
        .all(|v| v.is_finite())
    {
        return Err("the camera pose holds a non-finite number".into());
    }
    Ok(())
}

/// A turntable export in progress, with the model it renders.
struct ExportJob {
    model: ModelKind,
    export: TurntableExport,
}

impl ExportJob {
    fn start(
        scene: &Scene,
        settings: ExportSettings,
        model: ModelKind,
    ) -> Result<ExportJob, String> {
        Ok(ExportJob {
            model,
            export: TurntableExport::start(scene, settings)?,
        })
    }

    fn progress(&self) -> (usize, usize) {
        (self.export.done(), self.export.total())
    }

    fn render_next(&mut self, model: &dyn RadianceModel) -> Result<bool, String> {
        self.export.render_next(model)
    }

    fn finish(self) -> Result<Vec<PathBuf>, String> {
        self.export.finish()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Simulates the worker's loop: each model's steps take a fixed time;
    /// returns each model's training seconds and the order of the turns.
    fn simulate(
        settings: &InTurn,
        step_seconds: &[f64],
        total_seconds: f64,
    ) -> (Vec<f64>, Vec<ModelKind>) {
        let index = |kind: ModelKind| settings.models.iter().position(|&m| m == kind).unwrap();
        let mut trained = vec![0.0; settings.models.len()];
        let mut turns = Turns::new(settings, |_| 0.0);
        let mut order = Vec::new();
        while trained.iter().sum::<f64>() < total_seconds {
            let kind = turns.model_to_train(|m| trained[index(m)]);
            if order.last() != Some(&kind) {
                order.push(kind);
            }
            trained[index(kind)] += step_seconds[index(kind)];
        }
        (trained, order)
    }

    #[test]
    fn turns_go_round_in_order_at_equal_shares_of_training_time() {
        let settings = InTurn {
            models: vec![ModelKind::Ngp, ModelKind::Nerf, ModelKind::MipNerf],
            slice_seconds: 0.5,
        };
        // Steps of very different cost, none dividing the slice evenly.
        let steps = [0.013, 0.07, 0.3];
        let (trained, order) = simulate(&settings, &steps, 60.0);
        let expected: Vec<ModelKind> = (0..order.len()).map(|i| settings.models[i % 3]).collect();
        assert_eq!(order, expected);
        assert!(order.len() >= 3 * 30, "{} turns", order.len());
        // Within one slice and one step of each other, however many turns
        // (the overshoot of each turn does not add up).
        let (low, high) = trained
            .iter()
            .fold((f64::INFINITY, 0f64), |(l, h), &t| (l.min(t), h.max(t)));
        assert!(high - low <= 0.5 + 0.3 + 1e-9, "{trained:?}");
        // The slowest model's share is a third to within that bound.
        assert!((trained[2] / trained.iter().sum::<f64>() - 1.0 / 3.0).abs() < 0.02);
    }

    #[test]
    fn a_step_longer_than_the_slice_still_passes_the_turn_on() {
        let settings = InTurn {
            models: vec![ModelKind::Ngp, ModelKind::Nerf],
            slice_seconds: 0.1,
        };
        let (trained, order) = simulate(&settings, &[0.01, 0.35], 10.0);
        assert_eq!(
            &order[..4],
            [
                ModelKind::Ngp,
                ModelKind::Nerf,
                ModelKind::Ngp,
                ModelKind::Nerf
            ]
        );
        assert!(
            (trained[0] - trained[1]).abs() <= 0.1 + 0.35 + 1e-9,
            "{trained:?}"
        );
    }
}
