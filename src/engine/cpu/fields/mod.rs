//! Fields on the `cpu` engine: what maps a sample (position, direction) to
//! density and colour, forward and backward. A model's driver
//! ([`super::model`]) chains a sampler, fields, compositing, the loss and
//! the optimiser; the fields are the part that differs between models.

pub mod density;
pub mod nerf;
pub mod nerf_density;
pub mod ngp;

use crate::field::FieldShape;
pub use crate::field::appearance::{Appearance, AppearanceShape};
use crate::field::params::ParamLayout;

// Where a field's positions live is a property of the field on either
// engine: declared beside the recipe.
use crate::field::common::Coordinates;

/// The model's fields of `shapes` on the `cpu` engine (their initial
/// parameters come from the shapes, [`crate::field::model_params`]).
pub fn fields_for(shapes: &[FieldShape]) -> Vec<Box<dyn Field>> {
    shapes
        .iter()
        .map(|shape| match shape {
            FieldShape::Ngp(shape) => Box::new(ngp::NgpField::new(shape.clone())) as Box<dyn Field>,
            FieldShape::Nerf(shape) => Box::new(nerf::NerfField::new(shape.clone())),
            FieldShape::Density(shape) => Box::new(density::DensityField::new(shape.clone())),
            FieldShape::NerfDensity(shape) => {
                Box::new(nerf_density::NerfDensityField::new(shape.clone()))
            }
        })
        .collect()
}

/// How a backward pass leaves the field's gradient.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Gradient {
    /// Replaces whatever the gradient held (the field's first contribution
    /// in a step: no separate clearing pass over its parameters).
    Overwrite,
    /// Adds to it (later chunks and levels of the same step).
    Add,
}

/// Density and colour at samples, with gradients.
///
/// A field holds its own scratch (activations kept between
/// [`Field::forward`] and [`Field::backward`]); its parameters live in the
/// driver's flat vector and are passed in, so one optimiser and one
/// checkpoint serve every field.
pub trait Field: Send + Sync {
    /// Its parameters, part by part, and how the optimiser updates each.
    fn layout(&self) -> ParamLayout;

    fn param_count(&self) -> usize {
        self.layout().len()
    }

    /// The dense kernels its networks run on.
    fn kernels(&self) -> crate::engine::cpu::dense::Backend;

    /// Where the positions it is given live.
    fn coordinates(&self) -> Coordinates {
        Coordinates::World
    }

    /// The side of the box its encoding spans, where a checkpoint must
    /// match it (Instant-NGP's hash grid); `None` for fields without one.
    fn grid_extent(&self) -> Option<f32> {
        None
    }

    /// Samples per round when rendering (each round's activations are
    /// held at once).
    fn inference_rows(&self) -> usize {
        1 << 15
    }

    /// σ at positions (n × 3), without keeping activations: for the
    /// occupancy grid and for finding where rays become opaque.
    /// `variances` (n × 3), where given, make each sample a Gaussian with
    /// that diagonal covariance around its position (Mip-NeRF's frustums);
    /// a field without an integrated encoding ignores them.
    fn density(
        &self,
        params: &[f32],
        positions: &[f32],
        variances: Option<&[f32]>,
        sigma: &mut [f32],
    );

    /// σ of every marched sample, to find each ray's cut, before
    /// [`Field::forward_before_cut`] on the samples before it. A field may
    /// keep what the σ pass computed that the forward pass needs again
    /// (Instant-NGP keeps the hash features, and σ itself); by default,
    /// [`Field::density`].
    fn density_for_cut(
        &mut self,
        params: &[f32],
        positions: &[f32],
        variances: Option<&[f32]>,
        sigma: &mut [f32],
    ) {
        self.density(params, positions, variances, sigma);
    }

    /// [`Field::forward`] on the samples before each ray's cut: `rows` are
    /// their indices among the samples of the last
    /// [`Field::density_for_cut`], and `positions`, `variances` and
    /// `directions` those rows gathered; `appearance` is theirs too (per
    /// gathered row). By default the forward pass on the gathered rows.
    #[allow(clippy::too_many_arguments)]
    fn forward_before_cut(
        &mut self,
        params: &[f32],
        rows: &[u32],
        positions: &[f32],
        variances: Option<&[f32]>,
        directions: &[f32],
        appearance: Appearance<'_>,
        sigma: &mut [f32],
        rgb: &mut [f32],
    ) {
        let _ = rows;
        self.forward(
            params, positions, variances, directions, appearance, sigma, rgb,
        );
    }

    /// Whether a marched step may find the cut in a forward pass over every
    /// marched sample instead of a σ pass first, where that is cheaper
    /// (see `CpuModel::marched_step`). A field whose σ pass does work the
    /// forward pass reuses says no.
    fn may_find_cut_in_forward(&self) -> bool {
        true
    }

    /// σ (n) and colour (n × 3) at positions (with `variances` as in
    /// [`Field::density`]) and unit directions (n × 3 each), each sample's
    /// colour with its `appearance` where the field has embeddings, keeping
    /// what [`Field::backward`] needs.
    #[allow(clippy::too_many_arguments)]
    fn forward(
        &mut self,
        params: &[f32],
        positions: &[f32],
        variances: Option<&[f32]>,
        directions: &[f32],
        appearance: Appearance<'_>,
        sigma: &mut [f32],
        rgb: &mut [f32],
    );

    /// Writes or adds (`mode`) to `gradients` (this field's parameters) the
    /// gradient of the loss given its gradients with respect to the last
    /// forward pass's σ and colour. Positions and directions get no
    /// gradient: no model here learns its sample positions. The appearance
    /// embeddings the forward pass used get theirs.
    fn backward(
        &mut self,
        params: &[f32],
        d_sigma: &[f32],
        d_rgb: &[f32],
        gradients: &mut [f32],
        mode: Gradient,
    );

    /// Asks the backward passes that follow to keep what
    /// [`Field::input_gradients`] needs (camera refinement); off by
    /// default, when a backward pass does nothing more than it did. A
    /// field that cannot give its inputs' gradient answers false.
    fn keep_input_gradients(&mut self, keep: bool) -> bool {
        let _ = keep;
        false
    }

    /// After a backward pass with input gradients kept: the loss's
    /// gradient with respect to each row's position (in the field's
    /// coordinates) and direction, written (rows × 3 each).
    fn input_gradients(
        &mut self,
        params: &[f32],
        d_positions: &mut [f32],
        d_directions: &mut [f32],
    ) {
        let _ = params;
        d_positions.fill(0.0);
        d_directions.fill(0.0);
    }

    /// σ and colour without keeping activations (rendering).
    #[allow(clippy::too_many_arguments)]
    fn radiance(
        &self,
        params: &[f32],
        positions: &[f32],
        variances: Option<&[f32]>,
        directions: &[f32],
        appearance: Appearance<'_>,
        sigma: &mut [f32],
        rgb: &mut [f32],
    );

    /// Its table of appearance embeddings, if it has one.
    fn appearance(&self) -> Option<AppearanceShape> {
        None
    }

    /// A field of the same shape with scratch of its own, for a later level
    /// that evaluates the same parameters while this field's activations
    /// still wait for their backward pass (Mip-NeRF 360's one proposal MLP
    /// serves both proposal rounds, whose backward passes follow the final
    /// level's); `None` for a field that no recipe shares so.
    fn twin(&self) -> Option<Box<dyn Field>> {
        None
    }

    /// Multiply-adds of the networks per sample in one forward pass (the
    /// backward pass does twice as many), for the benchmark's FLOP/s.
    fn macs_per_sample(&self) -> usize;

    /// Multiply-adds per sample of [`Field::density`].
    fn density_macs_per_sample(&self) -> usize;

    /// Bytes of scratch held.
    fn workspace_bytes(&self) -> usize;
}

/// The hash grid's backward pass from the gradient of its features,
/// writing or adding (`mode`) its entries' gradient.
pub(crate) fn hash_grid_backward(
    grid: &crate::field::encoding::HashGridLayout,
    positions: &[[f32; 3]],
    d_encoded: &[f32],
    grid_gradient: &mut [f32],
    scratch: &mut Vec<f32>,
    mode: Gradient,
) {
    use crate::engine::cpu::hash_grid;
    match mode {
        Gradient::Overwrite => hash_grid::encode_gradient_with_scratch(
            grid,
            positions,
            d_encoded,
            grid_gradient,
            scratch,
        ),
        Gradient::Add => hash_grid::encode_backward_with_scratch(
            grid,
            positions,
            d_encoded,
            grid_gradient,
            scratch,
        ),
    }
}

/// Sets the length of a buffer about to be overwritten in full: only growth
/// is zero-filled.
pub(crate) fn set_len<T: Copy + Default>(v: &mut Vec<T>, n: usize) {
    v.truncate(n);
    v.resize(n, T::default());
}

/// Rows per rayon task in [`gather_rows`].
const ROWS_PER_TASK: usize = 4096;

/// Rows of `src` (`width` values each) picked by `rows`, into `dst`: how
/// the samples a step uses are gathered from all it marched.
pub(crate) fn gather_rows(src: &[f32], width: usize, rows: &[u32], dst: &mut Vec<f32>) {
    use rayon::prelude::*;
    set_len(dst, rows.len() * width);
    dst.par_chunks_mut(ROWS_PER_TASK * width)
        .zip(rows.par_chunks(ROWS_PER_TASK))
        .for_each(|(dst, rows)| {
            for (out, &row) in dst.chunks_exact_mut(width).zip(rows) {
                out.copy_from_slice(&src[row as usize * width..][..width]);
            }
        });
}
