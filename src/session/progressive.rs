//! Progressive rendering for the viewport: a camera is shown first at a
//! coarse level, then refined level by level (the levels' sizes are
//! [`super::schedule`]'s choice), each level drawn in chunks of rays so
//! that the training thread can answer commands between chunks and drop a
//! level the user has moved away from.

use std::time::Duration;

use glam::Vec3;

use crate::engine::gpu::GpuContext;
use crate::model::{RadianceModel, RenderMode, RenderRays, RenderedPixel, TextureRender};
use crate::scene::{Camera, Intrinsics};

/// `camera` seen at 1/`downscale` of its resolution, at least one pixel each
/// way. The image plane keeps its extent, so the focal lengths and the
/// principal point scale with the size actually kept (which differs from
/// 1/`downscale` when the size is not a multiple of it).
pub fn level_camera(camera: &Camera, downscale: u32) -> Camera {
    let k = camera.intrinsics;
    let width = (k.width / downscale.max(1)).max(1);
    let height = (k.height / downscale.max(1)).max(1);
    let sx = width as f32 / k.width.max(1) as f32;
    let sy = height as f32 / k.height.max(1) as f32;
    Camera::new(
        Intrinsics {
            width,
            height,
            fx: k.fx * sx,
            fy: k.fy * sy,
            cx: k.cx * sx,
            cy: k.cy * sy,
            lens: k.lens,
        },
        camera.camera_to_world,
    )
    .with_ndc(camera.ndc)
}

/// Rows `first .. first + rows` of `camera`'s image as a camera of their
/// own (`rows` high, the principal point moved up by `first`): its pixel
/// (i, j) looks along `camera`'s pixel (i, first + j), so a level can be
/// drawn band by band.
pub fn band_camera(camera: &Camera, first: u32, rows: u32) -> Camera {
    let k = camera.intrinsics;
    Camera::new(
        Intrinsics {
            height: rows.max(1),
            cy: k.cy - first as f32,
            ..k
        },
        camera.camera_to_world,
    )
    .with_ndc(camera.ndc)
}

/// Which rows of which view a band draws, and over what.
#[derive(Debug, Clone, Copy)]
pub struct Band<'a> {
    /// The whole view the band is part of.
    pub camera: &'a Camera,
    /// The band's first row in the view.
    pub first: u32,
    pub mode: RenderMode,
    pub background: [f32; 3],
}

/// Draws rows `band.first .. band.first + through.height()` of
/// `band.camera`'s view into `target` (the camera's size) through
/// `through` (a texture that many rows high, usable as a copy source): the
/// band's camera ([`band_camera`]) drawn with the engine's ordinary texture
/// render, then copied into place, so that a level slower than a unit of
/// the training thread's work is drawn a band at a time.
pub fn draw_band_to_texture(
    gpu: &dyn TextureRender,
    context: &GpuContext,
    band: Band<'_>,
    through: &wgpu::Texture,
    target: &wgpu::Texture,
) -> Result<(), String> {
    let Band {
        camera,
        first,
        mode,
        background,
    } = band;
    let rows = through.height();
    let k = camera.intrinsics;
    if through.width() != k.width || first.checked_add(rows).is_none_or(|end| end > k.height) {
        return Err(format!(
            "a band of {}×{rows} pixels at row {first} does not fit a {}×{} view",
            through.width(),
            k.width,
            k.height
        ));
    }
    gpu.render_to_texture(&band_camera(camera, first, rows), mode, background, through)?;
    let mut encoder = context.device.create_command_encoder(&Default::default());
    encoder.copy_texture_to_texture(
        through.as_image_copy(),
        wgpu::TexelCopyTextureInfo {
            texture: target,
            mip_level: 0,
            origin: wgpu::Origin3d {
                x: 0,
                y: first,
                z: 0,
            },
            aspect: wgpu::TextureAspect::All,
        },
        wgpu::Extent3d {
            width: k.width,
            height: rows,
            depth_or_array_layers: 1,
        },
    );
    context.queue.submit([encoder.finish()]);
    Ok(())
}

/// One level of one camera being rendered, chunk by chunk, row-major from
/// the top.
pub struct LevelRender {
    pub downscale: u32,
    camera: Camera,
    pixels: Vec<RenderedPixel>,
    done: usize,
    origins: Vec<Vec3>,
    directions: Vec<Vec3>,
    radii: Vec<f32>,
}

impl LevelRender {
    pub fn new(camera: &Camera, downscale: u32) -> Self {
        let camera = level_camera(camera, downscale);
        let count = camera.intrinsics.width as usize * camera.intrinsics.height as usize;
        Self {
            downscale,
            camera,
            pixels: vec![RenderedPixel::default(); count],
            done: 0,
            origins: Vec::new(),
            directions: Vec::new(),
            radii: Vec::new(),
        }
    }

    pub fn width(&self) -> u32 {
        self.camera.intrinsics.width
    }

    pub fn height(&self) -> u32 {
        self.camera.intrinsics.height
    }

    pub fn is_done(&self) -> bool {
        self.done == self.pixels.len()
    }

    /// Pixels rendered so far.
    pub fn rendered(&self) -> usize {
        self.done
    }

    /// Renders up to `max_rays` more pixels over `background`; returns how
    /// many it rendered.
    pub fn render_chunk(
        &mut self,
        model: &dyn RadianceModel,
        max_rays: usize,
        background: [f32; 3],
    ) -> usize {
        let end = (self.done + max_rays.max(1)).min(self.pixels.len());
        let width = self.camera.intrinsics.width as usize;
        self.origins.clear();
        self.directions.clear();
        self.radii.clear();
        for index in self.done..end {
            let ray = self
                .camera
                .pixel_ray((index % width) as u32, (index / width) as u32);
            self.origins.push(ray.origin);
            self.directions.push(ray.direction);
            self.radii.push(ray.radius());
        }
        let rays = RenderRays {
            origins: &self.origins,
            directions: &self.directions,
            radii: &self.radii,
            background,
        };
        model.render(rays, &mut self.pixels[self.done..end]);
        let rendered = end - self.done;
        self.done = end;
        rendered
    }

    /// Fills the pixels not rendered yet from `previous`, a finished level
    /// of the same camera (`width × height`, row-major, this level's size
    /// or coarser): each takes the previous pixel its centre falls in, so
    /// that the level shown before it is done keeps the old picture, enlarged
    /// where it was coarser, below the new rows. False when `previous` is
    /// not `width × height` or is finer than this level.
    pub fn fill_rest_from(&mut self, previous: &[RenderedPixel], width: u32, height: u32) -> bool {
        let (own_width, own_height) = (self.width(), self.height());
        if previous.len() != width as usize * height as usize
            || width == 0
            || height == 0
            || width > own_width
            || height > own_height
        {
            return false;
        }
        let own_width = own_width as usize;
        for index in self.done..self.pixels.len() {
            let (x, y) = (index % own_width, index / own_width);
            // Centre (x + ½) / own size, in the previous level's pixels.
            let from_x = ((2 * x + 1) * width as usize) / (2 * own_width);
            let from_y = ((2 * y + 1) * height as usize) / (2 * own_height as usize);
            self.pixels[index] = previous[from_y * width as usize + from_x];
        }
        true
    }

    /// The pixels as they stand: those rendered so far, and after them
    /// what [`Self::fill_rest_from`] put there (or defaults), row-major.
    pub fn pixels_so_far(&self) -> &[RenderedPixel] {
        &self.pixels
    }
}

/// Sizes chunks of rays so that each takes about `target` on this machine
/// and engine, from the rate of the chunks rendered so far.
#[derive(Debug, Clone, Copy)]
pub struct ChunkPacer {
    target: Duration,
    /// Smoothed rays per second; `None` before the first chunk.
    rays_per_second: Option<f64>,
}

impl ChunkPacer {
    /// Chunks never go below this, so per-call overheads stay small.
    const MIN_RAYS: usize = 256;
    /// Nor above this (the cpu engine's inference works in 2^16 chunks).
    const MAX_RAYS: usize = 1 << 16;
    /// The first chunk, before any rate is known: small enough to be quick
    /// on a slow software path.
    const FIRST_RAYS: usize = 2048;

    pub fn new(target: Duration) -> Self {
        Self {
            target,
            rays_per_second: None,
        }
    }

    pub fn chunk_rays(&self) -> usize {
        match self.rays_per_second {
            None => Self::FIRST_RAYS,
            Some(rate) => {
                ((rate * self.target.as_secs_f64()) as usize).clamp(Self::MIN_RAYS, Self::MAX_RAYS)
            }
        }
    }

    /// [`Self::chunk_rays`] without the upper bound (at least the lower):
    /// for callers that draw a chunk in one call of any size, where the
    /// bound would only add calls.
    pub fn uncapped_chunk_rays(&self) -> usize {
        match self.rays_per_second {
            None => Self::FIRST_RAYS,
            Some(rate) => {
                ((rate * self.target.as_secs_f64()).min(1e12) as usize).max(Self::MIN_RAYS)
            }
        }
    }

    /// Records that `rays` took `seconds`.
    pub fn record(&mut self, rays: usize, seconds: f64) {
        if rays == 0 || seconds <= 0.0 || !seconds.is_finite() {
            return;
        }
        let rate = rays as f64 / seconds;
        // Half-and-half smoothing: follows a change of engine load within a
        // few chunks without jumping on one slow chunk.
        self.rays_per_second = Some(match self.rays_per_second {
            None => rate,
            Some(old) => 0.5 * old + 0.5 * rate,
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Mat4;

    fn camera(width: u32, height: u32) -> Camera {
        let k = Intrinsics::from_fov_x(width, height, 0.7);
        Camera::new(k, Mat4::from_translation(Vec3::new(0.1, -0.2, 4.0)))
    }

    #[test]
    fn a_level_pixel_looks_through_the_centre_of_its_block() {
        let full = camera(64, 48);
        for downscale in [2, 4, 8] {
            let level = level_camera(&full, downscale);
            assert_eq!(level.intrinsics.width, 64 / downscale);
            assert_eq!(level.intrinsics.height, 48 / downscale);
            // Level pixel (i, j) covers full pixels [d i, d (i + 1)), whose
            // centre is at d i + d/2 in full-resolution pixel units.
            let (i, j) = (3, 2);
            let d = downscale as f32;
            let expected = full.ray_through(d * i as f32 + 0.5 * d, d * j as f32 + 0.5 * d);
            let got = level.pixel_ray(i, j);
            assert!((got.direction - expected.direction).length() < 1e-6);
            assert_eq!(got.origin, expected.origin);
        }
    }

    #[test]
    fn the_rows_not_drawn_show_the_coarser_picture_enlarged() {
        let full = camera(8, 4);
        let mut level = LevelRender::new(&full, 1);
        let coarse: Vec<RenderedPixel> = (0..8)
            .map(|i| RenderedPixel {
                depth: i as f32,
                ..Default::default()
            })
            .collect();
        // Not the size it claims, or finer than the level: refused.
        assert!(!level.fill_rest_from(&coarse[..7], 4, 2));
        let finer = vec![RenderedPixel::default(); 32];
        assert!(!level.fill_rest_from(&finer, 16, 2));
        // Two rows drawn, then the rest from a 4 × 2 picture: each pixel
        // takes the coarse pixel its centre falls in.
        let drawn = level.pixels_so_far().len();
        assert_eq!(drawn, 32);
        level.done = 16;
        assert!(level.fill_rest_from(&coarse, 4, 2));
        let depths: Vec<f32> = level.pixels_so_far()[16..]
            .iter()
            .map(|p| p.depth)
            .collect();
        assert_eq!(
            depths,
            vec![
                4.0, 4.0, 5.0, 5.0, 6.0, 6.0, 7.0, 7.0, 4.0, 4.0, 5.0, 5.0, 6.0, 6.0, 7.0, 7.0
            ]
        );
        assert!(level.pixels_so_far()[..16].iter().all(|p| p.depth == 0.0));
    }

    #[test]
    fn a_tiny_view_keeps_a_pixel_at_any_level() {
        let tiny = level_camera(&camera(5, 3), 8);
        assert_eq!((tiny.intrinsics.width, tiny.intrinsics.height), (1, 1));
    }

    #[test]
    fn a_band_looks_along_the_rows_it_covers() {
        let full = level_camera(&camera(64, 48), 2);
        let band = band_camera(&full, 7, 5);
        assert_eq!(
            (band.intrinsics.width, band.intrinsics.height),
            (full.intrinsics.width, 5)
        );
        for (i, j) in [(0, 0), (31, 4), (12, 2)] {
            let expected = full.pixel_ray(i, 7 + j);
            let got = band.pixel_ray(i, j);
            assert_eq!(got.origin, expected.origin);
            // The principal point moved by a whole number of rows: equal
            // up to the rounding of cy − first.
            assert!((got.direction - expected.direction).length() < 1e-6);
        }
    }

    #[test]
    fn the_pacer_aims_at_its_target_within_bounds() {
        let mut pacer = ChunkPacer::new(Duration::from_millis(50));
        assert_eq!(pacer.chunk_rays(), ChunkPacer::FIRST_RAYS);
        pacer.record(10_000, 0.1); // 100 000 rays/s → 5 000 rays in 50 ms
        assert_eq!(pacer.chunk_rays(), 5_000);
        // A very slow engine (0.1 rays/s): the smoothed rate halves each
        // time, and the chunk ends at the minimum rather than at zero.
        for _ in 0..20 {
            pacer.record(1, 10.0);
        }
        assert_eq!(pacer.chunk_rays(), ChunkPacer::MIN_RAYS);
    }
}
