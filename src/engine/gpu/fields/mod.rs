//! Fields on the `gpu` engine: what maps a sample (position, direction) to
//! density and colour, forward and backward, recorded into a command
//! encoder. The gpu twins of [`crate::engine::cpu::fields`], with the same
//! parameter layouts, so a model's parameters move between engines as they
//! are.

pub mod nerf;
