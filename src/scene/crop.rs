//! The crop box: the part of the scene that renders and exports keep.
//! Outside it a render shows the background and a mesh or point cloud has
//! nothing, which hides floaters and cuts an object out of its
//! surroundings.
//!
//! A run keeps its crop box in `crop.json` in its folder.

use std::path::{Path, PathBuf};

use glam::{Quat, Vec3};
use serde::{Deserialize, Serialize};

use crate::scene::Aabb;

/// The name of a run's crop box file.
pub const CROP_FILE: &str = "crop.json";

/// The largest `crop.json` read: zrak writes about 200 bytes (nine
/// numbers), so 64 kB is room for any hand-written one.
const MAX_CROP_FILE_BYTES: u64 = 64 << 10;

/// A box of `size` centred at `centre`, turned by `rotation` (world
/// coordinates).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CropBox {
    pub centre: Vec3,
    pub size: Vec3,
    /// From the box's own axes to the world's (identity: axis-aligned).
    pub rotation: Quat,
}

/// `crop.json`: the box's centre and size, and its rotation as a unit
/// quaternion `[x, y, z, w]` when it is turned.
#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct CropFile {
    centre: [f32; 3],
    size: [f32; 3],
    #[serde(default, skip_serializing_if = "Option::is_none")]
    rotation: Option<[f32; 4]>,
}

impl CropBox {
    /// An axis-aligned box.
    pub fn axis_aligned(centre: Vec3, size: Vec3) -> Self {
        Self {
            centre,
            size,
            rotation: Quat::IDENTITY,
        }
    }

    /// The box that fills `aabb`.
    pub fn of_aabb(aabb: &Aabb) -> Self {
        Self::axis_aligned(aabb.centre(), aabb.size())
    }

    /// Refuses a box that no render could use: non-finite numbers, a size
    /// not above zero, a rotation that is no unit quaternion.
    pub fn check(&self) -> Result<(), String> {
        if !(self.centre.is_finite() && self.size.is_finite() && self.rotation.is_finite()) {
            return Err(format!(
                "the crop box must be finite numbers, got centre {}, size {}",
                self.centre, self.size
            ));
        }
        if self.size.min_element() <= 0.0 {
            return Err(format!(
                "the crop box's size must be above zero on every axis, got {}",
                self.size
            ));
        }
        if (self.rotation.length() - 1.0).abs() > 1e-3 {
            return Err(format!(
                "the crop box's rotation must be a unit quaternion, got {} (length {})",
                self.rotation,
                self.rotation.length()
            ));
        }
        Ok(())
    }

    /// `point` in the box's own frame: its centre at the origin, its sides
    /// along the axes.
    fn local(&self, point: Vec3) -> Vec3 {
        self.rotation.inverse() * (point - self.centre)
    }

    /// Whether `point` is inside (or on) the box.
    pub fn contains(&self, point: Vec3) -> bool {
        let local = self.local(point);
        local.abs().cmple(0.5 * self.size).all()
    }

    /// The parameter interval `[t_enter, t_exit]` (with `t_enter ≥ t_min`)
    /// where `origin + t · direction` is inside the box, or `None` when the
    /// ray misses it: the slab test in the box's own frame, where it is
    /// axis-aligned (a rotation keeps lengths, so `t` is the same).
    pub fn intersect(&self, origin: Vec3, direction: Vec3, t_min: f32) -> Option<(f32, f32)> {
        let half = 0.5 * self.size;
        Aabb::new(-half, half).intersect(
            self.local(origin),
            self.rotation.inverse() * direction,
            t_min,
        )
    }

    /// The smallest axis-aligned box that holds this one.
    pub fn bounding_aabb(&self) -> Aabb {
        let half = 0.5 * self.size;
        let axes = [
            self.rotation * Vec3::X,
            self.rotation * Vec3::Y,
            self.rotation * Vec3::Z,
        ];
        let extent = axes[0].abs() * half.x + axes[1].abs() * half.y + axes[2].abs() * half.z;
        Aabb::new(self.centre - extent, self.centre + extent)
    }

    /// The box's eight corners (for drawing it).
    pub fn corners(&self) -> [Vec3; 8] {
        std::array::from_fn(|c| {
            let sign = Vec3::new(
                if c & 1 == 0 { -0.5 } else { 0.5 },
                if c & 2 == 0 { -0.5 } else { 0.5 },
                if c & 4 == 0 { -0.5 } else { 0.5 },
            );
            self.centre + self.rotation * (sign * self.size)
        })
    }

    /// Where a run keeps its crop box.
    pub fn path_in(run: &Path) -> PathBuf {
        run.join(CROP_FILE)
    }

    /// The crop box saved in run folder `run`, if any.
    pub fn load_from_run(run: &Path) -> Result<Option<CropBox>, String> {
        let path = Self::path_in(run);
        if !crate::files::exists_at_all(&path) {
            return Ok(None);
        }
        // A regular file of a bounded size only: a named pipe would block,
        // a link to a device be read until memory ran out.
        let text = crate::files::read_text_bounded(&path, MAX_CROP_FILE_BYTES, "a crop box")
            .map_err(|problem| {
                format!(
                    "{}: cannot read the crop box: {problem}; remove it, or give --crop to \
                     replace it",
                    path.display()
                )
            })?;
        let file: CropFile = serde_json::from_str(&text)
            .map_err(|e| format!("{}: not a crop box: {e}", path.display()))?;
        let crop = CropBox {
            centre: file.centre.into(),
            size: file.size.into(),
            rotation: file.rotation.map_or(Quat::IDENTITY, Quat::from_array),
        };
        crop.check()
            .map_err(|e| format!("{}: {e}", path.display()))?;
        Ok(Some(crop))
    }

    /// Saves the crop box in run folder `run` (`None` removes it).
    pub fn save_to_run(crop: Option<&CropBox>, run: &Path) -> Result<(), String> {
        let path = Self::path_in(run);
        match crop {
            Some(crop) => {
                let file = CropFile {
                    centre: crop.centre.into(),
                    size: crop.size.into(),
                    rotation: (crop.rotation != Quat::IDENTITY).then(|| crop.rotation.into()),
                };
                let text = serde_json::to_string_pretty(&file).expect("a crop box serialises");
                crate::files::write_bytes_atomically(&path, text.as_bytes())
                    .map_err(|e| format!("{}: cannot write the crop box: {e}", path.display()))
            }
            None => match std::fs::remove_file(&path) {
                Err(e) if e.kind() != std::io::ErrorKind::NotFound => Err(format!(
                    "{}: cannot remove the crop box: {e}",
                    path.display()
                )),
                _ => Ok(()),
            },
        }
    }
}

/// What `--crop` asks for.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum CropArg {
    /// No crop box, even if the run has one saved.
    None,
    Box(CropBox),
}

impl std::str::FromStr for CropArg {
    type Err = String;

    /// `none`; `cx,cy,cz,sx,sy,sz` (centre and size, axis-aligned); or
    /// those and three angles in degrees, `…,rx,ry,rz`: the box turned
    /// about the world's x, then y, then z axis.
    fn from_str(text: &str) -> Result<Self, String> {
        if text.trim().eq_ignore_ascii_case("none") {
            return Ok(CropArg::None);
        }
        let numbers: Vec<f32> = text
            .split(',')
            .map(|word| {
                word.trim()
                    .parse::<f32>()
                    .map_err(|_| format!("`{text}`: `{}` is not a number", word.trim()))
            })
            .collect::<Result<_, _>>()?;
        let rotation = match numbers.len() {
            6 => Quat::IDENTITY,
            9 => Quat::from_euler(
                glam::EulerRot::ZYX,
                numbers[8].to_radians(),
                numbers[7].to_radians(),
                numbers[6].to_radians(),
            ),
            n => {
                return Err(format!(
                    "`{text}`: a crop box is cx,cy,cz,sx,sy,sz (centre and size), optionally \
                     with ,rx,ry,rz (degrees), or `none`; got {n} numbers"
                ));
            }
        };
        let crop = CropBox {
            centre: Vec3::new(numbers[0], numbers[1], numbers[2]),
            size: Vec3::new(numbers[3], numbers[4], numbers[5]),
            rotation,
        };
        crop.check().map_err(|e| format!("`{text}`: {e}"))?;
        Ok(CropArg::Box(crop))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_axis_aligned_box_contains_and_clips_like_its_aabb() {
        let crop = CropBox::axis_aligned(Vec3::new(1.0, 0.0, 0.0), Vec3::new(2.0, 4.0, 6.0));
        assert!(crop.contains(Vec3::new(1.9, 1.9, -2.9)));
        assert!(!crop.contains(Vec3::new(2.1, 0.0, 0.0)));
        let aabb = crop.bounding_aabb();
        assert_eq!(
            aabb,
            Aabb::new(Vec3::new(0.0, -2.0, -3.0), Vec3::new(2.0, 2.0, 3.0))
        );
        let (t0, t1) = crop
            .intersect(Vec3::new(1.0, 0.0, 10.0), -Vec3::Z, 0.0)
            .unwrap();
        assert!((t0 - 7.0).abs() < 1e-5 && (t1 - 13.0).abs() < 1e-5);
        assert!(
            crop.intersect(Vec3::new(5.0, 0.0, 10.0), -Vec3::Z, 0.0)
                .is_none()
        );
    }

    #[test]
    fn a_turned_box_clips_rays_in_its_own_frame() {
        // A unit cube turned 45° about z: its corner reaches √½ along x.
        let crop = CropBox {
            centre: Vec3::ZERO,
            size: Vec3::ONE,
            rotation: Quat::from_rotation_z(45f32.to_radians()),
        };
        let reach = 0.5f32.sqrt();
        assert!(crop.contains(Vec3::new(reach - 0.01, 0.0, 0.0)));
        assert!(!crop.contains(Vec3::new(0.45, 0.45, 0.0)));
        let (t0, t1) = crop
            .intersect(Vec3::new(-5.0, 0.0, 0.0), Vec3::X, 0.0)
            .unwrap();
        assert!((t0 - (5.0 - reach)).abs() < 1e-5, "{t0}");
        assert!((t1 - (5.0 + reach)).abs() < 1e-5, "{t1}");
        let aabb = crop.bounding_aabb();
        assert!(
            (aabb.max - Vec3::new(reach, reach, 0.5))
                .abs()
                .max_element()
                < 1e-6
        );
        for corner in crop.corners() {
            assert!(aabb.contains(corner * 0.9999));
            assert!((corner.z.abs() - 0.5).abs() < 1e-6);
        }
    }

    #[test]
    fn the_command_line_takes_six_or_nine_numbers_or_none() {
        assert_eq!("none".parse(), Ok(CropArg::None));
        assert_eq!(
            "0,0,0.5, 1,2,3".parse(),
            Ok(CropArg::Box(CropBox::axis_aligned(
                Vec3::new(0.0, 0.0, 0.5),
                Vec3::new(1.0, 2.0, 3.0)
            )))
        );
        let Ok(CropArg::Box(turned)) = "0,0,0,1,1,1,0,0,90".parse::<CropArg>() else {
            panic!("nine numbers are a turned box");
        };
        assert!((turned.rotation * Vec3::X - Vec3::Y).length() < 1e-6);
        let refusal = |text: &str| text.parse::<CropArg>().unwrap_err();
        assert!(
            refusal("1,2,3").contains("got 3 numbers"),
            "{}",
            refusal("1,2,3")
        );
        assert_eq!(refusal("0,0,0,1,x,1"), "`0,0,0,1,x,1`: `x` is not a number");
        assert!(refusal("0,0,0,1,0,1").contains("above zero"));
        assert!(refusal("0,0,NaN,1,1,1").contains("finite"));
    }

    #[test]
    fn a_run_keeps_its_crop_box_in_crop_json() {
        let dir = tempfile::tempdir().unwrap();
        assert_eq!(CropBox::load_from_run(dir.path()), Ok(None));
        let crop = CropBox {
            centre: Vec3::new(0.1, -0.2, 0.3),
            size: Vec3::new(1.0, 2.0, 0.5),
            rotation: Quat::from_rotation_y(0.3),
        };
        CropBox::save_to_run(Some(&crop), dir.path()).unwrap();
        assert_eq!(CropBox::load_from_run(dir.path()), Ok(Some(crop)));
        // Axis-aligned boxes leave the rotation out.
        let plain = CropBox::axis_aligned(Vec3::ZERO, Vec3::ONE);
        CropBox::save_to_run(Some(&plain), dir.path()).unwrap();
        let text = std::fs::read_to_string(dir.path().join(CROP_FILE)).unwrap();
        assert!(!text.contains("rotation"), "{text}");
        assert_eq!(CropBox::load_from_run(dir.path()), Ok(Some(plain)));
        CropBox::save_to_run(None, dir.path()).unwrap();
        assert_eq!(CropBox::load_from_run(dir.path()), Ok(None));
        // A damaged file names itself and the problem.
        std::fs::write(
            dir.path().join(CROP_FILE),
            r#"{"centre":[0,0,0],"size":[1,-1,1]}"#,
        )
        .unwrap();
        let error = CropBox::load_from_run(dir.path()).unwrap_err();
        assert!(
            error.contains("crop.json") && error.contains("above zero"),
            "{error}"
        );
    }
}
