//! The `cpu` engine: every stage in plain Rust, and the reference the `gpu`
//! engine is tested against.

pub(crate) mod appearance;
pub mod composite;
pub mod composite_batch;
pub mod dense;
pub mod fields;
pub mod frequency;
pub mod frustum;
pub mod hash_grid;
pub mod loss;
pub mod march;
pub mod model;
pub mod sampling;
pub mod sh;
pub mod weight_losses;

// What both engines hold on the host, under the paths the cpu engine's
// stages have always named them by.
