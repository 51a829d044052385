//! Recording a chunk's levels on the device (sampling, the fields'
//! forward and backward passes, compositing and the loss) and a training
//! step with the paper samplers' fixed samples per ray.

use super::*;
use crate::engine::gpu::fields::{FieldInputs, FieldOutputs, GpuAppearance};
use crate::engine::gpu::proposal::{CompositedSamples, ContractedInputs, IntervalBuffers};
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
            twins,
            rays,
            near,
            far,
            levels,
            edges,
            bin_weights,
            fine_t,
            d_weights,
            weight_scratch,
            weight_ray_loss,
            clock,
            ..
        } = work;
        let mut mark = |rec: &mut Recorder, stage| {
            if timed {
                clock.mark(rec, stage);
            }
        };
        let recipe = &self.core.recipe;
        let frustums = recipe.samples == SampleShape::ConicalFrustums;
        let last = recipe.levels.len() - 1;
        let proposals = recipe.levels.iter().any(|l| !l.colour);
        let training = matches!(purpose, Purpose::Training { .. });
        for (li, level) in recipe.levels.iter().enumerate() {
            let (before, rest) = levels.split_at_mut(li);
            let lb = &mut rest[0];
            let per_ray = lb.per_ray;
            let rows = count * per_ray;
            let sampler = &self.samplers[li];
            sampler.record(
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
                    proposal: &s.proposal,
                },
                jitter(li),
            );
            let field: &mut dyn GpuField = match twins[li].as_mut() {
                Some(twin) => twin.as_mut(),
                None => fields[level.field].as_mut(),
            };
            if frustums {
                let on = FrustumRays {
                    origins: &rays.origins,
                    directions: &rays.directions,
                    radii: &rays.radii,
                };
                let out = FrustumSamples {
                    t: &lb.t,
                    dt: &lb.dt,
                    means: &lb.positions,
                    variances: &lb.variances,
                    directions: &lb.directions,
                };
                match &recipe.contraction {
                    // The Gaussians in contracted space: the field's inputs
                    // already.
                    Some(contraction) => s.proposal.record_contracted_frustums(
                        rec,
                        contraction,
                        on,
                        &lb.edges,
                        count,
                        per_ray,
                        out,
                    ),
                    None => s
                        .frustums
                        .record_edges(rec, on, &lb.edges, count, per_ray, out),
                }
            } else {
                if sampler.draws_intervals() {
                    // Each interval's sample at its midpoint, composited
                    // over its length (as the cpu).
                    s.proposal
                        .record_midpoints(rec, &lb.edges, count, per_ray, &lb.t, &lb.dt);
                } else {
                    s.sampling
                        .record_intervals_to_far(rec, &lb.t, far, count, per_ray, &lb.dt);
                }
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
                if let Some(contraction) = &recipe.contraction {
                    let inputs = match field.coordinates() {
                        Coordinates::UnitCube => ContractedInputs::UnitCube,
                        Coordinates::World => ContractedInputs::Contracted,
                    };
                    s.proposal
                        .record_contract(rec, contraction, inputs, &lb.positions, rows);
                }
            }
            mark(rec, Stage::March);

            field.record_forward(
                rec,
                &self.params,
                FieldInputs {
                    positions: &lb.positions,
                    variances: frustums.then_some(&lb.variances),
                    directions: &lb.directions,
                },
                // Training: each sample its ray's image (ray r's samples
                // are rows r · per_ray ..).
                if training {
                    GpuAppearance::PerRay {
                        images: &rays.images,
                        ray_offsets: &lb.ray_offsets,
                        rays: count,
                    }
                } else {
                    self.rendered_appearance()
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
            // cut), as the cpu's fixed-count levels. The final level's
            // weights are needed too where losses on weights train.
            let min_transmittance = 0.0;
            if li < last || (training && (proposals || recipe.contraction.is_some())) {
                s.composite.record_weights(
                    rec,
                    &rays.batch(samples, count),
                    min_transmittance,
                    &lb.weights,
                );
            }
            match purpose {
                // A proposal level: its weights place the next level's
                // samples; its backward pass waits for the final level's
                // weights.
                Purpose::Training { .. } if !level.colour => mark(rec, Stage::Composite),
                Purpose::Training {
                    share,
                    losses,
                    first_slot,
                    batch_rays,
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
                    // The distortion loss on the level's intervals in s, per
                    // ray of the batch, as the cpu's `distortion_in_spacing`.
                    if let Some(contraction) = &recipe.contraction
                        && recipe.distortion > 0.0
                    {
                        let intervals = IntervalBuffers {
                            edges: &lb.edges,
                            weights: &lb.weights,
                            per_ray,
                        };
                        s.proposal.record_distortion(
                            rec,
                            contraction,
                            intervals,
                            count,
                            recipe.distortion / *batch_rays as f32,
                            d_weights,
                        );
                        s.proposal.record_weights_to_densities(
                            rec,
                            CompositedSamples {
                                sigma: &lb.sigma,
                                dt: &lb.dt,
                                weights: &lb.weights,
                                per_ray,
                            },
                            count,
                            d_weights,
                            weight_scratch,
                            &lb.d_sigma,
                        );
                    }
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
                Purpose::Inference if !level.colour => {}
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

        // The proposal levels' backward passes, as the cpu's
        // `train_proposals`: each one's interlevel loss against the final
        // level's weights (held still), through its weights to its
        // densities. The loss of each (summed over the chunk's rays) goes
        // to the level's slot.
        let Purpose::Training {
            losses,
            first_slot,
            batch_rays,
            ..
        } = purpose
        else {
            return;
        };
        let Some(contraction) = &recipe.contraction else {
            return;
        };
        if !proposals {
            return;
        }
        let (before, final_level) = levels.split_at_mut(last);
        let final_level = &final_level[0];
        for (index, lb) in before.iter_mut().enumerate() {
            let level = recipe.levels[index];
            if level.colour {
                continue;
            }
            s.proposal.record_interlevel(
                rec,
                contraction,
                IntervalBuffers {
                    edges: &final_level.edges,
                    weights: &final_level.weights,
                    per_ray: final_level.per_ray,
                },
                IntervalBuffers {
                    edges: &lb.edges,
                    weights: &lb.weights,
                    per_ray: lb.per_ray,
                },
                count,
                recipe.interlevel / *batch_rays as f32,
                weight_scratch,
                d_weights,
                weight_ray_loss,
            );
            s.loss
                .record_sum(rec, weight_ray_loss, count, &rays.loss_total);
            rec.encoder.copy_buffer_to_buffer(
                &rays.loss_total,
                0,
                losses,
                4 * (first_slot + index) as u64,
                4,
            );
            rec.encoder.clear_buffer(&lb.d_sigma, 0, None);
            s.proposal.record_weights_to_densities(
                rec,
                CompositedSamples {
                    sigma: &lb.sigma,
                    dt: &lb.dt,
                    weights: &lb.weights,
                    per_ray: lb.per_ray,
                },
                count,
                d_weights,
                weight_scratch,
                &lb.d_sigma,
            );
            mark(rec, Stage::Composite);
            let field: &dyn GpuField = match twins[index].as_ref() {
                Some(twin) => twin.as_ref(),
                None => fields[level.field].as_ref(),
            };
            field.record_backward(
                rec,
                &self.params,
                &lb.d_sigma,
                &lb.d_rgb,
                count * lb.per_ray,
                &self.gradients,
            );
            mark(rec, Stage::NetworksBackward);
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
        let mut proposal_samples = 0usize;
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
                    batch_rays: rays,
                },
                true,
            );
            for (level, buffers) in self.core.recipe.levels.iter().zip(&work.levels) {
                if level.colour {
                    samples += count * buffers.per_ray;
                } else {
                    proposal_samples += count * buffers.per_ray;
                }
            }
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
        // A proposal level's slot holds its interlevel loss summed over the
        // chunk's rays: the batch's is their sum times λ / rays.
        let mut sum = LevelLossSum::default();
        let mut proposal_loss = 0f64;
        let interlevel = self.core.recipe.interlevel as f64 / rays as f64;
        for (chunk, &share) in shares.iter().enumerate() {
            for (li, level) in self.core.recipe.levels.iter().enumerate() {
                if !level.colour {
                    proposal_loss += values[chunk * levels + li] as f64 * interlevel;
                    continue;
                }
                sum.add(
                    li,
                    level.loss_weight,
                    share,
                    values[chunk * levels + li] as f64,
                );
            }
        }
        let mut stats = sum.into_stats(rays, samples, times, 0.0);
        stats.proposal_samples = proposal_samples;
        stats.proposal_loss = proposal_loss as f32;
        stats
    }
}
