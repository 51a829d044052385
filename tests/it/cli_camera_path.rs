//! `zrak render RUN --camera-path FILE` as a user runs it, on a run of the
//! tiny demo scene: PNG frames, a range of them, continuing an interrupted
//! render, the file's crop block, the MP4 video checked with an independent decoder (FFmpeg's
//! `ffprobe` and `ffmpeg`, from Debian's `ffmpeg` package, which `.ci/run`
//! installs), and bad path files refused by name.

use crate::common;

use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

use glam::DVec3;
use zrak::render::camera_path::crop_block::PathCrop;
use zrak::render::camera_path::nerfstudio::CameraPathFile;
use zrak::render::camera_path::{CameraPath, Keyframe, look_at};
use zrak::scene::crop::CropBox;

fn run_in(dir: &Path, program: &Path, args: &[&str]) -> Output {
    Command::new(program)
        .args(args)
        .current_dir(dir)
        .stdin(Stdio::null())
        .output()
        .unwrap_or_else(|e| panic!("{} starts: {e}", program.display()))
}

fn succeed(dir: &Path, args: &[&str]) -> String {
    let output = run_in(dir, &common::zrak_bin(), args);
    assert!(
        output.status.success(),
        "zrak {} failed ({}):\nstdout:\n{}\nstderr:\n{}",
        args.join(" "),
        output.status,
        String::from_utf8_lossy(&output.stdout),
        String::from_utf8_lossy(&output.stderr)
    );
    String::from_utf8_lossy(&output.stdout).into_owned()
}

fn fail(dir: &Path, args: &[&str]) -> String {
    let output = run_in(dir, &common::zrak_bin(), args);
    assert!(
        !output.status.success(),
        "zrak {} should have failed:\n{}",
        args.join(" "),
        String::from_utf8_lossy(&output.stdout)
    );
    let stderr = String::from_utf8_lossy(&output.stderr).into_owned();
    assert!(!stderr.contains("panicked"), "{stderr}");
    stderr
}

/// FFmpeg's tools, which the test needs: Debian's `ffmpeg` package.
fn ffmpeg_tool(name: &str) -> PathBuf {
    let path = PathBuf::from("/usr/bin").join(name);
    assert!(
        path.is_file(),
        "{} not found: the video test decodes with FFmpeg, an independent decoder; install \
         Debian's ffmpeg package (apt-get install ffmpeg), as .ci/run does",
        path.display()
    );
    path
}

/// A trained run of the demo scene (32 × 32 views) in `d/run`: 60 cpu
/// steps, enough that its renders show the scene's objects rather than a
/// uniform haze.
fn trained_run(d: &Path) {
    succeed(
        d,
        &["demo", "--out", "scene", "--size", "32", "--views", "10"],
    );
    succeed(
        d,
        &[
            "train", "scene", "--model", "ngp", "--steps", "60", "--engine", "cpu", "--out", "run",
        ],
    );
}

/// Four keyframes round the demo's objects (they sit about the origin, the
/// cameras about 4 units away with +z up), the last moving in closer with a
/// wider view; 0.5 s between keyframes.
fn four_keyframe_path() -> CameraPath {
    let at = |eye: DVec3, fov: f64| Keyframe::new(look_at(eye, DVec3::ZERO, DVec3::Z), fov);
    let mut path = CameraPath::new(vec![
        at(DVec3::new(4.0, 0.0, 1.5), 40.0),
        at(DVec3::new(0.0, 4.0, 2.0), 40.0),
        at(DVec3::new(-3.5, 0.5, 1.0), 45.0),
        at(DVec3::new(0.5, -3.0, 1.5), 50.0),
    ]);
    path.default_transition_seconds = 0.5;
    path
}

/// The path file, baked at 8 frames a second: 12 frames of 32 × 24.
fn write_path_file(d: &Path) -> CameraPathFile {
    let file = CameraPathFile::new(four_keyframe_path(), 32, 24, 8.0, glam::DMat4::IDENTITY);
    file.save(&d.join("path.json")).unwrap();
    file
}

fn frame(dir: &Path, index: usize) -> PathBuf {
    dir.join(format!("frame_{index:05}.png"))
}

fn rgb(path: &Path) -> image::RgbImage {
    image::open(path)
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
        .to_rgb8()
}

#[test]
fn frames_ranges_and_continuing_where_a_render_stopped() {
    let _cores = crate::common::shared();
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    trained_run(d);
    write_path_file(d);
    let out = succeed(
        d,
        &[
            "render",
            "run",
            "--camera-path",
            "path.json",
            "--out",
            "frames",
        ],
    );
    assert!(
        out.contains("wrote 12 frames to frames (12 rendered in"),
        "{out}"
    );
    for i in 0..12 {
        let image = rgb(&frame(&d.join("frames"), i));
        assert_eq!(image.dimensions(), (32, 24), "frame {i}");
    }
    assert!(!frame(&d.join("frames"), 12).exists());
    // The frames differ along the path (the camera moves), and they are
    // not blank.
    let (a, b) = (
        rgb(&frame(&d.join("frames"), 0)),
        rgb(&frame(&d.join("frames"), 6)),
    );
    assert_ne!(a, b);
    // A range renders those frames of the same path, bit for bit.
    succeed(
        d,
        &[
            "render",
            "run",
            "--camera-path",
            "path.json",
            "--frames",
            "3..5",
            "--out",
            "part",
        ],
    );
    assert_eq!(
        rgb(&frame(&d.join("part"), 3)),
        rgb(&frame(&d.join("frames"), 3))
    );
    assert_eq!(
        rgb(&frame(&d.join("part"), 4)),
        rgb(&frame(&d.join("frames"), 4))
    );
    assert!(!frame(&d.join("part"), 2).exists() && !frame(&d.join("part"), 5).exists());

    // Continuing: frames on disk are kept, missing ones rendered.
    let kept = frame(&d.join("frames"), 5);
    let kept_time = std::fs::metadata(&kept).unwrap().modified().unwrap();
    let reference = std::fs::read(frame(&d.join("frames"), 2)).unwrap();
    std::fs::remove_file(frame(&d.join("frames"), 2)).unwrap();
    std::fs::remove_file(frame(&d.join("frames"), 9)).unwrap();
    let out = succeed(
        d,
        &[
            "render",
            "run",
            "--camera-path",
            "path.json",
            "--out",
            "frames",
        ],
    );
    assert!(
        out.contains("(2 rendered in") && out.contains("10 already there"),
        "{out}"
    );
    assert_eq!(
        std::fs::read(frame(&d.join("frames"), 2)).unwrap(),
        reference
    );
    assert_eq!(
        std::fs::metadata(&kept).unwrap().modified().unwrap(),
        kept_time
    );
    // Another mode into the same folder is refused, then replaced on
    // --force.
    let refusal = fail(
        d,
        &[
            "render",
            "run",
            "--camera-path",
            "path.json",
            "--mode",
            "depth",
            "--out",
            "frames",
        ],
    );
    assert!(
        refusal.contains("frames holds frames of another render"),
        "{refusal}"
    );
    let out = succeed(
        d,
        &[
            "render",
            "run",
            "--camera-path",
            "path.json",
            "--mode",
            "depth",
            "--out",
            "frames",
            "--force",
        ],
    );
    assert!(out.contains("(12 rendered in"), "{out}");
    let depth = rgb(&frame(&d.join("frames"), 0));
    assert!(
        depth.pixels().all(|p| p[0] == p[1] && p[1] == p[2]),
        "depth is grey"
    );

    // An interrupt stops between frames, says how to continue, and the same
    // command continues. 150 frames of 32 × 24 take long enough to catch.
    let long = tempfile::tempdir().unwrap();
    let args = [
        "render",
        "run",
        "--camera-path",
        "path.json",
        "--fps",
        "100",
        "--out",
    ];
    let long_out = long.path().join("long");
    let mut child = Command::new(common::zrak_bin())
        .args(args)
        .arg(&long_out)
        .current_dir(d)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let deadline = Instant::now() + Duration::from_secs(120);
    while !frame(&long_out, 0).exists() {
        assert!(Instant::now() < deadline, "no frame within 120 s");
        assert!(
            child.try_wait().unwrap().is_none(),
            "zrak ended before its first frame"
        );
        std::thread::sleep(Duration::from_millis(10));
    }
    common::send_signal(child.id(), libc::SIGINT);
    let output = common::finish(child, 60);
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(
        stderr.contains("interrupted after") && stderr.contains("run the same command again"),
        "{stderr}"
    );
    let done = (0..150).filter(|&i| frame(&long_out, i).exists()).count();
    assert!(
        (1..150).contains(&done),
        "{done} frames after the interrupt"
    );
    let out = succeed(d, &[&args[..], &[long_out.to_str().unwrap()]].concat());
    assert!(
        out.contains("wrote 150 frames") && out.contains(&format!("{done} already there")),
        "{out}"
    );

    // The file's crop block is honoured: a box far from the objects leaves
    // only the white background; an explicit --crop wins over it.
    let mut cropped = write_path_file(d);
    cropped.crop = Some(PathCrop::new(CropBox::axis_aligned(
        glam::Vec3::splat(30.0),
        glam::Vec3::splat(0.5),
    )));
    cropped.save(&d.join("cropped.json")).unwrap();
    let render_to = |out: &str, extra: &[&str]| {
        let args = [
            &[
                "render",
                "run",
                "--camera-path",
                "cropped.json",
                "--frames",
                "0..2",
                "--out",
                out,
            ][..],
            extra,
        ]
        .concat();
        succeed(d, &args);
        rgb(&frame(&d.join(out), 0))
    };
    let empty = render_to("cropped", &[]);
    assert!(empty.pixels().all(|p| p.0 == [255; 3]), "only background");
    let whole = render_to("uncropped", &["--crop", "none"]);
    let shown = whole.pixels().filter(|p| p.0 != [255; 3]).count();
    assert!(shown > 32 * 24 / 10, "{shown} pixels show the objects");
}

/// Mean absolute difference per channel, in levels of 255.
fn mean_absolute_error(a: &image::RgbImage, b: &image::RgbImage) -> f64 {
    assert_eq!(a.dimensions(), b.dimensions());
    let sum: u64 = a
        .as_raw()
        .iter()
        .zip(b.as_raw())
        .map(|(&x, &y)| x.abs_diff(y) as u64)
        .sum();
    sum as f64 / a.as_raw().len() as f64
}

/// Bound on the mean absolute error per channel between a decoded video
/// frame and its PNG, in levels of 255 (2.4 %): H.264 at the encoder's
/// rate for a 64 × 48 frame (quantiser up to 36), 4:2:0 chroma (colour at
/// half resolution, which blurs the colour edges of so small a frame) and
/// BT.601 studio swing (8-bit RGB through 220 luma levels, truncated by the
/// encoder's conversion). Measured 3.4 to 4.3 on these frames; a frame of
/// another frame is further off (checked below).
const VIDEO_MAE_BOUND: f64 = 6.0;

#[test]
fn a_video_decodes_with_ffmpeg_to_the_frames_it_was_made_of() {
    let _cores = crate::common::shared();
    let ffprobe = ffmpeg_tool("ffprobe");
    let ffmpeg = ffmpeg_tool("ffmpeg");
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    trained_run(d);
    write_path_file(d);
    let out = succeed(
        d,
        &[
            "render",
            "run",
            "--camera-path",
            "path.json",
            "--size",
            "64x48",
            "--out",
            "video.mp4",
            "--keep-frames",
        ],
    );
    assert!(
        out.contains("wrote video.mp4: 12 frames, 64×48, 8 frames a second"),
        "{out}"
    );
    assert!(d.join("video.frames").is_dir());
    let probe = run_in(
        d,
        &ffprobe,
        &[
            "-v",
            "error",
            "-count_frames",
            "-select_streams",
            "v:0",
            "-show_entries",
            "stream=codec_name,width,height,r_frame_rate,nb_read_frames",
            "-of",
            "json",
            "video.mp4",
        ],
    );
    assert!(
        probe.status.success(),
        "{}",
        String::from_utf8_lossy(&probe.stderr)
    );
    let json: serde_json::Value = serde_json::from_slice(&probe.stdout).unwrap();
    let stream = &json["streams"][0];
    assert_eq!(stream["codec_name"], "h264", "{json}");
    assert_eq!(
        (stream["width"].as_u64(), stream["height"].as_u64()),
        (Some(64), Some(48))
    );
    assert_eq!(stream["r_frame_rate"], "8/1", "{json}");
    assert_eq!(stream["nb_read_frames"], "12", "{json}");
    // Every decoded frame matches the PNG of the same frame.
    let decoded = d.join("decoded");
    std::fs::create_dir(&decoded).unwrap();
    let status = run_in(
        d,
        &ffmpeg,
        &["-v", "error", "-i", "video.mp4", "decoded/%03d.png"],
    );
    assert!(
        status.status.success(),
        "{}",
        String::from_utf8_lossy(&status.stderr)
    );
    let mut errors = Vec::new();
    for i in 0..12 {
        let video = rgb(&decoded.join(format!("{:03}.png", i + 1)));
        let png = rgb(&frame(&d.join("video.frames"), i));
        errors.push(mean_absolute_error(&video, &png));
    }
    assert!(!decoded.join("013.png").exists());
    let worst = errors.iter().cloned().fold(0.0, f64::max);
    assert!(
        worst < VIDEO_MAE_BOUND,
        "mean absolute error per channel of each frame: {errors:.2?}"
    );
    // The test can tell frames apart: frame 0 against frame 6's PNG is
    // far off.
    let other = mean_absolute_error(
        &rgb(&decoded.join("001.png")),
        &rgb(&frame(&d.join("video.frames"), 6)),
    );
    assert!(
        other > 2.0 * VIDEO_MAE_BOUND,
        "frames 0 and 6 differ by only {other:.2}"
    );
    eprintln!("video MAE per frame: {errors:.2?}; frame 0 vs 6: {other:.2}");

    // Without --keep-frames the frames go once the video is written, and
    // an existing video is not replaced without --force.
    let refusal = fail(
        d,
        &[
            "render",
            "run",
            "--camera-path",
            "path.json",
            "--size",
            "64x48",
            "--out",
            "video.mp4",
        ],
    );
    assert!(
        refusal.contains("video.mp4 already exists; give --force"),
        "{refusal}"
    );
    succeed(
        d,
        &[
            "render",
            "run",
            "--camera-path",
            "path.json",
            "--size",
            "64x48",
            "--out",
            "video.mp4",
            "--force",
        ],
    );
    assert!(!d.join("video.frames").exists());
    // An odd size cannot be H.264.
    let refusal = fail(
        d,
        &[
            "render",
            "run",
            "--camera-path",
            "path.json",
            "--out",
            "odd.mp4",
            "--size",
            "33x24",
        ],
    );
    assert!(refusal.contains("even width and height"), "{refusal}");
}

#[test]
fn bad_path_files_are_refused_by_name() {
    let _cores = crate::common::shared();
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    succeed(
        d,
        &["demo", "--out", "scene", "--size", "16", "--views", "3"],
    );
    succeed(
        d,
        &[
            "train", "scene", "--steps", "1", "--engine", "cpu", "--out", "run",
        ],
    );
    let text = write_path_file(d).to_text();
    let cases: [(&str, String, &str); 4] = [
        (
            "nan.json",
            text.replacen("\"fov\": 40.0", "\"fov\": NaN", 1),
            "nan.json: `camera_path[0].fov` is NaN",
        ),
        (
            "type.json",
            text.replace("\"perspective\"", "\"cylindrical\""),
            "type.json: `camera_type` \"cylindrical\" is not a camera type",
        ),
        (
            "empty.json",
            r#"{"keyframes": [], "camera_path": [], "render_width": 8, "render_height": 8, "fps": 24}"#
                .into(),
            "empty.json: the file has no frames",
        ),
        (
            "nosize.json",
            text.replace("\"render_width\"", "\"width\""),
            "nosize.json: missing field `render_width`",
        ),
    ];
    for (name, content, expected) in cases {
        std::fs::write(d.join(name), content).unwrap();
        let error = fail(d, &["render", "run", "--camera-path", name, "--out", "f"]);
        assert!(error.contains(expected), "{name}: {error}");
    }
    let error = fail(
        d,
        &[
            "render",
            "run",
            "--camera-path",
            "missing.json",
            "--out",
            "f",
        ],
    );
    assert!(error.contains("missing.json: not found"), "{error}");
    let error = fail(
        d,
        &[
            "render",
            "run",
            "--camera-path",
            "path.json",
            "--frames",
            "20..",
            "--out",
            "f",
        ],
    );
    assert!(error.contains("not within the path's 12 frames"), "{error}");
    let error = fail(
        d,
        &["render", "run", "--view", "0", "--fps", "30", "--out", "f"],
    );
    assert!(error.contains("--camera-path"), "{error}");
}
