//! Camera refinement: a learned pose correction per training image
//! (nerfstudio's `CameraOptimizer`, mode "SO3xR3"), applied to each
//! training ray before it is sampled and trained with the field.
//!
//! Image i's correction is six values: a rotation vector ω (so(3), about
//! the world axes) and a translation t (world units), both starting at
//! zero. A ray (o, d) of image i becomes
//!
//! ```text
//! o' = o + t        d' = exp(ω) d
//! ```
//!
//! as nerfstudio's `apply_to_raybundle` corrects its rays, so the corrected
//! camera-to-world matrix is the correction composed on the left of the
//! given pose, with the rotation about the camera's centre: R' = exp(ω) R,
//! c' = c + t. On the left, in world axes, the correction's values are
//! angles and lengths of the scene, the same for every camera, so one
//! learning rate and one penalty suit all images; rotating about the centre
//! rather than the world origin keeps rotation and translation apart
//! (SO(3) × R³, not SE(3)), so a rotation moves no camera.
//!
//! The gradient: with the rays' gradients dL/do' and dL/dd' (the field's
//! input gradients summed along each ray), dL/dt = Σ dL/do' and, since a
//! small rotation δ moves ω's exp(ω) to exp(J_l(ω) δ) exp(ω) (J_l the left
//! Jacobian of SO(3)), dL/dω = J_l(ω)ᵀ Σ d' × dL/dd'.

use glam::{DMat3, DVec3, Mat4, Vec3};

use super::adam::Adam;
use crate::field::camera::{CAMERA_OPTIMISER, ROTATION_PENALTY, TRANSLATION_PENALTY};
use crate::field::params::{ParamLayout, Update};

/// Values per image: ω then t.
pub const VALUES_PER_IMAGE: usize = 6;

/// The pose corrections of a scene's training images, their gradient and
/// their optimiser's state.
#[derive(Debug, Clone)]
pub struct CameraRefinement {
    /// Image after image: ω (3), t (3).
    values: Vec<f32>,
    gradients: Vec<f32>,
    adam: Adam,
    /// exp(ω) of each image, refreshed whenever the values change.
    rotations: Vec<DMat3>,
}

impl CameraRefinement {
    /// No correction for each of `images` training images.
    pub fn new(images: usize) -> Self {
        let count = images * VALUES_PER_IMAGE;
        Self {
            values: vec![0.0; count],
            gradients: vec![0.0; count],
            adam: Adam::new(count),
            rotations: vec![DMat3::IDENTITY; images],
        }
    }

    pub fn images(&self) -> usize {
        self.rotations.len()
    }

    /// Image after image: ω (3), t (3).
    pub fn values(&self) -> &[f32] {
        &self.values
    }

    /// The values' gradient from the last [`Self::backward`] (the loss's
    /// only; the penalty joins in [`Self::step`]).
    pub fn gradients(&self) -> &[f32] {
        &self.gradients
    }

    pub fn adam(&self) -> &Adam {
        &self.adam
    }

    /// Sets the values (a checkpoint, a test's finite differences) and the
    /// optimiser's state where given.
    pub fn set_values(&mut self, values: &[f32], adam: Option<Adam>) {
        assert_eq!(values.len(), self.values.len(), "six values per image");
        self.values.copy_from_slice(values);
        if let Some(adam) = adam {
            assert_eq!(adam.len(), self.values.len(), "the optimiser's state");
            self.adam = adam;
        }
        self.refresh_rotations();
    }

    fn refresh_rotations(&mut self) {
        for (rotation, values) in self
            .rotations
            .iter_mut()
            .zip(self.values.chunks_exact(VALUES_PER_IMAGE))
        {
            *rotation = so3_exp(omega_of(values));
        }
    }

    /// Corrects rays (R × 3 origins and unit directions) in place; ray r
    /// belongs to training image `images[r]`. A ray of no training image
    /// (an index past the last) stays as it is.
    pub fn apply(&self, images: &[u32], origins: &mut [f32], directions: &mut [f32]) {
        for ((&image, o), d) in images
            .iter()
            .zip(origins.chunks_exact_mut(3))
            .zip(directions.chunks_exact_mut(3))
        {
            let Some(rotation) = self.rotations.get(image as usize) else {
                continue;
            };
            let t = &self.values[image as usize * VALUES_PER_IMAGE + 3..][..3];
            for a in 0..3 {
                o[a] += t[a];
            }
            let turned = *rotation * DVec3::new(d[0] as f64, d[1] as f64, d[2] as f64);
            d.copy_from_slice(&turned.as_vec3().to_array());
        }
    }

    /// Writes the values' gradient from each corrected ray's gradients
    /// (R × 3 each; `directions` are the corrected ones).
    pub fn backward(
        &mut self,
        images: &[u32],
        directions: &[f32],
        d_origins: &[f32],
        d_directions: &[f32],
    ) {
        let mut sums = vec![[DVec3::ZERO; 2]; self.images()];
        for (r, &image) in images.iter().enumerate() {
            let Some(sum) = sums.get_mut(image as usize) else {
                continue;
            };
            let at = |v: &[f32]| DVec3::from(Vec3::from_slice(&v[3 * r..3 * r + 3]));
            sum[0] += at(directions).cross(at(d_directions));
            sum[1] += at(d_origins);
        }
        for ((gradient, values), [turn, shift]) in self
            .gradients
            .chunks_exact_mut(VALUES_PER_IMAGE)
            .zip(self.values.chunks_exact(VALUES_PER_IMAGE))
            .zip(sums)
        {
            let d_omega = so3_left_jacobian(omega_of(values)).transpose() * turn;
            gradient[..3].copy_from_slice(&d_omega.as_vec3().to_array());
            gradient[3..].copy_from_slice(&shift.as_vec3().to_array());
        }
    }

    /// One Adam step (nerfacto's, [`CAMERA_OPTIMISER`]) from the last
    /// [`Self::backward`]'s gradient and the gradient of nerfstudio's
    /// penalty on the corrections' lengths.
    pub fn step(&mut self) {
        let images = self.images().max(1) as f32;
        let mut gradients = self.gradients.clone();
        for (gradient, values) in gradients
            .chunks_exact_mut(VALUES_PER_IMAGE)
            .zip(self.values.chunks_exact(VALUES_PER_IMAGE))
        {
            // d/dv (w · mean |v|) = w / N · v / |v| (none at v = 0, where
            // the length has no gradient: torch's norm gives 0 there too).
            for (range, weight) in [(0..3, ROTATION_PENALTY), (3..6, TRANSLATION_PENALTY)] {
                let part = Vec3::from_slice(&values[range.clone()]);
                let length = part.length();
                if length > 0.0 {
                    let push = part * (weight / images / length);
                    for (g, p) in gradient[range].iter_mut().zip(push.to_array()) {
                        *g += p;
                    }
                }
            }
        }
        let layout = ParamLayout::new().with(
            "camera corrections",
            self.values.len(),
            Update::Dense { l2: false },
        );
        self.adam
            .step_layout(&CAMERA_OPTIMISER, &layout, &mut self.values, &gradients);
        self.refresh_rotations();
    }

    /// Training image `image`'s camera-to-world matrix `given` with its
    /// correction (see [`corrected_pose`]).
    pub fn corrected(&self, image: usize, given: Mat4) -> Mat4 {
        corrected_pose(
            &self.values[image * VALUES_PER_IMAGE..][..VALUES_PER_IMAGE],
            given,
        )
    }
}

/// The camera-to-world matrix `given` with the correction of `values` (ω,
/// t): R' = exp(ω) R, centre c' = c + t.
pub fn corrected_pose(values: &[f32], given: Mat4) -> Mat4 {
    let rotation = so3_exp(omega_of(values)).as_mat3();
    let t = Vec3::from_slice(&values[3..6]);
    Mat4::from_cols(
        (rotation * given.x_axis.truncate()).extend(0.0),
        (rotation * given.y_axis.truncate()).extend(0.0),
        (rotation * given.z_axis.truncate()).extend(0.0),
        (given.w_axis.truncate() + t).extend(1.0),
    )
}

fn omega_of(values: &[f32]) -> DVec3 {
    DVec3::new(values[0] as f64, values[1] as f64, values[2] as f64)
}

/// [ω]×, the matrix of ω × ·.
fn cross_matrix(w: DVec3) -> DMat3 {
    DMat3::from_cols(
        DVec3::new(0.0, w.z, -w.y),
        DVec3::new(-w.z, 0.0, w.x),
        DVec3::new(w.y, -w.x, 0.0),
    )
}

/// Below this angle the series' first terms replace the closed forms,
/// whose divisions by θ² and θ³ lose every digit (the next terms are
/// below 1e-16 of the first there).
const SMALL_ANGLE: f64 = 1e-4;

/// exp([ω]×) = I + (sin θ / θ) K + ((1 − cos θ) / θ²) K² (Rodrigues).
pub fn so3_exp(w: DVec3) -> DMat3 {
    let theta = w.length();
    let k = cross_matrix(w);
    let (a, b) = if theta < SMALL_ANGLE {
        (1.0 - theta * theta / 6.0, 0.5 - theta * theta / 24.0)
    } else {
        (theta.sin() / theta, (1.0 - theta.cos()) / (theta * theta))
    };
    DMat3::IDENTITY + k * a + k * k * b
}

/// The left Jacobian of SO(3): I + ((1 − cos θ) / θ²) K + ((θ − sin θ) /
/// θ³) K².
pub fn so3_left_jacobian(w: DVec3) -> DMat3 {
    let theta = w.length();
    let k = cross_matrix(w);
    let (b, c) = if theta < SMALL_ANGLE {
        (
            0.5 - theta * theta / 24.0,
            1.0 / 6.0 - theta * theta / 120.0,
        )
    } else {
        (
            (1.0 - theta.cos()) / (theta * theta),
            (theta - theta.sin()) / (theta * theta * theta),
        )
    };
    DMat3::IDENTITY + k * b + k * k * c
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exp_turns_about_the_axis_by_the_vectors_length() {
        let axis = DVec3::new(1.0, 2.0, -0.5).normalize();
        for angle in [0.0, 1e-6, 0.3, 2.0] {
            let ours = so3_exp(axis * angle);
            let theirs = DMat3::from_axis_angle(axis, angle);
            let error = (ours - theirs).to_cols_array().map(f64::abs);
            assert!(error.iter().all(|&e| e < 1e-12), "{angle}: {error:?}");
        }
    }

    /// exp(ω + δ) = exp(J_l(ω) δ) exp(ω) to first order: the difference
    /// of the two sides is O(|δ|²), far below the O(|δ|) a wrong Jacobian
    /// leaves.
    #[test]
    fn left_jacobian_moves_exp_as_a_left_rotation() {
        let delta = 1e-6;
        for w in [DVec3::new(0.2, -0.4, 0.1), DVec3::new(1e-7, 0.0, 2e-7)] {
            for axis in [DVec3::X, DVec3::Y, DVec3::Z] {
                let moved = so3_exp(w + axis * delta);
                let turned = so3_exp(so3_left_jacobian(w) * axis * delta) * so3_exp(w);
                let error = (moved - turned).to_cols_array().map(f64::abs);
                assert!(error.iter().all(|&e| e < 1e-10), "{w} {axis}: {error:?}");
            }
        }
    }

    #[test]
    fn rays_and_cameras_are_corrected_alike() {
        let mut refinement = CameraRefinement::new(2);
        refinement.set_values(
            &[0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.1, 0.0, 1.0, -2.0, 0.5],
            None,
        );
        let given = Mat4::from_translation(Vec3::new(3.0, 0.0, 1.0));
        let corrected = refinement.corrected(1, given);
        // A camera at (3, 0, 1) looking down −z, turned by 0.1 rad about y
        // and moved by (1, −2, 0.5).
        let mut origins = [3.0, 0.0, 1.0, 3.0, 0.0, 1.0];
        let mut directions = [0.0, 0.0, -1.0, 0.0, 0.0, -1.0];
        refinement.apply(&[1, 7], &mut origins, &mut directions);
        let centre = corrected.w_axis.truncate();
        let forward = -corrected.z_axis.truncate();
        assert!((Vec3::from_slice(&origins[..3]) - centre).length() < 1e-6);
        assert!((Vec3::from_slice(&directions[..3]) - forward).length() < 1e-6);
        assert!((centre - Vec3::new(4.0, -2.0, 1.5)).length() < 1e-6);
        assert!((forward - Vec3::new(-0.1f32.sin(), 0.0, -0.1f32.cos())).length() < 1e-6);
        // Image 7 is none of the training images: left alone.
        assert_eq!(origins[3..], [3.0, 0.0, 1.0]);
        assert_eq!(directions[3..], [0.0, 0.0, -1.0]);
    }
}
