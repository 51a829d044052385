//! End to end: Instant-NGP on the cpu engine learns the built-in demo scene,
//! measured on held-out views against the simplest possible predictor.

use std::io::Write;
use std::sync::Arc;
use std::time::Instant;

use zrak::engine::cpu::model::CpuModel;
use zrak::field::ModelKind;
use zrak::field::common::LossKind;
use zrak::field::mlp::Precision;
use zrak::model::RadianceModel;
use zrak::scene::Scene;
use zrak::train::eval::{mean_colour_psnr, mean_psnr};
use zrak::train::trainer::Trainer;

use crate::common::demo_ngp;

fn env_or<T: std::str::FromStr>(name: &str, default: T) -> T {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

/// Mean held-out PSNR of `model` on `scene`'s val views.
fn val_psnr(model: &dyn RadianceModel, scene: &Scene) -> f64 {
    mean_psnr(model, &scene.val.iter().collect::<Vec<_>>())
}

/// Trains Instant-NGP with products at `precision` for `steps` steps of
/// `batch` samples and returns its mean held-out PSNR. With
/// `ZRAK_E2E_LOG_PSNR` set it logs the held-out PSNR every 50 steps on the
/// way (five renders a run: 4 s of a 28 s run on a 2-core Zen 4);
/// `ZRAK_E2E_GRID` sets the occupancy grid's resolution (the paper's 128
/// unless given).
fn train_and_score(
    scene: &Arc<Scene>,
    precision: Precision,
    seed: u64,
    steps: u32,
    batch: usize,
    loss: LossKind,
) -> f64 {
    let mut recipe = zrak::field::ngp::recipe(scene.unit_cube.aabb_scale);
    let paper_grid = recipe.occupancy.resolution;
    let grid = env_or("ZRAK_E2E_GRID", paper_grid);
    recipe.occupancy.resolution = grid;
    let started = Instant::now();
    // The mesh tests train on from this run: it is trained once
    // (common::demo_ngp), unless the PSNR is logged along the way.
    let shared = (precision, seed, steps, batch, loss, grid)
        == (
            Precision::F32,
            demo_ngp::SEED,
            demo_ngp::SHARED_STEPS,
            demo_ngp::BATCH_SAMPLES,
            demo_ngp::LOSS,
            paper_grid,
        )
        && scene.train[0].camera.intrinsics.width == demo_ngp::SIZE
        && std::env::var("ZRAK_E2E_LOG_PSNR").is_err();
    if shared {
        let trainer = demo_ngp::trained(steps);
        let trained = val_psnr(trainer.model.as_ref(), &trainer.scene);
        eprintln!(
            "{precision:?} seed {seed}: {trained:.2} dB after {steps} steps (shared with the \
             mesh tests; {:.0} s here)",
            started.elapsed().as_secs_f64()
        );
        return trained;
    }
    let mut request =
        crate::common::request(ModelKind::Ngp, seed, loss, Some(batch)).with_recipe(recipe);
    request.settings.precision = precision;
    let model = CpuModel::build(&request, scene);
    let mut trainer = Trainer::new(Box::new(model), scene.clone(), seed);
    let mut last_loss = 0.0;
    while trainer.step < steps {
        last_loss = trainer.step().loss;
        if trainer.step.is_multiple_of(50) && std::env::var("ZRAK_E2E_LOG_PSNR").is_ok() {
            eprintln!(
                "{precision:?} seed {seed}: step {} loss {last_loss:.5} val psnr {:.2} ({:.0} s)",
                trainer.step,
                val_psnr(trainer.model.as_ref(), scene),
                started.elapsed().as_secs_f64()
            );
        }
    }
    let trained = val_psnr(trainer.model.as_ref(), scene);
    eprintln!(
        "{precision:?} seed {seed}: {trained:.2} dB after {steps} steps ({:.0} s), loss {last_loss:.5}",
        started.elapsed().as_secs_f64()
    );
    trained
}

/// How far the mean PSNR of mixed-precision training over [`SEEDS`] may
/// fall below f32's. Rounding the products' operands to bf16 sends each
/// run down another path from the first step on, as another seed does:
/// on a 2-core Zen 4 (AVX512-BF16) the three seeds' f32 runs end 3.0 dB
/// apart (25.27, 28.26, 27.69 dB) and mixed minus f32 is −1.73, +0.43,
/// +0.24 dB (spread ≈ 1.2 dB a seed, ≈ 0.7 dB for the mean of three; mean
/// −0.35 dB). 1.5 dB is about two such spreads below the measured mean;
/// a wrong bf16 product or gradient costs far more. Training is
/// deterministic whatever the thread count, so on one machine the test
/// gives the same figures every run.
const MIXED_TOLERANCE_DB: f64 = 1.5;
const SEEDS: [u64; 3] = [0, 1, 2];

/// Instant-NGP learns the demo scene well above the mean colour in f32;
/// and, on a processor with bf16 kernels, as well with the networks'
/// products in bf16 as in f32, over three seeds (see
/// [`MIXED_TOLERANCE_DB`]). The f32 run of the first seed is both the
/// learning check and the first of the comparison's f32 runs, so the
/// comparison trains five more rather than six.
#[test]
fn learns_the_demo_scene_well_above_the_mean_colour() {
    let _cores = crate::common::shared();
    // 64×64 views, 250 steps of 2^16 samples: about a minute on two idle
    // cores. Measured on the development machine (seed 0): 9.7 dB for the
    // mean colour, 22 dB at step 200, 27 dB at step 300.
    let size = env_or("ZRAK_E2E_SIZE", 64u32);
    let steps = env_or("ZRAK_E2E_STEPS", 250u32);
    let batch = env_or("ZRAK_E2E_BATCH", 1usize << 16);
    let loss = if std::env::var("ZRAK_E2E_L2").is_ok() {
        LossKind::L2
    } else {
        LossKind::Huber
    };
    let scene = demo_ngp::demo_scene(size);

    // The baseline: every pixel of a held-out view predicted as the mean
    // colour of the training images on white.
    let baseline = mean_colour_psnr(&scene.train, &scene.val);
    let seed = env_or("ZRAK_E2E_SEED", SEEDS[0]);
    let trained = train_and_score(&scene, Precision::F32, seed, steps, batch, loss);
    eprintln!("baseline {baseline:.2} dB");
    // 10 dB over the baseline is a tenth of its squared error: far past
    // what opacity alone (a silhouette on white) can reach on this scene,
    // so colour, shading and geometry must all have been learned.
    assert!(
        trained > baseline + 10.0,
        "baseline {baseline:.2} dB, trained {trained:.2} dB"
    );

    if Precision::Mixed.kernels_here() != Precision::Mixed {
        // Past the test harness's capture, so a skipped check is seen.
        let mut stderr = std::io::stderr();
        let _ = writeln!(
            stderr,
            "SKIPPED mixed precision against f32: this processor has no bf16 kernels"
        );
        return;
    }
    // The comparison holds its seeds and the first's settings.
    if seed != SEEDS[0] || size != 64 || loss != LossKind::Huber {
        return;
    }
    let mean = |precision: Precision, first: Option<f64>| {
        SEEDS
            .iter()
            .enumerate()
            .map(|(i, &seed)| match first {
                Some(psnr) if i == 0 => psnr,
                _ => train_and_score(&scene, precision, seed, steps, batch, loss),
            })
            .sum::<f64>()
            / SEEDS.len() as f64
    };
    let (f32_psnr, mixed) = (
        mean(Precision::F32, Some(trained)),
        mean(Precision::Mixed, None),
    );
    eprintln!("mean over seeds: f32 {f32_psnr:.2} dB, mixed {mixed:.2} dB");
    assert!(
        mixed > f32_psnr - MIXED_TOLERANCE_DB,
        "mixed precision {mixed:.2} dB, f32 {f32_psnr:.2} dB (means over seeds)"
    );
}
