//! The viewer's training thread on the gpu engine (lavapipe here), on a
//! device it shares with the window, as `zrak view --engine gpu` runs it:
//! the view is drawn into textures on that device (`Event::GpuFrame`) and
//! shows the same pixels as the read-back render of the same camera; a
//! request that needs the pixels (comparing with a photograph) gets them.
//!
//! lavapipe runs the engine's WGSL slowly (seconds for a few hundred rays),
//! so the scene and the view are tiny: a 12 × 12 view, drawn at 1/8, 1/4,
//! 1/2 and full size.

use std::path::Path;
use std::sync::Arc;
use std::time::Instant;

use crate::common::worker::wait_for;
use zrak::engine::gpu::GpuContext;
use zrak::engine::gpu::render::read_texture_rgba8;
use zrak::engine::request::{ModelRequest, ModelSettings};
use zrak::engine::{EngineChoice, EngineKind, build, build_gpu};
use zrak::field::ModelKind;
use zrak::field::common::LossKind;
use zrak::metrics::WHITE;
use zrak::model::checkpoint::Checkpoint;
use zrak::model::pixels::{render_pixels, to_image};
use zrak::model::{RenderMode, RenderedPixel};
use zrak::scene::demo::{
    DemoConfig, {self},
};
use zrak::scene::{Camera, Scene};
use zrak::session::protocol::{
    Command, Event, GpuFrame, RenderRequest, RenderedFrame, SceneSource,
};
use zrak::session::worker::{TrainingWorker, WorkerOptions};
use zrak::train::trainer::Trainer;

const SEED: u64 = 5;

/// Samples per batch, for training and for the renders' rounds alike.
const BATCH_SAMPLES: usize = 1 << 12;

/// Cpu steps before the checkpoint: enough for the field to show the demo
/// scene's shapes (an untrained field renders a nearly flat grey).
const PRETRAIN_STEPS: usize = 60;

fn demo_config() -> DemoConfig {
    DemoConfig {
        size: 12,
        train_views: 12,
        val_views: 1,
        test_views: 1,
    }
}

fn settings() -> ModelSettings {
    ModelSettings {
        seed: SEED,
        loss: LossKind::Huber,
        batch_samples: Some(BATCH_SAMPLES),
        sampling: zrak::field::common::Sampling::Occupancy,
        precision: zrak::field::mlp::Precision::F32,
        refine_cameras: false,
        appearance: false,
    }
}

/// Another context on the same device.
fn share(context: &GpuContext) -> GpuContext {
    GpuContext::from_existing(
        &context.adapter,
        context.device.clone(),
        context.queue.clone(),
    )
    .expect("the same device again")
}

/// Trains on the cpu engine (the fast one here) and saves a checkpoint
/// the viewer can load.
fn pretrained_checkpoint(scene: &Arc<Scene>, path: &Path) {
    let cpu = EngineChoice {
        kind: EngineKind::Cpu,
        gpu: None,
        reason: String::new(),
    };
    let model =
        build(&ModelRequest::new(ModelKind::Ngp, settings()), cpu, scene).expect("cpu model");
    let mut trainer = Trainer::new(model, scene.clone(), SEED);
    for _ in 0..PRETRAIN_STEPS {
        trainer.step();
    }
    trainer
        .checkpoint(serde_json::json!({ "saved_by": "viewer_gpu test" }))
        .save(path)
        .expect("the checkpoint is written");
}

/// The read-back render of `camera` by a gpu model holding `checkpoint`
/// (`render_pixels`, which `to_image` turns into images as `zrak render`
/// does).
fn read_back_render(
    context: GpuContext,
    scene: &Arc<Scene>,
    checkpoint: &Path,
    camera: &Camera,
) -> Vec<RenderedPixel> {
    let gpu = EngineChoice {
        kind: EngineKind::Gpu,
        gpu: Some(context),
        reason: String::new(),
    };
    let model =
        build(&ModelRequest::new(ModelKind::Ngp, settings()), gpu, scene).expect("gpu model");
    let mut trainer = Trainer::new(model, scene.clone(), SEED);
    trainer
        .restore(&Checkpoint::load(checkpoint).expect("reads"))
        .expect("restores");
    render_pixels(trainer.model.as_ref(), camera, WHITE)
}

fn request(
    worker: &TrainingWorker,
    generation: u64,
    camera: Camera,
    mode: RenderMode,
    needs_pixels: bool,
) {
    worker.send(Command::Render(RenderRequest {
        generation,
        camera,
        mode,
        moving: false,
        needs_pixels,
    }));
}

/// The texture frames answering `generation`, up to the full-size one.
fn texture_frames(worker: &TrainingWorker, generation: u64) -> Vec<GpuFrame> {
    let mut frames: Vec<GpuFrame> = Vec::new();
    wait_for(worker, |event| match event {
        Event::GpuFrame(frame) if frame.generation == generation => {
            frames.push(frame.clone());
            (frame.downscale == 1).then_some(())
        }
        Event::Frame(_) => panic!("the view came as pixels, not as a texture"),
        Event::Error(error) => panic!("{error}"),
        _ => None,
    });
    frames
}

/// Per channel, the largest difference between two RGBA8 images.
fn largest_difference(a: &[u8], b: &[u8]) -> u8 {
    assert_eq!(a.len(), b.len(), "images of different sizes");
    a.iter()
        .zip(b)
        .map(|(x, y)| x.abs_diff(*y))
        .max()
        .unwrap_or(0)
}

#[test]
fn the_gpu_engine_draws_the_view_into_a_texture_on_the_shared_device() {
    let _cores = crate::common::shared();
    let clock = Instant::now();
    let config = demo_config();
    let scene = Arc::new(demo::build(&config));
    let folder = std::env::temp_dir().join(format!("zrak-viewer-gpu-{}", std::process::id()));
    std::fs::create_dir_all(&folder).expect("temp folder");
    let checkpoint = folder.join("pretrained.zrak");
    pretrained_checkpoint(&scene, &checkpoint);
    println!("cpu pretraining: {:.1} s", clock.elapsed().as_secs_f64());

    let context = GpuContext::new().expect("lavapipe or a GPU");
    let worker = TrainingWorker::spawn_with(
        SceneSource::Demo,
        Some(EngineKind::Gpu),
        ModelKind::Ngp,
        WorkerOptions {
            seed: SEED,
            demo: config,
            batch_samples: Some(BATCH_SAMPLES),
            gpu_device: Some(share(&context)),
            ..WorkerOptions::default()
        },
    );
    let engine = wait_for(&worker, |event| match event {
        Event::Engine { kind, .. } => Some(*kind),
        _ => None,
    });
    assert_eq!(engine, EngineKind::Gpu);
    worker.send(Command::LoadCheckpoint(checkpoint.clone()));
    let step = wait_for(&worker, |event| match event {
        Event::CheckpointLoaded { step, .. } => Some(*step),
        Event::Error(error) => panic!("{error}"),
        _ => None,
    });
    assert_eq!(step as usize, PRETRAIN_STEPS);

    // A held-out camera of the scene, 12 × 12.
    let camera = scene.val[0].camera;
    let drawn = Instant::now();
    request(&worker, 1, camera, RenderMode::Rgb, false);
    let frames = texture_frames(&worker, 1);
    println!(
        "texture levels {:?} in {:.1} s",
        frames
            .iter()
            .map(|f| (f.downscale, f.width, f.height))
            .collect::<Vec<_>>(),
        drawn.elapsed().as_secs_f64()
    );
    let downscales: Vec<u32> = frames.iter().map(|f| f.downscale).collect();
    assert_eq!(downscales, [8, 4, 2, 1], "coarse to fine");
    let full = frames.last().expect("the full level");
    assert_eq!((full.width, full.height), (12, 12));
    assert_eq!(full.step as usize, PRETRAIN_STEPS);
    assert_eq!(
        full.texture.format(),
        wgpu::TextureFormat::Rgba8Unorm,
        "egui-wgpu samples Rgba8Unorm as the colours to show"
    );
    let on_gpu = read_texture_rgba8(&context, &full.texture);

    let clock = Instant::now();
    let reference = read_back_render(share(&context), &scene, &checkpoint, &camera);
    let image = |mode| to_image(&reference, 12, 12, mode, scene.depth_range()).data;
    let expected = image(RenderMode::Rgb);
    println!("read-back render: {:.1} s", clock.elapsed().as_secs_f64());
    // Both march the same samples and composite them in the same order;
    // they differ by f32 rounding and the conversion to 8 bits, which may
    // round either way at a half level.
    let worst = largest_difference(&on_gpu, &expected);
    let distinct: std::collections::BTreeSet<&[u8]> = expected.chunks(4).collect();
    println!(
        "texture vs read-back render: largest difference {worst} level(s); {} distinct colours",
        distinct.len()
    );
    assert!(worst <= 1, "the texture differs by {worst} levels");
    assert!(distinct.len() > 10, "a flat image proves little");

    // Another mode is drawn again (a texture holds one mode's colours).
    request(&worker, 2, camera, RenderMode::Opacity, false);
    let opacity = texture_frames(&worker, 2);
    let full = opacity.last().expect("the full level");
    assert_eq!(full.mode, RenderMode::Opacity);
    let worst = largest_difference(
        &read_texture_rgba8(&context, &full.texture),
        &image(RenderMode::Opacity),
    );
    println!("opacity texture vs read-back render: largest difference {worst} level(s)");
    assert!(worst <= 1, "the opacity texture differs by {worst} levels");

    // Comparing with a photograph needs pixels: the same camera, asked
    // with `needs_pixels`, comes back as a frame of pixels.
    request(&worker, 3, camera, RenderMode::Rgb, true);
    let pixels: RenderedFrame = wait_for(&worker, |event| match event {
        Event::Frame(frame) if frame.generation == 3 && frame.downscale == 1 => Some(frame.clone()),
        Event::GpuFrame(frame) if frame.generation == 3 => {
            panic!("a request that needs pixels got a texture")
        }
        Event::Error(error) => panic!("{error}"),
        _ => None,
    });
    let as_image = to_image(&pixels.pixels, 12, 12, RenderMode::Rgb, (0.0, 1.0)).data;
    assert_eq!(pixels.mode, RenderMode::Rgb);
    let pixel_worst = largest_difference(&as_image, &expected);
    println!("pixels frame vs read-back render: largest difference {pixel_worst} level(s)");
    assert!(pixel_worst <= 1);

    worker.shutdown();
    let _ = std::fs::remove_dir_all(&folder);
}

/// A level drawn band by band (as the viewer draws a level slower than a
/// unit of its work) is the level drawn whole: for Instant-NGP, whose
/// texture render runs on the device, and for NeRF (a small one), whose
/// pixels are composited on the host and uploaded.
#[test]
fn a_level_drawn_in_bands_is_the_level_drawn_whole() {
    let _cores = crate::common::shared();
    use zrak::engine::gpu::render::render_target;
    use zrak::session::progressive::{Band, draw_band_to_texture};
    let config = demo_config();
    let scene = Arc::new(demo::build(&config));
    let folder = std::env::temp_dir().join(format!("zrak-viewer-bands-{}", std::process::id()));
    std::fs::create_dir_all(&folder).expect("temp folder");
    let checkpoint = folder.join("pretrained.zrak");
    pretrained_checkpoint(&scene, &checkpoint);
    let context = GpuContext::new().expect("lavapipe or a GPU");
    let gpu = |context: GpuContext| EngineChoice {
        kind: EngineKind::Gpu,
        gpu: Some(context),
        reason: String::new(),
    };
    let ngp = {
        let model = build(
            &ModelRequest::new(ModelKind::Ngp, settings()),
            gpu(share(&context)),
            &scene,
        )
        .expect("gpu model");
        let mut trainer = Trainer::new(model, scene.clone(), SEED);
        trainer
            .restore(&Checkpoint::load(&checkpoint).expect("reads"))
            .expect("restores");
        trainer.model
    };
    // NeRF in miniature, a few steps in so that its picture is not flat.
    let nerf = {
        let shape = zrak::field::nerf::NerfShape::new(
            zrak::field::encoding::FrequencyEncoding {
                frequencies: 3,
                include_input: true,
            },
            zrak::field::encoding::FrequencyEncoding {
                frequencies: 2,
                include_input: true,
            },
            16,
            4,
            2,
            8,
            zrak::field::nerf::DensityActivation::Relu,
        );
        let model = build_gpu(
            share(&context),
            &ModelRequest::new(ModelKind::Nerf, settings()).with_shape(shape),
            &scene,
        )
        .expect("gpu nerf");
        let mut trainer = Trainer::new(Box::new(model), scene.clone(), SEED);
        for _ in 0..3 {
            trainer.step();
        }
        trainer.model
    };
    let camera = scene.val[0].camera;
    let (width, height) = (camera.intrinsics.width, camera.intrinsics.height);
    for (name, model) in [("Instant-NGP", &ngp), ("NeRF", &nerf)] {
        let gpu = model.texture_render().expect("draws into textures");
        for mode in [RenderMode::Rgb, RenderMode::Depth] {
            let whole = render_target(&context.device, width, height);
            gpu.render_to_texture(&camera, mode, WHITE, &whole)
                .expect("drawn whole");
            // Bands of 5, 5 and 2 rows.
            let banded = render_target(&context.device, width, height);
            let mut first = 0;
            while first < height {
                let rows = 5.min(height - first);
                let band = render_target(&context.device, width, rows);
                let rows_drawn = Band {
                    camera: &camera,
                    first,
                    mode,
                    background: WHITE,
                };
                draw_band_to_texture(gpu, &context, rows_drawn, &band, &banded)
                    .expect("a band fits");
                first += rows;
            }
            let (a, b) = (
                read_texture_rgba8(&context, &whole),
                read_texture_rgba8(&context, &banded),
            );
            let worst = largest_difference(&a, &b);
            let distinct: std::collections::BTreeSet<&[u8]> = a.chunks(4).collect();
            println!(
                "{name} {mode:?}: banded vs whole, largest difference {worst} level(s); {} colours",
                distinct.len()
            );
            // The band's camera moves the principal point by whole rows:
            // the same rays up to f32 rounding of cy − first.
            assert!(
                worst <= 1,
                "{name} {mode:?}: bands differ by {worst} levels"
            );
            assert!(
                distinct.len() > 4,
                "{name} {mode:?}: a flat image proves little"
            );
        }
        // A band that does not fit the view is refused, not drawn.
        let band = render_target(&context.device, width, 5);
        let past_the_bottom = Band {
            camera: &camera,
            first: height - 2,
            mode: RenderMode::Rgb,
            background: WHITE,
        };
        let error = draw_band_to_texture(
            gpu,
            &context,
            past_the_bottom,
            &band,
            &render_target(&context.device, width, height),
        )
        .expect_err("rows past the bottom");
        assert!(error.contains("does not fit"), "{error}");
    }
    let _ = std::fs::remove_dir_all(&folder);
}
