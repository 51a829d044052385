//! The gate of moving Instant-NGP onto the generic model drivers (issue
//! 28): on the same seed, Instant-NGP through `CpuModel` with its field
//! and recipe matches its own earlier driver, `CpuNgp`, bit for bit: every
//! step's loss, the parameters, Adam's state and the occupancy grid after
//! 20 steps, the rendered pixels and the checkpoint's bytes; and either
//! one's checkpoint loads into the other.

mod common;

use std::sync::Arc;

use zrak::engine::cpu::fields::ngp::NgpShape;
use zrak::engine::cpu::ngp::CpuNgp;
use zrak::field::ngp::LossKind;
use zrak::scene::Scene;
use zrak::train::checkpoint::Checkpoint;
use zrak::train::model::{RadianceModel, RenderedPixel};
use zrak::train::trainer::Trainer;

const SEED: u64 = 7;
/// Steps compared: they include the grid's first (full) update at step 0
/// and its next at step 16.
const STEPS: usize = 20;
/// 2^13 samples a batch: a few hundred rays on the small scene.
const BATCH_SAMPLES: usize = 1 << 13;

fn small_scene() -> Arc<Scene> {
    common::small_scene(32)
}

fn render_view(model: &dyn RadianceModel, scene: &Scene) -> Vec<RenderedPixel> {
    let camera = &scene.val[0].camera;
    let k = camera.intrinsics;
    let (mut origins, mut directions) = (Vec::new(), Vec::new());
    for y in 0..k.height {
        for x in 0..k.width {
            let ray = camera.pixel_ray(x, y);
            origins.push(ray.origin);
            directions.push(ray.direction);
        }
    }
    let mut out = vec![RenderedPixel::default(); origins.len()];
    model.render(
        &origins,
        &directions,
        &vec![0.0; origins.len()],
        [1.0; 3],
        &mut out,
    );
    out
}

/// The bits of every pixel's colour, opacity and depth.
fn pixel_bits(pixels: &[RenderedPixel]) -> Vec<u32> {
    pixels
        .iter()
        .flat_map(|p| [p.rgb[0], p.rgb[1], p.rgb[2], p.opacity, p.depth])
        .map(f32::to_bits)
        .collect()
}

/// A checkpoint's bytes as a file holds them.
fn file_bytes(checkpoint: &Checkpoint) -> Vec<u8> {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("model.zrak");
    checkpoint.save(&path).unwrap();
    std::fs::read(path).unwrap()
}

/// Trains `model` for [`STEPS`] steps on the batches a trainer seeded with
/// [`SEED`] draws; returns each step's loss bits and the trainer.
fn train(model: Box<dyn RadianceModel>, scene: &Arc<Scene>) -> (Vec<u32>, Trainer) {
    let mut trainer = Trainer::new(model, scene.clone(), SEED);
    let losses = (0..STEPS).map(|_| trainer.step().loss.to_bits()).collect();
    (losses, trainer)
}

/// Asserts two checkpoints hold the same bits in every tensor and the same
/// header, naming what differs.
fn assert_same_state(old: &Checkpoint, new: &Checkpoint) {
    assert_eq!(old.header, new.header, "headers differ");
    for (name, values) in &old.tensors {
        let other = new
            .tensor(name)
            .unwrap_or_else(|| panic!("no `{name}` in the new driver's checkpoint"));
        assert_eq!(values.len(), other.len(), "`{name}` length");
        let differing = values
            .iter()
            .zip(other)
            .filter(|(a, b)| a.to_bits() != b.to_bits())
            .count();
        assert_eq!(differing, 0, "`{name}` differs in {differing} values");
    }
    assert_eq!(old.tensors.len(), new.tensors.len(), "tensor count");
}

#[test]
fn cpu_model_trains_instant_ngp_as_its_own_driver_did() {
    let scene = small_scene();
    let old = CpuNgp::with_batch_samples(&scene, SEED, LossKind::Huber, BATCH_SAMPLES);
    let new = zrak::train::cpu_ngp_with_shape(
        &scene,
        NgpShape::for_scene(&scene),
        SEED,
        LossKind::Huber,
        Some(BATCH_SAMPLES),
    );
    assert_eq!(old.describe(), new.describe());
    assert!(
        old.save().tensor("params") == new.save().tensor("params"),
        "initial parameters differ"
    );

    let (old_losses, old) = train(Box::new(old), &scene);
    let (new_losses, new) = train(Box::new(new), &scene);
    assert_eq!(old_losses, new_losses, "losses (bits) per step");

    let (old_state, new_state) = (old.model.save(), new.model.save());
    assert_same_state(&old_state, &new_state);
    assert!(
        file_bytes(&old_state) == file_bytes(&new_state),
        "checkpoint files differ"
    );
    assert_eq!(
        pixel_bits(&render_view(old.model.as_ref(), &scene)),
        pixel_bits(&render_view(new.model.as_ref(), &scene)),
        "rendered pixels (bits)"
    );

    // Checkpoints move both ways: the old driver's into the new one, and
    // back, and the next step agrees.
    let mut from_old = zrak::train::cpu_ngp_with_shape(
        &scene,
        NgpShape::for_scene(&scene),
        0,
        LossKind::L2,
        Some(BATCH_SAMPLES),
    );
    from_old.load(&old_state).unwrap();
    assert_same_state(&old_state, &from_old.save());
    let mut from_new = CpuNgp::with_batch_samples(&scene, 0, LossKind::L2, BATCH_SAMPLES);
    from_new.load(&new_state).unwrap();
    assert_same_state(&new_state, &from_new.save());
    let rays = common::batch(&scene, 256, 3);
    let a = from_new.step(&rays, STEPS as u32);
    let b = from_old.step(&rays, STEPS as u32);
    assert_eq!(a.loss.to_bits(), b.loss.to_bits());
    assert_same_state(&from_new.save(), &from_old.save());
}
