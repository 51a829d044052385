//! COLMAP sparse models: `cameras`, `images` and (optionally) `points3D`,
//! each as `.bin` or `.txt`, in `sparse/0/`, `sparse/` or the folder
//! itself, with the photographs in `images/`.
//!
//! The formats are COLMAP's documented ones ("Output format" in the COLMAP
//! documentation): a text line per camera `CAMERA_ID MODEL WIDTH HEIGHT
//! PARAMS...`, two lines per image `IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID
//! NAME` and its 2-D points, a line per point `POINT3D_ID X Y Z R G B ERROR
//! TRACK...`; the binary files hold the same fields little-endian, each
//! list preceded by its length as a u64.
//!
//! Poses: COLMAP stores world-to-camera rotations (a unit quaternion, w
//! first) and translations in OpenCV camera axes (x right, y down, z
//! forward). zrak's camera-to-world is the inverse with the camera's y and
//! z axes negated (OpenGL axes). The scene is then moved and scaled (never
//! rotated) as instant-ngp's `colmap2nerf.py` does for the same reason: its
//! centre goes to the origin and the cameras to a mean distance of
//! [`CAMERA_DISTANCE`] from it, so that the default unit-cube mapping
//! (scale 0.33, offset 0.5) holds the scene; `aabb_scale` is chosen from
//! where the cameras and the sparse points are (see [`choose_aabb_scale`]).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use glam::{DMat3, DQuat, DVec3, Mat4, Vec4};
use serde_json::{Value, json};

use super::error::{SceneError, SceneResult, shown};
use super::pose::{FrameSource, check_downscale, decode_images};
use super::{
    Frame, LoadOptions, Scene, SceneFormat, SpaceAnalysis, SparsePoints, UnitCubeMapping,
    folder_name, space,
};
use crate::scene::{Camera, Intrinsics, Lens};

mod files;

use files::*;
pub use files::{write_binary, write_text};

/// The mean distance of the cameras from the scene centre after
/// normalisation: 4, the distance the NeRF-synthetic cameras keep and that
/// instant-ngp's `colmap2nerf.py` scales COLMAP scenes to.
pub const CAMERA_DISTANCE: f64 = 4.0;

/// The share of sparse points the chosen `aabb_scale` must hold (the rest
/// are the far, noisy tail: sky and distant walls).
pub const POINT_SHARE_IN_BOX: f64 = 0.95;

/// instant-ngp's largest `aabb_scale` (its cascades stop at 128).
pub const MAX_AABB_SCALE: f32 = 128.0;

/// Without explicit splits, every `VAL_EVERY`-th image (sorted by name) is
/// held out, as for instant-ngp files ([`super::instant_ngp::VAL_EVERY`]).
pub const VAL_EVERY: usize = super::instant_ngp::VAL_EVERY;

/// One COLMAP camera.
#[derive(Debug, Clone, PartialEq)]
pub struct ColmapCamera {
    pub id: u32,
    /// COLMAP's model name, e.g. `OPENCV`.
    pub model: String,
    pub width: u64,
    pub height: u64,
    pub params: Vec<f64>,
}

/// One registered image.
#[derive(Debug, Clone, PartialEq)]
pub struct ColmapImage {
    pub id: u32,
    /// World-to-camera rotation, (w, x, y, z).
    pub rotation: [f64; 4],
    /// World-to-camera translation.
    pub translation: [f64; 3],
    pub camera_id: u32,
    /// The file name within `images/`.
    pub name: String,
}

/// A sparse model as read.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ColmapModel {
    pub cameras: BTreeMap<u32, ColmapCamera>,
    pub images: Vec<ColmapImage>,
    /// Positions of the sparse points (empty when the file is absent).
    pub points: Vec<[f64; 3]>,
}

/// COLMAP's camera models (`src/colmap/sensor/models.h`): id, name and
/// parameter count.
const MODELS: [(i32, &str, usize); 11] = [
    (0, "SIMPLE_PINHOLE", 3),
    (1, "PINHOLE", 4),
    (2, "SIMPLE_RADIAL", 4),
    (3, "RADIAL", 5),
    (4, "OPENCV", 8),
    (5, "OPENCV_FISHEYE", 8),
    (6, "FULL_OPENCV", 12),
    (7, "FOV", 5),
    (8, "SIMPLE_RADIAL_FISHEYE", 4),
    (9, "RADIAL_FISHEYE", 5),
    (10, "THIN_PRISM_FISHEYE", 12),
];

fn model_by_name(name: &str) -> Option<(i32, &'static str, usize)> {
    MODELS.iter().copied().find(|(_, n, _)| *n == name)
}

fn model_by_id(id: i32) -> Option<(i32, &'static str, usize)> {
    MODELS.iter().copied().find(|(i, _, _)| *i == id)
}

impl ColmapCamera {
    /// zrak's intrinsics and lens for this camera. COLMAP's pixel
    /// coordinates put the centre of the top-left pixel at (0.5, 0.5), as
    /// zrak's do, so the principal point carries over unchanged.
    pub fn intrinsics(&self) -> Result<Intrinsics, String> {
        let p = &self.params;
        let zero = 0.0;
        // (fx, fy, cx, cy, lens) per model.
        let (fx, fy, cx, cy, lens) = match self.model.as_str() {
            "SIMPLE_PINHOLE" => (p[0], p[0], p[1], p[2], Lens::Pinhole),
            "PINHOLE" => (p[0], p[1], p[2], p[3], Lens::Pinhole),
            "SIMPLE_RADIAL" => (p[0], p[0], p[1], p[2], radial(p[3], zero, zero, zero)),
            "RADIAL" => (p[0], p[0], p[1], p[2], radial(p[3], p[4], zero, zero)),
            "OPENCV" => (p[0], p[1], p[2], p[3], radial(p[4], p[5], p[6], p[7])),
            "FULL_OPENCV" => {
                // k4..k6 are OpenCV's rational denominator, which zrak's
                // lens (and instant-ngp's) does not have.
                if p[9..12].iter().any(|&k| k != 0.0) {
                    return Err(format!(
                        "camera {}: FULL_OPENCV with rational terms k4 k5 k6 = {:?} is not \
                         supported (only k1 k2 p1 p2 k3)",
                        self.id,
                        &p[9..12]
                    ));
                }
                let lens = Lens::RadialTangential {
                    k1: p[4] as f32,
                    k2: p[5] as f32,
                    k3: p[8] as f32,
                    k4: 0.0,
                    p1: p[6] as f32,
                    p2: p[7] as f32,
                };
                (p[0], p[1], p[2], p[3], lens)
            }
            "OPENCV_FISHEYE" => (p[0], p[1], p[2], p[3], fisheye(p[4], p[5], p[6], p[7])),
            "SIMPLE_RADIAL_FISHEYE" => (p[0], p[0], p[1], p[2], fisheye(p[3], zero, zero, zero)),
            "RADIAL_FISHEYE" => (p[0], p[0], p[1], p[2], fisheye(p[3], p[4], zero, zero)),
            other => {
                return Err(format!(
                    "camera {}: COLMAP camera model {other} is not supported (zrak reads \
                     SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV, \
                     OPENCV_FISHEYE, SIMPLE_RADIAL_FISHEYE, RADIAL_FISHEYE)",
                    self.id
                ));
            }
        };
        // Positive and finite as the f32 the cameras keep: 1e-300 is a
        // positive f64 but 0 as an f32.
        let usable = |f: f64| (f as f32) > 0.0 && (f as f32).is_finite();
        if !(usable(fx) && usable(fy)) {
            return Err(format!(
                "camera {}: focal lengths {fx}, {fy} must be positive and finite in single \
                 precision",
                self.id
            ));
        }
        // Finite as the f32 the cameras keep, not only as read: 1e308 is a
        // finite f64 but an infinite f32.
        if p.iter().any(|&v| !(v as f32).is_finite()) {
            return Err(format!(
                "camera {}: parameters {p:?} are not finite in single precision",
                self.id
            ));
        }
        let size = |v: u64, what: &str| -> Result<u32, String> {
            u32::try_from(v)
                .ok()
                .filter(|&v| v > 0)
                .ok_or_else(|| format!("camera {}: {what} {v} is not a usable size", self.id))
        };
        let lens = if lens.is_pinhole() {
            Lens::Pinhole
        } else {
            lens
        };
        Ok(Intrinsics {
            width: size(self.width, "width")?,
            height: size(self.height, "height")?,
            fx: fx as f32,
            fy: fy as f32,
            cx: cx as f32,
            cy: cy as f32,
            lens,
        })
    }
}

fn radial(k1: f64, k2: f64, p1: f64, p2: f64) -> Lens {
    Lens::RadialTangential {
        k1: k1 as f32,
        k2: k2 as f32,
        k3: 0.0,
        k4: 0.0,
        p1: p1 as f32,
        p2: p2 as f32,
    }
}

fn fisheye(k1: f64, k2: f64, k3: f64, k4: f64) -> Lens {
    Lens::Fisheye {
        k1: k1 as f32,
        k2: k2 as f32,
        k3: k3 as f32,
        k4: k4 as f32,
    }
}

impl ColmapImage {
    /// Camera-to-world in COLMAP's world, OpenGL camera axes, in f64.
    pub fn camera_to_world(&self) -> (DMat3, DVec3) {
        let [w, x, y, z] = self.rotation;
        let world_to_camera = DMat3::from_quat(DQuat::from_xyzw(x, y, z, w).normalize());
        let rotation = world_to_camera.transpose();
        let position = -(rotation * DVec3::from_array(self.translation));
        // OpenCV camera axes (y down, z forward) to OpenGL (y up, z back).
        let rotation = DMat3::from_cols(rotation.x_axis, -rotation.y_axis, -rotation.z_axis);
        (rotation, position)
    }

    /// The inverse of [`Self::camera_to_world`]: an image from a zrak pose
    /// (OpenGL axes), for writing models.
    pub fn from_camera_to_world(
        id: u32,
        camera_id: u32,
        name: &str,
        camera_to_world: Mat4,
    ) -> Self {
        let m = camera_to_world.as_dmat4();
        let rotation = DMat3::from_cols(
            m.x_axis.truncate(),
            -m.y_axis.truncate(),
            -m.z_axis.truncate(),
        );
        let world_to_camera = rotation.transpose();
        let translation = -(world_to_camera * m.w_axis.truncate());
        let q = DQuat::from_mat3(&world_to_camera).normalize();
        Self {
            id,
            rotation: [q.w, q.x, q.y, q.z],
            translation: translation.to_array(),
            camera_id,
            name: name.to_owned(),
        }
    }
}

/// The folder holding the model files under `root`, if any: `sparse/0`,
/// `sparse` or `root` itself, the first with both a cameras and an images
/// file.
pub fn find_model_folder(root: &Path) -> Option<PathBuf> {
    [
        root.join("sparse").join("0"),
        root.join("sparse"),
        root.to_path_buf(),
    ]
    .into_iter()
    .find(|dir| {
        let has = |stem: &str| {
            dir.join(format!("{stem}.bin")).is_file() || dir.join(format!("{stem}.txt")).is_file()
        };
        has("cameras") && has("images")
    })
}

/// Whether `root` holds a COLMAP model.
pub fn is_colmap_folder(root: &Path) -> bool {
    find_model_folder(root).is_some()
}

/// Reads the model in `folder` (binary files preferred when both forms are
/// present, as COLMAP writes binary by default).
pub fn read_model(folder: &Path) -> SceneResult<ColmapModel> {
    let pick = |stem: &str| -> Option<(PathBuf, bool)> {
        let bin = folder.join(format!("{stem}.bin"));
        let txt = folder.join(format!("{stem}.txt"));
        if bin.is_file() {
            Some((bin, true))
        } else if txt.is_file() {
            Some((txt, false))
        } else {
            None
        }
    };
    let missing = |stem: &str| {
        SceneError::not_a_scene(
            folder,
            format!("no {stem}.bin or {stem}.txt: not a COLMAP sparse model"),
        )
    };
    let (cameras_path, binary) = pick("cameras").ok_or_else(|| missing("cameras"))?;
    let bytes_or_text = |path: &Path| {
        std::fs::read(path).map_err(|e| SceneError::unreadable(path, format!("cannot read: {e}")))
    };
    let data = bytes_or_text(&cameras_path)?;
    let cameras = if binary {
        read_cameras_binary(&data)
    } else {
        read_cameras_text(&as_text(&data))
    }
    .map_err(|p| SceneError::new(&cameras_path, p))?;
    let (images_path, binary) = pick("images").ok_or_else(|| missing("images"))?;
    let data = bytes_or_text(&images_path)?;
    let images = if binary {
        read_images_binary(&data)
    } else {
        read_images_text(&as_text(&data))
    }
    .map_err(|p| SceneError::new(&images_path, p))?;
    let points = match pick("points3D") {
        None => Vec::new(),
        Some((path, binary)) => {
            let data = bytes_or_text(&path)?;
            if binary {
                read_points_binary(&data)
            } else {
                read_points_text(&as_text(&data))
            }
            .map_err(|p| SceneError::new(&path, p))?
        }
    };
    for image in &images {
        if !cameras.contains_key(&image.camera_id) {
            return Err(SceneError::new(
                &images_path,
                format!(
                    "image {} ({}) names camera {}, which {} does not define",
                    image.id,
                    image.name,
                    image.camera_id,
                    cameras_path.display()
                ),
            ));
        }
    }
    Ok(ColmapModel {
        cameras,
        images,
        points,
    })
}

/// A registered image in zrak's terms, before its photograph is read.
#[derive(Debug, Clone)]
pub struct PosedImage {
    pub name: String,
    pub image_path: PathBuf,
    /// Camera-to-world after normalisation, OpenGL axes.
    pub camera_to_world: Mat4,
    pub intrinsics: Intrinsics,
}

/// A model turned into zrak's frames: poses normalised, unit cube chosen.
#[derive(Debug, Clone)]
pub struct Converted {
    /// Sorted by image name.
    pub images: Vec<PosedImage>,
    pub unit_cube: UnitCubeMapping,
    /// The normalisation applied: zrak world = (COLMAP world − centre) ·
    /// scale.
    pub centre: DVec3,
    pub scale: f64,
    /// How far the sparse points lie from the cameras, in zrak world
    /// (`None` without points).
    pub sparse_points: Option<SparsePoints>,
}

/// Reads and converts the COLMAP model under `root` (see the module notes).
pub fn convert(root: &Path) -> SceneResult<Converted> {
    if !root.is_dir() {
        return Err(SceneError::new(
            root,
            crate::files::describe_not_a_folder(root),
        ));
    }
    let folder = find_model_folder(root).ok_or_else(|| {
        SceneError::new(
            root,
            "no COLMAP model: none of sparse/0, sparse or the folder itself holds \
             cameras.bin/.txt and images.bin/.txt",
        )
    })?;
    let model = read_model(&folder)?;
    let images_file = ["images.bin", "images.txt"]
        .iter()
        .map(|f| folder.join(f))
        .find(|p| p.is_file())
        .unwrap_or_else(|| folder.clone());
    if model.images.is_empty() {
        return Err(SceneError::new(&images_file, "no registered images"));
    }
    let mut images = model.images.clone();
    images.sort_by(|a, b| a.name.cmp(&b.name));
    let poses: Vec<(DMat3, DVec3)> = images.iter().map(ColmapImage::camera_to_world).collect();
    let positions: Vec<DVec3> = poses.iter().map(|(_, p)| *p).collect();
    let forwards: Vec<DVec3> = poses.iter().map(|(r, _)| -r.z_axis).collect();
    let points: Vec<DVec3> = model.points.iter().map(|p| DVec3::from_array(*p)).collect();
    let centre = scene_centre(&positions, &forwards, &points);
    let mean_distance =
        positions.iter().map(|p| p.distance(centre)).sum::<f64>() / positions.len() as f64;
    let scale = if mean_distance > 1e-12 && mean_distance.is_finite() {
        CAMERA_DISTANCE / mean_distance
    } else {
        1.0
    };
    let to_zrak = |p: DVec3| (p - centre) * scale;
    let zrak_positions: Vec<DVec3> = positions.iter().map(|&p| to_zrak(p)).collect();
    let zrak_points: Vec<DVec3> = points.iter().map(|&p| to_zrak(p)).collect();
    let unit_cube = UnitCubeMapping {
        aabb_scale: choose_aabb_scale(
            &zrak_positions,
            &zrak_points,
            UnitCubeMapping::BLENDER.scale as f64,
        ),
        ..UnitCubeMapping::BLENDER
    };
    let image_folder = root.join("images");
    let cameras_file = ["cameras.bin", "cameras.txt"]
        .iter()
        .map(|f| folder.join(f))
        .find(|p| p.is_file())
        .unwrap_or_else(|| folder.clone());
    let mut posed = Vec::with_capacity(images.len());
    for (image, (rotation, position)) in images.iter().zip(&poses) {
        let camera = &model.cameras[&image.camera_id];
        let intrinsics = camera
            .intrinsics()
            .map_err(|p| SceneError::new(&cameras_file, p))?;
        let p = to_zrak(*position).as_vec3();
        let r = rotation.as_mat3();
        if !(p.is_finite() && r.is_finite()) {
            return Err(SceneError::new(
                &images_file,
                format!(
                    "image {} ({}): its pose (rotation {:?}, translation {:?}) is not finite \
                     in single precision once the scene is centred and scaled",
                    image.id, image.name, image.rotation, image.translation
                ),
            ));
        }
        posed.push(PosedImage {
            name: image.name.clone(),
            image_path: image_folder.join(&image.name),
            camera_to_world: Mat4::from_cols(
                r.x_axis.extend(0.0),
                r.y_axis.extend(0.0),
                r.z_axis.extend(0.0),
                Vec4::new(p.x, p.y, p.z, 1.0),
            ),
            intrinsics,
        });
    }
    Ok(Converted {
        images: posed,
        unit_cube,
        centre,
        scale,
        sparse_points: SparsePoints::measure(&zrak_points, &zrak_positions),
    })
}

/// The scene's centre: the per-axis median of the sparse points when there
/// are enough of them (robust to the far tail), else the point nearest to
/// every camera's optical axis in the least-squares sense (where the
/// cameras look), else the mean camera position (axes all parallel).
fn scene_centre(positions: &[DVec3], forwards: &[DVec3], points: &[DVec3]) -> DVec3 {
    const ENOUGH_POINTS: usize = 16;
    if points.len() >= ENOUGH_POINTS {
        let median = |axis: usize| {
            let mut values: Vec<f64> = points.iter().map(|p| p[axis]).collect();
            values.sort_by(f64::total_cmp);
            values[values.len() / 2]
        };
        return DVec3::new(median(0), median(1), median(2));
    }
    let mean = positions.iter().copied().sum::<DVec3>() / positions.len() as f64;
    // Σ (I − d dᵀ) p = Σ (I − d dᵀ) c over cameras c with unit axes d.
    let mut a = DMat3::ZERO;
    let mut b = DVec3::ZERO;
    for (&c, &d) in positions.iter().zip(forwards) {
        let d = d.normalize_or_zero();
        let projector = DMat3::IDENTITY - DMat3::from_cols(d * d.x, d * d.y, d * d.z);
        a += projector;
        b += projector * c;
    }
    // A well-conditioned system needs axes in at least two directions.
    if a.determinant().abs() > 1e-6 * positions.len().pow(3) as f64 {
        let centre = a.inverse() * b;
        if centre.is_finite() {
            return centre;
        }
    }
    mean
}

/// The smallest power of two (1 to [`MAX_AABB_SCALE`]) whose cube, in unit
/// coordinates at `unit_scale` world-to-unit, holds every camera and
/// [`POINT_SHARE_IN_BOX`] of the sparse points (all in zrak world,
/// centred). Without points, the cameras' box doubled: what they look at
/// lies around them.
pub fn choose_aabb_scale(cameras: &[DVec3], points: &[DVec3], unit_scale: f64) -> f32 {
    let reach = |p: &DVec3| p.abs().max_element();
    let camera_reach = cameras.iter().map(reach).fold(0.0, f64::max);
    let point_reach = if points.is_empty() {
        2.0 * camera_reach
    } else {
        let mut reaches: Vec<f64> = points.iter().map(reach).collect();
        reaches.sort_by(f64::total_cmp);
        let index = ((reaches.len() as f64 * POINT_SHARE_IN_BOX).ceil() as usize)
            .clamp(1, reaches.len())
            - 1;
        reaches[index]
    };
    // The cube of side aabb_scale around 0.5 reaches aabb_scale/2 unit
    // units, i.e. aabb_scale / (2 · unit_scale) world units, from the centre.
    let needed = 2.0 * unit_scale * camera_reach.max(point_reach);
    let mut aabb_scale = 1.0f32;
    while (aabb_scale as f64) < needed && aabb_scale < MAX_AABB_SCALE {
        aabb_scale *= 2.0;
    }
    aabb_scale
}

/// Loads a COLMAP folder as a scene: every [`VAL_EVERY`]-th image by name
/// held out for validation, the rest train.
pub fn load(root: &Path, options: LoadOptions) -> SceneResult<Scene> {
    check_downscale(root, options.downscale)?;
    let converted = convert(root)?;
    let model_file = find_model_folder(root).unwrap_or_else(|| root.to_path_buf());
    let sources: Vec<FrameSource> = converted
        .images
        .iter()
        .enumerate()
        .map(|(index, image)| FrameSource {
            json_path: model_file.clone(),
            index,
            image_path: image.image_path.clone(),
            camera_to_world: image.camera_to_world,
        })
        .collect();
    for (source, image) in sources.iter().zip(&converted.images) {
        if !source.image_path.is_file() {
            let name = crate::scene::escape_controls(&image.name);
            let path = &source.image_path;
            return Err(source.error(if crate::files::exists_at_all(path) {
                format!(
                    "image {name} ({}) is {}: put the photograph there",
                    shown(path),
                    super::pose::what_is_there(path)
                )
            } else {
                format!("image {name}: {}", super::pose::image_not_found(path, None))
            }));
        }
    }
    let decoded = decode_images(&sources, options.downscale)?;
    let mut scene = Scene {
        name: folder_name(root),
        root: root.to_path_buf(),
        format: SceneFormat::Colmap,
        train: Vec::new(),
        val: Vec::new(),
        test: Vec::new(),
        has_alpha: decoded.iter().any(|d| d.file_has_alpha),
        unit_cube: converted.unit_cube,
        bounds: converted.unit_cube.world_bounds(),
        smaller_training_views: 0,
        sparse_points: converted.sparse_points,
        space: SpaceAnalysis::default(),
        poses: crate::scene::PoseOrigin::estimated(
            "a COLMAP model: its cameras were estimated by structure from motion",
        ),
    };
    for (index, ((source, image), posed)) in sources
        .into_iter()
        .zip(decoded)
        .zip(&converted.images)
        .enumerate()
    {
        let k = posed.intrinsics;
        if (image.width, image.height) != (k.width, k.height) {
            return Err(source.error(format!(
                "image {} is {}×{}, but its COLMAP camera is {}×{}",
                source.image_path.display(),
                image.width,
                image.height,
                k.width,
                k.height
            )));
        }
        let frame = Frame {
            camera: Camera::new(k.downscaled(options.downscale), source.camera_to_world),
            image: image.image,
            image_path: source.image_path,
            mask: None,
        };
        if index % VAL_EVERY == 0 {
            scene.val.push(frame);
        } else {
            scene.train.push(frame);
        }
    }
    scene.space = space::analyse(&scene);
    Ok(scene)
}

/// The instant-ngp / nerfstudio `transforms.json` of a converted model,
/// with image paths relative to `out_folder` where they lie under it
/// (absolute otherwise), per-frame intrinsics and lens.
pub fn transforms_json(converted: &Converted, out_folder: &Path) -> Value {
    let frames: Vec<Value> = converted
        .images
        .iter()
        .map(|image| {
            let file_path = image
                .image_path
                .strip_prefix(out_folder)
                .map(|p| p.to_string_lossy().replace('\\', "/"))
                .unwrap_or_else(|_| image.image_path.to_string_lossy().into_owned());
            let m = image.camera_to_world;
            let rows: Vec<Value> = (0..4).map(|r| json!(m.row(r).to_array())).collect();
            let k = image.intrinsics;
            let mut frame = json!({
                "file_path": file_path,
                "transform_matrix": rows,
                "w": k.width, "h": k.height,
                "fl_x": k.fx, "fl_y": k.fy, "cx": k.cx, "cy": k.cy,
            });
            let object = frame.as_object_mut().expect("an object");
            match k.lens {
                Lens::Pinhole => {
                    object.insert("camera_model".into(), json!("OPENCV"));
                }
                Lens::RadialTangential {
                    k1,
                    k2,
                    k3,
                    k4,
                    p1,
                    p2,
                } => {
                    object.insert("camera_model".into(), json!("OPENCV"));
                    for (key, v) in [("k1", k1), ("k2", k2), ("k3", k3), ("k4", k4)] {
                        object.insert(key.into(), json!(v));
                    }
                    object.insert("p1".into(), json!(p1));
                    object.insert("p2".into(), json!(p2));
                }
                Lens::Fisheye { k1, k2, k3, k4 } => {
                    object.insert("camera_model".into(), json!("OPENCV_FISHEYE"));
                    object.insert("is_fisheye".into(), json!(true));
                    for (key, v) in [("k1", k1), ("k2", k2), ("k3", k3), ("k4", k4)] {
                        object.insert(key.into(), json!(v));
                    }
                }
            }
            frame
        })
        .collect();
    let m = converted.unit_cube;
    json!({
        "aabb_scale": m.aabb_scale,
        "scale": m.scale,
        "offset": m.offset.to_array(),
        "frames": frames,
    })
}

/// The camera positions of `scene` made into a COLMAP model with one
/// PINHOLE camera per distinct intrinsics (or the lens's model), images
/// named `name(i)`; for tests and for writing models from zrak scenes.
pub fn model_from_cameras(cameras: &[Camera], name: impl Fn(usize) -> String) -> ColmapModel {
    let mut model = ColmapModel::default();
    for (i, camera) in cameras.iter().enumerate() {
        let k = camera.intrinsics;
        let (fx, fy, cx, cy) = (k.fx as f64, k.fy as f64, k.cx as f64, k.cy as f64);
        let (model_name, params) = match k.lens {
            Lens::Pinhole => ("PINHOLE", vec![fx, fy, cx, cy]),
            Lens::RadialTangential { k1, k2, p1, p2, .. } => (
                "OPENCV",
                [fx, fy, cx, cy]
                    .into_iter()
                    .chain([k1, k2, p1, p2].map(f64::from))
                    .collect(),
            ),
            Lens::Fisheye { k1, k2, k3, k4 } => (
                "OPENCV_FISHEYE",
                [fx, fy, cx, cy]
                    .into_iter()
                    .chain([k1, k2, k3, k4].map(f64::from))
                    .collect(),
            ),
        };
        let existing = model
            .cameras
            .values()
            .find(|c| c.model == model_name && c.params == params)
            .map(|c| c.id);
        let camera_id = existing.unwrap_or_else(|| {
            let id = model.cameras.len() as u32 + 1;
            model.cameras.insert(
                id,
                ColmapCamera {
                    id,
                    model: model_name.into(),
                    width: k.width as u64,
                    height: k.height as u64,
                    params,
                },
            );
            id
        });
        model.images.push(ColmapImage::from_camera_to_world(
            i as u32 + 1,
            camera_id,
            &name(i),
            camera.camera_to_world,
        ));
    }
    model
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::Split;
    use crate::scene::demo::{DemoConfig, split_cameras};
    use crate::scene::pose::test_support::assert_mentions;

    fn demo_model() -> (Vec<Camera>, ColmapModel) {
        let config = DemoConfig {
            size: 16,
            ..DemoConfig::default()
        };
        let cameras = split_cameras(&config, Split::Train);
        let mut model = model_from_cameras(&cameras, |i| format!("view {i:03}.png"));
        // A few sparse points around the objects.
        model.points = (0..40)
            .map(|i| {
                let a = i as f64 * 0.7;
                [a.sin() * 0.8, a.cos() * 0.8, (i % 5) as f64 * 0.2 - 0.4]
            })
            .collect();
        (cameras, model)
    }

    fn assert_same_model(a: &ColmapModel, b: &ColmapModel) {
        assert_eq!(a.cameras, b.cameras);
        assert_eq!(a.images.len(), b.images.len());
        for (x, y) in a.images.iter().zip(&b.images) {
            assert_eq!((x.id, x.camera_id, &x.name), (y.id, y.camera_id, &y.name));
            for (p, q) in x.rotation.iter().zip(&y.rotation) {
                assert!((p - q).abs() < 1e-12);
            }
            for (p, q) in x.translation.iter().zip(&y.translation) {
                assert!((p - q).abs() < 1e-12);
            }
        }
        assert_eq!(a.points, b.points);
    }

    /// The demo's cameras written as a COLMAP model, text and binary, come
    /// back as the same cameras to 1e-5.
    #[test]
    fn text_and_binary_models_read_back_the_demo_cameras() {
        let (cameras, model) = demo_model();
        for binary in [false, true] {
            let dir = tempfile::tempdir().unwrap();
            let folder = dir.path().join("sparse/0");
            if binary {
                write_binary(&model, &folder).unwrap();
            } else {
                write_text(&model, &folder).unwrap();
            }
            let read = read_model(&folder).unwrap();
            assert_same_model(&read, &model);
            for (image, camera) in read.images.iter().zip(&cameras) {
                let (rotation, position) = image.camera_to_world();
                let want = camera.camera_to_world.as_dmat4();
                assert!((position - want.w_axis.truncate()).length() < 1e-5);
                for (got, want) in [
                    (rotation.x_axis, want.x_axis),
                    (rotation.y_axis, want.y_axis),
                    (rotation.z_axis, want.z_axis),
                ] {
                    assert!((got - want.truncate()).length() < 1e-5);
                }
                let k = read.cameras[&image.camera_id].intrinsics().unwrap();
                assert_eq!(k, camera.intrinsics);
            }
        }
    }

    /// Conversion recentres and rescales: the demo's cameras (4 from the
    /// origin) shifted and scaled by COLMAP come back where they were.
    #[test]
    fn conversion_undoes_a_shift_and_scale() {
        let (cameras, mut model) = demo_model();
        let (shift, factor) = (DVec3::new(3.0, -1.0, 0.5), 0.25);
        // COLMAP world = demo world · factor + shift.
        for (image, camera) in model.images.iter_mut().zip(&cameras) {
            let mut pose = camera.camera_to_world;
            let p = pose.w_axis.truncate().as_dvec3() * factor + shift;
            pose.w_axis = p.as_vec3().extend(1.0);
            *image =
                ColmapImage::from_camera_to_world(image.id, image.camera_id, &image.name, pose);
        }
        // Points symmetric about the demo's origin, so their median is it.
        model.points = (0..40)
            .map(|i| {
                let s = if i % 2 == 0 { 1.0 } else { -1.0 };
                let p = DVec3::new(0.3, -0.2, 0.1) * s * (1 + i / 2) as f64 / 20.0;
                (p * factor + shift).to_array()
            })
            .collect();
        let dir = tempfile::tempdir().unwrap();
        write_text(&model, &dir.path().join("sparse/0")).unwrap();
        let converted = convert(dir.path()).unwrap();
        assert!((converted.centre - shift).length() < 0.05 * factor);
        let mean_distance = cameras
            .iter()
            .map(|c| c.position().length() as f64)
            .sum::<f64>()
            / cameras.len() as f64;
        // Names sort in the cameras' order ("view 000.png", ...).
        for (posed, camera) in converted.images.iter().zip(&cameras) {
            let want = camera.position().as_dvec3() * CAMERA_DISTANCE / mean_distance;
            let got = posed.camera_to_world.w_axis.truncate().as_dvec3();
            assert!((got - want).length() < 0.05, "{got} vs {want}");
            assert!(
                posed
                    .camera_to_world
                    .abs_diff_eq(camera.camera_to_world, 0.05 + 1e-3 * 4.0)
                    || (got - want).length() < 0.05
            );
        }
        // Cameras 4 out: 2 · 0.33 · 4 = 2.6, so 4.
        assert_eq!(converted.unit_cube.aabb_scale, 4.0);
    }

    #[test]
    fn centre_without_points_is_where_the_cameras_look() {
        let (cameras, mut model) = demo_model();
        model.points.clear();
        let dir = tempfile::tempdir().unwrap();
        write_binary(&model, &dir.path().join("sparse/0")).unwrap();
        let converted = convert(dir.path()).unwrap();
        // The demo's cameras look at the origin.
        assert!(converted.centre.length() < 1e-3, "{}", converted.centre);
        assert_eq!(converted.images.len(), cameras.len());
    }

    #[test]
    fn bad_models_are_reported_with_the_file() {
        let (_, model) = demo_model();
        let dir = tempfile::tempdir().unwrap();
        let folder = dir.path().join("sparse/0");
        write_binary(&model, &folder).unwrap();
        // Truncated images.bin.
        let images = std::fs::read(folder.join("images.bin")).unwrap();
        std::fs::write(folder.join("images.bin"), &images[..images.len() - 5]).unwrap();
        let e = read_model(&folder).unwrap_err().to_string();
        assert_mentions(&e, &["images.bin", "the file ends"]);
        // A text camera with the wrong number of parameters.
        let dir = tempfile::tempdir().unwrap();
        let folder = dir.path().join("sparse");
        write_text(&model, &folder).unwrap();
        std::fs::write(folder.join("cameras.txt"), "1 OPENCV 16 16 10 10 8 8\n").unwrap();
        let e = read_model(&folder).unwrap_err().to_string();
        assert_mentions(
            &e,
            &["cameras.txt", "line 1", "OPENCV has 8 parameters, found 4"],
        );
        // An image naming a camera that does not exist.
        std::fs::write(folder.join("cameras.txt"), "7 PINHOLE 16 16 10 10 8 8\n").unwrap();
        let e = read_model(&folder).unwrap_err().to_string();
        assert_mentions(&e, &["images.txt", "names camera 1"]);
        // An unsupported model.
        let camera = ColmapCamera {
            id: 1,
            model: "FOV".into(),
            width: 4,
            height: 4,
            params: vec![1.0, 1.0, 2.0, 2.0, 0.1],
        };
        assert!(
            camera
                .intrinsics()
                .unwrap_err()
                .contains("FOV is not supported")
        );
        // A folder without images/.
        write_text(&model, &folder).unwrap();
        let e = load(dir.path(), LoadOptions::default())
            .unwrap_err()
            .to_string();
        assert_mentions(&e, &["not found"]);
    }

    #[test]
    fn aabb_scale_holds_cameras_and_most_points() {
        let cameras = [DVec3::new(4.0, 0.0, 0.0), DVec3::new(-4.0, 0.0, 0.0)];
        assert_eq!(choose_aabb_scale(&cameras, &[DVec3::ZERO; 20], 0.33), 4.0);
        // 95 % of points within 10: 2 · 0.33 · 10 = 6.6 → 8; a far tail
        // of 5 % does not count.
        let mut points = vec![DVec3::new(0.0, 10.0, 0.0); 95];
        points.extend([DVec3::new(0.0, 1000.0, 0.0); 5]);
        assert_eq!(choose_aabb_scale(&cameras, &points, 0.33), 8.0);
        let far = [DVec3::splat(1e6); 10];
        assert_eq!(choose_aabb_scale(&cameras, &far, 0.33), MAX_AABB_SCALE);
    }

    /// A COLMAP folder with its photographs loads as a scene, and the
    /// transforms.json `zrak convert` writes loads as the same scene.
    #[test]
    fn folder_loads_and_converts_to_the_same_scene() {
        let (cameras, model) = demo_model();
        let dir = tempfile::tempdir().unwrap();
        write_binary(&model, &dir.path().join("sparse/0")).unwrap();
        std::fs::create_dir_all(dir.path().join("images")).unwrap();
        for (i, camera) in cameras.iter().enumerate() {
            crate::scene::demo::render_view(camera)
                .save_png(&dir.path().join(format!("images/view {i:03}.png")))
                .unwrap();
        }
        let scene = Scene::load(dir.path(), LoadOptions::default()).unwrap();
        assert_eq!(scene.format, SceneFormat::Colmap);
        assert_eq!(scene.train.len() + scene.val.len(), cameras.len());
        assert_eq!(scene.val.len(), cameras.len().div_ceil(VAL_EVERY));

        let converted = convert(dir.path()).unwrap();
        let json = transforms_json(&converted, dir.path());
        let json_path = dir.path().join("transforms.json");
        std::fs::write(&json_path, serde_json::to_string(&json).unwrap()).unwrap();
        let from_json =
            crate::scene::instant_ngp::load(&json_path, LoadOptions::default()).unwrap();
        assert_eq!(from_json.unit_cube, scene.unit_cube);
        for (a, b) in scene.frames().zip(from_json.frames()) {
            assert_eq!(a.image_path, b.image_path);
            assert_eq!(a.camera.intrinsics, b.camera.intrinsics);
            assert!(
                a.camera
                    .camera_to_world
                    .abs_diff_eq(b.camera.camera_to_world, 1e-6)
            );
        }
    }
}
