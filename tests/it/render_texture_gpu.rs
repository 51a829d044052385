//! The viewer's render path on the gpu engine (lavapipe): `render_to_texture`
//! writes the same pixels as the read-back render (`render_pixels` then
//! `to_image`), in every mode, on a model with structure (a few hundred cpu
//! steps on the demo scene, moved to the gpu through a checkpoint).

use std::sync::{Arc, Mutex};

use glam::{Quat, Vec3};

use zrak::engine::build_gpu;
use zrak::engine::cpu::model::CpuModel;
use zrak::engine::gpu::GpuContext;
use zrak::engine::gpu::model::GpuModel;
use zrak::engine::gpu::render::{read_texture_rgba8, render_target};
use zrak::field::ModelKind;
use zrak::field::common::LossKind;
use zrak::model::batch::{RayBatch, TrainingBackground, sample_rays};
use zrak::model::checkpoint::Checkpoint;
use zrak::model::pixels::{render_pixels, to_image};
use zrak::model::{RadianceModel, RenderMode, RenderedPixel, TextureRender};
use zrak::rng::Pcg32;
use zrak::scene::crop::CropBox;
use zrak::scene::demo::{
    DemoConfig, {self},
};
use zrak::scene::{Camera, Scene};

const SEED: u64 = 3;

const SMALL_TRAIN_VIEWS: usize = 16;

fn scene() -> Arc<Scene> {
    Arc::new(demo::build(&DemoConfig {
        size: 24,
        train_views: SMALL_TRAIN_VIEWS,
        val_views: 2,
        test_views: 1,
    }))
}

/// A gpu model holding what a cpu model learned in 60 steps (the cpu
/// engine is the fast one here). Its batches of 1024 samples make a render
/// of 24 × 24 rays take several rounds, the first of three groups of rays.
fn trained_gpu_model(scene: &Scene, batch_samples: usize) -> GpuModel {
    trained_models(scene, batch_samples).1
}

/// The cpu model of [`trained_gpu_model`] and the gpu model loaded from it.
/// The small scene's training ([`scene`]) is done once and shared by the
/// tests that render it (each gets its own models from its checkpoint).
fn trained_models(scene: &Scene, batch_samples: usize) -> (impl RadianceModel, GpuModel) {
    static SMALL_SCENE_TRAINED: Mutex<Option<Checkpoint>> = Mutex::new(None);
    let small = scene.train.len() == SMALL_TRAIN_VIEWS && scene.unit_cube.aabb_scale == 1.0;
    let mut cpu = untrained_cpu_model(scene);
    if small {
        // Held while the first test trains, so the others wait for its
        // checkpoint instead of training too.
        let mut shared = SMALL_SCENE_TRAINED
            .lock()
            .unwrap_or_else(|e| e.into_inner());
        match &*shared {
            Some(checkpoint) => cpu.load(checkpoint).expect("the shared checkpoint loads"),
            None => {
                train(&mut cpu, scene);
                *shared = Some(cpu.save());
            }
        }
    } else {
        train(&mut cpu, scene);
    }
    let context = GpuContext::new().expect("lavapipe or a GPU");
    let mut gpu = build_gpu(
        context,
        &crate::common::request(ModelKind::Ngp, SEED, LossKind::Huber, Some(batch_samples)),
        scene,
    )
    .expect("gpu model");
    gpu.load(&cpu.save()).expect("the cpu checkpoint loads");
    (cpu, gpu)
}

fn untrained_cpu_model(scene: &Scene) -> CpuModel {
    CpuModel::build(
        &crate::common::request(ModelKind::Ngp, SEED, LossKind::Huber, Some(1 << 12))
            .with_shape(zrak::field::ngp::NgpShape::for_scene(scene)),
        scene,
    )
}

/// 60 steps of the cpu engine on `scene`'s training views.
fn train(cpu: &mut CpuModel, scene: &Scene) {
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
}

/// Renders `camera` into a texture in `mode` and checks it against the
/// read-back render's `pixels` (made with the same background).
fn compare(
    gpu: &GpuModel,
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
    let _cores = crate::common::shared();
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

/// With a crop box (turned, so its rotation is used) the texture holds the
/// read-back render's pixels, and both hold the cpu engine's: samples
/// outside the box have no density on either engine, so the background
/// shows where the box cuts the objects away.
#[test]
fn a_crop_box_renders_the_same_into_the_texture_and_on_both_engines() {
    let _cores = crate::common::shared();
    let scene = scene();
    let (mut cpu, mut gpu) = trained_models(&scene, 1 << 10);
    let camera = scene.val[0].camera;
    let background = [1.0; 3];
    let whole = render_pixels(&gpu, &camera, background);
    let crop = CropBox {
        centre: Vec3::new(-0.85, 0.0, 0.2),
        size: Vec3::new(1.0, 1.2, 1.0),
        rotation: Quat::from_rotation_y(0.5),
    };
    cpu.set_crop(Some(crop)).unwrap();
    gpu.set_crop(Some(crop)).expect("the gpu engine crops");
    let cropped = render_pixels(&gpu, &camera, background);
    let on_cpu = render_pixels(&cpu, &camera, background);
    let worst = cropped
        .iter()
        .zip(&on_cpu)
        .flat_map(|(g, c)| (0..3).map(move |k| (g.rgb[k] - c.rgb[k]).abs()))
        .fold(0f32, f32::max);
    println!("cropped: worst colour difference between engines {worst:e}");
    // The same samples and σ on both engines up to f32 rounding of the
    // networks (the uncropped parity tests allow the same).
    assert!(worst < 1e-3, "{worst}");
    compare(&gpu, &camera, RenderMode::Rgb, background, &cropped);
    compare(&gpu, &camera, RenderMode::Opacity, background, &cropped);
    let width = camera.intrinsics.width;
    let (mut missed, mut cut) = (0, 0);
    for (i, (a, b)) in whole.iter().zip(&cropped).enumerate() {
        let ray = camera.pixel_ray(i as u32 % width, i as u32 / width);
        if crop.intersect(ray.origin, ray.direction, 0.0).is_none() {
            assert_eq!((b.opacity, b.rgb), (0.0, background), "pixel {i}");
            missed += 1;
            cut += usize::from(a.opacity > 0.5);
        }
    }
    println!("{missed} rays miss the box, {cut} of them on an object uncropped");
    assert!(cut > 10, "the box must cut something away: {cut}");
}

/// Meshes ask a model for σ and colour at points: the gpu engine answers
/// as the cpu engine does for the same parameters (σ zero in empty cells on
/// both), so `zrak export mesh` and the viewer's export work on either.
#[test]
fn density_and_colour_at_points_match_the_cpu_engine() {
    let _cores = crate::common::shared();
    let scene = scene();
    let (cpu, gpu) = trained_models(&scene, 1 << 10);
    let n = 2000;
    let (largest, empty) =
        crate::common::assert_engines_agree_at_points("Instant-NGP", &cpu, &gpu, n, 0.01);
    assert!(largest > 0.5, "a model with structure: σ up to {largest}");
    assert!(empty > 0 && empty < n, "{empty} of {n} in empty cells");
}

/// On a large scene (aabb_scale 8) the march steps by cone angle: the
/// texture render's steps must grow along each ray as the read-back
/// render's (the cpu marcher's) do, or the colours move apart.
#[test]
fn render_to_texture_matches_the_read_back_render_with_cone_steps() {
    let _cores = crate::common::shared();
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
    let _cores = crate::common::shared();
    let scene = scene();
    let context = GpuContext::new().expect("lavapipe or a GPU");
    let gpu = build_gpu(
        context,
        &crate::common::request(ModelKind::Ngp, SEED, LossKind::Huber, Some(1 << 10)),
        &scene,
    )
    .unwrap();
    let camera = scene.val[0].camera;
    let small = render_target(&gpu.context().device, 8, 8);
    let message = gpu
        .render_to_texture(&camera, RenderMode::Rgb, [1.0; 3], &small)
        .unwrap_err()
        .to_string();
    assert!(message.contains("8×8"), "{message}");
    let cpu: &dyn RadianceModel = &CpuModel::build(
        &crate::common::request(ModelKind::Ngp, 1, LossKind::Huber, Some(1024))
            .with_shape(zrak::field::ngp::NgpShape::for_scene(&scene)),
        &scene,
    );
    assert!(cpu.texture_render().is_none());
}
