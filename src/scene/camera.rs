//! Cameras and the rays through their pixels: a pinhole with an optional
//! lens distortion ([`Lens`]).
//!
//! Convention (docs/design.md): the pose is camera-to-world as in the
//! `transform_matrix` of NeRF-synthetic and instant-ngp files, OpenGL axes
//! (x right, y up, the camera looks down -z). Pixel (i, j) has its centre at
//! (i + 0.5, j + 0.5), with j counting rows from the top of the image.

use glam::{Mat3, Mat4, Vec3};

use super::lens::Lens;

/// Intrinsics in pixels, and the lens that bends the rays.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Intrinsics {
    pub width: u32,
    pub height: u32,
    pub fx: f32,
    pub fy: f32,
    pub cx: f32,
    pub cy: f32,
    /// Lens distortion, in normalised image coordinates (unchanged by
    /// downscaling).
    pub lens: Lens,
}

impl Intrinsics {
    /// Intrinsics from a horizontal field of view, as NeRF-synthetic files
    /// give it: focal = 0.5 W / tan(0.5 camera_angle_x), square pixels,
    /// principal point at the image centre.
    pub fn from_fov_x(width: u32, height: u32, camera_angle_x: f32) -> Self {
        let focal = focal_from_fov(width, camera_angle_x);
        Self {
            width,
            height,
            fx: focal,
            fy: focal,
            cx: 0.5 * width as f32,
            cy: 0.5 * height as f32,
            lens: Lens::Pinhole,
        }
    }

    /// The same camera seen at 1/`factor` of the resolution (integer
    /// downscale): the image plane keeps its extent, so focal lengths and the
    /// principal point shrink by the same factor.
    pub fn downscaled(&self, factor: u32) -> Self {
        let k = factor as f32;
        Self {
            width: self.width / factor,
            height: self.height / factor,
            fx: self.fx / k,
            fy: self.fy / k,
            cx: self.cx / k,
            cy: self.cy / k,
            lens: self.lens,
        }
    }

    /// The pixels `x0..x0 + width`, `y0..y0 + height` of this camera's
    /// image as an image of their own: the same focal lengths and lens, the
    /// principal point moved by the crop's corner, so every pixel keeps its
    /// ray.
    pub fn cropped(&self, x0: u32, y0: u32, width: u32, height: u32) -> Self {
        Self {
            width,
            height,
            cx: self.cx - x0 as f32,
            cy: self.cy - y0 as f32,
            ..*self
        }
    }

    /// Horizontal field of view in radians.
    pub fn fov_x(&self) -> f32 {
        2.0 * (0.5 * self.width as f32 / self.fx).atan()
    }

    /// Vertical field of view in radians.
    pub fn fov_y(&self) -> f32 {
        2.0 * (0.5 * self.height as f32 / self.fy).atan()
    }
}

/// Focal length in pixels for an image `size` pixels across that spans
/// `angle` radians: 0.5 · size / tan(0.5 · angle).
pub fn focal_from_fov(size: u32, angle: f32) -> f32 {
    0.5 * size as f32 / (0.5 * angle).tan()
}

/// A ray `origin + t · direction`, with what Mip-NeRF needs besides.
///
/// From a camera that carries an [`NdcSpace`] the ray lives in normalised
/// device coordinates instead of the world (see [`NdcSpace::ray`]): the
/// origin on the near plane z' = −1, `t` in NDC units along the unit
/// `direction`, the scene inside the box [−1, 1]³ with infinity at z' = 1.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Ray {
    pub origin: Vec3,
    /// Unit length.
    pub direction: Vec3,
    /// The un-normalised direction: the camera-space direction with z = -1
    /// rotated into the world, so `t` along it is depth along the optical
    /// axis. Mip-NeRF builds its cones along this vector. In NDC it is the
    /// paper's d′, whose z component is 2 (the origin is on the near
    /// plane): `t` from 0 to 1 along it runs from the near plane to
    /// infinity, the NeRF paper's NDC near 0 and far 1.
    pub direction_unnormalised: Vec3,
    /// Radius of the pixel's cone at unit distance along
    /// `direction_unnormalised`: 2/√12 of the pixel width there (Mip-NeRF,
    /// Barron et al. 2021, section 3.1), which gives the cone the variance of
    /// the pixel's square footprint. In NDC, 2/√12 of the spacing of
    /// neighbouring pixels' origins on the near plane, so the cone reaches
    /// the pixel's footprint at t = 1 along d′ (infinity), as Mip-NeRF's
    /// LLFF loader sizes it (`internal/datasets.py`, radii from the NDC
    /// origins).
    pub cone_radius: f32,
}

impl Ray {
    pub fn at(&self, t: f32) -> Vec3 {
        self.origin + t * self.direction
    }

    /// The cone's radius at unit distance along the unit `direction`: a
    /// point at distance s along it lies at s / |direction_unnormalised|
    /// along the un-normalised one, where the radius is that times
    /// `cone_radius`.
    pub fn radius(&self) -> f32 {
        self.cone_radius / self.direction_unnormalised.length()
    }
}

/// Normalised device coordinates of a forward-facing scene (NeRF paper,
/// Mildenhall et al. 2020, appendix C; `ndc_rays` in its code): the
/// perspective projection of a reference camera at the world origin looking
/// down −z, which maps the frustum from the near plane z = −`near` out to
/// infinity onto the box [−1, 1]³, so that samples spaced evenly in NDC are
/// spaced evenly in disparity in the world. Its intrinsics are the scene's
/// (the photographs'), shared by every camera whatever its own resolution:
/// only the ratios focal / half-size matter.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NdcSpace {
    pub focal_x: f32,
    pub focal_y: f32,
    pub width: f32,
    pub height: f32,
    /// The near plane's distance: z = −near maps to z′ = −1.
    pub near: f32,
}

impl NdcSpace {
    /// The NDC space of a reference camera with intrinsics `k` and near
    /// plane `near`.
    pub fn of(k: &Intrinsics, near: f32) -> Self {
        Self {
            focal_x: k.fx,
            focal_y: k.fy,
            width: k.width as f32,
            height: k.height as f32,
            near,
        }
    }

    /// How much NDC x′ and y′ grow per unit of x/z and y/z:
    /// focal / (size / 2).
    fn axis_scales(&self) -> (f32, f32) {
        (
            self.focal_x / (0.5 * self.width),
            self.focal_y / (0.5 * self.height),
        )
    }

    /// A world point's image in NDC: (−sx·x/z, −sy·y/z, 1 + 2·near/z).
    pub fn point(&self, p: Vec3) -> Vec3 {
        let (sx, sy) = self.axis_scales();
        Vec3::new(
            -sx * p.x / p.z,
            -sy * p.y / p.z,
            1.0 + 2.0 * self.near / p.z,
        )
    }

    /// The world ray `origin + t · direction` in NDC, as the paper's
    /// appendix C derives it: the origin first moved along the ray to the
    /// near plane z = −near, then o′ is its image and d′ the direction
    /// whose z′ is 2 at the near plane, so that o′ + d′ is the image of the
    /// ray's point at infinity. Every world point of the ray in front of the
    /// near plane maps onto o′ + s·d′ for some s in [0, 1).
    pub fn ray(&self, origin: Vec3, direction: Vec3) -> (Vec3, Vec3) {
        let (sx, sy) = self.axis_scales();
        let to_near = -(self.near + origin.z) / direction.z;
        let o = origin + to_near * direction;
        let d = direction;
        let ndc_origin = self.point(o);
        let ndc_direction = Vec3::new(
            -sx * (d.x / d.z - o.x / o.z),
            -sy * (d.y / d.z - o.y / o.z),
            -2.0 * self.near / o.z,
        );
        (ndc_origin, ndc_direction)
    }
}

/// A pinhole camera: intrinsics and a camera-to-world pose.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Camera {
    pub intrinsics: Intrinsics,
    pub camera_to_world: Mat4,
    /// When set, [`Camera::ray_through`] gives rays in these normalised
    /// device coordinates rather than the world (forward-facing scenes,
    /// [`super::Scene::with_ndc`]); the pose and [`Camera::project`] stay
    /// in the world.
    pub ndc: Option<NdcSpace>,
}

impl Camera {
    pub fn new(intrinsics: Intrinsics, camera_to_world: Mat4) -> Self {
        Self {
            intrinsics,
            camera_to_world,
            ndc: None,
        }
    }

    /// The same camera, its rays in `ndc` (or in the world for `None`).
    pub fn with_ndc(self, ndc: Option<NdcSpace>) -> Self {
        Self { ndc, ..self }
    }

    /// The camera centre in world space.
    pub fn position(&self) -> Vec3 {
        self.camera_to_world.w_axis.truncate()
    }

    /// The rotation part of the pose (camera axes in world space as columns).
    pub fn rotation(&self) -> Mat3 {
        Mat3::from_mat4(self.camera_to_world)
    }

    /// Viewing direction (unit length) in world space: the camera's -z axis.
    pub fn forward(&self) -> Vec3 {
        -self.camera_to_world.z_axis.truncate().normalize()
    }

    /// The camera-space directions through image point (u, v) in pixel
    /// units, v counting down from the top edge: unit length, and scaled to
    /// z = -1. Through the undistorted position of the point when the lens
    /// distorts.
    fn camera_space_directions(&self, u: f32, v: f32) -> (Vec3, Vec3) {
        let k = &self.intrinsics;
        if k.lens == Lens::Pinhole {
            let on_plane = Vec3::new((u - k.cx) / k.fx, -(v - k.cy) / k.fy, -1.0);
            return (on_plane.normalize(), on_plane);
        }
        let xd = (u as f64 - k.cx as f64) / k.fx as f64;
        let yd = (v as f64 - k.cy as f64) / k.fy as f64;
        // OpenCV axes (y down, z forward) to zrak's (y up, z back). A
        // fisheye can see 90° off axis and beyond, where no z = -1 point
        // exists: the depth is clamped so the vector stays finite and keeps
        // its side (it only sizes Mip-NeRF's cones).
        let [x, y, z] = k.lens.undistort(xd, yd).direction;
        let unit = Vec3::new(x as f32, -y as f32, -z as f32);
        let depth = z.max(MIN_UNIT_DEPTH);
        let on_plane = Vec3::new((x / depth) as f32, (-y / depth) as f32, -1.0);
        (unit, on_plane)
    }

    /// The ray through image point (u, v) in pixel units; the centre of
    /// pixel (i, j) is (i + 0.5, j + 0.5). In the world, or in NDC when the
    /// camera carries an [`NdcSpace`].
    pub fn ray_through(&self, u: f32, v: f32) -> Ray {
        let world = self.world_ray_through(u, v);
        match self.ndc {
            None => world,
            Some(ndc) => ndc_ray(&ndc, &world, &self.intrinsics),
        }
    }

    /// The world ray through image point (u, v), whatever NDC the camera
    /// carries.
    pub fn world_ray_through(&self, u: f32, v: f32) -> Ray {
        let (unit, on_plane) = self.camera_space_directions(u, v);
        let rotation = self.rotation();
        let direction_unnormalised = rotation * on_plane;
        let direction = if self.intrinsics.lens == Lens::Pinhole {
            // Bit for bit what it was before lenses existed.
            direction_unnormalised.normalize()
        } else {
            (rotation * unit).normalize()
        };
        Ray {
            origin: self.position(),
            direction,
            direction_unnormalised,
            // The pixel is 1/fx wide at unit depth (mean of both axes for
            // non-square pixels).
            cone_radius: pixel_width_at_unit_depth(&self.intrinsics) * 2.0 / 12f32.sqrt(),
        }
    }

    /// The ray through the centre of pixel (column `i`, row `j`).
    pub fn pixel_ray(&self, i: u32, j: u32) -> Ray {
        self.ray_through(i as f32 + 0.5, j as f32 + 0.5)
    }

    /// Rays through the centre of every pixel, row by row from the top.
    pub fn all_rays(&self) -> Vec<Ray> {
        let k = &self.intrinsics;
        (0..k.height)
            .flat_map(|j| (0..k.width).map(move |i| (i, j)))
            .map(|(i, j)| self.pixel_ray(i, j))
            .collect()
    }

    /// Projects a world-space point to image coordinates (u, v) in pixels
    /// through the lens, or `None` when the lens does not see it (on or
    /// behind the camera plane, except for a fisheye).
    pub fn project(&self, point: Vec3) -> Option<(f32, f32)> {
        let in_camera = self.camera_to_world.inverse().transform_point3(point);
        if in_camera.z >= 0.0 {
            return None;
        }
        let k = &self.intrinsics;
        if k.lens == Lens::Pinhole {
            let depth = -in_camera.z;
            return Some((
                k.cx + k.fx * in_camera.x / depth,
                k.cy - k.fy * in_camera.y / depth,
            ));
        }
        let (xd, yd) = k.lens.distort_direction(
            in_camera.x as f64,
            -in_camera.y as f64,
            -in_camera.z as f64,
        )?;
        Some((
            (k.cx as f64 + k.fx as f64 * xd) as f32,
            (k.cy as f64 + k.fy as f64 * yd) as f32,
        ))
    }

    /// A camera at `eye` looking at `target`, with `up` roughly up, in the
    /// OpenGL convention.
    pub fn look_at(intrinsics: Intrinsics, eye: Vec3, target: Vec3, up: Vec3) -> Self {
        let back = (eye - target).normalize();
        let right = up.cross(back).normalize();
        let true_up = back.cross(right);
        let camera_to_world = Mat4::from_cols(
            right.extend(0.0),
            true_up.extend(0.0),
            back.extend(0.0),
            eye.extend(1.0),
        );
        Self::new(intrinsics, camera_to_world)
    }
}

/// `world` (a ray from the camera centre, `direction_unnormalised` at unit
/// depth per unit t) in `ndc`.
fn ndc_ray(ndc: &NdcSpace, world: &Ray, k: &Intrinsics) -> Ray {
    let (origin, direction_unnormalised) = ndc.ray(world.origin, world.direction_unnormalised);
    // The origin moved to the near plane lies `depth` along the optical
    // axis, where a pixel is `depth` pixel widths wide; NDC stretches x and
    // y there by scale / near.
    let depth = (-(ndc.near + world.origin.z) / world.direction_unnormalised.z).abs();
    let (sx, sy) = ndc.axis_scales();
    let spacing = pixel_width_at_unit_depth(k) * depth * 0.5 * (sx + sy) / ndc.near;
    Ray {
        origin,
        direction: direction_unnormalised.normalize(),
        direction_unnormalised,
        cone_radius: spacing * 2.0 / 12f32.sqrt(),
    }
}

/// The smallest optical-axis component of a unit direction that
/// [`Camera::ray_through`] scales to z = -1 (about 89.9° off axis).
const MIN_UNIT_DEPTH: f64 = 1e-3;

/// The cone's pixel width: the pinhole's, also for distorted lenses (whose
/// pixels vary in footprint across the image; the centre's is kept).
fn pixel_width_at_unit_depth(k: &Intrinsics) -> f32 {
    0.5 * (1.0 / k.fx + 1.0 / k.fy)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn test_camera() -> Camera {
        let intrinsics = Intrinsics {
            width: 64,
            height: 48,
            fx: 70.0,
            fy: 72.0,
            cx: 31.3,
            cy: 24.9,
            lens: Lens::Pinhole,
        };
        Camera::look_at(
            intrinsics,
            Vec3::new(2.0, -3.0, 1.5),
            Vec3::new(0.1, 0.2, -0.3),
            Vec3::Z,
        )
    }

    #[test]
    fn focal_from_camera_angle_x_matches_formula() {
        // lego's camera_angle_x at 400 px: 0.5 * 400 / tan(0.5 * 0.6911112)
        let angle = 0.691_111_2_f32;
        let expected = 0.5 * 400.0 / (0.5f64 * angle as f64).tan();
        let k = Intrinsics::from_fov_x(400, 400, angle);
        assert!(
            (k.fx as f64 - expected).abs() < 1e-3,
            "{} vs {expected}",
            k.fx
        );
        assert!((k.fx - 555.555).abs() < 1e-3);
        assert_eq!(k.fx, k.fy);
        assert!((k.fov_x() - angle).abs() < 1e-6);
    }

    #[test]
    fn projected_point_lies_on_its_pixel_ray() {
        let camera = test_camera();
        let points = [
            Vec3::new(0.0, 0.0, 0.0),
            Vec3::new(0.3, -0.2, 0.1),
            Vec3::new(-0.4, 0.5, -0.6),
        ];
        for point in points {
            let (u, v) = camera.project(point).expect("point in front of camera");
            let ray = camera.ray_through(u, v);
            // Distance from the point to the ray.
            let t = (point - ray.origin).dot(ray.direction);
            let closest = ray.at(t);
            assert!(
                (closest - point).length() < 1e-5,
                "point {point} is {} from its ray",
                (closest - point).length()
            );
            // And the un-normalised direction reaches the point at its depth.
            let depth = camera
                .camera_to_world
                .inverse()
                .transform_point3(point)
                .z
                .abs();
            let reached = ray.origin + depth * ray.direction_unnormalised;
            assert!((reached - point).length() < 1e-5);
        }
    }

    #[test]
    fn pixel_centre_projects_back_to_its_centre() {
        let camera = test_camera();
        let ray = camera.pixel_ray(10, 7);
        let (u, v) = camera.project(ray.at(3.0)).unwrap();
        assert!(
            (u - 10.5).abs() < 1e-4 && (v - 7.5).abs() < 1e-4,
            "({u}, {v})"
        );
    }

    #[test]
    fn corner_rays_point_where_expected() {
        // Identity pose: camera at the origin looking down -z, y up.
        let intrinsics = Intrinsics::from_fov_x(4, 2, std::f32::consts::FRAC_PI_2);
        let camera = Camera::new(intrinsics, Mat4::IDENTITY);
        let rays = camera.all_rays();
        assert_eq!(rays.len(), 8);
        // fx = 0.5 * 4 / tan(pi/4) = 2; pixel centres at x = 0.5..3.5,
        // so the corner directions are ((0.5 - 2)/2, ±(1 - 0.5)/2, -1).
        let expect = |x: f32, y: f32| Vec3::new(x, y, -1.0).normalize();
        let top_left = expect(-0.75, 0.25);
        let top_right = expect(0.75, 0.25);
        let bottom_left = expect(-0.75, -0.25);
        let bottom_right = expect(0.75, -0.25);
        for (ray, want) in [
            (rays[0], top_left),
            (rays[3], top_right),
            (rays[4], bottom_left),
            (rays[7], bottom_right),
        ] {
            assert!(
                (ray.direction - want).length() < 1e-6,
                "{} vs {want}",
                ray.direction
            );
            assert_eq!(ray.origin, Vec3::ZERO);
            assert!((ray.direction_unnormalised.z + 1.0).abs() < 1e-7);
        }
        // Every ray has unit length and points forward.
        for ray in &rays {
            assert!((ray.direction.length() - 1.0).abs() < 1e-6);
            assert!(ray.direction.z < 0.0);
        }
    }

    #[test]
    fn cone_radius_is_pixel_footprint() {
        let intrinsics = Intrinsics::from_fov_x(100, 100, 1.0);
        let camera = Camera::new(intrinsics, Mat4::IDENTITY);
        let ray = camera.pixel_ray(0, 0);
        let pixel_width = 1.0 / intrinsics.fx;
        assert!((ray.cone_radius - pixel_width * 2.0 / 12f32.sqrt()).abs() < 1e-9);
        // Neighbouring pixel rays (un-normalised) are one pixel width apart.
        let next = camera.pixel_ray(1, 0);
        let gap = (next.direction_unnormalised - ray.direction_unnormalised).length();
        assert!((gap - pixel_width).abs() < 1e-6);
    }

    #[test]
    fn downscale_keeps_field_of_view() {
        let k = Intrinsics::from_fov_x(400, 400, 0.69);
        let half = k.downscaled(2);
        assert_eq!((half.width, half.height), (200, 200));
        assert!((half.fov_x() - k.fov_x()).abs() < 1e-6);
        assert!((half.cx - 100.0).abs() < 1e-6);
    }

    /// Project → unproject through each lens model: the pixel comes back to
    /// 1e-4 px, and the ray passes through the point.
    #[test]
    fn distorted_cameras_round_trip_to_a_ten_thousandth_of_a_pixel() {
        let lenses = [
            Lens::RadialTangential {
                k1: -0.12,
                k2: 0.05,
                k3: -0.01,
                k4: 0.0,
                p1: 0.001,
                p2: -0.0015,
            },
            Lens::Fisheye {
                k1: 0.05,
                k2: -0.01,
                k3: 0.003,
                k4: -0.0005,
            },
        ];
        for lens in lenses {
            let mut camera = test_camera();
            camera.intrinsics.lens = lens;
            for j in 0..=12 {
                for i in 0..=16 {
                    let (u, v) = (i as f32 * 4.0, j as f32 * 4.0);
                    let ray = camera.ray_through(u, v);
                    assert!((ray.direction.length() - 1.0).abs() < 1e-6);
                    let point = ray.at(2.5);
                    let (pu, pv) = camera.project(point).expect("seen");
                    assert!(
                        (pu - u).abs() < 1e-4 && (pv - v).abs() < 1e-4,
                        "{lens:?}: ({u}, {v}) came back as ({pu}, {pv})"
                    );
                }
            }
        }
    }

    /// A closed-form case: k1 only, identity pose, fx = fy = 100, centre
    /// (50, 50). The pixel (50 + 100 · x (1 + k1 x²), 50) sees direction
    /// (x, 0, -1).
    #[test]
    fn radial_distortion_bends_rays_as_the_closed_form_says() {
        let mut intrinsics = Intrinsics::from_fov_x(100, 100, std::f32::consts::FRAC_PI_2);
        intrinsics.fx = 100.0;
        intrinsics.fy = 100.0;
        intrinsics.lens = Lens::RadialTangential {
            k1: 0.2,
            k2: 0.0,
            k3: 0.0,
            k4: 0.0,
            p1: 0.0,
            p2: 0.0,
        };
        let camera = Camera::new(intrinsics, Mat4::IDENTITY);
        for x in [0.1f32, 0.3, -0.45] {
            let u = 50.0 + 100.0 * x * (1.0 + 0.2 * x * x);
            let ray = camera.ray_through(u, 50.0);
            let want = Vec3::new(x, 0.0, -1.0);
            assert!((ray.direction - want.normalize()).length() < 1e-6);
            assert!((ray.direction_unnormalised - want).length() < 1e-6);
        }
        // Equidistant fisheye: a pixel 100 · θ from the centre sees θ off
        // axis, also beyond 90°.
        intrinsics.lens = Lens::Fisheye {
            k1: 0.0,
            k2: 0.0,
            k3: 0.0,
            k4: 0.0,
        };
        let camera = Camera::new(intrinsics, Mat4::IDENTITY);
        for theta in [0.2f32, 1.2, 1.8] {
            let ray = camera.ray_through(50.0, 50.0 - 100.0 * theta);
            // Up the image is +y in zrak's axes.
            let want = Vec3::new(0.0, theta.sin(), -theta.cos());
            assert!(
                (ray.direction - want).length() < 1e-6,
                "{theta}: {}",
                ray.direction
            );
        }
    }

    /// A forward-facing view: 80 × 60, focal 70, beside the reference
    /// camera at the origin and turned a little, looking down −z.
    fn forward_facing_camera() -> (Camera, NdcSpace) {
        let k = Intrinsics {
            width: 80,
            height: 60,
            fx: 70.0,
            fy: 70.0,
            cx: 40.0,
            cy: 30.0,
            lens: Lens::Pinhole,
        };
        let pose = Mat4::from_translation(Vec3::new(0.15, -0.1, 0.05))
            * Mat4::from_axis_angle(Vec3::new(0.3, 1.0, 0.1).normalize(), 0.08);
        let ndc = NdcSpace::of(&k, 1.0);
        (Camera::new(k, pose).with_ndc(Some(ndc)), ndc)
    }

    /// The paper's closed form (appendix C, eq. 25 and 26) after moving
    /// the origin to z = −n, written out here apart from `NdcSpace::ray`.
    fn paper_ndc(o: Vec3, d: Vec3, f: f32, w: f32, h: f32, n: f32) -> (Vec3, Vec3) {
        let t = -(n + o.z) / d.z;
        let o = o + t * d;
        let (ax, ay) = (-f / (w / 2.0), -f / (h / 2.0));
        let origin = Vec3::new(ax * o.x / o.z, ay * o.y / o.z, 1.0 + 2.0 * n / o.z);
        let direction = Vec3::new(
            ax * (d.x / d.z - o.x / o.z),
            ay * (d.y / d.z - o.y / o.z),
            -2.0 * n / o.z,
        );
        (origin, direction)
    }

    #[test]
    fn ndc_rays_follow_the_papers_closed_form() {
        let (camera, _) = forward_facing_camera();
        for (u, v) in [(0.5, 0.5), (40.0, 30.0), (79.5, 12.25), (3.0, 59.5)] {
            let world = camera.world_ray_through(u, v);
            let (o, d) = paper_ndc(
                world.origin,
                world.direction_unnormalised,
                70.0,
                80.0,
                60.0,
                1.0,
            );
            let ray = camera.ray_through(u, v);
            assert!((ray.origin - o).length() < 1e-5, "{} vs {o}", ray.origin);
            assert!((ray.direction_unnormalised - d).length() < 1e-5);
            assert!((ray.direction - d.normalize()).length() < 1e-6);
            assert!((ray.direction.length() - 1.0).abs() < 1e-6);
            // From the near plane, d′ reaches infinity at t = 1.
            assert!((ray.origin.z + 1.0).abs() < 1e-6);
            assert!((ray.direction_unnormalised.z - 2.0).abs() < 1e-5);
        }
        // The same direction (not unit length) gives the same NDC ray.
        let world = camera.world_ray_through(10.0, 20.0);
        let ndc = camera.ndc.unwrap();
        let (a, b) = ndc.ray(world.origin, world.direction);
        assert!((a - camera.ray_through(10.0, 20.0).origin).length() < 1e-5);
        assert!((b - camera.ray_through(10.0, 20.0).direction_unnormalised).length() < 1e-5);
    }

    #[test]
    fn points_on_a_world_ray_map_onto_its_ndc_ray() {
        let (camera, ndc) = forward_facing_camera();
        for (u, v) in [(5.5, 7.5), (60.0, 44.0)] {
            let world = camera.world_ray_through(u, v);
            let ray = camera.ray_through(u, v);
            let mut last_s = 0.0;
            for depth in [1.5f32, 2.0, 5.0, 40.0, 1e4] {
                let p = world.origin + depth * world.direction_unnormalised;
                // Its image, from the paper's projection.
                let image = Vec3::new(
                    -70.0 / 40.0 * p.x / p.z,
                    -70.0 / 30.0 * p.y / p.z,
                    1.0 + 2.0 / p.z,
                );
                assert!((ndc.point(p) - image).length() < 1e-5);
                let s = (image - ray.origin).dot(ray.direction_unnormalised)
                    / ray.direction_unnormalised.length_squared();
                let on_ray = ray.origin + s * ray.direction_unnormalised;
                assert!(
                    (on_ray - image).length() < 1e-4,
                    "depth {depth}: {image} is {} from the NDC ray",
                    (on_ray - image).length()
                );
                // Farther in the world is farther along the NDC ray, within
                // [0, 1].
                assert!(s > last_s && s < 1.0, "{s}");
                last_s = s;
            }
        }
    }

    #[test]
    fn the_near_plane_is_minus_one_and_infinity_plus_one() {
        let (camera, ndc) = forward_facing_camera();
        let near_point = Vec3::new(0.3, -0.2, -1.0);
        assert!((ndc.point(near_point).z + 1.0).abs() < 1e-7);
        let far_point = Vec3::new(3e6, -2e6, -1e7);
        assert!((ndc.point(far_point).z - 1.0).abs() < 1e-6);
        // The ray's end at t = 1 along d′ is the image of its direction at
        // infinity.
        let world = camera.world_ray_through(20.0, 50.0);
        let ray = camera.ray_through(20.0, 50.0);
        let end = ray.origin + ray.direction_unnormalised;
        let far = ndc.point(world.origin + 1e6 * world.direction_unnormalised);
        assert!((end - far).length() < 1e-4, "{end} vs {far}");
        assert!((end.z - 1.0).abs() < 1e-6);
    }

    #[test]
    fn the_reference_cameras_ndc_rays_are_parallel_and_a_pixel_apart() {
        let (camera, ndc) = forward_facing_camera();
        let reference = Camera::new(camera.intrinsics, Mat4::IDENTITY).with_ndc(Some(ndc));
        let rays = reference.all_rays();
        for ray in &rays {
            assert!(
                ray.direction.abs_diff_eq(Vec3::Z, 1e-6),
                "{}",
                ray.direction
            );
        }
        // Pixel centres across the image span x′ from −1 + 1/W to 1 − 1/W.
        assert!((rays[0].origin.x - (-1.0 + 1.0 / 80.0)).abs() < 1e-6);
        assert!((rays[0].origin.y - (1.0 - 1.0 / 60.0)).abs() < 1e-6);
        assert!((rays[79].origin.x - (1.0 - 1.0 / 80.0)).abs() < 1e-6);
        // The cone: 2/√12 of the spacing of neighbouring origins (2/W
        // across, 2/H down), the mean of both axes as Mip-NeRF takes it.
        let across = (rays[1].origin - rays[0].origin).length();
        let down = (rays[80].origin - rays[0].origin).length();
        assert!((across - 2.0 / 80.0).abs() < 1e-6 && (down - 2.0 / 60.0).abs() < 1e-6);
        let spacing = 0.5 * (across + down);
        assert!((rays[0].cone_radius - spacing * 2.0 / 12f32.sqrt()).abs() < 1e-6);
        // A downscaled copy keeps the NDC, its pixels twice as wide.
        let half = Camera::new(reference.intrinsics.downscaled(2), Mat4::IDENTITY)
            .with_ndc(Some(ndc))
            .all_rays();
        assert!(((half[1].origin - half[0].origin).length() - 4.0 / 80.0).abs() < 1e-6);
        assert!((half[0].cone_radius - 2.0 * rays[0].cone_radius).abs() < 1e-6);
    }
}
