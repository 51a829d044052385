//! The NeRF-synthetic ("Blender") layout: a folder with
//! `transforms_train.json`, `transforms_val.json` and `transforms_test.json`,
//! each holding `camera_angle_x` and a list of `frames` with a `file_path`
//! and a camera-to-world `transform_matrix` (Mildenhall et al. 2020).

use std::path::Path;

use super::error::{SceneError, SceneResult};
use super::pose::{
    FrameSource, decode_images, frame_object, parse_transform_matrix, read_json_object,
    required_array, required_number, required_str, resolve_image_path,
};
use super::{
    Frame, LoadOptions, Scene, SceneFormat, SpaceAnalysis, Split, UnitCubeMapping, folder_name,
    space,
};
use crate::scene::{Camera, Intrinsics};

/// The file name of a split's JSON file, e.g. `transforms_train.json`.
pub fn split_file_name(split: Split) -> String {
    format!("transforms_{}.json", split.name())
}

/// Whether `folder` holds at least one of the split files. A split file
/// that cannot be read (a link that loops or points nowhere, a folder of
/// that name) counts, so that loading it says what is wrong with it.
pub fn is_blender_folder(folder: &Path) -> bool {
    Split::ALL
        .iter()
        .any(|&split| crate::files::exists_at_all(&folder.join(split_file_name(split))))
}

/// One split file, read and checked, its images not yet decoded.
struct SplitFile {
    split: Split,
    camera_angle_x: f32,
    frames: Vec<FrameSource>,
}

/// Loads a NeRF-synthetic scene from `folder`. A split whose file is absent
/// is left empty (the lego copy in the shared data has no test split); a
/// folder with none of them is an error, and so is a scene without frames.
pub fn load(folder: &Path, options: LoadOptions) -> SceneResult<Scene> {
    super::pose::check_downscale(folder, options.downscale)?;
    if !folder.is_dir() {
        let problem = crate::files::describe_not_a_folder(folder);
        return Err(if crate::files::exists_at_all(folder) {
            SceneError::unreadable(folder, problem)
        } else {
            SceneError::not_found(folder, problem)
        });
    }
    let mut files = Vec::new();
    for split in Split::ALL {
        let path = folder.join(split_file_name(split));
        // Anything of that name is read: a split file that cannot be (a
        // link that loops, say) is an error naming it, not a split left
        // empty, which would train on the others without a word.
        if crate::files::exists_at_all(&path) {
            files.push(read_split_file(folder, &path, split)?);
        }
    }
    if files.is_empty() {
        return Err(SceneError::not_a_scene(
            folder,
            "no transforms_train.json, transforms_val.json or transforms_test.json in this folder",
        ));
    }
    let sources: Vec<FrameSource> = files
        .iter()
        .flat_map(|f| f.frames.iter().cloned())
        .collect();
    if sources.is_empty() {
        let names: Vec<String> = files.iter().map(|f| split_file_name(f.split)).collect();
        return Err(SceneError::new(
            folder,
            format!("no frames: {} list none", names.join(", ")),
        ));
    }

    let decoded = decode_images(&sources, options.downscale)?;
    let has_alpha = decoded.iter().any(|d| d.file_has_alpha);
    // Images come back in `sources` order, which is file by file.
    let mut decoded = decoded.into_iter();

    let mut scene = Scene {
        name: folder_name(folder),
        root: folder.to_path_buf(),
        format: SceneFormat::Blender,
        train: Vec::new(),
        val: Vec::new(),
        test: Vec::new(),
        has_alpha,
        unit_cube: UnitCubeMapping::BLENDER,
        bounds: UnitCubeMapping::BLENDER.world_bounds(),
        smaller_training_views: 0,
        sparse_points: None,
        space: SpaceAnalysis::default(),
        poses: crate::scene::PoseOrigin::exact(
            "NeRF-synthetic renders: each camera is the one Blender rendered its image from",
        ),
    };
    for file in files {
        let frames: Vec<Frame> = file
            .frames
            .into_iter()
            .zip(decoded.by_ref())
            .map(|(source, image)| {
                // The angle spans the full-resolution width; the downscale
                // then shrinks the focal length with the image.
                let intrinsics =
                    Intrinsics::from_fov_x(image.width, image.height, file.camera_angle_x)
                        .downscaled(options.downscale);
                Frame {
                    camera: Camera::new(intrinsics, source.camera_to_world),
                    image: image.image,
                    image_path: source.image_path,
                    mask: None,
                }
            })
            .collect();
        match file.split {
            Split::Train => scene.train = frames,
            Split::Val => scene.val = frames,
            Split::Test => scene.test = frames,
        }
    }
    scene.space = space::analyse(&scene);
    Ok(scene)
}

/// Reads one split file and checks everything in it that does not need the
/// images: keys, types, the camera angle and every pose.
fn read_split_file(folder: &Path, path: &Path, split: Split) -> SceneResult<SplitFile> {
    let json = read_json_object(path)?;
    let file_error = |problem: String| SceneError::new(path, problem);
    let camera_angle_x = required_number(&json, "camera_angle_x").map_err(file_error)?;
    // tan(0.5 · angle) must be positive and finite for the focal length
    // 0.5 W / tan(0.5 · angle) to be.
    // Checked as the f32 focal length it becomes: an angle of 1e-50 is
    // positive, but its tangent is 0 in f32 and the focal length infinite.
    let unit_focal = super::camera::focal_from_fov(1, camera_angle_x as f32);
    let usable = camera_angle_x > 0.0
        && camera_angle_x < std::f64::consts::PI
        && unit_focal > 0.0
        && unit_focal.is_finite();
    if !usable {
        return Err(file_error(format!(
            "camera_angle_x = {camera_angle_x} does not give a positive, finite focal length: \
             it must be an angle between 0 and π radians"
        )));
    }
    let frames = required_array(&json, "frames").map_err(file_error)?;
    let frames = frames
        .iter()
        .enumerate()
        .map(|(index, value)| {
            let (file_path, camera_to_world) =
                read_frame(value).map_err(|problem| SceneError::in_frame(path, index, problem))?;
            let image_path = resolve_image_path(folder, file_path).map_err(|e| {
                let problem = e.problem().to_string();
                e.in_frame_of(path, index, problem)
            })?;
            Ok(FrameSource {
                json_path: path.to_path_buf(),
                index,
                image_path,
                camera_to_world,
            })
        })
        .collect::<SceneResult<Vec<_>>>()?;
    Ok(SplitFile {
        split,
        camera_angle_x: camera_angle_x as f32,
        frames,
    })
}

/// A frame's `file_path` (resolved by the caller, last) and pose.
fn read_frame(value: &serde_json::Value) -> Result<(&str, glam::Mat4), String> {
    let frame = frame_object(value)?;
    let file_path = required_str(frame, "file_path")?;
    let matrix = frame
        .get("transform_matrix")
        .ok_or_else(|| super::pose::missing_key("transform_matrix"))?;
    let camera_to_world = parse_transform_matrix(matrix)?;
    Ok((file_path, camera_to_world))
}

#[cfg(test)]
mod tests {
    use std::path::Path;

    use glam::Vec3;
    use serde_json::{Value, json};

    use super::*;
    use crate::scene::pose::test_support::*;

    /// lego's camera_angle_x.
    const ANGLE: f64 = 0.6911112070083618;

    fn frame(file_path: &str, tx: f64) -> Value {
        json!({ "file_path": file_path, "rotation": 0.01, "transform_matrix": pose_json(tx, 0.5, 4.0) })
    }

    fn split(frames: Vec<Value>) -> Value {
        json!({ "camera_angle_x": ANGLE, "frames": frames })
    }

    /// A valid 8×6 scene: three train frames (file paths written the three
    /// usual ways), one val frame, no test file.
    fn write_scene(root: &Path) {
        for name in ["train/r_0", "train/r_1", "train/r_2", "val/r_0"] {
            write_rgba_png(&root.join(format!("{name}.png")), 8, 6);
        }
        let train = vec![
            frame("./train/r_0", 0.25),
            frame("train/r_1", 1.0),
            frame("./train/r_2.png", 2.0),
        ];
        write_json(&root.join("transforms_train.json"), &split(train));
        write_json(
            &root.join("transforms_val.json"),
            &split(vec![frame("./val/r_0", 3.0)]),
        );
    }

    /// Loads `root` and returns the error's message.
    fn load_error(root: &Path, options: LoadOptions) -> String {
        match load(root, options) {
            Ok(_) => panic!("loading {} should fail", root.display()),
            Err(e) => e.to_string(),
        }
    }

    /// Rewrites `file` (relative to `root`) through `edit` on its JSON.
    fn edit_json(root: &Path, file: &str, edit: impl FnOnce(&mut Value)) {
        let path = root.join(file);
        let mut value: Value =
            serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
        edit(&mut value);
        write_json(&path, &value);
    }

    #[test]
    fn valid_scene_loads() {
        let dir = tempfile::tempdir().unwrap();
        write_scene(dir.path());
        let scene = load(dir.path(), LoadOptions::default()).unwrap();
        assert_eq!(scene.format, SceneFormat::Blender);
        assert_eq!(
            (scene.train.len(), scene.val.len(), scene.test.len()),
            (3, 1, 0)
        );
        assert_eq!(scene.resolution(), Some((8, 6)));
        assert!(scene.has_alpha);
        assert_eq!(scene.root, dir.path());
        assert_eq!(scene.name, folder_name(dir.path()));
        assert_eq!(scene.unit_cube, UnitCubeMapping::BLENDER);
        assert_eq!(scene.bounds, UnitCubeMapping::BLENDER.world_bounds());

        let expected_focal = 0.5 * 8.0 / (0.5 * ANGLE).tan();
        let first = &scene.train[0];
        let k = first.camera.intrinsics;
        assert!((k.fx as f64 - expected_focal).abs() < 1e-4, "{}", k.fx);
        assert_eq!(k.fx, k.fy);
        assert_eq!((k.cx, k.cy), (4.0, 3.0));
        // The pose: JSON rows are matrix rows.
        assert_eq!(first.camera.position(), Vec3::new(0.25, 0.5, 4.0));
        assert_eq!(first.camera.rotation().x_axis, Vec3::Y);
        assert_eq!(first.camera.forward(), -Vec3::Z);
        // File paths with and without `./` and extension, in file order.
        let names: Vec<_> = scene.frames().map(|f| f.image_path.clone()).collect();
        let root = dir.path();
        assert_eq!(
            names,
            [
                root.join("train/r_0.png"),
                root.join("train/r_1.png"),
                root.join("train/r_2.png"),
                root.join("val/r_0.png"),
            ]
        );
        assert_eq!(scene.val[0].camera.position().x, 3.0);
        assert_eq!(scene.train[0].image.data[..4], [128, 128, 128, 128]);
    }

    #[test]
    fn opaque_rgb_images_have_no_alpha() {
        let dir = tempfile::tempdir().unwrap();
        write_rgb_png(&dir.path().join("r_0.png"), 4, 4);
        write_json(
            &dir.path().join("transforms_test.json"),
            &split(vec![frame("r_0", 0.0)]),
        );
        let scene = load(dir.path(), LoadOptions::default()).unwrap();
        assert_eq!(
            (scene.train.len(), scene.val.len(), scene.test.len()),
            (0, 0, 1)
        );
        assert!(!scene.has_alpha);
        assert_eq!(scene.test[0].image.data[..4], [10, 200, 30, 255]);
    }

    #[test]
    fn downscale_halves_size_and_focal() {
        let dir = tempfile::tempdir().unwrap();
        write_scene(dir.path());
        let full = load(dir.path(), LoadOptions::default()).unwrap();
        let half = load(dir.path(), LoadOptions { downscale: 2 }).unwrap();
        assert_eq!(half.resolution(), Some((4, 3)));
        let (k, k2) = (
            full.train[0].camera.intrinsics,
            half.train[0].camera.intrinsics,
        );
        assert!((k2.fx - 0.5 * k.fx).abs() < 1e-5);
        assert_eq!((k2.cx, k2.cy), (2.0, 1.5));
        assert_eq!(half.train[0].image.width, 4);
        assert_eq!(
            half.train[0].camera.camera_to_world,
            full.train[0].camera.camera_to_world
        );
    }

    #[test]
    fn folder_without_split_files() {
        let dir = tempfile::tempdir().unwrap();
        let e = load_error(dir.path(), LoadOptions::default());
        assert_mentions(
            &e,
            &[
                &dir.path().display().to_string(),
                "no transforms_train.json",
            ],
        );
    }

    #[test]
    fn missing_folder() {
        let dir = tempfile::tempdir().unwrap();
        let e = load_error(&dir.path().join("nowhere"), LoadOptions::default());
        assert_mentions(&e, &["nowhere", "folder not found"]);
    }

    #[test]
    fn missing_image_file() {
        let dir = tempfile::tempdir().unwrap();
        write_scene(dir.path());
        std::fs::remove_file(dir.path().join("train/r_1.png")).unwrap();
        let e = load_error(dir.path(), LoadOptions::default());
        assert_mentions(
            &e,
            &[
                "transforms_train.json: frame 1",
                "image file not found",
                "r_1.png",
            ],
        );
    }

    #[test]
    fn malformed_json_gives_line_and_column() {
        let dir = tempfile::tempdir().unwrap();
        write_scene(dir.path());
        std::fs::write(
            dir.path().join("transforms_val.json"),
            "{\n  \"camera_angle_x\": 0.69\n  \"frames\": []\n}",
        )
        .unwrap();
        let e = load_error(dir.path(), LoadOptions::default());
        assert_mentions(
            &e,
            &["transforms_val.json", "malformed JSON at line 3, column 3"],
        );
    }

    #[test]
    fn missing_camera_angle_x() {
        let dir = tempfile::tempdir().unwrap();
        write_scene(dir.path());
        edit_json(dir.path(), "transforms_train.json", |v| {
            v.as_object_mut().unwrap().remove("camera_angle_x");
        });
        let e = load_error(dir.path(), LoadOptions::default());
        assert_mentions(&e, &["transforms_train.json: missing key `camera_angle_x`"]);
    }

    #[test]
    fn missing_transform_matrix() {
        let dir = tempfile::tempdir().unwrap();
        write_scene(dir.path());
        edit_json(dir.path(), "transforms_train.json", |v| {
            v["frames"][2]
                .as_object_mut()
                .unwrap()
                .remove("transform_matrix");
        });
        let e = load_error(dir.path(), LoadOptions::default());
        assert_mentions(
            &e,
            &["transforms_train.json: frame 2: missing key `transform_matrix`"],
        );
    }

    #[test]
    fn missing_file_path() {
        let dir = tempfile::tempdir().unwrap();
        write_scene(dir.path());
        edit_json(dir.path(), "transforms_val.json", |v| {
            v["frames"][0].as_object_mut().unwrap().remove("file_path");
        });
        let e = load_error(dir.path(), LoadOptions::default());
        assert_mentions(
            &e,
            &["transforms_val.json: frame 0: missing key `file_path`"],
        );
    }

    #[test]
    fn matrix_of_three_rows() {
        let dir = tempfile::tempdir().unwrap();
        write_scene(dir.path());
        edit_json(dir.path(), "transforms_train.json", |v| {
            v["frames"][1]["transform_matrix"]
                .as_array_mut()
                .unwrap()
                .pop();
        });
        let e = load_error(dir.path(), LoadOptions::default());
        assert_mentions(&e, &["transforms_train.json: frame 1", "4×4", "3 rows"]);
    }

    /// Writes the train file with the number 0.25 (frame 0's x position)
    /// replaced by `literal`, and returns the line it is on.
    fn write_train_with_literal(root: &Path, literal: &str) -> usize {
        let path = root.join("transforms_train.json");
        let text = std::fs::read_to_string(&path).unwrap();
        assert_eq!(text.matches("0.25").count(), 1);
        let line = text.lines().position(|l| l.contains("0.25")).unwrap() + 1;
        std::fs::write(&path, text.replace("0.25", literal)).unwrap();
        line
    }

    #[test]
    fn nan_literal_in_matrix() {
        let dir = tempfile::tempdir().unwrap();
        write_scene(dir.path());
        let line = write_train_with_literal(dir.path(), "NaN");
        let e = load_error(dir.path(), LoadOptions::default());
        assert_mentions(
            &e,
            &[
                "transforms_train.json",
                &format!("malformed JSON at line {line}, column"),
                "NaN",
            ],
        );
    }

    #[test]
    fn infinity_literal_in_matrix() {
        let dir = tempfile::tempdir().unwrap();
        write_scene(dir.path());
        let line = write_train_with_literal(dir.path(), "-Infinity");
        let e = load_error(dir.path(), LoadOptions::default());
        assert_mentions(
            &e,
            &[
                "transforms_train.json",
                &format!("malformed JSON at line {line}, column"),
                "Infinity",
            ],
        );
    }

    #[test]
    fn huge_number_in_matrix() {
        // Beyond f64: serde_json refuses it while parsing.
        let dir = tempfile::tempdir().unwrap();
        write_scene(dir.path());
        let line = write_train_with_literal(dir.path(), "1e400");
        let e = load_error(dir.path(), LoadOptions::default());
        assert_mentions(
            &e,
            &[
                "transforms_train.json",
                &format!("line {line}"),
                "out of range",
            ],
        );
        // Beyond f32 only: infinite once converted.
        write_scene(dir.path());
        write_train_with_literal(dir.path(), "1e39");
        let e = load_error(dir.path(), LoadOptions::default());
        assert_mentions(
            &e,
            &[
                "transforms_train.json: frame 0",
                "row 0 column 3",
                "not a finite",
            ],
        );
    }

    #[test]
    fn rotation_not_orthonormal() {
        let dir = tempfile::tempdir().unwrap();
        write_scene(dir.path());
        edit_json(dir.path(), "transforms_val.json", |v| {
            v["frames"][0]["transform_matrix"][0][1] = json!(-0.9);
        });
        let e = load_error(dir.path(), LoadOptions::default());
        assert_mentions(&e, &["transforms_val.json: frame 0", "not orthonormal"]);
    }

    #[test]
    fn frames_of_different_sizes() {
        let dir = tempfile::tempdir().unwrap();
        write_scene(dir.path());
        write_rgba_png(&dir.path().join("val/r_0.png"), 6, 6);
        let e = load_error(dir.path(), LoadOptions::default());
        assert_mentions(
            &e,
            &[
                "transforms_val.json: frame 0",
                "different sizes",
                "val/r_0.png is 6×6",
                "8×6",
            ],
        );
    }

    #[test]
    fn zero_frames() {
        let dir = tempfile::tempdir().unwrap();
        write_json(&dir.path().join("transforms_train.json"), &split(vec![]));
        write_json(&dir.path().join("transforms_val.json"), &split(vec![]));
        let e = load_error(dir.path(), LoadOptions::default());
        assert_mentions(
            &e,
            &["no frames", "transforms_train.json, transforms_val.json"],
        );
    }

    #[test]
    fn camera_angle_of_zero() {
        let dir = tempfile::tempdir().unwrap();
        write_scene(dir.path());
        edit_json(dir.path(), "transforms_train.json", |v| {
            v["camera_angle_x"] = json!(0.0)
        });
        let e = load_error(dir.path(), LoadOptions::default());
        assert_mentions(
            &e,
            &[
                "transforms_train.json",
                "camera_angle_x = 0",
                "focal length",
            ],
        );
        edit_json(dir.path(), "transforms_train.json", |v| {
            v["camera_angle_x"] = json!(3.2)
        });
        let e = load_error(dir.path(), LoadOptions::default());
        assert_mentions(&e, &["camera_angle_x = 3.2", "focal length"]);
    }

    #[test]
    fn undecodable_image() {
        let dir = tempfile::tempdir().unwrap();
        write_scene(dir.path());
        std::fs::write(dir.path().join("train/r_2.png"), b"not a png at all").unwrap();
        let e = load_error(dir.path(), LoadOptions::default());
        assert_mentions(&e, &["transforms_train.json: frame 2", "r_2.png", "cannot"]);
    }

    #[test]
    fn downscale_zero() {
        let dir = tempfile::tempdir().unwrap();
        write_scene(dir.path());
        let e = load_error(dir.path(), LoadOptions { downscale: 0 });
        assert_mentions(
            &e,
            &[&dir.path().display().to_string(), "downscale", "got 0"],
        );
    }

    #[test]
    fn downscale_larger_than_image() {
        let dir = tempfile::tempdir().unwrap();
        write_scene(dir.path());
        let e = load_error(dir.path(), LoadOptions { downscale: 7 });
        assert_mentions(
            &e,
            &["frame 0", "downscale 7 leaves no pixels of a 8×6 image"],
        );
    }
}
