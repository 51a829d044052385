//! Fields on the `cpu` engine: what maps a sample (position, direction) to
//! density and colour, forward and backward. A model's driver
//! ([`super::model`]) chains a sampler, fields, compositing, the loss and
//! the optimiser; the fields are the part that differs between models.

pub mod nerf;

/// Density and colour at samples, with gradients.
///
/// A field holds its own scratch (activations kept between
/// [`Field::forward`] and [`Field::backward`]); its parameters live in the
/// driver's flat vector and are passed in, so one optimiser and one
/// checkpoint serve every field.
pub trait Field: Send + Sync {
    fn param_count(&self) -> usize;

    /// The dense kernels its networks run on.
    fn kernels(&self) -> crate::engine::cpu::dense::Backend;

    /// Initial parameters, reproducible from `seed`.
    fn init_params(&self, seed: u64) -> Vec<f32>;

    /// σ at world positions (n × 3), without keeping activations: for the
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

    /// σ (n) and colour (n × 3) at world positions (with `variances` as in
    /// [`Field::density`]) and unit directions (n × 3 each), keeping what
    /// [`Field::backward`] needs.
    fn forward(
        &mut self,
        params: &[f32],
        positions: &[f32],
        variances: Option<&[f32]>,
        directions: &[f32],
        sigma: &mut [f32],
        rgb: &mut [f32],
    );

    /// Adds (+=) to `gradients` (this field's parameters) the gradient of
    /// the loss given its gradients with respect to the last forward pass's
    /// σ and colour. Positions and directions get no gradient: no model
    /// here learns its sample positions.
    fn backward(&mut self, params: &[f32], d_sigma: &[f32], d_rgb: &[f32], gradients: &mut [f32]);

    /// σ and colour without keeping activations (rendering).
    fn radiance(
        &self,
        params: &[f32],
        positions: &[f32],
        variances: Option<&[f32]>,
        directions: &[f32],
        sigma: &mut [f32],
        rgb: &mut [f32],
    );

    /// Multiply-adds of the networks per sample in one forward pass (the
    /// backward pass does twice as many), for the benchmark's FLOP/s.
    fn macs_per_sample(&self) -> usize;

    /// Multiply-adds per sample of [`Field::density`].
    fn density_macs_per_sample(&self) -> usize;

    /// Bytes of scratch held.
    fn workspace_bytes(&self) -> usize;
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
