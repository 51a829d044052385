//! `zrak bench gpu`: what the device offers, whether the gpu engine computes
//! what the cpu engine computes on it, and how long each stage of a training
//! step takes there.
//!
//! The self-check runs each model on the same small inputs on both engines,
//! from the same state, and holds the gpu to the tolerances the parity tests
//! hold it to on lavapipe (`tests/it/ngp_gpu.rs`, `tests/it/nerf_gpu.rs`,
//! `tests/it/render_texture_gpu.rs`): a user with any GPU learns whether zrak
//! computes right there with nothing but the binary.

use std::sync::Arc;

use wgpu::Features;

use crate::engine::gpu::GpuContext;
use crate::engine::gpu::render::{read_texture_rgba8, render_target};
use crate::engine::request::{ModelRequest, ModelSettings};
use crate::engine::{EngineChoice, EngineKind, build};
use crate::field::ModelKind;
use crate::field::common::Sampling;
use crate::field::mlp::Precision;
use crate::model::batch::{RayBatch, TrainingBackground, sample_rays};
use crate::model::checkpoint::Checkpoint;
use crate::model::pixels::{render_pixels, to_image};
use crate::model::{RadianceModel, RenderMode};
use crate::rng::Pcg32;
use crate::scene::demo::{
    DemoConfig, {self},
};

/// The features the engine uses or could use, with what each is for.
const FEATURES: [(Features, &str); 7] = [
    (
        Features::SHADER_FLOAT32_ATOMIC,
        "used: the hash grid's backward pass adds with float atomics (else compare-and-swap)",
    ),
    (
        Features::TIMESTAMP_QUERY,
        "used: the per-stage times of a training step",
    ),
    (
        Features::TIMESTAMP_QUERY_INSIDE_ENCODERS,
        "not needed: stage boundaries are empty passes",
    ),
    (Features::SHADER_F16, "requested; no kernel uses f16 yet"),
    (
        Features::SUBGROUP,
        "not used yet: reductions and scatter-adds in registers",
    ),
    (
        Features::EXPERIMENTAL_COOPERATIVE_MATRIX,
        "not used yet: tensor-core products for NeRF's 256-wide networks",
    ),
    (
        Features::SHADER_INT64,
        "not used: 64-bit hashing is not needed",
    ),
];

/// Lines describing the adapter, its driver, the limits the engine plans
/// with and the features it has, as `(name, value)` pairs.
pub fn describe_device(context: &GpuContext) -> Vec<(String, String)> {
    let info = &context.info;
    let limits = &context.limits;
    let mut lines = vec![
        ("adapter".to_string(), context.describe()),
        (
            "driver".into(),
            format!("{} {}", info.driver, info.driver_info)
                .trim()
                .to_string(),
        ),
        (
            "vendor / device".into(),
            format!("{:#06x} / {:#06x}", info.vendor, info.device),
        ),
        (
            "storage binding".into(),
            format!(
                "{} MiB at most (buffers up to {} MiB)",
                limits.max_storage_buffer_binding_size >> 20,
                limits.max_buffer_size >> 20
            ),
        ),
        (
            "storage buffers".into(),
            format!(
                "{} per shader stage",
                limits.max_storage_buffers_per_shader_stage
            ),
        ),
        (
            "workgroup memory".into(),
            format!(
                "{} KiB; {} invocations per workgroup; {} workgroups per dimension",
                limits.max_compute_workgroup_storage_size >> 10,
                limits.max_compute_invocations_per_workgroup,
                limits.max_compute_workgroups_per_dimension
            ),
        ),
        (
            "subgroup size".into(),
            format!("{} to {}", info.subgroup_min_size, info.subgroup_max_size),
        ),
    ];
    let adapter_features = context.adapter.features();
    for (feature, what) in FEATURES {
        let name = feature
            .iter_names()
            .next()
            .map_or_else(|| format!("{feature:?}"), |(name, _)| name.to_string());
        let state = match (
            adapter_features.contains(feature),
            context.device.features().contains(feature),
        ) {
            (true, true) => "yes, enabled",
            (true, false) => "yes",
            (false, _) => "no",
        };
        lines.push((name.to_lowercase(), format!("{state} ({what})")));
    }
    let cooperative = context.adapter.cooperative_matrix_properties();
    lines.push((
        "cooperative matrices".into(),
        if cooperative.is_empty() {
            "none".into()
        } else {
            cooperative
                .iter()
                .map(|p| {
                    format!(
                        "{}x{}x{} {:?}×{:?}→{:?}",
                        p.m_size, p.n_size, p.k_size, p.ab_type, p.ab_type, p.cr_type
                    )
                })
                .collect::<Vec<_>>()
                .join(", ")
        },
    ));
    lines
}

/// How large the self-check's inputs are.
#[derive(Debug, Clone, Copy)]
pub struct CheckSize {
    /// The demo scene's side in pixels.
    pub scene_pixels: u32,
    /// Samples per training batch.
    pub batch_samples: usize,
    /// Side of the rendered square of a held-out view, in pixels.
    pub render_pixels: u32,
}

impl CheckSize {
    /// A few seconds per model on a real GPU.
    pub const DEVICE: CheckSize = CheckSize {
        scene_pixels: 64,
        batch_samples: 1 << 14,
        render_pixels: 32,
    };
    /// Small enough for a software adapter (lavapipe runs NeRF's 8 × 256
    /// network at a few GFLOP/s): the check `cargo test` runs.
    pub const SOFTWARE: CheckSize = CheckSize {
        scene_pixels: 32,
        batch_samples: 1 << 12,
        render_pixels: 6,
    };
}

/// One comparison of the self-check.
#[derive(Debug, Clone)]
pub struct Check {
    pub model: ModelKind,
    pub what: &'static str,
    /// The figure measured, in words.
    pub measured: String,
    /// The tolerance it is held to, in words.
    pub limit: String,
    pub passed: bool,
}

/// Tolerances, each the one the parity tests use on lavapipe.
///
/// The loss is a mean of per-channel terms computed by the same formulas in
/// f32: the engines agree to ~1e-6, and 1e-4 still catches any wrong
/// sample, ray or weight (`tests/it/ngp_gpu.rs`).
const LOSS_RELATIVE: f32 = 1e-4;
/// An update that differs by more than this, relatively, is a mismatch.
const PARAMETER_RELATIVE: f32 = 1e-3;
/// Colours and opacity lie in [0, 1]; 1e-4 is a stage's relative 1e-4 at
/// full scale, and early termination can move a ray's cut by one sample
/// (`tests/it/ngp_gpu.rs`).
const RENDER_ABSOLUTE: f32 = 1e-4;
/// The texture render rounds to 8 bits on the device, the read-back render
/// on the host: a value at a half level may round either way
/// (`tests/it/render_texture_gpu.rs`).
const TEXTURE_LEVELS: u8 = 1;

fn relative(a: f32, b: f32) -> f32 {
    (a - b).abs() / a.abs().max(b.abs()).max(1e-30)
}

fn params_of(checkpoint: &Checkpoint) -> Option<&[f32]> {
    checkpoint
        .tensors
        .iter()
        .find(|(name, _)| name == "params")
        .map(|(_, values)| values.as_slice())
}

/// Runs the self-check of `kind` on `context`: one training step and one
/// render on the gpu engine against the cpu engine, from the same state.
pub fn self_check(context: &GpuContext, kind: ModelKind, size: CheckSize) -> Vec<Check> {
    let mut checks = Vec::new();
    let mut check = |what: &'static str, measured: String, limit: String, passed: bool| {
        checks.push(Check {
            model: kind,
            what,
            measured,
            limit,
            passed,
        });
    };
    let scene = Arc::new(demo::build(&DemoConfig {
        size: size.scene_pixels,
        train_views: 12,
        val_views: 2,
        test_views: 1,
    }));
    let settings = ModelSettings {
        seed: 5,
        loss: kind.default_loss(),
        batch_samples: Some(size.batch_samples),
        sampling: Sampling::Occupancy,
        precision: Precision::F32,
        refine_cameras: false,
        appearance: false,
    };
    let cpu_choice = EngineChoice {
        kind: EngineKind::Cpu,
        gpu: None,
        reason: "self-check".into(),
    };
    let gpu_choice = EngineChoice {
        kind: EngineKind::Gpu,
        gpu: Some(
            GpuContext::from_existing(
                &context.adapter,
                context.device.clone(),
                context.queue.clone(),
            )
            .expect("a device that made a context makes another"),
        ),
        reason: "self-check".into(),
    };
    let request = ModelRequest::new(kind, settings);
    let built = build(&request, cpu_choice, &scene)
        .and_then(|cpu| build(&request, gpu_choice, &scene).map(|gpu| (cpu, gpu)))
        .map_err(|e| e.to_string());
    let (mut cpu, mut gpu) = match built {
        Ok(models) => models,
        Err(error) => {
            check("build", error, "builds on both engines".into(), false);
            return checks;
        }
    };

    // A few steps on the cpu first (the occupancy grid's first updates),
    // then the gpu model takes the cpu model's whole state.
    let mut batch = RayBatch::default();
    let mut rng = Pcg32::new(17, 0);
    let mut draw = |model: &dyn RadianceModel, batch: &mut RayBatch| {
        sample_rays(
            &scene.train,
            model.rays_for_next_batch(),
            TrainingBackground::Random,
            &mut rng,
            batch,
        );
    };
    const FIRST_STEPS: u32 = 3;
    for step in 0..FIRST_STEPS {
        draw(cpu.as_ref(), &mut batch);
        cpu.step(&batch, step);
    }
    // The step's own loss and the cpu engine's order of grid updates.
    gpu.set_read_back_late(false);
    if let Err(error) = gpu.load(&cpu.save()) {
        check(
            "state",
            error,
            "the cpu model's checkpoint loads".into(),
            false,
        );
        return checks;
    }

    // The same step on both.
    let before = cpu.save();
    draw(cpu.as_ref(), &mut batch);
    let step = FIRST_STEPS;
    let cpu_stats = cpu.step(&batch, step);
    let gpu_stats = gpu.step(&batch, step);
    check(
        "samples marched",
        format!("cpu {} gpu {}", cpu_stats.samples, gpu_stats.samples),
        "equal".into(),
        cpu_stats.samples == gpu_stats.samples && cpu_stats.rays == gpu_stats.rays,
    );
    let loss_error = relative(gpu_stats.loss, cpu_stats.loss);
    check(
        "training loss",
        format!(
            "cpu {:.6e} gpu {:.6e}: relative {loss_error:.1e}",
            cpu_stats.loss, gpu_stats.loss
        ),
        format!("≤ {LOSS_RELATIVE:.0e}"),
        loss_error <= LOSS_RELATIVE && gpu_stats.loss.is_finite(),
    );
    let (cpu_after, gpu_after) = (cpu.save(), gpu.save());
    if let (Some(before), Some(cpu_params), Some(gpu_params)) = (
        params_of(&before),
        params_of(&cpu_after),
        params_of(&gpu_after),
    ) {
        let (mut changed, mut mismatched) = (0usize, 0usize);
        for ((&b, &c), &g) in before.iter().zip(cpu_params).zip(gpu_params) {
            if c == b && g == b {
                continue;
            }
            changed += 1;
            if !g.is_finite() || relative(g, c) > PARAMETER_RELATIVE {
                mismatched += 1;
            }
        }
        let allowed = kind.spec().engine_update_mismatch_share;
        let share = mismatched as f64 / changed.max(1) as f64;
        check(
            "parameters after Adam",
            format!(
                "{mismatched} of {changed} updated parameters differ by more than \
                 {PARAMETER_RELATIVE:.0e} ({:.3} %)",
                100.0 * share
            ),
            format!("≤ {:.1} %, and some updated", 100.0 * allowed),
            changed > 0 && share <= allowed,
        );
    }

    // The gpu's state rendered by both engines.
    if let Err(error) = cpu.load(&gpu_after) {
        check(
            "state",
            error,
            "the gpu model's checkpoint loads".into(),
            false,
        );
        return checks;
    }
    // The centre of a held-out view: where the demo's objects are.
    let full = &scene.val[0].camera;
    let k = full.intrinsics;
    let (width, height) = (
        size.render_pixels.min(k.width),
        size.render_pixels.min(k.height),
    );
    let camera = crate::scene::Camera::new(
        k.cropped(
            (k.width - width) / 2,
            (k.height - height) / 2,
            width,
            height,
        ),
        full.camera_to_world,
    );
    let background = [1.0; 3];
    let from_cpu = render_pixels(cpu.as_ref(), &camera, background);
    let from_gpu = render_pixels(gpu.as_ref(), &camera, background);
    let worst = from_cpu
        .iter()
        .zip(&from_gpu)
        .flat_map(|(a, b)| {
            a.rgb
                .iter()
                .zip(&b.rgb)
                .chain([(&a.opacity, &b.opacity)])
                .map(|(x, y)| {
                    if x.is_finite() && y.is_finite() {
                        (x - y).abs()
                    } else {
                        f32::INFINITY
                    }
                })
        })
        .fold(0f32, f32::max);
    check(
        "render",
        format!(
            "{} pixels: largest colour or opacity difference {worst:.1e}",
            from_cpu.len()
        ),
        format!("≤ {RENDER_ABSOLUTE:.0e}"),
        worst <= RENDER_ABSOLUTE,
    );
    if let Some(texture_render) = gpu.texture_render() {
        let (width, height) = (camera.intrinsics.width, camera.intrinsics.height);
        let texture = render_target(&context.device, width, height);
        match texture_render.render_to_texture(&camera, RenderMode::Rgb, background, &texture) {
            Ok(()) => {
                let on_device = read_texture_rgba8(context, &texture);
                let expected = to_image(&from_cpu, width, height, RenderMode::Rgb, (0.0, 1.0));
                let worst = on_device
                    .iter()
                    .zip(&expected.data)
                    .map(|(a, b)| a.abs_diff(*b))
                    .max()
                    .unwrap_or(0);
                check(
                    "texture render",
                    format!("largest difference {worst} level(s) of 255"),
                    format!("≤ {TEXTURE_LEVELS}"),
                    on_device.len() == expected.data.len() && worst <= TEXTURE_LEVELS,
                );
            }
            Err(error) => check("texture render", error, "renders".into(), false),
        }
    }
    checks
}

/// The self-check's verdict on a whole run: every check passed.
pub fn all_passed(checks: &[Check]) -> bool {
    checks.iter().all(|c| c.passed)
}

/// The scene the self-check trains on, for callers that report on it.
pub fn check_scene_name(size: CheckSize) -> String {
    format!("the demo scene at {0} × {0}", size.scene_pixels)
}
