//! The instant-ngp / nerfstudio layout: one `transforms.json` whose frames
//! carry a `file_path` and a camera-to-world `transform_matrix` (OpenGL axes,
//! as in NeRF-synthetic), with pinhole intrinsics at the top level, per
//! frame, or both (a frame's own value wins).
//!
//! Keys read: `fl_x`, `fl_y`, `camera_angle_x`, `camera_angle_y`, `cx`, `cy`,
//! `w`, `h`, the lens distortion `k1`..`k4`, `p1`, `p2` with the model
//! (nerfstudio's `camera_model`: `OPENCV` or `PINHOLE` radial-tangential,
//! `OPENCV_FISHEYE` fisheye; instant-ngp's `is_fisheye`), for the unit cube
//! `aabb_scale`, `scale`, `offset`, and nerfstudio's `train_filenames`,
//! `val_filenames`, `test_filenames`. Every camera key may be given at the
//! top level, per frame, or both. Equirectangular cameras are refused.
//! Masks ([`super::mask`]): a frame's nerfstudio `mask_path`, or else
//! instant-ngp's `dynamic_mask_<image stem>.png` beside its image.

use std::path::Path;

use glam::{Mat4, Vec3};
use serde_json::Value;

use super::camera::focal_from_fov;
use super::error::{SceneError, SceneResult};
use super::mask::{self, MaskConvention, MaskFile, PixelMask};
use super::pose::{
    DecodedImage, FrameSource, JsonObject, check_downscale, decode_images, describe, frame_object,
    number, parse_transform_matrix, read_json_object, required_array, required_str,
    resolve_image_path,
};
use super::{
    Frame, LoadOptions, Scene, SceneFormat, SpaceAnalysis, Split, UnitCubeMapping, folder_name,
    space,
};
use crate::scene::{Camera, Intrinsics, Lens};

/// The file this format lives in.
pub const FILE_NAME: &str = "transforms.json";

/// Without explicit splits, every `VAL_EVERY`-th frame (index 0, 8, 16, ...)
/// is held out for validation and the rest train; there is no test split.
/// This follows the hold-out used for LLFF and Mip-NeRF 360 scenes, which are
/// the captures this format usually carries.
pub const VAL_EVERY: usize = 8;

/// nerfstudio's explicit splits: lists of `file_path` values at the top level
/// of the file. When any is present, frames are assigned by name and frames
/// in no list are left out.
const SPLIT_KEYS: [(&str, Split); 3] = [
    ("train_filenames", Split::Train),
    ("val_filenames", Split::Val),
    ("test_filenames", Split::Test),
];

/// Lens distortion coefficients (OpenCV's radial k1..k4, tangential p1, p2),
/// in this order in [`CameraFields::distortion`].
const DISTORTION_KEYS: [&str; 6] = ["k1", "k2", "k3", "k4", "p1", "p2"];

/// Which lens model the coefficients belong to.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum LensModel {
    RadialTangential,
    Fisheye,
}

/// Loads a scene from a folder holding `transforms.json`, or from the JSON
/// file itself (nerfstudio sometimes names it otherwise). Image paths are
/// relative to the JSON file's folder.
pub fn load(path: &Path, options: LoadOptions) -> SceneResult<Scene> {
    check_downscale(path, options.downscale)?;
    let (folder, json_path) = if path.is_dir() {
        (path.to_path_buf(), path.join(FILE_NAME))
    } else {
        let folder = path
            .parent()
            .filter(|p| !p.as_os_str().is_empty())
            .unwrap_or(Path::new("."));
        (folder.to_path_buf(), path.to_path_buf())
    };
    let json = read_json_object(&json_path)?;
    let file_error = |problem: String| SceneError::new(&json_path, problem);
    let shared = CameraFields::read(&json).map_err(file_error)?;
    let unit_cube = unit_cube_mapping(&json).map_err(file_error)?;
    let frame_values = required_array(&json, "frames").map_err(file_error)?;
    if frame_values.is_empty() {
        return Err(file_error("no frames: `frames` is empty".into()));
    }

    let explicit = explicit_splits(&json, frame_values).map_err(file_error)?;

    let mut sources = Vec::with_capacity(frame_values.len());
    let mut cameras = Vec::with_capacity(frame_values.len());
    let mut splits = Vec::with_capacity(frame_values.len());
    let mut masks = Vec::with_capacity(frame_values.len());
    for (index, value) in frame_values.iter().enumerate() {
        let split = match &explicit {
            Some(assigned) => match assigned[index] {
                Some(split) => split,
                None => continue,
            },
            None if index % VAL_EVERY == 0 => Split::Val,
            None => Split::Train,
        };
        let (file_path, camera_to_world, camera) = read_frame(value, &shared)
            .map_err(|problem| SceneError::in_frame(&json_path, index, problem))?;
        let image_path = resolve_image_path(&folder, file_path).map_err(|e| {
            let problem = e.problem().to_string();
            e.in_frame_of(&json_path, index, problem)
        })?;
        let mask_file = read_mask_file(value, &folder, &image_path)
            .map_err(|problem| SceneError::in_frame(&json_path, index, problem))?;
        masks.push(mask_file);
        splits.push(split);
        sources.push(FrameSource {
            json_path: json_path.clone(),
            index,
            image_path,
            camera_to_world,
        });
        cameras.push(camera);
    }

    let decoded = decode_images(&sources, options.downscale)?;
    let masks = load_masks(&sources, &masks, &decoded, options.downscale)?;
    let has_alpha = decoded.iter().any(|d| d.file_has_alpha);
    let mut scene = Scene {
        name: folder_name(&folder),
        root: folder,
        format: SceneFormat::InstantNgp,
        train: Vec::new(),
        val: Vec::new(),
        test: Vec::new(),
        has_alpha,
        unit_cube,
        bounds: unit_cube.world_bounds(),
        smaller_training_views: 0,
        sparse_points: None,
        space: SpaceAnalysis::default(),
        poses: pose_origin(&json, frame_values, &sources, &cameras),
    };
    for ((((source, camera), image), split), mask) in sources
        .into_iter()
        .zip(cameras)
        .zip(decoded)
        .zip(splits)
        .zip(masks)
    {
        let intrinsics = camera
            .intrinsics(image.width, image.height)
            .map_err(|problem| source.error(problem))?
            .downscaled(options.downscale);
        let frame = Frame {
            camera: Camera::new(intrinsics, source.camera_to_world),
            image: image.image,
            image_path: source.image_path,
            mask,
        };
        match split {
            Split::Train => scene.train.push(frame),
            Split::Val => scene.val.push(frame),
            Split::Test => scene.test.push(frame),
        }
    }
    scene.space = space::analyse(&scene);
    Ok(scene)
}

/// Where a transforms.json's poses came from. The format carries both
/// renders (NeRF-synthetic's layout, Blender exports) and captures posed by
/// structure from motion; the tools that write the latter leave signs:
/// instant-ngp's colmap2nerf.py a per-frame `sharpness`, nerfstudio's
/// ns-process-data a per-frame `colmap_im_id` and a top-level
/// `applied_transform`, both the lens's distortion coefficients; and
/// photographs are JPEGs, renders seldom are.
fn pose_origin(
    json: &JsonObject,
    frames: &[Value],
    sources: &[FrameSource],
    cameras: &[CameraFields],
) -> super::PoseOrigin {
    let per_frame = |key: &str| frames.iter().filter(|f| f.get(key).is_some()).count();
    let mut signs = Vec::new();
    let sharpness = per_frame("sharpness");
    if sharpness > 0 {
        signs.push(format!(
            "{sharpness} frames carry colmap2nerf's `sharpness`"
        ));
    }
    let colmap_ids = per_frame("colmap_im_id");
    if colmap_ids > 0 {
        signs.push(format!(
            "{colmap_ids} frames carry nerfstudio's `colmap_im_id`"
        ));
    }
    if json.contains_key("applied_transform") {
        signs.push("it has nerfstudio's `applied_transform`".into());
    }
    if cameras
        .iter()
        .any(|c| c.distortion.iter().any(|k| k.is_some_and(|k| k != 0.0)))
    {
        signs.push("its cameras have lens distortion".into());
    }
    let jpegs = sources
        .iter()
        .filter(|s| {
            s.image_path
                .extension()
                .and_then(|e| e.to_str())
                .is_some_and(|e| e.eq_ignore_ascii_case("jpg") || e.eq_ignore_ascii_case("jpeg"))
        })
        .count();
    if jpegs * 2 > sources.len() {
        signs.push(format!("{jpegs} of {} images are JPEGs", sources.len()));
    }
    if signs.is_empty() {
        super::PoseOrigin::exact(
            "transforms.json without a sign of structure from motion (no lens distortion, \
             no colmap2nerf `sharpness`, no nerfstudio `colmap_im_id`, no JPEGs): its cameras \
             are taken as exact, as a render's",
        )
    } else {
        super::PoseOrigin::estimated(format!(
            "transforms.json posed by structure from motion: {}",
            signs.join("; ")
        ))
    }
}

/// A frame's mask file: nerfstudio's `mask_path` (relative to the JSON
/// file's folder) when the frame gives one, which must then be there;
/// otherwise instant-ngp's `dynamic_mask_<stem>.png` beside the image when
/// that exists.
fn read_mask_file(
    value: &Value,
    folder: &Path,
    image_path: &Path,
) -> Result<Option<MaskFile>, String> {
    if let Some(given) = value.get("mask_path") {
        let path = given
            .as_str()
            .ok_or_else(|| format!("`mask_path` must be a string, found {}", describe(given)))?;
        if path.contains('\0') {
            return Err(format!(
                "`mask_path` {path:?} holds a NUL character (\\0), which no file name can hold"
            ));
        }
        let relative = path.strip_prefix("./").unwrap_or(path);
        return Ok(Some(MaskFile {
            path: folder.join(relative),
            convention: MaskConvention::Keep,
        }));
    }
    Ok(mask::dynamic_mask_path(image_path)
        .filter(|path| crate::files::exists_at_all(path))
        .map(|path| MaskFile {
            path,
            convention: MaskConvention::Dynamic,
        }))
}

/// Reads every frame's mask that has one, in parallel, each checked
/// against its decoded image's size and downscaled as the image was; the
/// first bad mask in frame order is reported.
fn load_masks(
    sources: &[FrameSource],
    files: &[Option<MaskFile>],
    decoded: &[DecodedImage],
    downscale: u32,
) -> SceneResult<Vec<Option<PixelMask>>> {
    use rayon::prelude::*;
    let decodes_at_once = rayon::current_num_threads().min(sources.len()).max(1);
    let results: Vec<SceneResult<Option<PixelMask>>> = sources
        .par_iter()
        .zip(files)
        .zip(decoded)
        .map(|((source, file), image)| {
            file.as_ref()
                .map(|file| {
                    mask::load_mask(
                        file,
                        source,
                        (image.width, image.height),
                        downscale,
                        decodes_at_once,
                    )
                })
                .transpose()
        })
        .collect();
    results.into_iter().collect()
}

/// The split of each frame named by nerfstudio's `*_filenames` lists, or
/// `None` when the file has none. Every listed name must be a frame's
/// `file_path`, no frame may be in two lists, and something must train.
fn explicit_splits(
    json: &JsonObject,
    frames: &[Value],
) -> Result<Option<Vec<Option<Split>>>, String> {
    if SPLIT_KEYS.iter().all(|(key, _)| !json.contains_key(*key)) {
        return Ok(None);
    }
    let normalise = |path: &str| path.strip_prefix("./").unwrap_or(path).to_owned();
    let frame_paths: Vec<Option<String>> = frames
        .iter()
        .map(|frame| {
            frame
                .get("file_path")
                .and_then(Value::as_str)
                .map(normalise)
        })
        .collect();
    let mut assigned = vec![None; frames.len()];
    for (key, split) in SPLIT_KEYS {
        let Some(list) = json.get(key) else { continue };
        let names = list
            .as_array()
            .ok_or_else(|| format!("`{key}` must be an array, found {}", describe(list)))?;
        for name in names {
            let name = name
                .as_str()
                .ok_or_else(|| format!("`{key}` must list file paths, found {}", describe(name)))?;
            let wanted = normalise(name);
            let index = frame_paths
                .iter()
                .position(|path| path.as_deref() == Some(wanted.as_str()))
                .ok_or_else(|| format!("`{key}` names {name:?}, which no frame's file_path is"))?;
            match assigned[index] {
                Some(earlier) if earlier != split => {
                    return Err(format!(
                        "{name:?} is listed for both the {} and the {} split",
                        Split::name(earlier),
                        split.name()
                    ));
                }
                _ => assigned[index] = Some(split),
            }
        }
    }
    if !assigned.contains(&Some(Split::Train)) {
        return Err("`train_filenames` is missing or empty: no frame would train".into());
    }
    Ok(Some(assigned))
}

/// Reads one frame's `file_path` (resolved by the caller, last), pose and
/// camera (its own fields over the shared ones), checking all but what
/// needs the image.
fn read_frame<'a>(
    value: &'a Value,
    shared: &CameraFields,
) -> Result<(&'a str, Mat4, CameraFields), String> {
    let frame = frame_object(value)?;
    let file_path = required_str(frame, "file_path")?;
    let matrix = frame
        .get("transform_matrix")
        .ok_or_else(|| super::pose::missing_key("transform_matrix"))?;
    let camera_to_world = parse_transform_matrix(matrix)?;
    let camera = CameraFields::read(frame)?.or(shared);
    if camera.focal_x.is_none() && camera.focal_y.is_none() {
        return Err(
            "missing key `fl_x` (or `camera_angle_x`): the focal length is not given".into(),
        );
    }
    Ok((file_path, camera_to_world, camera))
}

/// A focal length as the file gives it: in pixels, or as a field of view
/// that becomes pixels once the image size is known.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Focal {
    Pixels(f64),
    Angle(f64),
}

impl Focal {
    /// Reads `fl_key` or, failing that, `angle_key`; both must give a
    /// positive, finite focal length.
    fn read(object: &JsonObject, fl_key: &str, angle_key: &str) -> Result<Option<Self>, String> {
        if let Some(fl) = number(object, fl_key)? {
            // Checked as the f32 it becomes: 1e-100 is positive as an f64
            // but a focal length of 0 as an f32.
            if !((fl as f32) > 0.0 && (fl as f32).is_finite()) {
                return Err(format!(
                    "focal length {fl_key} = {fl} must be positive and finite"
                ));
            }
            return Ok(Some(Focal::Pixels(fl)));
        }
        if let Some(angle) = number(object, angle_key)? {
            let unit_focal = focal_from_fov(1, angle as f32);
            if !(angle > 0.0
                && angle < std::f64::consts::PI
                && unit_focal > 0.0
                && unit_focal.is_finite())
            {
                return Err(format!(
                    "{angle_key} = {angle} does not give a positive, finite focal length: \
                     it must be an angle between 0 and π radians"
                ));
            }
            return Ok(Some(Focal::Angle(angle)));
        }
        Ok(None)
    }

    fn pixels(self, size: u32) -> f64 {
        match self {
            Focal::Pixels(fl) => fl,
            Focal::Angle(angle) => focal_from_fov(size, angle as f32) as f64,
        }
    }
}

/// The intrinsics one level of the file (top level or a frame) gives; absent
/// keys are `None` so that levels can be layered.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
struct CameraFields {
    width: Option<u32>,
    height: Option<u32>,
    focal_x: Option<Focal>,
    focal_y: Option<Focal>,
    cx: Option<f64>,
    cy: Option<f64>,
    distortion: [Option<f64>; 6],
    model: Option<LensModel>,
}

impl CameraFields {
    fn read(object: &JsonObject) -> Result<Self, String> {
        let model = lens_model(object)?;
        let mut distortion = [None; 6];
        for (slot, key) in distortion.iter_mut().zip(DISTORTION_KEYS) {
            *slot = match number(object, key)? {
                Some(v) if !(v as f32).is_finite() => {
                    return Err(format!("lens distortion `{key}` = {v} is not finite"));
                }
                v => v,
            };
        }
        let finite = |key: &str| -> Result<Option<f64>, String> {
            match number(object, key)? {
                Some(v) if !(v as f32).is_finite() => Err(format!("`{key}` = {v} is not finite")),
                v => Ok(v),
            }
        };
        Ok(Self {
            width: pixel_count(object, "w")?,
            height: pixel_count(object, "h")?,
            focal_x: Focal::read(object, "fl_x", "camera_angle_x")?,
            focal_y: Focal::read(object, "fl_y", "camera_angle_y")?,
            cx: finite("cx")?,
            cy: finite("cy")?,
            distortion,
            model,
        })
    }

    /// These fields where given, `fallback`'s elsewhere. A level that gives
    /// a focal length in either form overrides the other level's, whichever
    /// form that took.
    fn or(self, fallback: &Self) -> Self {
        Self {
            width: self.width.or(fallback.width),
            height: self.height.or(fallback.height),
            focal_x: self.focal_x.or(fallback.focal_x),
            focal_y: self.focal_y.or(fallback.focal_y),
            cx: self.cx.or(fallback.cx),
            cy: self.cy.or(fallback.cy),
            distortion: std::array::from_fn(|i| self.distortion[i].or(fallback.distortion[i])),
            model: self.model.or(fallback.model),
        }
    }

    /// The lens the coefficients and model describe: a fisheye when the
    /// model says so, otherwise radial-tangential when any coefficient is
    /// non-zero, otherwise a pinhole.
    fn lens(&self) -> Result<Lens, String> {
        let [k1, k2, k3, k4, p1, p2] = self.distortion.map(|c| c.unwrap_or(0.0) as f32);
        match self.model {
            Some(LensModel::Fisheye) => {
                if p1 != 0.0 || p2 != 0.0 {
                    return Err(format!(
                        "the fisheye model has no tangential terms, but p1 = {p1}, p2 = {p2}"
                    ));
                }
                Ok(Lens::Fisheye { k1, k2, k3, k4 })
            }
            _ => {
                let lens = Lens::RadialTangential {
                    k1,
                    k2,
                    k3,
                    k4,
                    p1,
                    p2,
                };
                Ok(if lens.is_pinhole() {
                    Lens::Pinhole
                } else {
                    lens
                })
            }
        }
    }

    /// The intrinsics for an image of `width`×`height` pixels (its size on
    /// disk). A `w` or `h` that disagrees with the image is an error: the
    /// focal length and principal point would be in the wrong units.
    fn intrinsics(&self, width: u32, height: u32) -> Result<Intrinsics, String> {
        if let Some(w) = self.width.filter(|&w| w != width) {
            return Err(format!("`w` = {w}, but the image is {width} pixels wide"));
        }
        if let Some(h) = self.height.filter(|&h| h != height) {
            return Err(format!("`h` = {h}, but the image is {height} pixels high"));
        }
        // instant-ngp's rule: one focal length given stands for both.
        let fx = self.focal_x.map(|f| f.pixels(width));
        let fy = self.focal_y.map(|f| f.pixels(height));
        let (Some(fx), Some(fy)) = (fx.or(fy), fy.or(fx)) else {
            return Err(
                "missing key `fl_x` (or `camera_angle_x`): the focal length is not given".into(),
            );
        };
        for (key, f) in [("fl_x", fx), ("fl_y", fy)] {
            if !((f as f32) > 0.0 && (f as f32).is_finite()) {
                return Err(format!(
                    "focal length {key} = {f} must be positive and finite"
                ));
            }
        }
        Ok(Intrinsics {
            width,
            height,
            fx: fx as f32,
            fy: fy as f32,
            cx: self.cx.unwrap_or(0.5 * width as f64) as f32,
            cy: self.cy.unwrap_or(0.5 * height as f64) as f32,
            lens: self.lens()?,
        })
    }
}

/// The lens model a level of the file names, if it names one: nerfstudio
/// writes `camera_model`, instant-ngp `is_fisheye`.
fn lens_model(object: &JsonObject) -> Result<Option<LensModel>, String> {
    let mut model = None;
    if let Some(value) = object.get("camera_model") {
        let name = value
            .as_str()
            .ok_or_else(|| format!("`camera_model` must be a string, found {}", describe(value)))?;
        model = Some(match name.to_ascii_uppercase().as_str() {
            // nerfstudio's names (its `CameraType` and COLMAP's models that
            // its converters write).
            "PINHOLE" | "SIMPLE_PINHOLE" | "OPENCV" | "PERSPECTIVE" | "SIMPLE_RADIAL"
            | "RADIAL" | "FULL_OPENCV" => LensModel::RadialTangential,
            "OPENCV_FISHEYE" | "FISHEYE" | "SIMPLE_RADIAL_FISHEYE" | "RADIAL_FISHEYE" => {
                LensModel::Fisheye
            }
            _ => {
                return Err(format!(
                    "camera model `{name}` is not supported: zrak reads PINHOLE, OPENCV and \
                     OPENCV_FISHEYE cameras"
                ));
            }
        });
    }
    match object.get("is_fisheye") {
        None => {}
        Some(Value::Bool(true)) => {
            if model == Some(LensModel::RadialTangential) {
                return Err(
                    "`is_fisheye` is true but `camera_model` names a non-fisheye model".into(),
                );
            }
            model = Some(LensModel::Fisheye);
        }
        Some(Value::Bool(false)) => {}
        Some(other) => {
            return Err(format!(
                "`is_fisheye` must be true or false, found {}",
                describe(other)
            ));
        }
    }
    Ok(model)
}

/// A width or height: a positive whole number (files often write 800.0).
fn pixel_count(object: &JsonObject, key: &str) -> Result<Option<u32>, String> {
    match number(object, key)? {
        None => Ok(None),
        Some(v) if v >= 1.0 && v.fract() == 0.0 && v <= u32::MAX as f64 => Ok(Some(v as u32)),
        Some(v) => Err(format!(
            "`{key}` = {v} must be a positive whole number of pixels"
        )),
    }
}

/// instant-ngp's mapping into the unit cube, with its defaults: `aabb_scale`
/// 1, `scale` 0.33, `offset` [0.5, 0.5, 0.5] (`src/nerf_loader.cu`).
fn unit_cube_mapping(json: &JsonObject) -> Result<UnitCubeMapping, String> {
    let defaults = UnitCubeMapping::BLENDER;
    let positive = |key: &str, default: f32| -> Result<f32, String> {
        match number(json, key)? {
            None => Ok(default),
            Some(v) if v > 0.0 && (v as f32).is_finite() => Ok(v as f32),
            Some(v) => Err(format!("`{key}` = {v} must be positive and finite")),
        }
    };
    let offset = match json.get("offset") {
        None => defaults.offset,
        Some(value) => {
            let entries: Option<Vec<f32>> = value.as_array().and_then(|a| {
                a.iter()
                    .map(|x| x.as_f64().map(|x| x as f32).filter(|x| x.is_finite()))
                    .collect()
            });
            match entries.as_deref() {
                Some(&[x, y, z]) => Vec3::new(x, y, z),
                _ => {
                    return Err(format!(
                        "`offset` must be an array of 3 finite numbers, found {value}"
                    ));
                }
            }
        }
    };
    let mapping = UnitCubeMapping {
        scale: positive("scale", defaults.scale)?,
        offset,
        aabb_scale: positive("aabb_scale", defaults.aabb_scale)?,
    };
    if mapping.aabb_scale > LARGEST_AABB_SCALE {
        return Err(format!(
            "`aabb_scale` = {} is more than {LARGEST_AABB_SCALE}, the largest box the \
             occupancy grid has cascades for (16; instant-ngp itself stops at 128)",
            mapping.aabb_scale
        ));
    }
    let bounds = mapping.world_bounds();
    if !(bounds.min.is_finite() && bounds.max.is_finite() && bounds.min.cmplt(bounds.max).all()) {
        return Err(format!(
            "`scale` = {} with `offset` {} and `aabb_scale` = {} puts the scene's box at \
             [{}, {}], which is not a finite box",
            mapping.scale, mapping.offset, mapping.aabb_scale, bounds.min, bounds.max
        ));
    }
    Ok(mapping)
}

/// The largest `aabb_scale` zrak takes: 2^15, a box the occupancy grid's
/// 16 cascades cover (each doubles the last).
pub const LARGEST_AABB_SCALE: f32 = 32768.0;

#[cfg(test)]
mod tests {
    use std::path::Path;

    use serde_json::json;

    use super::*;
    use crate::scene::pose::test_support::*;

    fn load_error(path: &Path) -> String {
        match load(path, LoadOptions::default()) {
            Ok(_) => panic!("loading {} should fail", path.display()),
            Err(e) => e.to_string(),
        }
    }

    /// A valid scene of `n` 8-bit RGBA 8×6 frames `images/f_{i}.png`, with the
    /// intrinsics at the top level; `edit` adjusts the JSON before it is
    /// written.
    fn write_scene(root: &Path, n: usize, edit: impl FnOnce(&mut Value)) {
        let frames: Vec<Value> = (0..n)
            .map(|i| {
                write_rgba_png(&root.join(format!("images/f_{i}.png")), 8, 6);
                json!({ "file_path": format!("images/f_{i}.png"), "transform_matrix": pose_json(i as f64, 0.0, 2.0) })
            })
            .collect();
        let mut value = json!({
            "fl_x": 10.0, "fl_y": 11.0, "cx": 4.5, "cy": 2.5, "w": 8, "h": 6,
            "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0,
            "camera_model": "OPENCV",
            "frames": frames,
        });
        edit(&mut value);
        write_json(&root.join(FILE_NAME), &value);
    }

    #[test]
    fn valid_scene_with_shared_and_per_frame_intrinsics() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path();
        write_scene(root, 10, |v| {
            v["aabb_scale"] = json!(4);
            v["scale"] = json!(0.5);
            v["offset"] = json!([0.5, 0.4, 0.3]);
            // Frame 3 has its own camera: focal from an angle, cx overridden.
            v["frames"][3]["camera_angle_x"] = json!(std::f64::consts::FRAC_PI_2);
            v["frames"][3]["cx"] = json!(3.0);
        });
        let scene = load(root, LoadOptions::default()).unwrap();
        assert_eq!(scene.format, SceneFormat::InstantNgp);
        // Frames 0 and 8 are held out.
        assert_eq!(
            (scene.train.len(), scene.val.len(), scene.test.len()),
            (8, 2, 0)
        );
        assert_eq!(scene.val[1].camera.position().x, 8.0);
        assert_eq!(scene.train[0].camera.position().x, 1.0);
        assert_eq!(scene.root, root);

        let shared = scene.train[0].camera.intrinsics;
        assert_eq!(
            (shared.fx, shared.fy, shared.cx, shared.cy),
            (10.0, 11.0, 4.5, 2.5)
        );
        // Frame 3 is train[2]: its fl from its angle (0.5·8/tan(π/4) = 4)
        // overrides the shared fl_x; fl_y and cy stay shared.
        let own = scene.train[2].camera.intrinsics;
        assert!((own.fx - 4.0).abs() < 1e-5, "{}", own.fx);
        assert_eq!((own.fy, own.cx, own.cy), (11.0, 3.0, 2.5));

        let mapping = scene.unit_cube;
        assert_eq!((mapping.scale, mapping.aabb_scale), (0.5, 4.0));
        assert_eq!(mapping.offset, Vec3::new(0.5, 0.4, 0.3));
        assert_eq!(scene.bounds, mapping.world_bounds());
        assert!(scene.has_alpha);
    }

    #[test]
    fn nerfstudio_split_lists_assign_frames_by_name() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path();
        write_scene(root, 6, |v| {
            v["train_filenames"] = json!(["images/f_1.png", "./images/f_2.png", "images/f_4.png"]);
            v["val_filenames"] = json!(["images/f_0.png"]);
            v["test_filenames"] = json!(["images/f_5.png"]);
            // Frame 3 is in no list: it is left out, and its image is not read.
            v["frames"][3]["file_path"] = json!("images/absent.png");
        });
        let scene = load(root, LoadOptions::default()).unwrap();
        let xs = |frames: &[Frame]| -> Vec<f32> {
            frames.iter().map(|f| f.camera.position().x).collect()
        };
        assert_eq!(xs(&scene.train), [1.0, 2.0, 4.0]);
        assert_eq!(xs(&scene.val), [0.0]);
        assert_eq!(xs(&scene.test), [5.0]);
    }

    #[test]
    fn nerfstudio_split_lists_are_checked() {
        let cases: [(Value, &str); 4] = [
            (
                json!({"train_filenames": ["images/f_9.png"]}),
                "`train_filenames` names \"images/f_9.png\", which no frame's file_path is",
            ),
            (
                json!({"train_filenames": ["images/f_0.png"], "val_filenames": ["images/f_0.png"]}),
                "listed for both the train and the val split",
            ),
            (
                json!({"val_filenames": ["images/f_0.png"]}),
                "no frame would train",
            ),
            (
                json!({"train_filenames": "images/f_0.png"}),
                "`train_filenames` must be an array",
            ),
        ];
        for (lists, expected) in cases {
            let dir = tempfile::tempdir().unwrap();
            write_scene(dir.path(), 3, |v| {
                for (key, value) in lists.as_object().unwrap() {
                    v[key] = value.clone();
                }
            });
            let error = load_error(dir.path());
            assert!(error.contains(expected), "{error}");
            assert!(error.contains(FILE_NAME), "{error}");
        }
    }

    #[test]
    fn defaults_when_keys_are_absent() {
        let dir = tempfile::tempdir().unwrap();
        write_scene(dir.path(), 2, |v| {
            let top = v.as_object_mut().unwrap();
            for key in ["fl_x", "fl_y", "cx", "cy", "w", "h"] {
                top.remove(key);
            }
            top.insert("camera_angle_x".into(), json!(std::f64::consts::FRAC_PI_2));
        });
        let scene = load(dir.path(), LoadOptions::default()).unwrap();
        let k = scene.val[0].camera.intrinsics;
        // Width from the image, fy = fx when only one is given, centre at
        // the image centre.
        assert_eq!((k.width, k.height), (8, 6));
        assert!((k.fx - 4.0).abs() < 1e-5 && k.fx == k.fy);
        assert_eq!((k.cx, k.cy), (4.0, 3.0));
        assert_eq!(scene.unit_cube, UnitCubeMapping::BLENDER);
    }

    #[test]
    fn sixteen_bit_png_and_jpeg_and_downscale() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path();
        write_scene(root, 3, |v| {
            v["frames"][1]["file_path"] = json!("images/deep.png");
            v["frames"][2]["file_path"] = json!("./images/photo.jpg");
        });
        image::ImageBuffer::<image::Rgb<u16>, Vec<u16>>::from_pixel(
            8,
            6,
            image::Rgb([65535, 0, 25700]),
        )
        .save(root.join("images/deep.png"))
        .unwrap();
        image::RgbImage::from_pixel(8, 6, image::Rgb([200, 100, 50]))
            .save(root.join("images/photo.jpg"))
            .unwrap();

        let scene = load(root, LoadOptions::default()).unwrap();
        let deep = &scene.train[0].image;
        assert_eq!(deep.data[..4], [255, 0, 100, 255]);
        let photo = &scene.train[1].image;
        for (got, want) in photo.data[..3].iter().zip([200, 100, 50]) {
            assert!(
                (*got as i32 - want).abs() <= 3,
                "JPEG pixel {:?}",
                &photo.data[..4]
            );
        }
        assert_eq!(photo.data[3], 255);

        let half = load(root, LoadOptions { downscale: 2 }).unwrap();
        assert_eq!(half.resolution(), Some((4, 3)));
        let (k, k2) = (
            scene.val[0].camera.intrinsics,
            half.val[0].camera.intrinsics,
        );
        assert_eq!(
            (k2.fx, k2.fy, k2.cx, k2.cy),
            (0.5 * k.fx, 0.5 * k.fy, 0.5 * k.cx, 0.5 * k.cy)
        );
        assert_eq!(half.train[0].image.data[..4], [255, 0, 100, 255]);
    }

    #[test]
    fn json_file_path_may_be_given() {
        let dir = tempfile::tempdir().unwrap();
        write_scene(dir.path(), 2, |_| {});
        std::fs::rename(dir.path().join(FILE_NAME), dir.path().join("other.json")).unwrap();
        let scene = load(&dir.path().join("other.json"), LoadOptions::default()).unwrap();
        assert_eq!(scene.frames().count(), 2);
        assert_eq!(scene.root, dir.path());
    }

    #[test]
    fn missing_transforms_file() {
        let dir = tempfile::tempdir().unwrap();
        let e = load_error(dir.path());
        assert_mentions(&e, &["transforms.json", "file not found"]);
    }

    #[test]
    fn negative_focal_length() {
        let dir = tempfile::tempdir().unwrap();
        write_scene(dir.path(), 2, |v| v["fl_x"] = json!(-5));
        let e = load_error(dir.path());
        assert_mentions(
            &e,
            &["transforms.json: focal length fl_x = -5 must be positive"],
        );
        // In a frame, the frame is named.
        write_scene(dir.path(), 2, |v| v["frames"][1]["fl_y"] = json!(0));
        let e = load_error(dir.path());
        assert_mentions(
            &e,
            &["transforms.json: frame 1: focal length fl_y = 0 must be positive"],
        );
    }

    #[test]
    fn camera_angle_out_of_range() {
        let dir = tempfile::tempdir().unwrap();
        write_scene(dir.path(), 2, |v| {
            v.as_object_mut().unwrap().remove("fl_x");
            v["camera_angle_x"] = json!(0);
        });
        assert_mentions(
            &load_error(dir.path()),
            &["camera_angle_x = 0", "focal length"],
        );
    }

    #[test]
    fn missing_focal_length() {
        let dir = tempfile::tempdir().unwrap();
        write_scene(dir.path(), 2, |v| {
            let top = v.as_object_mut().unwrap();
            top.remove("fl_x");
            top.remove("fl_y");
        });
        assert_mentions(&load_error(dir.path()), &["frame 0", "missing key `fl_x`"]);
    }

    #[test]
    fn lens_distortion_is_read_shared_and_per_frame() {
        let dir = tempfile::tempdir().unwrap();
        write_scene(dir.path(), 3, |v| {
            v["k1"] = json!(0.1);
            v["p2"] = json!(-0.002);
            // Frame 1 has its own lens: a fisheye (instant-ngp's flag).
            v["frames"][1]["is_fisheye"] = json!(true);
            v["frames"][1]["p2"] = json!(0);
            v["frames"][1]["k3"] = json!(0.01);
            // Frame 2 says pinhole in nerfstudio's words, with zeros.
            v["frames"][2]["camera_model"] = json!("PINHOLE");
            v["frames"][2]["k1"] = json!(0);
            v["frames"][2]["p2"] = json!(0);
        });
        let scene = load(dir.path(), LoadOptions::default()).unwrap();
        let lens = |f: &Frame| f.camera.intrinsics.lens;
        assert_eq!(
            lens(&scene.val[0]),
            Lens::RadialTangential {
                k1: 0.1,
                k2: 0.0,
                k3: 0.0,
                k4: 0.0,
                p1: 0.0,
                p2: -0.002
            }
        );
        assert_eq!(
            lens(&scene.train[0]),
            Lens::Fisheye {
                k1: 0.1,
                k2: 0.0,
                k3: 0.01,
                k4: 0.0
            }
        );
        assert_eq!(lens(&scene.train[1]), Lens::Pinhole);
        // Downscaling keeps the lens.
        let half = load(dir.path(), LoadOptions { downscale: 2 }).unwrap();
        assert_eq!(lens(&half.val[0]), lens(&scene.val[0]));
    }

    #[test]
    fn nerfstudio_fisheye_model() {
        let dir = tempfile::tempdir().unwrap();
        write_scene(dir.path(), 2, |v| {
            v["camera_model"] = json!("OPENCV_FISHEYE");
            v["k4"] = json!(0.003);
        });
        let scene = load(dir.path(), LoadOptions::default()).unwrap();
        assert_eq!(
            scene.val[0].camera.intrinsics.lens,
            Lens::Fisheye {
                k1: 0.0,
                k2: 0.0,
                k3: 0.0,
                k4: 0.003
            }
        );
    }

    #[test]
    fn unsupported_lenses_are_refused_clearly() {
        let dir = tempfile::tempdir().unwrap();
        write_scene(dir.path(), 2, |v| {
            v["camera_model"] = json!("EQUIRECTANGULAR")
        });
        assert_mentions(
            &load_error(dir.path()),
            &["transforms.json", "EQUIRECTANGULAR", "not supported"],
        );
        write_scene(dir.path(), 2, |v| {
            v["camera_model"] = json!("OPENCV_FISHEYE");
            v["frames"][1]["p1"] = json!(0.01);
        });
        assert_mentions(
            &load_error(dir.path()),
            &[
                "transforms.json: frame 1",
                "fisheye model has no tangential terms",
            ],
        );
        write_scene(dir.path(), 2, |v| v["is_fisheye"] = json!("yes"));
        assert_mentions(
            &load_error(dir.path()),
            &["`is_fisheye` must be true or false"],
        );
        write_scene(dir.path(), 2, |v| v["k2"] = json!("big"));
        assert_mentions(&load_error(dir.path()), &["`k2` must be a number"]);
    }

    #[test]
    fn size_in_json_must_match_image() {
        let dir = tempfile::tempdir().unwrap();
        write_scene(dir.path(), 2, |v| v["frames"][1]["w"] = json!(16));
        let e = load_error(dir.path());
        assert_mentions(
            &e,
            &["transforms.json: frame 1", "`w` = 16", "8 pixels wide"],
        );
    }

    #[test]
    fn zero_frames() {
        let dir = tempfile::tempdir().unwrap();
        write_scene(dir.path(), 0, |_| {});
        assert_mentions(&load_error(dir.path()), &["transforms.json", "no frames"]);
    }

    #[test]
    fn frame_without_transform_matrix() {
        let dir = tempfile::tempdir().unwrap();
        write_scene(dir.path(), 4, |v| {
            v["frames"][3]
                .as_object_mut()
                .unwrap()
                .remove("transform_matrix");
        });
        assert_mentions(
            &load_error(dir.path()),
            &["transforms.json: frame 3: missing key `transform_matrix`"],
        );
    }

    #[test]
    fn frames_of_different_sizes() {
        let dir = tempfile::tempdir().unwrap();
        write_scene(dir.path(), 3, |v| {
            v.as_object_mut()
                .unwrap()
                .remove("w")
                .map(drop)
                .unwrap_or(())
        });
        write_rgba_png(&dir.path().join("images/f_2.png"), 10, 6);
        let e = load_error(dir.path());
        assert_mentions(&e, &["transforms.json: frame 2", "different sizes", "10×6"]);
    }

    #[test]
    fn bad_unit_cube_keys() {
        let dir = tempfile::tempdir().unwrap();
        write_scene(dir.path(), 1, |v| v["offset"] = json!([0.5, 0.5]));
        assert_mentions(
            &load_error(dir.path()),
            &["transforms.json", "`offset` must be an array of 3"],
        );
        write_scene(dir.path(), 1, |v| v["aabb_scale"] = json!(0));
        assert_mentions(
            &load_error(dir.path()),
            &["`aabb_scale` = 0 must be positive"],
        );
        write_scene(dir.path(), 1, |v| v["scale"] = json!("big"));
        assert_mentions(
            &load_error(dir.path()),
            &["`scale` must be a number, found a string"],
        );
    }

    #[test]
    fn downscale_zero() {
        let dir = tempfile::tempdir().unwrap();
        write_scene(dir.path(), 1, |_| {});
        let e = load(dir.path(), LoadOptions { downscale: 0 })
            .unwrap_err()
            .to_string();
        assert_mentions(&e, &["downscale", "got 0"]);
    }
}
