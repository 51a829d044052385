//! The eframe application: opens the window (wgpu), spawns the training
//! thread, and adds what measuring and CI need around [`ViewerUi`]: a
//! screenshot after a delay, closing by itself, and a log of frame times.

use eframe::egui;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::Context as _;
use eframe::egui_wgpu::{WgpuConfiguration, WgpuSetup, WgpuSetupCreateNew};
use eframe::wgpu;

use super::ui::{NativeTextures, ViewerUi, describe_source};
use crate::engine::EngineKind;
use crate::engine::gpu::GpuContext;
use crate::field::ModelKind;
use crate::field::common::Sampling;
use crate::field::mlp::Precision;
use crate::session::protocol::{Command, SceneSource};
use crate::session::worker::{TrainingWorker, WorkerOptions};

/// What `zrak view` was asked to do.
#[derive(Debug, Clone)]
pub struct ViewerOptions {
    pub source: SceneSource,
    pub engine: Option<EngineKind>,
    pub model: ModelKind,
    /// The sampler asked for (each model that has it trains with it);
    /// `None` chooses per model from the scene's space.
    pub sampling: Option<Sampling>,
    /// Save a PNG of the window here, `screenshot_after` seconds in.
    pub screenshot: Option<PathBuf>,
    pub screenshot_after: f64,
    /// Close the window by itself after this many seconds.
    pub quit_after: Option<f64>,
    /// On exit, write the frame times here as JSON.
    pub frame_log: Option<PathBuf>,
    /// Orbit the camera by itself, as if dragged.
    pub auto_orbit: bool,
    /// How the cpu engine computes the networks' products.
    pub precision: Precision,
    /// How many of the runs kept on closing stay on disk (the newest).
    pub kept_runs: usize,
    /// The crop box to start with (its window opens).
    pub crop: Option<crate::scene::crop::CropBox>,
    /// Open the Export window on this kind at the start.
    pub open_export: Option<super::ui::ExportKind>,
    /// A `camera_path.json` to open in the path editor, and the time of the
    /// path to put the camera at.
    pub camera_path: Option<PathBuf>,
    pub path_time: Option<f64>,
    /// Play the camera path from the start (or `path_time`).
    pub path_play: bool,
    /// What every scene opened is treated as; `None` leaves it to the
    /// scene analysis.
    pub space: Option<crate::scene::SceneSpace>,
    /// Per-image appearance and camera refinement for every scene opened.
    pub photographs: crate::scene::photographs::Switches,
}

impl Default for ViewerOptions {
    fn default() -> Self {
        Self {
            source: SceneSource::Demo,
            engine: None,
            model: ModelKind::Ngp,
            sampling: None,
            screenshot: None,
            screenshot_after: 5.0,
            quit_after: None,
            frame_log: None,
            auto_orbit: false,
            precision: Precision::best_available(),
            kept_runs: crate::train::kept::DEFAULT_KEPT_RUNS,
            crop: None,
            open_export: None,
            camera_path: None,
            path_time: None,
            path_play: false,
            space: None,
            photographs: Default::default(),
        }
    }
}

/// The largest texture side the window asks for: a 4K screen's width
/// twice over, as egui-wgpu's own default (it asks 8192).
const MAX_TEXTURE_SIDE: u32 = 8192;

/// How long `--quit-after` waits past its time for a screenshot that is
/// still on its way.
const SCREENSHOT_GRACE: Duration = Duration::from_secs(10);

/// eframe's wgpu setup asking for the adapter's own limits: egui-wgpu's
/// default asks `Limits::default()`, which caps storage buffers and
/// workgroup memory below what the adapter offers (docs/design.md, the
/// lavapipe facts under "Two engines, one contract"). The device
/// is the gpu engine's own ([`GpuContext::device_descriptor`]: its
/// features too), so the training thread can share it and draw the view
/// into textures the window shows.
fn wgpu_configuration() -> WgpuConfiguration {
    let setup = WgpuSetupCreateNew {
        device_descriptor: Arc::new(|adapter: &wgpu::Adapter| {
            let descriptor = GpuContext::device_descriptor(adapter);
            let limits = descriptor.required_limits.clone();
            wgpu::DeviceDescriptor {
                label: Some("zrak viewer device"),
                required_limits: wgpu::Limits {
                    max_texture_dimension_2d: limits.max_texture_dimension_2d.min(MAX_TEXTURE_SIDE),
                    ..limits
                },
                ..descriptor
            }
        }),
        ..WgpuSetupCreateNew::without_display_handle()
    };
    WgpuConfiguration {
        wgpu_setup: WgpuSetup::CreateNew(setup),
        ..Default::default()
    }
}

/// Opens the viewer window and returns when it closes.
pub fn run(options: ViewerOptions) -> anyhow::Result<()> {
    let native_options = eframe::NativeOptions {
        renderer: eframe::Renderer::Wgpu,
        viewport: egui::ViewportBuilder::default()
            .with_title("zrak")
            .with_inner_size([1280.0, 800.0])
            .with_min_inner_size([640.0, 480.0])
            .with_drag_and_drop(true),
        wgpu_options: wgpu_configuration(),
        ..Default::default()
    };
    eframe::run_native(
        "zrak",
        native_options,
        Box::new(move |cc| Ok(Box::new(ViewerApp::new(cc, options)))),
    )
    .map_err(|error| anyhow::anyhow!("{error}"))
    .context(
        "the viewer window could not open (is there a display and a Vulkan, Metal or DX12 driver?)",
    )
}

/// The gpu engine's textures made drawable through egui-wgpu's renderer.
struct EguiWgpuTextures {
    render_state: eframe::egui_wgpu::RenderState,
}

impl NativeTextures for EguiWgpuTextures {
    fn register(
        &mut self,
        texture: &wgpu::Texture,
        previous: Option<egui::TextureId>,
    ) -> egui::TextureId {
        let view = texture.create_view(&wgpu::TextureViewDescriptor::default());
        let device = &self.render_state.device;
        let mut renderer = self.render_state.renderer.write();
        // Only ids this renderer registered can be re-pointed.
        match previous.filter(|id| renderer.texture(id).is_some()) {
            Some(id) => {
                renderer.update_egui_texture_from_wgpu_texture(
                    device,
                    &view,
                    wgpu::FilterMode::Linear,
                    id,
                );
                id
            }
            None => renderer.register_native_texture(device, &view, wgpu::FilterMode::Linear),
        }
    }

    fn free(&mut self, id: egui::TextureId) {
        self.render_state.renderer.write().free_texture(&id);
    }
}

/// How often the window redraws while the camera rests, on a software
/// rasteriser: twice a second is enough for stats, plots and a picture
/// refreshed every few seconds, and frees most of the CPU the window took
/// (measured on the demo under Xvfb on two cores: lavapipe's rasteriser
/// threads took ~0.7 of a core at ~3 frames a second, as much as
/// training).
const SOFTWARE_RESTING_REDRAW: Duration = Duration::from_millis(500);

/// One frame's timing.
#[derive(Debug, Clone, Copy)]
struct FrameTime {
    moving: bool,
    /// Time spent building the UI (our `ui` call).
    update_ms: f64,
    /// Time since the previous frame began (None for the first).
    interval_ms: Option<f64>,
}

/// The eframe application around [`ViewerUi`].
pub struct ViewerApp {
    ui: ViewerUi,
    options: ViewerOptions,
    started: Instant,
    last_frame: Option<Instant>,
    frames: Vec<FrameTime>,
    screenshot_requested: bool,
    screenshot_done: Arc<AtomicBool>,
    screenshot_error: Arc<Mutex<Option<String>>>,
}

impl ViewerApp {
    pub fn new(cc: &eframe::CreationContext<'_>, options: ViewerOptions) -> Self {
        let ctx = cc.egui_ctx.clone();
        // The gpu engine trains on the window's device, so the view it
        // draws stays on the GPU. Not on a software adapter (lavapipe): its
        // one queue runs a training step, minutes long there, before the
        // window's next frame, so the window would freeze; the engine then
        // makes its own device and the view comes through the CPU.
        let gpu_device = match &cc.wgpu_render_state {
            Some(render_state)
                if options.engine != Some(EngineKind::Cpu)
                    && render_state.adapter.get_info().device_type
                        != eframe::wgpu::DeviceType::Cpu =>
            {
                match GpuContext::from_existing(
                    &render_state.adapter,
                    render_state.device.clone(),
                    render_state.queue.clone(),
                ) {
                    Ok(context) => Some(context),
                    Err(error) => {
                        eprintln!(
                            "zrak view: the window's device cannot run the gpu engine \
                             ({error}); the engine makes its own and the view comes through \
                             the CPU"
                        );
                        None
                    }
                }
            }
            _ => None,
        };
        let worker = TrainingWorker::spawn_with(
            options.source.clone(),
            options.engine,
            options.model,
            WorkerOptions {
                gpu_device,
                sampling: options.sampling,
                precision: options.precision,
                space: options.space,
                photographs: options.photographs,
                autosave: crate::session::worker::default_autosave_folder(),
                kept_runs: options.kept_runs,
                ..WorkerOptions::default()
            },
        );
        // Events wake the window; without this it would sleep until input.
        // On a software rasteriser (lavapipe), no sooner than a resting
        // frame's interval: each frame of the window costs CPU that the
        // training thread shares.
        let software_display = cc
            .wgpu_render_state
            .as_ref()
            .is_some_and(|r| r.adapter.get_info().device_type == eframe::wgpu::DeviceType::Cpu);
        let resting_redraw = software_display.then_some(SOFTWARE_RESTING_REDRAW);
        let wake = ctx.clone();
        worker.set_repaint(Box::new(move || match resting_redraw {
            Some(interval) => wake.request_repaint_after(interval),
            None => wake.request_repaint(),
        }));
        // So does an interrupt (Ctrl-C in the terminal, SIGTERM), which the
        // next frame turns into closing the window.
        crate::interrupt::on_request(move || ctx.request_repaint());
        // The viewer trains from the start, as instant-ngp's testbed does.
        worker.send(Command::Start);
        let mut ui = ViewerUi::new(Box::new(worker), options.model);
        ui.set_opening(options.source.clone());
        ui.set_log_progress(true);
        ui.set_auto_orbit(options.auto_orbit);
        if options.crop.is_some() {
            ui.set_crop(options.crop);
        }
        if let Some(kind) = options.open_export {
            ui.open_export(kind);
        }
        ui.set_resting_redraw(resting_redraw);
        if let Some(file) = &options.camera_path {
            ui.open_camera_path(crate::session::path_state::PendingLoad {
                file: file.clone(),
                time: options.path_time,
                play: options.path_play,
            });
        }
        if let Some(render_state) = &cc.wgpu_render_state {
            let info = render_state.adapter.get_info();
            ui.set_display_adapter(format!("{} ({:?})", info.name, info.backend));
            ui.set_native_textures(Box::new(EguiWgpuTextures {
                render_state: render_state.clone(),
            }));
        }
        eprintln!(
            "zrak view: opening {} with {}",
            describe_source(&options.source),
            options.model.name()
        );
        Self {
            ui,
            options,
            started: Instant::now(),
            last_frame: None,
            frames: Vec::new(),
            screenshot_requested: false,
            screenshot_done: Arc::new(AtomicBool::new(false)),
            screenshot_error: Arc::new(Mutex::new(None)),
        }
    }

    fn automation(&mut self, ctx: &egui::Context) {
        let elapsed = self.started.elapsed();
        if let Some(path) = &self.options.screenshot {
            let due = Duration::from_secs_f64(self.options.screenshot_after.max(0.0));
            if !self.screenshot_requested && elapsed >= due {
                self.screenshot_requested = true;
                if let Some([x, y, width, height]) = self.ui.viewport().rect_pixels {
                    eprintln!("zrak view: viewport {x} {y} {width} {height}");
                }
                let path = path.clone();
                let done = self.screenshot_done.clone();
                let failure = self.screenshot_error.clone();
                ctx.request_screenshot(move |image| {
                    match save_png(&image, &path) {
                        Ok(()) => eprintln!("zrak view: screenshot saved to {}", path.display()),
                        Err(error) => {
                            eprintln!("zrak view: {error:#}");
                            if let Ok(mut slot) = failure.lock() {
                                *slot = Some(format!("{error:#}"));
                            }
                        }
                    }
                    done.store(true, Ordering::SeqCst);
                });
            }
            if !self.screenshot_requested {
                // A frame when it is due; frames every 50 ms until then
                // would take the CPU a software rasteriser's window costs
                // from training, and measure another viewer than a user's.
                ctx.request_repaint_after(due.saturating_sub(elapsed));
            } else if !self.screenshot_done.load(Ordering::SeqCst) {
                // Keep frames coming until the screenshot has been taken.
                ctx.request_repaint_after(Duration::from_millis(50));
            }
        }
        if let Some(quit_after) = self.options.quit_after {
            let due = Duration::from_secs_f64(quit_after.max(0.0));
            let screenshot_pending = self.options.screenshot.is_some()
                && !self.screenshot_done.load(Ordering::SeqCst)
                && elapsed < due + SCREENSHOT_GRACE;
            if elapsed >= due && !screenshot_pending {
                ctx.send_viewport_cmd(egui::ViewportCommand::Close);
            } else if elapsed >= due {
                ctx.request_repaint_after(Duration::from_millis(100));
            } else {
                ctx.request_repaint_after(due - elapsed);
            }
        }
    }

    fn write_frame_log(&self, path: &Path) -> anyhow::Result<()> {
        let mut json = frame_log_json(&self.frames, self.started.elapsed().as_secs_f64());
        json["schedule"] = schedule_json(self.ui.schedule_total());
        json["schedule_seconds"] = self
            .ui
            .schedule_log()
            .iter()
            .map(|&(at, wall, training)| {
                serde_json::json!({ "at_seconds": at, "wall": wall, "training": training })
            })
            .collect();
        json["shown"] = self
            .ui
            .shown_log()
            .iter()
            .map(|(at, shown)| {
                serde_json::json!({
                    "at_seconds": at,
                    "model": shown.model.key(),
                    "step": shown.step,
                    "train_seconds": shown.train_seconds,
                    "downscale": shown.downscale,
                    "width": shown.width,
                    "height": shown.height,
                })
            })
            .collect();
        json["trained"] =
            self.ui
                .latest_stats(self.ui.active_model())
                .map_or(serde_json::Value::Null, |stats| {
                    serde_json::json!({
                        "model": stats.model.key(),
                        "step": stats.step,
                        "train_seconds": stats.train_seconds,
                    })
                });
        let text = serde_json::to_string_pretty(&json)?;
        std::fs::write(path, text)
            .with_context(|| format!("writing the frame log {}", path.display()))?;
        eprintln!("zrak view: frame log written to {}", path.display());
        Ok(())
    }
}

impl eframe::App for ViewerApp {
    fn ui(&mut self, ui: &mut egui::Ui, _frame: &mut eframe::Frame) {
        let began = Instant::now();
        let interval_ms = self
            .last_frame
            .map(|last| began.duration_since(last).as_secs_f64() * 1e3);
        self.last_frame = Some(began);

        self.ui.show(ui);
        let ctx = ui.ctx().clone();
        self.automation(&ctx);
        // An interrupt closes the window as its close button does, so the
        // models trained since their last save are kept on the way out
        // (`on_exit`); `zrak view` then exits with the interrupted status.
        if crate::interrupt::requested() {
            ctx.send_viewport_cmd(egui::ViewportCommand::Close);
        }

        if self.options.frame_log.is_some() {
            self.frames.push(FrameTime {
                moving: self.ui.camera_moving(),
                update_ms: began.elapsed().as_secs_f64() * 1e3,
                interval_ms,
            });
        }
    }

    fn on_exit(&mut self) {
        if let Some(path) = self.options.frame_log.clone()
            && let Err(error) = self.write_frame_log(&path)
        {
            eprintln!("zrak view: {error:#}");
        }
        self.ui.take_link().shutdown();
    }
}

fn save_png(image: &egui::ColorImage, path: &Path) -> anyhow::Result<()> {
    let [width, height] = image.size;
    let bytes: Vec<u8> = image
        .pixels
        .iter()
        .flat_map(|c| [c.r(), c.g(), c.b(), 255])
        .collect();
    let buffer = image::RgbaImage::from_raw(width as u32, height as u32, bytes)
        .context("the screenshot's size does not match its pixels")?;
    if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent)
            .with_context(|| format!("creating the folder {}", parent.display()))?;
    }
    buffer
        .save(path)
        .with_context(|| format!("writing the screenshot {}", path.display()))
}

/// The median and the 95th percentile (nearest rank) of `values`.
pub fn median_and_p95(values: &[f64]) -> Option<(f64, f64)> {
    if values.is_empty() {
        return None;
    }
    let mut sorted = values.to_vec();
    sorted.sort_by(f64::total_cmp);
    let rank = |q: f64| {
        let index = ((q * sorted.len() as f64).ceil() as usize).clamp(1, sorted.len()) - 1;
        sorted[index]
    };
    let n = sorted.len();
    let median = if n % 2 == 1 {
        sorted[n / 2]
    } else {
        0.5 * (sorted[n / 2 - 1] + sorted[n / 2])
    };
    Some((median, rank(0.95)))
}

fn summary(values: &[f64]) -> serde_json::Value {
    match median_and_p95(values) {
        Some((median, p95)) => serde_json::json!({
            "count": values.len(),
            "median_ms": median,
            "p95_ms": p95,
            "ms": values,
        }),
        None => serde_json::json!({ "count": 0, "ms": [] }),
    }
}

/// The training thread's schedule over the session, in seconds.
fn schedule_json(trace: &crate::session::schedule::ScheduleTrace) -> serde_json::Value {
    serde_json::json!({
        "wall_seconds": trace.wall_seconds,
        "training_seconds": trace.training_seconds,
        "grid_update_seconds": trace.grid_update_seconds,
        "steps": trace.steps,
        "rendering": trace.rendering.iter().map(|level| serde_json::json!({
            "downscale": level.downscale,
            "seconds": level.seconds,
            "finished": level.finished,
        })).collect::<Vec<_>>(),
        "evaluation_seconds": trace.evaluation_seconds,
        "evaluations": trace.evaluations,
        "idle_seconds": trace.idle_seconds,
        "other_seconds": trace.other_seconds(),
    })
}

fn frame_log_json(frames: &[FrameTime], seconds: f64) -> serde_json::Value {
    let group = |moving: bool| {
        let chosen: Vec<&FrameTime> = frames.iter().filter(|f| f.moving == moving).collect();
        let update: Vec<f64> = chosen.iter().map(|f| f.update_ms).collect();
        let interval: Vec<f64> = chosen.iter().filter_map(|f| f.interval_ms).collect();
        serde_json::json!({
            "frames": chosen.len(),
            "update": summary(&update),
            "interval": summary(&interval),
        })
    };
    serde_json::json!({
        "frames": frames.len(),
        "seconds": seconds,
        "moving": group(true),
        "still": group(false),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn median_and_p95_by_nearest_rank() {
        let values: Vec<f64> = (1..=100).map(f64::from).collect();
        assert_eq!(median_and_p95(&values), Some((50.5, 95.0)));
        assert_eq!(median_and_p95(&[3.0, 1.0, 2.0]), Some((2.0, 3.0)));
        assert_eq!(median_and_p95(&[]), None);
    }

    #[test]
    fn frame_log_splits_moving_and_still() {
        let frames = [
            FrameTime {
                moving: true,
                update_ms: 2.0,
                interval_ms: None,
            },
            FrameTime {
                moving: false,
                update_ms: 1.0,
                interval_ms: Some(16.0),
            },
            FrameTime {
                moving: false,
                update_ms: 3.0,
                interval_ms: Some(17.0),
            },
        ];
        let json = frame_log_json(&frames, 1.0);
        assert_eq!(json["frames"], 3);
        assert_eq!(json["moving"]["frames"], 1);
        assert_eq!(json["moving"]["interval"]["count"], 0);
        assert_eq!(json["still"]["update"]["median_ms"], 2.0);
        assert_eq!(json["still"]["interval"]["p95_ms"], 17.0);
    }
}
