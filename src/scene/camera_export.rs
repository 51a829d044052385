//! Cameras written out for other tools: a training set's cameras (camera
//! refinement's corrected ones) as an instant-ngp / nerfstudio
//! transforms.json, each frame with its image's path, its camera-to-world
//! matrix and its pinhole intrinsics, and the scene's unit-cube mapping.

use std::path::PathBuf;

use serde_json::{Value, json};

use super::{Camera, UnitCubeMapping};

/// The transforms.json of `cameras` (each with its image's path, written
/// as given), as zrak and nerfstudio read it back.
pub fn transforms_json(cameras: &[(PathBuf, Camera)], unit_cube: UnitCubeMapping) -> Value {
    let frames: Vec<Value> = cameras
        .iter()
        .map(|(path, camera)| {
            let m = camera.camera_to_world;
            let rows: Vec<Value> = (0..4).map(|r| json!(m.row(r).to_array())).collect();
            let k = camera.intrinsics;
            json!({
                "file_path": path.to_string_lossy().replace('\\', "/"),
                "transform_matrix": rows,
                "camera_model": "OPENCV",
                "w": k.width, "h": k.height,
                "fl_x": k.fx, "fl_y": k.fy, "cx": k.cx, "cy": k.cy,
            })
        })
        .collect();
    json!({
        "aabb_scale": unit_cube.aabb_scale,
        "scale": unit_cube.scale,
        "offset": unit_cube.offset.to_array(),
        "frames": frames,
    })
}
