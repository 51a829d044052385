//! Peak signal-to-noise ratio for data range 1.
//!
//! The mean squared error is taken over every pixel and channel of the image
//! (not per channel and then averaged), accumulated in f64, as in
//! scikit-image's `peak_signal_noise_ratio(..., data_range=1.0)` and the
//! NeRF evaluation code.

use super::{MetricsError, RgbImage, check_pair};

/// The smallest MSE the PSNR formula sees. Identical images have MSE 0 and
/// an infinite PSNR, which would poison means and cannot be written to JSON;
/// flooring the MSE caps the PSNR at [`PSNR_CAP_DB`] instead. 1e-10 is far
/// below anything a trained model reaches (8-bit quantisation alone is
/// ~1e-6, i.e. ~59 dB), so the cap never touches a real score.
pub const MSE_FLOOR: f64 = 1e-10;

/// The largest PSNR reported: `-10 * log10(MSE_FLOOR)`.
pub const PSNR_CAP_DB: f64 = 100.0;

/// Mean squared error over all pixels and channels.
pub fn mse(a: &RgbImage, b: &RgbImage) -> Result<f64, MetricsError> {
    check_pair(a, b)?;
    let sum: f64 = a
        .pixels
        .iter()
        .zip(&b.pixels)
        .map(|(p, q)| {
            (0..3)
                .map(|c| {
                    let d = p[c] as f64 - q[c] as f64;
                    d * d
                })
                .sum::<f64>()
        })
        .sum();
    Ok(sum / (a.pixels.len() * 3) as f64)
}

/// Mean squared error over the pixels that count (`counts`, row-major,
/// one per pixel) and their channels; NaN when none counts.
pub fn mse_masked(a: &RgbImage, b: &RgbImage, counts: &[bool]) -> Result<f64, MetricsError> {
    check_pair(a, b)?;
    if counts.len() != a.pixels.len() {
        // A mask of another size: told as an image of one row.
        return Err(MetricsError::SizeMismatch {
            a_width: a.width,
            a_height: a.height,
            b_width: counts.len(),
            b_height: 1,
        });
    }
    let mut sum = 0f64;
    let mut counted = 0usize;
    for ((p, q), _) in a
        .pixels
        .iter()
        .zip(&b.pixels)
        .zip(counts)
        .filter(|(_, c)| **c)
    {
        for c in 0..3 {
            let d = p[c] as f64 - q[c] as f64;
            sum += d * d;
        }
        counted += 1;
    }
    Ok(if counted == 0 {
        f64::NAN
    } else {
        sum / (counted * 3) as f64
    })
}

/// PSNR in dB for data range 1, capped at [`PSNR_CAP_DB`].
pub fn psnr(a: &RgbImage, b: &RgbImage) -> Result<f64, MetricsError> {
    Ok(psnr_from_mse(mse(a, b)?))
}

/// PSNR in dB of a mean squared error (data range 1), capped at
/// [`PSNR_CAP_DB`]; training reports its loss through this. A NaN MSE stays
/// NaN: a diverged run must not read as a perfect one.
pub fn psnr_from_mse(mse: f64) -> f64 {
    if mse.is_nan() {
        f64::NAN
    } else if mse <= MSE_FLOOR {
        // Returned directly so that the cap is exactly the constant, not
        // whatever log10 rounds 1e-10 to.
        PSNR_CAP_DB
    } else {
        -10.0 * mse.log10()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn texture(x: usize, y: usize) -> [f32; 3] {
        let (x, y) = (x as f32, y as f32);
        [
            0.2 + 0.01 * x,
            0.5 + 0.3 * (0.4 * y).sin(),
            0.1 + 0.02 * (x + y),
        ]
    }

    #[test]
    fn identical_images_hit_the_cap() {
        let a = RgbImage::from_fn(20, 13, texture);
        assert_eq!(psnr(&a, &a).unwrap(), PSNR_CAP_DB);
        assert_eq!(psnr_from_mse(0.0), PSNR_CAP_DB);
        assert_eq!(psnr_from_mse(MSE_FLOOR), PSNR_CAP_DB);
        assert!((-10.0 * MSE_FLOOR.log10() - PSNR_CAP_DB).abs() < 1e-9);
    }

    #[test]
    fn formula() {
        assert!((psnr_from_mse(0.01) - 20.0).abs() < 1e-9);
        assert!((psnr_from_mse(1.0)).abs() < 1e-12);
        assert!(psnr_from_mse(f64::NAN).is_nan());
    }

    #[test]
    fn constant_offset_of_a_tenth_is_20_db() {
        // 0.1 is not an f32: each stored difference is 0.1 to within an f32
        // rounding step of the sum (≤ 3e-8 absolute for values below 0.5),
        // i.e. ≤ 3e-7 relative, which moves the PSNR by at most
        // 20/ln(10) * 3e-7 ≈ 3e-6 dB. The formula itself is checked to 1e-9
        // in `formula`, and an exactly representable offset below.
        let a = RgbImage::from_fn(17, 9, |x, y| {
            let v = ((x + 2 * y) % 16) as f32 / 40.0;
            [v, 0.4 - v, 0.5 * v]
        });
        let b = RgbImage::from_fn(17, 9, |x, y| a.get(x, y).map(|c| c + 0.1));
        assert!((psnr(&a, &b).unwrap() - 20.0).abs() < 1e-5);
        assert!((psnr(&b, &a).unwrap() - 20.0).abs() < 1e-5);
    }

    #[test]
    fn exactly_representable_offset_is_exact() {
        // Multiples of 1/64 plus 1/8 are exact in f32, so MSE = 1/64 exactly
        // and PSNR = 10 log10(64).
        let a = RgbImage::from_fn(16, 16, |x, y| {
            let v = ((x * 3 + y) % 48) as f32 / 64.0;
            [v, 0.75 - v, 0.125]
        });
        let b = RgbImage::from_fn(16, 16, |x, y| a.get(x, y).map(|c| c + 0.125));
        assert_eq!(mse(&a, &b).unwrap(), 1.0 / 64.0);
        assert!((psnr(&a, &b).unwrap() - 10.0 * 64f64.log10()).abs() < 1e-12);
    }

    #[test]
    fn symmetric() {
        let a = RgbImage::from_fn(20, 13, texture);
        let b = RgbImage::from_fn(20, 13, |x, y| texture(y % 20, x % 13));
        assert_eq!(psnr(&a, &b).unwrap(), psnr(&b, &a).unwrap());
    }

    #[test]
    fn mismatched_sizes_are_an_error() {
        let a = RgbImage::from_fn(20, 13, texture);
        let b = RgbImage::from_fn(13, 20, texture);
        assert!(matches!(
            psnr(&a, &b),
            Err(MetricsError::SizeMismatch { .. })
        ));
    }
}
