//! Where each part of a model's parameters sits in its one flat vector, and
//! how the optimiser treats it: what a field declares, and what Adam (on
//! either engine), the checkpoint and the gradient checks read.

use std::ops::Range;

/// How Adam updates a range of parameters.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Update {
    /// Every step, whatever the gradient (network weights: a zero gradient
    /// there is a dead unit, whose momentum and decay still apply). With
    /// `l2`, the optimiser's weight decay (λ·p, `OptimiserConfig::l2_weights`)
    /// is added to the gradient first.
    Dense { l2: bool },
    /// Only where the gradient is non-zero: a hash-table entry that no
    /// sample touched keeps its value, moments and bias correction
    /// (tiny-cuda-nn's Adam for instant-ngp, `optimizers/adam.h`). No
    /// weight decay.
    Sparse,
}

/// The name of a field's part that holds its appearance embeddings
/// ([`crate::field::appearance`]).
pub const APPEARANCE_PART: &str = "appearance embeddings";

/// A named part of the parameters.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ParamRange {
    /// "hash grid", "density network", …
    pub name: String,
    pub range: Range<usize>,
    pub update: Update,
}

/// A model's (or a field's) parameters, part after part, with no gaps.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct ParamLayout {
    parts: Vec<ParamRange>,
}

impl ParamLayout {
    pub fn new() -> Self {
        Self::default()
    }

    /// This layout with a part of `len` parameters after the last.
    pub fn with(mut self, name: impl Into<String>, len: usize, update: Update) -> Self {
        let start = self.len();
        self.parts.push(ParamRange {
            name: name.into(),
            range: start..start + len,
            update,
        });
        self
    }

    /// Appends `other`'s parts after this layout's, their names prefixed by
    /// `prefix` (e.g. "field 1: ").
    pub fn append(&mut self, other: &ParamLayout, prefix: &str) {
        let start = self.len();
        self.parts.extend(other.parts.iter().map(|part| ParamRange {
            name: format!("{prefix}{}", part.name),
            range: part.range.start + start..part.range.end + start,
            update: part.update,
        }));
    }

    /// Parameters in all.
    pub fn len(&self) -> usize {
        self.parts.last().map_or(0, |p| p.range.end)
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    pub fn parts(&self) -> &[ParamRange] {
        &self.parts
    }

    /// The span of the dense parts and whether they take weight decay, where
    /// they are contiguous and agree on it (every model's layout: NeRF's is
    /// all dense, Instant-NGP's a sparse grid then dense networks): one
    /// pass of an optimiser that knows one dense range then updates the
    /// whole vector. `None` where the layout needs one pass per part. A
    /// layout without dense parts gives an empty span.
    pub fn single_dense_span(&self) -> Option<(Range<usize>, bool)> {
        let mut span: Option<(Range<usize>, bool)> = None;
        for part in &self.parts {
            let Update::Dense { l2 } = part.update else {
                continue;
            };
            span = match span {
                None => Some((part.range.clone(), l2)),
                Some((range, decay)) if range.end == part.range.start && decay == l2 => {
                    Some((range.start..part.range.end, decay))
                }
                Some(_) => return None,
            };
        }
        Some(span.unwrap_or((0..0, false)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parts_follow_each_other_and_append_shifts_them() {
        let grid = ParamLayout::new()
            .with("hash grid", 10, Update::Sparse)
            .with("density network", 4, Update::Dense { l2: true });
        assert_eq!(grid.len(), 14);
        assert_eq!(grid.parts()[1].range, 10..14);
        let mut model = ParamLayout::new().with("a", 3, Update::Dense { l2: false });
        model.append(&grid, "field 1: ");
        assert_eq!(model.len(), 17);
        assert_eq!(model.parts()[1].name, "field 1: hash grid");
        assert_eq!(model.parts()[2].range, 13..17);
    }

    #[test]
    fn one_dense_span_where_the_dense_parts_are_contiguous() {
        let ngp = ParamLayout::new()
            .with("grid", 10, Update::Sparse)
            .with("density", 4, Update::Dense { l2: true })
            .with("colour", 6, Update::Dense { l2: true });
        assert_eq!(ngp.single_dense_span(), Some((10..20, true)));
        let split = ngp.clone().with("grid 2", 3, Update::Sparse).with(
            "more",
            2,
            Update::Dense { l2: true },
        );
        assert_eq!(split.single_dense_span(), None);
        let mixed_decay = ParamLayout::new()
            .with("a", 2, Update::Dense { l2: true })
            .with("b", 2, Update::Dense { l2: false });
        assert_eq!(mixed_decay.single_dense_span(), None);
        let sparse = ParamLayout::new().with("grid", 5, Update::Sparse);
        assert_eq!(sparse.single_dense_span(), Some((0..0, false)));
    }
}
