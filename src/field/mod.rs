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

    /// The model's row of [`MODELS`].
    pub fn spec(self) -> &'static ModelSpec {
        &MODELS[self as usize]
    }

    pub fn name(self) -> &'static str {
        self.spec().name
    }

    /// The loss the model trains with unless told otherwise.
    pub fn default_loss(self) -> ngp::LossKind {
        self.spec().default_loss
    }

    /// The name on the command line and in files (`--model ngp`).
    pub fn key(self) -> &'static str {
        self.spec().key
    }

    /// Whether it also trains with its paper's own sampler (NeRF's and
    /// Mip-NeRF's stratified plus hierarchical samples), besides the
    /// occupancy grid.
    pub fn has_paper_sampler(self) -> bool {
        self.spec().samplings.contains(&nerf::Sampling::Paper)
    }
}

/// What zrak says of a model wherever it names one (the command line, the
/// viewer, the reports and plots): one row per model, in [`ModelKind`]'s
/// order, so a new model is a new row rather than an arm in every `match`.
#[derive(Debug)]
pub struct ModelSpec {
    pub kind: ModelKind,
    pub name: &'static str,
    pub key: &'static str,
    /// The paper it follows.
    pub paper: &'static str,
    /// Huber for Instant-NGP (instant-ngp's default `loss`), the squared
    /// error of the NeRF and Mip-NeRF papers for them.
    pub default_loss: ngp::LossKind,
    /// The samplers it trains with, its default first.
    pub samplings: &'static [nerf::Sampling],
    /// Its colour in the viewer's plots and the exported ones (RGB).
    pub colour: [u8; 3],
}

/// Every model, in [`ModelKind`]'s order.
pub const MODELS: [ModelSpec; 3] = [
    ModelSpec {
        kind: ModelKind::Ngp,
        name: "Instant-NGP",
        key: "ngp",
        paper: "Müller et al. 2022",
        default_loss: ngp::LossKind::Huber,
        samplings: &[nerf::Sampling::Occupancy],
        colour: [0x4c, 0x9b, 0xe8],
    },
    ModelSpec {
        kind: ModelKind::Nerf,
        name: "NeRF",
        key: "nerf",
        paper: "Mildenhall et al. 2020",
        default_loss: ngp::LossKind::L2,
        samplings: &[nerf::Sampling::Occupancy, nerf::Sampling::Paper],
        colour: [0xe8, 0x8a, 0x3c],
    },
    ModelSpec {
        kind: ModelKind::MipNerf,
        name: "Mip-NeRF",
        key: "mipnerf",
        paper: "Barron et al. 2021",
        default_loss: ngp::LossKind::L2,
        samplings: &[nerf::Sampling::Occupancy, nerf::Sampling::Paper],
        colour: [0x5c, 0xc0, 0x6a],
    },
];

#[cfg(test)]
mod spec_tests {
    use super::*;

    #[test]
    fn every_model_has_its_own_row_and_name() {
        for (index, kind) in ModelKind::ALL.into_iter().enumerate() {
            assert_eq!(MODELS[index].kind, kind, "row {index}");
            assert_eq!(kind.spec().kind, kind);
        }
        let mut keys: Vec<_> = MODELS.iter().map(|m| m.key).collect();
        keys.dedup();
        assert_eq!(keys.len(), MODELS.len());
        // The key is what clap and serde read and write.
        for model in &MODELS {
            let parsed = <ModelKind as clap::ValueEnum>::from_str(model.key, false);
            assert_eq!(parsed, Ok(model.kind), "{}", model.key);
            assert_eq!(
                serde_json::to_value(model.kind).unwrap(),
                serde_json::Value::from(model.key)
            );
        }
        assert!(!ModelKind::Ngp.has_paper_sampler());
        assert!(ModelKind::Nerf.has_paper_sampler() && ModelKind::MipNerf.has_paper_sampler());
    }
}
