//! The gpu dense layers against the cpu ones on lavapipe: every layer's
//! output, the parameter gradients and the input gradient.

use zrak::engine::cpu::dense::{
    InputGradient, MlpGradients, MlpWorkspace, mlp_backward, mlp_forward, reference_forward,
};
use zrak::engine::gpu::GpuContext;
use zrak::engine::gpu::dense::GpuDense;
use zrak::field::encoding::HashGridConfig;
use zrak::field::mlp::{Activation, MlpLayout, NetworkConfig};
use zrak::rng::Pcg32;

fn random(rng: &mut Pcg32, n: usize, scale: f32) -> Vec<f32> {
    (0..n)
        .map(|_| (2.0 * rng.next_f32() - 1.0) * scale)
        .collect()
}

/// Pre-activations of the hidden layers of one row, in f64.
fn hidden_pre_activations(layout: &MlpLayout, params: &[f32], row: &[f32]) -> Vec<f64> {
    let p: Vec<f64> = params.iter().map(|&v| v as f64).collect();
    let x: Vec<f64> = row.iter().map(|&v| v as f64).collect();
    let mut pre = Vec::new();
    let mut input = x;
    for layer in 0..layout.layers() - 1 {
        let one = MlpLayout::new(
            layout.widths[layer..layer + 2].to_vec(),
            Activation::None,
            Activation::None,
            layout.bias,
        );
        let start = layout.weight_offset(layer);
        let params = &p[start..start + one.param_count()];
        let z = reference_forward(&one, params, &input, 1).pop().unwrap();
        pre.extend(&z);
        input = z.iter().map(|&v| layout.hidden.apply(v)).collect();
    }
    pre
}

/// Redraws input rows until no hidden ReLU unit sits within 1e-4 of its
/// kink: there the cpu and gpu, whose pre-activations differ by rounding
/// (≤ 64·ε·Σ|w x| ≈ 4e-5 here), could take different sides and the
/// gradients of that row would legitimately differ by order one.
fn inputs_away_from_kinks(
    layout: &MlpLayout,
    params: &[f32],
    rows: usize,
    rng: &mut Pcg32,
) -> Vec<f32> {
    let w = layout.input_width();
    let mut input = Vec::with_capacity(rows * w);
    for _ in 0..rows {
        loop {
            let row = random(rng, w, 1.0);
            if layout.hidden != Activation::Relu
                || hidden_pre_activations(layout, params, &row)
                    .iter()
                    .all(|z| z.abs() > 1e-4)
            {
                input.extend(row);
                break;
            }
        }
    }
    input
}

/// Every element within 1e-4 of the cpu, relative to its own magnitude plus
/// the tensor's root mean square. Both engines sum the same products (64 per
/// output at most, or the rows of a chunk for weight gradients) in f32 in
/// different orders, so each result differs by rounding: about √n·ε of the
/// terms' magnitude (≤ 1e-6 for n = 64; ≈ 3e-6 for 3000 rows), far inside
/// 1e-4. The rms floor covers results that cancel to near zero, where the
/// rounding of the terms is all that is left.
fn assert_close(what: &str, gpu: &[f32], cpu: &[f32]) {
    assert_eq!(gpu.len(), cpu.len(), "{what}: lengths");
    let rms = (cpu.iter().map(|&v| (v as f64).powi(2)).sum::<f64>() / cpu.len() as f64).sqrt();
    assert!(
        rms > 0.0,
        "{what}: all zero, the comparison would prove nothing"
    );
    let mut worst = 0f64;
    for (i, (&g, &c)) in gpu.iter().zip(cpu).enumerate() {
        let e = (g as f64 - c as f64).abs() / (c.abs() as f64 + rms);
        assert!(e <= 1e-4, "{what}[{i}]: gpu {g} cpu {c} (rms {rms:e})");
        worst = worst.max(e);
    }
    eprintln!("{what}: worst relative error {worst:e}");
}

#[test]
fn dense_layers_match_cpu() {
    let _cores = crate::common::shared();
    let context = GpuContext::new().expect("CI installs mesa-vulkan-drivers, so an adapter exists");
    let dense = GpuDense::new(&context).expect("the dense kernels compile");
    let ngp = NetworkConfig::PAPER;
    let cases = [
        (
            MlpLayout::ngp_density(&ngp, &HashGridConfig::paper(1.0)),
            3000,
        ),
        (MlpLayout::ngp_colour(&ngp), 2500),
        // Widths off every tile size, biases, sigmoid hidden layers, and the
        // clamped exponential.
        (
            MlpLayout::new(
                vec![37, 21, 70, 5],
                Activation::Relu,
                Activation::ClampedExp,
                true,
            ),
            1999,
        ),
        (
            MlpLayout::new(vec![3, 40, 2], Activation::Sigmoid, Activation::None, true),
            1000,
        ),
    ];
    let mut rng = Pcg32::new(11, 0);
    for (case, (layout, rows)) in cases.iter().enumerate() {
        let rows = *rows;
        let mut params = layout.init_params(case as u64);
        if layout.bias {
            for layer in 0..layout.layers() {
                let b = layout.bias_offset(layer).unwrap();
                let bias = random(&mut rng, layout.widths[layer + 1], 0.3);
                params[b..b + bias.len()].copy_from_slice(&bias);
            }
        }
        let input = inputs_away_from_kinks(layout, &params, rows, &mut rng);
        let d_output = random(&mut rng, rows * layout.output_width(), 1.0);

        let mut workspace = MlpWorkspace::new(layout, rows);
        let mut output = vec![0.0; rows * layout.output_width()];
        mlp_forward(layout, &params, &input, rows, &mut workspace, &mut output);
        let mut d_params = vec![0.0; params.len()];
        let mut d_input = vec![0.0; input.len()];
        mlp_backward(
            layout,
            &params,
            &input,
            rows,
            &mut workspace,
            MlpGradients {
                output: &d_output,
                params: &mut d_params,
                input: Some(InputGradient::every_column(&mut d_input, layout)),
            },
        );

        let (outputs, gpu_d_params, gpu_d_input) =
            dense.forward_backward_once(&context, layout, &params, &input, rows, &d_output);
        for (l, gpu) in outputs.iter().enumerate() {
            assert_close(
                &format!("case {case} layer {l} output"),
                gpu,
                &workspace.activations(l)[..gpu.len()],
            );
        }
        for layer in 0..layout.layers() {
            let start = layout.weight_offset(layer);
            let n = layout.widths[layer] * layout.widths[layer + 1];
            assert_close(
                &format!("case {case} layer {layer} d_weights"),
                &gpu_d_params[start..start + n],
                &d_params[start..start + n],
            );
            if let Some(b) = layout.bias_offset(layer) {
                let n = layout.widths[layer + 1];
                assert_close(
                    &format!("case {case} layer {layer} d_bias"),
                    &gpu_d_params[b..b + n],
                    &d_params[b..b + n],
                );
            }
        }
        assert_close(&format!("case {case} d_input"), &gpu_d_input, &d_input);

        // The forward-only helper gives the same outputs, and the weight
        // gradients (no atomics) are the same on a second run.
        let again = dense.forward_once(&context, layout, &params, &input, rows);
        assert_eq!(
            &again, &outputs,
            "case {case}: forward differs between runs"
        );
        let (_, d_params_again, _) =
            dense.forward_backward_once(&context, layout, &params, &input, rows, &d_output);
        assert_eq!(
            d_params_again, gpu_d_params,
            "case {case}: gradients differ between runs"
        );
    }
}
