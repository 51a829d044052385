//! The NeRF paper's forward-facing captures in LLFF's layout (Mildenhall et
//! al. 2019, "Local Light Field Fusion"): a folder with `poses_bounds.npy`
//! and the photographs in `images/` (or `images_N/`, the same at 1/N).
//!
//! `poses_bounds.npy` is a NumPy array of N × 17 numbers, one row per
//! photograph in file-name order: a 3 × 5 matrix row by row, then the near
//! and far bounds of what the photograph sees (depths along its optical
//! axis). The matrix's first three columns are the camera's axes in the
//! world in LLFF's order [down, right, backwards], the fourth its position,
//! the fifth [height, width, focal] in pixels of the photographs the poses
//! were computed from.
//!
//! zrak reads them as the NeRF paper's `load_llff_data` does (its
//! `load_llff.py`): the axes reordered to [right, up, backwards] (OpenGL's,
//! zrak's camera axes), the scene scaled so that the nearest bound is
//! 1/[`BOUNDS_FACTOR`], and the poses moved so that their average pose (mean
//! position, mean viewing direction, mean up) is the identity: the cameras
//! then sit around the origin looking down −z, the frame normalised device
//! coordinates need ([`super::Scene::with_ndc`]). Every
//! [`HOLD_OUT_EVERY`]-th photograph is held out for validation.

use std::path::{Path, PathBuf};

use glam::{DMat3, DMat4, DVec3, DVec4, Mat4};
use serde_json::{Value, json};

use super::error::{SceneError, SceneResult, shown};
use super::pose::{FrameSource, check_downscale, check_rigid, decode_images};
use super::space::{self, SpaceAnalysis};
use super::{
    Aabb, Camera, Frame, ImageRgba8, Intrinsics, Lens, LoadOptions, Scene, SceneFormat,
    UnitCubeMapping, folder_name,
};

/// The file the poses and bounds are in.
pub const POSES_FILE: &str = "poses_bounds.npy";

/// Numbers per row of [`POSES_FILE`]: a 3 × 5 matrix, near, far.
pub const ROW_LENGTH: usize = 17;

/// Every `HOLD_OUT_EVERY`-th photograph (index 0, 8, 16, …) is held out,
/// the rest train: the NeRF paper's `llffhold` (its `configs/fern.txt`).
pub const HOLD_OUT_EVERY: usize = 8;

/// The scene is scaled by 1 / (nearest bound · `BOUNDS_FACTOR`), so that
/// nothing is seen nearer than 1/0.75 and NDC's near plane at
/// [`NDC_NEAR`] lies in front of everything: `bd_factor=.75` in the NeRF
/// paper's `load_llff_data`.
pub const BOUNDS_FACTOR: f64 = 0.75;

/// The near plane of normalised device coordinates after the rescale: the
/// NeRF paper's `ndc_rays(H, W, K[0][0], 1., rays_o, rays_d)` in
/// `run_nerf.py`.
pub const NDC_NEAR: f32 = 1.0;

/// The largest `poses_bounds.npy` read: 64 MiB, some 490 000 photographs.
const MAX_FILE_BYTES: u64 = 64 << 20;

/// The photographs' file types, by extension in any case (the NeRF paper's
/// code takes `JPG`, `jpg` and `png`).
const IMAGE_EXTENSIONS: [&str; 3] = ["png", "jpg", "jpeg"];

/// Whether `path` is a folder in the LLFF layout (holds `poses_bounds.npy`).
pub fn is_llff_folder(path: &Path) -> bool {
    crate::files::exists_at_all(&path.join(POSES_FILE))
}

/// One row of `poses_bounds.npy`, in zrak's camera axes and the file's world.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LlffView {
    /// Camera-to-world, OpenGL axes (x right, y up, z backwards).
    pub camera_to_world: DMat4,
    /// The size in pixels and focal length of the photographs the row was
    /// computed from.
    pub height: f64,
    pub width: f64,
    pub focal: f64,
    /// Depths along the optical axis between which the photograph sees
    /// the scene.
    pub near: f64,
    pub far: f64,
}

impl LlffView {
    /// The view a row describes. LLFF's columns [down, right, backwards]
    /// become zrak's [right, up, backwards] = [c1, −c0, c2]: the NeRF
    /// paper's `np.concatenate([poses[:, 1:2], -poses[:, 0:1], poses[:, 2:]], 1)`.
    pub fn from_row(row: &[f64; ROW_LENGTH]) -> Result<Self, String> {
        let column = |c: usize| DVec3::new(row[c], row[5 + c], row[10 + c]);
        let (down, right, backwards) = (column(0), column(1), column(2));
        let rotation = DMat3::from_cols(right, -down, backwards);
        let position = column(3);
        let [height, width, focal] = column(4).to_array();
        let rows: [[f64; 4]; 4] = std::array::from_fn(|r| {
            if r == 3 {
                [0.0, 0.0, 0.0, 1.0]
            } else {
                [
                    rotation.x_axis[r],
                    rotation.y_axis[r],
                    rotation.z_axis[r],
                    position[r],
                ]
            }
        });
        check_rigid(&rows).map_err(|problem| {
            format!(
                "{problem} (columns 0 to 2 of the 3 × 5 matrix are the camera's down, right \
                 and backwards axes)"
            )
        })?;
        for (name, value) in [
            ("height", height),
            ("width", width),
            ("focal length", focal),
        ] {
            if value <= 0.0 {
                return Err(format!(
                    "the {name} (column 4 of the 3 × 5 matrix holds height, width, focal) is \
                     {value}; it must be positive"
                ));
            }
        }
        let (near, far) = (row[15], row[16]);
        if !(near > 0.0 && far > near) {
            return Err(format!(
                "the bounds are near {near}, far {far}; they must be 0 < near < far"
            ));
        }
        Ok(Self {
            camera_to_world: DMat4::from_cols(
                rotation.x_axis.extend(0.0),
                rotation.y_axis.extend(0.0),
                rotation.z_axis.extend(0.0),
                position.extend(1.0),
            ),
            height,
            width,
            focal,
            near,
            far,
        })
    }

    /// The row `from_row` reads back as this view.
    pub fn to_row(&self) -> [f64; ROW_LENGTH] {
        let m = self.camera_to_world;
        let (right, up, backwards) = (m.x_axis.truncate(), m.y_axis.truncate(), m.z_axis);
        let columns = [
            -up,
            right,
            backwards.truncate(),
            m.w_axis.truncate(),
            DVec3::new(self.height, self.width, self.focal),
        ];
        let mut row = [0.0; ROW_LENGTH];
        for (c, column) in columns.iter().enumerate() {
            for r in 0..3 {
                row[5 * r + c] = column[r];
            }
        }
        row[15] = self.near;
        row[16] = self.far;
        row
    }
}

/// Reads `poses_bounds.npy`: one view per row. Errors name the file, and
/// the row (as the frame) when one row is wrong.
pub fn read_poses_bounds(path: &Path) -> SceneResult<Vec<LlffView>> {
    if !crate::files::exists_at_all(path) {
        return Err(SceneError::not_found(path, "no such file"));
    }
    let bytes = crate::files::read_regular_bounded(path, MAX_FILE_BYTES, POSES_FILE)
        .map_err(|problem| SceneError::unreadable(path, problem))?;
    let array = parse_npy(&bytes).map_err(|problem| SceneError::new(path, problem))?;
    let shape = &array.shape;
    if shape.len() != 2 || shape[1] != ROW_LENGTH || shape[0] == 0 {
        let transposed = if shape.len() == 2 && shape[0] == ROW_LENGTH {
            " (it looks transposed)"
        } else {
            ""
        };
        return Err(SceneError::new(
            path,
            format!(
                "holds an array of shape {}{transposed}; {POSES_FILE} must be N × \
                 {ROW_LENGTH}, N ≥ 1: for each image a 3 × 5 pose-and-intrinsics matrix row by \
                 row, then its near and far bounds",
                shape_text(shape)
            ),
        ));
    }
    array
        .values
        .chunks_exact(ROW_LENGTH)
        .enumerate()
        .map(|(index, values)| {
            let row: &[f64; ROW_LENGTH] = values.try_into().expect("rows of ROW_LENGTH");
            if let Some(column) = row.iter().position(|v| !v.is_finite()) {
                return Err(SceneError::in_frame(
                    path,
                    index,
                    format!(
                        "column {column} is {}; every value must be finite",
                        row[column]
                    ),
                ));
            }
            LlffView::from_row(row).map_err(|problem| SceneError::in_frame(path, index, problem))
        })
        .collect()
}

/// Writes `views` as `poses_bounds.npy` at `path` (NumPy format 1.0,
/// little-endian float64).
pub fn write_poses_bounds(path: &Path, views: &[LlffView]) -> SceneResult<()> {
    let values: Vec<f64> = views.iter().flat_map(|view| view.to_row()).collect();
    let bytes = npy_bytes(&[views.len(), ROW_LENGTH], &values);
    crate::files::write_bytes_atomically(path, &bytes)
        .map_err(|e| SceneError::new(path, format!("cannot write file: {e}")))
}

/// A NumPy array as read: its shape and its values in C (row-major) order.
#[derive(Debug, Clone, PartialEq)]
struct NpyArray {
    shape: Vec<usize>,
    values: Vec<f64>,
}

/// The first bytes of every `.npy` file (NumPy's `format.py`).
const NPY_MAGIC: &[u8] = b"\x93NUMPY";

/// Parses a `.npy` file of little-endian float64 or float32 (NumPy's file
/// format versions 1.0, 2.0 and 3.0: the magic string, the version, the
/// header's length, a Python dict literal with `descr`, `fortran_order`
/// and `shape`, then the values).
fn parse_npy(bytes: &[u8]) -> Result<NpyArray, String> {
    if bytes.len() < NPY_MAGIC.len() + 4 || !bytes.starts_with(NPY_MAGIC) {
        return Err("not a NumPy .npy file: it does not begin with \\x93NUMPY".into());
    }
    let (major, minor) = (bytes[6], bytes[7]);
    let (header_length, header_start) = match major {
        1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10),
        2 | 3 if bytes.len() >= 12 => (
            u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize,
            12,
        ),
        2 | 3 => return Err("the .npy header ends before its length".into()),
        _ => {
            return Err(format!(
                "NumPy .npy format version {major}.{minor}; zrak reads versions 1, 2 and 3"
            ));
        }
    };
    let header_end = header_start + header_length;
    if header_end > bytes.len() {
        return Err(format!(
            "the .npy header says it is {header_length} bytes long, but the file ends {} \
             bytes after it starts",
            bytes.len() - header_start
        ));
    }
    let header = std::str::from_utf8(&bytes[header_start..header_end])
        .map_err(|_| "the .npy header is not text".to_string())?;
    let descr = header_string(header, "descr")?;
    let fortran_order = header_bool(header, "fortran_order")?;
    let shape = header_shape(header)?;
    let item_size = match descr {
        "<f8" => 8,
        "<f4" => 4,
        other => {
            return Err(format!(
                "holds values of type '{}'; zrak reads little-endian floating point, '<f8' \
                 (float64) or '<f4' (float32)",
                super::escape_controls(other)
            ));
        }
    };
    let count = shape
        .iter()
        .try_fold(1usize, |product, &n| product.checked_mul(n))
        .ok_or_else(|| format!("the shape {} is too large", shape_text(&shape)))?;
    let data = &bytes[header_end..];
    if count.checked_mul(item_size) != Some(data.len()) {
        return Err(format!(
            "the header says shape {} of '{descr}' ({count} values of {item_size} bytes), but \
             {} bytes of data follow it",
            shape_text(&shape),
            data.len()
        ));
    }
    let stored: Vec<f64> = if item_size == 8 {
        data.chunks_exact(8)
            .map(|b| f64::from_le_bytes(b.try_into().expect("8 bytes")))
            .collect()
    } else {
        data.chunks_exact(4)
            .map(|b| f32::from_le_bytes(b.try_into().expect("4 bytes")) as f64)
            .collect()
    };
    // Fortran order stores the first index fastest: element (i, j) of a
    // rows × columns array at j · rows + i.
    let values = match (&shape[..], fortran_order) {
        (&[rows, columns], true) => (0..rows)
            .flat_map(|i| (0..columns).map(move |j| j * rows + i))
            .map(|at| stored[at])
            .collect(),
        (_, true) if shape.len() > 2 => {
            return Err("holds an array of more than 2 dimensions in Fortran order".into());
        }
        _ => stored,
    };
    Ok(NpyArray { shape, values })
}

/// The text after `'key':` in a `.npy` header's dict, or an error naming
/// the key.
fn header_value<'a>(header: &'a str, key: &str) -> Result<&'a str, String> {
    [format!("'{key}'"), format!("\"{key}\"")]
        .iter()
        .find_map(|quoted| header.find(quoted.as_str()).map(|at| at + quoted.len()))
        .and_then(|after| header[after..].trim_start().strip_prefix(':'))
        .map(str::trim_start)
        .ok_or_else(|| {
            format!(
                "the .npy header {} has no '{key}'",
                super::escape_controls(header.trim_end())
            )
        })
}

fn header_string<'a>(header: &'a str, key: &str) -> Result<&'a str, String> {
    let value = header_value(header, key)?;
    let quote = value.chars().next().filter(|c| *c == '\'' || *c == '"');
    quote
        .and_then(|quote| {
            let rest = &value[1..];
            rest.find(quote).map(|end| &rest[..end])
        })
        .ok_or_else(|| format!("the .npy header's '{key}' is not a quoted string"))
}

fn header_bool(header: &str, key: &str) -> Result<bool, String> {
    let value = header_value(header, key)?;
    if value.starts_with("True") {
        Ok(true)
    } else if value.starts_with("False") {
        Ok(false)
    } else {
        Err(format!(
            "the .npy header's '{key}' is neither True nor False"
        ))
    }
}

fn header_shape(header: &str) -> Result<Vec<usize>, String> {
    let value = header_value(header, "shape")?;
    let malformed = || "the .npy header's 'shape' is not a tuple of whole numbers".to_string();
    let inside = value
        .strip_prefix('(')
        .and_then(|rest| rest.find(')').map(|end| &rest[..end]))
        .ok_or_else(malformed)?;
    inside
        .split(',')
        .map(str::trim)
        .filter(|part| !part.is_empty())
        .map(|part| part.parse::<usize>().map_err(|_| malformed()))
        .collect()
}

fn shape_text(shape: &[usize]) -> String {
    let parts: Vec<String> = shape.iter().map(usize::to_string).collect();
    format!("({})", parts.join(", "))
}

/// A `.npy` file (format 1.0) holding `values` as little-endian float64 of
/// `shape`, in C order.
fn npy_bytes(shape: &[usize], values: &[f64]) -> Vec<u8> {
    let dims: Vec<String> = shape.iter().map(usize::to_string).collect();
    let trailing_comma = if shape.len() == 1 { "," } else { "" };
    let mut header = format!(
        "{{'descr': '<f8', 'fortran_order': False, 'shape': ({}{trailing_comma}), }}",
        dims.join(", ")
    );
    // NumPy pads the header with spaces and a newline so that the values
    // start at a multiple of 64 bytes.
    let unpadded = NPY_MAGIC.len() + 4 + header.len() + 1;
    header.push_str(&" ".repeat((64 - unpadded % 64) % 64));
    header.push('\n');
    let mut bytes = Vec::with_capacity(NPY_MAGIC.len() + 4 + header.len() + 8 * values.len());
    bytes.extend_from_slice(NPY_MAGIC);
    bytes.extend_from_slice(&[1, 0]);
    bytes.extend_from_slice(&(header.len() as u16).to_le_bytes());
    bytes.extend_from_slice(header.as_bytes());
    for value in values {
        bytes.extend_from_slice(&value.to_le_bytes());
    }
    bytes
}

/// How the loader moves the file's world into zrak's: scaled by `scale`
/// about the origin, then expressed in the frame of `average_pose` (the
/// NeRF paper's `recenter_poses`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Normalisation {
    pub scale: f64,
    /// The average camera-to-world of the scaled poses: the mean position,
    /// the normalised sum of the backwards axes as z, the sum of the up
    /// axes made orthogonal to it as y (`poses_avg` and `viewmatrix` in the
    /// NeRF paper's `load_llff.py`).
    pub average_pose: DMat4,
}

impl Normalisation {
    /// The normalisation of a capture's views. For views that look every
    /// way (no mean direction), the rotation is left as it is and only
    /// the position moves.
    pub fn of(views: &[LlffView]) -> Self {
        let nearest = views.iter().map(|v| v.near).fold(f64::INFINITY, f64::min);
        let scale = if nearest.is_finite() && nearest > 0.0 {
            1.0 / (nearest * BOUNDS_FACTOR)
        } else {
            1.0
        };
        let count = views.len().max(1) as f64;
        let centre = views
            .iter()
            .map(|v| v.camera_to_world.w_axis.truncate() * scale)
            .sum::<DVec3>()
            / count;
        let backwards: DVec3 = views
            .iter()
            .map(|v| v.camera_to_world.z_axis.truncate())
            .sum();
        let up: DVec3 = views
            .iter()
            .map(|v| v.camera_to_world.y_axis.truncate())
            .sum();
        let rotation = backwards
            .try_normalize()
            .and_then(|z| {
                let x = up.cross(z).try_normalize()?;
                Some(DMat3::from_cols(x, z.cross(x), z))
            })
            .unwrap_or(DMat3::IDENTITY);
        Self {
            scale,
            average_pose: DMat4::from_cols(
                rotation.x_axis.extend(0.0),
                rotation.y_axis.extend(0.0),
                rotation.z_axis.extend(0.0),
                centre.extend(1.0),
            ),
        }
    }

    /// A camera-to-world of the file's world in zrak's.
    pub fn pose(&self, camera_to_world: DMat4) -> DMat4 {
        let mut scaled = camera_to_world;
        scaled.w_axis = (camera_to_world.w_axis.truncate() * self.scale).extend(1.0);
        self.average_pose.inverse() * scaled
    }

    /// The similarity from zrak's world back to the file's.
    pub fn to_original(&self) -> DMat4 {
        DMat4::from_scale(DVec3::splat(1.0 / self.scale)) * self.average_pose
    }
}

/// A photograph of the capture with the camera that took it (before the
/// normalisation), ready to become a frame.
#[derive(Debug, Clone)]
pub struct Photograph {
    pub image: ImageRgba8,
    pub image_path: PathBuf,
    pub intrinsics: Intrinsics,
}

/// The scene of `views` and their `photographs` (in the same order):
/// poses normalised, every [`HOLD_OUT_EVERY`]-th view held out for
/// validation, the box around every camera and what it sees between its
/// near and far bounds.
pub fn assemble(
    name: String,
    root: PathBuf,
    views: &[LlffView],
    photographs: Vec<Photograph>,
    has_alpha: bool,
) -> Scene {
    let normalisation = Normalisation::of(views);
    let intrinsics: Vec<Intrinsics> = photographs.iter().map(|p| p.intrinsics).collect();
    let bounds = content_box(&normalisation, views, &intrinsics);
    let mut scene = Scene {
        name,
        root,
        format: SceneFormat::Llff,
        train: Vec::new(),
        val: Vec::new(),
        test: Vec::new(),
        has_alpha,
        unit_cube: UnitCubeMapping::around(&bounds),
        bounds,
        smaller_training_views: 0,
        sparse_points: None,
        space: SpaceAnalysis::default(),
        poses: crate::scene::PoseOrigin::estimated(
            "LLFF's poses_bounds.npy: its cameras come from COLMAP's structure from motion (LLFF's imgs2poses)",
        ),
    };
    for (index, (view, photograph)) in views.iter().zip(photographs).enumerate() {
        let frame = Frame {
            camera: Camera::new(
                photograph.intrinsics,
                normalisation.pose(view.camera_to_world).as_mat4(),
            ),
            image: photograph.image,
            image_path: photograph.image_path,
            mask: None,
        };
        if index % HOLD_OUT_EVERY == 0 {
            scene.val.push(frame);
        } else {
            scene.train.push(frame);
        }
    }
    scene.space = space::analyse(&scene);
    scene
}

/// The box, in zrak's world, around every camera and the frustum it sees
/// between its near and far bounds.
fn content_box(
    normalisation: &Normalisation,
    views: &[LlffView],
    intrinsics: &[Intrinsics],
) -> Aabb {
    let mut min = DVec3::splat(f64::INFINITY);
    let mut max = DVec3::splat(f64::NEG_INFINITY);
    for (view, k) in views.iter().zip(intrinsics) {
        let pose = normalisation.pose(view.camera_to_world);
        let position = pose.w_axis.truncate();
        min = min.min(position);
        max = max.max(position);
        let (w, h) = (k.width as f64, k.height as f64);
        for (u, v) in [(0.0, 0.0), (w, 0.0), (0.0, h), (w, h)] {
            // The corner's direction at unit depth, OpenGL axes.
            let on_plane = DVec4::new(
                (u - k.cx as f64) / k.fx as f64,
                -(v - k.cy as f64) / k.fy as f64,
                -1.0,
                0.0,
            );
            let direction = (pose * on_plane).truncate();
            for depth in [view.near, view.far] {
                let point = position + depth * normalisation.scale * direction;
                min = min.min(point);
                max = max.max(point);
            }
        }
    }
    Aabb::new(min.as_vec3(), max.as_vec3())
}

/// The folder to read the photographs from and the downscale still to
/// apply: `images_{downscale}` when there is one, else `images/` downscaled.
fn image_folder(root: &Path, downscale: u32) -> SceneResult<(PathBuf, u32)> {
    let scaled = root.join(format!("images_{downscale}"));
    if downscale > 1 && scaled.is_dir() {
        return Ok((scaled, 1));
    }
    let full = root.join("images");
    if full.is_dir() {
        return Ok((full, downscale));
    }
    let mut others: Vec<String> = std::fs::read_dir(root)
        .map(|entries| {
            entries
                .filter_map(Result::ok)
                .filter(|e| e.path().is_dir())
                .map(|e| e.file_name().to_string_lossy().into_owned())
                .filter(|name| {
                    name.strip_prefix("images_")
                        .is_some_and(|n| n.parse::<u32>().is_ok())
                })
                .collect()
        })
        .unwrap_or_default();
    others.sort();
    let hint = match others.first() {
        Some(first) => format!(
            "; the folder holds {}: give a downscale of {} to read {first}",
            others.join(", "),
            &first["images_".len()..]
        ),
        None => String::new(),
    };
    let problem = format!(
        "no images/ folder beside {POSES_FILE}{}{hint}",
        if downscale > 1 {
            format!(" (nor images_{downscale}/)")
        } else {
            String::new()
        }
    );
    Err(if crate::files::exists_at_all(&full) {
        SceneError::unreadable(
            &full,
            format!("{problem}: {}", super::pose::what_is_there(&full)),
        )
    } else {
        SceneError::not_found(&full, problem)
    })
}

/// The photographs in `folder`, sorted by file name (as the NeRF paper's
/// `load_llff.py` matches them to rows).
fn list_images(folder: &Path) -> SceneResult<Vec<PathBuf>> {
    let entries = std::fs::read_dir(folder)
        .map_err(|e| SceneError::unreadable(folder, format!("cannot list the folder: {e}")))?;
    let mut images: Vec<PathBuf> = entries
        .filter_map(Result::ok)
        .map(|entry| entry.path())
        .filter(|path| {
            let name = path.file_name().unwrap_or_default().to_string_lossy();
            let extension = path.extension().unwrap_or_default().to_string_lossy();
            // Hidden files (a copy's `._name.jpg` beside each photograph)
            // are no photographs.
            !name.starts_with('.')
                && IMAGE_EXTENSIONS
                    .iter()
                    .any(|e| extension.eq_ignore_ascii_case(e))
        })
        .collect();
    images.sort_by(|a, b| a.file_name().cmp(&b.file_name()));
    Ok(images)
}

/// The intrinsics of a photograph `width` × `height` of `view`: its focal
/// length scaled from the size the row gives, the principal point at the
/// centre (LLFF's cameras are pinholes through the image centre).
fn photograph_intrinsics(view: &LlffView, width: u32, height: u32) -> Result<Intrinsics, String> {
    let sx = width as f64 / view.width;
    let sy = height as f64 / view.height;
    // Downscaled copies round their sizes to whole pixels: 504 × 378 from
    // 4032 × 3024 is exact, 1/3 of 1000 is not.
    if (sx - sy).abs() > 0.01 * sx.max(sy) {
        return Err(format!(
            "the photograph is {width}×{height}, which is no one scale of the {}×{} {POSES_FILE} \
             gives for it ({:.4} across, {:.4} down)",
            view.width, view.height, sx, sy
        ));
    }
    Ok(Intrinsics {
        width,
        height,
        fx: (view.focal * sx) as f32,
        fy: (view.focal * sy) as f32,
        cx: 0.5 * width as f32,
        cy: 0.5 * height as f32,
        lens: Lens::Pinhole,
    })
}

/// The photographs in `folder` for `views`, one per row by file name.
fn matched_images(npy: &Path, folder: &Path, views: &[LlffView]) -> SceneResult<Vec<PathBuf>> {
    let images = list_images(folder)?;
    if images.len() != views.len() {
        return Err(SceneError::new(
            npy,
            format!(
                "has {} rows, but {} holds {} photographs (.png, .jpg): each row belongs to \
                 one photograph, in file-name order",
                views.len(),
                shown(folder),
                images.len()
            ),
        ));
    }
    Ok(images)
}

/// Loads an LLFF folder (see the module notes). With a downscale N, the
/// photographs of `images_N/` when there is one, else those of `images/`
/// downscaled.
pub fn load(root: &Path, options: LoadOptions) -> SceneResult<Scene> {
    check_downscale(root, options.downscale)?;
    let npy = root.join(POSES_FILE);
    let views = read_poses_bounds(&npy)?;
    let (folder, downscale) = image_folder(root, options.downscale)?;
    let images = matched_images(&npy, &folder, &views)?;
    let sources: Vec<FrameSource> = images
        .into_iter()
        .enumerate()
        .map(|(index, image_path)| FrameSource {
            json_path: npy.clone(),
            index,
            image_path,
            camera_to_world: Mat4::IDENTITY,
        })
        .collect();
    let decoded = decode_images(&sources, downscale)?;
    let has_alpha = decoded.iter().any(|d| d.file_has_alpha);
    let mut photographs = Vec::with_capacity(views.len());
    for ((source, image), view) in sources.into_iter().zip(decoded).zip(&views) {
        let intrinsics = photograph_intrinsics(view, image.width, image.height)
            .map_err(|problem| {
                source.error(format!("image {}: {problem}", shown(&source.image_path)))
            })?
            .downscaled(downscale);
        photographs.push(Photograph {
            image: image.image,
            image_path: source.image_path,
            intrinsics,
        });
    }
    Ok(assemble(
        folder_name(root),
        root.to_path_buf(),
        &views,
        photographs,
        has_alpha,
    ))
}

/// An LLFF capture in zrak's terms, before its photographs are read: what
/// `zrak convert` writes as a transforms.json.
#[derive(Debug, Clone)]
pub struct Converted {
    /// The photographs of `images/`, by file name, each with its camera
    /// (normalised pose, intrinsics at the file's size).
    pub images: Vec<(PathBuf, Camera)>,
    pub normalisation: Normalisation,
    pub unit_cube: UnitCubeMapping,
}

/// Reads the LLFF folder `root`: poses as [`load`] normalises them, the
/// photographs of `images/` at their own size (read from their headers).
pub fn convert(root: &Path) -> SceneResult<Converted> {
    let npy = root.join(POSES_FILE);
    let views = read_poses_bounds(&npy)?;
    let (folder, _) = image_folder(root, 1)?;
    let images = matched_images(&npy, &folder, &views)?;
    let normalisation = Normalisation::of(&views);
    let mut converted = Vec::with_capacity(views.len());
    for (index, (path, view)) in images.into_iter().zip(&views).enumerate() {
        let frame_error = |problem: String| {
            SceneError::in_frame(&npy, index, format!("image {}: {problem}", shown(&path)))
        };
        let (width, height) = image::image_dimensions(&path)
            .map_err(|e| frame_error(format!("cannot read its size: {e}")))?;
        let intrinsics = photograph_intrinsics(view, width, height).map_err(frame_error)?;
        let pose = normalisation.pose(view.camera_to_world).as_mat4();
        converted.push((path, Camera::new(intrinsics, pose)));
    }
    let intrinsics: Vec<Intrinsics> = converted.iter().map(|(_, c)| c.intrinsics).collect();
    let bounds = content_box(&normalisation, &views, &intrinsics);
    Ok(Converted {
        images: converted,
        normalisation,
        unit_cube: UnitCubeMapping::around(&bounds),
    })
}

/// The instant-ngp / nerfstudio `transforms.json` of a converted capture:
/// image paths relative to `out_folder` where they lie under it (absolute
/// otherwise), per-frame pinhole intrinsics, the unit cube.
pub fn transforms_json(converted: &Converted, out_folder: &Path) -> Value {
    let frames: Vec<Value> = converted
        .images
        .iter()
        .map(|(path, camera)| {
            let file_path = path
                .strip_prefix(out_folder)
                .map(|p| p.to_string_lossy().replace('\\', "/"))
                .unwrap_or_else(|_| path.to_string_lossy().into_owned());
            let m = camera.camera_to_world;
            let rows: Vec<Value> = (0..4).map(|r| json!(m.row(r).to_array())).collect();
            let k = camera.intrinsics;
            json!({
                "file_path": file_path,
                "transform_matrix": rows,
                "camera_model": "OPENCV",
                "w": k.width, "h": k.height,
                "fl_x": k.fx, "fl_y": k.fy, "cx": k.cx, "cy": k.cy,
            })
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

/// The views of `cameras` (zrak's camera-to-world and intrinsics) with
/// their bounds, as rows of `poses_bounds.npy`.
pub fn views_of(cameras: &[Camera], bounds: &[(f64, f64)]) -> Vec<LlffView> {
    cameras
        .iter()
        .zip(bounds)
        .map(|(camera, &(near, far))| {
            let k = camera.intrinsics;
            LlffView {
                camera_to_world: camera.camera_to_world.as_dmat4(),
                height: k.height as f64,
                width: k.width as f64,
                focal: k.fx as f64,
                near,
                far,
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use glam::Vec3;

    use super::*;
    use crate::scene::pose::test_support::assert_mentions;

    /// A row whose camera looks along world +y with +z up: LLFF's down is
    /// −z, right +x, backwards −y (down × right = backwards, a rotation).
    fn looking_along_y(position: [f64; 3], near: f64, far: f64) -> [f64; ROW_LENGTH] {
        let (down, right, backwards) = ([0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]);
        let hwf = [60.0, 80.0, 50.0];
        let mut row = [0.0; ROW_LENGTH];
        for r in 0..3 {
            row[5 * r..5 * r + 5].copy_from_slice(&[
                down[r],
                right[r],
                backwards[r],
                position[r],
                hwf[r],
            ]);
        }
        row[15] = near;
        row[16] = far;
        row
    }

    /// A turn about `axis` by `angle` radians, as a camera-to-world.
    fn turned(view: &LlffView, axis: DVec3, angle: f64) -> LlffView {
        let turn = DMat4::from_axis_angle(axis.normalize(), angle);
        let mut turned = *view;
        turned.camera_to_world = turn * view.camera_to_world;
        turned
    }

    #[test]
    fn llff_axes_become_right_up_backwards() {
        let view = LlffView::from_row(&looking_along_y([1.0, 2.0, 3.0], 2.0, 9.0)).unwrap();
        let m = view.camera_to_world;
        assert_eq!(m.x_axis.truncate(), DVec3::X, "right");
        assert_eq!(m.y_axis.truncate(), DVec3::Z, "up is minus down");
        assert_eq!(m.z_axis.truncate(), -DVec3::Y, "backwards");
        assert_eq!(m.w_axis.truncate(), DVec3::new(1.0, 2.0, 3.0));
        assert_eq!((view.height, view.width, view.focal), (60.0, 80.0, 50.0));
        assert_eq!((view.near, view.far), (2.0, 9.0));
        // What the camera sees, independently of the formula: straight
        // ahead (+y) is the image centre, world +x is right of it, world
        // −z (LLFF's down) below it.
        let k = photograph_intrinsics(&view, 80, 60).unwrap();
        let camera = Camera::new(k, m.as_mat4());
        let ahead = Vec3::new(1.0, 7.0, 3.0);
        let (u, v) = camera.project(ahead).unwrap();
        assert!(
            (u - 40.0).abs() < 1e-4 && (v - 30.0).abs() < 1e-4,
            "({u}, {v})"
        );
        let (u, _) = camera.project(ahead + Vec3::X).unwrap();
        assert!(u > 45.0, "{u}");
        let (_, v) = camera.project(ahead - Vec3::Z).unwrap();
        assert!(v > 35.0, "{v}");
    }

    #[test]
    fn rows_read_back_as_written() {
        let view = LlffView::from_row(&looking_along_y([0.5, -1.0, 0.25], 1.5, 20.0)).unwrap();
        let view = turned(&view, DVec3::new(0.3, -0.5, 0.8), 0.7);
        let again = LlffView::from_row(&view.to_row()).unwrap();
        assert!(
            again
                .camera_to_world
                .abs_diff_eq(view.camera_to_world, 1e-12)
        );
        assert_eq!((again.near, again.far, again.focal), (1.5, 20.0, 50.0));
        // The NeRF paper's reorder, on the written row: [c1, −c0, c2].
        let row = view.to_row();
        let column = |c: usize| DVec3::new(row[c], row[5 + c], row[10 + c]);
        let m = view.camera_to_world;
        assert!(column(1).abs_diff_eq(m.x_axis.truncate(), 1e-12));
        assert!((-column(0)).abs_diff_eq(m.y_axis.truncate(), 1e-12));
        assert!(column(2).abs_diff_eq(m.z_axis.truncate(), 1e-12));
    }

    #[test]
    fn a_mirrored_or_scaled_matrix_and_bad_bounds_are_refused() {
        let mut row = looking_along_y([0.0; 3], 1.0, 2.0);
        row[0] = -row[0];
        row[5] = -row[5];
        row[10] = -row[10];
        let problem = LlffView::from_row(&row).unwrap_err();
        assert_mentions(&problem, &["reflection", "down, right and backwards"]);
        let mut row = looking_along_y([0.0; 3], 1.0, 2.0);
        row[1] = 2.0;
        assert_mentions(&LlffView::from_row(&row).unwrap_err(), &["not orthonormal"]);
        let row = looking_along_y([0.0; 3], 3.0, 2.0);
        assert_mentions(
            &LlffView::from_row(&row).unwrap_err(),
            &["near 3, far 2", "0 < near < far"],
        );
        let mut row = looking_along_y([0.0; 3], 1.0, 2.0);
        row[14] = 0.0;
        assert_mentions(
            &LlffView::from_row(&row).unwrap_err(),
            &["focal length", "is 0"],
        );
    }

    fn write_npy(dir: &Path, bytes: &[u8]) -> PathBuf {
        let path = dir.join(POSES_FILE);
        std::fs::write(&path, bytes).unwrap();
        path
    }

    fn read_error(path: &Path) -> String {
        read_poses_bounds(path).unwrap_err().to_string()
    }

    /// A `.npy` file with `header` (padded as NumPy pads it) and `data`.
    fn npy_with(major: u8, header: &str, data: &[u8]) -> Vec<u8> {
        let mut header = header.to_string();
        let prefix = if major == 1 { 10 } else { 12 };
        header.push_str(&" ".repeat((64 - (prefix + header.len() + 1) % 64) % 64));
        header.push('\n');
        let mut bytes = NPY_MAGIC.to_vec();
        bytes.extend_from_slice(&[major, 0]);
        if major == 1 {
            bytes.extend_from_slice(&(header.len() as u16).to_le_bytes());
        } else {
            bytes.extend_from_slice(&(header.len() as u32).to_le_bytes());
        }
        bytes.extend_from_slice(header.as_bytes());
        bytes.extend_from_slice(data);
        bytes
    }

    #[test]
    fn npy_files_of_every_version_and_order_are_read() {
        let dir = tempfile::tempdir().unwrap();
        let rows = [
            looking_along_y([0.0, 0.0, 0.0], 2.0, 10.0),
            looking_along_y([0.5, 0.0, 0.25], 2.5, 12.0),
        ];
        let values: Vec<f64> = rows.iter().flatten().copied().collect();
        let expected: Vec<LlffView> = rows
            .iter()
            .map(|row| LlffView::from_row(row).unwrap())
            .collect();
        // Written by zrak (format 1.0, float64).
        let path = dir.path().join(POSES_FILE);
        write_poses_bounds(&path, &expected).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        assert_eq!(bytes[..8], *b"\x93NUMPY\x01\x00");
        let data_start = 10 + u16::from_le_bytes([bytes[8], bytes[9]]) as usize;
        assert_eq!(data_start % 64, 0, "NumPy's alignment");
        assert_eq!(read_poses_bounds(&path).unwrap(), expected);
        // Format 2.0, float32.
        let f32_data: Vec<u8> = values
            .iter()
            .flat_map(|v| (*v as f32).to_le_bytes())
            .collect();
        let header = "{'descr': '<f4', 'fortran_order': False, 'shape': (2, 17), }";
        let path = write_npy(dir.path(), &npy_with(2, header, &f32_data));
        assert_eq!(read_poses_bounds(&path).unwrap(), expected);
        // Fortran order: column by column.
        let by_column: Vec<u8> = (0..ROW_LENGTH)
            .flat_map(|c| [rows[0][c], rows[1][c]])
            .flat_map(f64::to_le_bytes)
            .collect();
        let header = "{'descr': '<f8', 'fortran_order': True, 'shape': (2, 17), }";
        let path = write_npy(dir.path(), &npy_with(1, header, &by_column));
        assert_eq!(read_poses_bounds(&path).unwrap(), expected);
    }

    #[test]
    fn bad_npy_files_are_refused_naming_the_file_and_the_problem() {
        let dir = tempfile::tempdir().unwrap();
        let one_row: Vec<u8> = looking_along_y([0.0; 3], 2.0, 10.0)
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        let header = |descr: &str, shape: &str| {
            format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape}, }}")
        };
        let cases: Vec<(Vec<u8>, Vec<&str>)> = vec![
            (b"PK\x03\x04 a zip".to_vec(), vec!["not a NumPy .npy file"]),
            (
                npy_with(1, &header("<f8", "(1, 17)"), &one_row)[..40].to_vec(),
                vec!["header says it is", "bytes long"],
            ),
            (
                {
                    let mut bytes = npy_with(1, &header("<f8", "(1, 17)"), &one_row);
                    bytes[6] = 4;
                    bytes
                },
                vec!["format version 4.0", "versions 1, 2 and 3"],
            ),
            (
                npy_with(1, &header(">f8", "(1, 17)"), &one_row),
                vec!["'>f8'", "little-endian"],
            ),
            (
                npy_with(1, &header("<f8", "(1, 17)"), &one_row[..100]),
                vec!["shape (1, 17) of '<f8'", "100 bytes of data"],
            ),
            (
                npy_with(1, &header("<f8", "(17, 1)"), &one_row),
                vec!["shape (17, 1) (it looks transposed)", "N × 17"],
            ),
            (
                npy_with(1, &header("<f8", "(1, 15)"), &one_row[..120]),
                vec!["shape (1, 15)", "near and far bounds"],
            ),
            (
                npy_with(1, "{'descr': '<f8', 'shape': (1, 17), }", &one_row),
                vec!["has no 'fortran_order'"],
            ),
            (
                {
                    let mut row = looking_along_y([0.0; 3], 2.0, 10.0);
                    row[8] = f64::NAN;
                    let data: Vec<u8> = row.iter().flat_map(|v| v.to_le_bytes()).collect();
                    npy_with(1, &header("<f8", "(1, 17)"), &data)
                },
                vec!["frame 0", "column 8 is NaN", "must be finite"],
            ),
        ];
        for (bytes, parts) in cases {
            let path = write_npy(dir.path(), &bytes);
            let error = read_error(&path);
            assert!(error.starts_with(&path.display().to_string()), "{error}");
            assert_mentions(&error, &parts);
        }
        let missing = dir.path().join("elsewhere").join(POSES_FILE);
        assert!(matches!(
            read_poses_bounds(&missing),
            Err(SceneError::NotFound { .. })
        ));
    }

    /// Four views on a slanted plane, turned a little each, with bounds.
    fn capture() -> Vec<LlffView> {
        let base = LlffView::from_row(&looking_along_y([0.0; 3], 1.0, 2.0)).unwrap();
        (0..4)
            .map(|i| {
                let i = i as f64;
                let mut view = turned(&base, DVec3::new(0.2, 0.1, 1.0), 0.05 * i);
                view.camera_to_world.w_axis = DVec4::new(3.0 + 0.4 * i, -2.0, 1.0 + 0.3 * i, 1.0);
                view.near = 4.0 + i;
                view.far = 30.0 + i;
                view
            })
            .collect()
    }

    #[test]
    fn the_nearest_bound_becomes_four_thirds_and_the_average_pose_the_identity() {
        let views = capture();
        let n = Normalisation::of(&views);
        assert!((n.scale - 1.0 / (4.0 * 0.75)).abs() < 1e-12);
        assert!((views[0].near * n.scale - 1.0 / 0.75).abs() < 1e-12);
        let poses: Vec<DMat4> = views.iter().map(|v| n.pose(v.camera_to_world)).collect();
        let mean = poses.iter().map(|p| p.w_axis.truncate()).sum::<DVec3>() / 4.0;
        assert!(mean.length() < 1e-12, "{mean}");
        let backwards: DVec3 = poses.iter().map(|p| p.z_axis.truncate()).sum();
        assert!(
            backwards.normalize().abs_diff_eq(DVec3::Z, 1e-12),
            "{backwards}"
        );
        let up: DVec3 = poses.iter().map(|p| p.y_axis.truncate()).sum();
        assert!(
            up.x.abs() < 1e-12 && up.y > 0.0,
            "the mean up is in the y-z plane: {up}"
        );
        // A similarity: distances scale by `scale`, angles stay.
        let (a, b) = (&views[0].camera_to_world, &views[3].camera_to_world);
        let before = (a.w_axis - b.w_axis).length();
        let after = (poses[0].w_axis - poses[3].w_axis).length();
        assert!((after - n.scale * before).abs() < 1e-12);
        let angle = |m: &DMat4, k: &DMat4| m.z_axis.dot(k.z_axis);
        assert!((angle(a, b) - angle(&poses[0], &poses[3])).abs() < 1e-12);
        // And back.
        for (view, pose) in views.iter().zip(&poses) {
            let position = n.to_original().transform_point3(pose.w_axis.truncate());
            assert!(position.abs_diff_eq(view.camera_to_world.w_axis.truncate(), 1e-12));
        }
    }

    /// An LLFF folder of `count` views (as [`capture`], repeated) whose
    /// photographs in `images/` are 40 × 30 while the rows say 80 × 60.
    fn write_folder(dir: &Path, count: usize) -> Vec<LlffView> {
        let views: Vec<LlffView> = (0..count).map(|i| capture()[i % 4]).collect();
        write_poses_bounds(&dir.join(POSES_FILE), &views).unwrap();
        for i in 0..count {
            let grey = (10 * i) as u8;
            let image = ImageRgba8::new(40, 30, [grey, grey, grey, 255].repeat(40 * 30));
            std::fs::create_dir_all(dir.join("images")).unwrap();
            image
                .save_png(&dir.join(format!("images/IMG_{i:04}.png")))
                .unwrap();
        }
        views
    }

    #[test]
    fn a_folder_loads_with_every_eighth_photograph_held_out_and_focal_lengths_scaled() {
        let dir = tempfile::tempdir().unwrap();
        let views = write_folder(dir.path(), 10);
        // Not a photograph: left out.
        std::fs::write(dir.path().join("images/notes.txt"), "x").unwrap();
        let scene = Scene::load(dir.path(), LoadOptions::default()).unwrap();
        assert_eq!(scene.format, SceneFormat::Llff);
        assert_eq!(
            (scene.train.len(), scene.val.len(), scene.test.len()),
            (8, 2, 0)
        );
        let names: Vec<String> = scene
            .val
            .iter()
            .map(|f| {
                f.image_path
                    .file_name()
                    .unwrap()
                    .to_string_lossy()
                    .into_owned()
            })
            .collect();
        assert_eq!(names, ["IMG_0000.png", "IMG_0008.png"]);
        // Rows by file name: the photograph of row 9 is the 9th by name.
        assert_eq!(scene.train[7].image.rgba(0, 0)[0], 90.0 / 255.0);
        let k = scene.train[0].camera.intrinsics;
        assert_eq!(
            (k.width, k.height, k.fx, k.fy, k.cx, k.cy),
            (40, 30, 25.0, 25.0, 20.0, 15.0)
        );
        let n = Normalisation::of(&views);
        let pose = n.pose(views[1].camera_to_world).as_mat4();
        assert!(
            scene.train[0]
                .camera
                .camera_to_world
                .abs_diff_eq(pose, 1e-6)
        );
        // The box holds every camera and its frustum out to the far bound
        // (30 and more).
        for frame in scene.frames() {
            let ray = frame.camera.pixel_ray(0, 0);
            assert!(scene.bounds.contains(ray.origin));
            let far = 30.0 * n.scale as f32 * ray.direction_unnormalised.length() * 0.999;
            assert!(scene.bounds.contains(ray.at(far)), "{}", ray.at(far));
        }
        assert_eq!(scene.unit_cube.aabb_scale, 1.0);
        assert!(scene.unit_cube.world_bounds().contains(scene.bounds.min));
        assert!(scene.unit_cube.world_bounds().contains(scene.bounds.max));
    }

    #[test]
    fn a_downscale_reads_images_n_when_there_is_one() {
        let dir = tempfile::tempdir().unwrap();
        write_folder(dir.path(), 3);
        let options = LoadOptions { downscale: 2 };
        // images/ downscaled.
        let scene = Scene::load(dir.path(), options).unwrap();
        let k = scene.train[0].camera.intrinsics;
        assert_eq!((k.width, k.height, k.fx), (20, 15, 12.5));
        assert_eq!(scene.train[0].image.rgba(0, 0)[0], 10.0 / 255.0);
        // images_2/ as it is: told apart by its colour.
        for i in 0..3 {
            ImageRgba8::new(20, 15, [200, 0, 0, 255].repeat(20 * 15))
                .save_png(&dir.path().join(format!("images_2/{i}.png")))
                .unwrap_or_else(|_| {
                    std::fs::create_dir_all(dir.path().join("images_2")).unwrap();
                    ImageRgba8::new(20, 15, [200, 0, 0, 255].repeat(20 * 15))
                        .save_png(&dir.path().join(format!("images_2/{i}.png")))
                        .unwrap()
                });
        }
        let scene = Scene::load(dir.path(), options).unwrap();
        let k = scene.train[0].camera.intrinsics;
        assert_eq!((k.width, k.height, k.fx), (20, 15, 12.5));
        assert_eq!(scene.train[0].image.rgba(0, 0)[0], 200.0 / 255.0);
    }

    #[test]
    fn missing_or_mismatched_photographs_are_named() {
        let dir = tempfile::tempdir().unwrap();
        write_folder(dir.path(), 3);
        std::fs::remove_file(dir.path().join("images/IMG_0002.png")).unwrap();
        let error = Scene::load(dir.path(), LoadOptions::default())
            .unwrap_err()
            .to_string();
        assert_mentions(&error, &[POSES_FILE, "has 3 rows", "holds 2 photographs"]);
        // Photographs of another shape than the rows say.
        for i in 0..3 {
            ImageRgba8::new(40, 40, vec![255; 40 * 40 * 4])
                .save_png(&dir.path().join(format!("images/IMG_{i:04}.png")))
                .unwrap();
        }
        let error = Scene::load(dir.path(), LoadOptions::default())
            .unwrap_err()
            .to_string();
        assert_mentions(
            &error,
            &["frame 0", "IMG_0000.png", "40×40", "no one scale"],
        );
        // No images/, but images_4/.
        std::fs::rename(dir.path().join("images"), dir.path().join("images_4")).unwrap();
        let error = Scene::load(dir.path(), LoadOptions::default()).unwrap_err();
        assert!(matches!(error, SceneError::NotFound { .. }), "{error:?}");
        assert_mentions(
            &error.to_string(),
            &[
                "no images/ folder beside",
                "holds images_4",
                "downscale of 4",
            ],
        );
    }
}
