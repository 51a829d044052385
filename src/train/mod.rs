//! The training loop: batches, schedules, the optimiser, the occupancy grid,
//! evaluation, checkpoints and events.

pub mod eval;
pub mod folder_error;
pub mod kept;
pub mod lock;
pub mod log;
pub mod run;
pub mod trainer;
