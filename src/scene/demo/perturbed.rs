//! The demo with its training cameras off by a known amount, for camera
//! refinement's tests: the images are rendered from the true cameras, the
//! transforms files hold perturbed ones, and the true ones go to
//! [`CAMERA_TRUTH_FILE`] beside them. Held-out views keep their true
//! cameras, so their scores measure the field, not the poses.

use std::path::Path;

use glam::{Mat3, Mat4, Vec3};
use serde::{Deserialize, Serialize};

use super::{DemoConfig, build, write_blender};
use crate::rng::Pcg32;
use crate::scene::{Camera, SceneError, SceneResult};

/// The file beside the transforms files with the training cameras' true
/// camera-to-world matrices.
pub const CAMERA_TRUTH_FILE: &str = "cameras_truth.json";

/// The seed the perturbations are drawn from, so a demo written twice is
/// the same scene.
pub const PERTURBATION_SEED: u64 = 46;

/// How far each training camera is moved: turned by `degrees` about a
/// random axis through its centre, and its centre moved by
/// `offset_fraction` of the side of the scene's box in a random direction.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CameraPerturbation {
    pub degrees: f32,
    pub offset_fraction: f32,
}

/// The true cameras, in the order of the training frames.
#[derive(Debug, Serialize, Deserialize)]
struct TruthFile {
    /// Row-major camera-to-world matrices, as `transform_matrix`.
    transform_matrices: Vec<[[f32; 4]; 4]>,
}

/// A direction uniform on the sphere.
fn random_direction(rng: &mut Pcg32) -> Vec3 {
    let z = 2.0 * rng.next_f32() - 1.0;
    let angle = std::f32::consts::TAU * rng.next_f32();
    let across = (1.0 - z * z).max(0.0).sqrt();
    Vec3::new(across * angle.cos(), across * angle.sin(), z)
}

/// Moves each of `cameras` as `perturbation` says (`box_side` the scene's
/// box side in world units), from `seed`: the rotation acts in world axes
/// about the camera's centre, as camera refinement's correction does, so
/// the correction that undoes it is exactly its inverse.
pub fn perturb_cameras(
    cameras: &mut [Camera],
    perturbation: CameraPerturbation,
    box_side: f32,
    seed: u64,
) {
    let mut rng = Pcg32::new(seed, 46);
    for camera in cameras {
        let turn = Mat3::from_axis_angle(
            random_direction(&mut rng),
            perturbation.degrees.to_radians(),
        );
        let shift = random_direction(&mut rng) * perturbation.offset_fraction * box_side;
        let m = camera.camera_to_world;
        camera.camera_to_world = Mat4::from_cols(
            (turn * m.x_axis.truncate()).extend(0.0),
            (turn * m.y_axis.truncate()).extend(0.0),
            (turn * m.z_axis.truncate()).extend(0.0),
            (m.w_axis.truncate() + shift).extend(1.0),
        );
    }
}

/// Writes the demo (see [`super::write`]) with its training cameras
/// perturbed, and the true ones in [`CAMERA_TRUTH_FILE`].
pub fn write_with_perturbed_cameras(
    config: &DemoConfig,
    perturbation: CameraPerturbation,
    dir: &Path,
) -> SceneResult<()> {
    let mut scene = build(config);
    let truth = TruthFile {
        transform_matrices: scene
            .train
            .iter()
            .map(|f| std::array::from_fn(|row| f.camera.camera_to_world.row(row).to_array()))
            .collect(),
    };
    let mut cameras: Vec<Camera> = scene.train.iter().map(|f| f.camera).collect();
    let side = scene.bounds.size().max_element();
    perturb_cameras(&mut cameras, perturbation, side, PERTURBATION_SEED);
    for (frame, camera) in scene.train.iter_mut().zip(cameras) {
        frame.camera = camera;
    }
    write_blender(&scene, dir)?;
    let path = dir.join(CAMERA_TRUTH_FILE);
    let text = serde_json::to_string_pretty(&truth)
        .map_err(|e| SceneError::new(&path, format!("cannot encode JSON: {e}")))?;
    crate::files::write_bytes_atomically(&path, text.as_bytes())
        .map_err(|e| SceneError::new(&path, format!("cannot write file: {e}")))
}

/// The true camera-to-world matrices of a demo written with perturbed
/// cameras, in the order of its training frames.
pub fn read_camera_truth(dir: &Path) -> SceneResult<Vec<Mat4>> {
    let path = dir.join(CAMERA_TRUTH_FILE);
    let text = std::fs::read_to_string(&path)
        .map_err(|e| SceneError::new(&path, format!("cannot read file: {e}")))?;
    let file: TruthFile = serde_json::from_str(&text)
        .map_err(|e| SceneError::new(&path, format!("not a camera truth file: {e}")))?;
    Ok(file
        .transform_matrices
        .iter()
        .map(|rows| Mat4::from_cols_array_2d(rows).transpose())
        .collect())
}
