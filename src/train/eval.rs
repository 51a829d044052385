//! Evaluation: render held-out views on white and score them against the
//! photographs composited on white (the reference protocol).

use serde::{Deserialize, Serialize};

use crate::metrics::{
    ImageScores, RgbImage, WHITE, {self},
};
use crate::model::pixels::{render_pixels, rgb_of};
use crate::scene::Frame;

use crate::model::{RadianceModel, RayColumns};

/// Scores of one view.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct ViewScores {
    pub index: usize,
    pub image: String,
    pub psnr: f64,
    pub ssim: f64,
    /// Pixels the view's mask leaves out of both scores.
    #[serde(default)]
    pub masked_pixels: usize,
}

/// Scores of a split: per view and means (per-image PSNR, then the mean).
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct SplitScores {
    pub split: String,
    pub views: Vec<ViewScores>,
    pub mean_psnr: f64,
    pub mean_ssim: f64,
    pub render_seconds: f64,
    /// Pixels the views' masks leave out of the scores, all views together.
    #[serde(default)]
    pub masked_pixels: usize,
}

impl SplitScores {
    /// What the scores leave out, for the evaluation's output: `None` when
    /// no view has a mask.
    pub fn describe_masks(&self) -> Option<String> {
        let masked_views = self.views.iter().filter(|v| v.masked_pixels > 0).count();
        (self.masked_pixels > 0).then(|| {
            format!(
                "{} pixels of {masked_views} views masked out: PSNR over the pixels that \
                 count, SSIM over the 11×11 windows wholly on them",
                self.masked_pixels
            )
        })
    }
}

/// How a model with appearance embeddings renders held-out views, for the
/// evaluation's output: `None` for a model without them.
pub fn describe_appearance(model: &dyn RadianceModel) -> Option<String> {
    model.appearance_images().map(|images| {
        format!(
            "held-out views have no appearance embedding of their own: they are rendered with \
             the mean of the {images} training images' (nerfacto's choice)"
        )
    })
}

/// Renders `frame`'s camera over white and scores it against the image.
/// A render that is not finite (a diverged model) scores NaN, which the
/// callers report; it is not a reason to panic.
pub fn score_view(model: &dyn RadianceModel, frame: &Frame, with_ssim: bool) -> ImageScores {
    let k = frame.camera.intrinsics;
    let rendered = render_pixels(model, &frame.camera, WHITE);
    let (w, h) = (k.width as usize, k.height as usize);
    let prediction = RgbImage::new(w, h, rgb_of(&rendered)).expect("one pixel per ray");
    score_prediction(&prediction, frame, with_ssim)
}

/// Scores `prediction` against `frame`'s image on white: over every pixel,
/// or, where the frame has a mask, PSNR over the pixels that count and
/// SSIM over the windows that lie wholly on them.
pub fn score_prediction(prediction: &RgbImage, frame: &Frame, with_ssim: bool) -> ImageScores {
    let truth = RgbImage::from_rgba8_over(&frame.image, WHITE);
    let counts = frame.mask.as_ref().map(|mask| mask.counting());
    let psnr = match counts {
        None => metrics::psnr(prediction, &truth),
        Some(counts) => metrics::mse_masked(prediction, &truth, counts).map(metrics::psnr_from_mse),
    }
    .unwrap_or(f64::NAN);
    let ssim = match (with_ssim, counts) {
        (false, _) => Ok(f64::NAN),
        (true, None) => metrics::ssim(prediction, &truth),
        (true, Some(counts)) => metrics::ssim_masked(prediction, &truth, counts),
    }
    .unwrap_or(f64::NAN);
    ImageScores { psnr, ssim }
}

/// A held-out view's right half scored two ways (NeRF in the Wild's
/// protocol): drawn with the training vectors' mean (or as it renders, for
/// a model without them), and with the vector fitted to its left half
/// (`None` without vectors).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HalfScores {
    pub mean_psnr: f64,
    pub fitted_psnr: Option<f64>,
}

/// [`HalfScores`] of `frame` (over white; masked pixels count in neither
/// half): its left half's pixels (x below half the width) fit the vector,
/// its right half is scored.
pub fn score_right_half(
    model: &mut dyn RadianceModel,
    frame: &Frame,
) -> Result<HalfScores, String> {
    let k = frame.camera.intrinsics;
    let counts = |x: u32, y: u32| frame.mask.as_ref().is_none_or(|mask| mask.counts(x, y));
    let split = k.width / 2;
    let mut fit = crate::model::batch::RayBatch::default();
    let (mut right, mut truth) = (Vec::new(), Vec::new());
    for y in 0..k.height {
        for x in 0..k.width {
            if !counts(x, y) {
                continue;
            }
            let ray = frame.camera.pixel_ray(x, y);
            let target = frame.image.rgb_over(x, y, WHITE);
            if x < split {
                fit.origins.push(ray.origin);
                fit.directions.push(ray.direction);
                fit.radii.push(ray.radius());
                fit.targets.push(target);
                fit.backgrounds.push(WHITE);
            } else {
                right.push(ray);
                truth.push(target);
            }
        }
    }
    if right.is_empty() || fit.is_empty() {
        return Err("the view has no pixels to fit or to score in one of its halves".into());
    }
    let columns = RayColumns::of(&right);
    let rays = || crate::model::RenderRays {
        origins: &columns.origins,
        directions: &columns.directions,
        radii: &columns.radii,
        background: WHITE,
    };
    let psnr = |pixels: &[crate::model::RenderedPixel]| {
        let squared: f64 = pixels
            .iter()
            .zip(&truth)
            .map(|(p, t)| {
                (0..3)
                    .map(|c| ((p.rgb[c] - t[c]) as f64).powi(2))
                    .sum::<f64>()
            })
            .sum();
        metrics::psnr_from_mse(squared / (3 * pixels.len()) as f64)
    };
    let mut pixels = vec![crate::model::RenderedPixel::default(); right.len()];
    model.render(rays(), &mut pixels);
    let mean_psnr = psnr(&pixels);
    if model.appearance_images().is_none() {
        return Ok(HalfScores {
            mean_psnr,
            fitted_psnr: None,
        });
    }
    model.render_with_fitted_appearance(&fit, rays(), &mut pixels)?;
    Ok(HalfScores {
        mean_psnr,
        fitted_psnr: Some(psnr(&pixels)),
    })
}

/// Mean PSNR over `frames` (no SSIM), for progress reports.
pub fn mean_psnr(model: &dyn RadianceModel, frames: &[&Frame]) -> f64 {
    if frames.is_empty() {
        return f64::NAN;
    }
    frames
        .iter()
        .map(|f| score_view(model, f, false).psnr)
        .sum::<f64>()
        / frames.len() as f64
}

/// Mean PSNR over `frames` estimated from about `rays` pixels in all,
/// spread over a regular grid of each view (every s-th pixel in x and y,
/// the same s for a view's both axes): progress reports whose cost stays
/// bounded however large the views and however slow the model renders.
pub fn mean_psnr_sampled(model: &dyn RadianceModel, frames: &[&Frame], rays: usize) -> f64 {
    if frames.is_empty() {
        return f64::NAN;
    }
    let per_view = (rays / frames.len()).max(1);
    // A view whose mask hides every pixel of its grid has no estimate and
    // is left out of the mean.
    let estimates: Vec<f64> = frames
        .iter()
        .filter_map(|frame| {
            let k = frame.camera.intrinsics;
            let mut coordinates = pixel_grid(k.width, k.height, per_view);
            if let Some(mask) = &frame.mask {
                coordinates.retain(|&(x, y)| mask.counts(x, y));
                if coordinates.is_empty() {
                    return None;
                }
            }
            let rays: Vec<_> = coordinates
                .iter()
                .map(|&(x, y)| frame.camera.pixel_ray(x, y))
                .collect();
            let mut out = vec![Default::default(); coordinates.len()];
            model.render(RayColumns::of(&rays).over(WHITE), &mut out);
            let mut squared = 0f64;
            for (&(x, y), pixel) in coordinates.iter().zip(&out) {
                let truth = frame.image.rgb_over(x, y, WHITE);
                for (&p, &t) in pixel.rgb.iter().zip(&truth) {
                    squared += ((p - t) as f64).powi(2);
                }
            }
            Some(metrics::psnr_from_mse(
                squared / (3 * coordinates.len().max(1)) as f64,
            ))
        })
        .collect();
    if estimates.is_empty() {
        return f64::NAN;
    }
    estimates.iter().sum::<f64>() / estimates.len() as f64
}

/// About `count` pixels (column, row) of a `width × height` view (at most
/// all of them, at least one), on a regular grid: every s-th pixel in x
/// and y, the same s for both axes, centred in each s × s cell so that the
/// grid favours no image border, and inside the view however thin it is
/// (a view 1 pixel high must still give its pixels, not an empty grid and
/// the 100 dB of no error).
pub fn pixel_grid(width: u32, height: u32, count: usize) -> Vec<(u32, u32)> {
    let pixels = (width as usize * height as usize).max(1);
    let stride = ((pixels as f64 / count.max(1) as f64).sqrt().ceil() as u32).max(1);
    let first = stride / 2;
    let mut coordinates = Vec::new();
    let mut y = first.min(height.saturating_sub(1));
    while y < height {
        let mut x = first.min(width.saturating_sub(1));
        while x < width {
            coordinates.push((x, y));
            x += stride;
        }
        y += stride;
    }
    coordinates
}

/// Full evaluation of a split, with a callback per view for progress.
pub fn evaluate_split(
    model: &dyn RadianceModel,
    split: &str,
    frames: &[Frame],
    on_view: impl FnMut(&ViewScores),
) -> SplitScores {
    evaluate_split_until(
        model,
        split,
        frames,
        &std::sync::atomic::AtomicBool::new(false),
        on_view,
    )
}

/// [`evaluate_split`], stopping before the next view once `stop` is set
/// (the means are then over the views scored so far).
pub fn evaluate_split_until(
    model: &dyn RadianceModel,
    split: &str,
    frames: &[Frame],
    stop: &std::sync::atomic::AtomicBool,
    mut on_view: impl FnMut(&ViewScores),
) -> SplitScores {
    let started = std::time::Instant::now();
    let mut views = Vec::with_capacity(frames.len());
    for (index, frame) in frames.iter().enumerate() {
        if stop.load(std::sync::atomic::Ordering::SeqCst) {
            break;
        }
        let scores = score_view(model, frame, true);
        let view = ViewScores {
            index,
            image: frame.image_path.display().to_string(),
            psnr: scores.psnr,
            ssim: scores.ssim,
            masked_pixels: frame.mask.as_ref().map_or(0, |mask| mask.hidden()),
        };
        on_view(&view);
        views.push(view);
    }
    // A view whose mask hides every pixel has nothing to score: it is
    // listed, and left out of the means.
    let scored: Vec<&ViewScores> = views
        .iter()
        .filter(|v| {
            frames[v.index]
                .mask
                .as_ref()
                .is_none_or(|m| m.counted() > 0)
        })
        .collect();
    let n = scored.len().max(1) as f64;
    SplitScores {
        split: split.to_string(),
        mean_psnr: scored.iter().map(|v| v.psnr).sum::<f64>() / n,
        mean_ssim: scored.iter().map(|v| v.ssim).sum::<f64>() / n,
        masked_pixels: views.iter().map(|v| v.masked_pixels).sum(),
        views,
        render_seconds: started.elapsed().as_secs_f64(),
    }
}

/// Mean PSNR on `frames` of the simplest predictor: every pixel the mean
/// colour of the `train` images on white. A floor that learning must
/// clear by a margin.
pub fn mean_colour_psnr(train: &[Frame], frames: &[Frame]) -> f64 {
    let mut sum = [0f64; 3];
    let mut count = 0f64;
    for frame in train {
        for pixel in RgbImage::from_rgba8_over(&frame.image, WHITE).pixels {
            for (s, &c) in sum.iter_mut().zip(&pixel) {
                *s += c as f64;
            }
            count += 1.0;
        }
    }
    let mean = sum.map(|s| (s / count.max(1.0)) as f32);
    frames
        .iter()
        .map(|f| {
            let truth = RgbImage::from_rgba8_over(&f.image, WHITE);
            let flat = RgbImage::new(truth.width, truth.height, vec![mean; truth.pixels.len()])
                .expect("one colour per pixel");
            metrics::psnr(&flat, &truth).expect("same size")
        })
        .sum::<f64>()
        / frames.len().max(1) as f64
}

/// `count` views spread evenly over `frames` (all when there are fewer).
pub fn spread_views(frames: &[Frame], count: usize) -> Vec<&Frame> {
    if frames.len() <= count {
        return frames.iter().collect();
    }
    (0..count)
        .map(|i| &frames[i * frames.len() / count])
        .collect()
}

#[cfg(test)]
mod tests {
    use glam::{Mat4, Vec3};

    use super::*;
    use crate::model::batch::RayBatch;
    use crate::model::checkpoint::Checkpoint;
    use crate::model::{RenderRays, RenderedPixel, StepStats};
    use crate::scene::{Camera, ImageRgba8, Intrinsics};

    /// Renders every pixel black.
    struct Black;

    impl RadianceModel for Black {
        fn describe(&self) -> String {
            "black".into()
        }
        fn rays_for_next_batch(&self) -> usize {
            1
        }
        fn step(&mut self, _batch: &RayBatch, _step: u32) -> StepStats {
            StepStats::default()
        }
        fn render(&self, _: RenderRays, out: &mut [RenderedPixel]) {
            for pixel in out {
                pixel.rgb = [0.0; 3];
                pixel.opacity = 1.0;
            }
        }
        fn save(&self) -> Checkpoint {
            Checkpoint {
                header: serde_json::json!({}),
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

    /// A view of `width` × `height` white pixels.
    fn white_view(width: u32, height: u32) -> Frame {
        Frame {
            camera: Camera::new(
                Intrinsics::from_fov_x(width, height, 0.7),
                Mat4::from_translation(Vec3::new(0.0, 0.0, 4.0)),
            ),
            image: ImageRgba8::new(width, height, vec![255; (width * height * 4) as usize]),
            image_path: Default::default(),
            mask: None,
        }
    }

    /// Black on white is 0 dB however thin the view: a view one pixel high
    /// once gave the sampled estimate no pixels at all, and so 100 dB.
    #[test]
    fn a_sampled_psnr_of_a_thin_view_scores_its_pixels() {
        for (width, height) in [(64, 1), (1, 64), (400, 2), (64, 64)] {
            let view = white_view(width, height);
            let psnr = mean_psnr_sampled(&Black, &[&view], 16);
            assert!(psnr.abs() < 1e-6, "{width}×{height}: {psnr} dB");
        }
    }

    #[test]
    fn the_pixel_grid_spreads_about_the_count_asked_over_the_whole_view() {
        // 100 of 400 × 400: every 40th pixel each way, from the middle of
        // the first 40 × 40 cell.
        let grid = pixel_grid(400, 400, 100);
        assert_eq!(grid.len(), 100);
        assert_eq!(grid[0], (20, 20));
        assert_eq!(*grid.last().unwrap(), (380, 380));
        // More than the view holds: every pixel, once.
        assert_eq!(pixel_grid(4, 3, 1000).len(), 12);
        // A stride longer than a side still finds pixels inside the view.
        let thin = pixel_grid(400, 10, 1);
        assert!(!thin.is_empty() && thin.iter().all(|&(x, y)| x < 400 && y < 10));
        assert_eq!(pixel_grid(1, 1, 0), vec![(0, 0)]);
    }
}
