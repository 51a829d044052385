//! Buffers larger than the device's storage-binding limit are bound and
//! processed a piece at a time. lavapipe's real limit (128 MiB) is far above
//! what a test can afford, so these tests lower the limit the engine plans
//! with (`GpuContext::cap_storage_binding_size`) until buffers of a few MiB
//! must split, and compare with the same work unsplit on another context.
//!
//! Forward passes, dense backward passes and Adam are deterministic, so the
//! split results must be bit for bit the unsplit ones. The hash-grid
//! backward adds with atomics in an order that varies from run to run
//! either way, so it is compared up to reordering error.

use std::sync::Arc;

use zrak::engine::build_gpu;
use zrak::engine::gpu::GpuContext;
use zrak::engine::gpu::adam::GpuAdam;
use zrak::engine::gpu::dense::GpuDense;
use zrak::engine::gpu::hash_grid::GpuHashGrid;
use zrak::engine::gpu::kernel::{Recorder, read_buffer, rows_per_piece, storage_buffer};
use zrak::engine::shared::adam::Adam;
use zrak::field::ModelKind;
use zrak::field::common::{LossKind, OptimiserConfig};
use zrak::field::encoding::{HashGridConfig, HashGridLayout};
use zrak::field::mlp::{Activation, MlpLayout};
use zrak::model::batch::{RayBatch, TrainingBackground, sample_rays};
use zrak::rng::Pcg32;
use zrak::scene::Scene;
use zrak::scene::demo::{
    DemoConfig, {self},
};

fn context() -> GpuContext {
    GpuContext::new().expect("lavapipe or a GPU")
}

fn capped(bytes: u64) -> GpuContext {
    let mut context = context();
    context.cap_storage_binding_size(bytes);
    assert_eq!(context.storage_binding_limit(), bytes);
    context
}

fn random(rng: &mut Pcg32, n: usize, scale: f32) -> Vec<f32> {
    (0..n)
        .map(|_| scale * (2.0 * rng.next_f32() - 1.0))
        .collect()
}

fn assert_bits_equal(what: &str, split: &[f32], whole: &[f32]) {
    assert_eq!(split.len(), whole.len(), "{what}: lengths");
    for (i, (a, b)) in split.iter().zip(whole).enumerate() {
        assert_eq!(
            a.to_bits(),
            b.to_bits(),
            "{what}[{i}]: split {a} vs whole {b}"
        );
    }
}

#[test]
fn dense_forward_and_backward_split_by_rows_are_bit_exact() {
    let _cores = crate::common::shared();
    // 20 000 rows × 64 wide is 5 MiB per activation; under a 2 MiB limit
    // each layer runs in 3 pieces of 8192 rows, and the weight gradients'
    // partial sums of all pieces are reduced together. (The partials, 79
    // chunks of 256 rows × 64 × 65 weights = 1.3 MiB, still fit: a limit
    // below that would also make the chunks longer, which changes the
    // order of the sums, not their terms.)
    let cap = 2 << 20;
    let layout = MlpLayout::new(
        vec![32, 64, 64, 16],
        Activation::Relu,
        Activation::None,
        true,
    );
    let rows = 20_000;
    let mut rng = Pcg32::new(11, 0);
    let params = random(&mut rng, layout.param_count(), 0.3);
    let input = random(&mut rng, rows * 32, 1.0);
    let d_output = random(&mut rng, rows * 16, 1.0);

    let small = capped(cap);
    assert!(rows_per_piece(&small, 64, 1) < rows, "the test must split");
    let split = GpuDense::new(&small)
        .unwrap()
        .forward_backward_once(&small, &layout, &params, &input, rows, &d_output);
    let large = context();
    let whole = GpuDense::new(&large)
        .unwrap()
        .forward_backward_once(&large, &layout, &params, &input, rows, &d_output);
    for (l, (a, b)) in split.0.iter().zip(&whole.0).enumerate() {
        assert_bits_equal(&format!("layer {l} output"), a, b);
    }
    assert_bits_equal("parameter gradients", &split.1, &whole.1);
    assert_bits_equal("input gradients", &split.2, &whole.2);
}

/// 16 levels of at most 2^14 entries × 2 features: 128 KiB per level.
fn small_grid() -> HashGridLayout {
    HashGridLayout::new(&HashGridConfig {
        log2_table_size: 14,
        finest_resolution: 512,
        ..HashGridConfig::paper(1.0)
    })
}

#[test]
fn hash_grid_split_by_levels_and_samples_matches_whole() {
    let _cores = crate::common::shared();
    // A 300 KiB limit: the table (~1.7 MiB) is bound two levels at a time
    // and the 5000 × 32 encodings (625 KiB) in pieces of 2368 samples.
    let cap = 300 << 10;
    let layout = small_grid();
    assert!(4 * layout.param_count() as u64 > cap);
    let count = 5000;
    let mut rng = Pcg32::new(3, 0);
    let positions: Vec<[f32; 3]> = (0..count)
        .map(|_| [rng.next_f32(), rng.next_f32(), rng.next_f32()])
        .collect();
    let table = layout
        .init_params(9)
        .iter()
        .map(|v| v * 1e4)
        .collect::<Vec<f32>>();
    let d_encoded = random(&mut rng, count * layout.output_width(), 1.0);
    let magnitudes: Vec<f32> = d_encoded.iter().map(|g| g.abs()).collect();

    let small = capped(cap);
    let split_grid = GpuHashGrid::new(&small, &layout, true).unwrap();
    let large = context();
    let whole_grid = GpuHashGrid::new(&large, &layout, true).unwrap();

    let split = split_grid.encode_once(&small, &table, &positions);
    let whole = whole_grid.encode_once(&large, &table, &positions);
    assert_bits_equal("encodings", &split, &whole);

    let split = split_grid.backward_once(&small, &positions, &d_encoded);
    let whole = whole_grid.backward_once(&large, &positions, &d_encoded);
    // Σ|w · g| per entry: each run adds the same exact products in some
    // order, so each differs from the exact sum by at most (n − 1)·u·Σ|w·g|
    // (u = 2^-24, n contributions to the entry); 1e-5 ≈ 168·u covers two
    // such errors for entries of up to 84 contributions (the coarsest,
    // densest level averages 8 per entry here).
    let scale = whole_grid.backward_once(&large, &positions, &magnitudes);
    for (i, ((a, b), s)) in split.iter().zip(&whole).zip(&scale).enumerate() {
        assert!(
            (a - b).abs() <= 1e-5 * s,
            "gradient entry {i}: split {a} vs whole {b} (Σ|terms| {s})"
        );
    }
}

#[test]
fn a_single_level_over_the_limit_is_refused_clearly() {
    let _cores = crate::common::shared();
    let small = capped(64 << 10);
    let error = GpuHashGrid::new(&small, &small_grid(), true)
        .err()
        .expect("a 128 KiB level cannot fit 64 KiB");
    let message = error.to_string();
    assert!(message.contains("hash-grid level"), "{message}");
    assert!(message.contains("65536"), "{message}");
}

#[test]
fn adam_split_into_pieces_is_bit_exact() {
    let _cores = crate::common::shared();
    // 100 000 parameters (391 KiB per array) under a 64 KiB limit: seven
    // pieces, the network range crossing piece boundaries.
    let count = 100_000;
    let network = 30_000..70_000;
    let mut rng = Pcg32::new(5, 0);
    let params = random(&mut rng, count, 1.0);
    // Every third table gradient exactly zero: those entries are skipped.
    let gradients: Vec<f32> = random(&mut rng, count, 1e-2)
        .into_iter()
        .enumerate()
        .map(|(i, g)| {
            if i % 3 == 0 && !network.contains(&i) {
                0.0
            } else {
                g
            }
        })
        .collect();
    let config = OptimiserConfig::PAPER;
    let run = |context: &GpuContext| {
        let mut adam = GpuAdam::from_state(context, &Adam::new(count)).unwrap();
        let params_buffer = storage_buffer(context, "params", &params);
        let gradient_buffer = storage_buffer(context, "gradients", &gradients);
        for _ in 0..2 {
            let mut rec = Recorder::new(context);
            adam.record_step(
                &mut rec,
                &config,
                network.clone(),
                &params_buffer,
                &gradient_buffer,
            );
            rec.submit();
        }
        let state = adam.read_state(context);
        (read_buffer::<f32>(context, &params_buffer, count), state)
    };
    let (split_params, split_state) = run(&capped(64 << 10));
    let (whole_params, whole_state) = run(&context());
    assert_bits_equal("parameters", &split_params, &whole_params);
    assert_bits_equal("m", &split_state.m, &whole_state.m);
    assert_bits_equal("v", &split_state.v, &whole_state.v);
    assert_bits_equal("m_norm", &split_state.m_norm, &whole_state.m_norm);
    assert_bits_equal("v_norm", &split_state.v_norm, &whole_state.v_norm);
}

fn small_scene() -> Arc<Scene> {
    Arc::new(demo::build(&DemoConfig {
        size: 32,
        train_views: 8,
        val_views: 1,
        test_views: 1,
    }))
}

/// ‖a − b‖ / ‖b‖ in f64.
fn relative_norm(a: &[f32], b: &[f32]) -> f64 {
    let (mut diff, mut norm) = (0f64, 0f64);
    for (x, y) in a.iter().zip(b) {
        diff += (*x as f64 - *y as f64).powi(2);
        norm += (*y as f64).powi(2);
    }
    (diff / norm.max(1e-300)).sqrt()
}

#[test]
fn instant_ngp_step_with_split_bindings_matches_the_unsplit_step() {
    let _cores = crate::common::shared();
    // 2^15 samples under a 4.5 MiB limit: the paper's table (4 MiB per
    // hashed level) is bound a level at a time, the 64-wide activations
    // (8 MiB) in two pieces, Adam's 50 MiB arrays in twelve.
    let batch_samples = 1 << 15;
    let cap = 9 << 19;
    let scene = small_scene();
    let mut batch = RayBatch::default();
    sample_rays(
        &scene.train,
        64,
        TrainingBackground::Random,
        &mut Pcg32::new(7, 0),
        &mut batch,
    );
    let run = |context: GpuContext| {
        let mut model = build_gpu(
            context,
            &crate::common::request(ModelKind::Ngp, 5, LossKind::Huber, Some(batch_samples)),
            &scene,
        )
        .expect("gpu model");
        let stats = model.forward_backward(&batch, 0);
        (stats, model.gradients())
    };
    let (split_stats, split_gradients) = run(capped(cap));
    let (whole_stats, whole_gradients) = run(context());
    assert!(
        whole_stats.samples > batch_samples / 2,
        "the batch should fill most of the budget: {} samples",
        whole_stats.samples
    );
    assert_eq!(split_stats.samples, whole_stats.samples);
    assert_eq!(split_stats.rays, whole_stats.rays);
    // The forward pass is deterministic: the same loss, bit for bit.
    assert_eq!(split_stats.loss.to_bits(), whole_stats.loss.to_bits());
    // The networks' gradients come from deterministic kernels (the hash
    // grid's atomics only write the table's gradient): bit for bit.
    let table_params =
        HashGridLayout::new(&HashGridConfig::paper(scene.unit_cube.aabb_scale)).param_count();
    assert_bits_equal(
        "network gradients",
        &split_gradients[table_params..],
        &whole_gradients[table_params..],
    );
    // The table's gradient: atomics add in a varying order either way.
    let error = relative_norm(
        &split_gradients[..table_params],
        &whole_gradients[..table_params],
    );
    assert!(error < 1e-5, "table gradient differs by {error:e}");
}
