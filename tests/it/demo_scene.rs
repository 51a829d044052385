//! The demo scene through its public API only, as the viewer, the trainer
//! and the evaluation code use it.

use zrak::scene::demo::{
    CAMERA_ANGLE_X, DemoConfig, {self},
};
use zrak::scene::{Camera, Intrinsics, SceneFormat, Split, UnitCubeMapping};

use glam::Vec3;

#[test]
fn default_config_matches_nerf_synthetic_shape() {
    let _cores = crate::common::shared();
    let config = DemoConfig::default();
    assert_eq!(config.size, 128);
    assert_eq!(
        (config.train_views, config.val_views, config.test_views),
        (100, 10, 10)
    );
    assert_eq!(CAMERA_ANGLE_X, 0.691_111_2);
}

#[test]
fn built_frames_are_what_render_view_draws() {
    let _cores = crate::common::shared();
    let config = DemoConfig {
        size: 40,
        train_views: 4,
        val_views: 2,
        test_views: 2,
    };
    let scene = demo::build(&config);
    assert_eq!(scene.format, SceneFormat::Demo);
    assert_eq!(scene.name, "demo");
    assert!(scene.root.as_os_str().is_empty());
    assert!(scene.has_alpha);
    assert_eq!(scene.unit_cube, UnitCubeMapping::BLENDER);
    assert_eq!(scene.bounds, UnitCubeMapping::BLENDER.world_bounds());
    for split in Split::ALL {
        for frame in scene.split(split) {
            assert_eq!(frame.image, demo::render_view(&frame.camera));
            assert!((frame.camera.intrinsics.fov_x() - CAMERA_ANGLE_X).abs() < 1e-6);
            assert!((frame.camera.position().length() - 4.0).abs() < 1e-4);
            assert!(frame.image.has_transparency());
        }
    }
}

#[test]
fn render_view_works_for_any_camera() {
    let _cores = crate::common::shared();
    // A wide, non-square camera close to the scene, from the side.
    let intrinsics = Intrinsics::from_fov_x(60, 30, 1.2);
    let camera = Camera::look_at(intrinsics, Vec3::new(0.0, -2.5, 0.8), Vec3::ZERO, Vec3::Z);
    let image = demo::render_view(&camera);
    assert_eq!((image.width, image.height), (60, 30));
    // Top corners see the empty sky above the scene.
    assert_eq!(image.rgba(0, 0)[3], 0.0);
    assert_eq!(image.rgba(59, 0)[3], 0.0);
    // The middle sees the scene.
    assert_eq!(image.rgba(30, 15)[3], 1.0);
}

#[test]
fn written_scene_has_blender_files() {
    let _cores = crate::common::shared();
    let dir = tempfile::tempdir().unwrap();
    let config = DemoConfig {
        size: 16,
        train_views: 3,
        val_views: 1,
        test_views: 2,
    };
    demo::write(&config, dir.path()).unwrap();
    for (split, count) in [("train", 3), ("val", 1), ("test", 2)] {
        let json = dir.path().join(format!("transforms_{split}.json"));
        let value: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
        assert_eq!(value["frames"].as_array().unwrap().len(), count);
        for index in 0..count {
            assert!(
                dir.path()
                    .join(split)
                    .join(format!("r_{index}.png"))
                    .is_file()
            );
        }
        assert!(
            !dir.path()
                .join(split)
                .join(format!("r_{count}.png"))
                .exists()
        );
    }
}

#[test]
fn written_scene_loads_back_as_the_built_one() {
    let _cores = crate::common::shared();
    let dir = tempfile::tempdir().unwrap();
    let config = DemoConfig {
        size: 24,
        train_views: 3,
        val_views: 2,
        test_views: 2,
    };
    demo::write(&config, dir.path()).unwrap();
    let built = demo::build(&config);
    let loaded = zrak::scene::Scene::load(dir.path(), Default::default()).unwrap();
    assert_eq!(loaded.format, SceneFormat::Blender);
    assert!(loaded.has_alpha);
    for split in Split::ALL {
        let (a, b) = (built.split(split), loaded.split(split));
        assert_eq!(a.len(), b.len());
        for (x, y) in a.iter().zip(b) {
            assert_eq!(x.image, y.image);
            let (p, q) = (x.camera.intrinsics, y.camera.intrinsics);
            assert_eq!((p.width, p.height), (q.width, q.height));
            assert!((p.fx - q.fx).abs() < 1e-3 && (p.cx - q.cx).abs() < 1e-6);
            let difference = x.camera.camera_to_world - y.camera.camera_to_world;
            assert!(difference.to_cols_array().iter().all(|d| d.abs() < 1e-6));
        }
    }
}
