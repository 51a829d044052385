//! What the scene loaders share: reading their JSON files, checking the
//! camera poses in them, and finding and decoding the images they list.
//!
//! Every check here turns bad input into a [`SceneError`] that names the file
//! (and frame) and the problem; a loader never panics on what it reads.

use std::path::{Path, PathBuf};

use glam::{Mat4, Vec4};
use rayon::prelude::*;
use serde_json::{Map, Value};

use super::error::{SceneError, SceneResult, shown};
use super::image::load_image_sharing;
use crate::files::Unreadable;
use crate::scene::ImageRgba8;

/// How far `RᵀR` may stray from the identity. NeRF-synthetic rotations are
/// orthonormal to about 1e-7 and COLMAP-derived ones to about 1e-6; a
/// rotation further off than this carries a scale or shear, which would skew
/// every ray, so it is rejected rather than silently renormalised.
pub const ORTHONORMAL_TOLERANCE: f64 = 1e-3;

/// How far the bottom row of a pose may stray from `[0, 0, 0, 1]`.
pub const BOTTOM_ROW_TOLERANCE: f64 = 1e-6;

/// A JSON object, as the loaders walk it.
pub type JsonObject = Map<String, Value>;

/// Reads and parses a JSON file. A missing file, an unreadable one and
/// malformed JSON (reported with line and column) are errors naming the file.
pub fn read_json(path: &Path) -> SceneResult<Value> {
    crate::files::check_regular_file(path).map_err(|problem| match problem {
        Unreadable::NotFound => SceneError::not_found(path, "file not found"),
        Unreadable::Link(link) => SceneError::unreadable(
            path,
            format!(
                "cannot read it: it is {link}; replace the link with the JSON file itself, or \
                 remove it"
            ),
        ),
        Unreadable::Other(problem) => {
            SceneError::unreadable(path, format!("cannot read it: it is {problem}"))
        }
    })?;
    let bytes = std::fs::read(path)
        .map_err(|e| SceneError::unreadable(path, format!("cannot read file: {e}")))?;
    let text = json_text(&bytes).map_err(|problem| SceneError::new(path, problem))?;
    serde_json::from_slice(&text).map_err(|e| SceneError::new(path, malformed_json(&e, &text)))
}

/// The file's bytes as UTF-8 JSON text: a UTF-8 byte-order mark (which
/// Windows editors write and JSON forbids) is dropped, and UTF-16 with its
/// mark is converted, so such files load rather than fail at line 1.
fn json_text(bytes: &[u8]) -> Result<std::borrow::Cow<'_, [u8]>, String> {
    use std::borrow::Cow;
    if let Some(rest) = bytes.strip_prefix(&[0xEF, 0xBB, 0xBF]) {
        return Ok(Cow::Borrowed(rest));
    }
    let utf16 = |rest: &[u8], little_endian: bool| -> Result<Cow<'_, [u8]>, String> {
        if !rest.len().is_multiple_of(2) {
            return Err("UTF-16 text with an odd number of bytes (the file is cut off)".into());
        }
        let units: Vec<u16> = rest
            .chunks_exact(2)
            .map(|pair| {
                if little_endian {
                    u16::from_le_bytes([pair[0], pair[1]])
                } else {
                    u16::from_be_bytes([pair[0], pair[1]])
                }
            })
            .collect();
        String::from_utf16(&units)
            .map(|text| Cow::Owned(text.into_bytes()))
            .map_err(|_| "malformed UTF-16 text (save the file as UTF-8)".into())
    };
    match bytes {
        [0xFF, 0xFE, rest @ ..] => utf16(rest, true),
        [0xFE, 0xFF, rest @ ..] => utf16(rest, false),
        // UTF-16 without a mark: JSON starts with an ASCII character, so
        // one of its first two bytes is zero.
        [first, 0, ..] if *first != 0 => utf16(bytes, true),
        [0, second, ..] if *second != 0 => utf16(bytes, false),
        _ => Ok(Cow::Borrowed(bytes)),
    }
}

/// Reads a JSON file whose top level must be an object, as both formats'
/// files are.
pub fn read_json_object(path: &Path) -> SceneResult<JsonObject> {
    match read_json(path)? {
        Value::Object(object) => Ok(object),
        other => Err(SceneError::new(
            path,
            format!(
                "the top level must be a JSON object, found {}",
                describe(&other)
            ),
        )),
    }
}

/// The problem text for a parse error: position first, because that is what
/// one needs to fix the file.
fn malformed_json(error: &serde_json::Error, text: &[u8]) -> String {
    let (line, column) = (error.line(), error.column());
    // serde_json appends the position to its own message; drop it so that it
    // is not said twice.
    let message = error.to_string();
    let suffix = format!(" at line {line} column {column}");
    let message = message.strip_suffix(&suffix).unwrap_or(&message);
    // Python's json module writes NaN and ±Infinity for non-finite floats,
    // which are not JSON; say so, since the parser's own words ("expected
    // value") do not point there.
    let text = String::from_utf8_lossy(text);
    let at_error = text
        .lines()
        .nth(line.saturating_sub(1))
        .and_then(|l| l.get(column.saturating_sub(1)..))
        .unwrap_or("");
    let hint = if at_error.starts_with("NaN") || at_error.starts_with("Infinity") {
        " (NaN and Infinity are not valid JSON numbers: the file holds a non-finite value)"
    } else {
        ""
    };
    format!("malformed JSON at line {line}, column {column}: {message}{hint}")
}

/// A short description of a JSON value's type, for error messages.
pub fn describe(value: &Value) -> &'static str {
    match value {
        Value::Null => "null",
        Value::Bool(_) => "a boolean",
        Value::Number(_) => "a number",
        Value::String(_) => "a string",
        Value::Array(_) => "an array",
        Value::Object(_) => "an object",
    }
}

/// The number at `key`, `None` when the key is absent, an error when it holds
/// something else.
pub fn number(object: &JsonObject, key: &str) -> Result<Option<f64>, String> {
    match object.get(key) {
        None => Ok(None),
        Some(Value::Number(n)) => n
            .as_f64()
            .map(Some)
            .ok_or_else(|| format!("`{key}` = {n} is not representable as a number")),
        Some(other) => Err(format!(
            "`{key}` must be a number, found {}",
            describe(other)
        )),
    }
}

/// The number at `key`, which must be there.
pub fn required_number(object: &JsonObject, key: &str) -> Result<f64, String> {
    number(object, key)?.ok_or_else(|| missing_key(key))
}

/// The string at `key`, which must be there.
pub fn required_str<'a>(object: &'a JsonObject, key: &str) -> Result<&'a str, String> {
    match object.get(key) {
        None => Err(missing_key(key)),
        Some(Value::String(s)) => Ok(s),
        Some(other) => Err(format!(
            "`{key}` must be a string, found {}",
            describe(other)
        )),
    }
}

/// The array at `key`, which must be there.
pub fn required_array<'a>(object: &'a JsonObject, key: &str) -> Result<&'a [Value], String> {
    match object.get(key) {
        None => Err(missing_key(key)),
        Some(Value::Array(a)) => Ok(a),
        Some(other) => Err(format!(
            "`{key}` must be an array, found {}",
            describe(other)
        )),
    }
}

/// One entry of a `frames` array, which must be an object.
pub fn frame_object(value: &Value) -> Result<&JsonObject, String> {
    value
        .as_object()
        .ok_or_else(|| format!("a frame must be a JSON object, found {}", describe(value)))
}

pub fn missing_key(key: &str) -> String {
    format!("missing key `{key}`")
}

/// Parses a `transform_matrix` (camera-to-world, rows as written in the file)
/// and checks that it is a rigid motion: see [`check_rigid`].
pub fn parse_transform_matrix(value: &Value) -> Result<Mat4, String> {
    const KEY: &str = "`transform_matrix`";
    let shape_error = |found: String| format!("{KEY} must be a 4×4 array of numbers, {found}");
    let rows = value
        .as_array()
        .ok_or_else(|| shape_error(format!("found {}", describe(value))))?;
    if rows.len() != 4 {
        return Err(shape_error(format!("found {} rows", rows.len())));
    }
    let mut m = [[0f64; 4]; 4];
    for (r, row) in rows.iter().enumerate() {
        let row = row
            .as_array()
            .ok_or_else(|| shape_error(format!("row {r} is {}", describe(row))))?;
        if row.len() != 4 {
            return Err(shape_error(format!("row {r} has {} entries", row.len())));
        }
        for (c, entry) in row.iter().enumerate() {
            let x = entry.as_f64().ok_or_else(|| {
                // Some writers turn NaN into null; call it what it likely is.
                let what = if entry.is_null() {
                    "null (a NaN?)"
                } else {
                    describe(entry)
                };
                shape_error(format!("row {r} column {c} is {what}"))
            })?;
            // The value must survive the trip to f32, which is what the
            // renderer computes in: 1e39 is a fine f64 but infinite in f32.
            if !x.is_finite() || !(x as f32).is_finite() {
                return Err(format!(
                    "{KEY} row {r} column {c} = {x:e} is not a finite 32-bit number"
                ));
            }
            m[r][c] = x;
        }
    }
    check_rigid(&m).map_err(|problem| format!("{KEY}: {problem}"))?;
    // JSON row r is matrix row r; glam stores columns, so column c gathers
    // entry c of every row.
    let column = |c: usize| {
        Vec4::new(
            m[0][c] as f32,
            m[1][c] as f32,
            m[2][c] as f32,
            m[3][c] as f32,
        )
    };
    Ok(Mat4::from_cols(column(0), column(1), column(2), column(3)))
}

/// Checks that a camera-to-world matrix (row-major) is a rigid motion: an
/// orthonormal rotation with determinant +1 in the upper-left 3×3 and a
/// bottom row of `[0, 0, 0, 1]`. Rays are built from these columns as
/// directions, so a scale, shear or mirror would silently distort the scene.
pub fn check_rigid(m: &[[f64; 4]; 4]) -> Result<(), String> {
    let bottom = m[3];
    let expected = [0.0, 0.0, 0.0, 1.0];
    if bottom
        .iter()
        .zip(expected)
        .any(|(x, e)| (x - e).abs() > BOTTOM_ROW_TOLERANCE)
    {
        return Err(format!(
            "the bottom row must be [0, 0, 0, 1], found [{}, {}, {}, {}]",
            bottom[0], bottom[1], bottom[2], bottom[3]
        ));
    }
    let mut worst = 0f64;
    for i in 0..3 {
        for j in 0..3 {
            let dot: f64 = (0..3).map(|k| m[k][i] * m[k][j]).sum();
            let identity = if i == j { 1.0 } else { 0.0 };
            worst = worst.max((dot - identity).abs());
        }
    }
    if worst > ORTHONORMAL_TOLERANCE {
        return Err(format!(
            "the rotation (upper-left 3×3) is not orthonormal: RᵀR differs from the identity by {worst:.3e} \
             (tolerance {ORTHONORMAL_TOLERANCE:.0e}); the pose may carry a scale or shear"
        ));
    }
    let det = m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
        - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
        + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0]);
    if det < 0.0 {
        return Err(
            "the rotation (upper-left 3×3) is a reflection (determinant -1): the axes are mirrored"
                .into(),
        );
    }
    Ok(())
}

/// Finds the image a frame's `file_path` names, relative to `folder`. NeRF-
/// synthetic files write `./train/r_0` (a leading `./`, no extension, PNG
/// meant); others write the file name in full. The path as written wins; a
/// `.png` is tried only when that does not exist and the name has no image
/// extension of its own. A name that leads to something other than a file
/// (a folder, a named pipe, a device such as `/dev/stdin`) is refused by
/// what it is; a missing one says so, naming any file there whose name
/// differs only in how its accents are written. The error names the image
/// path and is of its kind ([`SceneError::NotFound`] for a missing one); a
/// loader tells it of the frame (see [`SceneError::in_frame_of`]).
pub fn resolve_image_path(folder: &Path, file_path: &str) -> SceneResult<PathBuf> {
    if let Some(at) = file_path.find('\0') {
        return Err(SceneError::new(
            folder,
            format!(
                "`file_path` {file_path:?} holds a NUL character (\\0) at byte {at}, which no \
                 file name can hold: write the image's path there"
            ),
        ));
    }
    let relative = file_path.strip_prefix("./").unwrap_or(file_path);
    let as_written = folder.join(relative);
    if as_written.is_file() {
        return Ok(as_written);
    }
    if crate::files::exists_at_all(&as_written) {
        return Err(SceneError::unreadable(
            &as_written,
            not_an_image_file(file_path, &as_written),
        ));
    }
    let has_image_extension = as_written
        .extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| ["png", "jpg", "jpeg"].contains(&e.to_ascii_lowercase().as_str()));
    if has_image_extension {
        return Err(SceneError::not_found(
            &as_written,
            image_not_found(&as_written, None),
        ));
    }
    let mut with_png = as_written.clone().into_os_string();
    with_png.push(".png");
    let with_png = PathBuf::from(with_png);
    if with_png.is_file() {
        Ok(with_png)
    } else if crate::files::exists_at_all(&with_png) {
        Err(SceneError::unreadable(
            &with_png,
            not_an_image_file(file_path, &with_png),
        ))
    } else {
        Err(SceneError::not_found(
            &with_png,
            image_not_found(&with_png, Some(&as_written)),
        ))
    }
}

/// "image file not found: PATH", with the other name tried and, where the
/// folder holds a name that differs only in how its accents are written,
/// that name.
pub fn image_not_found(path: &Path, also_tried: Option<&Path>) -> String {
    let mut message = format!("image file not found: {}", shown(path));
    if let Some(other) = also_tried {
        message += &format!(" (also tried {})", shown(other));
    }
    let hint = super::names::lookalike_hint(path)
        .or_else(|| also_tried.and_then(super::names::lookalike_hint));
    if let Some(hint) = hint {
        message += &format!("; {hint}");
    }
    message
}

/// Why the `file_path` `written`, which leads to `path`, is not an image
/// file: what is there instead, in words, and what to write instead.
fn not_an_image_file(written: &str, path: &Path) -> String {
    let what = what_is_there(path);
    let fix = "`file_path` must name a PNG or JPEG file";
    if Path::new(written) == path {
        format!("`file_path` {written:?} is {what}: {fix}")
    } else {
        format!(
            "`file_path` {written:?} leads to {}, which is {what}: {fix}",
            shown(path)
        )
    }
}

/// What is at `path`, which is not a regular file, in words: "a folder,
/// not a file", "a device, not a file", "a symbolic link that loops …".
/// What counts is what the name leads to through any links:
/// `/dev/stdin` is a link to a descriptor, and the device or pipe behind it
/// is what a reader would meet.
pub fn what_is_there(path: &Path) -> String {
    match std::fs::metadata(path) {
        Ok(meta) => match kind_of(&meta) {
            Some(kind) => format!("{kind}, not a file"),
            None => crate::files::describe_unreadable(
                path,
                &std::io::Error::other("not a regular file"),
            ),
        },
        Err(e) => crate::files::describe_unreadable(path, &e),
    }
}

/// What a path that is not a regular file is, in a few words.
fn kind_of(meta: &std::fs::Metadata) -> Option<&'static str> {
    if meta.is_dir() {
        return Some("a folder");
    }
    #[cfg(unix)]
    {
        use std::os::unix::fs::FileTypeExt;
        let kind = meta.file_type();
        if kind.is_fifo() {
            return Some("a named pipe (FIFO)");
        } else if kind.is_socket() {
            return Some("a socket");
        } else if kind.is_block_device() || kind.is_char_device() {
            return Some("a device");
        }
    }
    None
}

/// Checks the integer downscale factor of [`super::LoadOptions`].
pub fn check_downscale(path: &Path, downscale: u32) -> SceneResult<()> {
    if downscale == 0 {
        return Err(SceneError::new(
            path,
            "downscale must be a whole number ≥ 1 (1 keeps full resolution), got 0",
        ));
    }
    Ok(())
}

/// A frame as its JSON file describes it, before its image is read.
#[derive(Debug, Clone)]
pub struct FrameSource {
    /// The JSON file that lists the frame.
    pub json_path: PathBuf,
    /// The frame's index in that file's `frames` array.
    pub index: usize,
    pub image_path: PathBuf,
    pub camera_to_world: Mat4,
}

impl FrameSource {
    /// An error about this frame, naming its JSON file and index.
    pub fn error(&self, problem: impl Into<String>) -> SceneError {
        SceneError::in_frame(&self.json_path, self.index, problem)
    }
}

/// A frame's decoded image.
#[derive(Debug, Clone)]
pub struct DecodedImage {
    /// The size of the file's image, before any downscale.
    pub width: u32,
    pub height: u32,
    /// The image after the downscale.
    pub image: ImageRgba8,
    pub file_has_alpha: bool,
}

/// Decodes every frame's image in parallel and downscales it by `downscale`,
/// then checks that all have the same size. Errors name the JSON file, the
/// frame and the image; when several frames are bad, the first in `sources`
/// order is reported, so the message does not depend on thread timing.
pub fn decode_images(sources: &[FrameSource], downscale: u32) -> SceneResult<Vec<DecodedImage>> {
    // Each decode may use its share of the memory available: as many run
    // at once as rayon has threads (or frames, if fewer).
    let decodes_at_once = rayon::current_num_threads().min(sources.len()).max(1);
    let results: Vec<SceneResult<DecodedImage>> = sources
        .par_iter()
        .map(|source| decode_one(source, downscale, decodes_at_once))
        .collect();
    let decoded = results.into_iter().collect::<SceneResult<Vec<_>>>()?;
    check_same_size(sources, &decoded)?;
    Ok(decoded)
}

fn decode_one(
    source: &FrameSource,
    downscale: u32,
    decodes_at_once: usize,
) -> SceneResult<DecodedImage> {
    let image_error =
        |problem: &str| source.error(format!("image {}: {problem}", shown(&source.image_path)));
    // Told of the frame that lists the image, of the image's own kind (not
    // found, too large, …).
    let loaded = load_image_sharing(&source.image_path, decodes_at_once).map_err(|e| {
        let problem = format!("image {}: {}", shown(&source.image_path), e.problem());
        e.in_frame_of(&source.json_path, source.index, problem)
    })?;
    let (width, height) = (loaded.image.width, loaded.image.height);
    if width / downscale == 0 || height / downscale == 0 {
        return Err(image_error(&format!(
            "downscale {downscale} leaves no pixels of a {width}×{height} image"
        )));
    }
    // Downscaling here, inside the parallel loop, keeps only the small image
    // alive and spreads the averaging across threads; at full resolution
    // the decoded image is kept as it is, not copied.
    let image = if downscale == 1 {
        loaded.image
    } else {
        loaded.image.downscaled(downscale)
    };
    Ok(DecodedImage {
        width,
        height,
        image,
        file_has_alpha: loaded.file_has_alpha,
    })
}

/// Every model assumes one resolution for the whole scene, so a frame of
/// another size is an error naming both images.
fn check_same_size(sources: &[FrameSource], decoded: &[DecodedImage]) -> SceneResult<()> {
    let (Some(first_source), Some(first)) = (sources.first(), decoded.first()) else {
        return Ok(());
    };
    for (source, image) in sources.iter().zip(decoded) {
        if (image.width, image.height) != (first.width, first.height) {
            let first_file = shown(Path::new(
                first_source.json_path.file_name().unwrap_or_default(),
            ));
            return Err(source.error(format!(
                "frames of different sizes: image {} is {}×{}, but image {} (frame {} of {first_file}) is {}×{}",
                shown(&source.image_path),
                image.width,
                image.height,
                shown(&first_source.image_path),
                first_source.index,
                first.width,
                first.height,
            )));
        }
    }
    Ok(())
}

/// Helpers that build small scenes on disk for the loaders' tests.
#[cfg(test)]
pub(crate) mod test_support {
    use std::path::Path;

    use serde_json::{Value, json};

    use crate::scene::ImageRgba8;

    /// A PNG with an alpha channel, every pixel half transparent grey.
    pub fn write_rgba_png(path: &Path, width: u32, height: u32) {
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        let data = [128u8, 128, 128, 128].repeat((width * height) as usize);
        ImageRgba8::new(width, height, data).save_png(path).unwrap();
    }

    /// An 8-bit RGB PNG (no alpha channel).
    pub fn write_rgb_png(path: &Path, width: u32, height: u32) {
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        image::RgbImage::from_pixel(width, height, image::Rgb([10, 200, 30]))
            .save(path)
            .unwrap();
    }

    pub fn write_json(path: &Path, value: &Value) {
        std::fs::write(path, serde_json::to_string_pretty(value).unwrap()).unwrap();
    }

    /// A camera-to-world matrix, rows as in the JSON files: a rotation by 90°
    /// about z, so that a row/column mix-up shows, and a translation.
    pub fn pose_json(tx: f64, ty: f64, tz: f64) -> Value {
        json!([
            [0.0, -1.0, 0.0, tx],
            [1.0, 0.0, 0.0, ty],
            [0.0, 0.0, 1.0, tz],
            [0.0, 0.0, 0.0, 1.0]
        ])
    }

    /// Asserts that `message` contains every one of `parts`.
    #[track_caller]
    pub fn assert_mentions(message: &str, parts: &[&str]) {
        for part in parts {
            assert!(
                message.contains(part),
                "error {message:?} does not mention {part:?}"
            );
        }
    }
}

#[cfg(test)]
mod tests {
    use glam::Vec3;
    use serde_json::json;

    use super::test_support::*;
    use super::*;

    #[test]
    fn matrix_rows_become_matrix_rows() {
        let m = parse_transform_matrix(&pose_json(1.0, 2.0, 3.0)).unwrap();
        assert_eq!(m.w_axis.truncate(), Vec3::new(1.0, 2.0, 3.0));
        // Row 1 is [1, 0, 0, ...]: the camera's x axis (column 0) points to +y.
        assert_eq!(m.x_axis.truncate(), Vec3::Y);
        assert_eq!(m.y_axis.truncate(), -Vec3::X);
        assert_eq!(m.row(3), Vec4::new(0.0, 0.0, 0.0, 1.0));
    }

    #[test]
    fn matrix_of_wrong_shape_is_rejected() {
        let three_by_four = json!([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]);
        let e = parse_transform_matrix(&three_by_four).unwrap_err();
        assert_mentions(&e, &["4×4", "3 rows"]);
        let short_row = json!([[1, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]);
        assert_mentions(
            &parse_transform_matrix(&short_row).unwrap_err(),
            &["row 0 has 3 entries"],
        );
        let text = json!([[1, 0, 0, "x"], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]);
        assert_mentions(
            &parse_transform_matrix(&text).unwrap_err(),
            &["row 0 column 3", "string"],
        );
        let null = json!([[1, 0, 0, 0], [0, null, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]);
        assert_mentions(
            &parse_transform_matrix(&null).unwrap_err(),
            &["row 1 column 1", "NaN"],
        );
    }

    #[test]
    fn matrix_entry_beyond_f32_is_not_finite() {
        let huge = json!([[1, 0, 0, 1e39], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]);
        assert_mentions(
            &parse_transform_matrix(&huge).unwrap_err(),
            &["row 0 column 3", "not a finite"],
        );
    }

    #[test]
    fn scaled_rotation_is_not_orthonormal() {
        let scaled = json!([[2, 0, 0, 0], [0, 2, 0, 0], [0, 0, 2, 0], [0, 0, 0, 1]]);
        assert_mentions(
            &parse_transform_matrix(&scaled).unwrap_err(),
            &["not orthonormal"],
        );
        // Within tolerance: accepted.
        let nearly = json!([[1.0001, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]);
        assert!(parse_transform_matrix(&nearly).is_ok());
    }

    #[test]
    fn mirrored_axes_are_rejected() {
        let mirror = json!([[-1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]);
        assert_mentions(
            &parse_transform_matrix(&mirror).unwrap_err(),
            &["reflection"],
        );
    }

    #[test]
    fn bottom_row_must_be_homogeneous() {
        let bad = json!([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0.5, 1]]);
        assert_mentions(
            &parse_transform_matrix(&bad).unwrap_err(),
            &["bottom row", "[0, 0, 0, 1]"],
        );
    }

    #[test]
    fn malformed_json_names_line_and_column() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("broken.json");
        std::fs::write(&path, "{\n  \"a\": 1,\n  \"b\": [1, 2,, 3]\n}\n").unwrap();
        let e = read_json(&path).unwrap_err().to_string();
        assert_mentions(&e, &["broken.json", "malformed JSON", "line 3, column 14"]);
        // The position is given once, not twice.
        assert_eq!(e.matches("line 3").count(), 1, "{e}");
    }

    #[test]
    fn missing_json_file_is_named() {
        let dir = tempfile::tempdir().unwrap();
        let e = read_json(&dir.path().join("absent.json"))
            .unwrap_err()
            .to_string();
        assert_mentions(&e, &["absent.json", "file not found"]);
    }

    #[test]
    fn image_path_with_and_without_extension() {
        let dir = tempfile::tempdir().unwrap();
        write_rgba_png(&dir.path().join("train/r_0.png"), 2, 2);
        let want = dir.path().join("train/r_0.png");
        for written in [
            "./train/r_0",
            "train/r_0",
            "./train/r_0.png",
            "train/r_0.png",
        ] {
            assert_eq!(
                resolve_image_path(dir.path(), written).unwrap(),
                want,
                "{written}"
            );
        }
        let e = resolve_image_path(dir.path(), "./train/r_1").unwrap_err();
        assert!(matches!(e, SceneError::NotFound { .. }), "{e:?}");
        assert_mentions(e.problem(), &["not found", "r_1.png"]);
        let e = resolve_image_path(dir.path(), "train/r_1.jpg").unwrap_err();
        assert_mentions(e.problem(), &["not found", "r_1.jpg"]);
    }
}
