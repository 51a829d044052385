//! Forward-facing captures: the forward-facing demo written as an LLFF
//! folder and read back, `zrak convert` of it to a transforms.json, and its
//! rays in normalised device coordinates.

use std::path::Path;

use glam::Vec3;
use zrak::model::RenderMode;
use zrak::model::pixels::{render_pixels, to_image};
use zrak::render::camera_path::PathSample;
use zrak::render::camera_path::frames::{BACKGROUND, FrameJob, RenderSource};
use zrak::render::path::{Turntable, turntable_cameras};
use zrak::scene::demo::{self, ForwardFacingConfig};
use zrak::scene::llff::{self, BOUNDS_FACTOR};
use zrak::scene::{Frame, LoadOptions, Scene, SceneFormat};

use crate::common;

/// Runs `zrak ARGS` in `dir`, failing the test with its output unless it
/// succeeds; returns its stdout.
fn zrak_in(dir: &Path, args: &[&str]) -> String {
    let output = std::process::Command::new(common::zrak_bin())
        .args(args)
        .current_dir(dir)
        .stdin(std::process::Stdio::null())
        .output()
        .expect("the zrak binary starts");
    assert!(
        output.status.success(),
        "zrak {} failed:\n{}",
        args.join(" "),
        String::from_utf8_lossy(&output.stderr)
    );
    String::from_utf8_lossy(&output.stdout).into_owned()
}

fn small() -> ForwardFacingConfig {
    ForwardFacingConfig {
        width: 48,
        height: 36,
        views: 12,
    }
}

/// A few pixels of every view: the corners, the centre and one between.
fn some_pixels(frame: &Frame) -> Vec<(f32, f32)> {
    let k = frame.camera.intrinsics;
    let (w, h) = (k.width as f32, k.height as f32);
    vec![
        (0.5, 0.5),
        (w - 0.5, 0.5),
        (0.5, h - 0.5),
        (w - 0.5, h - 0.5),
        (0.5 * w, 0.5 * h),
        (0.3 * w, 0.7 * h),
    ]
}

#[test]
fn the_forward_facing_demo_round_trips_through_an_llff_folder() {
    let _cores = common::shared();
    let dir = tempfile::tempdir().unwrap();
    demo::write_forward_facing_llff(&small(), dir.path()).unwrap();
    assert!(dir.path().join("poses_bounds.npy").is_file());
    assert!(dir.path().join("images/00011.png").is_file());
    let loaded = Scene::load(dir.path(), LoadOptions::default()).unwrap();
    let built = demo::build_forward_facing(&small());
    assert_eq!(loaded.format, SceneFormat::Llff);
    assert!(!loaded.has_alpha && !built.has_alpha);
    // Every 8th view held out: views 0 and 8.
    assert_eq!(
        (loaded.train.len(), loaded.val.len(), loaded.test.len()),
        (10, 2, 0)
    );
    for (a, b) in loaded.frames().zip(built.frames()) {
        assert_eq!(a.camera.intrinsics, b.camera.intrinsics);
        assert!(
            a.camera
                .camera_to_world
                .abs_diff_eq(b.camera.camera_to_world, 1e-5)
        );
        assert_eq!(a.image.data, b.image.data, "{}", a.image_path.display());
        // Every pixel opaque: the wall fills what the objects leave.
        assert!(a.image.data.chunks_exact(4).all(|p| p[3] == 255));
    }
    assert_eq!(loaded.bounds, built.bounds);

    // Against the cameras as placed in the demo's world: the loader's
    // rescale and recentring is a similarity, with the scale that puts the
    // nearest bound at 1/0.75.
    let world = demo::forward_facing_cameras(&small());
    let nearest = world
        .iter()
        .map(|c| demo::view_bounds(c).0)
        .fold(f64::INFINITY, f64::min);
    let scale = (1.0 / (nearest * BOUNDS_FACTOR)) as f32;
    let in_file_order: Vec<&Frame> = {
        let mut frames: Vec<&Frame> = loaded.frames().collect();
        frames.sort_by(|a, b| a.image_path.cmp(&b.image_path));
        frames
    };
    for i in 0..world.len() {
        for j in 0..i {
            let before = world[i].position().distance(world[j].position());
            let after = in_file_order[i]
                .camera
                .position()
                .distance(in_file_order[j].camera.position());
            assert!(
                (after - scale * before).abs() < 1e-5 * after.max(1.0),
                "{i}, {j}: {after} vs {}",
                scale * before
            );
        }
    }
    let pixels = some_pixels(in_file_order[0]);
    for (u, v) in pixels {
        for i in [0, 5, 11] {
            for j in [3, 8] {
                let before = world[i]
                    .ray_through(u, v)
                    .direction
                    .dot(world[j].ray_through(u, v).direction);
                let after = in_file_order[i]
                    .camera
                    .ray_through(u, v)
                    .direction
                    .dot(in_file_order[j].camera.ray_through(u, v).direction);
                assert!((after - before).abs() < 1e-6, "{before} vs {after}");
            }
        }
    }
    // Recentred: around the origin, looking down −z on average.
    let count = world.len() as f32;
    let mean = loaded.frames().map(|f| f.camera.position()).sum::<Vec3>() / count;
    assert!(mean.length() < 1e-5, "{mean}");
    let facing = loaded.frames().map(|f| f.camera.forward()).sum::<Vec3>() / count;
    assert!(facing.normalize().abs_diff_eq(-Vec3::Z, 1e-5), "{facing}");
    // The cameras stand on one plane, facing along its normal within the
    // few degrees each turns to face the wall's centre.
    let p = |i: usize| in_file_order[i].camera.position();
    let normal = (p(1) - p(0)).cross(p(2) - p(0)).normalize();
    for frame in &in_file_order {
        let camera = &frame.camera;
        assert!((camera.position() - p(0)).dot(normal).abs() < 1e-5);
        assert!(camera.forward().dot(normal).abs() > 3f32.to_radians().cos());
    }
}

#[test]
fn an_llff_folder_converted_to_transforms_json_opens_with_the_same_rays() {
    let _cores = common::shared();
    let dir = tempfile::tempdir().unwrap();
    let folder = dir.path().join("capture");
    let folder_text = folder.to_str().unwrap();
    zrak_in(
        dir.path(),
        &[
            "demo",
            "--forward-facing",
            "--out",
            folder_text,
            "--size",
            "48",
            "--views",
            "10",
        ],
    );
    let json = folder.join("transforms.json");
    let stdout = zrak_in(
        dir.path(),
        &["convert", folder_text, "--out", json.to_str().unwrap()],
    );
    assert!(stdout.contains("10 frames of an LLFF capture"), "{stdout}");
    let text = std::fs::read_to_string(&json).unwrap();
    assert!(
        text.contains("\"file_path\": \"images/00000.png\""),
        "{text}"
    );
    let from_json = Scene::load(&json, LoadOptions::default()).unwrap();
    assert_eq!(from_json.format, SceneFormat::InstantNgp);
    // The folder itself is still the LLFF capture.
    let from_llff = Scene::load(&folder, LoadOptions::default()).unwrap();
    assert_eq!(from_llff.format, SceneFormat::Llff);
    assert_eq!(
        (from_json.train.len(), from_json.val.len()),
        (from_llff.train.len(), from_llff.val.len())
    );
    assert_eq!(from_json.unit_cube, from_llff.unit_cube);
    for (a, b) in from_json.frames().zip(from_llff.frames()) {
        assert_eq!(a.image_path, b.image_path);
        assert_eq!(a.camera.intrinsics, b.camera.intrinsics);
        assert_eq!(a.image.data, b.image.data);
        for (u, v) in some_pixels(a) {
            let (x, y) = (a.camera.ray_through(u, v), b.camera.ray_through(u, v));
            assert!((x.origin - y.origin).length() < 1e-5);
            assert!((x.direction - y.direction).length() < 1e-6);
        }
    }
    // What the loader and convert share: the scale from the rows.
    let views = llff::read_poses_bounds(&folder.join(llff::POSES_FILE)).unwrap();
    let nearest = views.iter().map(|v| v.near).fold(f64::INFINITY, f64::min);
    assert!((llff::Normalisation::of(&views).scale * nearest * BOUNDS_FACTOR - 1.0).abs() < 1e-12);
}

/// The rays of `scene` through some pixels of every view.
fn rays_of(scene: &Scene) -> Vec<zrak::scene::Ray> {
    scene
        .frames()
        .flat_map(|f| {
            some_pixels(f)
                .into_iter()
                .map(|(u, v)| f.camera.ray_through(u, v))
        })
        .collect()
}

#[test]
fn the_forward_facing_demo_in_ndc_fills_the_ndc_box() {
    let _cores = common::shared();
    let scene = demo::build_forward_facing(&small()).with_ndc();
    let ndc = scene.ndc().expect("cameras in NDC");
    let k = scene.train[0].camera.intrinsics;
    assert_eq!((ndc.width, ndc.height, ndc.focal_x), (48.0, 36.0, k.fx));
    assert_eq!(ndc.near, llff::NDC_NEAR);
    assert!(scene.frames().all(|f| f.camera.ndc == Some(ndc)));
    let b = scene.bounds;
    assert_eq!((b.min.z, b.max.z), (-1.0, 1.0));
    assert!(b.min.x < -1.0 && b.max.x > 1.0 && b.min.y < -1.0 && b.max.y > 1.0);
    // Tight: the box reaches no farther than the rays through the views'
    // pixel centres, plus half a pixel and its 1 % margin.
    let rays = rays_of(&scene);
    let points: Vec<Vec3> = rays
        .iter()
        .flat_map(|r| [r.origin, r.origin + r.direction_unnormalised])
        .collect();
    let reach_min = points.iter().fold(Vec3::INFINITY, |m, p| m.min(*p));
    let reach_max = points.iter().fold(Vec3::NEG_INFINITY, |m, p| m.max(*p));
    for (bound, reach) in [(b.min, reach_min), (b.max, reach_max)] {
        assert!((bound.x - reach.x).abs() < 0.1 && (bound.y - reach.y).abs() < 0.1);
    }
    let unit = scene.unit_cube.world_bounds();
    assert!(unit.contains(b.min) && unit.contains(b.max));
    assert!(scene.training_problem().is_none());
    for ray in rays {
        assert!((ray.origin.z + 1.0).abs() < 1e-5, "{}", ray.origin);
        let end = ray.origin + ray.direction_unnormalised;
        assert!((end.z - 1.0).abs() < 1e-5);
        let (near, far) = scene.ray_near_far(&ray).expect("inside the box");
        assert!(near.abs() < 1e-4, "{near}");
        let length = ray.direction_unnormalised.length();
        assert!((far - length).abs() < 1e-4 * length, "{far} vs {length}");
    }
    // Downscaled copies of the views keep their NDC.
    let scaled = demo::build_forward_facing(&small())
        .with_ndc()
        .with_training_scales(2);
    assert!(scaled.train.iter().all(|f| f.camera.ndc == Some(ndc)));
}

#[test]
fn a_loaded_llff_folder_takes_ndc_like_the_demo() {
    let _cores = common::shared();
    let dir = tempfile::tempdir().unwrap();
    demo::write_forward_facing_llff(&small(), dir.path()).unwrap();
    let loaded = Scene::load(dir.path(), LoadOptions::default())
        .unwrap()
        .with_ndc();
    let built = demo::build_forward_facing(&small()).with_ndc();
    assert_eq!(loaded.ndc(), built.ndc());
    for (a, b) in rays_of(&loaded).into_iter().zip(rays_of(&built)) {
        assert!((a.origin - b.origin).length() < 1e-4);
        assert!((a.direction - b.direction).length() < 1e-5);
    }
}

/// Instant-NGP trained on the forward-facing demo `scene` (in NDC) for
/// `steps` steps of 2^16 samples.
fn trained_in_ndc(steps: u32, scene: Scene) -> zrak::train::trainer::Trainer {
    use std::sync::Arc;
    use zrak::engine::cpu::model::CpuModel;
    use zrak::engine::request::{ModelRequest, ModelSettings};
    use zrak::field::ModelKind;
    use zrak::field::common::{LossKind, Sampling};
    use zrak::field::mlp::Precision;
    use zrak::train::trainer::Trainer;

    let scene = Arc::new(scene);
    let model = CpuModel::build(
        &ModelRequest::new(
            ModelKind::Ngp,
            ModelSettings {
                seed: 0,
                loss: LossKind::Huber,
                batch_samples: Some(1 << 16),
                sampling: Sampling::Occupancy,
                precision: Precision::F32,
                refine_cameras: false,
                appearance: false,
            },
        ),
        &scene,
    );
    let mut trainer = Trainer::new(Box::new(model), scene, 0);
    while trainer.step < steps {
        trainer.step();
    }
    trainer
}

/// Instant-NGP on the forward-facing demo in NDC for `steps`: the held-out
/// PSNR.
fn held_out_psnr_in_ndc_after(steps: u32, scene: Scene) -> f64 {
    let trainer = trained_in_ndc(steps, scene);
    let val = &trainer.scene.val;
    zrak::train::eval::evaluate_split(trainer.model.as_ref(), "val", val, |_| {}).mean_psnr
}

/// The forward-facing demo learns in NDC: Instant-NGP, 300 steps of 2^16
/// samples, held-out PSNR 29.1 dB when written (31.9 dB in the world,
/// where this demo's wall at 2.2 times the nearest depth needs no NDC; 21
/// dB after 100 steps either way). The floor leaves 3 dB for other
/// machines' rounding.
#[test]
fn the_forward_facing_demo_trains_in_ndc() {
    let _cores = common::shared();
    let scene = demo::build_forward_facing(&ndc_training_config()).with_ndc();
    let psnr = held_out_psnr_in_ndc_after(300, scene);
    assert!(psnr > 26.0, "held-out PSNR {psnr:.2} dB");
}

/// The demo's settings in the training tests.
fn ndc_training_config() -> ForwardFacingConfig {
    ForwardFacingConfig {
        width: 64,
        height: 48,
        views: 25,
    }
}

/// An LLFF folder written from the forward-facing demo opens as a
/// forward-facing scene, is put in NDC where its space is settled (as the
/// commands and the viewer do), and trains as the demo built in memory
/// does: the same cameras and photographs (8-bit either way), so the same
/// held-out PSNR up to the rounding of the poses read back from the file.
#[test]
fn an_llff_folder_written_from_the_demo_trains_the_same() {
    let _cores = common::shared();
    let dir = tempfile::tempdir().unwrap();
    demo::write_forward_facing_llff(&ndc_training_config(), dir.path()).unwrap();
    let loaded = Scene::load(dir.path(), LoadOptions::default()).unwrap();
    assert_eq!(loaded.space.space, zrak::scene::SceneSpace::ForwardFacing);
    let loaded = loaded.in_its_space();
    assert!(loaded.ndc().is_some());
    let from_folder = held_out_psnr_in_ndc_after(100, loaded);
    let built = demo::build_forward_facing(&ndc_training_config()).with_ndc();
    let in_memory = held_out_psnr_in_ndc_after(100, built);
    assert!(
        (from_folder - in_memory).abs() < 0.5,
        "{from_folder:.2} dB from the folder, {in_memory:.2} dB built in memory"
    );
}

/// A camera path of a forward-facing scene renders in its NDC, as the
/// training rays are: a path frame at a held-out camera's pose is that
/// camera's own render (up to the 8-bit rounding of a PNG and the f64
/// round trip of the pose), where world-space rays would show nothing the
/// field learned. The turntable's cameras carry the NDC too.
#[test]
fn a_camera_path_of_a_forward_facing_scene_renders_in_its_ndc() {
    let _cores = common::shared();
    let trainer = trained_in_ndc(
        60,
        demo::build_forward_facing(&ndc_training_config()).with_ndc(),
    );
    let scene = trainer.scene.clone();
    let ndc = scene.ndc().expect("the scene is in NDC");
    let camera = &scene.val[0].camera;
    let k = camera.intrinsics;
    let own = to_image(
        &render_pixels(trainer.model.as_ref(), camera, BACKGROUND),
        k.width,
        k.height,
        RenderMode::Rgb,
        scene.depth_range(),
    );
    let dir = tempfile::tempdir().unwrap();
    let job = FrameJob {
        samples: vec![PathSample {
            camera_to_world: camera.camera_to_world.as_dmat4(),
            fov_degrees: (k.fov_y() as f64).to_degrees(),
        }],
        range: 0..1,
        width: k.width,
        height: k.height,
        mode: RenderMode::Rgb,
        depth_range: scene.depth_range(),
        source: RenderSource::default(),
        out_dir: dir.path().to_path_buf(),
        ndc: scene.ndc(),
    };
    let frame = job.render_frame(trainer.model.as_ref(), 0).unwrap();
    let largest = own
        .data
        .iter()
        .zip(&frame.data)
        .map(|(a, b)| a.abs_diff(*b))
        .max()
        .unwrap();
    assert!(largest <= 2, "a path frame differs by {largest}/255");
    // The same frame in world rays is another picture.
    let world = FrameJob { ndc: None, ..job }
        .render_frame(trainer.model.as_ref(), 0)
        .unwrap();
    let mean_world_difference = own
        .data
        .iter()
        .zip(&world.data)
        .map(|(a, b)| a.abs_diff(*b) as f64)
        .sum::<f64>()
        / own.data.len() as f64;
    assert!(
        mean_world_difference > 10.0,
        "world rays differ by only {mean_world_difference:.1}/255 on average"
    );
    let turntable = Turntable {
        frames: 4,
        ..Turntable::default()
    };
    for view in turntable_cameras(&scene, &turntable) {
        assert_eq!(view.ndc, Some(ndc));
    }
}
