//! `zrak render`: a trained run's views, a turntable around its scene
//! (PNG files and a GIF), or a camera path (PNG files or an MP4 video, see
//! [`path`]).

mod path;

use std::path::PathBuf;

use anyhow::{Context, bail};
use clap::Args;
use indicatif::ProgressBar;
use zrak::engine::EngineKind;
use zrak::interrupt::{
    note, {self},
};
use zrak::model::RenderMode;
use zrak::model::pixels::{render_pixels, to_image};
use zrak::render::camera_path::frames::RenderSource;
use zrak::render::export::{ExportSettings, export_turntable};
use zrak::render::path::Turntable;
use zrak::scene::{Camera, Split};
use zrak::train::run::RunFolder;

use super::MAX_IMAGE_SIDE;
use super::run_config::restore_run;
use zrak::render::camera_path::export::{file_ending, is_video};
use zrak::render::camera_path::video::{encoder_memory_bytes, size_problem};
use zrak::render::{frame_memory_bytes, gif_memory_bytes};

#[derive(Args, Debug)]
pub struct RenderArgs {
    /// The run folder written by `zrak train`.
    run: PathBuf,
    /// Render the camera of this view of `--split`.
    #[arg(long, conflicts_with_all = ["turntable", "camera_path"])]
    view: Option<usize>,
    #[arg(long, value_enum, default_value_t = Split::Val)]
    split: Split,
    /// Render a turntable of this many frames.
    #[arg(long, conflicts_with = "camera_path")]
    turntable: Option<usize>,
    /// Render along this camera path (nerfstudio's camera_path.json); --out
    /// is a folder for PNG frames, or a file ending in .mp4 for a video.
    /// The file's crop box (its `crop` block) is used unless --crop is
    /// given: an explicit --crop wins.
    #[arg(long)]
    camera_path: Option<PathBuf>,
    /// Camera path: frames a second (default: the file's; another rate
    /// bakes the file's keyframes again).
    #[arg(long, requires = "camera_path")]
    fps: Option<f64>,
    /// Camera path: render only frames A..B (B excluded), A.. or one frame.
    #[arg(long, requires = "camera_path", value_parser = path::parse_frame_range)]
    frames: Option<path::FrameRange>,
    /// Camera path: keep a video's PNG frames (in NAME.frames/ beside it).
    #[arg(long, requires = "camera_path")]
    keep_frames: bool,
    /// Turntable elevation in degrees.
    #[arg(long, default_value_t = 30.0)]
    elevation: f32,
    /// Turntable radius (default: the training cameras' mean distance).
    #[arg(long)]
    radius: Option<f32>,
    /// Image size in pixels, N (square) or WxH (default: the training
    /// images', or the camera path file's).
    #[arg(long, value_parser = parse_size)]
    size: Option<ImageSize>,
    /// Also write the turntable as an animated GIF (`turntable.gif`).
    #[arg(long, conflicts_with = "camera_path")]
    gif: bool,
    #[arg(long, value_enum, default_value_t = RenderMode::Rgb)]
    mode: RenderMode,
    /// Output folder (created if missing; images already there are kept
    /// unless --force); for --camera-path, a file ending in .mp4 instead
    /// makes a video.
    #[arg(long)]
    out: PathBuf,
    #[arg(long, value_enum)]
    engine: Option<EngineKind>,
    /// Replace images of the same names already in --out.
    #[arg(long)]
    force: bool,
    #[command(flatten)]
    crop: super::export::CropArgs,
}

/// An image size on the command line.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ImageSize {
    pub width: u32,
    pub height: u32,
}

/// `N` (square) or `WxH`.
fn parse_size(text: &str) -> Result<ImageSize, String> {
    let number = |s: &str| {
        s.trim()
            .parse::<u32>()
            .map_err(|_| format!("`{text}` is not a size like 512 or 1280x720"))
    };
    match text.split_once(['x', 'X', '×']) {
        Some((w, h)) => Ok(ImageSize {
            width: number(w)?,
            height: number(h)?,
        }),
        None => {
            let side = number(text)?;
            Ok(ImageSize {
                width: side,
                height: side,
            })
        }
    }
}

/// The largest turntable: 10⁵ frames (over an hour of video at 25 frames a
/// second); the frames' cameras are placed up front.
const MAX_TURNTABLE_FRAMES: usize = 100_000;

impl RenderArgs {
    /// The turntable these arguments ask for, if any.
    fn turntable_settings(&self, frames: usize) -> ExportSettings {
        ExportSettings {
            turntable: Turntable {
                frames,
                elevation_degrees: self.elevation,
                radius: self.radius,
                size: self.size.map(|s| (s.width, s.height)),
            },
            mode: self.mode,
            out_dir: self.out.clone(),
            write_gif: self.gif,
            // Existing files were refused before the run loaded, unless
            // --force asked to replace them.
            replace_existing: true,
        }
    }

    /// The files this render writes, as far as they are known before the
    /// run loads.
    fn outputs(&self) -> Vec<PathBuf> {
        match (self.view, self.turntable) {
            (Some(view), None) => vec![
                self.out
                    .join(format!("{}_{view:03}.png", self.split.name())),
            ],
            (None, Some(frames)) => {
                let settings = self.turntable_settings(frames);
                let mut paths: Vec<PathBuf> = (0..frames).map(|i| settings.frame_path(i)).collect();
                if self.gif {
                    paths.push(settings.gif_path());
                }
                paths
            }
            _ => Vec::new(),
        }
    }
}

/// Refuses render settings that could never finish or would abort on an
/// allocation, before the run loads; then images of the same names in
/// --out, unless --force.
fn check_render_args(args: &RenderArgs) -> anyhow::Result<()> {
    if let Some(frames) = args.turntable {
        anyhow::ensure!(
            (1..=MAX_TURNTABLE_FRAMES).contains(&frames),
            "--turntable must be 1 to {MAX_TURNTABLE_FRAMES} frames, got {frames}"
        );
    }
    if let Some(ImageSize { width, height }) = args.size {
        for side in [width, height] {
            anyhow::ensure!(
                (1..=MAX_IMAGE_SIDE).contains(&side),
                "--size must be 1 to {MAX_IMAGE_SIDE} pixels, got {side}"
            );
        }
        let video = args.camera_path.is_some() && is_video(&args.out);
        if video && let Some(problem) = size_problem(width, height) {
            bail!(
                "--size {width}x{height} for {}: {problem}",
                args.out.display()
            );
        }
        check_frame_memory(width, height, args.gif, video)?;
    }
    if let Some(ending) = file_ending(&args.out) {
        match (&args.camera_path, args.turntable) {
            (Some(_), _) if ending == "mp4" => {}
            (Some(_), _) => bail!(
                "--out {}: a camera path is rendered into a folder of PNG frames or an .mp4 \
                 video, not a .{ending} file; give a folder or a file ending in .mp4",
                args.out.display()
            ),
            (None, Some(_)) => bail!(
                "--out {}: a turntable is written as PNG frames into a folder (and, with --gif, \
                 turntable.gif in it), not as a .{ending} file; give a folder for --out (for a \
                 video, render a camera path: --camera-path FILE --out NAME.mp4)",
                args.out.display()
            ),
            (None, None) => bail!(
                "--out {}: a view is written as a PNG file into a folder, not as a .{ending} \
                 file; give a folder for --out",
                args.out.display()
            ),
        }
    }
    // clap's `requires` lets these through without --camera-path (seen
    // with `--view 0 --fps 30`), so they are checked here.
    anyhow::ensure!(
        args.camera_path.is_some()
            || (args.fps.is_none() && args.frames.is_none() && !args.keep_frames),
        "--fps, --frames and --keep-frames go with --camera-path FILE"
    );
    if let Some(fps) = args.fps {
        anyhow::ensure!(
            fps.is_finite() && (1.0..=240.0).contains(&fps),
            "--fps must be 1 to 240 frames a second, got {fps}"
        );
    }
    anyhow::ensure!(
        args.elevation.is_finite(),
        "--elevation must be a number of degrees, got {}",
        args.elevation
    );
    if let Some(radius) = args.radius {
        anyhow::ensure!(
            radius.is_finite() && radius > 0.0,
            "--radius must be a positive distance, got {radius}"
        );
    }
    if args.force {
        return Ok(());
    }
    let outputs = args.outputs();
    let existing: Vec<&PathBuf> = outputs
        .iter()
        .filter(|p| zrak::files::exists_at_all(p))
        .collect();
    if let Some(first) = existing.first() {
        bail!(
            "{} already exists{}; give --force to replace this render's files, or another --out",
            first.display(),
            match existing.len() {
                1 => String::new(),
                n => format!(" (and {} more of the files this render writes)", n - 1),
            }
        );
    }
    Ok(())
}

/// Refuses a frame size whose render (with the GIF's or the video
/// encoder's share) would not fit in the memory this process has left.
fn check_frame_memory(width: u32, height: u32, gif: bool, video: bool) -> anyhow::Result<()> {
    let bytes = frame_memory_bytes(width, height)
        + if gif {
            gif_memory_bytes(width, height)
        } else {
            0
        }
        + if video {
            encoder_memory_bytes(width, height)
        } else {
            0
        };
    zrak::files::check_memory(&format!("a {width}×{height} frame"), bytes)
        .map_err(|problem| anyhow::anyhow!("{problem}; give a smaller --size"))
}

/// The run's weights as a render's record names them: the CRC-32C of its
/// checkpoint file (read again after loading; a few hundred MB a second
/// where the processor computes CRC-32C).
fn checkpoint_identity(folder: &RunFolder) -> anyhow::Result<String> {
    use std::io::Read;
    let path = folder.checkpoint_path();
    let (mut file, _) = zrak::files::open_regular(&path)
        .map_err(|problem| anyhow::anyhow!("{}: {problem}", path.display()))?;
    let mut crc = zrak::crc32c::Crc32c::new();
    let mut buffer = vec![0u8; 1 << 20];
    loop {
        let n = file
            .read(&mut buffer)
            .with_context(|| format!("{}: cannot read", path.display()))?;
        if n == 0 {
            break;
        }
        crc.update(&buffer[..n]);
    }
    Ok(format!("checkpoint CRC-32C {:08x}", crc.finish()))
}

pub fn render(args: RenderArgs) -> anyhow::Result<()> {
    check_render_args(&args)?;
    let path_file = args
        .camera_path
        .as_deref()
        .map(path::read_path_file)
        .transpose()?;
    let folder = RunFolder::open(&args.run).map_err(anyhow::Error::msg)?;
    let (config, mut trainer) = restore_run(&folder, args.engine, None)?;
    if let (Some(file_path), Some(file)) = (&args.camera_path, &path_file) {
        let file = path::move_into_scene(file, &trainer.scene)?;
        // The path file's own crop box, unless --crop says otherwise.
        let crop = match (&args.crop.crop, &file.crop) {
            (None, Some(block)) => {
                note(&format!(
                    "using the crop box of {} (--crop overrides it)",
                    file_path.display()
                ));
                Some(block.crop)
            }
            _ => args.crop.resolve(&args.run)?,
        };
        trainer.model.set_crop(crop).map_err(anyhow::Error::msg)?;
        let source = RenderSource {
            run: std::fs::canonicalize(&args.run)
                .unwrap_or_else(|_| args.run.clone())
                .display()
                .to_string(),
            weights: checkpoint_identity(&folder)?,
            model: config.model.name().to_string(),
            crop,
        };
        let scene = &trainer.scene;
        return path::render_camera_path(
            &args,
            &file,
            file_path,
            trainer.model.as_ref(),
            scene,
            source,
        );
    }
    let crop = args.crop.resolve(&args.run)?;
    trainer.model.set_crop(crop).map_err(anyhow::Error::msg)?;
    let scene = &trainer.scene;
    // Again now that the run's model takes its share of memory.
    if let Some((width, height)) = args
        .size
        .map(|s| (s.width, s.height))
        .or_else(|| scene.resolution())
    {
        check_frame_memory(width, height, args.gif, false)?;
    }
    let cameras: Vec<(String, Camera)> = match (args.view, args.turntable) {
        (Some(view), None) => {
            anyhow::ensure!(!args.gif, "--gif goes with --turntable FRAMES, not --view");
            let frames = scene.split(args.split);
            let frame = frames.get(view).with_context(|| {
                format!(
                    "the {} split has {} views; there is no view {view}",
                    args.split.name(),
                    frames.len()
                )
            })?;
            vec![(format!("{}_{view:03}", args.split.name()), frame.camera)]
        }
        (None, Some(frames)) => {
            anyhow::ensure!(frames >= 1, "--turntable needs at least one frame");
            let bar = ProgressBar::new(frames as u64);
            let mut frames_done = 0;
            let exported = export_turntable(
                trainer.model.as_ref(),
                scene,
                args.turntable_settings(frames),
                interrupt::flag(),
                &mut |done, _| {
                    frames_done = done;
                    bar.set_position(done as u64);
                },
            );
            if interrupt::requested() {
                bar.abandon();
                note(&format!(
                    "interrupted after {frames_done} of {frames} frames; those are in {} \
                     (no GIF)",
                    args.out.display()
                ));
                return Ok(());
            }
            let written = exported.map_err(anyhow::Error::msg)?;
            bar.finish();
            println!("wrote {} files to {}", written.len(), args.out.display());
            return Ok(());
        }
        _ => bail!("give --view N, --turntable FRAMES or --camera-path FILE"),
    };
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("{}: cannot create the output folder", args.out.display()))?;
    let depth_range = scene.depth_range();
    let bar = ProgressBar::new(cameras.len() as u64);
    for (name, camera) in &cameras {
        let pixels = render_pixels(trainer.model.as_ref(), camera, [1.0; 3]);
        let k = camera.intrinsics;
        let image = to_image(&pixels, k.width, k.height, args.mode, depth_range);
        let path = args.out.join(format!("{name}.png"));
        image.save_png(&path)?;
        bar.inc(1);
    }
    bar.finish();
    println!("wrote {} images to {}", cameras.len(), args.out.display());
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cli::parse_args;
    use clap::error::ErrorKind;

    fn render_args(args: &[&str]) -> RenderArgs {
        parse_args(args).unwrap_or_else(|e| panic!("{args:?}: {e}"))
    }

    #[test]
    fn render_defaults() {
        let args = render_args(&["RUN", "--view", "0", "--out", "frames"]);
        assert_eq!(args.run, PathBuf::from("RUN"));
        assert_eq!(args.view, Some(0));
        assert_eq!(args.split, Split::Val);
        assert_eq!(args.turntable, None);
        assert_eq!(args.elevation, 30.0);
        assert_eq!((args.radius, args.size), (None, None));
        assert_eq!(args.mode, RenderMode::Rgb);
        assert!(!args.gif && !args.force);
    }

    #[test]
    fn a_view_and_a_turntable_cannot_both_be_asked_for() {
        let error = parse_args::<RenderArgs>(&[
            "RUN",
            "--view",
            "0",
            "--turntable",
            "8",
            "--out",
            "frames",
        ])
        .unwrap_err();
        assert_eq!(error.kind(), ErrorKind::ArgumentConflict);
        let message = error.to_string();
        assert!(
            message.contains("--view <VIEW>") && message.contains("--turntable <TURNTABLE>"),
            "{message}"
        );
    }

    #[test]
    fn settings_that_could_never_finish_are_refused_before_the_run_loads() {
        let refusal = |args: &[&str]| {
            check_render_args(&render_args(args))
                .unwrap_err()
                .to_string()
        };
        assert_eq!(
            refusal(&["RUN", "--turntable", "0", "--out", "f"]),
            "--turntable must be 1 to 100000 frames, got 0"
        );
        assert_eq!(
            refusal(&["RUN", "--turntable", "100001", "--out", "f"]),
            "--turntable must be 1 to 100000 frames, got 100001"
        );
        assert_eq!(
            refusal(&["RUN", "--turntable", "4", "--size", "0", "--out", "f"]),
            "--size must be 1 to 16384 pixels, got 0"
        );
        assert_eq!(
            refusal(&[
                "RUN",
                "--turntable",
                "4",
                "--elevation",
                "NaN",
                "--out",
                "f"
            ]),
            "--elevation must be a number of degrees, got NaN"
        );
        assert_eq!(
            refusal(&["RUN", "--turntable", "4", "--radius=-1", "--out", "f"]),
            "--radius must be a positive distance, got -1"
        );
        assert!(
            check_render_args(&render_args(&["RUN", "--turntable", "4", "--out", "f"])).is_ok()
        );
    }

    #[test]
    fn images_already_in_out_are_kept_unless_force() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().display().to_string();
        let view = ["RUN", "--view", "2", "--split", "test", "--out", &out];
        assert_eq!(
            render_args(&view).outputs(),
            vec![dir.path().join("test_002.png")]
        );
        assert!(check_render_args(&render_args(&view)).is_ok());
        std::fs::write(dir.path().join("test_002.png"), "").unwrap();
        let error = check_render_args(&render_args(&view))
            .unwrap_err()
            .to_string();
        assert!(
            error.ends_with(
                "test_002.png already exists; give --force to replace this render's files, \
                 or another --out"
            ),
            "{error}"
        );
        let mut forced = view.to_vec();
        forced.push("--force");
        assert!(check_render_args(&render_args(&forced)).is_ok());

        // A turntable writes its frames and, with --gif, the GIF.
        let turntable = ["RUN", "--turntable", "3", "--gif", "--out", &out];
        let outputs = render_args(&turntable).outputs();
        assert_eq!(outputs.len(), 4);
        assert_eq!(outputs[3], dir.path().join("turntable.gif"));
        for path in &outputs[..2] {
            std::fs::write(path, "").unwrap();
        }
        let error = check_render_args(&render_args(&turntable))
            .unwrap_err()
            .to_string();
        assert!(
            error.contains("already exists (and 1 more of the files this render writes)"),
            "{error}"
        );
    }
}
