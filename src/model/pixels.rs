//! A model's rendered pixels: every pixel of a camera through
//! [`RadianceModel::render`] in tiles, and their 8-bit image in a render
//! mode. Below the engines, so that an engine can draw its view the way the
//! renderer does.

use rayon::prelude::*;

use super::{RadianceModel, RayColumns, RenderMode, RenderedPixel};
use crate::scene::{Camera, ImageRgba8, to_u8};

/// Rays per call into the model: large enough to keep every core busy,
/// small enough that a render can report progress.
const TILE_RAYS: usize = 1 << 14;

/// Renders every pixel of `camera` over `background`, row by row from the
/// top.
pub fn render_pixels(
    model: &dyn RadianceModel,
    camera: &Camera,
    background: [f32; 3],
) -> Vec<RenderedPixel> {
    let rays = camera.all_rays();
    let mut out = vec![RenderedPixel::default(); rays.len()];
    for (chunk, out) in rays.chunks(TILE_RAYS).zip(out.chunks_mut(TILE_RAYS)) {
        model.render(RayColumns::of(chunk).over(background), out);
    }
    out
}

/// RGB of rendered pixels, row-major.
pub fn rgb_of(pixels: &[RenderedPixel]) -> Vec<[f32; 3]> {
    pixels.iter().map(|p| p.rgb).collect()
}

/// Turns rendered pixels into an 8-bit image in `mode`. Depth is mapped
/// linearly from `depth_range` (near white, far black); pixels the model
/// sees as empty are black.
pub fn to_image(
    pixels: &[RenderedPixel],
    width: u32,
    height: u32,
    mode: RenderMode,
    depth_range: (f32, f32),
) -> ImageRgba8 {
    let data: Vec<u8> = pixels
        .par_iter()
        .flat_map_iter(|p| {
            let rgb = match mode {
                RenderMode::Rgb => p.rgb,
                RenderMode::Opacity => [p.opacity; 3],
                RenderMode::Depth => {
                    let (near, far) = depth_range;
                    let shade = if p.opacity > 0.5 {
                        let depth = p.depth / p.opacity;
                        1.0 - ((depth - near) / (far - near)).clamp(0.0, 1.0)
                    } else {
                        0.0
                    };
                    [shade; 3]
                }
            };
            [to_u8(rgb[0]), to_u8(rgb[1]), to_u8(rgb[2]), 255]
        })
        .collect();
    ImageRgba8::new(width, height, data)
}
