//! The unbounded demo: the demo's objects on their stand, standing on a
//! ground plane that runs to the horizon under a sky at infinity, every
//! pixel opaque. What a photograph of a real, unbounded scene holds, with a
//! known answer: the true depth of every pixel ([`unbounded_depth`]), the
//! sky's infinite.
//!
//! The ground is the plane z = [`GROUND_PLANE_Z`] (the stand's underside),
//! a checkerboard of [`GROUND_CELL`]-unit squares whose contrast fades
//! with distance (so it does not alias towards the horizon) under a light
//! haze. The sky's colour (a gradient with clouds) depends on the direction
//! alone, so it shows no parallax. Cameras lie on the demo's spiral, lower (from
//! [`LOWEST_ELEVATION_DEG`]), so that the lower half of them see the
//! horizon and the sky above it.

use std::path::Path;

use glam::Vec3;

use super::{
    AMBIENT, DemoConfig, FILL_INTENSITY, GROUND_THICKNESS, GROUND_Z, KEY_INTENSITY,
    SURFACE_EPSILON, World, build_with, render, spiral_cameras, write_instant_ngp,
};
use crate::scene::{
    Camera, ImageRgba8, Scene, SceneFormat, SceneResult, Split, UnitCubeMapping, space,
};

/// Height of the ground plane: the stand's underside, so the stand rests
/// on it.
pub const GROUND_PLANE_Z: f32 = GROUND_Z - GROUND_THICKNESS;

/// Side of the ground's checker squares, in world units: larger than the
/// stand's (0.22), so the two read apart.
pub const GROUND_CELL: f32 = 1.0;

/// Distance from the origin over which the checker's contrast falls to
/// 1/e: at the horizon the ground is its mean colour, as a photograph's
/// far field is.
const CHECKER_FADE_DISTANCE: f32 = 10.0;

/// Distance along a ray over which the haze takes 1/e of the ground's
/// colour towards the sky's at the horizon (aerial perspective).
const HAZE_DISTANCE: f32 = 60.0;

/// The unbounded demo's `aabb_scale`: what instant-ngp's `colmap2nerf.py`
/// recommends for real, unbounded captures (16, as gum-desk's).
pub const UNBOUNDED_AABB_SCALE: f32 = 16.0;

/// The training spiral's lowest and highest elevation, in degrees. A
/// camera at elevation e looks down by e, and the demo's cameras see 19.8°
/// above their axis: those below 19.8° (about 45 % of them) see the sky.
const LOWEST_ELEVATION_DEG: f32 = 3.0;
const HIGHEST_ELEVATION_DEG: f32 = 45.0;

const GROUND_LIGHT: Vec3 = Vec3::new(0.62, 0.6, 0.5);
const GROUND_DARK: Vec3 = Vec3::new(0.3, 0.4, 0.26);
const SKY_HORIZON: Vec3 = Vec3::new(0.8, 0.85, 0.92);
const SKY_ZENITH: Vec3 = Vec3::new(0.25, 0.45, 0.85);

/// The unbounded demo's cameras of one split, without rendering anything:
/// the demo's spiral (see [`super::split_cameras`]) from
/// [`LOWEST_ELEVATION_DEG`] up to [`HIGHEST_ELEVATION_DEG`].
pub fn unbounded_split_cameras(config: &DemoConfig, split: Split) -> Vec<Camera> {
    spiral_cameras(config, split, (LOWEST_ELEVATION_DEG, HIGHEST_ELEVATION_DEG))
}

/// Builds the unbounded demo in memory: the objects on the endless ground
/// under the sky, no alpha, `aabb_scale` [`UNBOUNDED_AABB_SCALE`], as an
/// instant-ngp scene.
pub fn build_unbounded(config: &DemoConfig) -> Scene {
    let mut scene = build_with(
        |split| unbounded_split_cameras(config, split),
        render_view_unbounded,
    );
    scene.name = "demo-unbounded".into();
    scene.format = SceneFormat::InstantNgp;
    scene.has_alpha = false;
    scene.unit_cube = UnitCubeMapping {
        aabb_scale: UNBOUNDED_AABB_SCALE,
        ..UnitCubeMapping::BLENDER
    };
    scene.bounds = scene.unit_cube.world_bounds();
    scene.space = space::analyse(&scene);
    scene
}

/// Writes the unbounded demo ([`build_unbounded`]) under `dir` in the
/// instant-ngp layout, as [`super::write_large`] does.
pub fn write_unbounded(config: &DemoConfig, dir: &Path) -> SceneResult<()> {
    write_instant_ngp(&build_unbounded(config), dir)
}

/// Renders the unbounded demo exactly (16 samples per pixel) as seen by
/// any camera above the ground: every pixel opaque.
pub fn render_view_unbounded(camera: &Camera) -> ImageRgba8 {
    render(camera, Some(ground_or_sky))
}

/// The true depth through image point (u, v) of `camera` (pixel units, as
/// [`Camera::ray_through`]): the distance from the camera along the ray's
/// unit direction to the first object or the ground, or `None` where the
/// ray meets the sky (at infinity). For a camera above the ground.
pub fn unbounded_depth(camera: &Camera, u: f32, v: f32) -> Option<f32> {
    let ray = camera.ray_through(u, v);
    let world = World::new();
    match world.intersect(ray.origin, ray.direction) {
        Some(hit) => Some(hit.t),
        None => ground_distance(ray.origin, ray.direction),
    }
}

/// Where a ray from `origin` along unit `direction` meets the ground, or
/// `None` when it runs level or upward (to the sky). Every object stands
/// above the ground, so a ray that meets one does so before the ground.
fn ground_distance(origin: Vec3, direction: Vec3) -> Option<f32> {
    (direction.z < 0.0 && origin.z > GROUND_PLANE_Z)
        .then(|| (GROUND_PLANE_Z - origin.z) / direction.z)
}

/// What a ray that misses every object sees: the ground, lit and shadowed
/// by the objects as they are, or the sky.
fn ground_or_sky(world: &World, origin: Vec3, direction: Vec3) -> Vec3 {
    let Some(t) = ground_distance(origin, direction) else {
        return sky(direction);
    };
    let point = origin + t * direction;
    let cell = (point.x / GROUND_CELL).floor() + (point.y / GROUND_CELL).floor();
    let checker = if cell.rem_euclid(2.0) < 0.5 {
        GROUND_LIGHT
    } else {
        GROUND_DARK
    };
    let mean = 0.5 * (GROUND_LIGHT + GROUND_DARK);
    let contrast = (-point.truncate().length() / CHECKER_FADE_DISTANCE).exp();
    let base = mean.lerp(checker, contrast);
    // The ground faces up; the key light's shadows are the objects'.
    let lift = point + SURFACE_EPSILON * Vec3::Z;
    let key_cos = world.key.z.max(0.0);
    let key_visible = if key_cos > 0.0 && !world.occluded(lift, world.key) {
        1.0
    } else {
        0.0
    };
    let light =
        AMBIENT + KEY_INTENSITY * key_cos * key_visible + FILL_INTENSITY * world.fill.z.max(0.0);
    let lit = (base * light).min(Vec3::ONE);
    let haze = 1.0 - (-t / HAZE_DISTANCE).exp();
    lit.lerp(SKY_HORIZON, haze)
}

/// The sky's colour along `direction`: pale at the horizon, deeper blue
/// towards the zenith, with clouds; it depends on the direction only (at
/// infinity).
fn sky(direction: Vec3) -> Vec3 {
    let blue = SKY_HORIZON.lerp(SKY_ZENITH, direction.z.clamp(0.0, 1.0).sqrt());
    blue.lerp(CLOUD, cloud_cover(direction))
}

/// The clouds' colour.
const CLOUD: Vec3 = Vec3::new(0.95, 0.95, 0.97);

/// Angular frequencies (radians⁻¹ along the unit sphere) and phases of
/// the waves whose sum makes the clouds: periods of 20° to 40°, several
/// pixels wide in every view, so that a sky placed at a finite distance
/// would not line up across the cameras' spread.
const CLOUD_WAVES: [(Vec3, f32); 4] = [
    (Vec3::new(11.0, 4.0, 3.0), 0.3),
    (Vec3::new(-5.0, 13.0, 2.0), 1.7),
    (Vec3::new(7.0, -8.0, 9.0), 4.1),
    (Vec3::new(-14.0, -6.0, 5.0), 2.6),
];

/// How much of the sky along unit `direction` is cloud, 0 to 1: the waves'
/// sum through a smooth threshold, about a third of the sky covered. Why
/// clouds: a sky that changes with elevation alone looks the same from
/// every camera at any distance along each elevation's cone, so parallax
/// barely pins it; a real sky has texture, and so does this one.
pub fn cloud_cover(direction: Vec3) -> f32 {
    let sum: f32 = CLOUD_WAVES
        .iter()
        .map(|&(frequency, phase)| (frequency.dot(direction) + phase).sin())
        .sum();
    // The sum of four unit waves spreads over about ±2; cover starts at 0.5.
    ((sum - 0.5) / 1.5).clamp(0.0, 1.0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::SceneSpace;

    fn small() -> DemoConfig {
        DemoConfig {
            size: 32,
            train_views: 12,
            val_views: 2,
            test_views: 2,
        }
    }

    #[test]
    fn every_pixel_is_opaque_and_low_cameras_see_the_sky() {
        let scene = build_unbounded(&small());
        assert_eq!(scene.format, SceneFormat::InstantNgp);
        assert!(!scene.has_alpha);
        assert_eq!(scene.unit_cube.aabb_scale, UNBOUNDED_AABB_SCALE);
        assert_eq!(
            scene.space.space,
            SceneSpace::Unbounded,
            "{:?}",
            scene.space
        );
        for frame in scene.frames() {
            assert!(frame.image.data.chunks_exact(4).all(|p| p[3] == 255));
        }
        // Every camera is above the ground and looks at the objects.
        let mut seeing_sky = 0;
        for frame in &scene.train {
            let camera = &frame.camera;
            assert!(camera.position().z > GROUND_PLANE_Z + 0.1);
            let k = camera.intrinsics;
            // The top row's centre: sky for the low cameras only.
            if unbounded_depth(camera, 0.5 * k.width as f32, 0.5).is_none() {
                seeing_sky += 1;
                // The sky's colour there, not the ground's.
                let [r, g, b, _] = frame.image.rgba(k.width / 2, 0);
                assert!(b > r && b > g, "sky pixel {r} {g} {b}");
            }
        }
        assert!(
            (3..=9).contains(&seeing_sky),
            "{seeing_sky} of 12 training views see the sky at the top"
        );
    }

    #[test]
    fn depth_is_the_ground_plane_or_an_object_or_none_for_the_sky() {
        // A camera 2 units above the ground looking straight down at a
        // point 5 units off the stand: the ground at depth 2 exactly.
        let intrinsics = crate::scene::Intrinsics::from_fov_x(16, 16, super::super::CAMERA_ANGLE_X);
        let above = Vec3::new(5.0, 0.0, GROUND_PLANE_Z + 2.0);
        let down = Camera::look_at(intrinsics, above, above - Vec3::Z, Vec3::Y);
        let depth = unbounded_depth(&down, 8.0, 8.0).unwrap();
        assert!((depth - 2.0).abs() < 1e-5, "{depth}");
        // Looking up: the sky, at no depth.
        let up = Camera::look_at(intrinsics, above, above + Vec3::Z, Vec3::Y);
        assert_eq!(unbounded_depth(&up, 8.0, 8.0), None);
        // Looking at the red ball from 4 units along x: its near surface.
        let eye = super::super::RED_CENTRE + Vec3::new(4.0, 0.0, 0.0);
        let at_ball = Camera::look_at(intrinsics, eye, super::super::RED_CENTRE, Vec3::Z);
        let depth = unbounded_depth(&at_ball, 8.0, 8.0).unwrap();
        assert!(
            (depth - (4.0 - super::super::RED_RADIUS)).abs() < 1e-3,
            "{depth}"
        );
        // A level ray over the ground runs to the horizon: the sky.
        let level = Camera::look_at(intrinsics, above, above + Vec3::X, Vec3::Z);
        assert_eq!(unbounded_depth(&level, 8.0, 7.0), None);
        assert!(unbounded_depth(&level, 8.0, 9.0).unwrap() > 10.0);
    }

    #[test]
    fn the_ground_fades_to_its_mean_and_the_sky_has_no_parallax() {
        let world = World::new();
        // Near the stand the checker squares differ; far off they do not.
        let from = Vec3::new(0.0, 0.0, 3.0);
        let towards = |x: f32, y: f32| (Vec3::new(x, y, GROUND_PLANE_Z) - from).normalize();
        let near_light = ground_or_sky(&world, from, towards(2.5, 3.5));
        let near_dark = ground_or_sky(&world, from, towards(3.5, 3.5));
        assert!((near_light - near_dark).length() > 0.1);
        let far_light = ground_or_sky(&world, from, towards(200.5, 0.5));
        let far_dark = ground_or_sky(&world, from, towards(201.5, 0.5));
        assert!((far_light - far_dark).length() < 0.01);
        // The same direction from two places: the same sky.
        let direction = Vec3::new(0.3, 0.2, 0.4).normalize();
        assert_eq!(
            ground_or_sky(&world, Vec3::ZERO, direction),
            ground_or_sky(&world, Vec3::new(5.0, -3.0, 1.0), direction)
        );
    }

    #[test]
    fn the_written_scene_loads_back_unbounded() {
        let dir = tempfile::tempdir().unwrap();
        let config = DemoConfig {
            size: 16,
            train_views: 6,
            val_views: 1,
            test_views: 1,
        };
        write_unbounded(&config, dir.path()).unwrap();
        let scene = Scene::load(dir.path(), crate::scene::LoadOptions::default()).unwrap();
        let built = build_unbounded(&config);
        assert_eq!(scene.unit_cube.aabb_scale, UNBOUNDED_AABB_SCALE);
        assert_eq!(
            (scene.train.len(), scene.val.len(), scene.test.len()),
            (6, 1, 1)
        );
        for (loaded, made) in scene.frames().zip(built.frames()) {
            assert_eq!(loaded.image.data, made.image.data);
        }
        // The PNGs carry an alpha channel, opaque everywhere: still unbounded.
        assert_eq!(
            scene.space.space,
            SceneSpace::Unbounded,
            "{:?}",
            scene.space
        );
    }
}
