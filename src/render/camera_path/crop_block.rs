//! The `crop` block of nerfstudio's `camera_path.json`: the crop box its
//! viewer had on when the path was saved, which `ns-render` renders with.
//!
//! The block, as nerfstudio's viewer writes it (`viewer/render_panel.py`)
//! and `ns-render` reads it (`scripts/render.py`, `get_crop_from_json`,
//! which builds `OrientedBox.from_params(center, rot, scale)` in
//! `data/scene_box.py`), is `null` or
//!
//! - `crop_center`: the box's centre, 3 numbers (world units);
//! - `crop_scale`: its full side lengths, 3 numbers (a point is inside when
//!   its offset along each of the box's axes is within half of them);
//! - `crop_rot`: roll, pitch, yaw in radians (optional, zero when absent):
//!   the box turned by `Rz(yaw) · Ry(pitch) · Rx(roll)`, i.e. about the
//!   world's x, then y, then z axis (viser's `SO3.from_rpy_radians`), the
//!   same order as `--crop`'s `,rx,ry,rz`;
//! - `crop_bg_color`: `{"r", "g", "b"}`, 0 to 255, the colour nerfstudio
//!   shows outside the box. zrak keeps it so a file it rewrites still holds
//!   it, but renders its own background (a crop box in zrak shows the
//!   scene's background where it leaves nothing).
//!
//! The block is in the file's frame, as the poses are: moving a path into
//! another scene's world moves its box the same way.

use glam::{DMat3, DMat4, DQuat, DVec3, EulerRot, Quat};
use serde_json::{Map, Value, json};

use crate::scene::crop::CropBox;
use crate::scene::pose::describe as describe_value;

/// The colour written when a box has none of its own: black, nerfstudio's
/// default `CropData.background_color`.
pub const DEFAULT_BACKGROUND: [f64; 3] = [0.0, 0.0, 0.0];

/// A parsed `crop` block.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PathCrop {
    pub crop: CropBox,
    /// `crop_bg_color`, 0 to 255 per channel.
    pub background: [f64; 3],
}

impl PathCrop {
    pub fn new(crop: CropBox) -> Self {
        Self {
            crop,
            background: DEFAULT_BACKGROUND,
        }
    }

    /// The block moved by the similarity `change` (a rotation times a
    /// positive uniform scale, and a translation), as the file's poses are.
    pub fn moved(&self, change: DMat4) -> PathCrop {
        let linear = DMat3::from_mat4(change);
        let scale = linear.x_axis.length();
        let rotation = DQuat::from_mat3(&(linear * (1.0 / scale)));
        let centre = change.transform_point3(self.crop.centre.as_dvec3());
        let turned = rotation * DQuat::from_array(self.crop.rotation.to_array().map(f64::from));
        PathCrop {
            crop: CropBox {
                centre: centre.as_vec3(),
                size: (self.crop.size.as_dvec3() * scale).as_vec3(),
                rotation: Quat::from_array(turned.normalize().to_array().map(|x| x as f32)),
            },
            background: self.background,
        }
    }

    /// The block as nerfstudio writes it.
    pub fn to_json(&self) -> Value {
        let (yaw, pitch, roll) = self.crop.rotation.to_euler(EulerRot::ZYX);
        let [r, g, b] = self.background;
        json!({
            "crop_center": self.crop.centre.to_array(),
            "crop_scale": self.crop.size.to_array(),
            "crop_rot": [roll, pitch, yaw],
            "crop_bg_color": {"r": r, "g": g, "b": b},
        })
    }
}

/// The `crop` field of a camera path: `null` when absent or null.
pub fn crop_to_json(crop: Option<&PathCrop>) -> Value {
    crop.map_or(Value::Null, PathCrop::to_json)
}

/// Parses the file's `crop` field (`None` when it is absent or null).
/// Errors name the field: `crop.crop_scale[1]`.
pub fn parse_crop(value: Option<&Value>) -> Result<Option<PathCrop>, String> {
    let object = match value {
        None | Some(Value::Null) => return Ok(None),
        Some(Value::Object(object)) => object,
        Some(other) => {
            return Err(format!(
                "`crop` must be null or an object with crop_center, crop_scale, crop_rot and \
                 crop_bg_color, found {}",
                describe_value(other)
            ));
        }
    };
    let centre = triple(object, "crop_center")?.ok_or("missing field `crop.crop_center`")?;
    let size = triple(object, "crop_scale")?.ok_or("missing field `crop.crop_scale`")?;
    if let Some(axis) = (0..3).find(|&i| size[i] <= 0.0) {
        return Err(format!(
            "`crop.crop_scale[{axis}]` = {} must be above zero: it is the box's full side length",
            size[axis]
        ));
    }
    let [roll, pitch, yaw] = triple(object, "crop_rot")?.unwrap_or([0.0; 3]);
    let rotation = DQuat::from_euler(EulerRot::ZYX, yaw, pitch, roll);
    let background = match object.get("crop_bg_color") {
        None | Some(Value::Null) => DEFAULT_BACKGROUND,
        Some(Value::Object(colour)) => {
            let mut rgb = [0.0; 3];
            for (i, key) in ["r", "g", "b"].into_iter().enumerate() {
                let name = format!("crop.crop_bg_color.{key}");
                let value = colour
                    .get(key)
                    .ok_or_else(|| format!("missing field `{name}`"))?;
                let number = number(value, &name)?;
                if !(0.0..=255.0).contains(&number) {
                    return Err(format!("`{name}` = {number} must be 0 to 255"));
                }
                rgb[i] = number;
            }
            rgb
        }
        Some(other) => {
            return Err(format!(
                "`crop.crop_bg_color` must be an object {{\"r\", \"g\", \"b\"}}, found {}",
                describe_value(other)
            ));
        }
    };
    let crop = CropBox {
        centre: DVec3::from_array(centre).as_vec3(),
        size: DVec3::from_array(size).as_vec3(),
        rotation: Quat::from_array(rotation.to_array().map(|x| x as f32)),
    };
    crop.check()
        .map_err(|problem| format!("`crop`: {problem}"))?;
    Ok(Some(PathCrop { crop, background }))
}

/// Three finite numbers at `crop.KEY`, or `None` when the key is absent.
fn triple(object: &Map<String, Value>, key: &str) -> Result<Option<[f64; 3]>, String> {
    let name = format!("crop.{key}");
    let items = match object.get(key) {
        None | Some(Value::Null) => return Ok(None),
        Some(Value::Array(items)) => items,
        Some(other) => {
            return Err(format!(
                "`{name}` must be a list of 3 numbers, found {}",
                describe_value(other)
            ));
        }
    };
    if items.len() != 3 {
        return Err(format!(
            "`{name}` must hold 3 numbers (x, y, z), found {}",
            items.len()
        ));
    }
    let mut out = [0.0; 3];
    for (i, item) in items.iter().enumerate() {
        out[i] = number(item, &format!("{name}[{i}]"))?;
    }
    Ok(Some(out))
}

fn number(value: &Value, name: &str) -> Result<f64, String> {
    finite(value, name)
}

/// A finite number at `field`.
pub(super) fn finite(value: &Value, field: &str) -> Result<f64, String> {
    match value {
        Value::Number(n) => n
            .as_f64()
            .filter(|x| x.is_finite())
            .ok_or_else(|| format!("`{field}` = {n} is not a finite number")),
        Value::String(s) if ["NaN", "Infinity", "-Infinity"].contains(&s.as_str()) => Err(format!(
            "`{field}` is {s}: every number in a camera path must be finite"
        )),
        other => Err(format!(
            "`{field}` must be a number, found {}",
            describe_value(other)
        )),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::camera_path::nerfstudio::CameraPathFile;
    use glam::Vec3;

    fn close(a: Vec3, b: Vec3, tolerance: f32) -> bool {
        (a - b).abs().max_element() <= tolerance
    }

    #[test]
    fn a_crop_block_round_trips() {
        let crop = PathCrop {
            crop: CropBox {
                centre: Vec3::new(0.25, -0.5, 0.125),
                size: Vec3::new(1.5, 0.75, 2.0),
                rotation: Quat::from_euler(EulerRot::ZYX, 0.4, -0.2, 0.1),
            },
            background: [10.0, 20.0, 255.0],
        };
        let read = parse_crop(Some(&crop.to_json())).unwrap().unwrap();
        assert_eq!(read.crop.centre, crop.crop.centre);
        assert_eq!(read.crop.size, crop.crop.size);
        assert_eq!(read.background, crop.background);
        // Through Euler angles and back: f32 rounding of a unit quaternion.
        assert!(
            read.crop.rotation.angle_between(crop.crop.rotation) < 1e-5,
            "{} vs {}",
            read.crop.rotation,
            crop.crop.rotation
        );
        assert_eq!(parse_crop(Some(&crop_to_json(None))), Ok(None));
        assert_eq!(parse_crop(None), Ok(None));
    }

    #[test]
    fn a_block_of_nerfstudios_documented_fields_loads_to_the_expected_box() {
        // What nerfstudio's viewer writes for a box centred at (1, 2, 3),
        // sides 2 × 4 × 6, turned 90° about z (yaw), on a grey background.
        let block = json!({
            "crop_center": [1.0, 2.0, 3.0],
            "crop_scale": [2.0, 4.0, 6.0],
            "crop_rot": [0.0, 0.0, std::f64::consts::FRAC_PI_2],
            "crop_bg_color": {"r": 128, "g": 128, "b": 128},
        });
        let crop = parse_crop(Some(&block)).unwrap().unwrap();
        assert_eq!(crop.crop.centre, Vec3::new(1.0, 2.0, 3.0));
        assert_eq!(crop.crop.size, Vec3::new(2.0, 4.0, 6.0));
        assert_eq!(crop.background, [128.0; 3]);
        // Yaw 90°: the box's x side (2 long) lies along the world's y.
        assert!(close(crop.crop.rotation * Vec3::X, Vec3::Y, 1e-6));
        let aabb = crop.crop.bounding_aabb();
        assert!(close(aabb.min, Vec3::new(-1.0, 1.0, 0.0), 1e-5), "{aabb:?}");
        assert!(close(aabb.max, Vec3::new(3.0, 3.0, 6.0), 1e-5), "{aabb:?}");
        // The older block without crop_rot is axis-aligned; roll turns
        // about x first.
        let plain = parse_crop(Some(&json!({
            "crop_center": [0, 0, 0], "crop_scale": [1, 1, 1],
            "crop_bg_color": {"r": 0, "g": 0, "b": 0},
        })))
        .unwrap()
        .unwrap();
        assert_eq!(plain.crop.rotation, Quat::IDENTITY);
        let rolled = parse_crop(Some(&json!({
            "crop_center": [0, 0, 0], "crop_scale": [1, 1, 1],
            "crop_rot": [std::f64::consts::FRAC_PI_2, 0.0, 0.0],
            "crop_bg_color": {"r": 0, "g": 0, "b": 0},
        })))
        .unwrap()
        .unwrap();
        assert!(close(rolled.crop.rotation * Vec3::Y, Vec3::Z, 1e-6));
    }

    #[test]
    fn a_malformed_block_names_the_field() {
        let refusal = |block: &str| {
            let value: Value = serde_json::from_str(block).unwrap();
            parse_crop(Some(&value)).unwrap_err()
        };
        let ok_colour = r#""crop_bg_color": {"r": 0, "g": 0, "b": 0}"#;
        assert_eq!(
            refusal(&format!(
                r#"{{"crop_center": [0, 0], "crop_scale": [1, 1, 1], {ok_colour}}}"#
            )),
            "`crop.crop_center` must hold 3 numbers (x, y, z), found 2"
        );
        assert_eq!(
            refusal(&format!(
                r#"{{"crop_center": [0, 0, 0], "crop_scale": [1, -2, 1], {ok_colour}}}"#
            )),
            "`crop.crop_scale[1]` = -2 must be above zero: it is the box's full side length"
        );
        assert_eq!(
            refusal(&format!(
                r#"{{"crop_center": [0, 0, 0], "crop_scale": [1, 1, 1], "crop_rot": [0, 0, 0, 1], {ok_colour}}}"#
            )),
            "`crop.crop_rot` must hold 3 numbers (x, y, z), found 4"
        );
        assert_eq!(
            refusal(r#"{"crop_scale": [1, 1, 1]}"#),
            "missing field `crop.crop_center`"
        );
        assert_eq!(
            refusal(
                r#"{"crop_center": [0, 0, 0], "crop_scale": [1, 1, 1], "crop_bg_color": {"r": 0, "g": 300, "b": 0}}"#
            ),
            "`crop.crop_bg_color.g` = 300 must be 0 to 255"
        );
        assert!(refusal("[1, 2, 3]").starts_with("`crop` must be null or an object"));
        // Python writes NaN, which is no JSON: the file reader quotes it
        // and the block names the field that holds it.
        let mut file = json!({
            "camera_type": "perspective",
            "render_height": 4, "render_width": 4, "fps": 1, "seconds": 1,
            "camera_path": [{
                "camera_to_world": [1,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1],
                "fov": 50, "aspect": 1,
            }],
        })
        .to_string();
        file.insert_str(
            file.len() - 1,
            r#","crop": {"crop_center": [0, NaN, 0], "crop_scale": [1, 1, 1]}"#,
        );
        let error = CameraPathFile::parse(&file).unwrap_err();
        assert!(error.contains("`crop.crop_center[1]` is NaN"), "{error}");
    }

    #[test]
    fn a_path_file_writes_its_crop_box_back_and_moves_it_with_the_poses() {
        use crate::render::camera_path::{CameraPath, Keyframe, look_at};
        let path = CameraPath::new(vec![
            Keyframe::new(
                look_at(DVec3::new(4.0, 0.0, 1.0), DVec3::ZERO, DVec3::Z),
                40.0,
            ),
            Keyframe::new(
                look_at(DVec3::new(0.0, 4.0, 1.0), DVec3::ZERO, DVec3::Z),
                40.0,
            ),
        ]);
        // Written for a scene whose original frame is zrak's scaled by 2.
        let to_original = DMat4::from_scale(DVec3::splat(2.0));
        let mut file = CameraPathFile::new(path, 32, 24, 4.0, to_original);
        let crop = CropBox::axis_aligned(Vec3::new(0.5, 0.0, 0.0), Vec3::splat(1.0));
        file.set_crop(Some(crop));
        let read = CameraPathFile::parse(&file.to_text()).unwrap();
        assert_eq!(read.crop, Some(PathCrop::new(crop)));
        assert!(file.to_text().contains("\"crop_center\""));
        // Read for a scene whose zrak world is the original frame: the box
        // doubles, as the camera positions do.
        let moved = read.moved_into(DMat4::IDENTITY).crop.unwrap().crop;
        assert!(close(moved.centre, Vec3::new(1.0, 0.0, 0.0), 1e-6));
        assert!(close(moved.size, Vec3::splat(2.0), 1e-6));
        file.set_crop(None);
        assert_eq!(CameraPathFile::parse(&file.to_text()).unwrap().crop, None);
    }

    #[test]
    fn a_box_moves_with_the_poses() {
        // The file's frame is zrak's scaled by 2 and moved by (1, 0, 0).
        let change = DMat4::from_translation(DVec3::X) * DMat4::from_scale(DVec3::splat(2.0));
        let crop = PathCrop::new(CropBox::axis_aligned(Vec3::new(0.0, 1.0, 0.0), Vec3::ONE));
        let moved = crop.moved(change);
        assert!(close(moved.crop.centre, Vec3::new(1.0, 2.0, 0.0), 1e-6));
        assert!(close(moved.crop.size, Vec3::splat(2.0), 1e-6));
        assert!(moved.crop.rotation.angle_between(Quat::IDENTITY) < 1e-6);
        for corner in crop.crop.corners() {
            let expected = change.transform_point3(corner.as_dvec3()).as_vec3();
            assert!(
                moved
                    .crop
                    .corners()
                    .iter()
                    .any(|c| close(*c, expected, 1e-5))
            );
        }
    }
}
