//! The wgpu context runs WGSL on whatever adapter the machine has (lavapipe in
//! CI) and returns what the cpu computes.

use crate::common;

use zrak::engine::build_gpu;
use zrak::engine::gpu::GpuContext;
use zrak::engine::gpu::kernel::{Kernel, groups_for, read_buffer, storage_buffer, uniform_buffer};
use zrak::field::ModelKind;

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct Params {
    a: f32,
    count: u32,
}

#[test]
fn compute_shader_matches_cpu() {
    let _cores = crate::common::shared();
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

    let kernel = Kernel::new(
        &context,
        "scale_add",
        include_str!("../../shaders/scale_add.wgsl"),
        "main",
    )
    .unwrap();
    let params = uniform_buffer(
        &context,
        "params",
        &Params {
            a,
            count: count as u32,
        },
    );
    let x_buffer = storage_buffer(&context, "x", &x);
    let y_buffer = storage_buffer(&context, "y", &y);
    kernel.dispatch(
        &context,
        &[&params, &x_buffer, &y_buffer],
        [groups_for(count, 64), 1, 1],
    );
    let result: Vec<f32> = read_buffer(&context, &y_buffer, count);

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

#[test]
fn shader_errors_are_reported_not_panicked() {
    let _cores = crate::common::shared();
    let context = GpuContext::new().expect("an adapter exists");
    let broken = "@compute @workgroup_size(1) fn main() { let x: f32 = undefined_name; }";
    let error = Kernel::new(&context, "broken", broken, "main")
        .err()
        .expect("must not compile");
    let message = error.to_string();
    assert!(
        message.contains("broken") && message.contains("undefined_name"),
        "{message}"
    );
}

/// The viewer hands the engine eframe's device: one made with
/// `GpuContext::device_descriptor` is accepted and runs every kernel of
/// Instant-NGP; one with wgpu's default limits (8 storage buffers per
/// stage) is refused with the limit named.
#[test]
fn an_existing_device_is_used_when_it_has_what_the_engine_needs() {
    let _cores = crate::common::shared();
    use zrak::field::common::LossKind;
    use zrak::scene::demo::{
        DemoConfig, {self},
    };

    let base = GpuContext::new().expect("an adapter exists");
    let adapter = &base.adapter;
    let (device, queue) =
        pollster::block_on(adapter.request_device(&GpuContext::device_descriptor(adapter)))
            .expect("the adapter grants its own limits");
    let context = GpuContext::from_existing(adapter, device, queue).expect("accepted");
    assert_eq!(context.features, base.features);
    assert_eq!(
        context.storage_binding_limit(),
        base.storage_binding_limit()
    );
    let scene = demo::build(&DemoConfig {
        size: 8,
        train_views: 2,
        val_views: 1,
        test_views: 1,
    });
    build_gpu(
        context,
        &crate::common::request(ModelKind::Ngp, 1, LossKind::Huber, Some(1024)),
        &scene,
    )
    .expect("every kernel compiles and binds on the shared device");

    let (device, queue) = pollster::block_on(adapter.request_device(&Default::default()))
        .expect("default limits are always granted");
    let message = GpuContext::from_existing(adapter, device, queue)
        .expect_err("8 storage buffers per stage are too few")
        .to_string();
    assert!(
        message.contains("max_storage_buffers_per_shader_stage"),
        "{message}"
    );
}

/// `scripts/gpu-report` end to end on whatever adapter the machine has
/// (lavapipe in CI), with tiny budgets and Instant-NGP alone: every
/// section runs and succeeds, and the report holds the self-check's verdict,
/// the device counts, the quality run's report and the evaluation.
#[test]
fn the_gpu_report_script_runs_end_to_end() {
    let _cores = crate::common::shared();
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("scene");
    let out = dir.path().join("report");
    let demo = std::process::Command::new(common::zrak_bin())
        .args(["demo", "--size", "64", "--views", "12", "--out"])
        .arg(&scene)
        .output()
        .expect("zrak runs");
    assert!(demo.status.success(), "{demo:?}");
    let script = concat!(env!("CARGO_MANIFEST_DIR"), "/scripts/gpu-report");
    let run = std::process::Command::new("bash")
        .arg(script)
        .arg(&scene)
        .arg(&out)
        .env("ZRAK", common::zrak_bin())
        .env("MODELS", "ngp")
        .env("NGP_BUDGET", "2s")
        .env("STEPS", "2")
        .env("CPU_WARMUP", "1")
        .output()
        .expect("bash runs");
    let report = std::fs::read_to_string(out.join("gpu-report.md")).expect("the report");
    assert!(run.status.success(), "{run:?}\n{report}");
    // Five commands (device and self-check, throughput on each engine, the
    // quality run, the evaluation), each successful.
    assert_eq!(report.matches("exit status ").count(), 5, "{report}");
    assert_eq!(report.matches("exit status 0,").count(), 5, "{report}");
    for part in [
        "self-check: 5 of 5 checks passed",
        "blocking readbacks per step",
        "dispatches per step",
        "## quality-ngp/report.md",
        "## Evaluation, Instant-NGP after 2s, the whole val split",
        "mean",
    ] {
        assert!(report.contains(part), "{part}:\n{report}");
    }
}
