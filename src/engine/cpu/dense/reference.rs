//! The dense networks in plain loops, generic over the float type: the
//! reference the fast kernels and the gpu engine are tested against, and
//! what finite differences run on in f64.

use super::*;

/// The forward pass in plain loops, generic over the float type: the
/// reference the fast kernels and the gpu engine are tested against, and
/// what finite differences run on in f64. Returns every layer's output.
pub fn reference_forward<F: Float>(
    layout: &MlpLayout,
    params: &[F],
    input: &[F],
    rows: usize,
) -> Vec<Vec<F>> {
    let mut outputs: Vec<Vec<F>> = Vec::with_capacity(layout.layers());
    for layer in 0..layout.layers() {
        let (iw, ow) = (layout.widths[layer], layout.widths[layer + 1]);
        let x = if layer == 0 {
            input
        } else {
            &outputs[layer - 1][..]
        };
        let w = &params[layout.weight_offset(layer)..][..iw * ow];
        let act = layout.activation(layer);
        let mut y = vec![F::zero(); rows * ow];
        for r in 0..rows {
            for o in 0..ow {
                let mut s = layout
                    .bias_offset(layer)
                    .map_or(F::zero(), |b| params[b + o]);
                for i in 0..iw {
                    s = s + w[o * iw + i] * x[r * iw + i];
                }
                y[r * ow + o] = act.apply(s);
            }
        }
        outputs.push(y);
    }
    outputs
}

/// The backward pass in plain loops: (parameter gradients, input gradient).
pub fn reference_backward<F: Float>(
    layout: &MlpLayout,
    params: &[F],
    input: &[F],
    rows: usize,
    outputs: &[Vec<F>],
    d_output: &[F],
) -> (Vec<F>, Vec<F>) {
    let mut d_params = vec![F::zero(); params.len()];
    let last = layout.layers() - 1;
    let mut g: Vec<F> = d_output[..rows * layout.output_width()]
        .iter()
        .zip(&outputs[last])
        .map(|(&d, &y)| d * layout.output.derivative_from_output(y))
        .collect();
    for layer in (0..layout.layers()).rev() {
        let (iw, ow) = (layout.widths[layer], layout.widths[layer + 1]);
        let x = if layer == 0 {
            input
        } else {
            &outputs[layer - 1][..]
        };
        let w_off = layout.weight_offset(layer);
        for r in 0..rows {
            for o in 0..ow {
                let go = g[r * ow + o];
                for i in 0..iw {
                    d_params[w_off + o * iw + i] =
                        d_params[w_off + o * iw + i] + go * x[r * iw + i];
                }
                if let Some(b) = layout.bias_offset(layer) {
                    d_params[b + o] = d_params[b + o] + go;
                }
            }
        }
        let mut dx = vec![F::zero(); rows * iw];
        for r in 0..rows {
            for i in 0..iw {
                let mut s = F::zero();
                for o in 0..ow {
                    s = s + g[r * ow + o] * params[w_off + o * iw + i];
                }
                dx[r * iw + i] = if layer > 0 {
                    s * layout.hidden.derivative_from_output(x[r * iw + i])
                } else {
                    s
                };
            }
        }
        g = dx;
    }
    (d_params, g)
}
