//! The paper samplers' levels (stratified, then importance or resampled
//! from the level before): a training step and a render with a fixed
//! number of samples per ray.

use super::*;
use crate::engine::cpu::weight_losses::{self, Intervals};
use crate::model::LevelLossSum;

impl CpuModel {
    /// A step of fixed-count levels (stratified, then importance or
    /// resampled; or a proposal sampler's levels), in chunks of rays.
    pub(super) fn fixed_step(&mut self, step: u32) -> StepStats {
        let mut times = StageTimes::default();
        let rays = self.buffers.origins.len() / 3;
        // Chunks and levels add to the gradient.
        self.buffers.gradients.fill(0.0);
        let mut losses = LevelLossSum::default();
        let mut samples = 0usize;
        let mut proposal_samples = 0usize;
        let mut proposal_loss = 0f64;
        let mut network_flops = 0f64;
        let (mut near, mut far) = (Vec::new(), Vec::new());
        {
            let b = &self.buffers;
            self.ray_bounds(&b.origins, &b.directions, &mut near, &mut far);
        }
        let step_seed = mix_seed(self.seed, step);
        let per_chunk = self.rays_per_chunk;
        let level_count = self.core.recipe.levels.len();
        for (chunk, start) in (0..rays).step_by(per_chunk).enumerate() {
            let end = (start + per_chunk).min(rays);
            let chunk_rays = end - start;
            // Each chunk and level draws its own jitter.
            let seed_of = |level: usize| chunk_jitter_seed(step_seed, chunk, level);
            let share = chunk_rays as f32 / rays as f32;
            for level_index in 0..level_count {
                let level = self.core.recipe.levels[level_index];
                let clock = Instant::now();
                self.sample_level(
                    (chunk, level_index),
                    start..end,
                    &near[start..end],
                    &far[start..end],
                    Some(seed_of(level_index)),
                );
                times[Stage::March] += clock.elapsed().as_secs_f64();

                let clock = Instant::now();
                let b = &mut self.buffers;
                let lb = &mut b.levels[level_index];
                let n = lb.t.len();
                if level.colour {
                    samples += n;
                } else {
                    proposal_samples += n;
                }
                network_flops += 6.0 * (self.fields[level.field].macs_per_sample() * n) as f64;
                let field_range = self.core.ranges[level.field].clone();
                let field_params = &self.params[field_range.clone()];
                set_len(&mut lb.sigma, n);
                set_len(&mut lb.rgb, 3 * n);
                let variances = (self.core.recipe.samples == SampleShape::ConicalFrustums)
                    .then_some(&lb.variances[..]);
                let field =
                    Self::level_field(&mut self.fields, &mut self.twins, level_index, level.field);
                let ray_images = b.ray_images.get(start..end).unwrap_or_default();
                sample_images(ray_images, &lb.ray_offsets, &mut b.sample_images);
                field.forward(
                    field_params,
                    &lb.positions,
                    variances,
                    &lb.directions,
                    training_appearance(&b.sample_images),
                    &mut lb.sigma,
                    &mut lb.rgb,
                );
                times[Stage::NetworksForward] += clock.elapsed().as_secs_f64();

                let clock = Instant::now();
                if !level.colour {
                    // A proposal level: its weights, for the next level's
                    // samples and the interlevel loss; its backward pass
                    // waits for the final level's weights.
                    composite_level(lb, &b.backgrounds[3 * start..3 * end], 0.0, &mut b.rays);
                    times[Stage::Composite] += clock.elapsed().as_secs_f64();
                    continue;
                }
                let level_loss = composite_and_loss(
                    lb,
                    &b.targets[3 * start..3 * end],
                    &b.backgrounds[3 * start..3 * end],
                    0.0,
                    self.loss,
                    level.loss_weight * share,
                    None,
                    &mut b.rays,
                );
                losses.add(level_index, level.loss_weight, share, level_loss);
                if let Some(contraction) = self.core.recipe.contraction {
                    let weight = self.core.recipe.distortion;
                    if weight > 0.0 {
                        distortion_in_spacing(
                            lb,
                            &contraction,
                            weight / rays as f32,
                            &mut b.proposal,
                        );
                    }
                }
                times[Stage::Composite] += clock.elapsed().as_secs_f64();

                let clock = Instant::now();
                Self::level_field(&mut self.fields, &mut self.twins, level_index, level.field)
                    .backward(
                        field_params,
                        &lb.d_sigma,
                        &lb.d_rgb,
                        &mut b.gradients[field_range],
                        Gradient::Add,
                    );
                times[Stage::NetworksBackward] += clock.elapsed().as_secs_f64();
            }
            proposal_loss += self.train_proposals(chunk_rays, rays, &mut times);
        }
        let mut stats = losses.into_stats(rays, samples, times, network_flops);
        stats.proposal_samples = proposal_samples;
        stats.proposal_loss = proposal_loss as f32;
        stats
    }

    /// The proposal levels' backward passes for the chunk just stepped:
    /// each one's interlevel loss against the final level's weights (held
    /// still), through its weights to its densities. Returns the chunk's
    /// share of the batch's interlevel loss.
    fn train_proposals(&mut self, chunk_rays: usize, rays: usize, times: &mut StageTimes) -> f64 {
        let recipe = &self.core.recipe;
        let Some(contraction) = recipe.contraction else {
            return 0.0;
        };
        let last = recipe.levels.len() - 1;
        if recipe.levels[..last].iter().all(|l| l.colour) {
            return 0.0;
        }
        let clock = Instant::now();
        let b = &mut self.buffers;
        let scale = recipe.interlevel / rays as f32;
        let scratch = &mut b.proposal;
        let (before, final_level) = b.levels.split_at_mut(last);
        let final_level = &final_level[0];
        spacing_edges(&final_level.edges, &contraction, &mut scratch.final_edges);
        let mut loss = 0f64;
        for (index, lb) in before.iter_mut().enumerate() {
            let level = recipe.levels[index];
            if level.colour {
                continue;
            }
            spacing_edges(&lb.edges, &contraction, &mut scratch.edges);
            scratch.d_weights.clear();
            scratch.d_weights.resize(lb.weights.len(), 0.0);
            loss += weight_losses::interlevel(
                Intervals {
                    edges: &scratch.final_edges,
                    weights: &final_level.weights,
                },
                Intervals {
                    edges: &scratch.edges,
                    weights: &lb.weights,
                },
                chunk_rays,
                scale,
                &mut scratch.d_weights,
            ) * (recipe.interlevel as f64 / rays as f64);
            let per_ray = lb.sigma.len() / chunk_rays.max(1);
            set_len(&mut lb.d_sigma, lb.sigma.len());
            lb.d_sigma.fill(0.0);
            weight_losses::weights_to_densities(
                &lb.sigma,
                &lb.dt,
                &lb.weights,
                &scratch.d_weights,
                per_ray,
                &mut lb.d_sigma,
            );
            set_len(&mut lb.d_rgb, lb.rgb.len());
            lb.d_rgb.fill(0.0);
            let range = self.core.ranges[level.field].clone();
            times[Stage::Composite] += clock.elapsed().as_secs_f64();
            let backward = Instant::now();
            Self::level_field(&mut self.fields, &mut self.twins, index, level.field).backward(
                &self.params[range.clone()],
                &lb.d_sigma,
                &lb.d_rgb,
                &mut b.gradients[range],
                Gradient::Add,
            );
            times[Stage::NetworksBackward] += backward.elapsed().as_secs_f64();
        }
        loss
    }

    /// Fills level `level`'s samples for rays `rays` of the step's buffers
    /// (see [`sample_level`]).
    fn sample_level(
        &mut self,
        (chunk, level): (usize, usize),
        rays: Range<usize>,
        near: &[f32],
        far: &[f32],
        jitter: Option<u32>,
    ) {
        let held = self
            .held_samples
            .as_ref()
            .and_then(|held| held.get(&(chunk, level)));
        let inputs = self.input_map(self.fields[self.core.recipe.levels[level].field].as_ref());
        let b = &mut self.buffers;
        while b.levels.len() <= level {
            b.levels.push(LevelBuffers::default());
        }
        let (before, rest) = b.levels.split_at_mut(level);
        let radii = if b.radii.is_empty() {
            &[][..]
        } else {
            &b.radii[rays.clone()]
        };
        sample_level(
            &*self.samplers[level],
            (self.core.recipe.samples, inputs),
            before.last(),
            RaysOfChunk {
                origins: &b.origins[3 * rays.start..3 * rays.end],
                directions: &b.directions[3 * rays.start..3 * rays.end],
                radii,
                near,
                far,
            },
            jitter,
            held.map(|d| &d[..]),
            &mut b.sampling,
            &mut rest[0],
        );
        if let Some(held) = self.held_samples.as_mut() {
            let lb = &self.buffers.levels[level];
            let distances = if self.samplers[level].draws_intervals() {
                &lb.edges
            } else {
                &lb.t
            };
            held.entry((chunk, level))
                .or_insert_with(|| distances.clone());
        }
    }

    /// Renders rays with the paper's levels (no jitter), in chunks.
    pub(super) fn render_fixed(
        &self,
        origins: &[f32],
        directions: &[f32],
        radii: &[f32],
        background: [f32; 3],
        out: &mut [RenderedPixel],
    ) {
        let rays = origins.len() / 3;
        let (mut near, mut far) = (Vec::new(), Vec::new());
        self.ray_bounds(origins, directions, &mut near, &mut far);
        if let Some(crop) = &self.crop {
            crop_ray_bounds(crop, origins, directions, &mut near, &mut far);
        }
        let mut scratch = SamplingScratch::default();
        let mut levels: Vec<LevelBuffers> = (0..self.core.recipe.levels.len())
            .map(|_| LevelBuffers::default())
            .collect();
        let mut pixels = RayScratch::default();
        let frustums = self.core.recipe.samples == SampleShape::ConicalFrustums;
        for start in (0..rays).step_by(RAYS_PER_CHUNK) {
            let end = (start + RAYS_PER_CHUNK).min(rays);
            let count = end - start;
            let backgrounds = background.repeat(count);
            for (index, level) in self.core.recipe.levels.iter().enumerate() {
                let (before, rest) = levels.split_at_mut(index);
                let lb = &mut rest[0];
                let inputs = self.input_map(self.fields[level.field].as_ref());
                sample_level(
                    &*self.samplers[index],
                    (self.core.recipe.samples, inputs),
                    before.last(),
                    RaysOfChunk {
                        origins: &origins[3 * start..3 * end],
                        directions: &directions[3 * start..3 * end],
                        radii: if frustums { &radii[start..end] } else { &[] },
                        near: &near[start..end],
                        far: &far[start..end],
                    },
                    None,
                    None,
                    &mut scratch,
                    lb,
                );
                let n = lb.t.len();
                set_len(&mut lb.sigma, n);
                set_len(&mut lb.rgb, 3 * n);
                self.fields[level.field].radiance(
                    &self.params[self.core.ranges[level.field].clone()],
                    &lb.positions,
                    frustums.then_some(&lb.variances[..]),
                    &lb.directions,
                    self.rendered_appearance(),
                    &mut lb.sigma,
                    &mut lb.rgb,
                );
                composite_level(lb, &backgrounds, 0.0, &mut pixels);
            }
            for (i, pixel) in out[start..end].iter_mut().enumerate() {
                *pixel = RenderedPixel {
                    rgb: [
                        pixels.rgb[3 * i],
                        pixels.rgb[3 * i + 1],
                        pixels.rgb[3 * i + 2],
                    ],
                    opacity: pixels.opacity[i],
                    depth: pixels.depth[i],
                };
            }
        }
    }
}

/// The rays of a chunk, as fixed-count sampling needs them.
pub(super) struct RaysOfChunk<'a> {
    /// R × 3 each.
    pub(super) origins: &'a [f32],
    pub(super) directions: &'a [f32],
    /// R cone radii (frustum recipes only; empty otherwise).
    pub(super) radii: &'a [f32],
    pub(super) near: &'a [f32],
    pub(super) far: &'a [f32],
}

/// Scratch of sampling a level, reused.
#[derive(Default)]
pub(super) struct SamplingScratch {
    pub(super) edges: Vec<f32>,
    pub(super) inner_weights: Vec<f32>,
    pub(super) blurred: Vec<f32>,
    pub(super) fine_t: Vec<f32>,
    /// Frustums: each sample's interval and ray.
    pub(super) starts: Vec<f32>,
    pub(super) ends: Vec<f32>,
    pub(super) rays: Vec<u32>,
}

/// Fills `lb` with a fixed-count level's samples for the rays of `chunk`:
/// distances `t` and intervals `dt` for compositing, the field's inputs
/// (positions, frustum covariances, directions) and the ray offsets.
///
/// Points (NeRF): stratified points, or the previous level's points merged
/// with importance samples of its weights; each interval runs to the next
/// point (the last one to far). Frustums (Mip-NeRF): `count` + 1 interval
/// edges, stratified or resampled from the previous level's edges and
/// blurred weights; each sample is the Gaussian of the frustum between
/// consecutive edges, at the interval's midpoint for compositing.
/// `held`, where given, replaces the drawn distances (points or edges).
#[allow(clippy::too_many_arguments)]
pub(super) fn sample_level(
    sampler: &dyn LevelSampler,
    (shape, inputs): (SampleShape, InputMap),
    previous: Option<&LevelBuffers>,
    chunk: RaysOfChunk,
    jitter: Option<u32>,
    held: Option<&[f32]>,
    scratch: &mut SamplingScratch,
    lb: &mut LevelBuffers,
) {
    let count = chunk.near.len();
    let intervals = sampler.draws_intervals();
    let per_ray = match (intervals, held) {
        (false, Some(t)) => {
            lb.t.clear();
            lb.t.extend_from_slice(t);
            t.len() / count.max(1)
        }
        (true, Some(edges)) => {
            lb.edges.clear();
            lb.edges.extend_from_slice(edges);
            (edges.len() / count.max(1)).saturating_sub(1)
        }
        (_, None) => sampler.draw(previous, &chunk, jitter, scratch, lb),
    };

    lb.ray_offsets.clear();
    lb.ray_offsets
        .extend((0..=count).map(|r| (r * per_ray) as u32));
    match (shape, intervals) {
        (SampleShape::Points, false) => {
            set_len(&mut lb.dt, count * per_ray);
            sampling::intervals_to_far(&lb.t, chunk.far, per_ray, &mut lb.dt);
            points_along_rays(
                chunk.origins,
                chunk.directions,
                &lb.t,
                per_ray,
                &mut lb.positions,
                &mut lb.directions,
            );
        }
        (SampleShape::Points, true) => {
            // Each interval's sample at its midpoint (nerfstudio's frustums'
            // positions), composited over its length.
            let n = count * per_ray;
            set_len(&mut lb.t, n);
            set_len(&mut lb.dt, n);
            for (r, edges) in lb.edges.chunks_exact(per_ray + 1).enumerate() {
                for (i, pair) in edges.windows(2).enumerate() {
                    lb.t[r * per_ray + i] = 0.5 * (pair[0] + pair[1]);
                    lb.dt[r * per_ray + i] = pair[1] - pair[0];
                }
            }
            points_along_rays(
                chunk.origins,
                chunk.directions,
                &lb.t,
                per_ray,
                &mut lb.positions,
                &mut lb.directions,
            );
        }
        (SampleShape::ConicalFrustums, _) => {
            let n = count * per_ray;
            scratch.starts.clear();
            scratch.ends.clear();
            scratch.rays.clear();
            for (r, edges) in lb.edges.chunks_exact(per_ray + 1).enumerate() {
                for pair in edges.windows(2) {
                    scratch.starts.push(pair[0]);
                    scratch.ends.push(pair[1]);
                    scratch.rays.push(r as u32);
                }
            }
            set_len(&mut lb.t, n);
            set_len(&mut lb.dt, n);
            for (i, (&t0, &t1)) in scratch.starts.iter().zip(&scratch.ends).enumerate() {
                lb.t[i] = 0.5 * (t0 + t1);
                lb.dt[i] = t1 - t0;
            }
            set_len(&mut lb.positions, 3 * n);
            set_len(&mut lb.variances, 3 * n);
            match inputs.contraction {
                // The Gaussians in contracted space: the positions are the
                // field's inputs already.
                Some(contraction) => contracted_frustum_gaussians(
                    chunk.origins,
                    chunk.directions,
                    chunk.radii,
                    &scratch.rays,
                    &scratch.starts,
                    &scratch.ends,
                    &contraction,
                    &mut lb.positions,
                    &mut lb.variances,
                ),
                None => frustum_gaussians(
                    chunk.origins,
                    chunk.directions,
                    chunk.radii,
                    &scratch.rays,
                    &scratch.starts,
                    &scratch.ends,
                    &mut lb.positions,
                    &mut lb.variances,
                ),
            }
            set_len(&mut lb.directions, 3 * n);
            for (d, &r) in lb.directions.chunks_exact_mut(3).zip(&scratch.rays) {
                d.copy_from_slice(&chunk.directions[3 * r as usize..][..3]);
            }
            // Frustums are placed in world units (the driver refuses
            // unit-cube fields of frustums), or contracted above.
            return;
        }
    }
    inputs.map_in_place(&mut lb.positions);
}

/// Scratch of the losses on proposal and final weights, reused.
#[derive(Default)]
pub(super) struct ProposalScratch {
    /// Edges in the spacing coordinate s: the final level's, and a
    /// proposal level's.
    final_edges: Vec<f32>,
    edges: Vec<f32>,
    d_weights: Vec<f32>,
}

/// Each edge's spacing coordinate s.
fn spacing_edges(edges: &[f32], contraction: &Contraction, out: &mut Vec<f32>) {
    out.clear();
    out.extend(edges.iter().map(|&t| contraction.spacing_of(t)));
}

/// Adds the distortion loss on the level's intervals in s (Mip-NeRF 360,
/// eq. 15), `scale` × its gradient, to the level's density gradients.
fn distortion_in_spacing(
    lb: &mut LevelBuffers,
    contraction: &Contraction,
    scale: f32,
    scratch: &mut ProposalScratch,
) {
    let rays = lb.ray_offsets.len() - 1;
    spacing_edges(&lb.edges, contraction, &mut scratch.final_edges);
    scratch.d_weights.clear();
    scratch.d_weights.resize(lb.weights.len(), 0.0);
    weight_losses::distortion(
        Intervals {
            edges: &scratch.final_edges,
            weights: &lb.weights,
        },
        rays,
        scale,
        &mut scratch.d_weights,
    );
    let per_ray = lb.sigma.len() / rays.max(1);
    weight_losses::weights_to_densities(
        &lb.sigma,
        &lb.dt,
        &lb.weights,
        &scratch.d_weights,
        per_ray,
        &mut lb.d_sigma,
    );
}

/// Composites a level's samples (σ, rgb, dt, t, ray offsets in `lb`) over
/// the rays' backgrounds, each ray stopping where its transmittance falls
/// below `min_transmittance`: the pixels into `pixels`, the per-sample
/// weights into `lb.weights` (for the next level).
pub(super) fn composite_level(
    lb: &mut LevelBuffers,
    backgrounds: &[f32],
    min_transmittance: f32,
    pixels: &mut RayScratch,
) {
    let rays = lb.ray_offsets.len() - 1;
    let batch = crate::engine::shared::composite::RayBatch {
        density: &lb.sigma,
        rgb: &lb.rgb,
        dt: &lb.dt,
        t: &lb.t,
        ray_offsets: &lb.ray_offsets,
        background: backgrounds,
    };
    set_len(&mut lb.weights, lb.sigma.len());
    composite_batch::sample_weights(&batch, min_transmittance, &mut lb.weights);
    set_len(&mut pixels.rgb, 3 * rays);
    set_len(&mut pixels.opacity, rays);
    set_len(&mut pixels.depth, rays);
    set_len(&mut pixels.samples_used, rays);
    composite_batch::composite_forward(
        &batch,
        min_transmittance,
        CompositeOutputs {
            rgb: &mut pixels.rgb,
            opacity: &mut pixels.opacity,
            depth: &mut pixels.depth,
            samples_used: &mut pixels.samples_used,
        },
    );
}

/// Per-ray values of compositing and the loss, reused between levels and
/// steps.
#[derive(Default)]
pub(super) struct RayScratch {
    pub(super) rgb: Vec<f32>,
    pub(super) opacity: Vec<f32>,
    pub(super) depth: Vec<f32>,
    /// Samples before each ray's cut.
    pub(super) samples_used: Vec<u32>,
    pub(super) d_rgb: Vec<f32>,
}

/// Composites a level's samples (σ, rgb, dt, t, ray offsets in `lb`) over
/// the rays' backgrounds, writes the per-sample weights into `lb.weights`,
/// and the gradients of `scale` × (mean loss against `targets`) with
/// respect to σ and colour into `lb.d_sigma` and `lb.d_rgb`. Returns the
/// mean loss (unscaled).
#[allow(clippy::too_many_arguments)]
pub(super) fn composite_and_loss(
    lb: &mut LevelBuffers,
    targets: &[f32],
    backgrounds: &[f32],
    min_transmittance: f32,
    loss_kind: LossKind,
    scale: f32,
    distortion: Option<Distortion<f32>>,
    scratch: &mut RayScratch,
) -> f64 {
    composite_level(lb, backgrounds, min_transmittance, scratch);
    let rays = lb.ray_offsets.len() - 1;
    let n = lb.sigma.len();
    set_len(&mut scratch.d_rgb, 3 * rays);
    let loss = loss_and_gradient(loss_kind, &scratch.rgb, targets, &mut scratch.d_rgb);
    if scale != 1.0 {
        for g in scratch.d_rgb.iter_mut() {
            *g *= scale;
        }
    }
    set_len(&mut lb.d_sigma, n);
    set_len(&mut lb.d_rgb, 3 * n);
    let batch = crate::engine::shared::composite::RayBatch {
        density: &lb.sigma,
        rgb: &lb.rgb,
        dt: &lb.dt,
        t: &lb.t,
        ray_offsets: &lb.ray_offsets,
        background: backgrounds,
    };
    composite_batch::composite_backward(
        &batch,
        min_transmittance,
        &scratch.d_rgb,
        distortion,
        CompositeGradients {
            density: &mut lb.d_sigma,
            rgb: &mut lb.d_rgb,
            background: None,
        },
    );
    loss
}

/// Importance samples for each ray from the previous level's `m` sorted
/// samples `t` and their weights (NeRF's `sample_pdf` on the midpoints of
/// the coarse samples with the weights of the interior samples: the first
/// and last samples have no bin of their own between midpoints).
#[allow(clippy::too_many_arguments)]
pub(super) fn importance_samples(
    t: &[f32],
    weights: &[f32],
    m: usize,
    count: usize,
    padding: f32,
    jitter: Option<u32>,
    edges: &mut Vec<f32>,
    inner: &mut Vec<f32>,
    out: &mut Vec<f32>,
) {
    assert!(m >= 3, "importance sampling needs three samples per ray");
    let rays = t.len() / m;
    set_len(edges, rays * (m - 1));
    set_len(inner, rays * (m - 2));
    for r in 0..rays {
        let t = &t[r * m..(r + 1) * m];
        for (e, pair) in edges[r * (m - 1)..(r + 1) * (m - 1)]
            .iter_mut()
            .zip(t.windows(2))
        {
            *e = 0.5 * (pair[0] + pair[1]);
        }
        inner[r * (m - 2)..(r + 1) * (m - 2)].copy_from_slice(&weights[r * m + 1..(r + 1) * m - 1]);
    }
    set_len(out, rays * count);
    sampling::sample_pdf(edges, inner, m - 2, padding, count, jitter, out);
}

/// Positions o + t·d (world) and directions of `per_ray` samples per ray.
pub(super) fn points_along_rays(
    origins: &[f32],
    directions: &[f32],
    t: &[f32],
    per_ray: usize,
    positions: &mut Vec<f32>,
    dirs: &mut Vec<f32>,
) {
    let n = t.len();
    set_len(positions, 3 * n);
    set_len(dirs, 3 * n);
    if per_ray == 0 {
        return;
    }
    positions
        .par_chunks_mut(3 * per_ray)
        .zip(dirs.par_chunks_mut(3 * per_ray))
        .zip(t.par_chunks(per_ray))
        .enumerate()
        .for_each(|(r, ((p, d), t))| {
            let o = Vec3::from_slice(&origins[3 * r..]);
            let dir = Vec3::from_slice(&directions[3 * r..]);
            for (k, &t) in t.iter().enumerate() {
                p[3 * k..3 * k + 3].copy_from_slice(&(o + t * dir).to_array());
                d[3 * k..3 * k + 3].copy_from_slice(&dir.to_array());
            }
        });
}
