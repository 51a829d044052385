//! End to end: NeRF and Mip-NeRF (the papers' fields, with the occupancy
//! sampler) on the cpu engine learn the built-in demo scene, measured on
//! held-out views against the simplest possible predictor, and Mip-NeRF's
//! cones serve three sizes of it better than NeRF's rays.

use std::sync::Arc;
use std::time::Instant;

use zrak::engine::cpu::model::CpuModel;
use zrak::engine::request::{ModelRequest, ModelSettings};
use zrak::field::ModelKind;
use zrak::field::common::{LossKind, Sampling};
use zrak::field::mlp::Precision;
use zrak::scene::Scene;
use zrak::scene::demo::{
    DemoConfig, {self},
};
use zrak::train::eval::{mean_colour_psnr, mean_psnr};
use zrak::train::trainer::Trainer;

fn env_or<T: std::str::FromStr>(name: &str, default: T) -> T {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum Kind {
    Nerf,
    MipNerf,
}

/// A trainer of `kind` on the demo at `size` pixels (60 training views, 4
/// held out; each training view also at ½, ¼, … size for `scales` > 1) with
/// batches of `batch` samples and a 32³ occupancy grid.
fn demo_trainer(
    kind: Kind,
    size: u32,
    scales: u32,
    batch: usize,
    precision: Precision,
) -> (Arc<Scene>, Trainer) {
    let scene = Arc::new(
        demo::build(&DemoConfig {
            size,
            train_views: 60,
            val_views: 4,
            test_views: 1,
        })
        .with_training_scales(scales),
    );
    let settings = ModelSettings {
        seed: 0,
        loss: LossKind::L2,
        batch_samples: Some(batch),
        sampling: Sampling::Occupancy,
        precision,
        refine_cameras: false,
        appearance: false,
    };
    let model_kind = match kind {
        Kind::Nerf => ModelKind::Nerf,
        Kind::MipNerf => ModelKind::MipNerf,
    };
    let mut recipe = (model_kind.spec().recipe)(&scene, settings.sampling);
    // The batch is 1/4 of the shipped 2^14 samples and the occupancy grid
    // gets 1/8 of its cells (32³ instead of 64³): an update then costs no
    // more of a step than it does in a real run. With 64³ cells the
    // grid's density queries took more than half of this test's time.
    recipe.occupancy.resolution = env_or("ZRAK_NERF_E2E_GRID", 32u32);
    let model = CpuModel::build(
        &ModelRequest::new(model_kind, settings).with_recipe(recipe),
        &scene,
    );
    let trainer = Trainer::new(Box::new(model), scene.clone(), 0);
    (scene, trainer)
}

/// Mean held-out PSNR of `trainer`'s model on `scene`'s validation views
/// shrunk by `factor` (area-averaged photographs, cameras with pixels
/// `factor` times wider: Mip-NeRF's cones widen with them).
fn held_out_psnr_at(trainer: &Trainer, scene: &Scene, factor: u32) -> f64 {
    let views: Vec<_> = scene.val.iter().map(|f| f.downscaled(factor)).collect();
    mean_psnr(trainer.model.as_ref(), &views.iter().collect::<Vec<_>>())
}

/// Mean PSNR of the model's renders of `scene`'s validation views drawn at
/// full size and area-averaged by `factor`: what a perfectly anti-aliased
/// render at that size would score, for comparison (ZRAK_AA_SUPERSAMPLED=1).
fn area_averaged_render_psnr(trainer: &Trainer, scene: &Scene, factor: usize) -> f64 {
    use zrak::metrics::{RgbImage, WHITE, psnr};
    use zrak::model::pixels::{render_pixels, rgb_of};
    let mut sum = 0.0;
    for frame in &scene.val {
        let k = frame.camera.intrinsics;
        let (w, h) = (k.width as usize, k.height as usize);
        let full = rgb_of(&render_pixels(trainer.model.as_ref(), &frame.camera, WHITE));
        let (small_w, small_h) = (w / factor, h / factor);
        let mut small = vec![[0f32; 3]; small_w * small_h];
        let share = 1.0 / (factor * factor) as f32;
        for y in 0..small_h * factor {
            for x in 0..small_w * factor {
                let pixel = &mut small[(y / factor) * small_w + x / factor];
                for (sum, value) in pixel.iter_mut().zip(full[y * w + x]) {
                    *sum += value * share;
                }
            }
        }
        let truth = RgbImage::from_rgba8_over(&frame.downscaled(factor as u32).image, WHITE);
        let small = RgbImage::new(small_w, small_h, small).expect("one pixel per block");
        sum += psnr(&small, &truth).expect("same size");
    }
    sum / scene.val.len() as f64
}

/// Mip-NeRF's anti-aliasing (Barron et al. 2021, section 5.1, the
/// multiscale Blender protocol): trained on every view at full, ½ and ¼
/// size (area-averaged photographs, an equal share of rays each), one
/// Mip-NeRF serves all three sizes, its cones as wide as each size's
/// pixels, while NeRF's single ray per pixel cannot tell the sizes apart
/// and must blur the full-size views and alias the small ones. Mip-NeRF's
/// held-out PSNR is above NeRF's at each size. Measured on the development
/// machine (Zen 4) after 600 steps, at full, ½ and ¼ size: mixed precision
/// NeRF 18.27 / 20.50 / 22.36 dB, Mip-NeRF 19.12 / 22.04 / 23.58; f32
/// NeRF 18.20 / 20.39 / 22.14, Mip-NeRF 19.11 / 22.04 / 23.78: ahead by at
/// least 0.85 dB everywhere. The lead at ¼ size is the cones' doing:
/// trained on full size only (ZRAK_AA_SCALES=1) Mip-NeRF starts faster as
/// well (it begins transparent, NeRF in a fog), 0.8 and 1.0 dB ahead at
/// full and ½ size after 600 steps, yet 3.0 dB behind at ¼ (19.46 against
/// 22.50 dB), a cone wider than any it was trained on. Later the lead
/// narrows at ½ size and widens at ¼ (1800 steps, mixed: 1.69, 0.82 and
/// 2.86 dB; f32: 1.06, 0.05 and 2.10).
///
/// The same runs show that each model learns the scene: at full size both
/// stand well above the simplest predictor, every pixel of a held-out view
/// the mean colour of the training images on white (about 10 dB). The
/// margins, 2.5 dB for NeRF (56 % of that predictor's squared error) and
/// 2 dB for Mip-NeRF (63 %), are what a field that learned nothing cannot
/// reach: NeRF's density first grows into a fog that fills the box (8.7 dB
/// at step 100, below the mean colour), Mip-NeRF begins nearly transparent
/// (softplus(raw − 1)).
///
/// ZRAK_AA_SUPERSAMPLED=1 also prints each model's views drawn at full
/// size and area-averaged: what a perfect anti-aliaser would score.
#[test]
fn mipnerf_trained_on_three_sizes_beats_nerf_at_each() {
    let _cores = crate::common::shared();
    let size = env_or("ZRAK_AA_SIZE", 32u32);
    let scales = env_or("ZRAK_AA_SCALES", 3u32);
    let steps = env_or("ZRAK_AA_STEPS", 600u32);
    let batch = env_or("ZRAK_AA_BATCH", 1usize << 12);
    let every = env_or("ZRAK_AA_EVERY", steps);
    let precision = if std::env::var("ZRAK_AA_F32").is_ok() {
        Precision::F32
    } else {
        Precision::best_available()
    };
    let mut scores = Vec::new();
    for (kind, margin) in [(Kind::Nerf, 2.5), (Kind::MipNerf, 2.0)] {
        let (scene, mut trainer) = demo_trainer(kind, size, scales, batch, precision);
        let baseline = mean_colour_psnr(&scene.train, &scene.val);
        eprintln!("{kind:?}: the mean colour scores {baseline:.2} dB at full size");
        let started = Instant::now();
        let mut psnrs = [0.0; 3];
        while trainer.step < steps {
            trainer.step();
            if trainer.step.is_multiple_of(every) || trainer.step == steps {
                psnrs = [1, 2, 4].map(|factor| held_out_psnr_at(&trainer, &scene, factor));
                eprintln!(
                    "{kind:?} step {}: {:.2} / {:.2} / {:.2} dB at full, ½, ¼ size \
                     ({:.0} s)",
                    trainer.step,
                    psnrs[0],
                    psnrs[1],
                    psnrs[2],
                    started.elapsed().as_secs_f64()
                );
            }
        }
        if std::env::var("ZRAK_AA_SUPERSAMPLED").is_ok() {
            eprintln!(
                "{kind:?} drawn at full size and area-averaged: {:.2} / {:.2} dB at ½, ¼ size",
                area_averaged_render_psnr(&trainer, &scene, 2),
                area_averaged_render_psnr(&trainer, &scene, 4)
            );
        }
        assert!(
            psnrs[0] > baseline + margin,
            "{kind:?}: the mean colour {baseline:.2} dB, trained {:.2} dB at full size",
            psnrs[0]
        );
        scores.push(psnrs);
    }
    let (nerf, mipnerf) = (scores[0], scores[1]);
    assert!(
        (0..3).all(|size| mipnerf[size] > nerf[size]),
        "held-out PSNR at full, ½, ¼ size: NeRF {nerf:.2?} dB, Mip-NeRF {mipnerf:.2?} dB"
    );
}
