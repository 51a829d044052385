//! The training loop: batches, schedules, the optimiser, the occupancy grid,
//! evaluation, checkpoints and events.

pub mod batch;
pub mod checkpoint;
pub mod eval;
pub mod log;
pub mod model;
pub mod run;
pub mod trainer;
