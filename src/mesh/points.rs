//! A coloured point cloud of a trained scene: each training ray's expected
//! depth, where the ray is opaque enough to have one.

use glam::Vec3;

use crate::model::{RadianceModel, RayColumns};
use crate::scene::crop::CropBox;
use crate::scene::{Frame, Ray, to_u8};

/// How to make a point cloud.
#[derive(Debug, Clone, PartialEq)]
pub struct PointSettings {
    /// Every `stride`-th pixel of every `stride`-th row of each view.
    pub stride: u32,
    /// Rays less opaque than this give no point: their expected depth
    /// mixes the surface with the background.
    pub min_opacity: f32,
    /// Points outside it are dropped.
    pub crop: Option<CropBox>,
}

/// Rays per call into the model.
const RAYS_PER_CALL: usize = 1 << 14;

/// The pixel stride that keeps a point cloud of `views` about `max_points`:
/// the square root of the pixels per point wanted, at least 1.
pub fn stride_for(views: &[Frame], max_points: usize) -> u32 {
    let pixels: u64 = views
        .iter()
        .map(|f| f.camera.intrinsics.width as u64 * f.camera.intrinsics.height as u64)
        .sum();
    ((pixels as f64 / max_points.max(1) as f64).sqrt().ceil() as u32).max(1)
}

/// The point cloud seen by `views`: for each kept ray, the point at its
/// expected depth (Σ wᵢ tᵢ / Σ wᵢ) and the colour there (the composited
/// colour over black, divided by the opacity). `progress` gets the views
/// done.
pub fn extract_points(
    model: &dyn RadianceModel,
    views: &[Frame],
    settings: &PointSettings,
    progress: &mut dyn FnMut(usize),
) -> (Vec<Vec3>, Vec<[u8; 3]>) {
    let (mut positions, mut colours) = (Vec::new(), Vec::new());
    for (index, view) in views.iter().enumerate() {
        points_of_view(model, view, settings, &mut positions, &mut colours);
        progress(index + 1);
    }
    (positions, colours)
}

/// The points one view adds to a cloud (see [`extract_points`]), for a
/// caller that does a view at a time.
pub fn points_of_view(
    model: &dyn RadianceModel,
    view: &Frame,
    settings: &PointSettings,
    positions: &mut Vec<Vec3>,
    colours: &mut Vec<[u8; 3]>,
) {
    let stride = settings.stride.max(1);
    let mut pixels = Vec::new();
    let k = view.camera.intrinsics;
    let rays: Vec<Ray> = (0..k.height)
        .step_by(stride as usize)
        .flat_map(|j| (0..k.width).step_by(stride as usize).map(move |i| (i, j)))
        .map(|(i, j)| view.camera.pixel_ray(i, j))
        .collect();
    for chunk in rays.chunks(RAYS_PER_CALL) {
        let columns = RayColumns::of(chunk);
        pixels.resize(chunk.len(), Default::default());
        model.render(columns.over([0.0; 3]), &mut pixels);
        for ((o, d), p) in columns.origins.iter().zip(&columns.directions).zip(&pixels) {
            if !(p.opacity >= settings.min_opacity && p.opacity > 0.0) {
                continue;
            }
            let point = *o + *d * (p.depth / p.opacity);
            if !point.is_finite() || settings.crop.is_some_and(|c| !c.contains(point)) {
                continue;
            }
            positions.push(point);
            colours.push(p.rgb.map(|c| to_u8(c / p.opacity)));
        }
    }
}
