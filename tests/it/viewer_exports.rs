//! The viewer's crop box and exports on the training thread: a cpu-engine
//! worker on a small demo scene, checked by value (what it renders, the
//! files it writes, what a cancel leaves). They check only what is
//! answered, so they run beside other tests.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use glam::{DMat4, DVec3, Vec3};
use zrak::field::ModelKind;
use zrak::field::mlp::Precision;
use zrak::mesh::extract::{MeshSettings, extract_mesh, sample_density};
use zrak::mesh::points::{PointSettings, extract_points, stride_for};
use zrak::mesh::points_to_ply;
use zrak::model::RenderMode;
use zrak::model::checkpoint::Checkpoint;
use zrak::render::camera_path::nerfstudio::CameraPathFile;
use zrak::render::camera_path::{CameraPath, Keyframe, look_at};
use zrak::scene::crop::CropBox;
use zrak::scene::demo::{
    DemoConfig, {self},
};
use zrak::session::protocol::{CameraPathExport, Command, Event, MeshExport, PointsExport};
use zrak::session::worker::{TrainingWorker, WorkerOptions};
use zrak::train::trainer::Trainer;

use crate::common;
use crate::common::worker::{
    camera, frames_until_full, options, render, small_demo, spawn, step_once, wait_for,
};

fn save(worker: &TrainingWorker, path: &Path) {
    worker.send(Command::SaveCheckpoint(path.to_path_buf()));
    let saved = wait_for(worker, |e| match e {
        Event::CheckpointSaved(p) => Some(p.clone()),
        Event::Error(e) => panic!("{e}"),
        _ => None,
    });
    assert_eq!(saved, path);
}

/// What an export says: its progress reports, then its files or error.
type ExportOutcome = (Vec<(usize, usize)>, Result<Vec<PathBuf>, String>);

/// The next `ExportFinished`, with every progress report before it.
fn export_result(worker: &TrainingWorker) -> ExportOutcome {
    let mut progress = Vec::new();
    let result = wait_for(worker, |e| match e {
        Event::ExportProgress { done, total } => {
            progress.push((*done, *total));
            None
        }
        Event::ExportFinished(result) => Some(result.clone()),
        _ => None,
    });
    (progress, result)
}

fn crop_answer(worker: &TrainingWorker) -> (Option<CropBox>, Option<String>) {
    wait_for(worker, |e| match e {
        Event::CropSet { crop, refused } => Some((*crop, refused.clone())),
        _ => None,
    })
}

#[test]
fn a_crop_box_that_holds_nothing_renders_only_background() {
    let _cores = common::shared();
    let worker = spawn(options());
    for _ in 0..20 {
        step_once(&worker);
    }
    render(&worker, 1, camera(24, 0.3));
    let before = frames_until_full(&worker, 1).pop().unwrap();
    let opaque = before.pixels.iter().filter(|p| p.opacity > 0.05).count();
    assert!(opaque > 0, "the uncropped view shows something");

    // A small box far outside the scene: nothing of it is left.
    let empty = CropBox::axis_aligned(Vec3::splat(50.0), Vec3::splat(0.1));
    worker.send(Command::SetCrop(Some(empty)));
    assert_eq!(crop_answer(&worker), (Some(empty), None));
    render(&worker, 2, camera(24, 0.3));
    let after = frames_until_full(&worker, 2).pop().unwrap();
    assert_eq!(after.pixels.len(), before.pixels.len());
    for p in &after.pixels {
        assert_eq!(p.opacity, 0.0, "{p:?}");
        assert_eq!(p.rgb, after.pixels[0].rgb, "one background colour");
    }
    // A bad box is refused and the one set stays.
    let bad = CropBox::axis_aligned(Vec3::ZERO, Vec3::new(1.0, 0.0, 1.0));
    worker.send(Command::SetCrop(Some(bad)));
    let (kept, refused) = crop_answer(&worker);
    assert_eq!(kept, Some(empty));
    assert!(refused.unwrap().contains("above zero"));
    // Off again: the picture comes back.
    worker.send(Command::SetCrop(None));
    assert_eq!(crop_answer(&worker), (None, None));
    render(&worker, 3, camera(24, 0.3));
    let back = frames_until_full(&worker, 3).pop().unwrap();
    assert_eq!(
        back.pixels.iter().filter(|p| p.opacity > 0.05).count(),
        opaque
    );
    worker.shutdown();
}

#[test]
fn the_viewers_mesh_and_points_are_the_commands_and_an_existing_file_stays() {
    let _cores = common::shared();
    let dir = tempfile::tempdir().unwrap();
    let options = WorkerOptions {
        precision: Precision::F32,
        ..options()
    };
    let (seed, batch_samples, sampling) = (options.seed, options.batch_samples, options.sampling);
    let worker = spawn(options);
    for _ in 0..20 {
        step_once(&worker);
    }
    let checkpoint = dir.path().join("mesh.zrak");
    save(&worker, &checkpoint);
    let crop = CropBox::axis_aligned(Vec3::new(0.1, 0.0, 0.0), Vec3::new(1.6, 1.4, 1.2));
    worker.send(Command::SetCrop(Some(crop)));
    crop_answer(&worker);
    // The command's function on the same model (the saved checkpoint),
    // settings and box.
    let scene = Arc::new(demo::build(&small_demo()));
    let settings = zrak::engine::request::ModelSettings {
        seed,
        loss: ModelKind::Ngp.default_loss(),
        batch_samples,
        sampling: sampling.unwrap_or(zrak::field::common::Sampling::Occupancy),
        precision: Precision::F32,
        refine_cameras: false,
        appearance: false,
    };
    let mut trainer = Trainer::new(
        Box::new(zrak::engine::cpu::model::CpuModel::build(
            &zrak::engine::request::ModelRequest::new(ModelKind::Ngp, settings),
            &scene,
        )),
        scene.clone(),
        seed,
    );
    trainer
        .restore(&Checkpoint::load(&checkpoint).unwrap())
        .unwrap();
    // A threshold the briefly trained field crosses: its 80th percentile
    // over the box (so about a fifth of the grid is inside the surface).
    let grid = sample_density(
        trainer.model.as_ref(),
        &MeshSettings {
            resolution: 40,
            threshold: 1.0,
            region: crop,
            min_component: None,
        },
        &mut |_| {},
    )
    .unwrap();
    let mut values = grid.values.clone();
    values.sort_by(f32::total_cmp);
    let threshold = values[values.len() * 4 / 5];
    assert!(threshold > 0.0, "{threshold}");
    let out = dir.path().join("viewer.ply");
    let order = MeshExport {
        out: out.clone(),
        resolution: 40,
        threshold: Some(threshold),
        min_component: None,
        replace_existing: false,
    };
    worker.send(Command::ExportMesh(order.clone()));
    let (progress, result) = export_result(&worker);
    assert_eq!(result, Ok(vec![out.clone()]));
    // One report per slab, then the surface.
    let (last_done, total) = *progress.last().unwrap();
    assert!(total >= 2 && last_done == total - 1, "{progress:?}");
    assert!(
        progress.windows(2).all(|w| w[1].0 == w[0].0 + 1),
        "{progress:?}"
    );

    let (mesh, _) = extract_mesh(
        trainer.model.as_ref(),
        &MeshSettings {
            resolution: 40,
            threshold,
            region: crop,
            min_component: None,
        },
        &mut |_| {},
    )
    .unwrap();
    assert!(
        mesh.positions.len() > 100,
        "{} vertices",
        mesh.positions.len()
    );
    let written = std::fs::read(&out).unwrap();
    let header = String::from_utf8_lossy(&written[..200]).to_string();
    assert!(
        header.contains(&format!("element vertex {}\n", mesh.positions.len())),
        "{header}"
    );
    // Same vertices (positions and colours) and faces, byte for byte.
    assert!(written == mesh.to_ply(), "the viewer's mesh differs");
    assert!(mesh.positions.iter().all(|p| crop.contains(*p)));

    // Asked again without "replace": refused, the file untouched.
    worker.send(Command::ExportMesh(order.clone()));
    let (_, refused) = export_result(&worker);
    assert!(refused.unwrap_err().contains("already exists"));
    assert!(std::fs::read(&out).unwrap() == written);
    worker.send(Command::ExportMesh(MeshExport {
        replace_existing: true,
        ..order
    }));
    assert_eq!(export_result(&worker).1, Ok(vec![out]));

    // The point cloud too: the command's function on the same model with
    // the same crop box gives the same file.
    let points = dir.path().join("points.ply");
    worker.send(Command::ExportPoints(PointsExport {
        out: points.clone(),
        max_rays: 3000,
        min_opacity: 0.2,
        replace_existing: false,
    }));
    let (progress, result) = export_result(&worker);
    assert_eq!(result, Ok(vec![points.clone()]));
    let views = scene.photographed_training_views();
    assert_eq!(progress.last(), Some(&(views.len(), views.len())));
    trainer.model.set_crop(Some(crop)).unwrap();
    let (positions, colours) = extract_points(
        trainer.model.as_ref(),
        views,
        &PointSettings {
            stride: stride_for(views, 3000),
            min_opacity: 0.2,
            crop: Some(crop),
        },
        &mut |_| {},
    );
    assert!(!positions.is_empty());
    assert!(std::fs::read(&points).unwrap() == points_to_ply(&positions, &colours));
    worker.shutdown();
}

fn two_keyframe_path(frames_per_second: f64) -> CameraPathFile {
    let look = |eye: DVec3| Keyframe::new(look_at(eye, DVec3::ZERO, DVec3::Z), 45.0);
    CameraPathFile::new(
        CameraPath::new(vec![
            look(DVec3::new(4.0, 0.0, 2.0)),
            look(DVec3::new(0.0, 4.0, 2.0)),
        ]),
        16,
        16,
        frames_per_second,
        DMat4::IDENTITY,
    )
}

#[test]
fn cancelled_exports_leave_their_frames_and_no_half_written_file() {
    let _cores = common::shared();
    let dir = tempfile::tempdir().unwrap();
    let worker = spawn(options());
    let cancel_after = |done_at_least: usize| {
        wait_for(&worker, |e| match e {
            Event::ExportProgress { done, .. } if *done >= done_at_least => Some(()),
            Event::ExportFinished(result) => panic!("finished before the cancel: {result:?}"),
            _ => None,
        });
        worker.send(Command::CancelExport);
        let (_, result) = export_result(&worker);
        assert!(result.unwrap_err().contains("cancelled"));
    };

    // A video: cancelled while its frames render.
    let video = dir.path().join("path.mp4");
    worker.send(Command::ExportCameraPath(CameraPathExport {
        file: two_keyframe_path(120.0),
        out: video.clone(),
        size: None,
        fps: None,
        mode: RenderMode::Rgb,
        replace_existing: false,
    }));
    cancel_after(2);
    assert!(!video.exists());
    let frames = dir.path().join("path.frames");
    let names: Vec<String> = std::fs::read_dir(&frames)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().to_string())
        .collect();
    let pngs = names.iter().filter(|n| n.ends_with(".png")).count();
    assert!((2..120).contains(&pngs), "{names:?}");
    assert!(
        names
            .iter()
            .all(|n| n.starts_with("frame_") || n == "camera_path_render.json"),
        "only whole frames and the manifest: {names:?}"
    );
    // Nothing but the frames folder beside the video.
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);

    // A mesh: cancelled between slabs of its grid.
    let mesh = dir.path().join("mesh.obj");
    worker.send(Command::ExportMesh(MeshExport {
        out: mesh.clone(),
        resolution: 400,
        threshold: None,
        min_component: None,
        replace_existing: false,
    }));
    cancel_after(1);
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);

    // The video again, to the end: it continues from the frames on disk
    // and leaves the video alone.
    worker.send(Command::ExportCameraPath(CameraPathExport {
        file: two_keyframe_path(8.0),
        out: video.clone(),
        size: Some((32, 16)),
        fps: None,
        mode: RenderMode::Depth,
        replace_existing: true,
    }));
    let (progress, result) = export_result(&worker);
    assert_eq!(result, Ok(vec![video.clone()]));
    // 8 frames rendered, then 8 encoded.
    assert_eq!(progress.last(), Some(&(16, 16)), "{progress:?}");
    assert!(std::fs::metadata(&video).unwrap().len() > 100);
    assert!(!frames.exists(), "the frames are removed once encoded");
    worker.shutdown();
}

#[test]
fn a_runs_crop_box_is_saved_beside_its_checkpoint_and_comes_back_with_it() {
    let _cores = common::shared();
    let dir = tempfile::tempdir().unwrap();
    let worker = spawn(options());
    step_once(&worker);
    let crop = CropBox {
        centre: Vec3::new(0.1, 0.2, -0.1),
        size: Vec3::new(0.8, 0.9, 1.0),
        rotation: glam::Quat::from_rotation_z(0.4),
    };
    worker.send(Command::SetCrop(Some(crop)));
    assert_eq!(crop_answer(&worker), (Some(crop), None));
    // A run folder: the checkpoint is checkpoint.zrak.
    let run = dir.path().join("run");
    std::fs::create_dir(&run).unwrap();
    let checkpoint = run.join(zrak::train::run::CHECKPOINT_FILE);
    save(&worker, &checkpoint);
    assert_eq!(CropBox::load_from_run(&run), Ok(Some(crop)));
    // A checkpoint anywhere else leaves its folder alone.
    save(&worker, &dir.path().join("loose.zrak"));
    assert_eq!(CropBox::load_from_run(dir.path()), Ok(None));

    worker.send(Command::SetCrop(None));
    assert_eq!(crop_answer(&worker), (None, None));
    worker.send(Command::LoadCheckpoint(checkpoint));
    assert_eq!(crop_answer(&worker), (Some(crop), None));
    worker.shutdown();
}

/// The figure in the notes: the viewer's mesh export of the demo scene
/// (128 × 128 views, 100 of them) at resolution 128 after 300 steps of
/// Instant-NGP on the cpu engine. Run with `cargo test --release --test it --
/// --ignored viewer_mesh_export_of_the_demo`.
#[test]
#[ignore = "a measurement, minutes long"]
fn viewer_mesh_export_of_the_demo() {
    let _cores = common::shared();
    let dir = tempfile::tempdir().unwrap();
    let worker = spawn(WorkerOptions {
        demo: DemoConfig::default(),
        ..WorkerOptions::default()
    });
    let started = Instant::now();
    for _ in 0..300 {
        step_once(&worker);
    }
    eprintln!("300 steps in {:.1} s", started.elapsed().as_secs_f64());
    let out = dir.path().join("demo.ply");
    let started = Instant::now();
    worker.send(Command::ExportMesh(MeshExport {
        out: out.clone(),
        resolution: 128,
        threshold: None,
        min_component: None,
        replace_existing: false,
    }));
    let (progress, result) = export_result(&worker);
    let seconds = started.elapsed().as_secs_f64();
    assert_eq!(result, Ok(vec![out.clone()]));
    let bytes = std::fs::read(&out).unwrap();
    let header = String::from_utf8_lossy(&bytes[..300]).to_string();
    let count = |element: &str| {
        header
            .lines()
            .find_map(|l| l.strip_prefix(&format!("element {element} ")))
            .unwrap()
            .to_string()
    };
    eprintln!(
        "viewer mesh export at resolution 128: {seconds:.1} s, {} units, {} vertices, {} faces, {} bytes",
        progress.last().unwrap().1,
        count("vertex"),
        count("face"),
        bytes.len()
    );
    worker.shutdown();
}
