//! NeRF and Mip-NeRF on the cpu engine (one driver, one field shape, two
//! recipes): the field's gradients, the whole step's gradient with either
//! sampler, exact resumption, and recovery from an emptied grid. Hard
//! numerical cases are in tests/it/hard_cases.rs, for every model.

use crate::common;

use std::sync::Arc;

use common::{NerfKind, batch, small_nerf_shape};
use glam::Vec3;
use zrak::engine::cpu::fields::nerf::NerfField;
use zrak::engine::cpu::fields::{Field, Gradient};
use zrak::engine::cpu::model::CpuModel;
use zrak::engine::request::{ModelRequest, ModelSettings};
use zrak::field::ModelKind;
use zrak::field::common::{LossKind, Sampling};
use zrak::model::RadianceModel;
use zrak::model::checkpoint::Checkpoint;
use zrak::rng::Pcg32;
use zrak::scene::Scene;
use zrak::train::trainer::Trainer;

fn small_scene() -> Arc<Scene> {
    common::small_scene(24)
}

const KINDS: [NerfKind; 2] = [NerfKind::Nerf, NerfKind::MipNerf];

fn model_of(scene: &Scene, kind: NerfKind, sampling: Sampling) -> CpuModel {
    let settings = ModelSettings {
        seed: 3,
        loss: LossKind::L2,
        batch_samples: Some(1 << 12),
        sampling,
        precision: zrak::field::mlp::Precision::F32,
        refine_cameras: false,
        appearance: false,
    };
    match kind {
        NerfKind::Nerf => CpuModel::build(
            &ModelRequest::new(ModelKind::Nerf, settings).with_shape(small_nerf_shape(kind)),
            scene,
        ),
        NerfKind::MipNerf => CpuModel::build(
            &ModelRequest::new(ModelKind::MipNerf, settings).with_shape(small_nerf_shape(kind)),
            scene,
        ),
    }
}

fn model(scene: &Scene, sampling: Sampling) -> CpuModel {
    model_of(scene, NerfKind::Nerf, sampling)
}

/// Variances log-uniform in [1e-6, 1e-1]: from nearly points (every
/// frequency kept) to frustums that damp all but the lowest.
fn variances(rng: &mut Pcg32, n: usize) -> Vec<f32> {
    (0..3 * n)
        .map(|_| 10f32.powf(uniform(rng, -6.0, -1.0)))
        .collect()
}

fn uniform(rng: &mut Pcg32, lo: f32, hi: f32) -> f32 {
    lo + (hi - lo) * rng.next_f32()
}

#[test]
fn field_gradient_matches_finite_differences() {
    let _cores = crate::common::shared();
    for kind in KINDS {
        check_field_gradient(kind);
    }
}

fn check_field_gradient(kind: NerfKind) {
    let mut field = NerfField::new(small_nerf_shape(kind));
    let mut rng = Pcg32::new(17, 0);
    let mut params = small_nerf_shape(kind).init_params(5);
    // Biases away from zero, so every layer's bias gradient is exercised
    // and few ReLUs sit at their kink.
    for p in params.iter_mut() {
        *p += uniform(&mut rng, -0.05, 0.05);
    }
    let n = 64;
    let positions: Vec<f32> = (0..3 * n).map(|_| uniform(&mut rng, -1.5, 1.5)).collect();
    let directions: Vec<f32> = (0..n)
        .flat_map(|_| {
            let d = Vec3::new(
                uniform(&mut rng, -1.0, 1.0),
                uniform(&mut rng, -1.0, 1.0),
                uniform(&mut rng, -1.0, 1.0),
            )
            .normalize();
            d.to_array()
        })
        .collect();
    let variances = (kind == NerfKind::MipNerf).then(|| variances(&mut rng, n));
    let variances = variances.as_deref();
    // The loss Σ a·σ + Σ b·rgb with fixed random a, b.
    let a: Vec<f32> = (0..n).map(|_| uniform(&mut rng, -1.0, 1.0)).collect();
    let b: Vec<f32> = (0..3 * n).map(|_| uniform(&mut rng, -1.0, 1.0)).collect();
    let loss = |field: &mut NerfField, params: &[f32]| -> f64 {
        let (mut sigma, mut rgb) = (vec![0f32; n], vec![0f32; 3 * n]);
        field.forward(
            params,
            &positions,
            variances,
            &directions,
            zrak::field::appearance::Appearance::None,
            &mut sigma,
            &mut rgb,
        );
        sigma
            .iter()
            .zip(&a)
            .map(|(&s, &w)| (s * w) as f64)
            .sum::<f64>()
            + rgb
                .iter()
                .zip(&b)
                .map(|(&c, &w)| (c * w) as f64)
                .sum::<f64>()
    };
    let _ = loss(&mut field, &params);
    let mut gradient = vec![0f32; params.len()];
    field.backward(&params, &a, &b, &mut gradient, Gradient::Add);

    // The forward pass agrees with inference and with the σ-only pass.
    let (mut sigma, mut rgb) = (vec![0f32; n], vec![0f32; 3 * n]);
    field.forward(
        &params,
        &positions,
        variances,
        &directions,
        zrak::field::appearance::Appearance::None,
        &mut sigma,
        &mut rgb,
    );
    let (mut sigma_inf, mut rgb_inf) = (vec![0f32; n], vec![0f32; 3 * n]);
    field.radiance(
        &params,
        &positions,
        variances,
        &directions,
        zrak::field::appearance::Appearance::None,
        &mut sigma_inf,
        &mut rgb_inf,
    );
    let mut sigma_only = vec![0f32; n];
    field.density(&params, &positions, variances, &mut sigma_only);
    for i in 0..n {
        assert!((sigma[i] - sigma_inf[i]).abs() <= 1e-5 * (1.0 + sigma[i].abs()));
        assert!((sigma[i] - sigma_only[i]).abs() <= 1e-5 * (1.0 + sigma[i].abs()));
    }
    for i in 0..3 * n {
        assert!((rgb[i] - rgb_inf[i]).abs() <= 1e-5);
    }

    // The eight parameters with the largest gradient in each network
    // (trunk before the skip, after it, colour branch).
    let shape = small_nerf_shape(kind);
    let a = shape.trunk_a.param_count();
    let b = a + shape.trunk_b.param_count();
    let networks = [0..a, a..b, b..params.len()];
    let mut checked = 0;
    for range in networks {
        let mut order: Vec<usize> = range.collect();
        order.sort_by(|&i, &j| gradient[j].abs().total_cmp(&gradient[i].abs()));
        for &index in order.iter().take(8) {
            let original = params[index];
            // The loss is a sum of 256 terms of order 1, summed in f64 from
            // f32 values (rounding ~1e-7 each, ~2e-6 in all); h = 2e-3 moves
            // it by g·h ≈ 1e-3 for these largest gradients, so rounding is
            // below 0.5% of the difference, while few of the 64 × 16 ReLUs
            // of a layer cross their kink within ±h.
            let h = 2e-3f32;
            params[index] = original + h;
            let plus = loss(&mut field, &params);
            params[index] = original - h;
            let minus = loss(&mut field, &params);
            params[index] = original;
            let numeric = (plus - minus) / (2.0 * h as f64);
            let analytic = gradient[index] as f64;
            let error = (numeric - analytic).abs() / analytic.abs().max(numeric.abs()).max(1e-3);
            // 2%: a wrong link (a missing activation derivative, a
            // misplaced skip column) is off by far more; a ReLU crossing its
            // kink inside ±h can account for the rest.
            assert!(
                error < 0.02,
                "{kind:?} parameter {index}: analytic {analytic:e}, numeric {numeric:e}"
            );
            checked += 1;
        }
    }
    assert_eq!(checked, 24);
}

/// The whole step's gradient against central differences of the step's
/// loss, for the parameters with the largest gradients in each field.
fn check_step_gradient(kind: NerfKind, sampling: Sampling) {
    let scene = small_scene();
    let mut trainer = Trainer::new(Box::new(model_of(&scene, kind, sampling)), scene.clone(), 3);
    for _ in 0..20 {
        trainer.step();
    }
    let checkpoint = trainer.model.save();
    let mut nerf = model_of(&scene, kind, sampling);
    nerf.load(&checkpoint).unwrap();
    // No gradient flows through where the second level's samples go: they
    // stay where the first evaluation put them.
    nerf.hold_samples(true);

    let rays = batch(&scene, 96, 11);
    let step = 1001; // seeds every jitter identically on each call
    // The occupancy sampler finds each ray's cut with a σ pass first when
    // the last step used few of its samples, else with the forward pass:
    // both orders are checked, and give one gradient.
    let orders: &[f64] = match sampling {
        Sampling::Occupancy => &[0.0, 1.0],
        Sampling::Paper | Sampling::Proposal => &[1.0],
    };
    let mut gradients: Vec<Vec<f32>> = Vec::new();
    for &used in orders {
        nerf.assume_used_fraction(used);
        let stats = nerf.forward_backward(&rays, step);
        assert!(stats.samples > 500, "{stats:?}");
        gradients.push(nerf.gradients().to_vec());
    }
    if let [sigma_first, forward_first] = &gradients[..] {
        // The same sums, but σ for the cut and the compositing from the
        // σ-only inference (σ's head as one dot product) or from the
        // forward pass (σ's head beside the features): last bits apart.
        let difference = sigma_first
            .iter()
            .zip(forward_first)
            .map(|(a, b)| ((a - b) as f64).powi(2))
            .sum::<f64>()
            .sqrt();
        let norm = forward_first
            .iter()
            .map(|&a| (a as f64).powi(2))
            .sum::<f64>()
            .sqrt();
        assert!(
            difference < 1e-4 * norm,
            "{kind:?}: the two orders' gradients differ by {difference:e} of {norm:e}"
        );
    }
    let gradient = gradients[0].clone();
    let ranges = nerf.parameter_ranges().to_vec();
    for (field, range) in ranges.iter().enumerate() {
        // σ first, as the analytic gradient above.
        let level_loss = |nerf: &mut CpuModel| {
            nerf.assume_used_fraction(orders[0]);
            nerf.forward_backward(&rays, step).loss as f64
        };
        let mut order: Vec<usize> = range.clone().collect();
        order.sort_by(|&a, &b| gradient[b].abs().total_cmp(&gradient[a].abs()));
        for &index in order.iter().take(4) {
            let original = nerf.params()[index];
            let h = (original.abs() * 1e-2).max(1e-3);
            nerf.params_mut()[index] = original + h;
            let plus = level_loss(&mut nerf);
            nerf.params_mut()[index] = original - h;
            let minus = level_loss(&mut nerf);
            nerf.params_mut()[index] = original;
            let numeric = (plus - minus) / (2.0 * h as f64);
            let analytic = gradient[index] as f64;
            // 5%, as for Instant-NGP's step: f32 over thousands of samples;
            // a broken link in the chain is off by far more.
            let error = (numeric - analytic).abs() / analytic.abs().max(numeric.abs());
            assert!(
                error < 0.05,
                "{kind:?} {sampling:?} field {field} parameter {index}: analytic {analytic:e}, numeric {numeric:e}"
            );
        }
    }
}

#[test]
fn step_gradient_matches_finite_differences_with_the_occupancy_sampler() {
    let _cores = crate::common::shared();
    for kind in KINDS {
        check_step_gradient(kind, Sampling::Occupancy);
    }
}

#[test]
fn step_gradient_matches_finite_differences_with_the_paper_sampler() {
    let _cores = crate::common::shared();
    for kind in KINDS {
        check_step_gradient(kind, Sampling::Paper);
    }
}

fn check_resume(kind: NerfKind, sampling: Sampling) {
    let scene = small_scene();
    let steps = 36; // spans two occupancy-grid updates (every 16 steps)
    let model = |scene: &Scene, sampling| model_of(scene, kind, sampling);
    let mut whole = Trainer::new(Box::new(model(&scene, sampling)), scene.clone(), 5);
    for _ in 0..steps {
        whole.step();
    }
    let mut first = Trainer::new(Box::new(model(&scene, sampling)), scene.clone(), 5);
    for _ in 0..17 {
        first.step();
    }
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("checkpoint.zrak");
    first.checkpoint(serde_json::json!({})).save(&path).unwrap();
    drop(first);
    let mut resumed = Trainer::new(Box::new(model(&scene, sampling)), scene.clone(), 5);
    resumed.restore(&Checkpoint::load(&path).unwrap()).unwrap();
    assert_eq!(resumed.step, 17);
    while resumed.step < steps {
        resumed.step();
    }
    let (a, b) = (whole.model.save(), resumed.model.save());
    let mut names = vec!["params", "adam.m", "adam.v"];
    if sampling == Sampling::Occupancy {
        names.push("occupancy");
    }
    for name in names {
        let (x, y) = (a.tensor(name).unwrap(), b.tensor(name).unwrap());
        let differing = x
            .iter()
            .zip(y)
            .filter(|(p, q)| p.to_bits() != q.to_bits())
            .count();
        assert_eq!(
            differing, 0,
            "{kind:?} {sampling:?}: `{name}` differs in {differing} values"
        );
    }
}

#[test]
fn resumed_run_matches_uninterrupted_run_with_either_sampler() {
    let _cores = crate::common::shared();
    for kind in KINDS {
        check_resume(kind, Sampling::Occupancy);
        check_resume(kind, Sampling::Paper);
    }
}

#[test]
fn checkpoint_of_the_other_sampler_or_model_is_refused() {
    let _cores = crate::common::shared();
    let scene = small_scene();
    let paper = model(&scene, Sampling::Paper).save();
    let error = model(&scene, Sampling::Occupancy).load(&paper).unwrap_err();
    assert!(
        error.contains("parameters") || error.contains("sampling"),
        "{error}"
    );
    let ngp = CpuModel::build(
        &crate::common::request(ModelKind::Ngp, 1, LossKind::L2, Some(1 << 12))
            .with_shape(zrak::field::ngp::NgpShape::for_scene(&scene)),
        &scene,
    );
    let error = model(&scene, Sampling::Occupancy)
        .load(&ngp.save())
        .unwrap_err();
    assert!(error.contains("`ngp`"), "{error}");
    let mip = model_of(&scene, NerfKind::MipNerf, Sampling::Occupancy).save();
    let error = model(&scene, Sampling::Occupancy).load(&mip).unwrap_err();
    assert!(error.contains("`mipnerf`"), "{error}");
}

#[test]
fn every_sample_in_empty_space_gives_no_samples_and_a_finite_step() {
    let _cores = crate::common::shared();
    let scene = small_scene();
    let mut trainer = Trainer::new(
        Box::new(model(&scene, Sampling::Occupancy)),
        scene.clone(),
        9,
    );
    for _ in 0..20 {
        trainer.step();
    }
    let mut nerf = model(&scene, Sampling::Occupancy);
    nerf.load(&trainer.model.save()).unwrap();
    let grid = nerf.occupancy_mut().unwrap();
    grid.values_mut().fill(0.0);
    grid.build_bitfield();
    assert_eq!(nerf.occupancy().unwrap().occupied_count(), 0);
    let rays = batch(&scene, 64, 4);
    let stats = nerf.step(&rays, 21);
    assert_eq!(stats.samples, 0, "an empty grid gives no samples");
    assert!(stats.loss.is_finite());
    assert!(nerf.params().iter().all(|p| p.is_finite()));
    // The next update (step 32) samples every cell of the emptied grid
    // again and finds the density that is still there.
    let mut trainer = Trainer::new(Box::new(nerf), scene.clone(), 9);
    trainer.step = 22;
    let mut last = None;
    while trainer.step < 40 {
        last = Some(trainer.step());
    }
    let last = last.unwrap();
    assert!(last.samples > 0, "the grid was not re-occupied: {last:?}");
}

#[test]
fn centre_crop_covers_the_first_steps_only() {
    let _cores = crate::common::shared();
    let scene = small_scene();
    let nerf = model(&scene, Sampling::Paper);
    // config_lego.txt: precrop_iters 500, precrop_frac 0.5.
    assert_eq!(nerf.centre_crop(0), Some(0.5));
    assert_eq!(nerf.centre_crop(499), Some(0.5));
    assert_eq!(nerf.centre_crop(500), None);
}
