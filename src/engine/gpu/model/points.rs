//! σ and colour at given points (meshes and point clouds), as the cpu
//! model answers them: the last level's field, a cube of the footprint's
//! side as a Gaussian for a field of frustums, σ zero in cells the
//! occupancy grid marks empty (where rendering never looks).

use super::*;
use crate::engine::gpu::fields::{FieldInputs, FieldOutputs};

impl GpuModel {
    /// σ of the last level's field at world `positions`, and with
    /// `colour` (directions and an output) its colour, evaluated on the
    /// device in passes of the field's capacity.
    pub(super) fn evaluate_points(
        &self,
        positions: &[Vec3],
        footprint: f32,
        sigma: &mut [f32],
        mut colour: Option<(&[Vec3], &mut [f32])>,
    ) {
        let ctx = &self.context;
        let level = *self.core.recipe.levels.last().expect("a recipe has levels");
        let frustums = self.core.recipe.samples == SampleShape::ConicalFrustums;
        // A cube of side s as a Gaussian of the same variance per axis,
        // s²/12 (that of a uniform distribution over the side).
        let variance = footprint * footprint / 12.0;
        let mut guard = self.work();
        let field = &mut guard.fields[level.field];
        let unit_cube = field.coordinates() == Coordinates::UnitCube;
        let mapping = self.grid.as_ref().map(|g| g.mapping);
        let contraction = self.core.recipe.contraction;
        let chunk = field.capacity().min(positions.len()).max(1);
        let f = |label: &str, n: usize| zeroed_storage_buffer::<f32>(ctx, label, n);
        let point_buffer = f("points positions", 3 * chunk);
        let variance_buffer = f("points variances", if frustums { 3 * chunk } else { 1 });
        let direction_buffer = f("points directions", 3 * chunk);
        let sigma_buffer = f("points sigma", chunk);
        let rgb_buffer = f("points rgb", 3 * chunk);
        let queue = &ctx.queue;
        for (i, (points, sigma)) in positions
            .chunks(chunk)
            .zip(sigma.chunks_mut(chunk))
            .enumerate()
        {
            let n = points.len();
            let (flat, variances): (Vec<[f32; 3]>, Vec<[f32; 3]>) = points
                .iter()
                .map(|&p| match (contraction, mapping) {
                    // Through the contraction where the recipe has one (the
                    // cpu's `InputMap::fill`): a frustum's Gaussian through
                    // its linearisation.
                    (Some(c), _) if frustums => {
                        let (mean, covariance) = c.contract_world_gaussian(
                            p,
                            glam::Mat3::from_diagonal(Vec3::splat(variance)),
                        );
                        (mean.to_array(), covariance.diagonal().to_array())
                    }
                    (Some(c), _) if unit_cube => (c.to_unit_cube(p).to_array(), [variance; 3]),
                    (Some(c), _) => (c.contract_world(p).to_array(), [variance; 3]),
                    (None, Some(mapping)) if unit_cube => {
                        (mapping.to_unit(p).to_array(), [variance; 3])
                    }
                    _ => (p.to_array(), [variance; 3]),
                })
                .unzip();
            queue.write_buffer(&point_buffer, 0, bytemuck::cast_slice(&flat));
            if frustums {
                queue.write_buffer(&variance_buffer, 0, bytemuck::cast_slice(&variances));
            }
            let variances = frustums.then_some(&variance_buffer);
            let mut rec = Recorder::new(ctx);
            match colour.as_ref() {
                Some((directions, _)) => {
                    let rows = &directions[chunk * i..chunk * i + n];
                    let flat: Vec<f32> = rows.iter().flat_map(|d| d.to_array()).collect();
                    queue.write_buffer(&direction_buffer, 0, bytemuck::cast_slice(&flat));
                    field.record_forward(
                        &mut rec,
                        &self.params,
                        FieldInputs {
                            positions: &point_buffer,
                            variances,
                            directions: &direction_buffer,
                        },
                        self.rendered_appearance(),
                        n,
                        FieldOutputs {
                            sigma: &sigma_buffer,
                            rgb: &rgb_buffer,
                        },
                    );
                }
                None => field.record_density(
                    &mut rec,
                    &self.params,
                    &point_buffer,
                    variances,
                    n,
                    &sigma_buffer,
                ),
            }
            rec.submit();
            sigma.copy_from_slice(&read_buffer::<f32>(ctx, &sigma_buffer, n));
            if let Some((_, rgb)) = colour.as_mut() {
                rgb[3 * chunk * i..3 * (chunk * i + n)].copy_from_slice(&read_buffer::<f32>(
                    ctx,
                    &rgb_buffer,
                    3 * n,
                ));
            }
        }
        if colour.is_none()
            && let Some(grid) = &self.grid
        {
            for (s, p) in sigma.iter_mut().zip(positions) {
                if !grid.grid.occupied_at(grid.mapping.to_unit(*p)) {
                    *s = 0.0;
                }
            }
        }
    }
}
