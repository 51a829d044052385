//! The eframe viewer: viewport, camera controls, panels, plots, and the
//! training thread it talks to.

pub mod camera;
pub mod path_state;
pub mod progressive;
pub mod protocol;
pub mod schedule;
pub mod ui;
pub mod viewer;
pub mod worker;
