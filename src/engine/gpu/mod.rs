//! The `gpu` engine: wgpu compute pipelines over the WGSL in `shaders/`.

pub mod context;

pub use context::{GpuContext, GpuError};
