//! Real spherical harmonics of a unit direction: Instant-NGP's view-direction
//! encoding (config "dir_encoding": SphericalHarmonics, degree 4).
//!
//! "Degree" counts bands as tiny-cuda-nn does: degree n gives the n² functions
//! of bands l = 0 … n − 1, at index l² + l + m for m = −l … l. The basis is
//! the real one with the Condon–Shortley phase, for a direction
//! d = (x, y, z) = (sin θ cos φ, sin θ sin φ, cos θ):
//!
//! ```text
//! Y_l^m = √2 K_l^|m| P_l^|m|(cos θ) cos(mφ)     m > 0
//!         K_l^0 P_l^0(cos θ)                    m = 0
//!         √2 K_l^|m| P_l^|m|(cos θ) sin(|m|φ)   m < 0
//! K_l^m = √((2l + 1)/(4π) · (l − m)!/(l + m)!)
//! P_l^m(z) = (−1)^m (1 − z²)^{m/2} dᵐ/dzᵐ P_l(z)
//! ```
//!
//! and since sinᵐθ cos(mφ) = Re (x + iy)ᵐ and sinᵐθ sin(mφ) = Im (x + iy)ᵐ,
//! every function is a polynomial in x, y, z:
//! Y_l^m = (−1)^m √2 K_l^m · P_l⁽ᵐ⁾(z) · Re/Im (x + iy)^|m|. The constants
//! below are those products (each with its closed form); the tests rebuild
//! every function from the definition above and compare. This is the same
//! basis, order and sign as tiny-cuda-nn's encoding. tiny-cuda-nn takes its
//! input in [0, 1]³ and maps it back with 2v − 1 (instant-ngp passes
//! (d + 1)/2); here the unit direction is taken as it is.

use num_traits::Float;
use rayon::prelude::*;

use crate::field::encoding::{SH_MAX_DEGREE, sh_coefficients};

/// 1/(2√π) = K_0^0.
const C0: f64 = 0.282_094_791_773_878_14;
/// √(3/(4π)).
const C1: f64 = 0.488_602_511_902_919_9;
/// √(15/(4π)): xy, yz, xz terms of band 2.
const C2_XY: f64 = 1.092_548_430_592_079_2;
/// (3/2)√(5/(4π)) and (1/2)√(5/(4π)): Y_2^0 = a z² − b.
const C2_Z2: f64 = 0.946_174_695_757_560_1;
const C2_1: f64 = 0.315_391_565_252_520_05;
/// (1/2)√(15/(4π)): Y_2^2 = c (x² − y²).
const C2_XX: f64 = 0.546_274_215_296_039_5;
/// (1/4)√(35/(2π)): Y_3^{±3}.
const C3_3: f64 = 0.590_043_589_926_643_5;
/// √(105/(4π)): Y_3^{−2} = c xyz.
const C3_XYZ: f64 = 2.890_611_442_640_554;
/// (1/4)√(21/(2π)): Y_3^{±1}.
const C3_1: f64 = 0.457_045_799_464_465_8;
/// (1/2)√(7/(4π)): Y_3^0 = c z (5z² − 3).
const C3_0: f64 = 0.373_176_332_590_115_4;
/// (1/2)√(105/(4π)): Y_3^2 = c z (x² − y²).
const C3_2: f64 = 1.445_305_721_320_277;

fn c<F: Float>(x: f64) -> F {
    F::from(x).expect("representable")
}

/// The first `degree²` basis functions at direction `d` into `out`.
pub fn sh_basis<F: Float>(degree: u32, d: [F; 3], out: &mut [F]) {
    assert!(
        (1..=SH_MAX_DEGREE).contains(&degree),
        "degree {degree} not in 1..={SH_MAX_DEGREE}"
    );
    let [x, y, z] = d;
    out[0] = c(C0);
    if degree <= 1 {
        return;
    }
    out[1] = -c::<F>(C1) * y;
    out[2] = c::<F>(C1) * z;
    out[3] = -c::<F>(C1) * x;
    if degree <= 2 {
        return;
    }
    let (xx, yy, zz) = (x * x, y * y, z * z);
    out[4] = c::<F>(C2_XY) * x * y;
    out[5] = -c::<F>(C2_XY) * y * z;
    out[6] = c::<F>(C2_Z2) * zz - c(C2_1);
    out[7] = -c::<F>(C2_XY) * x * z;
    out[8] = c::<F>(C2_XX) * (xx - yy);
    if degree <= 3 {
        return;
    }
    let three: F = c(3.0);
    let five: F = c(5.0);
    out[9] = c::<F>(C3_3) * y * (yy - three * xx);
    out[10] = c::<F>(C3_XYZ) * x * y * z;
    out[11] = c::<F>(C3_1) * y * (F::one() - five * zz);
    out[12] = c::<F>(C3_0) * z * (five * zz - three);
    out[13] = c::<F>(C3_1) * x * (F::one() - five * zz);
    out[14] = c::<F>(C3_2) * z * (xx - yy);
    out[15] = c::<F>(C3_3) * x * (three * yy - xx);
}

/// ∂Y_k/∂(x, y, z) of the polynomials above (the components varied
/// independently, not along the sphere).
pub fn sh_jacobian<F: Float>(degree: u32, d: [F; 3], out: &mut [[F; 3]]) {
    assert!(
        (1..=SH_MAX_DEGREE).contains(&degree),
        "degree {degree} not in 1..={SH_MAX_DEGREE}"
    );
    let [x, y, z] = d;
    let o = F::zero();
    out[0] = [o; 3];
    if degree <= 1 {
        return;
    }
    let c1: F = c(C1);
    out[1] = [o, -c1, o];
    out[2] = [o, o, c1];
    out[3] = [-c1, o, o];
    if degree <= 2 {
        return;
    }
    let two: F = c(2.0);
    let a: F = c(C2_XY);
    out[4] = [a * y, a * x, o];
    out[5] = [o, -a * z, -a * y];
    out[6] = [o, o, two * c::<F>(C2_Z2) * z];
    out[7] = [-a * z, o, -a * x];
    let b: F = c(C2_XX);
    out[8] = [two * b * x, -two * b * y, o];
    if degree <= 3 {
        return;
    }
    let (xx, yy, zz) = (x * x, y * y, z * z);
    let three: F = c(3.0);
    let five: F = c(5.0);
    let c33: F = c(C3_3);
    let cxyz: F = c(C3_XYZ);
    let c31: F = c(C3_1);
    let c30: F = c(C3_0);
    let c32: F = c(C3_2);
    let six: F = c(6.0);
    let ten: F = c(10.0);
    out[9] = [-six * c33 * x * y, three * c33 * (yy - xx), o];
    out[10] = [cxyz * y * z, cxyz * x * z, cxyz * x * y];
    out[11] = [o, c31 * (F::one() - five * zz), -ten * c31 * y * z];
    out[12] = [o, o, c30 * (c::<F>(15.0) * zz - three)];
    out[13] = [c31 * (F::one() - five * zz), o, -ten * c31 * x * z];
    out[14] = [two * c32 * x * z, -two * c32 * y * z, c32 * (xx - yy)];
    out[15] = [three * c33 * (yy - xx), six * c33 * x * y, o];
}

/// Rows per parallel task.
const TASK_ROWS: usize = 4096;

/// Encodes `rows` unit directions (rows × 3) into `output`: row r's
/// `degree²` coefficients go to `output[r·stride ..]`, so the encoding can be
/// written straight into a wider input matrix (pass the slice starting at
/// its column and the matrix width as `stride`). Other columns are left as
/// they are.
pub fn sh_encode(degree: u32, directions: &[f32], rows: usize, output: &mut [f32], stride: usize) {
    let n = sh_coefficients(degree);
    assert!(
        stride >= n,
        "stride {stride} narrower than {n} coefficients"
    );
    assert!(
        directions.len() >= 3 * rows,
        "directions hold fewer than {rows} rows"
    );
    if rows == 0 {
        return;
    }
    assert!(
        output.len() >= (rows - 1) * stride + n,
        "output holds fewer than {rows} rows"
    );
    output
        .par_chunks_mut(TASK_ROWS * stride)
        .enumerate()
        .for_each(|(t, block)| {
            let first = t * TASK_ROWS;
            let count = TASK_ROWS.min(rows.saturating_sub(first));
            for r in 0..count {
                let d = &directions[3 * (first + r)..][..3];
                sh_basis(degree, [d[0], d[1], d[2]], &mut block[r * stride..][..n]);
            }
        });
}

/// The gradient with respect to the directions (written, rows × 3) of a
/// loss whose gradient with respect to the encoding is `d_output` (row r at
/// `d_output[r·stride ..]`).
pub fn sh_encode_backward(
    degree: u32,
    directions: &[f32],
    rows: usize,
    d_output: &[f32],
    stride: usize,
    d_directions: &mut [f32],
) {
    let n = sh_coefficients(degree);
    assert!(stride >= n && d_directions.len() >= 3 * rows && directions.len() >= 3 * rows);
    if rows == 0 {
        return;
    }
    assert!(
        d_output.len() >= (rows - 1) * stride + n,
        "d_output holds fewer than {rows} rows"
    );
    d_directions[..3 * rows]
        .par_chunks_mut(3 * TASK_ROWS)
        .enumerate()
        .for_each(|(t, block)| {
            let mut jacobian = [[0f32; 3]; 16];
            for (i, g) in block.chunks_exact_mut(3).enumerate() {
                let r = t * TASK_ROWS + i;
                let d = &directions[3 * r..][..3];
                sh_jacobian(degree, [d[0], d[1], d[2]], &mut jacobian);
                let up = &d_output[r * stride..][..n];
                let mut sum = [0f32; 3];
                for (j, u) in jacobian.iter().zip(up) {
                    for a in 0..3 {
                        sum[a] += u * j[a];
                    }
                }
                g.copy_from_slice(&sum);
            }
        });
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Pcg32;
    use std::f64::consts::PI;

    fn random_directions(seed: u64, n: usize) -> Vec<[f64; 3]> {
        let mut rng = Pcg32::new(seed, 3);
        (0..n)
            .map(|_| {
                // Uniform on the sphere: z uniform in [−1, 1], φ uniform.
                let z = 2.0 * rng.next_f32() as f64 - 1.0;
                let phi = 2.0 * PI * rng.next_f32() as f64;
                let s = (1.0 - z * z).sqrt();
                [s * phi.cos(), s * phi.sin(), z]
            })
            .collect()
    }

    fn factorial(n: u32) -> f64 {
        (1..=n).map(|k| k as f64).product()
    }

    /// P_l^m(z) with the Condon–Shortley phase, by the standard recurrences:
    /// P_m^m = (−1)^m (2m − 1)!! (1 − z²)^{m/2},
    /// P_{m+1}^m = z (2m + 1) P_m^m,
    /// (l − m) P_l^m = z (2l − 1) P_{l−1}^m − (l + m − 1) P_{l−2}^m.
    fn legendre(l: u32, m: u32, z: f64) -> f64 {
        let mut pmm = 1.0;
        let s = (1.0 - z * z).sqrt();
        for i in 1..=m {
            pmm *= -((2 * i - 1) as f64) * s;
        }
        if l == m {
            return pmm;
        }
        let mut pm1 = z * (2 * m + 1) as f64 * pmm;
        if l == m + 1 {
            return pm1;
        }
        let mut p = 0.0;
        for ll in m + 2..=l {
            p = (z * (2 * ll - 1) as f64 * pm1 - (ll + m - 1) as f64 * pmm) / (ll - m) as f64;
            pmm = pm1;
            pm1 = p;
        }
        p
    }

    /// Y_l^m from the definition in the module documentation.
    fn from_definition(l: u32, m: i32, d: [f64; 3]) -> f64 {
        let am = m.unsigned_abs();
        let k = ((2 * l + 1) as f64 / (4.0 * PI) * factorial(l - am) / factorial(l + am)).sqrt();
        let theta = d[2].clamp(-1.0, 1.0).acos();
        let phi = d[1].atan2(d[0]);
        let p = legendre(l, am, theta.cos());
        match m.cmp(&0) {
            std::cmp::Ordering::Greater => 2f64.sqrt() * k * p * (m as f64 * phi).cos(),
            std::cmp::Ordering::Equal => k * p,
            std::cmp::Ordering::Less => 2f64.sqrt() * k * p * (am as f64 * phi).sin(),
        }
    }

    #[test]
    fn constant_term_is_one_over_two_root_pi() {
        let mut out = [0f64; 1];
        sh_basis(1, [0.0, 0.0, 1.0], &mut out);
        assert!((out[0] - 0.282_094_79).abs() < 1e-8);
        assert_eq!(out[0], 0.5 / PI.sqrt());
    }

    #[test]
    fn polynomials_match_the_definition() {
        // Both sides are the same function in f64: the only differences are
        // rounding in acos/atan2/recurrences (≈ 1e-15); 1e-12 fails on any
        // wrong constant, sign or index.
        let mut out = [0f64; 16];
        for d in random_directions(1, 200).into_iter().chain([
            [0.0, 0.0, 1.0],
            [1.0, 0.0, 0.0],
            [0.0, -1.0, 0.0],
        ]) {
            sh_basis(4, d, &mut out);
            for l in 0..4u32 {
                for m in -(l as i32)..=l as i32 {
                    let k = (l * l) as usize + (l as i32 + m) as usize;
                    let want = from_definition(l, m, d);
                    assert!(
                        (out[k] - want).abs() < 1e-12,
                        "Y_{l}^{m} at {d:?}: {} vs {want}",
                        out[k]
                    );
                }
            }
        }
    }

    /// Gauss–Legendre nodes and weights on [−1, 1] (Newton on P_n).
    fn gauss_legendre(n: usize) -> Vec<(f64, f64)> {
        (0..n)
            .map(|i| {
                let mut x = (PI * (i as f64 + 0.75) / (n as f64 + 0.5)).cos();
                let mut dp = 1.0;
                for _ in 0..100 {
                    let (mut p0, mut p1) = (1.0, x);
                    for k in 2..=n {
                        let p2 = ((2 * k - 1) as f64 * x * p1 - (k - 1) as f64 * p0) / k as f64;
                        p0 = p1;
                        p1 = p2;
                    }
                    dp = n as f64 * (x * p1 - p0) / (x * x - 1.0);
                    let step = p1 / dp;
                    x -= step;
                    if step.abs() < 1e-16 {
                        break;
                    }
                }
                (x, 2.0 / ((1.0 - x * x) * dp * dp))
            })
            .collect()
    }

    #[test]
    fn basis_is_orthonormal_on_the_sphere() {
        // Product quadrature: Gauss–Legendre in z = cos θ with 8 nodes is
        // exact for polynomials of degree ≤ 15 in z, and 16 equally spaced
        // φ are exact for trigonometric polynomials of degree < 16. A product
        // Y_i Y_j has degree ≤ 6 in each, so the Gram matrix comes out as the
        // exact integral up to rounding (≈ 1e-15 over 128 terms): 1e-12
        // leaves margin and catches any normalisation or sign error (which
        // shows up at order 1).
        let nodes = gauss_legendre(8);
        let n_phi = 16;
        let mut gram = [[0f64; 16]; 16];
        let mut y = [0f64; 16];
        for &(z, w) in &nodes {
            for j in 0..n_phi {
                let phi = 2.0 * PI * j as f64 / n_phi as f64;
                let s = (1.0 - z * z).sqrt();
                sh_basis(4, [s * phi.cos(), s * phi.sin(), z], &mut y);
                let weight = w * 2.0 * PI / n_phi as f64;
                for a in 0..16 {
                    for b in 0..16 {
                        gram[a][b] += weight * y[a] * y[b];
                    }
                }
            }
        }
        for (a, row) in gram.iter().enumerate() {
            for (b, &g) in row.iter().enumerate() {
                let want = if a == b { 1.0 } else { 0.0 };
                assert!((g - want).abs() < 1e-12, "⟨Y{a}, Y{b}⟩ = {g}");
            }
        }
    }

    #[test]
    fn jacobian_matches_central_differences() {
        // f64, h = 1e-5: truncation h²/6·|f'''| ≤ 1.7e-11 · 11.2 ≈ 2e-10
        // (the largest third derivative along one axis is 30·C3_0 ≈ 11.2,
        // from Y_3^0's 5z³), rounding ε·|f|/h ≈ 1e-11. 1e-7 relative with
        // magnitudes below 1e-2 measured against 1e-2 (floor 1e-9) bounds
        // both, and a wrong term is off by order 1.
        let h = 1e-5;
        let mut jac = [[0f64; 3]; 16];
        let (mut plus, mut minus) = ([0f64; 16], [0f64; 16]);
        let mut worst = 0f64;
        for d in random_directions(2, 100) {
            sh_jacobian(4, d, &mut jac);
            for a in 0..3 {
                let (mut dp, mut dm) = (d, d);
                dp[a] += h;
                dm[a] -= h;
                sh_basis(4, dp, &mut plus);
                sh_basis(4, dm, &mut minus);
                for k in 0..16 {
                    let numeric = (plus[k] - minus[k]) / (2.0 * h);
                    let e =
                        (jac[k][a] - numeric).abs() / jac[k][a].abs().max(numeric.abs()).max(1e-2);
                    worst = worst.max(e);
                }
            }
        }
        assert!(worst < 1e-7, "worst relative error {worst:e}");
    }

    #[test]
    fn batch_encoding_writes_strided_rows_and_backward_sums_the_jacobian() {
        let rows = 9000;
        let dirs: Vec<f32> = random_directions(3, rows)
            .iter()
            .flatten()
            .map(|&v| v as f32)
            .collect();
        // Into columns 16..32 of a 32-wide matrix, as the colour network's
        // input is laid out; the first 16 columns must be untouched.
        let stride = 32;
        let mut matrix = vec![-7.0f32; rows * stride];
        sh_encode(4, &dirs, rows, &mut matrix[16..], stride);
        let mut want = [0f64; 16];
        for r in 0..rows {
            let d = [
                dirs[3 * r] as f64,
                dirs[3 * r + 1] as f64,
                dirs[3 * r + 2] as f64,
            ];
            sh_basis(4, d, &mut want);
            assert!(
                matrix[r * stride..r * stride + 16]
                    .iter()
                    .all(|&v| v == -7.0)
            );
            for k in 0..16 {
                // A few f32 roundings of values below 3: 1e-6 absolute.
                assert!(
                    (matrix[r * stride + 16 + k] as f64 - want[k]).abs() < 1e-6,
                    "row {r} k {k}"
                );
            }
        }
        let d_out: Vec<f32> = (0..rows * stride)
            .map(|i| ((i * 37 % 101) as f32 - 50.0) / 50.0)
            .collect();
        let mut d_dirs = vec![f32::NAN; rows * 3];
        sh_encode_backward(4, &dirs, rows, &d_out[16..], stride, &mut d_dirs);
        let mut jac = [[0f64; 3]; 16];
        for r in (0..rows).step_by(7) {
            let d = [
                dirs[3 * r] as f64,
                dirs[3 * r + 1] as f64,
                dirs[3 * r + 2] as f64,
            ];
            sh_jacobian(4, d, &mut jac);
            for a in 0..3 {
                let want: f64 = (0..16)
                    .map(|k| d_out[r * stride + 16 + k] as f64 * jac[k][a])
                    .sum();
                // 16 f32 products of magnitude ≤ 10: ≤ 16·10·ε ≈ 2e-5.
                assert!(
                    (d_dirs[3 * r + a] as f64 - want).abs() < 2e-5,
                    "row {r} axis {a}"
                );
            }
        }
    }

    #[test]
    fn lower_degrees_are_prefixes() {
        let d = [0.36, -0.48, 0.8];
        let mut full = [0f64; 16];
        sh_basis(4, d, &mut full);
        for degree in 1..4 {
            let mut part = vec![0f64; sh_coefficients(degree)];
            sh_basis(degree, d, &mut part);
            assert_eq!(&part[..], &full[..part.len()]);
        }
    }
}
