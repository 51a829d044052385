//! The `cpu` engine: every stage in plain Rust, and the reference the `gpu`
//! engine is tested against.

pub mod composite;
pub mod adam;
pub mod composite_batch;
pub mod loss;
pub mod hash_grid;
pub mod dense;
pub mod march;
pub mod occupancy;
pub mod sh;
pub mod ngp;
