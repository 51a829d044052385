//! Instant-NGP on the `cpu` engine: the stages chained into a training step
//! and an inference pass.
//!
//! Parameters live in one flat vector, `[hash grid | density MLP | colour
//! MLP]`, so one Adam instance updates them all; L2 regularisation applies
//! to the two MLPs only (the range after the grid).

use std::ops::Range;
use std::time::Instant;

use glam::Vec3;
use rayon::prelude::*;

use super::adam::Adam;
use super::composite_batch::{self, CompositeGradients, CompositeOutputs, Distortion};
use super::dense::{
    MlpLayout, MlpWorkspace, Precision, mlp_backward, mlp_backward_columns, mlp_forward,
    mlp_inference, mlp_inference_leading,
};
use super::fields::{gather_rows, set_len};
use super::hash_grid::{self, HashGridLayout};
use super::loss::loss_and_gradient;
use super::march::{
    BatchSizer, MarchParams, MarchWorkspace, MarchedSamples, march, mix_seed, render_through_grid,
};
use super::occupancy::OccupancyGrid;
use super::sh::sh_encode;
use super::state::{ModelHeader, ModelState};
use crate::field::ngp::{
    HashGridConfig, LossKind, MarchConfig, NetworkConfig, OccupancyConfig, OptimiserConfig,
    SAMPLES_PER_BATCH,
};
use crate::scene::{Scene, UnitCubeMapping};
use crate::train::batch::RayBatch;
use crate::train::checkpoint::Checkpoint;
use crate::train::model::{RadianceModel, RenderedPixel, StageTimes, StepStats};

/// Samples per round of inference (rendering and grid updates).
const INFERENCE_CHUNK: usize = 1 << 16;

/// The parts of the model that do not change during training.
#[derive(Debug, Clone)]
pub struct NgpShape {
    pub grid: HashGridLayout,
    pub density: MlpLayout,
    pub colour: MlpLayout,
    pub network: NetworkConfig,
    pub mapping: UnitCubeMapping,
}

impl NgpShape {
    pub fn for_scene(scene: &Scene) -> Self {
        let network = NetworkConfig::PAPER;
        let grid_config = HashGridConfig::paper(scene.unit_cube.aabb_scale);
        Self {
            grid: HashGridLayout::new(&grid_config),
            density: MlpLayout::ngp_density(&network, &grid_config),
            colour: MlpLayout::ngp_colour(&network),
            network,
            mapping: scene.unit_cube,
        }
    }

    /// The same model with its networks' products at `precision`.
    pub fn with_precision(mut self, precision: Precision) -> Self {
        self.density = self.density.with_precision(precision);
        self.colour = self.colour.with_precision(precision);
        self
    }

    fn grid_range(&self) -> Range<usize> {
        0..self.grid.param_count()
    }

    fn density_range(&self) -> Range<usize> {
        let start = self.grid.param_count();
        start..start + self.density.param_count()
    }

    fn colour_range(&self) -> Range<usize> {
        let start = self.density_range().end;
        start..start + self.colour.param_count()
    }

    pub fn param_count(&self) -> usize {
        self.colour_range().end
    }

    /// Inference of σ at unit-cube positions (n × 3), with the hash
    /// features kept in `encoded` and `scratch` (grown as needed, reused
    /// between calls). Only output 0 (log-density) of the density network
    /// is computed (equal to that output of the full pass up to rounding).
    fn density(
        &self,
        params: &[f32],
        positions: &[f32],
        sigma: &mut [f32],
        encoded: &mut Vec<f32>,
        scratch: &mut Vec<f32>,
    ) {
        let n = sigma.len();
        set_len(encoded, n * self.grid.output_width());
        hash_grid::encode_with_scratch(
            &self.grid,
            &params[self.grid_range()],
            bytemuck::cast_slice(positions),
            encoded,
            scratch,
        );
        mlp_inference_leading(
            &self.density,
            &params[self.density_range()],
            encoded,
            n,
            sigma,
            1,
        );
        for s in sigma.iter_mut() {
            *s = density_activation(*s);
        }
    }

    /// Inference of σ and colour at unit-cube positions and directions.
    fn radiance(
        &self,
        params: &[f32],
        positions: &[f32],
        directions: &[f32],
        sigma: &mut [f32],
        rgb: &mut [f32],
    ) {
        let n = sigma.len();
        let mut encoded = vec![0f32; n * self.grid.output_width()];
        let density_width = self.density.output_width();
        let colour_width = self.colour.input_width();
        let mut colour_input = vec![0f32; n * colour_width];
        hash_grid::encode(
            &self.grid,
            &params[self.grid_range()],
            bytemuck::cast_slice(positions),
            &mut encoded,
        );
        let mut raw = vec![0f32; n * density_width];
        mlp_inference(
            &self.density,
            &params[self.density_range()],
            &encoded,
            n,
            &mut raw,
        );
        for ((s, row), input) in sigma
            .iter_mut()
            .zip(raw.chunks_exact(density_width))
            .zip(colour_input.chunks_exact_mut(colour_width))
        {
            *s = density_activation(row[0]);
            input[..density_width].copy_from_slice(row);
        }
        sh_encode(
            self.network.sh_degree,
            directions,
            n,
            &mut colour_input[density_width..],
            colour_width,
        );
        mlp_inference(
            &self.colour,
            &params[self.colour_range()],
            &colour_input,
            n,
            rgb,
        );
    }
}

/// σ = exp(x), clamped (field/ngp.rs, DENSITY_EXP_CLAMP).
fn density_activation(x: f32) -> f32 {
    x.min(crate::field::ngp::DENSITY_EXP_CLAMP).exp()
}

/// Buffers of one training step, sized for the batch and reused.
#[derive(Default)]
struct StepBuffers {
    origins: Vec<f32>,
    directions: Vec<f32>,
    samples: MarchedSamples,
    march: MarchWorkspace,
    /// Hash features of every marched sample (S × L·F).
    encoded: Vec<f32>,
    encode_scratch: Vec<f32>,
    /// σ of every marched sample (S), to find where each ray's
    /// compositing stops.
    sigma_marched: Vec<f32>,
    /// The samples before each ray's cut, gathered ("compacted"): U of the
    /// S marched samples. Colour and every gradient are computed for
    /// these only.
    used: CompactSamples,
    density_out: Vec<f32>,
    sigma: Vec<f32>,
    colour_input: Vec<f32>,
    rgb: Vec<f32>,
    ray_rgb: Vec<f32>,
    ray_opacity: Vec<f32>,
    ray_depth: Vec<f32>,
    samples_used: Vec<u32>,
    targets: Vec<f32>,
    backgrounds: Vec<f32>,
    d_ray_rgb: Vec<f32>,
    d_sigma: Vec<f32>,
    d_rgb: Vec<f32>,
    d_density_out: Vec<f32>,
    d_encoded: Vec<f32>,
    gradients: Vec<f32>,
}

/// The samples of a batch that compositing uses (those before each ray's
/// transmittance cut), in ray order, gathered from the marched samples.
#[derive(Default)]
struct CompactSamples {
    /// Index of each used sample among the marched ones (U).
    source: Vec<u32>,
    /// R + 1 offsets of the rays into the used samples.
    ray_offsets: Vec<u32>,
    /// U × L·F hash features.
    encoded: Vec<f32>,
    /// U × 3 unit-cube positions.
    positions: Vec<f32>,
    /// U × 3 world directions.
    directions: Vec<f32>,
    dt: Vec<f32>,
    t: Vec<f32>,
}

/// Sets σ to zero at the samples (unit-cube positions, n × 3) outside
/// `crop`: they then add nothing to their rays, and the background shows
/// where the crop box leaves nothing.
pub fn crop_densities(
    crop: &crate::scene::crop::CropBox,
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

/// Rows per rayon task in the element-wise passes of the step.
const ROWS_PER_TASK: usize = 4096;

/// Instant-NGP trained by the `cpu` engine.
pub struct CpuNgp {
    shape: NgpShape,
    params: Vec<f32>,
    adam: Adam,
    grid: OccupancyGrid,
    batch_sizer: BatchSizer,
    optimiser: OptimiserConfig,
    loss: LossKind,
    seed: u64,
    density_workspace: MlpWorkspace,
    colour_workspace: MlpWorkspace,
    buffers: StepBuffers,
    /// Samples per batch (the paper's 2^18 unless a test asks for fewer).
    batch_samples: usize,
    /// What rendering keeps ([`RadianceModel::set_crop`]).
    crop: Option<crate::scene::crop::CropBox>,
}

impl CpuNgp {
    pub fn new(scene: &Scene, seed: u64, loss: LossKind) -> Self {
        Self::with_batch_samples(scene, seed, loss, SAMPLES_PER_BATCH)
    }

    /// A model whose batches hold `batch_samples` samples instead of the
    /// paper's 2^18: the same training, in smaller steps, for tests that
    /// must finish quickly.
    pub fn with_batch_samples(
        scene: &Scene,
        seed: u64,
        loss: LossKind,
        batch_samples: usize,
    ) -> Self {
        Self::with_shape(NgpShape::for_scene(scene), seed, loss, batch_samples)
    }

    /// [`Self::with_batch_samples`] with parts of another size than the
    /// paper's (tests use a small hash table, as they use small NeRF
    /// networks: the same stages on fewer parameters).
    pub fn with_shape(shape: NgpShape, seed: u64, loss: LossKind, batch_samples: usize) -> Self {
        let mut params = hash_grid::init_params(&shape.grid, seed);
        params.extend(shape.density.init_params(seed ^ 0x64656e73));
        params.extend(shape.colour.init_params(seed ^ 0x636f6c6f));
        assert_eq!(params.len(), shape.param_count());
        let adam = Adam::new(params.len());
        let grid = OccupancyGrid::new(
            OccupancyConfig::PAPER,
            OccupancyConfig::cascades(shape.mapping.aabb_scale),
            // The grid stores σ · step with σ per world unit, so the step is
            // converted from unit-cube to world length.
            MarchConfig::PAPER.step / shape.mapping.scale,
        );
        let density_workspace = MlpWorkspace::new(&shape.density, 0);
        let colour_workspace = MlpWorkspace::new(&shape.colour, 0);
        Self {
            shape,
            params,
            adam,
            grid,
            batch_sizer: BatchSizer::new(batch_samples),
            optimiser: OptimiserConfig::PAPER,
            loss,
            seed,
            density_workspace,
            colour_workspace,
            buffers: StepBuffers::default(),
            batch_samples,
            crop: None,
        }
    }

    pub fn occupancy(&self) -> &OccupancyGrid {
        &self.grid
    }

    pub fn params(&self) -> &[f32] {
        &self.params
    }

    /// Marches, evaluates and composites `batch`, and writes the gradient
    /// of the mean loss with respect to every parameter into the step
    /// buffers (see [`Self::gradients`]), without changing any parameter.
    /// `step` seeds the marching jitter. Returns the step's statistics
    /// (optimiser and grid times zero).
    pub fn forward_backward(&mut self, batch: &RayBatch, step: u32) -> StepStats {
        let mut times = StageTimes::default();
        let shape = &self.shape;
        let b = &mut self.buffers;
        let rays = batch.len();

        // March.
        let clock = Instant::now();
        b.origins.clear();
        b.directions.clear();
        for (o, d) in batch.origins.iter().zip(&batch.directions) {
            b.origins.extend_from_slice(&o.to_array());
            b.directions.extend_from_slice(&d.to_array());
        }
        let march_params = MarchParams {
            sample_budget: self.batch_samples,
            config: MarchConfig::paper_or_environment(),
            ..MarchParams::training(shape.mapping, mix_seed(self.seed, step))
        };
        let marched = march(
            &self.grid,
            &b.origins,
            &b.directions,
            &march_params,
            &mut b.march,
            &mut b.samples,
        );
        // Rays past the budget were never walked: only the kept ones say
        // how many samples a ray holds.
        self.batch_sizer.record(marched.rays_kept, marched.samples);
        let kept = marched.rays_kept;
        let s = marched.samples;
        times.march = clock.elapsed().as_secs_f64();

        // Encode every marched sample: its density decides where the ray's
        // compositing stops.
        let clock = Instant::now();
        let grid_width = shape.grid.output_width();
        set_len(&mut b.encoded, s * grid_width);
        hash_grid::encode_with_scratch(
            &shape.grid,
            &self.params[shape.grid_range()],
            bytemuck::cast_slice(&b.samples.positions),
            &mut b.encoded,
            &mut b.encode_scratch,
        );
        times.encode = clock.elapsed().as_secs_f64();

        // σ of every sample (output 0 of the density network only), the
        // cut of each ray, and the samples before it gathered. After the
        // cut a sample's colour is never read and every gradient through it
        // is exactly zero, so the colour network and all backward passes
        // run on the used samples only (instant-ngp's compaction).
        let clock = Instant::now();
        let min_transmittance = MarchConfig::PAPER.min_transmittance;
        set_len(&mut b.sigma_marched, s);
        mlp_inference_leading(
            &shape.density,
            &self.params[shape.density_range()],
            &b.encoded,
            s,
            &mut b.sigma_marched,
            1,
        );
        b.sigma_marched
            .par_chunks_mut(ROWS_PER_TASK)
            .for_each(|chunk| {
                for sigma in chunk {
                    *sigma = density_activation(*sigma);
                }
            });
        set_len(&mut b.samples_used, kept);
        composite_batch::samples_before_cut(
            &b.sigma_marched,
            &b.samples.dt,
            &b.samples.ray_offsets[..kept + 1],
            min_transmittance,
            &mut b.samples_used,
        );
        let used = &mut b.used;
        used.source.clear();
        used.ray_offsets.clear();
        used.ray_offsets.push(0);
        for (r, &count) in b.samples_used.iter().enumerate() {
            let first = b.samples.ray_offsets[r];
            used.source.extend(first..first + count);
            used.ray_offsets.push(used.source.len() as u32);
        }
        let u = used.source.len();
        gather_rows(&b.encoded, grid_width, &used.source, &mut used.encoded);
        gather_rows(&b.samples.positions, 3, &used.source, &mut used.positions);
        gather_rows(&b.samples.directions, 3, &used.source, &mut used.directions);
        gather_rows(&b.samples.dt, 1, &used.source, &mut used.dt);
        gather_rows(&b.samples.t, 1, &used.source, &mut used.t);

        // Networks forward on the used samples.
        let density_width = shape.density.output_width();
        let colour_width = shape.colour.input_width();
        set_len(&mut b.density_out, u * density_width);
        self.density_workspace.reserve(u);
        mlp_forward(
            &shape.density,
            &self.params[shape.density_range()],
            &used.encoded,
            u,
            &mut self.density_workspace,
            &mut b.density_out,
        );
        // σ is the one the cut was found with (the σ-only inference sums in
        // another order than the full pass, so the two can differ in the
        // last bits): compositing the used samples then stops exactly where
        // the cut said.
        gather_rows(&b.sigma_marched, 1, &used.source, &mut b.sigma);
        set_len(&mut b.colour_input, u * colour_width);
        b.colour_input
            .par_chunks_mut(ROWS_PER_TASK * colour_width)
            .zip(b.density_out.par_chunks(ROWS_PER_TASK * density_width))
            .for_each(|(inputs, rows)| {
                for (input, row) in inputs
                    .chunks_exact_mut(colour_width)
                    .zip(rows.chunks_exact(density_width))
                {
                    input[..density_width].copy_from_slice(row);
                }
            });
        sh_encode(
            shape.network.sh_degree,
            &used.directions,
            u,
            // Empty when the batch has no samples (an empty grid).
            b.colour_input.get_mut(density_width..).unwrap_or_default(),
            colour_width,
        );
        set_len(&mut b.rgb, u * 3);
        self.colour_workspace.reserve(u);
        mlp_forward(
            &shape.colour,
            &self.params[shape.colour_range()],
            &b.colour_input,
            u,
            &mut self.colour_workspace,
            &mut b.rgb,
        );
        times.networks_forward = clock.elapsed().as_secs_f64();

        // Composite, loss, composite backward (rays that fitted the budget,
        // samples before the cut: compositing them gives what compositing
        // all marched samples with the cut gives, bit for bit).
        let clock = Instant::now();
        b.backgrounds.clear();
        b.targets.clear();
        for r in 0..kept {
            b.backgrounds.extend_from_slice(&batch.backgrounds[r]);
            b.targets.extend_from_slice(&batch.targets[r]);
        }
        let ray_batch = composite_batch::RayBatch {
            density: &b.sigma,
            rgb: &b.rgb,
            dt: &used.dt,
            t: &used.t,
            ray_offsets: &used.ray_offsets,
            background: &b.backgrounds,
        };
        set_len(&mut b.ray_rgb, kept * 3);
        set_len(&mut b.ray_opacity, kept);
        set_len(&mut b.ray_depth, kept);
        composite_batch::composite_forward(
            &ray_batch,
            min_transmittance,
            CompositeOutputs {
                rgb: &mut b.ray_rgb,
                opacity: &mut b.ray_opacity,
                depth: &mut b.ray_depth,
                samples_used: &mut b.samples_used,
            },
        );
        set_len(&mut b.d_ray_rgb, kept * 3);
        let loss = loss_and_gradient(self.loss, &b.ray_rgb, &b.targets, &mut b.d_ray_rgb);
        set_len(&mut b.d_sigma, u);
        set_len(&mut b.d_rgb, u * 3);
        let distortion_weight = crate::field::ngp::distortion_weight(shape.mapping.aabb_scale);
        let distortion = (distortion_weight > 0.0 && kept > 0).then(|| Distortion {
            weight_per_ray: distortion_weight / kept as f32,
            distance_scale: shape.mapping.diagonal_scale(),
        });
        composite_batch::composite_backward(
            &ray_batch,
            min_transmittance,
            &b.d_ray_rgb,
            distortion,
            CompositeGradients {
                density: &mut b.d_sigma,
                rgb: &mut b.d_rgb,
                background: None,
            },
        );
        times.composite = clock.elapsed().as_secs_f64();

        // Networks backward.
        let clock = Instant::now();
        // The networks' backward passes add to their gradients, which are
        // cleared here; the hash grid's backward writes its own (most of the
        // vector) in parallel.
        set_len(&mut b.gradients, self.params.len());
        let (grid_grad, network_grad) = b.gradients.split_at_mut(shape.grid.param_count());
        network_grad.fill(0.0);
        let (density_grad, colour_grad) = network_grad.split_at_mut(shape.density.param_count());
        // The colour network's input gradient is wanted for its density
        // features only (the first columns), not for the direction encoding.
        set_len(&mut b.d_density_out, u * density_width);
        mlp_backward_columns(
            &shape.colour,
            &self.params[shape.colour_range()],
            &b.colour_input,
            u,
            &mut self.colour_workspace,
            &b.d_rgb,
            colour_grad,
            &mut b.d_density_out,
            0..density_width,
        );
        for ((d_out, &d_sigma), &sigma) in b
            .d_density_out
            .chunks_exact_mut(density_width)
            .zip(&b.d_sigma)
            .zip(&b.sigma)
        {
            // dσ/dx = σ below the clamp, 0 above it.
            let clamped = sigma >= crate::field::ngp::DENSITY_EXP_CLAMP.exp();
            if !clamped {
                d_out[0] += d_sigma * sigma;
            }
        }
        set_len(&mut b.d_encoded, u * grid_width);
        mlp_backward(
            &shape.density,
            &self.params[shape.density_range()],
            &used.encoded,
            u,
            &mut self.density_workspace,
            &b.d_density_out,
            density_grad,
            Some(&mut b.d_encoded),
        );
        times.networks_backward = clock.elapsed().as_secs_f64();

        let clock = Instant::now();
        hash_grid::encode_gradient_with_scratch(
            &shape.grid,
            bytemuck::cast_slice(&used.positions),
            &b.d_encoded,
            grid_grad,
            &mut b.encode_scratch,
        );
        times.encode_backward = clock.elapsed().as_secs_f64();

        StepStats {
            loss: loss as f32,
            level_losses: [loss as f32, 0.0],
            rays: if rays == 0 { 0 } else { kept },
            samples: s,
            samples_composited: Some(u),
            times,
            network_flops: 0.0,
        }
    }

    /// The gradient written by the last [`Self::forward_backward`], in the
    /// parameters' layout.
    pub fn gradients(&self) -> &[f32] {
        &self.buffers.gradients
    }

    /// Parameters, writable (for gradient checks).
    pub fn params_mut(&mut self) -> &mut [f32] {
        &mut self.params
    }

    /// The occupancy grid, writable (for tests of recovery).
    pub fn occupancy_mut(&mut self) -> &mut OccupancyGrid {
        &mut self.grid
    }

    /// Where each part of the model sits in the parameter vector.
    pub fn parameter_ranges(&self) -> [(&'static str, Range<usize>); 3] {
        [
            ("hash grid", self.shape.grid_range()),
            ("density network", self.shape.density_range()),
            ("colour network", self.shape.colour_range()),
        ]
    }

    /// σ at unit-cube positions (n × 3), as the occupancy grid's updates
    /// see it: for probes of where the field holds density.
    pub fn densities(&self, positions: &[f32]) -> Vec<f32> {
        let mut sigma = vec![0f32; positions.len() / 3];
        let (mut encoded, mut scratch) = (Vec::new(), Vec::new());
        self.shape.density(
            &self.params,
            positions,
            &mut sigma,
            &mut encoded,
            &mut scratch,
        );
        sigma
    }

    fn update_grid(&mut self, step: u32) {
        let shape = &self.shape;
        let params = &self.params;
        // The step's encoding buffers serve as the update's: the grid asks
        // for densities in chunks of a training batch at most.
        let b = &mut self.buffers;
        self.grid.update(step, self.seed, |positions, sigma| {
            shape.density(
                params,
                positions,
                sigma,
                &mut b.encoded,
                &mut b.encode_scratch,
            );
        });
    }
}

impl RadianceModel for CpuNgp {
    fn describe(&self) -> String {
        "Instant-NGP (cpu)".into()
    }

    fn cpu_kernels(&self) -> Option<super::dense::Backend> {
        Some(self.shape.density.kernels())
    }

    fn rays_for_next_batch(&self) -> usize {
        self.batch_sizer.rays()
    }

    fn step(&mut self, batch: &RayBatch, step: u32) -> StepStats {
        let clock = Instant::now();
        if self.grid.is_due(step) {
            self.update_grid(step);
        }
        let grid_update = clock.elapsed().as_secs_f64();

        let mut stats = self.forward_backward(batch, step);
        stats.times.grid_update = grid_update;

        let clock = Instant::now();
        let weights = self.shape.density_range().start..self.shape.param_count();
        self.adam.step(
            &self.optimiser,
            weights,
            &mut self.params,
            &self.buffers.gradients,
        );
        stats.times.optimiser = clock.elapsed().as_secs_f64();
        stats
    }

    fn render(
        &self,
        origins: &[Vec3],
        directions: &[Vec3],
        _radii: &[f32],
        background: [f32; 3],
        out: &mut [RenderedPixel],
    ) {
        let shape = &self.shape;
        let params = &self.params;
        render_through_grid(
            &self.grid,
            &shape.mapping,
            origins,
            directions,
            background,
            &MarchConfig::paper_or_environment(),
            INFERENCE_CHUNK,
            |samples, sigma, rgb| {
                shape.radiance(params, samples.positions, samples.directions, sigma, rgb);
                if let Some(crop) = &self.crop {
                    crop_densities(crop, &shape.mapping, samples.positions, sigma);
                }
            },
            out,
        );
    }

    fn density_at(
        &self,
        positions: &[Vec3],
        _footprint: f32,
        sigma: &mut [f32],
    ) -> Result<(), String> {
        let mapping = self.shape.mapping;
        let (mut unit, mut encoded, mut scratch) = (Vec::new(), Vec::new(), Vec::new());
        for (points, sigma) in positions
            .chunks(INFERENCE_CHUNK)
            .zip(sigma.chunks_mut(INFERENCE_CHUNK))
        {
            unit.clear();
            unit.extend(points.iter().flat_map(|&p| mapping.to_unit(p).to_array()));
            self.shape
                .density(&self.params, &unit, sigma, &mut encoded, &mut scratch);
            // What the renderer sees: nothing in cells the occupancy grid
            // marks empty, which rays skip. The network's density there is
            // never trained down (no sample lands there), so without the
            // mask it leaves floaters in meshes that no render shows.
            for (s, p) in sigma.iter_mut().zip(unit.chunks_exact(3)) {
                if !self.grid.occupied_at(Vec3::from_slice(p)) {
                    *s = 0.0;
                }
            }
        }
        Ok(())
    }

    fn colour_at(
        &self,
        positions: &[Vec3],
        directions: &[Vec3],
        _footprint: f32,
        rgb: &mut [f32],
    ) -> Result<(), String> {
        let mapping = self.shape.mapping;
        let (mut unit, mut flat_directions, mut sigma) = (Vec::new(), Vec::new(), Vec::new());
        for ((points, directions), rgb) in positions
            .chunks(INFERENCE_CHUNK)
            .zip(directions.chunks(INFERENCE_CHUNK))
            .zip(rgb.chunks_mut(3 * INFERENCE_CHUNK))
        {
            unit.clear();
            unit.extend(points.iter().flat_map(|&p| mapping.to_unit(p).to_array()));
            flat_directions.clear();
            flat_directions.extend(directions.iter().flat_map(|d| d.to_array()));
            set_len(&mut sigma, points.len());
            self.shape
                .radiance(&self.params, &unit, &flat_directions, &mut sigma, rgb);
        }
        Ok(())
    }

    fn set_crop(&mut self, crop: Option<crate::scene::crop::CropBox>) -> Result<(), String> {
        self.crop = crop;
        Ok(())
    }

    fn save(&self) -> Checkpoint {
        ModelState {
            header: ModelHeader {
                model: "ngp".into(),
                loss: self.loss,
                seed: self.seed,
                adam_step: self.adam.step,
                samples_per_ray: self.batch_sizer.samples_per_ray(),
                param_count: self.params.len(),
                sampling: None,
                used_fraction: None,
                grid_extent: Some(self.shape.grid.config().extent),
            },
            params: self.params.clone(),
            adam: self.adam.clone(),
            occupancy: Some(self.grid.values().to_vec()),
        }
        .into_checkpoint()
    }

    fn load(&mut self, checkpoint: &Checkpoint) -> Result<(), String> {
        let state = ModelState::from_checkpoint(
            checkpoint,
            "ngp",
            self.params.len(),
            Some(self.grid.values().len()),
        )?;
        state
            .header
            .check_grid_extent(self.shape.grid.config().extent)?;
        self.params = state.params;
        self.adam = state.adam;
        if let Some(occupancy) = &state.occupancy {
            self.grid.values_mut().copy_from_slice(occupancy);
        }
        self.grid.build_bitfield();
        self.batch_sizer
            .set_samples_per_ray(state.header.samples_per_ray);
        self.loss = state.header.loss;
        self.seed = state.header.seed;
        Ok(())
    }

    fn memory_bytes(&self) -> usize {
        let b = &self.buffers;
        let floats = self.params.len() * 5
            + self.grid.values().len()
            + [
                &b.origins,
                &b.directions,
                &b.encoded,
                &b.encode_scratch,
                &b.sigma_marched,
                &b.used.encoded,
                &b.used.positions,
                &b.used.directions,
                &b.used.dt,
                &b.used.t,
                &b.density_out,
                &b.sigma,
                &b.colour_input,
                &b.rgb,
                &b.d_sigma,
                &b.d_rgb,
                &b.d_density_out,
                &b.d_encoded,
                &b.gradients,
                &b.samples.positions,
                &b.samples.directions,
                &b.samples.dt,
                &b.samples.t,
            ]
            .iter()
            .map(|v| v.capacity())
            .sum::<usize>();
        floats * 4
    }
}
