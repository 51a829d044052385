//! Lines drawn over the viewport's image: scene-space shapes (the crop
//! box; the camera path in `path_overlay`) projected with the viewport
//! camera, by one pinhole projection.

use eframe::egui;
use egui::{Color32, Pos2, Rect, Stroke};
use glam::{Mat4, Vec3};

use crate::scene::Camera;
use crate::scene::crop::CropBox;

/// How far in front of the camera a line is cut where it passes behind
/// it (world units): near enough that nothing visible is lost, far enough
/// that the division by depth stays finite.
const NEAR: f32 = 1e-3;

/// The colour of the crop box's edges: amber, apart from the scenes'
/// usual greys and whites.
pub const CROP_COLOUR: Color32 = Color32::from_rgb(0xff, 0xc0, 0x30);

/// A pinhole projection of world points into a screen rect: the viewport
/// camera's pose and intrinsics, its image stretched over `rect`.
#[derive(Debug, Clone, Copy)]
pub struct Projection {
    world_to_camera: Mat4,
    /// Focal lengths and principal point in screen points, the latter
    /// relative to the rect's top-left corner.
    fx: f32,
    fy: f32,
    cx: f32,
    cy: f32,
    rect: Rect,
    /// Points nearer than this depth are not drawn.
    near: f32,
}

impl Projection {
    /// `camera` at any pixel size, shown over `rect`.
    pub fn new(camera: &Camera, rect: Rect, near: f32) -> Self {
        let k = camera.intrinsics;
        let sx = rect.width() / k.width.max(1) as f32;
        let sy = rect.height() / k.height.max(1) as f32;
        Self {
            world_to_camera: camera.camera_to_world.inverse(),
            fx: k.fx * sx,
            fy: k.fy * sy,
            cx: k.cx * sx,
            cy: k.cy * sy,
            rect,
            near,
        }
    }

    /// Where `point` appears on screen, or `None` when it is nearer than
    /// the near plane or behind the camera.
    pub fn project(&self, point: Vec3) -> Option<Pos2> {
        let p = self.world_to_camera.transform_point3(point);
        let depth = -p.z;
        if depth.is_nan() || depth < self.near {
            return None;
        }
        Some(self.place(p))
    }

    /// Both ends of a segment on screen, or `None` when either lies
    /// behind the near plane.
    pub fn segment(&self, a: Vec3, b: Vec3) -> Option<[Pos2; 2]> {
        Some([self.project(a)?, self.project(b)?])
    }

    /// The on-screen part of the segment `a`–`b`: cut where it passes the
    /// near plane, `None` when all of it is nearer.
    pub fn clipped_segment(&self, a: Vec3, b: Vec3) -> Option<[Pos2; 2]> {
        let (mut a, mut b) = (
            self.world_to_camera.transform_point3(a),
            self.world_to_camera.transform_point3(b),
        );
        let in_front = |p: Vec3| -p.z >= self.near;
        match (in_front(a), in_front(b)) {
            (false, false) => return None,
            (true, true) => {}
            (front_a, _) => {
                // The point where the segment crosses z = −near.
                let t = (-self.near - a.z) / (b.z - a.z);
                let cut = a + (b - a) * t;
                if front_a {
                    b = cut;
                } else {
                    a = cut;
                }
            }
        }
        Some([self.place(a), self.place(b)])
    }

    /// A camera-frame point in front of the camera, on screen.
    fn place(&self, p: Vec3) -> Pos2 {
        let depth = -p.z;
        Pos2::new(
            self.rect.min.x + self.cx + self.fx * p.x / depth,
            self.rect.min.y + self.cy - self.fy * p.y / depth,
        )
    }
}

/// Where world `point` appears on screen when the camera's picture fills
/// `image`, or `None` when it is behind the camera (or on its plane). The
/// pinhole model: the viewport camera has no lens distortion.
pub fn project_to_viewport(camera: &Camera, point: Vec3, image: Rect) -> Option<Pos2> {
    Projection::new(camera, image, NEAR).project(point)
}

/// The on-screen segment of the world segment `a`–`b`: cut where it passes
/// behind the camera (at [`NEAR`] in front), `None` when all of it is
/// behind.
pub fn project_segment(camera: &Camera, a: Vec3, b: Vec3, image: Rect) -> Option<[Pos2; 2]> {
    Projection::new(camera, image, NEAR).clipped_segment(a, b)
}

/// The 12 edges of a box as pairs of [`CropBox::corners`] indices: the
/// corners differing in one bit (one axis) of their index.
pub fn box_edges() -> [(usize, usize); 12] {
    let mut edges = [(0, 0); 12];
    let mut n = 0;
    for corner in 0..8 {
        for bit in [1, 2, 4] {
            if corner & bit == 0 {
                edges[n] = (corner, corner | bit);
                n += 1;
            }
        }
    }
    edges
}

/// Draws the crop box's edges over the picture of `camera` filling
/// `image` (the painter clips them to the viewport).
pub fn draw_crop_box(painter: &egui::Painter, camera: &Camera, image: Rect, crop: &CropBox) {
    let corners = crop.corners();
    let stroke = Stroke::new(1.5, CROP_COLOUR);
    let projection = Projection::new(camera, image, NEAR);
    for (a, b) in box_edges() {
        if let Some(segment) = projection.clipped_segment(corners[a], corners[b]) {
            painter.line_segment(segment, stroke);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::Intrinsics;

    /// 60° across, 200 × 100 pixels, at (0, 0, 5) looking at the origin.
    fn camera() -> Camera {
        Camera::look_at(
            Intrinsics::from_fov_x(200, 100, 60f32.to_radians()),
            Vec3::new(0.0, 0.0, 5.0),
            Vec3::ZERO,
            Vec3::Y,
        )
    }

    fn close(a: Pos2, b: Pos2) -> bool {
        (a - b).length() < 1e-3
    }

    #[test]
    fn a_point_on_the_axis_projects_to_the_centre_and_one_at_the_field_edge_to_the_edge() {
        let camera = camera();
        // Shown at half size, moved: the projection follows the rect.
        let image = Rect::from_min_size(Pos2::new(10.0, 20.0), egui::vec2(100.0, 50.0));
        let on_axis = project_to_viewport(&camera, Vec3::new(0.0, 0.0, -3.0), image).unwrap();
        assert!(close(on_axis, image.center()), "{on_axis:?}");
        // 30° off axis to the right, at depth 5: x = 5 · tan 30°.
        let right = 5.0 * 30f32.to_radians().tan();
        let edge = project_to_viewport(&camera, Vec3::new(right, 0.0, 0.0), image).unwrap();
        assert!(
            close(edge, Pos2::new(image.max.x, image.center().y)),
            "{edge:?}"
        );
        let edge = project_to_viewport(&camera, Vec3::new(-right, 0.0, 0.0), image).unwrap();
        assert!(
            close(edge, Pos2::new(image.min.x, image.center().y)),
            "{edge:?}"
        );
        // Up is up on screen: the top edge at half the vertical field.
        let up = 5.0 * (camera.intrinsics.fov_y() / 2.0).tan();
        let top = project_to_viewport(&camera, Vec3::new(0.0, up, 0.0), image).unwrap();
        assert!(
            close(top, Pos2::new(image.center().x, image.min.y)),
            "{top:?}"
        );
        // Behind the camera: nothing.
        assert_eq!(
            project_to_viewport(&camera, Vec3::new(0.0, 0.0, 6.0), image),
            None
        );
    }

    #[test]
    fn a_segment_through_the_camera_plane_is_cut_in_front_of_it() {
        let camera = camera();
        let image = Rect::from_min_size(Pos2::ZERO, egui::vec2(200.0, 100.0));
        let front = Vec3::new(1.0, 0.0, 0.0);
        // Reaches 3 units behind the camera, off to the right.
        let behind = Vec3::new(1.0, 0.0, 8.0);
        let [a, b] = project_segment(&camera, front, behind, image).unwrap();
        assert!(close(
            a,
            project_to_viewport(&camera, front, image).unwrap()
        ));
        // The cut end is just in front of the camera: far off to the right,
        // on the horizon row, and finite.
        assert!(b.x > 1e4 && b.x.is_finite(), "{b:?}");
        assert!((b.y - 50.0).abs() < 1e-2, "{b:?}");
        assert_eq!(
            project_segment(&camera, Vec3::new(0.0, 0.0, 6.0), behind, image),
            None
        );
    }

    #[test]
    fn a_box_has_twelve_edges_each_along_one_axis() {
        let edges = box_edges();
        let crop = CropBox::axis_aligned(Vec3::ZERO, Vec3::new(1.0, 2.0, 3.0));
        let corners = crop.corners();
        let mut lengths: Vec<f32> = edges
            .iter()
            .map(|&(a, b)| (corners[a] - corners[b]).length())
            .collect();
        lengths.sort_by(f32::total_cmp);
        assert_eq!(
            lengths,
            [1.0, 1.0, 1.0, 1.0, 2.0, 2.0, 2.0, 2.0, 3.0, 3.0, 3.0, 3.0]
        );
    }
}
