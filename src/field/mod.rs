//! What is learned: each model's encodings, network shapes, activations,
//! sampling strategy and paper defaults, one place per model.

pub mod ngp;

/// The models zrak trains.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "lowercase")]
pub enum ModelKind {
    /// Instant-NGP (Müller et al. 2022).
    Ngp,
}

impl ModelKind {
    pub const ALL: [ModelKind; 1] = [ModelKind::Ngp];

    pub fn name(self) -> &'static str {
        match self {
            ModelKind::Ngp => "Instant-NGP",
        }
    }
}
