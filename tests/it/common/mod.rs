//! Helpers shared by the integration tests: small demo scenes, ray batches,
//! NeRF's field in miniature, a gpu context, and the `zrak` binary run as a
//! child process.
//!
//! Every test holds [`shared`] or [`alone`] while it runs.
#![allow(dead_code)]

pub mod demo_ngp;
pub mod gate_record;
pub mod march;
pub mod worker;

use std::path::PathBuf;
use std::process::{Child, Output};
use std::sync::{Arc, RwLock, RwLockReadGuard, RwLockWriteGuard};
use std::time::{Duration, Instant};

use zrak::engine::gpu::GpuContext;
use zrak::field::encoding::FrequencyEncoding;
use zrak::field::nerf::{DensityActivation, NerfShape};
use zrak::model::batch::{RayBatch, TrainingBackground, sample_rays};
use zrak::rng::Pcg32;
use zrak::scene::Scene;
use zrak::scene::demo::{
    DemoConfig, {self},
};

/// The demo scene at `size` × `size` pixels with 12 training views (2
/// held out, 1 test): enough views for a few training steps, small enough
/// to build in milliseconds.
pub fn small_scene(size: u32) -> Arc<Scene> {
    Arc::new(demo::build(&DemoConfig {
        size,
        train_views: 12,
        val_views: 2,
        test_views: 1,
    }))
}

/// `rays` training rays of `scene`, drawn with `seed`, each over a random
/// background as training draws them.
pub fn batch(scene: &Scene, rays: usize, seed: u64) -> RayBatch {
    let mut batch = RayBatch::default();
    sample_rays(
        &scene.train,
        rays,
        TrainingBackground::Random,
        &mut Pcg32::new(seed, 0),
        &mut batch,
    );
    batch
}

/// Which of the two NeRF-shaped models a small field is for.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum NerfKind {
    Nerf,
    MipNerf,
}

/// Each model's field in miniature: the same parts (NeRF: both encodings
/// with their raw inputs, ReLU density; Mip-NeRF: the integrated position
/// encoding without it, shifted softplus, widened colours; both: a trunk
/// with the skip, the σ and feature heads, the colour branch), narrow
/// enough for finite differences to be quick and for lavapipe to run a
/// step in seconds.
pub fn small_nerf_shape(kind: NerfKind) -> NerfShape {
    let shape = |position, density| {
        NerfShape::new(
            position,
            FrequencyEncoding {
                frequencies: 2,
                include_input: true,
            },
            16,
            4,
            2,
            8,
            density,
        )
    };
    match kind {
        NerfKind::Nerf => shape(
            FrequencyEncoding {
                frequencies: 3,
                include_input: true,
            },
            DensityActivation::Relu,
        ),
        NerfKind::MipNerf => shape(
            FrequencyEncoding {
                frequencies: 4,
                include_input: false,
            },
            DensityActivation::ShiftedSoftplus { shift: 1.0 },
        )
        .with_colour_padding(zrak::field::mipnerf::RGB_PADDING),
    }
}

/// The gpu engine's device: lavapipe where there is no GPU.
/// The first validation view of `scene` rendered by `model` over white,
/// row-major, with rays without cones (as the gates' records were made).
pub fn render_first_val_view(
    model: &dyn zrak::model::RadianceModel,
    scene: &Scene,
) -> Vec<zrak::model::RenderedPixel> {
    let rays = scene.val[0].camera.all_rays();
    let columns = zrak::model::RayColumns {
        radii: vec![0.0; rays.len()],
        ..zrak::model::RayColumns::of(&rays)
    };
    let mut out = vec![zrak::model::RenderedPixel::default(); rays.len()];
    model.render(columns.over([1.0; 3]), &mut out);
    out
}

pub fn gpu_context() -> GpuContext {
    GpuContext::new().expect("CI installs mesa-vulkan-drivers, so an adapter exists")
}

/// |a − b| / |b|.
pub fn relative(a: f32, b: f32) -> f32 {
    (a - b).abs() / b.abs().max(1e-30)
}

/// ‖a − b‖ / ‖b‖ in f64.
pub fn relative_norm(a: &[f32], b: &[f32]) -> f64 {
    let (mut d, mut n) = (0.0f64, 0.0f64);
    for (&x, &y) in a.iter().zip(b) {
        d += (x as f64 - y as f64).powi(2);
        n += (y as f64).powi(2);
    }
    (d / n.max(1e-300)).sqrt()
}

/// What σ and colour two models holding the same parameters, one per
/// engine, answer at `n` random points of [-1.2, 1.2]³ with random
/// directions: f32 networks on both engines summed in different orders,
/// so σ must agree within 1e-4 of the largest and colours in [0, 1]
/// within 1e-4. Returns the largest σ and how many points the gpu engine
/// gave σ zero (empty cells).
pub fn assert_engines_agree_at_points(
    label: &str,
    cpu: &dyn zrak::model::RadianceModel,
    gpu: &dyn zrak::model::RadianceModel,
    n: usize,
    footprint: f32,
) -> (f32, usize) {
    let mut rng = Pcg32::new(11, 0);
    let mut uniform = || 2.4 * rng.next_f32() - 1.2;
    let positions: Vec<glam::Vec3> = (0..n)
        .map(|_| glam::Vec3::new(uniform(), uniform(), uniform()))
        .collect();
    let directions: Vec<glam::Vec3> = (0..n)
        .map(|_| glam::Vec3::new(uniform(), uniform(), uniform()).normalize_or(glam::Vec3::Z))
        .collect();
    let query = zrak::model::PointQuery {
        positions: &positions,
        directions: &directions,
        footprint,
    };
    let (mut sigma_cpu, mut sigma_gpu) = (vec![0.0; n], vec![0.0; n]);
    cpu.density_at(query, &mut sigma_cpu).unwrap();
    gpu.density_at(query, &mut sigma_gpu)
        .expect("the gpu engine answers σ at points");
    let (mut rgb_cpu, mut rgb_gpu) = (vec![0.0; 3 * n], vec![0.0; 3 * n]);
    cpu.colour_at(query, &mut rgb_cpu).unwrap();
    gpu.colour_at(query, &mut rgb_gpu)
        .expect("the gpu engine answers colours at points");
    let largest = sigma_cpu.iter().fold(0f32, |m, s| m.max(s.abs()));
    let worst = |a: &[f32], b: &[f32]| a.iter().zip(b).fold(0f32, |m, (x, y)| m.max((x - y).abs()));
    let (worst_sigma, worst_rgb) = (worst(&sigma_cpu, &sigma_gpu), worst(&rgb_cpu, &rgb_gpu));
    let empty = sigma_gpu.iter().filter(|s| **s == 0.0).count();
    println!(
        "{label}: σ up to {largest}, worst difference {worst_sigma:e}; colour {worst_rgb:e}; \
         {empty} of {n} zero"
    );
    assert!(worst_sigma <= 1e-4 * largest, "{label}: σ {worst_sigma}");
    assert!(worst_rgb <= 1e-4, "{label}: colour {worst_rgb}");
    (largest, empty)
}

/// The binary under test. `ZRAK_BIN` overrides cargo's path to it for a
/// target folder shared by several checkouts, where another checkout's build
/// may replace `target/debug/zrak` while these tests run.
pub fn zrak_bin() -> PathBuf {
    std::env::var_os("ZRAK_BIN")
        .map_or_else(|| PathBuf::from(env!("CARGO_BIN_EXE_zrak")), PathBuf::from)
}

/// Sends `signal` to the process `pid`, which must still be running (not
/// yet reaped by its parent), so the pid cannot have been reused.
pub fn send_signal(pid: u32, signal: i32) {
    // SAFETY: kill(2) takes no pointers; the caller vouches for the pid.
    let result = unsafe { libc::kill(pid as libc::pid_t, signal) };
    assert_eq!(result, 0, "kill({pid}, {signal})");
}

/// Waits for the child to end (at most `seconds`), returning its output.
pub fn finish(mut child: Child, seconds: u64) -> Output {
    let deadline = Instant::now() + Duration::from_secs(seconds);
    while child.try_wait().expect("waiting on zrak").is_none() {
        if Instant::now() > deadline {
            let _ = child.kill();
            panic!("zrak did not end within {seconds} s of the signal");
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    child.wait_with_output().expect("collecting zrak's output")
}

/// Blocking read-backs of each training step `from..to` of `model` (on
/// the gpu engine, whose context's `counters` count them), on batches of
/// `rays` rays of `scene`.
pub fn readbacks_per_step(
    model: &mut dyn zrak::model::RadianceModel,
    counters: &zrak::engine::gpu::GpuCounters,
    scene: &Scene,
    steps: std::ops::Range<u32>,
) -> Vec<u64> {
    let mut counts = Vec::new();
    for step in steps {
        let rays = batch(scene, model.rays_for_next_batch(), 100 + step as u64);
        let before = counters.read();
        model.step(&rays, step);
        counts.push((counters.read() - before).blocking_readbacks);
    }
    counts
}

/// Held by every test: shared by those that may run side by side, taken
/// whole by those that must run alone.
///
/// The integration tests were one binary per file, and cargo ran the
/// binaries one after another; now one process runs them all, two at a
/// time. A test that measures how the machine shares its time (the
/// viewer's training thread: training's share of the wall clock, how far
/// the picture lags behind training, how soon a resting camera is drawn
/// whole) ran alone in its binary, beside nothing but another test of that
/// binary waiting for its turn. Beside any other test of this process it
/// would share the two cores and rayon's one global thread pool (its steps
/// queued behind another test's work), and its bounds would measure that
/// test too. std's RwLock on Linux lets no new reader in while a writer
/// waits, so [`alone`] waits only for the tests already running.
static CORES: RwLock<()> = RwLock::new(());

/// For a test that may run beside other tests (all but [`alone`]'s).
pub fn shared() -> RwLockReadGuard<'static, ()> {
    // A test that panicked while running alone poisons the lock; the lock
    // guards no data, so the next test goes on.
    CORES.read().unwrap_or_else(|e| e.into_inner())
}

/// For a test that must have the process to itself: see [`CORES`].
pub fn alone() -> RwLockWriteGuard<'static, ()> {
    CORES.write().unwrap_or_else(|e| e.into_inner())
}

/// A request for a model of `kind` with a test's seed, loss and batch,
/// its other settings the model's defaults (f32 products, its default
/// sampler).
pub fn request(
    kind: zrak::field::ModelKind,
    seed: u64,
    loss: zrak::field::common::LossKind,
    batch_samples: Option<usize>,
) -> zrak::engine::request::ModelRequest {
    use zrak::engine::request::{ModelRequest, ModelSettings};
    ModelRequest::new(
        kind,
        ModelSettings {
            loss,
            batch_samples,
            ..ModelSettings::of(kind, seed)
        },
    )
}

/// Checks the step gradient of a proposal-sampled `model` (its samples
/// held) against central finite differences, on the four largest entries
/// of each field: a proposal field's (`proposal(field)`) against the
/// interlevel loss that trains it, the others' against the loss on pixels.
/// 5 %, as for the other models' steps: f32 sums over thousands of
/// samples; a broken link in the chain is off by far more.
pub fn check_proposal_step_gradient(
    model: &mut zrak::engine::cpu::model::CpuModel,
    rays: &RayBatch,
    step: u32,
    proposal: impl Fn(usize) -> bool,
    label: &str,
) {
    let stats = model.forward_backward(rays, step);
    assert!(stats.proposal_loss > 0.0, "{label}: {stats:?}");
    let gradient = model.gradients().to_vec();
    let ranges = model.parameter_ranges().to_vec();
    for (field, range) in ranges.iter().enumerate() {
        let objective = |model: &mut zrak::engine::cpu::model::CpuModel| {
            let stats = model.forward_backward(rays, step);
            if proposal(field) {
                stats.proposal_loss as f64
            } else {
                stats.loss as f64
            }
        };
        let mut order: Vec<usize> = range.clone().collect();
        order.sort_by(|&a, &b| gradient[b].abs().total_cmp(&gradient[a].abs()));
        for &index in order.iter().take(4) {
            let original = model.params()[index];
            let h = (original.abs() * 1e-2).max(1e-3);
            model.params_mut()[index] = original + h;
            let plus = objective(model);
            model.params_mut()[index] = original - h;
            let minus = objective(model);
            model.params_mut()[index] = original;
            let numeric = (plus - minus) / (2.0 * h as f64);
            let analytic = gradient[index] as f64;
            let error = (numeric - analytic).abs() / analytic.abs().max(numeric.abs());
            assert!(
                error < 0.05,
                "{label} field {field} parameter {index}: analytic {analytic:e}, numeric {numeric:e}"
            );
        }
    }
}
