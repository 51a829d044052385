//! A training step through the occupancy grid (the host marches, the
//! device computes the fields), the grid's updates, and σ and colour of
//! marched samples for rendering.

use super::*;
use crate::engine::shared::composite::Distortion;

impl GpuModel {
    /// A step through the occupancy grid, in two submissions: the march,
    /// whose two counters (samples, rays kept) are read back to size the
    /// rest; then the field, compositing with the
    /// march's transmittance cut, the loss, the backward passes and Adam.
    ///
    /// Unlike the cpu model, the field's forward and backward passes run on
    /// every marched sample, not only on those before each ray's cut: the
    /// gradient is the same (compositing's backward pass gives the samples
    /// past the cut zero gradient), the work is larger by the share of
    /// samples past the cut. A σ-first pass and compaction on the device
    /// are not built yet.
    pub(super) fn run_marched(&mut self, batch: &RayBatch, step: u32, optimise: bool) -> StepStats {
        let ctx = &self.context;
        let grid = self.grid.as_ref().expect("a marched recipe has a grid");
        let level = self.recipe.levels[0];
        let rays = batch.len();
        let mut guard = self.work.lock().unwrap_or_else(|e| e.into_inner());
        let work = &mut *guard;
        let frustums = self.recipe.samples == SampleShape::ConicalFrustums;
        let unit_cube = work.fields[level.field].coordinates() == Coordinates::UnitCube;
        let marched = work.marched.as_mut().expect("a marched recipe has buffers");
        if rays > marched.rays.capacity {
            *marched = MarchedBuffers::new(ctx, rays, grid.samples, frustums);
        }
        marched.rays.upload(ctx, batch, 0..rays, &mut work.scratch);

        // Submission 1: the march and its counters.
        let (samples, kept) = if rays == 0 {
            (0, 0)
        } else {
            marched.out.ray_count = rays;
            let mut encoder = ctx.device.create_command_encoder(&Default::default());
            work.clock.restart(ctx, &mut encoder);
            grid.march.record(
                ctx,
                &mut encoder,
                GpuGrid {
                    geometry: grid.grid.geometry(),
                    bitfield: &grid.bitfield,
                },
                GpuRays {
                    origins: &marched.rays.origins,
                    directions: &marched.rays.directions,
                },
                &MarchParams {
                    config: self.recipe.march,
                    mapping: grid.mapping,
                    jitter_seed: Some(mix_seed(self.seed, step)),
                    sample_budget: grid.samples,
                },
                &marched.out,
            );
            work.clock.mark(ctx, &mut encoder, Stage::March);
            encoder.copy_buffer_to_buffer(&marched.out.counters, 0, &grid.counters_staging, 0, 8);
            ctx.queue.submit([encoder.finish()]);
            let counters: Vec<u32> = read_mapped(ctx, &grid.counters_staging, 2);
            (counters[0] as usize, counters[1] as usize)
        };
        let previous = work.readback.take_previous(ctx);

        // Submission 2: field, compositing, loss, backward, Adam.
        let s = &self.stages;
        let mut encoder = ctx.device.create_command_encoder(&Default::default());
        work.clock.restart(ctx, &mut encoder);
        encoder.clear_buffer(&self.gradients, 0, None);
        if frustums {
            // Each marched sample stands for the frustum of its step,
            // centred on it; its Gaussian's mean replaces the point.
            s.frustums.record_marched(
                ctx,
                &mut encoder,
                FrustumRays {
                    origins: &marched.rays.origins,
                    directions: &marched.rays.directions,
                    radii: &marched.rays.radii,
                },
                MarchedIntervals {
                    ray_offsets: &marched.out.ray_offsets,
                    t: &marched.out.t,
                    dt: &marched.out.dt,
                    samples,
                },
                kept,
                &marched.world,
                &marched.variances,
            );
        } else if !unit_cube {
            s.sampling.record_to_world(
                ctx,
                &mut encoder,
                &grid.mapping,
                &marched.out.positions,
                samples,
                &marched.world,
            );
        }
        work.clock.mark(ctx, &mut encoder, Stage::March);
        let positions = if unit_cube {
            &marched.out.positions
        } else {
            &marched.world
        };
        let field = &mut work.fields[level.field];
        field.record_forward(
            ctx,
            &mut encoder,
            &self.params,
            positions,
            frustums.then_some(&marched.variances),
            &marched.out.directions,
            samples,
            &marched.sigma,
            &marched.rgb,
        );
        work.clock.mark(ctx, &mut encoder, Stage::NetworksForward);
        // As the cpu model: the recipe's λ spread over the batch's rays,
        // distances in the unit cube's units.
        let distortion = (self.recipe.distortion > 0.0 && kept > 0).then(|| Distortion {
            weight_per_ray: self.recipe.distortion / kept as f32,
            distance_scale: grid.mapping.diagonal_scale(),
        });
        CompositeAndLoss {
            composite: &s.composite,
            loss: &s.loss,
        }
        .record(
            ctx,
            &mut encoder,
            &marched.rays,
            SampleBuffers {
                sigma: &marched.sigma,
                rgb: &marched.rgb,
                dt: &marched.out.dt,
                t: &marched.out.t,
                ray_offsets: &marched.out.ray_offsets,
            },
            kept,
            self.recipe.march.min_transmittance,
            self.loss,
            level.loss_weight,
            distortion,
            SampleGradientBuffers {
                sigma: &marched.d_sigma,
                rgb: &marched.d_rgb,
            },
        );
        work.clock.mark(ctx, &mut encoder, Stage::Composite);
        field.record_backward(
            ctx,
            &mut encoder,
            &self.params,
            &marched.d_sigma,
            &marched.d_rgb,
            samples,
            &self.gradients,
        );
        work.clock.mark(ctx, &mut encoder, Stage::NetworksBackward);
        if optimise {
            self.adam.record_step_layout(
                ctx,
                &mut encoder,
                &self.recipe.optimiser,
                &self.layout,
                &self.params,
                &self.gradients,
            );
        }
        work.clock.mark(ctx, &mut encoder, Stage::Optimiser);
        work.readback
            .record(&mut encoder, &work.clock, &marched.rays.loss_total);
        ctx.queue.submit([encoder.finish()]);
        let StepResults { loss, times } = work.readback.finish(ctx, &work.clock, previous);
        drop(guard);
        self.batch_sizer.record(kept, samples);
        StepStats {
            loss,
            level_losses: [loss, 0.0],
            rays: if rays == 0 { 0 } else { kept },
            samples,
            samples_composited: None,
            times,
            network_flops: 0.0,
        }
    }

    /// The occupancy update of `step`: cells and points chosen on the host
    /// (the cpu engine's code and random choices), densities evaluated by
    /// the field on the device in chunks of the batch's samples (one
    /// submission) and read back, the EMA and bitfield on the host, the
    /// bitfield uploaded. Read a step late, the densities come back with
    /// the step's march read-back and the new bitfield is used from the
    /// next step on.
    pub(super) fn update_grid(&mut self, step: u32) {
        let ctx = &self.context;
        let Some(grid) = self.grid.as_mut() else {
            return;
        };
        let report = grid.grid.plan_update(step, self.seed);
        let n = report.samples;
        let mut guard = self.work.lock().unwrap_or_else(|e| e.into_inner());
        let work = &mut *guard;
        let field = &mut work.fields[self.recipe.levels[0].field];
        let positions = if field.coordinates() == Coordinates::UnitCube {
            storage_buffer(ctx, "grid update positions", grid.grid.update_positions())
        } else {
            let mut world = Vec::new();
            to_world(&grid.mapping, grid.grid.update_positions(), &mut world);
            storage_buffer(ctx, "grid update positions", &world)
        };
        let all_sigma = zeroed_storage_buffer::<f32>(ctx, "grid update sigma", n);
        let marched = work.marched.as_ref().expect("a marched recipe has buffers");
        let mut encoder = ctx.device.create_command_encoder(&Default::default());
        let late = work.readback.is_late();
        if late {
            work.clock.restart(ctx, &mut encoder);
        }
        for start in (0..n).step_by(grid.samples) {
            let count = grid.samples.min(n - start);
            encoder.copy_buffer_to_buffer(
                &positions,
                12 * start as u64,
                &marched.world,
                0,
                12 * count as u64,
            );
            field.record_density(
                ctx,
                &mut encoder,
                &self.params,
                &marched.world,
                grid.cell_variances.as_ref(),
                count,
                &marched.sigma,
            );
            encoder.copy_buffer_to_buffer(
                &marched.sigma,
                0,
                &all_sigma,
                4 * start as u64,
                4 * count as u64,
            );
        }
        if late {
            work.clock.mark(ctx, &mut encoder, Stage::GridUpdate);
            let staging = staging_buffer(ctx, "grid update read-back", 4 * n as u64);
            encoder.copy_buffer_to_buffer(&all_sigma, 0, &staging, 0, 4 * n as u64);
            ctx.queue.submit([encoder.finish()]);
            self.pending_grid = Some(MapRequest::new(&staging, 4 * n as u64));
            return;
        }
        ctx.queue.submit([encoder.finish()]);
        let sigma: Vec<f32> = read_buffer(ctx, &all_sigma, n);
        grid.apply(ctx, &sigma);
    }

    /// Applies densities read a step late by [`Self::update_grid`], once
    /// the device is done with them.
    pub(super) fn apply_pending_grid_update(&mut self) {
        if let (Some(request), Some(grid)) = (self.pending_grid.take(), self.grid.as_mut()) {
            let sigma: Vec<f32> = request.take(&self.context);
            grid.apply(&self.context, &sigma);
        }
    }

    /// σ and colour of `samples` marched through the grid for rendering
    /// rays `origins`, `directions` (with cone `radii`, for frustums), on
    /// the device in chunks of the batch's samples. The field's inputs are
    /// made on the host (world positions, or the Gaussians of the steps'
    /// frustums, with the cpu engine's code), as rendering on the cpu does.
    pub(super) fn radiance(
        &self,
        samples: &GridSamples,
        origins: &[Vec3],
        directions: &[Vec3],
        radii: &[f32],
        sigma: &mut [f32],
        rgb: &mut [f32],
    ) {
        let ctx = &self.context;
        let grid = self.grid.as_ref().expect("a marched recipe has a grid");
        let frustums = self.recipe.samples == SampleShape::ConicalFrustums;
        let mut guard = self.work();
        let work = &mut *guard;
        let field = &mut work.fields[self.recipe.levels[0].field];
        let unit_cube = field.coordinates() == Coordinates::UnitCube;
        let (mut world, mut variances) = (Vec::new(), Vec::new());
        if unit_cube {
            world.extend_from_slice(samples.positions);
        } else {
            grid_sample_inputs(
                samples,
                frustums,
                &grid.mapping,
                origins,
                directions,
                radii,
                &mut world,
                &mut variances,
            );
        }
        let marched = work.marched.as_ref().expect("a marched recipe has buffers");
        let chunk = grid.samples;
        for (i, ((sigma, rgb), d)) in sigma
            .chunks_mut(chunk)
            .zip(rgb.chunks_mut(3 * chunk))
            .zip(samples.directions.chunks(3 * chunk))
            .enumerate()
        {
            let count = sigma.len();
            let rows = 3 * chunk * i..3 * (chunk * i + count);
            let queue = &ctx.queue;
            queue.write_buffer(
                &marched.world,
                0,
                bytemuck::cast_slice(&world[rows.clone()]),
            );
            queue.write_buffer(&marched.out.directions, 0, bytemuck::cast_slice(d));
            if frustums {
                queue.write_buffer(
                    &marched.variances,
                    0,
                    bytemuck::cast_slice(&variances[rows]),
                );
            }
            let mut encoder = ctx.device.create_command_encoder(&Default::default());
            field.record_forward(
                ctx,
                &mut encoder,
                &self.params,
                &marched.world,
                frustums.then_some(&marched.variances),
                &marched.out.directions,
                count,
                &marched.sigma,
                &marched.rgb,
            );
            ctx.queue.submit([encoder.finish()]);
            sigma.copy_from_slice(&read_buffer::<f32>(ctx, &marched.sigma, count));
            rgb.copy_from_slice(&read_buffer::<f32>(ctx, &marched.rgb, 3 * count));
        }
    }
}
