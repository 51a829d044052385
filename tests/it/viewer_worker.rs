//! The viewer's training thread on the cpu engine and a small demo scene:
//! what it answers to each command, checked by value.
//!
//! The tests whose bounds are on the wall clock (training's share, the
//! picture's lag, a resting camera's first whole picture, turns, a scene
//! read while steps go on, the progressive levels a render budget picks)
//! run alone; those that check only what is answered, however long it
//! takes within [`PATIENCE`], run beside other tests.
//!
//! [`PATIENCE`]: common::worker::PATIENCE

use crate::common;
use crate::common::worker::{
    camera, frames_until_full, options, render, small_demo, spawn, stats_step, step_once, wait_for,
};

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use zrak::engine::EngineKind;
use zrak::field::ModelKind;
use zrak::field::common::{LossKind, Sampling};
use zrak::model::RenderMode;
use zrak::render::export::ExportSettings;
use zrak::render::path::Turntable;
use zrak::scene::demo::{
    DemoConfig, {self},
};
use zrak::session::protocol::{Command, Event, InTurn, RenderRequest, SceneSource};
use zrak::session::worker::{TrainingWorker, WorkerOptions};

#[test]
fn training_reports_stats_with_a_finite_loss_and_honest_psnrs() {
    let _cores = common::shared();
    let worker = spawn(WorkerOptions {
        loss: Some(LossKind::L2),
        // Evaluate after every step, so the first report carries a PSNR.
        val_every_train_seconds: 0.0,
        ..options()
    });
    let engine = wait_for(&worker, |e| match e {
        Event::Engine { kind, .. } => Some(*kind),
        _ => None,
    });
    assert_eq!(engine, EngineKind::Cpu);
    worker.send(Command::Start);
    // The first report with a held-out PSNR (the evaluation renders in
    // chunks after the step, so it may come in a later report).
    let stats = wait_for(&worker, |e| match e {
        Event::Stats(stats) if stats.step > 0 && stats.val_psnr.is_some() => Some(*stats),
        Event::Stats(stats) => {
            assert!(stats.loss.is_finite(), "{stats:?}");
            None
        }
        _ => None,
    });
    assert_eq!(stats.model, ModelKind::Ngp);
    assert!(stats.loss.is_finite() && stats.loss > 0.0, "{stats:?}");
    // L2 is the batch's MSE, so its PSNR is -10 log10(loss) exactly.
    let batch_psnr = stats.batch_psnr.expect("an L2 loss has a batch PSNR");
    assert!(
        (batch_psnr + 10.0 * stats.loss.log10()).abs() < 1e-3,
        "{stats:?}"
    );
    let val_psnr = stats.val_psnr.expect("picked for it");
    // Colours lie in [0, 1], so the MSE is at most 1 (PSNR ≥ 0); an
    // untrained field is far from the 100 dB cap.
    assert!((0.0..60.0).contains(&val_psnr), "{stats:?}");
    assert!(
        stats.train_seconds > 0.0 && stats.ms_per_step > 0.0,
        "{stats:?}"
    );
    assert!(stats.samples_per_ray > 0.0 && stats.samples_per_second > 0.0);
    assert!(stats.memory_bytes > 1 << 20, "{stats:?}");
    worker.send(Command::Pause);
    wait_for(&worker, |e| {
        matches!(e, Event::Running(false)).then_some(())
    });
    worker.shutdown();
}

#[test]
fn a_render_request_refines_to_full_size_and_old_generations_stop() {
    let _alone = common::alone();
    let worker = spawn(options());
    // An untrained field is dense everywhere, so every ray marches its
    // full length: views stay small to keep the test short.
    render(&worker, 7, camera(32, 0.3));
    let frames = frames_until_full(&worker, 7);
    let sizes: Vec<(u32, u32, u32)> = frames
        .iter()
        .map(|f| (f.downscale, f.width, f.height))
        .collect();
    assert_eq!(sizes, vec![(8, 4, 4), (4, 8, 8), (2, 16, 16), (1, 32, 32)]);
    for frame in &frames {
        assert_eq!(frame.pixels.len(), (frame.width * frame.height) as usize);
        assert_eq!((frame.model, frame.step), (ModelKind::Ngp, 0));
        for p in &frame.pixels {
            assert!(p.rgb.iter().all(|c| (0.0..=1.0).contains(c)), "{p:?}");
            assert!((0.0..=1.0).contains(&p.opacity), "{p:?}");
        }
    }

    // A larger view, at once replaced by another: after the newer one's
    // first frame, nothing of the older one arrives.
    render(&worker, 8, camera(256, 1.0));
    render(&worker, 9, camera(32, 2.0));
    let mut newer_seen = false;
    let mut newer = Vec::new();
    wait_for(&worker, |event| match event {
        Event::Frame(frame) if frame.generation == 8 => {
            assert!(!newer_seen, "a frame of generation 8 after generation 9's");
            None
        }
        Event::Frame(frame) if frame.generation == 9 => {
            newer_seen = true;
            newer.push(frame.downscale);
            (frame.downscale == 1 && frame.complete).then_some(())
        }
        _ => None,
    });
    assert_eq!(newer, vec![8, 4, 2, 1]);
    // Nothing of generation 8 is still on its way: a third request (tiny)
    // is answered in full with no frame of generation 8 among its frames.
    render(&worker, 10, camera(8, 3.0));
    wait_for(&worker, |event| match event {
        Event::Frame(frame) => {
            assert_ne!(frame.generation, 8, "generation 8 went on");
            (frame.generation == 10 && frame.downscale == 1 && frame.complete).then_some(())
        }
        _ => None,
    });

    // A moving camera gets its coarsest level at once; the same camera at
    // rest is refined to full size under the new generation.
    let dragged = camera(32, 4.0);
    worker.send(Command::Render(RenderRequest {
        generation: 11,
        camera: dragged,
        mode: RenderMode::Rgb,
        moving: true,
        needs_pixels: false,
    }));
    let first = wait_for(&worker, |event| match event {
        Event::Frame(frame) if frame.generation == 11 => Some(frame.downscale),
        _ => None,
    });
    assert_eq!(first, 8);
    render(&worker, 12, dragged);
    let mut rested = false;
    wait_for(&worker, |event| match event {
        Event::Frame(frame) if frame.generation == 11 => {
            assert!(!rested, "generation 11 after generation 12");
            None
        }
        Event::Frame(frame) if frame.generation == 12 => {
            rested = true;
            assert_eq!(frame.pixels.len(), (frame.width * frame.height) as usize);
            (frame.downscale == 1 && frame.complete).then_some(())
        }
        _ => None,
    });
    worker.shutdown();
}

#[test]
fn reset_forgets_the_steps_and_selecting_the_model_keeps_them() {
    let _cores = common::shared();
    let worker = spawn(options());
    for expected in 1..=3 {
        assert_eq!(step_once(&worker), expected);
    }
    worker.send(Command::SelectModel(ModelKind::Ngp));
    wait_for(&worker, |e| {
        matches!(e, Event::ModelSelected(ModelKind::Ngp)).then_some(())
    });
    render(&worker, 1, camera(16, 0.5));
    let frames = frames_until_full(&worker, 1);
    assert!(frames.iter().all(|f| f.step == 3), "{:?}", frames.len());

    worker.send(Command::Reset);
    render(&worker, 2, camera(16, 1.5));
    let frames = frames_until_full(&worker, 2);
    assert!(frames.iter().all(|f| f.step == 0));
    worker.shutdown();
}

#[test]
fn a_missing_scene_folder_is_reported_while_training_goes_on() {
    let _cores = common::shared();
    let worker = spawn(options());
    worker.send(Command::Start);
    let first = wait_for(&worker, |e| match e {
        Event::Stats(stats) if stats.step > 0 => Some(*stats),
        _ => None,
    });
    // Huber (the default loss) is not a squared error: no batch PSNR.
    assert_eq!(first.batch_psnr, None);
    let before = first.step;
    let missing = PathBuf::from("/nonexistent/zrak-missing-scene");
    worker.send(Command::OpenScene(SceneSource::Folder(missing.clone())));
    let (source, error) = wait_for(&worker, |e| match e {
        Event::SceneFailed { source, error } => Some((source.clone(), error.clone())),
        Event::SceneLoaded(_) => panic!("a missing folder loaded"),
        _ => None,
    });
    assert_eq!(source, SceneSource::Folder(missing));
    assert!(
        error.contains("/nonexistent/zrak-missing-scene") && error.contains("not found"),
        "{error}"
    );
    // The same model keeps counting: the scene was not replaced.
    let after = wait_for(&worker, |e| stats_step(e).filter(|&s| s > before));
    assert!(after > before);
    worker.shutdown();
}

fn save(worker: &TrainingWorker, path: &Path) {
    worker.send(Command::SaveCheckpoint(path.to_path_buf()));
    let saved = wait_for(worker, |e| match e {
        Event::CheckpointSaved(p) => Some(p.clone()),
        Event::Error(e) => panic!("{e}"),
        _ => None,
    });
    assert_eq!(saved, path);
}

#[test]
fn a_checkpoint_restores_its_step_and_one_of_another_scene_is_refused() {
    let _cores = common::shared();
    let dir = tempfile::tempdir().unwrap();
    let checkpoint = dir.path().join("viewer.zrak");
    let worker = spawn(options());
    assert_eq!(step_once(&worker), 1);
    assert_eq!(step_once(&worker), 2);
    save(&worker, &checkpoint);
    assert_eq!(step_once(&worker), 3);

    worker.send(Command::LoadCheckpoint(checkpoint.clone()));
    let (path, model, step) = wait_for(&worker, |e| match e {
        Event::CheckpointLoaded { path, model, step } => Some((path.clone(), *model, *step)),
        Event::Error(e) => panic!("{e}"),
        _ => None,
    });
    assert_eq!((path, model, step), (checkpoint.clone(), ModelKind::Ngp, 2));
    assert_eq!(step_once(&worker), 3);

    // Another scene on disk: the checkpoint no longer fits.
    let other = dir.path().join("other-scene");
    let other_config = DemoConfig {
        train_views: 6,
        ..small_demo()
    };
    demo::write(&other_config, &other).unwrap();
    worker.send(Command::OpenScene(SceneSource::Folder(other.clone())));
    let frames = wait_for(&worker, |e| match e {
        Event::SceneLoaded(info) => Some(info.scene.train.len()),
        Event::SceneFailed { error, .. } => panic!("{error}"),
        _ => None,
    });
    assert_eq!(frames, 6);
    assert_eq!(step_once(&worker), 1);
    worker.send(Command::LoadCheckpoint(checkpoint.clone()));
    let error = wait_for(&worker, |e| match e {
        Event::Error(error) => Some(error.clone()),
        Event::CheckpointLoaded { .. } => panic!("a checkpoint of another scene loaded"),
        _ => None,
    });
    assert!(
        error.contains("viewer.zrak") && error.contains("the checkpoint was trained on scene"),
        "{error}"
    );
    // The current model is untouched.
    assert_eq!(step_once(&worker), 2);
    worker.shutdown();
}

fn turntable(out_dir: &Path, frames: usize) -> ExportSettings {
    ExportSettings {
        turntable: Turntable {
            frames,
            size: Some((8, 8)),
            ..Turntable::default()
        },
        mode: RenderMode::Rgb,
        out_dir: out_dir.to_path_buf(),
        write_gif: true,
        replace_existing: false,
    }
}

#[test]
fn a_turntable_export_reports_progress_and_can_be_cancelled() {
    let _cores = common::shared();
    let dir = tempfile::tempdir().unwrap();
    let worker = spawn(options());
    worker.send(Command::ExportTurntable(turntable(dir.path(), 3)));
    let mut progress = Vec::new();
    let files = wait_for(&worker, |e| match e {
        Event::ExportProgress { done, total } => {
            progress.push((*done, *total));
            None
        }
        Event::ExportFinished(result) => Some(result.clone()),
        _ => None,
    })
    .expect("the export succeeds");
    assert_eq!(progress, vec![(0, 3), (1, 3), (2, 3), (3, 3)]);
    // Three PNG frames, then the GIF.
    assert_eq!(files.len(), 4, "{files:?}");
    assert!(files.iter().all(|f| f.is_file()), "{files:?}");
    assert!(files[3].ends_with("turntable.gif"));

    let cancelled = dir.path().join("cancelled");
    worker.send(Command::ExportTurntable(turntable(&cancelled, 10_000)));
    wait_for(&worker, |e| {
        matches!(e, Event::ExportProgress { done: 1, .. }).then_some(())
    });
    worker.send(Command::CancelExport);
    let result = wait_for(&worker, |e| match e {
        Event::ExportFinished(result) => Some(result.clone()),
        _ => None,
    });
    assert!(result.unwrap_err().contains("cancelled"));
    // Cancelled before the end: not every frame was written, and the
    // unfinished GIF was removed.
    let written = std::fs::read_dir(&cancelled).unwrap().count();
    assert!((1..10_000).contains(&written), "{written} files");
    assert!(!cancelled.join("turntable.gif").exists());
    worker.shutdown();
}

#[test]
fn closing_keeps_each_model_trained_since_its_last_save() {
    let _cores = common::shared();
    let dir = tempfile::tempdir().unwrap();
    let kept_in = |runs: &Path| -> Vec<PathBuf> {
        std::fs::read_dir(runs)
            .map(|entries| entries.map(|e| e.unwrap().path()).collect())
            .unwrap_or_default()
    };

    // Trained and never saved: kept as a run folder when the thread stops.
    let runs = dir.path().join("runs");
    let worker = spawn(WorkerOptions {
        autosave: Some(runs.clone()),
        ..options()
    });
    assert_eq!(step_once(&worker), 1);
    assert_eq!(step_once(&worker), 2);
    worker.shutdown();
    let kept = kept_in(&runs);
    assert_eq!(kept.len(), 1, "{kept:?}");
    let name = kept[0].file_name().unwrap().to_string_lossy().into_owned();
    assert!(name.starts_with("demo-ngp-"), "{name}");
    let checkpoint =
        zrak::model::checkpoint::Checkpoint::load(&kept[0].join("checkpoint.zrak")).unwrap();
    assert_eq!(checkpoint.header["trainer"]["step"], 2);
    let run: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(kept[0].join("run.json")).unwrap()).unwrap();
    assert_eq!(
        (&run["scene"], &run["model"]),
        (&"demo".into(), &"ngp".into())
    );

    // Saved and not trained since: nothing more to keep.
    let runs = dir.path().join("runs_after_save");
    let worker = spawn(WorkerOptions {
        autosave: Some(runs.clone()),
        ..options()
    });
    assert_eq!(step_once(&worker), 1);
    save(&worker, &dir.path().join("saved.zrak"));
    worker.shutdown();
    assert!(kept_in(&runs).is_empty(), "{:?}", kept_in(&runs));

    // `--keep-runs 0`: nothing of this session kept, and the run kept by
    // the first session above is not removed to make room.
    let runs = dir.path().join("runs");
    let worker = spawn(WorkerOptions {
        autosave: Some(runs.clone()),
        kept_runs: 0,
        ..options()
    });
    assert_eq!(step_once(&worker), 1);
    worker.shutdown();
    assert_eq!(kept_in(&runs), kept);
}

#[test]
fn a_scene_loads_while_the_current_one_trains() {
    let _alone = common::alone();
    let dir = tempfile::tempdir().unwrap();
    // Large enough that reading and decoding it takes longer than a couple
    // of small steps.
    let big = dir.path().join("big");
    demo::write(&DemoConfig::default(), &big).unwrap();
    let worker = spawn(options());
    assert_eq!(step_once(&worker), 1);
    worker.send(Command::OpenScene(SceneSource::Folder(big)));
    worker.send(Command::StepOnce);
    worker.send(Command::StepOnce);
    let mut steps_before_loaded = Vec::new();
    let frames = wait_for(&worker, |e| match e {
        Event::Stats(stats) => {
            steps_before_loaded.push(stats.step);
            None
        }
        Event::SceneLoaded(info) => Some(info.scene.train.len()),
        Event::SceneFailed { error, .. } => panic!("{error}"),
        _ => None,
    });
    assert_eq!(frames, DemoConfig::default().train_views);
    // The steps asked for after the scene were taken while it loaded, on
    // the scene of the moment (a stalled thread would take them after,
    // on the new scene, from step 1).
    assert!(
        steps_before_loaded.contains(&2),
        "steps answered before the scene loaded: {steps_before_loaded:?}"
    );
    // The new scene's model starts afresh.
    assert_eq!(step_once(&worker), 1);
    worker.shutdown();
}

#[test]
fn models_in_turn_train_in_order_at_equal_shares_of_training_time() {
    let _alone = common::alone();
    let worker = spawn(WorkerOptions {
        // NeRF with the paper's sampler on batches of 4 rays (1024
        // samples): steps of tens of ms and no occupancy-grid update, so
        // turns come quickly. No held-out evaluations, which would pause
        // training.
        sampling: Some(Sampling::Paper),
        batch_samples: Some(1 << 10),
        val_every_train_seconds: 1e9,
        ..options()
    });
    const SLICE: f64 = 0.4;
    let turns = InTurn {
        models: vec![ModelKind::Ngp, ModelKind::Nerf],
        slice_seconds: SLICE,
    };
    worker.send(Command::TrainInTurn(Some(turns.clone())));
    let echoed = wait_for(&worker, |e| match e {
        Event::InTurn(settings) => Some(settings.clone()),
        _ => None,
    });
    assert_eq!(echoed, Some(turns));
    worker.send(Command::Start);
    // Each turn's model, its training seconds at the last report of the
    // turn (the one sent when the turn passes on), and the longest step it
    // may have taken in the turn. Reports give the median step of the last
    // seconds, which hides one long step (an occupancy-grid update, the
    // first Instant-NGP step), so a step is bounded instead by the
    // training time between the two reports that bracket it.
    let mut ends: Vec<(ModelKind, f64, f64)> = Vec::new();
    let mut last_seconds = [None::<f64>; ModelKind::ALL.len()];
    wait_for(&worker, |e| {
        let Event::Stats(stats) = e else {
            return None;
        };
        let since = last_seconds[stats.model as usize]
            .replace(stats.train_seconds)
            .map_or(stats.train_seconds, |before| stats.train_seconds - before);
        match ends.last_mut() {
            Some(last) if last.0 == stats.model => {
                last.1 = stats.train_seconds;
                last.2 = last.2.max(since);
            }
            _ => ends.push((stats.model, stats.train_seconds, since)),
        }
        // Five turns started: four have ended.
        (ends.len() == 5).then_some(())
    });
    worker.send(Command::Pause);
    let order: Vec<ModelKind> = ends.iter().map(|e| e.0).collect();
    assert_eq!(
        order,
        [
            ModelKind::Ngp,
            ModelKind::Nerf,
            ModelKind::Ngp,
            ModelKind::Nerf,
            ModelKind::Ngp
        ]
    );
    // A turn ends when its model's training time has crossed a whole
    // number of slices since the turns began, within a step after (a step
    // is not cut short). A model that a long step put ahead (the first
    // Instant-NGP step can take longer than a slice) is passed over until
    // the others have caught up, so a turn may span several slices.
    for (i, &(model, seconds, step)) in ends[..4].iter().enumerate() {
        let slices = (seconds / SLICE).floor();
        assert!(
            slices >= 1.0 && seconds - slices * SLICE <= 3.0 * step + 0.25,
            "turn {i} of {model:?} ended at {seconds:.3} s (steps of at most {step:.3} s): {ends:?}"
        );
    }
    // At every hand-over after the first, the two models' training times
    // are within a slice and a step of each other.
    for pair in ends[..4].windows(2).skip(1) {
        let (a, b) = (&pair[0], &pair[1]);
        assert!(
            (a.1 - b.1).abs() <= SLICE + 3.0 * a.2.max(b.2) + 0.25,
            "{ends:?}"
        );
    }
    worker.send(Command::TrainInTurn(None));
    let echoed = wait_for(&worker, |e| match e {
        Event::InTurn(settings) => Some(settings.clone()),
        _ => None,
    });
    assert_eq!(echoed, None);
    worker.shutdown();
}

#[test]
fn training_goes_on_while_the_camera_never_rests() {
    let _alone = common::alone();
    let worker = spawn(options());
    wait_for(&worker, |event| match event {
        Event::Engine { .. } => Some(()),
        _ => None,
    });
    // A new moving camera every 20 ms, as a long drag or `--auto-orbit`
    // sends, the first before training starts: each coarse frame (1/8 of
    // 256 px, an untrained field marched end to end) takes longer than
    // that, so without a share kept for training the renders would follow
    // one another and no step would run.
    let moving_camera = |generation: u64| {
        Command::Render(RenderRequest {
            generation,
            camera: camera(256, generation as f32 * 0.05),
            mode: RenderMode::Rgb,
            moving: true,
            needs_pixels: false,
        })
    };
    let mut generation = 100;
    worker.send(moving_camera(generation));
    worker.send(Command::Start);
    let started = Instant::now();
    let mut trained_seconds = 0.0;
    let mut steps = Vec::new();
    while started.elapsed() < Duration::from_secs(8) {
        generation += 1;
        worker.send(moving_camera(generation));
        let next_request = Instant::now() + Duration::from_millis(20);
        while let Some(left) = next_request.checked_duration_since(Instant::now()) {
            if let Some(Event::Stats(stats)) = worker.recv_timeout(left) {
                steps.push(stats.step);
                trained_seconds = stats.train_seconds;
            }
        }
    }
    let elapsed = started.elapsed().as_secs_f64();
    worker.shutdown();
    // Training gets a quarter of the time while the camera moves (a step
    // of d seconds, then 3 d for rendering: `MOVING_IDLE_PER_STEP`); a
    // tenth allows for the step in progress when the clock stops and for
    // a loaded machine.
    assert!(
        trained_seconds >= 0.1 * elapsed,
        "{trained_seconds:.2} s of training in {elapsed:.1} s of a moving camera, steps {steps:?}"
    );
}

/// A frame of the view as it arrived: when (seconds since the run began),
/// the step and training seconds its level began at, and its downscale.
#[derive(Debug, Clone, Copy)]
struct Arrival {
    at: f64,
    step: u32,
    train_seconds: f64,
    downscale: u32,
    /// Sent with all its rows drawn (not band by band before its last).
    complete: bool,
}

/// What a run of the thread showed.
#[derive(Debug, Default)]
struct Watched {
    frames: Vec<Arrival>,
    /// (seconds since the run began, training seconds, step) of each
    /// stats event.
    stats: Vec<(f64, f64, u32)>,
    /// A bound on the longest step: the most training time between two
    /// reports (a report's ms per step is a median, which hides the one
    /// long step that also updated the grid).
    longest_step: f64,
    /// Render seconds of each level finished, by downscale, as the
    /// thread's traces of where its time went add them up.
    levels: Vec<(u32, f64)>,
    /// Render seconds of levels not yet finished, by downscale.
    level_in_progress: Vec<(u32, f64)>,
    /// Where the thread's time went, over the traces received.
    time: zrak::session::schedule::ScheduleTrace,
}

impl Watched {
    /// Adds a trace's rendering: the seconds of each downscale go to the
    /// level in progress until a level of it finishes. A trace that holds
    /// the end of one level and the start of the next charges both to the
    /// first, which only lengthens the measured cost.
    fn add_trace(&mut self, trace: &zrak::session::schedule::ScheduleTrace) {
        self.time.merge(trace);
        for level in &trace.rendering {
            let index = match self
                .level_in_progress
                .iter()
                .position(|(d, _)| *d == level.downscale)
            {
                Some(index) => index,
                None => {
                    self.level_in_progress.push((level.downscale, 0.0));
                    self.level_in_progress.len() - 1
                }
            };
            self.level_in_progress[index].1 += level.seconds;
            if level.finished > 0 {
                let seconds = std::mem::take(&mut self.level_in_progress[index].1);
                // Several levels in one trace: each its share.
                for _ in 0..level.finished {
                    self.levels
                        .push((level.downscale, seconds / level.finished as f64));
                }
            }
        }
    }

    /// The longest render of a level of `downscale` measured, in seconds.
    fn longest_level(&self, downscale: u32) -> Option<f64> {
        self.levels
            .iter()
            .filter(|(d, _)| *d == downscale)
            .map(|(_, seconds)| *seconds)
            .reduce(f64::max)
    }

    /// The longest render of any level measured, in seconds, counting
    /// the levels still in progress for what they have cost so far.
    fn longest_any_level(&self) -> f64 {
        self.levels
            .iter()
            .chain(&self.level_in_progress)
            .map(|(_, s)| *s)
            .fold(0.0, f64::max)
    }
}

/// Collects frames of `generation` (as pixels or textures) and stats for
/// `seconds`, or until `stop` says so of a frame.
fn watch(
    worker: &TrainingWorker,
    generation: u64,
    began: Instant,
    seconds: f64,
    mut stop: impl FnMut(&Arrival) -> bool,
    into: &mut Watched,
) {
    let deadline = began + Duration::from_secs_f64(seconds);
    while let Some(left) = deadline.checked_duration_since(Instant::now()) {
        let Some(event) = worker.recv_timeout(left) else {
            break;
        };
        let at = began.elapsed().as_secs_f64();
        let arrival = match &event {
            Event::Frame(f) if f.generation == generation => Arrival {
                at,
                step: f.step,
                train_seconds: f.train_seconds,
                downscale: f.downscale,
                complete: f.complete,
            },
            Event::GpuFrame(f) if f.generation == generation => Arrival {
                at,
                step: f.step,
                train_seconds: f.train_seconds,
                downscale: f.downscale,
                complete: f.complete,
            },
            Event::Stats(s) => {
                // The first report's steps began before the watch did.
                if let Some(&(_, before, _)) = into.stats.last() {
                    into.longest_step = into.longest_step.max(s.train_seconds - before);
                }
                into.stats.push((at, s.train_seconds, s.step));
                continue;
            }
            Event::Schedule(trace) => {
                into.add_trace(trace);
                continue;
            }
            Event::Error(error) => panic!("{error}"),
            _ => continue,
        };
        into.frames.push(arrival);
        if stop(&arrival) {
            return;
        }
    }
}

/// How long the camera rests, after the first step, while training's share
/// and the picture's lag are measured. The share of a run read at a report is off by at most a
/// fraction of a step: with the longest steps measured on two busy cores
/// (3.0 s for NeRF on the cpu engine, a grid update; 2.1 s on lavapipe),
/// 0.3 of one over 15 s is 0.06, inside the 0.1 between the schedule's 0.7
/// and the 0.6 asked for (a step of 5 s would still fit). Measured on a
/// 2-core Zen 4 over 20 s: 26 steps on the cpu engine and 59 to 63 on
/// lavapipe, shares 0.69 to 0.74; three quarters of those steps are still
/// many more than the three advances of the picture asserted.
const WATCH_SECONDS: f64 = 15.0;

/// A guard on the wait for the first step, which the watch then follows:
/// not a bound on its time, which the lag bound takes from the longest
/// step measured.
const FIRST_STEP_PATIENCE: f64 = 300.0;

/// NeRF or Mip-NeRF with the camera at rest: training gets its share, the
/// picture keeps up, and a camera that comes to rest is drawn at full
/// resolution within [`settle_bound_seconds`]. Both bounds are computed
/// from what this run measured on this machine (its longest step, and the
/// render seconds of the levels it drew, from the thread's traces), never
/// from an assumed speed: on a slow machine a full-resolution picture
/// takes longer, and comes all the same. `view` is the viewport's side.
fn the_picture_keeps_up_while_training_keeps_its_share(
    model: ModelKind,
    engine: EngineKind,
    options: WorkerOptions,
    view: u32,
) {
    use zrak::session::schedule::{
        DEFAULT_TRAINING_SHARE, lag_bound_seconds, settle_bound_seconds,
    };
    let worker = TrainingWorker::spawn_with(SceneSource::Demo, Some(engine), model, options);
    wait_for(&worker, |event| match event {
        Event::Engine { kind, .. } => {
            assert_eq!(*kind, engine);
            Some(())
        }
        _ => None,
    });
    let began = Instant::now();
    render(&worker, 1, camera(view, 0.3));
    worker.send(Command::Start);
    let mut run = Watched::default();
    // Until the first step ends (Instant-NGP's first steps on lavapipe
    // update every cell of its 128³ occupancy grid: tens of seconds), then
    // for the watch itself.
    while run.stats.is_empty() && began.elapsed().as_secs_f64() < FIRST_STEP_PATIENCE {
        let until = began.elapsed().as_secs_f64() + 0.5;
        watch(&worker, 1, began, until, |_| false, &mut run);
    }
    let first_step_at = run.stats.first().map_or(0.0, |s| s.0);
    watch(
        &worker,
        1,
        began,
        first_step_at + WATCH_SECONDS,
        |_| false,
        &mut run,
    );

    // Training's share of the wall time, from the start to its last report.
    // The share is 0.7; the issue asks for at least 0.6. The time is shared
    // step by step, so over a run of a few steps (a step that updates the
    // occupancy grid takes seconds on two busy cores) the share measured
    // swings by up to 0.3 of a step over the run; and evaluation takes at
    // least 48 pixels however slow the model.
    assert!(
        !run.stats.is_empty(),
        "no step in {WATCH_SECONDS} s; frames {:?}",
        run.frames
    );
    let (first, last) = (run.stats[0], *run.stats.last().expect("stats"));
    let (wall, trained) = (last.0, last.1);
    let share = trained / wall;
    let steps = last.2;
    let time = &run.time;
    println!(
        "{model:?} on {engine:?}: {steps} steps, training {trained:.1} s of {wall:.1} s \
         ({share:.2}); the thread's traces: {:.1} s of wall time, training {:.1} s, drawing \
         {:.1} s, evaluating {:.1} s, idle {:.1} s, other {:.1} s; longest step {:.2} s; \
         frames {:?}",
        time.wall_seconds,
        time.training_seconds,
        time.rendering_seconds(),
        time.evaluation_seconds,
        time.idle_seconds,
        time.other_seconds(),
        run.longest_step,
        run.frames
            .iter()
            .map(|f| (format!("{:.1}", f.at), f.step, f.downscale))
            .collect::<Vec<_>>()
    );
    assert!(
        share >= 0.6,
        "training had {share:.2} of the wall time ({trained:.1} of {wall:.1} s)"
    );
    // No upper bound: the view takes its share only while it has work. A
    // view this small is redrawn at full resolution in a fraction of a
    // step, and once the picture shows the latest step there is nothing
    // to draw until the next, so training goes on (measured: 0.91 for
    // NeRF on a 16-pixel view). What the view gets is checked below.

    // The picture keeps up: after the first step, a picture of a later
    // step than any shown before comes at least every `lag_bound_seconds`
    // (two redraws at rendering's share, each behind a step), so the one
    // shown is never older than that. A redraw costs at most the longest
    // level measured.
    let bound = lag_bound_seconds(
        DEFAULT_TRAINING_SHARE,
        run.longest_any_level(),
        run.longest_step,
    );
    let shown = &run.frames;
    assert!(
        shown.windows(2).all(|p| p[1].step >= p[0].step),
        "a picture of an earlier step after a later one: {shown:?}"
    );
    let mut advances: Vec<&Arrival> = Vec::new();
    for frame in shown.iter().filter(|f| f.at >= first.0) {
        if advances.last().is_none_or(|a| frame.step > a.step) {
            advances.push(frame);
        }
    }
    assert!(
        advances.len() >= 3,
        "the shown step advanced {} times in {wall:.1} s: {shown:?}",
        advances.len()
    );
    let mut since = first.0;
    for frame in &advances {
        assert!(
            frame.at - since <= bound,
            "the shown step stood still for {:.1} s (bound {bound:.1} s) before {frame:?}: \
             {shown:?}",
            frame.at - since
        );
        since = frame.at;
    }
    assert!(
        last.0 - since <= bound,
        "the shown step stood still for the last {:.1} s (bound {bound:.1} s)",
        last.0 - since
    );
    let latest = shown.last().expect("frames");
    assert!(
        last.1 - latest.train_seconds <= bound,
        "the last picture is {:.1} s of training behind (bound {bound:.1} s)",
        last.1 - latest.train_seconds
    );

    // The camera moves for a second, then rests: its full-resolution
    // picture comes within the settle bound (the first level and the
    // refinements, all of them at most 4/3 of the full level's render
    // time, at rendering's share, and a step), from the full level's cost
    // as measured here. Doubled, and a second more: the levels' costs move
    // as training goes on (an occupancy grid that fills or empties).
    let moved = camera(view, 1.3);
    for generation in 2..=6 {
        worker.send(Command::Render(RenderRequest {
            generation,
            camera: moved,
            mode: RenderMode::Rgb,
            moving: true,
            needs_pixels: false,
        }));
        std::thread::sleep(Duration::from_millis(200));
    }
    let rested = Instant::now();
    render(&worker, 7, moved);
    let mut after = Watched::default();
    // Only a guard against a thread that never draws it: the bound itself
    // is checked below, from what the levels cost.
    let patience = 60.0
        + 10.0
            * settle_bound_seconds(
                DEFAULT_TRAINING_SHARE,
                run.longest_any_level(),
                run.longest_step,
            );
    watch(
        &worker,
        7,
        rested,
        patience,
        |f| f.downscale == 1 && f.complete,
        &mut after,
    );
    let full = *after
        .frames
        .iter()
        .find(|f| f.downscale == 1 && f.complete)
        .unwrap_or_else(|| {
            panic!(
                "no full-resolution frame in {patience:.0} s: {:?}",
                after.frames
            )
        });
    // The trace that holds the full level's last band comes within a
    // trace interval.
    let trace_wait = zrak::session::schedule::TRACE_INTERVAL.as_secs_f64() + 0.5;
    watch(
        &worker,
        7,
        Instant::now(),
        trace_wait,
        |_| false,
        &mut after,
    );
    let full_level = [run.longest_level(1), after.longest_level(1)]
        .into_iter()
        .flatten()
        .fold(0.0, f64::max);
    let longest_step = run.longest_step.max(after.longest_step);
    let limit = 2.0 * settle_bound_seconds(DEFAULT_TRAINING_SHARE, full_level, longest_step) + 1.0;
    println!(
        "full resolution {:.1} s after the camera came to rest (a full level {full_level:.2} s \
         of render time, bound {limit:.1} s): {:?}",
        full.at, after.frames
    );
    assert!(
        full.at <= limit,
        "full resolution came {:.1} s after the camera rested (bound {limit:.1} s)",
        full.at
    );
    worker.shutdown();
}

/// Issue 43: on a slow machine a whole viewport of NeRF takes several
/// refresh budgets to render, and the picture stayed at the finest level
/// that fit one budget (1/3 of the viewport for 40 s on a 2-core Zen 3).
/// Here a viewport of 96 × 96 pixels of NeRF on the cpu engine takes
/// seconds of render time (1 to 11 s on a 2-core Zen 4 as the occupancy
/// grid fills): the resting picture must still reach full
/// resolution, within the settle bound of the full level's measured cost,
/// and a level slower than the budget must be shown band by band (frames
/// sent before its last row) while training goes on.
#[test]
fn a_resting_picture_reaches_full_resolution_when_a_level_takes_several_budgets() {
    let _alone = common::alone();
    use zrak::session::schedule::{DEFAULT_TRAINING_SHARE, refresh_budget, settle_bound_seconds};
    let worker = TrainingWorker::spawn_with(
        SceneSource::Demo,
        Some(EngineKind::Cpu),
        ModelKind::Nerf,
        WorkerOptions {
            demo: small_demo(),
            ..WorkerOptions::default()
        },
    );
    wait_for(&worker, |event| {
        matches!(event, Event::Engine { .. }).then_some(())
    });
    let began = Instant::now();
    render(&worker, 1, camera(96, 0.3));
    worker.send(Command::Start);
    let mut run = Watched::default();
    // A guard only: the bound is checked below from what the levels cost.
    watch(
        &worker,
        1,
        began,
        300.0,
        |f| f.downscale == 1 && f.complete,
        &mut run,
    );
    let full = *run
        .frames
        .iter()
        .find(|f| f.downscale == 1 && f.complete)
        .unwrap_or_else(|| panic!("no full-resolution frame: {:?}", run.frames));
    // The trace of the full level's last band.
    let trace_wait = zrak::session::schedule::TRACE_INTERVAL.as_secs_f64() + 0.5;
    watch(&worker, 1, Instant::now(), trace_wait, |_| false, &mut run);
    worker.shutdown();
    let full_level = run
        .longest_level(1)
        .expect("the full level finished and was traced");
    let limit =
        2.0 * settle_bound_seconds(DEFAULT_TRAINING_SHARE, full_level, run.longest_step) + 1.0;
    let budget = refresh_budget(DEFAULT_TRAINING_SHARE);
    println!(
        "full resolution after {:.1} s (full level {full_level:.2} s of render time, budget \
         {budget:.1} s, longest step {:.2} s, bound {limit:.1} s); frames {:?}",
        full.at,
        run.longest_step,
        run.frames
            .iter()
            .map(|f| (format!("{:.1}", f.at), f.step, f.downscale, f.complete))
            .collect::<Vec<_>>()
    );
    assert!(
        full.at <= limit,
        "full resolution came {:.1} s after the camera rested (bound {limit:.1} s)",
        full.at
    );
    // A level longer than the budget and a unit of drawing (~40 ms) is
    // sent at least once before its last row, over the coarser picture.
    if full_level > 1.2 * budget {
        let sent_early = run.frames.iter().any(|f| f.downscale == 1 && !f.complete);
        assert!(
            sent_early,
            "a full level of {full_level:.1} s (budget {budget:.1} s) was not shown band by \
             band: {:?}",
            run.frames
        );
    } else {
        println!("the full level fit the budget here: no redraw was sent in bands");
    }
}

/// `model` on the cpu engine, viewed `view` pixels wide.
fn on_the_cpu_engine(model: ModelKind, view: u32) {
    let _alone = common::alone();
    the_picture_keeps_up_while_training_keeps_its_share(
        model,
        EngineKind::Cpu,
        WorkerOptions {
            demo: small_demo(),
            ..WorkerOptions::default()
        },
        view,
    );
}

#[test]
fn nerf_on_the_cpu_engine_trains_at_its_share_and_its_picture_keeps_up() {
    on_the_cpu_engine(ModelKind::Nerf, 16);
}

#[test]
fn mipnerf_on_the_cpu_engine_trains_at_its_share_and_its_picture_keeps_up() {
    on_the_cpu_engine(ModelKind::MipNerf, 16);
}

#[test]
fn ngp_on_the_cpu_engine_trains_at_its_share_and_its_picture_keeps_up() {
    on_the_cpu_engine(ModelKind::Ngp, 32);
}

/// The gpu engine (lavapipe here) on a device shared with a window, as
/// `zrak view --engine gpu` runs it: the view comes as textures drawn band
/// by band. lavapipe runs the papers' 8 × 256 networks at well under a
/// G FLOP/s on two busy cores (`zrak bench throughput --engine gpu --model
/// nerf`: 86 s a step of 2^12 samples), a pixel of them in about a second,
/// so NeRF and Mip-NeRF have the small networks the gpu parity tests use
/// (`shape`); Instant-NGP has its own.
fn on_the_gpu_engine(model: ModelKind, shape: Option<common::NerfKind>, view: u32) {
    let _alone = common::alone();
    let context = match zrak::engine::gpu::GpuContext::new() {
        Ok(context) => context,
        Err(error) => {
            println!("no gpu adapter ({error}): nothing to test");
            return;
        }
    };
    the_picture_keeps_up_while_training_keeps_its_share(
        model,
        EngineKind::Gpu,
        WorkerOptions {
            demo: small_demo(),
            batch_samples: Some(1 << 12),
            nerf_shape: shape.map(common::small_nerf_shape),
            gpu_device: Some(context),
            ..WorkerOptions::default()
        },
        view,
    );
}

#[test]
fn nerf_on_the_gpu_engine_trains_at_its_share_and_its_picture_keeps_up() {
    on_the_gpu_engine(ModelKind::Nerf, Some(common::NerfKind::Nerf), 8);
}

#[test]
fn mipnerf_on_the_gpu_engine_trains_at_its_share_and_its_picture_keeps_up() {
    on_the_gpu_engine(ModelKind::MipNerf, Some(common::NerfKind::MipNerf), 8);
}

#[test]
fn ngp_on_the_gpu_engine_trains_at_its_share_and_its_picture_keeps_up() {
    on_the_gpu_engine(ModelKind::Ngp, None, 16);
}
