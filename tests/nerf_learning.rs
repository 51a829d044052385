//! End to end: NeRF and Mip-NeRF (the papers' fields, with the occupancy
//! sampler) on the cpu engine learn the built-in demo scene, measured on
//! held-out views against the simplest possible predictor.

use std::sync::Arc;
use std::time::Instant;

use zrak::engine::cpu::fields::nerf::NerfShape;
use zrak::field::nerf::Sampling;
use zrak::field::ngp::LossKind;
use zrak::scene::demo::{self, DemoConfig};
use zrak::train::eval::{mean_colour_psnr, score_view};
use zrak::train::trainer::Trainer;
use zrak::train::{
    ModelSettings, cpu_model_of_nerf_fields, mipnerf_identity, mipnerf_recipe, nerf_identity,
    nerf_recipe,
};

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

/// Trains `kind` for `steps` on the 32-pixel demo; returns (baseline,
/// held-out PSNR) in dB.
fn train_demo(kind: Kind, default_steps: u32) -> (f64, f64) {
    // 32×32 views and batches of 2^12 samples keep a step of the 8 × 256
    // network near a quarter of a second on two cores. Measured on the
    // development machine (AVX2 kernels, seed 0, 64³ grid): 10.0 dB for the
    // mean colour; 8.7, 11.4, 12.6 and 13.5 dB at steps 100 to 400; with
    // the 32³ grid below, 13.95 dB at step 400 (232 s with Mip-NeRF's test
    // beside it, against 360 s with 64³, side by side on a 2-core AVX2 EPYC).
    // NeRF starts slowly: its density first grows into a fog that fills the
    // box, so the occupancy grid samples every ray end to end (~300
    // samples) and a batch holds a dozen rays until the fog clears.
    let size = env_or("ZRAK_NERF_E2E_SIZE", 32u32);
    let steps = env_or("ZRAK_NERF_E2E_STEPS", default_steps);
    let batch = env_or("ZRAK_NERF_E2E_BATCH", 1usize << 12);
    let scene = Arc::new(demo::build(&DemoConfig {
        size,
        train_views: 60,
        val_views: 4,
        test_views: 1,
    }));

    // The baseline: every pixel of a held-out view predicted as the mean
    // colour of the training images on white.
    let baseline = mean_colour_psnr(&scene.train, &scene.val);

    let settings = ModelSettings {
        seed: 0,
        loss: LossKind::L2,
        batch_samples: Some(batch),
        sampling: Sampling::Occupancy,
        precision: zrak::engine::cpu::dense::Precision::F32,
    };
    let (identity, mut recipe, shape) = match kind {
        Kind::Nerf => (
            nerf_identity(&settings),
            nerf_recipe(&scene, &settings),
            NerfShape::paper(),
        ),
        Kind::MipNerf => (
            mipnerf_identity(&settings),
            mipnerf_recipe(&scene, &settings),
            NerfShape::mipnerf(),
        ),
    };
    // The batch is 1/4 of the shipped 2^14 samples and the occupancy grid
    // gets 1/8 of its cells (32³ instead of 64³): an update then costs no
    // more of a step than it does in a real run. With 64³ cells the
    // grid's density queries took more than half of this test's time.
    recipe.occupancy.resolution = env_or("ZRAK_NERF_E2E_GRID", 32u32);
    let model = cpu_model_of_nerf_fields(identity, recipe, &scene, &settings, &shape);
    let mut trainer = Trainer::new(Box::new(model), scene.clone(), 0);
    let started = Instant::now();
    let mut last_loss = 0.0;
    let held_out = |trainer: &Trainer| {
        scene
            .val
            .iter()
            .map(|f| score_view(trainer.model.as_ref(), f, false).psnr)
            .sum::<f64>()
            / scene.val.len() as f64
    };
    // Held-out views are rendered at the end only (each evaluation of the
    // fog-filled early field costs about as much as 80 training steps);
    // ZRAK_NERF_E2E_PROGRESS=1 prints the curve every 100 steps.
    let progress = std::env::var("ZRAK_NERF_E2E_PROGRESS").is_ok();
    while trainer.step < steps {
        last_loss = trainer.step().loss;
        if progress && trainer.step.is_multiple_of(100) {
            eprintln!(
                "{kind:?} step {} loss {last_loss:.5} val psnr {:.2} ({:.0} s)",
                trainer.step,
                held_out(&trainer),
                started.elapsed().as_secs_f64()
            );
        }
    }
    let trained = held_out(&trainer);
    eprintln!(
        "{kind:?}: baseline {baseline:.2} dB, trained {trained:.2} dB after {steps} steps ({:.0} s), loss {last_loss:.5}",
        started.elapsed().as_secs_f64()
    );
    (baseline, trained)
}

#[test]
fn nerf_learns_the_demo_scene_above_the_mean_colour() {
    let (baseline, trained) = train_demo(Kind::Nerf, 400);
    // 2.5 dB over the baseline is 56 % of its squared error, 1 dB short of
    // what was measured (other kernels round differently and the run
    // diverges in its last bits); the mean colour cannot get there, and a
    // field that learned nothing stays near or below it (8.7 dB at step
    // 100, before the fog has cleared).
    assert!(
        trained > baseline + 2.5,
        "baseline {baseline:.2} dB, trained {trained:.2} dB"
    );
}

#[test]
fn mipnerf_learns_the_demo_scene_above_the_mean_colour() {
    // Measured on the development machine (AVX2 kernels, seed 0, two cores
    // shared with other builds, 64³ grid): 11.6, 13.0 and 14.9 dB at steps
    // 100, 200 and 300 against the mean colour's 10.0; 12.83 dB at step 200
    // with the test's 32³ grid. Mip-NeRF starts faster than
    // NeRF: softplus(raw − 1) begins nearly transparent, so there is no fog
    // to clear. 200 steps keep the test near NeRF's in time.
    let (baseline, trained) = train_demo(Kind::MipNerf, 200);
    // 2 dB over the baseline (63 % of its squared error), 1 dB below what
    // was measured, for the same reasons as NeRF's margin.
    assert!(
        trained > baseline + 2.0,
        "baseline {baseline:.2} dB, trained {trained:.2} dB"
    );
}
