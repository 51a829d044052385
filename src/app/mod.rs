//! The eframe viewer: viewport, camera controls, panels and plots, drawn
//! from what the training thread of [`crate::session`] sends.

pub mod ui;
pub mod viewer;
