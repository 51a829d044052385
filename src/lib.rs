//! zrak: train neural radiance fields while you watch.
//!
//! Data flows one way: [`scene`] makes rays and target colours, [`engine`]
//! computes on them, [`metrics`] scores the results. See `docs/design.md` for
//! the whole picture.

pub mod app;
pub mod bench;
pub mod crc32c;
pub mod engine;
pub mod field;
pub mod files;
pub mod interrupt;
pub mod isa;
pub mod mesh;
pub mod metrics;
pub mod model;
pub mod render;
pub mod rng;
pub mod scene;
pub mod session;
pub mod train;
