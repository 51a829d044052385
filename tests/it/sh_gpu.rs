//! The gpu spherical-harmonics encoding against the cpu on lavapipe.

use zrak::engine::cpu::sh::sh_encode;
use zrak::engine::gpu::GpuContext;
use zrak::engine::gpu::kernel::{Columns, Recorder, read_buffer, storage_buffer};
use zrak::engine::gpu::sh::GpuSh;
use zrak::field::encoding::sh_coefficients;
use zrak::rng::Pcg32;

fn directions(rows: usize) -> Vec<f32> {
    let mut rng = Pcg32::new(5, 1);
    let mut d = Vec::with_capacity(3 * rows);
    // The poles and axes first: zero components must not upset anything.
    for axis in [
        [1.0, 0.0, 0.0],
        [0.0, 1.0, 0.0],
        [0.0, 0.0, 1.0],
        [0.0, 0.0, -1.0],
        [-1.0, 0.0, 0.0],
    ] {
        d.extend(axis);
    }
    while d.len() < 3 * rows {
        let z = 2.0 * rng.next_f32() as f64 - 1.0;
        let phi = std::f64::consts::TAU * rng.next_f32() as f64;
        let s = (1.0 - z * z).sqrt();
        d.extend([(s * phi.cos()) as f32, (s * phi.sin()) as f32, z as f32]);
    }
    d
}

/// Coefficients are below 3 in magnitude and each is a product of at most
/// four f32 roundings on both sides (the constants are the same f32 values):
/// they differ by a few ε·3 ≈ 1e-6 at most, so 1e-6 relative to max(1, |v|)
/// is well within the 1e-4 asked of every gpu stage.
fn close(gpu: f32, cpu: f32) -> bool {
    (gpu - cpu).abs() <= 1e-6 * cpu.abs().max(1.0)
}

#[test]
fn sh_encoding_matches_cpu() {
    let _cores = crate::common::shared();
    let context = GpuContext::new().expect("CI installs mesa-vulkan-drivers, so an adapter exists");
    let sh = GpuSh::new(&context).expect("the kernel compiles");
    let rows = 4001;
    let dirs = directions(rows);
    for degree in 1..=4 {
        let n = sh_coefficients(degree);
        let gpu = sh.encode_once(&context, degree, &dirs, rows);
        let mut cpu = vec![0.0; rows * n];
        sh_encode(degree, &dirs, rows, &mut cpu, n);
        for (i, (&g, &c)) in gpu.iter().zip(&cpu).enumerate() {
            assert!(
                close(g, c),
                "degree {degree}, row {} coefficient {}: gpu {g} cpu {c}",
                i / n,
                i % n
            );
        }
    }
}

#[test]
fn sh_encoding_writes_into_a_wider_matrix() {
    let _cores = crate::common::shared();
    let context = GpuContext::new().expect("an adapter exists");
    let sh = GpuSh::new(&context).expect("the kernel compiles");
    let rows = 3000;
    let dirs = directions(rows);
    // Columns 16..32 of the colour network's 32-wide input; the density
    // features in columns 0..16 must survive.
    let stride = 32;
    let matrix: Vec<f32> = (0..rows * stride).map(|i| -(i as f32)).collect();
    let input = storage_buffer(&context, "directions", &dirs);
    let output = storage_buffer(&context, "matrix", &matrix);
    let mut rec = Recorder::new(&context);
    let columns = Columns {
        buffer: &output,
        stride,
        start: 16,
        width: sh_coefficients(4),
    };
    sh.record_encode(&mut rec, 4, &input, rows, columns);
    rec.submit();
    let gpu: Vec<f32> = read_buffer(&context, &output, rows * stride);
    let mut cpu = matrix.clone();
    sh_encode(4, &dirs, rows, &mut cpu[16..], stride);
    for r in 0..rows {
        for k in 0..stride {
            let (g, c) = (gpu[r * stride + k], cpu[r * stride + k]);
            if k < 16 {
                assert_eq!(
                    g,
                    matrix[r * stride + k],
                    "row {r} column {k} was overwritten"
                );
            } else {
                assert!(close(g, c), "row {r} column {k}: gpu {g} cpu {c}");
            }
        }
    }
}
