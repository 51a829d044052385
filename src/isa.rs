//! Which vector instructions the cpu engine's kernels may use: what the
//! processor has, capped by `ZRAK_CPU_KERNELS` when it is set. Most users'
//! desktops have AVX2 and no AVX-512, so a machine with AVX-512 must be
//! able to run (and time, and test) the kernels those desktops run:
//! `ZRAK_CPU_KERNELS=avx2` runs the AVX2 kernels (no AVX-512, no bf16
//! products, no matrix units), `portable` the plain Rust ones. Every
//! kernel path gives the same sums within rounding, so the cap changes
//! speed, never what is learned beyond that.

use std::sync::OnceLock;

/// The widest kernels allowed, narrowest first.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum KernelCap {
    Portable,
    Avx2,
    Best,
}

/// The cap `ZRAK_CPU_KERNELS` sets (read once): unset, empty or `best`
/// for none. An unknown value is reported once on standard error and
/// ignored, rather than silently running kernels the user did not ask for.
pub fn kernel_cap() -> KernelCap {
    static CAP: OnceLock<KernelCap> = OnceLock::new();
    *CAP.get_or_init(|| {
        let value = std::env::var("ZRAK_CPU_KERNELS").unwrap_or_default();
        match value.trim().to_ascii_lowercase().as_str() {
            "" | "best" => KernelCap::Best,
            "avx2" => KernelCap::Avx2,
            "portable" => KernelCap::Portable,
            other => {
                eprintln!(
                    "zrak: ZRAK_CPU_KERNELS={other:?} is not one of best, avx2, portable; \
                     running the best kernels this processor has"
                );
                KernelCap::Best
            }
        }
    })
}

/// Whether the AVX-512 kernels (F, VL, DQ and BW, with AVX2, FMA and the
/// bit-manipulation sets they are compiled with) may run.
pub fn avx512() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        kernel_cap() == KernelCap::Best
            && std::is_x86_feature_detected!("avx512f")
            && std::is_x86_feature_detected!("avx512vl")
            && std::is_x86_feature_detected!("avx512dq")
            && std::is_x86_feature_detected!("avx512bw")
            && avx2_fma()
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// Whether the AVX2 kernels (with FMA and the bit-manipulation sets BMI1
/// and BMI2, which every processor with AVX2 and FMA has had) may run.
pub fn avx2_fma() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        kernel_cap() >= KernelCap::Avx2
            && std::is_x86_feature_detected!("avx2")
            && std::is_x86_feature_detected!("fma")
            && std::is_x86_feature_detected!("bmi1")
            && std::is_x86_feature_detected!("bmi2")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}
