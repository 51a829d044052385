//! A model's fields as the engines build them: one variant per kind of
//! field, with what both engines take from it before any pass runs (the
//! parameters' layout and their initial values). A model of several
//! fields (NeRF's coarse and fine networks) has that many of one shape.

use std::ops::Range;

use super::mlp::Precision;
use super::nerf::NerfShape;
use super::ngp::NgpShape;
use super::params::ParamLayout;

/// The shape of a model's fields: the only place, with each engine's
/// `fields_for`, where the kinds of field are told apart.
#[derive(Debug, Clone)]
pub enum FieldShape {
    /// Instant-NGP's hash grid with its density and colour networks.
    Ngp(NgpShape),
    /// NeRF's networks on a frequency encoding (Mip-NeRF's on the
    /// integrated one).
    Nerf(NerfShape),
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
        }
    }

    /// One field's initial parameters, reproducible from `seed`.
    pub fn init_params(&self, seed: u64) -> Vec<f32> {
        match self {
            FieldShape::Ngp(shape) => shape.init_params(seed),
            FieldShape::Nerf(shape) => shape.init_params(seed),
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
            FieldShape::Nerf(_) => field_seed(model_seed, index),
        }
    }

    /// The same fields with their networks' products at `precision` (the
    /// `cpu` engine's choice; the `gpu` engine computes in f32).
    pub fn with_precision(self, precision: Precision) -> Self {
        match self {
            FieldShape::Ngp(shape) => FieldShape::Ngp(shape.with_precision(precision)),
            FieldShape::Nerf(shape) => FieldShape::Nerf(shape.with_precision(precision)),
        }
    }

    /// The initial parameters of a model of `fields` fields of this shape,
    /// one after the other, and where each sits. Both engines start a model
    /// from these, so a model starts identical on either.
    pub fn model_params(&self, fields: usize, seed: u64) -> (Vec<f32>, Vec<Range<usize>>) {
        let mut params = Vec::new();
        let mut ranges = Vec::new();
        for index in 0..fields {
            let start = params.len();
            params.extend(self.init_params(self.init_seed(seed, index)));
            ranges.push(start..params.len());
        }
        (params, ranges)
    }

    /// The parts of such a model's parameters, one field after the other
    /// (named "field i: …" where there are several).
    pub fn model_layout(&self, fields: usize) -> ParamLayout {
        let one = self.layout();
        let mut layout = ParamLayout::new();
        for index in 0..fields {
            let prefix = if fields > 1 {
                format!("field {index}: ")
            } else {
                String::new()
            };
            layout.append(&one, &prefix);
        }
        layout
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_model_of_several_fields_seeds_each_apart_and_lays_them_out_in_turn() {
        let shape = FieldShape::Nerf(NerfShape::paper());
        let (params, ranges) = shape.model_params(2, 7);
        let one = shape.layout().len();
        assert_eq!(ranges, vec![0..one, one..2 * one]);
        assert_eq!(params.len(), 2 * one);
        assert_eq!(params[..one], shape.init_params(field_seed(7, 0))[..]);
        assert_ne!(params[..one], params[one..]);
        assert_eq!(shape.model_layout(2).len(), 2 * one);
    }
}
