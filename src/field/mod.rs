//! What is learned: each model's encodings, network shapes, activations,
//! sampling strategy and paper defaults, one place per model.

pub mod ngp;
