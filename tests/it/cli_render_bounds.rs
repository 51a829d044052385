//! `zrak render` and `zrak export mesh` at their bounds (issue 43): a
//! render's record of its frames names the run, checkpoint and crop box;
//! outputs named like files are never made folders; frame files are
//! never written through a link; camera path files are bounded before
//! they are parsed; frame sizes beyond memory or the H.264 encoder are
//! refused before the first frame; an empty mesh says why.

use crate::common;

use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

use glam::DVec3;
use zrak::render::camera_path::nerfstudio::CameraPathFile;
use zrak::render::camera_path::{CameraPath, Keyframe, look_at};

fn run_in(dir: &Path, args: &[&str]) -> Output {
    Command::new(common::zrak_bin())
        .args(args)
        .current_dir(dir)
        .stdin(Stdio::null())
        .output()
        .expect("zrak starts")
}

fn succeed(dir: &Path, args: &[&str]) -> String {
    let output = run_in(dir, args);
    assert!(
        output.status.success(),
        "zrak {} failed ({}):\n{}",
        args.join(" "),
        output.status,
        String::from_utf8_lossy(&output.stderr)
    );
    String::from_utf8_lossy(&output.stdout).into_owned() + &String::from_utf8_lossy(&output.stderr)
}

/// The refusal's text; the exit is an error's (1), never a panic's (101)
/// or an abort's (134).
fn check_refused(output: &Output, args: &str) -> String {
    let stderr = String::from_utf8_lossy(&output.stderr).into_owned();
    assert_eq!(
        output.status.code(),
        Some(1),
        "zrak {args} should have been refused:\n{stderr}"
    );
    assert!(!stderr.contains("panicked"), "{stderr}");
    stderr
}

fn fail(dir: &Path, args: &[&str]) -> String {
    check_refused(&run_in(dir, args), &args.join(" "))
}

/// zrak under `ulimit -v` of `kib` KiB, as a shell with that limit runs it.
fn fail_under_ulimit(dir: &Path, kib: u64, args: &[&str]) -> String {
    let command = format!("ulimit -v {kib}; exec \"$0\" \"$@\"");
    let output = Command::new("sh")
        .arg("-c")
        .arg(command)
        .arg(common::zrak_bin())
        .args(args)
        .current_dir(dir)
        .stdin(Stdio::null())
        .output()
        .expect("sh starts");
    check_refused(&output, &args.join(" "))
}

/// The demo scene (16 × 16 views) and runs of it: `run` and `other`
/// (trained a step further, so its checkpoint differs).
fn runs(d: &Path) {
    succeed(
        d,
        &["demo", "--out", "scene", "--size", "16", "--views", "3"],
    );
    for (out, steps) in [("run", "1"), ("other", "2")] {
        succeed(
            d,
            &[
                "train", "scene", "--steps", steps, "--engine", "cpu", "--out", out,
            ],
        );
    }
}

/// Two keyframes a second apart at 4 frames a second: 4 frames of 16 × 12.
fn path_file() -> CameraPathFile {
    let at = |eye: DVec3| Keyframe::new(look_at(eye, DVec3::ZERO, DVec3::Z), 40.0);
    let path = CameraPath::new(vec![
        at(DVec3::new(4.0, 0.0, 1.5)),
        at(DVec3::new(0.0, 4.0, 2.0)),
    ]);
    CameraPathFile::new(path, 16, 12, 4.0, glam::DMat4::IDENTITY)
}

fn frame(dir: &Path, index: usize) -> PathBuf {
    dir.join(format!("frame_{index:05}.png"))
}

fn render_path(extra: &[&str]) -> Vec<String> {
    let mut args: Vec<String> = [
        "render",
        "run",
        "--camera-path",
        "path.json",
        "--out",
        "frames",
    ]
    .iter()
    .map(|s| s.to_string())
    .collect();
    args.extend(extra.iter().map(|s| s.to_string()));
    args
}

fn strs(args: &[String]) -> Vec<&str> {
    args.iter().map(String::as_str).collect()
}

#[test]
fn frames_of_another_checkpoint_or_crop_box_are_refused_and_force_removes_them() {
    let _cores = common::shared();
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    runs(d);
    path_file().save(&d.join("path.json")).unwrap();
    let out = succeed(d, &strs(&render_path(&[])));
    assert!(
        out.contains("wrote 4 frames to frames (4 rendered"),
        "{out}"
    );
    let record: serde_json::Value =
        serde_json::from_slice(&std::fs::read(d.join("frames/camera_path_render.json")).unwrap())
            .unwrap();
    assert!(
        record["weights"]
            .as_str()
            .unwrap()
            .starts_with("checkpoint CRC-32C "),
        "{record}"
    );

    // Another checkpoint of the same run: refused, naming the folder and
    // the fix; nothing is rendered into the folder.
    let checkpoint = d.join("run/checkpoint.zrak");
    let first = std::fs::read(&checkpoint).unwrap();
    std::fs::copy(d.join("other/checkpoint.zrak"), &checkpoint).unwrap();
    let before = std::fs::read(frame(&d.join("frames"), 0)).unwrap();
    let refusal = fail(d, &strs(&render_path(&[])));
    assert!(
        refusal.contains("frames holds frames of another render (another checkpoint")
            && refusal.contains("give --force"),
        "{refusal}"
    );
    assert_eq!(std::fs::read(frame(&d.join("frames"), 0)).unwrap(), before);

    // Another crop box, with the first checkpoint back.
    std::fs::write(&checkpoint, &first).unwrap();
    let refusal = fail(
        d,
        &strs(&render_path(&["--crop", "0,0,0,1,1,1", "--frames", "0..2"])),
    );
    assert!(refusal.contains("(another crop box"), "{refusal}");
    // (--crop saved the box in the run: remove it again.)
    succeed(d, &strs(&render_path(&["--crop", "none", "--frames", "0"])));

    // --force with another checkpoint renders the range again and removes
    // the other render's frames outside it.
    std::fs::copy(d.join("other/checkpoint.zrak"), &checkpoint).unwrap();
    let out = succeed(d, &strs(&render_path(&["--frames", "0..2", "--force"])));
    assert!(out.contains("(2 rendered"), "{out}");
    for i in 2..4 {
        assert!(!frame(&d.join("frames"), i).exists(), "frame {i} was kept");
    }
    // And now the rest continues that render.
    let out = succeed(d, &strs(&render_path(&[])));
    assert!(
        out.contains("(2 rendered") && out.contains("2 already there"),
        "{out}"
    );
}

#[test]
fn a_damaged_kept_frame_is_rendered_again_and_a_linked_one_replaced_not_followed() {
    let _cores = common::shared();
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    runs(d);
    path_file().save(&d.join("path.json")).unwrap();
    succeed(d, &strs(&render_path(&[])));
    let frames = d.join("frames");
    let whole = std::fs::read(frame(&frames, 2)).unwrap();
    std::fs::write(frame(&frames, 2), &whole[..whole.len() - 30]).unwrap();
    // Frame 3 is a link to a file outside the folder.
    std::fs::write(d.join("victim"), "keep me").unwrap();
    std::fs::remove_file(frame(&frames, 3)).unwrap();
    std::os::unix::fs::symlink(d.join("victim"), frame(&frames, 3)).unwrap();
    let out = succeed(d, &strs(&render_path(&[])));
    assert!(
        out.contains("(2 rendered") && out.contains("2 already there"),
        "{out}"
    );
    assert_eq!(std::fs::read(frame(&frames, 2)).unwrap(), whole);
    assert_eq!(
        std::fs::read_to_string(d.join("victim")).unwrap(),
        "keep me"
    );
    assert!(
        std::fs::symlink_metadata(frame(&frames, 3))
            .unwrap()
            .file_type()
            .is_file()
    );
}

#[test]
fn an_out_named_like_a_video_or_image_is_never_made_a_folder() {
    let _cores = common::shared();
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let refusal = fail(d, &["render", "run", "--turntable", "3", "--out", "tt.mp4"]);
    assert!(
        refusal.contains("--out tt.mp4: a turntable is written as PNG frames into a folder"),
        "{refusal}"
    );
    let refusal = fail(
        d,
        &["render", "run", "--camera-path", "p.json", "--out", "p.gif"],
    );
    assert!(
        refusal.contains(
            "--out p.gif: a camera path is rendered into a folder of PNG frames or an .mp4 video"
        ),
        "{refusal}"
    );
    assert!(!d.join("tt.mp4").exists() && !d.join("p.gif").exists());
}

#[test]
fn camera_path_files_are_bounded_before_parsing_and_their_rates_named() {
    let _cores = common::shared();
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let baked = |frames: usize| {
        let one =
            r#"{"camera_to_world":[1,0,0,0,0,1,0,0,0,0,1,4,0,0,0,1],"fov":50,"aspect":1.333333},"#;
        let mut text = String::with_capacity(one.len() * frames + 100);
        text.push_str(r#"{"render_width":16,"render_height":12,"fps":24,"camera_path":["#);
        for _ in 0..frames {
            text.push_str(one);
        }
        text.pop();
        text.push_str("]}");
        text
    };
    // A million frames (81 MB): refused at once by the file's size; 200000
    // (16 MB) at once by their count. The run need not exist: the file is read
    // first.
    std::fs::write(d.join("million.json"), baked(1_000_000)).unwrap();
    std::fs::write(d.join("many.json"), baked(200_000)).unwrap();
    for (name, says) in [
        ("million.json", "million.json: 81.0 MB, more than"),
        (
            "many.json",
            "many.json: `camera_path` has 200000 frames, more than the 100000",
        ),
    ] {
        let started = Instant::now();
        let refusal = fail(d, &["render", "run", "--camera-path", name, "--out", "f"]);
        assert!(refusal.contains(says), "{refusal}");
        assert!(
            started.elapsed() < Duration::from_secs(3),
            "{name} took {:?}",
            started.elapsed()
        );
    }
    let million = fail(
        d,
        &[
            "render",
            "run",
            "--camera-path",
            "million.json",
            "--out",
            "f",
        ],
    );
    assert!(
        million.contains("more than the 64.0 MB a camera path can be"),
        "{million}"
    );

    // Rates: a frame rate of 1e9, and seconds of 0 with no fps.
    let text = path_file().to_text();
    let mut value: serde_json::Value = serde_json::from_str(&text).unwrap();
    value["fps"] = serde_json::json!(1e9);
    std::fs::write(d.join("fast.json"), value.to_string()).unwrap();
    value.as_object_mut().unwrap().remove("fps");
    value["seconds"] = serde_json::json!(0);
    std::fs::write(d.join("instant.json"), value.to_string()).unwrap();
    let refusal = fail(
        d,
        &["render", "run", "--camera-path", "fast.json", "--out", "f"],
    );
    assert!(
        refusal.contains("fast.json: `fps` must be a frame rate above 0 and at most 240"),
        "{refusal}"
    );
    let refusal = fail(
        d,
        &[
            "render",
            "run",
            "--camera-path",
            "instant.json",
            "--out",
            "f",
        ],
    );
    assert!(
        refusal.contains("instant.json: `seconds` is 0 and there is no `fps`"),
        "{refusal}"
    );

    // A byte order mark is no error: the file reads, and only the missing
    // run stops the render.
    std::fs::write(d.join("bom.json"), format!("\u{feff}{text}")).unwrap();
    let refusal = fail(
        d,
        &["render", "run", "--camera-path", "bom.json", "--out", "f"],
    );
    assert!(
        !refusal.contains("bom.json") && refusal.contains("run"),
        "{refusal}"
    );
}

#[test]
fn sizes_beyond_memory_or_the_encoder_are_refused_before_the_first_frame() {
    let _cores = common::shared();
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    path_file().save(&d.join("path.json")).unwrap();
    // Under a 4 GB address space: refused with the size named, exit 1.
    let refusal = fail_under_ulimit(
        d,
        4_000_000,
        &[
            "render",
            "run",
            "--camera-path",
            "path.json",
            "--size",
            "16384x16384",
            "--out",
            "f",
        ],
    );
    assert!(
        refusal.contains("a 16384×16384 frame needs about")
            && refusal.contains("give a smaller --size"),
        "{refusal}"
    );
    let refusal = fail_under_ulimit(
        d,
        4_000_000,
        &[
            "render",
            "run",
            "--turntable",
            "1",
            "--size",
            "16384",
            "--gif",
            "--out",
            "t",
        ],
    );
    assert!(
        refusal.contains("a 16384×16384 frame needs about"),
        "{refusal}"
    );
    // Beyond what OpenH264 encodes: refused before the run loads.
    let refusal = fail(
        d,
        &[
            "render",
            "run",
            "--camera-path",
            "path.json",
            "--size",
            "4096x2160",
            "--out",
            "v.mp4",
        ],
    );
    assert!(
        refusal.contains("up to 3840×2160") && refusal.contains("got 4096×2160"),
        "{refusal}"
    );
    assert!(!d.join("v.frames").exists() && !d.join("f").exists());
}

#[test]
fn a_mesh_emptied_by_min_component_names_the_pieces_it_removed() {
    let _cores = common::shared();
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    runs(d);
    // A threshold below every density closes the surface along the box:
    // one piece, which no piece of a thousand million faces leaves.
    let out = succeed(
        d,
        &[
            "export",
            "mesh",
            "run",
            "--resolution",
            "8",
            "--threshold",
            "0.0000001",
            "--min-component",
            "1000000000",
            "--out",
            "m.ply",
        ],
    );
    assert!(
        out.contains("the mesh is empty: --min-component 1000000000 removed all")
            && out.contains("give a --min-component of")
            && !out.contains("lower --threshold"),
        "{out}"
    );
}
