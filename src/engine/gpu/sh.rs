//! The spherical-harmonics direction encoding on the GPU
//! (`shaders/sh_encode.wgsl`), the basis of [`crate::engine::cpu::sh`].

use super::kernel::{
    Columns, Kernel, Recorder, float_range, pieces, read_buffer, rows_per_piece, storage_buffer,
    uniform_buffer, zeroed_storage_buffer,
};
use crate::engine::gpu::{GpuContext, GpuError};
use crate::field::encoding::{SH_MAX_DEGREE, sh_coefficients};

/// Threads per workgroup in sh_encode.wgsl.
const WORKGROUP: u32 = 64;
/// Workgroups per dispatch dimension (wgpu's default limit).
const MAX_GROUPS_PER_DIMENSION: u32 = 65535;

#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct Params {
    rows: u32,
    degree: u32,
    stride: u32,
    offset: u32,
}

/// The compiled encoding kernel.
pub struct GpuSh {
    kernel: Kernel,
}

impl GpuSh {
    pub fn new(context: &GpuContext) -> Result<Self, GpuError> {
        Ok(Self {
            kernel: Kernel::new(
                context,
                "sh_encode",
                include_str!("../../../shaders/sh_encode.wgsl"),
                "main",
            )?,
        })
    }

    /// Records the encoding of `rows` unit directions (rows × 3): row r's
    /// `degree²` coefficients go to the `out` columns of row r, so they can
    /// be written straight into the colour network's input matrix.
    pub fn record_encode(
        &self,
        rec: &mut Recorder,
        degree: u32,
        directions: &wgpu::Buffer,
        rows: usize,
        out: Columns,
    ) {
        let context = rec.context;
        let Columns {
            buffer: output,
            stride,
            start: offset,
            width,
        } = out;
        assert!(
            (1..=SH_MAX_DEGREE).contains(&degree),
            "degree {degree} not in 1..={SH_MAX_DEGREE}"
        );
        assert_eq!(width, sh_coefficients(degree), "degree² columns");
        assert!(offset + width <= stride, "coefficients overrun the row");
        // Rows beyond one storage binding go a piece at a time.
        for piece in pieces(rows, rows_per_piece(context, stride.max(3), 1)) {
            let params = Params {
                rows: piece.len() as u32,
                degree,
                stride: stride as u32,
                offset: offset as u32,
            };
            let uniform = uniform_buffer(context, "sh params", &params);
            let groups = (piece.len() as u32).div_ceil(WORKGROUP).max(1);
            let y = groups.div_ceil(MAX_GROUPS_PER_DIMENSION);
            self.kernel.record_bindings(
                rec,
                &[
                    uniform.as_entire_buffer_binding(),
                    float_range(directions, 3 * piece.start, 3 * piece.len()),
                    float_range(output, stride * piece.start, stride * piece.len()),
                ],
                [groups.div_ceil(y), y, 1],
            );
        }
    }

    /// Uploads, encodes and reads back rows × degree² coefficients (for tests
    /// and tools).
    pub fn encode_once(
        &self,
        context: &GpuContext,
        degree: u32,
        directions: &[f32],
        rows: usize,
    ) -> Vec<f32> {
        let n = sh_coefficients(degree);
        let input = storage_buffer(context, "directions", &directions[..3 * rows]);
        let output = zeroed_storage_buffer::<f32>(context, "sh", rows * n);
        let mut rec = Recorder::new(context);
        self.record_encode(&mut rec, degree, &input, rows, Columns::all(&output, n));
        rec.submit();
        read_buffer(context, &output, rows * n)
    }
}

/// The uniforms as the shaders declare them (`engine::gpu::mirror`).
#[cfg(test)]
mod uniform_mirrors {
    use super::*;
    use crate::engine::gpu::mirror::assert_mirrors;

    #[test]
    fn params_of_sh_encode_mirror_the_shader() {
        assert_mirrors!(
            include_str!("../../../shaders/sh_encode.wgsl"),
            "Params",
            Params,
            [rows, degree, stride, offset]
        );
    }
}
