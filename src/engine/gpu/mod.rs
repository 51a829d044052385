//! The `gpu` engine: wgpu compute pipelines over the WGSL in `shaders/`.

pub mod context;
pub mod kernel;
pub mod hash_grid;

pub use context::{GpuContext, GpuError};
pub mod dense;
pub mod sh;
pub mod adam;
pub mod composite;
pub mod loss;
pub mod march;
pub mod occupancy;
