//! The camera path drawn over the viewport: the spline as a line, each
//! keyframe as a small camera frustum (the selected one highlighted), and
//! where the timeline stands.
//!
//! Points are projected with the viewport camera; a segment with an end
//! closer than the near plane (or behind the camera) is not drawn, so
//! nothing behind the viewer folds over the picture.

use eframe::egui;
use egui::{Color32, Pos2, Rect, Stroke};
use glam::Vec3;

use super::ViewerUi;
use super::overlay::Projection;
use crate::render::camera_path::{CameraPath, Keyframe};

/// Samples of the spline per keyframe-to-keyframe segment: enough that
/// the polyline looks curved at any zoom a user draws paths at.
const SAMPLES_PER_SEGMENT: usize = 48;

/// The most samples of a whole path, however many keyframes it has.
const MAX_SAMPLES: usize = 4000;

/// Frustum depth in scene sizes (the diagonal of the scene's box): big
/// enough to see which way a keyframe looks, small enough not to cover
/// the object.
const FRUSTUM_SCENE_SIZES: f32 = 0.08;

/// Near plane in scene sizes: points closer than this to the eye (the
/// eye itself, when the camera stands on the path) are not drawn.
const NEAR_SCENE_SIZES: f32 = 0.005;

const CURVE_COLOUR: Color32 = Color32::from_rgb(255, 150, 30);
const KEYFRAME_COLOUR: Color32 = Color32::from_rgb(80, 170, 255);
const SELECTED_COLOUR: Color32 = Color32::from_rgb(255, 225, 0);
const NOW_COLOUR: Color32 = Color32::from_rgb(240, 40, 60);

/// Points along the path, evenly spaced in time.
pub fn curve_points(path: &CameraPath) -> Vec<Vec3> {
    if path.problem().is_some() {
        return Vec::new();
    }
    let segments = if path.is_cycle {
        path.keyframes.len()
    } else {
        path.keyframes.len().saturating_sub(1)
    };
    let count = (segments * SAMPLES_PER_SEGMENT).clamp(1, MAX_SAMPLES);
    path.bake(count + usize::from(path.is_cycle))
        .iter()
        .map(|s| s.camera_to_world.w_axis.truncate().as_vec3())
        .chain(
            // A cycle's bake leaves out the closing point.
            path.is_cycle
                .then(|| path.keyframes[0].position().as_vec3()),
        )
        .collect()
}

/// The frustum of a keyframe `depth` deep for an image of aspect `aspect`
/// (width / height): the eye, then the image-plane corners clockwise from
/// top-left, then the tip of the "up" mark above the top edge.
pub fn frustum(keyframe: &Keyframe, aspect: f32, depth: f32) -> [Vec3; 6] {
    let pose = keyframe.camera_to_world.as_mat4();
    let half_height = depth * (0.5 * keyframe.fov_degrees as f32).to_radians().tan();
    let half_width = half_height * aspect;
    let corner = |x: f32, y: f32| pose.transform_point3(Vec3::new(x, y, -depth));
    [
        pose.transform_point3(Vec3::ZERO),
        corner(-half_width, half_height),
        corner(half_width, half_height),
        corner(half_width, -half_height),
        corner(-half_width, -half_height),
        corner(0.0, 1.5 * half_height),
    ]
}

/// A line drawn over a dark, wider one, so it reads on white backgrounds
/// and on dark ones alike.
fn outlined(painter: &egui::Painter, points: [Pos2; 2], width: f32, colour: Color32) {
    painter.line_segment(
        points,
        Stroke::new(width + 2.0, Color32::from_black_alpha(150)),
    );
    painter.line_segment(points, Stroke::new(width, colour));
}

/// Draws the path being edited over the viewport image in `rect`.
pub fn draw(state: &ViewerUi, painter: &egui::Painter, rect: Rect) {
    let editor = &state.path_editor;
    if !(editor.open && editor.show_overlay) || editor.keyframes().is_empty() {
        return;
    }
    let Some(view) = &state.camera else {
        return;
    };
    let size = view.scene_size();
    let camera = view.camera(
        rect.width().round().max(1.0) as u32,
        rect.height().round().max(1.0) as u32,
    );
    let projection = Projection::new(&camera, rect, NEAR_SCENE_SIZES * size);

    // The curve, as runs of visible points.
    let points = curve_points(&editor.path);
    let mut run: Vec<Pos2> = Vec::new();
    let flush = |run: &mut Vec<Pos2>| {
        if run.len() > 1 {
            painter.add(egui::Shape::line(
                run.clone(),
                Stroke::new(4.0, Color32::from_black_alpha(140)),
            ));
            painter.add(egui::Shape::line(
                std::mem::take(run),
                Stroke::new(2.0, CURVE_COLOUR),
            ));
        }
        run.clear();
    };
    for point in points {
        match projection.project(point) {
            Some(p) => run.push(p),
            None => flush(&mut run),
        }
    }
    flush(&mut run);

    // The keyframes' frustums, the selected one last so it lies on top.
    let aspect = editor.width as f32 / editor.height.max(1) as f32;
    let depth = FRUSTUM_SCENE_SIZES * size;
    let mut order: Vec<usize> = (0..editor.keyframes().len()).collect();
    if let Some(selected) = editor.selected {
        order.retain(|&i| i != selected);
        order.push(selected);
    }
    for i in order {
        let selected = editor.selected == Some(i);
        let (colour, width) = if selected {
            (SELECTED_COLOUR, 2.5)
        } else {
            (KEYFRAME_COLOUR, 1.5)
        };
        let [eye, a, b, c, d, up] = frustum(&editor.keyframes()[i], aspect, depth);
        // A keyframe at (or behind) the viewport camera would frame the
        // whole view: only the keyframes seen from outside are drawn.
        let Some(at) = projection.project(eye) else {
            continue;
        };
        for (p, q) in [
            (eye, a),
            (eye, b),
            (eye, c),
            (eye, d),
            (a, b),
            (b, c),
            (c, d),
            (d, a),
            (a, up),
            (up, b),
        ] {
            if let Some(segment) = projection.segment(p, q) {
                outlined(painter, segment, width, colour);
            }
        }
        let text = format!("{}", i + 1);
        let galley = painter.layout_no_wrap(text, egui::FontId::proportional(12.0), Color32::WHITE);
        let label =
            egui::Align2::RIGHT_BOTTOM.anchor_size(at - egui::vec2(4.0, 4.0), galley.size());
        painter.rect_filled(label.expand(2.0), 3, colour.gamma_multiply(0.85));
        painter.galley(label.min, galley, Color32::BLACK);
    }

    // Where the timeline stands, unless the camera is there itself.
    if editor.can_sample() && !editor.driving {
        let now = editor.path.sample(editor.time);
        let position = now.camera_to_world.w_axis.truncate().as_vec3();
        if let Some(at) = projection.project(position) {
            painter.circle(at, 5.0, NOW_COLOUR, Stroke::new(1.5, Color32::WHITE));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::camera_path::look_at;
    use crate::scene::{Camera, Intrinsics};
    use glam::{DVec3, Mat4};

    /// A camera at the origin looking down −z with a 60° vertical field of
    /// view, 200 × 100 pixels, shown over a 400 × 200 rect at (10, 20).
    fn projection() -> (Projection, Rect) {
        let fov = 60f32.to_radians();
        let focal = 50.0 / (0.5 * fov).tan();
        let camera = Camera::new(
            Intrinsics {
                fx: focal,
                fy: focal,
                ..Intrinsics::from_fov_x(200, 100, 1.0)
            },
            Mat4::IDENTITY,
        );
        let rect = Rect::from_min_size(Pos2::new(10.0, 20.0), egui::vec2(400.0, 200.0));
        (Projection::new(&camera, rect, 0.1), rect)
    }

    fn close(a: Pos2, b: Pos2) -> bool {
        // f32 trigonometry on values of a few hundred points.
        (a - b).length() < 1e-3
    }

    #[test]
    fn a_point_on_the_axis_lands_in_the_centre() {
        let (projection, rect) = projection();
        for depth in [0.5, 3.0, 100.0] {
            let p = projection.project(Vec3::new(0.0, 0.0, -depth)).unwrap();
            assert!(close(p, rect.center()), "{p:?} vs {:?}", rect.center());
        }
    }

    #[test]
    fn a_point_at_the_edge_of_the_view_lands_on_the_edge() {
        let (projection, rect) = projection();
        let half = (30f32).to_radians().tan();
        let depth = 4.0;
        // Top edge: up by tan(fov/2) at unit depth; y counts down on screen.
        let top = projection
            .project(Vec3::new(0.0, half * depth, -depth))
            .unwrap();
        assert!(close(top, rect.center_top()), "{top:?}");
        let bottom = projection
            .project(Vec3::new(0.0, -half * depth, -depth))
            .unwrap();
        assert!(close(bottom, rect.center_bottom()), "{bottom:?}");
        // Right edge: the horizontal half-angle's tangent is the vertical
        // one's times the aspect, 2.
        let right = projection
            .project(Vec3::new(2.0 * half * depth, 0.0, -depth))
            .unwrap();
        assert!(close(right, rect.right_center()), "{right:?}");
    }

    #[test]
    fn points_behind_the_near_plane_are_not_drawn() {
        let (projection, _) = projection();
        assert_eq!(projection.project(Vec3::new(0.0, 0.0, 1.0)), None);
        assert_eq!(projection.project(Vec3::new(0.0, 0.0, -0.05)), None);
        assert_eq!(projection.project(Vec3::NAN), None);
        let front = Vec3::new(0.3, 0.2, -2.0);
        assert!(
            projection
                .segment(front, Vec3::new(0.0, 0.0, -1.0))
                .is_some()
        );
        assert_eq!(projection.segment(front, Vec3::new(0.0, 0.0, 2.0)), None);
        assert_eq!(projection.segment(Vec3::new(1.0, 0.0, 0.0), front), None);
    }

    #[test]
    fn the_projection_follows_the_camera_pose() {
        // A camera at (0, −5, 0) looking at the origin (+z up): the origin
        // is in the centre, a point to the camera's right is right of it.
        let pose = look_at(DVec3::new(0.0, -5.0, 0.0), DVec3::ZERO, DVec3::Z).as_mat4();
        let camera = Camera::new(Intrinsics::from_fov_x(64, 48, 1.0), pose);
        let rect = Rect::from_min_size(Pos2::ZERO, egui::vec2(64.0, 48.0));
        let projection = Projection::new(&camera, rect, 0.01);
        assert!(close(
            projection.project(Vec3::ZERO).unwrap(),
            rect.center()
        ));
        assert!(projection.project(Vec3::X).unwrap().x > rect.center().x);
        assert!(projection.project(Vec3::Z).unwrap().y < rect.center().y);
        // Agrees with the scene camera's own projection.
        let point = Vec3::new(0.4, 1.0, -0.3);
        let (u, v) = camera.project(point).unwrap();
        assert!(close(projection.project(point).unwrap(), Pos2::new(u, v)));
    }

    #[test]
    fn a_frustum_opens_with_the_field_of_view() {
        let keyframe = Keyframe::new(glam::DMat4::IDENTITY, 90.0);
        let [eye, top_left, top_right, bottom_right, bottom_left, up] =
            frustum(&keyframe, 2.0, 1.0);
        assert_eq!(eye, Vec3::ZERO);
        // tan(45°) = 1: the corners stand at ±2 × ±1 at depth 1.
        for (corner, expected) in [
            (top_left, Vec3::new(-2.0, 1.0, -1.0)),
            (top_right, Vec3::new(2.0, 1.0, -1.0)),
            (bottom_right, Vec3::new(2.0, -1.0, -1.0)),
            (bottom_left, Vec3::new(-2.0, -1.0, -1.0)),
        ] {
            assert!(
                (corner - expected).length() < 1e-6,
                "{corner} vs {expected}"
            );
        }
        assert!(up.y > top_left.y);
    }

    #[test]
    fn the_curve_passes_through_the_keyframes_and_closes_a_cycle() {
        let key = |x: f64, y: f64| {
            Keyframe::new(look_at(DVec3::new(x, y, 1.0), DVec3::ZERO, DVec3::Z), 40.0)
        };
        let mut path = CameraPath::new(vec![key(3.0, 0.0), key(0.0, 3.0), key(-3.0, 0.0)]);
        let points = curve_points(&path);
        assert_eq!(points.len(), 2 * SAMPLES_PER_SEGMENT);
        assert!((points[0] - Vec3::new(3.0, 0.0, 1.0)).length() < 1e-5);
        assert!((points.last().unwrap().x + 3.0).abs() < 1e-5);
        path.is_cycle = true;
        let points = curve_points(&path);
        assert!((*points.last().unwrap() - points[0]).length() < 1e-5);
        assert!(curve_points(&CameraPath::new(Vec::new())).is_empty());
    }
}
