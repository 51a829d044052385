//! The turns and the stats of the training part, driven with given step
//! times: no thread, no model.

use std::time::{Duration, Instant};

use super::{RecentSteps, StatsWindow, StepRate, Training, Turns};
use crate::field::ModelKind;
use crate::field::common::LossKind;
use crate::metrics::psnr_from_mse;
use crate::model::{Stage, StepStats};
use crate::session::protocol::InTurn;

/// Simulates the worker's loop: `step(model, n)` is the time of the `n`th
/// step of `model`; returns each model's training seconds and the order of
/// the turns.
fn simulate_with(
    settings: &InTurn,
    mut step: impl FnMut(ModelKind, usize) -> f64,
    total_seconds: f64,
) -> (Vec<f64>, Vec<ModelKind>) {
    let index = |kind: ModelKind| settings.models.iter().position(|&m| m == kind).unwrap();
    let mut trained = vec![0.0; settings.models.len()];
    let mut steps = vec![0; settings.models.len()];
    let mut turns = Turns::new(settings, |_| 0.0);
    let mut order = Vec::new();
    while trained.iter().sum::<f64>() < total_seconds {
        let kind = turns.model_to_train(|m| trained[index(m)]);
        if order.last() != Some(&kind) {
            order.push(kind);
        }
        trained[index(kind)] += step(kind, steps[index(kind)]);
        steps[index(kind)] += 1;
    }
    (trained, order)
}

/// [`simulate_with`] where each model's steps take a fixed time.
fn simulate(
    settings: &InTurn,
    step_seconds: &[f64],
    total_seconds: f64,
) -> (Vec<f64>, Vec<ModelKind>) {
    let index = |kind: ModelKind| settings.models.iter().position(|&m| m == kind).unwrap();
    simulate_with(settings, |kind, _| step_seconds[index(kind)], total_seconds)
}

fn spread(trained: &[f64]) -> f64 {
    let (low, high) = trained
        .iter()
        .fold((f64::INFINITY, 0f64), |(l, h), &t| (l.min(t), h.max(t)));
    high - low
}

#[test]
fn turns_go_round_in_order_at_equal_shares_of_training_time() {
    let settings = InTurn {
        models: vec![ModelKind::Ngp, ModelKind::Nerf, ModelKind::MipNerf],
        slice_seconds: 0.5,
    };
    // Steps of very different cost, none dividing the slice evenly.
    let steps = [0.013, 0.07, 0.3];
    let (trained, order) = simulate(&settings, &steps, 60.0);
    let expected: Vec<ModelKind> = (0..order.len()).map(|i| settings.models[i % 3]).collect();
    assert_eq!(order, expected);
    assert!(order.len() >= 3 * 30, "{} turns", order.len());
    // Within one slice and one step of each other, however many turns
    // (the overshoot of each turn does not add up).
    assert!(spread(&trained) <= 0.5 + 0.3 + 1e-9, "{trained:?}");
    // The slowest model's share is a third to within that bound.
    assert!((trained[2] / trained.iter().sum::<f64>() - 1.0 / 3.0).abs() < 0.02);
}

#[test]
fn a_step_longer_than_the_slice_still_passes_the_turn_on() {
    let settings = InTurn {
        models: vec![ModelKind::Ngp, ModelKind::Nerf],
        slice_seconds: 0.1,
    };
    let (trained, order) = simulate(&settings, &[0.01, 0.35], 10.0);
    assert_eq!(
        &order[..4],
        [
            ModelKind::Ngp,
            ModelKind::Nerf,
            ModelKind::Ngp,
            ModelKind::Nerf
        ]
    );
    assert!(
        (trained[0] - trained[1]).abs() <= 0.1 + 0.35 + 1e-9,
        "{trained:?}"
    );
}

#[test]
fn a_model_a_long_first_step_put_ahead_is_passed_over_until_the_other_catches_up() {
    // Instant-NGP's first step can take 1.25 s against slices of 0.3 s:
    // NeRF then trains several slices in a row, and the two end level.
    let settings = InTurn {
        models: vec![ModelKind::Ngp, ModelKind::Nerf],
        slice_seconds: 0.3,
    };
    let step = |kind, n| match (kind, n) {
        (ModelKind::Ngp, 0) => 1.25,
        (ModelKind::Ngp, _) => 0.02,
        _ => 0.05,
    };
    // NeRF's first turn runs until it has had as many slices as
    // Instant-NGP has finished (four: 1.25 s is over four slices), about
    // 1.2 s: still its turn at 1.15 s.
    let (_, order) = simulate_with(&settings, step, 1.25 + 1.15);
    assert_eq!(order, [ModelKind::Ngp, ModelKind::Nerf], "one long turn");
    let (trained, order) = simulate_with(&settings, step, 10.0);
    assert_eq!(
        order[..3],
        [ModelKind::Ngp, ModelKind::Nerf, ModelKind::Ngp]
    );
    assert!(spread(&trained) <= 0.3 + 0.05 + 1e-9, "{trained:?}");
}

#[test]
fn turns_count_from_the_training_time_the_models_had_when_they_began() {
    let settings = InTurn {
        models: vec![ModelKind::Nerf, ModelKind::Ngp],
        slice_seconds: 1.0,
    };
    // NeRF had trained 100 s alone before the turns began: that is not a
    // share it has had of the turns.
    let before = |kind| if kind == ModelKind::Nerf { 100.0 } else { 0.0 };
    let mut turns = Turns::new(&settings, before);
    assert_eq!(turns.current(), ModelKind::Nerf);
    assert_eq!(turns.model_to_train(before), ModelKind::Nerf);
    let after_a_slice = |kind| if kind == ModelKind::Nerf { 101.0 } else { 0.0 };
    assert_eq!(turns.model_to_train(after_a_slice), ModelKind::Ngp);
    // A lone model keeps the turn; the slice is at least a millisecond.
    let mut alone = Turns::new(
        &InTurn {
            models: vec![ModelKind::Ngp],
            slice_seconds: 0.0,
        },
        |_| 0.0,
    );
    assert_eq!(alone.settings().slice_seconds, 1e-3);
    assert_eq!(alone.model_to_train(|_| 50.0), ModelKind::Ngp);
}

#[test]
fn the_trainee_is_the_active_model_without_turns_and_the_turns_model_with_them() {
    let mut training = Training::new(ModelKind::Nerf);
    assert_eq!(training.trainee(), ModelKind::Nerf);
    assert!(!training.can_train(), "no model built, not running");
    assert_eq!(training.pass_turn(), None, "no turns");
    training.set_turns(Some(InTurn {
        models: vec![ModelKind::Ngp, ModelKind::Nerf],
        slice_seconds: 0.5,
    }));
    assert_eq!(training.trainee(), ModelKind::Ngp);
    assert_eq!(
        training.turns().map(|t| t.models),
        Some(vec![ModelKind::Ngp, ModelKind::Nerf])
    );
    // No model built: each has trained 0 s, so the turn stays.
    assert_eq!(training.pass_turn(), None);
    assert!(training.clear(), "the turns end with the models");
    assert_eq!(training.trainee(), ModelKind::Nerf);
}

#[test]
fn training_waits_three_times_its_last_step_while_the_camera_moves() {
    let mut training = Training::new(ModelKind::Ngp);
    let now = Instant::now();
    assert!(training.step_due_while_moving(now), "no step yet");
    assert_eq!(training.wait_while_moving(now), Duration::ZERO);
    training.stepped(0.1);
    let ended = Instant::now();
    let wait = training.wait_while_moving(ended);
    assert!(
        wait <= Duration::from_millis(300) && wait > Duration::from_millis(290),
        "{wait:?}"
    );
    assert!(!training.step_due_while_moving(ended + Duration::from_millis(250)));
    assert!(training.step_due_while_moving(ended + Duration::from_millis(301)));
    assert_eq!(
        training.wait_while_moving(ended + Duration::from_millis(301)),
        Duration::ZERO
    );
}

fn step(loss: f32, rays: usize, samples: usize, composited: Option<usize>) -> StepStats {
    let mut stats = StepStats {
        loss,
        rays,
        samples,
        samples_composited: composited,
        ..StepStats::default()
    };
    stats.times[Stage::GridUpdate] = 0.01;
    stats
}

#[test]
fn a_window_of_steps_reports_their_means() {
    let mut window = StatsWindow::default();
    let rate = StepRate {
        ms_per_step: 400.0,
        samples_per_second: 10_000.0,
    };
    assert!(
        window
            .stats(ModelKind::Ngp, LossKind::L2, 0, 0.0, 0, rate)
            .is_none()
    );
    window.add(&step(0.01, 100, 2000, Some(500)));
    window.add(&step(0.04, 300, 6000, Some(1500)));
    let stats = window
        .stats(ModelKind::Ngp, LossKind::L2, 7, 3.5, 1234, rate)
        .unwrap();
    assert_eq!(
        (
            stats.model,
            stats.step,
            stats.train_seconds,
            stats.memory_bytes
        ),
        (ModelKind::Ngp, 7, 3.5, 1234)
    );
    // The loss is the mean over rays, not over steps.
    let loss = (0.01 * 100.0 + 0.04 * 300.0) / 400.0;
    assert!((stats.loss - loss as f32).abs() < 1e-7, "{}", stats.loss);
    assert_eq!(stats.batch_psnr, Some(psnr_from_mse(loss) as f32));
    assert_eq!(stats.val_psnr, None);
    assert!((stats.ms_per_step - 400.0).abs() < 1e-3);
    assert_eq!(stats.samples_per_ray, 20.0);
    assert_eq!(stats.composited_per_ray, Some(5.0));
    assert_eq!(stats.samples_per_second, 10_000.0);
    assert!((stats.times[Stage::GridUpdate] - 0.01).abs() < 1e-12);
    // Huber has no honest PSNR; a step without composited counts makes
    // the window's unknown.
    window.add(&step(0.02, 100, 100, None));
    let stats = window
        .stats(ModelKind::Ngp, LossKind::Huber, 8, 3.6, 1234, rate)
        .unwrap();
    assert_eq!((stats.batch_psnr, stats.composited_per_ray), (None, None));
}

/// The viewer's speed figures: 189 ms steps of 2^16 samples and one step
/// of 864 ms that also updated the occupancy grid (the panel once showed
/// "ms/step 863.9" and "samples/s 0.08 M" from such a step alone).
#[test]
fn speed_figures_are_medians_that_one_long_step_does_not_swing() {
    let mut recent = RecentSteps::default();
    assert_eq!(recent.rate(), None);
    let mut clock = 0.0;
    for seconds in [0.189, 0.189, 0.864, 0.189, 0.189] {
        clock += seconds;
        recent.add(clock, seconds, 1 << 16);
    }
    let rate = recent.rate().unwrap();
    assert!((rate.ms_per_step - 189.0).abs() < 1e-9, "{rate:?}");
    // Samples per step over the median time: 0.35 M samples/s, not 0.08.
    assert!(
        (rate.samples_per_second - 65536.0 / 0.189).abs() < 1e-6,
        "{rate:?}"
    );
    // An even count takes the mean of the middle two; samples per step are
    // the steps' mean.
    recent.add(clock + 0.2, 0.2, 3 << 16);
    let rate = recent.rate().unwrap();
    assert!((rate.ms_per_step - 189.0).abs() < 1e-9, "{rate:?}");
    let samples_per_step = 8.0 * 65536.0 / 6.0;
    assert!(
        (rate.samples_per_second - samples_per_step / 0.189).abs() < 1e-6,
        "{rate:?}"
    );
}

/// The figures cover the last training seconds: older steps leave once
/// enough steps are newer, a clock that goes back (a loaded checkpoint)
/// starts afresh, and time that is not training (the training clock
/// stands still) ages nothing.
#[test]
fn speed_figures_cover_the_last_training_seconds() {
    let mut recent = RecentSteps::default();
    // Ten slow steps of 1 s, then fast ones of 0.1 s: after 5 training
    // seconds of fast steps, the slow ones are gone.
    let mut clock = 0.0;
    for _ in 0..10 {
        clock += 1.0;
        recent.add(clock, 1.0, 100);
    }
    assert_eq!(recent.rate().unwrap().ms_per_step, 1000.0);
    for _ in 0..52 {
        clock += 0.1;
        recent.add(clock, 0.1, 100);
    }
    assert!((recent.rate().unwrap().ms_per_step - 100.0).abs() < 1e-9);
    // Slow steps keep at least five, the window's length notwithstanding.
    let mut slow = RecentSteps::default();
    for (i, seconds) in [9.0, 9.0, 9.0, 30.0, 9.0, 9.0].into_iter().enumerate() {
        slow.add(10.0 * (i + 1) as f64, seconds, 100);
    }
    assert_eq!(slow.rate().unwrap().ms_per_step, 9000.0);
    // A checkpoint loaded: its clock is behind the steps kept.
    slow.add(3.0, 0.5, 100);
    assert_eq!(slow.rate().unwrap().ms_per_step, 500.0);
}

/// A model whose steps take `step` of wall time.
struct Sleepy {
    step: Duration,
}

impl crate::model::RadianceModel for Sleepy {
    fn describe(&self) -> String {
        "sleepy".into()
    }
    fn rays_for_next_batch(&self) -> usize {
        4
    }
    fn step(&mut self, batch: &crate::model::batch::RayBatch, _step: u32) -> StepStats {
        std::thread::sleep(self.step);
        StepStats {
            rays: batch.len(),
            samples: 10 * batch.len(),
            ..StepStats::default()
        }
    }
    fn render(&self, _: crate::model::RenderRays, out: &mut [crate::model::RenderedPixel]) {
        out.fill(crate::model::RenderedPixel::default());
    }
    fn save(&self) -> crate::model::checkpoint::Checkpoint {
        crate::model::checkpoint::Checkpoint {
            header: serde_json::json!({}),
            tensors: Vec::new(),
        }
    }
    fn load(&mut self, _: &crate::model::checkpoint::Checkpoint) -> Result<(), String> {
        Ok(())
    }
    fn memory_bytes(&self) -> usize {
        0
    }
}

/// Between a slot's steps the thread pauses (renders, waits for commands):
/// ms/step is the steps' own time, not the time from one to the next.
#[test]
fn time_between_steps_does_not_count_in_ms_per_step() {
    let scene = std::sync::Arc::new(crate::scene::demo::build(&crate::scene::demo::DemoConfig {
        size: 8,
        train_views: 2,
        val_views: 1,
        test_views: 1,
    }));
    let model = Box::new(Sleepy {
        step: Duration::from_millis(20),
    });
    let trainer = crate::train::trainer::Trainer::new(model, scene, 0);
    let mut training = Training::new(ModelKind::Ngp);
    let mut slot = training.new_slot(ModelKind::Ngp, trainer, LossKind::L2, 1e9);
    for revision in 0..5 {
        slot.step(revision);
        std::thread::sleep(Duration::from_millis(200));
    }
    let stats = slot.take_report().unwrap();
    // 20 ms each, with room for a busy machine; counting the pauses would
    // give at least 220.
    assert!(
        (20.0..150.0).contains(&stats.ms_per_step),
        "{}",
        stats.ms_per_step
    );
    let samples_per_second = 40.0 / (stats.ms_per_step as f64 / 1000.0);
    assert!(
        (stats.samples_per_second as f64 / samples_per_second - 1.0).abs() < 1e-4,
        "{} against {samples_per_second}",
        stats.samples_per_second
    );
}
