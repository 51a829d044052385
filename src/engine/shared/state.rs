//! What a model's checkpoint holds, on either engine, so checkpoints move
//! between engines: a small JSON header, the parameters, Adam's state and,
//! for models that march through one, the occupancy grid.

use serde::{Deserialize, Serialize};

use super::adam::Adam;
use crate::field::common::LossKind;
use crate::model::checkpoint::Checkpoint;

/// The checkpoint header of a model.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub(crate) struct ModelHeader {
    /// "ngp", "nerf", …
    pub model: String,
    pub loss: LossKind,
    pub seed: u64,
    pub adam_step: u32,
    pub samples_per_ray: Option<f64>,
    pub param_count: usize,
    /// The sampler, for models that have a choice ("paper", "occupancy").
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sampling: Option<String>,
    /// The share of marched samples the last step used (before their ray's
    /// cut), by which the cpu engine orders its next step's passes.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub used_fraction: Option<f64>,
    /// The side of the box an Instant-NGP hash grid spans (the scene's
    /// aabb_scale); absent from checkpoints written before the grid spanned
    /// the box rather than the unit cube.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub grid_extent: Option<f32>,
    /// Training images with appearance embeddings, for a model that has
    /// them (absent otherwise, and from checkpoints written before they
    /// existed).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub appearance_images: Option<usize>,
}

impl ModelHeader {
    /// Whether the checkpoint's hash grid spans the box this model's does
    /// (`extent`). Checkpoints without the field spanned the unit cube: they
    /// serve object scenes as before, but on a large scene their field
    /// outside the unit cube was the cube's faces drawn outward, which the
    /// box-spanning grid cannot read back.
    pub fn check_grid_extent(&self, extent: f32) -> Result<(), String> {
        match self.grid_extent {
            Some(saved) if saved == extent => Ok(()),
            None if extent == 1.0 => Ok(()),
            Some(saved) => Err(format!(
                "the checkpoint's hash grid spans a box of side {saved}, this scene's {extent}"
            )),
            None => Err(format!(
                "the checkpoint was written before zrak's hash grid spanned a large scene's \
                 whole box (aabb_scale {extent}); its field does not carry over: train the scene again"
            )),
        }
    }
}

/// Whether `checkpoint` was trained with the appearance embeddings the
/// model has (`images`: its training images with embeddings, `None`
/// without), before its parameter count is compared: a checkpoint of the
/// other kind says so rather than that the counts differ. A header that
/// does not read is left to [`ModelState::from_checkpoint`] to refuse.
pub(crate) fn check_appearance(
    checkpoint: &Checkpoint,
    images: Option<usize>,
) -> Result<(), String> {
    let Ok(header) = serde_json::from_value::<ModelHeader>(checkpoint.header.clone()) else {
        return Ok(());
    };
    match (header.appearance_images, images) {
        (saved, wanted) if saved == wanted => Ok(()),
        (Some(saved), None) => Err(format!(
            "the checkpoint was trained with appearance embeddings (of {saved} training images) \
             and this model has none: load it with appearance on"
        )),
        (None, Some(_)) => Err(
            "the checkpoint was trained without appearance embeddings and this model has them: \
             load it with appearance off"
                .into(),
        ),
        (Some(saved), Some(wanted)) => Err(format!(
            "the checkpoint has appearance embeddings of {saved} training images, this scene \
             {wanted}"
        )),
        (None, None) => Ok(()),
    }
}

/// Everything a checkpoint holds.
pub(crate) struct ModelState {
    pub header: ModelHeader,
    pub params: Vec<f32>,
    pub adam: Adam,
    pub occupancy: Option<Vec<f32>>,
    /// Camera refinement's pose corrections and their optimiser's state.
    pub cameras: Option<CameraState>,
}

/// The pose corrections of a model that refines its cameras
/// ([`super::camera_refinement`]), six values per training image.
pub(crate) struct CameraState {
    pub values: Vec<f32>,
    pub adam: Adam,
}

impl ModelState {
    pub fn into_checkpoint(self) -> Checkpoint {
        let mut tensors = vec![
            ("params".into(), self.params),
            ("adam.m".into(), self.adam.m),
            ("adam.v".into(), self.adam.v),
            ("adam.m_norm".into(), self.adam.m_norm),
            ("adam.v_norm".into(), self.adam.v_norm),
        ];
        if let Some(occupancy) = self.occupancy {
            tensors.push(("occupancy".into(), occupancy));
        }
        let mut header = serde_json::to_value(&self.header).expect("serialisable");
        if let Some(cameras) = self.cameras {
            header["cameras_adam_step"] = cameras.adam.step.into();
            tensors.extend([
                ("cameras".into(), cameras.values),
                ("cameras.adam.m".into(), cameras.adam.m),
                ("cameras.adam.v".into(), cameras.adam.v),
                ("cameras.adam.m_norm".into(), cameras.adam.m_norm),
                ("cameras.adam.v_norm".into(), cameras.adam.v_norm),
            ]);
        }
        Checkpoint { header, tensors }
    }

    /// Reads and checks every part before the caller changes anything, so
    /// a bad checkpoint leaves the model as it was. `model` is the header's
    /// expected model name; `occupancy_len` the grid's size, if the model
    /// has a grid; `cameras_len` the pose corrections' count, if the model
    /// refines its cameras (a checkpoint without them starts them at zero).
    pub fn from_checkpoint(
        checkpoint: &Checkpoint,
        model: &str,
        param_count: usize,
        occupancy_len: Option<usize>,
        cameras_len: Option<usize>,
    ) -> Result<Self, String> {
        let header: ModelHeader = serde_json::from_value(checkpoint.header.clone())
            .map_err(|e| format!("not a checkpoint of a model: {e}"))?;
        if header.model != model {
            return Err(format!(
                "the checkpoint holds a `{}` model, not `{model}`",
                header.model
            ));
        }
        if header.param_count != param_count {
            return Err(format!(
                "the checkpoint has {} parameters, this model {param_count}",
                header.param_count
            ));
        }
        let tensor = |name: &str, len: usize| -> Result<Vec<f32>, String> {
            let values = checkpoint
                .tensor(name)
                .ok_or_else(|| format!("the checkpoint has no `{name}`"))?;
            if values.len() != len {
                return Err(format!(
                    "`{name}` has {} values, expected {len}",
                    values.len()
                ));
            }
            Ok(values.to_vec())
        };
        let adam = Adam {
            m: tensor("adam.m", param_count)?,
            v: tensor("adam.v", param_count)?,
            m_norm: tensor("adam.m_norm", param_count)?,
            v_norm: tensor("adam.v_norm", param_count)?,
            step: header.adam_step,
        };
        let cameras = match cameras_len {
            Some(len) if checkpoint.tensor("cameras").is_some() => Some(CameraState {
                values: tensor("cameras", len)?,
                adam: Adam {
                    m: tensor("cameras.adam.m", len)?,
                    v: tensor("cameras.adam.v", len)?,
                    m_norm: tensor("cameras.adam.m_norm", len)?,
                    v_norm: tensor("cameras.adam.v_norm", len)?,
                    step: checkpoint.header["cameras_adam_step"]
                        .as_u64()
                        .ok_or("the checkpoint's cameras have no optimiser step")?
                        as u32,
                },
            }),
            _ => None,
        };
        Ok(Self {
            params: tensor("params", param_count)?,
            adam,
            occupancy: occupancy_len
                .map(|len| tensor("occupancy", len))
                .transpose()?,
            cameras,
            header,
        })
    }
}

#[cfg(test)]
mod tests {
    use proptest::prelude::*;
    use serde_json::{Value, json};

    use super::*;

    fn valid_header() -> Value {
        json!({"model": "ngp", "loss": "Huber", "seed": 0, "adam_step": 3,
            "samples_per_ray": 4.0, "param_count": 4})
    }

    /// An Instant-NGP checkpoint reads back only into a grid over the same
    /// box; one without the field (written when every grid spanned the unit
    /// cube) still serves object scenes, and a large scene refuses it,
    /// saying why.
    #[test]
    fn grid_extent_must_match_the_scenes_box() {
        let header = |extent: Option<f32>| {
            let mut value = valid_header();
            if let Some(extent) = extent {
                value["grid_extent"] = json!(extent);
            }
            serde_json::from_value::<ModelHeader>(value).expect("a valid header")
        };
        assert_eq!(header(None).check_grid_extent(1.0), Ok(()));
        assert_eq!(header(Some(8.0)).check_grid_extent(8.0), Ok(()));
        let old = header(None).check_grid_extent(8.0).unwrap_err();
        assert!(
            old.contains("aabb_scale 8") && old.contains("train the scene again"),
            "{old}"
        );
        let other = header(Some(4.0)).check_grid_extent(8.0).unwrap_err();
        assert!(
            other.contains("side 4") && other.contains("scene's 8"),
            "{other}"
        );
        // Written and read back.
        let written = serde_json::to_value(header(Some(8.0))).expect("serialisable");
        assert_eq!(written["grid_extent"], json!(8.0));
    }

    /// Header values of the wrong type, size or content.
    fn header_value() -> impl Strategy<Value = Value> {
        prop_oneof![
            Just(Value::Null),
            any::<i64>().prop_map(Value::from),
            any::<u64>().prop_map(Value::from),
            (-1e40f64..1e40).prop_map(Value::from),
            prop::sample::select(vec!["ngp", "nerf", "Huber", "L2", "", "paper"])
                .prop_map(Value::from),
            Just(json!([])),
            Just(json!({})),
        ]
    }

    fn header() -> impl Strategy<Value = Value> {
        prop::collection::vec(
            (
                prop::sample::select(vec![
                    "model",
                    "loss",
                    "seed",
                    "adam_step",
                    "samples_per_ray",
                    "param_count",
                    "sampling",
                ]),
                prop::option::of(header_value()),
            ),
            0..4,
        )
        .prop_map(|edits| {
            let mut header = valid_header();
            for (key, value) in edits {
                match value {
                    Some(value) => header[key] = value,
                    None => {
                        header.as_object_mut().expect("an object").remove(key);
                    }
                }
            }
            header
        })
    }

    fn tensors() -> impl Strategy<Value = Vec<(String, Vec<f32>)>> {
        prop::collection::vec(
            (
                prop::sample::select(vec![
                    "params",
                    "adam.m",
                    "adam.v",
                    "adam.m_norm",
                    "adam.v_norm",
                    "occupancy",
                    "other",
                ]),
                prop::collection::vec(any::<f32>(), 0..10),
            ),
            0..8,
        )
        .prop_map(|list| list.into_iter().map(|(n, v)| (n.to_string(), v)).collect())
    }

    proptest! {
        #![proptest_config(ProptestConfig {
            cases: 500,
            failure_persistence: None,
            ..ProptestConfig::default()
        })]

        /// Whatever a checkpoint file held, reading a model's state from it
        /// gives that state with every length as the model needs, or an
        /// error; it never panics.
        #[test]
        fn model_state_from_any_checkpoint(header in header(), tensors in tensors()) {
            let checkpoint = Checkpoint { header, tensors };
            if let Ok(state) = ModelState::from_checkpoint(&checkpoint, "ngp", 4, Some(8), None) {
                prop_assert_eq!(state.params.len(), 4);
                prop_assert_eq!(state.adam.v_norm.len(), 4);
                prop_assert_eq!(state.occupancy.map(|o| o.len()), Some(8));
            }
        }
    }
}
