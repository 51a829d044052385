//! `Scene::load` picks the format from what the folder holds.

use std::path::Path;

use serde_json::{Value, json};
use zrak::scene::{ImageRgba8, LoadOptions, Scene, SceneError, SceneFormat};

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
    let e = Scene::load(dir.path(), LoadOptions::default()).unwrap_err();
    assert!(matches!(e, SceneError::NotAScene { .. }), "{e:?}");
}

#[test]
fn missing_folder() {
    let _cores = crate::common::shared();
    let dir = tempfile::tempdir().unwrap();
    let e = Scene::load(&dir.path().join("gone"), LoadOptions::default()).unwrap_err();
    assert!(e.to_string().contains("gone: folder not found"), "{e}");
    assert!(matches!(e, SceneError::NotFound { .. }), "{e:?}");
}

/// The kinds a caller decides on: nothing there, something unreadable
/// there, and a file that was read and is wrong; each naming the file.
#[test]
fn errors_say_their_kind() {
    let _cores = crate::common::shared();
    let dir = tempfile::tempdir().unwrap();
    let options = LoadOptions::default();
    let json = dir.path().join("transforms.json");
    let e = Scene::load(&json, options).unwrap_err();
    assert_eq!(e.path(), json);
    assert_eq!(
        e.to_string(),
        format!("{}: folder not found", json.display())
    );
    assert!(
        matches!(e, SceneError::NotFound { frame: None, .. }),
        "{e:?}"
    );

    // A folder named transforms.json: there, but no file.
    std::fs::create_dir(&json).unwrap();
    let e = Scene::load(dir.path(), options).unwrap_err();
    assert!(matches!(e, SceneError::Unreadable { .. }), "{e:?}");
    assert!(
        e.to_string()
            .ends_with("cannot read it: it is a folder, not a file"),
        "{e}"
    );
    std::fs::remove_dir(&json).unwrap();

    std::fs::write(&json, "{\"frames\": [").unwrap();
    let e = Scene::load(dir.path(), options).unwrap_err();
    assert!(
        matches!(e, SceneError::Invalid { frame: None, .. }),
        "{e:?}"
    );
    assert!(e.problem().starts_with("malformed JSON at line 1"), "{e}");

    // An image a frame lists that is not there: the image's kind, told of
    // the frame.
    write_instant_ngp(dir.path());
    std::fs::remove_file(dir.path().join("images/b.png")).unwrap();
    let e = Scene::load(dir.path(), options).unwrap_err();
    assert_eq!((e.path(), e.frame()), (json.as_path(), Some(1)));
    assert!(matches!(e, SceneError::NotFound { .. }), "{e:?}");
    assert_eq!(
        e.problem(),
        format!(
            "image file not found: {}",
            dir.path().join("images/b.png").display()
        )
    );
}

#[test]
fn downscale_zero() {
    let _cores = crate::common::shared();
    let dir = tempfile::tempdir().unwrap();
    write_blender(dir.path());
    let e = Scene::load(dir.path(), LoadOptions { downscale: 0 }).unwrap_err();
    assert!(e.to_string().contains("downscale"), "{e}");
}
