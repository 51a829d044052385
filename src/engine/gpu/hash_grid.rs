//! The multiresolution hash encoding on the GPU (`shaders/hash_*.wgsl`),
//! forward and backward, with the layouts of [`crate::engine::cpu::hash_grid`].
//!
//! The forward pass runs one invocation per (sample, level). The backward
//! pass scatters each invocation's 8 · F contributions into the gradient
//! table with atomic adds: native `atomic<f32>` where the device has
//! `SHADER_FLOAT32_ATOMIC`, otherwise a compare-and-swap loop on the f32's
//! bits in an `atomic<u32>`, which every device supports. Both add exact
//! f32 values; the order of additions varies from run to run either way.

use crate::engine::gpu::{GpuContext, GpuError};
use std::ops::Range;

use super::kernel::{
    FloatsAt, Kernel, Recorder, float_range, pieces, read_buffer, rows_per_piece, storage_buffer,
    uniform_buffer, zeroed_storage_buffer,
};
use crate::field::encoding::{HashGridLayout, LevelLayout};

/// Threads per workgroup in the hash kernels (WORKGROUP in hash_common.wgsl).
const WORKGROUP: u32 = 64;
/// Workgroups per dispatch dimension (wgpu's default limit); larger batches
/// fold into z.
const MAX_GROUPS_PER_DIMENSION: u32 = 65535;

const COMMON: &str = include_str!("../../../shaders/hash_common.wgsl");
const ENCODE: &str = include_str!("../../../shaders/hash_encode.wgsl");
const BACKWARD: &str = include_str!("../../../shaders/hash_backward.wgsl");
pub(crate) const ACCUMULATE_FLOAT: &str =
    include_str!("../../../shaders/hash_accumulate_float.wgsl");
pub(crate) const ACCUMULATE_CAS: &str = include_str!("../../../shaders/hash_accumulate_cas.wgsl");

/// `Params` in hash_common.wgsl.
#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct Params {
    count: u32,
    features: u32,
    width: u32,
    groups_x: u32,
    // The dispatch covers levels first_level.. (workgroup y counts from
    // there), and the table binding starts at parameter table_base.
    first_level: u32,
    table_base: u32,
    // The grid's box, see `LevelMath` in the cpu stage.
    box_min: f32,
    inverse_extent: f32,
}

/// Levels whose tables are bound together: `params[base..base + len]`
/// covers them all, `base` rounded down to the device's offset alignment.
#[derive(Debug, Clone, PartialEq)]
struct LevelGroup {
    levels: Range<u32>,
    base: usize,
    len: usize,
}

/// Splits the table into groups of consecutive levels whose parameters
/// fit one storage binding of `limit` bytes, each starting at a multiple
/// of `alignment` bytes.
fn level_groups(
    layout: &HashGridLayout,
    limit: u64,
    alignment: u64,
) -> Result<Vec<LevelGroup>, GpuError> {
    let features = layout.features();
    let align_floats = (alignment / 4).max(1) as usize;
    let span =
        |level: &LevelLayout| level.offset * features..(level.offset + level.entries) * features;
    let mut groups: Vec<LevelGroup> = Vec::new();
    for (l, level) in layout.levels().iter().enumerate() {
        let range = span(level);
        if let Some(group) = groups.last_mut()
            && ((range.end - group.base) * 4) as u64 <= limit
        {
            group.levels.end = l as u32 + 1;
            group.len = range.end - group.base;
            continue;
        }
        let base = range.start / align_floats * align_floats;
        let len = range.end - base;
        if (len * 4) as u64 > limit {
            return Err(GpuError::BindingTooLarge {
                what: format!("hash-grid level {l} ({} entries)", level.entries),
                bytes: (len * 4) as u64,
                limit,
            });
        }
        groups.push(LevelGroup {
            levels: l as u32..l as u32 + 1,
            base,
            len,
        });
    }
    Ok(groups)
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

/// Which pass [`GpuHashGrid::record_pieces`] records: the encoding (the
/// table bound third) or the backward pass (the table's gradient bound
/// fifth).
#[derive(Debug, Clone, Copy)]
enum Pass {
    Encode,
    Backward,
}

/// The compiled hash-grid kernels for one layout.
pub struct GpuHashGrid {
    encode: Kernel,
    backward: Kernel,
    levels: wgpu::Buffer,
    /// Levels bound together (one group unless the table exceeds the
    /// storage-binding limit).
    groups: Vec<LevelGroup>,
    features: u32,
    width: u32,
    box_min: f32,
    inverse_extent: f32,
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
    /// The paper's grid takes at most 64 MiB (16 levels × 2^19 entries ×
    /// 2 features × 4 B), one binding on any adapter wgpu exposes with its
    /// own limits (at least 128 MiB). A table over the device's
    /// storage-binding limit is bound as groups of levels, one dispatch per
    /// group; only a single level over the limit is refused. Batches whose
    /// positions or encodings exceed the limit are processed in pieces of
    /// samples.
    pub fn new(
        context: &GpuContext,
        layout: &HashGridLayout,
        use_float_atomics: bool,
    ) -> Result<Self, GpuError> {
        let groups = level_groups(
            layout,
            context.storage_binding_limit(),
            context.limits.min_storage_buffer_offset_alignment as u64,
        )?;
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
        let (box_min, inverse_extent) = layout.config().box_mapping();
        Ok(Self {
            encode,
            backward,
            levels: storage_buffer(context, "hash levels", &levels),
            groups,
            features: layout.features() as u32,
            width: layout.output_width() as u32,
            box_min: box_min as f32,
            inverse_extent: inverse_extent as f32,
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

    /// Records `pass` over `count` samples: one dispatch per piece of
    /// samples and group of levels, binding the uniform, the levels, the
    /// table range of the group (of `table`) and the piece's rows of
    /// positions and of the per-sample matrix (`rows`, count × L·F).
    fn record_pieces(
        &self,
        rec: &mut Recorder,
        pass: Pass,
        table: FloatsAt,
        positions: &wgpu::Buffer,
        rows: &wgpu::Buffer,
        count: usize,
    ) {
        let context = rec.context;
        let (kernel, table_binding) = match pass {
            Pass::Encode => (&self.encode, 2),
            Pass::Backward => (&self.backward, 4),
        };
        let width = self.width as usize;
        let align = Self::offset_alignment(context);
        let per = rows_per_piece(context, width.max(3), 1);
        for piece in pieces(count, per) {
            let groups = u32::try_from(piece.len().div_ceil(WORKGROUP as usize))
                .expect("batch too large for one dispatch")
                .max(1);
            let z = groups.div_ceil(MAX_GROUPS_PER_DIMENSION);
            let x = groups.div_ceil(z);
            for group in &self.groups {
                // A table that starts off the binding alignment (a field
                // after another in a model's flat buffer) is bound from the
                // aligned offset below it; the shader's index, less
                // `table_base`, wraps (u32) onto the same entries.
                let start = table.offset + group.base;
                let lead = start % align;
                let params = Params {
                    count: piece.len() as u32,
                    features: self.features,
                    width: self.width,
                    groups_x: x,
                    first_level: group.levels.start,
                    table_base: (group.base as u32).wrapping_sub(lead as u32),
                    box_min: self.box_min,
                    inverse_extent: self.inverse_extent,
                };
                // A fresh uniform per recorded dispatch, so several can
                // share one command encoder with different batch sizes.
                let uniform = uniform_buffer(context, "hash params", &params);
                let mut bindings = vec![
                    uniform.as_entire_buffer_binding(),
                    self.levels.as_entire_buffer_binding(),
                    float_range(positions, 3 * piece.start, 3 * piece.len()),
                    float_range(rows, width * piece.start, width * piece.len()),
                ];
                bindings.insert(
                    table_binding,
                    float_range(table.buffer, start - lead, group.len + lead),
                );
                kernel.record_bindings(rec, &bindings, [x, group.levels.len() as u32, z]);
            }
        }
    }

    /// Records the encoding of `count` positions (count × 3 f32) into
    /// `encoded` (count × L·F f32), reading the table from `params`.
    pub fn record_encode(
        &self,
        rec: &mut Recorder,
        params: &wgpu::Buffer,
        positions: &wgpu::Buffer,
        encoded: &wgpu::Buffer,
        count: usize,
    ) {
        self.record_encode_at(rec, FloatsAt::start(params), positions, encoded, count);
    }

    /// As [`Self::record_encode`], the table at `table` (any offset).
    pub fn record_encode_at(
        &self,
        rec: &mut Recorder,
        table: FloatsAt,
        positions: &wgpu::Buffer,
        encoded: &wgpu::Buffer,
        count: usize,
    ) {
        self.record_pieces(rec, Pass::Encode, table, positions, encoded, count);
    }

    /// The f32s a table's offset in its buffer must be a multiple of: the
    /// device's storage-binding offset alignment.
    pub fn offset_alignment(context: &GpuContext) -> usize {
        (context.limits.min_storage_buffer_offset_alignment as usize / 4).max(1)
    }

    /// Records the backward pass: adds (+=) ∂loss/∂params into `d_params`
    /// given ∂loss/∂encoded in `d_encoded` (count × L·F). Clear `d_params`
    /// first (`encoder.clear_buffer`) for a fresh gradient.
    pub fn record_backward(
        &self,
        rec: &mut Recorder,
        positions: &wgpu::Buffer,
        d_encoded: &wgpu::Buffer,
        d_params: &wgpu::Buffer,
        count: usize,
    ) {
        self.record_backward_at(rec, positions, d_encoded, FloatsAt::start(d_params), count);
    }

    /// As [`Self::record_backward`], the table's gradient at `d_table`
    /// (any offset).
    pub fn record_backward_at(
        &self,
        rec: &mut Recorder,
        positions: &wgpu::Buffer,
        d_encoded: &wgpu::Buffer,
        d_table: FloatsAt,
        count: usize,
    ) {
        self.record_pieces(rec, Pass::Backward, d_table, positions, d_encoded, count);
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
        let mut rec = Recorder::new(context);
        self.record_encode(&mut rec, &params, &positions, &encoded, count);
        rec.submit();
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
        let mut rec = Recorder::new(context);
        // wgpu zero-initialises new buffers already; clearing states it.
        rec.encoder.clear_buffer(&d_params, 0, None);
        self.record_backward(&mut rec, &positions, &d_encoded, &d_params, count);
        rec.submit();
        read_buffer(context, &d_params, self.param_count)
    }
}

/// The uniforms as the shaders declare them (`engine::gpu::mirror`).
#[cfg(test)]
mod uniform_mirrors {
    use super::*;
    use crate::engine::gpu::mirror::assert_mirrors;

    #[test]
    fn params_of_hash_common_mirror_the_shader() {
        assert_mirrors!(
            include_str!("../../../shaders/hash_common.wgsl"),
            "Params",
            Params,
            [
                count,
                features,
                width,
                groups_x,
                first_level,
                table_base,
                box_min,
                inverse_extent
            ]
        );
    }
    #[test]
    fn level_of_hash_common_mirror_the_shader() {
        assert_mirrors!(
            include_str!("../../../shaders/hash_common.wgsl"),
            "Level",
            Level,
            [resolution, offset, dense, mask]
        );
    }
}
