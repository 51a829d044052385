//! What both engines composite from: a batch's samples and rays as the
//! volume-rendering stage reads them ([`RayBatch`], laid out as
//! `engine::cpu::composite_batch` describes) and the distortion loss's
//! weights ([`Distortion`]). The `cpu` engine's `composite_batch` and the
//! `gpu` engine's `composite` take these same descriptions, so the two
//! are handed identical batches.

/// The inputs of compositing for a batch of rays.
#[derive(Debug, Clone, Copy)]
pub struct RayBatch<'a, F> {
    /// σ per sample, already activated (≥ 0; negative values are treated as
    /// empty space, as in the reference).
    pub density: &'a [F],
    /// Colour per sample, S × 3, already through the sigmoid.
    pub rgb: &'a [F],
    /// Interval length δ per sample, in world units.
    pub dt: &'a [F],
    /// Distance of each sample along its ray, in world units (for depth).
    pub t: &'a [F],
    /// R + 1 offsets into the samples, non-decreasing.
    pub ray_offsets: &'a [u32],
    /// Background colour per ray, R × 3.
    pub background: &'a [F],
}

impl<F> RayBatch<'_, F> {
    pub fn ray_count(&self) -> usize {
        self.ray_offsets.len().saturating_sub(1)
    }

    /// Samples covered by the rays (`ray_offsets[R]`).
    pub fn sample_count(&self) -> usize {
        self.ray_offsets.last().map_or(0, |&n| n as usize)
    }
}

/// Mip-NeRF 360's distortion loss (`engine::cpu::composite::distortion`) added
/// to the loss on colours: λ × the mean over rays of each ray's distortion,
/// on the samples before its cut, at distances s = t × `distance_scale`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Distortion<F> {
    /// λ divided by the rays of the batch.
    pub weight_per_ray: F,
    /// Converts distances along the ray into the loss's unit (the models
    /// use the scene box's diagonal as 1, so λ means the same in every
    /// scene).
    pub distance_scale: F,
}
