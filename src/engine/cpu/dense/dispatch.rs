//! Entry points compiled once per instruction set, so the generic kernels
//! are inlined with that set enabled.

use super::*;

macro_rules! entry_points {
    ($module:ident, $products:ty, $($features:literal)?) => {
        pub mod $module {
            #[allow(unused_imports)]
            #[cfg(target_arch = "x86_64")]
            use super::super::x86::*;
            use super::super::*;

            $(#[target_feature(enable = $features)])?
            pub unsafe fn forward(job: &ForwardJob, rows: Range<usize>, scratch: *mut f32) {
                unsafe { forward_rows::<$products>(job, rows, scratch) }
            }
            $(#[target_feature(enable = $features)])?
            pub unsafe fn inference(job: &InferenceJob, rows: Range<usize>, scratch: *mut f32) {
                unsafe { inference_rows::<$products>(job, rows, scratch) }
            }
            $(#[target_feature(enable = $features)])?
            pub unsafe fn backward(
                job: &BackwardJob,
                rows: Range<usize>,
                partial: *mut f32,
                scratch: *mut f32,
            ) {
                unsafe { backward_rows::<$products>(job, rows, partial, scratch) }
            }
            /// The f32 product alone (the peak measurement).
            $(#[target_feature(enable = $features)])?
            pub unsafe fn gemm(g: &Gemm) {
                unsafe { super::super::gemm::<<$products as Products>::L>(g) }
            }
        }
    };
}

// The tile instructions are inline assembly and need no feature enabled.
#[cfg(target_arch = "x86_64")]
entry_points!(
    amxbf16,
    bf16::amx::AmxProducts,
    "avx512f,avx512vl,avx512bw,avx512bf16,avx2,fma"
);
#[cfg(target_arch = "x86_64")]
entry_points!(
    avx512bf16,
    bf16::Bf16Products,
    "avx512f,avx512vl,avx512bw,avx512bf16,avx2,fma"
);
#[cfg(target_arch = "x86_64")]
entry_points!(avx512, F32Products<Avx512>, "avx512f,avx512vl,avx2,fma");
#[cfg(target_arch = "x86_64")]
entry_points!(avx2, F32Products<Avx2>, "avx2,fma");
entry_points!(portable, F32Products<Portable>,);

macro_rules! route {
    ($backend:expr, $f:ident($($arg:expr),*)) => {
        match $backend {
            #[cfg(target_arch = "x86_64")]
            Backend::AmxBf16 => unsafe { amxbf16::$f($($arg),*) },
            #[cfg(target_arch = "x86_64")]
            Backend::Avx512Bf16 => unsafe { avx512bf16::$f($($arg),*) },
            #[cfg(target_arch = "x86_64")]
            Backend::Avx512 => unsafe { avx512::$f($($arg),*) },
            #[cfg(target_arch = "x86_64")]
            Backend::Avx2 => unsafe { avx2::$f($($arg),*) },
            _ => unsafe { portable::$f($($arg),*) },
        }
    };
}

/// # Safety
/// `backend` must be supported by this CPU (see [`backend`]), and the
/// job's pointers valid for `rows`.
pub unsafe fn forward(backend: Backend, job: &ForwardJob, rows: Range<usize>, scratch: *mut f32) {
    route!(backend, forward(job, rows, scratch))
}
pub unsafe fn inference(
    backend: Backend,
    job: &InferenceJob,
    rows: Range<usize>,
    scratch: *mut f32,
) {
    route!(backend, inference(job, rows, scratch))
}
pub unsafe fn backward(
    backend: Backend,
    job: &BackwardJob,
    rows: Range<usize>,
    partial: *mut f32,
    scratch: *mut f32,
) {
    route!(backend, backward(job, rows, partial, scratch))
}
pub unsafe fn gemm(backend: Backend, g: &Gemm) {
    route!(backend, gemm(g))
}
