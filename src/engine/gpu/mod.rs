//! The `gpu` engine: wgpu compute pipelines over the WGSL in `shaders/`.

pub mod context;
pub mod kernel;

pub use context::{GpuContext, GpuError};
