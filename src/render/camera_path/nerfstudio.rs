//! nerfstudio camera_path.json
