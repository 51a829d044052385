//! The frequency (positional) encoding and its integrated form on the GPU
//! (`shaders/frequency_encode.wgsl`): the forward pass of
//! [`crate::engine::cpu::frequency`], same formulas and layout.

use super::kernel::{
    Kernel, Recorder, float_range, pieces, read_buffer, rows_per_piece, storage_buffer,
    uniform_buffer, zeroed_storage_buffer,
};
use crate::engine::gpu::{GpuContext, GpuError};
use crate::field::encoding::{FrequencyEncoding, MAX_FREQUENCIES};

/// Threads per workgroup in frequency_encode.wgsl.
const WORKGROUP: u32 = 64;
/// Workgroups per dispatch dimension (wgpu's default limit).
const MAX_GROUPS_PER_DIMENSION: u32 = 65535;

#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct Params {
    rows: u32,
    frequencies: u32,
    include_input: u32,
    width: u32,
}

/// The compiled encoding kernels: the ordinary encoding, and the integrated
/// one, which also binds a variance.
pub struct GpuFrequency {
    plain: Kernel,
    integrated: Kernel,
}

impl GpuFrequency {
    pub fn new(context: &GpuContext) -> Result<Self, GpuError> {
        let source = include_str!("../../../shaders/frequency_encode.wgsl");
        Ok(Self {
            plain: Kernel::new(context, "frequency_encode", source, "main")?,
            integrated: Kernel::new(
                context,
                "frequency_encode_integrated",
                source,
                "main_integrated",
            )?,
        })
    }

    /// Records the encoding of `rows` points (`inputs`, rows × 3) into `out`
    /// (rows × [`FrequencyEncoding::output_width`]), damped by `variance`
    /// (rows × 3) when one is given.
    pub fn record(
        &self,
        rec: &mut Recorder,
        encoding: &FrequencyEncoding,
        inputs: &wgpu::Buffer,
        variance: Option<&wgpu::Buffer>,
        rows: u32,
        out: &wgpu::Buffer,
    ) {
        let context = rec.context;
        assert!(
            encoding.frequencies <= MAX_FREQUENCIES,
            "{} frequencies, at most {MAX_FREQUENCIES} supported",
            encoding.frequencies
        );
        let width = encoding.output_width();
        let rows = rows as usize;
        // Rows beyond one storage binding go a piece at a time; a piece
        // starts at a multiple of 64 rows, which keeps every binding offset
        // aligned for any width.
        for piece in pieces(rows, rows_per_piece(context, width.max(3), 1)) {
            let params = Params {
                rows: piece.len() as u32,
                frequencies: encoding.frequencies,
                include_input: encoding.include_input as u32,
                width: width as u32,
            };
            let uniform = uniform_buffer(context, "frequency params", &params);
            // A 2-D grid when one dimension is not enough; the shader's
            // row_index flattens it back.
            let groups = (piece.len() as u32).div_ceil(WORKGROUP).max(1);
            let y = groups.div_ceil(MAX_GROUPS_PER_DIMENSION);
            let mut bindings = vec![
                uniform.as_entire_buffer_binding(),
                float_range(inputs, 3 * piece.start, 3 * piece.len()),
                float_range(out, width * piece.start, width * piece.len()),
            ];
            let kernel = match variance {
                Some(variance) => {
                    bindings.push(float_range(variance, 3 * piece.start, 3 * piece.len()));
                    &self.integrated
                }
                None => &self.plain,
            };
            kernel.record_bindings(rec, &bindings, [groups.div_ceil(y), y, 1]);
        }
    }

    /// Uploads, encodes and reads back rows × width values (for tests and
    /// tools).
    pub fn encode(
        &self,
        context: &GpuContext,
        encoding: &FrequencyEncoding,
        inputs: &[f32],
        variance: Option<&[f32]>,
    ) -> Vec<f32> {
        let rows = inputs.len() / 3;
        assert_eq!(inputs.len(), 3 * rows, "inputs are not rows of 3");
        let width = encoding.output_width();
        let input = storage_buffer(context, "frequency inputs", inputs);
        let variance = variance.map(|v| {
            assert_eq!(v.len(), inputs.len(), "variance and inputs differ in size");
            storage_buffer(context, "frequency variance", v)
        });
        let out = zeroed_storage_buffer::<f32>(context, "frequency encoding", rows * width);
        let mut rec = Recorder::new(context);
        self.record(
            &mut rec,
            encoding,
            &input,
            variance.as_ref(),
            rows as u32,
            &out,
        );
        rec.submit();
        read_buffer(context, &out, rows * width)
    }
}

/// The uniforms as the shaders declare them (`engine::gpu::mirror`).
#[cfg(test)]
mod uniform_mirrors {
    use super::*;
    use crate::engine::gpu::mirror::assert_mirrors;

    #[test]
    fn params_of_frequency_encode_mirror_the_shader() {
        assert_mirrors!(
            include_str!("../../../shaders/frequency_encode.wgsl"),
            "Params",
            Params,
            [rows, frequencies, include_input, width]
        );
    }
}
