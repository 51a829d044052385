//! The viewer's free camera: orbit around the scene, or fly through it, and
//! jump to any training view.
//!
//! One pose serves both navigation modes: an orientation (camera-to-world
//! rotation, OpenGL axes: x right, y up, looking down -z), a target on the
//! optical axis and the distance from the eye to it. Orbiting turns about
//! the target, flying turns about the eye; since neither mode keeps state of
//! its own, switching between them never moves the camera.

use glam::{Mat4, Quat, Vec3};

use crate::render::path::scene_up;
use crate::scene::{Camera, Intrinsics, Lens, NdcSpace, Scene};

/// How the mouse and keys move the camera.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Navigation {
    /// Drag turns the camera around the target, scroll zooms, pan slides.
    Orbit,
    /// Mouse look turns the camera about the eye; WASD/QE move it.
    Fly,
}

/// Key state for one fly step; each axis in [-1, 1].
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct FlyInput {
    /// Along the view direction (W = +1, S = -1).
    pub forward: f32,
    /// Along the camera's right axis (D = +1, A = -1).
    pub right: f32,
    /// Along the scene's up direction (E = +1, Q = -1).
    pub up: f32,
    /// Move [`FAST_FACTOR`] times faster (Shift).
    pub fast: bool,
}

/// Orbit drag: radians per pixel, so that a drag across a 600-pixel view
/// turns the scene about 170°.
const ORBIT_RADIANS_PER_PIXEL: f32 = 0.005;

/// Mouse look: radians per pixel, gentler than orbiting because turning the
/// head swings the whole view.
const LOOK_RADIANS_PER_PIXEL: f32 = 0.003;

/// How close to straight up or down the view may tilt. Short of 90° so that
/// the yaw axis (the scene's up) never lines up with the view direction,
/// where yaw would turn into roll.
const PITCH_LIMIT_DEGREES: f32 = 89.0;

/// Zoom: the distance shrinks by exp(-rate · scroll). The window's toolkit
/// reports about 50 points per wheel notch, so one notch moves about 10%
/// closer.
const ZOOM_RATE_PER_SCROLL: f32 = 0.002;

/// Nearest and farthest target distance, in scene sizes (the diagonal of the
/// scene's box): close enough to inspect detail, far enough to see it whole
/// many times over, never zero (the target would sit on the eye).
const MIN_DISTANCE_SCENE_SIZES: f32 = 1e-3;
const MAX_DISTANCE_SCENE_SIZES: f32 = 100.0;

/// Fly speed in scene sizes per second: crossing the scene takes two
/// seconds, slow enough to aim, fast enough not to bore.
const FLY_SCENE_SIZES_PER_SECOND: f32 = 0.5;

/// Speed factor while [`FlyInput::fast`] is held.
pub const FAST_FACTOR: f32 = 4.0;

/// The longest time step a fly call moves for: a stalled frame (a long
/// render, a window drag) must not throw the camera through the scene.
const MAX_FLY_STEP_SECONDS: f32 = 0.1;

/// Vertical field of view when the scene has no camera to copy.
const DEFAULT_FOV_Y_DEGREES: f32 = 40.0;

/// The field of view the camera may take: a pinhole needs 0° < fov < 180°.
const MIN_FOV_Y_DEGREES: f32 = 1.0;
const MAX_FOV_Y_DEGREES: f32 = 170.0;

/// The viewer's camera.
#[derive(Debug, Clone, PartialEq)]
pub struct ViewCamera {
    /// Vertical field of view, in degrees.
    pub fov_y_degrees: f32,
    navigation: Navigation,
    /// Camera-to-world rotation (unit quaternion).
    rotation: Quat,
    /// The point orbiting turns about, on the optical axis.
    target: Vec3,
    /// From the eye to the target, > 0.
    distance: f32,
    /// The scene's up direction (unit): the yaw axis.
    up: Vec3,
    /// The scene's box centre and diagonal, for snapping and speeds.
    scene_centre: Vec3,
    scene_size: f32,
    /// fx / fy of the view last snapped to (1 for square pixels).
    pixel_aspect: f32,
    /// Principal point as fractions of the width and height (0.5 = centre).
    principal_point: (f32, f32),
    /// The lens of the view last snapped to, so that a training view is
    /// rendered through the same distortion as its photograph.
    lens: Lens,
    /// The scene's normalised device coordinates, where its rays are in
    /// NDC (a forward-facing capture): the views are rendered in them too.
    ndc: Option<NdcSpace>,
}

impl ViewCamera {
    /// Orbits around the centre of the scene's box, with the scene's up as
    /// the yaw axis, starting from the first training camera (its position,
    /// roll and field of view), turned just enough to face the centre.
    pub fn for_scene(scene: &Scene) -> Self {
        // A scene in NDC has its box in NDC; the camera moves in the world.
        let (centre, size) = scene.view_centre_and_size();
        let scene_size = if size.is_finite() && size > 0.0 {
            size
        } else {
            1.0
        };
        let up = scene_up(scene);
        let mut camera = Self {
            fov_y_degrees: DEFAULT_FOV_Y_DEGREES,
            navigation: Navigation::Orbit,
            rotation: Quat::IDENTITY,
            target: centre,
            distance: scene_size,
            up,
            scene_centre: centre,
            scene_size,
            pixel_aspect: 1.0,
            principal_point: (0.5, 0.5),
            lens: Lens::Pinhole,
            ndc: scene.ndc(),
        };
        let first = scene.train.first().or_else(|| scene.frames().next());
        match first {
            Some(frame) => {
                camera.snap_to(&frame.camera);
                // Face the centre exactly: the smallest turn from the
                // training view's direction, so its roll is kept.
                let to_centre = centre - camera.eye();
                if let Some(direction) = to_centre.try_normalize() {
                    let turn = Quat::from_rotation_arc(camera.forward(), direction);
                    camera.rotation = (turn * camera.rotation).normalize();
                    camera.distance = camera.clamp_distance(to_centre.length());
                    camera.target = centre;
                }
            }
            None => {
                // Look at the centre from 30° above the horizon.
                let eye_direction =
                    horizontal_axis(up) * 30f32.to_radians().cos() + up * 30f32.to_radians().sin();
                let eye = centre + 1.5 * scene_size * eye_direction;
                let look = Camera::look_at(Intrinsics::from_fov_x(1, 1, 1.0), eye, centre, up);
                camera.rotation = Quat::from_mat3(&look.rotation()).normalize();
                camera.distance = 1.5 * scene_size;
            }
        }
        camera
    }

    /// Back to where [`Self::for_scene`] starts, keeping the navigation mode.
    pub fn reset(&mut self, scene: &Scene) {
        let navigation = self.navigation;
        *self = Self::for_scene(scene);
        self.navigation = navigation;
    }

    pub fn navigation(&self) -> Navigation {
        self.navigation
    }

    /// Switches mode; the pose stays as it is.
    pub fn set_navigation(&mut self, navigation: Navigation) {
        self.navigation = navigation;
    }

    /// Orbit drag by (`dx`, `dy`) pixels: right turns the scene right (the
    /// eye moves left around the target), down tilts it towards the viewer
    /// (the eye rises). Yaw is about the scene's up; pitch stops
    /// [`PITCH_LIMIT_DEGREES`] short of the poles. The target stays put.
    pub fn orbit(&mut self, dx_pixels: f32, dy_pixels: f32) {
        self.turn(
            -dx_pixels * ORBIT_RADIANS_PER_PIXEL,
            -dy_pixels * ORBIT_RADIANS_PER_PIXEL,
            false,
        );
    }

    /// Scroll: positive moves towards the target. The distance changes by a
    /// factor (exp(-rate · scroll)), so zooming feels the same at any range;
    /// the view direction is unchanged.
    pub fn zoom(&mut self, scroll: f32) {
        if !scroll.is_finite() {
            return;
        }
        self.distance = self.clamp_distance(self.distance * (-ZOOM_RATE_PER_SCROLL * scroll).exp());
    }

    /// Pan drag by (`dx`, `dy`) pixels in a view `viewport_height_pixels`
    /// tall: eye and target slide together parallel to the image plane so
    /// that what lies at the target's depth follows the cursor exactly.
    pub fn pan(&mut self, dx_pixels: f32, dy_pixels: f32, viewport_height_pixels: f32) {
        if !(viewport_height_pixels > 0.0 && dx_pixels.is_finite() && dy_pixels.is_finite()) {
            return;
        }
        let fy = self.focal_y(viewport_height_pixels);
        let fx = fy * self.pixel_aspect;
        // At depth d a pixel spans d / f world units; the world moves with
        // the cursor, so the camera moves the other way (v counts down).
        let right = self.rotation * Vec3::X;
        let camera_up = self.rotation * Vec3::Y;
        let shift = self.distance * (-dx_pixels / fx * right + dy_pixels / fy * camera_up);
        self.target += shift;
    }

    /// Mouse look by (`dx`, `dy`) pixels: right turns right, down looks
    /// down; the eye stays put and the target swings around it.
    pub fn look(&mut self, dx_pixels: f32, dy_pixels: f32) {
        self.turn(
            -dx_pixels * LOOK_RADIANS_PER_PIXEL,
            -dy_pixels * LOOK_RADIANS_PER_PIXEL,
            true,
        );
    }

    /// Moves eye and target for `dt_seconds` of held keys: forward along the
    /// view direction, right along the camera's right axis, up along the
    /// scene's up, at [`Self::fly_speed`] (× [`FAST_FACTOR`] when fast).
    /// Diagonals are no faster than straight moves.
    pub fn fly(&mut self, input: FlyInput, dt_seconds: f32) {
        let axis = |value: f32| {
            if value.is_finite() {
                value.clamp(-1.0, 1.0)
            } else {
                0.0
            }
        };
        let mut direction = axis(input.forward) * self.forward()
            + axis(input.right) * (self.rotation * Vec3::X)
            + axis(input.up) * self.up;
        if direction.length_squared() > 1.0 {
            direction = direction.normalize();
        }
        let dt = if dt_seconds.is_finite() {
            dt_seconds.clamp(0.0, MAX_FLY_STEP_SECONDS)
        } else {
            0.0
        };
        let speed = self.fly_speed() * if input.fast { FAST_FACTOR } else { 1.0 };
        self.target += direction * speed * dt;
    }

    /// World units per second of an unhurried fly move.
    pub fn fly_speed(&self) -> f32 {
        FLY_SCENE_SIZES_PER_SECOND * self.scene_size
    }

    /// Takes a training view's exact pose and field of view (and its pixel
    /// aspect and principal point, so that [`Self::camera`] at the view's
    /// size reproduces its intrinsics). The target goes on the new optical
    /// axis at the depth of the scene's centre, so orbiting afterwards turns
    /// about the object the view looks at.
    pub fn snap_to(&mut self, camera: &Camera) {
        let k = camera.intrinsics;
        let rotation = Quat::from_mat3(&camera.rotation()).normalize();
        let eye = camera.position();
        if !(rotation.is_finite() && eye.is_finite()) {
            return;
        }
        self.rotation = rotation;
        let fov_y = k.fov_y().to_degrees();
        if fov_y.is_finite() && fov_y > 0.0 {
            self.fov_y_degrees = fov_y;
        }
        if k.fx > 0.0 && k.fy > 0.0 && k.width > 0 && k.height > 0 {
            self.pixel_aspect = k.fx / k.fy;
            self.principal_point = (k.cx / k.width as f32, k.cy / k.height as f32);
        }
        self.lens = k.lens;
        let centre_depth = (self.scene_centre - eye).dot(self.forward());
        let min_distance = MIN_DISTANCE_SCENE_SIZES * self.scene_size;
        if centre_depth > min_distance {
            self.distance = self.clamp_distance(centre_depth);
        }
        self.target = eye + self.forward() * self.distance;
    }

    /// Puts the camera at a pose given as a camera-to-world matrix (OpenGL
    /// axes; any scale in it is taken out) with vertical field of view
    /// `fov_y_degrees`: what a camera path's keyframe or sample holds. The
    /// view becomes a plain pinhole (square pixels, principal point at the
    /// centre), as a path is rendered; the target goes on the optical axis
    /// at the depth of the scene's centre, as [`Self::snap_to`] puts it. A
    /// pose that is not finite is ignored.
    pub fn set_pose(&mut self, camera_to_world: Mat4, fov_y_degrees: f32) {
        let axes = glam::Mat3::from_mat4(camera_to_world);
        let unit = glam::Mat3::from_cols(
            axes.x_axis.normalize_or_zero(),
            axes.y_axis.normalize_or_zero(),
            axes.z_axis.normalize_or_zero(),
        );
        let rotation = Quat::from_mat3(&unit).normalize();
        let eye = camera_to_world.w_axis.truncate();
        if !(rotation.is_finite() && eye.is_finite()) {
            return;
        }
        self.rotation = rotation;
        if fov_y_degrees.is_finite() && fov_y_degrees > 0.0 {
            self.fov_y_degrees = fov_y_degrees.clamp(MIN_FOV_Y_DEGREES, MAX_FOV_Y_DEGREES);
        }
        self.pixel_aspect = 1.0;
        self.principal_point = (0.5, 0.5);
        self.lens = Lens::Pinhole;
        let centre_depth = (self.scene_centre - eye).dot(self.forward());
        if centre_depth > MIN_DISTANCE_SCENE_SIZES * self.scene_size {
            self.distance = self.clamp_distance(centre_depth);
        }
        self.target = eye + self.forward() * self.distance;
    }

    /// The scene's size (its box's diagonal), which the camera's speeds and
    /// distances follow.
    pub fn scene_size(&self) -> f32 {
        self.scene_size
    }

    /// The camera to render a `width` × `height` view with (OpenGL axes, as
    /// every [`Camera`]).
    pub fn camera(&self, width: u32, height: u32) -> Camera {
        let (width, height) = (width.max(1), height.max(1));
        let fy = self.focal_y(height as f32);
        let intrinsics = Intrinsics {
            width,
            height,
            fx: fy * self.pixel_aspect,
            fy,
            cx: self.principal_point.0 * width as f32,
            cy: self.principal_point.1 * height as f32,
            lens: self.lens,
        };
        Camera::new(
            intrinsics,
            Mat4::from_rotation_translation(self.rotation, self.eye()),
        )
        .with_ndc(self.ndc)
    }

    pub fn eye(&self) -> Vec3 {
        self.target - self.distance * self.forward()
    }

    pub fn target(&self) -> Vec3 {
        self.target
    }

    /// From the eye to the target.
    pub fn distance(&self) -> f32 {
        self.distance
    }

    /// Unit view direction.
    pub fn forward(&self) -> Vec3 {
        self.rotation * Vec3::NEG_Z
    }

    /// The scene's up direction, about which the camera yaws.
    pub fn up(&self) -> Vec3 {
        self.up
    }

    /// Focal length in pixels for a view `height` pixels tall.
    fn focal_y(&self, height: f32) -> f32 {
        let fov = self
            .fov_y_degrees
            .clamp(MIN_FOV_Y_DEGREES, MAX_FOV_Y_DEGREES);
        // NaN survives clamp; fall back to the default then.
        let fov = if fov.is_finite() {
            fov
        } else {
            DEFAULT_FOV_Y_DEGREES
        };
        0.5 * height / (0.5 * fov.to_radians()).tan()
    }

    fn clamp_distance(&self, distance: f32) -> f32 {
        distance.clamp(
            MIN_DISTANCE_SCENE_SIZES * self.scene_size,
            MAX_DISTANCE_SCENE_SIZES * self.scene_size,
        )
    }

    /// Turns by `yaw` radians about the scene's up (positive turns the view
    /// left) and raises the view direction by `pitch` radians, within the
    /// pitch limit; about the eye when `keep_eye`, else about the target.
    fn turn(&mut self, yaw: f32, pitch: f32, keep_eye: bool) {
        if !(yaw.is_finite() && pitch.is_finite()) {
            return;
        }
        let eye = self.eye();
        let turned = (Quat::from_axis_angle(self.up, yaw) * self.rotation).normalize();
        let forward = turned * Vec3::NEG_Z;
        let elevation = forward.dot(self.up).clamp(-1.0, 1.0).asin();
        let limit = PITCH_LIMIT_DEGREES.to_radians();
        // A view already past the limit (a snapped top-down view) may only
        // move back towards it.
        let new_elevation =
            (elevation + pitch).clamp((-limit).min(elevation), limit.max(elevation));
        let applied = new_elevation - elevation;
        // Rotating about forward × up raises forward straight towards up,
        // so the elevation changes by exactly the angle.
        let axis = forward
            .cross(self.up)
            .try_normalize()
            .unwrap_or(turned * Vec3::X);
        self.rotation = (Quat::from_axis_angle(axis, applied) * turned).normalize();
        if keep_eye {
            self.target = eye + self.distance * self.forward();
        }
    }
}

/// A unit vector perpendicular to `up`.
fn horizontal_axis(up: Vec3) -> Vec3 {
    let reference = if up.dot(Vec3::X).abs() < 0.9 {
        Vec3::X
    } else {
        Vec3::Y
    };
    up.cross(reference).normalize()
}

/// Index of the training view after (`forward`) or before `current`,
/// wrapping around `count` views; `None` (or an index past the end) starts
/// at the first view going forward and the last going back. `None` when
/// there are no views.
pub fn step_view(current: Option<usize>, count: usize, forward: bool) -> Option<usize> {
    if count == 0 {
        return None;
    }
    Some(match (current.filter(|&i| i < count), forward) {
        (None, true) => 0,
        (None, false) => count - 1,
        (Some(i), true) => (i + 1) % count,
        (Some(i), false) => (i + count - 1) % count,
    })
}

#[cfg(test)]
mod tests {
    use std::f32::consts::TAU;

    use super::*;
    use crate::scene::demo::{DemoConfig, build};

    const WIDTH: u32 = 64;
    const HEIGHT: u32 = 48;

    fn scene() -> Scene {
        build(&DemoConfig {
            size: 16,
            train_views: 4,
            val_views: 1,
            test_views: 1,
        })
    }

    fn close(a: Vec3, b: Vec3, tolerance: f32) -> bool {
        (a - b).length() <= tolerance
    }

    fn assert_same_camera(a: &Camera, b: &Camera, tolerance: f32) {
        assert!(
            a.camera_to_world.abs_diff_eq(b.camera_to_world, tolerance),
            "{:?}\nvs\n{:?}",
            a.camera_to_world,
            b.camera_to_world
        );
        let (ka, kb) = (a.intrinsics, b.intrinsics);
        assert_eq!((ka.width, ka.height), (kb.width, kb.height));
        for (x, y) in [
            (ka.fx, kb.fx),
            (ka.fy, kb.fy),
            (ka.cx, kb.cx),
            (ka.cy, kb.cy),
        ] {
            assert!((x - y).abs() < 1e-3, "{ka:?} vs {kb:?}");
        }
        assert_eq!(ka.lens, kb.lens);
    }

    /// Where the target lands in the image.
    fn target_pixel(view: &ViewCamera) -> (f32, f32) {
        view.camera(WIDTH, HEIGHT)
            .project(view.target())
            .expect("target in front of the camera")
    }

    #[test]
    fn starts_at_the_first_training_view_facing_the_centre() {
        let scene = scene();
        let view = ViewCamera::for_scene(&scene);
        let first = scene.train[0].camera;
        assert!(close(view.target(), scene.bounds.centre(), 1e-6));
        assert!(close(view.eye(), first.position(), 1e-5));
        // The demo's cameras look at the origin, the centre of its box, so
        // the pose is the training pose itself.
        let size = first.intrinsics;
        assert_same_camera(&view.camera(size.width, size.height), &first, 1e-5);
        assert_eq!(view.navigation(), Navigation::Orbit);
    }

    #[test]
    fn orbit_keeps_distance_and_target_centred() {
        let mut view = ViewCamera::for_scene(&scene());
        let (target, distance) = (view.target(), view.distance());
        for (dx, dy) in [(40.0, 0.0), (0.0, 25.0), (-130.0, -60.0), (7.0, 300.0)] {
            view.orbit(dx, dy);
            assert!(close(view.target(), target, 1e-6));
            assert!(((view.eye() - view.target()).length() - distance).abs() < 1e-4);
            let (u, v) = target_pixel(&view);
            assert!(
                (u - WIDTH as f32 / 2.0).abs() < 1e-3 && (v - HEIGHT as f32 / 2.0).abs() < 1e-3,
                "target at ({u}, {v})"
            );
        }
    }

    #[test]
    fn orbit_moves_the_eye_the_expected_way() {
        let mut view = ViewCamera::for_scene(&scene());
        let right = view.camera(WIDTH, HEIGHT).rotation() * Vec3::X;
        let eye = view.eye();
        view.orbit(10.0, 0.0);
        // Dragging right moves the eye left around the target.
        assert!((view.eye() - eye).dot(right) < 0.0);
        let height = (view.eye() - view.target()).dot(view.up());
        view.orbit(0.0, 10.0);
        // Dragging down lifts the eye.
        assert!((view.eye() - view.target()).dot(view.up()) > height);
    }

    #[test]
    fn full_turn_of_yaw_returns_to_start() {
        let mut view = ViewCamera::for_scene(&scene());
        let start = view.camera(WIDTH, HEIGHT);
        let steps = 100;
        let pixels_per_turn = TAU / ORBIT_RADIANS_PER_PIXEL;
        for _ in 0..steps {
            view.orbit(pixels_per_turn / steps as f32, 0.0);
        }
        // 100 rotations of f32 round-off on a pose of size ~4.
        assert_same_camera(&view.camera(WIDTH, HEIGHT), &start, 1e-4);
    }

    #[test]
    fn pitch_stops_short_of_the_poles() {
        let mut view = ViewCamera::for_scene(&scene());
        let limit = PITCH_LIMIT_DEGREES.to_radians();
        let elevation = |view: &ViewCamera| view.forward().dot(view.up()).asin();
        // Far down: the eye rises to the limit, looking down.
        view.orbit(0.0, 1e5);
        assert!(
            (elevation(&view) + limit).abs() < 1e-4,
            "{}",
            elevation(&view)
        );
        view.orbit(0.0, 1e5);
        assert!((elevation(&view) + limit).abs() < 1e-4);
        // And the other way.
        view.orbit(0.0, -1e5);
        assert!(
            (elevation(&view) - limit).abs() < 1e-4,
            "{}",
            elevation(&view)
        );
        // Mouse look clamps the same way.
        view.set_navigation(Navigation::Fly);
        view.look(0.0, -1e5);
        assert!((elevation(&view) - limit).abs() < 1e-4);
        // Still a valid camera: the target projects to the centre.
        let (u, v) = target_pixel(&view);
        assert!((u - 32.0).abs() < 1e-2 && (v - 24.0).abs() < 1e-2);
    }

    #[test]
    fn zoom_keeps_the_direction() {
        let mut view = ViewCamera::for_scene(&scene());
        let (target, direction, distance) = (
            view.target(),
            (view.eye() - view.target()).normalize(),
            view.distance(),
        );
        view.zoom(100.0);
        assert!(view.distance() < distance);
        assert!((view.distance() - distance * (-ZOOM_RATE_PER_SCROLL * 100.0).exp()).abs() < 1e-5);
        assert!(close(view.target(), target, 1e-6));
        assert!(close(
            (view.eye() - view.target()).normalize(),
            direction,
            1e-5
        ));
        // However far one scrolls, the eye never reaches the target.
        view.zoom(1e9);
        assert!(view.distance() > 0.0);
        assert!(close(
            (view.eye() - view.target()).normalize(),
            direction,
            1e-4
        ));
        view.zoom(-1e9);
        assert!(view.distance().is_finite());
        view.zoom(f32::NAN);
        assert!(view.distance().is_finite());
    }

    #[test]
    fn pan_drags_the_point_under_the_cursor() {
        let mut view = ViewCamera::for_scene(&scene());
        view.orbit(50.0, -20.0);
        let before = view.camera(WIDTH, HEIGHT);
        let offset = view.eye() - view.target();
        // A point off-centre in the plane through the target facing the
        // camera: at the target's depth.
        let right = before.rotation() * Vec3::X;
        let camera_up = before.rotation() * Vec3::Y;
        let point = view.target() + 0.3 * right - 0.2 * camera_up;
        let (u0, v0) = before.project(point).unwrap();
        let (dx, dy) = (13.0, -7.5);
        view.pan(dx, dy, HEIGHT as f32);
        assert!(close(view.eye() - view.target(), offset, 1e-5));
        let (u1, v1) = view.camera(WIDTH, HEIGHT).project(point).unwrap();
        assert!(
            (u1 - u0 - dx).abs() < 1e-3 && (v1 - v0 - dy).abs() < 1e-3,
            "moved by ({}, {})",
            u1 - u0,
            v1 - v0
        );
    }

    #[test]
    fn fly_forward_moves_along_the_view_direction() {
        let mut view = ViewCamera::for_scene(&scene());
        view.set_navigation(Navigation::Fly);
        let (eye, forward, distance) = (view.eye(), view.forward(), view.distance());
        let dt = 0.05;
        view.fly(
            FlyInput {
                forward: 1.0,
                ..Default::default()
            },
            dt,
        );
        assert!(close(
            view.eye(),
            eye + forward * view.fly_speed() * dt,
            1e-5
        ));
        assert!((view.distance() - distance).abs() < 1e-6);
        // Fast is four times faster; keys along several axes at once are no
        // faster than one.
        let eye = view.eye();
        view.fly(
            FlyInput {
                forward: -1.0,
                fast: true,
                ..Default::default()
            },
            dt,
        );
        assert!(((view.eye() - eye).length() - FAST_FACTOR * view.fly_speed() * dt).abs() < 1e-5);
        let eye = view.eye();
        view.fly(
            FlyInput {
                forward: 1.0,
                right: 1.0,
                up: 1.0,
                fast: false,
            },
            dt,
        );
        assert!(((view.eye() - eye).length() - view.fly_speed() * dt).abs() < 1e-5);
        // Fly speed follows the scene's size.
        assert!((view.fly_speed() - 0.5 * scene().bounds.size().length()).abs() < 1e-5);
    }

    #[test]
    fn look_keeps_the_eye_fixed() {
        let mut view = ViewCamera::for_scene(&scene());
        view.set_navigation(Navigation::Fly);
        let (eye, forward) = (view.eye(), view.forward());
        view.look(30.0, -20.0);
        assert!(close(view.eye(), eye, 1e-5));
        assert!(!close(view.forward(), forward, 1e-2));
        // Looking right turns the view right.
        let right = view.camera(WIDTH, HEIGHT).rotation() * Vec3::X;
        let forward = view.forward();
        view.look(5.0, 0.0);
        assert!((view.forward() - forward).dot(right) > 0.0);
    }

    #[test]
    fn snap_reproduces_a_training_view() {
        let scene = scene();
        let mut view = ViewCamera::for_scene(&scene);
        view.orbit(123.0, 45.0);
        view.fov_y_degrees = 70.0;
        for frame in &scene.train {
            view.snap_to(&frame.camera);
            let k = frame.camera.intrinsics;
            assert_same_camera(&view.camera(k.width, k.height), &frame.camera, 1e-5);
        }
        // Off-centre principal point and non-square pixels too.
        let k = Intrinsics {
            width: 40,
            height: 30,
            fx: 50.0,
            fy: 45.0,
            cx: 21.5,
            cy: 14.0,
            lens: Lens::Pinhole,
        };
        let odd = Camera::look_at(
            k,
            Vec3::new(1.0, -3.0, 2.0),
            Vec3::new(0.2, 0.1, 0.0),
            Vec3::new(0.1, 0.0, 1.0),
        );
        view.snap_to(&odd);
        assert_same_camera(&view.camera(40, 30), &odd, 1e-5);
        // A distorted training view keeps its lens.
        let mut fisheye = odd;
        fisheye.intrinsics.lens = Lens::Fisheye {
            k1: 0.1,
            k2: 0.0,
            k3: 0.0,
            k4: 0.0,
        };
        view.snap_to(&fisheye);
        assert_eq!(view.camera(40, 30).intrinsics.lens, fisheye.intrinsics.lens);
        assert_same_camera(&view.camera(40, 30), &fisheye, 1e-5);
    }

    /// A camera → a path keyframe (what the editor stores) → back: the
    /// same pose and field of view, whatever the view was snapped to.
    #[test]
    fn set_pose_round_trips_through_a_keyframe() {
        use crate::render::camera_path::Keyframe;
        let scene = scene();
        let mut view = ViewCamera::for_scene(&scene);
        view.orbit(140.0, -35.0);
        view.pan(9.0, 4.0, HEIGHT as f32);
        view.fov_y_degrees = 57.5;
        let before = view.camera(WIDTH, HEIGHT);
        let keyframe = Keyframe::from_camera(&before);
        assert!((keyframe.fov_degrees - 57.5).abs() < 1e-4);
        let mut other = ViewCamera::for_scene(&scene);
        // Snapped to a view with odd intrinsics first: set_pose undoes them.
        let odd = Camera::new(
            Intrinsics {
                width: 40,
                height: 30,
                fx: 50.0,
                fy: 45.0,
                cx: 21.5,
                cy: 14.0,
                lens: Lens::Pinhole,
            },
            Mat4::IDENTITY,
        );
        other.snap_to(&odd);
        other.set_pose(
            keyframe.camera_to_world.as_mat4(),
            keyframe.fov_degrees as f32,
        );
        // f32 poses of size ~4, through an f64 keyframe and a quaternion.
        assert_same_camera(&other.camera(WIDTH, HEIGHT), &before, 1e-5);
        // The target sits on the new optical axis, in front of the eye.
        let (u, v) = target_pixel(&other);
        assert!((u - 32.0).abs() < 1e-2 && (v - 24.0).abs() < 1e-2);
        // Scale in the matrix is taken out; a pose with NaN is ignored.
        let scaled = Mat4::from_scale(Vec3::splat(2.0));
        other.set_pose(before.camera_to_world * scaled, 57.5);
        assert_same_camera(&other.camera(WIDTH, HEIGHT), &before, 1e-5);
        other.set_pose(Mat4::from_translation(Vec3::NAN), 30.0);
        assert_same_camera(&other.camera(WIDTH, HEIGHT), &before, 1e-5);
    }

    #[test]
    fn switching_navigation_keeps_the_view() {
        let mut view = ViewCamera::for_scene(&scene());
        view.orbit(80.0, 15.0);
        let before = view.camera(WIDTH, HEIGHT);
        view.set_navigation(Navigation::Fly);
        assert_eq!(view.navigation(), Navigation::Fly);
        assert_eq!(view.camera(WIDTH, HEIGHT), before);
        view.look(10.0, 5.0);
        let flown = view.camera(WIDTH, HEIGHT);
        view.set_navigation(Navigation::Orbit);
        assert_eq!(view.camera(WIDTH, HEIGHT), flown);
    }

    #[test]
    fn reset_returns_to_the_start_and_keeps_the_mode() {
        let scene = scene();
        let mut view = ViewCamera::for_scene(&scene);
        let start = view.camera(WIDTH, HEIGHT);
        view.set_navigation(Navigation::Fly);
        view.look(100.0, 20.0);
        view.reset(&scene);
        assert_eq!(view.navigation(), Navigation::Fly);
        assert_eq!(view.camera(WIDTH, HEIGHT), start);
    }

    #[test]
    fn scene_without_views_gets_a_usable_camera() {
        let mut scene = scene();
        scene.train.clear();
        scene.val.clear();
        scene.test.clear();
        let view = ViewCamera::for_scene(&scene);
        let camera = view.camera(WIDTH, HEIGHT);
        assert!(camera.camera_to_world.is_finite());
        let (u, v) = target_pixel(&view);
        assert!((u - 32.0).abs() < 1e-3 && (v - 24.0).abs() < 1e-3);
    }

    #[test]
    fn step_view_wraps() {
        assert_eq!(step_view(Some(2), 3, true), Some(0));
        assert_eq!(step_view(Some(0), 3, true), Some(1));
        assert_eq!(step_view(Some(0), 3, false), Some(2));
        assert_eq!(step_view(Some(2), 3, false), Some(1));
        assert_eq!(step_view(None, 3, true), Some(0));
        assert_eq!(step_view(None, 3, false), Some(2));
        assert_eq!(step_view(Some(7), 3, true), Some(0));
        assert_eq!(step_view(None, 0, true), None);
        assert_eq!(step_view(Some(0), 0, false), None);
        assert_eq!(step_view(Some(0), 1, true), Some(0));
    }
}
