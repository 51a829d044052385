//! NeRF's field (Mildenhall et al. 2020, figure 7): frequency encodings of
//! position and direction, an 8 × 256 ReLU trunk with the encoded position
//! entering again after its fifth layer, σ from a linear head on the trunk,
//! and colour from a 256-wide linear feature layer concatenated with the
//! encoded direction → 128 → RGB.
//!
//! The trunk is three dense networks, so each is a fused multi-layer pass of
//! [`super::super::dense`]:
//!
//! ```text
//! γ(x) ──► A: 63 → 256 → 256 → 256 → 256 → 256 (ReLU) ──┐
//!   └────────────────────────────────────────────────────┴► [h | γ(x)]
//! B: 319 → 256 → 256 → 256 (ReLU) → 257 (linear: σ_raw, feature 256)
//! C: [feature | γ(d)] 283 → 128 (ReLU) → 3 (sigmoid)
//! ```
//!
//! B's last layer is the paper's σ head and feature layer side by side (both
//! are linear maps of the same 256 activations). The skip puts h before
//! γ(x), where the reference concatenates γ(x) first: the order of a
//! layer's inputs only permutes its weight columns. Parameters are laid
//! out `[A | B | C]`.

use rayon::prelude::*;

use super::{Appearance, Field, Gradient, set_len};
use crate::engine::cpu::appearance::{KeptAppearance, appearance_backward, write_appearance};
use crate::engine::cpu::dense::{
    InputGradient, MlpGradients, MlpWorkspace, mlp_backward, mlp_forward, mlp_inference,
    mlp_inference_leading,
};
use crate::engine::cpu::frequency;
use crate::field::params::ParamLayout;

/// Rows per rayon task in the copies between the networks.
const ROWS_PER_TASK: usize = 1024;

/// Rows per round of inference, so rendering a whole image keeps its
/// activations small.
const INFERENCE_ROWS: usize = 1 << 14;

use crate::field::nerf::NerfShape;

impl NerfShape {
    /// Widens the sigmoid's colours in place (see `colour_padding`).
    fn pad_colours(&self, rgb: &mut [f32]) {
        let p = self.colour_padding;
        if p != 0.0 {
            for c in rgb.iter_mut() {
                *c = *c * (1.0 + 2.0 * p) - p;
            }
        }
    }

    fn width(&self) -> usize {
        self.trunk_a.output_width()
    }
}

/// What the forward pass keeps for the backward pass.
struct Activations {
    encoded_position: Vec<f32>,
    trunk_a_out: Vec<f32>,
    trunk_b_in: Vec<f32>,
    trunk_b_out: Vec<f32>,
    colour_in: Vec<f32>,
    rows: usize,
    // Gradients, reused.
    d_trunk_b_out: Vec<f32>,
    d_feature: Vec<f32>,
    d_trunk_a_out: Vec<f32>,
    /// The colour gradient through the padding.
    d_colour: Vec<f32>,
    /// Which appearance vector each row took, and the gradient of the
    /// colour network's whole input (fields with embeddings).
    appearance: KeptAppearance,
    d_colour_in: Vec<f32>,
}

/// NeRF's field on the `cpu` engine.
pub struct NerfField {
    shape: NerfShape,
    a: MlpWorkspace,
    b: MlpWorkspace,
    c: MlpWorkspace,
    kept: Activations,
}

impl NerfField {
    pub fn new(shape: NerfShape) -> Self {
        Self {
            a: MlpWorkspace::new(&shape.trunk_a, 0),
            b: MlpWorkspace::new(&shape.trunk_b, 0),
            c: MlpWorkspace::new(&shape.colour, 0),
            shape,
            kept: Activations {
                encoded_position: Vec::new(),
                trunk_a_out: Vec::new(),
                trunk_b_in: Vec::new(),
                trunk_b_out: Vec::new(),
                colour_in: Vec::new(),
                rows: 0,
                d_trunk_b_out: Vec::new(),
                d_feature: Vec::new(),
                d_trunk_a_out: Vec::new(),
                d_colour: Vec::new(),
                appearance: KeptAppearance::default(),
                d_colour_in: Vec::new(),
            },
        }
    }

    pub fn shape(&self) -> &NerfShape {
        &self.shape
    }
}

/// Scratch of inference up to trunk B's input, for one round of rows.
struct TrunkInput {
    encoded: Vec<f32>,
    hidden: Vec<f32>,
    /// [h | γ(x)] per row: trunk B's input.
    b_in: Vec<f32>,
}

impl TrunkInput {
    fn new(shape: &NerfShape, rows: usize) -> Self {
        let (width, enc) = (shape.width(), shape.position.output_width());
        Self {
            encoded: vec![0f32; rows * enc],
            hidden: vec![0f32; rows * width],
            b_in: vec![0f32; rows * (width + enc)],
        }
    }

    /// Encodes `positions` (m × 3), runs trunk A and writes trunk B's input
    /// for the m rows; returns it.
    fn fill(
        &mut self,
        shape: &NerfShape,
        trunk_a: &[f32],
        positions: &[f32],
        variances: Option<&[f32]>,
        m: usize,
    ) -> &[f32] {
        let (width, enc) = (shape.width(), shape.position.output_width());
        frequency::encode(
            &shape.position,
            positions,
            variances,
            &mut self.encoded[..m * enc],
        );
        mlp_inference(
            &shape.trunk_a,
            trunk_a,
            &self.encoded[..m * enc],
            m,
            &mut self.hidden[..m * width],
        );
        concat_rows(
            &self.hidden[..m * width],
            width,
            &self.encoded[..m * enc],
            enc,
            &mut self.b_in[..m * (width + enc)],
        );
        &self.b_in[..m * (width + enc)]
    }
}

/// Writes `[left row | right row]` for every row.
fn concat_rows(left: &[f32], lw: usize, right: &[f32], rw: usize, out: &mut [f32]) {
    let w = lw + rw;
    out.par_chunks_mut(ROWS_PER_TASK * w)
        .zip(left.par_chunks(ROWS_PER_TASK * lw))
        .zip(right.par_chunks(ROWS_PER_TASK * rw))
        .for_each(|((out, left), right)| {
            for ((o, l), r) in out
                .chunks_exact_mut(w)
                .zip(left.chunks_exact(lw))
                .zip(right.chunks_exact(rw))
            {
                o[..lw].copy_from_slice(l);
                o[lw..].copy_from_slice(r);
            }
        });
}

/// Columns `columns` of every row of `src` (`width` wide), into `dst`.
fn take_columns(src: &[f32], width: usize, columns: std::ops::Range<usize>, dst: &mut [f32]) {
    let w = columns.len();
    dst.par_chunks_mut(ROWS_PER_TASK * w)
        .zip(src.par_chunks(ROWS_PER_TASK * width))
        .for_each(|(dst, src)| {
            for (d, s) in dst.chunks_exact_mut(w).zip(src.chunks_exact(width)) {
                d.copy_from_slice(&s[columns.clone()]);
            }
        });
}

impl Field for NerfField {
    fn layout(&self) -> ParamLayout {
        self.shape.layout()
    }

    fn kernels(&self) -> crate::engine::cpu::dense::Backend {
        self.shape.trunk_a.kernels()
    }

    fn density(
        &self,
        params: &[f32],
        positions: &[f32],
        variances: Option<&[f32]>,
        sigma: &mut [f32],
    ) {
        let s = &self.shape;
        let [ra, rb, _] = s.ranges();
        let rows = INFERENCE_ROWS.min(sigma.len().max(1));
        let mut trunk = TrunkInput::new(s, rows);
        for (chunk, (positions, sigma)) in positions
            .chunks(3 * rows)
            .zip(sigma.chunks_mut(rows))
            .enumerate()
        {
            let m = sigma.len();
            let variances = variances.map(|v| &v[3 * rows * chunk..][..3 * m]);
            let b_in = trunk.fill(s, &params[ra.clone()], positions, variances, m);
            mlp_inference_leading(&s.trunk_b, &params[rb.clone()], b_in, m, sigma, 1);
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
        directions: &[f32],
        appearance: Appearance<'_>,
        sigma: &mut [f32],
        rgb: &mut [f32],
    ) {
        let s = &self.shape;
        let [ra, rb, rc] = s.ranges();
        let n = sigma.len();
        let (width, enc, enc_dir) = (
            s.width(),
            s.position.output_width(),
            s.direction.output_width(),
        );
        let k = &mut self.kept;
        k.rows = n;
        set_len(&mut k.encoded_position, n * enc);
        frequency::encode(&s.position, positions, variances, &mut k.encoded_position);
        set_len(&mut k.trunk_a_out, n * width);
        self.a.reserve(n);
        mlp_forward(
            &s.trunk_a,
            &params[ra],
            &k.encoded_position,
            n,
            &mut self.a,
            &mut k.trunk_a_out,
        );
        set_len(&mut k.trunk_b_in, n * (width + enc));
        concat_rows(
            &k.trunk_a_out,
            width,
            &k.encoded_position,
            enc,
            &mut k.trunk_b_in,
        );
        set_len(&mut k.trunk_b_out, n * (width + 1));
        self.b.reserve(n);
        mlp_forward(
            &s.trunk_b,
            &params[rb],
            &k.trunk_b_in,
            n,
            &mut self.b,
            &mut k.trunk_b_out,
        );
        for (sigma, row) in sigma.iter_mut().zip(k.trunk_b_out.chunks_exact(width + 1)) {
            *sigma = s.density.apply(row[0]);
        }
        // The colour network's input: the feature columns, then γ(d), then
        // the appearance vector where the field has embeddings.
        let colour_width = s.colour.input_width();
        set_len(&mut k.colour_in, n * colour_width);
        let mut encoded_direction = vec![0f32; n * enc_dir];
        frequency::encode(&s.direction, directions, None, &mut encoded_direction);
        k.colour_in
            .par_chunks_mut(ROWS_PER_TASK * colour_width)
            .zip(k.trunk_b_out.par_chunks(ROWS_PER_TASK * (width + 1)))
            .zip(encoded_direction.par_chunks(ROWS_PER_TASK * enc_dir))
            .for_each(|((out, b), d)| {
                for ((o, b), d) in out
                    .chunks_exact_mut(colour_width)
                    .zip(b.chunks_exact(width + 1))
                    .zip(d.chunks_exact(enc_dir))
                {
                    o[..width].copy_from_slice(&b[1..]);
                    o[width..width + enc_dir].copy_from_slice(d);
                }
            });
        if let Some(table) = &s.appearance {
            write_appearance(
                table,
                &params[s.appearance_range()],
                appearance,
                &mut k.colour_in,
                colour_width,
                width + enc_dir,
                Some(&mut k.appearance),
            );
        }
        self.c.reserve(n);
        mlp_forward(&s.colour, &params[rc], &k.colour_in, n, &mut self.c, rgb);
        s.pad_colours(rgb);
    }

    fn backward(
        &mut self,
        params: &[f32],
        d_sigma: &[f32],
        d_rgb: &[f32],
        gradients: &mut [f32],
        mode: Gradient,
    ) {
        // The networks' backward passes add to their gradients.
        if mode == Gradient::Overwrite {
            gradients.fill(0.0);
        }
        let s = &self.shape;
        let [ra, rb, rc] = s.ranges();
        let k = &mut self.kept;
        let n = k.rows;
        assert!(
            d_sigma.len() == n && d_rgb.len() == 3 * n,
            "gradients of {n} samples"
        );
        let width = s.width();
        // Through the widening of the colours: a constant factor.
        let d_rgb = if s.colour_padding != 0.0 {
            let scale = 1.0 + 2.0 * s.colour_padding;
            set_len(&mut k.d_colour, 3 * n);
            for (out, &g) in k.d_colour.iter_mut().zip(d_rgb) {
                *out = g * scale;
            }
            &k.d_colour[..]
        } else {
            d_rgb
        };
        let (grad_a, rest) = gradients.split_at_mut(ra.end);
        let (grad_b, rest) = rest.split_at_mut(rb.len());
        let (grad_c, grad_appearance) = rest.split_at_mut(rc.len());
        set_len(&mut k.d_feature, n * width);
        match &s.appearance {
            // Colour network; the input gradient of its feature columns
            // only (the direction encoding has no parameters).
            None => mlp_backward(
                &s.colour,
                &params[rc],
                &k.colour_in,
                n,
                &mut self.c,
                MlpGradients {
                    output: d_rgb,
                    params: grad_c,
                    input: Some(InputGradient {
                        values: &mut k.d_feature,
                        columns: 0..width,
                    }),
                },
            ),
            // And of the appearance columns, after the direction's: the
            // whole input's gradient, split.
            Some(table) => {
                let colour_width = s.colour.input_width();
                set_len(&mut k.d_colour_in, n * colour_width);
                mlp_backward(
                    &s.colour,
                    &params[rc],
                    &k.colour_in,
                    n,
                    &mut self.c,
                    MlpGradients {
                        output: d_rgb,
                        params: grad_c,
                        input: Some(InputGradient::every_column(&mut k.d_colour_in, &s.colour)),
                    },
                );
                take_columns(&k.d_colour_in, colour_width, 0..width, &mut k.d_feature);
                appearance_backward(
                    table,
                    &k.appearance,
                    &k.d_colour_in,
                    colour_width,
                    width + s.direction.output_width(),
                    grad_appearance,
                );
            }
        }
        // [dσ_raw | d feature] for trunk B's output.
        set_len(&mut k.d_trunk_b_out, n * (width + 1));
        let density = s.density;
        k.d_trunk_b_out
            .par_chunks_mut(ROWS_PER_TASK * (width + 1))
            .zip(k.d_feature.par_chunks(ROWS_PER_TASK * width))
            .zip(k.trunk_b_out.par_chunks(ROWS_PER_TASK * (width + 1)))
            .zip(d_sigma.par_chunks(ROWS_PER_TASK))
            .for_each(|(((out, feature), raw), d_sigma)| {
                for (((o, f), raw), &ds) in out
                    .chunks_exact_mut(width + 1)
                    .zip(feature.chunks_exact(width))
                    .zip(raw.chunks_exact(width + 1))
                    .zip(d_sigma)
                {
                    o[0] = ds * density.derivative(raw[0]);
                    o[1..].copy_from_slice(f);
                }
            });
        set_len(&mut k.d_trunk_a_out, n * width);
        mlp_backward(
            &s.trunk_b,
            &params[rb],
            &k.trunk_b_in,
            n,
            &mut self.b,
            MlpGradients {
                output: &k.d_trunk_b_out,
                params: grad_b,
                input: Some(InputGradient {
                    values: &mut k.d_trunk_a_out,
                    columns: 0..width,
                }),
            },
        );
        mlp_backward(
            &s.trunk_a,
            &params[ra],
            &k.encoded_position,
            n,
            &mut self.a,
            MlpGradients {
                output: &k.d_trunk_a_out,
                params: grad_a,
                input: None,
            },
        );
    }

    fn radiance(
        &self,
        params: &[f32],
        positions: &[f32],
        variances: Option<&[f32]>,
        directions: &[f32],
        appearance: Appearance<'_>,
        sigma: &mut [f32],
        rgb: &mut [f32],
    ) {
        let s = &self.shape;
        let [ra, rb, rc] = s.ranges();
        let (width, enc_dir) = (s.width(), s.direction.output_width());
        // The vector every sample takes, where the field has embeddings:
        // a render's samples share one.
        let shared = s.appearance.map(|table| {
            (
                table,
                table.shared_vector(&params[s.appearance_range()], appearance),
            )
        });
        let rows = INFERENCE_ROWS.min(sigma.len().max(1));
        let mut trunk = TrunkInput::new(s, rows);
        let mut feature = vec![0f32; rows * width];
        let mut b_out = vec![0f32; rows * (width + 1)];
        let mut encoded_direction = vec![0f32; rows * enc_dir];
        let mut colour_in = vec![0f32; rows * (width + enc_dir)];
        let mut widened = Vec::new();
        for (chunk, (((positions, directions), sigma), rgb)) in positions
            .chunks(3 * rows)
            .zip(directions.chunks(3 * rows))
            .zip(sigma.chunks_mut(rows))
            .zip(rgb.chunks_mut(3 * rows))
            .enumerate()
        {
            let m = sigma.len();
            let variances = variances.map(|v| &v[3 * rows * chunk..][..3 * m]);
            let b_in = trunk.fill(s, &params[ra.clone()], positions, variances, m);
            mlp_inference(
                &s.trunk_b,
                &params[rb.clone()],
                b_in,
                m,
                &mut b_out[..m * (width + 1)],
            );
            for (sigma, row) in sigma.iter_mut().zip(b_out.chunks_exact(width + 1)) {
                *sigma = s.density.apply(row[0]);
            }
            frequency::encode(
                &s.direction,
                directions,
                None,
                &mut encoded_direction[..m * enc_dir],
            );
            take_columns(
                &b_out[..m * (width + 1)],
                width + 1,
                1..width + 1,
                &mut feature[..m * width],
            );
            concat_rows(
                &feature[..m * width],
                width,
                &encoded_direction[..m * enc_dir],
                enc_dir,
                &mut colour_in[..m * (width + enc_dir)],
            );
            let colour_in = match &shared {
                None => &colour_in[..m * (width + enc_dir)],
                Some((table, vector)) => {
                    let colour_width = width + enc_dir + table.width;
                    set_len(&mut widened, m * colour_width);
                    for ((out, row), image) in widened
                        .chunks_exact_mut(colour_width)
                        .zip(colour_in.chunks_exact(width + enc_dir))
                        .zip(0..)
                    {
                        out[..width + enc_dir].copy_from_slice(row);
                        let vector = match (vector, appearance) {
                            (Some(vector), _) => &vector[..],
                            (None, Appearance::PerSample(images)) => {
                                let row = images[chunk * rows + image] as usize;
                                &params[s.appearance_range()][row * table.width..][..table.width]
                            }
                            (None, _) => unreachable!("only per-sample appearance varies"),
                        };
                        out[width + enc_dir..].copy_from_slice(vector);
                    }
                    &widened[..]
                }
            };
            mlp_inference(&s.colour, &params[rc.clone()], colour_in, m, rgb);
            s.pad_colours(rgb);
        }
    }

    fn appearance(&self) -> Option<crate::field::appearance::AppearanceShape> {
        self.shape.appearance
    }

    fn macs_per_sample(&self) -> usize {
        self.shape.macs_per_sample()
    }

    fn density_macs_per_sample(&self) -> usize {
        self.shape.density_macs_per_sample()
    }

    fn workspace_bytes(&self) -> usize {
        let k = &self.kept;
        4 * [
            &k.encoded_position,
            &k.trunk_a_out,
            &k.trunk_b_in,
            &k.trunk_b_out,
            &k.colour_in,
            &k.d_trunk_b_out,
            &k.d_feature,
            &k.d_trunk_a_out,
            &k.d_colour,
            &k.d_colour_in,
        ]
        .iter()
        .map(|v| v.capacity())
        .sum::<usize>()
            + self.a.bytes()
            + self.b.bytes()
            + self.c.bytes()
            + k.appearance.bytes()
    }
}
