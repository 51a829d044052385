//! Camera paths for novel views: the turntable around a scene.

use glam::Vec3;

use crate::scene::{Camera, Intrinsics, Scene};

/// A circular orbit around the scene's centre.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Turntable {
    pub frames: usize,
    /// Degrees above the horizontal plane.
    pub elevation_degrees: f32,
    /// Distance from the centre; `None` takes the training cameras' mean.
    pub radius: Option<f32>,
    /// Image size; `None` takes the training images'.
    pub size: Option<(u32, u32)>,
}

impl Default for Turntable {
    fn default() -> Self {
        Self {
            frames: 60,
            elevation_degrees: 30.0,
            radius: None,
            size: None,
        }
    }
}

/// The scene's up direction: the mean of the training cameras' up axes
/// (for NeRF-synthetic scenes, +z), falling back to +z.
pub fn scene_up(scene: &Scene) -> Vec3 {
    let sum: Vec3 = scene
        .train
        .iter()
        .map(|f| f.camera.camera_to_world.y_axis.truncate())
        .sum();
    sum.try_normalize().unwrap_or(Vec3::Z)
}

/// The cameras of `turntable` around `scene`, looking at its view centre
/// ([`Scene::view_centre_and_size`]: its box's centre, unless its rays are
/// in NDC), with the field of view of its first training view and the
/// scene's NDC, if any.
pub fn turntable_cameras(scene: &Scene, turntable: &Turntable) -> Vec<Camera> {
    let (centre, _) = scene.view_centre_and_size();
    let up = scene_up(scene);
    let first = scene.train.first().or_else(|| scene.frames().next());
    let mean_distance = if scene.train.is_empty() {
        4.0
    } else {
        scene
            .train
            .iter()
            .map(|f| (f.camera.position() - centre).length())
            .sum::<f32>()
            / scene.train.len() as f32
    };
    let radius = turntable.radius.unwrap_or(mean_distance);
    let intrinsics = {
        let base = first
            .map(|f| f.camera.intrinsics)
            .unwrap_or(Intrinsics::from_fov_x(128, 128, 0.691_111_2));
        match turntable.size {
            Some((w, h)) => Intrinsics::from_fov_x(w, h, base.fov_x()),
            None => base,
        }
    };
    // Two axes spanning the horizontal plane.
    let reference = if up.dot(Vec3::X).abs() < 0.9 {
        Vec3::X
    } else {
        Vec3::Y
    };
    let east = up.cross(reference).normalize();
    let north = up.cross(east);
    let elevation = turntable.elevation_degrees.to_radians();
    (0..turntable.frames)
        .map(|i| {
            let azimuth = std::f32::consts::TAU * i as f32 / turntable.frames.max(1) as f32;
            let horizontal = east * azimuth.cos() + north * azimuth.sin();
            let eye = centre + radius * (horizontal * elevation.cos() + up * elevation.sin());
            Camera::look_at(intrinsics, eye, centre, up).with_ndc(scene.ndc())
        })
        .collect()
}
