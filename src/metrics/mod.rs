//! Image metrics: PSNR and SSIM as the NeRF reference evaluation computes
//! them.
//!
//! Both work on [`RgbImage`], float RGB in [0, 1] with data range 1. The
//! reference protocol scores RGBA renders composited on white, so
//! [`RgbImage::from_rgba8_over`] with [`WHITE`] is the usual way in.
//! Everything is accumulated in f64: the f32 pixels are exact in f64, and the
//! figures then agree with scikit-image to ~1e-15 (see the tests in
//! `ssim.rs`).

mod psnr;
mod ssim;

use serde::{Deserialize, Serialize};
use thiserror::Error;

use crate::scene::ImageRgba8;

pub use psnr::{MSE_FLOOR, PSNR_CAP_DB, mse, mse_masked, psnr, psnr_from_mse};
pub use ssim::{SSIM_WINDOW, ssim, ssim_masked};

/// The background the reference protocol composites RGBA images on.
pub const WHITE: [f32; 3] = [1.0, 1.0, 1.0];

/// Why a metric could not be computed.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum MetricsError {
    #[error("image of {width}×{height} needs {expected} pixels, got {actual}")]
    PixelCount {
        width: usize,
        height: usize,
        expected: usize,
        actual: usize,
    },
    #[error("images differ in size: {a_width}×{a_height} vs {b_width}×{b_height}")]
    SizeMismatch {
        a_width: usize,
        a_height: usize,
        b_width: usize,
        b_height: usize,
    },
    #[error("image of {width}×{height} is smaller than the {min}×{min} SSIM window")]
    TooSmall {
        width: usize,
        height: usize,
        min: usize,
    },
    #[error("image has no pixels")]
    Empty,
    // A diverged model renders NaN; reporting that as an error keeps it from
    // being averaged into a table (or, through the MSE floor, scored 100 dB).
    #[error("image contains a NaN or infinite value")]
    NonFinite,
}

/// An RGB image with float channels (nominally in [0, 1]), row-major from
/// the top.
#[derive(Debug, Clone, PartialEq)]
pub struct RgbImage {
    pub width: usize,
    pub height: usize,
    /// `width * height` pixels, row-major.
    pub pixels: Vec<[f32; 3]>,
}

impl RgbImage {
    /// An image from its pixels; fails if there are not `width * height`.
    pub fn new(width: usize, height: usize, pixels: Vec<[f32; 3]>) -> Result<Self, MetricsError> {
        let image = Self {
            width,
            height,
            pixels,
        };
        image.check_pixel_count()?;
        Ok(image)
    }

    /// An image whose pixel (x, y) is `f(x, y)`.
    pub fn from_fn(
        width: usize,
        height: usize,
        mut f: impl FnMut(usize, usize) -> [f32; 3],
    ) -> Self {
        let pixels = (0..height)
            .flat_map(|y| (0..width).map(move |x| (x, y)))
            .map(|(x, y)| f(x, y))
            .collect();
        Self {
            width,
            height,
            pixels,
        }
    }

    /// An 8-bit RGBA image composited over `background` (use [`WHITE`] for
    /// the reference protocol).
    pub fn from_rgba8_over(image: &ImageRgba8, background: [f32; 3]) -> Self {
        Self {
            width: image.width as usize,
            height: image.height as usize,
            pixels: image.to_rgb_over(background),
        }
    }

    /// Colour at pixel (x, y).
    pub fn get(&self, x: usize, y: usize) -> [f32; 3] {
        self.pixels[y * self.width + x]
    }

    // The fields are public, so a struct built by hand can disagree with its
    // own size; catch that here rather than panic on an index later.
    fn check_pixel_count(&self) -> Result<(), MetricsError> {
        let expected = self.width.checked_mul(self.height);
        if expected == Some(self.pixels.len()) {
            Ok(())
        } else {
            Err(MetricsError::PixelCount {
                width: self.width,
                height: self.height,
                expected: expected.unwrap_or(usize::MAX),
                actual: self.pixels.len(),
            })
        }
    }

    fn check_finite(&self) -> Result<(), MetricsError> {
        if self.pixels.iter().flatten().all(|c| c.is_finite()) {
            Ok(())
        } else {
            Err(MetricsError::NonFinite)
        }
    }
}

/// Fails unless both images have the same width and height.
pub fn check_same_size(a: &RgbImage, b: &RgbImage) -> Result<(), MetricsError> {
    if (a.width, a.height) == (b.width, b.height) {
        Ok(())
    } else {
        Err(MetricsError::SizeMismatch {
            a_width: a.width,
            a_height: a.height,
            b_width: b.width,
            b_height: b.height,
        })
    }
}

/// The checks every metric needs before it may index both images alike.
fn check_pair(a: &RgbImage, b: &RgbImage) -> Result<(), MetricsError> {
    check_same_size(a, b)?;
    a.check_pixel_count()?;
    b.check_pixel_count()?;
    if a.pixels.is_empty() {
        return Err(MetricsError::Empty);
    }
    a.check_finite()?;
    b.check_finite()
}

/// The per-image scores the evaluation reports.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ImageScores {
    /// Decibels, at most [`PSNR_CAP_DB`].
    pub psnr: f64,
    /// In [-1, 1]; 1 for identical images.
    pub ssim: f64,
}

/// PSNR and SSIM of `a` against `b` (the order does not matter; both are
/// symmetric).
pub fn score(a: &RgbImage, b: &RgbImage) -> Result<ImageScores, MetricsError> {
    Ok(ImageScores {
        psnr: psnr(a, b)?,
        ssim: ssim(a, b)?,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn constructor_checks_pixel_count() {
        assert!(RgbImage::new(2, 2, vec![[0.0; 3]; 4]).is_ok());
        assert!(matches!(
            RgbImage::new(2, 2, vec![[0.0; 3]; 3]),
            Err(MetricsError::PixelCount {
                expected: 4,
                actual: 3,
                ..
            })
        ));
    }

    #[test]
    fn rgba_is_composited_on_white() {
        // Opaque red, fully transparent (with a meaningless green colour),
        // and half-transparent black.
        let data = vec![
            255, 0, 0, 255, //
            0, 255, 0, 0, //
            0, 0, 0, 128,
        ];
        let rgba = ImageRgba8::new(3, 1, data);
        let image = RgbImage::from_rgba8_over(&rgba, WHITE);
        assert_eq!((image.width, image.height), (3, 1));
        assert_eq!(image.get(0, 0), [1.0, 0.0, 0.0]);
        assert_eq!(image.get(1, 0), [1.0, 1.0, 1.0]);
        let grey = 1.0 - 128.0 / 255.0;
        for c in image.get(2, 0) {
            assert!((c - grey).abs() < 1e-6);
        }
    }

    #[test]
    fn transparent_render_scores_as_white_background() {
        // An empty (fully transparent) render against a white ground truth is
        // perfect under the white-background protocol.
        let rgba = ImageRgba8::new(12, 12, vec![0; 12 * 12 * 4]);
        let render = RgbImage::from_rgba8_over(&rgba, WHITE);
        let white = RgbImage::from_fn(12, 12, |_, _| WHITE);
        let scores = score(&render, &white).unwrap();
        assert_eq!(scores.psnr, PSNR_CAP_DB);
        assert!((scores.ssim - 1.0).abs() < 1e-12);
    }

    #[test]
    fn mismatched_sizes_are_an_error() {
        let a = RgbImage::from_fn(16, 16, |_, _| [0.5; 3]);
        let b = RgbImage::from_fn(16, 15, |_, _| [0.5; 3]);
        assert!(matches!(
            check_same_size(&a, &b),
            Err(MetricsError::SizeMismatch { .. })
        ));
        assert!(matches!(
            score(&a, &b),
            Err(MetricsError::SizeMismatch { .. })
        ));
    }

    #[test]
    fn inconsistent_struct_is_an_error_not_a_panic() {
        let a = RgbImage::from_fn(12, 12, |_, _| [0.5; 3]);
        let mut b = a.clone();
        b.pixels.pop();
        assert!(matches!(psnr(&a, &b), Err(MetricsError::PixelCount { .. })));
        assert!(matches!(ssim(&a, &b), Err(MetricsError::PixelCount { .. })));
    }

    #[test]
    fn nan_is_an_error() {
        let a = RgbImage::from_fn(12, 12, |_, _| [0.5; 3]);
        let mut b = a.clone();
        b.pixels[7][1] = f32::NAN;
        assert_eq!(psnr(&a, &b), Err(MetricsError::NonFinite));
        assert_eq!(ssim(&b, &a), Err(MetricsError::NonFinite));
    }

    #[test]
    fn empty_images_are_an_error() {
        let a = RgbImage::new(0, 5, Vec::new()).unwrap();
        assert_eq!(psnr(&a, &a), Err(MetricsError::Empty));
    }

    #[test]
    fn scores_serialise_to_json() {
        let scores = ImageScores {
            psnr: 30.5,
            ssim: 0.9,
        };
        let json = serde_json::to_string(&scores).unwrap();
        assert_eq!(json, r#"{"psnr":30.5,"ssim":0.9}"#);
    }
}
