//! The `gpu` engine: wgpu compute pipelines over the WGSL in `shaders/`.

mod context;
pub mod hash_grid;
pub mod kernel;

pub use context::{CounterReading, GpuContext, GpuCounters, GpuError};
pub mod adam;
pub mod appearance;
pub mod compact;
pub mod composite;
pub mod dense;
pub mod fields;
pub mod frequency;
pub mod frustum;
pub mod loss;
pub mod march;
#[cfg(test)]
pub(crate) mod mirror;
pub mod model;
pub mod proposal;
pub mod render;
pub mod sampling;
pub mod sh;
pub mod step;
pub mod timing;
