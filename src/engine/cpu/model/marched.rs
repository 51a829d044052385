//! A training step through the occupancy grid: march, then the fields,
//! compositing and the loss over the marched samples, and the grid's
//! updates.

use super::*;
use crate::engine::shared::driver::sigma_first;

impl CpuModel {
    /// A step through the occupancy grid (one level).
    pub(super) fn marched_step(&mut self, step: u32) -> StepStats {
        let mut times = StageTimes::default();
        let level = self.core.recipe.levels[0];
        let field_range = self.core.ranges[level.field].clone();
        let grid = self.grid.as_ref().expect("marching recipes have a grid");
        let b = &mut self.buffers;
        let rays = b.origins.len() / 3;

        let clock = Instant::now();
        let budget = match self.core.batch_size {
            BatchSize::Samples(samples) => samples,
            BatchSize::Rays(_) => usize::MAX,
        };
        let params = MarchParams {
            config: self.core.recipe.march,
            mapping: self.mapping,
            jitter_seed: Some(mix_seed(self.seed, step)),
            sample_budget: budget,
        };
        let held = self.held_samples.is_some();
        let marched = match b.held_march {
            // Samples held (gradient checks of the cameras): each keeps its
            // distance along its ray, the ray wherever its pose puts it.
            Some(stats) if held && stats.rays == rays => {
                let m = &mut b.marched;
                for r in 0..stats.rays_kept {
                    let origin = Vec3::from_slice(&b.origins[3 * r..3 * r + 3]);
                    let direction = Vec3::from_slice(&b.directions[3 * r..3 * r + 3]);
                    for i in m.ray(r) {
                        let p = self.mapping.to_unit(origin + direction * m.t[i]);
                        m.positions[3 * i..3 * i + 3].copy_from_slice(&p.to_array());
                        m.directions[3 * i..3 * i + 3].copy_from_slice(&direction.to_array());
                    }
                }
                stats
            }
            _ => march(
                grid,
                &b.origins,
                &b.directions,
                &params,
                &mut b.march,
                &mut b.marched,
            ),
        };
        b.held_march = held.then_some(marched);
        self.core
            .batch_sizer
            .record(marched.rays_kept, marched.samples);
        let kept = marched.rays_kept;
        let s = marched.samples;
        let field = &self.fields[level.field];
        let unit_cube = field.coordinates() == Coordinates::UnitCube;
        if !unit_cube {
            to_world(&self.mapping, &b.marched.positions, &mut b.world);
        }
        let frustums = self.core.recipe.samples == SampleShape::ConicalFrustums;
        if frustums {
            // Each marched sample stands for the frustum of its step,
            // centred on it.
            let m = &b.marched;
            let scratch = &mut b.sampling;
            scratch.starts.clear();
            scratch.ends.clear();
            scratch.rays.clear();
            for r in 0..kept {
                for i in m.ray(r) {
                    scratch.starts.push((m.t[i] - 0.5 * m.dt[i]).max(0.0));
                    scratch.ends.push(m.t[i] + 0.5 * m.dt[i]);
                    scratch.rays.push(r as u32);
                }
            }
            set_len(&mut b.variances_marched, 3 * s);
            frustum_gaussians(
                &b.origins,
                &b.directions,
                &b.radii,
                &scratch.rays,
                &scratch.starts,
                &scratch.ends,
                &mut b.world,
                &mut b.variances_marched,
            );
        }
        times[Stage::March] = clock.elapsed().as_secs_f64();

        // Where each ray becomes opaque (its cut): σ first or forward
        // first, as `sigma_first` weighs them. Both passes are counted as
        // the networks' forward time (the encodings are part of the field
        // here).
        let clock = Instant::now();
        let (forward_macs, density_macs) =
            (field.macs_per_sample(), field.density_macs_per_sample());
        let forward_first = !sigma_first(
            field.may_find_cut_in_forward(),
            forward_macs,
            density_macs,
            self.used_fraction,
        );
        let field_params = &self.params[field_range.clone()];
        // The field's positions: unit-cube ones as marched, or world ones.
        let positions = if unit_cube {
            &b.marched.positions
        } else {
            &b.world
        };
        let min_transmittance = self.core.recipe.march.min_transmittance;
        if forward_first {
            set_len(&mut b.sigma_forward, s);
            set_len(&mut b.rgb_marched, 3 * s);
            sample_images(
                &b.ray_images,
                &b.marched.ray_offsets[..kept + 1],
                &mut b.sample_images,
            );
            self.fields[level.field].forward(
                field_params,
                positions,
                frustums.then_some(&b.variances_marched[..]),
                &b.marched.directions,
                training_appearance(&b.sample_images),
                &mut b.sigma_forward,
                &mut b.rgb_marched,
            );
            set_len(&mut b.rays.samples_used, kept);
            composite_batch::samples_before_cut(
                &b.sigma_forward,
                &b.marched.dt,
                &b.marched.ray_offsets[..kept + 1],
                min_transmittance,
                &mut b.rays.samples_used,
            );
        } else {
            set_len(&mut b.sigma_marched, s);
            self.fields[level.field].density_for_cut(
                field_params,
                positions,
                frustums.then_some(&b.variances_marched[..]),
                &mut b.sigma_marched,
            );
            set_len(&mut b.rays.samples_used, kept);
            composite_batch::samples_before_cut(
                &b.sigma_marched,
                &b.marched.dt,
                &b.marched.ray_offsets[..kept + 1],
                min_transmittance,
                &mut b.rays.samples_used,
            );
        }
        if b.levels.is_empty() {
            b.levels.push(LevelBuffers::default());
        }
        let lb = &mut b.levels[0];
        b.source.clear();
        lb.ray_offsets.clear();
        lb.ray_offsets.push(0);
        for (r, &count) in b.rays.samples_used.iter().enumerate() {
            let first = b.marched.ray_offsets[r];
            b.source.extend(first..first + count);
            lb.ray_offsets.push(b.source.len() as u32);
        }
        let u = b.source.len();
        gather_rows(&b.marched.dt, 1, &b.source, &mut lb.dt);
        gather_rows(&b.marched.t, 1, &b.source, &mut lb.t);
        if forward_first {
            gather_rows(&b.sigma_forward, 1, &b.source, &mut lb.sigma);
            gather_rows(&b.rgb_marched, 3, &b.source, &mut lb.rgb);
        } else {
            gather_rows(positions, 3, &b.source, &mut lb.positions);
            gather_rows(&b.marched.directions, 3, &b.source, &mut lb.directions);
            if frustums {
                gather_rows(&b.variances_marched, 3, &b.source, &mut lb.variances);
            }
            // Compositing uses the σ the cut was found with, so it stops
            // exactly where the cut said (the forward pass may differ from
            // the σ-only inference in the last bits).
            set_len(&mut b.sigma_forward, u);
            set_len(&mut lb.rgb, 3 * u);
            sample_images(&b.ray_images, &lb.ray_offsets, &mut b.sample_images);
            self.fields[level.field].forward_before_cut(
                field_params,
                &b.source,
                &lb.positions,
                frustums.then_some(&lb.variances[..]),
                &lb.directions,
                training_appearance(&b.sample_images),
                &mut b.sigma_forward,
                &mut lb.rgb,
            );
            gather_rows(&b.sigma_marched, 1, &b.source, &mut lb.sigma);
        }
        times[Stage::NetworksForward] = clock.elapsed().as_secs_f64();

        let clock = Instant::now();
        let distortion = (self.core.recipe.distortion > 0.0 && kept > 0).then(|| Distortion {
            weight_per_ray: self.core.recipe.distortion / kept as f32,
            distance_scale: self.mapping.diagonal_scale(),
        });
        let loss = composite_and_loss(
            lb,
            &b.targets[..3 * kept],
            &b.backgrounds[..3 * kept],
            min_transmittance,
            self.loss,
            level.loss_weight,
            distortion,
            &mut b.rays,
        );
        times[Stage::Composite] = clock.elapsed().as_secs_f64();

        let clock = Instant::now();
        // The one field's backward pass writes its gradient; any other
        // field's is zero.
        for (i, range) in self.core.ranges.iter().enumerate() {
            if i != level.field {
                b.gradients[range.clone()].fill(0.0);
            }
        }
        if forward_first {
            // The used samples' gradients back in their marched rows.
            set_len(&mut b.d_sigma_marched, s);
            set_len(&mut b.d_rgb_marched, 3 * s);
            b.d_sigma_marched.fill(0.0);
            b.d_rgb_marched.fill(0.0);
            for (k, &i) in b.source.iter().enumerate() {
                let i = i as usize;
                b.d_sigma_marched[i] = lb.d_sigma[k];
                b.d_rgb_marched[3 * i..3 * i + 3].copy_from_slice(&lb.d_rgb[3 * k..3 * k + 3]);
            }
            self.fields[level.field].backward(
                field_params,
                &b.d_sigma_marched,
                &b.d_rgb_marched,
                &mut b.gradients[field_range.clone()],
                Gradient::Overwrite,
            );
        } else {
            self.fields[level.field].backward(
                field_params,
                &lb.d_sigma,
                &lb.d_rgb,
                &mut b.gradients[field_range.clone()],
                Gradient::Overwrite,
            );
        }
        if let Some(refinement) = &mut self.refinement {
            // The rows the backward pass saw: every marched sample (zero
            // past the cut) or the used ones.
            let (rows, offsets, t) = if forward_first {
                (s, &b.marched.ray_offsets[..kept + 1], &b.marched.t)
            } else {
                (u, &lb.ray_offsets[..], &lb.t)
            };
            set_len(&mut b.d_positions, 3 * rows);
            set_len(&mut b.d_sample_directions, 3 * rows);
            self.fields[level.field].input_gradients(
                &self.params[field_range.clone()],
                &mut b.d_positions,
                &mut b.d_sample_directions,
            );
            // The field's position is o + t·d, in the unit cube (scaled by
            // the mapping) or in the world.
            let scale = if unit_cube { self.mapping.scale } else { 1.0 };
            ray_gradients(
                offsets,
                t,
                scale,
                &b.d_positions,
                &b.d_sample_directions,
                rays,
                &mut b.d_origins,
                &mut b.d_directions,
            );
            refinement.backward(&b.images, &b.directions, &b.d_origins, &b.d_directions);
        }
        times[Stage::NetworksBackward] = clock.elapsed().as_secs_f64();
        if s > 0 {
            self.used_fraction = u as f64 / s as f64;
        }

        let network_flops = if forward_first {
            6.0 * (forward_macs * s) as f64
        } else {
            // σ of every marched sample, then forward (2 FLOP a
            // multiply-add) and backward (twice the forward) of the used.
            2.0 * (density_macs * s) as f64 + 6.0 * (forward_macs * u) as f64
        };
        StepStats {
            loss: loss as f32,
            level_losses: [loss as f32, 0.0],
            rays: if rays == 0 { 0 } else { kept },
            samples: s,
            samples_composited: Some(u),
            proposal_samples: 0,
            proposal_loss: 0.0,
            times,
            network_flops,
        }
    }

    pub(super) fn update_grid(&mut self, step: u32) {
        let Some(grid) = self.grid.as_mut() else {
            return;
        };
        let level = self.core.recipe.levels[0];
        let field = &self.fields[level.field];
        let params = &self.params[self.core.ranges[level.field].clone()];
        let mapping = self.mapping;
        let mut world = Vec::new();
        let frustums = self.core.recipe.samples == SampleShape::ConicalFrustums;
        let cell_variance = grid_cell_variance(grid, &mapping);
        let mut variances = Vec::new();
        let unit_cube = field.coordinates() == Coordinates::UnitCube;
        grid.update(step, self.seed, |positions, sigma| {
            if unit_cube {
                field.density(params, positions, None, sigma);
                return;
            }
            to_world(&mapping, positions, &mut world);
            if frustums {
                set_len(&mut variances, world.len());
                variances.fill(cell_variance);
            }
            field.density(params, &world, frustums.then_some(&variances[..]), sigma);
        });
    }
}

/// Each ray's gradients (`rays` × 3, rays past the offsets' zero) from its
/// samples' gradients with respect to the field's positions x = scale ·
/// (o + t d) + offset and its directions: dL/do = scale · Σ dL/dx, dL/dd =
/// Σ (scale · t · dL/dx + dL/d(direction)), the samples' t held still (no
/// gradient flows through where the march put them).
#[allow(clippy::too_many_arguments)]
fn ray_gradients(
    offsets: &[u32],
    t: &[f32],
    scale: f32,
    d_positions: &[f32],
    d_directions: &[f32],
    rays: usize,
    d_origins: &mut Vec<f32>,
    d_ray_directions: &mut Vec<f32>,
) {
    set_len(d_origins, 3 * rays);
    set_len(d_ray_directions, 3 * rays);
    d_origins.fill(0.0);
    d_ray_directions.fill(0.0);
    for (r, window) in offsets.windows(2).enumerate() {
        let (mut origin, mut direction) = ([0f64; 3], [0f64; 3]);
        for i in window[0] as usize..window[1] as usize {
            for a in 0..3 {
                let dx = (scale * d_positions[3 * i + a]) as f64;
                origin[a] += dx;
                direction[a] += t[i] as f64 * dx + d_directions[3 * i + a] as f64;
            }
        }
        for a in 0..3 {
            d_origins[3 * r + a] = origin[a] as f32;
            d_ray_directions[3 * r + a] = direction[a] as f32;
        }
    }
}
