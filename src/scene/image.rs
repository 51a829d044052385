//! Images held as 8-bit RGBA (straight alpha), converted to float on the fly.
//!
//! Eight bits per channel keeps a 100-view 400×400 scene at 64 MB; training
//! reads a handful of pixels per ray, so the conversion costs nothing.

use std::path::Path;

use super::error::{SceneError, SceneResult};

/// An RGBA image, 8 bits per channel, straight (not premultiplied) alpha,
/// rows from the top.
#[derive(Debug, Clone, PartialEq)]
pub struct ImageRgba8 {
    pub width: u32,
    pub height: u32,
    /// `width * height * 4` bytes, row-major.
    pub data: Vec<u8>,
}

impl ImageRgba8 {
    pub fn new(width: u32, height: u32, data: Vec<u8>) -> Self {
        assert_eq!(data.len(), width as usize * height as usize * 4);
        Self {
            width,
            height,
            data,
        }
    }

    /// Colour and alpha in [0, 1] at pixel (x, y).
    pub fn rgba(&self, x: u32, y: u32) -> [f32; 4] {
        let at = (y as usize * self.width as usize + x as usize) * 4;
        let p = &self.data[at..at + 4];
        [p[0], p[1], p[2], p[3]].map(|c| c as f32 / 255.0)
    }

    /// Colour at pixel (x, y) composited over `background`.
    pub fn rgb_over(&self, x: u32, y: u32, background: [f32; 3]) -> [f32; 3] {
        let [r, g, b, a] = self.rgba(x, y);
        [
            r * a + background[0] * (1.0 - a),
            g * a + background[1] * (1.0 - a),
            b * a + background[2] * (1.0 - a),
        ]
    }

    /// The whole image composited over `background`, as RGB floats, row-major.
    pub fn to_rgb_over(&self, background: [f32; 3]) -> Vec<[f32; 3]> {
        (0..self.height)
            .flat_map(|y| (0..self.width).map(move |x| (x, y)))
            .map(|(x, y)| self.rgb_over(x, y, background))
            .collect()
    }

    /// Whether any pixel is not fully opaque.
    pub fn has_transparency(&self) -> bool {
        self.data.chunks_exact(4).any(|p| p[3] < 255)
    }

    /// The pixels `x0..x0 + width`, `y0..y0 + height` (inside the image).
    pub fn cropped(&self, x0: u32, y0: u32, width: u32, height: u32) -> Self {
        assert!(x0 + width <= self.width && y0 + height <= self.height);
        let mut data = Vec::with_capacity(width as usize * height as usize * 4);
        for y in y0..y0 + height {
            let row = (y as usize * self.width as usize + x0 as usize) * 4;
            data.extend_from_slice(&self.data[row..row + width as usize * 4]);
        }
        Self::new(width, height, data)
    }

    /// The image at 1/`factor` of its resolution: each output pixel is the
    /// area average of a `factor`×`factor` block, averaged in premultiplied
    /// colour so that transparent pixels do not bleed their (meaningless)
    /// colour into the edges. Trailing rows and columns that do not fill a
    /// block are dropped.
    pub fn downscaled(&self, factor: u32) -> Self {
        assert!(factor >= 1);
        if factor == 1 {
            return self.clone();
        }
        let (w, h) = (self.width / factor, self.height / factor);
        let count = (factor * factor) as f32;
        let mut data = Vec::with_capacity(w as usize * h as usize * 4);
        for y in 0..h {
            for x in 0..w {
                let mut premultiplied = [0f32; 3];
                let mut alpha = 0f32;
                for dy in 0..factor {
                    for dx in 0..factor {
                        let [r, g, b, a] = self.rgba(x * factor + dx, y * factor + dy);
                        premultiplied[0] += r * a;
                        premultiplied[1] += g * a;
                        premultiplied[2] += b * a;
                        alpha += a;
                    }
                }
                let mean_alpha = alpha / count;
                let colour = premultiplied.map(|c| if alpha > 0.0 { c / alpha } else { 0.0 });
                for c in colour {
                    data.push(to_u8(c));
                }
                data.push(to_u8(mean_alpha));
            }
        }
        Self::new(w, h, data)
    }

    /// Writes the image as an 8-bit RGBA PNG, encoded in memory and
    /// written through a temporary file (a failed write leaves any file
    /// already at `path` whole).
    pub fn save_png(&self, path: &Path) -> SceneResult<()> {
        use image::ImageEncoder;
        let mut bytes = Vec::new();
        image::codecs::png::PngEncoder::new(&mut bytes)
            .write_image(
                &self.data,
                self.width,
                self.height,
                image::ExtendedColorType::Rgba8,
            )
            .map_err(|e| SceneError::new(path, format!("cannot encode PNG: {e}")))?;
        crate::files::write_bytes_atomically(path, &bytes)
            .map_err(|e| SceneError::new(path, format!("cannot write PNG: {e}")))
    }
}

/// A value in [0, 1] to 8 bits, rounded to nearest.
pub fn to_u8(value: f32) -> u8 {
    (value.clamp(0.0, 1.0) * 255.0).round() as u8
}

/// A decoded image file, with whether the file itself carried an alpha
/// channel.
#[derive(Debug, Clone)]
pub struct LoadedImage {
    pub image: ImageRgba8,
    pub file_has_alpha: bool,
}

/// Reads a PNG (8- or 16-bit) or JPEG, RGB or RGBA, grey or grey-alpha, into
/// 8-bit RGBA, turned upright by its EXIF orientation when it has one.
/// 16-bit channels are rounded to 8 bits. The memory the decode needs is
/// checked against what the process has available before any of it is
/// allocated: see [`load_image_sharing`].
pub fn load_image(path: &Path) -> SceneResult<LoadedImage> {
    load_image_sharing(path, 1)
}

/// [`load_image`] for one of `decodes_at_once` images decoded side by side
/// (a scene decodes its images in parallel), each of which may take only
/// its share of the memory available. A small file can hold a huge image
/// (a 30000×30000 PNG of one colour compresses to a few megabytes and
/// decodes to gigabytes), so the size in the file's header, not the file's
/// length, decides: an image whose decode would not fit is refused with its
/// size and the memory it needs, instead of aborting the process when an
/// allocation fails.
pub fn load_image_sharing(path: &Path, decodes_at_once: usize) -> SceneResult<LoadedImage> {
    // Opened as a regular file only, without blocking: a named pipe or a
    // device named like an image is refused, not read forever.
    let (file, file_length) =
        crate::files::open_regular(path).map_err(|problem| match problem {
            crate::files::Unreadable::NotFound => {
                SceneError::not_found(path, "image file not found")
            }
            problem => SceneError::unreadable(path, format!("the image file is {problem}")),
        })?;
    let mut reader = image::ImageReader::new(std::io::BufReader::new(file))
        .with_guessed_format()
        .map_err(|e| SceneError::unreadable(path, format!("cannot read image: {e}")))?;
    let budget = MemoryBudget::now(decodes_at_once);
    // The JPEG decoder reads the whole file into memory before its header.
    let is_jpeg = reader.format() == Some(image::ImageFormat::Jpeg);
    if is_jpeg {
        budget.check(path, None, file_length)?;
    }
    // The decoders' own buffers (the PNG decoder's chunk and row buffers)
    // stay within the share too.
    let mut limits = image::Limits::default();
    if let Some(share) = budget.share() {
        limits.max_alloc = Some(share);
    }
    reader.limits(limits.clone());
    // Phones store JPEGs in the sensor's orientation with an EXIF tag
    // saying how to turn them; the intrinsics COLMAP and other tools
    // estimate are for the turned image, as every viewer shows it.
    let decode_error = |e: image::ImageError| match e {
        image::ImageError::Limits(limit) => SceneError::too_large(
            path,
            format!(
                "cannot decode image: {limit} ({})",
                budget.describe_available()
            ),
        ),
        e => SceneError::new(path, format!("cannot decode image: {e}")),
    };
    let mut decoder = reader.into_decoder().map_err(decode_error)?;
    let orientation = image::ImageDecoder::orientation(&mut decoder).map_err(decode_error)?;
    let (width, height) = image::ImageDecoder::dimensions(&decoder);
    let colour = image::ImageDecoder::color_type(&decoder);
    let jpeg_file = if is_jpeg { Some(file_length) } else { None };
    let needed = decode_memory(&decoder, jpeg_file, orientation);
    budget.check(path, Some((width, height)), needed)?;
    // The size is now known to fit: the decoder may not exceed it.
    limits.max_image_width = Some(width);
    limits.max_image_height = Some(height);
    image::ImageDecoder::set_limits(&mut decoder, limits).map_err(decode_error)?;
    let mut decoded = image::DynamicImage::from_decoder(decoder).map_err(decode_error)?;
    decoded.apply_orientation(orientation);
    let file_has_alpha = colour.has_alpha();
    let rgba = decoded.into_rgba8();
    let (width, height) = rgba.dimensions();
    Ok(LoadedImage {
        image: ImageRgba8::new(width, height, rgba.into_raw()),
        file_has_alpha,
    })
}

/// Bytes a decode of `decoder`'s image holds at its peak: the decoded
/// pixels in the file's own layout, the 8-bit RGBA copy they are turned
/// into (unless they are that already), a turned copy when the EXIF
/// orientation turns or mirrors the image, and for a JPEG (of
/// `jpeg_file` bytes) the file itself and the decoder's working planes.
fn decode_memory(
    decoder: &impl image::ImageDecoder,
    jpeg_file: Option<u64>,
    orientation: image::metadata::Orientation,
) -> u64 {
    let (width, height) = decoder.dimensions();
    let decoded = decoder.total_bytes();
    let rgba = u64::from(width) * u64::from(height) * 4;
    let mut needed = decoded;
    if decoder.color_type() != image::ColorType::Rgba8 {
        needed = needed.saturating_add(rgba);
    }
    if orientation != image::metadata::Orientation::NoTransforms {
        needed = needed.saturating_add(rgba);
    }
    if let Some(file_length) = jpeg_file {
        needed = needed.saturating_add(file_length).saturating_add(decoded);
    }
    needed
}

/// The memory one of several decodes running side by side may use.
struct MemoryBudget {
    /// What the process has available, when known.
    available: Option<u64>,
    decodes_at_once: u64,
}

impl MemoryBudget {
    fn now(decodes_at_once: usize) -> Self {
        Self {
            available: crate::files::available_memory(),
            decodes_at_once: decodes_at_once.max(1) as u64,
        }
    }

    /// This decode's share of the available memory.
    fn share(&self) -> Option<u64> {
        self.available.map(|a| a / self.decodes_at_once)
    }

    fn describe_available(&self) -> String {
        match (self.available, self.share()) {
            (Some(all), Some(share)) if self.decodes_at_once > 1 => format!(
                "{} available to each of the {} images decoded at once, {} in all",
                crate::files::human_bytes(share),
                self.decodes_at_once,
                crate::files::human_bytes(all)
            ),
            (Some(all), _) => format!("{} available", crate::files::human_bytes(all)),
            _ => "the memory available is unknown".into(),
        }
    }

    /// Refuses `needed` bytes beyond this decode's share, naming the image
    /// (and its size in pixels, when known) and the memory on both sides.
    fn check(&self, path: &Path, pixels: Option<(u32, u32)>, needed: u64) -> SceneResult<()> {
        let Some(share) = self.share() else {
            return Ok(());
        };
        if needed <= share {
            return Ok(());
        }
        let needed_words = crate::files::human_bytes(needed);
        let what = match pixels {
            Some((width, height)) => format!(
                "{width}×{height} pixels, which need about {needed_words} of memory to decode"
            ),
            None => format!("a {needed_words} file, which the JPEG decoder reads whole"),
        };
        Err(SceneError::too_large(
            path,
            format!(
                "{what}, more than the {}; make the image smaller (zrak decodes each image at \
                 full size before any --downscale) or give zrak more memory",
                self.describe_available()
            ),
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn downscale_averages_premultiplied_colour() {
        // A 2×2 block: one opaque red pixel, three fully transparent green
        // ones. Straight averaging would turn the edge green; premultiplied
        // averaging keeps it red with a quarter coverage.
        let data = vec![
            255, 0, 0, 255, //
            0, 255, 0, 0, //
            0, 255, 0, 0, //
            0, 255, 0, 0,
        ];
        let image = ImageRgba8::new(2, 2, data);
        let small = image.downscaled(2);
        assert_eq!((small.width, small.height), (1, 1));
        assert_eq!(small.data, vec![255, 0, 0, 64]);
    }

    #[test]
    fn downscale_of_opaque_image_is_plain_mean() {
        let data = vec![
            0, 0, 0, 255, 100, 100, 100, 255, //
            200, 200, 200, 255, 50, 50, 50, 255,
        ];
        let small = ImageRgba8::new(2, 2, data).downscaled(2);
        // (0 + 100 + 200 + 50) / 4 = 87.5, within one rounding step.
        assert!((small.data[0] as i32 - 88).abs() <= 1);
        assert_eq!(small.data[3], 255);
    }

    #[test]
    fn compositing_over_background() {
        let image = ImageRgba8::new(1, 1, vec![255, 0, 0, 51]);
        let [r, g, b] = image.rgb_over(0, 0, [1.0, 1.0, 1.0]);
        assert!((r - 1.0).abs() < 1e-6);
        assert!((g - 0.8).abs() < 1e-6 && (b - 0.8).abs() < 1e-6);
    }

    /// A phone JPEG stored sideways with EXIF orientation 6 (turn 90°
    /// clockwise to view) loads upright: 4×2 stored, 2×4 loaded.
    #[test]
    fn jpeg_exif_orientation_is_applied() {
        use image::ImageEncoder;
        // A little-endian TIFF header and one IFD entry: tag 0x0112
        // (Orientation), type 3 (SHORT), count 1, value 6.
        let mut exif = vec![0x49, 0x49, 42, 0, 8, 0, 0, 0, 1, 0];
        exif.extend([0x12, 0x01, 3, 0, 1, 0, 0, 0, 6, 0, 0, 0]);
        exif.extend([0, 0, 0, 0]);
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("sideways.jpg");
        let file = std::fs::File::create(&path).unwrap();
        let mut encoder = image::codecs::jpeg::JpegEncoder::new(file);
        encoder.set_exif_metadata(exif).unwrap();
        encoder
            .write_image(&[128u8; 4 * 2 * 3], 4, 2, image::ExtendedColorType::Rgb8)
            .unwrap();
        let loaded = load_image(&path).unwrap();
        assert_eq!((loaded.image.width, loaded.image.height), (2, 4));
    }
}
