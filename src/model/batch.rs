//! Training batches: random pixels of random training views, with the
//! colour each should come out as.

use glam::Vec3;

use crate::rng::Pcg32;
use crate::scene::{Frame, Scene};

/// Rays for one step, with targets composited on each ray's background.
#[derive(Debug, Clone, Default)]
pub struct RayBatch {
    pub origins: Vec<Vec3>,
    /// Unit directions.
    pub directions: Vec<Vec3>,
    pub targets: Vec<[f32; 3]>,
    pub backgrounds: Vec<[f32; 3]>,
    /// Cone radius at unit distance of each ray ([`crate::scene::Ray::radius`]).
    pub radii: Vec<f32>,
    /// Each ray's training image: its index among the frames it was drawn
    /// from (the scene's training views), which picks its appearance
    /// vector and its pose correction in a model that learns them; may be
    /// empty for rays of no image.
    pub images: Vec<u32>,
}

impl RayBatch {
    pub fn len(&self) -> usize {
        self.origins.len()
    }

    pub fn is_empty(&self) -> bool {
        self.origins.is_empty()
    }

    fn clear(&mut self) {
        self.origins.clear();
        self.directions.clear();
        self.targets.clear();
        self.backgrounds.clear();
        self.radii.clear();
        self.images.clear();
    }
}

/// How the background behind transparent pixels is chosen during training.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum TrainingBackground {
    /// A uniformly random colour per ray (instant-ngp, for images with
    /// alpha): the field cannot explain a background it cannot predict, so
    /// it learns empty space as transparent instead of painting it.
    Random,
    Fixed([f32; 3]),
}

/// How many draws inside the centre crop a masked frame gets before its
/// pixel is drawn from the whole frame.
pub const CROP_TRIES: usize = 64;

/// Fills `batch` with `count` rays through the centres of uniformly random
/// pixels of uniformly random training frames.
pub fn sample_rays(
    frames: &[Frame],
    count: usize,
    background: TrainingBackground,
    rng: &mut Pcg32,
    batch: &mut RayBatch,
) {
    sample_rays_cropped(frames, count, background, None, rng, batch);
}

/// [`sample_rays`] with the pixels drawn from the centred rectangle of
/// `crop` × the width and height when given (NeRF's `precrop_frac`).
///
/// A frame with a mask gives only pixels that count, uniformly among them
/// (inside the crop when there is one: up to [`CROP_TRIES`] draws there,
/// then among all the frame's counted pixels, so a crop the mask hides
/// whole cannot stall a step). Frames whose mask hides every pixel are
/// skipped; the others are drawn uniformly, as without masks.
pub fn sample_rays_cropped(
    frames: &[Frame],
    count: usize,
    background: TrainingBackground,
    crop: Option<f32>,
    rng: &mut Pcg32,
    batch: &mut RayBatch,
) {
    batch.clear();
    // Only when a mask hides a whole frame are the frames listed; otherwise
    // the draws are those of a scene without masks.
    let drawable: Option<Vec<usize>> = frames
        .iter()
        .any(|frame| frame.mask.as_ref().is_some_and(|mask| mask.counted() == 0))
        .then(|| {
            (0..frames.len())
                .filter(|&i| {
                    frames[i]
                        .mask
                        .as_ref()
                        .is_none_or(|mask| mask.counted() > 0)
                })
                .collect()
        });
    let choices = drawable.as_ref().map_or(frames.len(), Vec::len);
    if choices == 0 {
        return;
    }
    for _ in 0..count {
        let choice = rng.below(choices as u32) as usize;
        let index = drawable.as_ref().map_or(choice, |d| d[choice]);
        let frame = &frames[index];
        let k = frame.camera.intrinsics;
        let (x, y) = match (crop, &frame.mask) {
            (None, None) => (rng.below(k.width), rng.below(k.height)),
            (None, Some(mask)) => mask.draw(rng).expect("a drawable frame has counted pixels"),
            (Some(fraction), mask) => {
                // The central `fraction` of each side, at least one pixel.
                let span = |size: u32| ((size as f32 * fraction).round() as u32).clamp(1, size);
                let (w, h) = (span(k.width), span(k.height));
                let (x0, y0) = ((k.width - w) / 2, (k.height - h) / 2);
                let mut in_crop = || (x0 + rng.below(w), y0 + rng.below(h));
                match mask {
                    None => in_crop(),
                    Some(mask) => (0..CROP_TRIES)
                        .map(|_| in_crop())
                        .find(|&(x, y)| mask.counts(x, y))
                        .unwrap_or_else(|| {
                            mask.draw(rng).expect("a drawable frame has counted pixels")
                        }),
                }
            }
        };
        let ray = frame.camera.pixel_ray(x, y);
        let bg = match background {
            TrainingBackground::Random => [rng.next_f32(), rng.next_f32(), rng.next_f32()],
            TrainingBackground::Fixed(colour) => colour,
        };
        batch.origins.push(ray.origin);
        batch.directions.push(ray.direction);
        batch.radii.push(ray.radius());
        batch.targets.push(frame.image.rgb_over(x, y, bg));
        batch.backgrounds.push(bg);
        batch.images.push(index as u32);
    }
}

/// The background policy for a scene: a random colour per ray on every
/// scene, as instant-ngp trains (`random_bg_color`, on by default, also for
/// captures without alpha). Where the images are opaque, the target does
/// not depend on the background, so any transmittance a ray keeps lets a
/// random colour into its prediction and is penalised: the field must
/// explain sky and walls with opaque content (which settles at the far
/// side of the box) instead of semi-transparent fog blended with a fixed
/// background colour, which fills the occupancy grid along every ray.
/// White stays the colour the reference protocol evaluates on.
pub fn training_background(_scene: &Scene) -> TrainingBackground {
    TrainingBackground::Random
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::{Camera, ImageRgba8, Intrinsics};
    use glam::Mat4;

    fn frame(colour: [u8; 4]) -> Frame {
        let intrinsics = Intrinsics::from_fov_x(4, 4, 1.0);
        Frame {
            camera: Camera::new(intrinsics, Mat4::IDENTITY),
            image: ImageRgba8::new(4, 4, colour.repeat(16)),
            image_path: Default::default(),
            mask: None,
        }
    }

    #[test]
    fn targets_are_composited_on_their_own_background() {
        // Half-transparent red: target = 0.5·red + 0.5·background.
        let frames = [frame([255, 0, 0, 128])];
        let mut batch = RayBatch::default();
        let mut rng = Pcg32::new(5, 0);
        sample_rays(
            &frames,
            500,
            TrainingBackground::Random,
            &mut rng,
            &mut batch,
        );
        assert_eq!(batch.len(), 500);
        let alpha = 128.0 / 255.0;
        for (target, bg) in batch.targets.iter().zip(&batch.backgrounds) {
            let want = [
                alpha + bg[0] * (1.0 - alpha),
                bg[1] * (1.0 - alpha),
                bg[2] * (1.0 - alpha),
            ];
            for c in 0..3 {
                assert!((target[c] - want[c]).abs() < 1e-6);
            }
        }
        // The backgrounds really vary.
        let spread = batch.backgrounds.iter().map(|b| b[0]).fold(0f32, f32::max)
            - batch.backgrounds.iter().map(|b| b[0]).fold(1f32, f32::min);
        assert!(spread > 0.9);
    }

    #[test]
    fn same_rng_same_batch() {
        let frames = [frame([10, 20, 30, 255]), frame([40, 50, 60, 255])];
        let mut a = RayBatch::default();
        let mut b = RayBatch::default();
        sample_rays(
            &frames,
            64,
            TrainingBackground::Random,
            &mut Pcg32::new(9, 1),
            &mut a,
        );
        sample_rays(
            &frames,
            64,
            TrainingBackground::Random,
            &mut Pcg32::new(9, 1),
            &mut b,
        );
        assert_eq!(a.directions, b.directions);
        assert_eq!(a.targets, b.targets);
    }

    /// A 4 × 4 frame whose pixel (x, y) has red x·60 and green y·60, and
    /// whose mask hides the pixels `hidden` says.
    fn masked_frame(hidden: impl Fn(u32, u32) -> bool) -> Frame {
        let mut frame = frame([0, 0, 0, 255]);
        for y in 0..4 {
            for x in 0..4 {
                let at = ((y * 4 + x) * 4) as usize;
                frame.image.data[at] = (x * 60) as u8;
                frame.image.data[at + 1] = (y * 60) as u8;
            }
        }
        let counts = (0..16).map(|i| !hidden(i % 4, i / 4)).collect();
        frame.mask = Some(crate::scene::PixelMask::new(4, 4, counts));
        frame
    }

    /// The pixel a target came from, read back from its colour.
    fn pixel_of(target: [f32; 3]) -> (u32, u32) {
        let at = |c: f32| (c * 255.0 / 60.0).round() as u32;
        (at(target[0]), at(target[1]))
    }

    #[test]
    fn masked_pixels_are_never_drawn_and_a_fully_masked_frame_is_skipped() {
        // Frame 0 hides its left half, frame 1 everything but (3, 3),
        // frame 2 every pixel.
        let frames = [
            masked_frame(|x, _| x < 2),
            masked_frame(|x, y| (x, y) != (3, 3)),
            masked_frame(|_, _| true),
        ];
        for crop in [None, Some(0.5)] {
            let mut batch = RayBatch::default();
            let mut rng = Pcg32::new(11, 2);
            let background = TrainingBackground::Fixed([0.0; 3]);
            sample_rays_cropped(&frames, 4000, background, crop, &mut rng, &mut batch);
            assert_eq!(batch.len(), 4000);
            let mut per_pixel = std::collections::HashMap::new();
            for &target in &batch.targets {
                *per_pixel.entry(pixel_of(target)).or_insert(0u32) += 1;
            }
            // Only frame 0's right half and frame 1's one pixel come out.
            for (&(x, y), &n) in &per_pixel {
                assert!(
                    x >= 2,
                    "{crop:?}: drew the hidden pixel ({x}, {y}) {n} times"
                );
            }
            // The two drawable frames share the rays evenly: frame 1's
            // (3, 3), outside the crop but all it has, gets half of them;
            // frame 0's 8 pixels (its (3, 3) among them) a sixteenth each,
            // or in the crop its 2 counted pixels a quarter each. The
            // tolerances are over 3 standard deviations of 4000 draws.
            let share = |pixel| per_pixel.get(&pixel).copied().unwrap_or(0) as f64 / 4000.0;
            let (corner, other) = (share((3, 3)), share((2, 1)));
            let (want_corner, want_other) = match crop {
                None => (0.5 + 1.0 / 16.0, 1.0 / 16.0),
                Some(_) => (0.5, 0.25),
            };
            assert!((corner - want_corner).abs() < 0.03, "{crop:?}: {corner}");
            assert!((other - want_other).abs() < 0.025, "{crop:?}: {other}");
        }
        // Nothing to draw: no rays, no endless search.
        let mut batch = RayBatch::default();
        sample_rays(
            &frames[2..],
            10,
            TrainingBackground::Random,
            &mut Pcg32::new(1, 1),
            &mut batch,
        );
        assert!(batch.is_empty());
    }
}
