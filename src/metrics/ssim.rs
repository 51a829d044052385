//! Structural similarity (Wang et al. 2004) as the NeRF and Mip-NeRF
//! evaluations compute it.
//!
//! - 11×11 Gaussian window, σ = 1.5, normalised to sum 1, applied separably;
//! - 'valid' filtering: no padding, so the SSIM map is (H−10)×(W−10) and
//!   border pixels only ever contribute through windows that fit;
//! - C1 = (0.01 L)², C2 = (0.03 L)² with data range L = 1;
//! - population moments: σx² = E[x²] − E[x]², σxy = E[xy] − E[x]E[y];
//! - each channel on its own, then the mean over the map and the channels.
//!
//! This equals scikit-image's `structural_similarity(a, b, channel_axis=-1,
//! data_range=1.0, gaussian_weights=True, sigma=1.5,
//! use_sample_covariance=False)`: its Gaussian is truncated at 3.5σ, a radius
//! of 5, and it crops a 5-pixel border from a reflect-padded map, which
//! leaves exactly the windows that fit. `tests/reference/metrics_reference.py`
//! checks that against a direct numpy implementation (they agree to 1e-15).

use rayon::prelude::*;

use super::{MetricsError, RgbImage, check_pair};

/// Side of the (square) Gaussian window; images must be at least this big.
pub const SSIM_WINDOW: usize = 11;

const RADIUS: usize = SSIM_WINDOW / 2;
const SIGMA: f64 = 1.5;
const K1: f64 = 0.01;
const K2: f64 = 0.03;
const DATA_RANGE: f64 = 1.0;
const C1: f64 = (K1 * DATA_RANGE) * (K1 * DATA_RANGE);
const C2: f64 = (K2 * DATA_RANGE) * (K2 * DATA_RANGE);

/// The windowed moments are kept as five planes side by side: means of x and
/// y, of x² and y², and of xy.
const MOMENTS: usize = 5;

/// Mean SSIM of two RGB images of the same size, at least 11×11.
pub fn ssim(a: &RgbImage, b: &RgbImage) -> Result<f64, MetricsError> {
    check_pair(a, b)?;
    if a.width < SSIM_WINDOW || a.height < SSIM_WINDOW {
        return Err(MetricsError::TooSmall {
            width: a.width,
            height: a.height,
            min: SSIM_WINDOW,
        });
    }
    let taps = gaussian_taps();
    let per_channel: Vec<f64> = (0..3)
        .into_par_iter()
        .map(|c| channel_ssim(a, b, c, &taps, None))
        .collect();
    Ok(per_channel.iter().sum::<f64>() / 3.0)
}

/// [`ssim`] over the windows that lie wholly on pixels that count
/// (`counts`, row-major, one per pixel): a pixel left out never enters
/// the score, not even at the edge of a window. NaN when no window fits
/// among the counted pixels.
pub fn ssim_masked(a: &RgbImage, b: &RgbImage, counts: &[bool]) -> Result<f64, MetricsError> {
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
    if a.width < SSIM_WINDOW || a.height < SSIM_WINDOW {
        return Err(MetricsError::TooSmall {
            width: a.width,
            height: a.height,
            min: SSIM_WINDOW,
        });
    }
    let windows = windows_on_counted_pixels(a.width, a.height, counts);
    if !windows.contains(&true) {
        return Ok(f64::NAN);
    }
    let taps = gaussian_taps();
    let per_channel: Vec<f64> = (0..3)
        .into_par_iter()
        .map(|c| channel_ssim(a, b, c, &taps, Some(&windows)))
        .collect();
    Ok(per_channel.iter().sum::<f64>() / 3.0)
}

/// For each window that fits ('valid' filtering, (H−10)×(W−10) of them,
/// row-major), whether every pixel under it counts: a summed-area table of
/// the pixels left out, read at each window's corners.
fn windows_on_counted_pixels(width: usize, height: usize, counts: &[bool]) -> Vec<bool> {
    let mut left_out = vec![0u32; (width + 1) * (height + 1)];
    for y in 0..height {
        for x in 0..width {
            let here = u32::from(!counts[y * width + x]);
            left_out[(y + 1) * (width + 1) + x + 1] =
                here + left_out[y * (width + 1) + x + 1] + left_out[(y + 1) * (width + 1) + x]
                    - left_out[y * (width + 1) + x];
        }
    }
    let at = |x: usize, y: usize| left_out[y * (width + 1) + x];
    let (out_width, out_height) = (width - 2 * RADIUS, height - 2 * RADIUS);
    (0..out_height)
        .flat_map(|i| (0..out_width).map(move |j| (j, i)))
        .map(|(j, i)| {
            let (x1, y1) = (j + SSIM_WINDOW, i + SSIM_WINDOW);
            at(x1, y1) + at(j, i) - at(j, y1) - at(x1, i) == 0
        })
        .collect()
}

/// The 1-D Gaussian, normalised so the 2-D window sums to 1.
fn gaussian_taps() -> [f64; SSIM_WINDOW] {
    let mut taps = [0.0; SSIM_WINDOW];
    for (i, t) in taps.iter_mut().enumerate() {
        let d = i as f64 - RADIUS as f64;
        *t = (-0.5 * (d / SIGMA) * (d / SIGMA)).exp();
    }
    let sum: f64 = taps.iter().sum();
    taps.map(|t| t / sum)
}

/// Outputs computed together: a fixed-size block the compiler keeps in
/// vector registers. Rows are padded to a multiple of it so there is no
/// scalar tail; the padding columns are computed and then ignored.
const LANES: usize = 8;

/// One block of filter outputs, `Σk taps[k] · tap(k)[l]`. The window is
/// symmetric, so mirrored inputs are added before their shared weight is
/// applied (centre first, then outwards): six multiplications instead of
/// eleven. The sum lives in a local array, not
/// behind a reference, so that it stays in registers.
#[inline(always)]
fn filter_block<'a>(
    taps: &[f64; SSIM_WINDOW],
    tap: impl Fn(usize) -> &'a [f64; LANES],
) -> [f64; LANES] {
    let centre = tap(RADIUS);
    let mut acc = [0.0; LANES];
    for l in 0..LANES {
        acc[l] = taps[RADIUS] * centre[l];
    }
    for k in 1..=RADIUS {
        let (before, after) = (tap(RADIUS - k), tap(RADIUS + k));
        for l in 0..LANES {
            acc[l] += taps[RADIUS + k] * (before[l] + after[l]);
        }
    }
    acc
}

/// A sum in `LANES` interleaved partial sums, then across them: a fixed
/// order (so the result is the same on every run) that does not chain every
/// addition on the previous one.
fn sum_in_lanes(values: &[f64]) -> f64 {
    let mut partial = [0.0f64; LANES];
    let blocks = values.chunks_exact(LANES);
    let tail: f64 = blocks.remainder().iter().sum();
    for block in blocks {
        for l in 0..LANES {
            partial[l] += block[l];
        }
    }
    partial.iter().sum::<f64>() + tail
}

/// Mean of the SSIM map of one channel, over the map entries `windows`
/// selects (row-major) when given, else over all of them.
fn channel_ssim(
    a: &RgbImage,
    b: &RgbImage,
    channel: usize,
    taps: &[f64; SSIM_WINDOW],
    windows: Option<&[bool]>,
) -> f64 {
    let (width, height) = (a.width, a.height);
    let out_width = width - 2 * RADIUS;
    let out_height = height - 2 * RADIUS;
    let padded = out_width.next_multiple_of(LANES);
    let run = padded + 2 * RADIUS;

    // Horizontal pass: every input row filtered along x, for each moment,
    // as five consecutive runs of `padded` values. One flat buffer: per-row
    // allocations of this size made glibc return and re-fault pages on every
    // call, which cost more than the filtering.
    let plane = MOMENTS * padded;
    let mut rows = vec![0.0f64; height * plane];
    rows.par_chunks_mut(plane).enumerate().for_each_init(
        // Per worker: the five signals whose local means SSIM needs (x, y,
        // x², y², xy), each in a run of `run` whose zero tail is never
        // written.
        || vec![0.0f64; MOMENTS * run],
        |signals, (row, out)| {
            let pixels = row * width..(row + 1) * width;
            let (pa, pb) = (&a.pixels[pixels.clone()], &b.pixels[pixels]);
            let (sx, rest) = signals.split_at_mut(run);
            let (sy, rest) = rest.split_at_mut(run);
            let (sxx, rest) = rest.split_at_mut(run);
            let (syy, sxy) = rest.split_at_mut(run);
            for (i, (p, q)) in pa.iter().zip(pb).enumerate() {
                let (x, y) = (p[channel] as f64, q[channel] as f64);
                sx[i] = x;
                sy[i] = y;
                sxx[i] = x * x;
                syy[i] = y * y;
                sxy[i] = x * y;
            }
            for (src, dst) in signals.chunks_exact(run).zip(out.chunks_exact_mut(padded)) {
                for (block, dst) in dst.chunks_exact_mut(LANES).enumerate() {
                    let at = block * LANES;
                    let sums =
                        filter_block(taps, |k| src[at + k..at + k + LANES].try_into().unwrap());
                    dst.copy_from_slice(&sums);
                }
            }
        },
    );

    // Vertical pass, fused with the SSIM formula so the filtered moments are
    // never stored whole: per worker, one row of moments and one row of the
    // SSIM map.
    let row_sums: Vec<f64> = (0..out_height)
        .into_par_iter()
        .map_init(
            || (vec![0.0f64; plane], vec![0.0f64; padded]),
            |(moments, map), i| {
                let window = &rows[i * plane..(i + SSIM_WINDOW) * plane];
                for (block, out) in moments.chunks_exact_mut(LANES).enumerate() {
                    let at = block * LANES;
                    let sums = filter_block(taps, |k| {
                        window[k * plane + at..k * plane + at + LANES]
                            .try_into()
                            .unwrap()
                    });
                    out.copy_from_slice(&sums);
                }
                let (mx, rest) = moments.split_at(padded);
                let (my, rest) = rest.split_at(padded);
                let (mxx, rest) = rest.split_at(padded);
                let (myy, mxy) = rest.split_at(padded);
                // Elementwise, with no running sum in the loop, so that the
                // divisions vectorise too.
                for j in 0..padded {
                    let (ux, uy) = (mx[j], my[j]);
                    let vx = mxx[j] - ux * ux;
                    let vy = myy[j] - uy * uy;
                    let vxy = mxy[j] - ux * uy;
                    map[j] = ((2.0 * ux * uy + C1) * (2.0 * vxy + C2))
                        / ((ux * ux + uy * uy + C1) * (vx + vy + C2));
                }
                if let Some(windows) = windows {
                    let selected = &windows[i * out_width..(i + 1) * out_width];
                    for (value, &kept) in map.iter_mut().zip(selected) {
                        if !kept {
                            *value = 0.0;
                        }
                    }
                }
                sum_in_lanes(&map[..out_width])
            },
        )
        .collect();
    let scored = windows.map_or(out_width * out_height, |w| {
        w.iter().filter(|&&kept| kept).count()
    });
    // Summed in row order, not by rayon's reduction tree, so the result does
    // not depend on how work was split between threads.
    row_sums.iter().sum::<f64>() / scored as f64
}

#[cfg(test)]
mod tests {
    use super::*;

    // The test images, built by the same formulas as
    // tests/reference/metrics_reference.py: each value computed in f64 (the
    // same libm sin/cos Python's math module calls) and then rounded to f32.

    fn hash32(x: u32, y: u32, c: u32, seed: u32) -> u32 {
        let mut h = x.wrapping_mul(0x9E37_79B1)
            ^ y.wrapping_mul(0x85EB_CA77)
            ^ c.wrapping_mul(0xC2B2_AE3D)
            ^ seed.wrapping_mul(0x27D4_EB2F);
        h ^= h >> 16;
        h = h.wrapping_mul(0x7FEB_352D);
        h ^= h >> 15;
        h = h.wrapping_mul(0x846C_A68B);
        h ^= h >> 16;
        h
    }

    fn noise(x: usize, y: usize, c: usize, seed: u32) -> f64 {
        (hash32(x as u32, y as u32, c as u32, seed) >> 8) as f64 / 16_777_216.0
    }

    fn gradient(x: usize, y: usize, c: usize, w: usize, h: usize) -> f64 {
        (x as f64 + 0.5) / w as f64 * 0.6 + (y as f64 + 0.5) / h as f64 * 0.3 + 0.05 * c as f64
    }

    fn texture(x: usize, y: usize, c: usize, _w: usize, _h: usize) -> f64 {
        let (x, y, c) = (x as f64, y as f64, c as f64);
        0.5 + 0.3 * (0.7 * x + 0.9 * c).sin() * (0.45 * y).cos() + 0.15 * (0.11 * (x + y) + c).sin()
    }

    fn checker(x: usize, y: usize, c: usize, _w: usize, _h: usize) -> f64 {
        if (x / 4 + y / 4 + c).is_multiple_of(2) {
            0.85
        } else {
            0.15
        }
    }

    fn build(w: usize, h: usize, f: impl Fn(usize, usize, usize, usize, usize) -> f64) -> RgbImage {
        RgbImage::from_fn(w, h, |x, y| [0, 1, 2].map(|c| f(x, y, c, w, h) as f32))
    }

    struct Reference {
        name: &'static str,
        a: RgbImage,
        b: RgbImage,
        psnr: f64,
        ssim: f64,
    }

    /// Figures printed by `tests/reference/metrics_reference.py` with
    /// scikit-image 0.26.0 (numpy 2.4.6, Python 3.11):
    /// `peak_signal_noise_ratio(a, b, data_range=1.0)` and
    /// `structural_similarity(a, b, channel_axis=-1, data_range=1.0,
    /// gaussian_weights=True, sigma=1.5, use_sample_covariance=False)` on
    /// the f32 images widened to f64. The script's own numpy valid-filter
    /// SSIM agreed with scikit-image to 1.4e-15 on all of them.
    fn references() -> Vec<Reference> {
        vec![
            Reference {
                name: "gradient_noisy",
                a: build(16, 16, gradient),
                b: build(16, 16, |x, y, c, w, h| {
                    (gradient(x, y, c, w, h) + 0.1 * (noise(x, y, c, 7) - 0.5)).clamp(0.0, 1.0)
                }),
                psnr: 30.89996390523115,
                ssim: 0.9104786203420848,
            },
            Reference {
                name: "texture_contrast",
                a: build(23, 19, texture),
                b: build(23, 19, |x, y, c, w, h| {
                    0.8 * texture(x, y, c, w, h) + 0.1 + 0.05 * (noise(x, y, c, 3) - 0.5)
                }),
                psnr: 27.969358333862235,
                ssim: 0.9670996955278488,
            },
            Reference {
                name: "checker_blend",
                a: build(32, 32, checker),
                b: build(32, 32, |x, y, c, w, h| {
                    0.7 * checker(x, y, c, w, h) + 0.3 * noise(x, y, c, 11)
                }),
                psnr: 17.405445932707735,
                ssim: 0.9013253814316166,
            },
            Reference {
                name: "noise_vs_noise",
                a: build(32, 32, |x, y, c, _, _| noise(x, y, c, 1)),
                b: build(32, 32, |x, y, c, _, _| noise(x, y, c, 2)),
                psnr: 7.748165415773702,
                ssim: -0.00498900512382269,
            },
            Reference {
                name: "texture_vs_gradient",
                a: build(19, 23, texture),
                b: build(19, 23, gradient),
                psnr: 9.870351365876116,
                ssim: -0.015330934421482268,
            },
            Reference {
                name: "minimum_size",
                a: build(11, 11, texture),
                b: build(11, 11, |x, y, c, _, _| noise(x, y, c, 5)),
                psnr: 9.278366064041375,
                ssim: 0.008546669703729366,
            },
        ]
    }

    #[test]
    fn matches_scikit_image() {
        // Both sides compute in f64 from identical f32 inputs; only the
        // summation order differs (~1e-15 here, as the script shows); the
        // literals are Python's repr, exact f64s. 1e-6 is generous, yet far tighter than any
        // real discrepancy: measured on these pairs, a 13-tap window,
        // reflect-padded 'same' filtering or sample covariance each move at
        // least one figure by more than 3e-4 (up to 2e-2).
        for r in references() {
            let psnr = crate::metrics::psnr(&r.a, &r.b).unwrap();
            let ssim = ssim(&r.a, &r.b).unwrap();
            assert!(
                (psnr - r.psnr).abs() < 1e-6,
                "{}: PSNR {psnr} vs {}",
                r.name,
                r.psnr
            );
            assert!(
                (ssim - r.ssim).abs() < 1e-6,
                "{}: SSIM {ssim} vs {}",
                r.name,
                r.ssim
            );
        }
    }

    #[test]
    fn taps_are_normalised_and_symmetric() {
        let taps = gaussian_taps();
        assert!((taps.iter().sum::<f64>() - 1.0).abs() < 1e-15);
        for k in 0..SSIM_WINDOW {
            assert_eq!(taps[k], taps[SSIM_WINDOW - 1 - k]);
        }
        assert!(taps[RADIUS] > taps[RADIUS - 1]);
    }

    #[test]
    fn identical_images_score_one() {
        for r in references() {
            for image in [&r.a, &r.b] {
                let s = ssim(image, image).unwrap();
                assert!((s - 1.0).abs() < 1e-12, "{}: {s}", r.name);
            }
        }
    }

    #[test]
    fn symmetric() {
        for r in references() {
            let ab = ssim(&r.a, &r.b).unwrap();
            let ba = ssim(&r.b, &r.a).unwrap();
            assert!((ab - ba).abs() < 1e-15, "{}: {ab} vs {ba}", r.name);
        }
    }

    #[test]
    fn negative_image_scores_below_zero() {
        let a = build(32, 24, texture);
        let negative = RgbImage::from_fn(32, 24, |x, y| a.get(x, y).map(|c| 1.0 - c));
        let s = ssim(&a, &negative).unwrap();
        assert!(s < 0.0, "{s}");
    }

    #[test]
    fn small_images_are_an_error() {
        let a = build(10, 30, texture);
        assert!(matches!(
            ssim(&a, &a),
            Err(MetricsError::TooSmall {
                width: 10,
                height: 30,
                min: 11
            })
        ));
        let b = build(30, 10, texture);
        assert!(matches!(ssim(&b, &b), Err(MetricsError::TooSmall { .. })));
    }

    #[test]
    fn mismatched_sizes_are_an_error() {
        let a = build(16, 16, texture);
        let b = build(16, 17, texture);
        assert!(matches!(
            ssim(&a, &b),
            Err(MetricsError::SizeMismatch { .. })
        ));
    }

    /// SSIM straight from the definition: every valid window position,
    /// the full 2-D weights, no separability and no shared sums.
    fn brute_force(a: &RgbImage, b: &RgbImage) -> f64 {
        let taps = gaussian_taps();
        let (ow, oh) = (a.width - 2 * RADIUS, a.height - 2 * RADIUS);
        let mut total = 0.0;
        for c in 0..3 {
            for i in 0..oh {
                for j in 0..ow {
                    let [mut ux, mut uy, mut uxx, mut uyy, mut uxy] = [0.0; 5];
                    for di in 0..SSIM_WINDOW {
                        for dj in 0..SSIM_WINDOW {
                            let wgt = taps[di] * taps[dj];
                            let x = a.get(j + dj, i + di)[c] as f64;
                            let y = b.get(j + dj, i + di)[c] as f64;
                            ux += wgt * x;
                            uy += wgt * y;
                            uxx += wgt * x * x;
                            uyy += wgt * y * y;
                            uxy += wgt * x * y;
                        }
                    }
                    let (vx, vy, vxy) = (uxx - ux * ux, uyy - uy * uy, uxy - ux * uy);
                    total += ((2.0 * ux * uy + C1) * (2.0 * vxy + C2))
                        / ((ux * ux + uy * uy + C1) * (vx + vy + C2));
                }
            }
        }
        total / (3 * ow * oh) as f64
    }

    #[test]
    fn matches_the_definition() {
        // Non-square sizes make a row/column mix-up in the separable passes
        // show; the map widths 19, 16 and 1 cover a padded last block, no
        // padding at all, and a single column. 1e-12: the separable, mirrored
        // sums differ from the direct ones only in rounding (~1e-15).
        for (w, h) in [(29, 17), (26, 12), (11, 30)] {
            let a = build(w, h, texture);
            let b = build(w, h, |x, y, c, w, h| {
                0.6 * texture(x, y, c, w, h) + 0.4 * noise(x, y, c, 9)
            });
            let fast = ssim(&a, &b).unwrap();
            let slow = brute_force(&a, &b);
            assert!((fast - slow).abs() < 1e-12, "{w}×{h}: {fast} vs {slow}");
        }
    }

    #[test]
    fn a_corner_pixel_counts_at_minimum_size() {
        // At 11×11 the map is a single window covering every pixel, so even
        // the corner (weight g0² ≈ 1e-5) must move the score.
        let a = build(11, 11, texture);
        let mut b = a.clone();
        b.pixels[0] = [0.0, 0.0, 0.0];
        assert!(ssim(&a, &b).unwrap() < 1.0);
    }

    #[test]
    fn a_mask_leaves_out_every_window_touching_a_hidden_pixel() {
        let a = build(24, 20, texture);
        let b = build(24, 20, |x, y, c, w, h| 0.8 * texture(x, y, c, w, h) + 0.1);
        // Nothing hidden: the same score as without a mask, to the bit.
        let all = vec![true; 24 * 20];
        assert_eq!(ssim_masked(&a, &b, &all).unwrap(), ssim(&a, &b).unwrap());
        // Pixel (12, 9) hidden: of the 14 × 10 windows, those whose 11 × 11
        // span covers it (x from 2 to 12; every row does) go: the columns
        // at x 0, 1 and 13 stay.
        let mut one_hidden = all.clone();
        one_hidden[9 * 24 + 12] = false;
        let windows = windows_on_counted_pixels(24, 20, &one_hidden);
        assert_eq!(windows.iter().filter(|&&w| w).count(), 3 * 10);
        assert!(windows[0] && windows[1] && !windows[2] && !windows[12] && windows[13]);
        // Four hidden pixels 11 apart each way: every window covers one.
        let mut none_fits = all;
        none_fits[5 * 24 + 5] = false;
        none_fits[5 * 24 + 16] = false;
        none_fits[16 * 24 + 5] = false;
        none_fits[16 * 24 + 16] = false;
        assert!(ssim_masked(&a, &b, &none_fits).unwrap().is_nan());
    }
}
