//! Command bodies that have outgrown `main.rs`, one file per command.

pub mod quality;
