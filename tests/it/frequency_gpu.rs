//! The gpu frequency encoding (and its integrated form) against the cpu on
//! lavapipe.
//!
//! Tolerance. Both engines form the angle 2^ℓ·x exactly (a power-of-two
//! scaling), so they differ only by their sin, cos and exp. WGSL promises
//! sin/cos only to 2^-11 absolute inside [−π, π] and nothing outside, so
//! what lavapipe does with large angles was measured (20 000 rows, |x| ≤ 4,
//! ℓ < 24, against glibc's sinf/cosf): the worst difference is 6e-8 (half
//! an ulp near 1) for every angle below 2^22, 1.2e-7 in [2^22, 2^23), 4e-5
//! in [2^23, 2^24) and 0.03 above. The inputs below keep every angle below
//! 2^17 (|x| ≤ 4 at ℓ ≤ 15, Mip-NeRF's Blender coordinates), where lavapipe
//! is accurate to rounding. The damping exp(−t) adds WGSL's exp error,
//! (3 + 2t) ulp relative, i.e. ≤ w·(3 + 2t)·6e-8 ≤ 2.2e-7 absolute since
//! w·t = t·e^(−t) ≤ 1/e. So 1e-6 absolute bounds the difference with a
//! factor of ~3 over WGSL's own exp bound and ~8 over the measured sin/cos
//! one, and is far below what a wrong frequency, layout or damping would
//! give (order 1e-2 or more). This says nothing about real GPUs, whose
//! sin/cos may be much worse for large angles.

use zrak::engine::cpu::frequency::encode;
use zrak::engine::gpu::GpuContext;
use zrak::engine::gpu::frequency::GpuFrequency;
use zrak::field::encoding::FrequencyEncoding;
use zrak::rng::Pcg32;

const TOLERANCE: f32 = 1e-6;

/// NeRF's position and direction encodings (bmild/nerf `run_nerf.py`,
/// `multires` 10 and `multires_views` 4, with the input) and Mip-NeRF's
/// position encoding (google/mipnerf `internal/models.py`, degrees 0..16,
/// no input).
const NERF_POSITION: FrequencyEncoding = FrequencyEncoding {
    frequencies: 10,
    include_input: true,
};
const NERF_DIRECTION: FrequencyEncoding = FrequencyEncoding {
    frequencies: 4,
    include_input: true,
};
const MIP_POSITION: FrequencyEncoding = FrequencyEncoding {
    frequencies: 16,
    include_input: false,
};

fn uniform(rng: &mut Pcg32, lo: f64, hi: f64) -> f64 {
    lo + (hi - lo) * rng.next_f32() as f64
}

fn points(seed: u64, rows: usize, range: f64) -> Vec<f32> {
    let mut rng = Pcg32::new(seed, 1);
    (0..3 * rows)
        .map(|_| uniform(&mut rng, -range, range) as f32)
        .collect()
}

/// Compares every value; the raw input columns must be copied bit for bit.
fn compare(encoding: &FrequencyEncoding, gpu: &[f32], cpu: &[f32], what: &str) {
    assert_eq!(gpu.len(), cpu.len(), "{what}: lengths");
    let w = encoding.output_width();
    let first = 3 * encoding.include_input as usize;
    for (i, (&g, &c)) in gpu.iter().zip(cpu).enumerate() {
        let (r, k) = (i / w, i % w);
        if k < first {
            assert_eq!(g, c, "{what}: row {r} input column {k}");
        } else {
            assert!(
                g.is_finite() && (g - c).abs() <= TOLERANCE,
                "{what}: row {r} column {k}: gpu {g} cpu {c}"
            );
        }
    }
}

fn cpu_encode(encoding: &FrequencyEncoding, x: &[f32], v: Option<&[f32]>) -> Vec<f32> {
    let mut out = vec![0.0; x.len() / 3 * encoding.output_width()];
    encode(encoding, x, v, &mut out);
    out
}

#[test]
fn nerf_encodings_match_cpu() {
    let _cores = crate::common::shared();
    let context = GpuContext::new().expect("CI installs mesa-vulkan-drivers, so an adapter exists");
    let frequency = GpuFrequency::new(&context).expect("the kernels compile");
    let rows = 4001;
    // Positions in the Blender scenes' box, directions' components in
    // [−1, 1]; a zero row checks sin 0 = 0 and cos 0 = 1.
    for (encoding, range) in [(NERF_POSITION, 1.5), (NERF_DIRECTION, 1.0)] {
        let mut x = points(1, rows, range);
        x[..3].fill(0.0);
        let gpu = frequency.encode(&context, &encoding, &x, None);
        compare(
            &encoding,
            &gpu,
            &cpu_encode(&encoding, &x, None),
            &format!("{encoding:?}"),
        );
    }
}

#[test]
fn integrated_encoding_matches_cpu() {
    let _cores = crate::common::shared();
    let context = GpuContext::new().expect("an adapter exists");
    let frequency = GpuFrequency::new(&context).expect("the kernels compile");
    let rows = 4001;
    let x = points(2, rows, 4.0);
    let mut rng = Pcg32::new(3, 1);
    // Log-uniform over 1e-8..10: from barely damped at ℓ = 15 to damped to
    // nothing at ℓ = 0; then the extremes, which must give finite values
    // (σ² = 0 the plain encoding, the huge ones zeros).
    let mut v: Vec<f32> = (0..3 * rows)
        .map(|_| uniform(&mut rng, 1e-8f64.ln(), 10f64.ln()).exp() as f32)
        .collect();
    for (r, var) in [0.0, 1e-30, 1e30, f32::MAX, f32::INFINITY]
        .into_iter()
        .enumerate()
    {
        v[3 * r..3 * r + 3].fill(var);
    }
    let with_input = FrequencyEncoding {
        include_input: true,
        ..MIP_POSITION
    };
    for encoding in [MIP_POSITION, with_input] {
        let gpu = frequency.encode(&context, &encoding, &x, Some(&v));
        compare(
            &encoding,
            &gpu,
            &cpu_encode(&encoding, &x, Some(&v)),
            &format!("{encoding:?} with variance"),
        );
    }
    // Undamped, all 16 frequencies: angles up to 2^17, still within what
    // lavapipe computes to rounding (see the module documentation).
    let gpu = frequency.encode(&context, &MIP_POSITION, &x, None);
    compare(
        &MIP_POSITION,
        &gpu,
        &cpu_encode(&MIP_POSITION, &x, None),
        "Mip-NeRF's frequencies without variance",
    );
}

#[test]
fn more_rows_than_one_dispatch_dimension_holds() {
    let _cores = crate::common::shared();
    let context = GpuContext::new().expect("an adapter exists");
    let frequency = GpuFrequency::new(&context).expect("the kernels compile");
    // 65535 workgroups of 64 rows and then some: the grid must go 2-D and
    // the shader must flatten it back to the right rows. One frequency
    // without the input keeps the output (100 MB) in one storage binding,
    // so this is the 2-D grid and not the piecewise binding at work.
    let rows = 65535 * 64 + 1000;
    let encoding = FrequencyEncoding {
        frequencies: 1,
        include_input: false,
    };
    let x = points(4, rows, 4.0);
    let v: Vec<f32> = points(5, rows, 1.0).iter().map(|a| a * a).collect();
    let gpu = frequency.encode(&context, &encoding, &x, Some(&v));
    compare(
        &encoding,
        &gpu,
        &cpu_encode(&encoding, &x, Some(&v)),
        "a 2-D grid",
    );
}
