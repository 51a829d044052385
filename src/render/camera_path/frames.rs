//! A camera path rendered into numbered PNG frames, one at a time, so that
//! a caller can show progress, stop between frames and, later, continue
//! where it stopped.
//!
//! Every frame is written under a temporary name and renamed into place
//! (see [`crate::files`]), so a frame file with its final name is whole. A
//! manifest beside the frames (`camera_path_render.json`) holds a
//! fingerprint of what they show (every camera, the size, the mode): a
//! render continues only over frames of the same render, and refuses to mix
//! frames of another path into the folder unless told to replace them.

use std::ops::Range;
use std::path::{Path, PathBuf};

use serde_json::json;

use super::PathSample;
use crate::crc32c::Crc32c;
use crate::model::RadianceModel;
use crate::render::{RenderMode, render_pixels, to_image};
use crate::scene::ImageRgba8;

/// The manifest's file name in the frames folder.
pub const MANIFEST: &str = "camera_path_render.json";

/// What RGB frames are composited over: white, as the turntable and the
/// NeRF-synthetic evaluation images are.
pub const BACKGROUND: [f32; 3] = [1.0; 3];

/// Frames of a camera path to render into a folder.
#[derive(Debug, Clone)]
pub struct FrameJob {
    /// Every frame of the path (the fingerprint covers them all, so that
    /// rendering another range of the same path continues the same render).
    pub samples: Vec<PathSample>,
    /// The frames to render now.
    pub range: Range<usize>,
    pub width: u32,
    pub height: u32,
    pub mode: RenderMode,
    pub out_dir: PathBuf,
}

impl FrameJob {
    /// Where frame `index` is written: `frame_00042.png`.
    pub fn frame_path(&self, index: usize) -> PathBuf {
        frame_path(&self.out_dir, index)
    }

    /// A fingerprint of the frames' content: CRC-32C of every camera's
    /// pose and field of view (their f64 bits), the size and the mode.
    pub fn fingerprint(&self) -> String {
        let mut crc = Crc32c::new();
        for s in &self.samples {
            for x in s.camera_to_world.to_cols_array() {
                crc.update(&x.to_bits().to_le_bytes());
            }
            crc.update(&s.fov_degrees.to_bits().to_le_bytes());
        }
        crc.update(&self.width.to_le_bytes());
        crc.update(&self.height.to_le_bytes());
        crc.update(mode_name(self.mode).as_bytes());
        format!("{:08x}", crc.finish())
    }

    fn manifest_json(&self) -> serde_json::Value {
        json!({
            "fingerprint": self.fingerprint(),
            "frames": self.samples.len(),
            "width": self.width,
            "height": self.height,
            "mode": mode_name(self.mode),
        })
    }

    /// Creates the folder, checks that it holds no frames of another render
    /// (unless `replace`), writes the manifest and returns the frames of
    /// [`Self::range`] still to render: those not already on disk whole at
    /// this size (all of them when `replace`).
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
        if !replace {
            let same = match std::fs::read(&manifest_path) {
                Ok(bytes) => serde_json::from_slice::<serde_json::Value>(&bytes)
                    .is_ok_and(|old| old == manifest),
                // No manifest: the folder must not already hold frames.
                Err(_) => !self.has_any_frame()?,
            };
            if !same {
                return Err(format!(
                    "{} holds frames of another render (another path, size or mode); give \
                     --force to replace them, or another --out",
                    dir.display()
                ));
            }
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

    fn has_any_frame(&self) -> Result<bool, String> {
        let entries = std::fs::read_dir(&self.out_dir)
            .map_err(|e| format!("{}: cannot list: {e}", self.out_dir.display()))?;
        Ok(entries.flatten().any(|e| {
            let name = e.file_name();
            let name = name.to_string_lossy();
            name.starts_with("frame_") && name.ends_with(".png")
        }))
    }

    /// Whether frame `index` is on disk as a PNG of this render's size.
    pub fn is_complete(&self, index: usize) -> bool {
        image::image_dimensions(self.frame_path(index))
            .is_ok_and(|size| size == (self.width, self.height))
    }

    /// Renders frame `index` and writes it; returns the image.
    pub fn render_frame(
        &self,
        model: &dyn RadianceModel,
        index: usize,
        depth_range: (f32, f32),
    ) -> Result<ImageRgba8, String> {
        let camera = self.samples[index].camera(self.width, self.height);
        let pixels = render_pixels(model, &camera, BACKGROUND);
        let image = to_image(&pixels, self.width, self.height, self.mode, depth_range);
        image
            .save_png(&self.frame_path(index))
            .map_err(|e| e.to_string())?;
        Ok(image)
    }
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
            out_dir: dir.to_path_buf(),
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
        assert!(e.ends_with("holds frames of another render (another path, size or mode); give --force to replace them, or another --out"), "{e}");
        assert_eq!(depth.prepare(true).unwrap(), (0..6).collect::<Vec<_>>());
        assert_ne!(job.fingerprint(), depth.fingerprint());
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
