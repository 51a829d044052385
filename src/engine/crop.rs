//! The crop box at the samples, as both engines apply it: a sample outside
//! the box has no density, so it adds nothing to its ray and the background
//! shows where the box leaves nothing ([`crate::model::RadianceModel::set_crop`]).
//! Zeroing σ rather than dropping the sample keeps the march itself (and so
//! each ray's sample cap) the same with and without a box.

use glam::Vec3;
use rayon::prelude::*;

use crate::scene::UnitCubeMapping;
use crate::scene::crop::CropBox;

/// Sets σ to zero at the samples (unit-cube positions, n × 3) outside
/// `crop`.
pub fn crop_densities(
    crop: &CropBox,
    mapping: &UnitCubeMapping,
    unit_positions: &[f32],
    sigma: &mut [f32],
) {
    sigma
        .par_iter_mut()
        .zip(unit_positions.par_chunks_exact(3))
        .for_each(|(s, p)| {
            if !crop.contains(mapping.to_world(Vec3::from_slice(p))) {
                *s = 0.0;
            }
        });
}

/// Cuts each ray's interval `[near, far]` to the crop box (the slab test in
/// the box's frame), so every sample of a fixed sampler lands inside it; a
/// ray that misses the box gets an empty interval (`far = near`) and shows
/// the background. `origins` and `directions` are world rays, n × 3.
pub fn crop_ray_bounds(
    crop: &CropBox,
    origins: &[f32],
    directions: &[f32],
    near: &mut [f32],
    far: &mut [f32],
) {
    for (r, (near, far)) in near.iter_mut().zip(far.iter_mut()).enumerate() {
        let (n, f) = crop
            .intersect(
                Vec3::from_slice(&origins[3 * r..]),
                Vec3::from_slice(&directions[3 * r..]),
                *near,
            )
            .map_or((*near, *near), |(t0, t1)| (t0, t1.min(*far)));
        *near = n;
        *far = f.max(n);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn samples_outside_the_box_lose_their_density_and_rays_their_length_outside_it() {
        let mapping = UnitCubeMapping::BLENDER;
        let crop = CropBox::axis_aligned(Vec3::new(0.5, 0.0, 0.0), Vec3::splat(1.0));
        // World x = 0.2 (inside), x = −0.2 (outside), y = 0.6 (outside).
        let world = [
            Vec3::new(0.2, 0.0, 0.0),
            Vec3::new(-0.2, 0.0, 0.0),
            Vec3::new(0.5, 0.6, 0.0),
        ];
        let unit: Vec<f32> = world
            .iter()
            .flat_map(|&w| mapping.to_unit(w).to_array())
            .collect();
        let mut sigma = vec![3.0; 3];
        crop_densities(&crop, &mapping, &unit, &mut sigma);
        assert_eq!(sigma, [3.0, 0.0, 0.0]);

        // A ray along +x from x = −2 meets the box over x ∈ [0, 1]: t ∈
        // [2, 3], cut again by its own far bound 2.5; a ray along +y at
        // x = −1 misses it.
        let origins = [-2.0, 0.0, 0.0, -1.0, -2.0, 0.0];
        let directions = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0];
        let (mut near, mut far) = (vec![0.5, 0.5], vec![2.5, 4.0]);
        crop_ray_bounds(&crop, &origins, &directions, &mut near, &mut far);
        assert_eq!((near[0], far[0]), (2.0, 2.5));
        assert_eq!(near[1], far[1]);
    }
}
