//! The parameters of a model's fields: how they are laid out and their
//! initial values, from the `cpu` engine's fields. What the two engines'
//! drivers share (ray bounds, chunk seeds, the grid's sample inputs) is in
//! [`crate::engine::shared::driver`], re-exported here.

use super::*;
pub use crate::engine::shared::driver::*;

/// The parameters of `fields` laid out one after the other, each from its
/// own seed ([`Field::init_seed`]), and where each sits. Both engines start
/// a model from these, so a model starts identical on either.
pub fn init_field_params<F: AsRef<dyn Field>>(
    fields: &[F],
    seed: u64,
) -> (Vec<f32>, Vec<Range<usize>>) {
    let mut params = Vec::new();
    let mut ranges = Vec::new();
    for (i, field) in fields.iter().enumerate() {
        let field = field.as_ref();
        let start = params.len();
        params.extend(field.init_params(field.init_seed(seed, i)));
        assert_eq!(params.len() - start, field.param_count(), "field {i}");
        ranges.push(start..params.len());
    }
    (params, ranges)
}

/// The parts of `fields`' parameters one after the other (named "field
/// i: …" where there are several fields).
pub fn model_layout<F: AsRef<dyn Field>>(fields: &[F]) -> ParamLayout {
    let mut layout = ParamLayout::new();
    for (i, field) in fields.iter().enumerate() {
        let prefix = if fields.len() > 1 {
            format!("field {i}: ")
        } else {
            String::new()
        };
        layout.append(&field.as_ref().layout(), &prefix);
    }
    layout
}
