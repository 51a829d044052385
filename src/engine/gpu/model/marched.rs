//! A training step through the occupancy grid (the host marches, the
//! device computes the fields), the grid's updates, and σ and colour of
//! marched samples for rendering.

use super::*;
use crate::engine::gpu::fields::{FieldInputs, FieldOutputs, GpuAppearance};
use crate::engine::gpu::frustum::Gaussians;
use crate::engine::gpu::step::LevelLoss;
use crate::engine::shared::composite::Distortion;

impl GpuModel {
    /// A step through the occupancy grid, in two submissions: the march,
    /// and for a σ-first step the σ pass over every marched sample, each
    /// ray's cut and the compaction of the samples before it, whose
    /// counters (samples, rays kept, samples used) are read back to size
    /// the rest; then the field's forward pass (on the samples before the
    /// cut, or on every marched sample going forward first), compositing
    /// with the march's transmittance cut, the loss, the backward passes
    /// and Adam. σ first or forward first is chosen as on the cpu engine
    /// ([`sigma_first`]), from the share of samples the last measured step
    /// used: a σ-first step's own share, read with its counters; a
    /// forward-first step's, counted on the device after its compositing,
    /// is read with the next step's counters, so it chooses the step after
    /// that (one step later than on the cpu engine, which adds no wait).
    pub(super) fn run_marched(&mut self, batch: &RayBatch, step: u32, optimise: bool) -> StepStats {
        let ctx = &self.context;
        let grid = self.grid.as_ref().expect("a marched recipe has a grid");
        let level = self.core.recipe.levels[0];
        let rays = batch.len();
        let mut guard = self.work.lock().unwrap_or_else(|e| e.into_inner());
        let work = &mut *guard;
        let frustums = self.core.recipe.samples == SampleShape::ConicalFrustums;
        let field = &mut work.fields[level.field];
        let unit_cube = field.coordinates() == Coordinates::UnitCube;
        let compact = sigma_first(
            field.may_find_cut_in_forward(),
            field.macs_per_sample(),
            field.density_macs_per_sample(),
            grid.used_fraction,
        );
        let marched = work.marched.as_mut().expect("a marched recipe has buffers");
        // New buffers lose the last forward-first step's count of samples
        // used.
        let reallocated = rays > marched.rays.capacity;
        if reallocated {
            *marched = MarchedBuffers::new(ctx, rays, grid.samples, frustums);
        }
        marched.rays.upload(ctx, batch, 0..rays, &mut work.scratch);
        marched.out.ray_count = rays;
        let marched = &*marched;
        let s = &self.stages;
        // The field's inputs from the march's samples: unit-cube positions
        // as marched, world positions, or each step's frustum.
        let record_inputs = |rec: &mut Recorder, samples: usize, rays: usize| {
            if frustums {
                // Each marched sample stands for the frustum of its step,
                // centred on it; its Gaussian's mean replaces the point.
                s.frustums.record_marched(
                    rec,
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
                    rays,
                    Gaussians {
                        means: &marched.world,
                        variances: &marched.variances,
                    },
                );
            } else if !unit_cube {
                s.sampling.record_to_world(
                    rec,
                    &grid.mapping,
                    &marched.out.positions,
                    samples,
                    &marched.world,
                );
            }
        };
        let positions = if unit_cube {
            &marched.out.positions
        } else {
            &marched.world
        };
        let variances = frustums.then_some(&marched.variances);

        // Submission 1: the march (and σ first: the σ pass, the cut and the
        // compaction) and its counters.
        let (samples, kept, used, counters) = if rays == 0 {
            (0, 0, 0, None)
        } else {
            let mut rec = Recorder::new(ctx);
            work.clock.restart(&mut rec);
            // The samples the last forward-first step used, counted after
            // its compositing (before this step's compaction reuses the
            // counter).
            rec.encoder.copy_buffer_to_buffer(
                &marched.compacted.counters,
                0,
                &grid.counters_staging,
                12,
                4,
            );
            grid.march.record(
                &mut rec,
                GpuGrid {
                    geometry: grid.grid.geometry(),
                    bitfield: &grid.bitfield,
                },
                GpuRays {
                    origins: &marched.rays.origins,
                    directions: &marched.rays.directions,
                },
                &MarchParams {
                    config: self.core.recipe.march,
                    mapping: grid.mapping,
                    jitter_seed: Some(mix_seed(self.seed, step)),
                    sample_budget: grid.samples,
                },
                &marched.out,
            );
            if compact {
                // How many samples the march kept is not known here: the
                // inputs and σ are made for the march's whole capacity
                // (rays past the budget have empty ranges, slots past the
                // samples are never read), which the batch sizer keeps
                // close to the samples marched.
                record_inputs(&mut rec, grid.samples, rays);
                work.clock.mark(&mut rec, Stage::March);
                field.record_density(
                    &mut rec,
                    &self.params,
                    positions,
                    variances,
                    grid.samples,
                    &marched.sigma,
                );
                // Each ray's samples before its cut, by compositing's own
                // arithmetic over the σ pass (its colours are not read
                // back; compositing runs again on the kept samples).
                s.composite.record_forward(
                    &mut rec,
                    &marched.rays.batch(
                        SampleBuffers {
                            sigma: &marched.sigma,
                            rgb: &marched.rgb,
                            dt: &marched.out.dt,
                            t: &marched.out.t,
                            ray_offsets: &marched.out.ray_offsets,
                        },
                        rays,
                    ),
                    self.core.recipe.march.min_transmittance,
                    &CompositeOutputBuffers {
                        rgb: &marched.rays.rgb,
                        opacity: &marched.rays.opacity,
                        depth: &marched.rays.depth,
                        samples_used: &marched.rays.samples_used,
                    },
                );
                grid.compaction.record(
                    &mut rec,
                    &grid.march,
                    rays,
                    MarchedInputs {
                        ray_offsets: &marched.out.ray_offsets,
                        samples_used: &marched.rays.samples_used,
                        positions,
                        directions: &marched.out.directions,
                        variances,
                        dt: &marched.out.dt,
                        t: &marched.out.t,
                        sigma: &marched.sigma,
                    },
                    &marched.compacted,
                );
                work.clock.mark(&mut rec, Stage::NetworksForward);
            } else {
                work.clock.mark(&mut rec, Stage::March);
            }
            rec.encoder.copy_buffer_to_buffer(
                &marched.out.counters,
                0,
                &grid.counters_staging,
                0,
                8,
            );
            rec.encoder.copy_buffer_to_buffer(
                &marched.compacted.counters,
                0,
                &grid.counters_staging,
                8,
                4,
            );
            rec.submit();
            let counters: Vec<u32> = read_mapped(ctx, &grid.counters_staging, 4);
            let (samples, kept) = (counters[0] as usize, counters[1] as usize);
            let used = if compact {
                counters[2] as usize
            } else {
                samples
            };
            (samples, kept, used, Some(counters))
        };
        let previous = work.readback.take_previous(ctx);

        // Submission 2: field, compositing, loss, backward, Adam.
        let mut rec = Recorder::new(ctx);
        work.clock.restart(&mut rec);
        rec.encoder.clear_buffer(&self.gradients, 0, None);
        // The samples the field, compositing and the backward pass see: the
        // compacted ones (σ from the σ pass, as the cut was found with it),
        // or all marched ones.
        let c = &marched.compacted;
        let (field_positions, field_variances, directions, sample_sigma, dt, t, offsets) =
            if compact {
                (
                    &c.positions,
                    frustums.then_some(&c.variances),
                    &c.directions,
                    &c.sigma,
                    &c.dt,
                    &c.t,
                    &c.ray_offsets,
                )
            } else {
                record_inputs(&mut rec, samples, kept);
                work.clock.mark(&mut rec, Stage::March);
                (
                    positions,
                    variances,
                    &marched.out.directions,
                    &marched.sigma,
                    &marched.out.dt,
                    &marched.out.t,
                    &marched.out.ray_offsets,
                )
            };
        // σ first, the forward pass's own σ goes to the march's σ buffer,
        // unused.
        field.record_forward(
            &mut rec,
            &self.params,
            FieldInputs {
                positions: field_positions,
                variances: field_variances,
                directions,
            },
            // Each sample its ray's image: the kept rays are the batch's
            // first, in order.
            GpuAppearance::PerRay {
                images: &marched.rays.images,
                ray_offsets: offsets,
                rays: kept,
            },
            used,
            FieldOutputs {
                sigma: &marched.sigma,
                rgb: &marched.rgb,
            },
        );
        work.clock.mark(&mut rec, Stage::NetworksForward);
        // As the cpu model: the recipe's λ spread over the batch's rays,
        // distances in the unit cube's units.
        let distortion = (self.core.recipe.distortion > 0.0 && kept > 0).then(|| Distortion {
            weight_per_ray: self.core.recipe.distortion / kept as f32,
            distance_scale: grid.mapping.diagonal_scale(),
        });
        CompositeAndLoss {
            composite: &s.composite,
            loss: &s.loss,
        }
        .record(
            &mut rec,
            &marched.rays,
            SampleBuffers {
                sigma: sample_sigma,
                rgb: &marched.rgb,
                dt,
                t,
                ray_offsets: offsets,
            },
            kept,
            LevelLoss {
                min_transmittance: self.core.recipe.march.min_transmittance,
                loss: self.loss,
                gradient_weight: level.loss_weight,
                distortion,
            },
            SampleGradientBuffers {
                sigma: &marched.d_sigma,
                rgb: &marched.d_rgb,
            },
        );
        if !compact && kept > 0 {
            // The samples this step used, for the next step's choice.
            grid.compaction.record_count(
                &mut rec,
                &grid.march,
                &marched.rays.samples_used,
                kept,
                &marched.compacted,
            );
        }
        work.clock.mark(&mut rec, Stage::Composite);
        field.record_backward(
            &mut rec,
            &self.params,
            &marched.d_sigma,
            &marched.d_rgb,
            used,
            &self.gradients,
        );
        work.clock.mark(&mut rec, Stage::NetworksBackward);
        if optimise {
            self.adam.record_step_layout(
                &mut rec,
                &self.core.recipe.optimiser,
                &self.core.layout,
                &self.params,
                &self.gradients,
            );
        }
        work.clock.mark(&mut rec, Stage::Optimiser);
        work.readback
            .record(&mut rec, &work.clock, &marched.rays.loss_total);
        rec.submit();
        let StepResults { loss, times } = work.readback.finish(ctx, &work.clock, previous);
        drop(guard);
        self.core.batch_sizer.record(kept, samples);
        // The share of samples used, for the next step's choice: this
        // step's, σ first; the last forward-first step's, counted after its
        // compositing and read with this step's counters.
        let grid = self.grid.as_mut().expect("a marched recipe has a grid");
        if let Some(counters) = counters {
            if let Some(previous) = grid.forward_first_samples.take()
                && previous > 0
                && !reallocated
            {
                grid.used_fraction = counters[3] as f64 / previous as f64;
            }
            if compact && samples > 0 {
                grid.used_fraction = used as f64 / samples as f64;
            }
        }
        if !compact && kept > 0 {
            grid.forward_first_samples = Some(samples);
        }
        StepStats {
            loss,
            level_losses: [loss, 0.0],
            rays: if rays == 0 { 0 } else { kept },
            samples,
            samples_composited: compact.then_some(used),
            proposal_samples: 0,
            proposal_loss: 0.0,
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
        let field = &mut work.fields[self.core.recipe.levels[0].field];
        let positions = if field.coordinates() == Coordinates::UnitCube {
            storage_buffer(ctx, "grid update positions", grid.grid.update_positions())
        } else {
            let mut world = Vec::new();
            to_world(&grid.mapping, grid.grid.update_positions(), &mut world);
            storage_buffer(ctx, "grid update positions", &world)
        };
        let all_sigma = zeroed_storage_buffer::<f32>(ctx, "grid update sigma", n);
        let marched = work.marched.as_ref().expect("a marched recipe has buffers");
        let mut rec = Recorder::new(ctx);
        let late = work.readback.is_late();
        if late {
            work.clock.restart(&mut rec);
        }
        for start in (0..n).step_by(grid.samples) {
            let count = grid.samples.min(n - start);
            rec.encoder.copy_buffer_to_buffer(
                &positions,
                12 * start as u64,
                &marched.world,
                0,
                12 * count as u64,
            );
            field.record_density(
                &mut rec,
                &self.params,
                &marched.world,
                grid.cell_variances.as_ref(),
                count,
                &marched.sigma,
            );
            rec.encoder.copy_buffer_to_buffer(
                &marched.sigma,
                0,
                &all_sigma,
                4 * start as u64,
                4 * count as u64,
            );
        }
        if late {
            work.clock.mark(&mut rec, Stage::GridUpdate);
            let staging = staging_buffer(ctx, "grid update read-back", 4 * n as u64);
            rec.encoder
                .copy_buffer_to_buffer(&all_sigma, 0, &staging, 0, 4 * n as u64);
            rec.submit();
            self.pending_grid = Some(MapRequest::new(&staging, 4 * n as u64));
            return;
        }
        rec.submit();
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
        let frustums = self.core.recipe.samples == SampleShape::ConicalFrustums;
        let mut guard = self.work();
        let work = &mut *guard;
        let field = &mut work.fields[self.core.recipe.levels[0].field];
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
            let mut rec = Recorder::new(ctx);
            field.record_forward(
                &mut rec,
                &self.params,
                FieldInputs {
                    positions: &marched.world,
                    variances: frustums.then_some(&marched.variances),
                    directions: &marched.out.directions,
                },
                self.rendered_appearance(),
                count,
                FieldOutputs {
                    sigma: &marched.sigma,
                    rgb: &marched.rgb,
                },
            );
            rec.submit();
            sigma.copy_from_slice(&read_buffer::<f32>(ctx, &marched.sigma, count));
            rgb.copy_from_slice(&read_buffer::<f32>(ctx, &marched.rgb, 3 * count));
        }
    }
}
