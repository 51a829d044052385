//! Frequency (positional) encoding of 3-D points, NeRF's γ(p), and its
//! integrated form for Gaussians, Mip-NeRF's IPE. One stage serves both, as
//! nerfstudio's `NeRFEncoding` does: the IPE is the ordinary encoding with
//! every sinusoid damped by the variance.
//!
//! Ordinary encoding (Mildenhall et al. 2020, §5.1, eq. 4, as implemented in
//! bmild/nerf `run_nerf_helpers.py`, `Embedder`): for each coordinate x and
//! ℓ = 0 … L − 1, the pair sin(2^ℓ x), cos(2^ℓ x). The paper writes
//! sin(2^ℓ π p); the reference code has no π (its frequency bands are
//! `2.**linspace(0, L-1, L)`) and keeps the raw input in front. We follow the
//! code: NeRF's position (L = 10, with input) is 63 wide, its direction
//! (L = 4, with input) 27.
//!
//! Integrated encoding (Barron et al. 2021, §3.1, eq. 14, as implemented in
//! google/mipnerf `internal/mip.py`, `integrated_pos_enc` and
//! `expected_sin`): for a Gaussian of mean μ and diagonal variance σ² per
//! coordinate, E[sin(2^ℓ x)] = sin(2^ℓ μ) · exp(−½ · 4^ℓ · σ²) and the same
//! for cos (the characteristic function of a Gaussian). Mip-NeRF uses
//! ℓ = 0 … 15 without the raw input: 96 values.
//!
//! Layout of one output row: `[x y z]` when the input is included, then for
//! ℓ = 0 … L − 1 the six values `[sin(2^ℓ x), sin(2^ℓ y), sin(2^ℓ z),
//! cos(2^ℓ x), cos(2^ℓ y), cos(2^ℓ z)]`. This is `Embedder`'s order. mip.py
//! orders the same 6L values differently (all sines, ℓ-major, then all
//! cosines); the network learns either equally, but weights trained by the
//! reference code would need their input columns permuted.
//!
//! Accuracy. The angle is formed as `x · 2^ℓ`: multiplying by a power of two
//! only changes the exponent, so (short of overflow, impossible here: the
//! largest factor is 2^31 and any finite |x| < 2^96 stays finite) the angle
//! is the exact real number 2^ℓ·x, and the only error in sin/cos is the
//! library function's own rounding (Rust's `sin`/`cos` call the platform
//! libm, which reduces large arguments exactly; glibc's `sinf`/`cosf` are
//! within 1 ulp for every finite input). Forming the angle with π, or by the
//! double-angle recurrence sin 2a = 2 sin a cos a, would add an error that
//! grows with 2^ℓ·|x| — at ℓ = 15 and |x| ≈ 4 (Mip-NeRF's world
//! coordinates) an angle near 1.3·10⁵, where one f32 ulp of the angle is
//! already 0.008. What remains is the input's own rounding, amplified by
//! 2^ℓ, which no encoding can undo. The damping factor's exponent
//! −½·4^ℓ·σ² is again a power of two times σ², so it is exact too; exp of it
//! is 1 for σ² = 0 and underflows cleanly to 0 for large σ² — including
//! σ² = f32::MAX, where the product overflows to +∞ and exp(−∞) = 0 — so no
//! NaN can arise from a non-negative variance.

use num_traits::Float;
use rayon::prelude::*;

use crate::field::encoding::{FrequencyEncoding, MAX_FREQUENCIES};

impl FrequencyEncoding {
    /// Column of the first sinusoid (after the raw input, if any).
    const fn first_sinusoid(&self) -> usize {
        3 * self.include_input as usize
    }

    fn check(&self) {
        assert!(
            self.frequencies <= MAX_FREQUENCIES,
            "{} frequencies, at most {MAX_FREQUENCIES} supported",
            self.frequencies
        );
    }
}

/// Rows per parallel task: large enough that task overhead is negligible
/// (a row costs 6L sin/cos, ~1 µs at L = 16), small enough to spread a
/// batch of tens of thousands of samples over the cores.
const TASK_ROWS: usize = 2048;

/// 2^ℓ and ½·4^ℓ = 2^(2ℓ−1) for ℓ < [`MAX_FREQUENCIES`], exact in any float
/// type with at least 8 exponent bits.
fn scales<F: Float>(frequencies: u32) -> Vec<(F, F)> {
    (0..frequencies as i32)
        .map(|l| {
            let two = 2f64.powi(l);
            (
                F::from(two).expect("power of two"),
                F::from(0.5 * two * two).expect("power of two"),
            )
        })
        .collect()
}

/// One row of [`encode`].
fn encode_row<F: Float>(
    encoding: &FrequencyEncoding,
    scales: &[(F, F)],
    x: &[F],
    variance: Option<&[F]>,
    out: &mut [F],
) {
    let mut o = 0;
    if encoding.include_input {
        out[..3].copy_from_slice(&x[..3]);
        o = 3;
    }
    for &(scale, half_square) in scales {
        for a in 0..3 {
            // Exact: see the module documentation.
            let angle = x[a] * scale;
            let (s, c) = (angle.sin(), angle.cos());
            match variance {
                Some(v) => {
                    // mip.py `expected_sin`: exp(−½ · var(2^ℓ x)).
                    let damping = (-(half_square * v[a])).exp();
                    out[o + a] = s * damping;
                    out[o + 3 + a] = c * damping;
                }
                None => {
                    out[o + a] = s;
                    out[o + 3 + a] = c;
                }
            }
        }
        o += 6;
    }
}

/// One row of [`encode_backward`]: the derivatives of
/// w·sin(2^ℓ x) and w·cos(2^ℓ x), w = exp(−½·4^ℓ·σ²), are
/// ∂/∂x = 2^ℓ·w·cos and −2^ℓ·w·sin, ∂/∂σ² = −½·4^ℓ·(w·sin) and
/// −½·4^ℓ·(w·cos). The σ² terms multiply the already damped value, so a
/// damping that underflowed to 0 gives 0, never ∞·0.
fn backward_row<F: Float>(
    encoding: &FrequencyEncoding,
    scales: &[(F, F)],
    x: &[F],
    variance: Option<&[F]>,
    d_out: &[F],
    d_x: &mut [F],
    d_variance: Option<&mut [F]>,
) {
    let mut gx = [F::zero(); 3];
    let mut gv = [F::zero(); 3];
    if encoding.include_input {
        gx.copy_from_slice(&d_out[..3]);
    }
    let mut o = encoding.first_sinusoid();
    for &(scale, half_square) in scales {
        for a in 0..3 {
            let angle = x[a] * scale;
            let (s, c) = (angle.sin(), angle.cos());
            let (us, uc) = (d_out[o + a], d_out[o + 3 + a]);
            match variance {
                Some(v) => {
                    let damping = (-(half_square * v[a])).exp();
                    let (ws, wc) = (s * damping, c * damping);
                    gx[a] = gx[a] + scale * (us * wc - uc * ws);
                    gv[a] = gv[a] - half_square * (us * ws + uc * wc);
                }
                None => gx[a] = gx[a] + scale * (us * c - uc * s),
            }
        }
        o += 6;
    }
    d_x[..3].copy_from_slice(&gx);
    if let Some(d_v) = d_variance {
        d_v[..3].copy_from_slice(&gv);
    }
}

/// Encodes n points. `inputs` is n×3 row-major; `variance` is n×3 (the
/// diagonal variance of each coordinate, non-negative) for the integrated
/// encoding or `None` for the ordinary one; `out` is n×W,
/// W = [`FrequencyEncoding::output_width`], in the layout of the module
/// documentation. With a variance, each sinusoid of frequency 2^ℓ is
/// multiplied by exp(−½·4^ℓ·var) and the raw input (if included) is the mean.
///
/// Parallel over blocks of rows; every row is computed by one thread in a
/// fixed order, so the result does not depend on the number of threads.
pub fn encode<F: Float + Send + Sync>(
    encoding: &FrequencyEncoding,
    inputs: &[F],
    variance: Option<&[F]>,
    out: &mut [F],
) {
    encoding.check();
    let width = encoding.output_width();
    let rows = inputs.len() / 3;
    assert_eq!(inputs.len(), 3 * rows, "inputs are not rows of 3");
    assert_eq!(out.len(), width * rows, "out is not {rows} rows of {width}");
    if let Some(v) = variance {
        assert_eq!(v.len(), inputs.len(), "variance and inputs differ in size");
    }
    if width == 0 {
        return;
    }
    let scales = scales::<F>(encoding.frequencies);
    out.par_chunks_mut(TASK_ROWS * width)
        .enumerate()
        .for_each(|(t, block)| {
            for (i, row) in block.chunks_exact_mut(width).enumerate() {
                let r = t * TASK_ROWS + i;
                let x = &inputs[3 * r..3 * r + 3];
                let v = variance.map(|v| &v[3 * r..3 * r + 3]);
                encode_row(encoding, &scales, x, v, row);
            }
        });
}

/// Gradients of a loss through [`encode`]: given its gradient `d_out`
/// (n×W) with respect to the encoding, writes (overwrites) `d_inputs` (n×3)
/// and, when given, `d_variance` (n×3). `d_variance` is only meaningful
/// with a `variance`; without one it is written with zeros.
pub fn encode_backward<F: Float + Send + Sync>(
    encoding: &FrequencyEncoding,
    inputs: &[F],
    variance: Option<&[F]>,
    d_out: &[F],
    d_inputs: &mut [F],
    d_variance: Option<&mut [F]>,
) {
    encoding.check();
    let width = encoding.output_width();
    let rows = inputs.len() / 3;
    assert_eq!(inputs.len(), 3 * rows, "inputs are not rows of 3");
    assert_eq!(
        d_out.len(),
        width * rows,
        "d_out is not {rows} rows of {width}"
    );
    assert_eq!(d_inputs.len(), 3 * rows, "d_inputs is not {rows} rows of 3");
    if let Some(v) = variance {
        assert_eq!(v.len(), inputs.len(), "variance and inputs differ in size");
    }
    let scales = scales::<F>(encoding.frequencies);
    let task = |t: usize, d_x: &mut [F], mut d_v: Option<&mut [F]>| {
        for i in 0..d_x.len() / 3 {
            let r = t * TASK_ROWS + i;
            backward_row(
                encoding,
                &scales,
                &inputs[3 * r..3 * r + 3],
                variance.map(|v| &v[3 * r..3 * r + 3]),
                &d_out[width * r..width * (r + 1)],
                &mut d_x[3 * i..3 * i + 3],
                d_v.as_deref_mut().map(|d| &mut d[3 * i..3 * i + 3]),
            );
        }
    };
    match d_variance {
        Some(d_v) => {
            assert_eq!(d_v.len(), 3 * rows, "d_variance is not {rows} rows of 3");
            d_inputs
                .par_chunks_mut(3 * TASK_ROWS)
                .zip(d_v.par_chunks_mut(3 * TASK_ROWS))
                .enumerate()
                .for_each(|(t, (d_x, d_v))| task(t, d_x, Some(d_v)));
        }
        None => d_inputs
            .par_chunks_mut(3 * TASK_ROWS)
            .enumerate()
            .for_each(|(t, d_x)| task(t, d_x, None)),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Pcg32;

    /// NeRF's position and direction encodings (bmild/nerf `run_nerf.py`:
    /// `multires` 10, `multires_views` 4, `include_input` True) and
    /// Mip-NeRF's position encoding (google/mipnerf `internal/models.py`:
    /// `min_deg_point` 0, `max_deg_point` 16, no identity).
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

    /// n×3 values uniform in [−range, range], rounded to f32.
    fn points(seed: u64, n: usize, range: f64) -> Vec<f32> {
        let mut rng = Pcg32::new(seed, 11);
        (0..3 * n)
            .map(|_| uniform(&mut rng, -range, range) as f32)
            .collect()
    }

    /// n×3 variances log-uniform in [lo, hi].
    fn variances(seed: u64, n: usize, lo: f64, hi: f64) -> Vec<f32> {
        let mut rng = Pcg32::new(seed, 12);
        (0..3 * n)
            .map(|_| (uniform(&mut rng, lo.ln(), hi.ln())).exp() as f32)
            .collect()
    }

    /// The formula written out independently of the code under test, in f64:
    /// entry k of one row.
    fn formula(encoding: &FrequencyEncoding, x: [f64; 3], v: Option<[f64; 3]>, k: usize) -> f64 {
        if encoding.include_input && k < 3 {
            return x[k];
        }
        let k = k - 3 * encoding.include_input as usize;
        let (l, j) = (k / 6, k % 6);
        let a = j % 3;
        let angle = 2f64.powi(l as i32) * x[a];
        let trig = if j < 3 { angle.sin() } else { angle.cos() };
        let damping = v.map_or(1.0, |v| (-0.5 * 4f64.powi(l as i32) * v[a]).exp());
        trig * damping
    }

    fn row3<T: Copy + Into<f64>>(values: &[T], r: usize) -> [f64; 3] {
        [
            values[3 * r].into(),
            values[3 * r + 1].into(),
            values[3 * r + 2].into(),
        ]
    }

    #[test]
    fn paper_output_widths() {
        assert_eq!(NERF_POSITION.output_width(), 63);
        assert_eq!(NERF_DIRECTION.output_width(), 27);
        assert_eq!(MIP_POSITION.output_width(), 96);
    }

    #[test]
    fn forward_matches_the_formula_in_f64() {
        // Known values first: at x = 0 every sine is 0 and every cosine 1,
        // after the raw input; a variance damps them by exp(−½·4^ℓ·σ²).
        let mut out = vec![f32::NAN; 27];
        encode(&NERF_DIRECTION, &[0.0, 0.0, 0.0], None, &mut out);
        for l in 0..4 {
            assert_eq!(&out[3 + 6 * l..9 + 6 * l], &[0., 0., 0., 1., 1., 1.]);
        }
        encode(&NERF_DIRECTION, &[0.5, -2.0, 3.0], None, &mut out);
        assert_eq!(&out[..3], &[0.5, -2.0, 3.0], "raw input first");
        assert_eq!(out[3], 0.5f32.sin(), "sin(2^0 x) of x");
        assert_eq!(out[7], (-2.0f32).cos(), "cos(2^0 y) of y");
        assert_eq!(out[3 + 6 + 2], 6.0f32.sin(), "sin(2^1 z) of z");
        let mut out = vec![f32::NAN; 12];
        let ipe = FrequencyEncoding {
            frequencies: 2,
            include_input: false,
        };
        encode(&ipe, &[0.0; 3], Some(&[1.0, 0.0, 2.0]), &mut out);
        let e = |t: f64| t.exp() as f32;
        assert_eq!(&out[3..6], &[e(-0.5), 1.0, e(-1.0)]);
        assert_eq!(&out[9..12], &[e(-2.0), 1.0, e(-4.0)]);

        // Then many rows (more than one parallel task) against the formula.
        // Inputs up to ±1e4 at 2^15: the angle reaches 3·10⁸, where an
        // encoding that rounds its angle would be off by O(1). Since the
        // angle is exact, the f32 result differs from the f64 one by
        // sin/cos's rounding (≤ 1 ulp ≤ 6e-8 for values ≤ 1), exp's (≤ 1
        // ulp) and the product's (½ ulp): ≤ 2.5·6e-8 = 1.5e-7. 3e-7
        // absolute leaves margin for the platform's libm; any error in
        // frequency, layout or damping is of order 1e-2 or more.
        let rows = 5000;
        for (encoding, range) in [
            (NERF_POSITION, 1.5),
            (NERF_DIRECTION, 1.0),
            (MIP_POSITION, 4.0),
            (MIP_POSITION, 1e4),
        ] {
            let x = points(1, rows, range);
            let v = variances(2, rows, 1e-8, 10.0);
            let w = encoding.output_width();
            for variance in [None, Some(&v[..])] {
                let mut out = vec![f32::NAN; rows * w];
                encode(&encoding, &x, variance, &mut out);
                let mut worst = 0f64;
                for r in 0..rows {
                    let vr = variance.map(|v| row3(v, r));
                    for k in 0..w {
                        let want = formula(&encoding, row3(&x, r), vr, k);
                        worst = worst.max((out[r * w + k] as f64 - want).abs());
                    }
                }
                assert!(
                    worst < 3e-7,
                    "{encoding:?} range {range} variance {}: worst {worst:e}",
                    variance.is_some()
                );
            }
        }
    }

    #[test]
    fn backward_matches_central_differences_in_f64() {
        // One Jacobian entry at a time (d_out one-hot), each against a
        // central difference of the f64 forward with a step scaled to that
        // entry's frequency: h = 1e-5/2^ℓ for x and 1e-5/(½·4^ℓ) for σ², so
        // (h·rate)² is the same for every ℓ. Then the truncation error is
        // (h·rate)²/6 ≈ 1.7e-11 relative to the entry's natural size
        // (2^ℓ·w for ∂/∂x, ½·4^ℓ·w for ∂/∂σ², 1 for the raw input) and
        // rounding is ε/(h·rate) ≈ 2e-11 of it. 1e-8 bounds both with room;
        // a wrong factor or sign is off by order 1.
        let rows = 20;
        let x: Vec<f64> = points(3, rows, 2.0).iter().map(|&v| v as f64).collect();
        let v: Vec<f64> = variances(4, rows, 1e-8, 10.0)
            .iter()
            .map(|&v| v as f64)
            .collect();
        for encoding in [NERF_POSITION, MIP_POSITION] {
            let w = encoding.output_width();
            for variance in [None, Some(&v[..])] {
                let mut worst = 0f64;
                for r in 0..rows {
                    let xr = &x[3 * r..3 * r + 3];
                    let vr = variance.map(|v| &v[3 * r..3 * r + 3]);
                    let forward = |xr: &[f64], vr: Option<&[f64]>, k: usize| {
                        let mut out = vec![0.0; w];
                        encode(&encoding, xr, vr, &mut out);
                        out[k]
                    };
                    for k in 0..w {
                        let mut d_out = vec![0.0; w];
                        d_out[k] = 1.0;
                        let (mut gx, mut gv) = ([f64::NAN; 3], [f64::NAN; 3]);
                        encode_backward(&encoding, xr, vr, &d_out, &mut gx, Some(&mut gv));
                        let first = encoding.first_sinusoid();
                        let (rate_x, rate_v, a) = if k < first {
                            (1.0, 1.0, k)
                        } else {
                            let l = ((k - first) / 6) as i32;
                            (2f64.powi(l), 0.5 * 4f64.powi(l), (k - first) % 3)
                        };
                        let damping = vr.map_or(1.0, |v| {
                            if k < first {
                                1.0
                            } else {
                                (-rate_v * v[a]).exp()
                            }
                        });
                        for b in 0..3 {
                            let h = 1e-5 / rate_x;
                            let (mut plus, mut minus) = (xr.to_vec(), xr.to_vec());
                            plus[b] += h;
                            minus[b] -= h;
                            // The step actually taken: x ± h rounds, and at
                            // h = 3e-10 an ulp of x is 1e-6 of h.
                            let numeric = (forward(&plus, vr, k) - forward(&minus, vr, k))
                                / (plus[b] - minus[b]);
                            let size = (rate_x * damping).max(1e-290);
                            worst = worst.max((gx[b] - numeric).abs() / size);
                        }
                        match vr {
                            None => assert_eq!(gv, [0.0; 3], "no variance, no gradient"),
                            Some(vr) => {
                                for b in 0..3 {
                                    let h = 1e-5 / rate_v;
                                    let (mut plus, mut minus) = (vr.to_vec(), vr.to_vec());
                                    plus[b] += h;
                                    minus[b] -= h;
                                    let numeric = (forward(xr, Some(&plus), k)
                                        - forward(xr, Some(&minus), k))
                                        / (plus[b] - minus[b]);
                                    let size = (rate_v * damping).max(1e-290);
                                    worst = worst.max((gv[b] - numeric).abs() / size);
                                }
                            }
                        }
                    }
                }
                assert!(
                    worst < 1e-8,
                    "{encoding:?} variance {}: worst relative error {worst:e}",
                    variance.is_some()
                );
            }
        }
    }

    #[test]
    fn batch_backward_sums_rows_like_the_f64_reference_on_any_thread_count() {
        // The parallel f32 path over 9000 rows (five tasks) against the f64
        // path row by row: this catches block-indexing errors the one-row
        // tests cannot. Each d_inputs entry is a sum of ≤ 2L + 1 terms of
        // size ≤ 2^ℓ·|u|; f32 rounding of each term (sin/cos, exp, 3
        // products: ≤ 5 ulp) and of the running sum (≤ 2L + 1 ulp) bound the
        // error by (2L + 6)·ε·Σ|terms|. The same for d_variance with ½·4^ℓ.
        let rows = 9000;
        let encoding = MIP_POSITION;
        let w = encoding.output_width();
        let x = points(5, rows, 1.5);
        let v = variances(6, rows, 1e-6, 1.0);
        let mut rng = Pcg32::new(7, 13);
        let d_out: Vec<f32> = (0..rows * w).map(|_| rng.next_f32() * 2.0 - 1.0).collect();
        let mut gx = vec![f32::NAN; 3 * rows];
        let mut gv = vec![f32::NAN; 3 * rows];
        encode_backward(&encoding, &x, Some(&v), &d_out, &mut gx, Some(&mut gv));
        let bound_factor = (2.0 * encoding.frequencies as f64 + 6.0) * f32::EPSILON as f64;
        for r in 0..rows {
            let x64 = row3(&x, r);
            let v64 = row3(&v, r);
            let u: Vec<f64> = d_out[r * w..(r + 1) * w]
                .iter()
                .map(|&u| u as f64)
                .collect();
            let (mut wx, mut wv) = ([0.0; 3], [0.0; 3]);
            encode_backward(&encoding, &x64, Some(&v64), &u, &mut wx, Some(&mut wv));
            for a in 0..3 {
                let (mut sx, mut sv) = (0f64, 0f64);
                for l in 0..encoding.frequencies as i32 {
                    let size = (u[6 * l as usize + a].abs() + u[6 * l as usize + 3 + a].abs())
                        * (-0.5 * 4f64.powi(l) * v64[a]).exp();
                    sx += 2f64.powi(l) * size;
                    sv += 0.5 * 4f64.powi(l) * size;
                }
                assert!(
                    (gx[3 * r + a] as f64 - wx[a]).abs() <= bound_factor * sx,
                    "row {r} d_x{a}: {} vs {}",
                    gx[3 * r + a],
                    wx[a]
                );
                assert!(
                    (gv[3 * r + a] as f64 - wv[a]).abs() <= bound_factor * sv,
                    "row {r} d_var{a}: {} vs {}",
                    gv[3 * r + a],
                    wv[a]
                );
            }
        }
        // Bit for bit the same on one thread: each row is one thread's work
        // in a fixed order.
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .unwrap();
        let (mut gx1, mut gv1) = (vec![0f32; 3 * rows], vec![0f32; 3 * rows]);
        let mut out = vec![0f32; rows * w];
        let mut out1 = vec![0f32; rows * w];
        encode(&encoding, &x, Some(&v), &mut out);
        pool.install(|| {
            encode_backward(&encoding, &x, Some(&v), &d_out, &mut gx1, Some(&mut gv1));
            encode(&encoding, &x, Some(&v), &mut out1);
        });
        assert!(gx == gx1 && gv == gv1 && out == out1);
    }

    #[test]
    fn ipe_tends_to_the_encoding_as_variance_vanishes_and_to_zero_as_it_grows() {
        let rows = 500;
        let encoding = MIP_POSITION;
        let w = encoding.output_width();
        // In f64, at σ² = 1e-12, each damped value differs from the plain
        // one by (1 − e^(−t))·p with t = ½·4^ℓ·σ² ≤ 5.4e-4, and
        // t − t²/2 ≤ 1 − e^(−t) ≤ t: assert the difference is t·p within
        // t²/2·|p| plus the rounding of the two values (4ε·|p|). This pins
        // the ½·4^ℓ exponent (a 2^ℓ or a missing ½ fails at ℓ ≥ 1).
        let x: Vec<f64> = points(8, rows, 2.0).iter().map(|&v| v as f64).collect();
        let tiny = vec![1e-12; 3 * rows];
        let (mut plain, mut ipe) = (vec![0.0; rows * w], vec![0.0; rows * w]);
        encode(&encoding, &x, None, &mut plain);
        encode(&encoding, &x, Some(&tiny), &mut ipe);
        for (k, (&p, &q)) in plain.iter().zip(&ipe).enumerate() {
            let l = ((k % w) / 6) as i32;
            let t = 0.5 * 4f64.powi(l) * 1e-12;
            assert!(
                ((p - q) - t * p).abs() <= (t * t / 2.0 + 4.0 * f64::EPSILON) * p.abs(),
                "entry {k}: plain {p}, damped {q}"
            );
        }
        // In f32 the whole difference stays below the largest t (5.4e-4 at
        // ℓ = 15) plus a rounding of each side.
        let x32 = points(8, rows, 2.0);
        let (mut plain, mut ipe) = (vec![0f32; rows * w], vec![0f32; rows * w]);
        encode(&encoding, &x32, None, &mut plain);
        encode(&encoding, &x32, Some(&vec![1e-12f32; 3 * rows]), &mut ipe);
        let bound = 0.5 * 4f32.powi(15) * 1e-12 + 2.0 * f32::EPSILON;
        let worst = plain
            .iter()
            .zip(&ipe)
            .map(|(p, q)| (p - q).abs())
            .fold(0f32, f32::max);
        assert!(worst <= bound, "worst {worst:e} over {bound:e}");
        // Large variances: e^(−½·30) = 3e-7 at ℓ = 0, the least damped.
        let with_input = FrequencyEncoding {
            frequencies: 16,
            include_input: true,
        };
        let w = with_input.output_width();
        for var in [30.0, 1e3, 1e30] {
            let mut out = vec![f32::NAN; rows * w];
            encode(&with_input, &x32, Some(&vec![var; 3 * rows]), &mut out);
            for r in 0..rows {
                assert_eq!(&out[r * w..r * w + 3], &x32[3 * r..3 * r + 3], "the mean");
                for &o in &out[r * w + 3..(r + 1) * w] {
                    assert!(o.abs() < 1e-6, "row {r} at σ² = {var}: {o}");
                }
            }
        }
    }

    #[test]
    fn extreme_variances_and_inputs_stay_finite() {
        let encoding = FrequencyEncoding {
            frequencies: 16,
            include_input: true,
        };
        let w = encoding.output_width();
        let x = [1e4f32, -1e4, 0.0, -1e4, 1e4, 1.0];
        let rows = 2;
        let mut rng = Pcg32::new(9, 1);
        let d_out: Vec<f32> = (0..rows * w).map(|_| rng.next_f32() * 2.0 - 1.0).collect();
        let mut plain = vec![0f32; rows * w];
        encode(&encoding, &x, None, &mut plain);
        let mut plain_gx = vec![0f32; 3 * rows];
        encode_backward(&encoding, &x, None, &d_out, &mut plain_gx, None);
        for var in [0.0, 1e-30, 1e30, f32::MAX, f32::INFINITY] {
            let v = vec![var; 3 * rows];
            let mut out = vec![f32::NAN; rows * w];
            encode(&encoding, &x, Some(&v), &mut out);
            let (mut gx, mut gv) = (vec![f32::NAN; 3 * rows], vec![f32::NAN; 3 * rows]);
            encode_backward(&encoding, &x, Some(&v), &d_out, &mut gx, Some(&mut gv));
            assert!(
                out.iter().chain(&gx).chain(&gv).all(|o| o.is_finite()),
                "σ² = {var}: {out:?} {gx:?} {gv:?}"
            );
            if var <= 1e-30 {
                // exp(−0) = 1 exactly, and ½·4^15·1e-30 rounds exp to 1.
                assert_eq!(out, plain, "σ² = {var} is the plain encoding");
                assert_eq!(gx, plain_gx, "σ² = {var} has the plain gradient");
            }
            if var >= 1e30 {
                // Every damping underflows to 0: only the raw input is left,
                // and only it carries a gradient.
                for r in 0..rows {
                    assert!(out[r * w + 3..(r + 1) * w].iter().all(|&o| o == 0.0));
                    assert_eq!(&gx[3 * r..3 * r + 3], &d_out[r * w..r * w + 3]);
                }
                assert!(gv.iter().all(|&g| g == 0.0));
            }
        }
    }
}
