//! The `cpu` engine: every stage in plain Rust, and the reference the `gpu`
//! engine is tested against.

pub mod composite;
