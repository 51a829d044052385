//! Nothing a user already has is lost, bad input is refused by name,
//! nothing panics (issue 31): every command against bad input, signals,
//! full disks and full standard output.

use super::*;

// ---------------------------------------------------------------------
// Issue 31: nothing a user already has is lost, bad input is refused by
// name, nothing panics.
// ---------------------------------------------------------------------

/// Copies the folder `from` to `to` (files and folders only).
fn copy_folder(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for entry in std::fs::read_dir(from).unwrap() {
        let entry = entry.unwrap();
        let target = to.join(entry.file_name());
        if entry.file_type().unwrap().is_dir() {
            copy_folder(&entry.path(), &target);
        } else {
            std::fs::copy(entry.path(), target).unwrap();
        }
    }
}

/// An instant-ngp scene in `d/name`: the demo `scene`'s training views
/// (their images copied), with `edit` applied to the transforms.json.
fn instant_ngp_variant(d: &Path, name: &str, edit: impl FnOnce(&mut serde_json::Value)) {
    let blender = read_json(&d.join("scene/transforms_train.json"));
    let frames: Vec<serde_json::Value> = blender["frames"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| {
            let file = f["file_path"].as_str().unwrap().trim_start_matches("./");
            serde_json::json!({
                "file_path": format!("{file}.png"),
                "transform_matrix": f["transform_matrix"],
            })
        })
        .collect();
    let mut json = serde_json::json!({
        "camera_angle_x": blender["camera_angle_x"],
        "frames": frames,
    });
    edit(&mut json);
    let folder = d.join(name);
    copy_folder(&d.join("scene/train"), &folder.join("train"));
    std::fs::write(
        folder.join("transforms.json"),
        serde_json::to_string_pretty(&json).unwrap(),
    )
    .unwrap();
}

/// A COLMAP model of the demo's cameras with their photographs, in
/// `d/name`; `edit` may change images.txt's text.
fn colmap_scene(d: &Path, name: &str, edit: impl FnOnce(String) -> String) {
    let demo = zrak::scene::demo::build(&zrak::scene::demo::DemoConfig {
        size: 16,
        train_views: 9,
        val_views: 1,
        test_views: 1,
    });
    let cameras: Vec<_> = demo.train.iter().map(|f| f.camera).collect();
    let model = zrak::scene::colmap::model_from_cameras(&cameras, |i| format!("{i:03}.png"));
    let sparse = d.join(name).join("sparse/0");
    zrak::scene::colmap::write_text(&model, &sparse).unwrap();
    let images = sparse.join("images.txt");
    let text = std::fs::read_to_string(&images).unwrap();
    std::fs::write(&images, edit(text)).unwrap();
    std::fs::create_dir_all(d.join(name).join("images")).unwrap();
    for (i, frame) in demo.train.iter().enumerate() {
        frame
            .image
            .save_png(&d.join(name).join(format!("images/{i:03}.png")))
            .unwrap();
    }
}

/// Sum of the split counts `zrak info` prints on its `frames` line.
fn frames_in_info(stdout: &str) -> usize {
    let line = stdout
        .lines()
        .find(|l| l.starts_with("frames"))
        .unwrap_or_else(|| panic!("no frames line in {stdout}"));
    line.split(',')
        .filter_map(|part| part.split_whitespace().last()?.parse::<usize>().ok())
        .sum()
}

fn make_fifo(path: &Path) {
    let name = std::ffi::CString::new(path.to_str().unwrap()).unwrap();
    // SAFETY: a valid NUL-terminated path.
    assert_eq!(unsafe { libc::mkfifo(name.as_ptr(), 0o600) }, 0);
}

/// One refusal (or acceptance) as a user meets it: the command, whether it
/// must succeed, and words its standard error (or output) must hold.
struct Case {
    args: &'static [&'static str],
    succeeds: bool,
    says: &'static [&'static str],
}

const fn refused(args: &'static [&'static str], says: &'static [&'static str]) -> Case {
    Case {
        args,
        succeeds: false,
        says,
    }
}

const fn accepted(args: &'static [&'static str], says: &'static [&'static str]) -> Case {
    Case {
        args,
        succeeds: true,
        says,
    }
}

/// The cases, each run against the built binary in a folder set
/// up by [`bad_input_fixture`].
const CASES: &[Case] = &[
    // A folder holding a run is not trained over.
    refused(
        &[
            "train", "scene", "--steps", "1", "--engine", "cpu", "--out", "run",
        ],
        &[
            "run already holds a run (step 2",
            "--resume run",
            "--force",
            "nothing deleted",
        ],
    ),
    // `1e9h` is a duration (the refusal is the run's, not the unit's).
    refused(
        &[
            "train", "scene", "--time", "1e9h", "--engine", "cpu", "--out", "run",
        ],
        &["already holds a run"],
    ),
    refused(
        &["train", "scene", "--time", "5x", "--out", "new"],
        &["unknown unit `x`"],
    ),
    // Resume targets the run has reached.
    refused(
        &["train", "--resume", "run", "--steps", "2"],
        &["already at step 2", "give more than 2"],
    ),
    refused(
        &["train", "--resume", "run", "--time", "0.001s"],
        &["--time", "leaves nothing to train"],
    ),
    refused(
        &["train", "--resume", "nowhere", "--steps", "9"],
        &["nowhere: no such run folder"],
    ),
    refused(
        &["train", "--resume", "scene", "--steps", "9"],
        &["no checkpoint to resume from"],
    ),
    // convert never destroys its input, nor overwrites without --force.
    refused(
        &["convert", "colmap", "--out", "colmap/sparse/0/images.txt"],
        &["the COLMAP model's own images.txt", "convert reads it"],
    ),
    refused(
        &[
            "convert",
            "colmap",
            "--out",
            "colmap/sparse/0/../0/cameras.txt",
            "--force",
        ],
        &["own cameras.txt"],
    ),
    refused(
        &["convert", "colmap", "--out", "colmap/images/x.json"],
        &["photographs folder"],
    ),
    refused(
        &["convert", "colmap", "--out", "existing.json"],
        &["existing.json already exists", "--force"],
    ),
    refused(
        &["convert", "colmap", "--out", "scene"],
        &["scene: is a folder"],
    ),
    refused(
        &["convert", "nowhere", "--out", "n.json"],
        &["nowhere: folder not found"],
    ),
    refused(&["convert", "fifo", "--out", "n.json"], &["named pipe"]),
    // demo and render do not write over what is there.
    refused(
        &["demo", "--out", "scene", "--size", "16", "--views", "3"],
        &["scene is not empty", "--force"],
    ),
    refused(
        &["render", "run", "--view", "0", "--out", "rendered"],
        &["rendered/val_000.png already exists", "--force"],
    ),
    refused(
        &["render", "run", "--turntable", "3", "--out", "rendered"],
        &["turntable_0000.png already exists (and 1 more"],
    ),
    // Training that would do nothing.
    refused(
        &[
            "train", "noviews", "--steps", "1", "--engine", "cpu", "--out", "r1",
        ],
        &["noviews: nothing to train: the scene has no training views"],
    ),
    refused(
        &[
            "train", "far", "--steps", "1", "--engine", "cpu", "--out", "r2",
        ],
        &[
            "far: nothing to train",
            "no training camera's rays cross the scene's box",
        ],
    ),
    // A field of view of nearly 180°: every ray leaves sideways.
    refused(
        &[
            "train", "wide", "--steps", "1", "--engine", "cpu", "--out", "r5",
        ],
        &["wide: nothing to train", "rays cross"],
    ),
    refused(
        &["info", "tiny-scale"],
        &["transforms.json", "`scale` = ", "not a finite box"],
    ),
    refused(
        &["info", "huge-aabb"],
        &["transforms.json", "`aabb_scale` = 40000 is more than 32768"],
    ),
    // Sizes, counts and scales bounded before any work.
    refused(
        &[
            "train",
            "demo",
            "--downscale",
            "200",
            "--steps",
            "1",
            "--out",
            "r3",
        ],
        &["--downscale 200 leaves no pixels", "at most 128"],
    ),
    refused(
        &["render", "run", "--turntable", "4294967296", "--out", "t1"],
        &["--turntable must be 1 to 100000"],
    ),
    refused(
        &[
            "render",
            "run",
            "--turntable",
            "2",
            "--size",
            "65535",
            "--gif",
            "--out",
            "t2",
        ],
        &["--size must be 1 to 16384"],
    ),
    refused(
        &["demo", "--size", "100000", "--out", "big"],
        &["--size must be 8 to 16384"],
    ),
    refused(
        &[
            "train",
            "scene",
            "--training-scales",
            "8",
            "--steps",
            "1",
            "--engine",
            "cpu",
            "--out",
            "r4",
        ],
        &[
            "--training-scales 8",
            "the smallest here is 16",
            "give at most 5",
        ],
    ),
    // Silent misreads and the messages that named the wrong problem.
    refused(
        &["info", "folding"],
        &[
            "transforms.json",
            "folds over inside its 16×16 image",
            "k1 -10",
        ],
    ),
    refused(&["info", "folding-huge"], &["folds over"]),
    refused(&["info", "fifo"], &["fifo", "named pipe"]),
    refused(
        &["info", "dangling"],
        &["dangling", "dangling symbolic link", "gone"],
    ),
    refused(&["info", "loop"], &["loop", "symbolic link that loops"]),
    refused(
        &["info", "folder-image"],
        &["r_0.png", "a folder, not a file"],
    ),
    refused(&["info", "pipe-json/transforms.json"], &["named pipe"]),
    accepted(&["info", "bom"], &["frames ", "images      16×16"]),
    accepted(&["info", "utf16"], &["frames ", "images      16×16"]),
    // A damaged or diverged checkpoint is refused by name; nothing panics.
    refused(
        &["eval", "run-flipped"],
        &["damaged", "tensor `params` fails its checksum"],
    ),
    refused(
        &["eval", "run-nan"],
        &["tensor `params` holds NaN at index 0", "diverged"],
    ),
    refused(
        &["render", "run-nan", "--view", "0", "--out", "nan-frames"],
        &["holds NaN"],
    ),
    refused(
        &["train", "--resume", "run-nan", "--steps", "9"],
        &["holds NaN"],
    ),
    // Views under SSIM's window are said to be, not left as a bare NaN.
    accepted(
        &["eval", "run", "--downscale", "2"],
        &["SSIM is NaN for 1 of the 1 views", "11×11 window"],
    ),
];

/// The folder the cases run in: a demo scene, a run trained 2 steps on it,
/// a COLMAP model, and the broken inputs the cases name.
fn bad_input_fixture(d: &Path) {
    succeed(
        d,
        &["demo", "--out", "scene", "--size", "16", "--views", "3"],
    );
    succeed(
        d,
        &[
            "train", "scene", "--steps", "2", "--engine", "cpu", "--out", "run",
        ],
    );
    succeed(
        d,
        &["render", "run", "--turntable", "2", "--out", "rendered"],
    );
    succeed(d, &["render", "run", "--view", "0", "--out", "rendered"]);
    colmap_scene(d, "colmap", |text| text);
    std::fs::write(d.join("existing.json"), "{\"mine\": true}").unwrap();
    // A Blender folder with held-out views only.
    std::fs::create_dir_all(d.join("noviews")).unwrap();
    std::fs::copy(
        d.join("scene/transforms_val.json"),
        d.join("noviews/transforms_val.json"),
    )
    .unwrap();
    copy_folder(&d.join("scene/val"), &d.join("noviews/val"));
    instant_ngp_variant(d, "far", |j| {
        j["offset"] = serde_json::json!([1e6, 1e6, 1e6])
    });
    instant_ngp_variant(d, "wide", |j| {
        j["camera_angle_x"] = serde_json::json!(std::f64::consts::PI * 0.99999)
    });
    instant_ngp_variant(d, "tiny-scale", |j| j["scale"] = serde_json::json!(1e-45));
    instant_ngp_variant(d, "huge-aabb", |j| {
        j["aabb_scale"] = serde_json::json!(40000)
    });
    instant_ngp_variant(d, "folding", |j| j["k1"] = serde_json::json!(-10.0));
    instant_ngp_variant(d, "folding-huge", |j| j["k1"] = serde_json::json!(1e30));
    instant_ngp_variant(d, "bom", |_| {});
    let text = std::fs::read(d.join("bom/transforms.json")).unwrap();
    let mut with_bom = vec![0xEF, 0xBB, 0xBF];
    with_bom.extend_from_slice(&text);
    std::fs::write(d.join("bom/transforms.json"), with_bom).unwrap();
    instant_ngp_variant(d, "utf16", |_| {});
    let text = std::fs::read_to_string(d.join("utf16/transforms.json")).unwrap();
    let mut utf16 = vec![0xFF, 0xFE];
    for unit in text.encode_utf16() {
        utf16.extend_from_slice(&unit.to_le_bytes());
    }
    std::fs::write(d.join("utf16/transforms.json"), utf16).unwrap();
    instant_ngp_variant(d, "folder-image", |_| {});
    std::fs::remove_file(d.join("folder-image/train/r_0.png")).unwrap();
    std::fs::create_dir(d.join("folder-image/train/r_0.png")).unwrap();
    std::fs::create_dir(d.join("pipe-json")).unwrap();
    make_fifo(&d.join("pipe-json/transforms.json"));
    make_fifo(&d.join("fifo"));
    std::os::unix::fs::symlink(d.join("gone"), d.join("dangling")).unwrap();
    std::os::unix::fs::symlink(d.join("loop"), d.join("loop")).unwrap();
    // A run whose checkpoint has one flipped bit in its parameters.
    copy_folder(&d.join("run"), &d.join("run-flipped"));
    let path = d.join("run-flipped/checkpoint.zrak");
    let mut bytes = std::fs::read(&path).unwrap();
    let header_length = u64::from_le_bytes(bytes[12..20].try_into().unwrap()) as usize;
    bytes[20 + header_length + 4 + 1000] ^= 0x04;
    std::fs::write(&path, bytes).unwrap();
    // A run whose model diverged (written as a version 1 file: version 2
    // refuses to save it).
    copy_folder(&d.join("run"), &d.join("run-nan"));
    let mut checkpoint = Checkpoint::load(&d.join("run/checkpoint.zrak")).unwrap();
    checkpoint.tensors[0].1[0] = f32::NAN;
    assert_eq!(checkpoint.tensors[0].0, "params");
    let table = serde_json::json!({
        "header": checkpoint.header,
        "tensors": checkpoint.tensors.iter().map(|(n, v)| serde_json::json!([n, v.len()])).collect::<Vec<_>>(),
    });
    let header = serde_json::to_vec(&table).unwrap();
    let mut bytes = b"ZRAKCKPT".to_vec();
    bytes.extend_from_slice(&1u32.to_le_bytes());
    bytes.extend_from_slice(&(header.len() as u64).to_le_bytes());
    bytes.extend_from_slice(&header);
    for (_, values) in &checkpoint.tensors {
        for v in values {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
    }
    std::fs::write(d.join("run-nan/checkpoint.zrak"), bytes).unwrap();
}

/// A snapshot of every regular file under `dir` (path and bytes), to show
/// that refused commands changed nothing.
fn snapshot(dir: &Path) -> Vec<(std::path::PathBuf, Vec<u8>)> {
    let mut files = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(folder) = stack.pop() {
        for entry in std::fs::read_dir(&folder).unwrap() {
            let entry = entry.unwrap();
            let kind = entry.file_type().unwrap();
            if kind.is_dir() {
                stack.push(entry.path());
            } else if kind.is_file() && entry.file_name() != ".zrak.lock" {
                files.push((entry.path(), std::fs::read(entry.path()).unwrap()));
            }
        }
    }
    files.sort();
    files
}

#[test]
fn bad_input_is_refused_by_name_and_nothing_on_disk_is_lost() {
    let _cores = crate::common::shared();
    let dir = temp_dir();
    let d = dir.path();
    bad_input_fixture(d);
    let before = snapshot(d);
    let mut failures = Vec::new();
    for case in CASES {
        let output = run_in(d, case.args);
        let stderr = String::from_utf8_lossy(&output.stderr);
        let stdout = String::from_utf8_lossy(&output.stdout);
        let both = format!("{stdout}{stderr}");
        // Refusals end with status 1 (zrak's) or 2 (a usage error clap
        // reports), never by a signal.
        let status_ok = output.status.success() == case.succeeds
            && (case.succeeds || matches!(output.status.code(), Some(1 | 2)));
        let missing: Vec<&&str> = case.says.iter().filter(|s| !both.contains(**s)).collect();
        if !status_ok || !missing.is_empty() || both.contains("panicked") {
            failures.push(format!(
                "zrak {}: {} (expected {}), missing {missing:?}:\n{both}",
                case.args.join(" "),
                output.status,
                if case.succeeds {
                    "success"
                } else {
                    "status 1 or 2"
                }
            ));
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n\n"));
    // Refused commands wrote nothing over what was there (the accepted
    // eval wrote its own scores).
    let after: Vec<_> = snapshot(d)
        .into_iter()
        .filter(|(p, _)| !p.ends_with("run/eval_val_d2.json"))
        .collect();
    let changed: Vec<_> = before
        .iter()
        .filter(|(p, bytes)| !after.iter().any(|(q, b)| q == p && b == bytes))
        .map(|(p, _)| p.display().to_string())
        .collect();
    assert!(changed.is_empty(), "changed or removed: {changed:?}");
    let added: Vec<_> = after
        .iter()
        .filter(|(p, _)| !before.iter().any(|(q, _)| q == p))
        .map(|(p, _)| p.display().to_string())
        .collect();
    assert!(added.is_empty(), "left behind: {added:?}");
}

#[test]
fn force_moves_the_old_run_aside_and_never_deletes_it() {
    let _cores = crate::common::shared();
    let dir = temp_dir();
    let d = dir.path();
    succeed(
        d,
        &["demo", "--out", "scene", "--size", "16", "--views", "3"],
    );
    succeed(
        d,
        &[
            "train", "scene", "--steps", "2", "--engine", "cpu", "--out", "run",
        ],
    );
    succeed(d, &["eval", "run"]);
    let out = run_in(
        d,
        &[
            "train", "scene", "--steps", "1", "--engine", "cpu", "--out", "run", "--force",
        ],
    );
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    assert!(
        stderr.contains("moved the run that was in run aside to run.old"),
        "{stderr}"
    );
    assert_eq!(checkpoint_step(&d.join("run")), 1);
    assert_eq!(checkpoint_step(&d.join("run.old")), 2);
    // The old scores went with the model they describe.
    assert!(d.join("run.old/eval_val.json").is_file());
    assert!(!d.join("run/eval_val.json").exists());
    // Again: the next name.
    succeed(
        d,
        &[
            "train", "scene", "--steps", "3", "--engine", "cpu", "--out", "run", "--force",
        ],
    );
    assert_eq!(checkpoint_step(&d.join("run.old-2")), 1);
    assert_eq!(checkpoint_step(&d.join("run")), 3);
}

#[test]
fn a_resumed_log_is_cut_back_to_the_checkpoint() {
    let _cores = crate::common::shared();
    let dir = temp_dir();
    let d = dir.path();
    succeed(
        d,
        &["demo", "--out", "scene", "--size", "16", "--views", "3"],
    );
    succeed(
        d,
        &[
            "train", "scene", "--steps", "20", "--engine", "cpu", "--out", "run",
        ],
    );
    // Lines logged after the last checkpoint by a run that was then killed.
    let metrics = d.join("run/metrics.jsonl");
    let mut text = std::fs::read_to_string(&metrics).unwrap();
    let last = text.lines().last().unwrap().to_string();
    text.push_str(&last.replace("\"step\":20", "\"step\":32"));
    text.push('\n');
    text.push_str("{\"step\":48,\"wall");
    std::fs::write(&metrics, text).unwrap();
    let out = run_in(d, &["train", "--resume", "run", "--steps", "24"]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    assert!(
        stderr.contains("dropped 2 lines logged after the checkpoint's step 20"),
        "{stderr}"
    );
    let steps: Vec<u64> = metrics_lines(&d.join("run"))
        .iter()
        .map(|l| l["step"].as_u64().unwrap())
        .collect();
    assert!(steps.windows(2).all(|w| w[0] < w[1]), "{steps:?}");
    assert_eq!(steps.last(), Some(&24));
}

#[test]
fn a_colmap_images_txt_without_point_lines_loads_every_image() {
    let _cores = crate::common::shared();
    let dir = temp_dir();
    let d = dir.path();
    colmap_scene(d, "with-points", |text| text);
    colmap_scene(d, "without-points", |text| {
        text.lines()
            .filter(|l| !l.trim().is_empty())
            .map(|l| format!("{l}\n"))
            .collect()
    });
    let with = frames_in_info(&succeed(d, &["info", "with-points"]));
    let without = frames_in_info(&succeed(d, &["info", "without-points"]));
    assert_eq!(with, 9);
    assert_eq!(without, 9);
}

#[test]
fn a_refused_bench_quality_leaves_nothing_that_blocks_its_corrected_run() {
    let _cores = crate::common::shared();
    let dir = temp_dir();
    let d = dir.path();
    succeed(
        d,
        &["demo", "--out", "scene", "--size", "16", "--views", "3"],
    );
    let error = fail(
        d,
        &[
            "bench",
            "quality",
            "scene",
            "--eval-downscale",
            "64",
            "--engine",
            "cpu",
            "--out",
            "q",
        ],
    );
    assert!(error.contains("--eval-downscale 64"), "{error}");
    assert!(!d.join("q/experiment.json").exists());
    let mut args = vec![
        "bench",
        "quality",
        "scene",
        "--models",
        "ngp",
        "--budget",
        "0.2s",
        "--out",
        "q",
        "--eval-downscale",
        "1",
        "--every",
        "1",
        "--engine",
        "cpu",
        "--split",
        "val",
        "--batch-samples",
        "1024",
    ];
    succeed(d, &args);
    assert!(d.join("q/experiment.json").is_file());
    // The same folder under other settings is still refused by name.
    args[6] = "0.3s";
    let error = fail(d, &args);
    assert!(
        error.contains("holds an experiment with other settings"),
        "{error}"
    );
}

/// `zrak ARGS` with its standard output on /dev/full.
fn with_full_stdout(dir: &Path, args: &[&str]) -> Output {
    let full = std::fs::OpenOptions::new()
        .write(true)
        .open("/dev/full")
        .expect("/dev/full");
    zrak()
        .args(args)
        .current_dir(dir)
        .stdin(Stdio::null())
        .stdout(full)
        .stderr(Stdio::piped())
        .output()
        .expect("the zrak binary starts")
}

#[test]
fn a_full_standard_output_is_an_error_not_a_panic() {
    let _cores = crate::common::shared();
    let dir = temp_dir();
    let d = dir.path();
    succeed(
        d,
        &["demo", "--out", "scene", "--size", "16", "--views", "3"],
    );
    succeed(
        d,
        &[
            "train", "scene", "--steps", "2", "--engine", "cpu", "--out", "run",
        ],
    );
    colmap_scene(d, "colmap", |text| text);
    for args in [
        &["info", "scene"][..],
        &["eval", "run"],
        &["demo", "--out", "demo2", "--size", "16", "--views", "2"],
        &["convert", "colmap", "--out", "converted.json"],
        &["render", "run", "--view", "0", "--out", "frames"],
        &[
            "bench",
            "throughput",
            "--scene",
            "scene",
            "--warmup",
            "0",
            "--steps",
            "1",
            "--engine",
            "cpu",
        ],
        &[
            "train", "scene", "--steps", "1", "--engine", "cpu", "--out", "run2",
        ],
        &["--help"],
        &["train", "--help"],
        &["--version"],
    ] {
        let output = with_full_stdout(d, args);
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert_eq!(output.status.code(), Some(1), "zrak {args:?}: {stderr}");
        assert!(
            stderr.contains("cannot write to standard output: No space left on device"),
            "zrak {args:?}: {stderr}"
        );
        assert!(!stderr.contains("panicked"), "zrak {args:?}: {stderr}");
    }
    // Their files were written all the same.
    assert_eq!(checkpoint_step(&d.join("run2")), 1);
    assert!(d.join("converted.json").is_file());
    assert!(d.join("frames/val_000.png").is_file());
}

/// A small tmpfs mounted for a test, unmounted when dropped.
struct SmallDisk(std::path::PathBuf);

impl SmallDisk {
    /// Mounts a tmpfs of `bytes` at `at`, where the machine allows it
    /// (root, a kernel that lets this container mount): `None` otherwise.
    fn mount(at: &Path, bytes: usize) -> Option<Self> {
        std::fs::create_dir_all(at).unwrap();
        let status = Command::new("mount")
            .args(["-t", "tmpfs", "-o", &format!("size={bytes}"), "tmpfs"])
            .arg(at)
            .stderr(Stdio::null())
            .status()
            .ok()?;
        status.success().then(|| Self(at.to_path_buf()))
    }
}

impl Drop for SmallDisk {
    fn drop(&mut self) {
        let _ = Command::new("umount").arg(&self.0).status();
    }
}

/// Fills the file system holding `folder` to the last byte.
fn fill_disk(folder: &Path) {
    use std::io::Write;
    let mut filler = std::fs::File::create(folder.join("filler")).unwrap();
    let block = vec![0u8; 4096];
    while filler.write_all(&block).is_ok() {}
    while filler.write_all(&block[..1]).is_ok() {}
}

/// On a full disk a write fails with the reason and leaves the file that
/// was there whole (convert once left a user's transforms.json cut off
/// at 4 KiB).
#[test]
fn a_full_disk_never_cuts_a_file_short() {
    let _cores = crate::common::shared();
    let dir = temp_dir();
    let d = dir.path();
    let Some(_disk) = SmallDisk::mount(&d.join("full"), 256 * 1024) else {
        eprintln!("skipped: this machine does not let the test mount a tmpfs");
        return;
    };
    colmap_scene(d, "colmap", |text| text);
    let old = format!("{{\"mine\": \"{}\"}}", "x".repeat(6000));
    let transforms = d.join("full/transforms.json");
    std::fs::write(&transforms, &old).unwrap();
    fill_disk(&d.join("full"));
    let error = fail(
        d,
        &[
            "convert",
            "colmap",
            "--out",
            "full/transforms.json",
            "--force",
        ],
    );
    assert!(
        error.contains("full/transforms.json") && error.contains("No space left on device"),
        "{error}"
    );
    assert_eq!(std::fs::read_to_string(&transforms).unwrap(), old);
    let mut left: Vec<String> = std::fs::read_dir(d.join("full"))
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    left.sort();
    assert_eq!(
        left,
        ["filler", "transforms.json"],
        "a temporary file was left"
    );
}
