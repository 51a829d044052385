//! The Adam step on the GPU (`shaders/adam.wgsl`): the state of
//! [`crate::engine::shared::adam::Adam`] in GPU buffers, updated by the same
//! formula, one invocation per parameter.

use std::ops::Range;

use super::composite::grid;
use super::kernel::{
    Kernel, Recorder, float_range, pieces, read_buffer, rows_per_piece, storage_buffer,
    uniform_buffer,
};
use crate::engine::gpu::{GpuContext, GpuError};
use crate::engine::shared::adam::Adam;
use crate::field::common::OptimiserConfig;
use crate::field::params::{ParamLayout, Update};

/// Threads per workgroup in adam.wgsl.
const WORKGROUP: u32 = 256;

#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct Params {
    count: u32,
    row_stride: u32,
    network_start: u32,
    network_end: u32,
    learning_rate: f32,
    beta1: f32,
    beta2: f32,
    one_minus_beta1: f32,
    one_minus_beta2: f32,
    epsilon: f32,
    l2: f32,
    first: u32,
}

/// Adam's state on the GPU and the compiled step.
pub struct GpuAdam {
    kernel: Kernel,
    pub m: wgpu::Buffer,
    pub v: wgpu::Buffer,
    pub m_norm: wgpu::Buffer,
    pub v_norm: wgpu::Buffer,
    /// Optimiser steps taken (drives the learning-rate schedule).
    pub step: u32,
    count: usize,
}

impl GpuAdam {
    /// Fresh state for `count` parameters.
    pub fn new(context: &GpuContext, count: usize) -> Result<Self, GpuError> {
        Self::from_state(context, &Adam::new(count))
    }

    /// The GPU copy of a cpu state (a fresh one, or one from a checkpoint).
    pub fn from_state(context: &GpuContext, state: &Adam) -> Result<Self, GpuError> {
        let count = state.len();
        // Arrays larger than the storage-binding limit are updated a piece
        // at a time (`record_step`).
        Ok(Self {
            kernel: Kernel::new(
                context,
                "adam",
                include_str!("../../../shaders/adam.wgsl"),
                "main",
            )?,
            m: storage_buffer(context, "adam m", &state.m),
            v: storage_buffer(context, "adam v", &state.v),
            m_norm: storage_buffer(context, "adam m_norm", &state.m_norm),
            v_norm: storage_buffer(context, "adam v_norm", &state.v_norm),
            step: state.step,
            count,
        })
    }

    pub fn len(&self) -> usize {
        self.count
    }

    pub fn is_empty(&self) -> bool {
        self.count == 0
    }

    /// Reads the state back (for checkpoints and tests).
    pub fn read_state(&self, context: &GpuContext) -> Adam {
        Adam {
            m: read_buffer(context, &self.m, self.count),
            v: read_buffer(context, &self.v, self.count),
            m_norm: read_buffer(context, &self.m_norm, self.count),
            v_norm: read_buffer(context, &self.v_norm, self.count),
            step: self.step,
        }
    }

    /// Records one update of `params` from `gradients` (both `len()` f32s).
    /// `network_weights` gets L2 regularisation and dense updates; every
    /// other parameter is skipped where its gradient is exactly zero, as
    /// in [`Adam::step`].
    pub fn record_step(
        &mut self,
        rec: &mut Recorder,
        config: &OptimiserConfig,
        network_weights: Range<usize>,
        params: &wgpu::Buffer,
        gradients: &wgpu::Buffer,
    ) {
        assert!(network_weights.start <= network_weights.end && network_weights.end <= self.count);
        let learning_rate = config.learning_rate_at(self.step);
        self.step += 1;
        self.record_span(
            rec,
            (config, learning_rate, config.l2_weights),
            0..self.count,
            network_weights,
            (params, gradients),
        );
    }

    /// Records one update of `params` from `gradients`, each part of
    /// `layout` as its [`Update`] says (as the cpu's `Adam::step_layout`):
    /// one pass over every parameter where the dense parts are contiguous
    /// and agree on weight decay (every model's layout), else one per part.
    pub fn record_step_layout(
        &mut self,
        rec: &mut Recorder,
        config: &OptimiserConfig,
        layout: &ParamLayout,
        params: &wgpu::Buffer,
        gradients: &wgpu::Buffer,
    ) {
        assert_eq!(layout.len(), self.count, "the layout's parameters");
        let learning_rate = config.learning_rate_at(self.step);
        self.step += 1;
        let decay = |l2: bool| if l2 { config.l2_weights } else { 0.0 };
        if let Some((dense, l2)) = layout.single_dense_span() {
            self.record_span(
                rec,
                (config, learning_rate, decay(l2)),
                0..self.count,
                dense,
                (params, gradients),
            );
            return;
        }
        for part in layout.parts() {
            let (dense, l2) = match part.update {
                Update::Dense { l2 } => (part.range.clone(), l2),
                Update::Sparse => (part.range.start..part.range.start, false),
            };
            self.record_span(
                rec,
                (config, learning_rate, decay(l2)),
                part.range.clone(),
                dense,
                (params, gradients),
            );
        }
    }

    /// Records the update of parameters `span` (`dense` among them updated
    /// densely with weight decay `l2`, the rest sparsely) at
    /// `learning_rate`.
    fn record_span(
        &self,
        rec: &mut Recorder,
        (config, learning_rate, l2): (&OptimiserConfig, f32, f32),
        span: Range<usize>,
        network_weights: Range<usize>,
        (params, gradients): (&wgpu::Buffer, &wgpu::Buffer),
    ) {
        let context = rec.context;
        // Every array is bound a piece at a time when it exceeds the
        // storage-binding limit (or the span starts inside the buffer);
        // each element's update is independent.
        // A piece that starts off the binding alignment (a part of the
        // layout after another) is bound from the aligned offset below it,
        // the elements before its start skipped.
        let align = (context.limits.min_storage_buffer_offset_alignment as usize / 4).max(1);
        let per = rows_per_piece(context, 1, 1).saturating_sub(align).max(1);
        for piece in pieces(span.len(), per) {
            let piece = span.start + piece.start..span.start + piece.end;
            let bound = piece.start / align * align;
            let (groups, row_stride) = grid(piece.end - bound, WORKGROUP);
            let relative = |i: usize| i.clamp(piece.start, piece.end) - bound;
            let uniform = Params {
                count: (piece.end - bound) as u32,
                row_stride,
                network_start: relative(network_weights.start) as u32,
                network_end: relative(network_weights.end) as u32,
                learning_rate,
                beta1: config.beta1,
                beta2: config.beta2,
                one_minus_beta1: 1.0 - config.beta1,
                one_minus_beta2: 1.0 - config.beta2,
                epsilon: config.epsilon,
                l2,
                first: (piece.start - bound) as u32,
            };
            let uniform = uniform_buffer(context, "adam params", &uniform);
            let range = |buffer| float_range(buffer, bound, piece.end - bound);
            self.kernel.record_bindings(
                rec,
                &[
                    uniform.as_entire_buffer_binding(),
                    range(params),
                    range(gradients),
                    range(&self.m),
                    range(&self.v),
                    range(&self.m_norm),
                    range(&self.v_norm),
                ],
                groups,
            );
        }
    }
}

/// The uniforms as the shaders declare them (`engine::gpu::mirror`).
#[cfg(test)]
mod uniform_mirrors {
    use super::*;
    use crate::engine::gpu::mirror::assert_mirrors;

    #[test]
    fn params_of_adam_mirror_the_shader() {
        assert_mirrors!(
            include_str!("../../../shaders/adam.wgsl"),
            "Params",
            Params,
            [
                count,
                row_stride,
                network_start,
                network_end,
                learning_rate,
                beta1,
                beta2,
                one_minus_beta1,
                one_minus_beta2,
                epsilon,
                l2,
                first
            ]
        );
    }
}
