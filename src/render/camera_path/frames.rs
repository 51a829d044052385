//! A camera path rendered into numbered PNG frames, one at a time, so that
//! a caller can show progress, stop between frames and, later, continue
//! where it stopped.
//!
//! Every frame is written under a temporary name and renamed into place
//! (see [`crate::files`]), so a frame file with its final name is whole
//! unless something else cut it short; a kept frame is decoded before it is
//! counted as done. A manifest beside the frames (`camera_path_render.json`)
//! records everything that decides their pixels: the run, its weights (the
//! checkpoint's checksum), the model, the crop box, every camera, the size,
//! the mode and the depth range. A render continues only over frames of the
//! same render; frames of another are refused, or with `replace` removed,
//! so a folder never mixes two renders.

use std::io::BufReader;
use std::ops::Range;
use std::path::{Path, PathBuf};

use serde_json::{Value, json};

use super::PathSample;
use crate::crc32c::Crc32c;
use crate::model::pixels::{render_pixels, to_image};
use crate::model::{RadianceModel, RenderMode};
use crate::scene::crop::CropBox;
use crate::scene::{ImageRgba8, NdcSpace};

/// The manifest's file name in the frames folder.
pub const MANIFEST: &str = "camera_path_render.json";

/// The manifest's format: 2 records the run, weights, model and crop box
/// (format 1, without them, is another render's as far as zrak can tell).
const MANIFEST_FORMAT: u64 = 2;

/// What RGB frames are composited over: white, as the turntable and the
/// NeRF-synthetic evaluation images are.
pub const BACKGROUND: [f32; 3] = [1.0; 3];

/// What renders the frames, besides the cameras: the model's weights and
/// the crop box it renders inside.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct RenderSource {
    /// The run folder (its absolute path), or what the viewer shows.
    pub run: String,
    /// Which weights: `checkpoint CRC-32C 1a2b3c4d` for a saved run, the
    /// training step for the viewer's model.
    pub weights: String,
    /// The model's name (`ngp`, `nerf`).
    pub model: String,
    pub crop: Option<CropBox>,
}

/// Frames of a camera path to render into a folder.
#[derive(Debug, Clone)]
pub struct FrameJob {
    /// Every frame of the path (the manifest covers them all, so that
    /// rendering another range of the same path continues the same render).
    pub samples: Vec<PathSample>,
    /// The frames to render now.
    pub range: Range<usize>,
    pub width: u32,
    pub height: u32,
    pub mode: RenderMode,
    /// The depth that maps to white and to black in depth mode.
    pub depth_range: (f32, f32),
    pub source: RenderSource,
    pub out_dir: PathBuf,
    /// A forward-facing scene's normalised device coordinates: each
    /// frame's rays are mapped into them, as the training rays were.
    pub ndc: Option<NdcSpace>,
}

/// The manifest's fields in the order a difference is reported, each with
/// the words for it.
const MANIFEST_FIELDS: [(&str, &str); 10] = [
    ("run", "run"),
    ("weights", "checkpoint"),
    ("model", "model"),
    ("crop", "crop box"),
    ("frames", "camera path"),
    ("cameras", "camera path"),
    ("width", "size"),
    ("height", "size"),
    ("mode", "mode"),
    ("depth_range", "depth range"),
];

impl FrameJob {
    /// Where frame `index` is written: `frame_00042.png`.
    pub fn frame_path(&self, index: usize) -> PathBuf {
        frame_path(&self.out_dir, index)
    }

    /// A fingerprint of the cameras: CRC-32C of every camera's pose and
    /// field of view (their f64 bits).
    pub fn cameras_fingerprint(&self) -> String {
        let mut crc = Crc32c::new();
        for s in &self.samples {
            for x in s.camera_to_world.to_cols_array() {
                crc.update(&x.to_bits().to_le_bytes());
            }
            crc.update(&s.fov_degrees.to_bits().to_le_bytes());
        }
        format!("{:08x}", crc.finish())
    }

    fn manifest_json(&self) -> Value {
        let crop = self.source.crop.map(|c| {
            let numbers: Vec<f32> = [c.centre.to_array(), c.size.to_array()]
                .concat()
                .into_iter()
                .chain(c.rotation.to_array())
                .collect();
            numbers
        });
        json!({
            "format": MANIFEST_FORMAT,
            "run": self.source.run,
            "weights": self.source.weights,
            "model": self.source.model,
            "crop": crop,
            "frames": self.samples.len(),
            "cameras": self.cameras_fingerprint(),
            "width": self.width,
            "height": self.height,
            "mode": mode_name(self.mode),
            "depth_range": [self.depth_range.0, self.depth_range.1],
        })
    }

    /// Why the frames in the folder, recorded by `old`, are not this
    /// render's, or `None` when they are.
    fn difference(&self, old: &Value, new: &Value) -> Option<String> {
        if old.get("format").and_then(Value::as_u64) != Some(MANIFEST_FORMAT) {
            return Some(
                "an earlier zrak's render, whose record does not say which run and checkpoint \
                 it shows"
                    .into(),
            );
        }
        let show = |v: Option<&Value>| match v {
            Some(Value::String(s)) => s.clone(),
            Some(Value::Null) | None => "none".into(),
            Some(other) => other.to_string(),
        };
        MANIFEST_FIELDS.iter().find_map(|(key, words)| {
            (old.get(key) != new.get(key)).then(|| {
                format!(
                    "another {words}: {} there, {} now",
                    show(old.get(key)),
                    show(new.get(key))
                )
            })
        })
    }

    /// Creates the folder, checks that it holds no frames of another render
    /// (with `replace`, removes them), writes the manifest and returns the
    /// frames of [`Self::range`] still to render: those not already on disk
    /// as whole frames of this render (all of them when `replace`).
    pub fn prepare(&self, replace: bool) -> Result<Vec<usize>, String> {
        if self.range.end > self.samples.len() || self.range.is_empty() {
            return Err(format!(
                "frames {}..{} are not within the path's {} frames",
                self.range.start,
                self.range.end,
                self.samples.len()
            ));
        }
        let dir = &self.out_dir;
        std::fs::create_dir_all(dir)
            .map_err(|e| format!("{}: cannot create the output folder: {e}", dir.display()))?;
        let manifest_path = dir.join(MANIFEST);
        let manifest = self.manifest_json();
        let old = crate::files::read_regular_bounded(&manifest_path, 1 << 20, "a render's record")
            .ok()
            .and_then(|bytes| serde_json::from_slice::<Value>(&bytes).ok());
        let other_render = match &old {
            Some(old) => self.difference(old, &manifest),
            None if self.has_any_frame()? => Some("a render that left no record".into()),
            None if crate::files::exists_at_all(&manifest_path) => {
                Some("a render whose record cannot be read".into())
            }
            None => None,
        };
        if let Some(why) = &other_render {
            if !replace {
                return Err(format!(
                    "{} holds frames of another render ({why}); give --force to render every \
                     frame again (the other render's frames are removed), or another --out",
                    dir.display()
                ));
            }
            // The record first: a folder with frames and no record is
            // refused, so a stop half way through cannot pass old frames
            // off as new.
            remove_if_there(&manifest_path)?;
            self.remove_all_frames()?;
        }
        let text = serde_json::to_string_pretty(&manifest).expect("JSON serialises") + "\n";
        crate::files::write_bytes_atomically(&manifest_path, text.as_bytes())
            .map_err(|e| format!("{}: cannot write: {e}", manifest_path.display()))?;
        Ok(self
            .range
            .clone()
            .filter(|&i| replace || !self.is_complete(i))
            .collect())
    }

    fn frame_files(&self) -> Result<Vec<PathBuf>, String> {
        let entries = std::fs::read_dir(&self.out_dir)
            .map_err(|e| format!("{}: cannot list: {e}", self.out_dir.display()))?;
        Ok(entries
            .flatten()
            .filter(|e| is_frame_name(&e.file_name().to_string_lossy()))
            .map(|e| e.path())
            .collect())
    }

    fn has_any_frame(&self) -> Result<bool, String> {
        Ok(!self.frame_files()?.is_empty())
    }

    /// Removes every frame file in the folder (a link is removed, never
    /// followed).
    fn remove_all_frames(&self) -> Result<(), String> {
        for path in self.frame_files()? {
            remove_if_there(&path)?;
        }
        Ok(())
    }

    /// Whether frame `index` is on disk as a regular file holding a PNG of
    /// this render's size that decodes whole. A link, a truncated or
    /// damaged file is rendered again (and replaced, the link itself
    /// rather than what it points at).
    pub fn is_complete(&self, index: usize) -> bool {
        read_frame(&self.frame_path(index))
            .is_ok_and(|image| image.dimensions() == (self.width, self.height))
    }

    /// Renders frame `index` and writes it; returns the image.
    pub fn render_frame(
        &self,
        model: &dyn RadianceModel,
        index: usize,
    ) -> Result<ImageRgba8, String> {
        let camera = self.samples[index]
            .camera(self.width, self.height)
            .with_ndc(self.ndc);
        let pixels = render_pixels(model, &camera, BACKGROUND);
        let image = to_image(
            &pixels,
            self.width,
            self.height,
            self.mode,
            self.depth_range,
        );
        drop(pixels);
        image
            .save_png(&self.frame_path(index))
            .map_err(|e| e.to_string())?;
        Ok(image)
    }
}

/// Reads a frame file back: only a regular file (not a link, a pipe or a
/// device), decoded whole.
pub fn read_frame(path: &Path) -> Result<image::RgbaImage, String> {
    let metadata = std::fs::symlink_metadata(path).map_err(|e| e.to_string())?;
    if !metadata.file_type().is_file() {
        return Err("not a regular file".into());
    }
    let (file, _) = crate::files::open_regular(path).map_err(|e| e.to_string())?;
    let mut reader = image::ImageReader::new(BufReader::new(file))
        .with_guessed_format()
        .map_err(|e| e.to_string())?;
    // The render's own memory check covers a frame's size.
    reader.no_limits();
    Ok(reader.decode().map_err(|e| e.to_string())?.to_rgba8())
}

fn remove_if_there(path: &Path) -> Result<(), String> {
    match std::fs::remove_file(path) {
        Ok(()) => Ok(()),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(()),
        Err(e) => Err(format!("{}: cannot remove: {e}", path.display())),
    }
}

/// Whether `name` is a frame's file name: `frame_` and digits, `.png`.
fn is_frame_name(name: &str) -> bool {
    name.strip_prefix("frame_")
        .and_then(|rest| rest.strip_suffix(".png"))
        .is_some_and(|digits| !digits.is_empty() && digits.bytes().all(|b| b.is_ascii_digit()))
}

/// The mode's name as on the command line (`rgb`, `depth`, `opacity`).
pub fn mode_name(mode: RenderMode) -> &'static str {
    match mode {
        RenderMode::Rgb => "rgb",
        RenderMode::Depth => "depth",
        RenderMode::Opacity => "opacity",
    }
}

/// Where frame `index` of a render into `dir` is written.
pub fn frame_path(dir: &Path, index: usize) -> PathBuf {
    dir.join(format!("frame_{index:05}.png"))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::camera_path::{CameraPath, Keyframe, look_at};
    use glam::DVec3;

    fn job(dir: &Path, mode: RenderMode) -> FrameJob {
        let path = CameraPath::new(vec![
            Keyframe::new(
                look_at(DVec3::new(4.0, 0.0, 1.0), DVec3::ZERO, DVec3::Z),
                40.0,
            ),
            Keyframe::new(
                look_at(DVec3::new(0.0, 4.0, 1.0), DVec3::ZERO, DVec3::Z),
                40.0,
            ),
        ]);
        FrameJob {
            samples: path.bake(6),
            range: 0..6,
            width: 8,
            height: 6,
            mode,
            depth_range: (2.0, 6.0),
            source: RenderSource {
                run: "/runs/a".into(),
                weights: "checkpoint CRC-32C 00000001".into(),
                model: "ngp".into(),
                crop: None,
            },
            out_dir: dir.to_path_buf(),
            ndc: None,
        }
    }

    #[test]
    fn frames_on_disk_are_skipped_and_other_renders_refused() {
        let dir = tempfile::tempdir().unwrap();
        let job = job(dir.path(), RenderMode::Rgb);
        assert_eq!(job.prepare(false).unwrap(), (0..6).collect::<Vec<_>>());
        // Frames 1 and 3 finished; frame 4 is a stray file of another size.
        let image = ImageRgba8::new(8, 6, vec![0; 8 * 6 * 4]);
        image.save_png(&job.frame_path(1)).unwrap();
        image.save_png(&job.frame_path(3)).unwrap();
        ImageRgba8::new(4, 4, vec![0; 64])
            .save_png(&job.frame_path(4))
            .unwrap();
        // Frame 0 is cut short: its header is whole, its pixels are not.
        let whole = std::fs::read(job.frame_path(1)).unwrap();
        std::fs::write(job.frame_path(0), &whole[..whole.len() - 20]).unwrap();
        assert_eq!(job.prepare(false).unwrap(), vec![0, 2, 4, 5]);
        // A range of the same render.
        let part = FrameJob {
            range: 2..4,
            ..job.clone()
        };
        assert_eq!(part.prepare(false).unwrap(), vec![2]);
        // The same folder for another mode is refused, then replaced.
        let depth = self::job(dir.path(), RenderMode::Depth);
        let e = depth.prepare(false).unwrap_err();
        assert!(
            e.ends_with(
                "holds frames of another render (another mode: rgb there, depth now); give \
                 --force to render every frame again (the other render's frames are removed), \
                 or another --out"
            ),
            "{e}"
        );
        assert_eq!(depth.prepare(true).unwrap(), (0..6).collect::<Vec<_>>());
        // The other render's frames went with --force, the stray one too.
        assert!(!job.frame_path(1).exists() && !job.frame_path(4).exists());
        // Another checkpoint of the same run is another render.
        let mut retrained = depth.clone();
        retrained.source.weights = "checkpoint CRC-32C 00000002".into();
        let e = retrained.prepare(false).unwrap_err();
        assert!(
            e.contains(
                "(another checkpoint: checkpoint CRC-32C 00000001 there, checkpoint \
                 CRC-32C 00000002 now)"
            ),
            "{e}"
        );
        let mut cropped = depth.clone();
        cropped.source.crop = Some(CropBox::axis_aligned(glam::Vec3::ZERO, glam::Vec3::ONE));
        assert!(
            cropped
                .prepare(false)
                .unwrap_err()
                .contains("another crop box")
        );
        assert!(depth.prepare(false).is_ok());
        // Frames without a manifest are not taken as this render's.
        let other = tempfile::tempdir().unwrap();
        image.save_png(&frame_path(other.path(), 0)).unwrap();
        assert!(
            self::job(other.path(), RenderMode::Rgb)
                .prepare(false)
                .is_err()
        );
        // A range past the end.
        let beyond = FrameJob { range: 4..9, ..job };
        assert!(
            beyond
                .prepare(false)
                .unwrap_err()
                .contains("not within the path's 6 frames")
        );
    }
}
