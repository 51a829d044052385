//! The wgpu context runs WGSL on whatever adapter the machine has (lavapipe in
//! CI) and returns what the cpu computes.

use wgpu::util::DeviceExt;
use zrak::engine::gpu::GpuContext;

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct Params {
    a: f32,
    count: u32,
}

#[test]
fn compute_shader_matches_cpu() {
    let context = GpuContext::new().expect("CI installs mesa-vulkan-drivers, so an adapter exists");
    eprintln!("adapter: {}", context.describe());
    // The engine asks for the adapter's own limits, not wgpu's defaults.
    assert_eq!(
        context.device.limits().max_storage_buffer_binding_size,
        context.adapter.limits().max_storage_buffer_binding_size
    );

    // Not a multiple of the workgroup size, so the bounds check matters.
    let count = 1000usize;
    let x: Vec<f32> = (0..count).map(|i| (i as f32).sin()).collect();
    let y: Vec<f32> = (0..count).map(|i| 0.5 * i as f32).collect();
    let a = 1.75f32;

    let device = &context.device;
    let module = device.create_shader_module(wgpu::include_wgsl!("../shaders/scale_add.wgsl"));
    let pipeline = device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
        label: Some("scale_add"),
        layout: None,
        module: &module,
        entry_point: Some("main"),
        compilation_options: Default::default(),
        cache: None,
    });
    let params = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
        label: Some("params"),
        contents: bytemuck::bytes_of(&Params {
            a,
            count: count as u32,
        }),
        usage: wgpu::BufferUsages::UNIFORM,
    });
    let x_buffer = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
        label: Some("x"),
        contents: bytemuck::cast_slice(&x),
        usage: wgpu::BufferUsages::STORAGE,
    });
    let y_buffer = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
        label: Some("y"),
        contents: bytemuck::cast_slice(&y),
        usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
    });
    let readback = device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("readback"),
        size: (count * 4) as u64,
        usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });
    let bind_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
        label: Some("scale_add"),
        layout: &pipeline.get_bind_group_layout(0),
        entries: &[
            wgpu::BindGroupEntry {
                binding: 0,
                resource: params.as_entire_binding(),
            },
            wgpu::BindGroupEntry {
                binding: 1,
                resource: x_buffer.as_entire_binding(),
            },
            wgpu::BindGroupEntry {
                binding: 2,
                resource: y_buffer.as_entire_binding(),
            },
        ],
    });
    let mut encoder = device.create_command_encoder(&Default::default());
    {
        let mut pass = encoder.begin_compute_pass(&Default::default());
        pass.set_pipeline(&pipeline);
        pass.set_bind_group(0, &bind_group, &[]);
        pass.dispatch_workgroups((count as u32).div_ceil(64), 1, 1);
    }
    encoder.copy_buffer_to_buffer(&y_buffer, 0, &readback, 0, (count * 4) as u64);
    context.queue.submit([encoder.finish()]);

    let slice = readback.slice(..);
    slice.map_async(wgpu::MapMode::Read, |result| result.expect("map readback"));
    device
        .poll(wgpu::PollType::wait_indefinitely())
        .expect("device poll");
    let result: Vec<f32> = bytemuck::cast_slice(&slice.get_mapped_range().unwrap()).to_vec();

    for i in 0..count {
        let want = a * x[i] + y[i];
        // One fused or unfused multiply-add: at most one rounding apart.
        let tolerance = 2.0 * f32::EPSILON * want.abs().max(1.0);
        assert!(
            (result[i] - want).abs() <= tolerance,
            "element {i}: gpu {} cpu {want}",
            result[i]
        );
    }
}
