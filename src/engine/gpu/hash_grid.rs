//! The multiresolution hash encoding on the GPU (`shaders/hash_*.wgsl`),
//! forward and backward, with the layouts of [`crate::engine::cpu::hash_grid`].
//!
//! The forward pass runs one invocation per (sample, level). The backward
//! pass scatters each invocation's 8 · F contributions into the gradient
//! table with atomic adds: native `atomic<f32>` where the device has
//! `SHADER_FLOAT32_ATOMIC`, otherwise a compare-and-swap loop on the f32's
//! bits in an `atomic<u32>`, which every device supports. Both add exact
//! f32 values; the order of additions varies from run to run either way.

use super::context::{GpuContext, GpuError};
use super::kernel::{Kernel, read_buffer, storage_buffer, uniform_buffer, zeroed_storage_buffer};
use crate::engine::cpu::hash_grid::HashGridLayout;

/// Threads per workgroup in the hash kernels (WORKGROUP in hash_common.wgsl).
const WORKGROUP: u32 = 64;
/// Workgroups per dispatch dimension (wgpu's default limit); larger batches
/// fold into z.
const MAX_GROUPS_PER_DIMENSION: u32 = 65535;

const COMMON: &str = include_str!("../../../shaders/hash_common.wgsl");
const ENCODE: &str = include_str!("../../../shaders/hash_encode.wgsl");
const BACKWARD: &str = include_str!("../../../shaders/hash_backward.wgsl");
const ACCUMULATE_FLOAT: &str = include_str!("../../../shaders/hash_accumulate_float.wgsl");
const ACCUMULATE_CAS: &str = include_str!("../../../shaders/hash_accumulate_cas.wgsl");

/// `Params` in hash_common.wgsl.
#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct Params {
    count: u32,
    features: u32,
    width: u32,
    groups_x: u32,
}

/// `Level` in hash_common.wgsl.
#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct Level {
    resolution: u32,
    offset: u32,
    dense: u32,
    mask: u32,
}

/// The compiled hash-grid kernels for one layout.
pub struct GpuHashGrid {
    encode: Kernel,
    backward: Kernel,
    levels: wgpu::Buffer,
    level_count: u32,
    features: u32,
    width: u32,
    param_count: usize,
    float_atomics: bool,
}

impl GpuHashGrid {
    /// Compiles the kernels for `layout`. The backward pass uses native
    /// float atomics when `use_float_atomics` is asked for and the device has
    /// them ([`GpuContext::has_float_atomics`]); otherwise the
    /// compare-and-swap fallback. [`GpuHashGrid::uses_float_atomics`] says
    /// which was chosen.
    ///
    /// The whole parameter array is one storage binding, so it must fit the
    /// device's binding limit: the paper's grid takes at most 64 MiB
    /// (16 levels × 2^19 entries × 2 features × 4 B) against at least
    /// 128 MiB on every adapter wgpu exposes with its own limits.
    pub fn new(
        context: &GpuContext,
        layout: &HashGridLayout,
        use_float_atomics: bool,
    ) -> Result<Self, GpuError> {
        let param_bytes = (layout.param_count() * std::mem::size_of::<f32>()) as u64;
        let limit = context.limits.max_storage_buffer_binding_size;
        assert!(
            param_bytes <= limit,
            "hash-grid parameters ({param_bytes} B) exceed the device's storage binding limit ({limit} B)"
        );
        let float_atomics = use_float_atomics && context.has_float_atomics();
        let encode = Kernel::new(
            context,
            "hash_encode",
            &format!("{COMMON}\n{ENCODE}"),
            "main",
        )?;
        let (name, accumulate) = if float_atomics {
            ("hash_backward (f32 atomics)", ACCUMULATE_FLOAT)
        } else {
            ("hash_backward (compare-and-swap)", ACCUMULATE_CAS)
        };
        let backward = Kernel::new(
            context,
            name,
            &format!("{COMMON}\n{accumulate}\n{BACKWARD}"),
            "main",
        )?;
        let mask = (layout.config().table_size() - 1) as u32;
        let levels: Vec<Level> = layout
            .levels()
            .iter()
            .map(|level| Level {
                resolution: level.resolution,
                offset: level.offset as u32,
                dense: level.dense as u32,
                mask,
            })
            .collect();
        Ok(Self {
            encode,
            backward,
            levels: storage_buffer(context, "hash levels", &levels),
            level_count: levels.len() as u32,
            features: layout.features() as u32,
            width: layout.output_width() as u32,
            param_count: layout.param_count(),
            float_atomics,
        })
    }

    /// True when the backward pass uses native f32 atomics.
    pub fn uses_float_atomics(&self) -> bool {
        self.float_atomics
    }

    /// Parameters (f32) the `params` and `d_params` buffers hold.
    pub fn param_count(&self) -> usize {
        self.param_count
    }

    /// The uniform and workgroup counts of a dispatch over `count` samples.
    fn dispatch(&self, context: &GpuContext, count: usize) -> (wgpu::Buffer, [u32; 3]) {
        let groups = u32::try_from(count.div_ceil(WORKGROUP as usize))
            .expect("batch too large for one dispatch")
            .max(1);
        let z = groups.div_ceil(MAX_GROUPS_PER_DIMENSION);
        let x = groups.div_ceil(z);
        let params = Params {
            count: count as u32,
            features: self.features,
            width: self.width,
            groups_x: x,
        };
        // A fresh uniform per recorded dispatch, so several can share one
        // command encoder with different batch sizes.
        (
            uniform_buffer(context, "hash params", &params),
            [x, self.level_count, z],
        )
    }

    /// Records the encoding of `count` positions (count × 3 f32) into
    /// `encoded` (count × L·F f32), reading the table from `params`.
    pub fn record_encode(
        &self,
        context: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        params: &wgpu::Buffer,
        positions: &wgpu::Buffer,
        encoded: &wgpu::Buffer,
        count: usize,
    ) {
        let (uniform, groups) = self.dispatch(context, count);
        self.encode.record(
            context,
            encoder,
            &[&uniform, &self.levels, params, positions, encoded],
            groups,
        );
    }

    /// Records the backward pass: adds (+=) ∂loss/∂params into `d_params`
    /// given ∂loss/∂encoded in `d_encoded` (count × L·F). Clear `d_params`
    /// first (`encoder.clear_buffer`) for a fresh gradient.
    pub fn record_backward(
        &self,
        context: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        positions: &wgpu::Buffer,
        d_encoded: &wgpu::Buffer,
        d_params: &wgpu::Buffer,
        count: usize,
    ) {
        let (uniform, groups) = self.dispatch(context, count);
        self.backward.record(
            context,
            encoder,
            &[&uniform, &self.levels, positions, d_encoded, d_params],
            groups,
        );
    }

    /// Uploads, encodes and reads back positions.len() × L·F features (for
    /// tests and tools).
    pub fn encode_once(
        &self,
        context: &GpuContext,
        params: &[f32],
        positions: &[[f32; 3]],
    ) -> Vec<f32> {
        assert_eq!(params.len(), self.param_count, "params");
        let count = positions.len();
        let outputs = count * self.width as usize;
        let params = storage_buffer(context, "hash params", params);
        let positions = storage_buffer(context, "positions", positions);
        let encoded = zeroed_storage_buffer::<f32>(context, "encoded", outputs);
        let mut encoder = context.device.create_command_encoder(&Default::default());
        self.record_encode(context, &mut encoder, &params, &positions, &encoded, count);
        context.queue.submit([encoder.finish()]);
        read_buffer(context, &encoded, outputs)
    }

    /// Uploads, runs the backward pass into a zeroed gradient and reads it
    /// back (for tests and tools).
    pub fn backward_once(
        &self,
        context: &GpuContext,
        positions: &[[f32; 3]],
        d_encoded: &[f32],
    ) -> Vec<f32> {
        let count = positions.len();
        assert_eq!(
            d_encoded.len(),
            count * self.width as usize,
            "d_encoded must be S × L·F"
        );
        let positions = storage_buffer(context, "positions", positions);
        let d_encoded = storage_buffer(context, "d_encoded", d_encoded);
        let d_params = zeroed_storage_buffer::<f32>(context, "d_params", self.param_count);
        let mut encoder = context.device.create_command_encoder(&Default::default());
        // wgpu zero-initialises new buffers already; clearing states it.
        encoder.clear_buffer(&d_params, 0, None);
        self.record_backward(
            context,
            &mut encoder,
            &positions,
            &d_encoded,
            &d_params,
            count,
        );
        context.queue.submit([encoder.finish()]);
        read_buffer(context, &d_params, self.param_count)
    }
}
