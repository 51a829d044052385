//! Novel views from a trained model: whole images in tiles, render modes.

pub mod camera_path;
pub mod export;
pub mod path;

/// Bytes rendering one `width` × `height` frame and writing it as a PNG
/// takes at its peak: the frame's rays (origin and direction, 24 bytes a
/// pixel), the rendered pixels (colour, opacity, depth: 20), the 8-bit
/// image (4) and the PNG encoder's copy of it (4, the most it compresses
/// to), beyond the model itself.
pub fn frame_memory_bytes(width: u32, height: u32) -> u64 {
    width as u64 * height as u64 * (24 + 20 + 4 + 4)
}

/// Bytes an animated GIF's encoder adds to a frame's: a copy of the RGBA
/// frame it quantises (4 bytes a pixel), the frame's palette indices (1)
/// and its compressed form (up to 1), rounded up to 8.
pub fn gif_memory_bytes(width: u32, height: u32) -> u64 {
    width as u64 * height as u64 * 8
}
