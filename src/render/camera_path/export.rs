//! A camera path rendered into PNG frames or an MP4 video one unit at a
//! time: a frame rendered, or a frame encoded into the video. `zrak render
//! --camera-path` runs the units back to back under a progress bar; the
//! viewer runs one per turn of its training thread, so it can show
//! progress and stop between any two.
//!
//! A video's frames are rendered into a folder beside it (`NAME.frames/`)
//! and encoded once all are there; the video is written under a temporary
//! name and renamed into place when whole, so a job stopped early leaves
//! the frames rendered so far (a later job with the same settings
//! continues from them) and no video file.

use std::ops::Range;
use std::path::{Path, PathBuf};

use super::PathSample;
use super::frames::{FrameJob, MANIFEST, RenderSource, read_frame};
use super::video::{Mp4Encoder, VideoInfo, size_problem};
use crate::model::{RadianceModel, RenderMode};
use crate::scene::{ImageRgba8, NdcSpace};

/// Whether `out` names a video file rather than a folder of frames.
pub fn is_video(out: &Path) -> bool {
    out.extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("mp4"))
}

/// File name endings that name an image or a video file: an output folder
/// given one of these names is surely a mistake for a file.
const FILE_ENDINGS: [&str; 12] = [
    "mp4", "gif", "png", "jpg", "jpeg", "avi", "mov", "mkv", "webm", "m4v", "mpg", "mpeg",
];

/// The ending of `out` (lower case) when it names an image or video file
/// rather than a folder.
pub fn file_ending(out: &Path) -> Option<String> {
    let ending = out.extension()?.to_string_lossy().to_ascii_lowercase();
    FILE_ENDINGS.contains(&ending.as_str()).then_some(ending)
}

/// Where a video's frames are rendered: `NAME.frames/` beside it.
pub fn frames_folder(video: &Path) -> PathBuf {
    video.with_extension("frames")
}

/// What to render.
#[derive(Debug, Clone)]
pub struct PathRenderSettings {
    /// Every frame of the path.
    pub samples: Vec<PathSample>,
    /// The frames to render.
    pub range: Range<usize>,
    pub width: u32,
    pub height: u32,
    /// Frames a second of the video.
    pub fps: f64,
    pub mode: RenderMode,
    /// A folder of PNG frames, or a file ending in `.mp4`.
    pub out: PathBuf,
    /// Replace an existing video and frames of another render in the
    /// folder; without it both are refused before any work.
    pub replace_existing: bool,
    /// Keep a video's PNG frames once it is encoded.
    pub keep_frames: bool,
    /// The depth that maps to black and to white in depth mode.
    pub depth_range: (f32, f32),
    /// The model and crop box rendered: the frames' record holds them, so
    /// frames of another checkpoint or box are never taken as this
    /// render's.
    pub source: RenderSource,
    /// A forward-facing scene's normalised device coordinates (the
    /// scene's [`crate::scene::Scene::ndc`]).
    pub ndc: Option<NdcSpace>,
}

/// What a finished render wrote.
#[derive(Debug, Clone, PartialEq)]
pub struct PathRenderOutput {
    /// The video, when one was asked for.
    pub video: Option<VideoInfo>,
    /// The frames folder, and the frame files left in it.
    pub frames_dir: PathBuf,
    pub frame_files: Vec<PathBuf>,
    /// Frames rendered by this job, and found on disk from an earlier one.
    pub rendered: usize,
    pub already: usize,
}

/// A camera path render under way.
pub struct PathRender {
    settings: PathRenderSettings,
    job: FrameJob,
    /// Frames still to render, in order.
    todo: Vec<usize>,
    next_todo: usize,
    already: usize,
    /// The video being encoded, and the next frame to encode into it.
    encoder: Option<Mp4Encoder>,
    next_encoded: usize,
}

impl PathRender {
    /// Checks the settings and the output (an existing video is refused
    /// unless `replace_existing`), creates the frames folder and finds the
    /// frames already there.
    pub fn start(settings: PathRenderSettings) -> Result<Self, String> {
        let video = is_video(&settings.out);
        if let Some(ending) = file_ending(&settings.out).filter(|_| !video) {
            return Err(format!(
                "{}: a camera path is rendered into a folder of PNG frames or an .mp4 video, not \
                 a .{ending} file; give a folder or a file ending in .mp4",
                settings.out.display()
            ));
        }
        crate::files::check_memory(
            &format!("a {}×{} frame", settings.width, settings.height),
            crate::render::frame_memory_bytes(settings.width, settings.height)
                + if video {
                    super::video::encoder_memory_bytes(settings.width, settings.height)
                } else {
                    0
                },
        )?;
        if video {
            if let Some(problem) = size_problem(settings.width, settings.height) {
                return Err(format!("{}: {problem}", settings.out.display()));
            }
            if !(settings.fps.is_finite() && (1.0..=240.0).contains(&settings.fps)) {
                return Err(format!(
                    "a video's frame rate must be 1 to 240 frames a second, got {}",
                    settings.fps
                ));
            }
            if !settings.replace_existing && crate::files::exists_at_all(&settings.out) {
                return Err(format!(
                    "{} already exists and replacing it was not asked for; choose another file",
                    settings.out.display()
                ));
            }
        }
        let frames_dir = if video {
            frames_folder(&settings.out)
        } else {
            settings.out.clone()
        };
        let job = FrameJob {
            samples: settings.samples.clone(),
            range: settings.range.clone(),
            width: settings.width,
            height: settings.height,
            mode: settings.mode,
            depth_range: settings.depth_range,
            source: settings.source.clone(),
            out_dir: frames_dir,
            ndc: settings.ndc,
        };
        let todo = job.prepare(settings.replace_existing)?;
        Ok(Self {
            already: settings.range.len() - todo.len(),
            settings,
            job,
            todo,
            next_todo: 0,
            encoder: None,
            next_encoded: 0,
        })
    }

    /// Units done and in all: frames rendered (or found on disk), then,
    /// for a video, frames encoded.
    pub fn progress(&self) -> (usize, usize) {
        let frames = self.settings.range.len();
        let video = is_video(&self.settings.out);
        let done = self.already + self.next_todo + self.next_encoded;
        (done, if video { 2 * frames } else { frames })
    }

    /// Frames rendered by this job so far.
    pub fn rendered(&self) -> usize {
        self.next_todo
    }

    /// Frames found on disk, whole, when the job started.
    pub fn already(&self) -> usize {
        self.already
    }

    pub fn frames_dir(&self) -> &Path {
        &self.job.out_dir
    }

    /// Does the next unit; false when none is left (then [`Self::finish`]).
    pub fn step(&mut self, model: &dyn RadianceModel) -> Result<bool, String> {
        if let Some(&index) = self.todo.get(self.next_todo) {
            self.job.render_frame(model, index)?;
            self.next_todo += 1;
            return Ok(true);
        }
        if !is_video(&self.settings.out) {
            return Ok(false);
        }
        let range = self.settings.range.clone();
        if self.next_encoded == range.len() {
            return Ok(false);
        }
        if self.encoder.is_none() {
            self.encoder = Some(Mp4Encoder::create(
                &self.settings.out,
                self.settings.width,
                self.settings.height,
                self.settings.fps,
            )?);
        }
        let path = self.job.frame_path(range.start + self.next_encoded);
        let image = read_frame(&path).map_err(|e| {
            format!(
                "{}: cannot read the frame back ({e}); run the same command again to render it \
                 anew",
                path.display()
            )
        })?;
        let (w, h) = image.dimensions();
        self.encoder
            .as_mut()
            .expect("created above")
            .add_frame(&ImageRgba8::new(w, h, image.into_raw()))?;
        self.next_encoded += 1;
        Ok(self.next_encoded < range.len())
    }

    /// Finishes the job (doing whatever units are left): the video renamed
    /// into place and, unless `keep_frames`, its frames removed.
    pub fn finish(mut self, model: &dyn RadianceModel) -> Result<PathRenderOutput, String> {
        while self.step(model)? {}
        let range = self.settings.range.clone();
        let video = match self.encoder.take() {
            Some(encoder) => Some(encoder.finish()?),
            None => None,
        };
        let mut frame_files: Vec<PathBuf> = range.clone().map(|i| self.job.frame_path(i)).collect();
        if video.is_some() && !self.settings.keep_frames {
            for file in frame_files.drain(..) {
                let _ = std::fs::remove_file(file);
            }
            let _ = std::fs::remove_file(self.job.out_dir.join(MANIFEST));
            // Only when empty: frames of other ranges stay.
            let _ = std::fs::remove_dir(&self.job.out_dir);
        }
        Ok(PathRenderOutput {
            video,
            frames_dir: self.job.out_dir.clone(),
            frame_files,
            rendered: self.next_todo,
            already: self.already,
        })
    }
}
