//! `zrak render RUN --camera-path FILE --out DIR|VIDEO.mp4`: a camera path
//! (nerfstudio's `camera_path.json`) rendered frame by frame into PNG
//! files, and for an `.mp4` output encoded into an H.264 video.
//!
//! Frames are written as they finish; running the same command again after
//! an interrupt renders only the frames not yet on disk (see
//! [`zrak::render::camera_path::frames`]). A video's frames go to a folder
//! beside it (`NAME.frames/`) and the video is encoded from them once all
//! are there; the folder is removed afterwards unless `--keep-frames`.

use std::ops::Range;
use std::path::Path;
use std::time::Instant;

use indicatif::{ProgressBar, ProgressStyle};
use zrak::interrupt::{
    note, {self},
};
use zrak::model::RadianceModel;
use zrak::render::camera_path::export::{PathRender, PathRenderSettings};
use zrak::render::camera_path::frames::RenderSource;
use zrak::render::camera_path::nerfstudio::{CameraPathFile, scene_to_original};
use zrak::render::camera_path::video::size_problem;
use zrak::scene::Scene;

use super::RenderArgs;

/// A range of frames on the command line: `A..B` (B excluded), `A..` (to
/// the end), `..B`, or `A` (that frame alone).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FrameRange {
    pub start: usize,
    pub end: Option<usize>,
}

impl FrameRange {
    /// The frames of a path of `total` frames this range covers.
    pub fn resolve(&self, total: usize) -> anyhow::Result<Range<usize>> {
        let end = self.end.unwrap_or(total);
        anyhow::ensure!(
            self.start < end && end <= total,
            "--frames {}..{end} is not within the path's {total} frames (0..{total})",
            self.start
        );
        Ok(self.start..end)
    }
}

pub fn parse_frame_range(text: &str) -> Result<FrameRange, String> {
    let number = |s: &str| {
        s.trim()
            .parse::<usize>()
            .map_err(|_| format!("`{text}` is not a frame range like 10..20, 10.. or 7"))
    };
    match text.split_once("..") {
        Some((a, b)) => {
            let start = if a.trim().is_empty() { 0 } else { number(a)? };
            let end = if b.trim().is_empty() {
                None
            } else {
                Some(number(b)?)
            };
            if end.is_some_and(|end| end <= start) {
                return Err(format!("`{text}` is empty: the end is not after the start"));
            }
            Ok(FrameRange { start, end })
        }
        None => {
            let frame = number(text)?;
            Ok(FrameRange {
                start: frame,
                end: Some(frame + 1),
            })
        }
    }
}

use zrak::render::camera_path::export::is_video;

/// The camera path file `file_path`, read (before the run loads, so that a
/// bad file is refused at once).
pub fn read_path_file(file_path: &Path) -> anyhow::Result<CameraPathFile> {
    CameraPathFile::load(file_path).map_err(anyhow::Error::msg)
}

/// A camera path file moved into `scene`'s world.
pub fn move_into_scene(file: &CameraPathFile, scene: &Scene) -> anyhow::Result<CameraPathFile> {
    Ok(file.moved_into(scene_to_original(scene).map_err(anyhow::Error::msg)?))
}

pub fn render_camera_path(
    args: &RenderArgs,
    file: &CameraPathFile,
    file_path: &Path,
    model: &dyn RadianceModel,
    scene: &Scene,
    source: RenderSource,
) -> anyhow::Result<()> {
    let samples = match args.fps {
        Some(fps) => file.frames_at(fps),
        None => file.frames(),
    }
    .map_err(|e| anyhow::anyhow!("{}: {e}", file_path.display()))?;
    let fps = args.fps.unwrap_or(file.fps);
    let (width, height) = args
        .size
        .map_or((file.render_width, file.render_height), |s| {
            (s.width, s.height)
        });
    let range = match args.frames {
        Some(frames) => frames.resolve(samples.len())?,
        None => 0..samples.len(),
    };
    if is_video(&args.out) {
        if let Some(problem) = size_problem(width, height) {
            anyhow::bail!(
                "{}: {problem}, the size {} (give --size WxH)",
                args.out.display(),
                if args.size.is_some() {
                    "--size gives".to_string()
                } else {
                    format!(
                        "{} gives (`render_width`, `render_height`)",
                        file_path.display()
                    )
                }
            );
        }
        if !(1.0..=240.0).contains(&fps) {
            anyhow::bail!(
                "{}: `fps` is {fps}, and a video's frame rate must be 1 to 240 frames a second; \
                 give --fps",
                file_path.display()
            );
        }
        if !args.force && zrak::files::exists_at_all(&args.out) {
            anyhow::bail!(
                "{} already exists; give --force to replace it, or another --out",
                args.out.display()
            );
        }
    }
    let mut render = PathRender::start(PathRenderSettings {
        samples,
        range: range.clone(),
        width,
        height,
        fps,
        mode: args.mode,
        out: args.out.clone(),
        replace_existing: args.force,
        keep_frames: args.keep_frames,
        depth_range: scene.depth_range(),
        source,
        ndc: scene.ndc(),
    })
    .map_err(anyhow::Error::msg)?;
    let already = render.already();
    let frames_dir = render.frames_dir().to_path_buf();
    let bar = ProgressBar::new(range.len() as u64).with_style(
        ProgressStyle::with_template(
            "{bar:30} {pos}/{len} frames, {elapsed} so far, about {eta} to go",
        )
        .expect("a valid template"),
    );
    bar.set_position(already as u64);
    // The frames found on disk took no time now: the estimate counts only
    // those rendered from here on.
    bar.reset_eta();
    let started = Instant::now();
    let todo = range.len() - already;
    while render.rendered() < todo {
        if interrupt::requested() {
            bar.abandon();
            note(&format!(
                "interrupted after {} of {} frames; they are in {}: run the same command again \
                 to render the other {}",
                already + render.rendered(),
                range.len(),
                frames_dir.display(),
                todo - render.rendered()
            ));
            return Ok(());
        }
        render.step(model).map_err(anyhow::Error::msg)?;
        bar.inc(1);
    }
    bar.finish();
    let seconds = started.elapsed().as_secs_f64();
    let output = render.finish(model).map_err(anyhow::Error::msg)?;
    let rendered = output.rendered;
    match output.video {
        None => println!(
            "wrote {} frames to {} ({rendered} rendered in {seconds:.1} s, {already} already there)",
            range.len(),
            frames_dir.display()
        ),
        Some(info) => println!(
            "wrote {}: {} frames, {}×{}, {} frames a second, {} bytes ({rendered} frames rendered \
             in {seconds:.1} s, {already} already there)",
            info.path.display(),
            info.frames,
            info.width,
            info.height,
            info.fps,
            info.bytes
        ),
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::PathBuf;
    use zrak::render::camera_path::export::frames_folder;

    #[test]
    fn frame_ranges() {
        let r = |t| parse_frame_range(t).unwrap();
        assert_eq!(r("3..7").resolve(10).unwrap(), 3..7);
        assert_eq!(r("3..").resolve(10).unwrap(), 3..10);
        assert_eq!(r("..4").resolve(10).unwrap(), 0..4);
        assert_eq!(r("9").resolve(10).unwrap(), 9..10);
        assert_eq!(
            r("3..12").resolve(10).unwrap_err().to_string(),
            "--frames 3..12 is not within the path's 10 frames (0..10)"
        );
        assert!(r("10..").resolve(10).is_err());
        assert!(parse_frame_range("5..5").unwrap_err().contains("is empty"));
        assert!(
            parse_frame_range("a..b")
                .unwrap_err()
                .contains("not a frame range")
        );
    }

    #[test]
    fn videos_are_told_from_folders_by_their_extension() {
        assert!(is_video(Path::new("out/path.MP4")));
        assert!(!is_video(Path::new("out/frames")));
        assert_eq!(
            frames_folder(Path::new("out/path.mp4")),
            PathBuf::from("out/path.frames")
        );
    }
}
