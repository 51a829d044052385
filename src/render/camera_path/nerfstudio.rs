//! nerfstudio's `camera_path.json`: the file its viewer saves, its
//! `ns-render camera-path` renders, and its Blender add-on reads and
//! writes.
//!
//! The format, as nerfstudio's viewer writes it (`viewer/render_panel.py`)
//! and `ns-render` reads it (`cameras/camera_paths.py`,
//! `get_path_from_json`):
//!
//! - `keyframes`: a list of `{matrix, fov, aspect,
//!   override_transition_enabled, override_transition_sec}`, `matrix` the
//!   keyframe's camera-to-world as 16 numbers row by row, `fov` the vertical
//!   field of view in degrees;
//! - `camera_path`: the path baked into frames, a list of
//!   `{camera_to_world, fov, aspect}` in the same conventions: what
//!   `ns-render` renders, one image per entry;
//! - `render_width`, `render_height`, `fps`, `seconds`, `is_cycle`,
//!   `smoothness_value` (the spline's tension, 0 to 1), `default_fov`,
//!   `default_transition_sec`, `camera_type` (`perspective`, `fisheye` or
//!   `equirectangular`) and `crop` (null or nerfstudio's crop block).
//!
//! Poses use OpenGL camera axes (x right, y up, looking down −z), as zrak's
//! do. zrak writes them in its own world frame and adds
//! `zrak_world_to_original`: the similarity (16 numbers row by row) that
//! takes a point of zrak's world into the scene's original frame (the
//! frame of the capture's own files: identity for NeRF-synthetic and
//! instant-ngp scenes, whose poses zrak takes as written; for a COLMAP
//! model, zrak's centring and scaling undone). A file that carries it is
//! mapped into the frame of the scene it is rendered with, so a path saved
//! for one run of a capture lines up with another; a file without it is
//! taken to be in zrak's world already (nerfstudio's own files: for
//! NeRF-synthetic scenes nerfstudio's world is the files' frame too).
//!
//! Bad input is an error that names the field (`keyframes[2].matrix[5]`)
//! and the problem; nothing in a file makes the reader panic. Python's json
//! writes NaN and ±Infinity for non-finite floats, which are not JSON: the
//! reader reads them as such so that it can name the field that holds one.

use std::path::{Path, PathBuf};

use glam::{DMat3, DMat4};
use serde_json::{Map, Value, json};

use super::crop_block::{PathCrop, crop_to_json, finite, parse_crop};
use super::{CameraPath, FOV_RANGE_DEGREES, Keyframe, PathSample};
use crate::scene::pose::{check_rigid, describe};
use crate::scene::{Scene, SceneFormat};

/// The only camera model zrak renders paths with.
pub const PERSPECTIVE: &str = "perspective";

/// The field zrak adds for the transform to the scene's original frame.
pub const TO_ORIGINAL_FIELD: &str = "zrak_world_to_original";

/// The largest rendered image side a path file may ask for: zrak's
/// `MAX_IMAGE_SIDE` on the command line.
const MAX_RENDER_SIDE: u64 = 16384;

/// The most frames a file may bake or ask to be baked: 10⁵ (55 minutes at
/// 30 frames a second, as many as `zrak render --turntable` takes), so a
/// typo in `fps` or `seconds` cannot make zrak try to allocate the
/// impossible.
pub const MAX_FRAMES: usize = 100_000;

/// The largest camera path file read: 64 MB. A baked frame takes 350
/// (nerfstudio's compact JSON) to 600 bytes (zrak's, indented), so this
/// holds [`MAX_FRAMES`] frames of either; parsed, a file takes up to about
/// 20 times its size in memory (see [`PARSE_BYTES_PER_BYTE`]).
pub const MAX_FILE_BYTES: u64 = 64_000_000;

/// Memory parsing takes per byte of the file, at most: a number written in
/// two bytes (`0,`) becomes a 32-byte JSON value, plus the text and its
/// copy with Python's non-finite numbers quoted.
const PARSE_BYTES_PER_BYTE: u64 = 20;

/// The highest frame rate a file may give: 240 frames a second, the most a
/// video here takes.
pub const MAX_FPS: f64 = 240.0;

/// One entry of the baked `camera_path` list, as the file has it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BakedFrame {
    /// Camera-to-world, row by row.
    pub camera_to_world: [f64; 16],
    /// Vertical field of view in degrees.
    pub fov_degrees: f64,
    /// Width over height; nerfstudio's renderer ignores it in favour of
    /// `render_width` / `render_height`, and so does zrak.
    pub aspect: f64,
}

impl BakedFrame {
    pub fn sample(&self) -> PathSample {
        PathSample {
            camera_to_world: DMat4::from_cols_array(&self.camera_to_world).transpose(),
            fov_degrees: self.fov_degrees,
        }
    }

    pub fn from_sample(sample: &PathSample, aspect: f64) -> Self {
        Self {
            camera_to_world: sample.camera_to_world.transpose().to_cols_array(),
            fov_degrees: sample.fov_degrees,
            aspect,
        }
    }
}

/// A `camera_path.json`.
#[derive(Debug, Clone, PartialEq)]
pub struct CameraPathFile {
    /// The keyframes and spline settings; `None` when the file has no
    /// keyframes (only a baked list).
    pub path: Option<CameraPath>,
    /// The field of view of keyframes that set none of their own.
    pub default_fov_degrees: f64,
    pub render_width: u32,
    pub render_height: u32,
    pub fps: f64,
    pub seconds: f64,
    pub is_cycle: bool,
    pub baked: Vec<BakedFrame>,
    /// nerfstudio's `crop` block (`None`: null or absent), in the frame
    /// of the poses.
    pub crop: Option<PathCrop>,
    /// zrak world to the scene's original frame; `None` when the file does
    /// not say (it is then taken to be in zrak's world).
    pub to_original: Option<DMat4>,
}

impl CameraPathFile {
    /// A file for `path`, baked at `fps` for a `width` × `height` render.
    pub fn new(path: CameraPath, width: u32, height: u32, fps: f64, to_original: DMat4) -> Self {
        let seconds = path.duration();
        let aspect = width as f64 / height as f64;
        let baked = path
            .bake(path.frame_count(fps))
            .iter()
            .map(|s| BakedFrame::from_sample(s, aspect))
            .collect();
        Self {
            default_fov_degrees: path.keyframes.first().map_or(50.0, |k| k.fov_degrees),
            is_cycle: path.is_cycle,
            path: Some(path),
            render_width: width,
            render_height: height,
            fps,
            seconds,
            baked,
            crop: None,
            to_original: Some(to_original),
        }
    }

    /// The frames to render: the baked list as the file has it (what
    /// nerfstudio renders), or, when the file has none, its keyframes baked
    /// at its `fps` over its `seconds`.
    pub fn frames(&self) -> Result<Vec<PathSample>, String> {
        if !self.baked.is_empty() {
            return Ok(self.baked.iter().map(BakedFrame::sample).collect());
        }
        self.frames_at(self.fps)
    }

    /// The keyframes baked again at `fps`.
    pub fn frames_at(&self, fps: f64) -> Result<Vec<PathSample>, String> {
        let path = self.path.as_ref().ok_or_else(|| {
            format!(
                "the file has no keyframes, only a baked `camera_path` of {} frames, so it \
                 cannot be baked again at another frame rate",
                self.baked.len()
            )
        })?;
        if !(fps.is_finite() && fps > 0.0) {
            return Err(format!("the frame rate must be positive, got {fps}"));
        }
        let frames = path.duration() * fps;
        if frames > MAX_FRAMES as f64 {
            return Err(format!(
                "{:.0} seconds at {fps} frames a second is more than {MAX_FRAMES} frames",
                path.duration()
            ));
        }
        Ok(path.bake(path.frame_count(fps)))
    }

    /// The file's poses moved into the world of a scene whose own transform
    /// to its original frame is `scene_to_original`: each pose `C` becomes
    /// `S⁻¹ · F · C` with `F` the file's transform, its rotation rescaled to
    /// unit axes. A file without a transform is left as it is.
    pub fn moved_into(&self, scene_to_original: DMat4) -> CameraPathFile {
        let Some(file_to_original) = self.to_original else {
            return self.clone();
        };
        let change = scene_to_original.inverse() * file_to_original;
        let move_pose = |pose: DMat4| {
            let moved = change * pose;
            let r = DMat3::from_mat4(moved);
            let unit = DMat3::from_cols(
                r.x_axis.normalize(),
                r.y_axis.normalize(),
                r.z_axis.normalize(),
            );
            DMat4::from_cols(
                unit.x_axis.extend(0.0),
                unit.y_axis.extend(0.0),
                unit.z_axis.extend(0.0),
                moved.w_axis,
            )
        };
        let mut moved = self.clone();
        if let Some(path) = &mut moved.path {
            for k in &mut path.keyframes {
                k.camera_to_world = move_pose(k.camera_to_world);
            }
        }
        for frame in &mut moved.baked {
            let sample = frame.sample();
            *frame = BakedFrame::from_sample(
                &PathSample {
                    camera_to_world: move_pose(sample.camera_to_world),
                    ..sample
                },
                frame.aspect,
            );
        }
        moved.crop = self.crop.map(|crop| crop.moved(change));
        moved.to_original = Some(scene_to_original);
        moved
    }

    /// The file as JSON.
    pub fn to_json(&self) -> Value {
        let aspect = self.render_width as f64 / self.render_height as f64;
        let row_major = |m: &DMat4| m.transpose().to_cols_array().to_vec();
        let (keyframes, default_transition, tension) = match &self.path {
            Some(path) => (
                path.keyframes
                    .iter()
                    .map(|k| {
                        json!({
                            "matrix": row_major(&k.camera_to_world),
                            "fov": k.fov_degrees,
                            "aspect": aspect,
                            "override_transition_enabled": k.transition_seconds.is_some(),
                            "override_transition_sec": k.transition_seconds,
                        })
                    })
                    .collect(),
                path.default_transition_seconds,
                path.tension,
            ),
            None => (Vec::new(), 1.0, 0.0),
        };
        let baked: Vec<Value> = self
            .baked
            .iter()
            .map(|f| {
                json!({
                    "camera_to_world": f.camera_to_world.to_vec(),
                    "fov": f.fov_degrees,
                    "aspect": f.aspect,
                })
            })
            .collect();
        let mut object = json!({
            "keyframes": keyframes,
            "camera_type": PERSPECTIVE,
            "render_height": self.render_height,
            "render_width": self.render_width,
            "camera_path": baked,
            "fps": self.fps,
            "seconds": self.seconds,
            "smoothness_value": tension,
            "is_cycle": self.is_cycle,
            "default_fov": self.default_fov_degrees,
            "default_transition_sec": default_transition,
            "crop": crop_to_json(self.crop.as_ref()),
        });
        if let Some(m) = &self.to_original {
            object[TO_ORIGINAL_FIELD] = json!(row_major(m));
        }
        object
    }

    /// The file's text: pretty-printed JSON and a final newline.
    pub fn to_text(&self) -> String {
        let mut text =
            serde_json::to_string_pretty(&self.to_json()).expect("a JSON value always serialises");
        text.push('\n');
        text
    }

    /// Writes the file atomically (a crash leaves the old file or the new
    /// one, whole).
    pub fn save(&self, path: &Path) -> Result<(), String> {
        crate::files::write_bytes_atomically(path, self.to_text().as_bytes())
            .map_err(|e| format!("{}: cannot write the camera path: {e}", path.display()))
    }

    /// Reads a camera path file; errors name the file and the field.
    pub fn load(path: &Path) -> Result<CameraPathFile, CameraPathError> {
        let error = |kind: fn(PathBuf, String) -> CameraPathError, problem: String| {
            kind(path.to_path_buf(), problem)
        };
        let bytes = crate::files::read_regular_bounded(path, MAX_FILE_BYTES, "a camera path")
            .map_err(|problem| {
                if crate::files::exists_at_all(path) {
                    error(CameraPathError::unreadable, problem)
                } else {
                    error(CameraPathError::not_found, problem)
                }
            })?;
        let text = String::from_utf8(bytes).map_err(|_| {
            error(
                CameraPathError::invalid,
                "not UTF-8 text (a camera path is a JSON file)".into(),
            )
        })?;
        Self::parse(&text).map_err(|problem| error(CameraPathError::invalid, problem))
    }

    /// Parses a camera path from JSON text (a UTF-8 byte order mark before
    /// it is allowed, as Windows editors write one).
    pub fn parse(text: &str) -> Result<CameraPathFile, String> {
        let text = text.strip_prefix('\u{feff}').unwrap_or(text);
        // Counted before parsing, which takes far more memory than the
        // text: every baked frame has one `camera_to_world`.
        let frames = text.matches("\"camera_to_world\"").count();
        if frames > MAX_FRAMES {
            return Err(format!(
                "`camera_path` has {frames} frames, more than the {MAX_FRAMES} a camera path may \
                 have"
            ));
        }
        crate::files::check_memory(
            "reading the camera path",
            text.len() as u64 * PARSE_BYTES_PER_BYTE,
        )?;
        let value: Value = serde_json::from_str(&quote_non_finite(text)).map_err(|e| {
            format!(
                "malformed JSON at line {}, column {}: {e}",
                e.line(),
                e.column()
            )
        })?;
        let Value::Object(top) = value else {
            return Err(format!(
                "the top level must be a JSON object, found {}",
                describe(&value)
            ));
        };
        from_object(&top)
    }
}

/// A camera path file could not be read, by the kind a caller decides on;
/// each names the file and what is wrong, and shows as `PATH: PROBLEM`.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CameraPathError {
    /// Nothing is at the path.
    #[error("{}: {problem}", path.display())]
    NotFound { path: PathBuf, problem: String },
    /// Something is there that cannot be read as a camera path: a folder,
    /// a named pipe, a file too large to be one, an error while reading.
    #[error("{}: {problem}", path.display())]
    Unreadable { path: PathBuf, problem: String },
    /// The file was read and is not a camera path zrak takes: not UTF-8,
    /// malformed JSON, a field or keyframe missing or out of range.
    #[error("{}: {problem}", path.display())]
    Invalid { path: PathBuf, problem: String },
}

impl CameraPathError {
    fn not_found(path: PathBuf, problem: String) -> Self {
        Self::NotFound { path, problem }
    }

    fn unreadable(path: PathBuf, problem: String) -> Self {
        Self::Unreadable { path, problem }
    }

    fn invalid(path: PathBuf, problem: String) -> Self {
        Self::Invalid { path, problem }
    }
}

impl CameraPathFile {
    /// Sets the crop box the file carries (`None`: `"crop": null`), in the
    /// frame of its poses; a background colour it had is kept.
    pub fn set_crop(&mut self, crop: Option<crate::scene::crop::CropBox>) {
        self.crop = crop.map(|crop| PathCrop {
            crop,
            background: self
                .crop
                .map_or(super::crop_block::DEFAULT_BACKGROUND, |c| c.background),
        });
    }
}

/// The text with Python's bare `NaN`, `Infinity` and `-Infinity` (outside
/// strings) put in quotes, so that the JSON parses and the reader can say
/// which field holds one.
fn quote_non_finite(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    let mut in_string = false;
    let mut escaped = false;
    let mut rest = text;
    while let Some(c) = rest.chars().next() {
        if in_string {
            out.push(c);
            if escaped {
                escaped = false;
            } else if c == '\\' {
                escaped = true;
            } else if c == '"' {
                in_string = false;
            }
            rest = &rest[c.len_utf8()..];
            continue;
        }
        if c == '"' {
            in_string = true;
        }
        if let Some(token) = ["NaN", "Infinity", "-Infinity"]
            .into_iter()
            .find(|t| rest.starts_with(t))
        {
            out.push('"');
            out.push_str(token);
            out.push('"');
            rest = &rest[token.len()..];
            continue;
        }
        out.push(c);
        rest = &rest[c.len_utf8()..];
    }
    out
}

fn field<'a>(object: &'a Map<String, Value>, key: &str, name: &str) -> Result<&'a Value, String> {
    object
        .get(key)
        .ok_or_else(|| format!("missing field `{name}`"))
}

fn number_at(object: &Map<String, Value>, key: &str, name: &str) -> Result<f64, String> {
    finite(field(object, key, name)?, name)
}

fn optional_number(
    object: &Map<String, Value>,
    key: &str,
    name: &str,
) -> Result<Option<f64>, String> {
    match object.get(key) {
        None | Some(Value::Null) => Ok(None),
        Some(value) => finite(value, name).map(Some),
    }
}

fn boolean(object: &Map<String, Value>, key: &str) -> Result<Option<bool>, String> {
    match object.get(key) {
        None | Some(Value::Null) => Ok(None),
        Some(Value::Bool(b)) => Ok(Some(*b)),
        Some(other) => Err(format!(
            "`{key}` must be true or false, found {}",
            describe(other)
        )),
    }
}

fn array<'a>(object: &'a Map<String, Value>, key: &str) -> Result<Option<&'a [Value]>, String> {
    match object.get(key) {
        None | Some(Value::Null) => Ok(None),
        Some(Value::Array(a)) => Ok(Some(a)),
        Some(other) => Err(format!("`{key}` must be a list, found {}", describe(other))),
    }
}

fn entry<'a>(value: &'a Value, name: &str) -> Result<&'a Map<String, Value>, String> {
    value
        .as_object()
        .ok_or_else(|| format!("`{name}` must be an object, found {}", describe(value)))
}

/// A positive whole number of pixels at `key`.
fn pixels(object: &Map<String, Value>, key: &str) -> Result<u32, String> {
    let value = number_at(object, key, key)?;
    if value.fract() != 0.0 || !(1.0..=MAX_RENDER_SIDE as f64).contains(&value) {
        return Err(format!(
            "`{key}` must be a whole number of pixels from 1 to {MAX_RENDER_SIDE}, got {value}"
        ));
    }
    Ok(value as u32)
}

/// 16 finite numbers at `field`, row by row.
fn matrix(value: &Value, name: &str) -> Result<[f64; 16], String> {
    let Value::Array(items) = value else {
        return Err(format!(
            "`{name}` must be a list of 16 numbers (a 4×4 matrix row by row), found {}",
            describe(value)
        ));
    };
    if items.len() != 16 {
        return Err(format!(
            "`{name}` must hold 16 numbers (a 4×4 matrix row by row), found {}",
            items.len()
        ));
    }
    let mut m = [0.0; 16];
    for (i, item) in items.iter().enumerate() {
        m[i] = finite(item, &format!("{name}[{i}]"))?;
    }
    Ok(m)
}

/// A camera-to-world at `name` that must be a rigid motion.
fn pose(value: &Value, name: &str) -> Result<[f64; 16], String> {
    let m = matrix(value, name)?;
    let rows = [
        [m[0], m[1], m[2], m[3]],
        [m[4], m[5], m[6], m[7]],
        [m[8], m[9], m[10], m[11]],
        [m[12], m[13], m[14], m[15]],
    ];
    check_rigid(&rows).map_err(|problem| format!("`{name}` is not a camera pose: {problem}"))?;
    Ok(m)
}

fn fov(value: f64, name: &str) -> Result<f64, String> {
    let (low, high) = FOV_RANGE_DEGREES;
    if !(low..=high).contains(&value) {
        return Err(format!(
            "`{name}` must be a vertical field of view of {low} to {high} degrees, got {value}"
        ));
    }
    Ok(value)
}

fn from_object(top: &Map<String, Value>) -> Result<CameraPathFile, String> {
    match top.get("camera_type") {
        None | Some(Value::Null) => {}
        Some(Value::String(kind)) if kind == PERSPECTIVE => {}
        Some(Value::String(kind))
            if ["fisheye", "equirectangular", "omnidirectional"].contains(&kind.as_str()) =>
        {
            return Err(format!(
                "`camera_type` is \"{kind}\": zrak renders camera paths with the perspective \
                 (pinhole) camera only"
            ));
        }
        Some(Value::String(kind)) => {
            return Err(format!(
                "`camera_type` \"{kind}\" is not a camera type nerfstudio writes (perspective, \
                 fisheye, equirectangular)"
            ));
        }
        Some(other) => {
            return Err(format!(
                "`camera_type` must be a string, found {}",
                describe(other)
            ));
        }
    }
    let render_width = pixels(top, "render_width")?;
    let render_height = pixels(top, "render_height")?;
    let baked_values = array(top, "camera_path")?.ok_or("missing field `camera_path`")?;
    if baked_values.len() > MAX_FRAMES {
        return Err(format!(
            "`camera_path` has {} frames, more than the {MAX_FRAMES} a camera path may have",
            baked_values.len()
        ));
    }
    let mut baked = Vec::with_capacity(baked_values.len());
    for (i, value) in baked_values.iter().enumerate() {
        let name = format!("camera_path[{i}]");
        let object = entry(value, &name)?;
        let camera_to_world = pose(
            field(
                object,
                "camera_to_world",
                &format!("{name}.camera_to_world"),
            )?,
            &format!("{name}.camera_to_world"),
        )?;
        let fov_name = format!("{name}.fov");
        let fov_degrees = fov(number_at(object, "fov", &fov_name)?, &fov_name)?;
        let aspect = optional_number(object, "aspect", &format!("{name}.aspect"))?
            .unwrap_or(render_width as f64 / render_height as f64);
        baked.push(BakedFrame {
            camera_to_world,
            fov_degrees,
            aspect,
        });
    }
    let is_cycle = boolean(top, "is_cycle")?.unwrap_or(false);
    let tension = optional_number(top, "smoothness_value", "smoothness_value")?.unwrap_or(0.0);
    if !(0.0..=1.0).contains(&tension) {
        return Err(format!(
            "`smoothness_value` (the spline's tension) must be 0 to 1, got {tension}"
        ));
    }
    let default_fov_degrees = match optional_number(top, "default_fov", "default_fov")? {
        Some(value) => fov(value, "default_fov")?,
        None => baked.first().map_or(50.0, |f| f.fov_degrees),
    };
    let default_transition =
        optional_number(top, "default_transition_sec", "default_transition_sec")?.unwrap_or(1.0);
    if default_transition <= 0.0 {
        return Err(format!(
            "`default_transition_sec` must be a positive number of seconds, got {default_transition}"
        ));
    }
    let keyframe_values = array(top, "keyframes")?.unwrap_or(&[]);
    let mut keyframes = Vec::with_capacity(keyframe_values.len());
    for (i, value) in keyframe_values.iter().enumerate() {
        let name = format!("keyframes[{i}]");
        let object = entry(value, &name)?;
        let matrix_name = format!("{name}.matrix");
        let m = pose(field(object, "matrix", &matrix_name)?, &matrix_name)?;
        let fov_name = format!("{name}.fov");
        let fov_degrees = match optional_number(object, "fov", &fov_name)? {
            Some(value) => fov(value, &fov_name)?,
            None => default_fov_degrees,
        };
        let overridden = boolean(object, "override_transition_enabled")
            .map_err(|e| format!("{name}.{e}"))?
            .unwrap_or(false);
        let transition_name = format!("{name}.override_transition_sec");
        let transition = optional_number(object, "override_transition_sec", &transition_name)?;
        let transition_seconds = match (overridden, transition) {
            (true, Some(t)) if t > 0.0 => Some(t),
            (true, Some(t)) => {
                return Err(format!(
                    "`{transition_name}` must be a positive number of seconds, got {t}"
                ));
            }
            (true, None) => return Err(format!("missing field `{transition_name}`")),
            (false, _) => None,
        };
        keyframes.push(Keyframe {
            camera_to_world: DMat4::from_cols_array(&m).transpose(),
            fov_degrees,
            transition_seconds,
        });
    }
    if keyframes.is_empty() && baked.is_empty() {
        return Err(
            "the file has no frames: both `keyframes` and `camera_path` are empty (a camera path \
             needs at least one keyframe or one baked frame)"
                .into(),
        );
    }
    let path = (!keyframes.is_empty()).then_some(CameraPath {
        keyframes,
        default_transition_seconds: default_transition,
        is_cycle,
        tension,
    });
    let seconds = optional_number(top, "seconds", "seconds")?;
    let fps = optional_number(top, "fps", "fps")?;
    // nerfstudio's renderer takes the frame rate as frames over seconds
    // when it is not given; one of the two must be there.
    let (fps, seconds) = match (fps, seconds) {
        (Some(fps), Some(seconds)) => (fps, seconds),
        (Some(fps), None) => (
            fps,
            path.as_ref()
                .map_or(baked.len() as f64 / fps, CameraPath::duration),
        ),
        (None, Some(seconds)) if !baked.is_empty() => {
            if seconds <= 0.0 {
                return Err(format!(
                    "`seconds` is {seconds} and there is no `fps`: the frame rate would be the \
                     {} frames over {seconds} seconds; give `fps`, or `seconds` above 0",
                    baked.len()
                ));
            }
            let fps = baked.len() as f64 / seconds;
            if fps > MAX_FPS {
                return Err(format!(
                    "there is no `fps`, and the {} frames over `seconds` = {seconds} make {fps} \
                     frames a second, more than {MAX_FPS}; give `fps`",
                    baked.len()
                ));
            }
            (fps, seconds)
        }
        _ => return Err("missing field `fps`".into()),
    };
    if !(fps > 0.0 && fps <= MAX_FPS) {
        return Err(format!(
            "`fps` must be a frame rate above 0 and at most {MAX_FPS} frames a second, got {fps}"
        ));
    }
    if seconds < 0.0 {
        return Err(format!(
            "`seconds` must be a duration of 0 seconds or more, got {seconds}"
        ));
    }
    if baked.is_empty() && seconds * fps > MAX_FRAMES as f64 {
        return Err(format!(
            "`seconds` × `fps` = {:.0} frames, more than {MAX_FRAMES}",
            seconds * fps
        ));
    }
    // `seconds` is the path's length as the viewer showed it; the
    // keyframes' transitions are scaled to it where they disagree.
    let path = path.map(|mut path| {
        if seconds > 0.0 && (path.duration() - seconds).abs() > 1e-9 * seconds {
            path.set_duration(seconds);
        }
        path
    });
    if let Some(problem) = path.as_ref().and_then(CameraPath::problem) {
        return Err(format!("`keyframes`: {problem}"));
    }
    let to_original = match top.get(TO_ORIGINAL_FIELD) {
        None | Some(Value::Null) => None,
        Some(value) => {
            let m = matrix(value, TO_ORIGINAL_FIELD)?;
            let m = DMat4::from_cols_array(&m).transpose();
            check_similarity(&m).map_err(|problem| format!("`{TO_ORIGINAL_FIELD}` {problem}"))?;
            Some(m)
        }
    };
    Ok(CameraPathFile {
        path,
        default_fov_degrees,
        render_width,
        render_height,
        fps,
        seconds,
        is_cycle,
        baked,
        crop: parse_crop(top.get("crop"))?,
        to_original,
    })
}

/// Checks that `m` is a similarity: a rotation times a positive uniform
/// scale, a translation, and a bottom row of [0, 0, 0, 1].
fn check_similarity(m: &DMat4) -> Result<(), String> {
    let bottom = m.row(3);
    if (bottom - glam::DVec4::W).abs().max_element() > 1e-9 {
        return Err(format!(
            "must have the bottom row [0, 0, 0, 1], found {bottom}"
        ));
    }
    let r = DMat3::from_mat4(*m);
    let scale = r.determinant().cbrt();
    if !(scale > 0.0 && scale.is_finite()) {
        return Err(
            "must be a rotation with a positive scale (its determinant is not positive)".into(),
        );
    }
    let unit = r * (1.0 / scale);
    let error = (unit.transpose() * unit - DMat3::IDENTITY)
        .to_cols_array()
        .iter()
        .fold(0f64, |a, x| a.max(x.abs()));
    if error > 1e-6 {
        return Err(format!(
            "must be a rotation with a uniform scale; its axes are off by {error:.2e}"
        ));
    }
    Ok(())
}

/// The similarity from zrak's world to `scene`'s original frame: the
/// identity for scenes whose poses zrak takes as written (NeRF-synthetic,
/// instant-ngp, the demo), and for a COLMAP model the inverse of the
/// centring and scaling its loader applies (`zrak = (colmap − centre) ·
/// scale`, see [`crate::scene::colmap::convert`]); for an LLFF capture the
/// inverse of its rescale and recentring
/// ([`crate::scene::llff::Normalisation`]), the identity for one built in
/// memory.
pub fn scene_to_original(scene: &Scene) -> Result<DMat4, String> {
    match scene.format {
        SceneFormat::Blender | SceneFormat::InstantNgp | SceneFormat::Demo => Ok(DMat4::IDENTITY),
        SceneFormat::Colmap => {
            let converted =
                crate::scene::colmap::convert(&scene.root).map_err(|e| e.to_string())?;
            Ok(DMat4::from_translation(converted.centre)
                * DMat4::from_scale(glam::DVec3::splat(1.0 / converted.scale)))
        }
        SceneFormat::Llff if scene.root.as_os_str().is_empty() => Ok(DMat4::IDENTITY),
        SceneFormat::Llff => {
            use crate::scene::llff;
            let views = llff::read_poses_bounds(&scene.root.join(llff::POSES_FILE))
                .map_err(|e| e.to_string())?;
            Ok(llff::Normalisation::of(&views).to_original())
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::camera_path::look_at;
    use glam::DVec3;

    fn look(eye: DVec3, fov: f64) -> Keyframe {
        Keyframe::new(look_at(eye, DVec3::ZERO, DVec3::Z), fov)
    }

    fn sample_path() -> CameraPath {
        let mut keyframes = vec![
            look(DVec3::new(4.0, 0.1, 1.0), 40.0),
            look(DVec3::new(0.3, 3.0, 2.0), 52.5),
            look(DVec3::new(-4.0, 0.5, 0.5), 35.0),
            look(DVec3::new(0.1, -3.5, 1.5), 45.0),
        ];
        keyframes[1].transition_seconds = Some(0.8);
        CameraPath {
            keyframes,
            default_transition_seconds: 1.3,
            is_cycle: false,
            tension: 0.25,
        }
    }

    fn sample_file() -> CameraPathFile {
        let to_original = DMat4::from_translation(DVec3::new(0.5, -1.0, 2.0))
            * DMat4::from_scale(DVec3::splat(2.5));
        CameraPathFile::new(sample_path(), 64, 48, 10.0, to_original)
    }

    #[test]
    fn round_trips_bit_for_bit() {
        let file = sample_file();
        assert_eq!(file.baked.len(), 34, "3.4 s at 10 fps");
        let text = file.to_text();
        let read = CameraPathFile::parse(&text).unwrap();
        assert_eq!(read, file);
        // Every f64 the same bits, not just equal.
        for (a, b) in read.baked.iter().zip(&file.baked) {
            for (x, y) in a.camera_to_world.iter().zip(&b.camera_to_world) {
                assert_eq!(x.to_bits(), y.to_bits());
            }
        }
        assert_eq!(read.to_text(), text);
        // And through a file on disk.
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("camera_path.json");
        file.save(&path).unwrap();
        assert_eq!(std::fs::read_to_string(&path).unwrap(), text);
        assert_eq!(CameraPathFile::load(&path).unwrap(), file);
    }

    /// A file as nerfstudio's viewer writes it, built here from its
    /// documented fields (with values a person would have: integers where
    /// the viewer's widgets give integers, no zrak field), loads, and the
    /// frames it renders are its baked list.
    #[test]
    fn a_nerfstudio_file_loads_and_renders_its_baked_list() {
        let keyframe = |eye: DVec3, fov: f64| {
            let m = look_at(eye, DVec3::ZERO, DVec3::Z);
            json!({
                "matrix": m.transpose().to_cols_array().to_vec(),
                "fov": fov,
                "aspect": 1.5,
                "override_transition_enabled": false,
                "override_transition_sec": null,
            })
        };
        // The baked list: a path nerfstudio's spline made, which zrak need
        // not reproduce; here a slow arc, each pose built on its own.
        let baked: Vec<Value> = (0..12)
            .map(|i| {
                let angle = i as f64 * 0.1;
                let eye = DVec3::new(4.0 * angle.cos(), 4.0 * angle.sin(), 1.0);
                let m = look_at(eye, DVec3::ZERO, DVec3::Z);
                json!({
                    "camera_to_world": m.transpose().to_cols_array().to_vec(),
                    "fov": 50 + i,
                    "aspect": 1.5,
                })
            })
            .collect();
        let file = json!({
            "default_fov": 50,
            "default_transition_sec": 2,
            "keyframes": [keyframe(DVec3::new(4.0, 0.0, 1.0), 50.0), keyframe(DVec3::new(0.0, 4.0, 1.0), 61.0)],
            "camera_type": "perspective",
            "render_height": 480,
            "render_width": 720,
            "camera_path": baked,
            "fps": 6,
            "seconds": 2,
            "smoothness_value": 0.5,
            "is_cycle": false,
            "crop": null,
        });
        let read = CameraPathFile::parse(&file.to_string()).unwrap();
        assert_eq!((read.render_width, read.render_height), (720, 480));
        assert_eq!((read.fps, read.seconds), (6.0, 2.0));
        assert_eq!(read.to_original, None);
        let path = read.path.as_ref().unwrap();
        assert_eq!(path.keyframes.len(), 2);
        assert_eq!(path.tension, 0.5);
        let frames = read.frames().unwrap();
        assert_eq!(frames.len(), 12);
        for (i, (frame, value)) in frames.iter().zip(&baked).enumerate() {
            let rows: Vec<f64> = serde_json::from_value(value["camera_to_world"].clone()).unwrap();
            let expected = DMat4::from_cols_array(&rows.try_into().unwrap()).transpose();
            assert_eq!(frame.camera_to_world, expected, "frame {i}");
            assert_eq!(frame.fov_degrees, 50.0 + i as f64);
            // The camera rendered has that vertical field of view.
            let camera = frame.camera(720, 480);
            assert!(
                (camera.intrinsics.fov_y().to_degrees() as f64 - frame.fov_degrees).abs() < 1e-3
            );
        }
        // Baked again from its keyframes at its own rate: 12 frames over
        // the 2 seconds, from the first keyframe to the second.
        let rebaked = read.frames_at(6.0).unwrap();
        assert_eq!(rebaked.len(), 12);
        assert!(
            (rebaked[0].camera_to_world.w_axis.truncate() - DVec3::new(4.0, 0.0, 1.0)).length()
                < 1e-12
        );
        assert!(
            (rebaked[11].camera_to_world.w_axis.truncate() - DVec3::new(0.0, 4.0, 1.0)).length()
                < 1e-12
        );
    }

    #[test]
    fn a_file_with_only_the_baked_list_loads() {
        let mut value = sample_file().to_json();
        value.as_object_mut().unwrap().remove("keyframes");
        value.as_object_mut().unwrap().remove(TO_ORIGINAL_FIELD);
        let read = CameraPathFile::parse(&value.to_string()).unwrap();
        assert_eq!(read.path, None);
        assert_eq!(read.frames().unwrap().len(), 34);
        assert_eq!(read.frames().unwrap()[5], sample_file().baked[5].sample());
        assert!(read.frames_at(30.0).unwrap_err().contains("no keyframes"));
        // And with keyframes but no baked list, the keyframes are baked.
        let mut value = sample_file().to_json();
        value["camera_path"] = json!([]);
        let read = CameraPathFile::parse(&value.to_string()).unwrap();
        assert_eq!(read.frames().unwrap(), sample_path().bake(34));
    }

    #[test]
    fn a_path_moves_into_the_frame_of_the_scene_it_renders_with() {
        // Written for a scene whose zrak world is its original frame scaled
        // by 2.5 and moved; read for one with the identity.
        let file = sample_file();
        let moved = file.moved_into(DMat4::IDENTITY);
        let original = file.to_original.unwrap();
        for (a, b) in file.baked.iter().zip(&moved.baked) {
            let (a, b) = (a.sample(), b.sample());
            let expected = original.transform_point3(a.camera_to_world.w_axis.truncate());
            assert!((b.camera_to_world.w_axis.truncate() - expected).length() < 1e-12);
            // Rotation unchanged (a uniform scale and a translation only).
            let (ra, rb) = (
                DMat3::from_mat4(a.camera_to_world),
                DMat3::from_mat4(b.camera_to_world),
            );
            assert!((ra - rb).to_cols_array().iter().all(|x| x.abs() < 1e-12));
        }
        // Moving into the frame it was written for changes nothing.
        let same = file.moved_into(original);
        for (a, b) in file.baked.iter().zip(&same.baked) {
            for (x, y) in a.camera_to_world.iter().zip(&b.camera_to_world) {
                assert!((x - y).abs() < 1e-12);
            }
        }
    }

    /// The text of the sample file with `edit` applied, parsed.
    fn parse_edited(edit: impl FnOnce(&mut Value)) -> Result<CameraPathFile, String> {
        let mut value = sample_file().to_json();
        edit(&mut value);
        CameraPathFile::parse(&value.to_string())
    }

    #[test]
    fn bad_input_names_the_field() {
        // NaN as Python writes it: bare, not JSON.
        let text = sample_file()
            .to_text()
            .replacen("\"fov\": 52.5", "\"fov\": NaN", 1);
        assert!(text.contains("NaN"));
        assert_eq!(
            CameraPathFile::parse(&text).unwrap_err(),
            "`keyframes[1].fov` is NaN: every number in a camera path must be finite"
        );
        let text = sample_file().to_text();
        let at = text.find("\"camera_to_world\": [").unwrap() + "\"camera_to_world\": [".len();
        let number_end = at + text[at..].find(',').unwrap();
        let text = format!("{}-Infinity{}", &text[..at], &text[number_end..]);
        assert_eq!(
            CameraPathFile::parse(&text).unwrap_err(),
            "`camera_path[0].camera_to_world[0]` is -Infinity: every number in a camera path \
             must be finite"
        );
        // Zero keyframes and no baked frames.
        let e = parse_edited(|v| {
            v["keyframes"] = json!([]);
            v["camera_path"] = json!([]);
        })
        .unwrap_err();
        assert!(
            e.contains("both `keyframes` and `camera_path` are empty"),
            "{e}"
        );
        // A matrix that is not a rotation.
        let e = parse_edited(|v| v["keyframes"][2]["matrix"][0] = json!(2.0)).unwrap_err();
        assert!(
            e.starts_with("`keyframes[2].matrix` is not a camera pose: the rotation (upper-left 3×3) is not orthonormal"),
            "{e}"
        );
        let e = parse_edited(|v| {
            let m = &mut v["camera_path"][3]["camera_to_world"];
            for i in [0, 4, 8] {
                m[i] = json!(-m[i].as_f64().unwrap());
            }
        })
        .unwrap_err();
        assert!(
            e.starts_with("`camera_path[3].camera_to_world` is not a camera pose")
                && e.contains("reflection"),
            "{e}"
        );
        let e = parse_edited(|v| v["camera_path"][0]["camera_to_world"] = json!([1, 0, 0]))
            .unwrap_err();
        assert_eq!(
            e,
            "`camera_path[0].camera_to_world` must hold 16 numbers (a 4×4 matrix row by row), found 3"
        );
        // Camera types.
        let e = parse_edited(|v| v["camera_type"] = json!("pinhole-ish")).unwrap_err();
        assert!(
            e.starts_with("`camera_type` \"pinhole-ish\" is not a camera type"),
            "{e}"
        );
        let e = parse_edited(|v| v["camera_type"] = json!("fisheye")).unwrap_err();
        assert!(e.contains("perspective (pinhole) camera only"), "{e}");
        // Missing fields.
        for (key, expected) in [
            ("render_width", "missing field `render_width`"),
            ("render_height", "missing field `render_height`"),
            ("camera_path", "missing field `camera_path`"),
        ] {
            let e = parse_edited(|v| {
                v.as_object_mut().unwrap().remove(key);
            })
            .unwrap_err();
            assert_eq!(e, expected);
        }
        let e = parse_edited(|v| {
            v.as_object_mut().unwrap().remove("keyframes");
            v.as_object_mut().unwrap().remove("fps");
            v.as_object_mut().unwrap().remove("seconds");
        })
        .unwrap_err();
        assert_eq!(e, "missing field `fps`");
        let e = parse_edited(|v| {
            v["keyframes"][0].as_object_mut().unwrap().remove("matrix");
        })
        .unwrap_err();
        assert_eq!(e, "missing field `keyframes[0].matrix`");
        let e = parse_edited(|v| {
            v["camera_path"][7].as_object_mut().unwrap().remove("fov");
        })
        .unwrap_err();
        assert_eq!(e, "missing field `camera_path[7].fov`");
        // Values out of range.
        let e = parse_edited(|v| v["render_width"] = json!(0)).unwrap_err();
        assert!(
            e.starts_with("`render_width` must be a whole number of pixels"),
            "{e}"
        );
        let e = parse_edited(|v| v["smoothness_value"] = json!(3)).unwrap_err();
        assert!(e.starts_with("`smoothness_value`"), "{e}");
        let e = parse_edited(|v| v["keyframes"][1]["fov"] = json!(180.5)).unwrap_err();
        assert!(
            e.starts_with("`keyframes[1].fov` must be a vertical field of view"),
            "{e}"
        );
        let e =
            parse_edited(|v| v["keyframes"][1]["override_transition_sec"] = json!(-1)).unwrap_err();
        assert!(
            e.starts_with("`keyframes[1].override_transition_sec` must be a positive"),
            "{e}"
        );
        let e = parse_edited(|v| v[TO_ORIGINAL_FIELD][1] = json!(0.3)).unwrap_err();
        assert!(
            e.starts_with("`zrak_world_to_original` must be a rotation with a uniform scale"),
            "{e}"
        );
        let e = parse_edited(|v| v["fps"] = json!("fast")).unwrap_err();
        assert_eq!(e, "`fps` must be a number, found a string");
        // Not JSON, or not an object.
        assert!(
            CameraPathFile::parse("{")
                .unwrap_err()
                .starts_with("malformed JSON at line 1")
        );
        assert_eq!(
            CameraPathFile::parse("[]").unwrap_err(),
            "the top level must be a JSON object, found an array"
        );
        // NaN inside a string is just text.
        assert_eq!(
            quote_non_finite(r#"{"a": "NaN \" NaN", "b": NaN}"#),
            r#"{"a": "NaN \" NaN", "b": "NaN"}"#
        );
    }

    #[test]
    fn a_missing_file_is_named() {
        let e = CameraPathFile::load(Path::new("/nonexistent/camera_path.json")).unwrap_err();
        assert_eq!(
            e,
            CameraPathError::NotFound {
                path: "/nonexistent/camera_path.json".into(),
                problem: "not found".into()
            }
        );
        assert_eq!(e.to_string(), "/nonexistent/camera_path.json: not found");
    }

    #[test]
    fn load_errors_say_their_kind() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("camera_path.json");
        // A keyframe whose field of view is out of range: read, and wrong.
        let mut value = sample_file().to_json();
        value["keyframes"][1]["fov"] = json!(200.0);
        std::fs::write(&path, value.to_string()).unwrap();
        let e = CameraPathFile::load(&path).unwrap_err();
        assert!(matches!(e, CameraPathError::Invalid { .. }), "{e:?}");
        assert!(
            e.to_string()
                .starts_with(&format!("{}: `keyframes[1].fov` must be", path.display())),
            "{e}"
        );
        std::fs::write(&path, [0xff, 0xfe, 0x00]).unwrap();
        let e = CameraPathFile::load(&path).unwrap_err();
        assert_eq!(
            e,
            CameraPathError::Invalid {
                path: path.clone(),
                problem: "not UTF-8 text (a camera path is a JSON file)".into()
            }
        );
        // A folder of that name: there, but no file.
        std::fs::remove_file(&path).unwrap();
        std::fs::create_dir(&path).unwrap();
        let e = CameraPathFile::load(&path).unwrap_err();
        assert_eq!(
            e,
            CameraPathError::Unreadable {
                path: path.clone(),
                problem: "a folder, not a file".into()
            }
        );
    }
}
