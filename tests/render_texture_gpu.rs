//! The viewer's render path on the gpu engine (lavapipe): `render_to_texture`
//! writes the same pixels as the read-back render (`render_pixels` then
//! `to_image`), in every mode, on a model with structure (a few hundred cpu
//! steps on the demo scene, moved to the gpu through a checkpoint).

use std::sync::Arc;

use zrak::engine::gpu::GpuContext;
use zrak::engine::gpu::ngp::GpuNgp;
use zrak::engine::gpu::render::{read_texture_rgba8, render_target};
use zrak::field::ngp::LossKind;
use zrak::render::{RenderMode, render_pixels, to_image};
use zrak::rng::Pcg32;
use zrak::scene::demo::{self, DemoConfig};
use zrak::scene::{Camera, Scene};
use zrak::train::batch::{RayBatch, TrainingBackground, sample_rays};
use zrak::train::model::{RadianceModel, RenderedPixel};

const SEED: u64 = 3;

fn scene() -> Arc<Scene> {
    Arc::new(demo::build(&DemoConfig {
        size: 24,
        train_views: 16,
        val_views: 2,
        test_views: 1,
    }))
}

/// A gpu model holding what a cpu model learned in 60 steps (the cpu
/// engine is the fast one here). Its batches of 1024 samples make a render
/// of 24 × 24 rays take several rounds, the first of three groups of rays.
fn trained_gpu_model(scene: &Scene, batch_samples: usize) -> GpuNgp {
    let mut cpu = zrak::train::cpu_ngp_with_shape(
        scene,
        zrak::engine::cpu::fields::ngp::NgpShape::for_scene(scene),
        SEED,
        LossKind::Huber,
        Some(1 << 12),
    );
    let mut rng = Pcg32::new(SEED, 1);
    let mut batch = RayBatch::default();
    for step in 0..60 {
        sample_rays(
            &scene.train,
            cpu.rays_for_next_batch(),
            TrainingBackground::Random,
            &mut rng,
            &mut batch,
        );
        cpu.step(&batch, step);
    }
    let context = GpuContext::new().expect("lavapipe or a GPU");
    let mut gpu = GpuNgp::with_batch_samples(context, scene, SEED, LossKind::Huber, batch_samples)
        .expect("gpu model");
    gpu.load(&cpu.save()).expect("the cpu checkpoint loads");
    gpu
}

/// Renders `camera` into a texture in `mode` and checks it against the
/// read-back render's `pixels` (made with the same background).
fn compare(
    gpu: &GpuNgp,
    camera: &Camera,
    mode: RenderMode,
    background: [f32; 3],
    pixels: &[RenderedPixel],
) {
    let (width, height) = (camera.intrinsics.width, camera.intrinsics.height);
    let texture = render_target(&gpu.context().device, width, height);
    let clock = std::time::Instant::now();
    gpu.render_to_texture(camera, mode, background, &texture)
        .expect("renders");
    let on_gpu = read_texture_rgba8(gpu.context(), &texture);
    println!(
        "{mode:?}: render_to_texture {:.2} s",
        clock.elapsed().as_secs_f64()
    );
    let expected = to_image(pixels, width, height, mode, gpu.depth_range());
    assert_eq!(on_gpu.len(), expected.data.len());
    // Both march the same samples and composite them in the same order;
    // they differ by f32 rounding (exp, the 1 − e^{−τ} series) and the
    // conversion to 8 bits, which may round either way at a half level.
    let mut worst = 0;
    for (i, (a, b)) in on_gpu.iter().zip(&expected.data).enumerate() {
        let difference = a.abs_diff(*b);
        worst = worst.max(difference);
        assert!(
            difference <= 1,
            "{mode:?}: pixel {} channel {}: texture {a}, read-back {b}",
            i / 4,
            i % 4
        );
    }
    // The image must show something, or the comparison proves little.
    let distinct: std::collections::BTreeSet<&[u8]> = expected.data.chunks(4).collect();
    println!(
        "{mode:?}: {} distinct colours, largest difference {worst} level(s)",
        distinct.len()
    );
    assert!(distinct.len() > 20, "{mode:?}: a flat image");
}

#[test]
fn render_to_texture_matches_the_read_back_render() {
    let scene = scene();
    let gpu = trained_gpu_model(&scene, 1 << 10);
    let model: &dyn RadianceModel = &gpu;
    assert!(model.texture_render().is_some(), "a gpu model says so");
    let camera = scene.val[0].camera;
    for background in [[1.0; 3], [0.1, 0.5, 0.9]] {
        let clock = std::time::Instant::now();
        let pixels = render_pixels(&gpu, &camera, background);
        println!("read-back render {:.2} s", clock.elapsed().as_secs_f64());
        compare(&gpu, &camera, RenderMode::Rgb, background, &pixels);
        if background == [1.0; 3] {
            compare(&gpu, &camera, RenderMode::Depth, background, &pixels);
            compare(&gpu, &camera, RenderMode::Opacity, background, &pixels);
        }
    }
}

/// On a large scene (aabb_scale 8) the march steps by cone angle: the
/// texture render's steps must grow along each ray as the read-back
/// render's (the cpu marcher's) do, or the colours move apart.
#[test]
fn render_to_texture_matches_the_read_back_render_with_cone_steps() {
    let scene = Arc::new(demo::build_large(&DemoConfig {
        size: 24,
        train_views: 16,
        val_views: 2,
        test_views: 1,
    }));
    assert!(
        scene.unit_cube.aabb_scale > 1.0,
        "a large scene marches cones"
    );
    // Rays cross the backdrop's whole box: rounds of up to 64 samples a
    // ray (2^14 samples for the rays rendered) keep the rounds few.
    let gpu = trained_gpu_model(&scene, 1 << 14);
    // The middle 8 × 8 pixels of a held-out view (the objects, in front of
    // the backdrop; 38 distinct colours on lavapipe): a ninth of the rays
    // keeps lavapipe's time down (the middle 12 × 12 took twice as long).
    let view = scene.val[0].camera;
    let camera = Camera::new(view.intrinsics.cropped(8, 8, 8, 8), view.camera_to_world);
    let background = [1.0; 3];
    let pixels = render_pixels(&gpu, &camera, background);
    // Colour only: the backdrop's depth range leaves a handful of 8-bit
    // depth levels, too few to show anything, while every colour depends
    // on each sample's step through 1 − e^{−σ·dt}.
    compare(&gpu, &camera, RenderMode::Rgb, background, &pixels);
}

#[test]
fn a_wrong_target_is_refused_with_what_is_wrong() {
    let scene = scene();
    let context = GpuContext::new().expect("lavapipe or a GPU");
    let gpu = GpuNgp::with_batch_samples(context, &scene, SEED, LossKind::Huber, 1 << 10).unwrap();
    let camera = scene.val[0].camera;
    let small = render_target(&gpu.context().device, 8, 8);
    let message = gpu
        .render_to_texture(&camera, RenderMode::Rgb, [1.0; 3], &small)
        .unwrap_err()
        .to_string();
    assert!(message.contains("8×8"), "{message}");
    let cpu: &dyn RadianceModel = &zrak::train::cpu_ngp_with_shape(
        &scene,
        zrak::engine::cpu::fields::ngp::NgpShape::for_scene(&scene),
        1,
        LossKind::Huber,
        Some(1024),
    );
    assert!(cpu.texture_render().is_none());
}
