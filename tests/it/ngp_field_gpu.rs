//! Instant-NGP's field on the gpu engine (`GpuNgpField`, the field that
//! moves Instant-NGP onto `GpuModel`) against the cpu engine's `NgpField`
//! on lavapipe: σ, colour, σ alone and each part's parameter gradient, for
//! a small hash table, the field's parameters starting at offset 0 and at
//! an offset inside a larger buffer (as a model's second field would).
//!
//! Tolerances are those of tests/it/ngp_gpu.rs's step comparison, whose
//! stages these are: each stage matches the cpu within 1e-4 relative
//! (tests/*_gpu.rs), the chain multiplies a handful of such factors, and
//! relative norms are dominated by the large, well-conditioned entries.
//! The hash table's gradient is summed by many samples into shared
//! entries in another order on the gpu, within the same bound.

use crate::common;

use common::relative_norm;
use zrak::engine::cpu::fields::ngp::NgpField;
use zrak::engine::cpu::fields::{Field, Gradient};
use zrak::engine::gpu::GpuContext;
use zrak::engine::gpu::fields::ngp::GpuNgpField;
use zrak::engine::gpu::fields::{FieldInputs, FieldOutputs, GpuAppearance, GpuField};
use zrak::engine::gpu::kernel::{Recorder, read_buffer, storage_buffer, zeroed_storage_buffer};
use zrak::field::encoding::{HashGridConfig, HashGridLayout};
use zrak::field::ngp::NgpShape;
use zrak::rng::Pcg32;

const ROWS: usize = 512;
const TOLERANCE: f64 = 1e-4;

fn uniform(rng: &mut Pcg32, lo: f32, hi: f32) -> f32 {
    lo + (hi - lo) * rng.next_f32()
}

/// The paper's field with a 2^12-entry table per level (tests/it/hard_cases.rs
/// uses the same): every level hashes, as the paper's finer levels do.
fn small_shape() -> NgpShape {
    let scene = common::small_scene(8);
    let mut shape = NgpShape::for_scene(&scene);
    shape.grid = HashGridLayout::new(&HashGridConfig {
        log2_table_size: 12,
        ..HashGridConfig::paper(scene.unit_cube.aabb_scale)
    });
    shape
}

/// The field's initial parameters with the table's entries in ±0.5
/// instead of ±1e-4, so features, and through them σ and colour, vary
/// from sample to sample.
fn params(shape: &NgpShape, seed: u64) -> Vec<f32> {
    let mut params = shape.init_params(seed);
    let mut rng = Pcg32::new(seed, 3);
    for v in &mut params[shape.grid_range()] {
        *v = uniform(&mut rng, -0.5, 0.5);
    }
    params
}

/// What one engine computed: σ, colour, σ alone, the gradient.
struct Outputs {
    sigma: Vec<f32>,
    rgb: Vec<f32>,
    density: Vec<f32>,
    gradient: Vec<f32>,
}

/// The gpu field's outputs at `inputs` with its parameters at f32 `offset`
/// of a larger buffer (the gradient read back from the same offset).
fn gpu_outputs(
    context: &GpuContext,
    shape: &NgpShape,
    (params, offset): (&[f32], usize),
    inputs: FieldInputs<[f32]>,
    d_sigma: &[f32],
    d_rgb: &[f32],
) -> Outputs {
    let mut field = GpuNgpField::new(context, shape, ROWS).expect("the kernels compile");
    assert_eq!(field.param_count(), params.len());
    field.set_param_offset(offset);
    let mut all = vec![0.25f32; offset];
    all.extend_from_slice(params);
    let params_buffer = storage_buffer(context, "params", &all);
    let gradients = zeroed_storage_buffer::<f32>(context, "gradients", all.len());
    let positions = storage_buffer(context, "positions", inputs.positions);
    let directions = storage_buffer(context, "directions", inputs.directions);
    let inputs = FieldInputs {
        positions: &positions,
        variances: None,
        directions: &directions,
    };
    let d_sigma = storage_buffer(context, "d sigma", d_sigma);
    let d_rgb = storage_buffer(context, "d rgb", d_rgb);
    let sigma = zeroed_storage_buffer::<f32>(context, "sigma", ROWS);
    let rgb = zeroed_storage_buffer::<f32>(context, "rgb", 3 * ROWS);
    let density = zeroed_storage_buffer::<f32>(context, "density", ROWS);

    let mut rec = Recorder::new(context);
    rec.encoder.clear_buffer(&gradients, 0, None);
    let outputs = FieldOutputs {
        sigma: &sigma,
        rgb: &rgb,
    };
    field.record_forward(
        &mut rec,
        &params_buffer,
        inputs,
        GpuAppearance::Mean,
        ROWS,
        outputs,
    );
    field.record_backward(&mut rec, &params_buffer, &d_sigma, &d_rgb, ROWS, &gradients);
    rec.submit();
    let (sigma, rgb) = (
        read_buffer(context, &sigma, ROWS),
        read_buffer(context, &rgb, 3 * ROWS),
    );
    let gradient: Vec<f32> = read_buffer(context, &gradients, all.len());
    assert!(
        gradient[..offset].iter().all(|&g| g == 0.0),
        "the gradient reached parameters before the field's"
    );

    let mut rec = Recorder::new(context);
    field.record_density(&mut rec, &params_buffer, &positions, None, ROWS, &density);
    rec.submit();
    Outputs {
        sigma,
        rgb,
        density: read_buffer(context, &density, ROWS),
        gradient: gradient[offset..].to_vec(),
    }
}

#[test]
fn gpu_ngp_field_matches_the_cpu_field() {
    let _cores = crate::common::shared();
    let shape = small_shape();
    let params = params(&shape, 5);
    let mut rng = Pcg32::new(5, 7);
    // Unit-cube positions (the field's coordinates) and unit directions.
    let positions: Vec<f32> = (0..3 * ROWS).map(|_| rng.next_f32()).collect();
    let mut directions = Vec::with_capacity(3 * ROWS);
    while directions.len() < 3 * ROWS {
        let d: Vec<f32> = (0..3).map(|_| uniform(&mut rng, -1.0, 1.0)).collect();
        let n = d.iter().map(|v| v * v).sum::<f32>().sqrt();
        if (0.1..=1.0).contains(&n) {
            directions.extend(d.iter().map(|v| v / n));
        }
    }
    let d_sigma: Vec<f32> = (0..ROWS).map(|_| uniform(&mut rng, -1.0, 1.0)).collect();
    let d_rgb: Vec<f32> = (0..3 * ROWS)
        .map(|_| uniform(&mut rng, -1.0, 1.0))
        .collect();

    let mut cpu = NgpField::new(shape.clone());
    let (mut sigma, mut rgb) = (vec![0.0; ROWS], vec![0.0; 3 * ROWS]);
    cpu.forward(
        &params,
        &positions,
        None,
        &directions,
        zrak::field::appearance::Appearance::None,
        &mut sigma,
        &mut rgb,
    );
    let mut gradient = vec![0.0; params.len()];
    cpu.backward(&params, &d_sigma, &d_rgb, &mut gradient, Gradient::Add);
    let mut density = vec![0.0; ROWS];
    cpu.density(&params, &positions, None, &mut density);
    let cpu = Outputs {
        sigma,
        rgb,
        density,
        gradient,
    };
    assert!(
        cpu.sigma.iter().any(|&s| s > 1e-3) && cpu.gradient.iter().any(|&g| g != 0.0),
        "the comparison would prove nothing"
    );

    let context = common::gpu_context();
    // 0, and an offset past other parameters that binding offsets allow.
    for offset in [0, 256] {
        let inputs = FieldInputs {
            positions: &positions[..],
            variances: None,
            directions: &directions[..],
        };
        let gpu = gpu_outputs(
            &context,
            &shape,
            (&params, offset),
            inputs,
            &d_sigma,
            &d_rgb,
        );
        let check = |what: &str, g: &[f32], c: &[f32]| {
            let error = relative_norm(g, c);
            eprintln!("offset {offset}, {what}: relative error {error:.2e}");
            assert!(error < TOLERANCE, "offset {offset}, {what}: {error:e}");
        };
        check("σ", &gpu.sigma, &cpu.sigma);
        check("colour", &gpu.rgb, &cpu.rgb);
        check("σ alone", &gpu.density, &cpu.density);
        for (name, range) in [
            ("hash grid", shape.grid_range()),
            ("density network", shape.density_range()),
            ("colour network", shape.colour_range()),
        ] {
            check(
                &format!("{name} gradient"),
                &gpu.gradient[range.clone()],
                &cpu.gradient[range],
            );
        }
    }
}
