//! A trained model's surface as a mesh: its density sampled on a grid over
//! a box, marching cubes at a threshold, vertex colours from its radiance.

use glam::Vec3;

use super::marching::{ScalarGrid, marching_cubes};
use super::{Mesh, MinComponent};
use crate::field::ModelKind;
use crate::model::{PointQuery, RadianceModel};
use crate::scene::crop::CropBox;
use crate::scene::to_u8;

/// The largest grid side: 2048³ nodes take 32 GiB of densities.
pub const MAX_RESOLUTION: u32 = 2048;

/// Grid nodes per call into the model: a slice of a 256³ grid at a time
/// at most, so the positions and densities in flight stay a few MB.
const NODES_PER_BATCH: usize = 1 << 16;

/// The density (per world unit) a mesh's surface is drawn at unless told
/// otherwise, for each model: 30 per unit-cube length, i.e. 30 · `scale`
/// world⁻¹ (9.9 on NeRF-synthetic's scale of 0.33).
///
/// Instant-NGP's testbed meshes at σ = 2.5 in its own units, per unit-cube
/// length (instant-ngp `include/neural-graphics-primitives/testbed.h`,
/// `compute_and_save_marching_cubes_mesh`'s default `thresh`); zrak's
/// densities are per world unit, a world unit being `scale` unit-cube
/// lengths, so that is 2.5 · `scale` here. On the demo scene after 300
/// steps, where the true surfaces are known (`tests/it/mesh_export.rs`, cells
/// of 0.024 world units), vertices lie a median 2.9 cells from them at
/// 2.5 world⁻¹ (NGP's 2.5 per unit length is 0.83 world⁻¹: 3.1 cells) and
/// 1.1 cells at 10 and at 25 world⁻¹, while at 100 most of the surface is
/// gone (a twelfth of the vertices): a briefly trained field's density
/// ramps up over a few cells in front of each surface and leaves faint
/// haze in the air, which the low threshold meshes. 30 per unit-cube
/// length is in the good range, and a cell of a 128-node grid over the
/// unit cube is then about 20 % opaque (1 − exp(−30/128)). NeRF's and
/// Mip-NeRF's densities (ReLU, softplus) are per world unit too and take
/// the same default, not measured on them yet.
pub fn default_threshold(_model: ModelKind, unit_cube_scale: f32) -> f32 {
    30.0 * unit_cube_scale
}

/// How to mesh a model.
#[derive(Debug, Clone, PartialEq)]
pub struct MeshSettings {
    /// Grid nodes along the box's longest side.
    pub resolution: u32,
    /// The density (per world unit) the surface is drawn at.
    pub threshold: f32,
    /// The box meshed; nothing outside it is kept.
    pub region: CropBox,
    pub min_component: Option<MinComponent>,
}

/// What an extraction did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MeshReport {
    pub dims: [usize; 3],
    /// Grid spacing along each axis, world units.
    pub spacing: Vec3,
    pub components_dropped: usize,
    /// Pieces of the surface before any was dropped, and the faces of the
    /// largest (0 when `min_component` was not given).
    pub components_before: usize,
    pub largest_component_faces: usize,
}

/// Grid nodes per axis and their spacing for `resolution` nodes along the
/// longest side of a box of `size`: about cubic cells, the box covered
/// exactly (the nodes of each axis span its side).
pub fn grid_dims(size: Vec3, resolution: u32) -> ([usize; 3], Vec3) {
    let longest = size.max_element();
    let cell = longest / (resolution.max(2) - 1) as f32;
    let dims = size
        .to_array()
        .map(|s| ((s / cell).round() as usize + 1).max(2));
    let spacing = Vec3::new(
        size.x / (dims[0] - 1) as f32,
        size.y / (dims[1] - 1) as f32,
        size.z / (dims[2] - 1) as f32,
    );
    (dims, spacing)
}

/// Bytes a mesh of `resolution` takes while it is extracted: the
/// densities (4 bytes a node) and the surface (about 6 cells' worth of
/// faces per surface cell, bounded by a few full grid slices).
pub fn mesh_bytes(dims: [usize; 3]) -> u64 {
    let nodes = dims.iter().map(|&d| d as u64).product::<u64>();
    let slice = dims.iter().map(|&d| d as u64).max().unwrap_or(0).pow(2);
    nodes * 4 + slice * 16 * 64
}

/// The model's density on a grid over a box, sampled a slab of z layers
/// at a time so that a caller can report progress and stop between slabs
/// (the viewer's mesh export, which gets one slab per unit of its thread's
/// time). [`extract_mesh`] runs the same slabs back to back, so both make
/// the same grid.
pub struct DensitySampler {
    settings: MeshSettings,
    grid: ScalarGrid,
    /// z layers sampled so far.
    layers_done: usize,
    /// z layers per slab: about [`NODES_PER_BATCH`] nodes, at least one.
    layers_per_slab: usize,
}

impl DensitySampler {
    /// Checks `settings` and sets up the grid; samples nothing yet.
    pub fn new(settings: &MeshSettings) -> Result<Self, String> {
        if settings.resolution < 2 || settings.resolution > MAX_RESOLUTION {
            return Err(format!(
                "the resolution must be 2 to {MAX_RESOLUTION} grid nodes a side, got {}",
                settings.resolution
            ));
        }
        if !(settings.threshold.is_finite() && settings.threshold > 0.0) {
            return Err(format!(
                "the threshold must be a positive density, got {}",
                settings.threshold
            ));
        }
        settings.region.check()?;
        let aabb = settings.region.bounding_aabb();
        let (dims, spacing) = grid_dims(aabb.size(), settings.resolution);
        let layer = dims[0] * dims[1];
        Ok(Self {
            settings: settings.clone(),
            grid: ScalarGrid {
                dims,
                origin: aabb.min,
                spacing,
                values: vec![0.0; dims.iter().product()],
            },
            layers_done: 0,
            layers_per_slab: (NODES_PER_BATCH / layer).max(1),
        })
    }

    /// (z layers sampled, z layers in all).
    pub fn progress(&self) -> (usize, usize) {
        (self.layers_done, self.grid.dims[2])
    }

    /// Slabs in all.
    pub fn slabs(&self) -> usize {
        self.grid.dims[2].div_ceil(self.layers_per_slab)
    }

    /// Slabs sampled so far.
    pub fn slabs_done(&self) -> usize {
        self.layers_done.div_ceil(self.layers_per_slab)
    }

    pub fn is_done(&self) -> bool {
        self.layers_done == self.grid.dims[2]
    }

    /// Samples the next slab of z layers; false once all are done.
    pub fn sample_slab(&mut self, model: &dyn RadianceModel) -> Result<bool, String> {
        if self.is_done() {
            return Ok(false);
        }
        let dims = self.grid.dims;
        let layer = dims[0] * dims[1];
        let first = self.layers_done;
        let last = (first + self.layers_per_slab).min(dims[2]);
        let region = &self.settings.region;
        let turned = region.rotation != glam::Quat::IDENTITY;
        let footprint = self.grid.spacing.max_element();
        let total = last * layer;
        let mut positions = Vec::with_capacity(NODES_PER_BATCH.min(total - first * layer));
        for start in (first * layer..total).step_by(NODES_PER_BATCH) {
            let end = (start + NODES_PER_BATCH).min(total);
            positions.clear();
            positions.extend((start..end).map(|index| {
                let i = index % dims[0];
                let j = index / dims[0] % dims[1];
                let k = index / layer;
                self.grid.position(i, j, k)
            }));
            let query = PointQuery {
                positions: &positions,
                directions: &[],
                footprint,
            };
            model.density_at(query, &mut self.grid.values[start..end])?;
            if turned {
                // The grid covers the turned box's bounding box: nodes
                // outside the box itself are empty.
                for (value, p) in self.grid.values[start..end].iter_mut().zip(&positions) {
                    if !region.contains(*p) {
                        *value = 0.0;
                    }
                }
            }
        }
        self.layers_done = last;
        Ok(!self.is_done())
    }

    /// The sampled grid (whole once [`Self::is_done`]).
    pub fn grid(&self) -> &ScalarGrid {
        &self.grid
    }

    /// The surface of the sampled grid with vertex colours: see
    /// [`extract_mesh`]. Samples whatever slabs are left first.
    pub fn finish(mut self, model: &dyn RadianceModel) -> Result<(Mesh, MeshReport), String> {
        while self.sample_slab(model)? {}
        surface_of(&self.grid, &self.settings, model)
    }
}

/// Samples the model's density on a grid over `settings.region`.
/// `progress` gets the share done (0 to 1).
pub fn sample_density(
    model: &dyn RadianceModel,
    settings: &MeshSettings,
    progress: &mut dyn FnMut(f32),
) -> Result<ScalarGrid, String> {
    let mut sampler = DensitySampler::new(settings)?;
    while sampler.sample_slab(model)? {
        let (done, total) = sampler.progress();
        progress(done as f32 / total as f32);
    }
    progress(1.0);
    Ok(sampler.grid)
}

/// The model's surface at `settings.threshold` over `settings.region`,
/// closed where it meets the region's faces, with vertex colours: the
/// radiance at each vertex looking along the inward normal (the normal
/// being −∇σ, by central differences on the grid), as a camera facing the
/// surface would see it.
pub fn extract_mesh(
    model: &dyn RadianceModel,
    settings: &MeshSettings,
    progress: &mut dyn FnMut(f32),
) -> Result<(Mesh, MeshReport), String> {
    let grid = sample_density(model, settings, &mut |share| progress(0.9 * share))?;
    let result = surface_of(&grid, settings, model)?;
    progress(1.0);
    Ok(result)
}

/// Marching cubes on a sampled grid, small pieces dropped as asked, and
/// the vertices' colours.
fn surface_of(
    grid: &ScalarGrid,
    settings: &MeshSettings,
    model: &dyn RadianceModel,
) -> Result<(Mesh, MeshReport), String> {
    let mut mesh = marching_cubes(grid, settings.threshold, true);
    let (components_before, largest_component_faces) = match settings.min_component {
        Some(_) => {
            let (_, sizes) = mesh.components();
            (sizes.len(), sizes.iter().copied().max().unwrap_or(0))
        }
        None => (0, 0),
    };
    let components_dropped = settings
        .min_component
        .map_or(0, |min| mesh.remove_small_components(min));
    let normals: Vec<Vec3> = mesh
        .positions
        .iter()
        .map(|&p| -interpolated_gradient(grid, p).normalize_or_zero())
        .collect();
    let directions: Vec<Vec3> = normals
        .iter()
        .map(|&n| if n == Vec3::ZERO { -Vec3::Z } else { -n })
        .collect();
    let mut rgb = vec![0f32; 3 * mesh.positions.len()];
    let query = PointQuery {
        positions: &mesh.positions,
        directions: &directions,
        footprint: grid.spacing.max_element(),
    };
    model.colour_at(query, &mut rgb)?;
    mesh.colours = rgb
        .chunks_exact(3)
        .map(|c| [to_u8(c[0]), to_u8(c[1]), to_u8(c[2])])
        .collect();
    Ok((
        mesh,
        MeshReport {
            dims: grid.dims,
            spacing: grid.spacing,
            components_dropped,
            components_before,
            largest_component_faces,
        },
    ))
}

/// The grid's gradient at `p` (world), trilinear between the nodes'
/// central-difference gradients.
pub fn interpolated_gradient(grid: &ScalarGrid, p: Vec3) -> Vec3 {
    let local = ((p - grid.origin) / grid.spacing).max(Vec3::ZERO);
    let mut base = [0usize; 3];
    let mut fraction = Vec3::ZERO;
    for axis in 0..3 {
        let top = grid.dims[axis] - 2;
        let cell = (local[axis].floor() as usize).min(top);
        base[axis] = cell;
        fraction[axis] = (local[axis] - cell as f32).clamp(0.0, 1.0);
    }
    let mut gradient = Vec3::ZERO;
    for corner in 0..8 {
        let offset = [corner & 1, (corner >> 1) & 1, (corner >> 2) & 1];
        let weight = (0..3)
            .map(|a| {
                if offset[a] == 1 {
                    fraction[a]
                } else {
                    1.0 - fraction[a]
                }
            })
            .product::<f32>();
        if weight > 0.0 {
            gradient += weight
                * grid.gradient(
                    base[0] + offset[0],
                    base[1] + offset[1],
                    base[2] + offset[2],
                );
        }
    }
    gradient
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_grid_covers_the_box_with_about_cubic_cells() {
        let (dims, spacing) = grid_dims(Vec3::new(2.0, 1.0, 0.5), 257);
        assert_eq!(dims, [257, 129, 65]);
        assert!((spacing - Vec3::splat(2.0 / 256.0)).abs().max_element() < 1e-7);
        // A side too short for a cell still gets two nodes.
        let (dims, _) = grid_dims(Vec3::new(1.0, 1e-6, 1.0), 64);
        assert_eq!(dims[1], 2);
    }

    #[test]
    fn the_gradient_of_a_linear_field_is_exact_between_nodes() {
        let grid = ScalarGrid::sample([5, 6, 7], Vec3::splat(-1.0), Vec3::splat(0.5), |p| {
            3.0 * p.x - 2.0 * p.y + 0.5 * p.z
        });
        for p in [
            Vec3::ZERO,
            Vec3::new(0.3, 0.7, 1.9),
            Vec3::new(-1.0, -1.0, -1.0),
        ] {
            let g = interpolated_gradient(&grid, p);
            assert!((g - Vec3::new(3.0, -2.0, 0.5)).length() < 1e-4, "{p}: {g}");
        }
    }
}
