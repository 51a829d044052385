//! The viewer's window, driven with egui_kittest: its controls are there,
//! they send the commands they should, frames reach the viewport, and a bad
//! scene folder is reported in the window.
//!
//! Most tests talk to a recording link (commands are inspected, events are
//! injected); one runs the real training thread on the demo scene.

use std::collections::VecDeque;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use eframe::egui;
use egui_kittest::Harness;
use egui_kittest::kittest::Queryable;
use zrak::app::ui::{ExportKind, PlotAxis, TrainingLink, ViewerUi};
use zrak::engine::EngineKind;
use zrak::field::ModelKind;
use zrak::model::{RenderMode, RenderedPixel, Stage, StageTimes};
use zrak::scene::crop::CropBox;
use zrak::scene::demo::{
    DemoConfig, {self},
};
use zrak::session::protocol::{
    Command, Event, InTurn, MeshExport, RenderedFrame, SceneInfo, SceneSource, TrainingStats,
};
use zrak::session::worker::TrainingWorker;

/// Records every command; hands out events the test queued.
#[derive(Clone, Default)]
struct RecordingLink {
    sent: Arc<Mutex<Vec<Command>>>,
    events: Arc<Mutex<VecDeque<Event>>>,
}

impl RecordingLink {
    fn push(&self, event: Event) {
        self.events.lock().unwrap().push_back(event);
    }

    fn sent(&self) -> Vec<Command> {
        self.sent.lock().unwrap().clone()
    }

    fn clear(&self) {
        self.sent.lock().unwrap().clear();
    }

    fn render_requests(&self) -> Vec<zrak::session::protocol::RenderRequest> {
        self.sent()
            .into_iter()
            .filter_map(|c| match c {
                Command::Render(request) => Some(request),
                _ => None,
            })
            .collect()
    }
}

impl TrainingLink for RecordingLink {
    fn send(&self, command: Command) {
        self.sent.lock().unwrap().push(command);
    }

    fn try_recv(&self) -> Option<Event> {
        self.events.lock().unwrap().pop_front()
    }
}

const WINDOW: [f32; 2] = [1280.0, 800.0];

/// The button (or selectable label) called `label`: the same text may also
/// stand in a plain label (the model's name in the stats).
fn button<'h>(harness: &'h Harness<'_, ViewerUi>, label: &'h str) -> egui_kittest::Node<'h> {
    harness.get_by_role_and_label(egui::accesskit::Role::Button, label)
}

fn small_demo() -> SceneInfo {
    let config = DemoConfig {
        size: 32,
        train_views: 4,
        val_views: 1,
        test_views: 1,
    };
    SceneInfo {
        scene: Arc::new(demo::build(&config)),
        source: SceneSource::Demo,
        photographs: Default::default(),
    }
}

fn stats(step: u32, loss: f32) -> TrainingStats {
    TrainingStats {
        model: ModelKind::Ngp,
        step,
        train_seconds: step as f64 * 0.1,
        loss,
        batch_psnr: Some(20.0),
        val_psnr: None,
        ms_per_step: 123.4,
        samples_per_ray: 17.5,
        composited_per_ray: Some(9.3),
        samples_per_second: 2.5e6,
        memory_bytes: 64 << 20,
        times: StageTimes::from_fn(|stage| match stage {
            Stage::March => 0.01,
            Stage::Encode => 0.05,
            _ => 0.0,
        }),
    }
}

/// A window on a recording link, with the small demo scene loaded.
fn harness_with_scene() -> (Harness<'static, ViewerUi>, RecordingLink) {
    let link = RecordingLink::default();
    let mut ui = ViewerUi::new(Box::new(link.clone()), ModelKind::Ngp);
    ui.set_dialogs_available(false);
    link.push(Event::Engine {
        kind: EngineKind::Cpu,
        description: "cpu (test, 2 threads)".into(),
    });
    link.push(Event::SceneLoaded(small_demo()));
    link.push(Event::ModelSelected(ModelKind::Ngp));
    link.push(Event::Running(false));
    let mut harness = Harness::builder()
        .with_size(WINDOW)
        .build_ui_state(|ui, state: &mut ViewerUi| state.show(ui), ui);
    harness.run_steps(3);
    (harness, link)
}

#[test]
fn panels_show_every_control() {
    let _cores = crate::common::shared();
    let (mut harness, link) = harness_with_scene();
    link.push(Event::Stats(stats(7, 0.0123)));
    harness.run_steps(2);

    for label in [
        "Start",
        "Step",
        "Reset",
        "RGB",
        "Depth",
        "Opacity",
        "Side by side",
        "Split",
        "Orbit",
        "Fly",
        "< Prev view",
        "Next view >",
        "Reset view",
        "Export…",
        "Crop box…",
        "Save…",
        "Load…",
        "Loss and PSNR",
        "steps",
        "wall time",
        "Stats",
        "Time per stage",
    ] {
        assert!(
            harness.query_by_label(label).is_some(),
            "no control labelled {label:?}"
        );
    }
    for kind in ModelKind::ALL {
        button(&harness, kind.name());
    }
    // The stats show the figures that arrived, formatted.
    harness.get_by_label("123.4");
    harness.get_by_label("17.5 (9.3 composited)");
    harness.get_by_label("2.50 M");
    harness.get_by_label("64.0 MiB");
    harness.get_by_label("0.01230");
    // The stages of a step, one click away from where the time goes.
    harness.get_by_label("Time per stage").click();
    harness.run_steps(2);
    harness.get_by_label("10.00 ms");
    harness.get_by_label("50.00 ms");
    harness.get_by_label("60.00 ms");
    harness.get_by_label("83%");
    harness.get_by_label("cpu: cpu (test, 2 threads)");
    assert_eq!(
        harness.state().latest_stats(ModelKind::Ngp).unwrap().step,
        7
    );
}

#[test]
fn start_pause_step_and_reset_send_their_commands() {
    let _cores = crate::common::shared();
    let (mut harness, link) = harness_with_scene();
    link.clear();
    harness.get_by_label("Start").click();
    harness.run_steps(2);
    assert!(harness.state().is_running());
    harness.get_by_label("Pause").click();
    harness.run_steps(2);
    harness.get_by_label("Step").click();
    harness.run_steps(2);
    harness.get_by_label("Reset").click();
    harness.run_steps(2);
    let lifecycle: Vec<String> = link
        .sent()
        .into_iter()
        .filter(|c| !matches!(c, Command::Render(_)))
        .map(|c| format!("{c:?}"))
        .collect();
    assert_eq!(lifecycle, ["Start", "Pause", "StepOnce", "Reset"]);
}

#[test]
fn model_toggle_selects_each_model_once() {
    let _cores = crate::common::shared();
    let (mut harness, link) = harness_with_scene();
    link.clear();
    // Clicking the active model changes nothing: its state is kept.
    button(&harness, ModelKind::Ngp.name()).click();
    harness.run_steps(2);
    assert!(
        !link
            .sent()
            .iter()
            .any(|c| matches!(c, Command::SelectModel(_)))
    );
    // Every other model is one click away, and the click names it.
    for &kind in ModelKind::ALL.iter().rev() {
        link.clear();
        let before = harness.state().active_model();
        button(&harness, kind.name()).click();
        harness.run_steps(2);
        let selected: Vec<ModelKind> = link
            .sent()
            .into_iter()
            .filter_map(|c| match c {
                Command::SelectModel(k) => Some(k),
                _ => None,
            })
            .collect();
        let expected = if kind == before { vec![] } else { vec![kind] };
        assert_eq!(selected, expected);
        assert_eq!(harness.state().active_model(), kind);
    }
}

#[test]
fn render_requests_follow_mode_and_nothing_else() {
    let _cores = crate::common::shared();
    let (mut harness, link) = harness_with_scene();
    let first = link.render_requests();
    assert_eq!(first.len(), 1, "one request for the first view");
    let request = &first[0];
    assert_eq!(request.generation, 1);
    assert_eq!(request.mode, RenderMode::Rgb);
    assert!(!request.moving);
    // The request has the viewport's own size in pixels (render scale 1×,
    // the default), whatever the photographs' resolution.
    let k = request.camera.intrinsics;
    let [_, _, width, height] = harness.state().viewport().rect_pixels.unwrap();
    assert_eq!((k.width, k.height), (width, height), "{k:?}");
    assert!(k.height > k.width / 4 && k.height < k.width, "{k:?}");

    // Frames with nothing changed send nothing.
    harness.run_steps(5);
    assert_eq!(link.render_requests().len(), 1);

    harness.get_by_label("Depth").click();
    harness.run_steps(2);
    let requests = link.render_requests();
    assert_eq!(requests.len(), 2);
    assert_eq!(requests[1].generation, 2);
    assert_eq!(requests[1].mode, RenderMode::Depth);
    assert_eq!(requests[1].camera, request.camera);
    assert_eq!(harness.state().render_mode(), RenderMode::Depth);

    harness.get_by_label("Opacity").click();
    harness.run_steps(2);
    let last = link.render_requests().pop().unwrap();
    assert_eq!((last.generation, last.mode), (3, RenderMode::Opacity));

    // Half the resolution: half the pixels along each side (rounded).
    harness.get_by_label("½×").click();
    harness.run_steps(2);
    let half = link.render_requests().pop().unwrap();
    assert_eq!(half.generation, 4);
    let k = half.camera.intrinsics;
    let round_half = |side: u32| (side as f32 * 0.5).round() as u32;
    assert_eq!((k.width, k.height), (round_half(width), round_half(height)));
}

#[test]
fn next_view_snaps_the_camera_to_that_training_view() {
    let _cores = crate::common::shared();
    let (mut harness, link) = harness_with_scene();
    harness.get_by_label("Side by side").click();
    harness.run_steps(2);
    harness.get_by_label("Next view >").click();
    harness.run_steps(2);
    let scene = small_demo().scene;
    let last = link.render_requests().pop().unwrap();
    // Comparing renders from the photograph's own camera, so pixels match.
    assert_eq!(last.camera, scene.train[0].camera);
    harness.get_by_label("at training view 1 of 4");
    harness.get_by_label("Next view >").click();
    harness.run_steps(2);
    assert_eq!(
        link.render_requests().pop().unwrap().camera,
        scene.train[1].camera
    );
}

fn solid_frame(generation: u64, width: u32, height: u32, rgb: [f32; 3]) -> RenderedFrame {
    RenderedFrame {
        generation,
        model: ModelKind::Ngp,
        step: 42,
        train_seconds: 4.2,
        downscale: 1,
        complete: true,
        width,
        height,
        mode: RenderMode::Rgb,
        pixels: vec![
            RenderedPixel {
                rgb,
                opacity: 1.0,
                depth: 1.0,
            };
            (width * height) as usize
        ],
    }
}

#[test]
fn the_latest_frame_fills_the_viewport_and_stale_frames_are_dropped() {
    let _cores = crate::common::shared();
    let (mut harness, link) = harness_with_scene();
    let request = link.render_requests().pop().unwrap();
    let k = request.camera.intrinsics;
    // A coarse frame (an eighth) of the current request, pure red.
    link.push(Event::Frame(solid_frame(
        request.generation,
        k.width / 8,
        k.height / 8,
        [1.0, 0.0, 0.0],
    )));
    harness.run_steps(2);
    let shown = harness.state().viewport().shown().expect("frame shown");
    assert_eq!((shown.generation, shown.step), (request.generation, 42));

    // A frame of an older generation never replaces it.
    link.push(Event::Frame(solid_frame(0, 8, 8, [0.0, 0.0, 1.0])));
    harness.run_steps(2);
    assert_eq!(harness.state().viewport().frames_dropped, 1);
    assert_eq!(harness.state().viewport().frames_shown, 1);

    // On screen, the viewport's centre is the frame's red (linear filtering
    // of a solid image is the same red). The viewport lies right of the
    // controls (the right edge of their "Reset view" button) and above the
    // bottom panel (the "Stats" header).
    let image = harness.render().expect("render the window");
    let left = harness.get_by_label("Reset view").rect().right();
    let bottom = harness.get_by_label("Stats").rect().top();
    let x = ((left + WINDOW[0]) / 2.0) as u32;
    let y = (bottom / 2.0) as u32;
    let pixel = image.get_pixel(x, y);
    assert!(
        pixel[0] > 240 && pixel[1] < 15 && pixel[2] < 15,
        "pixel at ({x}, {y}) is {pixel:?}, expected red"
    );
}

#[test]
fn plots_record_every_model_and_reset_starts_the_curve_again() {
    let _cores = crate::common::shared();
    let (mut harness, link) = harness_with_scene();
    for step in 1..=5 {
        link.push(Event::Stats(stats(step, 0.1 / step as f32)));
    }
    harness.run_steps(2);
    let history = harness.state().history(ModelKind::Ngp).unwrap();
    assert_eq!(history.points.len(), 5);
    assert_eq!(history.points[4].loss, 0.02);
    // A model that starts again from step 1 (reset elsewhere) restarts its curve.
    link.push(Event::Stats(stats(1, 0.2)));
    harness.run_steps(2);
    assert_eq!(
        harness
            .state()
            .history(ModelKind::Ngp)
            .unwrap()
            .points
            .len(),
        1
    );
    harness.get_by_label("wall time").click();
    harness.run_steps(2);
}

#[test]
fn a_failed_scene_shows_its_error_in_the_window() {
    let _cores = crate::common::shared();
    let (mut harness, link) = harness_with_scene();
    link.push(Event::SceneFailed {
        source: SceneSource::Folder("/nowhere/broken-scene".into()),
        error: "no transforms_train.json".into(),
    });
    harness.run_steps(2);
    harness
        .get_all_by_label_contains("/nowhere/broken-scene")
        .next()
        .unwrap();
    // The scene that was open stays open.
    assert_eq!(harness.state().scene().unwrap().scene.train.len(), 4);
}

/// The real training thread: opening a folder that is not a scene leaves
/// the demo scene running and says which folder failed, in the window.
#[test]
fn opening_a_bad_folder_with_the_real_worker_names_the_folder() {
    let _cores = crate::common::shared();
    let folder = tempfile::tempdir().unwrap();
    let bad = folder.path().join("not-a-scene");
    std::fs::create_dir(&bad).unwrap();
    std::fs::write(bad.join("readme.txt"), "no cameras here").unwrap();

    let worker = TrainingWorker::spawn(SceneSource::Demo, Some(EngineKind::Cpu), ModelKind::Ngp);
    let mut ui = ViewerUi::new(Box::new(worker), ModelKind::Ngp);
    ui.set_dialogs_available(false);
    let mut harness = Harness::builder()
        .with_size(WINDOW)
        .build_ui_state(|ui, state: &mut ViewerUi| state.show(ui), ui);

    let wait_for =
        |harness: &mut Harness<'_, ViewerUi>, what: &str, done: &dyn Fn(&ViewerUi) -> bool| {
            let started = Instant::now();
            while !done(harness.state()) {
                assert!(
                    started.elapsed() < Duration::from_secs(120),
                    "timed out waiting for {what}"
                );
                harness.step();
                std::thread::sleep(Duration::from_millis(20));
            }
        };
    wait_for(&mut harness, "the demo scene", &|ui| ui.scene().is_some());

    let field = || egui::accesskit::Role::TextInput;
    harness.get_by_role_and_label(field(), "Folder").focus();
    harness.run_steps(2);
    harness
        .get_by_role_and_label(field(), "Folder")
        .type_text(&bad.display().to_string());
    harness.run_steps(2);
    assert_eq!(
        harness.get_by_role_and_label(field(), "Folder").value(),
        Some(bad.display().to_string())
    );
    harness.get_by_label("Open").click();
    harness.run_steps(2);
    wait_for(&mut harness, "the scene error", &|ui| {
        ui.scene_error().is_some()
    });
    harness.run_steps(2);

    let error = harness.state().scene_error().unwrap().to_string();
    assert!(error.contains(&bad.display().to_string()), "{error}");
    harness
        .get_all_by_label_contains("not-a-scene")
        .next()
        .expect("the error names the folder in the window");
    assert_eq!(
        harness.state().scene().unwrap().source,
        SceneSource::Demo,
        "the demo scene keeps running"
    );
    harness.state_mut().take_link().shutdown();
}

/// At a training view, the error against the photograph is measured on the
/// frame rendered from the photograph's camera: a render off by 0.1 in
/// every channel has MSE 0.01, so PSNR = −10·log10(0.01) = 20 dB exactly.
#[test]
fn comparing_at_a_training_view_measures_the_error() {
    let _cores = crate::common::shared();
    let (mut harness, link) = harness_with_scene();
    button(&harness, "Side by side").click();
    harness.run_steps(2);
    button(&harness, "Error").click();
    harness.run_steps(2);
    harness.get_by_label("Next view >").click();
    harness.run_steps(2);
    let request = link.render_requests().pop().unwrap();
    // The error map needs the render's pixels, also from the gpu engine.
    assert!(request.needs_pixels, "comparing asks for pixels");
    let scene = small_demo().scene;
    let truth = scene.train[0].image.to_rgb_over([1.0, 1.0, 1.0]);
    let k = request.camera.intrinsics;
    let mut frame = solid_frame(request.generation, k.width, k.height, [0.0; 3]);
    for (pixel, target) in frame.pixels.iter_mut().zip(&truth) {
        pixel.rgb = target.map(|c| c + 0.1);
    }
    link.push(Event::Frame(frame));
    harness.run_steps(2);
    let psnr = harness
        .state()
        .viewport()
        .view_psnr
        .expect("PSNR of the view");
    assert!((psnr - 20.0).abs() < 1e-3, "{psnr}");
    harness.get_by_label("PSNR of this view: 20.00 dB");
    if let Ok(path) = std::env::var("ZRAK_VIEWER_SNAPSHOT") {
        harness.render().unwrap().save(path).unwrap();
    }
}

#[test]
fn training_all_models_in_turn_is_one_click_and_plots_against_training_time() {
    let _cores = crate::common::shared();
    let (mut harness, link) = harness_with_scene();
    link.clear();
    button(&harness, "Train all models in turn").click();
    harness.run_steps(2);
    let sent: Vec<String> = link
        .sent()
        .into_iter()
        .filter(|c| !matches!(c, Command::Render(_)))
        .map(|c| format!("{c:?}"))
        .collect();
    // Every model, two seconds of training a turn, and training starts.
    assert_eq!(
        sent,
        [
            "TrainInTurn(Some(InTurn { models: [Ngp, Nerf, MipNerf], slice_seconds: 2.0 }))",
            "Start"
        ]
    );
    assert!(harness.state().is_running());
    assert_eq!(harness.state().plot_axis(), PlotAxis::TrainTime);
    // The thread's answer is what the window shows.
    link.push(Event::InTurn(Some(InTurn {
        models: vec![ModelKind::Ngp, ModelKind::Nerf],
        slice_seconds: 2.0,
    })));
    harness.run_steps(2);
    assert_eq!(harness.state().in_turn().unwrap().models.len(), 2);
    harness.get_by_label_contains("take turns of 2 s");
    link.clear();
    button(&harness, "Train all models in turn").click();
    harness.run_steps(2);
    assert!(
        link.sent()
            .iter()
            .any(|c| matches!(c, Command::TrainInTurn(None)))
    );
    assert!(harness.state().in_turn().is_none());
}

/// Stats of `model` at `step`, `train_seconds` in, with a held-out PSNR.
fn evaluated(model: ModelKind, step: u32, train_seconds: f64, val_psnr: f32) -> TrainingStats {
    TrainingStats {
        model,
        train_seconds,
        val_psnr: Some(val_psnr),
        samples_per_second: 1.5e6,
        memory_bytes: 32 << 20,
        ..stats(step, 0.01)
    }
}

#[test]
fn the_plot_and_table_export_from_the_window_with_the_sessions_numbers() {
    let _cores = crate::common::shared();
    let (mut harness, link) = harness_with_scene();
    // Instant-NGP: 20 dB after 10 s of training, 30 dB after 40 s;
    // NeRF: 15 dB after 10 s.
    link.push(Event::Stats(evaluated(ModelKind::Ngp, 100, 10.0, 20.0)));
    link.push(Event::Stats(evaluated(ModelKind::Ngp, 400, 40.0, 30.0)));
    link.push(Event::Stats(evaluated(ModelKind::Nerf, 50, 10.0, 15.0)));
    harness.run_steps(2);
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("comparison");
    harness
        .state_mut()
        .set_comparison_folder(out.display().to_string());
    button(&harness, "Export plot and table").click();
    harness.run_steps(2);
    for file in ["psnr.png", "psnr.svg", "table.md", "table.csv"] {
        assert!(out.join(file).is_file(), "{file} not exported");
    }
    let csv = std::fs::read_to_string(out.join("table.csv")).unwrap();
    // 25 dB half-way from 20 to 30 dB, in log time between 10 and 40 s:
    // √(10 · 40) = 20 s.
    assert_eq!(
        csv,
        "model,steps,training time,held-out PSNR,to 25 dB,to 30 dB,to 33 dB,samples/s,memory\n\
         Instant-NGP,400,40 s,30.00,20 s,40 s,not in 40 s,1.50 M,32 MiB\n\
         NeRF,50,10 s,15.00,not in 10 s,not in 10 s,not in 10 s,1.50 M,32 MiB\n"
    );
    let markdown = std::fs::read_to_string(out.join("table.md")).unwrap();
    assert!(markdown.contains("| Instant-NGP | 400 | 40 s | 30.00 | 20 s | 40 s |"));
    let png = image::open(out.join("psnr.png")).unwrap();
    assert_eq!((png.width(), png.height()), (1000, 620));
    let svg = std::fs::read_to_string(out.join("psnr.svg")).unwrap();
    assert!(svg.contains("Instant-NGP") && svg.contains("NeRF"));
    assert!(
        harness
            .state()
            .notices()
            .any(|n| !n.is_error && n.text.starts_with("Exported 4 files"))
    );
}

#[test]
fn the_stats_show_where_the_thread_time_goes_and_how_far_the_picture_lags() {
    let _cores = crate::common::shared();
    use zrak::session::schedule::{LevelTime, ScheduleTrace};
    let (mut harness, link) = harness_with_scene();
    // The timing column shows where the thread's time goes, or on a click
    // the stages of a step.
    assert_eq!(
        harness.state().timing_view(),
        zrak::app::ui::TimingView::Thread
    );
    assert!(harness.query_by_label("nothing yet").is_some());
    harness.get_by_label("Time per stage").click();
    harness.run_steps(2);
    assert!(harness.query_by_label("no step yet").is_some());
    harness.get_by_label("Where the time goes").click();
    harness.run_steps(2);
    assert!(harness.query_by_label("nothing yet").is_some());
    // Two seconds of the thread's time, reported a second at a time.
    let second = ScheduleTrace {
        wall_seconds: 1.0,
        training_seconds: 0.7,
        grid_update_seconds: 0.1,
        steps: 7,
        rendering: vec![
            LevelTime {
                downscale: 8,
                seconds: 0.01,
                finished: 1,
            },
            LevelTime {
                downscale: 5,
                seconds: 0.02,
                finished: 0,
            },
            LevelTime {
                downscale: 4,
                seconds: 0.13,
                finished: 1,
            },
            LevelTime {
                downscale: 2,
                seconds: 0.04,
                finished: 0,
            },
        ],
        evaluation_seconds: 0.05,
        evaluations: 1,
        idle_seconds: 0.0,
    };
    link.push(Event::Schedule(second.clone()));
    link.push(Event::Schedule(second));
    harness.run_steps(2);
    let recent = harness.state().recent_schedule().expect("traces kept");
    assert_eq!((recent.steps, recent.rendering[2].finished), (14, 2));
    assert!((recent.training_seconds / recent.wall_seconds - 0.7).abs() < 1e-9);
    for label in [
        "training (14 steps)",
        "  of it grid updates",
        "render 1/4 (×2)",
        "render 1/2 (×0)",
        // The column keeps its height: the other levels in one row.
        "render, 2 other sizes (×2)",
        "evaluation (×2)",
        "idle",
        "other",
    ] {
        assert!(
            harness.query_by_label(label).is_some(),
            "no row labelled {label:?}"
        );
    }
    // 70 % training; "other" is what no part claims: 2 − 1.4 − 0.4 − 0.1.
    assert!(harness.query_by_label("70%").is_some());
    assert!((harness.state().schedule_total().other_seconds() - 0.1).abs() < 1e-9);

    // A frame of step 42 (4.2 s of training) while training has gone on to
    // step 50 (5 s): 0.8 s of training behind.
    let request = link.render_requests().pop().unwrap();
    let k = request.camera.intrinsics;
    link.push(Event::Frame(solid_frame(
        request.generation,
        k.width,
        k.height,
        [0.5; 3],
    )));
    link.push(Event::Stats(stats(50, 0.01)));
    harness.run_steps(2);
    let lag = harness.state().shown_lag_seconds().expect("both known");
    assert!((lag - 0.8).abs() < 1e-9, "{lag}");
    assert_eq!(harness.state().shown_log().len(), 1);
}

#[test]
fn the_crop_box_window_sends_the_box_and_shows_a_refusal() {
    let _cores = crate::common::shared();
    let (mut harness, link) = harness_with_scene();
    button(&harness, "Crop box…").click();
    harness.run_steps(2);
    link.clear();
    harness.get_by_label("crop the scene to the box").click();
    harness.run_steps(2);
    // Ticked: the box that fills the scene's.
    let bounds = small_demo().scene.bounds;
    let sent: Vec<Option<CropBox>> = link
        .sent()
        .into_iter()
        .filter_map(|c| match c {
            Command::SetCrop(crop) => Some(crop),
            _ => None,
        })
        .collect();
    assert_eq!(sent, vec![Some(CropBox::of_aabb(&bounds))]);
    assert_eq!(harness.state().crop_panel().drawn(), sent[0]);
    // The gpu engine refuses: the window says why and draws no box.
    link.push(Event::CropSet {
        crop: None,
        refused: Some("the gpu engine does not render with a crop box".into()),
    });
    harness.run_steps(2);
    harness.get_by_label("the gpu engine does not render with a crop box");
    assert_eq!(harness.state().crop_panel().drawn(), None);
    // Unticked: no box.
    link.clear();
    harness.get_by_label("crop the scene to the box").click();
    harness.run_steps(2);
    assert!(matches!(link.sent().as_slice(), [Command::SetCrop(None)]));
}

#[test]
fn the_export_window_sends_a_mesh_export_and_shows_its_progress() {
    let _cores = crate::common::shared();
    let (mut harness, link) = harness_with_scene();
    harness.state_mut().open_export(ExportKind::Mesh);
    harness.run_steps(2);
    // The model's default threshold for this scene, shown.
    let scale = small_demo().scene.unit_cube.scale;
    harness.get_by_label(&format!(
        "the model's default, σ = {:.3}",
        zrak::mesh::extract::default_threshold(ModelKind::Ngp, scale)
    ));
    link.clear();
    button(&harness, "Export").click();
    harness.run_steps(2);
    let orders: Vec<MeshExport> = link
        .sent()
        .into_iter()
        .filter_map(|c| match c {
            Command::ExportMesh(order) => Some(order),
            _ => None,
        })
        .collect();
    assert_eq!(orders.len(), 1, "{:?}", link.sent());
    assert_eq!(orders[0].resolution, 256);
    assert_eq!(orders[0].threshold, None);
    assert!(!orders[0].replace_existing);
    link.push(Event::ExportProgress { done: 3, total: 10 });
    harness.run_steps(2);
    harness.get_by_label("Cancel");
    link.push(Event::ExportFinished(Ok(vec![orders[0].out.clone()])));
    harness.run_steps(2);
    assert!(
        harness
            .state()
            .notices()
            .any(|n| n.text == format!("Exported {}", orders[0].out.display()))
    );
}

#[test]
fn the_path_editor_adds_keyframes_and_plays_them_in_the_viewport() {
    let _cores = crate::common::shared();
    let (mut harness, link) = harness_with_scene();
    harness.get_by_label("Camera path…").click();
    harness.run_steps(2);
    assert!(harness.state().path_editor().open);
    // Two keyframes: at the first training view and at the second.
    let scene = small_demo().scene;
    for _ in 0..2 {
        harness.get_by_label("Next view >").click();
        harness.run_steps(2);
        harness.get_by_label("Add keyframe").click();
        harness.run_steps(2);
    }
    let editor = harness.state().path_editor();
    assert_eq!(editor.keyframes().len(), 2);
    assert_eq!(editor.selected, Some(1));
    let second = scene.train[1].camera.camera_to_world.as_dmat4();
    let error = (editor.keyframes()[1].camera_to_world - second)
        .to_cols_array()
        .iter()
        .fold(0f64, |m, x| m.max(x.abs()));
    // The viewport camera's f32 pose, through a quaternion.
    assert!(error < 1e-5, "{error}");
    harness.get_by_label("Keyframe 2 of 2");
    harness.get_by_label_contains("1.00 s   fov");
    // Play: the viewport camera moves along the path, rendered as a
    // moving camera.
    link.clear();
    harness.get_by_label("Play").click();
    harness.run_steps(3);
    assert!(harness.state().path_editor().playing);
    assert!(harness.state().camera_moving());
    let requests = link.render_requests();
    assert!(!requests.is_empty() && requests.iter().all(|r| r.moving));
    harness.get_by_label("Pause").click();
    harness.run_steps(2);
    assert!(!harness.state().path_editor().playing);
    // Delete the selected keyframe: one is left, selected.
    harness.get_by_label("Delete").click();
    harness.run_steps(2);
    assert_eq!(harness.state().path_editor().keyframes().len(), 1);
    assert_eq!(harness.state().path_editor().selected, Some(0));
}

#[test]
fn the_scene_panel_shows_the_space_and_why() {
    let _cores = crate::common::shared();
    let (mut harness, _link) = harness_with_scene();
    let analysis = harness.state().scene().unwrap().scene.space.clone();
    assert_eq!(analysis.space, zrak::scene::SceneSpace::Object);
    harness.get_by_label("Space: object (from the scene)");
    // The reasons open under it.
    assert!(
        harness
            .query_by_label(&format!("• {}", analysis.reasons[0]))
            .is_none()
    );
    harness.get_by_label("Why").click();
    harness.run_steps(3);
    for reason in &analysis.reasons {
        harness.get_by_label(&format!("• {reason}"));
    }
}

/// Where the scene's photographs have appearance vectors, the Render panel
/// chooses which the models draw with: the mean, or a training image's.
#[test]
fn the_appearance_control_shows_where_the_photographs_have_vectors() {
    let _cores = crate::common::shared();
    let (mut harness, link) = harness_with_scene();
    assert!(
        harness.query_by_label("Mean").is_none(),
        "no appearance control on a render"
    );
    let mut info = small_demo();
    info.photographs.appearance.on = true;
    link.push(Event::SceneLoaded(info));
    harness.run_steps(3);
    link.clear();
    harness.state_mut().set_appearance_view(Some(2));
    harness.run_steps(2);
    harness.get_by_label("Mean").click();
    harness.run_steps(2);
    let chosen: Vec<String> = link
        .sent()
        .into_iter()
        .filter(|c| matches!(c, Command::SetAppearance(_)))
        .map(|c| format!("{c:?}"))
        .collect();
    assert_eq!(chosen, ["SetAppearance(Some(2))", "SetAppearance(None)"]);
    assert_eq!(harness.state().appearance_view(), None);
}
