//! Per-pixel masks: read in instant-ngp's and nerfstudio's conventions,
//! refused clearly when wrong, and left out of the held-out scores.

use std::path::Path;

use serde_json::{Value, json};
use zrak::scene::{ImageRgba8, LoadOptions, Scene, SceneError};

/// A 4 × 4 opaque image whose pixel (x, y) has red 40·x and green 40·y.
fn write_image(path: &Path) {
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    let data = (0..16u8)
        .flat_map(|i| [40 * (i % 4), 40 * (i / 4), 0, 255])
        .collect();
    ImageRgba8::new(4, 4, data).save_png(path).unwrap();
}

/// A grey PNG of `width` × `height`, `value(x, y)` at each pixel.
fn write_grey(path: &Path, width: u32, height: u32, value: impl Fn(u32, u32) -> u8) {
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    image::GrayImage::from_fn(width, height, |x, y| image::Luma([value(x, y)]))
        .save(path)
        .unwrap();
}

fn frame(file_path: &str) -> Value {
    let pose = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 3], [0, 0, 0, 1]];
    json!({ "file_path": file_path, "transform_matrix": pose })
}

/// A transforms.json scene of three 4 × 4 frames `images/f_{i}.png`, all
/// training (nerfstudio's split lists); `edit` adjusts the JSON.
fn write_scene(root: &Path, edit: impl FnOnce(&mut Value)) {
    let names: Vec<String> = (0..3).map(|i| format!("images/f_{i}.png")).collect();
    for name in &names {
        write_image(&root.join(name));
    }
    let mut value = json!({
        "fl_x": 4.0,
        "train_filenames": names,
        "frames": names.iter().map(|n| frame(n)).collect::<Vec<_>>(),
    });
    edit(&mut value);
    std::fs::write(root.join("transforms.json"), value.to_string()).unwrap();
}

fn load(root: &Path, downscale: u32) -> Result<Scene, SceneError> {
    Scene::load(root, LoadOptions { downscale })
}

fn counting(scene: &Scene, frame: usize) -> Option<Vec<bool>> {
    scene.train[frame]
        .mask
        .as_ref()
        .map(|mask| mask.counting().to_vec())
}

#[test]
fn instant_ngp_dynamic_masks_hide_their_non_zero_pixels() {
    let _cores = crate::common::shared();
    let dir = tempfile::tempdir().unwrap();
    write_scene(dir.path(), |_| {});
    // Frame 1's mask marks its top-left 2 × 2 block and pixel (3, 3) as
    // dynamic (any non-zero value; here 1 and 255).
    write_grey(
        &dir.path().join("images/dynamic_mask_f_1.png"),
        4,
        4,
        |x, y| match (x, y) {
            (0..=1, 0..=1) => 255,
            (3, 3) => 1,
            _ => 0,
        },
    );
    let scene = load(dir.path(), 1).unwrap();
    assert_eq!(counting(&scene, 0), None);
    assert_eq!(counting(&scene, 2), None);
    let mask = counting(&scene, 1).unwrap();
    let hidden: Vec<usize> = (0..16).filter(|&i| !mask[i]).collect();
    assert_eq!(hidden, [0, 1, 4, 5, 15]);
    assert_eq!(scene.masked_frames(), (1, 5));
    let said = scene.describe_masks().unwrap();
    assert!(
        said.starts_with("1 frames have masks (train 1 of 3"),
        "{said}"
    );
    assert!(said.contains("5 pixels masked out"), "{said}");

    // At ½ a pixel counts only where its whole 2 × 2 block counts: the
    // top-left block and the bottom-right one (which holds (3, 3)) are out.
    let half = load(dir.path(), 2).unwrap();
    assert_eq!(counting(&half, 1).unwrap(), [false, true, true, false]);
    assert_eq!(half.train[1].image.width, 2);
}

#[test]
fn nerfstudio_mask_paths_hide_their_zero_pixels() {
    let _cores = crate::common::shared();
    let dir = tempfile::tempdir().unwrap();
    write_scene(dir.path(), |v| {
        v["frames"][2]["mask_path"] = json!("./masks/m_2.png");
    });
    // Zero in the left column: ignored; everything else counts. A
    // dynamic_mask file beside the same image is not read: mask_path wins.
    write_grey(&dir.path().join("masks/m_2.png"), 4, 4, |x, _| {
        if x == 0 { 0 } else { 255 }
    });
    write_grey(
        &dir.path().join("images/dynamic_mask_f_2.png"),
        4,
        4,
        |_, _| 255,
    );
    let scene = load(dir.path(), 1).unwrap();
    let mask = counting(&scene, 2).unwrap();
    for (i, &counts) in mask.iter().enumerate() {
        assert_eq!(counts, i % 4 != 0, "pixel {i}");
    }
    assert_eq!(counting(&scene, 0), None);
}

/// The error loading the scene with frame 1's `mask_path` set to `mask`.
fn mask_path_error(mask: Value, prepare: impl FnOnce(&Path)) -> (SceneError, String) {
    let dir = tempfile::tempdir().unwrap();
    write_scene(dir.path(), |v| v["frames"][1]["mask_path"] = mask);
    prepare(dir.path());
    let error = load(dir.path(), 1).expect_err("the mask is wrong");
    let message = error.to_string();
    assert!(message.contains("transforms.json: frame 1: "), "{message}");
    (error, message)
}

#[test]
fn bad_masks_are_refused_naming_the_file_and_the_problem() {
    let _cores = crate::common::shared();
    // Missing.
    let (error, message) = mask_path_error(json!("masks/gone.png"), |_| {});
    assert!(matches!(error, SceneError::NotFound { .. }), "{error:?}");
    assert!(message.contains("masks/gone.png"), "{message}");
    // Another size than its image.
    let (error, message) = mask_path_error(json!("m.png"), |root| {
        write_grey(&root.join("m.png"), 5, 4, |_, _| 255)
    });
    assert!(matches!(error, SceneError::Invalid { .. }), "{error:?}");
    assert!(
        message.contains("m.png: the mask is 5×4 pixels, but its image")
            && message.contains("f_1.png is 4×4"),
        "{message}"
    );
    // Not an image.
    let (error, message) = mask_path_error(json!("m.png"), |root| {
        std::fs::write(root.join("m.png"), b"not a png").unwrap()
    });
    assert!(matches!(error, SceneError::Invalid { .. }), "{error:?}");
    assert!(message.contains("m.png"), "{message}");
    // A folder.
    let (error, _) = mask_path_error(json!("masks"), |root| {
        std::fs::create_dir_all(root.join("masks")).unwrap()
    });
    assert!(matches!(error, SceneError::Unreadable { .. }), "{error:?}");
    // Not a string.
    let (error, message) = mask_path_error(json!(7), |_| {});
    assert!(matches!(error, SceneError::Invalid { .. }), "{error:?}");
    assert!(
        message.contains("`mask_path` must be a string"),
        "{message}"
    );
    // An instant-ngp mask of the wrong size is refused too.
    let dir = tempfile::tempdir().unwrap();
    write_scene(dir.path(), |_| {});
    write_grey(
        &dir.path().join("images/dynamic_mask_f_0.png"),
        4,
        3,
        |_, _| 0,
    );
    let message = load(dir.path(), 1).unwrap_err().to_string();
    assert!(
        message.contains("frame 0: mask ")
            && message.contains("dynamic_mask_f_0.png: the mask is 4×3 pixels"),
        "{message}"
    );
}

#[test]
fn a_scene_whose_masks_hide_every_training_pixel_has_nothing_to_train() {
    let _cores = crate::common::shared();
    let dir = tempfile::tempdir().unwrap();
    write_scene(dir.path(), |_| {});
    for i in 0..3 {
        write_grey(
            &dir.path().join(format!("images/dynamic_mask_f_{i}.png")),
            4,
            4,
            |_, _| 9,
        );
    }
    let scene = load(dir.path(), 1).unwrap();
    assert_eq!(scene.fully_masked_training_views().len(), 3);
    let problem = scene.training_problem().unwrap();
    assert!(
        problem.contains("every pixel of the 3 training views is masked out"),
        "{problem}"
    );
}

/// A 32 × 32 view of a texture whose pixels in the box `hidden` hold
/// `inside(x, y)` instead, with a mask hiding that box.
fn view_with_box(inside: impl Fn(u32, u32) -> [u8; 3]) -> zrak::scene::Frame {
    use glam::{Mat4, Vec3};
    use zrak::scene::{Camera, Intrinsics, PixelMask};
    let size = 32;
    let hidden = |x: u32, y: u32| (20..28).contains(&x) && (4..30).contains(&y);
    let data = (0..size * size)
        .flat_map(|i| {
            let (x, y) = (i % size, i / size);
            let [r, g, b] = if hidden(x, y) {
                inside(x, y)
            } else {
                [(x * 7) as u8, (y * 5 + 20) as u8, ((x + y) * 3) as u8]
            };
            [r, g, b, 255]
        })
        .collect();
    let counts = (0..size * size)
        .map(|i| !hidden(i % size, i / size))
        .collect();
    zrak::scene::Frame {
        camera: Camera::new(
            Intrinsics::from_fov_x(size, size, 0.7),
            Mat4::from_translation(Vec3::new(0.0, 0.0, 4.0)),
        ),
        image: ImageRgba8::new(size, size, data),
        image_path: Default::default(),
        mask: Some(PixelMask::new(size, size, counts)),
    }
}

#[test]
fn masked_garbage_changes_neither_psnr_nor_ssim() {
    let _cores = crate::common::shared();
    use zrak::metrics::{RgbImage, WHITE};
    use zrak::train::eval::score_prediction;
    let clean = view_with_box(|x, y| [(x * 7) as u8, (y * 5 + 20) as u8, ((x + y) * 3) as u8]);
    let garbage = view_with_box(|x, y| [(x * 97 + y * 31) as u8, (x * y) as u8, 255]);
    // The prediction: the clean texture 0.05 brighter, black in the box.
    let truth = RgbImage::from_rgba8_over(&clean.image, WHITE);
    let prediction = RgbImage::new(
        32,
        32,
        truth
            .pixels
            .iter()
            .enumerate()
            .map(|(i, p)| {
                let (x, y) = (i % 32, i / 32);
                if (20..28).contains(&x) && (4..30).contains(&y) {
                    [0.0; 3]
                } else {
                    p.map(|c| c + 0.05)
                }
            })
            .collect(),
    )
    .unwrap();
    let on_clean = score_prediction(&prediction, &clean, true);
    let on_garbage = score_prediction(&prediction, &garbage, true);
    assert_eq!(on_clean, on_garbage);
    // Every counted pixel is off by 0.05 in each channel: 26.02 dB, to
    // f32 rounding of the sums (far below 1e-4 dB).
    let want = -10.0 * 0.0025f64.log10();
    assert!((on_clean.psnr - want).abs() < 1e-4, "{}", on_clean.psnr);
    // An offset alone leaves the structure: SSIM near 1 on the windows
    // clear of the box (some exist: its columns 0..20 hold 10 of them a row).
    assert!(
        on_clean.ssim > 0.9 && on_clean.ssim < 1.0,
        "{}",
        on_clean.ssim
    );
    // Without the masks the box counts, and the garbage changes both.
    let unmasked = |mut frame: zrak::scene::Frame| {
        frame.mask = None;
        score_prediction(&prediction, &frame, true)
    };
    let (plain_clean, plain_garbage) = (unmasked(clean), unmasked(garbage));
    assert!(plain_clean.psnr < want - 1.0, "{}", plain_clean.psnr);
    assert_ne!(plain_clean.psnr, plain_garbage.psnr);
    assert_ne!(plain_clean.ssim, plain_garbage.ssim);
}

/// The moving-object demo at `size` pixels with `views` training views
/// and 4 held out.
fn moving_demo(size: u32, views: usize) -> Scene {
    zrak::scene::demo::build_moving_object(&zrak::scene::demo::DemoConfig {
        size,
        train_views: views,
        val_views: 4,
        test_views: 1,
    })
}

#[test]
fn the_moving_object_demo_reads_back_with_its_masks_over_the_ball() {
    let _cores = crate::common::shared();
    let built = moving_demo(32, 8);
    let dir = tempfile::tempdir().unwrap();
    zrak::scene::demo::write_moving_object(
        &zrak::scene::demo::DemoConfig {
            size: 32,
            train_views: 8,
            val_views: 4,
            test_views: 1,
        },
        dir.path(),
    )
    .unwrap();
    assert!(dir.path().join("train/dynamic_mask_r_3.png").is_file());
    let loaded = Scene::load(dir.path(), LoadOptions::default()).unwrap();
    assert_eq!(loaded.train.len(), 8);
    assert!(loaded.val.iter().all(|frame| frame.mask.is_none()));
    for (index, (read, made)) in loaded.train.iter().zip(&built.train).enumerate() {
        assert_eq!(read.mask, made.mask, "view {index}");
        assert_eq!(read.image, made.image, "view {index}");
        // The ball's centre projects onto a hidden pixel, and the mask
        // hides a disc of about its size: a radius of 0.3 at 3.1 to 4.9
        // from the camera (its places are 0.93 from the origin, the
        // cameras 4) with a focal length of 32 / (2 tan(0.3456)) ≈ 44.4
        // pixels is 2.7 to 4.3 pixels, so 23 to 58 pixels; the samples
        // that graze it widen that by up to a pixel all round.
        let mask = read.mask.as_ref().unwrap();
        let centre = zrak::scene::demo::moving_object_centre(index);
        let (u, v) = project(&read.camera, centre);
        assert!(!mask.counts(u as u32, v as u32), "view {index}: ({u}, {v})");
        assert!(
            (20..=100).contains(&mask.hidden()),
            "view {index}: {}",
            mask.hidden()
        );
    }
    // The held-out views never show the ball: they are the plain demo's.
    let plain = zrak::scene::demo::build(&zrak::scene::demo::DemoConfig {
        size: 32,
        train_views: 8,
        val_views: 4,
        test_views: 1,
    });
    assert_eq!(loaded.val[2].image, plain.val[2].image);
    assert_ne!(loaded.train[2].image, plain.train[2].image);
}

/// Where `point` appears in `camera`'s image, in pixels.
fn project(camera: &zrak::scene::Camera, point: glam::Vec3) -> (f32, f32) {
    let local = camera.camera_to_world.inverse().transform_point3(point);
    let k = camera.intrinsics;
    // OpenGL axes: the camera looks down −z, y up, rows from the top.
    (
        k.cx + k.fx * local.x / -local.z,
        k.cy - k.fy * local.y / -local.z,
    )
}

/// Instant-NGP (cpu engine, occupancy sampling) trained on `scene` for
/// `steps` steps: its mean held-out PSNR and its mean density at the
/// places the ball visited.
fn train_moving(scene: Scene, steps: u32) -> (f64, f32) {
    use std::sync::Arc;
    use zrak::engine::cpu::model::CpuModel;
    use zrak::field::ModelKind;
    use zrak::field::common::LossKind;
    use zrak::model::PointQuery;
    let scene = Arc::new(scene);
    let request = crate::common::request(ModelKind::Ngp, 3, LossKind::Huber, Some(1 << 14));
    let model = CpuModel::build(&request, &scene);
    let mut trainer = zrak::train::trainer::Trainer::new(Box::new(model), scene.clone(), 3);
    while trainer.step < steps {
        trainer.step();
    }
    let views: Vec<_> = scene.val.iter().collect();
    let psnr = zrak::train::eval::mean_psnr(trainer.model.as_ref(), &views);
    // Points through the ball's volume at each place: 5 × 5 × 5 spread
    // over the cube inside it (half side R/√3), 125 a place.
    let radius = zrak::scene::demo::MOVING_RADIUS / 3f32.sqrt();
    let places: Vec<glam::Vec3> = (0..zrak::scene::demo::MOVING_PLACES)
        .flat_map(|place| {
            let centre = zrak::scene::demo::moving_object_centre(place);
            (0..125).map(move |i| {
                let at = |k: usize| (k as f32 / 2.0 - 1.0) * radius;
                centre + glam::Vec3::new(at(i % 5), at(i / 5 % 5), at(i / 25))
            })
        })
        .collect();
    let mut sigma = vec![0f32; places.len()];
    trainer
        .model
        .density_at(
            PointQuery {
                positions: &places,
                directions: &[],
                footprint: 0.0,
            },
            &mut sigma,
        )
        .unwrap();
    (psnr, sigma.iter().sum::<f32>() / sigma.len() as f32)
}

/// The demo's known answer: a ball that moves between the training views
/// leaves fog where it passed unless its masks keep it out of training.
#[test]
fn with_masks_the_moving_object_leaves_no_floater() {
    let _cores = crate::common::shared();
    let started = std::time::Instant::now();
    let masked = moving_demo(32, 24);
    let mut unmasked = masked.clone();
    for frame in &mut unmasked.train {
        frame.mask = None;
    }
    let steps = 300;
    let (psnr_masked, sigma_masked) = train_moving(masked, steps);
    let (psnr_unmasked, sigma_unmasked) = train_moving(unmasked, steps);
    eprintln!(
        "held-out PSNR {psnr_masked:.2} dB with masks, {psnr_unmasked:.2} dB without; σ where \
         the ball passed {sigma_masked:.3} with masks, {sigma_unmasked:.3} without ({:.0} s)",
        started.elapsed().as_secs_f64()
    );
    // Seen here: 26.3 dB against 22.8, σ 0.11 against 0.45 (and at 40 px
    // with 30 views, 26.2 against 22.5, σ 0.20 against 0.47). A sampler
    // that ignored the masks would train the same model twice.
    assert!(
        psnr_masked > psnr_unmasked + 1.0,
        "{psnr_masked} against {psnr_unmasked}"
    );
    assert!(
        sigma_masked < 0.5 * sigma_unmasked,
        "{sigma_masked} against {sigma_unmasked}"
    );
}

/// `zrak demo --moving-object` writes the scene with its masks, and
/// `zrak info` says so (and says so of a scene without masks).
#[test]
fn zrak_info_says_how_many_frames_have_masks() {
    let _cores = crate::common::shared();
    let zrak = |args: &[&str]| {
        let output = std::process::Command::new(crate::common::zrak_bin())
            .args(args)
            .output()
            .unwrap();
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert!(output.status.success(), "zrak {args:?}: {stderr}");
        String::from_utf8(output.stdout).unwrap()
    };
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("moving");
    let out = out.to_str().unwrap();
    zrak(&[
        "demo",
        "--moving-object",
        "--out",
        out,
        "--size",
        "16",
        "--views",
        "4",
    ]);
    let printed = zrak(&["info", out]);
    assert!(
        printed.contains(
            "\nmasks       4 frames have masks (train 4 of 4, val 0 of 1, test 0 of 1); "
        ),
        "{printed}"
    );
    let plain = zrak(&["info", "demo", "--downscale", "16"]);
    assert!(
        plain.contains("\nmasks       none (every pixel counts)\n"),
        "{plain}"
    );
}
