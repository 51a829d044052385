//! Instant-NGP with the proposal sampler on the cpu engine: the counts a
//! step evaluates, its gradients against finite differences of the losses
//! that train each field, and that it learns the demo scene.

use std::sync::Arc;

use zrak::engine::cpu::model::CpuModel;
use zrak::engine::request::ModelRequest;
use zrak::field::ModelKind;
use zrak::field::common::{LossKind, Sampling};
use zrak::field::ngp::{PROPOSAL_FIELD_SAMPLES, PROPOSAL_SAMPLES};
use zrak::model::RadianceModel;
use zrak::scene::Scene;
use zrak::train::eval::{mean_colour_psnr, mean_psnr};
use zrak::train::trainer::Trainer;

use crate::common::{batch, request, small_scene};

/// Instant-NGP with the proposal sampler on `scene`, `rays` rays a batch.
fn proposal_request(rays: usize) -> ModelRequest {
    let mut request = request(ModelKind::Ngp, 3, LossKind::L2, None);
    request.settings.sampling = Sampling::Proposal;
    let per_ray: usize = PROPOSAL_SAMPLES.iter().sum::<usize>() + PROPOSAL_FIELD_SAMPLES;
    request.settings.batch_samples = Some(rays * per_ray);
    request
}

#[test]
fn a_step_evaluates_48_field_samples_and_the_proposals_apart() {
    let _cores = crate::common::shared();
    let scene = small_scene(24);
    let mut model = CpuModel::build(&proposal_request(64), &scene);
    assert_eq!(model.rays_for_next_batch(), 64);
    let rays = batch(&scene, 64, 5);
    let stats = model.forward_backward(&rays, 1);
    assert_eq!(stats.samples, 64 * PROPOSAL_FIELD_SAMPLES);
    assert_eq!(stats.samples_per_ray(), PROPOSAL_FIELD_SAMPLES as f32);
    assert_eq!(
        stats.proposal_samples,
        64 * PROPOSAL_SAMPLES.iter().sum::<usize>()
    );
    assert!(stats.loss.is_finite() && stats.loss > 0.0, "{stats:?}");
    assert!(
        stats.proposal_loss.is_finite() && stats.proposal_loss >= 0.0,
        "{stats:?}"
    );
    // Every field gets a gradient: the proposals from the interlevel loss,
    // the full field from the pixels.
    for (field, range) in model.parameter_ranges().iter().enumerate() {
        let norm: f64 = model.gradients()[range.clone()]
            .iter()
            .map(|&g| (g as f64).powi(2))
            .sum();
        assert!(norm > 0.0, "field {field} has no gradient");
    }
    assert!(model.describe().contains("proposal"), "{}", model.describe());
}

/// With the samples held still, a proposal field's parameters change only
/// its weights, so the interlevel loss is what its gradient differentiates;
/// the full field's parameters change the colours (and the final weights,
/// which the interlevel loss holds still: no gradient reaches them from
/// it), so with the distortion loss off the loss on pixels is what its
/// gradient differentiates.
#[test]
fn step_gradient_matches_finite_differences_of_each_fields_loss() {
    let _cores = crate::common::shared();
    let scene = small_scene(24);
    let mut request = proposal_request(32);
    let mut recipe = (ModelKind::Ngp.spec().recipe)(&scene, Sampling::Proposal);
    recipe.distortion = 0.0;
    request = request.with_recipe(recipe);
    let mut model = CpuModel::build(&request, &scene);
    let rays = batch(&scene, 32, 9);
    // A few steps first, so the proposals and the field hold some density
    // and the interlevel loss is not zero.
    let mut trainer_model = CpuModel::build(&request, &scene);
    for step in 0..30 {
        trainer_model.step(&batch(&scene, 32, 100 + step), step as u32);
    }
    model.params_mut().copy_from_slice(trainer_model.params());
    model.hold_samples(true);
    let step = 77;
    let stats = model.forward_backward(&rays, step);
    assert!(stats.proposal_loss > 0.0, "{stats:?}");
    let gradient = model.gradients().to_vec();
    let ranges = model.parameter_ranges().to_vec();
    let last = ranges.len() - 1;
    for (field, range) in ranges.iter().enumerate() {
        let objective = |model: &mut CpuModel| {
            let stats = model.forward_backward(&rays, step);
            if field == last {
                stats.loss as f64
            } else {
                stats.proposal_loss as f64
            }
        };
        let mut order: Vec<usize> = range.clone().collect();
        order.sort_by(|&a, &b| gradient[b].abs().total_cmp(&gradient[a].abs()));
        for &index in order.iter().take(4) {
            let original = model.params()[index];
            let h = (original.abs() * 1e-2).max(1e-3);
            model.params_mut()[index] = original + h;
            let plus = objective(&mut model);
            model.params_mut()[index] = original - h;
            let minus = objective(&mut model);
            model.params_mut()[index] = original;
            let numeric = (plus - minus) / (2.0 * h as f64);
            let analytic = gradient[index] as f64;
            // 5 %, as for the other models' steps: f32 sums over thousands
            // of samples; a broken link in the chain is off by far more.
            let error = (numeric - analytic).abs() / analytic.abs().max(numeric.abs());
            assert!(
                error < 0.05,
                "field {field} parameter {index}: analytic {analytic:e}, numeric {numeric:e}"
            );
        }
    }
}

/// Trained for a few hundred steps on the demo scene, the proposal sampler
/// gives a held-out PSNR well above the mean colour's.
#[test]
fn instant_ngp_with_proposals_learns_the_demo_scene() {
    let _cores = crate::common::shared();
    let scene: Arc<Scene> = small_scene(48);
    let model = CpuModel::build(&proposal_request(256), &scene);
    let mut trainer = Trainer::new(Box::new(model), scene.clone(), 11);
    let views: Vec<_> = scene.val.iter().collect();
    let baseline = mean_colour_psnr(&scene.train, &scene.val);
    let mut psnr = 0.0;
    for step in 1..=400 {
        let stats = trainer.step();
        if step % 50 == 0 {
            psnr = mean_psnr(trainer.model.as_ref(), &views);
            eprintln!(
                "step {step}: loss {:.4}, interlevel {:.5}, held-out {psnr:.2} dB",
                stats.loss, stats.proposal_loss
            );
        }
    }
    eprintln!("proposal sampler on the demo: {psnr:.2} dB (mean colour {baseline:.2} dB)");
    assert!(psnr > baseline + 6.0, "{psnr} vs mean colour {baseline}");
}
