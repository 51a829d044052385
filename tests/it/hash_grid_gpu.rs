//! The gpu hash encoding against the cpu on lavapipe: forward, and backward
//! with native f32 atomics and with the compare-and-swap fallback.
//!
//! Tolerances. An output is Σ_c w_c θ_c over 8 corners, computed by the
//! same f32 operations in the same order on both engines; they may differ by
//! fused multiply-adds and so by a few roundings, each at most ε = 6e-8 of
//! Σ_c w_c |θ_c|. A gradient entry is a sum of n contributions w · g, added
//! in a different order on the gpu (atomics land in any order): each
//! ordering of an f32 sum is within (n − 1) · ε · Σ|terms| of the exact sum,
//! so the two differ by at most 2 (n − 1) ε Σ|terms|. On the paper's grid
//! with 4000 samples n is about 1 on average and a few dozen at most; the
//! deliberately contended tables below keep n ≤ 800, so the bound stays
//! under 9.5e-5 · Σ|terms|. Both passes are held to the 1e-4 relative error
//! asked of every gpu stage, measured against the sum
//! of absolute terms (the condition-free scale of a sum; against the sum
//! itself, cancellation could make any tolerance fail or pass by luck).

use zrak::engine::cpu::hash_grid::{encode, encode_backward};
use zrak::engine::gpu::GpuContext;
use zrak::engine::gpu::hash_grid::GpuHashGrid;
use zrak::engine::gpu::kernel::{Recorder, read_buffer, storage_buffer, zeroed_storage_buffer};
use zrak::field::encoding::{HashGridConfig, HashGridLayout};
use zrak::rng::Pcg32;

const TOLERANCE: f32 = 1e-4;

/// The paper's grid with entries of order 1, so relative errors are not
/// drowned by the 1e-4 initial scale.
fn paper_layout() -> HashGridLayout {
    HashGridLayout::new(&HashGridConfig {
        init_range: 1.0,
        ..HashGridConfig::paper(1.0)
    })
}

/// Random positions, then the hard ones: the box's corners and faces, cell
/// boundaries of every level, and a few slightly outside the box.
fn positions(layout: &HashGridLayout, count: usize, seed: u64) -> Vec<[f32; 3]> {
    let mut rng = Pcg32::new(seed, 7);
    let mut special = vec![0.0f32, 1.0, 0.5, -1e-6, 1.0 + 1e-6];
    for level in layout.levels() {
        let n = level.resolution as f32;
        special.extend([1.0 / n, (n - 1.0) / n, (n / 2.0).floor() / n]);
    }
    let mut p = Vec::with_capacity(count);
    for (i, &x) in special.iter().enumerate() {
        p.push([
            x,
            special[(i * 3 + 1) % special.len()],
            special[(i * 7 + 2) % special.len()],
        ]);
    }
    p.push([1.0; 3]);
    p.push([0.0; 3]);
    while p.len() < count {
        p.push([rng.next_f32(), rng.next_f32(), rng.next_f32()]);
    }
    p
}

fn symmetric(count: usize, seed: u64) -> Vec<f32> {
    let mut rng = Pcg32::new(seed, 3);
    (0..count).map(|_| 2.0 * rng.next_f32() - 1.0).collect()
}

fn context() -> GpuContext {
    GpuContext::new().expect("CI installs mesa-vulkan-drivers, so an adapter exists")
}

/// Worst |gpu − cpu| / scale over all elements, where `scale` is Σ|terms|
/// of each element; elements whose scale is 0 must be exactly 0 on both.
fn worst_relative_error(gpu: &[f32], cpu: &[f32], scale: &[f32]) -> f32 {
    assert_eq!(gpu.len(), cpu.len());
    let mut worst = 0.0f32;
    for i in 0..cpu.len() {
        assert!(gpu[i].is_finite(), "element {i}: gpu {}", gpu[i]);
        if scale[i] == 0.0 {
            assert_eq!((gpu[i], cpu[i]), (0.0, 0.0), "element {i} has no terms");
            continue;
        }
        worst = worst.max((gpu[i] - cpu[i]).abs() / scale[i]);
    }
    worst
}

/// The grid of a large scene (aabb_scale 8): it spans the box [−3.5, 4.5]³.
fn box_layout() -> HashGridLayout {
    HashGridLayout::new(&HashGridConfig {
        init_range: 1.0,
        ..HashGridConfig::paper(8.0)
    })
}

/// [`positions`] spread over the box of `layout`'s grid (its hard cases
/// land on the box's faces, its cells' boundaries and just outside).
fn box_positions(layout: &HashGridLayout, count: usize, seed: u64) -> Vec<[f32; 3]> {
    let extent = layout.config().extent;
    positions(layout, count, seed)
        .into_iter()
        .map(|p| p.map(|x| x * extent + 0.5 - 0.5 * extent))
        .collect()
}

#[test]
fn forward_matches_cpu() {
    let _cores = crate::common::shared();
    let layout = paper_layout();
    check_forward(&layout, &positions(&layout, 4000, 2));
}

#[test]
fn forward_over_a_large_scenes_box_matches_cpu() {
    let _cores = crate::common::shared();
    let layout = box_layout();
    check_forward(&layout, &box_positions(&layout, 4000, 2));
}

#[test]
fn backward_over_a_large_scenes_box_matches_cpu() {
    let _cores = crate::common::shared();
    let layout = box_layout();
    check_backward_at(&layout, &box_positions(&layout, 4000, 4), true);
}

fn check_forward(layout: &HashGridLayout, positions: &[[f32; 3]]) {
    let context = context();
    let grid = GpuHashGrid::new(&context, layout, true).expect("the kernels compile");
    let params = layout.init_params(1);
    let width = layout.output_width();

    let gpu = grid.encode_once(&context, &params, positions);
    let mut cpu = vec![0.0; positions.len() * width];
    encode(layout, &params, positions, &mut cpu);
    // Σ_c w_c |θ_c|: the weights are ≥ 0.
    let abs_params: Vec<f32> = params.iter().map(|p| p.abs()).collect();
    let mut scale = vec![0.0; cpu.len()];
    encode(layout, &abs_params, positions, &mut scale);

    let worst = worst_relative_error(&gpu, &cpu, &scale);
    eprintln!("forward: worst error {worst:e} of Σ|w θ|");
    assert!(worst <= TOLERANCE, "worst relative error {worst:e}");
}

/// The gradient on the gpu (native atomics or the fallback) against the cpu.
fn check_backward(layout: &HashGridLayout, count: usize, float_atomics: bool) {
    check_backward_at(layout, &positions(layout, count, 4), float_atomics);
}

fn check_backward_at(layout: &HashGridLayout, positions: &[[f32; 3]], float_atomics: bool) {
    let count = positions.len();
    let context = context();
    let grid = GpuHashGrid::new(&context, layout, float_atomics).expect("the kernels compile");
    assert_eq!(
        grid.uses_float_atomics(),
        float_atomics && context.has_float_atomics()
    );
    if float_atomics && !grid.uses_float_atomics() {
        eprintln!("this adapter has no f32 atomics: the fallback was tested instead");
    }
    let d_out = symmetric(count * layout.output_width(), 5);

    let gpu = grid.backward_once(&context, positions, &d_out);
    let mut cpu = vec![0.0; layout.param_count()];
    encode_backward(layout, positions, &d_out, &mut cpu);
    let abs_d_out: Vec<f32> = d_out.iter().map(|g| g.abs()).collect();
    let mut scale = vec![0.0; layout.param_count()];
    encode_backward(layout, positions, &abs_d_out, &mut scale);

    // n, the contributions per entry, sets the bound in the header; print
    // its average (the busiest entries of the coarsest level get a few
    // times that).
    let touched = scale.iter().filter(|&&s| s != 0.0).count();
    let contributions = count * 8 * layout.levels().len() * layout.features();
    eprintln!(
        "backward ({}): {touched} entries touched, {:.1} contributions each on average",
        if grid.uses_float_atomics() {
            "f32 atomics"
        } else {
            "compare-and-swap"
        },
        contributions as f64 / touched as f64
    );

    let worst = worst_relative_error(&gpu, &cpu, &scale);
    eprintln!("backward: worst error {worst:e} of Σ|w g|");
    assert!(worst <= TOLERANCE, "worst relative error {worst:e}");
}

#[test]
fn backward_with_float_atomics_matches_cpu() {
    let _cores = crate::common::shared();
    check_backward(&paper_layout(), 4000, true);
}

#[test]
fn backward_with_compare_and_swap_matches_cpu() {
    let _cores = crate::common::shared();
    check_backward(&paper_layout(), 4000, false);
}

/// Tables of at most 64 entries per level shared by 800 samples: every entry
/// gets dozens to hundreds of simultaneous adds, so a lost update (a broken
/// compare-and-swap loop) shows as an error of order 0.1, far above the
/// tolerance (checked by breaking the loop on purpose).
fn contended_layout() -> HashGridLayout {
    HashGridLayout::new(&HashGridConfig {
        levels: 3,
        features_per_level: 2,
        log2_table_size: 6,
        base_resolution: 2,
        finest_resolution: 16,
        init_range: 1.0,
        extent: 1.0,
    })
}

#[test]
fn contended_backward_loses_no_update() {
    let _cores = crate::common::shared();
    let layout = contended_layout();
    // Level 0 is a dense 3³ grid whose centre vertex is a corner of every
    // cell, so it gets a contribution from each sample: n ≤ 800, and the
    // sum-order bound is 2 · 800 · ε ≈ 9.5e-5, within the tolerance.
    for float_atomics in [true, false] {
        check_backward(&layout, 800, float_atomics);
    }
}

#[test]
fn dispatches_share_one_encoder() {
    let _cores = crate::common::shared();
    // Two batch sizes recorded into one encoder: each dispatch must see its
    // own sample count, and the backward must see the forward's inputs.
    let context = context();
    let layout = contended_layout();
    let grid = GpuHashGrid::new(&context, &layout, false).expect("the kernels compile");
    let params = layout.init_params(9);
    let width = layout.output_width();
    let positions = positions(&layout, 800, 10);
    let small = 100;

    let params_buffer = storage_buffer(&context, "params", &params);
    let positions_buffer = storage_buffer(&context, "positions", &positions);
    let encoded_small =
        zeroed_storage_buffer::<f32>(&context, "encoded small", positions.len() * width);
    let encoded_all =
        zeroed_storage_buffer::<f32>(&context, "encoded all", positions.len() * width);
    let d_params = zeroed_storage_buffer::<f32>(&context, "d_params", layout.param_count());
    let mut rec = Recorder::new(&context);
    grid.record_encode(
        &mut rec,
        &params_buffer,
        &positions_buffer,
        &encoded_small,
        small,
    );
    grid.record_encode(
        &mut rec,
        &params_buffer,
        &positions_buffer,
        &encoded_all,
        positions.len(),
    );
    // The gradient of Σ encoded: d_encoded = the forward's output would do
    // as well, but ones make the cpu reference independent of the forward.
    let ones = storage_buffer(&context, "ones", &vec![1.0f32; positions.len() * width]);
    grid.record_backward(
        &mut rec,
        &positions_buffer,
        &ones,
        &d_params,
        positions.len(),
    );
    rec.submit();

    let mut cpu = vec![0.0; positions.len() * width];
    encode(&layout, &params, &positions, &mut cpu);
    let small_gpu: Vec<f32> = read_buffer(&context, &encoded_small, positions.len() * width);
    let all_gpu: Vec<f32> = read_buffer(&context, &encoded_all, positions.len() * width);
    for i in 0..cpu.len() {
        // |θ| ≤ 1 and Σw = 1: outputs are below 1, errors a few ε.
        assert!((all_gpu[i] - cpu[i]).abs() <= 1e-6, "element {i}");
        if i < small * width {
            assert!((small_gpu[i] - cpu[i]).abs() <= 1e-6, "element {i}");
        } else {
            assert_eq!(small_gpu[i], 0.0, "element {i} is past the small batch");
        }
    }
    let mut cpu_gradient = vec![0.0; layout.param_count()];
    encode_backward(
        &layout,
        &positions,
        &vec![1.0; positions.len() * width],
        &mut cpu_gradient,
    );
    let gpu_gradient: Vec<f32> = read_buffer(&context, &d_params, layout.param_count());
    // Each entry sums at most 800 non-negative weights (see above): the
    // orders differ by at most 2 · 800 · ε ≈ 9.5e-5 relative.
    for (i, (g, c)) in gpu_gradient.iter().zip(&cpu_gradient).enumerate() {
        assert!(
            (g - c).abs() <= 1e-4 * c.abs(),
            "entry {i}: gpu {g} cpu {c}"
        );
    }
}

#[test]
fn large_batches_fold_into_more_dispatch_dimensions() {
    let _cores = crate::common::shared();
    // 65535 workgroups of 64 cover 4194240 samples; one more sample needs a
    // second row of workgroups (z = 2), whose samples must not be lost.
    let context = context();
    let layout = HashGridLayout::new(&HashGridConfig {
        levels: 1,
        features_per_level: 1,
        log2_table_size: 12,
        base_resolution: 8,
        finest_resolution: 8,
        init_range: 1.0,
        extent: 1.0,
    });
    let grid = GpuHashGrid::new(&context, &layout, true).expect("the kernels compile");
    let params = layout.init_params(3);
    let count = 65535 * 64 + 1000;
    let mut rng = Pcg32::new(8, 1);
    let positions: Vec<[f32; 3]> = (0..count)
        .map(|_| [rng.next_f32(), rng.next_f32(), rng.next_f32()])
        .collect();
    let gpu = grid.encode_once(&context, &params, &positions);
    let mut cpu = vec![0.0; count];
    encode(&layout, &params, &positions, &mut cpu);
    let mut worst = 0.0f32;
    for (g, c) in gpu.iter().zip(&cpu) {
        worst = worst.max((g - c).abs());
    }
    // |θ| ≤ 1, Σw = 1: a few ε.
    assert!(worst <= 1e-6, "worst error {worst:e}");
}

/// A table that starts off the storage-binding alignment (a field after
/// another in a model's flat buffer: Instant-NGP's after its proposal
/// grids) encodes and accumulates exactly what the same table at its
/// buffer's start does, and touches nothing before it. Encodings are the
/// same operations on the same entries (bit-equal); gradients add the same
/// terms in the atomics' order (the tolerance above).
#[test]
fn a_table_off_the_binding_alignment_reads_and_adds_the_same_entries() {
    let _cores = crate::common::shared();
    use zrak::engine::gpu::kernel::FloatsAt;
    let context = context();
    let layout = contended_layout();
    let grid = GpuHashGrid::new(&context, &layout, true).expect("hash grid");
    let n = layout.param_count();
    let params = symmetric(n, 5);
    let positions = positions(&layout, 300, 9);
    let count = positions.len();
    let width = layout.output_width();
    let d_encoded = symmetric(count * width, 6);
    let encoded_at_start = grid.encode_once(&context, &params, &positions);
    let gradient_at_start = grid.backward_once(&context, &positions, &d_encoded);
    // 37 f32s: off any alignment a device asks for (4 bytes at least).
    let lead = 37;
    let mut padded = vec![9.0f32; lead];
    padded.extend(&params);
    let padded = storage_buffer(&context, "padded params", &padded);
    let gradient = zeroed_storage_buffer::<f32>(&context, "padded gradient", lead + n);
    let position_buffer = storage_buffer(&context, "positions", &positions);
    let d_encoded_buffer = storage_buffer(&context, "d encoded", &d_encoded);
    let encoded = zeroed_storage_buffer::<f32>(&context, "encoded", count * width);
    let mut rec = Recorder::new(&context);
    grid.record_encode_at(
        &mut rec,
        FloatsAt {
            buffer: &padded,
            offset: lead,
        },
        &position_buffer,
        &encoded,
        count,
    );
    grid.record_backward_at(
        &mut rec,
        &position_buffer,
        &d_encoded_buffer,
        FloatsAt {
            buffer: &gradient,
            offset: lead,
        },
        count,
    );
    rec.submit();
    let encoded: Vec<f32> = read_buffer(&context, &encoded, count * width);
    assert!(encoded == encoded_at_start, "the encodings differ");
    let gradient: Vec<f32> = read_buffer(&context, &gradient, lead + n);
    assert!(
        gradient[..lead].iter().all(|&g| g == 0.0),
        "written before the table"
    );
    let largest = gradient_at_start.iter().fold(0f32, |m, g| m.max(g.abs()));
    for (i, (g, e)) in gradient[lead..].iter().zip(&gradient_at_start).enumerate() {
        assert!(
            (g - e).abs() <= TOLERANCE * largest,
            "entry {i}: {g} vs {e}"
        );
    }
}
