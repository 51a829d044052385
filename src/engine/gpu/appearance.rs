//! Appearance embeddings on the `gpu` engine (`shaders/appearance_*.wgsl`):
//! each row's vector written into a colour network's input, and the
//! gradient of those columns added back to the table's rows, as the cpu
//! engine's `engine::cpu::appearance` (see [`crate::field::appearance`]).
//!
//! Training rows take their rays' images: each ray's image is uploaded
//! with the batch, and a kernel gives each of its samples that image. The
//! backward pass adds each row's gradient to its image's row with atomic
//! adds, native f32 atomics where the device has them and the hash grid's
//! compare-and-swap loop otherwise (`shaders/hash_accumulate_*.wgsl`).
//! Renders take the mean of the rows (computed on the device, so the table
//! never travels to the host) or one image's row.

use super::hash_grid::{ACCUMULATE_CAS, ACCUMULATE_FLOAT, GpuHashGrid};
use super::kernel::{
    Columns, FloatsAt, Kernel, Recorder, float_range, pieces, rows_per_piece, uniform_buffer,
    zeroed_storage_buffer,
};
use super::march::dispatch_grid;
use crate::engine::gpu::{GpuContext, GpuError};
use crate::field::appearance::AppearanceShape;

/// Threads per workgroup of the appearance kernels.
const WORKGROUP: u32 = 64;

const COMMON: &str = include_str!("../../../shaders/appearance_common.wgsl");

/// Which appearance vector each sample of a field's forward pass takes on
/// the `gpu` engine (the cpu's [`crate::field::appearance::Appearance`]).
/// Fields without a table ignore it.
#[derive(Debug, Clone, Copy)]
pub enum GpuAppearance<'a> {
    /// The mean of the training images' vectors (renders, held-out views,
    /// and passes that ask for none, as the cpu's `Appearance::None`).
    Mean,
    /// One training image's vector for every sample.
    Image(u32),
    /// Training: each sample its ray's image. Ray r's image is `images[r]`
    /// (u32) and its samples are rows `ray_offsets[r] .. ray_offsets[r +
    /// 1]` of the pass (u32), for `rays` rays.
    PerRay {
        images: &'a wgpu::Buffer,
        ray_offsets: &'a wgpu::Buffer,
        rays: usize,
    },
}

impl GpuAppearance<'static> {
    /// What renders take: the mean, or the chosen training image's vector.
    pub fn rendered(image: Option<usize>) -> Self {
        match image {
            None => GpuAppearance::Mean,
            Some(image) => GpuAppearance::Image(image as u32),
        }
    }
}

/// `Params` in appearance_common.wgsl.
#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct Params {
    rows: u32,
    row_stride: u32,
    width: u32,
    images: u32,
    stride: u32,
    column: u32,
    image: u32,
    one_image: u32,
    table_base: u32,
    _pad: [u32; 3],
}

/// Which vector the rows of the last forward pass took, for its backward
/// pass.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Taken {
    Mean,
    Image(u32),
    /// Each its own, in the `images` buffer.
    PerSample,
}

/// A field's table of appearance embeddings on the `gpu` engine: the
/// compiled kernels and the per-row scratch for passes of up to
/// `capacity` rows.
pub struct GpuAppearanceTable {
    shape: AppearanceShape,
    capacity: usize,
    sample_images: Kernel,
    mean: Kernel,
    write: Kernel,
    backward: Kernel,
    spread: Kernel,
    /// Each row's image in a training pass (u32).
    images: wgpu::Buffer,
    /// The mean of the rows, and its gradient.
    mean_vector: wgpu::Buffer,
    d_mean: wgpu::Buffer,
    taken: Option<Taken>,
}

impl GpuAppearanceTable {
    /// The kernels for a table of `shape` and passes of up to
    /// `capacity_rows` rows.
    pub fn new(
        context: &GpuContext,
        shape: AppearanceShape,
        capacity_rows: usize,
    ) -> Result<Self, GpuError> {
        let capacity = capacity_rows.max(1);
        let kernel = |name: &str, source: &str| {
            Kernel::new(context, name, &format!("{COMMON}\n{source}"), "main")
        };
        let (backward_name, accumulate) = if context.has_float_atomics() {
            ("appearance_backward (f32 atomics)", ACCUMULATE_FLOAT)
        } else {
            ("appearance_backward (compare-and-swap)", ACCUMULATE_CAS)
        };
        let backward_source = include_str!("../../../shaders/appearance_backward.wgsl");
        Ok(Self {
            sample_images: kernel(
                "appearance_images",
                include_str!("../../../shaders/appearance_images.wgsl"),
            )?,
            mean: kernel(
                "appearance_mean",
                include_str!("../../../shaders/appearance_mean.wgsl"),
            )?,
            write: kernel(
                "appearance_write",
                include_str!("../../../shaders/appearance_write.wgsl"),
            )?,
            backward: kernel(backward_name, &format!("{accumulate}\n{backward_source}"))?,
            spread: kernel(
                "appearance_spread",
                include_str!("../../../shaders/appearance_spread.wgsl"),
            )?,
            images: zeroed_storage_buffer::<u32>(context, "appearance images", capacity),
            mean_vector: zeroed_storage_buffer::<f32>(context, "appearance mean", shape.width),
            d_mean: zeroed_storage_buffer::<f32>(context, "appearance d mean", shape.width),
            taken: None,
            shape,
            capacity,
        })
    }

    pub fn shape(&self) -> AppearanceShape {
        self.shape
    }

    /// The uniform with the table's shape and `out`'s columns filled in.
    fn params(&self, columns: &Columns, taken: Taken, table_base: usize) -> Params {
        let (image, one_image) = match taken {
            Taken::Mean => (0, 1),
            Taken::Image(image) => (image, 1),
            Taken::PerSample => (0, 0),
        };
        Params {
            rows: 0,
            row_stride: 0,
            width: self.shape.width as u32,
            images: self.shape.images as u32,
            stride: columns.stride as u32,
            column: columns.start as u32,
            image,
            one_image,
            table_base: table_base as u32,
            _pad: [0; 3],
        }
    }

    /// The binding of the table (or its gradient) at `table`, from the
    /// aligned offset at or below it, and where the table starts in it.
    fn table_binding<'a>(
        &self,
        context: &GpuContext,
        table: FloatsAt<'a>,
    ) -> (wgpu::BufferBinding<'a>, usize) {
        let lead = table.offset % GpuHashGrid::offset_alignment(context);
        let binding = float_range(
            table.buffer,
            table.offset - lead,
            self.shape.param_count() + lead,
        );
        (binding, lead)
    }

    /// Records each of `rows` rows' vector of `appearance` into the `out`
    /// columns (the colour network's input), from the table at `table`
    /// (the model's parameters at the table's offset); keeps which rows
    /// took which for [`Self::record_backward`].
    pub fn record_forward(
        &mut self,
        rec: &mut Recorder,
        table: FloatsAt,
        appearance: GpuAppearance,
        rows: usize,
        out: Columns,
    ) {
        let context = rec.context;
        assert!(rows <= self.capacity, "{rows} rows of {}", self.capacity);
        assert_eq!(out.width, self.shape.width, "a vector's columns");
        assert!(
            out.start + out.width <= out.stride,
            "columns overrun the row"
        );
        let (table_binding, lead) = self.table_binding(context, table);
        let taken = match appearance {
            GpuAppearance::Mean => Taken::Mean,
            GpuAppearance::Image(image) => {
                assert!(
                    (image as usize) < self.shape.images,
                    "image {image} of {} with embeddings",
                    self.shape.images
                );
                Taken::Image(image)
            }
            GpuAppearance::PerRay { .. } => Taken::PerSample,
        };
        let mut params = self.params(&out, taken, lead);
        // The mean is read from its own buffer, as a table of one row.
        let source = match appearance {
            GpuAppearance::Mean => {
                params.rows = 1;
                let uniform = uniform_buffer(context, "appearance mean", &params);
                self.mean.record_bindings(
                    rec,
                    &[
                        uniform.as_entire_buffer_binding(),
                        table_binding,
                        self.mean_vector.as_entire_buffer_binding(),
                    ],
                    [(self.shape.width as u32).div_ceil(WORKGROUP), 1, 1],
                );
                params.table_base = 0;
                self.mean_vector.as_entire_buffer_binding()
            }
            GpuAppearance::Image(_) => table_binding,
            GpuAppearance::PerRay {
                images,
                ray_offsets,
                rays,
            } => {
                let (groups, row_stride) = dispatch_grid(rays, WORKGROUP);
                let uniform = uniform_buffer(
                    context,
                    "appearance images",
                    &Params {
                        rows: rays as u32,
                        row_stride,
                        ..params
                    },
                );
                self.sample_images.record_bindings(
                    rec,
                    &[
                        uniform.as_entire_buffer_binding(),
                        images.as_entire_buffer_binding(),
                        ray_offsets.as_entire_buffer_binding(),
                        self.images.as_entire_buffer_binding(),
                    ],
                    groups,
                );
                table_binding
            }
        };
        let width = self.shape.width;
        for piece in pieces(rows, rows_per_piece(context, out.stride, 1)) {
            let (groups, row_stride) = dispatch_grid(piece.len() * width, WORKGROUP);
            let uniform = uniform_buffer(
                context,
                "appearance write",
                &Params {
                    rows: piece.len() as u32,
                    row_stride,
                    ..params
                },
            );
            self.write.record_bindings(
                rec,
                &[
                    uniform.as_entire_buffer_binding(),
                    source.clone(),
                    float_range(&self.images, piece.start, piece.len()),
                    float_range(
                        out.buffer,
                        out.stride * piece.start,
                        out.stride * piece.len(),
                    ),
                ],
                groups,
            );
        }
        self.taken = Some(taken);
    }

    /// Records the backward pass of the last [`Self::record_forward`] over
    /// the same `rows`: adds (+=) the gradient of its columns of `d_input`
    /// (the colour network's input gradient) to the table's gradient at
    /// `d_table`: each row's to its image's row, or for rows that shared
    /// the mean, their sum to every row divided by the images.
    pub fn record_backward(
        &self,
        rec: &mut Recorder,
        d_input: Columns,
        rows: usize,
        d_table: FloatsAt,
    ) {
        let context = rec.context;
        let taken = self.taken.expect("a forward pass before the backward pass");
        assert!(rows <= self.capacity, "{rows} rows of {}", self.capacity);
        let (table_binding, lead) = self.table_binding(context, d_table);
        let mut params = self.params(&d_input, taken, lead);
        // Rows that shared the mean add into its gradient first.
        let target = if taken == Taken::Mean {
            rec.encoder.clear_buffer(&self.d_mean, 0, None);
            params.table_base = 0;
            self.d_mean.as_entire_buffer_binding()
        } else {
            table_binding.clone()
        };
        let width = self.shape.width;
        for piece in pieces(rows, rows_per_piece(context, d_input.stride, 1)) {
            let (groups, row_stride) = dispatch_grid(piece.len() * width, WORKGROUP);
            let uniform = uniform_buffer(
                context,
                "appearance backward",
                &Params {
                    rows: piece.len() as u32,
                    row_stride,
                    ..params
                },
            );
            self.backward.record_bindings(
                rec,
                &[
                    uniform.as_entire_buffer_binding(),
                    float_range(&self.images, piece.start, piece.len()),
                    float_range(
                        d_input.buffer,
                        d_input.stride * piece.start,
                        d_input.stride * piece.len(),
                    ),
                    target.clone(),
                ],
                groups,
            );
        }
        if taken == Taken::Mean {
            let (groups, row_stride) = dispatch_grid(self.shape.param_count(), WORKGROUP);
            let uniform = uniform_buffer(
                context,
                "appearance spread",
                &Params {
                    row_stride,
                    table_base: lead as u32,
                    ..params
                },
            );
            self.spread.record_bindings(
                rec,
                &[
                    uniform.as_entire_buffer_binding(),
                    self.d_mean.as_entire_buffer_binding(),
                    table_binding,
                ],
                groups,
            );
        }
    }

    /// Bytes of its buffers on the device.
    pub fn bytes(&self) -> usize {
        [&self.images, &self.mean_vector, &self.d_mean]
            .iter()
            .map(|b| b.size() as usize)
            .sum()
    }
}

/// The uniform as the shaders declare it (`engine::gpu::mirror`).
#[cfg(test)]
mod uniform_mirrors {
    use super::*;
    use crate::engine::gpu::mirror::assert_mirrors;

    #[test]
    fn params_of_appearance_common_mirror_the_shader() {
        assert_mirrors!(
            COMMON,
            "Params",
            Params,
            [
                rows, row_stride, width, images, stride, column, image, one_image, table_base
            ]
        );
    }
}
