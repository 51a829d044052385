//! Recording a chunk's levels on the device (sampling, the fields'
//! forward and backward passes, compositing and the loss) and a training
//! step with the paper samplers' fixed samples per ray.

use super::*;
use crate::engine::gpu::fields::{FieldInputs, FieldOutputs};
use crate::engine::gpu::sampling::{RayBounds, SamplePoints};
use crate::engine::gpu::step::LevelLoss;
use crate::model::LevelLossSum;

impl GpuModel {
    /// Records every level of a chunk of `count` rays (already on the
    /// device): sampling, the field's forward pass, and compositing; for
    /// training also the loss and the backward pass. `jitter(level)` seeds
    /// a level's random sample positions (`None`: the deterministic
    /// positions). Marks stage boundaries on `clock` when given.
    pub(super) fn record_levels(
        &self,
        work: &mut Work,
        rec: &mut Recorder,
        count: usize,
        jitter: impl Fn(usize) -> Option<u32>,
        purpose: &Purpose,
        timed: bool,
    ) {
        let s = &self.stages;
        let Work {
            fields,
            rays,
            near,
            far,
            levels,
            edges,
            bin_weights,
            fine_t,
            clock,
            ..
        } = work;
        let mut mark = |rec: &mut Recorder, stage| {
            if timed {
                clock.mark(rec, stage);
            }
        };
        let frustums = self.core.recipe.samples == SampleShape::ConicalFrustums;
        for (li, level) in self.core.recipe.levels.iter().enumerate() {
            let (before, rest) = levels.split_at_mut(li);
            let lb = &mut rest[0];
            let per_ray = lb.per_ray;
            let rows = count * per_ray;
            self.samplers[li].record(
                rec,
                &s.sampling,
                LevelSampling {
                    rays: count,
                    bounds: RayBounds { near, far },
                    previous: before.last(),
                    edges,
                    bin_weights,
                    fine_t,
                    out: lb,
                },
                jitter(li),
            );
            if frustums {
                s.frustums.record_edges(
                    rec,
                    FrustumRays {
                        origins: &rays.origins,
                        directions: &rays.directions,
                        radii: &rays.radii,
                    },
                    &lb.edges,
                    count,
                    per_ray,
                    FrustumSamples {
                        t: &lb.t,
                        dt: &lb.dt,
                        means: &lb.positions,
                        variances: &lb.variances,
                        directions: &lb.directions,
                    },
                );
            } else {
                s.sampling
                    .record_intervals_to_far(rec, &lb.t, far, count, per_ray, &lb.dt);
                s.sampling.record_points(
                    rec,
                    GpuRays {
                        origins: &rays.origins,
                        directions: &rays.directions,
                    },
                    &lb.t,
                    count,
                    per_ray,
                    SamplePoints {
                        positions: &lb.positions,
                        directions: &lb.directions,
                    },
                );
            }
            mark(rec, Stage::March);

            let field = &mut fields[level.field];
            field.record_forward(
                rec,
                &self.params,
                FieldInputs {
                    positions: &lb.positions,
                    variances: frustums.then_some(&lb.variances),
                    directions: &lb.directions,
                },
                rows,
                FieldOutputs {
                    sigma: &lb.sigma,
                    rgb: &lb.rgb,
                },
            );
            mark(rec, Stage::NetworksForward);

            let samples = SampleBuffers {
                sigma: &lb.sigma,
                rgb: &lb.rgb,
                dt: &lb.dt,
                t: &lb.t,
                ray_offsets: &lb.ray_offsets,
            };
            // The paper's levels composite every sample (no transmittance
            // cut), as the cpu's fixed-count levels.
            let min_transmittance = 0.0;
            if li + 1 < self.core.recipe.levels.len() {
                s.composite.record_weights(
                    rec,
                    &rays.batch(samples, count),
                    min_transmittance,
                    &lb.weights,
                );
            }
            match purpose {
                Purpose::Training {
                    share,
                    losses,
                    first_slot,
                } => {
                    CompositeAndLoss {
                        composite: &s.composite,
                        loss: &s.loss,
                    }
                    .record(
                        rec,
                        rays,
                        samples,
                        count,
                        LevelLoss {
                            min_transmittance,
                            loss: self.loss,
                            gradient_weight: level.loss_weight * share,
                            distortion: None,
                        },
                        SampleGradientBuffers {
                            sigma: &lb.d_sigma,
                            rgb: &lb.d_rgb,
                        },
                    );
                    rec.encoder.copy_buffer_to_buffer(
                        &rays.loss_total,
                        0,
                        losses,
                        4 * (first_slot + li) as u64,
                        4,
                    );
                    mark(rec, Stage::Composite);
                    field.record_backward(
                        rec,
                        &self.params,
                        &lb.d_sigma,
                        &lb.d_rgb,
                        rows,
                        &self.gradients,
                    );
                    mark(rec, Stage::NetworksBackward);
                }
                Purpose::Inference => {
                    s.composite.record_forward(
                        rec,
                        &rays.batch(samples, count),
                        min_transmittance,
                        &CompositeOutputBuffers {
                            rgb: &rays.rgb,
                            opacity: &rays.opacity,
                            depth: &rays.depth,
                            samples_used: &rays.samples_used,
                        },
                    );
                }
            }
        }
    }

    /// A step of fixed-count levels, in chunks of rays.
    pub(super) fn run_fixed(&mut self, batch: &RayBatch, step: u32, optimise: bool) -> StepStats {
        let ctx = &self.context;
        let rays = batch.len();
        let levels = self.core.recipe.levels.len();
        let per_chunk = self.rays_per_chunk;
        let chunks = rays.div_ceil(per_chunk);
        let losses = zeroed_storage_buffer::<f32>(ctx, "chunk losses", chunks * levels);
        let step_seed = mix_seed(self.seed, step);
        let flat = |v: &[Vec3]| v.iter().flat_map(|x| x.to_array()).collect::<Vec<f32>>();
        let (origins, directions) = (flat(&batch.origins), flat(&batch.directions));
        // The lock of the field alone (not `self.work()`), so Adam's state
        // stays writable below.
        let mut guard = self.work.lock().unwrap_or_else(|e| e.into_inner());
        let work = &mut *guard;
        work.clock.reset();
        let mut samples = 0usize;
        let mut shares = Vec::with_capacity(chunks);
        let mut rec = Recorder::new(ctx);
        rec.encoder.clear_buffer(&self.gradients, 0, None);
        for chunk in 0..chunks {
            let start = chunk * per_chunk;
            let end = (start + per_chunk).min(rays);
            let count = end - start;
            let share = count as f32 / rays as f32;
            shares.push(share);
            let mut scratch = std::mem::take(&mut work.scratch);
            work.rays.upload(ctx, batch, start..end, &mut scratch);
            work.scratch = scratch;
            self.upload_bounds(
                work,
                &origins[3 * start..3 * end],
                &directions[3 * start..3 * end],
                None,
            );
            work.clock.restart(&mut rec);
            self.record_levels(
                work,
                &mut rec,
                count,
                |level| Some(chunk_jitter_seed(step_seed, chunk, level)),
                &Purpose::Training {
                    share,
                    losses: &losses,
                    first_slot: chunk * levels,
                },
                true,
            );
            samples += work.levels.iter().map(|l| count * l.per_ray).sum::<usize>();
            // One submission per chunk: the next chunk's rays are written
            // into the same buffers before the following submission.
            rec.submit_so_far();
        }
        work.clock.restart(&mut rec);
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
        work.clock.resolve(&mut rec);
        rec.submit();
        let values: Vec<f32> = read_buffer(ctx, &losses, chunks * levels);
        let times = work.clock.read(ctx);
        drop(guard);

        // The cpu's sums: the loss weighted per level and chunk, the level
        // losses per chunk's share.
        let mut sum = LevelLossSum::default();
        for (chunk, &share) in shares.iter().enumerate() {
            for (li, level) in self.core.recipe.levels.iter().enumerate() {
                sum.add(
                    li,
                    level.loss_weight,
                    share,
                    values[chunk * levels + li] as f64,
                );
            }
        }
        sum.into_stats(rays, samples, times, 0.0)
    }
}
