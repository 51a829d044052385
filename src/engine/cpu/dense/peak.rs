//! What this machine's arithmetic can do, as references for the dense
//! kernels' achieved rates: a matrix product with the f32 kernels, and the
//! register-only ceiling of the multiply-add instructions themselves.

use rayon::prelude::*;

use super::{BLOCK, Backend, Epi, Gemm, SendPtr, backend, dispatch};
use crate::rng::Pcg32;

/// Single-precision GEMM throughput of this machine with these kernels: a
/// 1024 × 1024 × 1024 product on all threads, the best of five runs, in
/// GFLOP/s (2 FLOP per multiply-add). A reference for how close the MLPs
/// come to the machine's peak. The best rather than the median: on a
/// shared machine other work only ever slows a run down (medians of the
/// same build read 101 to 201 GFLOP/s on one Zen 4 machine).
pub fn measure_peak_gflops() -> f64 {
    let n = 1024;
    let mut rng = Pcg32::new(1, 2);
    let a: Vec<f32> = (0..n * n).map(|_| rng.next_f32() - 0.5).collect();
    let b: Vec<f32> = (0..n * n).map(|_| rng.next_f32() - 0.5).collect();
    let mut c = vec![0.0f32; n * n];
    let backend = backend();
    assert!(backend.runs_here(), "{backend:?} kernels on this processor");
    let mut run = || {
        let start = std::time::Instant::now();
        let cp = SendPtr(c.as_mut_ptr());
        (0..n / BLOCK).into_par_iter().for_each(|t| {
            let g = Gemm {
                m: BLOCK,
                n,
                k: n,
                a: a[t * BLOCK * n..].as_ptr(),
                a_m: n,
                a_k: 1,
                b: b.as_ptr(),
                b_k: n,
                // SAFETY: t < n / BLOCK, so the offset is inside c (n × n).
                c: unsafe { cp.get().add(t * BLOCK * n) },
                c_m: n,
                epi: Epi::Store,
            };
            // SAFETY: `backend` runs here (asserted above); a, b and c are
            // n × n, and the task reads BLOCK rows of a and all of b and
            // writes its own BLOCK rows of c, which no other task touches.
            unsafe { dispatch::gemm(backend, &g) }
        });
        start.elapsed().as_secs_f64()
    };
    run();
    let best = (0..5).map(|_| run()).fold(f64::INFINITY, f64::min);
    2.0 * (n * n * n) as f64 / best / 1e9
}

/// The multiply-add ceiling of `kernels` on all threads, in GFLOP/s:
/// each thread runs independent chains of the instruction the kernels
/// multiply with (f32 FMA, bf16 pair dot products for
/// [`Backend::Avx512Bf16`], tile products for [`Backend::AmxBf16`]) on
/// registers only, the best of five runs. No
/// kernel that reads memory can pass it.
pub fn arithmetic_peak_gflops(kernels: Backend) -> f64 {
    const ITERATIONS: usize = 1 << 22;
    let threads = rayon::current_num_threads();
    let run = || {
        let start = std::time::Instant::now();
        let flop: f64 = (0..threads)
            .into_par_iter()
            .map(|t| {
                let (flop, sink) = chains(kernels, ITERATIONS, t as f32);
                std::hint::black_box(sink);
                flop
            })
            .sum();
        flop / start.elapsed().as_secs_f64() / 1e9
    };
    run();
    (0..5).map(|_| run()).fold(0.0, f64::max)
}

/// Runs `iterations` rounds of independent multiply-add chains and returns
/// the FLOP done and a value that depends on every chain.
fn chains(kernels: Backend, iterations: usize, seed: f32) -> (f64, f32) {
    assert!(kernels.runs_here(), "{kernels:?} kernels on this processor");
    match kernels {
        #[cfg(target_arch = "x86_64")]
        // SAFETY: the processor has AMX-BF16 and this process may use the
        // tile registers (runs_here, asserted above, asked `available`).
        Backend::AmxBf16 => unsafe { super::bf16::amx::tile_chains(iterations, seed) },
        #[cfg(target_arch = "x86_64")]
        // SAFETY: the processor has AVX512-BF16 (asserted above).
        Backend::Avx512Bf16 => unsafe { x86::bf16_chains(iterations, seed) },
        #[cfg(target_arch = "x86_64")]
        // SAFETY: the processor has AVX-512F (asserted above).
        Backend::Avx512 => unsafe { x86::avx512_chains(iterations, seed) },
        #[cfg(target_arch = "x86_64")]
        // SAFETY: the processor has AVX2 and FMA (asserted above).
        Backend::Avx2 => unsafe { x86::avx2_chains(iterations, seed) },
        _ => {
            let mut acc = [seed; 16];
            for _ in 0..iterations {
                for a in &mut acc {
                    *a = a.mul_add(0.999_999, 1e-7);
                }
            }
            (2.0 * 16.0 * iterations as f64, acc.iter().sum())
        }
    }
}

#[cfg(target_arch = "x86_64")]
mod x86 {
    use std::arch::x86_64::*;

    /// Chains per thread: enough to cover the instruction's latency on
    /// every pipe (4–6 cycles, two pipes).
    const CHAINS: usize = 16;

    #[target_feature(enable = "avx512f")]
    pub unsafe fn avx512_chains(iterations: usize, seed: f32) -> (f64, f32) {
        let mut acc = [_mm512_set1_ps(seed); CHAINS];
        let (a, b) = (_mm512_set1_ps(0.999_999), _mm512_set1_ps(1e-7));
        for _ in 0..iterations {
            for x in &mut acc {
                *x = _mm512_fmadd_ps(*x, a, b);
            }
        }
        let sum = acc.iter().map(|&x| _mm512_reduce_add_ps(x)).sum();
        ((2 * 16 * CHAINS * iterations) as f64, sum)
    }

    #[target_feature(enable = "avx2,fma")]
    pub unsafe fn avx2_chains(iterations: usize, seed: f32) -> (f64, f32) {
        let mut acc = [_mm256_set1_ps(seed); CHAINS];
        let (a, b) = (_mm256_set1_ps(0.999_999), _mm256_set1_ps(1e-7));
        for _ in 0..iterations {
            for x in &mut acc {
                *x = _mm256_fmadd_ps(*x, a, b);
            }
        }
        let mut lanes = [0f32; 8];
        let mut sum = 0.0;
        for x in acc {
            // SAFETY: `lanes` holds the 8 floats stored.
            unsafe { _mm256_storeu_ps(lanes.as_mut_ptr(), x) };
            sum += lanes.iter().sum::<f32>();
        }
        ((2 * 8 * CHAINS * iterations) as f64, sum)
    }

    /// `vdpbf16ps`: 16 lanes × 2 products, each a multiply-add.
    #[target_feature(enable = "avx512f,avx512bf16")]
    pub unsafe fn bf16_chains(iterations: usize, seed: f32) -> (f64, f32) {
        let mut acc = [_mm512_set1_ps(seed); CHAINS];
        let a = _mm512_cvtne2ps_pbh(_mm512_set1_ps(0.5), _mm512_set1_ps(0.25));
        let b = _mm512_cvtne2ps_pbh(_mm512_set1_ps(1e-3), _mm512_set1_ps(-1e-3));
        for _ in 0..iterations {
            for x in &mut acc {
                *x = _mm512_dpbf16_ps(*x, a, b);
            }
        }
        let sum = acc.iter().map(|&x| _mm512_reduce_add_ps(x)).sum();
        ((2 * 32 * CHAINS * iterations) as f64, sum)
    }
}
