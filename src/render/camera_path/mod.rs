//! Camera paths through a scene: keyframes (a pose, a vertical field of
//! view and the time to the next keyframe) joined by a spline, sampled at
//! any time and baked into the frames of a video.
//!
//! Positions and the field of view follow a cubic Hermite spline in time
//! whose velocity at each keyframe is the Kochanek–Bartels tangent with
//! zero continuity and bias: `(1 − tension)` times the time-weighted
//! central difference of the neighbouring keyframes (Kochanek & Bartels,
//! "Interpolating splines with local tension, continuity, and bias
//! control", SIGGRAPH 1984). Tension 0 is the Catmull-Rom spline; tension 1
//! stops the camera at every keyframe. Because each keyframe has one
//! velocity, used by the segments on both its sides, positions are C1 in
//! time even when the transitions differ in length.
//!
//! Orientations follow squad (Shoemake, "Animating rotation with
//! quaternion curves", SIGGRAPH 1985) with its inner control quaternions
//! chosen so that each keyframe's angular velocity is the same weighted
//! difference of the neighbouring rotations: orientations are C1 too, and
//! every value is a product of unit quaternions (unit up to rounding).
//!
//! An open path's ends take the "natural" condition (no acceleration at the
//! first and last keyframes), so a path of two keyframes is a straight line
//! travelled at constant speed with a constant-rate turn. A cycle
//! (`is_cycle`) adds the transition from the last keyframe back to the first
//! and treats the keyframes as a ring: its end is its start, velocity
//! included.

pub mod crop_block;
pub mod export;
pub mod frames;
pub mod nerfstudio;
pub mod video;

use glam::{DMat3, DMat4, DQuat, DVec3, DVec4};

use crate::scene::{Camera, Intrinsics};

/// One keyframe: where the camera is, where it looks, how wide it sees,
/// and how long the move to the next keyframe takes.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Keyframe {
    /// Camera-to-world, OpenGL axes (x right, y up, looking down −z), as
    /// [`Camera::camera_to_world`]; a rigid motion.
    pub camera_to_world: DMat4,
    /// Vertical field of view in degrees.
    pub fov_degrees: f64,
    /// Seconds from this keyframe to the next; `None` takes the path's
    /// default.
    pub transition_seconds: Option<f64>,
}

impl Keyframe {
    pub fn new(camera_to_world: DMat4, fov_degrees: f64) -> Self {
        Self {
            camera_to_world,
            fov_degrees,
            transition_seconds: None,
        }
    }

    /// A keyframe at `camera`'s pose and vertical field of view.
    pub fn from_camera(camera: &Camera) -> Self {
        Self::new(
            camera.camera_to_world.as_dmat4(),
            (camera.intrinsics.fov_y() as f64).to_degrees(),
        )
    }

    pub fn position(&self) -> DVec3 {
        self.camera_to_world.w_axis.truncate()
    }

    pub fn rotation(&self) -> DQuat {
        DQuat::from_mat3(&DMat3::from_mat4(self.camera_to_world)).normalize()
    }
}

/// The camera-to-world of a camera at `eye` looking at `target`, its
/// image's up towards `up` (OpenGL axes: x right, y up, looking down −z).
pub fn look_at(eye: DVec3, target: DVec3, up: DVec3) -> DMat4 {
    let forward = (target - eye).normalize();
    let right = forward.cross(up).normalize();
    let up = right.cross(forward);
    DMat4::from_cols(
        right.extend(0.0),
        up.extend(0.0),
        (-forward).extend(0.0),
        eye.extend(1.0),
    )
}

/// A pose and field of view on the path.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PathSample {
    pub camera_to_world: DMat4,
    /// Vertical field of view in degrees.
    pub fov_degrees: f64,
}

impl PathSample {
    /// The camera that renders this sample at `width` × `height` pixels:
    /// square pixels, principal point at the centre, the vertical field of
    /// view as given (the horizontal one follows from the aspect ratio).
    pub fn camera(&self, width: u32, height: u32) -> Camera {
        let focal = 0.5 * height as f64 / (0.5 * self.fov_degrees.to_radians()).tan();
        let intrinsics = Intrinsics {
            fx: focal as f32,
            fy: focal as f32,
            ..Intrinsics::from_fov_x(width, height, 1.0)
        };
        Camera::new(intrinsics, self.camera_to_world.as_mat4())
    }
}

/// The smallest and largest vertical field of view a path may hold, in
/// degrees: beyond 179° the pinhole's focal length goes to zero.
pub const FOV_RANGE_DEGREES: (f64, f64) = (0.1, 179.0);

/// Keyframes and how to move between them.
#[derive(Debug, Clone, PartialEq)]
pub struct CameraPath {
    pub keyframes: Vec<Keyframe>,
    /// Seconds between keyframes that set no transition of their own.
    pub default_transition_seconds: f64,
    /// Whether the path returns from the last keyframe to the first.
    pub is_cycle: bool,
    /// Kochanek–Bartels tension, 0 (Catmull-Rom) to 1 (stop at every
    /// keyframe); nerfstudio writes it as `smoothness_value`.
    pub tension: f64,
}

impl CameraPath {
    pub fn new(keyframes: Vec<Keyframe>) -> Self {
        Self {
            keyframes,
            default_transition_seconds: 1.0,
            is_cycle: false,
            tension: 0.0,
        }
    }

    /// A path through `cameras` in order, every `every`-th of them (at
    /// least one; the last camera always ends the path), each keyframe
    /// with its camera's pose and vertical field of view: a path from a
    /// scene's training cameras.
    pub fn through_cameras(cameras: &[Camera], every: usize) -> Self {
        let every = every.max(1);
        let mut chosen: Vec<&Camera> = cameras.iter().step_by(every).collect();
        if let Some(last) = cameras.last()
            && !(cameras.len() - 1).is_multiple_of(every)
        {
            chosen.push(last);
        }
        Self::new(chosen.into_iter().map(Keyframe::from_camera).collect())
    }

    /// Why this path cannot be sampled, or `None`.
    pub fn problem(&self) -> Option<String> {
        if self.keyframes.is_empty() {
            return Some("a camera path needs at least one keyframe".into());
        }
        if !(self.tension.is_finite() && (0.0..=1.0).contains(&self.tension)) {
            return Some(format!(
                "the spline tension must be 0 to 1, got {}",
                self.tension
            ));
        }
        if !(self.default_transition_seconds.is_finite() && self.default_transition_seconds > 0.0) {
            return Some(format!(
                "the default transition must be a positive number of seconds, got {}",
                self.default_transition_seconds
            ));
        }
        for (i, k) in self.keyframes.iter().enumerate() {
            if !k.camera_to_world.is_finite() {
                return Some(format!("keyframe {i}: its pose is not finite"));
            }
            let (low, high) = FOV_RANGE_DEGREES;
            if !(k.fov_degrees.is_finite() && (low..=high).contains(&k.fov_degrees)) {
                return Some(format!(
                    "keyframe {i}: the field of view must be {low} to {high} degrees, got {}",
                    k.fov_degrees
                ));
            }
            if let Some(t) = k.transition_seconds
                && !(t.is_finite() && t > 0.0)
            {
                return Some(format!(
                    "keyframe {i}: the transition must be a positive number of seconds, got {t}"
                ));
            }
        }
        None
    }

    /// Seconds from keyframe `i` to the next.
    pub fn transition(&self, i: usize) -> f64 {
        self.keyframes[i]
            .transition_seconds
            .unwrap_or(self.default_transition_seconds)
    }

    /// The number of moves between keyframes: one fewer than the keyframes,
    /// or as many for a cycle.
    fn segments(&self) -> usize {
        let n = self.keyframes.len();
        if self.is_cycle {
            n
        } else {
            n.saturating_sub(1)
        }
    }

    /// The time at which the path reaches each keyframe, and (for a cycle)
    /// the first keyframe again at the end.
    pub fn knot_times(&self) -> Vec<f64> {
        let mut times = vec![0.0];
        for i in 0..self.segments() {
            times.push(times[i] + self.transition(i));
        }
        times
    }

    /// The path's length in seconds.
    pub fn duration(&self) -> f64 {
        (0..self.segments()).map(|i| self.transition(i)).sum()
    }

    /// Scales every transition so the path lasts `seconds`.
    pub fn set_duration(&mut self, seconds: f64) {
        let now = self.duration();
        if now > 0.0 && seconds > 0.0 && seconds.is_finite() {
            let factor = seconds / now;
            for i in 0..self.segments() {
                let t = self.transition(i) * factor;
                self.keyframes[i].transition_seconds = Some(t);
            }
            self.default_transition_seconds *= factor;
        }
    }

    /// The pose and field of view at `time` seconds (clamped to the path).
    /// Panics on a path with no keyframes: check [`Self::problem`] first.
    pub fn sample(&self, time: f64) -> PathSample {
        let spline = Spline::new(self);
        spline.sample(time)
    }

    /// The path baked into `frames` samples for a video: for a cycle at
    /// `i / frames` of the duration (the first frame is not repeated at the
    /// end); for an open path at `i / (frames − 1)`, so the video starts at
    /// the first keyframe and ends on the last.
    pub fn bake(&self, frames: usize) -> Vec<PathSample> {
        let spline = Spline::new(self);
        let duration = self.duration();
        let steps = if self.is_cycle {
            frames
        } else {
            frames.saturating_sub(1).max(1)
        };
        (0..frames)
            .map(|i| spline.sample(duration * i as f64 / steps as f64))
            .collect()
    }

    /// The number of frames a video of this path has at `fps`.
    pub fn frame_count(&self, fps: f64) -> usize {
        ((self.duration() * fps).round() as usize).max(1)
    }
}

/// The log of a unit quaternion as a rotation vector (axis × angle), along
/// the shorter way round.
fn log(q: DQuat) -> DVec3 {
    let q = if q.w < 0.0 { -q } else { q };
    let v = DVec3::new(q.x, q.y, q.z);
    let s = v.length();
    if s < 1e-12 {
        // sin(θ/2) ≈ θ/2 for tiny angles.
        return 2.0 * v;
    }
    2.0 * s.atan2(q.w) / s * v
}

/// The unit quaternion of rotation vector `v`.
fn exp(v: DVec3) -> DQuat {
    let angle = v.length();
    if angle < 1e-12 {
        return DQuat::from_xyzw(0.5 * v.x, 0.5 * v.y, 0.5 * v.z, 1.0);
    }
    let s = (0.5 * angle).sin() / angle;
    DQuat::from_xyzw(s * v.x, s * v.y, s * v.z, (0.5 * angle).cos())
}

/// Shoemake's spherical linear interpolation, `a · exp(s · log(a⁻¹ b))`.
fn slerp(a: DQuat, b: DQuat, s: f64) -> DQuat {
    a * exp(s * log(a.conjugate() * b))
}

/// A path prepared for sampling: knot times, each keyframe's velocity and
/// angular velocity, and the squad control quaternions of each segment.
struct Spline {
    times: Vec<f64>,
    /// Position and field of view at each knot (a cycle repeats the first
    /// keyframe at the end).
    values: Vec<DVec4>,
    velocities: Vec<DVec4>,
    rotations: Vec<DQuat>,
    /// Per segment: squad's inner quaternions at its start and its end.
    controls: Vec<(DQuat, DQuat)>,
}

impl Spline {
    fn new(path: &CameraPath) -> Spline {
        let n = path.keyframes.len();
        assert!(n > 0, "a camera path needs at least one keyframe");
        let segments = path.segments();
        let times = path.knot_times();
        let knot = |i: usize| &path.keyframes[i % n];
        let values: Vec<DVec4> = (0..=segments)
            .map(|i| knot(i).position().extend(knot(i).fov_degrees))
            .collect();
        // Rotations on one hemisphere, each the nearer sign of its
        // predecessor's, so slerp never goes the long way round.
        let mut rotations: Vec<DQuat> = Vec::with_capacity(segments + 1);
        for i in 0..=segments {
            let q = knot(i).rotation();
            let q = match rotations.last() {
                Some(previous) if previous.dot(q) < 0.0 => -q,
                _ => q,
            };
            rotations.push(q);
        }
        let dt: Vec<f64> = (0..segments).map(|i| times[i + 1] - times[i]).collect();
        let scale = 1.0 - path.tension;

        // Time-weighted central difference at an interior knot: exact for
        // quadratics, and the Catmull-Rom tangent for equal spacing.
        fn blend<T>(before: T, after: T, dt_before: f64, dt_after: f64) -> T
        where
            T: std::ops::Mul<f64, Output = T> + std::ops::Add<Output = T>,
        {
            let total = dt_before + dt_after;
            before * (dt_after / total) + after * (dt_before / total)
        }

        let slopes: Vec<DVec4> = (0..segments)
            .map(|i| (values[i + 1] - values[i]) / dt[i])
            .collect();
        let turns: Vec<DVec3> = (0..segments)
            .map(|i| log(rotations[i].conjugate() * rotations[i + 1]) / dt[i])
            .collect();
        let mut velocities = vec![DVec4::ZERO; segments + 1];
        let mut spins = vec![DVec3::ZERO; segments + 1];
        if segments > 0 {
            for i in 1..segments {
                velocities[i] = blend(slopes[i - 1], slopes[i], dt[i - 1], dt[i]) * scale;
                spins[i] = blend(turns[i - 1], turns[i], dt[i - 1], dt[i]) * scale;
            }
            if path.is_cycle {
                // The first knot's neighbours are the last keyframe and the
                // second; the closing knot is the first keyframe again.
                let last = segments - 1;
                velocities[0] = blend(slopes[last], slopes[0], dt[last], dt[0]) * scale;
                spins[0] = blend(turns[last], turns[0], dt[last], dt[0]) * scale;
                velocities[segments] = velocities[0];
                spins[segments] = spins[0];
            } else if segments == 1 {
                // Natural ends on both sides: constant velocity.
                velocities[0] = slopes[0];
                velocities[1] = slopes[0];
                spins[0] = turns[0];
                spins[1] = turns[0];
            } else {
                // Natural end: a Hermite segment with no second derivative
                // at its free end has v_end = (3 · slope − v_other) / 2.
                velocities[0] = (3.0 * slopes[0] - velocities[1]) * 0.5;
                spins[0] = (3.0 * turns[0] - spins[1]) * 0.5;
                let last = segments - 1;
                velocities[segments] = (3.0 * slopes[last] - velocities[last]) * 0.5;
                spins[segments] = (3.0 * turns[last] - spins[last]) * 0.5;
            }
        }
        // Squad's derivative in the body frame is L + 2 log(q₀⁻¹ a) at a
        // segment's start and L − 2 log(q₁⁻¹ b) at its end, with L the
        // segment's rotation vector: solve both for the wanted spins.
        let controls = (0..segments)
            .map(|i| {
                let step = log(rotations[i].conjugate() * rotations[i + 1]);
                let a = rotations[i] * exp(0.5 * (dt[i] * spins[i] - step));
                let b = rotations[i + 1] * exp(0.5 * (step - dt[i] * spins[i + 1]));
                (a, b)
            })
            .collect();
        Spline {
            times,
            values,
            velocities,
            rotations,
            controls,
        }
    }

    /// The segment holding `time` and the fraction of it gone by.
    fn locate(&self, time: f64) -> (usize, f64) {
        let segments = self.times.len() - 1;
        if segments == 0 {
            return (0, 0.0);
        }
        let end = self.times[segments];
        let time = if time.is_nan() {
            0.0
        } else {
            time.clamp(0.0, end)
        };
        // The last knot at or before `time`, but never the closing knot.
        let i = self
            .times
            .partition_point(|&t| t <= time)
            .saturating_sub(1)
            .min(segments - 1);
        let s = (time - self.times[i]) / (self.times[i + 1] - self.times[i]);
        (i, s.clamp(0.0, 1.0))
    }

    /// Position and field of view at `time`.
    fn value(&self, time: f64) -> DVec4 {
        let (i, s) = self.locate(time);
        if self.times.len() == 1 {
            return self.values[0];
        }
        let dt = self.times[i + 1] - self.times[i];
        let (s2, s3) = (s * s, s * s * s);
        let h00 = 2.0 * s3 - 3.0 * s2 + 1.0;
        let h10 = s3 - 2.0 * s2 + s;
        let h01 = -2.0 * s3 + 3.0 * s2;
        let h11 = s3 - s2;
        self.values[i] * h00
            + self.velocities[i] * (h10 * dt)
            + self.values[i + 1] * h01
            + self.velocities[i + 1] * (h11 * dt)
    }

    /// Orientation at `time`, before any renormalisation.
    fn rotation(&self, time: f64) -> DQuat {
        if self.times.len() == 1 {
            return self.rotations[0];
        }
        let (i, s) = self.locate(time);
        let (a, b) = self.controls[i];
        slerp(
            slerp(self.rotations[i], self.rotations[i + 1], s),
            slerp(a, b, s),
            2.0 * s * (1.0 - s),
        )
    }

    fn sample(&self, time: f64) -> PathSample {
        let value = self.value(time);
        let rotation = self.rotation(time).normalize();
        let (low, high) = FOV_RANGE_DEGREES;
        PathSample {
            camera_to_world: DMat4::from_rotation_translation(rotation, value.truncate()),
            // A spline can overshoot between keyframes far apart in field
            // of view; keep it a field of view a pinhole can have.
            fov_degrees: value.w.clamp(low, high),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A camera at `eye` looking at `target` with +z up.
    fn look(eye: DVec3, target: DVec3, fov: f64) -> Keyframe {
        Keyframe::new(look_at(eye, target, DVec3::Z), fov)
    }

    /// Four keyframes round a scene at uneven heights, distances, fields
    /// of view and transition times.
    fn four_keyframes(is_cycle: bool, tension: f64) -> CameraPath {
        let mut keyframes = vec![
            look(DVec3::new(4.0, 0.0, 1.0), DVec3::ZERO, 40.0),
            look(DVec3::new(0.0, 3.0, 2.0), DVec3::ZERO, 55.0),
            look(DVec3::new(-4.5, 0.5, 0.5), DVec3::new(0.0, 0.0, 0.3), 35.0),
            look(DVec3::new(0.0, -3.5, 1.5), DVec3::ZERO, 50.0),
        ];
        keyframes[0].transition_seconds = Some(0.7);
        keyframes[2].transition_seconds = Some(1.6);
        CameraPath {
            keyframes,
            default_transition_seconds: 1.1,
            is_cycle,
            tension,
        }
    }

    fn position(sample: &PathSample) -> DVec3 {
        sample.camera_to_world.w_axis.truncate()
    }

    #[test]
    fn passes_through_every_keyframe() {
        for is_cycle in [false, true] {
            for tension in [0.0, 0.5, 1.0] {
                let path = four_keyframes(is_cycle, tension);
                assert_eq!(path.problem(), None);
                let times = path.knot_times();
                for (k, &t) in path.keyframes.iter().zip(&times) {
                    let s = path.sample(t);
                    // Rounding only: the Hermite basis is exactly (1, 0, 0,
                    // 0) at a knot, and squad is q₀ there.
                    let pose_error = (s.camera_to_world - k.camera_to_world)
                        .to_cols_array()
                        .iter()
                        .fold(0f64, |m, x| m.max(x.abs()));
                    assert!(pose_error < 1e-12, "t {t}: pose off by {pose_error}");
                    assert!((s.fov_degrees - k.fov_degrees).abs() < 1e-12);
                }
            }
        }
    }

    /// Positions are C1 at every keyframe: the one-sided difference
    /// quotients from before and after agree. Each one-sided quotient over
    /// a step h differs from the true derivative by h/2 · |p''| at most
    /// (Taylor), so two of them differ by h · max|p''| if the derivative is
    /// continuous, while a kink gives a difference of order |Δv|
    /// independent of h.
    #[test]
    fn positions_are_c1_at_keyframes() {
        let h = 1e-5;
        for is_cycle in [false, true] {
            for tension in [0.0, 0.3] {
                let path = four_keyframes(is_cycle, tension);
                let times = path.knot_times();
                let duration = path.duration();
                // Bound |p''| by second differences over the whole path.
                let step = 1e-3;
                let mut max_accel = 0f64;
                let mut t = step;
                while t < duration - step {
                    let p = |t| position(&path.sample(t));
                    let a = (p(t + step) - 2.0 * p(t) + p(t - step)) / (step * step);
                    max_accel = max_accel.max(a.length());
                    t += step;
                }
                let tolerance = 2.0 * h * max_accel + 1e-6;
                let interior: Vec<f64> = if is_cycle {
                    times[..times.len() - 1].to_vec()
                } else {
                    times[1..times.len() - 1].to_vec()
                };
                for &t in &interior {
                    let p = |t: f64| position(&path.sample(t.rem_euclid(duration)));
                    let before = (p(t) - p(t - h)) / h;
                    let after = (p(t + h) - p(t)) / h;
                    let gap = (after - before).length();
                    assert!(
                        gap < tolerance,
                        "cycle {is_cycle} tension {tension} t {t}: derivatives differ by {gap} \
                         (tolerance {tolerance}, speed {})",
                        after.length()
                    );
                }
            }
        }
    }

    /// The C1 test above must catch a kink: a polyline (tension 1 still
    /// has zero velocity at keyframes, so it is C1; a linear path is not).
    #[test]
    fn the_c1_check_sees_a_kink() {
        let path = four_keyframes(false, 0.0);
        let linear = |t: f64| {
            let times = path.knot_times();
            let i = times.partition_point(|&x| x <= t).saturating_sub(1).min(2);
            let s = (t - times[i]) / (times[i + 1] - times[i]);
            path.keyframes[i]
                .position()
                .lerp(path.keyframes[i + 1].position(), s)
        };
        let h = 1e-5;
        let t = path.knot_times()[1];
        let gap = ((linear(t + h) - linear(t)) / h - (linear(t) - linear(t - h)) / h).length();
        assert!(gap > 1.0, "a polyline's kink measured {gap}");
    }

    #[test]
    fn two_keyframes_make_a_straight_line_at_constant_speed() {
        for tension in [0.0, 0.7] {
            let mut path = CameraPath::new(vec![
                look(DVec3::new(3.0, -1.0, 0.5), DVec3::ZERO, 30.0),
                look(DVec3::new(-2.0, 2.0, 1.5), DVec3::new(0.2, 0.0, 0.0), 60.0),
            ]);
            path.tension = tension;
            path.default_transition_seconds = 2.5;
            let (a, b) = (path.keyframes[0].position(), path.keyframes[1].position());
            let speed = (b - a).length() / 2.5;
            let direction = (b - a).normalize();
            let frames = path.bake(26);
            for (i, s) in frames.iter().enumerate() {
                let p = position(s);
                // On the line: no component off it.
                let off = (p - a) - direction * (p - a).dot(direction);
                assert!(off.length() < 1e-12, "frame {i} is {} off", off.length());
                // At constant speed: the distance grows linearly in time.
                let t = 2.5 * i as f64 / 25.0;
                assert!(((p - a).dot(direction) - speed * t).abs() < 1e-12);
                // The field of view too moves linearly.
                assert!((s.fov_degrees - (30.0 + 30.0 * t / 2.5)).abs() < 1e-9);
            }
            // And it turns at a constant rate: equal angles per frame.
            let angles: Vec<f64> = frames
                .windows(2)
                .map(|w| {
                    let q0 = DQuat::from_mat4(&w[0].camera_to_world);
                    let q1 = DQuat::from_mat4(&w[1].camera_to_world);
                    q0.angle_between(q1)
                })
                .collect();
            for a in &angles {
                assert!((a - angles[0]).abs() < 1e-9, "{angles:?}");
            }
            assert!(angles[0] > 1e-3);
        }
    }

    #[test]
    fn orientation_is_a_unit_quaternion_everywhere() {
        for is_cycle in [false, true] {
            for tension in [0.0, 0.5] {
                let path = four_keyframes(is_cycle, tension);
                let spline = Spline::new(&path);
                let duration = path.duration();
                let mut worst = 0f64;
                for i in 0..=2000 {
                    let q = spline.rotation(duration * i as f64 / 2000.0);
                    worst = worst.max((q.length() - 1.0).abs());
                }
                // Products of a few unit quaternions in f64: a few ulps.
                assert!(worst < 1e-12, "|q| strays from 1 by {worst}");
                // And the pose built from it is a rotation: RᵀR = I.
                for s in path.bake(50) {
                    let r = DMat3::from_mat4(s.camera_to_world);
                    let e = (r.transpose() * r - DMat3::IDENTITY)
                        .to_cols_array()
                        .iter()
                        .fold(0f64, |m, x| m.max(x.abs()));
                    assert!(e < 1e-12);
                    assert!((r.determinant() - 1.0).abs() < 1e-12);
                }
            }
        }
    }

    /// Orientations are C1 too: the angular velocity just before and just
    /// after each keyframe agree (same bound as for positions).
    #[test]
    fn orientations_are_c1_at_keyframes() {
        let path = four_keyframes(true, 0.2);
        let spline = Spline::new(&path);
        let h = 1e-5;
        let duration = path.duration();
        let q = |t: f64| spline.rotation(t.rem_euclid(duration));
        for &t in &path.knot_times()[..4] {
            let before = log(q(t - h).conjugate() * q(t)) / h;
            let after = log(q(t).conjugate() * q(t + h)) / h;
            assert!(
                (after - before).length() < 1e-3,
                "t {t}: {before} vs {after}"
            );
        }
    }

    #[test]
    fn a_cycle_ends_where_it_starts_with_the_same_velocity() {
        let path = four_keyframes(true, 0.0);
        let duration = path.duration();
        assert!((duration - (0.7 + 1.1 + 1.6 + 1.1)).abs() < 1e-12);
        let start = path.sample(0.0);
        let end = path.sample(duration);
        let error = (start.camera_to_world - end.camera_to_world)
            .to_cols_array()
            .iter()
            .fold(0f64, |m, x| m.max(x.abs()));
        assert!(error < 1e-12, "end differs from start by {error}");
        let h = 1e-6;
        let p = |t| position(&path.sample(t));
        let start_velocity = (p(h) - p(0.0)) / h;
        let end_velocity = (p(duration) - p(duration - h)) / h;
        assert!(start_velocity.length() > 1.0);
        assert!(
            (start_velocity - end_velocity).length() < 1e-3,
            "{start_velocity} vs {end_velocity}"
        );
        // An open path of the same keyframes does not close.
        let open = four_keyframes(false, 0.0);
        let gap = (position(&open.sample(open.duration())) - position(&open.sample(0.0))).length();
        assert!(gap > 1.0);
    }

    #[test]
    fn baking_spaces_frames_evenly_in_time() {
        let path = four_keyframes(false, 0.0);
        let frames = path.bake(5);
        assert_eq!(frames.len(), 5);
        assert_eq!(frames[0], path.sample(0.0));
        assert_eq!(frames[4], path.sample(path.duration()));
        assert_eq!(frames[2], path.sample(0.5 * path.duration()));
        // A cycle does not repeat its first frame at the end.
        let cycle = four_keyframes(true, 0.0);
        let frames = cycle.bake(4);
        assert_eq!(frames[1], cycle.sample(0.25 * cycle.duration()));
        assert_eq!(cycle.frame_count(24.0), (4.5f64 * 24.0).round() as usize);
    }

    #[test]
    fn one_keyframe_holds_still() {
        let k = look(DVec3::new(1.0, 2.0, 3.0), DVec3::ZERO, 45.0);
        let path = CameraPath::new(vec![k]);
        assert_eq!(path.duration(), 0.0);
        assert_eq!(path.frame_count(30.0), 1);
        let s = path.sample(0.3);
        assert!((position(&s) - k.position()).length() < 1e-12);
    }

    #[test]
    fn problems_are_named() {
        assert!(
            CameraPath::new(vec![])
                .problem()
                .unwrap()
                .contains("at least one keyframe")
        );
        let mut path = four_keyframes(false, 0.0);
        path.keyframes[2].fov_degrees = f64::NAN;
        assert!(
            path.problem()
                .unwrap()
                .starts_with("keyframe 2: the field of view")
        );
        let mut path = four_keyframes(false, 0.0);
        path.tension = 2.0;
        assert!(path.problem().unwrap().contains("tension"));
        let mut path = four_keyframes(false, 0.0);
        path.keyframes[1].transition_seconds = Some(0.0);
        assert!(
            path.problem()
                .unwrap()
                .starts_with("keyframe 1: the transition")
        );
    }

    #[test]
    fn a_sample_renders_with_its_vertical_field_of_view() {
        let s = PathSample {
            camera_to_world: DMat4::IDENTITY,
            fov_degrees: 50.0,
        };
        let camera = s.camera(320, 180);
        assert!((camera.intrinsics.fov_y().to_degrees() - 50.0).abs() < 1e-4);
        assert_eq!((camera.intrinsics.cx, camera.intrinsics.cy), (160.0, 90.0));
        assert_eq!(camera.intrinsics.fx, camera.intrinsics.fy);
    }

    #[test]
    fn a_path_through_cameras_keeps_their_order_and_ends_on_the_last() {
        let cameras: Vec<Camera> = (0..7)
            .map(|i| {
                let eye = DVec3::new(4.0, i as f64, 1.0);
                PathSample {
                    camera_to_world: look_at(eye, DVec3::ZERO, DVec3::Z),
                    fov_degrees: 30.0 + i as f64,
                }
                .camera(40, 30)
            })
            .collect();
        let path = CameraPath::through_cameras(&cameras, 3);
        let ys: Vec<f64> = path.keyframes.iter().map(|k| k.position().y).collect();
        assert_eq!(ys, vec![0.0, 3.0, 6.0]);
        let path = CameraPath::through_cameras(&cameras, 4);
        let ys: Vec<f64> = path.keyframes.iter().map(|k| k.position().y).collect();
        assert_eq!(ys, vec![0.0, 4.0, 6.0]);
        // Each keyframe has its camera's field of view (f32 intrinsics).
        assert!((path.keyframes[1].fov_degrees - 34.0).abs() < 1e-3);
        assert_eq!(CameraPath::through_cameras(&cameras, 1).keyframes.len(), 7);
        assert!(CameraPath::through_cameras(&[], 2).keyframes.is_empty());
    }

    #[test]
    fn set_duration_scales_every_transition() {
        let mut path = four_keyframes(true, 0.0);
        path.set_duration(9.0);
        assert!((path.duration() - 9.0).abs() < 1e-12);
        assert!((path.transition(0) - 1.4).abs() < 1e-12);
    }
}
