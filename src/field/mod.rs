//! What is learned: each model's encodings, network shapes, activations,
//! sampling strategy and paper defaults, one place per model.

pub mod common;
pub mod nerf;
pub mod ngp;

/// The models zrak trains.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "lowercase")]
pub enum ModelKind {
    /// Instant-NGP (Müller et al. 2022).
    Ngp,
    /// NeRF (Mildenhall et al. 2020).
    Nerf,
}

impl ModelKind {
    pub const ALL: [ModelKind; 2] = [ModelKind::Ngp, ModelKind::Nerf];

    pub fn name(self) -> &'static str {
        match self {
            ModelKind::Ngp => "Instant-NGP",
            ModelKind::Nerf => "NeRF",
        }
    }

    /// The name on the command line and in files (`--model ngp`).
    pub fn key(self) -> &'static str {
        match self {
            ModelKind::Ngp => "ngp",
            ModelKind::Nerf => "nerf",
        }
    }
}
