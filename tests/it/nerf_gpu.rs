//! NeRF and Mip-NeRF on the gpu engine (lavapipe) against the cpu engine,
//! each with a small field: one whole training step from the same state
//! with the paper's sampler (loss, gradient, parameters after Adam) and with
//! the occupancy sampler (loss, gradient, the grid's update), and a
//! checkpoint moved from the gpu engine to the cpu engine, and the view
//! the viewer draws into a texture. Every test runs once per model: the two
//! models are one gpu driver with two recipes.
//!
//! Tolerances. Every stage of the step has its own parity test against the
//! cpu (tests/it/nerf_field_gpu.rs, sampling_gpu.rs, composite and loss
//! tests): the sampling kernels are bit-equal, the rest agree to f32
//! rounding, ~1e-6 relative, different only in summation order and in
//! `exp` (the gpu's 1 − e^{−τ} is a Taylor series below τ = 0.25, the
//! cpu's is `exp_m1`). A step chains about a dozen such stages per level
//! (sampling, encodings, three networks forward and back, compositing,
//! loss), and the importance samples move continuously with the coarse
//! weights they are drawn from, so the chain's error is ~1e-5 of the
//! quantities; the tolerances below are 1e-4 (relative), ten times that,
//! and still far below what a wrong sample, weight, chunk share or
//! parameter offset gives (those are off by O(1)). Mip-NeRF's step adds
//! two stages to the chain, both with parity tests of their own: the
//! frustum Gaussians (tests/it/sampling_gpu.rs: within a few ulps, bit-equal
//! on lavapipe) and the integrated encoding (tests/it/frequency_gpu.rs: within
//! 2.2e-7 absolute, the exp of the damping); its resampled edges move
//! continuously with the blurred coarse weights, as NeRF's importance
//! samples do. So the same 1e-4 holds for it, and a frustum stage or
//! encoding that ignored the variances would be off by far more: the small
//! field's highest frequency, 2⁷, is damped by exp(−½·4⁷·σ²), far from 1
//! for this 24-pixel scene's frustums (σ² ~ 1e-5 along a ray, more across
//! its cone).

use std::sync::Arc;
use std::time::Instant;

use glam::{Quat, Vec3};
use zrak::engine::build_gpu;
use zrak::engine::cpu::model::CpuModel;
use zrak::engine::gpu::GpuContext;
use zrak::engine::gpu::model::GpuModel;
use zrak::engine::gpu::render::{read_texture_rgba8, render_target};
use zrak::engine::request::{ModelRequest, ModelSettings};
use zrak::field::common::{LossKind, Recipe, Sampling};
use zrak::field::encoding::FrequencyEncoding;
use zrak::field::nerf::{DensityActivation, NerfShape};
use zrak::field::{ModelKind, mipnerf};
use zrak::model::batch::{RayBatch, TrainingBackground, sample_rays};
use zrak::model::pixels::{render_pixels, to_image};
use zrak::model::{RadianceModel, RenderMode, RenderedPixel};
use zrak::rng::Pcg32;
use zrak::scene::Scene;
use zrak::scene::crop::CropBox;
use zrak::scene::demo::{
    DemoConfig, {self},
};

const SEED: u64 = 3;

fn small_scene() -> Arc<Scene> {
    Arc::new(demo::build(&DemoConfig {
        size: 24,
        train_views: 12,
        val_views: 2,
        test_views: 1,
    }))
}

/// The two models the gpu driver runs on NeRF's field.
#[derive(Debug, Clone, Copy)]
enum Model {
    Nerf,
    MipNerf,
}

impl Model {
    /// The model's field in miniature, as tests/it/nerf_cpu.rs: every part of
    /// the paper's (NeRF: both encodings with raw inputs; Mip-NeRF: the
    /// integrated position encoding without, the shifted softplus and the
    /// widened colour; the skip, σ and feature heads, the colour branch),
    /// narrow enough for lavapipe to run a step in seconds.
    fn shape(self) -> NerfShape {
        let direction = FrequencyEncoding {
            frequencies: 2,
            include_input: true,
        };
        match self {
            Model::Nerf => NerfShape::new(
                FrequencyEncoding {
                    frequencies: 3,
                    include_input: true,
                },
                direction,
                16,
                4,
                2,
                8,
                DensityActivation::Relu,
            ),
            // Six frequencies: the frustums' variances damp the highest
            // ones strongly (see the tolerances above).
            Model::MipNerf => NerfShape::new(
                FrequencyEncoding {
                    frequencies: 6,
                    include_input: false,
                },
                direction,
                16,
                4,
                2,
                8,
                DensityActivation::ShiftedSoftplus {
                    shift: -mipnerf::DENSITY_BIAS,
                },
            )
            .with_colour_padding(mipnerf::RGB_PADDING),
        }
    }

    /// The model on the cpu engine and on the gpu engine, from the same
    /// recipe (the model's own for `scene`, with `change` applied) and
    /// seed.
    fn engines(
        self,
        scene: &Scene,
        settings: &ModelSettings,
        change: impl FnOnce(&mut Recipe),
    ) -> (CpuModel, GpuModel) {
        let kind = match self {
            Model::Nerf => ModelKind::Nerf,
            Model::MipNerf => ModelKind::MipNerf,
        };
        let mut recipe = (kind.spec().recipe)(scene, settings.sampling);
        change(&mut recipe);
        let request = ModelRequest::new(kind, *settings)
            .with_shape(self.shape())
            .with_recipe(recipe);
        let cpu = CpuModel::build(&request, scene);
        let mut gpu = build_gpu(context(), &request, scene).expect("gpu model");
        // Each step's own loss and the cpu's order of grid updates, to
        // compare step by step.
        gpu.set_read_back_late(false);
        (cpu, gpu)
    }
}

fn settings(sampling: Sampling) -> ModelSettings {
    ModelSettings {
        seed: SEED,
        loss: LossKind::L2,
        batch_samples: None,
        sampling,
        precision: zrak::field::mlp::Precision::F32,
        refine_cameras: false,
        appearance: false,
    }
}

fn context() -> GpuContext {
    GpuContext::new().expect("CI installs mesa-vulkan-drivers, so an adapter exists")
}

/// Rays per chunk in these tests (instead of 256), so a batch of a dozen
/// rays spans two chunks, exercising the chunk shares and seeds while
/// lavapipe runs the step in seconds.
const RAYS_PER_CHUNK: usize = 8;

/// The model with the paper's sampler on both engines.
fn models(model: Model, scene: &Scene) -> (CpuModel, GpuModel) {
    let (mut cpu, mut gpu) = model.engines(scene, &settings(Sampling::Paper), |_| {});
    cpu.set_rays_per_chunk(RAYS_PER_CHUNK);
    gpu.set_rays_per_chunk(RAYS_PER_CHUNK).unwrap();
    (cpu, gpu)
}

fn batch(scene: &Scene, rays: usize, seed: u64) -> RayBatch {
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

fn relative(a: f32, b: f32) -> f32 {
    (a - b).abs() / b.abs().max(1e-30)
}

/// ‖a − b‖ / ‖b‖ in f64.
fn relative_norm(a: &[f32], b: &[f32]) -> f64 {
    let (mut d, mut n) = (0.0f64, 0.0f64);
    for (&x, &y) in a.iter().zip(b) {
        d += (x as f64 - y as f64).powi(2);
        n += (y as f64).powi(2);
    }
    (d / n.max(1e-300)).sqrt()
}

#[test]
fn nerf_training_step_matches_the_cpu_engine() {
    let _cores = crate::common::shared();
    one_training_step_matches_the_cpu_engine(Model::Nerf);
}

#[test]
fn mipnerf_training_step_matches_the_cpu_engine() {
    let _cores = crate::common::shared();
    one_training_step_matches_the_cpu_engine(Model::MipNerf);
}

/// One whole step, gpu against cpu, on a batch of two chunks (8 rays and
/// 4: the chunk shares and each chunk's jitter seed are exercised).
fn one_training_step_matches_the_cpu_engine(model: Model) {
    let scene = small_scene();
    let (mut cpu, mut gpu) = models(model, &scene);
    assert!(
        gpu.params() == cpu.params(),
        "initial parameters differ: the engines must start identical"
    );
    let rays = batch(&scene, 12, 17);
    let step = 1;
    let before = cpu.params().to_vec();

    // The gradient first, without Adam.
    let cpu_stats = cpu.forward_backward(&rays, step);
    let clock = Instant::now();
    let gpu_stats = gpu.forward_backward(&rays, step);
    println!(
        "{model:?}: gpu forward + backward: {:.0} ms for {} samples; times {:?}",
        clock.elapsed().as_secs_f64() * 1e3,
        gpu_stats.samples,
        gpu_stats.times
    );
    assert_eq!(gpu_stats.samples, cpu_stats.samples);
    assert_eq!(gpu_stats.rays, cpu_stats.rays);
    println!(
        "loss cpu {} gpu {}; levels cpu {:?} gpu {:?}",
        cpu_stats.loss, gpu_stats.loss, cpu_stats.level_losses, gpu_stats.level_losses
    );
    assert!(
        relative(gpu_stats.loss, cpu_stats.loss) < 1e-4,
        "loss: gpu {} cpu {}",
        gpu_stats.loss,
        cpu_stats.loss
    );
    for level in 0..2 {
        let (g, c) = (gpu_stats.level_losses[level], cpu_stats.level_losses[level]);
        assert!(c > 0.0, "level {level} has no loss: {cpu_stats:?}");
        assert!(relative(g, c) < 1e-4, "level {level} loss: gpu {g} cpu {c}");
    }
    let cpu_gradient = cpu.gradients().to_vec();
    let gpu_gradient = gpu.gradients();
    let ranges = cpu.parameter_ranges().to_vec();
    assert_eq!(ranges, gpu.parameter_ranges());
    for (field, range) in ranges.iter().enumerate() {
        let g = &cpu_gradient[range.clone()];
        assert!(g.iter().any(|&x| x != 0.0), "field {field} has no gradient");
        let error = relative_norm(&gpu_gradient[range.clone()], g);
        println!("gradient of field {field}: relative error {error:.2e}");
        assert!(error < 1e-4, "field {field}: {error:e}");
    }

    // The whole step: Adam's first update moves each parameter by about
    // lr · g / (|g| + ε), so the engines agree to rounding wherever the
    // gradient agrees in sign.
    let cpu_stats = cpu.step(&rays, step);
    let gpu_stats = gpu.step(&rays, step);
    assert!(relative(gpu_stats.loss, cpu_stats.loss) < 1e-4);
    let cpu_after = cpu.params();
    let gpu_after = gpu.params();
    let (mut changed, mut mismatched) = (0usize, 0usize);
    for range in &ranges {
        let largest = range
            .clone()
            .map(|i| cpu_gradient[i].abs())
            .fold(0f32, f32::max);
        for i in range.clone() {
            if cpu_after[i] == before[i] && gpu_after[i] == before[i] {
                continue;
            }
            changed += 1;
            // Compared as the update (after − before): 1e-3 of the
            // learning rate is ~1e-3 of a step, far above the rounding of
            // the update itself. Each engine then rounds p − update to f32,
            // half an ulp of the parameter each, so one ulp (≤ ε·|p|) more
            // may separate them: with NeRF's rate (5e-4) that is ~1e-4 of a
            // step, with Mip-NeRF's first warm-up rate (5e-6, 0.01 of its
            // 5e-4) ~1e-2.
            let (dc, dg) = (cpu_after[i] - before[i], gpu_after[i] - before[i]);
            let ulp = f32::EPSILON
                * before[i]
                    .abs()
                    .max(cpu_after[i].abs())
                    .max(gpu_after[i].abs());
            if (dc - dg).abs() > 1e-3 * dc.abs().max(dg.abs()) + ulp {
                mismatched += 1;
                // Only a gradient at the level of summation noise may
                // differ in sign (see tests/it/ngp_gpu.rs for the bound).
                assert!(
                    cpu_gradient[i].abs() <= 1e-4 * largest,
                    "parameter {i}: update gpu {dg} cpu {dc} (gradient cpu {} gpu {})",
                    cpu_gradient[i],
                    gpu_gradient[i]
                );
            }
        }
    }
    println!("parameters changed: {changed}; updates beyond 1e-3: {mismatched}");
    assert!(changed * 2 > before.len(), "{changed} of {}", before.len());
    // Each mismatch sits at a gradient near zero (asserted above); they
    // are rare: 4 of 3688 on a 260-ray batch, none expected to pass 1%.
    assert!(mismatched * 100 <= changed, "{mismatched} of {changed}");
}

fn render(model: &dyn RadianceModel, scene: &Scene) -> Vec<RenderedPixel> {
    let camera = &scene.val[0].camera;
    let k = camera.intrinsics;
    let (mut origins, mut directions, mut radii) = (Vec::new(), Vec::new(), Vec::new());
    // Every twelfth row: 48 rays, six chunks.
    for y in (0..k.height).step_by(12) {
        for x in 0..k.width {
            let ray = camera.pixel_ray(x, y);
            origins.push(ray.origin);
            directions.push(ray.direction);
            radii.push(ray.radius());
        }
    }
    let mut out = vec![RenderedPixel::default(); origins.len()];
    let rays = zrak::model::RenderRays {
        origins: &origins,
        directions: &directions,
        radii: &radii,
        background: [1.0; 3],
    };
    model.render(rays, &mut out);
    out
}

#[test]
fn a_nerf_gpu_checkpoint_loads_on_the_cpu_engine_and_renders_the_same() {
    let _cores = crate::common::shared();
    a_gpu_checkpoint_loads_on_the_cpu_engine_and_renders_the_same(Model::Nerf);
}

#[test]
fn a_mipnerf_gpu_checkpoint_loads_on_the_cpu_engine_and_renders_the_same() {
    let _cores = crate::common::shared();
    a_gpu_checkpoint_loads_on_the_cpu_engine_and_renders_the_same(Model::MipNerf);
}

/// Two steps on the gpu (Adam's moments and step count past their first
/// values), saved, loaded by the cpu engine: the same parameters and Adam
/// state, and the same rendered pixels (rendering has no jitter, so the
/// only differences are f32 rounding, as above).
fn a_gpu_checkpoint_loads_on_the_cpu_engine_and_renders_the_same(model: Model) {
    let scene = small_scene();
    let (mut cpu, mut gpu) = models(model, &scene);
    for step in 0..2 {
        gpu.step(&batch(&scene, 16, 100 + step as u64), step);
    }
    let checkpoint = gpu.save();
    cpu.load(&checkpoint)
        .expect("a gpu checkpoint loads on the cpu");
    assert!(cpu.params() == gpu.params().as_slice());
    let saved = cpu.save();
    for name in ["params", "adam.m", "adam.v"] {
        assert_eq!(
            checkpoint.tensor(name).unwrap(),
            saved.tensor(name).unwrap(),
            "{name}"
        );
    }
    let (a, b) = (render(&gpu, &scene), render(&cpu, &scene));
    let mut worst = 0f32;
    for (g, c) in a.iter().zip(&b) {
        for k in 0..3 {
            worst = worst.max((g.rgb[k] - c.rgb[k]).abs());
        }
        worst = worst.max((g.opacity - c.opacity).abs());
    }
    println!("{model:?}: worst pixel difference: {worst:e}");
    // Colours and opacities are in [0, 1]: 1e-4 absolute.
    assert!(worst < 1e-4, "{worst}");
}

#[test]
fn nerf_occupancy_step_and_grid_update_match_the_cpu_engine() {
    let _cores = crate::common::shared();
    one_occupancy_step_and_grid_update_match_the_cpu_engine(Model::Nerf);
}

#[test]
fn mipnerf_occupancy_step_and_grid_update_match_the_cpu_engine() {
    let _cores = crate::common::shared();
    one_occupancy_step_and_grid_update_match_the_cpu_engine(Model::MipNerf);
}

/// With the occupancy sampler: both engines march the same grid (a ball
/// of occupied cells, shared through a cpu checkpoint, which also checks
/// that one loads on the gpu); one step's loss and gradient agree; then a
/// step whose occupancy update is due gives the same grid (densities by
/// the gpu field, EMA on the host) and the same loss. For Mip-NeRF each
/// marched sample is the frustum of its step, and the grid's densities
/// are those of cell-sized Gaussians.
///
/// The grid has 32³ cells instead of the recipe's 64³: the same code on a
/// grid an eighth the size, whose update lavapipe evaluates in seconds
/// rather than half a minute.
fn one_occupancy_step_and_grid_update_match_the_cpu_engine(model: Model) {
    let scene = small_scene();
    let settings = ModelSettings {
        batch_samples: Some(1 << 13),
        ..settings(Sampling::Occupancy)
    };
    let (mut cpu, mut gpu) = model.engines(&scene, &settings, |recipe| {
        recipe.occupancy.resolution = 32;
    });
    assert!(gpu.params() == cpu.params(), "initial parameters differ");
    {
        let grid = cpu.occupancy_mut().expect("a grid");
        let geometry = grid.geometry();
        for (i, v) in grid.values_mut().iter_mut().enumerate() {
            let cell = geometry.cell_at(i);
            let centre = geometry.cell_centre(cell);
            *v = if (centre - Vec3::splat(0.5)).length() < 0.2 {
                1.0
            } else {
                0.0
            };
        }
        grid.build_bitfield();
    }
    // A fresh field's raw σ can be negative at every marched sample (ReLU:
    // no gradient at all); the σ head's bias at 10 makes the ball's samples
    // dense enough that rays become opaque inside it, so the march's
    // transmittance cut is exercised too.
    let shape = model.shape();
    let last = shape.trunk_b.layers() - 1;
    let bias = shape.trunk_a.param_count() + shape.trunk_b.bias_offset(last).unwrap();
    cpu.params_mut()[bias] = 10.0;
    gpu.load(&cpu.save())
        .expect("a cpu checkpoint loads on the gpu");
    assert_eq!(
        gpu.occupancy().unwrap().bitfield(),
        cpu.occupancy().unwrap().bitfield()
    );

    let rays = batch(&scene, 48, 19);
    let step = 1; // no update due
    // Each ray's cut is found with a σ pass first when the last step used
    // few of its samples (the forward and backward passes then run on the
    // samples before the cut only), else with the forward pass: both
    // engines take the same order, and each order gives the cpu's loss and
    // gradient.
    for used in [0.0, 1.0] {
        cpu.assume_used_fraction(used);
        gpu.assume_used_fraction(used);
        let cpu_stats = cpu.forward_backward(&rays, step);
        let clock = Instant::now();
        let gpu_stats = gpu.forward_backward(&rays, step);
        println!(
            "{model:?}, last step used {used}: gpu marched forward + backward: {:.0} ms, \
             {} samples ({:?} before the cut), {} rays; loss cpu {} gpu {}",
            clock.elapsed().as_secs_f64() * 1e3,
            gpu_stats.samples,
            gpu_stats.samples_composited,
            gpu_stats.rays,
            cpu_stats.loss,
            gpu_stats.loss
        );
        // The same march: the same samples and rays.
        assert_eq!(gpu_stats.samples, cpu_stats.samples);
        assert_eq!(gpu_stats.rays, cpu_stats.rays);
        assert!(cpu_stats.samples > 500, "{cpu_stats:?}");
        if used == 0.0 {
            // σ first on both: the same samples before the same cuts, and
            // the dense ball cuts rays short (577 of 642 samples kept for
            // NeRF, 596 for Mip-NeRF), so the compaction drops samples.
            assert_eq!(gpu_stats.samples_composited, cpu_stats.samples_composited);
            let kept = gpu_stats.samples_composited.expect("σ first counts them");
            assert!(kept < gpu_stats.samples, "{gpu_stats:?}");
        } else {
            assert_eq!(gpu_stats.samples_composited, None, "forward first");
        }
        assert!(
            relative(gpu_stats.loss, cpu_stats.loss) < 1e-4,
            "loss: gpu {} cpu {}",
            gpu_stats.loss,
            cpu_stats.loss
        );
        let (c, g) = (cpu.gradients().to_vec(), gpu.gradients());
        assert!(c.iter().any(|&x| x != 0.0));
        let error = relative_norm(&g, &c);
        println!("{model:?}: marched gradient: relative error {error:.2e}");
        assert!(error < 1e-4, "{error:e}");
    }

    // Step 272: an update is due (every 16 steps) and the warm-up (256
    // steps, every cell measured) is over, so a quarter of the cells and
    // a quarter's worth of occupied ones are measured: the same code path,
    // half of lavapipe's time.
    let rays = batch(&scene, 48, 23);
    let cpu_stats = cpu.step(&rays, 272);
    let gpu_stats = gpu.step(&rays, 272);
    let (cv, gv) = (
        cpu.occupancy().unwrap().values(),
        gpu.occupancy().unwrap().values(),
    );
    let worst = cv
        .iter()
        .zip(gv)
        .map(|(&c, &g)| (c - g).abs() / c.abs().max(1e-3))
        .fold(0f32, f32::max);
    println!("{model:?}: grid values: worst relative difference {worst:e}");
    // σ · step per cell from the same field, EMA'd: f32 rounding.
    assert!(worst < 1e-4, "{worst}");
    assert_eq!(
        gpu.occupancy().unwrap().bitfield(),
        cpu.occupancy().unwrap().bitfield()
    );
    assert_eq!(gpu_stats.samples, cpu_stats.samples);
    assert!(relative(gpu_stats.loss, cpu_stats.loss) < 1e-4);
}

#[test]
fn nerf_draws_its_view_into_a_texture_as_the_cpu_engine_renders_it() {
    let _cores = crate::common::shared();
    texture_matches_the_cpu_render(Model::Nerf, Sampling::Paper);
}

/// The largest difference between two RGBA8 images' bytes, and how many
/// distinct pixels the expected one holds (one means nothing was drawn).
fn compare_images(drawn: &[u8], expected: &[u8]) -> (u8, usize) {
    assert_eq!(drawn.len(), expected.len());
    let worst = drawn
        .iter()
        .zip(expected)
        .map(|(a, b)| a.abs_diff(*b))
        .max()
        .unwrap_or(0);
    let distinct: std::collections::HashSet<&[u8]> = expected.chunks(4).collect();
    (worst, distinct.len())
}

/// With the occupancy sampler NeRF and Mip-NeRF are drawn on the device
/// (the render walk, its points mapped to the world for NeRF's field, or
/// turned into the frustums of their steps for Mip-NeRF's), not composited
/// on the host: after 24 steps, the texture holds the image of the same
/// model's read-back render, in every mode, within the one level of
/// rounding a half-level difference may take.
#[test]
fn nerf_with_the_occupancy_grid_draws_its_view_on_the_device() {
    let _cores = crate::common::shared();
    draws_its_view_through_the_grid_on_the_device(Model::Nerf);
}

#[test]
fn mipnerf_with_the_occupancy_grid_draws_its_view_on_the_device() {
    let _cores = crate::common::shared();
    draws_its_view_through_the_grid_on_the_device(Model::MipNerf);
}

fn draws_its_view_through_the_grid_on_the_device(model: Model) {
    let scene = small_scene();
    let settings = ModelSettings {
        batch_samples: Some(1 << 11),
        ..settings(Sampling::Occupancy)
    };
    let (_, mut gpu) = model.engines(&scene, &settings, |recipe| {
        recipe.occupancy.resolution = 16;
    });
    for step in 0..24 {
        let rays = batch(&scene, gpu.rays_for_next_batch(), 300 + step as u64);
        gpu.step(&rays, step);
    }
    assert!(gpu.walks_on_device(), "{model:?} is drawn on the host");
    let camera = scene.val[0].downscaled(2).camera;
    let (width, height) = (camera.intrinsics.width, camera.intrinsics.height);
    let pixels = render_pixels(&gpu, &camera, [1.0; 3]);
    let drawer = gpu.texture_render().expect("draws into textures");
    for mode in [RenderMode::Rgb, RenderMode::Depth, RenderMode::Opacity] {
        let texture = render_target(&gpu.context().device, width, height);
        drawer
            .render_to_texture(&camera, mode, [1.0; 3], &texture)
            .expect("draws");
        let drawn = read_texture_rgba8(gpu.context(), &texture);
        let expected = to_image(&pixels, width, height, mode, scene.depth_range());
        let (worst, distinct) = compare_images(&drawn, &expected.data);
        println!(
            "{model:?} (grid) {mode:?}: worst byte difference {worst}, {} distinct pixels",
            distinct
        );
        assert!(worst <= 1, "{mode:?}: {worst}");
        if mode == RenderMode::Opacity {
            assert!(distinct > 1, "nothing drawn");
        }
    }
}

#[test]
fn mipnerf_draws_its_view_into_a_texture_as_the_cpu_engine_renders_it() {
    let _cores = crate::common::shared();
    texture_matches_the_cpu_render(Model::MipNerf, Sampling::Occupancy);
}

/// The viewer's texture path: the texture read back holds the cpu engine's image of the same
/// parameters (`to_image` of its rendered pixels, the scene's depth range)
/// in every mode, without and with a crop box (turned, so the rotation is
/// used). One model per sampler, so both of the gpu driver's render paths
/// (fixed samples, cut to the box, and marching through the grid, σ zeroed
/// outside it) are drawn.
fn texture_matches_the_cpu_render(model: Model, sampling: Sampling) {
    let scene = small_scene();
    // Both engines start from the same parameters (one seed, one layout),
    // so no training is needed for the pixels to mean something.
    let (mut cpu, mut gpu) = model.engines(&scene, &settings(sampling), |_| {});
    assert!(cpu.params() == gpu.params().as_slice());
    // 12 × 12 pixels: the val camera at half size.
    let frame = scene.val[0].downscaled(2);
    let camera = frame.camera;
    let (width, height) = (camera.intrinsics.width, camera.intrinsics.height);
    // Around the demo's green block, turned 0.5 rad about y.
    let crop = CropBox {
        centre: Vec3::new(-0.85, 0.0, 0.2),
        size: Vec3::new(1.0, 1.2, 1.0),
        rotation: Quat::from_rotation_y(0.5),
    };
    let mut uncropped = Vec::new();
    for crop in [None, Some(crop)] {
        cpu.set_crop(crop).unwrap();
        gpu.set_crop(crop).expect("the gpu engine crops");
        let drawer = gpu
            .texture_render()
            .expect("a model on the gpu engine draws into textures");
        let expected_pixels = render_pixels(&cpu, &camera, [1.0; 3]);
        for mode in [RenderMode::Rgb, RenderMode::Depth, RenderMode::Opacity] {
            let texture = render_target(&gpu.context().device, width, height);
            drawer
                .render_to_texture(&camera, mode, [1.0; 3], &texture)
                .expect("draws");
            let drawn = read_texture_rgba8(gpu.context(), &texture);
            let expected = to_image(&expected_pixels, width, height, mode, scene.depth_range());
            assert_eq!(drawn.len(), expected.data.len());
            // The engines' pixels agree to ~1e-5 (the render test above);
            // the conversion to 8 bits may round such a difference either
            // way at a half level, so one level is allowed, no more.
            let (worst, distinct) = compare_images(&drawn, &expected.data);
            println!(
                "{model:?} {mode:?} crop {}: worst byte difference {worst}, {} distinct pixels",
                crop.is_some(),
                distinct
            );
            assert!(worst <= 1, "{model:?} {mode:?}: {worst}");
        }
        // Rays that miss the box show nothing but the background.
        if let Some(crop) = crop {
            let mut missed = 0;
            for (i, pixel) in expected_pixels.iter().enumerate() {
                let ray = camera.pixel_ray(i as u32 % width, i as u32 / width);
                if crop.intersect(ray.origin, ray.direction, 0.0).is_none() {
                    assert_eq!(pixel.opacity, 0.0, "pixel {i}");
                    missed += 1;
                }
            }
            let changed = uncropped
                .iter()
                .zip(&expected_pixels)
                .filter(|(a, b): &(&RenderedPixel, &RenderedPixel)| {
                    (a.opacity - b.opacity).abs() > 1e-3
                })
                .count();
            println!("{missed} rays miss the box; {changed} pixels changed by cropping");
            assert!(missed > 0 && changed > 0, "the box cuts nothing away");
        } else {
            uncropped = expected_pixels;
        }
    }
}

/// A training step through the occupancy grid waits for the device once
/// (for the march's counters, which size the rest of the step); its loss,
/// stage times and grid update come back with the next step's wait. Steps
/// 1 to 17 include step 16's grid update; step 0 has no earlier step and
/// waits for its own loss.
#[test]
fn an_occupancy_step_waits_for_the_device_once() {
    let _cores = crate::common::shared();
    for model in [Model::Nerf, Model::MipNerf] {
        let scene = small_scene();
        let settings = ModelSettings {
            batch_samples: Some(1 << 11),
            ..settings(Sampling::Occupancy)
        };
        let (_, mut gpu) = model.engines(&scene, &settings, |recipe| {
            recipe.occupancy.resolution = 16;
        });
        gpu.set_read_back_late(true);
        let counters = gpu.context().counters.clone();
        let counts: Vec<u64> = (0..18)
            .map(|step| {
                let rays = batch(&scene, gpu.rays_for_next_batch(), 100 + step as u64);
                let before = counters.read();
                gpu.step(&rays, step);
                (counters.read() - before).blocking_readbacks
            })
            .collect();
        println!("{model:?}: blocking read-backs per step {counts:?}");
        assert_eq!(
            counts[0], 2,
            "{model:?}: the first step waits for its loss too"
        );
        assert!(counts[1..].iter().all(|&n| n == 1), "{model:?}: {counts:?}");
    }
}

/// σ and colour at points (what meshes and point clouds are made of) from
/// the last level's field on the gpu engine, against the cpu engine's
/// answer for the same parameters: NeRF's fine field at points, Mip-NeRF's
/// field at a cube of the footprint's side as a Gaussian, and σ zero where
/// the occupancy grid is empty.
#[test]
fn density_and_colour_at_points_match_the_cpu_engine() {
    let _cores = crate::common::shared();
    for (model, sampling) in [
        (Model::Nerf, Sampling::Paper),
        (Model::MipNerf, Sampling::Occupancy),
    ] {
        let scene = small_scene();
        let (mut cpu, mut gpu) = model.engines(&scene, &settings(sampling), |_| {});
        if let Some(grid) = cpu.occupancy_mut() {
            // Half the cells occupied, so the empty ones are seen too.
            let geometry = grid.geometry();
            for (i, v) in grid.values_mut().iter_mut().enumerate() {
                *v = if geometry.cell_centre(geometry.cell_at(i)).x < 0.5 {
                    1.0
                } else {
                    0.0
                };
            }
            grid.build_bitfield();
            gpu.load(&cpu.save()).unwrap();
        }
        let n = 700;
        let label = format!("{model:?}");
        let (largest, empty) =
            crate::common::assert_engines_agree_at_points(&label, &cpu, &gpu, n, 0.05);
        assert!(largest > 0.0, "{model:?}: σ all zero");
        if sampling == Sampling::Occupancy {
            assert!(empty > n / 4 && empty < n, "{model:?}: {empty} of {n} zero");
        }
    }
}
