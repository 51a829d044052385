//! The gpu half of issue 28's gate: Instant-NGP through the generic gpu
//! driver (`GpuModel` with `GpuNgpField` and the recipe of `field::ngp`)
//! reproduces what its own driver, `GpuNgp`, produced on a fixed seed:
//! every step's loss over 20 steps (the grid's full update at step 0 and
//! its next at step 16 among them), the CRC-32C of every checkpoint tensor
//! (parameters, Adam's moments, the occupancy grid), of a rendered view's
//! pixels, of the colour image drawn into the viewer's texture and of the
//! checkpoint file's bytes apart from the format version. The record,
//! `tests/fixtures/ngp_gpu_driver.txt`, was written from `GpuNgp` on
//! lavapipe while both drivers existed (`record_the_old_driver` in this
//! file at commit da8e5bd, which also compared the two drivers' runs bit
//! for bit and loaded each one's checkpoint into the other); the same
//! checkpoint bytes mean the old driver's checkpoints load into the new.
//!
//! The hash table has 2^12 entries per level instead of 2^19 (every level
//! hashes, as the paper's finer levels do), to keep the test to a minute on
//! lavapipe. On another device than the record's (another GPU, another
//! LLVM under lavapipe) f32 sums and float atomic adds run in other orders,
//! so there the losses are compared within a tolerance
//! ([`LOSS_TOLERANCE`]). Lavapipe gave the same bits for two runs of the
//! old driver, float atomics of the hash grid's backward pass included.

use crate::common;
use crate::common::gate_record::{Fixture, GateRecord};

use std::sync::Arc;

use zrak::engine::build_gpu;
use zrak::engine::gpu::GpuContext;
use zrak::engine::gpu::render::{read_texture_rgba8, render_target};
use zrak::field::ModelKind;
use zrak::field::common::LossKind;
use zrak::field::encoding::{HashGridConfig, HashGridLayout};
use zrak::field::ngp::NgpShape;
use zrak::model::{RadianceModel, RenderMode};
use zrak::scene::Scene;
use zrak::train::trainer::Trainer;

const SEED: u64 = 7;
/// Steps compared: the grid updates at step 0 (all cells) and 16.
const STEPS: usize = 20;
/// 2^12 samples a batch: a few dozen rays on the small scene.
const BATCH_SAMPLES: usize = 1 << 12;

fn small_scene() -> Arc<Scene> {
    common::small_scene(32)
}

/// The paper's field with a 2^12-entry table per level (as
/// tests/hard_cases.rs and tests/ngp_field_gpu.rs).
fn small_shape(scene: &Scene) -> NgpShape {
    let mut shape = NgpShape::for_scene(scene);
    shape.grid = HashGridLayout::new(&HashGridConfig {
        log2_table_size: 12,
        ..HashGridConfig::paper(scene.unit_cube.aabb_scale)
    });
    shape
}

/// The test's device, shared by both drivers and the textures they draw
/// into (a context per driver, as the viewer's worker makes them).
fn shared(context: &GpuContext) -> GpuContext {
    GpuContext::from_existing(
        &context.adapter,
        context.device.clone(),
        context.queue.clone(),
    )
    .unwrap()
}

fn new_driver(scene: &Scene, context: &GpuContext) -> Box<dyn RadianceModel> {
    Box::new(
        build_gpu(
            shared(context),
            &crate::common::request(ModelKind::Ngp, SEED, LossKind::Huber, Some(BATCH_SAMPLES))
                .with_shape(small_shape(scene)),
            scene,
        )
        .expect("the new driver"),
    )
}

/// The bytes `model` draws into the viewer's texture for the first
/// validation view.
fn texture_of(
    model: &dyn RadianceModel,
    scene: &Scene,
    context: &GpuContext,
    mode: RenderMode,
) -> Vec<u8> {
    let camera = &scene.val[0].camera;
    let (width, height) = (camera.intrinsics.width, camera.intrinsics.height);
    let texture = render_target(&context.device, width, height);
    let render = model
        .texture_render()
        .expect("a gpu model draws into textures");
    render
        .render_to_texture(camera, mode, [1.0; 3], &texture)
        .unwrap();
    let bytes = read_texture_rgba8(context, &texture);
    // Not all one colour: the view shows the trained field (its depth,
    // after 20 steps, is still too faint to show).
    if mode == RenderMode::Rgb {
        assert!(
            bytes.chunks_exact(4).any(|p| p != &bytes[..4]),
            "a flat image"
        );
    }
    bytes
}

/// The new driver's record of the fixed-seed run: its losses, checkpoint,
/// a validation view's pixels and the colour image it draws into the
/// viewer's texture.
fn record_of(
    model: Box<dyn RadianceModel>,
    scene: &Arc<Scene>,
    context: &GpuContext,
) -> GateRecord {
    let mut trainer = Trainer::new(model, scene.clone(), SEED);
    let losses = (0..STEPS).map(|_| trainer.step().loss.to_bits()).collect();
    let model = trainer.model.as_ref();
    let texture = texture_of(model, scene, context, RenderMode::Rgb);
    GateRecord::new(
        device_name(context),
        losses,
        &model.save(),
        &common::render_first_val_view(model, scene),
        Some(&texture),
    )
}

/// The old driver's record: the device it ran on, and the header
/// `record_the_old_driver` wrote.
const FIXTURE: Fixture = Fixture {
    path: concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/tests/fixtures/ngp_gpu_driver.txt"
    ),
    origin_key: "device",
    header: "# Instant-NGP through its own gpu driver (GpuNgp), seed 7, 20 steps of\n\
             # 2^12 samples on the 32-pixel demo scene, hash table 2^12 per level:\n\
             # written by record_the_old_driver in tests/ngp_gpu_driver_gate.rs\n\
             # while both drivers existed; CRCs are CRC-32C.\n",
    steps: STEPS,
};

/// Relative difference allowed between a step's loss here and the
/// record's on another device than the record's (another GPU, or
/// lavapipe of another LLVM): such a device only reorders f32 sums and
/// float atomic adds (≈ 1e-7 relative each), which 20 steps keep orders of
/// magnitude below 1e-3, while a broken stage moves the losses by more (the
/// cpu gate's argument, tests/it/ngp_driver_gate.rs).
const LOSS_TOLERANCE: f64 = 1e-3;

/// The adapter and its driver, as the record names them.
fn device_name(context: &GpuContext) -> String {
    format!("{} / {}", context.info.name, context.info.driver_info)
}

#[test]
fn gpu_model_reproduces_the_old_drivers_record() {
    let _cores = crate::common::shared();
    let scene = small_scene();
    let context = common::gpu_context();
    let expected = GateRecord::read(&FIXTURE);
    let record = record_of(new_driver(&scene, &context), &scene, &context);
    // The fixture's format reads back what it writes.
    assert_eq!(
        GateRecord::parse(&record.to_text(&FIXTURE), &FIXTURE).as_ref(),
        Ok(&record)
    );
    record.assert_reproduces(&expected, &FIXTURE, LOSS_TOLERANCE);
}
