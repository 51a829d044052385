//! `Scene::load` picks the format from what the folder holds.

use std::path::Path;

use serde_json::{Value, json};
use zrak::scene::{ImageRgba8, LoadOptions, Scene, SceneFormat};

fn write_png(path: &Path) {
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    ImageRgba8::new(2, 2, vec![255; 16]).save_png(path).unwrap();
}

fn frame(file_path: &str) -> Value {
    let identity = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]];
    json!({ "file_path": file_path, "transform_matrix": identity })
}

fn write_blender(root: &Path) {
    write_png(&root.join("train/r_0.png"));
    let file = json!({ "camera_angle_x": 0.69, "frames": [frame("./train/r_0")] });
    std::fs::write(root.join("transforms_train.json"), file.to_string()).unwrap();
}

fn write_instant_ngp(root: &Path) {
    write_png(&root.join("images/a.png"));
    write_png(&root.join("images/b.png"));
    let file = json!({ "fl_x": 3.0, "frames": [frame("images/a.png"), frame("images/b.png")] });
    std::fs::write(root.join("transforms.json"), file.to_string()).unwrap();
}

#[test]
fn blender_folder() {
    let _cores = crate::common::shared();
    let dir = tempfile::tempdir().unwrap();
    write_blender(dir.path());
    let scene = Scene::load(dir.path(), LoadOptions::default()).unwrap();
    assert_eq!(scene.format, SceneFormat::Blender);
    assert_eq!(scene.train.len(), 1);
}

#[test]
fn instant_ngp_folder() {
    let _cores = crate::common::shared();
    let dir = tempfile::tempdir().unwrap();
    write_instant_ngp(dir.path());
    let scene = Scene::load(dir.path(), LoadOptions::default()).unwrap();
    assert_eq!(scene.format, SceneFormat::InstantNgp);
    assert_eq!((scene.train.len(), scene.val.len()), (1, 1));
}

#[test]
fn split_files_win_over_transforms_json() {
    let _cores = crate::common::shared();
    let dir = tempfile::tempdir().unwrap();
    write_blender(dir.path());
    write_instant_ngp(dir.path());
    let scene = Scene::load(dir.path(), LoadOptions::default()).unwrap();
    assert_eq!(scene.format, SceneFormat::Blender);
}

#[test]
fn path_to_a_json_file() {
    let _cores = crate::common::shared();
    let dir = tempfile::tempdir().unwrap();
    write_blender(dir.path());
    write_instant_ngp(dir.path());
    let options = LoadOptions::default();
    let ngp = Scene::load(&dir.path().join("transforms.json"), options).unwrap();
    assert_eq!(ngp.format, SceneFormat::InstantNgp);
    let blender = Scene::load(&dir.path().join("transforms_train.json"), options).unwrap();
    assert_eq!(blender.format, SceneFormat::Blender);
    assert_eq!(blender.root, dir.path());
}

#[test]
fn folder_without_scene_files() {
    let _cores = crate::common::shared();
    let dir = tempfile::tempdir().unwrap();
    let e = Scene::load(dir.path(), LoadOptions::default())
        .unwrap_err()
        .to_string();
    assert!(e.contains(&dir.path().display().to_string()), "{e}");
    assert!(
        e.contains("transforms_train.json") && e.contains("transforms.json"),
        "{e}"
    );
}

#[test]
fn missing_folder() {
    let _cores = crate::common::shared();
    let dir = tempfile::tempdir().unwrap();
    let e = Scene::load(&dir.path().join("gone"), LoadOptions::default()).unwrap_err();
    assert!(e.to_string().contains("gone: folder not found"), "{e}");
}

#[test]
fn downscale_zero() {
    let _cores = crate::common::shared();
    let dir = tempfile::tempdir().unwrap();
    write_blender(dir.path());
    let e = Scene::load(dir.path(), LoadOptions { downscale: 0 }).unwrap_err();
    assert!(e.to_string().contains("downscale"), "{e}");
}
