//! A density-only field on the `cpu` engine: a proposal level's (Mip-NeRF
//! 360, section 2.1, with nerfstudio's hash-grid proposal networks). A
//! small multiresolution hash grid of a position in the contracted cube,
//! one hidden layer, σ through the clamped exponential:
//!
//! ```text
//! position ─ hash grid (5 levels) ─► 10 ─ ReLU 16 ─► σ = exp(x)
//! ```
//!
//! It has no colour: the proposal level composites weights only, and its
//! colour output is zero. Its parameters are `[hash grid | network]`, the
//! grid's updated sparsely, the network's densely with L2, as Instant-NGP's
//! field's.

use std::sync::Mutex;

use super::{Appearance, Field, Gradient, hash_grid_backward, set_len};
use crate::engine::cpu::dense::{
    Backend, InputGradient, MlpGradients, MlpWorkspace, mlp_backward, mlp_forward, mlp_inference,
};
use crate::engine::cpu::hash_grid;
use crate::field::common::Coordinates;
use crate::field::ngp::DensityShape;
use crate::field::params::ParamLayout;

/// A proposal level's field on the `cpu` engine.
pub struct DensityField {
    shape: DensityShape,
    workspace: MlpWorkspace,
    /// What the last forward pass keeps for the backward pass: hash
    /// features and positions per row.
    encoded: Vec<f32>,
    positions: Vec<f32>,
    d_encoded: Vec<f32>,
    /// ∂L/∂y of the network's outputs y (σ = scale · y).
    d_output: Vec<f32>,
    encode_scratch: Vec<f32>,
    /// Hash features of σ inference through `&self`.
    inference: Mutex<Vec<f32>>,
}

impl DensityField {
    pub fn new(shape: DensityShape) -> Self {
        Self {
            workspace: MlpWorkspace::new(&shape.density, 0),
            shape,
            encoded: Vec::new(),
            positions: Vec::new(),
            d_encoded: Vec::new(),
            d_output: Vec::new(),
            encode_scratch: Vec::new(),
            inference: Mutex::new(Vec::new()),
        }
    }
}

impl Field for DensityField {
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

    fn density(
        &self,
        params: &[f32],
        positions: &[f32],
        _variances: Option<&[f32]>,
        sigma: &mut [f32],
    ) {
        let mut encoded = self.inference.lock().unwrap_or_else(|e| e.into_inner());
        let n = sigma.len();
        set_len(&mut encoded, n * self.shape.grid.output_width());
        hash_grid::encode(
            &self.shape.grid,
            &params[self.shape.grid_range()],
            bytemuck::cast_slice(positions),
            &mut encoded,
        );
        mlp_inference(
            &self.shape.density,
            &params[self.shape.density_range()],
            &encoded,
            n,
            sigma,
        );
        scale_densities(sigma, self.shape.density_scale);
    }

    fn forward(
        &mut self,
        params: &[f32],
        positions: &[f32],
        _variances: Option<&[f32]>,
        _directions: &[f32],
        _appearance: Appearance<'_>,
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
        self.workspace.reserve(n);
        mlp_forward(
            &shape.density,
            &params[shape.density_range()],
            &self.encoded,
            n,
            &mut self.workspace,
            sigma,
        );
        scale_densities(sigma, shape.density_scale);
        rgb.fill(0.0);
    }

    fn backward(
        &mut self,
        params: &[f32],
        d_sigma: &[f32],
        _d_rgb: &[f32],
        gradients: &mut [f32],
        mode: Gradient,
    ) {
        let shape = &self.shape;
        let n = self.positions.len() / 3;
        assert_eq!(d_sigma.len(), n, "gradients of {n} samples");
        let (grid_grad, network_grad) = gradients.split_at_mut(shape.grid.param_count());
        if mode == Gradient::Overwrite {
            network_grad.fill(0.0);
        }
        set_len(&mut self.d_encoded, n * shape.grid.output_width());
        // σ = scale · y of the network's output y.
        self.d_output.clear();
        self.d_output
            .extend(d_sigma.iter().map(|d| d * shape.density_scale));
        mlp_backward(
            &shape.density,
            &params[shape.density_range()],
            &self.encoded,
            n,
            &mut self.workspace,
            MlpGradients {
                output: &self.d_output,
                params: network_grad,
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

    fn radiance(
        &self,
        params: &[f32],
        positions: &[f32],
        variances: Option<&[f32]>,
        _directions: &[f32],
        _appearance: Appearance<'_>,
        sigma: &mut [f32],
        rgb: &mut [f32],
    ) {
        self.density(params, positions, variances, sigma);
        rgb.fill(0.0);
    }

    fn macs_per_sample(&self) -> usize {
        self.shape.density.macs_per_row()
    }

    fn density_macs_per_sample(&self) -> usize {
        self.shape.density.macs_per_row()
    }

    fn workspace_bytes(&self) -> usize {
        4 * [
            &self.encoded,
            &self.positions,
            &self.d_encoded,
            &self.encode_scratch,
        ]
        .iter()
        .map(|v| v.capacity())
        .sum::<usize>()
            + self.workspace.bytes()
    }
}

/// σ = `scale` · y of the density network's outputs y, in place.
fn scale_densities(sigma: &mut [f32], scale: f32) {
    if scale != 1.0 {
        sigma.iter_mut().for_each(|s| *s *= scale);
    }
}
