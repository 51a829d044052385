use super::*;

/// Simulates the worker's loop: each model's steps take a fixed time;
/// returns each model's training seconds and the order of the turns.
fn simulate(
    settings: &InTurn,
    step_seconds: &[f64],
    total_seconds: f64,
) -> (Vec<f64>, Vec<ModelKind>) {
    let index = |kind: ModelKind| settings.models.iter().position(|&m| m == kind).unwrap();
    let mut trained = vec![0.0; settings.models.len()];
    let mut turns = Turns::new(settings, |_| 0.0);
    let mut order = Vec::new();
    while trained.iter().sum::<f64>() < total_seconds {
        let kind = turns.model_to_train(|m| trained[index(m)]);
        if order.last() != Some(&kind) {
            order.push(kind);
        }
        trained[index(kind)] += step_seconds[index(kind)];
    }
    (trained, order)
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
    let (low, high) = trained
        .iter()
        .fold((f64::INFINITY, 0f64), |(l, h), &t| (l.min(t), h.max(t)));
    assert!(high - low <= 0.5 + 0.3 + 1e-9, "{trained:?}");
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
fn viewer_batches_shrink_only_where_a_step_would_be_long() {
    use EngineKind::{Cpu, Gpu};
    use Sampling::{Occupancy, Paper};
    let batch =
        |kind, engine, software, sampling| viewer_batch_samples(kind, engine, software, sampling);
    // Instant-NGP on two cores: a quarter of its 2^18 samples, whatever
    // NeRF's sampler setting says; on any gpu adapter its own.
    for sampling in [Occupancy, Paper] {
        assert_eq!(batch(ModelKind::Ngp, Cpu, false, sampling), Some(1 << 16));
        assert_eq!(batch(ModelKind::Ngp, Gpu, true, sampling), None);
        assert_eq!(batch(ModelKind::Ngp, Gpu, false, sampling), None);
    }
    for kind in [ModelKind::Nerf, ModelKind::MipNerf] {
        // The occupancy sampler's recipe batch on the cpu engine, as
        // `zrak train` trains; the paper's sampler and lavapipe get 2^12.
        assert_eq!(batch(kind, Cpu, false, Occupancy), None);
        assert_eq!(batch(kind, Cpu, false, Paper), Some(1 << 12));
        assert_eq!(batch(kind, Gpu, true, Occupancy), Some(1 << 12));
        assert_eq!(batch(kind, Gpu, true, Paper), Some(1 << 12));
        assert_eq!(batch(kind, Gpu, false, Paper), None);
    }
}
