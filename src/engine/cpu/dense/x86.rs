//! The AVX-512 and AVX2 lanes of the kernels, and the mixed-precision
//! products on AVX512-BF16.

use super::Lanes;
use std::arch::x86_64::*;

pub struct Avx512;
impl Lanes for Avx512 {
    type V = __m512;
    type M = __mmask16;
    const N: usize = 16;
    const NV_MAX: usize = 4;
    #[inline(always)]
    unsafe fn zero() -> __m512 {
        // SAFETY: AVX-512F is enabled (the `Lanes` contract); no memory is
        // accessed.
        unsafe { _mm512_setzero_ps() }
    }
    #[inline(always)]
    unsafe fn splat(x: f32) -> __m512 {
        // SAFETY: AVX-512F is enabled (the `Lanes` contract); no memory is
        // accessed.
        unsafe { _mm512_set1_ps(x) }
    }
    #[inline(always)]
    unsafe fn mask(n: usize) -> __mmask16 {
        if n >= 16 {
            0xffff
        } else {
            ((1u32 << n) - 1) as u16
        }
    }
    #[inline(always)]
    unsafe fn load(p: *const f32, m: __mmask16) -> __m512 {
        // SAFETY: AVX-512F is enabled, and `p` is readable for the lanes `m`
        // selects (the `Lanes` contract); the masked load touches no other
        // lane.
        unsafe { _mm512_maskz_loadu_ps(m, p) }
    }
    #[inline(always)]
    unsafe fn store(p: *mut f32, v: __m512, m: __mmask16) {
        // SAFETY: AVX-512F is enabled, and `p` is writable for the lanes `m`
        // selects (the `Lanes` contract); the masked store touches no other
        // lane.
        unsafe { _mm512_mask_storeu_ps(p, m, v) }
    }
    #[inline(always)]
    unsafe fn fma(a: __m512, b: __m512, c: __m512) -> __m512 {
        // SAFETY: AVX-512F is enabled (the `Lanes` contract); no memory is
        // accessed.
        unsafe { _mm512_fmadd_ps(a, b, c) }
    }
    #[inline(always)]
    unsafe fn add(a: __m512, b: __m512) -> __m512 {
        // SAFETY: AVX-512F is enabled (the `Lanes` contract); no memory is
        // accessed.
        unsafe { _mm512_add_ps(a, b) }
    }
    #[inline(always)]
    unsafe fn relu(x: __m512) -> __m512 {
        // SAFETY: AVX-512F is enabled (the `Lanes` contract); no memory is
        // accessed.
        unsafe { _mm512_max_ps(x, _mm512_setzero_ps()) }
    }
    #[inline(always)]
    unsafe fn relu_gate(g: __m512, y: __m512) -> __m512 {
        // SAFETY: AVX-512F is enabled (the `Lanes` contract); no memory is
        // accessed.
        unsafe { _mm512_maskz_mov_ps(_mm512_cmp_ps_mask::<_CMP_GT_OQ>(y, _mm512_setzero_ps()), g) }
    }
    #[inline(always)]
    unsafe fn sum(v: __m512) -> f32 {
        // SAFETY: AVX-512F is enabled (the `Lanes` contract); no memory is
        // accessed.
        unsafe { _mm512_reduce_add_ps(v) }
    }
    #[inline(always)]
    unsafe fn stream_copy(dst: *mut f32, src: *const f32, n: usize) {
        // SAFETY: AVX-512F is enabled, and `n` floats are readable at `src` and
        // writable at `dst` (the `Lanes` contract); stream_with! streams whole
        // vectors within them, at 64-byte aligned addresses as the streaming
        // store requires.
        unsafe {
            stream_with!(dst, src, n, 64, 16, |d, s| _mm512_stream_ps(
                d,
                _mm512_loadu_ps(s)
            ))
        }
    }
    #[inline(always)]
    unsafe fn store_fence() {
        // SAFETY: SSE is enabled, as part of AVX-512F (the `Lanes` contract).
        unsafe { _mm_sfence() }
    }
}

pub struct Avx2;
/// Lane masks for maskload: 8 all-ones then 8 zeros, read at 8 − n.
static MASKS: [i32; 16] = [-1, -1, -1, -1, -1, -1, -1, -1, 0, 0, 0, 0, 0, 0, 0, 0];
impl Lanes for Avx2 {
    type V = __m256;
    /// The lane count and its mask: full vectors use plain loads.
    type M = (usize, __m256i);
    const N: usize = 8;
    const NV_MAX: usize = 2;
    #[inline(always)]
    unsafe fn zero() -> __m256 {
        // SAFETY: AVX2 with FMA is enabled (the `Lanes` contract); no memory is
        // accessed.
        unsafe { _mm256_setzero_ps() }
    }
    #[inline(always)]
    unsafe fn splat(x: f32) -> __m256 {
        // SAFETY: AVX2 with FMA is enabled (the `Lanes` contract); no memory is
        // accessed.
        unsafe { _mm256_set1_ps(x) }
    }
    #[inline(always)]
    unsafe fn mask(n: usize) -> (usize, __m256i) {
        let n = n.min(8);
        // SAFETY: AVX is enabled (the `Lanes` contract), and the 8 words read
        // from MASKS start at 8 − n ≥ 0 of its 16.
        unsafe {
            (
                n,
                _mm256_loadu_si256(MASKS.as_ptr().add(8 - n) as *const __m256i),
            )
        }
    }
    #[inline(always)]
    unsafe fn load(p: *const f32, m: (usize, __m256i)) -> __m256 {
        // SAFETY: AVX2 with FMA is enabled, and `p` is readable for the lanes
        // `m` selects (the `Lanes` contract); the masked load touches no other
        // lane.
        unsafe {
            if m.0 == 8 {
                _mm256_loadu_ps(p)
            } else {
                _mm256_maskload_ps(p, m.1)
            }
        }
    }
    #[inline(always)]
    unsafe fn store(p: *mut f32, v: __m256, m: (usize, __m256i)) {
        // SAFETY: AVX2 with FMA is enabled, and `p` is writable for the lanes
        // `m` selects (the `Lanes` contract); the masked store touches no other
        // lane.
        unsafe {
            if m.0 == 8 {
                _mm256_storeu_ps(p, v)
            } else {
                _mm256_maskstore_ps(p, m.1, v)
            }
        }
    }
    #[inline(always)]
    unsafe fn fma(a: __m256, b: __m256, c: __m256) -> __m256 {
        // SAFETY: AVX2 with FMA is enabled (the `Lanes` contract); no memory is
        // accessed.
        unsafe { _mm256_fmadd_ps(a, b, c) }
    }
    #[inline(always)]
    unsafe fn add(a: __m256, b: __m256) -> __m256 {
        // SAFETY: AVX2 with FMA is enabled (the `Lanes` contract); no memory is
        // accessed.
        unsafe { _mm256_add_ps(a, b) }
    }
    #[inline(always)]
    unsafe fn relu(x: __m256) -> __m256 {
        // SAFETY: AVX2 with FMA is enabled (the `Lanes` contract); no memory is
        // accessed.
        unsafe { _mm256_max_ps(x, _mm256_setzero_ps()) }
    }
    #[inline(always)]
    unsafe fn relu_gate(g: __m256, y: __m256) -> __m256 {
        // SAFETY: AVX2 with FMA is enabled (the `Lanes` contract); no memory is
        // accessed.
        unsafe { _mm256_and_ps(g, _mm256_cmp_ps::<_CMP_GT_OQ>(y, _mm256_setzero_ps())) }
    }
    #[inline(always)]
    unsafe fn sum(v: __m256) -> f32 {
        // SAFETY: AVX2 with FMA is enabled (the `Lanes` contract); no memory is
        // accessed.
        unsafe {
            let quad = _mm_add_ps(_mm256_castps256_ps128(v), _mm256_extractf128_ps::<1>(v));
            let pair = _mm_add_ps(quad, _mm_movehl_ps(quad, quad));
            _mm_cvtss_f32(_mm_add_ss(pair, _mm_movehdup_ps(pair)))
        }
    }
    #[inline(always)]
    unsafe fn stream_copy(dst: *mut f32, src: *const f32, n: usize) {
        // SAFETY: AVX2 with FMA is enabled, and `n` floats are readable at
        // `src` and writable at `dst` (the `Lanes` contract); stream_with!
        // streams whole vectors within them, at 32-byte aligned addresses as
        // the streaming store requires.
        unsafe {
            stream_with!(dst, src, n, 32, 8, |d, s| _mm256_stream_ps(
                d,
                _mm256_loadu_ps(s)
            ))
        }
    }
    #[inline(always)]
    unsafe fn store_fence() {
        // SAFETY: SSE is enabled, as part of AVX2 with FMA (the `Lanes`
        // contract).
        unsafe { _mm_sfence() }
    }
}
