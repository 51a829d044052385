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
pub fn sample_rays_cropped(
    frames: &[Frame],
    count: usize,
    background: TrainingBackground,
    crop: Option<f32>,
    rng: &mut Pcg32,
    batch: &mut RayBatch,
) {
    batch.clear();
    if frames.is_empty() {
        return;
    }
    for _ in 0..count {
        let frame = &frames[rng.below(frames.len() as u32) as usize];
        let k = frame.camera.intrinsics;
        let (x, y) = match crop {
            None => (rng.below(k.width), rng.below(k.height)),
            Some(fraction) => {
                // The central `fraction` of each side, at least one pixel.
                let span = |size: u32| ((size as f32 * fraction).round() as u32).clamp(1, size);
                let (w, h) = (span(k.width), span(k.height));
                let (x0, y0) = ((k.width - w) / 2, (k.height - h) / 2);
                (x0 + rng.below(w), y0 + rng.below(h))
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
}
