//! Fields on the `gpu` engine: what maps a sample (position, direction) to
//! density and colour, forward and backward, recorded into a command
//! encoder. The gpu twins of [`crate::engine::cpu::fields`], with the same
//! parameter layouts, so a model's parameters move between engines as they
//! are.

pub mod density;
pub mod nerf;
pub mod ngp;

use super::kernel::Recorder;
pub use crate::engine::gpu::appearance::GpuAppearance;
use crate::engine::gpu::{GpuContext, GpuError};
use crate::field::FieldShape;
use crate::field::appearance::AppearanceShape;
use crate::field::common::Coordinates;

/// One field of `shape` on the `gpu` engine, for passes of up to
/// `capacity_rows` samples (its initial parameters come from the shape,
/// [`crate::field::model_params`]).
pub fn fields_for(
    context: &GpuContext,
    shape: &FieldShape,
    capacity_rows: usize,
) -> Result<Box<dyn GpuField>, GpuError> {
    Ok(match shape {
        FieldShape::Ngp(shape) => Box::new(ngp::GpuNgpField::new(context, shape, capacity_rows)?),
        FieldShape::Nerf(shape) => {
            Box::new(nerf::GpuNerfField::new(context, shape, capacity_rows)?)
        }
        FieldShape::Density(shape) => Box::new(density::GpuDensityField::new(
            context,
            shape,
            capacity_rows,
        )?),
        FieldShape::NerfDensity(shape) => Box::new(density::GpuNerfDensityField::new(
            context,
            shape,
            capacity_rows,
        )?),
    })
}

/// A field's samples: `positions` and unit `directions` (rows × 3 each),
/// and, where given, `variances` (rows × 3) that make each sample a
/// Gaussian with that diagonal covariance around its position (Mip-NeRF's
/// frustums). On the device (`B` a buffer), or on the host (`[f32]`) for
/// the helpers that upload them.
#[derive(Debug)]
pub struct FieldInputs<'a, B: ?Sized = wgpu::Buffer> {
    pub positions: &'a B,
    pub variances: Option<&'a B>,
    pub directions: &'a B,
}

impl<B: ?Sized> Clone for FieldInputs<'_, B> {
    fn clone(&self) -> Self {
        *self
    }
}

impl<B: ?Sized> Copy for FieldInputs<'_, B> {}

/// Where a field's forward pass writes: σ (rows) and colour (rows × 3).
#[derive(Debug, Clone, Copy)]
pub struct FieldOutputs<'a> {
    pub sigma: &'a wgpu::Buffer,
    pub rgb: &'a wgpu::Buffer,
}

/// A field on the `gpu` engine, as a model driver records it: a forward
/// pass that keeps its activations, the backward pass of that forward
/// pass, and σ alone (for the occupancy grid). Parameters and gradients are
/// flat f32 buffers holding every field of a model; a field reads its own
/// from the offset [`GpuField::set_param_offset`] gave it.
pub trait GpuField: Send {
    /// Parameters of the field.
    fn param_count(&self) -> usize;

    /// Where the field's parameters (and gradients) start in the buffers
    /// passed to the `record_*` methods, in f32s.
    fn set_param_offset(&mut self, offset: usize);

    /// Samples one pass can hold.
    fn capacity(&self) -> usize;

    /// Where the positions it is given live (as the cpu twin's
    /// [`crate::engine::cpu::fields::Field::coordinates`]).
    fn coordinates(&self) -> Coordinates {
        Coordinates::World
    }

    /// The side of the box its encoding spans, where a checkpoint must
    /// match it (as the cpu twin's
    /// [`crate::engine::cpu::fields::Field::grid_extent`]).
    fn grid_extent(&self) -> Option<f32> {
        None
    }

    /// Its table of appearance embeddings, if it has one.
    fn appearance(&self) -> Option<AppearanceShape> {
        None
    }

    /// Records σ and colour at `rows` samples `inputs` into `out`, each
    /// sample's colour with its `appearance` where the field has
    /// embeddings, as the cpu's
    /// [`crate::engine::cpu::fields::Field::forward`].
    fn record_forward(
        &mut self,
        rec: &mut Recorder,
        params: &wgpu::Buffer,
        inputs: FieldInputs,
        appearance: GpuAppearance,
        rows: usize,
        out: FieldOutputs,
    );

    /// Records the backward pass of the last forward pass, adding (+=)
    /// the parameter gradient into `gradients` (the appearance embeddings
    /// the forward pass used get theirs).
    fn record_backward(
        &self,
        rec: &mut Recorder,
        params: &wgpu::Buffer,
        d_sigma: &wgpu::Buffer,
        d_rgb: &wgpu::Buffer,
        rows: usize,
        gradients: &wgpu::Buffer,
    );

    /// Records σ alone at `rows` positions (with `variances` as in
    /// [`FieldInputs`]).
    fn record_density(
        &mut self,
        rec: &mut Recorder,
        params: &wgpu::Buffer,
        positions: &wgpu::Buffer,
        variances: Option<&wgpu::Buffer>,
        rows: usize,
        sigma_out: &wgpu::Buffer,
    );

    /// Multiply-adds of the networks per sample in one forward pass, and of
    /// σ alone (as the cpu twin's), which weigh σ first against forward
    /// first in a marched step
    /// ([`crate::engine::shared::driver::sigma_first`]).
    fn macs_per_sample(&self) -> usize;

    fn density_macs_per_sample(&self) -> usize;

    /// Whether a marched step may find each ray's cut in the forward pass
    /// over every marched sample (as the cpu twin's
    /// [`crate::engine::cpu::fields::Field::may_find_cut_in_forward`]).
    fn may_find_cut_in_forward(&self) -> bool {
        true
    }

    /// Bytes of the field's workspaces on the device.
    fn workspace_bytes(&self) -> usize;
}
