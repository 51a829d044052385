//! Instant-NGP on the cpu engine as a whole: the chained step's gradient
//! against finite differences, exact resumption, and recovery from an
//! empty occupancy grid. Hard numerical cases are in tests/it/hard_cases.rs,
//! for every model.

use crate::common;

use std::sync::Arc;

use common::batch;
use zrak::engine::cpu::model::CpuModel;
use zrak::field::ModelKind;
use zrak::field::common::LossKind;
use zrak::model::RadianceModel;
use zrak::model::checkpoint::Checkpoint;
use zrak::scene::Scene;
use zrak::scene::demo::{
    DemoConfig, {self},
};
use zrak::train::trainer::Trainer;

fn small_scene() -> Arc<Scene> {
    common::small_scene(32)
}

fn model(scene: &Scene) -> CpuModel {
    CpuModel::build(
        &crate::common::request(ModelKind::Ngp, 3, LossKind::Huber, Some(1 << 13))
            .with_shape(zrak::field::ngp::NgpShape::for_scene(scene)),
        scene,
    )
}

#[test]
fn chained_gradient_matches_finite_differences() {
    let _cores = crate::common::shared();
    let scene = small_scene();
    let mut trainer = Trainer::new(Box::new(model(&scene)), scene.clone(), 3);
    // Train a little so the networks are past their symmetric start and
    // the occupancy grid has been updated.
    for _ in 0..20 {
        trainer.step();
    }
    let checkpoint = trainer.model.save();
    let mut ngp = model(&scene);
    ngp.load(&checkpoint).unwrap();

    let rays = batch(&scene, 512, 11);
    let step = 1001; // seeds the marching jitter identically every call
    let stats = ngp.forward_backward(&rays, step);
    assert!(stats.samples > 1000, "{stats:?}");
    let gradient = ngp.gradients().to_vec();
    let loss_at = |ngp: &mut CpuModel| ngp.forward_backward(&rays, step).loss as f64;

    let parts = ngp.layout().parts().to_vec();
    for part in parts {
        let (name, range) = (part.name, part.range);
        // The parameters with the largest gradients in this part: there the
        // signal stands far above f32 rounding noise in the loss.
        let mut order: Vec<usize> = range.clone().collect();
        order.sort_by(|&a, &b| gradient[b].abs().total_cmp(&gradient[a].abs()));
        for &index in order.iter().take(4) {
            let original = ngp.params()[index];
            // h large enough that the loss change (≈ g·h ≥ 1e-6 relative)
            // dwarfs f32 rounding of the loss (≈ 1e-7 relative), small
            // enough that curvature (O(h²)) and ReLU kinks stay negligible.
            let h = (original.abs() * 1e-2).max(1e-3);
            ngp.params_mut()[index] = original + h;
            let plus = loss_at(&mut ngp);
            ngp.params_mut()[index] = original - h;
            let minus = loss_at(&mut ngp);
            ngp.params_mut()[index] = original;
            let numeric = (plus - minus) / (2.0 * h as f64);
            let analytic = gradient[index] as f64;
            // 5%: the forward pass runs in f32 over thousands of samples; a
            // wrong link in the chain (a missing σ factor, a swapped column)
            // is off by far more.
            let error = (numeric - analytic).abs() / analytic.abs().max(numeric.abs());
            assert!(
                error < 0.05,
                "{name} parameter {index}: analytic {analytic:e}, numeric {numeric:e}"
            );
        }
    }
}

/// [`model`] with an occupancy grid of 32³ cells instead of the paper's
/// 128³: the same code at a 64th of the cost of each grid update (every
/// cell, every 16 steps during the warm-up), for tests that run many steps
/// to check how they chain rather than what they learn.
fn model_with_coarse_grid(scene: &Scene) -> CpuModel {
    let mut recipe = zrak::field::ngp::recipe(scene.unit_cube.aabb_scale);
    recipe.occupancy.resolution = 32;
    CpuModel::build(
        &crate::common::request(ModelKind::Ngp, 3, LossKind::Huber, Some(1 << 13))
            .with_shape(zrak::field::ngp::NgpShape::for_scene(scene))
            .with_recipe(recipe),
        scene,
    )
}

#[test]
fn resumed_run_matches_uninterrupted_run() {
    let _cores = crate::common::shared();
    let scene = small_scene();
    let steps = 40; // spans two occupancy-grid updates (every 16 steps)
    let model = model_with_coarse_grid;
    let mut whole = Trainer::new(Box::new(model(&scene)), scene.clone(), 5);
    for _ in 0..steps {
        whole.step();
    }

    let mut first = Trainer::new(Box::new(model(&scene)), scene.clone(), 5);
    for _ in 0..17 {
        first.step();
    }
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("checkpoint.zrak");
    first.checkpoint(serde_json::json!({})).save(&path).unwrap();
    drop(first);
    let mut resumed = Trainer::new(Box::new(model(&scene)), scene.clone(), 5);
    resumed.restore(&Checkpoint::load(&path).unwrap()).unwrap();
    assert_eq!(resumed.step, 17);
    while resumed.step < steps {
        resumed.step();
    }

    let a = whole.model.save();
    let b = resumed.model.save();
    for name in ["params", "adam.m", "adam.v", "occupancy"] {
        let (x, y) = (a.tensor(name).unwrap(), b.tensor(name).unwrap());
        let differing = x
            .iter()
            .zip(y)
            .filter(|(p, q)| p.to_bits() != q.to_bits())
            .count();
        assert_eq!(differing, 0, "`{name}` differs in {differing} values");
    }
}

#[test]
fn checkpoint_of_another_scene_is_refused() {
    let _cores = crate::common::shared();
    let scene = small_scene();
    let trainer = Trainer::new(Box::new(model(&scene)), scene.clone(), 1);
    let checkpoint = trainer.checkpoint(serde_json::json!({}));
    let other = Arc::new(demo::build(&DemoConfig {
        size: 32,
        train_views: 13,
        val_views: 2,
        test_views: 1,
    }));
    let mut elsewhere = Trainer::new(Box::new(model(&other)), other, 1);
    let error = elsewhere.restore(&checkpoint).unwrap_err();
    assert!(
        error.contains("12 training views") && error.contains("13 training views"),
        "{error}"
    );
}

#[test]
fn training_recovers_from_an_emptied_occupancy_grid() {
    let _cores = crate::common::shared();
    let scene = small_scene();
    let model = model_with_coarse_grid;
    let mut trainer = Trainer::new(Box::new(model(&scene)), scene.clone(), 9);
    for _ in 0..40 {
        trainer.step();
    }
    // A bad step that left every cell empty: values 0 everywhere.
    let mut ngp = model(&scene);
    ngp.load(&trainer.model.save()).unwrap();
    ngp.occupancy_mut().unwrap().values_mut().fill(0.0);
    ngp.occupancy_mut().unwrap().build_bitfield();
    assert_eq!(ngp.occupancy().unwrap().occupied_count(), 0);
    let mut trainer = Trainer::new(Box::new(ngp), scene.clone(), 9);
    trainer.step = 41;
    let stats = trainer.step();
    assert_eq!(stats.samples, 0, "an empty grid gives no samples");
    assert!(stats.loss.is_finite());
    // The next update (step 48) samples every cell again.
    let mut last = stats;
    while trainer.step < 60 {
        last = trainer.step();
    }
    assert!(last.samples > 0, "the grid was not re-occupied: {last:?}");
    assert!(last.loss.is_finite() && last.loss < 0.1, "{last:?}");
}
