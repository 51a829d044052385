//! Property-based fuzzing of every parser that reads a user's files: the
//! Blender `transforms_*.json`, instant-ngp's `transforms.json`, COLMAP
//! sparse models (text and binary) and the checkpoint reader. Random and mutated inputs must give a scene (with
//! finite, positive intrinsics and finite poses), a checkpoint, or an error
//! naming the problem; never a panic or an abort.
//!
//! `cargo test` runs a bounded number of cases. The long mode is ignored by
//! default: `ZRAK_FUZZ_MINUTES=60 cargo test --release --test it
//! fuzz_parsers -- --ignored --nocapture` runs every parser in turn, in rounds of
//! `ZRAK_FUZZ_CASES` cases (default 2000), until that much time has passed,
//! and prints the counts.

use std::cell::Cell;
use std::path::{Path, PathBuf};

use proptest::prelude::*;
use proptest::test_runner::{Config, RngAlgorithm, TestRng, TestRunner};
use serde_json::{Value, json};
use zrak::model::checkpoint::Checkpoint;
use zrak::scene::colmap::{
    ColmapCamera, ColmapImage, ColmapModel, {self},
};
use zrak::scene::{ImageRgba8, LoadOptions, Scene};

/// Cases per parser in `cargo test`: a few seconds in all.
const BOUNDED_CASES: u32 = 300;

/// A runner for `cases` cases: the bounded runs in `cargo test` draw the
/// same inputs every time (a failure in CI reproduces anywhere); the long
/// mode's rounds draw new ones.
fn runner(cases: u32) -> TestRunner {
    if cases <= BOUNDED_CASES {
        TestRunner::new_with_rng(
            config(cases),
            TestRng::deterministic_rng(RngAlgorithm::ChaCha),
        )
    } else {
        TestRunner::new(config(cases))
    }
}

fn config(cases: u32) -> Config {
    Config {
        cases,
        // Nothing written into the source tree; a failure prints its input.
        failure_persistence: None,
        max_shrink_iters: 2000,
        ..Config::default()
    }
}

/// A folder with the images the valid documents name (2×2 PNGs).
fn image_folder() -> tempfile::TempDir {
    let dir = tempfile::tempdir().expect("a temporary folder");
    for sub in ["train", "val", "test", "images"] {
        std::fs::create_dir_all(dir.path().join(sub)).unwrap();
        for i in 0..3 {
            let pixels: Vec<u8> = (0..16).map(|v| (v * 16 + i) as u8).collect();
            ImageRgba8::new(2, 2, pixels)
                .save_png(&dir.path().join(sub).join(format!("r_{i}.png")))
                .unwrap();
        }
    }
    dir
}

fn pose(z: f64) -> Value {
    json!([
        [1.0, 0.0, 0.0, 0.0],
        [0.0, 1.0, 0.0, 0.0],
        [0.0, 0.0, 1.0, z],
        [0.0, 0.0, 0.0, 1.0]
    ])
}

/// A valid NeRF-synthetic split file.
fn blender_document(split: &str) -> Value {
    json!({
        "camera_angle_x": 0.69,
        "frames": (0..3).map(|i| json!({
            "file_path": format!("./{split}/r_{i}"),
            "rotation": 0.01,
            "transform_matrix": pose(3.0 + i as f64),
        })).collect::<Vec<_>>(),
    })
}

/// A valid instant-ngp / nerfstudio file.
fn instant_ngp_document() -> Value {
    json!({
        "fl_x": 2.5, "fl_y": 2.5, "cx": 1.0, "cy": 1.0, "w": 2, "h": 2,
        "camera_angle_x": 0.8,
        "aabb_scale": 4, "scale": 0.33, "offset": [0.5, 0.5, 0.5],
        "frames": (0..3).map(|i| json!({
            "file_path": format!("images/r_{i}.png"),
            "transform_matrix": pose(2.0 + i as f64),
            "fl_x": 2.0 + i as f64,
        })).collect::<Vec<_>>(),
        "train_filenames": ["images/r_0.png", "images/r_1.png"],
        "val_filenames": ["images/r_2.png"],
    })
}

/// JSON values a parser might meet where it expects something else:
/// extremes, wrong types, odd strings and matrix-shaped arrays.
fn leaf() -> impl Strategy<Value = Value> {
    prop_oneof![
        Just(Value::Null),
        any::<bool>().prop_map(Value::from),
        any::<i64>().prop_map(Value::from),
        any::<u64>().prop_map(Value::from),
        any::<f64>()
            .prop_filter("JSON has no NaN or infinity", |v| v.is_finite())
            .prop_map(Value::from),
        prop::sample::select(vec![
            0.0,
            -0.0,
            1.0,
            -1.0,
            0.5,
            3.2,
            1e-45,
            1e-320,
            1e38,
            3.5e38,
            1e300,
            -1e300,
            f64::MAX,
            f64::MIN_POSITIVE,
            std::f64::consts::PI,
            std::f64::consts::PI - 1e-7,
            6.3,
        ])
        .prop_map(Value::from),
        prop::sample::select(vec![
            "",
            ".",
            "./",
            "..",
            "../..",
            "./train/r_0",
            "images/r_1.png",
            "r_0.jpg",
            "train",
            "\u{0}",
            "ü/ñ",
            "C:\\x",
            "////",
            "train/",
        ])
        .prop_map(Value::from),
        "[a-z_./0-9]{0,12}".prop_map(Value::from),
        prop::collection::vec(prop::collection::vec(-10.0f64..10.0, 0..6), 0..6)
            .prop_map(|rows| json!(rows)),
        Just(json!([])),
        Just(json!({})),
    ]
}

/// Any JSON value, a few levels deep.
fn any_json() -> impl Strategy<Value = Value> {
    leaf().prop_recursive(3, 24, 6, |inner| {
        prop_oneof![
            prop::collection::vec(inner.clone(), 0..6).prop_map(Value::Array),
            prop::collection::vec(
                (
                    prop::sample::select(vec![
                        "frames",
                        "file_path",
                        "transform_matrix",
                        "camera_angle_x",
                        "camera_angle_y",
                        "fl_x",
                        "fl_y",
                        "cx",
                        "cy",
                        "w",
                        "h",
                        "aabb_scale",
                        "scale",
                        "offset",
                        "train_filenames",
                        "val_filenames",
                        "test_filenames",
                        "k1",
                        "camera_model",
                        "x",
                    ]),
                    inner
                ),
                0..6
            )
            .prop_map(|pairs| Value::Object(
                pairs.into_iter().map(|(k, v)| (k.to_string(), v)).collect()
            )),
        ]
    })
}

/// One edit of a JSON document.
#[derive(Debug, Clone)]
enum Edit {
    /// Replace the `node`-th value (pre-order, modulo the count) with this.
    Replace(usize, Value),
    /// Remove the `node`-th value from its object or array.
    Remove(usize),
    /// Put a copy of the `node`-th value's parent's children twice.
    Duplicate(usize),
}

fn edit() -> impl Strategy<Value = Edit> {
    prop_oneof![
        3 => (any::<usize>(), any_json()).prop_map(|(n, v)| Edit::Replace(n, v)),
        1 => any::<usize>().prop_map(Edit::Remove),
        1 => any::<usize>().prop_map(Edit::Duplicate),
    ]
}

fn count(value: &Value) -> usize {
    1 + match value {
        Value::Array(items) => items.iter().map(count).sum(),
        Value::Object(map) => map.values().map(count).sum(),
        _ => 0,
    }
}

/// Applies `edit` to the `target`-th node below `value` (counting `value`
/// itself as 0); returns the nodes still to skip.
fn apply(value: &mut Value, target: usize, edit: &Edit) -> Option<usize> {
    if target == 0 {
        if let Edit::Replace(_, new) = edit {
            *value = new.clone();
        }
        return None;
    }
    let mut left = target - 1;
    match value {
        Value::Array(items) => {
            for i in 0..items.len() {
                if left == 0 {
                    match edit {
                        Edit::Remove(_) => {
                            items.remove(i);
                        }
                        Edit::Duplicate(_) => {
                            let copy = items[i].clone();
                            items.insert(i, copy);
                        }
                        Edit::Replace(..) => items[i] = replacement(edit),
                    }
                    return None;
                }
                left = apply(&mut items[i], left, edit)?;
            }
        }
        Value::Object(map) => {
            let keys: Vec<String> = map.keys().cloned().collect();
            for key in keys {
                if left == 0 {
                    match edit {
                        Edit::Remove(_) => {
                            map.remove(&key);
                        }
                        Edit::Duplicate(_) => {
                            let copy = map[&key].clone();
                            map.insert(key.clone(), json!([copy.clone(), copy]));
                        }
                        Edit::Replace(..) => {
                            map.insert(key, replacement(edit));
                        }
                    }
                    return None;
                }
                left = apply(map.get_mut(&key).expect("a key just listed"), left, edit)?;
            }
        }
        _ => {}
    }
    Some(left)
}

fn replacement(edit: &Edit) -> Value {
    match edit {
        Edit::Replace(_, new) => new.clone(),
        _ => Value::Null,
    }
}

fn mutate(mut document: Value, edits: &[Edit]) -> Value {
    for edit in edits {
        let node = match edit {
            Edit::Replace(n, _) | Edit::Remove(n) | Edit::Duplicate(n) => *n,
        };
        let target = node % count(&document);
        apply(&mut document, target, edit);
    }
    document
}

/// Byte-level damage to a file's text: truncation, flipped and inserted
/// bytes.
#[derive(Debug, Clone)]
enum ByteEdit {
    Truncate(usize),
    Set(usize, u8),
    Insert(usize, Vec<u8>),
}

fn byte_edit() -> impl Strategy<Value = ByteEdit> {
    prop_oneof![
        any::<usize>().prop_map(ByteEdit::Truncate),
        (any::<usize>(), any::<u8>()).prop_map(|(i, b)| ByteEdit::Set(i, b)),
        (any::<usize>(), prop::collection::vec(any::<u8>(), 1..8))
            .prop_map(|(i, b)| ByteEdit::Insert(i, b)),
    ]
}

fn damage(mut bytes: Vec<u8>, edits: &[ByteEdit]) -> Vec<u8> {
    for edit in edits {
        let len = bytes.len().max(1);
        match edit {
            ByteEdit::Truncate(i) => bytes.truncate(i % len),
            ByteEdit::Set(i, b) => {
                if !bytes.is_empty() {
                    let i = i % bytes.len();
                    bytes[i] = *b;
                }
            }
            ByteEdit::Insert(i, new) => {
                let i = i % (bytes.len() + 1);
                bytes.splice(i..i, new.iter().copied());
            }
        }
    }
    bytes
}

/// What a scene file's content may be: a mutated valid document, damaged
/// bytes of one, or anything at all.
#[derive(Debug, Clone)]
enum Input {
    Edited(Vec<Edit>),
    Damaged(Vec<Edit>, Vec<ByteEdit>),
    Json(Value),
    Bytes(Vec<u8>),
}

fn input() -> impl Strategy<Value = Input> {
    prop_oneof![
        4 => prop::collection::vec(edit(), 1..5).prop_map(Input::Edited),
        2 => (prop::collection::vec(edit(), 0..2), prop::collection::vec(byte_edit(), 1..4))
            .prop_map(|(e, b)| Input::Damaged(e, b)),
        1 => any_json().prop_map(Input::Json),
        1 => prop::collection::vec(any::<u8>(), 0..64).prop_map(Input::Bytes),
    ]
}

fn render_input(valid: Value, input: &Input) -> Vec<u8> {
    match input {
        Input::Edited(edits) => serde_json::to_vec(&mutate(valid, edits)).unwrap(),
        Input::Damaged(edits, bytes) => damage(
            serde_json::to_vec_pretty(&mutate(valid, edits)).unwrap(),
            bytes,
        ),
        Input::Json(value) => serde_json::to_vec(value).unwrap(),
        Input::Bytes(bytes) => bytes.clone(),
    }
}

/// Loads `folder` and checks the outcome: an error with a message naming a
/// path, or a scene whose cameras are usable.
fn check_load(folder: &Path) -> Result<bool, TestCaseError> {
    match Scene::load(folder, LoadOptions::default()) {
        Err(error) => {
            let message = error.to_string();
            prop_assert!(
                !error.problem().is_empty() && message.contains(&*error.path().to_string_lossy()),
                "an error without a file or a problem: {message:?}"
            );
            Ok(false)
        }
        Ok(scene) => {
            prop_assert!(scene.frames().next().is_some(), "a scene without frames");
            for frame in scene.frames() {
                let k = frame.camera.intrinsics;
                prop_assert!(
                    k.fx.is_finite() && k.fy.is_finite() && k.fx > 0.0 && k.fy > 0.0,
                    "intrinsics {k:?}"
                );
                prop_assert!(k.cx.is_finite() && k.cy.is_finite(), "intrinsics {k:?}");
                prop_assert!(
                    frame.camera.camera_to_world.is_finite(),
                    "pose {:?}",
                    frame.camera.camera_to_world
                );
            }
            Ok(true)
        }
    }
}

/// Counts of a fuzzing run, for the long mode's report.
/// (Cells: proptest runs a case through a shared `Fn`.)
#[derive(Default, Debug)]
struct Counts {
    cases: Cell<u64>,
    loaded: Cell<u64>,
    refused: Cell<u64>,
}

impl Counts {
    fn tally(&self, loaded: bool) {
        self.cases.set(self.cases.get() + 1);
        let count = if loaded { &self.loaded } else { &self.refused };
        count.set(count.get() + 1);
    }

    fn both_seen(&self) -> bool {
        self.loaded.get() > 0 && self.refused.get() > 0
    }
}

fn fuzz_blender(cases: u32) -> Counts {
    let dir = image_folder();
    let counts = Counts::default();
    let mut runner = runner(cases);
    let outcome = runner.run(
        &(input(), 0usize..3, any::<bool>()),
        |(input, which, keep_others)| {
            let splits = ["train", "val", "test"];
            for (i, split) in splits.iter().enumerate() {
                let path = dir.path().join(format!("transforms_{split}.json"));
                if i == which {
                    std::fs::write(&path, render_input(blender_document(split), &input)).unwrap();
                } else if keep_others {
                    std::fs::write(&path, blender_document(split).to_string()).unwrap();
                } else {
                    let _ = std::fs::remove_file(&path);
                }
            }
            let loaded = check_load(dir.path())?;
            counts.tally(loaded);
            Ok(())
        },
    );
    if let Err(failure) = outcome {
        panic!("Blender transforms: {failure}");
    }
    counts
}

fn fuzz_instant_ngp(cases: u32) -> Counts {
    let dir = image_folder();
    let path: PathBuf = dir.path().join("transforms.json");
    let counts = Counts::default();
    let mut runner = runner(cases);
    let outcome = runner.run(&input(), |input| {
        std::fs::write(&path, render_input(instant_ngp_document(), &input)).unwrap();
        let loaded = check_load(dir.path())?;
        counts.tally(loaded);
        Ok(())
    });
    if let Err(failure) = outcome {
        panic!("instant-ngp transforms.json: {failure}");
    }
    counts
}

/// A small valid checkpoint with the header shape the trainer writes.
fn checkpoint_bytes(dir: &Path) -> Vec<u8> {
    let checkpoint = Checkpoint {
        header: json!({
            "trainer": {"step": 3, "train_seconds": 1.5, "seed": 0,
                "scene": {"name": "demo", "train_frames": 3, "width": 2, "height": 2,
                    "cameras_hash": 12345}},
            "model": {"model": "ngp", "loss": "Huber", "seed": 0, "adam_step": 3,
                "samples_per_ray": 4.0, "param_count": 4},
            "run": {"scene": "demo", "model": "ngp", "downscale": 1, "loss": "Huber", "seed": 0},
        }),
        tensors: vec![
            ("params".into(), vec![0.5, -1.0, 2.0, 1e-3]),
            ("adam.m".into(), vec![0.0; 4]),
            ("occupancy".into(), vec![1.0; 8]),
        ],
    };
    let path = dir.join("valid.zrak");
    checkpoint.save(&path).unwrap();
    std::fs::read(path).unwrap()
}

/// Checkpoint damage: byte edits, or a header (JSON) edit with the bytes
/// re-framed so the damage reaches the tensor table.
#[derive(Debug, Clone)]
enum CheckpointInput {
    Bytes(Vec<ByteEdit>),
    Header(Vec<Edit>, i64),
    Random(Vec<u8>),
}

fn fuzz_checkpoint(cases: u32) -> Counts {
    let dir = tempfile::tempdir().unwrap();
    let valid = checkpoint_bytes(dir.path());
    let header_length = u64::from_le_bytes(valid[12..20].try_into().unwrap()) as usize;
    let header: Value = serde_json::from_slice(&valid[20..20 + header_length]).unwrap();
    let path = dir.path().join("checkpoint.zrak");
    let counts = Counts::default();
    let mut runner = runner(cases);
    let strategy = prop_oneof![
        2 => prop::collection::vec(byte_edit(), 1..4).prop_map(CheckpointInput::Bytes),
        3 => (prop::collection::vec(edit(), 1..4), -8i64..8)
            .prop_map(|(e, d)| CheckpointInput::Header(e, d)),
        1 => prop::collection::vec(any::<u8>(), 0..48).prop_map(CheckpointInput::Random),
    ];
    let outcome = runner.run(&strategy, |input| {
        let bytes = match &input {
            CheckpointInput::Bytes(edits) => damage(valid.clone(), edits),
            CheckpointInput::Header(edits, length_change) => {
                // Format 2 follows the header with its checksum: the edited
                // header gets its own, so the damage reaches the tensor
                // table instead of stopping at the checksum.
                let new_header = serde_json::to_vec(&mutate(header.clone(), edits)).unwrap();
                let declared = (new_header.len() as i64 + length_change).max(0) as u64;
                let mut bytes = valid[..12].to_vec();
                bytes.extend_from_slice(&declared.to_le_bytes());
                bytes.extend_from_slice(&new_header);
                bytes.extend_from_slice(&zrak::crc32c::crc32c(&new_header).to_le_bytes());
                bytes.extend_from_slice(&valid[20 + header_length + 4..]);
                bytes
            }
            CheckpointInput::Random(bytes) => {
                let mut with_magic = b"ZRAKCKPT\x01\x00\x00\x00".to_vec();
                with_magic.extend_from_slice(bytes);
                with_magic
            }
        };
        std::fs::write(&path, &bytes).unwrap();
        match Checkpoint::load(&path) {
            Ok(_) => counts.tally(true),
            Err(error) => {
                let message = error.to_string();
                prop_assert!(message.contains("checkpoint.zrak"), "{message}");
                counts.tally(false);
            }
        }
        Ok(())
    });
    if let Err(failure) = outcome {
        panic!("checkpoint reader: {failure}");
    }
    counts
}

/// A valid COLMAP model for the three images of [`image_folder`]: one
/// OPENCV camera with a little distortion, three images facing the origin,
/// a few sparse points.
fn colmap_model() -> ColmapModel {
    let mut model = ColmapModel::default();
    model.cameras.insert(
        1,
        ColmapCamera {
            id: 1,
            model: "OPENCV".into(),
            width: 2,
            height: 2,
            params: vec![2.5, 2.5, 1.0, 1.0, 0.01, -0.002, 0.0001, 0.0],
        },
    );
    for i in 0..3u32 {
        let half_turn = 0.3 * i as f64;
        model.images.push(ColmapImage {
            id: i + 1,
            rotation: [half_turn.cos(), 0.0, half_turn.sin(), 0.0],
            translation: [0.1 * i as f64, 0.0, 4.0],
            camera_id: 1,
            name: format!("r_{i}.png"),
        });
    }
    model.points = vec![[0.0, 0.0, 0.0], [0.5, -0.2, 0.1], [-0.3, 0.4, 0.2]];
    model
}

/// COLMAP damage: one of the three files of a text or binary model, edited
/// bytewise, or (text) a token replaced by an odd one, or replaced whole.
#[derive(Debug, Clone)]
enum ColmapInput {
    Bytes(bool, usize, Vec<ByteEdit>),
    Token(usize, usize, String),
    Whole(bool, usize, Vec<u8>),
}

const COLMAP_FILES: [&str; 3] = ["cameras", "images", "points3D"];

fn odd_token() -> impl Strategy<Value = String> {
    prop_oneof![
        prop::sample::select(vec![
            "",
            "0",
            "-1",
            "4294967296",
            "1e308",
            "-1e308",
            "nan",
            "inf",
            "1e-320",
            "PINHOLE",
            "OPENCV_FISHEYE",
            "FOV",
            "THIN_PRISM_FISHEYE",
            "r_0.png",
            "../r_1.png",
            "#",
            "\n",
            "18446744073709551615",
        ])
        .prop_map(String::from),
        "[-0-9.eE]{1,8}",
        any::<f64>().prop_map(|v| v.to_string()),
    ]
}

fn fuzz_colmap(cases: u32) -> Counts {
    let dir = image_folder();
    let model = colmap_model();
    let valid = |binary: bool| -> Vec<Vec<u8>> {
        let scratch = tempfile::tempdir().unwrap();
        if binary {
            colmap::write_binary(&model, scratch.path()).unwrap();
        } else {
            colmap::write_text(&model, scratch.path()).unwrap();
        }
        let extension = if binary { "bin" } else { "txt" };
        COLMAP_FILES
            .iter()
            .map(|file| std::fs::read(scratch.path().join(format!("{file}.{extension}"))).unwrap())
            .collect()
    };
    let (text, binary) = (valid(false), valid(true));
    let sparse = dir.path().join("sparse/0");
    let counts = Counts::default();
    let mut runner = runner(cases);
    let strategy = prop_oneof![
        3 => (any::<bool>(), 0usize..3, prop::collection::vec(byte_edit(), 1..4))
            .prop_map(|(b, f, e)| ColmapInput::Bytes(b, f, e)),
        3 => (0usize..3, any::<usize>(), odd_token())
            .prop_map(|(f, t, s)| ColmapInput::Token(f, t, s)),
        1 => (any::<bool>(), 0usize..3, prop::collection::vec(any::<u8>(), 0..64))
            .prop_map(|(b, f, bytes)| ColmapInput::Whole(b, f, bytes)),
    ];
    let outcome = runner.run(&strategy, |input| {
        let (is_binary, damaged_file, bytes) = match &input {
            ColmapInput::Bytes(b, f, edits) => {
                let files = if *b { &binary } else { &text };
                (*b, *f, damage(files[*f].clone(), edits))
            }
            ColmapInput::Token(f, which, token) => {
                let content = String::from_utf8(text[*f].clone()).unwrap();
                let tokens: Vec<&str> = content.split(' ').collect();
                let i = which % tokens.len();
                let mut edited = tokens.clone();
                edited[i] = token;
                (false, *f, edited.join(" ").into_bytes())
            }
            ColmapInput::Whole(b, f, bytes) => (*b, *f, bytes.clone()),
        };
        let _ = std::fs::remove_dir_all(&sparse);
        std::fs::create_dir_all(&sparse).unwrap();
        let (files, extension) = if is_binary {
            (&binary, "bin")
        } else {
            (&text, "txt")
        };
        for (i, file) in COLMAP_FILES.iter().enumerate() {
            let content = if i == damaged_file { &bytes } else { &files[i] };
            std::fs::write(sparse.join(format!("{file}.{extension}")), content).unwrap();
        }
        let loaded = check_load(dir.path())?;
        counts.tally(loaded);
        Ok(())
    });
    if let Err(failure) = outcome {
        panic!("COLMAP model: {failure}");
    }
    counts
}

#[test]
fn blender_transforms_never_panic() {
    let _cores = crate::common::shared();
    let counts = fuzz_blender(BOUNDED_CASES);
    assert!(counts.both_seen(), "{counts:?}");
}

#[test]
fn instant_ngp_transforms_never_panic() {
    let _cores = crate::common::shared();
    let counts = fuzz_instant_ngp(BOUNDED_CASES);
    assert!(counts.both_seen(), "{counts:?}");
}

#[test]
fn colmap_models_never_panic() {
    let _cores = crate::common::shared();
    let counts = fuzz_colmap(BOUNDED_CASES);
    assert!(counts.both_seen(), "{counts:?}");
}

#[test]
fn checkpoint_reader_never_panics() {
    let _cores = crate::common::shared();
    let counts = fuzz_checkpoint(BOUNDED_CASES);
    assert!(counts.both_seen(), "{counts:?}");
}

/// The long mode: every parser in turn, `ZRAK_FUZZ_CASES` cases at a time
/// (default 2000), for `ZRAK_FUZZ_MINUTES` (default 10) minutes.
#[test]
#[ignore = "long: set ZRAK_FUZZ_MINUTES and run with --ignored"]
fn long_fuzz_of_every_parser() {
    let _cores = crate::common::shared();
    let setting = |name: &str, default: u64| -> u64 {
        std::env::var(name)
            .ok()
            .and_then(|v| v.parse().ok())
            .unwrap_or(default)
    };
    let round = setting("ZRAK_FUZZ_CASES", 2000) as u32;
    let budget = std::time::Duration::from_secs(60 * setting("ZRAK_FUZZ_MINUTES", 10));
    type Fuzzer = fn(u32) -> Counts;
    let parsers: [(&str, Fuzzer); 4] = [
        ("Blender transforms_*.json", fuzz_blender),
        ("instant-ngp transforms.json", fuzz_instant_ngp),
        ("COLMAP sparse model", fuzz_colmap),
        ("checkpoint reader", fuzz_checkpoint),
    ];
    let mut totals = [(0u64, 0u64, 0u64); 4];
    let started = std::time::Instant::now();
    let mut rounds = 0;
    while started.elapsed() < budget {
        rounds += 1;
        for ((_, run), total) in parsers.iter().zip(&mut totals) {
            let counts = run(round);
            total.0 += counts.cases.get();
            total.1 += counts.loaded.get();
            total.2 += counts.refused.get();
        }
        eprintln!(
            "round {rounds}: {} cases in all, 0 panics ({:.0} s)",
            totals.iter().map(|t| t.0).sum::<u64>(),
            started.elapsed().as_secs_f64()
        );
    }
    for ((name, _), (cases, loaded, refused)) in parsers.iter().zip(totals) {
        eprintln!(
            "{name}: {cases} cases, {loaded} loaded, {refused} refused with an error, 0 panics"
        );
    }
}

/// What the long mode found: focal lengths positive as f64 but 0 (or
/// infinite) as the f32 the cameras use.
#[test]
fn focal_lengths_that_vanish_in_f32_are_refused() {
    let _cores = crate::common::shared();
    let dir = image_folder();
    let mut document = instant_ngp_document();
    document["frames"][0]["fl_x"] = json!(5.3e-134);
    std::fs::write(dir.path().join("transforms.json"), document.to_string()).unwrap();
    let error = Scene::load(dir.path(), LoadOptions::default()).unwrap_err();
    assert!(error.to_string().contains("fl_x"), "{error}");
    std::fs::remove_file(dir.path().join("transforms.json")).unwrap();

    let mut document = blender_document("train");
    document["camera_angle_x"] = json!(1e-50);
    std::fs::write(
        dir.path().join("transforms_train.json"),
        document.to_string(),
    )
    .unwrap();
    let error = Scene::load(dir.path(), LoadOptions::default()).unwrap_err();
    assert!(error.to_string().contains("camera_angle_x"), "{error}");
}

/// What the long mode found in COLMAP models: parameters finite as f64 but
/// infinite as f32, focal lengths positive as f64 but 0 as f32, and a
/// quaternion whose squared norm overflows (its rotation becomes NaN).
#[test]
fn colmap_values_that_break_in_f32_are_refused() {
    let _cores = crate::common::shared();
    let load_with = |edit: &dyn Fn(&mut ColmapModel)| {
        let dir = image_folder();
        let mut model = colmap_model();
        edit(&mut model);
        let sparse = dir.path().join("sparse/0");
        std::fs::create_dir_all(&sparse).unwrap();
        colmap::write_text(&model, &sparse).unwrap();
        Scene::load(dir.path(), LoadOptions::default())
            .map(|_| ())
            .unwrap_err()
            .to_string()
    };
    let error = load_with(&|m| m.cameras.get_mut(&1).unwrap().params[0] = 1e-300);
    assert!(
        error.contains("cameras.txt") && error.contains("focal"),
        "{error}"
    );
    let error = load_with(&|m| m.cameras.get_mut(&1).unwrap().params[2] = 1e308);
    assert!(
        error.contains("cameras.txt") && error.contains("finite"),
        "{error}"
    );
    let error = load_with(&|m| m.images[1].rotation[0] = 3e179);
    assert!(
        error.contains("images.txt") && error.contains("r_1.png"),
        "{error}"
    );
}
