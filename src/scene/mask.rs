//! Per-pixel masks: which pixels of a photograph count as training targets
//! and in the held-out scores. Photographs of real places hold things that
//! move between frames (people, cars, monitors); a field that had to explain
//! them would put fog where they passed, so their pixels are left out.
//!
//! Two conventions on disk, both read by [`super::instant_ngp`]:
//!
//! - instant-ngp: `dynamic_mask_<image stem>.png` in the image's folder; a
//!   pixel whose red, green or blue is not zero is *dynamic* and is ignored
//!   (instant-ngp `src/nerf_loader.cu`, `load_nerf`: the mask must have the
//!   image's resolution, and such pixels are painted with its `mask_color`,
//!   which training skips);
//! - nerfstudio: a frame's `mask_path` in transforms.json; a pixel of value
//!   0 is ignored, any other value counts (nerfstudio
//!   `nerfstudio/data/utils/data_utils.py`,
//!   `get_image_mask_tensor_from_path`: the mask as booleans).

use std::path::{Path, PathBuf};

use super::error::{SceneResult, shown};
use super::image::{ImageRgba8, load_image_sharing};
use super::pose::FrameSource;
use crate::rng::Pcg32;

/// Which pixels of an image count, row-major from the top, the image's
/// size.
#[derive(Debug, Clone, PartialEq)]
pub struct PixelMask {
    width: u32,
    height: u32,
    counts: Vec<bool>,
    counted: usize,
    /// The counted pixels' indices, kept only when they are few (under
    /// [`SPARSE_SHARE`] of the image): there a uniform draw by rejection
    /// would take many tries, and the list costs little memory.
    sparse: Vec<u32>,
}

/// Below one counted pixel in this many, draws pick from a list of the
/// counted pixels instead of rejecting hidden ones (at most 16 tries
/// expected by rejection; at most a quarter byte a pixel for the list).
const SPARSE_SHARE: usize = 16;

impl PixelMask {
    /// A mask of `width` × `height` pixels, `counts[y · width + x]` saying
    /// whether pixel (x, y) counts.
    pub fn new(width: u32, height: u32, counts: Vec<bool>) -> Self {
        assert_eq!(counts.len(), width as usize * height as usize);
        let counted = counts.iter().filter(|&&c| c).count();
        let sparse = if counted * SPARSE_SHARE < counts.len() {
            (0..counts.len() as u32)
                .filter(|&i| counts[i as usize])
                .collect()
        } else {
            Vec::new()
        };
        Self {
            width,
            height,
            counts,
            counted,
            sparse,
        }
    }

    /// A mask in instant-ngp's convention: a pixel with any colour channel
    /// above zero is dynamic, so it does not count.
    pub fn from_dynamic_mask(image: &ImageRgba8) -> Self {
        let counts = image
            .data
            .chunks_exact(4)
            .map(|p| p[0] == 0 && p[1] == 0 && p[2] == 0)
            .collect();
        Self::new(image.width, image.height, counts)
    }

    /// A mask in nerfstudio's convention: a pixel of value 0 is ignored,
    /// any other counts (a grey image's value is in every colour channel;
    /// in a colour image any channel above zero counts).
    pub fn from_keep_mask(image: &ImageRgba8) -> Self {
        let counts = image
            .data
            .chunks_exact(4)
            .map(|p| p[0] != 0 || p[1] != 0 || p[2] != 0)
            .collect();
        Self::new(image.width, image.height, counts)
    }

    pub fn width(&self) -> u32 {
        self.width
    }

    pub fn height(&self) -> u32 {
        self.height
    }

    /// Whether pixel (x, y) counts.
    pub fn counts(&self, x: u32, y: u32) -> bool {
        self.counts[y as usize * self.width as usize + x as usize]
    }

    /// Per pixel, row-major, whether it counts.
    pub fn counting(&self) -> &[bool] {
        &self.counts
    }

    /// How many pixels count.
    pub fn counted(&self) -> usize {
        self.counted
    }

    /// How many pixels are left out.
    pub fn hidden(&self) -> usize {
        self.counts.len() - self.counted
    }

    /// A uniformly random pixel among those that count, or `None` when
    /// none does.
    pub fn draw(&self, rng: &mut Pcg32) -> Option<(u32, u32)> {
        if self.counted == 0 {
            return None;
        }
        let index = if self.sparse.is_empty() {
            // At least one pixel in SPARSE_SHARE counts here, so this ends
            // after SPARSE_SHARE tries on average.
            loop {
                let index = rng.below(self.counts.len() as u32);
                if self.counts[index as usize] {
                    break index;
                }
            }
        } else {
            self.sparse[rng.below(self.sparse.len() as u32) as usize]
        };
        Some((index % self.width, index / self.width))
    }

    /// The mask at 1/`factor` of its resolution, as
    /// [`ImageRgba8::downscaled`] shrinks its image: a pixel counts only
    /// where every pixel of its `factor` × `factor` block counts, so no
    /// hidden pixel's colour leaks into a target; trailing rows and columns
    /// that fill no block are dropped.
    pub fn downscaled(&self, factor: u32) -> Self {
        assert!(factor >= 1);
        if factor == 1 {
            return self.clone();
        }
        let (w, h) = (self.width / factor, self.height / factor);
        let counts = (0..h)
            .flat_map(|y| (0..w).map(move |x| (x, y)))
            .map(|(x, y)| {
                (0..factor)
                    .all(|dy| (0..factor).all(|dx| self.counts(x * factor + dx, y * factor + dy)))
            })
            .collect();
        Self::new(w, h, counts)
    }

    /// The pixels `x0..x0 + width`, `y0..y0 + height` (inside the mask).
    pub fn cropped(&self, x0: u32, y0: u32, width: u32, height: u32) -> Self {
        assert!(x0 + width <= self.width && y0 + height <= self.height);
        let counts = (y0..y0 + height)
            .flat_map(|y| (x0..x0 + width).map(move |x| (x, y)))
            .map(|(x, y)| self.counts(x, y))
            .collect();
        Self::new(width, height, counts)
    }

    /// Writes the mask in instant-ngp's convention (white where a pixel is
    /// dynamic, black where it counts) as a PNG.
    pub fn save_dynamic_mask_png(&self, path: &Path) -> SceneResult<()> {
        let data = self
            .counts
            .iter()
            .flat_map(|&c| if c { [0, 0, 0, 255] } else { [255; 4] })
            .collect();
        ImageRgba8::new(self.width, self.height, data).save_png(path)
    }
}

/// The file name instant-ngp reads a dynamic mask from for an image:
/// `dynamic_mask_<stem>.png` in the image's folder (instant-ngp
/// `src/nerf_loader.cu`: `dynamic_mask_{}.png` of the image path's
/// basename, its name without the extension).
pub fn dynamic_mask_path(image_path: &Path) -> Option<std::path::PathBuf> {
    let stem = image_path.file_stem()?.to_string_lossy();
    Some(image_path.with_file_name(format!("dynamic_mask_{stem}.png")))
}

/// How a mask file marks the pixels that count.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MaskConvention {
    /// instant-ngp's `dynamic_mask_*.png`: non-zero marks a pixel to ignore.
    Dynamic,
    /// nerfstudio's `mask_path`: zero marks a pixel to ignore.
    Keep,
}

/// A frame's mask file and how it reads.
#[derive(Debug, Clone, PartialEq)]
pub struct MaskFile {
    pub path: PathBuf,
    pub convention: MaskConvention,
}

/// Reads `file`, the mask of `source`'s image of `image_size` pixels (as
/// decoded, before the downscale), and shrinks it by `downscale` as the
/// image was. Errors name the JSON file, the frame and the mask file, of
/// the mask file's own kind (not found, unreadable, too large, invalid);
/// a mask of another size than its image is invalid.
pub fn load_mask(
    file: &MaskFile,
    source: &FrameSource,
    image_size: (u32, u32),
    downscale: u32,
    decodes_at_once: usize,
) -> SceneResult<PixelMask> {
    let loaded = load_image_sharing(&file.path, decodes_at_once).map_err(|e| {
        let problem = format!("mask {}: {}", shown(&file.path), e.problem());
        e.in_frame_of(&source.json_path, source.index, problem)
    })?;
    let mask = match file.convention {
        MaskConvention::Dynamic => PixelMask::from_dynamic_mask(&loaded.image),
        MaskConvention::Keep => PixelMask::from_keep_mask(&loaded.image),
    };
    if (mask.width, mask.height) != image_size {
        return Err(source.error(format!(
            "mask {}: the mask is {}×{} pixels, but its image {} is {}×{}: a mask must have \
             its image's size",
            shown(&file.path),
            mask.width,
            mask.height,
            shown(&source.image_path),
            image_size.0,
            image_size.1
        )));
    }
    Ok(mask.downscaled(downscale))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn mask(width: u32, height: u32, hidden: &[(u32, u32)]) -> PixelMask {
        let counts = (0..height)
            .flat_map(|y| (0..width).map(move |x| (x, y)))
            .map(|p| !hidden.contains(&p))
            .collect();
        PixelMask::new(width, height, counts)
    }

    #[test]
    fn a_block_counts_only_where_every_pixel_of_it_counts() {
        // 5 × 4 at ½: blocks (0,0), (1,0), (0,1), (1,1); one hidden pixel in
        // the block (1,0) hides it; the fifth column is dropped, so its
        // hidden pixel hides nothing.
        let small = mask(5, 4, &[(3, 1), (4, 2)]).downscaled(2);
        assert_eq!((small.width(), small.height()), (2, 2));
        assert_eq!(small.counting(), &[true, false, true, true]);
        assert_eq!((small.counted(), small.hidden()), (3, 1));
    }

    #[test]
    fn the_conventions_are_opposite() {
        // Black, white, dark grey and pure red pixels.
        let image = ImageRgba8::new(
            4,
            1,
            vec![
                0, 0, 0, 255, 255, 255, 255, 255, 1, 1, 1, 255, 200, 0, 0, 255,
            ],
        );
        let dynamic = PixelMask::from_dynamic_mask(&image);
        assert_eq!(dynamic.counting(), &[true, false, false, false]);
        let keep = PixelMask::from_keep_mask(&image);
        assert_eq!(keep.counting(), &[false, true, true, true]);
    }

    #[test]
    fn draws_are_uniform_over_the_counted_pixels_only() {
        // Dense (rejection) and sparse (list) masks of 8 × 8.
        let all: Vec<(u32, u32)> = (0..8).flat_map(|y| (0..8).map(move |x| (x, y))).collect();
        let dense_hidden: Vec<_> = all.iter().copied().filter(|&(x, _)| x < 4).collect();
        let sparse_hidden: Vec<_> = all
            .iter()
            .copied()
            .filter(|&p| p != (2, 5) && p != (7, 1))
            .collect();
        for hidden in [dense_hidden, sparse_hidden] {
            let m = mask(8, 8, &hidden);
            let mut rng = Pcg32::new(3, 7);
            let mut seen = vec![0u32; 64];
            let draws = 64_000;
            for _ in 0..draws {
                let (x, y) = m.draw(&mut rng).unwrap();
                assert!(m.counts(x, y), "drew hidden pixel ({x}, {y})");
                seen[(y * 8 + x) as usize] += 1;
            }
            // Each counted pixel's share within 10 % of 1/counted: at 2000
            // to 32000 expected draws, 10 % is over 4 standard deviations.
            let expected = draws as f64 / m.counted() as f64;
            for (index, &n) in seen.iter().enumerate() {
                if m.counting()[index] {
                    assert!((n as f64 - expected).abs() < 0.1 * expected, "{index}: {n}");
                }
            }
        }
        assert_eq!(
            mask(2, 1, &[(0, 0), (1, 0)]).draw(&mut Pcg32::new(1, 1)),
            None
        );
    }

    #[test]
    fn the_mask_file_is_named_for_the_image_stem() {
        assert_eq!(
            dynamic_mask_path(Path::new("scene/images/0001.jpg")).unwrap(),
            Path::new("scene/images/dynamic_mask_0001.png")
        );
    }
}
