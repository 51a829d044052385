//! A compute kernel: one WGSL entry point, its bindings, dispatch and
//! read-back. Every `gpu` stage is built from these.

use bytemuck::Pod;
use wgpu::util::DeviceExt;

use crate::engine::gpu::{GpuContext, GpuError};

/// Where a stage records its work: the device it runs on and the command
/// encoder its dispatches and copies go into, submitted together by
/// [`Recorder::submit`]. Every `record_*` function of the engine takes one.
pub struct Recorder<'a> {
    pub context: &'a GpuContext,
    pub encoder: wgpu::CommandEncoder,
}

impl<'a> Recorder<'a> {
    /// A recorder with a fresh encoder on `context`'s device.
    pub fn new(context: &'a GpuContext) -> Self {
        Self {
            context,
            encoder: context.device.create_command_encoder(&Default::default()),
        }
    }

    /// Submits what was recorded so far and goes on in a fresh encoder.
    pub fn submit_so_far(&mut self) {
        let recorded = std::mem::replace(
            &mut self.encoder,
            self.context
                .device
                .create_command_encoder(&Default::default()),
        );
        self.context.queue.submit([recorded.finish()]);
    }

    /// Submits what was recorded.
    pub fn submit(self) {
        self.context.queue.submit([self.encoder.finish()]);
    }
}

/// A compiled compute pipeline. Bindings are taken in order: binding `i` of
/// group 0 is the `i`-th buffer passed to [`Kernel::dispatch`].
pub struct Kernel {
    pub name: String,
    pipeline: wgpu::ComputePipeline,
}

impl Kernel {
    /// Compiles `entry_point` of the WGSL `source`. Shader errors come back
    /// as [`GpuError::Shader`] instead of wgpu's default panic.
    pub fn new(
        context: &GpuContext,
        name: &str,
        source: &str,
        entry_point: &str,
    ) -> Result<Self, GpuError> {
        let device = &context.device;
        let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some(name),
            source: wgpu::ShaderSource::Wgsl(source.into()),
        });
        let pipeline = device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some(name),
            layout: None,
            module: &module,
            entry_point: Some(entry_point),
            compilation_options: Default::default(),
            cache: None,
        });
        if let Some(error) = pollster::block_on(scope.pop()) {
            return Err(GpuError::Shader {
                name: name.to_string(),
                message: error.to_string(),
            });
        }
        Ok(Self {
            name: name.to_string(),
            pipeline,
        })
    }

    /// Records one dispatch of `workgroups` with `buffers` bound in order to
    /// group 0.
    pub fn record(&self, rec: &mut Recorder, buffers: &[&wgpu::Buffer], workgroups: [u32; 3]) {
        let bindings: Vec<wgpu::BufferBinding> = buffers
            .iter()
            .map(|buffer| buffer.as_entire_buffer_binding())
            .collect();
        self.record_bindings(rec, &bindings, workgroups);
    }

    /// As [`Kernel::record`], with each binding a range of a buffer (see
    /// [`float_range`]): how buffers larger than the device's storage
    /// binding limit are processed a piece at a time.
    pub fn record_bindings(
        &self,
        rec: &mut Recorder,
        bindings: &[wgpu::BufferBinding],
        workgroups: [u32; 3],
    ) {
        let resources: Vec<wgpu::BindingResource> = bindings
            .iter()
            .map(|binding| wgpu::BindingResource::Buffer(binding.clone()))
            .collect();
        self.record_resources(rec, &resources, workgroups);
    }

    /// As [`Kernel::record`], with any resources (buffer ranges, texture
    /// views) bound in order.
    pub fn record_resources(
        &self,
        rec: &mut Recorder,
        resources: &[wgpu::BindingResource],
        workgroups: [u32; 3],
    ) {
        let context = rec.context;
        let layout = self.pipeline.get_bind_group_layout(0);
        let entries: Vec<wgpu::BindGroupEntry> = resources
            .iter()
            .enumerate()
            .map(|(i, resource)| wgpu::BindGroupEntry {
                binding: i as u32,
                resource: resource.clone(),
            })
            .collect();
        let bind_group = context
            .device
            .create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some(&self.name),
                layout: &layout,
                entries: &entries,
            });
        let mut pass = rec
            .encoder
            .begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some(&self.name),
                timestamp_writes: None,
            });
        pass.set_pipeline(&self.pipeline);
        pass.set_bind_group(0, &bind_group, &[]);
        pass.dispatch_workgroups(workgroups[0], workgroups[1], workgroups[2]);
        context.counters.count_dispatch();
    }

    /// Records, submits and waits for one dispatch.
    pub fn dispatch(&self, context: &GpuContext, buffers: &[&wgpu::Buffer], workgroups: [u32; 3]) {
        let mut rec = Recorder::new(context);
        self.record(&mut rec, buffers, workgroups);
        rec.submit();
    }
}

/// The f32s of `buffer` from element `offset` on: a network's or a hash
/// table's parameters (or their gradients, at the same offset) inside a
/// model's flat buffer of every field's.
#[derive(Debug, Clone, Copy)]
pub struct FloatsAt<'a> {
    pub buffer: &'a wgpu::Buffer,
    pub offset: usize,
}

impl<'a> FloatsAt<'a> {
    /// The whole of `buffer`, from its first f32.
    pub fn start(buffer: &'a wgpu::Buffer) -> Self {
        Self { buffer, offset: 0 }
    }
}

/// `width` columns from column `start` of a row-major matrix of `stride`
/// f32s a row: where an encoding writes into a network's input matrix, or
/// what a concatenation reads.
#[derive(Debug, Clone, Copy)]
pub struct Columns<'a> {
    pub buffer: &'a wgpu::Buffer,
    pub stride: usize,
    pub start: usize,
    pub width: usize,
}

impl<'a> Columns<'a> {
    /// Every column of a matrix `width` wide.
    pub fn all(buffer: &'a wgpu::Buffer, width: usize) -> Self {
        Self {
            buffer,
            stride: width,
            start: 0,
            width,
        }
    }
}

/// The binding of `len` 4-byte elements of `buffer` from element `start`
/// (a zero-length range binds one element: wgpu rejects empty bindings).
/// `4 · start` must be a multiple of the device's
/// `min_storage_buffer_offset_alignment`.
pub fn float_range(buffer: &wgpu::Buffer, start: usize, len: usize) -> wgpu::BufferBinding<'_> {
    wgpu::BufferBinding {
        buffer,
        offset: 4 * start as u64,
        size: std::num::NonZeroU64::new(4 * len.max(1) as u64),
    }
}

/// Rows of a piece are a multiple of this, so a piece of rows of any width
/// starts at a byte offset that is a multiple of 256, WebGPU's largest
/// `min_storage_buffer_offset_alignment` (4 B · 64 rows · width).
pub const PIECE_ROWS: usize = 64;

/// Rows per piece when rows of `floats_per_row` f32s are bound a piece at a
/// time under the device's storage-binding limit: as many as fit, a
/// multiple of `multiple` and of [`PIECE_ROWS`] (at least one such block).
pub fn rows_per_piece(context: &GpuContext, floats_per_row: usize, multiple: usize) -> usize {
    let limit = context.storage_binding_limit() as usize;
    let block = lcm(PIECE_ROWS, multiple.max(1));
    let fit = limit / (4 * floats_per_row.max(1));
    (fit / block * block).max(block)
}

/// `0..total` in consecutive pieces of at most `per` (one empty piece when
/// `total` is 0, so a dispatch is still recorded, as without pieces).
pub fn pieces(total: usize, per: usize) -> impl Iterator<Item = std::ops::Range<usize>> {
    let per = per.max(1);
    let count = total.div_ceil(per).max(1);
    (0..count).map(move |i| i * per..((i + 1) * per).min(total))
}

fn lcm(a: usize, b: usize) -> usize {
    let (mut x, mut y) = (a, b);
    while y != 0 {
        (x, y) = (y, x % y);
    }
    a / x * b
}

/// Workgroups needed to cover `count` items at `workgroup_size` per group.
pub fn groups_for(count: usize, workgroup_size: u32) -> u32 {
    (count as u32).div_ceil(workgroup_size).max(1)
}

/// A storage buffer holding `data`, readable back and writable from the CPU.
pub fn storage_buffer<T: Pod>(context: &GpuContext, label: &str, data: &[T]) -> wgpu::Buffer {
    let bytes: &[u8] = bytemuck::cast_slice(data);
    // wgpu rejects zero-sized bindings; an empty input still gets 4 bytes.
    let padded;
    let contents = if bytes.is_empty() {
        padded = [0u8; 4];
        &padded[..]
    } else {
        bytes
    };
    context
        .device
        .create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some(label),
            contents,
            usage: wgpu::BufferUsages::STORAGE
                | wgpu::BufferUsages::COPY_SRC
                | wgpu::BufferUsages::COPY_DST,
        })
}

/// A zero-filled storage buffer of `count` elements of `T`.
pub fn zeroed_storage_buffer<T: Pod>(
    context: &GpuContext,
    label: &str,
    count: usize,
) -> wgpu::Buffer {
    let size = (count * std::mem::size_of::<T>()).max(4) as u64;
    context.device.create_buffer(&wgpu::BufferDescriptor {
        label: Some(label),
        size,
        usage: wgpu::BufferUsages::STORAGE
            | wgpu::BufferUsages::COPY_SRC
            | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    })
}

/// A uniform buffer holding `value`.
pub fn uniform_buffer<T: Pod>(context: &GpuContext, label: &str, value: &T) -> wgpu::Buffer {
    context
        .device
        .create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some(label),
            contents: bytemuck::bytes_of(value),
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
        })
}

/// Copies `count` elements of `T` out of a storage buffer, waiting for the
/// GPU.
pub fn read_buffer<T: Pod>(context: &GpuContext, buffer: &wgpu::Buffer, count: usize) -> Vec<T> {
    let size = (count * std::mem::size_of::<T>()) as u64;
    if size == 0 {
        return Vec::new();
    }
    let staging = context.device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("read back"),
        size,
        usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });
    let mut encoder = context.device.create_command_encoder(&Default::default());
    encoder.copy_buffer_to_buffer(buffer, 0, &staging, 0, size);
    context.queue.submit([encoder.finish()]);
    context.counters.count_blocking_readback();
    let slice = staging.slice(..);
    let (sender, receiver) = std::sync::mpsc::channel();
    slice.map_async(wgpu::MapMode::Read, move |result| {
        let _ = sender.send(result);
    });
    context
        .device
        .poll(wgpu::PollType::wait_indefinitely())
        .expect("waiting for the GPU");
    receiver
        .recv()
        .expect("map callback ran")
        .expect("mapping the read-back buffer");
    let view = slice.get_mapped_range().expect("mapped range");
    bytemuck::cast_slice(&view).to_vec()
}

/// Maps a MAP_READ buffer, copies `count` values out and unmaps it.
pub fn read_mapped<T: bytemuck::Pod>(
    context: &GpuContext,
    staging: &wgpu::Buffer,
    count: usize,
) -> Vec<T> {
    let size = (count * std::mem::size_of::<T>()) as u64;
    context.counters.count_blocking_readback();
    let slice = staging.slice(..size);
    let (sender, receiver) = std::sync::mpsc::channel();
    slice.map_async(wgpu::MapMode::Read, move |result| {
        let _ = sender.send(result);
    });
    context
        .device
        .poll(wgpu::PollType::wait_indefinitely())
        .expect("waiting for the GPU");
    receiver
        .recv()
        .expect("map callback ran")
        .expect("mapping the read-back buffer");
    let values = {
        let view = slice.get_mapped_range().expect("mapped range");
        bytemuck::cast_slice(&view).to_vec()
    };
    staging.unmap();
    values
}

/// A read-back that does not wait: asked for right after the submission
/// that fills a MAP_READ buffer, and taken once the device has finished it,
/// which any later blocking read-back on the same queue guarantees (the
/// queue runs submissions in order). How a training step reads its loss,
/// stage times and occupancy densities with the next step's one blocking
/// read-back instead of one wait each.
pub struct MapRequest {
    buffer: wgpu::Buffer,
    bytes: u64,
    done: std::sync::mpsc::Receiver<Result<(), wgpu::BufferAsyncError>>,
}

impl MapRequest {
    /// Asks for the first `bytes` of `staging` (MAP_READ) to be mapped once
    /// the work submitted so far is done.
    pub fn new(staging: &wgpu::Buffer, bytes: u64) -> Self {
        let (sender, done) = std::sync::mpsc::channel();
        staging
            .slice(..bytes)
            .map_async(wgpu::MapMode::Read, move |result| {
                let _ = sender.send(result);
            });
        Self {
            buffer: staging.clone(),
            bytes,
            done,
        }
    }

    /// The values, and the buffer unmapped for the next copy into it. If
    /// the device has not finished yet, waits for it (a blocking read-back,
    /// counted as one).
    pub fn take<T: Pod>(self, context: &GpuContext) -> Vec<T> {
        let _ = context.device.poll(wgpu::PollType::Poll);
        let result = match self.done.try_recv() {
            Ok(result) => result,
            Err(_) => {
                context.counters.count_blocking_readback();
                context
                    .device
                    .poll(wgpu::PollType::wait_indefinitely())
                    .expect("waiting for the GPU");
                self.done.recv().expect("map callback ran")
            }
        };
        result.expect("mapping the read-back buffer");
        let slice = self.buffer.slice(..self.bytes);
        let values = {
            let view = slice.get_mapped_range().expect("mapped range");
            bytemuck::cast_slice(&view).to_vec()
        };
        self.buffer.unmap();
        values
    }
}

/// A buffer the host maps to read what the device wrote into it.
pub fn staging_buffer(context: &GpuContext, label: &str, bytes: u64) -> wgpu::Buffer {
    context.device.create_buffer(&wgpu::BufferDescriptor {
        label: Some(label),
        size: bytes.max(4),
        usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    })
}
