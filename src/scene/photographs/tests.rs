use std::path::PathBuf;

use glam::Vec3;

use super::*;
use crate::scene::{
    Camera, ImageRgba8, Intrinsics, PixelMask, PoseOrigin, SceneFormat, SpaceAnalysis,
    UnitCubeMapping,
};

/// Views on a circle of radius 4 around the origin, 2° apart, each an
/// 8 × 8 image of a grey gradient (the same content in every view) with
/// its colour multiplied by `gains(i)`.
fn scene_of(views: usize, gains: impl Fn(usize) -> [f32; 3], poses: PoseOrigin) -> Scene {
    let intrinsics = Intrinsics::from_fov_x(8, 8, 0.8);
    let frames = (0..views)
        .map(|i| {
            let angle = (2.0 * i as f32).to_radians();
            let eye = Vec3::new(4.0 * angle.cos(), 0.5, 4.0 * angle.sin());
            let camera = Camera::look_at(intrinsics, eye, Vec3::ZERO, Vec3::Y);
            let gain = gains(i);
            let data = (0..64)
                .flat_map(|p| {
                    let base = 60.0 + p as f32;
                    let [r, g, b] = gain.map(|k| (base * k).round().clamp(0.0, 255.0) as u8);
                    [r, g, b, 255]
                })
                .collect();
            Frame {
                camera,
                image: ImageRgba8::new(8, 8, data),
                image_path: PathBuf::new(),
                mask: None,
            }
        })
        .collect();
    let unit_cube = UnitCubeMapping::BLENDER;
    Scene {
        name: "circle".into(),
        root: PathBuf::new(),
        format: SceneFormat::InstantNgp,
        train: frames,
        val: Vec::new(),
        test: Vec::new(),
        has_alpha: false,
        unit_cube,
        bounds: unit_cube.world_bounds(),
        smaller_training_views: 0,
        sparse_points: None,
        space: SpaceAnalysis::default(),
        poses,
    }
}

/// A deterministic spread in [−1, 1] for view `i`.
fn jitter(i: usize, salt: usize) -> f32 {
    let x = ((i * 7919 + salt * 104_729) % 1000) as f32 / 999.0;
    2.0 * x - 1.0
}

#[test]
fn one_exposure_keeps_appearance_off_and_jittered_exposure_turns_it_on() {
    let same = scene_of(40, |_| [1.0; 3], PoseOrigin::default());
    let choice = analyse(&same, Switches::default()).appearance;
    assert!(!choice.on, "{choice:?}");
    assert!(!choice.chosen_by_hand);
    assert!(choice.reasons[0].contains("0.000 stops"), "{choice:?}");

    // ±1 stop: pairs differ by about 0.6 stops in the median.
    let exposed = scene_of(
        40,
        |i| [2f32.powf(jitter(i, 1)) * 0.5; 3],
        PoseOrigin::default(),
    );
    let choice = analyse(&exposed, Switches::default()).appearance;
    assert!(choice.on, "{choice:?}");
    let spread = measured_spread(&exposed.train).unwrap();
    assert!(spread.brightness_stops > 0.3, "{spread:?}");
    assert!(spread.colour_share < 0.02, "{spread:?}");
}

#[test]
fn white_balance_alone_turns_appearance_on() {
    let balanced = scene_of(
        40,
        |i| {
            [
                0.8 * (1.0 + 0.15 * jitter(i, 2)),
                0.8,
                0.8 * (1.0 + 0.15 * jitter(i, 3)),
            ]
        },
        PoseOrigin::default(),
    );
    let spread = measured_spread(&balanced.train).unwrap();
    assert!(spread.colour_share > COLOUR_SPREAD, "{spread:?}");
    assert!(
        spread.brightness_stops < BRIGHTNESS_SPREAD_STOPS,
        "{spread:?}"
    );
    assert!(analyse(&balanced, Switches::default()).appearance.on);
}

#[test]
fn views_that_do_not_overlap_or_are_too_few_leave_appearance_off() {
    let one = scene_of(1, |_| [1.0; 3], PoseOrigin::default());
    let choice = analyse(&one, Switches::default()).appearance;
    assert!(!choice.on);
    assert!(choice.reasons[0].contains("fewer than two"), "{choice:?}");

    // Six views 60° apart around the circle: none within 20° of another.
    let mut apart = scene_of(6, |i| [0.3 + 0.1 * i as f32; 3], PoseOrigin::default());
    for (i, frame) in apart.train.iter_mut().enumerate() {
        let angle = (60.0 * i as f32).to_radians();
        let eye = Vec3::new(4.0 * angle.cos(), 0.5, 4.0 * angle.sin());
        frame.camera = Camera::look_at(frame.camera.intrinsics, eye, Vec3::ZERO, Vec3::Y);
    }
    assert_eq!(measured_spread(&apart.train), None);
    let choice = analyse(&apart, Switches::default()).appearance;
    assert!(!choice.on);
    assert!(choice.reasons[0].contains("overlap"), "{choice:?}");
}

#[test]
fn exif_decides_where_every_image_records_its_exposure() {
    use crate::scene::exif::tests::jpeg_with_exif;
    let dir = tempfile::tempdir().unwrap();
    let write = |scene: &mut Scene, exif: &dyn Fn(usize) -> Vec<u8>| {
        for (i, frame) in scene.train.iter_mut().enumerate() {
            let path = dir.path().join(format!("{i}.jpg"));
            std::fs::write(&path, exif(i)).unwrap();
            frame.image_path = path;
        }
    };
    // The pixels disagree wildly, but EXIF says one exposure with manual
    // white balance: EXIF wins.
    let mut fixed = scene_of(
        12,
        |i| [2f32.powf(jitter(i, 4)) * 0.5; 3],
        PoseOrigin::default(),
    );
    write(&mut fixed, &|_| jpeg_with_exif(false, 60, 18, 100, 1));
    let choice = analyse(&fixed, Switches::default()).appearance;
    assert!(!choice.on, "{choice:?}");
    assert!(choice.reasons[0].starts_with("EXIF"), "{choice:?}");

    // ISO 100 and 200 alternate: one stop apart.
    let mut varied = scene_of(12, |_| [1.0; 3], PoseOrigin::default());
    write(&mut varied, &|i| {
        jpeg_with_exif(true, 60, 18, 100 << (i % 2), 1)
    });
    let choice = analyse(&varied, Switches::default()).appearance;
    assert!(choice.on, "{choice:?}");
    assert!(choice.reasons[0].contains("1.00 stops"), "{choice:?}");

    // One exposure but automatic white balance: the pixels decide, and
    // the EXIF sentence follows.
    let mut auto = scene_of(12, |_| [1.0; 3], PoseOrigin::default());
    write(&mut auto, &|_| jpeg_with_exif(false, 60, 18, 100, 0));
    let choice = analyse(&auto, Switches::default()).appearance;
    assert!(!choice.on, "{choice:?}");
    assert!(
        choice.reasons[0].starts_with("overlapping views"),
        "{choice:?}"
    );
    assert!(
        choice.reasons[1].contains("white balance automatic"),
        "{choice:?}"
    );
}

#[test]
fn estimated_poses_are_refined_and_exact_ones_are_not() {
    let exact = scene_of(3, |_| [1.0; 3], PoseOrigin::exact("rendered"));
    let choice = analyse(&exact, Switches::default()).refine_cameras;
    assert!(!choice.on);
    assert_eq!(choice.reasons[0], "rendered");
    let estimated = scene_of(3, |_| [1.0; 3], PoseOrigin::estimated("from COLMAP"));
    let choice = analyse(&estimated, Switches::default()).refine_cameras;
    assert!(choice.on);
    assert_eq!(choice.reasons[0], "from COLMAP");
}

#[test]
fn a_switch_overrides_the_analysis_and_keeps_its_reasons() {
    let scene = scene_of(40, |_| [1.0; 3], PoseOrigin::estimated("from COLMAP"));
    let auto = analyse(&scene, Switches::default());
    let chosen = analyse(
        &scene,
        Switches {
            appearance: Switch::On,
            refine_cameras: Switch::Off,
        },
    );
    assert!(chosen.appearance.on && chosen.appearance.chosen_by_hand);
    assert!(!chosen.refine_cameras.on && chosen.refine_cameras.chosen_by_hand);
    assert_eq!(
        chosen.appearance.reasons[0],
        "chosen with --appearance on (the scene alone would have it off)"
    );
    assert_eq!(chosen.appearance.reasons[1..], auto.appearance.reasons[..]);
    assert_eq!(
        chosen.refine_cameras.reasons[0],
        "chosen with --refine-cameras off (the scene alone would have it on)"
    );
    assert_eq!(chosen.masks, auto.masks);
}

#[test]
fn masks_are_on_wherever_an_image_has_one_and_masked_pixels_are_not_measured() {
    let mut scene = scene_of(40, |_| [1.0; 3], PoseOrigin::default());
    assert!(!analyse(&scene, Switches::default()).masks.on);
    // Each view's masked half is painted with a random exposure: the
    // counted half still agrees, so appearance stays off.
    for (i, frame) in scene.train.iter_mut().enumerate() {
        let counts: Vec<bool> = (0..64).map(|p| p % 8 < 4).collect();
        for (p, pixel) in frame.image.data.chunks_exact_mut(4).enumerate() {
            if !counts[p] {
                pixel[..3].fill((128.0 + 120.0 * jitter(i, 5)) as u8);
            }
        }
        frame.mask = Some(PixelMask::new(8, 8, counts));
    }
    let analysis = analyse(&scene, Switches::default());
    assert!(analysis.masks.on);
    assert!(
        analysis.masks.reasons[0].starts_with("40 of 40 training images"),
        "{:?}",
        analysis.masks
    );
    assert!(!analysis.appearance.on, "{:?}", analysis.appearance);
}
