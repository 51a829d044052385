//! Instant-NGP's field on the `cpu` engine (Müller et al. 2022, section 4
//! and 5.4): the multiresolution hash encoding of a unit-cube position, a
//! density network whose first output is log-density and whose 16 outputs
//! join the spherical-harmonics encoding of the direction in a colour
//! network:
//!
//! ```text
//! position ─ hash grid ─► features ─ density MLP ─► [x | 15 more] ─┬─ σ = exp(x)
//! direction ─ SH (degree 4) ─► 16 ──────────────────────────────────┴ colour MLP ─► RGB
//! ```
//!
//! Its parameters are `[hash grid | density network | colour network]`:
//! the grid's entries are updated sparsely (only where a sample touched
//! them) without weight decay, the networks densely with L2 (tiny-cuda-nn's
//! Adam for instant-ngp). The model around it is `CpuModel` with the recipe
//! of [`crate::field::ngp::recipe`].
//!
//! In a marched step, the σ pass over every marched sample
//! ([`Field::density_for_cut`]) keeps the hash features and σ; the forward
//! pass on the samples before each ray's cut gathers them instead of
//! encoding again, and composites with the σ the cut was found with.

use std::sync::Mutex;

use rayon::prelude::*;

use super::{
    Appearance, AppearanceShape, Field, Gradient, gather_rows, hash_grid_backward, set_len,
};
use crate::engine::cpu::appearance::{KeptAppearance, appearance_backward, write_appearance};
use crate::engine::cpu::dense::{
    Backend, InputGradient, MlpGradients, MlpWorkspace, mlp_backward, mlp_forward, mlp_inference,
    mlp_inference_leading,
};
use crate::engine::cpu::hash_grid;
use crate::engine::cpu::sh::{sh_encode, sh_encode_backward};
use crate::field::common::Coordinates;
use crate::field::mlp::DENSITY_EXP_CLAMP;
use crate::field::params::ParamLayout;

/// Rows per rayon task in the element-wise passes.
const ROWS_PER_TASK: usize = 4096;

/// Samples per round of inference when rendering: the field's activations
/// are ~80 floats a sample, so 2^16 rows hold ~20 MB.
const INFERENCE_ROWS: usize = 1 << 16;

use crate::field::ngp::NgpShape;

impl NgpShape {
    /// Inference of σ at unit-cube positions (n × 3), with the hash
    /// features kept in `encoded` and `scratch` (grown as needed, reused
    /// between calls). Only output 0 (log-density) of the density network
    /// is computed (equal to that output of the full pass up to rounding).
    pub fn density(
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
        let scale = self.density_scale;
        sigma.par_chunks_mut(ROWS_PER_TASK).for_each(|chunk| {
            for s in chunk {
                *s = density_activation(*s, scale);
            }
        });
    }

    /// Inference of σ and colour at unit-cube positions and directions,
    /// with `appearance` where the field has embeddings.
    pub fn radiance(
        &self,
        params: &[f32],
        positions: &[f32],
        directions: &[f32],
        appearance: Appearance<'_>,
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
            *s = density_activation(row[0], self.density_scale);
            input[..density_width].copy_from_slice(row);
        }
        sh_encode(
            self.network.sh_degree,
            directions,
            n,
            &mut colour_input[density_width..],
            colour_width,
        );
        if let Some(table) = &self.appearance {
            write_appearance(
                table,
                &params[self.appearance_range()],
                appearance,
                &mut colour_input,
                colour_width,
                self.appearance_column(),
                None,
            );
        }
        mlp_inference(
            &self.colour,
            &params[self.colour_range()],
            &colour_input,
            n,
            rgb,
        );
    }
}

impl NgpShape {
    /// The colour network's first appearance column: after the density
    /// outputs and the spherical harmonics.
    fn appearance_column(&self) -> usize {
        self.density.output_width() + self.network.sh_coefficients()
    }
}

/// σ = scale · exp(x), x clamped (field/ngp.rs, DENSITY_EXP_CLAMP; the
/// scale is the shape's `density_scale`).
pub fn density_activation(x: f32, scale: f32) -> f32 {
    scale * x.min(DENSITY_EXP_CLAMP).exp()
}

/// Instant-NGP's field on the `cpu` engine.
pub struct NgpField {
    shape: NgpShape,
    density_workspace: MlpWorkspace,
    colour_workspace: MlpWorkspace,
    /// Hash features (S × L·F) and σ (S) of every sample of the last
    /// [`Field::density_for_cut`].
    marched_encoded: Vec<f32>,
    marched_sigma: Vec<f32>,
    encode_scratch: Vec<f32>,
    /// What the last forward pass keeps for the backward pass, per row:
    /// hash features, unit-cube positions, σ (the cut's, where the rows
    /// came from one), the density network's outputs, the colour
    /// network's input.
    encoded: Vec<f32>,
    positions: Vec<f32>,
    sigma: Vec<f32>,
    density_out: Vec<f32>,
    colour_input: Vec<f32>,
    d_density_out: Vec<f32>,
    d_encoded: Vec<f32>,
    /// With camera refinement: whether the backward pass keeps the
    /// gradient of the colour network's whole input, direction encoding
    /// included, for [`Field::input_gradients`].
    keep_input_gradients: bool,
    /// With camera refinement: the last forward pass's directions.
    directions: Vec<f32>,
    /// Which appearance vector each row of the last forward pass took
    /// (fields with embeddings).
    appearance: KeptAppearance,
    /// The gradient of the colour network's whole input (rows × its
    /// width), with camera refinement or appearance embeddings.
    d_colour_input: Vec<f32>,
    /// Hash features and scratch of σ inference through `&self` (the
    /// occupancy grid's updates).
    inference: Mutex<(Vec<f32>, Vec<f32>)>,
}

impl NgpField {
    pub fn new(shape: NgpShape) -> Self {
        Self {
            density_workspace: MlpWorkspace::new(&shape.density, 0),
            colour_workspace: MlpWorkspace::new(&shape.colour, 0),
            shape,
            marched_encoded: Vec::new(),
            marched_sigma: Vec::new(),
            encode_scratch: Vec::new(),
            encoded: Vec::new(),
            positions: Vec::new(),
            sigma: Vec::new(),
            density_out: Vec::new(),
            colour_input: Vec::new(),
            d_density_out: Vec::new(),
            d_encoded: Vec::new(),
            keep_input_gradients: false,
            directions: Vec::new(),
            appearance: KeptAppearance::default(),
            d_colour_input: Vec::new(),
            inference: Mutex::new((Vec::new(), Vec::new())),
        }
    }

    pub fn shape(&self) -> &NgpShape {
        &self.shape
    }

    /// The networks' forward pass on the rows whose hash features are in
    /// `self.encoded` and σ in `self.sigma`: the colour of each into `rgb`.
    fn networks_forward(
        &mut self,
        params: &[f32],
        directions: &[f32],
        appearance: Appearance<'_>,
        rgb: &mut [f32],
    ) {
        if self.keep_input_gradients {
            self.directions.clear();
            self.directions.extend_from_slice(directions);
        }
        let shape = &self.shape;
        let u = self.sigma.len();
        let density_width = shape.density.output_width();
        let colour_width = shape.colour.input_width();
        set_len(&mut self.density_out, u * density_width);
        self.density_workspace.reserve(u);
        mlp_forward(
            &shape.density,
            &params[shape.density_range()],
            &self.encoded,
            u,
            &mut self.density_workspace,
            &mut self.density_out,
        );
        set_len(&mut self.colour_input, u * colour_width);
        self.colour_input
            .par_chunks_mut(ROWS_PER_TASK * colour_width)
            .zip(self.density_out.par_chunks(ROWS_PER_TASK * density_width))
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
            directions,
            u,
            // Empty when the batch has no samples (an empty grid).
            self.colour_input
                .get_mut(density_width..)
                .unwrap_or_default(),
            colour_width,
        );
        if let Some(table) = &shape.appearance {
            write_appearance(
                table,
                &params[shape.appearance_range()],
                appearance,
                &mut self.colour_input,
                colour_width,
                shape.appearance_column(),
                Some(&mut self.appearance),
            );
        }
        self.colour_workspace.reserve(u);
        mlp_forward(
            &shape.colour,
            &params[shape.colour_range()],
            &self.colour_input,
            u,
            &mut self.colour_workspace,
            rgb,
        );
    }
}

impl Field for NgpField {
    fn layout(&self) -> ParamLayout {
        self.shape.layout()
    }

    fn kernels(&self) -> Backend {
        self.shape.density.kernels()
    }

    fn coordinates(&self) -> Coordinates {
        Coordinates::UnitCube
    }

    fn grid_extent(&self) -> Option<f32> {
        Some(self.shape.grid.config().extent)
    }

    fn inference_rows(&self) -> usize {
        INFERENCE_ROWS
    }

    fn density(
        &self,
        params: &[f32],
        positions: &[f32],
        _variances: Option<&[f32]>,
        sigma: &mut [f32],
    ) {
        let mut guard = self.inference.lock().unwrap_or_else(|e| e.into_inner());
        let (encoded, scratch) = &mut *guard;
        self.shape
            .density(params, positions, sigma, encoded, scratch);
    }

    fn density_for_cut(
        &mut self,
        params: &[f32],
        positions: &[f32],
        _variances: Option<&[f32]>,
        sigma: &mut [f32],
    ) {
        self.shape.density(
            params,
            positions,
            sigma,
            &mut self.marched_encoded,
            &mut self.encode_scratch,
        );
        self.marched_sigma.clear();
        self.marched_sigma.extend_from_slice(sigma);
    }

    fn forward_before_cut(
        &mut self,
        params: &[f32],
        rows: &[u32],
        positions: &[f32],
        _variances: Option<&[f32]>,
        directions: &[f32],
        appearance: Appearance<'_>,
        sigma: &mut [f32],
        rgb: &mut [f32],
    ) {
        let width = self.shape.grid.output_width();
        gather_rows(&self.marched_encoded, width, rows, &mut self.encoded);
        // σ is the one the cut was found with (the σ-only inference sums in
        // another order than the full pass, so the two can differ in the
        // last bits): compositing then stops exactly where the cut said,
        // and the backward pass differentiates what was composited.
        gather_rows(&self.marched_sigma, 1, rows, &mut self.sigma);
        self.positions.clear();
        self.positions.extend_from_slice(positions);
        self.networks_forward(params, directions, appearance, rgb);
        sigma.copy_from_slice(&self.sigma);
    }

    fn may_find_cut_in_forward(&self) -> bool {
        // The σ pass's hash features serve the forward pass, so σ first
        // costs little more than the forward pass on the used samples.
        false
    }

    fn forward(
        &mut self,
        params: &[f32],
        positions: &[f32],
        _variances: Option<&[f32]>,
        directions: &[f32],
        appearance: Appearance<'_>,
        sigma: &mut [f32],
        rgb: &mut [f32],
    ) {
        let n = sigma.len();
        let shape = &self.shape;
        set_len(&mut self.encoded, n * shape.grid.output_width());
        hash_grid::encode_with_scratch(
            &shape.grid,
            &params[shape.grid_range()],
            bytemuck::cast_slice(positions),
            &mut self.encoded,
            &mut self.encode_scratch,
        );
        self.positions.clear();
        self.positions.extend_from_slice(positions);
        // σ from the density network's output 0 once the pass has run.
        set_len(&mut self.sigma, n);
        self.networks_forward(params, directions, appearance, rgb);
        let density_width = self.shape.density.output_width();
        let scale = self.shape.density_scale;
        for (s, row) in self
            .sigma
            .iter_mut()
            .zip(self.density_out.chunks_exact(density_width))
        {
            *s = density_activation(row[0], scale);
        }
        sigma.copy_from_slice(&self.sigma);
    }

    fn backward(
        &mut self,
        params: &[f32],
        d_sigma: &[f32],
        d_rgb: &[f32],
        gradients: &mut [f32],
        mode: Gradient,
    ) {
        let shape = &self.shape;
        let u = self.sigma.len();
        assert!(
            d_sigma.len() == u && d_rgb.len() == 3 * u,
            "gradients of {u} samples"
        );
        let density_width = shape.density.output_width();
        let grid_width = shape.grid.output_width();
        let (grid_grad, network_grad) = gradients.split_at_mut(shape.grid.param_count());
        // The networks' backward passes add to their gradients; the hash
        // grid's writes its own (most of the vector) in parallel.
        if mode == Gradient::Overwrite {
            network_grad.fill(0.0);
        }
        let (density_grad, colour_grad) = network_grad.split_at_mut(shape.density.param_count());
        let (colour_grad, appearance_grad) = colour_grad.split_at_mut(shape.colour.param_count());
        set_len(&mut self.d_density_out, u * density_width);
        if self.keep_input_gradients || shape.appearance.is_some() {
            // Every column: the density features' go where the pass below
            // reads them, the direction encoding's stay for
            // [`Field::input_gradients`] (camera refinement) and the
            // appearance columns' go to their images' rows.
            let colour_width = shape.colour.input_width();
            set_len(&mut self.d_colour_input, u * colour_width);
            mlp_backward(
                &shape.colour,
                &params[shape.colour_range()],
                &self.colour_input,
                u,
                &mut self.colour_workspace,
                MlpGradients {
                    output: d_rgb,
                    params: colour_grad,
                    input: Some(InputGradient::every_column(
                        &mut self.d_colour_input,
                        &shape.colour,
                    )),
                },
            );
            for (d_out, d_in) in self
                .d_density_out
                .chunks_exact_mut(density_width)
                .zip(self.d_colour_input.chunks_exact(colour_width))
            {
                d_out.copy_from_slice(&d_in[..density_width]);
            }
            if let Some(table) = &shape.appearance {
                appearance_backward(
                    table,
                    &self.appearance,
                    &self.d_colour_input,
                    colour_width,
                    shape.appearance_column(),
                    appearance_grad,
                );
            }
        } else {
            // The colour network's input gradient is wanted for its density
            // features only (the first columns), not for the direction
            // encoding.
            mlp_backward(
                &shape.colour,
                &params[shape.colour_range()],
                &self.colour_input,
                u,
                &mut self.colour_workspace,
                MlpGradients {
                    output: d_rgb,
                    params: colour_grad,
                    input: Some(InputGradient {
                        values: &mut self.d_density_out,
                        columns: 0..density_width,
                    }),
                },
            );
        }
        let sigma_at_clamp = shape.density_scale * DENSITY_EXP_CLAMP.exp();
        for ((d_out, &d_sigma), &sigma) in self
            .d_density_out
            .chunks_exact_mut(density_width)
            .zip(d_sigma)
            .zip(&self.sigma)
        {
            // dσ/dx = σ below the clamp, 0 above it.
            let clamped = sigma >= sigma_at_clamp;
            if !clamped {
                d_out[0] += d_sigma * sigma;
            }
        }
        set_len(&mut self.d_encoded, u * grid_width);
        mlp_backward(
            &shape.density,
            &params[shape.density_range()],
            &self.encoded,
            u,
            &mut self.density_workspace,
            MlpGradients {
                output: &self.d_density_out,
                params: density_grad,
                input: Some(InputGradient::every_column(
                    &mut self.d_encoded,
                    &shape.density,
                )),
            },
        );
        hash_grid_backward(
            &shape.grid,
            bytemuck::cast_slice(&self.positions),
            &self.d_encoded,
            grid_grad,
            &mut self.encode_scratch,
            mode,
        );
    }

    fn keep_input_gradients(&mut self, keep: bool) -> bool {
        self.keep_input_gradients = keep;
        true
    }

    /// Positions through the hash grid's trilinear interpolation (the
    /// density network's input gradient, which the backward pass keeps),
    /// directions through the spherical harmonics (the colour network's
    /// gradient of its direction columns).
    fn input_gradients(
        &mut self,
        params: &[f32],
        d_positions: &mut [f32],
        d_directions: &mut [f32],
    ) {
        assert!(
            self.keep_input_gradients,
            "input gradients were not asked for before the backward pass"
        );
        let shape = &self.shape;
        let u = self.sigma.len();
        hash_grid::position_gradient(
            &shape.grid,
            &params[shape.grid_range()],
            bytemuck::cast_slice(&self.positions),
            &self.d_encoded,
            bytemuck::cast_slice_mut(&mut d_positions[..3 * u]),
        );
        let density_width = shape.density.output_width();
        let colour_width = shape.colour.input_width();
        sh_encode_backward(
            shape.network.sh_degree,
            &self.directions,
            u,
            self.d_colour_input.get(density_width..).unwrap_or_default(),
            colour_width,
            d_directions,
        );
    }

    fn radiance(
        &self,
        params: &[f32],
        positions: &[f32],
        _variances: Option<&[f32]>,
        directions: &[f32],
        appearance: Appearance<'_>,
        sigma: &mut [f32],
        rgb: &mut [f32],
    ) {
        self.shape
            .radiance(params, positions, directions, appearance, sigma, rgb);
    }

    fn appearance(&self) -> Option<AppearanceShape> {
        self.shape.appearance
    }

    fn macs_per_sample(&self) -> usize {
        self.shape.macs_per_sample()
    }

    fn density_macs_per_sample(&self) -> usize {
        self.shape.density_macs_per_sample()
    }

    fn workspace_bytes(&self) -> usize {
        4 * [
            &self.marched_encoded,
            &self.marched_sigma,
            &self.encode_scratch,
            &self.encoded,
            &self.positions,
            &self.sigma,
            &self.density_out,
            &self.colour_input,
            &self.d_density_out,
            &self.d_encoded,
            &self.d_colour_input,
        ]
        .iter()
        .map(|v| v.capacity())
        .sum::<usize>()
            + self.density_workspace.bytes()
            + self.colour_workspace.bytes()
            + self.appearance.bytes()
    }
}
