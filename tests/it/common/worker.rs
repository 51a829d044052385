//! The viewer's training thread as the tests drive it: a cpu-engine
//! worker on a small demo scene, commands sent and events awaited by
//! value. One harness for every test of the thread (`viewer_worker`,
//! `viewer_exports`, `viewer_gpu`).

use std::time::{Duration, Instant};

use glam::Vec3;
use zrak::engine::EngineKind;
use zrak::field::ModelKind;
use zrak::model::RenderMode;
use zrak::scene::demo::{CAMERA_ANGLE_X, DemoConfig};
use zrak::scene::{Camera, Intrinsics};
use zrak::session::protocol::{Command, Event, RenderRequest, RenderedFrame, SceneSource};
use zrak::session::worker::{TrainingWorker, WorkerOptions};

/// Generous: on a loaded machine a step can take a second, and on a
/// software gpu adapter longer.
pub const PATIENCE: Duration = Duration::from_secs(120);

/// The demo scene at 32 × 32 pixels: 12 training views, 2 held out, 1 test.
pub fn small_demo() -> DemoConfig {
    DemoConfig {
        size: 32,
        train_views: 12,
        val_views: 2,
        test_views: 1,
    }
}

/// The small demo and small training batches; no run kept on closing
/// (the default: tests leave the user's data folder alone).
pub fn options() -> WorkerOptions {
    WorkerOptions {
        demo: small_demo(),
        batch_samples: Some(1 << 12),
        ..WorkerOptions::default()
    }
}

/// A worker training Instant-NGP on the cpu engine and the demo scene.
pub fn spawn(options: WorkerOptions) -> TrainingWorker {
    TrainingWorker::spawn_with(
        SceneSource::Demo,
        Some(EngineKind::Cpu),
        ModelKind::Ngp,
        options,
    )
}

/// Events until `pick` returns a value; panics with what was seen when
/// none does within [`PATIENCE`].
pub fn wait_for<T>(worker: &TrainingWorker, mut pick: impl FnMut(&Event) -> Option<T>) -> T {
    let deadline = Instant::now() + PATIENCE;
    let mut seen = Vec::new();
    while let Some(left) = deadline.checked_duration_since(Instant::now()) {
        let Some(event) = worker.recv_timeout(left) else {
            break;
        };
        if let Some(value) = pick(&event) {
            return value;
        }
        seen.push(summary(&event));
    }
    panic!("the awaited event did not come; seen: {seen:?}");
}

/// An event in a line, for a failure's message.
pub fn summary(event: &Event) -> String {
    let line = match event {
        Event::Frame(f) => format!(
            "Frame(gen {}, 1/{}, {}×{}, step {})",
            f.generation, f.downscale, f.width, f.height, f.step
        ),
        Event::GpuFrame(f) => format!(
            "GpuFrame(gen {}, 1/{}, {}×{}, step {})",
            f.generation, f.downscale, f.width, f.height, f.step
        ),
        Event::Stats(s) => format!("Stats(step {}, loss {})", s.step, s.loss),
        Event::SceneLoaded(info) => format!("SceneLoaded({})", info.scene.name),
        other => format!("{other:?}"),
    };
    line.chars().take(200).collect()
}

/// The step of a stats event.
pub fn stats_step(event: &Event) -> Option<u32> {
    match event {
        Event::Stats(stats) => Some(stats.step),
        _ => None,
    }
}

/// One training step; returns the step reported after it.
pub fn step_once(worker: &TrainingWorker) -> u32 {
    worker.send(Command::StepOnce);
    wait_for(worker, stats_step)
}

/// A `size` × `size` view of the demo scene from `azimuth` radians.
pub fn camera(size: u32, azimuth: f32) -> Camera {
    let eye = 4.0 * Vec3::new(azimuth.cos(), azimuth.sin(), 0.6).normalize();
    Camera::look_at(
        Intrinsics::from_fov_x(size, size, CAMERA_ANGLE_X),
        eye,
        Vec3::ZERO,
        Vec3::Z,
    )
}

/// Asks for a resting view of `camera` in colour.
pub fn render(worker: &TrainingWorker, generation: u64, camera: Camera) {
    worker.send(Command::Render(RenderRequest {
        generation,
        camera,
        mode: RenderMode::Rgb,
        moving: false,
        needs_pixels: false,
    }));
}

/// Frames of `generation` up to its complete full-resolution one.
pub fn frames_until_full(worker: &TrainingWorker, generation: u64) -> Vec<RenderedFrame> {
    let mut frames = Vec::new();
    wait_for(worker, |event| match event {
        Event::Frame(frame) if frame.generation == generation => {
            frames.push(frame.clone());
            (frame.downscale == 1 && frame.complete).then_some(())
        }
        _ => None,
    });
    frames
}
