//! The forward-facing demo: the demo's objects photographed as a hand-held
//! forward-facing capture is (the NeRF paper's LLFF scenes): every camera
//! on one plane, all looking the same way, in front of an opaque, textured
//! back wall that fills every view. Its poses, bounds and photographs are
//! known exactly, so the LLFF loader and normalised device coordinates can
//! be tested against them.

use std::path::{Path, PathBuf};

use glam::Vec3;
use rayon::prelude::*;

use super::{CAMERA_ANGLE_X, CONTENT_RADIUS, SAMPLES_PER_SIDE, World};
use crate::scene::llff::{self, LlffView, Photograph};
use crate::scene::{Camera, ImageRgba8, Intrinsics, Scene, SceneError, SceneResult, to_u8};

/// How large the forward-facing demo is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ForwardFacingConfig {
    /// The photographs' size in pixels.
    pub width: u32,
    pub height: u32,
    /// Photographs in all; every [`llff::HOLD_OUT_EVERY`]-th is held out.
    pub views: usize,
}

impl Default for ForwardFacingConfig {
    /// 4:3 photographs, as LLFF's phone captures are, and 24 of them (the
    /// NeRF paper's LLFF scenes have 20 to 62).
    fn default() -> Self {
        Self {
            width: 128,
            height: 96,
            views: 24,
        }
    }
}

/// Distance from the demo's centre back to the plane the cameras are on,
/// along the viewing direction.
pub const FORWARD_CAMERA_DISTANCE: f32 = 4.0;

/// Distance of the back wall beyond the demo's centre, along the viewing
/// direction: behind every object (they lie within 1.25 of the centre).
pub const WALL_DISTANCE: f32 = 2.0;

/// The radius of the disc the cameras stand on: a hand's sway. The nearest
/// content then moves some 40 pixels across a 128-pixel photograph between
/// the farthest views (LLFF's capture guide allows 64 at any size).
pub const CAPTURE_RADIUS: f32 = 0.3;

/// How far the cameras look down, in degrees, so the stand shows.
const PITCH_DEG: f32 = 15.0;

/// The size of the wall's squares, in world units.
const WALL_TILE: f32 = 0.4;

/// The direction every camera faces (give or take the few degrees each
/// turns to face the wall's centre): towards +y, tilted down.
pub fn viewing_direction() -> Vec3 {
    let pitch = PITCH_DEG.to_radians();
    Vec3::new(0.0, pitch.cos(), -pitch.sin())
}

/// The cameras of the capture in the demo's world (z up), in file order:
/// on a sunflower spiral filling the disc of [`CAPTURE_RADIUS`] on the
/// plane [`FORWARD_CAMERA_DISTANCE`] in front of the centre, each looking
/// at the wall's centre.
pub fn forward_facing_cameras(config: &ForwardFacingConfig) -> Vec<Camera> {
    let forward = viewing_direction();
    let right = forward.cross(Vec3::Z).normalize();
    let up = right.cross(forward);
    let plane_centre = -FORWARD_CAMERA_DISTANCE * forward;
    let target = WALL_DISTANCE * forward;
    let intrinsics = Intrinsics::from_fov_x(config.width, config.height, CAMERA_ANGLE_X);
    let golden_angle = std::f32::consts::PI * (3.0 - 5f32.sqrt());
    let count = config.views.max(1) as f32;
    (0..config.views)
        .map(|k| {
            let radius = CAPTURE_RADIUS * ((k as f32 + 0.5) / count).sqrt();
            let angle = k as f32 * golden_angle;
            let eye = plane_centre + radius * (angle.cos() * right + angle.sin() * up);
            Camera::look_at(intrinsics, eye, target, Vec3::Z)
        })
        .collect()
}

/// The depths along `camera`'s optical axis between which it sees the
/// scene: from the nearest the content can be (its bounding sphere) to the
/// farthest point of the wall in view (at a corner of the image).
pub fn view_bounds(camera: &Camera) -> (f64, f64) {
    let eye = camera.position();
    let near = (-eye).dot(camera.forward()) - CONTENT_RADIUS;
    let forward = viewing_direction();
    let k = camera.intrinsics;
    let (w, h) = (k.width as f32, k.height as f32);
    let far = [(0.0, 0.0), (w, 0.0), (0.0, h), (w, h)]
        .into_iter()
        .map(|(u, v)| {
            // Depth along the axis is t along the direction at unit depth.
            let d = camera.world_ray_through(u, v).direction_unnormalised;
            (WALL_DISTANCE - eye.dot(forward)) / d.dot(forward)
        })
        .fold(0.0f32, f32::max);
    (near as f64, far as f64)
}

/// The colour of the back wall where the ray from `origin` along unit
/// `direction` meets it: squares of two tones under slow colour gradients,
/// so every part of it differs from every other (no repeats to confuse).
fn wall(origin: Vec3, direction: Vec3) -> Vec3 {
    let forward = viewing_direction();
    let right = forward.cross(Vec3::Z).normalize();
    let up = right.cross(forward);
    let t = (WALL_DISTANCE - origin.dot(forward)) / direction.dot(forward);
    let p = origin + t * direction;
    let (a, b) = (p.dot(right), p.dot(up));
    let checker = ((a / WALL_TILE).floor() as i32 + (b / WALL_TILE).floor() as i32) & 1;
    let base = Vec3::new(
        0.55 + 0.25 * (0.7 * a).sin(),
        0.5 + 0.2 * (0.9 * b).cos(),
        0.45 + 0.2 * (0.5 * (a + b)).sin(),
    );
    if checker == 0 { base } else { base * 0.65 }
}

/// Renders a view of the forward-facing demo: the objects, and the wall
/// wherever no object is hit (16 samples per pixel, every pixel opaque).
/// `camera` must look towards the wall.
pub fn render_forward_facing_view(camera: &Camera) -> ImageRgba8 {
    let (width, height) = (camera.intrinsics.width, camera.intrinsics.height);
    let world = World::new();
    let mut data = vec![0u8; width as usize * height as usize * 4];
    if data.is_empty() {
        return ImageRgba8::new(width, height, data);
    }
    let n = SAMPLES_PER_SIDE;
    data.par_chunks_mut(width as usize * 4)
        .enumerate()
        .for_each(|(row, pixels)| {
            for (column, pixel) in pixels.chunks_exact_mut(4).enumerate() {
                let mut colour = Vec3::ZERO;
                for s in 0..n * n {
                    let (dx, dy) = (
                        ((s % n) as f32 + 0.5) / n as f32,
                        ((s / n) as f32 + 0.5) / n as f32,
                    );
                    let ray = camera.world_ray_through(column as f32 + dx, row as f32 + dy);
                    colour += world
                        .trace(ray.origin, ray.direction)
                        .unwrap_or_else(|| wall(ray.origin, ray.direction));
                }
                let mean = colour / (n * n) as f32;
                pixel.copy_from_slice(&[to_u8(mean.x), to_u8(mean.y), to_u8(mean.z), 255]);
            }
        });
    ImageRgba8::new(width, height, data)
}

/// The capture: its cameras in the demo's world, their LLFF rows and
/// their photographs, in file order.
fn capture(config: &ForwardFacingConfig) -> (Vec<Camera>, Vec<LlffView>, Vec<ImageRgba8>) {
    let cameras = forward_facing_cameras(config);
    let bounds: Vec<(f64, f64)> = cameras.iter().map(view_bounds).collect();
    let views = llff::views_of(&cameras, &bounds);
    let images = cameras.par_iter().map(render_forward_facing_view).collect();
    (cameras, views, images)
}

/// The forward-facing demo in memory, as the LLFF loader would give it
/// from the folder [`write_forward_facing_llff`] writes: normalised (the
/// nearest bound at 1/0.75, the average pose the identity), every 8th view
/// held out, in world coordinates (NDC through [`Scene::with_ndc`]).
pub fn build_forward_facing(config: &ForwardFacingConfig) -> Scene {
    let (cameras, views, images) = capture(config);
    let photographs = cameras
        .iter()
        .zip(images)
        .map(|(camera, image)| Photograph {
            image,
            image_path: PathBuf::new(),
            intrinsics: camera.intrinsics,
        })
        .collect();
    llff::assemble(
        "demo-forward-facing".into(),
        PathBuf::new(),
        &views,
        photographs,
        false,
    )
}

/// Writes the forward-facing demo under `dir` as an LLFF folder:
/// `poses_bounds.npy` and `images/NNNNN.png`.
pub fn write_forward_facing_llff(config: &ForwardFacingConfig, dir: &Path) -> SceneResult<()> {
    let (_, views, images) = capture(config);
    let folder = dir.join("images");
    std::fs::create_dir_all(&folder)
        .map_err(|e| SceneError::new(&folder, format!("cannot create folder: {e}")))?;
    // RGB files, as a camera's are: the photographs are opaque.
    images
        .par_iter()
        .enumerate()
        .try_for_each(|(index, image)| {
            let path = folder.join(format!("{index:05}.png"));
            let rgb: Vec<u8> = image
                .data
                .chunks_exact(4)
                .flat_map(|p| [p[0], p[1], p[2]])
                .collect();
            image::RgbImage::from_raw(image.width, image.height, rgb)
                .expect("3 bytes a pixel")
                .save(&path)
                .map_err(|e| SceneError::new(&path, format!("cannot write PNG: {e}")))
        })?;
    llff::write_poses_bounds(&dir.join(llff::POSES_FILE), &views)
}
