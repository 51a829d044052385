//! What is learned: each model's encodings, network shapes, activations,
//! sampling strategy and paper defaults, one place per model.

pub mod appearance;
pub mod camera;
pub mod common;
pub mod contraction;
pub mod encoding;
pub mod mipnerf;
pub mod mlp;
pub mod nerf;
pub mod ngp;
pub mod params;

use std::ops::Range;

use crate::scene::{Scene, SceneFormat};
use common::Sampling;
use mlp::Precision;
use nerf::NerfShape;
use ngp::NgpShape;
use params::ParamLayout;

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
    /// Every model, in [`MODELS`]'s order (read from it, so a new model is
    /// a variant and a row).
    pub const ALL: [ModelKind; MODELS.len()] = {
        let mut all = [ModelKind::Ngp; MODELS.len()];
        let mut index = 0;
        while index < MODELS.len() {
            all[index] = MODELS[index].kind;
            index += 1;
        }
        all
    };

    /// The model's row of [`MODELS`].
    pub fn spec(self) -> &'static ModelSpec {
        &MODELS[self as usize]
    }

    pub fn name(self) -> &'static str {
        self.spec().name
    }

    /// The loss the model trains with unless told otherwise.
    pub fn default_loss(self) -> crate::field::common::LossKind {
        self.spec().default_loss
    }

    /// The name on the command line and in files (`--model ngp`).
    pub fn key(self) -> &'static str {
        self.spec().key
    }

    /// The sampler it trains with on a scene of `space` unless told
    /// otherwise, and why: the proposal sampler in an unbounded scene's
    /// contracted space where the model has one, else its default.
    pub fn sampling_for(self, space: crate::scene::SceneSpace) -> (Sampling, &'static str) {
        let spec = self.spec();
        if space == crate::scene::SceneSpace::Unbounded
            && spec.samplings.contains(&Sampling::Proposal)
        {
            return (
                Sampling::Proposal,
                "the scene is unbounded: proposal fields sample its contracted space",
            );
        }
        (spec.samplings[0], "the model's default sampler")
    }

    /// The sampler asked for, if the model has it, else an error that names
    /// the ones it has; with none asked for, [`Self::sampling_for`]'s.
    pub fn choose_sampling(
        self,
        requested: Option<Sampling>,
        space: crate::scene::SceneSpace,
    ) -> Result<Sampling, String> {
        let spec = self.spec();
        match requested {
            None => Ok(self.sampling_for(space).0),
            Some(sampling) if spec.samplings.contains(&sampling) => Ok(sampling),
            Some(sampling) => Err(format!(
                "{} has no {} sampler (it has: {})",
                spec.name,
                sampling.name(),
                spec.samplings
                    .iter()
                    .map(|s| s.name())
                    .collect::<Vec<_>>()
                    .join(", ")
            )),
        }
    }

    /// Whether it also trains with its paper's own sampler (NeRF's and
    /// Mip-NeRF's stratified plus hierarchical samples), besides the
    /// occupancy grid.
    pub fn has_paper_sampler(self) -> bool {
        self.spec()
            .samplings
            .contains(&crate::field::common::Sampling::Paper)
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
    pub default_loss: crate::field::common::LossKind,
    /// The samplers it trains with, its default first.
    pub samplings: &'static [crate::field::common::Sampling],
    /// Its colour in the viewer's plots and the exported ones (RGB).
    pub colour: [u8; 3],
    /// Its recipe for a scene with a sampler (of [`Self::samplings`]).
    pub recipe: fn(&Scene, crate::field::common::Sampling) -> common::Recipe,
    /// The shape of its fields for a scene and sampler, the paper's (the
    /// proposal fields' come from it: [`FieldShape::for_recipe`]).
    pub shape: fn(&Scene, crate::field::common::Sampling) -> FieldShape,
    /// The sampler that its labels and checkpoints leave unnamed: a model's
    /// only sampler before it had a choice (Instant-NGP's occupancy grid),
    /// so its earlier checkpoints still load.
    pub unnamed_sampling: Option<crate::field::common::Sampling>,
    /// Samples per batch on the `gpu` engine where its recipe's batch is in
    /// samples sized for the cpu's, and the settings name none (`None`
    /// keeps the recipe's).
    pub gpu_batch_samples: Option<usize>,
    /// The viewer's training batches where the recipe's would make a step
    /// too long to wait behind.
    pub viewer_batch: ViewerBatch,
    /// Unmeasured steps before `zrak bench throughput` measures the model
    /// with its default sampler: past the occupancy grid's warm-up (its
    /// first updates visit every cell, twice the work of a later one) and
    /// a few updates more, so the figures are those of most of a run.
    pub bench_warmup_steps: usize,
    /// The share of changed parameters whose first Adam updates may differ
    /// between the engines in `zrak bench gpu`'s self-check: Adam's first
    /// steps move each parameter by about lr · sign(g), and where a
    /// gradient is at the level of summation-order noise its sign may
    /// differ between engines. The parity tests allow the same
    /// (`tests/it/ngp_gpu.rs`, `tests/it/nerf_gpu.rs`).
    pub engine_update_mismatch_share: f64,
}

/// The viewer's training batches, in samples, where the recipe's own would
/// make a step too long for the commands and render chunks that wait
/// behind it (`None` keeps the recipe's).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ViewerBatch {
    /// On the cpu engine with the model's default sampler.
    pub cpu: Option<usize>,
    /// With the paper's sampler on the cpu engine, or on a software gpu
    /// adapter (lavapipe's few GFLOP/s).
    pub slow: Option<usize>,
}

/// Instant-NGP's batch in the viewer on the cpu engine: a quarter of its
/// 2^18 samples, so a step takes ~60 ms rather than ~250 ms on two cores.
/// Commands and render chunks wait behind at most one step, and the view
/// improves in more, smaller steps during the first minute.
const NGP_VIEWER_CPU_SAMPLES: usize = 1 << 16;

/// NeRF's and Mip-NeRF's batch in the viewer with the paper's samplers, or
/// on a software gpu adapter: the paper's 1024 rays × 256 samples of the
/// 8 × 256 network are ~1 T FLOP a step, seconds on two cores (minutes on
/// lavapipe), so 2^12 samples. With the occupancy sampler on the cpu
/// engine they train on their recipe's batch (2^14 samples, ~0.15 s a
/// step on two cores), as `zrak train` does: their occupancy grid is
/// updated every 16 steps whatever the batch, at ~20 steps' cost (64³
/// density queries of the 8 × 256 network), so a quarter of the batch
/// spent half of the viewer's training time on grid updates (measured on
/// lego_400: 21.6 of 42.2 s), twice `zrak train`'s share; and the same
/// batch makes the viewer's steps comparable with `zrak train`'s.
const NERF_VIEWER_SMALL_SAMPLES: usize = 1 << 12;

/// Every model, in [`ModelKind`]'s order.
pub const MODELS: &[ModelSpec] = &[
    ModelSpec {
        kind: ModelKind::Ngp,
        name: "Instant-NGP",
        key: "ngp",
        paper: "Müller et al. 2022",
        default_loss: crate::field::common::LossKind::Huber,
        samplings: &[
            crate::field::common::Sampling::Occupancy,
            crate::field::common::Sampling::Proposal,
        ],
        colour: [0x4c, 0x9b, 0xe8],
        recipe: |scene, sampling| match sampling {
            crate::field::common::Sampling::Proposal => ngp::proposal_recipe(scene),
            _ => ngp::recipe(scene.unit_cube.aabb_scale),
        },
        shape: |scene, sampling| match sampling {
            crate::field::common::Sampling::Proposal => ngp::NgpShape::contracted(scene).into(),
            _ => ngp::NgpShape::for_scene(scene).into(),
        },
        unnamed_sampling: Some(crate::field::common::Sampling::Occupancy),
        gpu_batch_samples: None,
        viewer_batch: ViewerBatch {
            cpu: Some(NGP_VIEWER_CPU_SAMPLES),
            slow: None,
        },
        bench_warmup_steps: crate::field::common::OccupancyConfig::PAPER.warmup_steps as usize + 32,
        engine_update_mismatch_share: 0.001,
    },
    ModelSpec {
        kind: ModelKind::Nerf,
        name: "NeRF",
        key: "nerf",
        paper: "Mildenhall et al. 2020",
        default_loss: crate::field::common::LossKind::L2,
        samplings: &[
            crate::field::common::Sampling::Occupancy,
            crate::field::common::Sampling::Paper,
            crate::field::common::Sampling::Proposal,
        ],
        colour: [0xe8, 0x8a, 0x3c],
        recipe: |scene, sampling| match sampling {
            crate::field::common::Sampling::Proposal => nerf::proposal_recipe(scene),
            _ => nerf::recipe(sampling, scene.format == SceneFormat::Blender),
        },
        shape: |_, _| nerf::NerfShape::paper().into(),
        unnamed_sampling: None,
        gpu_batch_samples: Some(nerf::GPU_OCCUPANCY_SAMPLES_PER_BATCH),
        viewer_batch: ViewerBatch {
            cpu: None,
            slow: Some(NERF_VIEWER_SMALL_SAMPLES),
        },
        // A NeRF step costs 8 × 256 network evaluations per sample: one
        // grid update past the warm-up.
        bench_warmup_steps: nerf::OCCUPANCY.warmup_steps as usize + 16,
        engine_update_mismatch_share: 0.01,
    },
    ModelSpec {
        kind: ModelKind::MipNerf,
        name: "Mip-NeRF",
        key: "mipnerf",
        paper: "Barron et al. 2021",
        default_loss: crate::field::common::LossKind::L2,
        samplings: &[
            crate::field::common::Sampling::Occupancy,
            crate::field::common::Sampling::Paper,
            crate::field::common::Sampling::Proposal,
        ],
        colour: [0x5c, 0xc0, 0x6a],
        recipe: |scene, sampling| match sampling {
            crate::field::common::Sampling::Proposal => mipnerf::proposal_recipe(scene),
            _ => mipnerf::recipe(sampling, scene.format == SceneFormat::Blender),
        },
        shape: |_, _| nerf::NerfShape::mipnerf().into(),
        unnamed_sampling: None,
        gpu_batch_samples: Some(nerf::GPU_OCCUPANCY_SAMPLES_PER_BATCH),
        viewer_batch: ViewerBatch {
            cpu: None,
            slow: Some(NERF_VIEWER_SMALL_SAMPLES),
        },
        bench_warmup_steps: nerf::OCCUPANCY.warmup_steps as usize + 16,
        engine_update_mismatch_share: 0.01,
    },
];

/// The shape of a model's fields: the only place, with each engine's
/// `fields_for`, where the kinds of field are told apart.
#[derive(Debug, Clone)]
pub enum FieldShape {
    /// Instant-NGP's hash grid with its density and colour networks.
    Ngp(NgpShape),
    /// NeRF's networks on a frequency encoding (Mip-NeRF's on the
    /// integrated one).
    Nerf(NerfShape),
    /// A density-only field on a small hash grid: a proposal level's.
    Density(ngp::DensityShape),
    /// A density-only MLP on NeRF's or Mip-NeRF's position encoding: their
    /// proposal levels' (Mip-NeRF 360's proposal MLP).
    NerfDensity(nerf::NerfDensityShape),
}

impl From<NgpShape> for FieldShape {
    fn from(shape: NgpShape) -> Self {
        FieldShape::Ngp(shape)
    }
}

impl From<NerfShape> for FieldShape {
    fn from(shape: NerfShape) -> Self {
        FieldShape::Nerf(shape)
    }
}

/// The seed of field `index`'s initial parameters from the model's seed,
/// for fields seeded one per field.
pub fn field_seed(model_seed: u64, index: usize) -> u64 {
    model_seed ^ (0x6669_656c_6400 + index as u64)
}

impl FieldShape {
    /// One field's parameters, part by part, and how the optimiser updates
    /// each.
    pub fn layout(&self) -> ParamLayout {
        match self {
            FieldShape::Ngp(shape) => shape.layout(),
            FieldShape::Nerf(shape) => shape.layout(),
            FieldShape::Density(shape) => shape.layout(),
            FieldShape::NerfDensity(shape) => shape.layout(),
        }
    }

    /// One field's initial parameters, reproducible from `seed`.
    pub fn init_params(&self, seed: u64) -> Vec<f32> {
        match self {
            FieldShape::Ngp(shape) => shape.init_params(seed),
            FieldShape::Nerf(shape) => shape.init_params(seed),
            FieldShape::Density(shape) => shape.init_params(seed),
            FieldShape::NerfDensity(shape) => shape.init_params(seed),
        }
    }

    /// The seed of the initial parameters of the model's field `index`:
    /// [`field_seed`], so that NeRF's coarse and fine networks start apart;
    /// Instant-NGP is one field seeded part by part from the model's own
    /// seed, as its first driver did, so a seed starts the same run as
    /// before.
    pub fn init_seed(&self, model_seed: u64, index: usize) -> u64 {
        match self {
            FieldShape::Ngp(_) => model_seed,
            FieldShape::Nerf(_) | FieldShape::Density(_) | FieldShape::NerfDensity(_) => {
                field_seed(model_seed, index)
            }
        }
    }

    /// The same field with a table of appearance embeddings of `appearance`
    /// for its colour network, or without (`None`); density-only fields
    /// have no colour and stay as they are.
    pub fn with_appearance(self, appearance: Option<appearance::AppearanceShape>) -> Self {
        match self {
            FieldShape::Ngp(shape) => FieldShape::Ngp(shape.with_appearance(appearance)),
            FieldShape::Nerf(shape) => FieldShape::Nerf(shape.with_appearance(appearance)),
            FieldShape::Density(_) | FieldShape::NerfDensity(_) => self,
        }
    }

    /// The table of appearance embeddings of the field, if it has one.
    pub fn appearance(&self) -> Option<appearance::AppearanceShape> {
        match self {
            FieldShape::Ngp(shape) => shape.appearance,
            FieldShape::Nerf(shape) => shape.appearance,
            FieldShape::Density(_) | FieldShape::NerfDensity(_) => None,
        }
    }

    /// The same fields with their networks' products at `precision` (the
    /// `cpu` engine's choice; the `gpu` engine computes in f32).
    pub fn with_precision(self, precision: Precision) -> Self {
        match self {
            FieldShape::Ngp(shape) => FieldShape::Ngp(shape.with_precision(precision)),
            FieldShape::Nerf(shape) => FieldShape::Nerf(shape.with_precision(precision)),
            FieldShape::Density(shape) => FieldShape::Density(shape.with_precision(precision)),
            FieldShape::NerfDensity(shape) => {
                FieldShape::NerfDensity(shape.with_precision(precision))
            }
        }
    }

    /// The shape of the proposal field that is the model's `index`-th
    /// proposal field, beside a field of this shape (`None` where the
    /// model has no proposal fields). NeRF's and Mip-NeRF's recipes have
    /// one, which serves both proposal rounds (Mip-NeRF 360's one
    /// proposal MLP), of the same shape whatever its index.
    pub fn proposal(&self, index: usize) -> Option<FieldShape> {
        match self {
            FieldShape::Ngp(_) => ngp::PROPOSAL_FINEST
                .get(index)
                .map(|&finest| FieldShape::Density(ngp::DensityShape::proposal(finest))),
            // Any number of the same MLP (a recipe may give each round its
            // own, as a test of the shared one does).
            FieldShape::Nerf(shape) => Some(FieldShape::NerfDensity(
                nerf::NerfDensityShape::proposal(shape),
            )),
            FieldShape::Density(_) | FieldShape::NerfDensity(_) => None,
        }
    }

    /// The shapes of a recipe's fields, in its order: this shape for the
    /// fields of levels that composite colour, [`Self::proposal`]'s for
    /// those of proposal levels (in the order they first appear).
    pub fn for_recipe(&self, recipe: &common::Recipe) -> Vec<FieldShape> {
        let mut proposals = 0;
        (0..recipe.fields)
            .map(|field| {
                let proposal = recipe
                    .levels
                    .iter()
                    .find(|level| level.field == field)
                    .is_some_and(|level| !level.colour);
                if !proposal {
                    return self.clone();
                }
                proposals += 1;
                self.proposal(proposals - 1)
                    .unwrap_or_else(|| panic!("{self:?} has no proposal field {}", proposals - 1))
            })
            .collect()
    }
}

/// The initial parameters of a model whose fields have `shapes`, one after
/// the other, and where each sits. Both engines start a model from these,
/// so a model starts identical on either.
pub fn model_params(shapes: &[FieldShape], seed: u64) -> (Vec<f32>, Vec<Range<usize>>) {
    let mut params = Vec::new();
    let mut ranges = Vec::new();
    for (index, shape) in shapes.iter().enumerate() {
        let start = params.len();
        params.extend(shape.init_params(shape.init_seed(seed, index)));
        ranges.push(start..params.len());
    }
    (params, ranges)
}

/// The parts of such a model's parameters, one field after the other
/// (named "field i: …" where there are several).
pub fn model_layout(shapes: &[FieldShape]) -> ParamLayout {
    let mut layout = ParamLayout::new();
    for (index, shape) in shapes.iter().enumerate() {
        let prefix = if shapes.len() > 1 {
            format!("field {index}: ")
        } else {
            String::new()
        };
        layout.append(&shape.layout(), &prefix);
    }
    layout
}

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
        for model in MODELS {
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

    #[test]
    fn an_unbounded_scene_gets_the_proposal_sampler_where_the_model_has_one() {
        use crate::scene::SceneSpace;
        let ngp = ModelKind::Ngp;
        assert_eq!(
            ngp.sampling_for(SceneSpace::Unbounded).0,
            Sampling::Proposal
        );
        assert_eq!(ngp.sampling_for(SceneSpace::Object).0, Sampling::Occupancy);
        assert_eq!(
            ngp.sampling_for(SceneSpace::ForwardFacing).0,
            Sampling::Occupancy
        );
        for nerf in [ModelKind::Nerf, ModelKind::MipNerf] {
            assert_eq!(
                nerf.sampling_for(SceneSpace::Unbounded).0,
                Sampling::Proposal
            );
            assert_eq!(nerf.sampling_for(SceneSpace::Object).0, Sampling::Occupancy);
        }
        assert_eq!(
            ngp.choose_sampling(Some(Sampling::Occupancy), SceneSpace::Unbounded),
            Ok(Sampling::Occupancy)
        );
        let refused = ngp
            .choose_sampling(Some(Sampling::Paper), SceneSpace::Object)
            .unwrap_err();
        assert_eq!(
            refused,
            "Instant-NGP has no paper sampler (it has: occupancy, proposal)"
        );
    }
}

#[cfg(test)]
mod shape_tests {
    use super::*;

    #[test]
    fn a_model_of_several_fields_seeds_each_apart_and_lays_them_out_in_turn() {
        let shape = FieldShape::Nerf(NerfShape::paper());
        let shapes = [shape.clone(), shape.clone()];
        let (params, ranges) = model_params(&shapes, 7);
        let one = shape.layout().len();
        assert_eq!(ranges, vec![0..one, one..2 * one]);
        assert_eq!(params.len(), 2 * one);
        assert_eq!(params[..one], shape.init_params(field_seed(7, 0))[..]);
        assert_ne!(params[..one], params[one..]);
        assert_eq!(model_layout(&shapes).len(), 2 * one);
    }
}
