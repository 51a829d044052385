//! The viewer's window contents: panels, viewport, plots. Everything here
//! runs on the UI thread and talks to the training thread only through a
//! [`TrainingLink`], which never blocks: commands are sent, events are
//! polled with `try_recv` once per frame.
//!
//! [`ViewerUi`] knows nothing of eframe, so tests drive it with
//! `egui_kittest` and a link they can inspect.

use eframe::egui;
mod crop;
mod export;
pub mod overlay;
mod panels;
mod path_editor;
mod path_overlay;
mod plots;
mod viewport;

use std::collections::VecDeque;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use crate::engine::EngineKind;
use crate::field::ModelKind;
use crate::model::RenderMode;
use crate::session::camera::ViewCamera;
use crate::session::path_state::PathEditor;
use crate::session::protocol::{
    Balance, Command, Event, InTurn, SceneInfo, SceneSource, TrainingStats,
};
use crate::session::schedule::ScheduleTrace;
use crate::session::worker::TrainingWorker;

pub use crop::CropPanel;
pub use export::{ExportDialog, ExportKind};
pub use path_editor::request_path_export;
pub use plots::{History, HistoryPoint, PlotAxis, comparison_table, export_comparison};
pub use viewport::{CompareMode, CompareWith, ShownFrame, ViewportState};

/// The UI's end of the channel to the training thread.
pub trait TrainingLink {
    /// Queues a command; never waits for the thread.
    fn send(&self, command: Command);
    /// The next event, if one is waiting.
    fn try_recv(&self) -> Option<Event>;
    /// Stops the thread and waits for it to finish.
    fn shutdown(self: Box<Self>) {
        self.send(Command::Shutdown);
    }
}

impl TrainingLink for TrainingWorker {
    fn send(&self, command: Command) {
        TrainingWorker::send(self, command);
    }

    fn try_recv(&self) -> Option<Event> {
        TrainingWorker::try_recv(self)
    }

    fn shutdown(self: Box<Self>) {
        TrainingWorker::shutdown(*self);
    }
}

/// Makes textures the training thread drew on the GPU ([`GpuFrame`])
/// drawable by egui. The eframe app implements it with egui-wgpu's
/// renderer (`viewer.rs`); a UI without one (the kittest tests, whose
/// thread never shares a device) drops such frames.
///
/// [`GpuFrame`]: crate::session::protocol::GpuFrame
pub trait NativeTextures {
    /// An egui id showing `texture`: `previous` re-pointed at it when
    /// given (so ids are reused, not leaked), else a new one.
    fn register(
        &mut self,
        texture: &wgpu::Texture,
        previous: Option<egui::TextureId>,
    ) -> egui::TextureId;
    /// Lets go of an id from [`Self::register`] (and of its texture).
    fn free(&mut self, id: egui::TextureId);
}

/// A link to nothing, left behind once the real one has been shut down.
struct ClosedLink;

impl TrainingLink for ClosedLink {
    fn send(&self, _command: Command) {}

    fn try_recv(&self) -> Option<Event> {
        None
    }
}

/// Most events handled in one frame: a thread that floods the channel must
/// not stall the UI; the rest wait for the next frame.
const MAX_EVENTS_PER_FRAME: usize = 512;

/// How often training progress is written to stderr.
const PROGRESS_LOG_INTERVAL: Duration = Duration::from_secs(2);

/// How many notices the side panel keeps.
const MAX_NOTICES: usize = 6;

/// A line for the user: what happened, and whether it went wrong.
#[derive(Debug, Clone, PartialEq)]
pub struct Notice {
    pub text: String,
    pub is_error: bool,
}

/// Everything the window shows and remembers between frames.
pub struct ViewerUi {
    link: Box<dyn TrainingLink>,
    started: Instant,
    scene: Option<SceneInfo>,
    /// The scene being opened, until the thread answers.
    opening: Option<SceneSource>,
    /// Why the last scene failed to open, naming the folder.
    scene_error: Option<String>,
    notices: VecDeque<Notice>,
    engine: Option<(EngineKind, String)>,
    /// The adapter egui draws with (not necessarily the training engine's).
    display_adapter: Option<String>,
    active_model: ModelKind,
    running: bool,
    /// The models taking turns at training, as the thread last said.
    in_turn: Option<InTurn>,
    histories: Vec<History>,
    balance: Balance,
    mode: RenderMode,
    /// The training image whose appearance vector models with embeddings
    /// draw with (`None`: their mean).
    appearance_view: Option<usize>,
    camera: Option<ViewCamera>,
    viewport: ViewportState,
    plot_axis: PlotAxis,
    /// What the timing column shows.
    timing: TimingView,
    export: ExportDialog,
    crop: CropPanel,
    scene_path_text: String,
    checkpoint_path_text: String,
    /// Where the plot and table are exported.
    comparison_folder: String,
    /// Whether a native file dialog can open here (portal or zenity).
    dialogs_available: bool,
    /// The camera turns by itself as if dragged (for measuring).
    auto_orbit: bool,
    last_progress_log: Option<Instant>,
    /// The last stats logged, so a paused thread is not logged again.
    last_logged_step: Option<(ModelKind, u32)>,
    log_progress: bool,
    /// How frames drawn on the GPU reach the screen, when they can.
    native_textures: Option<Box<dyn NativeTextures>>,
    /// The training thread's recent schedule traces (wall seconds since
    /// the window opened when each came), for "where the time goes".
    schedule_recent: VecDeque<(f64, ScheduleTrace)>,
    /// Every trace of the session added up.
    schedule_total: ScheduleTrace,
    /// See [`Self::schedule_log`].
    schedule_log: Vec<(f64, f64, f64)>,
    /// At most how often the window redraws while the camera rests
    /// (`None`: whenever something changed); see [`Self::set_resting_redraw`].
    resting_redraw: Option<Duration>,
    /// Each frame shown: when (wall seconds since the window opened) and
    /// what, for the frame log.
    shown_log: Vec<(f64, ShownFrame)>,
    /// The camera-path editor (`path_editor.rs`).
    path_editor: PathEditor,
}

/// What the timing column beside the stats shows (one column, so the
/// plots keep their width).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TimingView {
    /// The stages of a training step.
    Stages,
    /// Where the training thread's wall time goes.
    Thread,
}

/// How many seconds of schedule traces the stats panel adds up.
pub const SCHEDULE_WINDOW_SECONDS: f64 = 10.0;

impl ViewerUi {
    /// A window talking to `link`, whose thread trains `model` first.
    pub fn new(link: Box<dyn TrainingLink>, model: ModelKind) -> Self {
        Self {
            link,
            started: Instant::now(),
            scene: None,
            opening: None,
            scene_error: None,
            notices: VecDeque::new(),
            engine: None,
            display_adapter: None,
            active_model: model,
            running: false,
            in_turn: None,
            histories: Vec::new(),
            balance: Balance::default(),
            mode: RenderMode::Rgb,
            appearance_view: None,
            camera: None,
            viewport: ViewportState::default(),
            plot_axis: PlotAxis::Step,
            timing: TimingView::Thread,
            export: ExportDialog::default(),
            crop: CropPanel::default(),
            scene_path_text: String::new(),
            checkpoint_path_text: String::new(),
            comparison_folder: std::env::temp_dir()
                .join("zrak-comparison")
                .display()
                .to_string(),
            dialogs_available: panels::file_dialog_available(),
            auto_orbit: false,
            last_progress_log: None,
            last_logged_step: None,
            log_progress: false,
            native_textures: None,
            schedule_recent: VecDeque::new(),
            schedule_total: ScheduleTrace::default(),
            schedule_log: Vec::new(),
            resting_redraw: None,
            shown_log: Vec::new(),
            path_editor: PathEditor::default(),
        }
    }

    /// Lets the window show frames the training thread draws on the GPU
    /// (the eframe app passes egui-wgpu's renderer).
    pub fn set_native_textures(&mut self, textures: Box<dyn NativeTextures>) {
        self.native_textures = Some(textures);
    }

    /// Writes one line of training progress to stderr every ~2 s.
    pub fn set_log_progress(&mut self, on: bool) {
        self.log_progress = on;
    }

    /// Turns the camera by itself, as if dragged, so that a moving camera
    /// can be measured without a mouse.
    pub fn set_auto_orbit(&mut self, on: bool) {
        self.auto_orbit = on;
    }

    /// Redraws at most every `interval` while the camera rests (it redraws
    /// at once while it moves): the viewer asks this on a software
    /// rasteriser, where a frame of the window costs a good part of a core
    /// and redrawing on every stats event took as much CPU as training.
    pub fn set_resting_redraw(&mut self, interval: Option<Duration>) {
        self.resting_redraw = interval;
    }

    /// Names the adapter egui draws with, for the stats panel.
    pub fn set_display_adapter(&mut self, description: String) {
        self.display_adapter = Some(description);
    }

    /// Says whether native file dialogs work here (tests turn them off).
    pub fn set_dialogs_available(&mut self, available: bool) {
        self.dialogs_available = available;
    }

    /// Sets the crop box (`zrak view --crop`) and opens its window.
    pub fn set_crop(&mut self, crop: Option<crate::scene::crop::CropBox>) {
        self.crop.show_box(crop);
        self.crop.open = true;
        self.send(Command::SetCrop(crop));
    }

    /// Opens the Export window on `kind` (`zrak view --open-export`).
    pub fn open_export(&mut self, kind: ExportKind) {
        self.export.kind = kind;
        self.export.open = true;
    }

    /// The crop box window's state.
    pub fn crop_panel(&self) -> &CropPanel {
        &self.crop
    }

    /// Marks the scene being opened (e.g. the one the thread was spawned
    /// with), so the panel says so until it has loaded.
    pub fn set_opening(&mut self, source: SceneSource) {
        self.opening = Some(source);
    }

    pub fn active_model(&self) -> ModelKind {
        self.active_model
    }

    pub fn render_mode(&self) -> RenderMode {
        self.mode
    }

    pub fn is_running(&self) -> bool {
        self.running
    }

    pub fn scene(&self) -> Option<&SceneInfo> {
        self.scene.as_ref()
    }

    pub fn scene_error(&self) -> Option<&str> {
        self.scene_error.as_deref()
    }

    pub fn notices(&self) -> impl Iterator<Item = &Notice> {
        self.notices.iter()
    }

    /// The latest figures of `model`, if it has trained in this session.
    pub fn latest_stats(&self, model: ModelKind) -> Option<&TrainingStats> {
        self.history(model).and_then(|h| h.latest.as_ref())
    }

    pub fn history(&self, model: ModelKind) -> Option<&History> {
        self.histories.iter().find(|h| h.model == model)
    }

    pub fn viewport(&self) -> &ViewportState {
        &self.viewport
    }

    pub fn timing_view(&self) -> TimingView {
        self.timing
    }

    pub fn set_timing_view(&mut self, view: TimingView) {
        self.timing = view;
    }

    /// The training thread's schedule over about the last
    /// [`SCHEDULE_WINDOW_SECONDS`] of wall time, if it sent any.
    pub fn recent_schedule(&self) -> Option<ScheduleTrace> {
        let mut sum: Option<ScheduleTrace> = None;
        for (_, trace) in &self.schedule_recent {
            sum.get_or_insert_with(ScheduleTrace::default).merge(trace);
        }
        sum
    }

    /// Every schedule trace of the session added up.
    pub fn schedule_total(&self) -> &ScheduleTrace {
        &self.schedule_total
    }

    /// Each frame shown, with when it came (wall seconds since the window
    /// opened).
    pub fn shown_log(&self) -> &[(f64, ShownFrame)] {
        &self.shown_log
    }

    /// Training seconds the shown frame is behind its model's training
    /// (as of the model's latest stats), when both are known.
    pub fn shown_lag_seconds(&self) -> Option<f64> {
        let shown = self.viewport.shown()?;
        let latest = self.latest_stats(shown.model)?;
        Some((latest.train_seconds - shown.train_seconds).max(0.0))
    }

    /// When each schedule trace came (wall seconds since the window
    /// opened), with the wall and training seconds it covered: the share
    /// over any stretch of the session.
    pub fn schedule_log(&self) -> &[(f64, f64, f64)] {
        &self.schedule_log
    }

    fn record_schedule(&mut self, trace: ScheduleTrace) {
        let now = self.started.elapsed().as_secs_f64();
        self.schedule_log
            .push((now, trace.wall_seconds, trace.training_seconds));
        self.schedule_total.merge(&trace);
        self.schedule_recent.push_back((now, trace));
        while self
            .schedule_recent
            .front()
            .is_some_and(|(at, _)| now - at > SCHEDULE_WINDOW_SECONDS)
        {
            self.schedule_recent.pop_front();
        }
    }

    /// True when a drag, a fly key, a scroll or the auto-orbit moved the
    /// camera in the last frame.
    pub fn camera_moving(&self) -> bool {
        self.viewport.moving
    }

    /// Asks the thread to open a scene folder (the previous scene keeps
    /// training until the new one has loaded).
    pub fn open_scene(&mut self, path: PathBuf) {
        self.scene_path_text = path.display().to_string();
        let source = SceneSource::Folder(path);
        self.opening = Some(source.clone());
        self.scene_error = None;
        self.link.send(Command::OpenScene(source));
    }

    /// Makes `kind` the model that trains and renders.
    pub fn select_model(&mut self, kind: ModelKind) {
        if kind != self.active_model {
            self.active_model = kind;
            self.link.send(Command::SelectModel(kind));
            // Frames of the previous model no longer answer what is shown.
            self.viewport.invalidate();
        }
    }

    /// Models with appearance embeddings draw with training image
    /// `image`'s vector, or their mean (`None`).
    pub fn set_appearance_view(&mut self, image: Option<usize>) {
        if self.appearance_view != image {
            self.appearance_view = image;
            self.link.send(Command::SetAppearance(image));
        }
    }

    /// The training image models with appearance embeddings draw with.
    pub fn appearance_view(&self) -> Option<usize> {
        self.appearance_view
    }

    pub fn set_render_mode(&mut self, mode: RenderMode) {
        // The next frame's request carries the mode; nothing else to send.
        self.mode = mode;
    }

    /// Starts or pauses training; the button shows the state the thread
    /// last reported, and is updated optimistically until it answers.
    pub fn toggle_running(&mut self) {
        if self.running {
            self.link.send(Command::Pause);
        } else {
            self.link.send(Command::Start);
        }
        self.running = !self.running;
    }

    /// The models taking turns at training, if they are.
    pub fn in_turn(&self) -> Option<&InTurn> {
        self.in_turn.as_ref()
    }

    pub fn plot_axis(&self) -> PlotAxis {
        self.plot_axis
    }

    /// Starts every model training in turn at equal shares of training
    /// time (and training, if paused), with the curves against training
    /// time; or stops the turns, leaving the active model training alone.
    pub fn toggle_in_turn(&mut self) {
        if self.in_turn.is_some() {
            self.link.send(Command::TrainInTurn(None));
            self.in_turn = None;
            return;
        }
        let settings = InTurn::all();
        self.link.send(Command::TrainInTurn(Some(settings.clone())));
        self.in_turn = Some(settings);
        // Models trained in turn share the wall clock: their own training
        // time is what compares them.
        self.plot_axis = PlotAxis::TrainTime;
        if !self.running {
            self.toggle_running();
        }
    }

    /// Sets the folder the plot and the table are exported to.
    pub fn set_comparison_folder(&mut self, folder: impl Into<String>) {
        self.comparison_folder = folder.into();
    }

    /// Writes the session's comparison (PSNR plot as PNG and SVG, the table
    /// as Markdown and CSV) into the export folder, and says so.
    pub fn export_comparison(&mut self) -> Result<Vec<PathBuf>, String> {
        let folder = PathBuf::from(self.comparison_folder.trim());
        let result = export_comparison(&self.histories, &folder);
        match &result {
            Ok(files) => self.notice(
                format!("Exported {} files to {}", files.len(), folder.display()),
                false,
            ),
            Err(error) => self.notice(format!("Export failed: {error}"), true),
        }
        result
    }

    /// Hands the link back (for shutdown), leaving a closed one behind.
    pub fn take_link(&mut self) -> Box<dyn TrainingLink> {
        std::mem::replace(&mut self.link, Box::new(ClosedLink))
    }

    fn send(&self, command: Command) {
        self.link.send(command);
    }

    fn notice(&mut self, text: impl Into<String>, is_error: bool) {
        let text = text.into();
        if is_error {
            eprintln!("zrak: {text}");
        }
        self.notices.push_back(Notice { text, is_error });
        while self.notices.len() > MAX_NOTICES {
            self.notices.pop_front();
        }
    }

    /// Draws the whole window for one frame.
    pub fn show(&mut self, ui: &mut egui::Ui) {
        let ctx = ui.ctx().clone();
        let got_events = self.poll_events(&ctx);
        self.take_dropped_folders(&ctx);
        self.log_progress_line();

        panels::menu_bar(self, ui);
        panels::controls_panel(self, ui);
        panels::bottom_panel(self, ui);
        // Before the viewport: the camera the path moves is the one this
        // frame renders.
        path_editor::panel(self, ui);
        egui::CentralPanel::default().show(ui, |ui| {
            viewport::show(self, ui);
        });
        export::export_window(self, &ctx);
        crop::crop_window(self, &ctx);

        // Training or a moving camera keeps the picture changing; the worker
        // may also wake us through its repaint callback, but a steady tick
        // keeps plots and stats live even without one.
        if self.viewport.moving || self.auto_orbit {
            ctx.request_repaint();
        } else if got_events || self.running {
            match self.resting_redraw {
                Some(interval) => ctx.request_repaint_after(interval),
                None => ctx.request_repaint(),
            }
        } else {
            ctx.request_repaint_after(Duration::from_millis(250));
        }
    }

    /// Handles waiting events; true if there were any.
    fn poll_events(&mut self, ctx: &egui::Context) -> bool {
        let mut newest_frame = None;
        let mut count = 0;
        while count < MAX_EVENTS_PER_FRAME {
            let Some(event) = self.link.try_recv() else {
                break;
            };
            count += 1;
            match event {
                Event::Frame(frame) => {
                    // Only the newest frame is worth uploading.
                    if self.viewport.accepts(frame.generation) {
                        newest_frame = Some(NewFrame::Pixels(frame));
                    }
                }
                Event::GpuFrame(frame) => {
                    if self.native_textures.is_some() && self.viewport.accepts(frame.generation) {
                        newest_frame = Some(NewFrame::Texture(frame));
                    } else if self.native_textures.is_none() {
                        self.viewport.frames_dropped += 1;
                    }
                }
                other => self.handle_event(other),
            }
        }
        let shown_before = self.viewport.frames_shown;
        match (newest_frame, self.native_textures.as_deref_mut()) {
            (Some(NewFrame::Pixels(frame)), textures) => {
                let released = self.viewport.show_frame(ctx, frame);
                if let (Some(id), Some(textures)) = (released, textures) {
                    textures.free(id);
                }
            }
            (Some(NewFrame::Texture(frame)), Some(textures)) => {
                self.viewport.show_gpu_frame(frame, textures)
            }
            _ => {}
        }
        if self.viewport.frames_shown != shown_before
            && let Some(shown) = self.viewport.shown()
        {
            self.shown_log
                .push((self.started.elapsed().as_secs_f64(), shown));
        }
        count > 0
    }

    fn handle_event(&mut self, event: Event) {
        match event {
            Event::SceneLoaded(info) => {
                if self.opening.as_ref() == Some(&info.source) {
                    self.opening = None;
                }
                self.scene_error = None;
                self.notice(
                    format!(
                        "Opened {} ({} training views)",
                        describe_source(&info.source),
                        info.scene.train.len()
                    ),
                    false,
                );
                match &mut self.camera {
                    Some(camera) => camera.reset(&info.scene),
                    None => self.camera = Some(ViewCamera::for_scene(&info.scene)),
                }
                // Every model's state of the previous scene is gone, and
                // with it the crop box (the first scene keeps `--crop`'s).
                self.crop
                    .scene_changed(info.scene.bounds, self.scene.is_none());
                self.histories.clear();
                self.viewport.scene_changed();
                self.appearance_view = None;
                self.scene = Some(info);
            }
            Event::SceneFailed { source, error } => {
                if self.opening.as_ref() == Some(&source) {
                    self.opening = None;
                }
                let text = format!("Could not open {}: {error}", describe_source(&source));
                self.scene_error = Some(text.clone());
                self.notice(text, true);
            }
            Event::Engine { kind, description } => {
                self.engine = Some((kind, description));
            }
            Event::ModelSelected(kind) => {
                self.active_model = kind;
            }
            Event::InTurn(settings) => self.in_turn = settings,
            Event::Running(running) => self.running = running,
            Event::Stats(stats) => self.record_stats(stats),
            Event::Schedule(trace) => self.record_schedule(trace),
            Event::Frame(_) | Event::GpuFrame(_) => {}
            Event::CheckpointSaved(path) => {
                self.notice(format!("Saved checkpoint {}", path.display()), false);
            }
            Event::CheckpointLoaded { path, model, step } => {
                self.notice(
                    format!(
                        "Loaded {} at step {step} from {}",
                        model.name(),
                        path.display()
                    ),
                    false,
                );
                // The loaded model continues from `step`: its curve restarts.
                if let Some(history) = self.histories.iter_mut().find(|h| h.model == model) {
                    history.points.retain(|p| p.step <= step);
                }
                self.active_model = model;
                self.viewport.invalidate();
            }
            Event::ExportProgress { done, total } => {
                self.export.progress = Some((done, total));
            }
            Event::ExportFinished(result) => {
                self.export.progress = None;
                match result {
                    Ok(files) => {
                        let folder = files
                            .first()
                            .and_then(|f| f.parent())
                            .map(|p| p.display().to_string())
                            .unwrap_or_default();
                        let text = match &files[..] {
                            [one] => format!("Exported {}", one.display()),
                            _ => format!("Exported {} files to {folder}", files.len()),
                        };
                        self.export.result = Some(Notice {
                            text: text.clone(),
                            is_error: false,
                        });
                        self.notice(text, false);
                    }
                    Err(error) => {
                        let text = format!("Export stopped: {error}");
                        self.export.result = Some(Notice {
                            text: text.clone(),
                            is_error: true,
                        });
                        self.notice(text, true);
                    }
                }
            }
            Event::CropSet { crop, refused } => {
                if let Some(problem) = &refused {
                    self.notice(format!("Crop box refused: {problem}"), true);
                }
                self.crop.answered(crop, refused);
            }
            Event::Error(error) => self.notice(error, true),
        }
    }

    fn record_stats(&mut self, stats: TrainingStats) {
        let wall_seconds = self.started.elapsed().as_secs_f64();
        let history = match self
            .histories
            .iter_mut()
            .position(|h| h.model == stats.model)
        {
            Some(i) => &mut self.histories[i],
            None => {
                self.histories.push(History::new(stats.model));
                self.histories.last_mut().expect("just pushed")
            }
        };
        history.record(&stats, wall_seconds);
    }

    /// Folders dropped onto the window open as scenes; a dropped file opens
    /// the folder it lies in (e.g. a transforms.json).
    fn take_dropped_folders(&mut self, ctx: &egui::Context) {
        let dropped: Vec<PathBuf> = ctx.input(|i| {
            i.raw
                .dropped_files
                .iter()
                .map(|f| f.path().to_path_buf())
                .collect()
        });
        if let Some(path) = dropped.into_iter().next() {
            let folder = if path.is_file() {
                path.parent().map(Path::to_path_buf).unwrap_or(path)
            } else {
                path
            };
            self.open_scene(folder);
        }
    }

    fn log_progress_line(&mut self) {
        if !self.log_progress {
            return;
        }
        let now = Instant::now();
        if self
            .last_progress_log
            .is_some_and(|last| now.duration_since(last) < PROGRESS_LOG_INTERVAL)
        {
            return;
        }
        let Some(stats) = self.latest_stats(self.active_model).copied() else {
            return;
        };
        if self.last_logged_step == Some((stats.model, stats.step)) {
            return;
        }
        self.last_progress_log = Some(now);
        self.last_logged_step = Some((stats.model, stats.step));
        let psnr = |value: Option<f32>| value.map_or("-".to_string(), |v| format!("{v:.2}"));
        let shown = match self.viewport.shown() {
            Some(shown) => format!(
                " shown step {} at 1/{} ({}x{}, {:.1}s of training behind)",
                shown.step,
                shown.downscale,
                shown.width,
                shown.height,
                self.shown_lag_seconds().unwrap_or(0.0)
            ),
            None => String::new(),
        };
        let share = self
            .recent_schedule()
            .filter(|t| t.wall_seconds > 0.0)
            .map_or(String::new(), |t| {
                format!(" training share {:.2}", t.training_seconds / t.wall_seconds)
            });
        eprintln!(
            "zrak view: {} step {} loss {:.5} psnr {} val_psnr {} ms/step {:.1} wall {:.1}s{shown}{share}",
            stats.model.name(),
            stats.step,
            stats.loss,
            psnr(stats.batch_psnr),
            psnr(self.history(stats.model).and_then(|h| h.latest_val_psnr())),
            stats.ms_per_step,
            self.started.elapsed().as_secs_f64()
        );
    }
}

/// The newest frame of a batch of events, either kind.
enum NewFrame {
    Pixels(crate::session::protocol::RenderedFrame),
    Texture(crate::session::protocol::GpuFrame),
}

/// "the demo scene" or the folder's path.
pub fn describe_source(source: &SceneSource) -> String {
    match source {
        SceneSource::Demo => "the built-in demo scene".to_string(),
        SceneSource::Folder(path) => path.display().to_string(),
    }
}
