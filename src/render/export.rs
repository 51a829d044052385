//! Turntable export: frames as PNG files and an animated GIF, one frame at
//! a time so a caller can report progress and cancel between frames.
//!
//! Every file is written under a temporary name in the output folder and
//! renamed into place when complete, so a file that was already there is
//! either left whole or replaced whole, never half-overwritten.

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};

use super::path::{Turntable, turntable_cameras};
use crate::model::pixels::{render_pixels, to_image};
use crate::model::{RadianceModel, RenderMode};
use crate::scene::{Camera, ImageRgba8, Scene};

/// What a turntable export writes.
#[derive(Debug, Clone, PartialEq)]
pub struct ExportSettings {
    pub turntable: Turntable,
    pub mode: RenderMode,
    pub out_dir: PathBuf,
    /// Also write `turntable.gif` beside the PNG frames.
    pub write_gif: bool,
    /// Write over frames and a GIF of the same names already in `out_dir`;
    /// without it, an export into a folder holding an earlier one is refused
    /// before anything is written.
    pub replace_existing: bool,
}

impl ExportSettings {
    /// Where frame `index` is written.
    pub fn frame_path(&self, index: usize) -> PathBuf {
        self.out_dir.join(format!("turntable_{index:04}.png"))
    }

    /// Where the animated GIF is written.
    pub fn gif_path(&self) -> PathBuf {
        self.out_dir.join("turntable.gif")
    }
}

/// Time each GIF frame is shown, in the format's unit of 10 ms: 4 gives
/// 25 frames per second, so the default 60-frame turntable turns once in
/// 2.4 seconds.
pub const GIF_FRAME_DELAY_CENTISECONDS: u16 = 4;

/// NeuQuant sampling speed for each frame's 256-colour palette, in the gif
/// crate's range 1 (best) to 30 (fastest); 10 is the crate's recommended
/// compromise between quality and time.
const GIF_QUANTISE_SPEED: i32 = 10;

/// What RGB frames are composited over: white, like the NeRF-synthetic
/// evaluation images.
const BACKGROUND: [f32; 3] = [1.0; 3];

/// A turntable export under way: [`Self::start`], then
/// [`Self::render_next`] until it returns `false`, then [`Self::finish`].
/// Dropped before `finish`, it leaves the frames already written and removes
/// its unfinished GIF.
pub struct TurntableExport {
    settings: ExportSettings,
    cameras: Vec<Camera>,
    depth_range: (f32, f32),
    done: usize,
    written: Vec<PathBuf>,
    last_image: Option<ImageRgba8>,
    gif: Option<GifInProgress>,
}

/// The GIF being encoded frame by frame into its temporary file.
struct GifInProgress {
    encoder: gif::Encoder<BufWriter<File>>,
    partial: PathBuf,
}

impl TurntableExport {
    /// Creates the output folder, checks now that files can be written in it
    /// (rather than after the first frame has rendered), and places the
    /// cameras.
    pub fn start(scene: &Scene, settings: ExportSettings) -> Result<TurntableExport, String> {
        if settings.turntable.frames == 0 {
            return Err("a turntable needs at least one frame".into());
        }
        let dir = &settings.out_dir;
        std::fs::create_dir_all(dir)
            .map_err(|e| format!("{}: cannot create the output folder: {e}", dir.display()))?;
        check_writable(dir)?;
        if !settings.replace_existing {
            refuse_existing(&settings)?;
        }
        let cameras = turntable_cameras(scene, &settings.turntable);
        let gif = if settings.write_gif {
            let k = cameras[0].intrinsics;
            Some(GifInProgress::create(
                &settings.gif_path(),
                k.width,
                k.height,
            )?)
        } else {
            None
        };
        Ok(TurntableExport {
            depth_range: scene.depth_range(),
            settings,
            cameras,
            done: 0,
            written: Vec::new(),
            last_image: None,
            gif,
        })
    }

    /// Frames in the whole turntable.
    pub fn total(&self) -> usize {
        self.cameras.len()
    }

    /// Frames rendered and written so far.
    pub fn done(&self) -> usize {
        self.done
    }

    pub fn settings(&self) -> &ExportSettings {
        &self.settings
    }

    /// The frame written last, for a preview.
    pub fn last_image(&self) -> Option<&ImageRgba8> {
        self.last_image.as_ref()
    }

    /// Renders frame [`Self::done`], writes it as `turntable_NNNN.png` (and
    /// adds it to the GIF), and says whether frames remain. Past the last
    /// frame it does nothing and returns `false`.
    pub fn render_next(&mut self, model: &dyn RadianceModel) -> Result<bool, String> {
        let Some(camera) = self.cameras.get(self.done) else {
            return Ok(false);
        };
        let pixels = render_pixels(model, camera, BACKGROUND);
        let k = camera.intrinsics;
        let image = to_image(
            &pixels,
            k.width,
            k.height,
            self.settings.mode,
            self.depth_range,
        );
        let path = self.settings.frame_path(self.done);
        write_png_replacing(&image, &path)?;
        self.written.push(path);
        if let Some(gif) = &mut self.gif {
            gif.add_frame(&image)?;
        }
        self.last_image = Some(image);
        self.done += 1;
        Ok(self.done < self.total())
    }

    /// Completes the GIF (when asked for; it holds the frames rendered so
    /// far) and returns every file written: the PNG frames in order, then
    /// the GIF.
    pub fn finish(mut self) -> Result<Vec<PathBuf>, String> {
        let mut written = std::mem::take(&mut self.written);
        if let Some(gif) = self.gif.take() {
            written.push(gif.finish(&self.settings.gif_path())?);
        }
        Ok(written)
    }
}

impl Drop for TurntableExport {
    fn drop(&mut self) {
        // Not finished (cancelled or failed): the partial GIF is no use.
        if let Some(gif) = self.gif.take() {
            gif.abandon();
        }
    }
}

impl GifInProgress {
    fn create(path: &Path, width: u32, height: u32) -> Result<Self, String> {
        let too_large = |_| {
            format!(
                "{}: a GIF is at most 65535 pixels on a side; the frames are {width}×{height}",
                path.display()
            )
        };
        let (w, h) = (
            u16::try_from(width).map_err(too_large)?,
            u16::try_from(height).map_err(too_large)?,
        );
        let partial = partial_path(path);
        // A new file only: never through a link someone left at the name.
        let file = File::create_new(&partial)
            .map_err(|e| format!("{}: cannot create file: {e}", partial.display()))?;
        let gif = Self::start_encoding(file, w, h)
            .map(|encoder| GifInProgress {
                encoder,
                partial: partial.clone(),
            })
            .map_err(|e| format!("{}: cannot write GIF: {e}", path.display()));
        if gif.is_err() {
            let _ = std::fs::remove_file(&partial);
        }
        gif
    }

    fn start_encoding(
        file: File,
        width: u16,
        height: u16,
    ) -> Result<gif::Encoder<BufWriter<File>>, gif::EncodingError> {
        // No global palette: each frame carries its own.
        let mut encoder = gif::Encoder::new(BufWriter::new(file), width, height, &[])?;
        encoder.set_repeat(gif::Repeat::Infinite)?;
        Ok(encoder)
    }

    fn add_frame(&mut self, image: &ImageRgba8) -> Result<(), String> {
        let mut rgba = image.data.clone();
        // Frames are the GIF's size (checked in `create`).
        let mut frame = gif::Frame::from_rgba_speed(
            image.width as u16,
            image.height as u16,
            &mut rgba,
            GIF_QUANTISE_SPEED,
        );
        frame.delay = GIF_FRAME_DELAY_CENTISECONDS;
        self.encoder
            .write_frame(&frame)
            .map_err(|e| format!("{}: cannot write GIF: {e}", self.partial.display()))
    }

    /// Writes the trailer, flushes, and renames the file into place.
    fn finish(self, path: &Path) -> Result<PathBuf, String> {
        let GifInProgress { encoder, partial } = self;
        let result = encoder
            .into_inner()
            .map_err(|e| e.to_string())
            .and_then(|writer| writer.into_inner().map_err(|e| e.error().to_string()))
            .and_then(|file| file.sync_all().map_err(|e| e.to_string()))
            .map_err(|e| format!("{}: cannot write GIF: {e}", partial.display()))
            .and_then(|()| rename_into_place(&partial, path));
        if result.is_err() {
            let _ = std::fs::remove_file(&partial);
        }
        result.map(|()| path.to_path_buf())
    }

    fn abandon(self) {
        let GifInProgress { encoder, partial } = self;
        drop(encoder);
        let _ = std::fs::remove_file(&partial);
    }
}

/// The whole export in one call, for the command line: `progress(done,
/// total)` after each frame. Stops with the error "cancelled" when `cancel`
/// is set (checked before each frame), keeping the frames already written.
pub fn export_turntable(
    model: &dyn RadianceModel,
    scene: &Scene,
    settings: ExportSettings,
    cancel: &AtomicBool,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<Vec<PathBuf>, String> {
    let mut export = TurntableExport::start(scene, settings)?;
    let total = export.total();
    while export.done() < total {
        if cancel.load(Ordering::Relaxed) {
            return Err("cancelled".into());
        }
        export.render_next(model)?;
        progress(export.done(), total);
    }
    export.finish()
}

/// Fails, naming `dir`, unless a file can be created in it.
/// Refuses an export whose frames or GIF would replace files already in
/// the folder, naming the first and how many there are.
fn refuse_existing(settings: &ExportSettings) -> Result<(), String> {
    let gif = settings.write_gif.then(|| settings.gif_path());
    let existing: Vec<PathBuf> = (0..settings.turntable.frames)
        .map(|i| settings.frame_path(i))
        .chain(gif)
        .filter(|path| crate::files::exists_at_all(path))
        .collect();
    match existing.first() {
        None => Ok(()),
        Some(first) => Err(format!(
            "{} already exists ({} file{} of this export would be replaced): choose another \
             folder, or ask to replace existing files",
            first.display(),
            existing.len(),
            if existing.len() == 1 { "" } else { "s" }
        )),
    }
}

fn check_writable(dir: &Path) -> Result<(), String> {
    // A name of this process's own, created new: a link at a fixed name
    // would have the probe written through it.
    let probe = crate::files::temporary_beside(&dir.join(".zrak-write-check"));
    let result = File::create_new(&probe).and_then(|mut file| {
        let written = file.write_all(b"zrak");
        let _ = std::fs::remove_file(&probe);
        written
    });
    result.map_err(|e| format!("{}: cannot write to the output folder: {e}", dir.display()))
}

/// A temporary name beside `path`, unique to this process and call (two
/// exports into one folder never share one), in the same folder so the
/// rename into place stays on one file system.
fn partial_path(path: &Path) -> PathBuf {
    crate::files::temporary_beside(path)
}

fn rename_into_place(partial: &Path, path: &Path) -> Result<(), String> {
    std::fs::rename(partial, path)
        .map_err(|e| format!("{}: cannot replace the file: {e}", path.display()))
}

/// Writes `image` as a PNG to a temporary file beside `path`, then renames
/// it over `path`. The file is encoded in memory and synced before the
/// rename, so every write error is seen (a buffered writer dropped at the
/// end would swallow the last one).
fn write_png_replacing(image: &ImageRgba8, path: &Path) -> Result<(), String> {
    use image::ImageEncoder;
    let mut bytes = Vec::new();
    image::codecs::png::PngEncoder::new(&mut bytes)
        .write_image(
            &image.data,
            image.width,
            image.height,
            image::ExtendedColorType::Rgba8,
        )
        .map_err(|e| format!("{}: cannot encode PNG: {e}", path.display()))?;
    crate::files::write_bytes_atomically(path, &bytes)
        .map_err(|e| format!("{}: cannot write file: {e}", path.display()))
}

#[cfg(test)]
mod tests {
    use glam::Vec3;

    use super::*;
    use crate::model::batch::RayBatch;
    use crate::model::checkpoint::Checkpoint;
    use crate::model::{RenderRays, RenderedPixel, StepStats};
    use crate::scene::demo::{DemoConfig, build};

    /// A model-free stand-in: every ray's colour is its direction, so
    /// frames from different cameras differ without any training.
    struct DirectionColour;

    impl RadianceModel for DirectionColour {
        fn describe(&self) -> String {
            "direction colour".into()
        }

        fn rays_for_next_batch(&self) -> usize {
            0
        }

        fn step(&mut self, _batch: &RayBatch, _step: u32) -> StepStats {
            StepStats::default()
        }

        fn render(&self, rays: RenderRays, out: &mut [RenderedPixel]) {
            for (pixel, d) in out.iter_mut().zip(rays.directions) {
                let colour = 0.5 * (*d + Vec3::ONE);
                *pixel = RenderedPixel {
                    rgb: colour.to_array(),
                    opacity: 1.0,
                    depth: 4.0,
                };
            }
        }

        fn save(&self) -> Checkpoint {
            Checkpoint {
                header: serde_json::Value::Null,
                tensors: Vec::new(),
            }
        }

        fn load(&mut self, _checkpoint: &Checkpoint) -> Result<(), String> {
            Ok(())
        }

        fn memory_bytes(&self) -> usize {
            0
        }
    }

    const WIDTH: u32 = 20;
    const HEIGHT: u32 = 12;

    fn scene() -> Scene {
        build(&DemoConfig {
            size: 8,
            train_views: 3,
            val_views: 1,
            test_views: 1,
        })
    }

    fn settings(out_dir: &Path, frames: usize, write_gif: bool) -> ExportSettings {
        ExportSettings {
            turntable: Turntable {
                frames,
                size: Some((WIDTH, HEIGHT)),
                ..Turntable::default()
            },
            mode: RenderMode::Rgb,
            out_dir: out_dir.to_path_buf(),
            write_gif,
            replace_existing: false,
        }
    }

    fn files_in(dir: &Path) -> Vec<String> {
        let mut names: Vec<String> = std::fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        names.sort();
        names
    }

    #[test]
    fn writes_frames_and_a_looping_gif() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("new/folder");
        let frames = 4;
        let mut calls = Vec::new();
        let written = export_turntable(
            &DirectionColour,
            &scene(),
            settings(&out, frames, true),
            &AtomicBool::new(false),
            &mut |done, total| calls.push((done, total)),
        )
        .unwrap();
        assert_eq!(calls, vec![(1, 4), (2, 4), (3, 4), (4, 4)]);
        let mut expected: Vec<String> = (0..frames)
            .map(|i| format!("turntable_{i:04}.png"))
            .collect();
        expected.push("turntable.gif".into());
        let names: Vec<String> = written
            .iter()
            .map(|p| p.file_name().unwrap().to_string_lossy().into_owned())
            .collect();
        assert_eq!(names, expected);
        // Nothing else is left behind (no temporary files).
        let mut sorted = expected.clone();
        sorted.sort();
        assert_eq!(files_in(&out), sorted);

        let pngs: Vec<_> = written[..frames]
            .iter()
            .map(|p| image::open(p).unwrap().to_rgba8())
            .collect();
        for png in &pngs {
            assert_eq!(png.dimensions(), (WIDTH, HEIGHT));
        }
        // The camera moved: the first and last frames differ.
        assert_ne!(pngs[0].as_raw(), pngs[frames - 1].as_raw());

        let mut options = gif::DecodeOptions::new();
        options.set_color_output(gif::ColorOutput::RGBA);
        let mut decoder = options
            .read_info(File::open(&written[frames]).unwrap())
            .unwrap();
        assert_eq!(
            (decoder.width() as u32, decoder.height() as u32),
            (WIDTH, HEIGHT)
        );
        let mut decoded = 0;
        while let Some(frame) = decoder.read_next_frame().unwrap() {
            assert_eq!((frame.width as u32, frame.height as u32), (WIDTH, HEIGHT));
            assert_eq!(frame.delay, GIF_FRAME_DELAY_CENTISECONDS);
            decoded += 1;
        }
        assert_eq!(decoded, frames);
        assert_eq!(decoder.repeat(), gif::Repeat::Infinite);
    }

    #[test]
    fn step_by_step_reports_progress_and_skips_the_gif_unless_asked() {
        let dir = tempfile::tempdir().unwrap();
        let mut export = TurntableExport::start(&scene(), settings(dir.path(), 2, false)).unwrap();
        assert_eq!((export.done(), export.total()), (0, 2));
        assert!(export.render_next(&DirectionColour).unwrap());
        assert_eq!(export.done(), 1);
        assert_eq!(export.last_image().unwrap().width, WIDTH);
        assert!(!export.render_next(&DirectionColour).unwrap());
        // Past the end: nothing more.
        assert!(!export.render_next(&DirectionColour).unwrap());
        assert_eq!(export.done(), 2);
        let written = export.finish().unwrap();
        assert_eq!(written.len(), 2);
        assert_eq!(
            files_in(dir.path()),
            vec!["turntable_0000.png", "turntable_0001.png"]
        );
    }

    #[test]
    fn an_existing_frame_is_replaced_whole() {
        let dir = tempfile::tempdir().unwrap();
        let first = dir.path().join("turntable_0000.png");
        std::fs::write(&first, b"an older file").unwrap();
        export_turntable(
            &DirectionColour,
            &scene(),
            ExportSettings {
                replace_existing: true,
                ..settings(dir.path(), 1, false)
            },
            &AtomicBool::new(false),
            &mut |_, _| {},
        )
        .unwrap();
        assert_eq!(
            image::open(&first).unwrap().to_rgba8().dimensions(),
            (WIDTH, HEIGHT)
        );
    }

    #[test]
    fn an_earlier_export_is_kept_unless_replacing_is_asked_for() {
        let dir = tempfile::tempdir().unwrap();
        let gif = dir.path().join("turntable.gif");
        std::fs::write(&gif, b"an earlier turntable").unwrap();
        let error = TurntableExport::start(&scene(), settings(dir.path(), 3, true))
            .err()
            .expect("an export over an earlier one is refused");
        assert!(
            error.contains("turntable.gif") && error.contains("1 file of this export"),
            "{error}"
        );
        assert_eq!(std::fs::read(&gif).unwrap(), b"an earlier turntable");
        assert_eq!(files_in(dir.path()), vec!["turntable.gif"]);
    }

    #[test]
    fn unwritable_folder_is_named() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("plain-file");
        std::fs::write(&file, b"not a folder").unwrap();
        let out = file.join("frames");
        let error = TurntableExport::start(&scene(), settings(&out, 3, true))
            .err()
            .expect("a folder under a regular file cannot be created");
        assert!(error.contains(&out.display().to_string()), "{error}");
        assert!(error.contains("output folder"), "{error}");
    }

    #[test]
    fn no_frames_is_an_error() {
        let dir = tempfile::tempdir().unwrap();
        let error = TurntableExport::start(&scene(), settings(dir.path(), 0, true))
            .err()
            .unwrap();
        assert!(error.contains("at least one frame"), "{error}");
    }

    #[test]
    fn cancel_keeps_the_frames_already_written() {
        let dir = tempfile::tempdir().unwrap();
        let cancel = AtomicBool::new(false);
        let error = export_turntable(
            &DirectionColour,
            &scene(),
            settings(dir.path(), 5, true),
            &cancel,
            &mut |done, _| {
                if done == 2 {
                    cancel.store(true, Ordering::Relaxed);
                }
            },
        )
        .unwrap_err();
        assert_eq!(error, "cancelled");
        // Exactly the two frames: no GIF, no temporary file.
        assert_eq!(
            files_in(dir.path()),
            vec!["turntable_0000.png", "turntable_0001.png"]
        );
    }

    #[test]
    fn depth_range_spans_the_scene_box() {
        let scene = scene();
        let (near, far) = scene.depth_range();
        // Demo cameras sit 4 from the origin; the box has half side
        // 0.5 / 0.33 ≈ 1.52, so rays enter before 4 and leave after it.
        assert!(near > 0.0 && near < 4.0 && far > 4.0, "{near}..{far}");
    }
}
