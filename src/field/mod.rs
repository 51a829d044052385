//! What is learned: each model's encodings, network shapes, activations,
//! sampling strategy and paper defaults, one place per model.

pub mod common;
pub mod mipnerf;
pub mod nerf;
pub mod ngp;
pub mod params;

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
    /// Mip-NeRF (Barron et al. 2021).
    #[value(name = "mipnerf")]
    MipNerf,
}

impl ModelKind {
    pub const ALL: [ModelKind; 3] = [ModelKind::Ngp, ModelKind::Nerf, ModelKind::MipNerf];

    pub fn name(self) -> &'static str {
        match self {
            ModelKind::Ngp => "Instant-NGP",
            ModelKind::Nerf => "NeRF",
            ModelKind::MipNerf => "Mip-NeRF",
        }
    }

    /// The loss the model trains with unless told otherwise: Huber for
    /// Instant-NGP (instant-ngp's default `loss`), the squared error of
    /// the NeRF and Mip-NeRF papers for them.
    pub fn default_loss(self) -> ngp::LossKind {
        match self {
            ModelKind::Ngp => ngp::LossKind::Huber,
            ModelKind::Nerf | ModelKind::MipNerf => ngp::LossKind::L2,
        }
    }

    /// The name on the command line and in files (`--model ngp`).
    pub fn key(self) -> &'static str {
        match self {
            ModelKind::Ngp => "ngp",
            ModelKind::Nerf => "nerf",
            ModelKind::MipNerf => "mipnerf",
        }
    }
}
