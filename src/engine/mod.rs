//! How fields are computed: the `cpu` engine (Rust, rayon), which is also the
//! reference for tests, and the `gpu` engine (wgpu).

pub mod cpu;
pub mod gpu;
