//! A density-only NeRF-shaped field on the `cpu` engine: the proposal MLP
//! of Mip-NeRF 360 (Barron et al. 2022, section 2.1; multinerf's `PropMLP`)
//! beside NeRF's and Mip-NeRF's fields:
//!
//! ```text
//! γ(x) (or Mip-NeRF's integrated encoding) ─► 4 × 256 (ReLU) ─► σ_raw ─► σ = softplus(σ_raw − 1)
//! ```
//!
//! It has no colour: a proposal level composites weights only, and its
//! colour output is zero. Its parameters are the one network's.

use super::{Appearance, Field, Gradient, set_len};
use crate::engine::cpu::dense::{
    Backend, MlpGradients, MlpWorkspace, mlp_backward, mlp_forward, mlp_inference,
};
use crate::engine::cpu::frequency;
use crate::field::nerf::NerfDensityShape;
use crate::field::params::ParamLayout;

/// Rows per round of inference, so σ queries of many points keep their
/// encodings small.
const INFERENCE_ROWS: usize = 1 << 14;

/// A NeRF or Mip-NeRF proposal level's field on the `cpu` engine.
pub struct NerfDensityField {
    shape: NerfDensityShape,
    workspace: MlpWorkspace,
    /// What the last forward pass keeps for the backward pass: the encoded
    /// positions and the raw σ per row.
    encoded: Vec<f32>,
    raw: Vec<f32>,
    d_raw: Vec<f32>,
}

impl NerfDensityField {
    pub fn new(shape: NerfDensityShape) -> Self {
        Self {
            workspace: MlpWorkspace::new(&shape.network, 0),
            shape,
            encoded: Vec::new(),
            raw: Vec::new(),
            d_raw: Vec::new(),
        }
    }
}

impl Field for NerfDensityField {
    fn layout(&self) -> ParamLayout {
        self.shape.layout()
    }

    fn kernels(&self) -> Backend {
        self.shape.network.kernels()
    }

    fn density(
        &self,
        params: &[f32],
        positions: &[f32],
        variances: Option<&[f32]>,
        sigma: &mut [f32],
    ) {
        let s = &self.shape;
        let width = s.position.output_width();
        let rows = INFERENCE_ROWS.min(sigma.len().max(1));
        let mut encoded = vec![0f32; rows * width];
        for (chunk, (positions, sigma)) in positions
            .chunks(3 * rows)
            .zip(sigma.chunks_mut(rows))
            .enumerate()
        {
            let m = sigma.len();
            let variances = variances.map(|v| &v[3 * rows * chunk..][..3 * m]);
            let encoded = &mut encoded[..m * width];
            frequency::encode(&s.position, positions, variances, encoded);
            mlp_inference(&s.network, params, encoded, m, sigma);
            for x in sigma.iter_mut() {
                *x = s.density.apply(*x);
            }
        }
    }

    fn forward(
        &mut self,
        params: &[f32],
        positions: &[f32],
        variances: Option<&[f32]>,
        _directions: &[f32],
        _appearance: Appearance<'_>,
        sigma: &mut [f32],
        rgb: &mut [f32],
    ) {
        let s = &self.shape;
        let n = sigma.len();
        set_len(&mut self.encoded, n * s.position.output_width());
        frequency::encode(&s.position, positions, variances, &mut self.encoded);
        set_len(&mut self.raw, n);
        self.workspace.reserve(n);
        mlp_forward(
            &s.network,
            params,
            &self.encoded,
            n,
            &mut self.workspace,
            &mut self.raw,
        );
        for (sigma, &raw) in sigma.iter_mut().zip(&self.raw) {
            *sigma = s.density.apply(raw);
        }
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
        // The network's backward pass adds to its gradient.
        if mode == Gradient::Overwrite {
            gradients.fill(0.0);
        }
        let s = &self.shape;
        let n = self.raw.len();
        assert_eq!(d_sigma.len(), n, "gradients of {n} samples");
        set_len(&mut self.d_raw, n);
        for ((d, &g), &raw) in self.d_raw.iter_mut().zip(d_sigma).zip(&self.raw) {
            *d = g * s.density.derivative(raw);
        }
        mlp_backward(
            &s.network,
            params,
            &self.encoded,
            n,
            &mut self.workspace,
            MlpGradients {
                output: &self.d_raw,
                params: gradients,
                input: None,
            },
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

    fn twin(&self) -> Option<Box<dyn Field>> {
        Some(Box::new(Self::new(self.shape.clone())))
    }

    fn macs_per_sample(&self) -> usize {
        self.shape.macs_per_sample()
    }

    fn density_macs_per_sample(&self) -> usize {
        self.shape.macs_per_sample()
    }

    fn workspace_bytes(&self) -> usize {
        4 * [&self.encoded, &self.raw, &self.d_raw]
            .iter()
            .map(|v| v.capacity())
            .sum::<usize>()
            + self.workspace.bytes()
    }
}
