//! The training loop: batches, schedules, the optimiser, the occupancy grid,
//! evaluation, checkpoints and events.

pub mod eval;
pub mod folder_error;
pub mod kept;
pub mod lock;
pub mod log;
pub mod run;
pub mod trainer;

// The model layer's modules, under their former paths (the app, the
// command line and the tests still name them so).
pub use crate::model::{self, batch, checkpoint};
