//! Frames into an MP4 file with one H.264 video track, encoded in-process:
//! Cisco's OpenH264 (BSD-2, built from source by the `openh264` crate)
//! makes the H.264 stream and the `mp4` crate (MIT) writes the container.
//!
//! The encoder gives Annex B NAL units (each after a start code); MP4
//! stores each frame as NAL units prefixed with their length, and the
//! sequence and picture parameter sets once, in the track's `avcC` box
//! (ISO/IEC 14496-15, section 5.3.3). The frames' RGB goes to YUV 4:2:0
//! with BT.601 studio-swing coefficients (the `openh264` crate's
//! conversion), and the stream's VUI says so, so that players convert back
//! with the same matrix.

use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};

use mp4::{
    AvcConfig, FourCC, MediaConfig, Mp4Config, Mp4Sample, Mp4Writer, TrackConfig, TrackType,
};
use openh264::OpenH264API;
use openh264::encoder::{
    BitRate, Encoder, EncoderConfig, FrameRate, FrameType, IntraFramePeriod, QpRange,
    RateControlMode, UsageType, VuiConfig,
};
use openh264::formats::{RgbaSliceU8, YUVBuffer};

use crate::scene::ImageRgba8;

/// The track's time unit: 90 kHz, MPEG's customary video clock, which
/// divides evenly by the common frame rates (24, 25, 30, 50, 60) and keeps
/// 29.97 within 3 ticks a minute.
pub const TIMESCALE: u32 = 90_000;

/// Bits per pixel per frame the encoder aims at: 0.25, enough for the
/// smooth, noise-free images a radiance field renders to look clean (at
/// 1920 × 1080 and 30 frames a second, 15.6 Mbit/s).
const BITS_PER_PIXEL: f64 = 0.25;

/// The quantiser range: 10 to 36 of H.264's 0 to 51. Below 10 the stream
/// grows with no visible gain; capping at 36 keeps the rate control from
/// starving a frame into blocks.
const QP_RANGE: (u8, u8) = (10, 36);

/// A key frame at least every 2 seconds, so players can seek.
const KEYFRAME_SECONDS: f64 = 2.0;

/// The largest frame OpenH264 encodes: 3840 × 2160 (its encoder refuses
/// a longer side over 3840 or a shorter over 2160, H.264 level 5.1's 4K),
/// upright too (2160 × 3840).
pub const MAX_LONG_SIDE: u32 = 3840;
pub const MAX_SHORT_SIDE: u32 = 2160;

/// The smallest side the encoder takes: one macroblock.
pub const MIN_SIDE: u32 = 16;

/// Bytes the encoder needs beyond the rendered frame: the frame read back
/// (RGBA, 4 bytes a pixel), its YUV 4:2:0 copy (1.5) and OpenH264's own
/// pictures (the reference, the one being coded and its padded copies,
/// about 6 bytes a pixel at this encoder's settings), rounded up to 16.
pub fn encoder_memory_bytes(width: u32, height: u32) -> u64 {
    width as u64 * height as u64 * 16
}

/// What an encoder was asked to make, and what it wrote.
#[derive(Debug, Clone, PartialEq)]
pub struct VideoInfo {
    pub path: PathBuf,
    pub frames: usize,
    pub width: u32,
    pub height: u32,
    pub fps: f64,
    pub bytes: u64,
}

/// Why frames of `width` × `height` cannot be an H.264 video here, or
/// `None`.
pub fn size_problem(width: u32, height: u32) -> Option<String> {
    if !width.is_multiple_of(2) || !height.is_multiple_of(2) {
        return Some(format!(
            "an H.264 video needs an even width and height (its colour is stored at half \
             resolution); got {width}×{height}"
        ));
    }
    let (long, short) = (width.max(height), width.min(height));
    if short < MIN_SIDE || long > MAX_LONG_SIDE || short > MAX_SHORT_SIDE {
        return Some(format!(
            "the H.264 encoder (OpenH264) takes frames of {MIN_SIDE} pixels a side up to \
             {MAX_LONG_SIDE}×{MAX_SHORT_SIDE} (or {MAX_SHORT_SIDE}×{MAX_LONG_SIDE}); got \
             {width}×{height}"
        ));
    }
    None
}

/// An MP4 being written frame by frame into a temporary file beside its
/// destination; [`Self::finish`] renames it into place. Dropped before
/// that, it removes the temporary file.
pub struct Mp4Encoder {
    encoder: Encoder,
    writer: Option<Mp4Writer<BufWriter<File>>>,
    partial: PathBuf,
    path: PathBuf,
    width: u32,
    height: u32,
    fps: f64,
    frames: usize,
    /// The parameter sets, once the first frame has given them.
    started: bool,
}

impl Mp4Encoder {
    pub fn create(path: &Path, width: u32, height: u32, fps: f64) -> Result<Self, String> {
        if let Some(problem) = size_problem(width, height) {
            return Err(problem);
        }
        if !(fps.is_finite() && (1.0..=240.0).contains(&fps)) {
            return Err(format!("a video's frame rate must be 1 to 240, got {fps}"));
        }
        let bits = BITS_PER_PIXEL * width as f64 * height as f64 * fps;
        let config = EncoderConfig::new()
            .bitrate(BitRate::from_bps(bits.min(u32::MAX as f64) as u32))
            .max_frame_rate(FrameRate::from_hz(fps as f32))
            .rate_control_mode(RateControlMode::Quality)
            // OpenH264 refuses its non-real-time camera usage ("invalid
            // usage type"); the real-time one still codes every frame.
            .usage_type(UsageType::CameraVideoRealTime)
            // Every rendered frame is a frame of the video.
            .skip_frames(false)
            .qp(QpRange::new(QP_RANGE.0, QP_RANGE.1))
            .intra_frame_period(IntraFramePeriod::from_num_frames(
                (KEYFRAME_SECONDS * fps).round().max(1.0) as u32,
            ))
            .vui(VuiConfig::bt601());
        let encoder = Encoder::with_api_config(OpenH264API::from_source(), config)
            .map_err(|e| format!("cannot start the H.264 encoder: {e}"))?;
        let partial = crate::files::temporary_beside(path);
        let file = File::create_new(&partial)
            .map_err(|e| format!("{}: cannot create: {e}", partial.display()))?;
        let mp4_config = Mp4Config {
            major_brand: FourCC::from(*b"isom"),
            minor_version: 512,
            compatible_brands: ["isom", "iso2", "avc1", "mp41"]
                .iter()
                .map(|b| FourCC::from(<[u8; 4]>::try_from(b.as_bytes()).expect("4 bytes")))
                .collect(),
            timescale: TIMESCALE,
        };
        let writer = Mp4Writer::write_start(BufWriter::new(file), &mp4_config).map_err(|e| {
            let _ = std::fs::remove_file(&partial);
            format!("{}: cannot write MP4: {e}", partial.display())
        })?;
        Ok(Self {
            encoder,
            writer: Some(writer),
            partial,
            path: path.to_path_buf(),
            width,
            height,
            fps,
            frames: 0,
            started: false,
        })
    }

    /// Encodes `image` as the next frame.
    pub fn add_frame(&mut self, image: &ImageRgba8) -> Result<(), String> {
        if (image.width, image.height) != (self.width, self.height) {
            return Err(format!(
                "frame {} is {}×{}, the video {}×{}",
                self.frames, image.width, image.height, self.width, self.height
            ));
        }
        let yuv = YUVBuffer::from_rgba8_source(RgbaSliceU8::new(
            &image.data,
            (image.width as usize, image.height as usize),
        ));
        let stream = self
            .encoder
            .encode(&yuv)
            .map_err(|e| format!("H.264 encoder: {e}"))?;
        let frame_type = stream.frame_type();
        let mut sample = Vec::new();
        let mut sps = None;
        let mut pps = None;
        for l in 0..stream.num_layers() {
            let layer = stream.layer(l).expect("a layer below num_layers");
            for n in 0..layer.nal_count() {
                let nal = strip_start_code(layer.nal_unit(n).expect("a NAL below nal_count"));
                match nal.first().map(|b| b & 0x1f) {
                    Some(7) => sps = Some(nal.to_vec()),
                    Some(8) => pps = Some(nal.to_vec()),
                    Some(_) => {
                        sample.extend_from_slice(&(nal.len() as u32).to_be_bytes());
                        sample.extend_from_slice(nal);
                    }
                    None => {}
                }
            }
        }
        if matches!(frame_type, FrameType::Skip | FrameType::Invalid) || sample.is_empty() {
            return Err(format!(
                "the H.264 encoder gave no picture for frame {} ({frame_type:?})",
                self.frames
            ));
        }
        let writer = self.writer.as_mut().expect("the writer lives until finish");
        let fail = |e: mp4::Error| format!("{}: cannot write MP4: {e}", self.partial.display());
        if !self.started {
            let (Some(sps), Some(pps)) = (sps, pps) else {
                return Err("the H.264 encoder's first frame has no parameter sets".into());
            };
            writer
                .add_track(&TrackConfig {
                    track_type: TrackType::Video,
                    timescale: TIMESCALE,
                    language: "und".into(),
                    media_conf: MediaConfig::AvcConfig(AvcConfig {
                        width: self.width as u16,
                        height: self.height as u16,
                        seq_param_set: sps,
                        pic_param_set: pps,
                    }),
                })
                .map_err(fail)?;
            self.started = true;
        }
        let start = frame_time(self.frames, self.fps);
        let duration = (frame_time(self.frames + 1, self.fps) - start) as u32;
        writer
            .write_sample(
                1,
                &Mp4Sample {
                    start_time: start,
                    duration,
                    rendering_offset: 0,
                    is_sync: matches!(frame_type, FrameType::IDR),
                    bytes: sample.into(),
                },
            )
            .map_err(fail)?;
        self.frames += 1;
        Ok(())
    }

    /// Writes the index, flushes the file to disk and renames it into
    /// place.
    pub fn finish(mut self) -> Result<VideoInfo, String> {
        if self.frames == 0 {
            return Err("a video needs at least one frame".into());
        }
        let mut writer = self.writer.take().expect("the writer lives until finish");
        let partial = self.partial.clone();
        let result = (|| {
            writer.write_end().map_err(|e| e.to_string())?;
            let file = writer
                .into_writer()
                .into_inner()
                .map_err(|e| e.error().to_string())?;
            file.sync_all().map_err(|e| e.to_string())?;
            let bytes = file.metadata().map_err(|e| e.to_string())?.len();
            drop(file);
            std::fs::rename(&partial, &self.path).map_err(|e| e.to_string())?;
            Ok::<u64, String>(bytes)
        })()
        .map_err(|e| format!("{}: cannot write MP4: {e}", self.path.display()));
        if result.is_err() {
            let _ = std::fs::remove_file(&partial);
        }
        Ok(VideoInfo {
            path: self.path.clone(),
            frames: self.frames,
            width: self.width,
            height: self.height,
            fps: self.fps,
            bytes: result?,
        })
    }
}

impl Drop for Mp4Encoder {
    fn drop(&mut self) {
        // Not finished: the partial file is no use.
        if self.writer.take().is_some() {
            let _ = std::fs::remove_file(&self.partial);
        }
    }
}

/// Frame `index`'s start in [`TIMESCALE`] ticks, rounded to the nearest
/// tick from the exact time so that durations never drift.
fn frame_time(index: usize, fps: f64) -> u64 {
    (index as f64 * TIMESCALE as f64 / fps).round() as u64
}

/// A NAL unit without its Annex B start code (`00 00 01` or `00 00 00 01`).
fn strip_start_code(nal: &[u8]) -> &[u8] {
    if let Some(rest) = nal.strip_prefix(&[0, 0, 0, 1]) {
        rest
    } else if let Some(rest) = nal.strip_prefix(&[0, 0, 1]) {
        rest
    } else {
        nal
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A test picture: smooth gradients and a sharp-edged square, which
    /// moves with `t`.
    fn picture(width: u32, height: u32, t: u32) -> ImageRgba8 {
        let mut data = Vec::with_capacity((width * height * 4) as usize);
        for y in 0..height {
            for x in 0..width {
                let inside = (x + 2 * t).abs_diff(width / 2) < 8 && y.abs_diff(height / 2) < 8;
                let (r, g, b) = if inside {
                    (230, 40, 40)
                } else {
                    ((x * 255 / width) as u8, (y * 255 / height) as u8, 128)
                };
                data.extend_from_slice(&[r, g, b, 255]);
            }
        }
        ImageRgba8::new(width, height, data)
    }

    /// The encoder's own decoder reads the file's frames back close to the
    /// pictures (the independent check, with ffmpeg, is in
    /// tests/it/cli_camera_path.rs).
    #[test]
    fn frames_survive_encoding() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("v.mp4");
        let (w, h) = (64, 48);
        let mut encoder = Mp4Encoder::create(&path, w, h, 12.0).unwrap();
        let pictures: Vec<_> = (0..10).map(|t| picture(w, h, t)).collect();
        for p in &pictures {
            encoder.add_frame(p).unwrap();
        }
        let info = encoder.finish().unwrap();
        assert_eq!(info.frames, 10);
        assert_eq!(info.bytes, std::fs::metadata(&path).unwrap().len());
        // Nothing else left in the folder (no temporary file).
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);

        let file = File::open(&path).unwrap();
        let size = file.metadata().unwrap().len();
        let mut reader = mp4::Mp4Reader::read_header(std::io::BufReader::new(file), size).unwrap();
        let track = reader.tracks().get(&1).unwrap();
        assert_eq!((track.width(), track.height()), (64, 48));
        assert_eq!(track.sample_count(), 10);
        assert!(
            (track.frame_rate() - 12.0).abs() < 1e-6,
            "{}",
            track.frame_rate()
        );
        let sps = track.sequence_parameter_set().unwrap().to_vec();
        let pps = track.picture_parameter_set().unwrap().to_vec();
        let mut decoder = openh264::decoder::Decoder::new().unwrap();
        let annex_b = |nal: &[u8]| [&[0, 0, 0, 1][..], nal].concat();
        decoder.decode(&annex_b(&sps)).unwrap();
        decoder.decode(&annex_b(&pps)).unwrap();
        for (i, p) in pictures.iter().enumerate() {
            let sample = reader.read_sample(1, i as u32 + 1).unwrap().unwrap();
            // Length-prefixed NAL units to Annex B.
            let mut bytes = &sample.bytes[..];
            let mut stream = Vec::new();
            while bytes.len() >= 4 {
                let n = u32::from_be_bytes(bytes[..4].try_into().unwrap()) as usize;
                stream.extend(annex_b(&bytes[4..4 + n]));
                bytes = &bytes[4 + n..];
            }
            let yuv = decoder
                .decode(&stream)
                .unwrap()
                .expect("a picture per sample");
            let mut rgb = vec![0u8; (w * h * 3) as usize];
            yuv.write_rgb8(&mut rgb);
            let error: f64 = rgb
                .chunks(3)
                .zip(p.data.chunks(4))
                .map(|(a, b)| {
                    (0..3)
                        .map(|c| (a[c] as f64 - b[c] as f64).abs())
                        .sum::<f64>()
                })
                .sum::<f64>()
                / (w * h * 3) as f64;
            assert!(
                error < 6.0,
                "frame {i}: mean absolute error {error:.2} levels"
            );
        }
    }

    #[test]
    fn sizes_and_rates_h264_cannot_take_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("v.mp4");
        let e = Mp4Encoder::create(&path, 65, 48, 30.0).err().unwrap();
        assert!(e.contains("even width and height"), "{e}");
        let e = Mp4Encoder::create(&path, 8, 8, 30.0).err().unwrap();
        assert!(e.contains("16 pixels a side up to 3840×2160"), "{e}");
        let e = Mp4Encoder::create(&path, 4096, 2160, 30.0).err().unwrap();
        assert!(e.contains("got 4096×2160"), "{e}");
        assert_eq!(size_problem(2160, 3840), None);
        let e = Mp4Encoder::create(&path, 64, 48, 0.0).err().unwrap();
        assert!(e.contains("frame rate"), "{e}");
        // A video dropped before it is finished leaves nothing behind.
        let encoder = Mp4Encoder::create(&path, 64, 48, 30.0).unwrap();
        drop(encoder);
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
    }

    #[test]
    fn frame_times_do_not_drift() {
        assert_eq!(frame_time(30, 30.0), 90_000);
        assert_eq!(frame_time(1, 24.0), 3750);
        // 29.97 frames a second: 1798 frames a minute, within a tick.
        let fps = 30_000.0 / 1001.0;
        assert_eq!(
            frame_time(1798, fps),
            (1798.0 * 1001.0 * 3.0f64).round() as u64
        );
    }
}
