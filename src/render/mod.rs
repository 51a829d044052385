//! Novel views from a trained model: whole images in tiles, render modes.

pub mod camera_path;
pub mod export;
pub mod path;

pub use crate::model::RenderMode;
pub use crate::model::pixels::{render_pixels, rgb_of, to_image};
