use super::*;
use crate::field::encoding::HashGridConfig;
use crate::field::mlp::{DENSITY_EXP_CLAMP, NetworkConfig};
use crate::rng::Pcg32;

fn random(seed: u64, n: usize, scale: f32) -> Vec<f32> {
    let mut rng = Pcg32::new(seed, 7);
    (0..n)
        .map(|_| (2.0 * rng.next_f32() - 1.0) * scale)
        .collect()
}

fn to_f64(x: &[f32]) -> Vec<f64> {
    x.iter().map(|&v| v as f64).collect()
}

fn available_backends() -> Vec<Backend> {
    let mut all = vec![Backend::Portable];
    #[cfg(target_arch = "x86_64")]
    {
        if is_x86_feature_detected!("avx2") && is_x86_feature_detected!("fma") {
            all.push(Backend::Avx2);
        }
        if is_x86_feature_detected!("avx512f")
            && is_x86_feature_detected!("avx2")
            && is_x86_feature_detected!("fma")
        {
            all.push(Backend::Avx512);
        }
    }
    all
}

#[test]
fn layout_offsets_and_counts() {
    let layout = MlpLayout::new(vec![3, 5, 2], Activation::Relu, Activation::None, true);
    assert_eq!(layout.weight_offset(0), 0);
    assert_eq!(layout.bias_offset(0), Some(15));
    assert_eq!(layout.weight_offset(1), 20);
    assert_eq!(layout.bias_offset(1), Some(30));
    assert_eq!(layout.param_count(), 32);
    let ngp = NetworkConfig::PAPER;
    let density = MlpLayout::ngp_density(&ngp, &HashGridConfig::paper(1.0));
    assert_eq!(density.widths, vec![32, 64, 16]);
    assert_eq!(density.param_count(), 32 * 64 + 64 * 16);
    let colour = MlpLayout::ngp_colour(&ngp);
    assert_eq!(colour.widths, vec![32, 64, 64, 3]);
    assert_eq!(colour.bias_offset(0), None);
}

#[test]
fn init_is_xavier_uniform() {
    let layout = MlpLayout::new(vec![32, 64, 16], Activation::Relu, Activation::None, true);
    let p = layout.init_params(3);
    let bound0 = (6.0f32 / 96.0).sqrt();
    let w0 = &p[..32 * 64];
    assert!(w0.iter().all(|w| w.abs() <= bound0));
    // Uniform on ±a has variance a²/3; over 2048 draws the sample
    // variance has a relative standard deviation of about 2.5%, so 10%
    // is four of them.
    let var = w0.iter().map(|w| (w * w) as f64).sum::<f64>() / w0.len() as f64;
    let want = (bound0 * bound0 / 3.0) as f64;
    assert!((var / want - 1.0).abs() < 0.1, "{var} vs {want}");
    assert!(
        p[layout.bias_offset(0).unwrap()..][..64]
            .iter()
            .all(|&b| b == 0.0)
    );
    assert_eq!(p, layout.init_params(3));
    assert_ne!(p, layout.init_params(4));
}

/// L = Σ c ⊙ output with fixed random weights c, so ∂L/∂output = c.
fn loss(layout: &MlpLayout, params: &[f64], input: &[f64], rows: usize, c: &[f64]) -> f64 {
    let out = reference_forward(layout, params, input, rows);
    out[layout.layers() - 1]
        .iter()
        .zip(c)
        .map(|(y, c)| y * c)
        .sum()
}

#[test]
fn reference_gradients_match_central_differences() {
    let cases = [
        MlpLayout::new(
            vec![5, 7, 6, 4],
            Activation::Relu,
            Activation::Sigmoid,
            true,
        ),
        MlpLayout::new(vec![4, 6, 3], Activation::Relu, Activation::None, false),
        MlpLayout::new(
            vec![3, 5, 2],
            Activation::Sigmoid,
            Activation::ClampedExp,
            true,
        ),
    ];
    for (case, layout) in cases.iter().enumerate() {
        let rows = 6;
        let params = to_f64(&random(10 + case as u64, layout.param_count(), 0.8));
        let input = to_f64(&random(20 + case as u64, rows * layout.input_width(), 1.0));
        let c = to_f64(&random(30 + case as u64, rows * layout.output_width(), 1.0));
        let outputs = reference_forward(layout, &params, &input, rows);
        // ReLU has a kink at 0: a central difference straddling it is
        // wrong. With h = 1e-5 and every pre-activation at least 1e-3
        // from 0 (checked), no difference straddles one.
        let h = 1e-5;
        let min_pre = min_abs_hidden_pre_activation(layout, &params, &input, rows);
        assert!(
            min_pre > 1e-3,
            "case {case}: a pre-activation at {min_pre:e} makes the test invalid"
        );
        let (d_params, d_input) = reference_backward(layout, &params, &input, rows, &outputs, &c);
        // Central differences: truncation h²/6·L''' ≈ 2e-11·|L'''|,
        // rounding ε·|L|/h ≈ 2e-11·|L| in f64, with |L|, |L'''| of order
        // 1-10 here. 1e-7 relative, with magnitudes below 1e-2 measured
        // against 1e-2 (an absolute floor of 1e-9), is far above that
        // and far below any wrong or missing term.
        let rel = |a: f64, b: f64| (a - b).abs() / a.abs().max(b.abs()).max(1e-2);
        let mut worst = 0f64;
        for j in 0..params.len() {
            let mut p = params.clone();
            p[j] += h;
            let plus = loss(layout, &p, &input, rows, &c);
            p[j] -= 2.0 * h;
            let minus = loss(layout, &p, &input, rows, &c);
            worst = worst.max(rel(d_params[j], (plus - minus) / (2.0 * h)));
        }
        for j in 0..input.len() {
            let mut x = input.clone();
            x[j] += h;
            let plus = loss(layout, &params, &x, rows, &c);
            x[j] -= 2.0 * h;
            let minus = loss(layout, &params, &x, rows, &c);
            worst = worst.max(rel(d_input[j], (plus - minus) / (2.0 * h)));
        }
        assert!(worst < 1e-7, "case {case}: worst relative error {worst:e}");
    }
}

/// The smallest |pre-activation| of any hidden unit over the batch.
fn min_abs_hidden_pre_activation(
    layout: &MlpLayout,
    params: &[f64],
    input: &[f64],
    rows: usize,
) -> f64 {
    let outputs = reference_forward(layout, params, input, rows);
    let mut min = f64::INFINITY;
    for layer in 0..layout.layers() - 1 {
        let (iw, ow) = (layout.widths[layer], layout.widths[layer + 1]);
        let x = if layer == 0 {
            input
        } else {
            &outputs[layer - 1][..]
        };
        let w = &params[layout.weight_offset(layer)..];
        for r in 0..rows {
            for o in 0..ow {
                let mut s = layout.bias_offset(layer).map_or(0.0, |b| params[b + o]);
                for i in 0..iw {
                    s += w[o * iw + i] * x[r * iw + i];
                }
                min = min.min(s.abs());
            }
        }
    }
    min
}

/// max |a − b| over the tensor, relative to max |b|.
fn max_relative(a: &[f32], b: &[f64]) -> f64 {
    assert_eq!(a.len(), b.len());
    let scale = b.iter().fold(0f64, |m, x| m.max(x.abs())).max(1e-30);
    a.iter()
        .zip(b)
        .fold(0f64, |m, (&x, &y)| m.max((x as f64 - y).abs()))
        / scale
}

#[test]
fn kernels_match_the_reference_on_every_backend() {
    let cases = [
        // Instant-NGP's shapes.
        (
            MlpLayout::new(vec![32, 64, 16], Activation::Relu, Activation::None, false),
            1000,
        ),
        (
            MlpLayout::new(
                vec![32, 64, 64, 3],
                Activation::Relu,
                Activation::Sigmoid,
                false,
            ),
            777,
        ),
        // Widths that are not multiples of any vector width, biases,
        // and more rows than one chunk per block.
        (
            MlpLayout::new(
                vec![37, 21, 70, 5],
                Activation::Relu,
                Activation::ClampedExp,
                true,
            ),
            2500,
        ),
        (
            MlpLayout::new(vec![3, 130, 1], Activation::Sigmoid, Activation::None, true),
            130,
        ),
        (
            MlpLayout::new(vec![8, 8], Activation::Relu, Activation::Relu, true),
            1,
        ),
    ];
    // Every remainder of rows below a tile's height (8 for one vector
    // column, 6 for two, 4 for more), for each panel width.
    let sweep = (1..=17).flat_map(|rows| {
        [
            (
                MlpLayout::new(vec![20, 40, 7], Activation::Relu, Activation::None, true),
                rows,
            ),
            (
                MlpLayout::new(
                    vec![9, 33, 50, 16],
                    Activation::Relu,
                    Activation::Sigmoid,
                    false,
                ),
                64 + rows,
            ),
        ]
    });
    let cases: Vec<(MlpLayout, usize)> = cases.into_iter().chain(sweep).collect();
    for backend in available_backends() {
        for (case, (layout, rows)) in cases.iter().enumerate() {
            let rows = *rows;
            let params = random(100 + case as u64, layout.param_count(), 0.5);
            let input = random(200 + case as u64, rows * layout.input_width(), 1.0);
            let d_out = random(300 + case as u64, rows * layout.output_width(), 1.0);
            let mut ws = MlpWorkspace::new(layout, rows);
            let mut out = vec![0.0; rows * layout.output_width()];
            forward_with(backend, layout, &params, &input, rows, &mut ws, &mut out);
            // Start from nonzero gradients to check that they accumulate.
            let mut d_params = vec![1.0f32; params.len()];
            let mut d_input = vec![f32::NAN; input.len()];
            backward_with(
                backend,
                layout,
                &params,
                &input,
                rows,
                &mut ws,
                MlpGradients {
                    output: &d_out,
                    params: &mut d_params,
                    input: Some(InputGradient::every_column(&mut d_input, layout)),
                },
            );

            let (p64, x64) = (to_f64(&params), to_f64(&input));
            let want = reference_forward(layout, &p64, &x64, rows);
            let (want_dp, want_dx) =
                reference_backward(layout, &p64, &x64, rows, &want, &to_f64(&d_out));
            let want_dp: Vec<f64> = want_dp.iter().map(|g| g + 1.0).collect();
            // Each value is a sum of at most 130 products per layer (the
            // weight gradients: of 2500 rows) in f32 against f64: the
            // worst-case bound n·ε·Σ|terms| is loose; with random signs
            // the error grows like √n·ε ≈ 60·6e-8 ≈ 4e-6 of the
            // tensor's scale for the weight gradients and less for the
            // rest. 2e-5 holds that with margin and fails on any wrong
            // index, missing term or wrong activation.
            let tol = 2e-5;
            for (l, y) in want.iter().enumerate() {
                let e = max_relative(&ws.activations(l)[..rows * layout.widths[l + 1]], y);
                assert!(e < tol, "{backend:?} case {case} layer {l} forward: {e:e}");
            }
            let e = max_relative(&out, &want[layout.layers() - 1]);
            assert!(e < tol, "{backend:?} case {case} output: {e:e}");
            let e = max_relative(&d_params, &want_dp);
            assert!(e < tol, "{backend:?} case {case} d_params: {e:e}");
            let e = max_relative(&d_input, &want_dx);
            assert!(e < tol, "{backend:?} case {case} d_input: {e:e}");

            let out_w = layout.output_width();
            let mut inferred = vec![0.0; out.len()];
            inference_with(backend, layout, &params, &input, rows, &mut inferred, out_w);
            assert_eq!(
                inferred, out,
                "{backend:?} case {case}: inference differs from forward"
            );
            // Only the first output: column 0 of the full forward pass,
            // summed by the narrow kernel where the full pass used a tile
            // (outputs wider than NARROW_COLUMNS), so equal to rounding.
            let mut first = vec![0.0; rows];
            inference_with(backend, layout, &params, &input, rows, &mut first, 1);
            let column: Vec<f64> = want[layout.layers() - 1]
                .chunks_exact(out_w)
                .map(|r| r[0])
                .collect();
            let e = max_relative(&first, &column);
            assert!(e < tol, "{backend:?} case {case} leading output: {e:e}");
            if out_w <= NARROW_COLUMNS {
                let same: Vec<f32> = out.chunks_exact(out_w).map(|r| r[0]).collect();
                assert_eq!(first, same, "{backend:?} case {case}: leading output");
            }
        }
    }
}

#[test]
fn backward_is_deterministic_and_skips_unwanted_input_gradient() {
    let layout = MlpLayout::new(
        vec![32, 64, 64, 3],
        Activation::Relu,
        Activation::Sigmoid,
        false,
    );
    let rows = 5000;
    let params = layout.init_params(9);
    let input = random(1, rows * 32, 1.0);
    let d_out = random(2, rows * 3, 1.0);
    let mut ws = MlpWorkspace::new(&layout, rows);
    let mut out = vec![0.0; rows * 3];
    mlp_forward(&layout, &params, &input, rows, &mut ws, &mut out);
    let mut first = vec![0.0; params.len()];
    mlp_backward(
        &layout,
        &params,
        &input,
        rows,
        &mut ws,
        MlpGradients {
            output: &d_out,
            params: &mut first,
            input: None,
        },
    );
    // On a pool of one thread, the summation order must be the same.
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap();
    let second = pool.install(|| {
        let mut d = vec![0.0; params.len()];
        mlp_backward(
            &layout,
            &params,
            &input,
            rows,
            &mut ws,
            MlpGradients {
                output: &d_out,
                params: &mut d,
                input: None,
            },
        );
        d
    });
    assert_eq!(first, second);
    assert!(first.iter().any(|&g| g != 0.0));

    // The gradient of some input columns only equals those columns of
    // the full input gradient, bit for bit (each element is the same
    // sum in the same order), and the parameter gradients are the same.
    let mut full = vec![0.0; rows * 32];
    let mut d_full = vec![0.0; params.len()];
    mlp_backward(
        &layout,
        &params,
        &input,
        rows,
        &mut ws,
        MlpGradients {
            output: &d_out,
            params: &mut d_full,
            input: Some(InputGradient::every_column(&mut full, &layout)),
        },
    );
    let mut part = vec![0.0; rows * 16];
    let mut d_part = vec![0.0; params.len()];
    mlp_backward(
        &layout,
        &params,
        &input,
        rows,
        &mut ws,
        MlpGradients {
            output: &d_out,
            params: &mut d_part,
            input: Some(InputGradient {
                values: &mut part,
                columns: 3..19,
            }),
        },
    );
    assert_eq!(d_part, d_full);
    for r in 0..rows {
        assert_eq!(
            part[r * 16..(r + 1) * 16],
            full[r * 32 + 3..r * 32 + 19],
            "row {r}"
        );
    }
}

#[test]
fn activations_and_their_derivatives() {
    assert_eq!(Activation::Relu.apply(-2.0f64), 0.0);
    assert_eq!(Activation::Sigmoid.apply(0.0f64), 0.5);
    assert_eq!(
        Activation::ClampedExp.apply(100.0f32),
        DENSITY_EXP_CLAMP.exp()
    );
    assert!(Activation::Sigmoid.apply(-1e4f32) == 0.0 && Activation::Sigmoid.apply(1e4f32) == 1.0);
    let clamp = DENSITY_EXP_CLAMP as f64;
    assert_eq!(
        Activation::ClampedExp.derivative_from_output(Activation::ClampedExp.apply(clamp + 1.0)),
        0.0
    );
    // Away from kinks and the clamp, the derivative from the output
    // matches a central difference (f64, h = 1e-6: error ≈ 1e-10).
    for act in [
        Activation::None,
        Activation::Relu,
        Activation::Sigmoid,
        Activation::ClampedExp,
    ] {
        for x in [-3.0, -0.5, 0.25, 2.0, clamp - 1.0] {
            let h = 1e-6;
            let numeric = (act.apply(x + h) - act.apply(x - h)) / (2.0 * h);
            let analytic = act.derivative_from_output(act.apply(x));
            assert!(
                (numeric - analytic).abs() <= 1e-7 * numeric.abs().max(1.0),
                "{act:?} at {x}"
            );
        }
    }
}
