//! Entry points compiled once per instruction set, so the generic kernels
//! are inlined with that set enabled.
//!
//! # Safety
//! Every function here runs its kernels on `rows` of a job and has one
//! contract: the instruction set it is compiled for (or `backend`) must be
//! one this processor has ([`Backend::runs_here`]), which is all the
//! [`Lanes`] and [`Products`] methods inlined into it need; and the job's
//! pointers must hold the rows its fields describe: `input` and the
//! activations `rows.end` rows of their layers, the output `rows.end`
//! rows of its columns, the weights (f32, transposed or bf16 pairs, as the
//! backend reads them) packed for the job's network, `scratch`
//! [`scratch_floats`]`(max_width)` floats and `partial` the network's
//! parameter count, none of it written by another thread meanwhile.

use super::*;

macro_rules! entry_points {
    ($module:ident, $products:ty, $($features:literal)?) => {
        pub mod $module {
            #[allow(unused_imports)]
            #[cfg(target_arch = "x86_64")]
            use super::super::x86::*;
            use super::super::*;

            /// # Safety
            /// As the [module](super)'s.
            $(#[target_feature(enable = $features)])?
            pub unsafe fn forward(job: &ForwardJob, rows: Range<usize>, scratch: *mut f32) {
                // SAFETY: the caller keeps the module's contract, all the
                // kernels need: the instructions enabled on this function
                // run here, and the job's pointers hold `rows`.
                unsafe { forward_rows::<$products>(job, rows, scratch) }
            }
            /// # Safety
            /// As the [module](super)'s.
            $(#[target_feature(enable = $features)])?
            pub unsafe fn inference(job: &InferenceJob, rows: Range<usize>, scratch: *mut f32) {
                // SAFETY: the caller keeps the module's contract, all the
                // kernels need: the instructions enabled on this function
                // run here, and the job's pointers hold `rows`.
                unsafe { inference_rows::<$products>(job, rows, scratch) }
            }
            /// # Safety
            /// As the [module](super)'s.
            $(#[target_feature(enable = $features)])?
            pub unsafe fn backward(
                job: &BackwardJob,
                rows: Range<usize>,
                partial: *mut f32,
                scratch: *mut f32,
            ) {
                // SAFETY: the caller keeps the module's contract, all the
                // kernels need: the instructions enabled on this function
                // run here, and the job's pointers hold `rows`.
                unsafe { backward_rows::<$products>(job, rows, partial, scratch) }
            }
            /// The f32 product alone (the peak measurement).
            ///
            /// # Safety
            /// The instruction set must be this processor's, and `g`'s
            /// operands readable and its result writable as [`Gemm`]
            /// describes.
            $(#[target_feature(enable = $features)])?
            pub unsafe fn gemm(g: &Gemm) {
                // SAFETY: the caller keeps this function's contract, all
                // the kernel needs.
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

/// The entry point of `$backend`'s instruction set. Used only in the
/// functions below, whose contract ([module](self)) is the entry points'.
macro_rules! route {
    ($backend:expr, $f:ident($($arg:expr),*)) => {
        // SAFETY: `$backend` runs here and the arguments are valid (the
        // calling function's contract), and the entry point called is
        // compiled for `$backend`'s instructions.
        unsafe {
            match $backend {
                #[cfg(target_arch = "x86_64")]
                Backend::AmxBf16 => amxbf16::$f($($arg),*),
                #[cfg(target_arch = "x86_64")]
                Backend::Avx512Bf16 => avx512bf16::$f($($arg),*),
                #[cfg(target_arch = "x86_64")]
                Backend::Avx512 => avx512::$f($($arg),*),
                #[cfg(target_arch = "x86_64")]
                Backend::Avx2 => avx2::$f($($arg),*),
                _ => portable::$f($($arg),*),
            }
        }
    };
}

/// # Safety
/// As the [module](self)'s.
pub unsafe fn forward(backend: Backend, job: &ForwardJob, rows: Range<usize>, scratch: *mut f32) {
    route!(backend, forward(job, rows, scratch))
}
/// # Safety
/// As the [module](self)'s.
pub unsafe fn inference(
    backend: Backend,
    job: &InferenceJob,
    rows: Range<usize>,
    scratch: *mut f32,
) {
    route!(backend, inference(job, rows, scratch))
}
/// # Safety
/// As the [module](self)'s.
pub unsafe fn backward(
    backend: Backend,
    job: &BackwardJob,
    rows: Range<usize>,
    partial: *mut f32,
    scratch: *mut f32,
) {
    route!(backend, backward(job, rows, partial, scratch))
}
/// # Safety
/// `backend` must run here ([`Backend::runs_here`]) and `g`'s operands be
/// readable and its result writable as [`Gemm`] describes.
pub unsafe fn gemm(backend: Backend, g: &Gemm) {
    route!(backend, gemm(g))
}
