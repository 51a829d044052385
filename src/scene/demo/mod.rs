//! The built-in demo scene: a handful of coloured primitives on a checkered
//! stand, rendered by an exact ray tracer into the NeRF-synthetic layout.
//!
//! It exists so that the viewer has something to open and the tests have
//! something to train on without any dataset on disk. It is deliberately
//! small (content within a radius of about 1.2 of the origin, inside
//! [`UnitCubeMapping::BLENDER`]'s box), deterministic (no randomness
//! anywhere: fixed supersampling pattern, fixed camera placement), and
//! learnable (flat colours, one texture, one glossy object so that view
//! dependence matters, a transparent background like the Blender scenes).
//!
//! World axes follow Blender: z is up. Cameras sit on the upper hemisphere
//! at distance [`CAMERA_DISTANCE`] looking at the origin, like
//! NeRF-synthetic's cameras at about 4.03.

use std::path::{Path, PathBuf};

use glam::Vec3;
use rayon::prelude::*;
use serde::Serialize;

use super::{
    Camera, Frame, ImageRgba8, Intrinsics, Scene, SceneError, SceneFormat, SceneResult,
    SpaceAnalysis, Split, UnitCubeMapping, space,
};
use crate::scene::to_u8;

mod forward;
mod perturbed;

pub use forward::{
    CAPTURE_RADIUS, FORWARD_CAMERA_DISTANCE, ForwardFacingConfig, WALL_DISTANCE,
    build_forward_facing, forward_facing_cameras, render_forward_facing_view, view_bounds,
    viewing_direction, write_forward_facing_llff,
};
pub use perturbed::{
    CAMERA_TRUTH_FILE, CameraPerturbation, PERTURBATION_SEED, perturb_cameras, read_camera_truth,
    write_with_perturbed_cameras,
};

/// Horizontal field of view of every demo camera, NeRF-synthetic's value.
pub const CAMERA_ANGLE_X: f32 = 0.691_111_2;

/// Distance of every demo camera from the origin.
pub const CAMERA_DISTANCE: f32 = 4.0;

/// Lowest and highest camera elevation of the training spiral, in degrees.
/// Below 10° the stand hides most of itself; above 80° the views stop adding
/// parallax.
const MIN_ELEVATION_DEG: f32 = 10.0;
const MAX_ELEVATION_DEG: f32 = 80.0;

/// Supersampling grid per pixel side: 4×4 = 16 samples, enough for smooth
/// alpha edges and an unaliased checkerboard at 128 px.
const SAMPLES_PER_SIDE: u32 = 4;

/// How large the demo scene is and how many views each split gets.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct DemoConfig {
    /// Width and height of every image, in pixels.
    pub size: u32,
    pub train_views: usize,
    pub val_views: usize,
    pub test_views: usize,
}

impl Default for DemoConfig {
    fn default() -> Self {
        Self {
            size: 128,
            train_views: 100,
            val_views: 10,
            test_views: 10,
        }
    }
}

impl DemoConfig {
    fn views(&self, split: Split) -> usize {
        match split {
            Split::Train => self.train_views,
            Split::Val => self.val_views,
            Split::Test => self.test_views,
        }
    }
}

/// Builds the scene in memory: every view of every split rendered.
pub fn build(config: &DemoConfig) -> Scene {
    build_with(|split| split_cameras(config, split), render_view)
}

/// The demo with the `cameras` of each split, each view rendered by
/// `render`.
fn build_with(
    cameras: impl Fn(Split) -> Vec<Camera>,
    render: impl Fn(&Camera) -> ImageRgba8 + Sync,
) -> Scene {
    let mut frames = Split::ALL.map(|split| {
        cameras(split)
            .par_iter()
            .map(|&camera| Frame {
                camera,
                image: render(&camera),
                image_path: PathBuf::new(),
                mask: None,
            })
            .collect::<Vec<_>>()
    });
    let unit_cube = UnitCubeMapping::BLENDER;
    let mut scene = Scene {
        name: "demo".to_string(),
        root: PathBuf::new(),
        format: SceneFormat::Demo,
        train: std::mem::take(&mut frames[0]),
        val: std::mem::take(&mut frames[1]),
        test: std::mem::take(&mut frames[2]),
        has_alpha: true,
        unit_cube,
        bounds: unit_cube.world_bounds(),
        smaller_training_views: 0,
        sparse_points: None,
        space: SpaceAnalysis::default(),
        poses: crate::scene::PoseOrigin::exact("the demo is rendered from the cameras it stores"),
    };
    scene.space = space::analyse(&scene);
    scene
}

/// Writes the scene in the NeRF-synthetic (Blender) layout under `dir`:
/// `transforms_{train,val,test}.json` and `{train,val,test}/r_N.png`.
pub fn write(config: &DemoConfig, dir: &Path) -> SceneResult<()> {
    write_blender(&build(config), dir)
}

/// Writes `scene` in the NeRF-synthetic layout under `dir` (see [`write`]).
fn write_blender(scene: &Scene, dir: &Path) -> SceneResult<()> {
    for split in Split::ALL {
        let frames = scene.split(split);
        let folder = dir.join(split.name());
        std::fs::create_dir_all(&folder)
            .map_err(|e| SceneError::new(&folder, format!("cannot create folder: {e}")))?;
        frames
            .par_iter()
            .enumerate()
            .try_for_each(|(index, frame)| {
                frame.image.save_png(&folder.join(format!("r_{index}.png")))
            })?;
        let file = TransformsFile {
            camera_angle_x: CAMERA_ANGLE_X,
            frames: frames
                .iter()
                .enumerate()
                .map(|(index, frame)| FrameEntry {
                    file_path: format!("./{}/r_{index}", split.name()),
                    transform_matrix: std::array::from_fn(|row| {
                        frame.camera.camera_to_world.row(row).to_array()
                    }),
                })
                .collect(),
        };
        let path = dir.join(format!("transforms_{}.json", split.name()));
        let text = serde_json::to_string_pretty(&file)
            .map_err(|e| SceneError::new(&path, format!("cannot encode JSON: {e}")))?;
        crate::files::write_bytes_atomically(&path, text.as_bytes())
            .map_err(|e| SceneError::new(&path, format!("cannot write file: {e}")))?;
    }
    Ok(())
}

/// Writes the large-extent demo ([`build_large`]) under `dir` in the
/// instant-ngp layout: `transforms.json` (with `aabb_scale` and nerfstudio's
/// split lists) and `{train,val,test}/r_N.png`, opaque.
pub fn write_large(config: &DemoConfig, dir: &Path) -> SceneResult<()> {
    write_instant_ngp(&build_large(config), dir)
}

/// Writes `scene` under `dir` in the instant-ngp layout: `transforms.json`
/// (with its `aabb_scale` and nerfstudio's split lists) and
/// `{train,val,test}/r_N.png`. Its cameras have the demo's field of view.
fn write_instant_ngp(scene: &Scene, dir: &Path) -> SceneResult<()> {
    let mut frames = Vec::new();
    let mut lists: [Vec<String>; 3] = Default::default();
    for (list, split) in lists.iter_mut().zip(Split::ALL) {
        let folder = dir.join(split.name());
        std::fs::create_dir_all(&folder)
            .map_err(|e| SceneError::new(&folder, format!("cannot create folder: {e}")))?;
        let views = scene.split(split);
        views
            .par_iter()
            .enumerate()
            .try_for_each(|(index, frame)| {
                frame.image.save_png(&folder.join(format!("r_{index}.png")))
            })?;
        for (index, frame) in views.iter().enumerate() {
            let file_path = format!("{}/r_{index}.png", split.name());
            let rows: [[f32; 4]; 4] =
                std::array::from_fn(|row| frame.camera.camera_to_world.row(row).to_array());
            frames.push(serde_json::json!({ "file_path": file_path, "transform_matrix": rows }));
            list.push(file_path);
        }
    }
    let json = serde_json::json!({
        "camera_angle_x": CAMERA_ANGLE_X,
        "aabb_scale": scene.unit_cube.aabb_scale,
        "train_filenames": lists[0],
        "val_filenames": lists[1],
        "test_filenames": lists[2],
        "frames": frames,
    });
    let path = dir.join("transforms.json");
    let text = serde_json::to_string_pretty(&json)
        .map_err(|e| SceneError::new(&path, format!("cannot encode JSON: {e}")))?;
    crate::files::write_bytes_atomically(&path, text.as_bytes())
        .map_err(|e| SceneError::new(&path, format!("cannot write file: {e}")))
}

#[derive(Serialize)]
struct TransformsFile {
    camera_angle_x: f32,
    frames: Vec<FrameEntry>,
}

#[derive(Serialize)]
struct FrameEntry {
    file_path: String,
    transform_matrix: [[f32; 4]; 4],
}

/// The cameras of one split, in file order, without rendering anything.
///
/// Training views lie on a golden-angle spiral whose heights are spaced
/// evenly (so the views cover the band of the hemisphere evenly in area).
/// Validation and test views lie on the same spiral half-way between two
/// training views, spread along its whole length (validation a quarter of
/// the way into each stretch, test three quarters): the same distribution
/// of viewpoints, but never one the model was trained on.
pub fn split_cameras(config: &DemoConfig, split: Split) -> Vec<Camera> {
    spiral_cameras(config, split, (MIN_ELEVATION_DEG, MAX_ELEVATION_DEG))
}

/// [`split_cameras`] on a spiral between `elevations` (lowest and highest,
/// in degrees).
fn spiral_cameras(config: &DemoConfig, split: Split, elevations: (f32, f32)) -> Vec<Camera> {
    let count = config.views(split);
    // With no training views there is nothing to avoid; the held-out views
    // then make their own spiral.
    let spiral_length = if config.train_views > 0 {
        config.train_views
    } else {
        count
    };
    let stretch = spiral_length as f32 / count as f32;
    let positions: Vec<Vec3> = match split {
        Split::Train => (0..count)
            .map(|k| spiral_position(k as f32, spiral_length, elevations))
            .collect(),
        Split::Val | Split::Test => {
            let phase = if split == Split::Val { 0.25 } else { 0.75 };
            (0..count)
                .map(|k| {
                    let index = ((k as f32 + phase) * stretch)
                        .floor()
                        .min(spiral_length as f32 - 1.0);
                    spiral_position(index + 0.5, spiral_length, elevations)
                })
                .collect()
        }
    };
    let intrinsics = Intrinsics::from_fov_x(config.size, config.size, CAMERA_ANGLE_X);
    positions
        .into_iter()
        .map(|eye| Camera::look_at(intrinsics, eye, Vec3::ZERO, Vec3::Z))
        .collect()
}

/// A point at `CAMERA_DISTANCE` with the given elevation and azimuth.
fn on_hemisphere(elevation: f32, azimuth: f32) -> Vec3 {
    CAMERA_DISTANCE
        * Vec3::new(
            elevation.cos() * azimuth.cos(),
            elevation.cos() * azimuth.sin(),
            elevation.sin(),
        )
}

/// The point at (possibly fractional) `index` of a spiral of `length`
/// views from the lowest of `elevations` up to the highest (in degrees).
fn spiral_position(index: f32, length: usize, elevations: (f32, f32)) -> Vec3 {
    // The golden angle never repeats a direction, so consecutive views are
    // far apart in azimuth while all views together fill the band evenly.
    let golden_angle = std::f32::consts::PI * (3.0 - 5f32.sqrt());
    let low = elevations.0.to_radians().sin();
    let high = elevations.1.to_radians().sin();
    let t = (index + 0.5) / length as f32;
    let elevation = (low + t * (high - low)).asin();
    on_hemisphere(elevation, index * golden_angle)
}

/// Renders the demo scene exactly (analytic intersections, 16 samples per
/// pixel) as seen by any camera. Where no sample hits anything the pixel is
/// fully transparent.
pub fn render_view(camera: &Camera) -> ImageRgba8 {
    render(camera, None)
}

/// The radius of the large demo's backdrop: a sphere around the objects,
/// 10 world units from the centre (2.5 camera distances), so that it lies
/// well outside the unit cube (3.3 unit-cube units from its centre at
/// scale 0.33) and inside the box of aabb_scale [`LARGE_AABB_SCALE`].
pub const BACKDROP_RADIUS: f32 = 10.0;

/// The large demo's aabb_scale: its box (half side 4 unit-cube units, 12
/// world units) holds the backdrop.
pub const LARGE_AABB_SCALE: f32 = 8.0;

/// [`render_view`] with an opaque backdrop where no object is hit: an
/// enclosing sphere of radius [`BACKDROP_RADIUS`] painted with a coarse
/// checkerboard of latitude and longitude (so that it has detail to learn
/// and parallax to show its depth), like the walls and sky of a real,
/// unbounded capture. Every pixel is opaque.
pub fn render_view_with_backdrop(camera: &Camera) -> ImageRgba8 {
    render(camera, Some(backdrop))
}

/// The colour of the backdrop where the ray from `origin` (inside the
/// sphere) along unit `direction` meets it.
fn backdrop(_world: &World, origin: Vec3, direction: Vec3) -> Vec3 {
    // |o + t d| = R, the positive root.
    let b = origin.dot(direction);
    let c = origin.length_squared() - BACKDROP_RADIUS * BACKDROP_RADIUS;
    let t = -b + (b * b - c).max(0.0).sqrt();
    let p = (origin + t * direction) / BACKDROP_RADIUS;
    let longitude = p.y.atan2(p.x);
    let latitude = p.z.clamp(-1.0, 1.0).asin();
    let cells = 12.0 / std::f32::consts::PI;
    let checker = ((longitude * cells).floor() as i32 + (latitude * cells).floor() as i32) & 1;
    // Brighter towards the top, like a sky over walls.
    let height = 0.5 + 0.5 * p.z;
    let base = Vec3::new(0.35, 0.45, 0.6) * (0.6 + 0.4 * height);
    if checker == 0 {
        base
    } else {
        base * 0.6 + Vec3::new(0.25, 0.2, 0.1)
    }
}

/// The large-extent demo: the same objects and cameras, every view
/// rendered with the backdrop ([`render_view_with_backdrop`], no alpha),
/// aabb_scale [`LARGE_AABB_SCALE`], as an instant-ngp scene.
pub fn build_large(config: &DemoConfig) -> Scene {
    let mut scene = build_with(
        |split| split_cameras(config, split),
        render_view_with_backdrop,
    );
    scene.name = "demo-large".into();
    scene.format = SceneFormat::InstantNgp;
    scene.has_alpha = false;
    scene.unit_cube = UnitCubeMapping {
        aabb_scale: LARGE_AABB_SCALE,
        ..UnitCubeMapping::BLENDER
    };
    scene.bounds = scene.unit_cube.world_bounds();
    scene.space = space::analyse(&scene);
    scene
}

/// The demo seen through cameras with `lens`: the photographs bent by the
/// lens (rendered through [`Camera::ray_through`], which undistorts), as a
/// capture with that lens would be.
pub fn build_distorted(config: &DemoConfig, lens: super::Lens) -> Scene {
    let mut scene = build_with(
        |split| {
            let mut cameras = split_cameras(config, split);
            for camera in &mut cameras {
                camera.intrinsics.lens = lens;
            }
            cameras
        },
        render_view,
    );
    scene.name = "demo-distorted".into();
    scene
}

/// What a ray that hits no object sees: a colour from the world, the ray's
/// origin and its unit direction.
type Surroundings = fn(&World, Vec3, Vec3) -> Vec3;

/// Renders the objects, and `surroundings` where a ray misses them
/// (transparent without).
fn render(camera: &Camera, surroundings: Option<Surroundings>) -> ImageRgba8 {
    let (width, height) = (camera.intrinsics.width, camera.intrinsics.height);
    let world = World::new();
    let mut data = vec![0u8; width as usize * height as usize * 4];
    if data.is_empty() {
        return ImageRgba8::new(width, height, data);
    }
    let n = SAMPLES_PER_SIDE;
    let offsets: Vec<(f32, f32)> = (0..n * n)
        .map(|s| {
            let (a, b) = (s % n, s / n);
            ((a as f32 + 0.5) / n as f32, (b as f32 + 0.5) / n as f32)
        })
        .collect();
    data.par_chunks_mut(width as usize * 4)
        .enumerate()
        .for_each(|(row, pixels)| {
            for (column, pixel) in pixels.chunks_exact_mut(4).enumerate() {
                let mut colour = Vec3::ZERO;
                let mut hits = 0u32;
                for &(dx, dy) in &offsets {
                    let ray = camera.ray_through(column as f32 + dx, row as f32 + dy);
                    if let Some(c) = world.trace(ray.origin, ray.direction) {
                        colour += c;
                        hits += 1;
                    } else if let Some(surroundings) = surroundings {
                        colour += surroundings(&world, ray.origin, ray.direction);
                        hits += 1;
                    }
                }
                // Every sample is either fully covered or empty, so the mean
                // of the hit colours is already the straight (not
                // premultiplied) colour, and coverage is the alpha.
                if hits > 0 {
                    let straight = colour / hits as f32;
                    pixel[0] = to_u8(straight.x);
                    pixel[1] = to_u8(straight.y);
                    pixel[2] = to_u8(straight.z);
                    pixel[3] = to_u8(hits as f32 / offsets.len() as f32);
                }
            }
        });
    ImageRgba8::new(width, height, data)
}

// ---------------------------------------------------------------------------
// The scene's content.

/// Height of the stand's top face: everything else rests on it.
const GROUND_Z: f32 = -0.42;
const GROUND_RADIUS: f32 = 1.1;
const GROUND_THICKNESS: f32 = 0.08;
const CHECKER_SIZE: f32 = 0.22;

/// Radius of a sphere around the origin that holds all content, used to
/// skip the per-object tests for rays that miss everything.
const CONTENT_RADIUS: f32 = 1.25;

/// Offset along the normal for secondary rays, so they do not hit the
/// surface they start on.
const SURFACE_EPSILON: f32 = 1e-3;

const AMBIENT: f32 = 0.2;
const KEY_INTENSITY: f32 = 0.8;
const FILL_INTENSITY: f32 = 0.25;

#[derive(Debug, Clone, Copy)]
enum Shape {
    Sphere {
        centre: Vec3,
        radius: f32,
    },
    /// A box turned by an angle (given as its cosine and sine) about the
    /// vertical axis through its centre.
    Block {
        centre: Vec3,
        half: Vec3,
        cos: f32,
        sin: f32,
    },
    /// An upright cylinder with flat caps, from `bottom` up to
    /// `bottom + height`.
    Cylinder {
        bottom: Vec3,
        radius: f32,
        height: f32,
    },
}

#[derive(Debug, Clone, Copy)]
enum Pigment {
    Solid(Vec3),
    /// Squares on the upward-facing part of the surface, a plain colour on
    /// the rest (the stand's rim).
    Checker {
        light: Vec3,
        dark: Vec3,
        rim: Vec3,
    },
}

#[derive(Debug, Clone, Copy)]
struct Material {
    pigment: Pigment,
    /// Glossy surfaces get a Blinn-Phong highlight from the key light and a
    /// Fresnel-weighted mirror reflection; matte ones only diffuse light.
    glossy: bool,
}

#[derive(Debug, Clone, Copy)]
struct Object {
    shape: Shape,
    material: Material,
}

struct Hit {
    t: f32,
    normal: Vec3,
    object: usize,
}

/// Glossy model parameters: a lacquered ball. The exponent keeps the
/// highlight a few pixels wide at 128 px so that a field can learn it; the
/// base reflectance of 0.06 is plastic-like, and Schlick's term raises it
/// towards grazing angles.
const SPECULAR_STRENGTH: f32 = 0.9;
const SHININESS: f32 = 60.0;
const FRESNEL_BASE: f32 = 0.06;

// Where the objects are; the tests look at them too.
pub const RED_CENTRE: Vec3 = Vec3::new(0.3, -0.25, GROUND_Z + 0.42);
pub const RED_RADIUS: f32 = 0.42;
pub const GREEN_CENTRE: Vec3 = Vec3::new(-0.58, -0.38, GROUND_Z + 0.24);
const GREEN_HALF: f32 = 0.24;
const GREEN_TURN_DEG: f32 = 25.0;
const BLUE_BOTTOM: Vec3 = Vec3::new(-0.3, 0.55, GROUND_Z);
const BLUE_RADIUS: f32 = 0.2;
const BLUE_HEIGHT: f32 = 0.8;
const YELLOW_CENTRE: Vec3 = Vec3::new(0.55, 0.55, GROUND_Z + 0.17);
const YELLOW_RADIUS: f32 = 0.17;

const RED: Vec3 = Vec3::new(0.85, 0.1, 0.08);
const GREEN: Vec3 = Vec3::new(0.15, 0.7, 0.2);
const BLUE: Vec3 = Vec3::new(0.12, 0.3, 0.85);
const YELLOW: Vec3 = Vec3::new(0.95, 0.8, 0.1);

struct World {
    objects: Vec<Object>,
    /// Unit vectors towards the lights.
    key: Vec3,
    fill: Vec3,
}

impl World {
    fn new() -> Self {
        let matte = |colour| Material {
            pigment: Pigment::Solid(colour),
            glossy: false,
        };
        let turn = GREEN_TURN_DEG.to_radians();
        let objects = vec![
            Object {
                shape: Shape::Cylinder {
                    bottom: Vec3::new(0.0, 0.0, GROUND_Z - GROUND_THICKNESS),
                    radius: GROUND_RADIUS,
                    height: GROUND_THICKNESS,
                },
                material: Material {
                    pigment: Pigment::Checker {
                        light: Vec3::new(0.9, 0.87, 0.8),
                        dark: Vec3::new(0.3, 0.33, 0.4),
                        rim: Vec3::new(0.45, 0.45, 0.5),
                    },
                    glossy: false,
                },
            },
            Object {
                shape: Shape::Sphere {
                    centre: RED_CENTRE,
                    radius: RED_RADIUS,
                },
                material: Material {
                    pigment: Pigment::Solid(RED),
                    glossy: true,
                },
            },
            Object {
                shape: Shape::Block {
                    centre: GREEN_CENTRE,
                    half: Vec3::splat(GREEN_HALF),
                    cos: turn.cos(),
                    sin: turn.sin(),
                },
                material: matte(GREEN),
            },
            Object {
                shape: Shape::Cylinder {
                    bottom: BLUE_BOTTOM,
                    radius: BLUE_RADIUS,
                    height: BLUE_HEIGHT,
                },
                material: matte(BLUE),
            },
            Object {
                shape: Shape::Sphere {
                    centre: YELLOW_CENTRE,
                    radius: YELLOW_RADIUS,
                },
                material: matte(YELLOW),
            },
        ];
        Self {
            objects,
            key: key_light(),
            fill: Vec3::new(-0.6, 0.55, 0.45).normalize(),
        }
    }

    /// The nearest surface along `origin + t · direction` with `t > 0`.
    fn intersect(&self, origin: Vec3, direction: Vec3) -> Option<Hit> {
        let mut nearest: Option<Hit> = None;
        for (index, object) in self.objects.iter().enumerate() {
            let limit = nearest.as_ref().map_or(f32::INFINITY, |h| h.t);
            if let Some((t, normal)) = intersect_shape(&object.shape, origin, direction, limit) {
                nearest = Some(Hit {
                    t,
                    normal,
                    object: index,
                });
            }
        }
        nearest
    }

    /// Whether anything lies along `origin + t · direction` for `t > 0`.
    fn occluded(&self, origin: Vec3, direction: Vec3) -> bool {
        self.objects
            .iter()
            .any(|o| intersect_shape(&o.shape, origin, direction, f32::INFINITY).is_some())
    }

    /// The colour seen along a camera ray, or `None` when it hits nothing.
    fn trace(&self, origin: Vec3, direction: Vec3) -> Option<Vec3> {
        if !hits_sphere(origin, direction, Vec3::ZERO, CONTENT_RADIUS) {
            return None;
        }
        self.shade(origin, direction, true)
    }

    fn shade(&self, origin: Vec3, direction: Vec3, allow_reflection: bool) -> Option<Vec3> {
        let hit = self.intersect(origin, direction)?;
        let point = origin + hit.t * direction;
        let n = hit.normal;
        let material = self.objects[hit.object].material;
        let base = match material.pigment {
            Pigment::Solid(colour) => colour,
            Pigment::Checker { light, dark, rim } => {
                if n.z > 0.5 {
                    let cell = (point.x / CHECKER_SIZE).floor() + (point.y / CHECKER_SIZE).floor();
                    if cell.rem_euclid(2.0) < 0.5 {
                        light
                    } else {
                        dark
                    }
                } else {
                    rim
                }
            }
        };
        let lift = point + SURFACE_EPSILON * n;
        let key_cos = n.dot(self.key).max(0.0);
        // Hard shadows from the key light only: the fill light stands in for
        // light bounced around a room, which casts none.
        let key_visible = if key_cos > 0.0 && !self.occluded(lift, self.key) {
            1.0
        } else {
            0.0
        };
        let light = AMBIENT
            + KEY_INTENSITY * key_cos * key_visible
            + FILL_INTENSITY * n.dot(self.fill).max(0.0);
        let diffuse = base * light;
        if !material.glossy {
            return Some(diffuse.min(Vec3::ONE));
        }
        let to_eye = -direction;
        let cos_view = n.dot(to_eye).clamp(0.0, 1.0);
        let halfway = (self.key + to_eye).normalize();
        let highlight = SPECULAR_STRENGTH
            * KEY_INTENSITY
            * key_visible
            * n.dot(halfway).max(0.0).powf(SHININESS);
        let fresnel = FRESNEL_BASE + (1.0 - FRESNEL_BASE) * (1.0 - cos_view).powi(5);
        let mirrored = direction - 2.0 * direction.dot(n) * n;
        // One bounce is exact here: the only glossy object is convex, so
        // its reflections never see it again.
        let reflected = if allow_reflection {
            self.shade(lift, mirrored, false)
                .unwrap_or_else(|| environment(mirrored))
        } else {
            environment(mirrored)
        };
        let colour = diffuse * (1.0 - fresnel) + reflected * fresnel + Vec3::splat(highlight);
        Some(colour.clamp(Vec3::ZERO, Vec3::ONE))
    }
}

/// Unit vector towards the key light: high on the -y side, so the shadows
/// fall back and to the left in the front views.
fn key_light() -> Vec3 {
    let (elevation, azimuth) = (50f32.to_radians(), (-60f32).to_radians());
    Vec3::new(
        elevation.cos() * azimuth.cos(),
        elevation.cos() * azimuth.sin(),
        elevation.sin(),
    )
}

/// What the glossy ball reflects where it sees no object: a pale sky above
/// the horizon and a grey floor below. The background stays transparent;
/// this only gives the reflection something to show.
fn environment(direction: Vec3) -> Vec3 {
    let horizon = Vec3::new(0.8, 0.8, 0.82);
    if direction.z >= 0.0 {
        let zenith = Vec3::new(0.45, 0.6, 0.85);
        horizon.lerp(zenith, direction.z.sqrt())
    } else {
        horizon.lerp(Vec3::splat(0.3), (-direction.z).sqrt())
    }
}

fn hits_sphere(origin: Vec3, direction: Vec3, centre: Vec3, radius: f32) -> bool {
    let oc = origin - centre;
    let b = oc.dot(direction);
    let c = oc.length_squared() - radius * radius;
    // Outside and moving away, or passing wide of it.
    !(c > 0.0 && b > 0.0) && b * b - c >= 0.0
}

/// Distance from `point` to the nearest surface of the demo's objects (the
/// stand and the four primitives), in world units: exact outside the
/// objects, and a lower bound inside them where they overlap. The tests of
/// meshes and point clouds measure against it.
pub fn surface_distance(point: Vec3) -> f32 {
    World::new()
        .objects
        .iter()
        .map(|o| signed_distance(&o.shape, point))
        .fold(f32::INFINITY, f32::min)
        .abs()
}

/// The signed distance from `point` to `shape` (negative inside).
fn signed_distance(shape: &Shape, point: Vec3) -> f32 {
    // A box of half sides `half` centred at the origin.
    let box_distance = |p: Vec3, half: Vec3| {
        let q = p.abs() - half;
        q.max(Vec3::ZERO).length() + q.max_element().min(0.0)
    };
    match *shape {
        Shape::Sphere { centre, radius } => (point - centre).length() - radius,
        Shape::Block {
            centre,
            half,
            cos,
            sin,
        } => {
            let v = point - centre;
            box_distance(
                Vec3::new(cos * v.x + sin * v.y, -sin * v.x + cos * v.y, v.z),
                half,
            )
        }
        Shape::Cylinder {
            bottom,
            radius,
            height,
        } => {
            let v = point - bottom;
            let radial = (v.x * v.x + v.y * v.y).sqrt() - radius;
            let axial = (v.z - 0.5 * height).abs() - 0.5 * height;
            let q = glam::Vec2::new(radial, axial);
            q.max(glam::Vec2::ZERO).length() + q.max_element().min(0.0)
        }
    }
}

/// The nearest entry of a ray into a shape with `0 < t < limit`, and the
/// outward unit normal there. Rays never start inside a solid (secondary rays
/// are lifted off the surface), so only entries from outside matter.
fn intersect_shape(
    shape: &Shape,
    origin: Vec3,
    direction: Vec3,
    limit: f32,
) -> Option<(f32, Vec3)> {
    match *shape {
        Shape::Sphere { centre, radius } => {
            let oc = origin - centre;
            let b = oc.dot(direction);
            let c = oc.length_squared() - radius * radius;
            let discriminant = b * b - c;
            if discriminant < 0.0 {
                return None;
            }
            let t = -b - discriminant.sqrt();
            (t > 0.0 && t < limit).then(|| (t, (oc + t * direction) / radius))
        }
        Shape::Block {
            centre,
            half,
            cos,
            sin,
        } => {
            // Into the box's own frame, where it is axis-aligned.
            let to_local = |v: Vec3| Vec3::new(cos * v.x + sin * v.y, -sin * v.x + cos * v.y, v.z);
            let o = to_local(origin - centre);
            let d = to_local(direction);
            let mut t_enter = f32::NEG_INFINITY;
            let mut t_exit = f32::INFINITY;
            let mut enter_axis = 0;
            for axis in 0..3 {
                if d[axis] == 0.0 {
                    if o[axis].abs() > half[axis] {
                        return None;
                    }
                    continue;
                }
                let t0 = (-half[axis] - o[axis]) / d[axis];
                let t1 = (half[axis] - o[axis]) / d[axis];
                let (near, far) = if t0 < t1 { (t0, t1) } else { (t1, t0) };
                if near > t_enter {
                    t_enter = near;
                    enter_axis = axis;
                }
                t_exit = t_exit.min(far);
            }
            if t_enter > t_exit || t_enter <= 0.0 || t_enter >= limit {
                return None;
            }
            let mut local_normal = Vec3::ZERO;
            local_normal[enter_axis] = -d[enter_axis].signum();
            let normal = Vec3::new(
                cos * local_normal.x - sin * local_normal.y,
                sin * local_normal.x + cos * local_normal.y,
                local_normal.z,
            );
            Some((t_enter, normal))
        }
        Shape::Cylinder {
            bottom,
            radius,
            height,
        } => {
            let o = origin - bottom;
            let mut best: Option<(f32, Vec3)> = None;
            let mut consider = |t: f32, normal: Vec3| {
                if t > 0.0 && t < best.map_or(limit, |b| b.0) {
                    best = Some((t, normal));
                }
            };
            // The curved side, as a circle in the xy plane.
            let a = direction.x * direction.x + direction.y * direction.y;
            if a > 0.0 {
                let b = o.x * direction.x + o.y * direction.y;
                let c = o.x * o.x + o.y * o.y - radius * radius;
                let discriminant = b * b - a * c;
                if discriminant >= 0.0 {
                    let t = (-b - discriminant.sqrt()) / a;
                    let z = o.z + t * direction.z;
                    if (0.0..=height).contains(&z) {
                        let p = o + t * direction;
                        consider(t, Vec3::new(p.x, p.y, 0.0) / radius);
                    }
                }
            }
            // The caps: whichever one the ray meets inside the circle.
            if direction.z != 0.0 {
                for (z, normal) in [(height, Vec3::Z), (0.0, -Vec3::Z)] {
                    // Only a cap that faces the ray can be an entry.
                    if normal.z * direction.z >= 0.0 {
                        continue;
                    }
                    let t = (z - o.z) / direction.z;
                    let p = o + t * direction;
                    if p.x * p.x + p.y * p.y <= radius * radius {
                        consider(t, normal);
                    }
                }
            }
            best
        }
    }
}

mod appearance;
mod moving;
#[cfg(test)]
mod tests;
mod unbounded;

pub use appearance::{
    APPEARANCE_TRUTH_FILE, AppearanceJitter, AppearanceTruth, ViewAppearance, apply_appearance,
    build_appearance_jitter, write_appearance_jitter,
};
pub use moving::{
    MOVING_PLACES, MOVING_RADIUS, build_moving_object, moving_object_centre, write_moving_object,
};

pub use unbounded::{
    UNBOUNDED_AABB_SCALE, build_unbounded, render_view_unbounded, unbounded_depth,
    unbounded_split_cameras, write_unbounded,
};
