//! The gpu sampling stages against the cpu engine on lavapipe. Stratified
//! samples, merges, blurs and intervals repeat the cpu's arithmetic with
//! operations WGSL rounds correctly (+, −, ×, min, max; fma prevented), so
//! they must match bit for bit, and with them the (seed, ray, index)
//! uniforms. Inverse-CDF samples pick their bin with those operations too;
//! only the position inside the bin involves a division, which WGSL allows
//! to be 2.5 ulp off.

use zrak::engine::cpu::sampling::{
    blur_weights, intervals_to_far, merge_sorted, sample_pdf, stratified,
};
use zrak::engine::gpu::GpuContext;
use zrak::engine::gpu::kernel::{read_buffer, storage_buffer, zeroed_storage_buffer};
use zrak::engine::gpu::sampling::GpuSampling;
use zrak::rng::Pcg32;

/// The context and kernels, or `None` (and a note) on a machine without an
/// adapter: these tests compare engines, they cannot say anything there.
fn setup() -> Option<(GpuContext, GpuSampling)> {
    let context = match GpuContext::new() {
        Ok(context) => context,
        Err(error) => {
            eprintln!("skipped: {error}");
            return None;
        }
    };
    let sampling = GpuSampling::new(&context).expect("the sampling kernels compile");
    Some((context, sampling))
}

/// Records `record` into an encoder, submits it, reads `count` floats of
/// the buffer it returns.
fn run(
    context: &GpuContext,
    count: usize,
    record: impl FnOnce(&mut wgpu::CommandEncoder, &wgpu::Buffer),
) -> Vec<f32> {
    let out = zeroed_storage_buffer::<f32>(context, "out", count);
    let mut encoder = context.device.create_command_encoder(&Default::default());
    record(&mut encoder, &out);
    context.queue.submit([encoder.finish()]);
    read_buffer(context, &out, count)
}

fn assert_bits_equal(gpu: &[f32], cpu: &[f32], what: &str) {
    assert_eq!(gpu.len(), cpu.len());
    for (i, (g, c)) in gpu.iter().zip(cpu).enumerate() {
        assert_eq!(
            g.to_bits(),
            c.to_bits(),
            "{what}, value {i}: gpu {g} cpu {c}"
        );
    }
}

/// Near and far planes: ordinary spans, tiny spans, empty spans.
fn planes(rays: usize, seed: u64) -> (Vec<f32>, Vec<f32>) {
    let mut rng = Pcg32::new(seed, 1);
    let near: Vec<f32> = (0..rays).map(|_| 0.05 + 4.0 * rng.next_f32()).collect();
    let far = near
        .iter()
        .map(|&n| n + [0.0, 1e-6, 0.5, 2.0, 30.0][rng.below(5) as usize] * rng.next_f32())
        .collect();
    (near, far)
}

#[test]
fn stratified_matches_cpu_bit_for_bit() {
    let Some((context, sampling)) = setup() else {
        return;
    };
    let rays = 777;
    let (near, far) = planes(rays, 3);
    let near_buffer = storage_buffer(&context, "near", &near);
    let far_buffer = storage_buffer(&context, "far", &far);
    for n in [1, 2, 64, 129] {
        for jitter in [None, Some(0), Some(12345)] {
            let gpu = run(&context, rays * n, |encoder, out| {
                sampling.record_stratified(
                    &context,
                    encoder,
                    &near_buffer,
                    &far_buffer,
                    rays,
                    n,
                    jitter,
                    out,
                )
            });
            let mut cpu = vec![0.0; rays * n];
            stratified(&near, &far, n, jitter, &mut cpu);
            assert_bits_equal(&gpu, &cpu, &format!("stratified N = {n}, {jitter:?}"));
        }
    }
}

/// Rays of B bins: edges from stratified samples, some with repeated
/// edges, and weights of every kind the pdf must survive.
fn pdf_inputs(rays: usize, bins: usize, seed: u64) -> (Vec<f32>, Vec<f32>) {
    let mut rng = Pcg32::new(seed, 2);
    let (near, far) = planes(rays, seed);
    let mut edges = vec![0.0; rays * (bins + 1)];
    stratified(&near, &far, bins + 1, Some(seed as u32), &mut edges);
    let mut weights = Vec::with_capacity(rays * bins);
    for r in 0..rays {
        let row = &mut edges[r * (bins + 1)..(r + 1) * (bins + 1)];
        if r % 7 == 3 {
            // Zero-width bins: runs of equal edges.
            for i in (1..bins).step_by(3) {
                row[i + 1] = row[i];
            }
        }
        let w: Vec<f32> = match r % 9 {
            0 => vec![0.0; bins],
            1 => vec![1e-30; bins],
            2 => {
                let mut w = vec![0.0; bins];
                w[rng.below(bins as u32) as usize] = 0.9;
                w
            }
            3 => vec![f32::MAX; bins],
            4 => (0..bins)
                .map(|i| match i % 5 {
                    0 => f32::NAN,
                    1 => -rng.next_f32(),
                    2 => 1e-40,
                    3 => f32::INFINITY,
                    _ => rng.next_f32(),
                })
                .collect(),
            // Peaked, as the weights of a trained coarse pass.
            5 => (0..bins).map(|_| rng.next_f32().powi(8)).collect(),
            _ => (0..bins).map(|_| rng.next_f32()).collect(),
        };
        weights.extend(w);
    }
    (edges, weights)
}

#[test]
fn sample_pdf_matches_cpu_within_ulps_of_the_bin_width() {
    let Some((context, sampling)) = setup() else {
        return;
    };
    let rays = 450;
    let bins = 63;
    let (edges, weights) = pdf_inputs(rays, bins, 7);
    let edges_buffer = storage_buffer(&context, "edges", &edges);
    let weights_buffer = storage_buffer(&context, "weights", &weights);
    let mut exact = 0;
    let mut total = 0;
    for count in [1, 128] {
        for padding in [0.0, 1e-5, 0.01] {
            for jitter in [None, Some(99)] {
                let gpu = run(&context, rays * count, |encoder, out| {
                    sampling.record_sample_pdf(
                        &context,
                        encoder,
                        &edges_buffer,
                        &weights_buffer,
                        rays,
                        bins,
                        padding,
                        count,
                        jitter,
                        out,
                    )
                });
                let mut cpu = vec![0.0; rays * count];
                sample_pdf(&edges, &weights, bins, padding, count, jitter, &mut cpu);
                for r in 0..rays {
                    let e = &edges[r * (bins + 1)..(r + 1) * (bins + 1)];
                    let widest = e.windows(2).map(|w| w[1] - w[0]).fold(0.0, f32::max);
                    let g = &gpu[r * count..(r + 1) * count];
                    let c = &cpu[r * count..(r + 1) * count];
                    assert!(
                        g.windows(2).all(|w| w[0] <= w[1]),
                        "ray {r}: gpu not sorted"
                    );
                    for k in 0..count {
                        assert!(
                            e[0] <= g[k] && g[k] <= e[bins],
                            "ray {r} sample {k}: gpu {} outside the edges",
                            g[k]
                        );
                        // Same bin; the fraction inside it differs by the
                        // division's 2.5 ulp (≤ 2.5 ε of the bin width), and
                        // lo + (hi − lo)·f may then round the other way (one
                        // ulp of the value): 4 ε · width + ε · |t|.
                        let tolerance = 4.0 * f32::EPSILON * widest + f32::EPSILON * c[k].abs();
                        assert!(
                            (g[k] - c[k]).abs() <= tolerance,
                            "ray {r} sample {k} (count {count}, padding {padding}, {jitter:?}): \
                             gpu {} cpu {}",
                            g[k],
                            c[k]
                        );
                        exact += (g[k] == c[k]) as usize;
                        total += 1;
                    }
                }
            }
        }
    }
    eprintln!("{exact} of {total} inverse-CDF samples bit-equal");
}

#[test]
fn merge_blur_and_intervals_match_cpu_bit_for_bit() {
    let Some((context, sampling)) = setup() else {
        return;
    };
    let rays = 333;
    let (na, nb) = (64, 128);
    let (near, far) = planes(rays, 11);
    let mut a = vec![0.0; rays * na];
    stratified(&near, &far, na, Some(1), &mut a);
    let (edges, weights) = pdf_inputs(rays, na - 1, 11);
    let mut b = vec![0.0; rays * nb];
    // Importance samples on the same rays (the edges of pdf_inputs are
    // another stratification of the same planes), with ties against `a`
    // where a ray's weights are degenerate.
    sample_pdf(&edges, &weights, na - 1, 1e-5, nb, Some(2), &mut b);
    let buffer = |label: &str, data: &[f32]| storage_buffer(&context, label, data);
    let (a_buffer, b_buffer) = (buffer("a", &a), buffer("b", &b));
    let gpu = run(&context, rays * (na + nb), |encoder, out| {
        sampling.record_merge_sorted(&context, encoder, &a_buffer, na, &b_buffer, nb, rays, out)
    });
    let mut merged = vec![0.0; rays * (na + nb)];
    merge_sorted(&a, na, &b, nb, &mut merged);
    assert_bits_equal(&gpu, &merged, "merge");

    let bins = na - 1;
    let finite: Vec<f32> = weights
        .iter()
        .map(|&w| if w.is_finite() { w } else { 0.5 })
        .collect();
    let weights_buffer = buffer("weights", &finite);
    let gpu = run(&context, rays * bins, |encoder, out| {
        sampling.record_blur_weights(&context, encoder, &weights_buffer, rays, bins, out)
    });
    let mut blurred = vec![0.0; rays * bins];
    blur_weights(&finite, bins, &mut blurred);
    assert_bits_equal(&gpu, &blurred, "blur");

    let n = na + nb;
    let (t_buffer, far_buffer) = (buffer("t", &merged), buffer("far", &far));
    let gpu = run(&context, rays * n, |encoder, out| {
        sampling.record_intervals_to_far(&context, encoder, &t_buffer, &far_buffer, rays, n, out)
    });
    let mut dt = vec![0.0; rays * n];
    intervals_to_far(&merged, &far, n, &mut dt);
    assert_bits_equal(&gpu, &dt, "intervals");
}
