//! Dense networks as both engines and the checkpoints see them: a
//! multilayer perceptron's shape ([`MlpLayout`]: widths, activations,
//! biases, the arithmetic of its products), its element-wise activations
//! and where each layer's parameters sit. The `cpu` engine's kernels
//! (`engine::cpu::dense`) and the `gpu` engine's (`engine::gpu::dense`)
//! compute the same networks from these.
//!
//! # Parameter layout
//!
//! All parameters of an MLP live in one flat `&[f32]`, layer after layer.
//! Layer k contributes its weight matrix W_k, `out × in` row-major (row o
//! holds the weights into output o, as in PyTorch's `nn.Linear` and in
//! tiny-cuda-nn), followed by its bias b_k (`out` values) when the layout has
//! biases. [`MlpLayout::weight_offset`] and [`MlpLayout::bias_offset`] give
//! the positions; gradients use the same layout.

use num_traits::Float;

use crate::rng::Pcg32;

/// An element-wise activation.
/// σ = exp(x) with x clamped, so a large raw output can neither overflow
/// nor send a huge gradient back (testbed: `network_to_density`, "Exponential"
/// activation; the clamp is zrak's). exp(15) ≈ 3.3e6 is far denser than any
/// surface needs at step √3/1024.
pub const DENSITY_EXP_CLAMP: f32 = 15.0;

/// The sizes of a density network followed by a colour network on its
/// features and the view direction's spherical harmonics (Instant-NGP's
/// tiny MLPs; its values are in `ngp.rs`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NetworkConfig {
    /// Density network: 32 → 64 → 16, ReLU hidden layer (one hidden layer).
    pub density_hidden_width: usize,
    pub density_hidden_layers: usize,
    /// The density network's output: the first is log-density, all 16 feed
    /// the colour network (paper, section 5.4).
    pub density_output_width: usize,
    /// Colour network: 16 + 16 → 64 → 64 → 3, two hidden layers, sigmoid.
    pub colour_hidden_width: usize,
    pub colour_hidden_layers: usize,
    /// Spherical-harmonics degree of the view direction encoding (config
    /// "dir_encoding": SphericalHarmonics, degree 4 → 16 coefficients).
    pub sh_degree: u32,
}

impl NetworkConfig {
    pub fn sh_coefficients(&self) -> usize {
        (self.sh_degree * self.sh_degree) as usize
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Activation {
    None,
    Relu,
    Sigmoid,
    /// exp with the input clamped to ≤ [`DENSITY_EXP_CLAMP`]; the gradient
    /// is zero above the clamp.
    ClampedExp,
}

impl Activation {
    pub fn apply<F: Float>(self, x: F) -> F {
        match self {
            Activation::None => x,
            Activation::Relu => x.max(F::zero()),
            Activation::Sigmoid => F::one() / (F::one() + (-x).exp()),
            Activation::ClampedExp => x.min(exp_clamp()).exp(),
        }
    }

    /// The derivative at the input that produced the output `y`. Every
    /// activation here can be differentiated from its output, so the
    /// backward pass needs only the stored outputs: ReLU y > 0; sigmoid
    /// y (1 − y); the clamped exponential y below exp(clamp) and 0 at it
    /// (an input within rounding of the clamp counts as clamped).
    pub fn derivative_from_output<F: Float>(self, y: F) -> F {
        match self {
            Activation::None => F::one(),
            Activation::Relu => {
                if y > F::zero() {
                    F::one()
                } else {
                    F::zero()
                }
            }
            Activation::Sigmoid => y * (F::one() - y),
            Activation::ClampedExp => {
                if y < exp_clamp::<F>().exp() {
                    y
                } else {
                    F::zero()
                }
            }
        }
    }
}

fn exp_clamp<F: Float>() -> F {
    F::from(DENSITY_EXP_CLAMP).expect("representable")
}
/// The arithmetic of a network's matrix products.
#[derive(
    Debug,
    Clone,
    Copy,
    PartialEq,
    Eq,
    Default,
    clap::ValueEnum,
    serde::Serialize,
    serde::Deserialize,
)]
#[serde(rename_all = "lowercase")]
pub enum Precision {
    /// Products and sums in f32.
    #[default]
    F32,
    /// Mixed-precision training: the operands of every product (weights,
    /// activations, gradients) rounded to bf16, the products summed in f32;
    /// master weights, bias, activations, gradient sums and the optimiser
    /// stay f32. Runs on the processor's bf16 dot-product instructions
    /// where it has them (`engine::cpu::dense::mixed_kernels_available`), in f32 elsewhere.
    Mixed,
}

impl Precision {
    pub fn name(self) -> &'static str {
        match self {
            Precision::F32 => "f32",
            Precision::Mixed => "mixed",
        }
    }

    /// What the precision computes, in words.
    pub fn describe(self) -> &'static str {
        match self {
            Precision::F32 => "f32 products and sums",
            Precision::Mixed => "mixed (bf16 products summed in f32, the rest f32)",
        }
    }
}

/// The shape of an MLP: `widths[0]` inputs, `widths.len() − 2` hidden layers,
/// `widths[last]` outputs.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct MlpLayout {
    pub widths: Vec<usize>,
    /// Activation after every layer but the last.
    pub hidden: Activation,
    /// Activation after the last layer.
    pub output: Activation,
    /// Whether every layer has a bias.
    pub bias: bool,
    /// How the products are computed (f32 unless asked otherwise).
    pub precision: Precision,
}

impl MlpLayout {
    pub fn new(widths: Vec<usize>, hidden: Activation, output: Activation, bias: bool) -> Self {
        assert!(
            widths.len() >= 2,
            "an MLP needs an input and an output width"
        );
        assert!(
            widths.iter().all(|&w| w > 0),
            "zero-width layer in {widths:?}"
        );
        Self {
            widths,
            hidden,
            output,
            bias,
            precision: Precision::F32,
        }
    }

    /// The same network with its products computed at `precision`.
    pub fn with_precision(mut self, precision: Precision) -> Self {
        self.precision = precision;
        self
    }
    pub fn layers(&self) -> usize {
        self.widths.len() - 1
    }

    pub fn input_width(&self) -> usize {
        self.widths[0]
    }

    pub fn output_width(&self) -> usize {
        *self.widths.last().expect("at least two widths")
    }

    pub fn activation(&self, layer: usize) -> Activation {
        if layer + 1 == self.layers() {
            self.output
        } else {
            self.hidden
        }
    }

    fn layer_params(&self, layer: usize) -> usize {
        let (i, o) = (self.widths[layer], self.widths[layer + 1]);
        o * i + if self.bias { o } else { 0 }
    }

    /// Where layer `layer`'s weights (`out × in` row-major) start.
    pub fn weight_offset(&self, layer: usize) -> usize {
        (0..layer).map(|l| self.layer_params(l)).sum()
    }

    /// Where layer `layer`'s bias starts, if the layout has biases.
    pub fn bias_offset(&self, layer: usize) -> Option<usize> {
        self.bias
            .then(|| self.weight_offset(layer) + self.widths[layer] * self.widths[layer + 1])
    }

    pub fn param_count(&self) -> usize {
        (0..self.layers()).map(|l| self.layer_params(l)).sum()
    }

    /// Multiply-adds per row of one forward pass.
    pub fn macs_per_row(&self) -> usize {
        self.widths.windows(2).map(|w| w[0] * w[1]).sum()
    }

    /// Initial parameters: weights uniform in ±√(6 / (in + out)) (Glorot &
    /// Bengio 2010, "Xavier uniform", which tiny-cuda-nn's MLPs use),
    /// biases zero.
    pub fn init_params(&self, seed: u64) -> Vec<f32> {
        let mut rng = Pcg32::new(seed, 0x006d_6c70);
        let mut params = vec![0.0; self.param_count()];
        for layer in 0..self.layers() {
            let (i, o) = (self.widths[layer], self.widths[layer + 1]);
            let scale = (6.0 / (i + o) as f32).sqrt();
            let start = self.weight_offset(layer);
            for w in &mut params[start..start + i * o] {
                *w = (2.0 * rng.next_f32() - 1.0) * scale;
            }
        }
        params
    }
}
