//! The gpu sampling stages (and Mip-NeRF's frustums, at the end) against
//! the cpu engine on lavapipe. Stratified samples, merges, blurs and
//! intervals repeat the cpu's arithmetic with operations WGSL rounds
//! correctly (+, −, ×, min, max; fma prevented), so they must match bit for
//! bit, and with them the (seed, ray, index) uniforms. Inverse-CDF samples
//! pick their bin with those operations too; only the position inside the
//! bin involves a division, which WGSL allows to be 2.5 ulp off.

use zrak::engine::cpu::frustum::frustum_gaussians;
use zrak::engine::cpu::sampling::{
    blur_weights, intervals_to_far, merge_sorted, sample_pdf, stratified,
};
use zrak::engine::gpu::GpuContext;
use zrak::engine::gpu::frustum::{
    FrustumRays, FrustumSamples, Gaussians, GpuFrustums, MarchedIntervals,
};
use zrak::engine::gpu::kernel::{Recorder, read_buffer, storage_buffer, zeroed_storage_buffer};
use zrak::engine::gpu::sampling::{GpuSampling, Pdf, RayBounds, SortedRows};
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

/// Records `record` into a recorder, submits it, reads `count` floats of
/// the buffer it returns.
fn run(
    context: &GpuContext,
    count: usize,
    record: impl FnOnce(&mut Recorder, &wgpu::Buffer),
) -> Vec<f32> {
    let out = zeroed_storage_buffer::<f32>(context, "out", count);
    let mut rec = Recorder::new(context);
    record(&mut rec, &out);
    rec.submit();
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
    let _cores = crate::common::shared();
    let Some((context, sampling)) = setup() else {
        return;
    };
    let rays = 777;
    let (near, far) = planes(rays, 3);
    let near_buffer = storage_buffer(&context, "near", &near);
    let far_buffer = storage_buffer(&context, "far", &far);
    for n in [1, 2, 64, 129] {
        for jitter in [None, Some(0), Some(12345)] {
            let gpu = run(&context, rays * n, |rec, out| {
                sampling.record_stratified(
                    rec,
                    RayBounds {
                        near: &near_buffer,
                        far: &far_buffer,
                    },
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
    let _cores = crate::common::shared();
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
                let gpu = run(&context, rays * count, |rec, out| {
                    sampling.record_sample_pdf(
                        rec,
                        Pdf {
                            edges: &edges_buffer,
                            weights: &weights_buffer,
                            bins,
                            padding,
                        },
                        rays,
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
    let _cores = crate::common::shared();
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
    let gpu = run(&context, rays * (na + nb), |rec, out| {
        let a = SortedRows {
            values: &a_buffer,
            per_ray: na,
        };
        let b = SortedRows {
            values: &b_buffer,
            per_ray: nb,
        };
        sampling.record_merge_sorted(rec, a, b, rays, out)
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
    let gpu = run(&context, rays * bins, |rec, out| {
        sampling.record_blur_weights(rec, &weights_buffer, rays, bins, out)
    });
    let mut blurred = vec![0.0; rays * bins];
    blur_weights(&finite, bins, &mut blurred);
    assert_bits_equal(&gpu, &blurred, "blur");

    let n = na + nb;
    let (t_buffer, far_buffer) = (buffer("t", &merged), buffer("far", &far));
    let gpu = run(&context, rays * n, |rec, out| {
        sampling.record_intervals_to_far(rec, &t_buffer, &far_buffer, rays, n, out)
    });
    let mut dt = vec![0.0; rays * n];
    intervals_to_far(&merged, &far, n, &mut dt);
    assert_bits_equal(&gpu, &dt, "intervals");
}

// ---------------------------------------------------------------------------
// Mip-NeRF's frustums (engine::gpu::frustum against engine::cpu::frustum).
//
// Tolerance. The kernels repeat the cpu's f32 operations in the cpu's order
// with every product rounded before the sum it feeds, so only the divisions
// may round differently: WGSL allows 2.5 ulp, the cpu rounds exactly. A
// frustum's axial mean adds one quotient to t_μ; each variance is a sum of
// at most three terms, each with at most two chained divisions (≤ 5 ulp of
// the term), and the terms cancel by at most a factor 2.2 (the axial
// variance of a frustum from the apex, t_δ²/3 − (11/60) t_δ², the worst
// case of the formula); so each variance is within ~11 ulp (7e-7) of itself
// and the mean within ~3 ulp of |o| + |d|·t₁ (the origin's coordinate may
// cancel the distance). The asserts allow 4e-6 and 1e-6: 5× and ~6× those
// bounds, while a wrong constant, index or ray gives relative errors of
// 1e-2 and more. On lavapipe every value is bit-equal (printed).

/// Rays with every kind of cone: `rays` origins in [−4, 4]³, unit
/// directions, radii from 0 and 1e-8 (a pixel of an enormous image) to 1e2.
fn cone_rays(rays: usize, seed: u64) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
    let mut rng = Pcg32::new(seed, 3);
    let mut origins = Vec::with_capacity(3 * rays);
    let mut directions = Vec::with_capacity(3 * rays);
    while directions.len() < 3 * rays {
        let d: Vec<f32> = (0..3).map(|_| 2.0 * rng.next_f32() - 1.0).collect();
        let n = d.iter().map(|v| v * v).sum::<f32>().sqrt();
        if (0.1..=1.0).contains(&n) {
            directions.extend(d.iter().map(|v| v / n));
            origins.extend((0..3).map(|_| 8.0 * rng.next_f32() - 4.0));
        }
    }
    // An axis-aligned ray: one coordinate carries all of the axial variance.
    directions[..3].copy_from_slice(&[0.0, 0.0, -1.0]);
    let radii = (0..rays)
        .map(|r| match r % 5 {
            0 => 0.0,
            1 => 1e-8,
            2 => 1e2,
            _ => (-7.0 * rng.next_f32()).exp2() * 0.01,
        })
        .collect();
    (origins, directions, radii)
}

/// Each ray's `n` + 1 sorted edges: ordinary stratified spans, spans from
/// the apex (t₀ = 0), thin far ones, and repeated edges (t₀ = t₁).
fn frustum_edges(rays: usize, n: usize, seed: u64) -> Vec<f32> {
    let (mut near, mut far) = planes(rays, seed);
    for r in (0..rays).step_by(4) {
        near[r] = 0.0;
    }
    for r in (1..rays).step_by(6) {
        far[r] = near[r] * (1.0 + 1e-5);
    }
    let mut edges = vec![0.0; rays * (n + 1)];
    stratified(&near, &far, n + 1, Some(seed as u32), &mut edges);
    for r in (2..rays).step_by(5) {
        edges[r * (n + 1) + 2] = edges[r * (n + 1) + 1];
    }
    edges
}

/// `gpu` against `cpu` within `tolerance(i)` each; returns the count of
/// bit-equal values.
fn assert_close(gpu: &[f32], cpu: &[f32], tolerance: impl Fn(usize) -> f32, what: &str) -> usize {
    assert_eq!(gpu.len(), cpu.len(), "{what}: lengths");
    for (i, (&g, &c)) in gpu.iter().zip(cpu).enumerate() {
        assert!(
            g.is_finite() && (g - c).abs() <= tolerance(i),
            "{what}, value {i}: gpu {g} cpu {c}"
        );
    }
    gpu.iter().zip(cpu).filter(|(g, c)| g == c).count()
}

/// Means within 1e-6 of |o| + |d|·t₁ of their ray, variances within 4e-6 of
/// themselves (see the tolerance above); returns the bit-equal count.
fn check_gaussians(
    (gpu_means, gpu_variances): (&[f32], &[f32]),
    (cpu_means, cpu_variances): (&[f32], &[f32]),
    origins: &[f32],
    directions: &[f32],
    rays_of: &[u32],
    ends: &[f32],
    what: &str,
) -> usize {
    let scale = |i: usize| {
        let (s, c) = (i / 3, i % 3);
        let r = rays_of[s] as usize;
        origins[3 * r + c].abs() + directions[3 * r + c].abs() * ends[s]
    };
    assert_close(
        gpu_means,
        cpu_means,
        |i| 1e-6 * scale(i),
        &format!("{what} means"),
    ) + assert_close(
        gpu_variances,
        cpu_variances,
        |i| 4e-6 * cpu_variances[i] + f32::MIN_POSITIVE,
        &format!("{what} variances"),
    )
}

#[test]
fn frustums_between_edges_match_cpu() {
    let _cores = crate::common::shared();
    let Some((context, _)) = setup() else {
        return;
    };
    // 70 rays (a workgroup and a bit), 5 frustums each.
    let (rays, n) = (70, 5);
    let (origins, directions, radii) = cone_rays(rays, 21);
    let edges = frustum_edges(rays, n, 22);
    // The cpu model's fixed-count level: midpoints, lengths, Gaussians.
    let (mut starts, mut ends, mut rays_of) = (Vec::new(), Vec::new(), Vec::new());
    for (r, e) in edges.chunks(n + 1).enumerate() {
        for pair in e.windows(2) {
            starts.push(pair[0]);
            ends.push(pair[1]);
            rays_of.push(r as u32);
        }
    }
    let s = rays * n;
    let (mut means, mut variances) = (vec![0.0; 3 * s], vec![0.0; 3 * s]);
    frustum_gaussians(
        &origins,
        &directions,
        &radii,
        &rays_of,
        &starts,
        &ends,
        &mut means,
        &mut variances,
    );
    let mid: Vec<f32> = starts
        .iter()
        .zip(&ends)
        .map(|(a, b)| 0.5 * (a + b))
        .collect();
    let length: Vec<f32> = starts.iter().zip(&ends).map(|(a, b)| b - a).collect();
    let per_sample_directions: Vec<f32> = rays_of
        .iter()
        .flat_map(|&r| directions[3 * r as usize..][..3].to_vec())
        .collect();

    // Whole, and with the rays in two pieces (64 + 6) under a storage
    // binding limit of 64 rays' widest rows (3N floats): the same bits.
    let capped = {
        let mut c = GpuContext {
            adapter: context.adapter.clone(),
            device: context.device.clone(),
            queue: context.queue.clone(),
            info: context.info.clone(),
            features: context.features,
            limits: context.limits.clone(),
            counters: context.counters.clone(),
        };
        c.cap_storage_binding_size(64 * 4 * 3 * n as u64);
        c
    };
    let mut runs = Vec::new();
    for context in [&context, &capped] {
        let frustums = GpuFrustums::new(context).expect("the frustum kernels compile");
        let buffer = |label: &str, data: &[f32]| storage_buffer(context, label, data);
        let (o, d, r, e) = (
            buffer("origins", &origins),
            buffer("directions", &directions),
            buffer("radii", &radii),
            buffer("edges", &edges),
        );
        let out: Vec<wgpu::Buffer> = [1, 1, 3, 3, 3]
            .iter()
            .map(|w| zeroed_storage_buffer::<f32>(context, "frustum out", w * s))
            .collect();
        let mut rec = Recorder::new(context);
        frustums.record_edges(
            &mut rec,
            FrustumRays {
                origins: &o,
                directions: &d,
                radii: &r,
            },
            &e,
            rays,
            n,
            FrustumSamples {
                t: &out[0],
                dt: &out[1],
                means: &out[2],
                variances: &out[3],
                directions: &out[4],
            },
        );
        rec.submit();
        let read: Vec<Vec<f32>> = out
            .iter()
            .zip([1, 1, 3, 3, 3])
            .map(|(b, w)| read_buffer(context, b, w * s))
            .collect();
        runs.push(read);
    }
    assert!(runs[0] == runs[1], "the pieces differ from one binding");
    let gpu = &runs[0];
    assert_bits_equal(&gpu[0], &mid, "frustum midpoints");
    assert_bits_equal(&gpu[1], &length, "frustum lengths");
    assert_bits_equal(&gpu[4], &per_sample_directions, "frustum directions");
    let equal = check_gaussians(
        (&gpu[2], &gpu[3]),
        (&means, &variances),
        &origins,
        &directions,
        &rays_of,
        &ends,
        "between edges",
    );
    assert!(
        variances.iter().any(|&v| v > 1e3) && variances.contains(&0.0),
        "the inputs cover wide cones and points"
    );
    eprintln!("{equal} of {} means and variances bit-equal", 6 * s);
}

#[test]
fn frustums_of_marched_steps_match_cpu() {
    let _cores = crate::common::shared();
    let Some((context, _)) = setup() else {
        return;
    };
    let rays = 70;
    let (origins, directions, radii) = cone_rays(rays, 31);
    // 0 to 6 samples a ray (rays without samples, as the march leaves
    // them), consecutive steps of varied length; the first ray's first step
    // starts behind the origin (t < dt/2), which clamps to the apex.
    let mut rng = Pcg32::new(32, 1);
    let (mut offsets, mut t, mut dt) = (vec![0u32], Vec::new(), Vec::new());
    for r in 0..rays {
        let mut at = if r == 0 { 1e-3 } else { 4.0 * rng.next_f32() };
        let count = if r == 0 { 3 } else { rng.below(7) };
        for _ in 0..count {
            let step = if r == 0 {
                0.02
            } else {
                [1.7e-3, 0.02, 0.3][rng.below(3) as usize]
            };
            t.push(at);
            dt.push(step);
            at += step;
        }
        offsets.push(t.len() as u32);
    }
    let s = t.len();
    let starts: Vec<f32> = t
        .iter()
        .zip(&dt)
        .map(|(t, d)| (t - 0.5 * d).max(0.0))
        .collect();
    let ends: Vec<f32> = t.iter().zip(&dt).map(|(t, d)| t + 0.5 * d).collect();
    let rays_of: Vec<u32> = (0..rays as u32)
        .flat_map(|r| {
            std::iter::repeat_n(r, (offsets[r as usize + 1] - offsets[r as usize]) as usize)
        })
        .collect();
    let (mut means, mut variances) = (vec![0.0; 3 * s], vec![0.0; 3 * s]);
    frustum_gaussians(
        &origins,
        &directions,
        &radii,
        &rays_of,
        &starts,
        &ends,
        &mut means,
        &mut variances,
    );

    let frustums = GpuFrustums::new(&context).expect("the frustum kernels compile");
    let buffer = |label: &str, data: &[f32]| storage_buffer(&context, label, data);
    let (o, d, r) = (
        buffer("origins", &origins),
        buffer("directions", &directions),
        buffer("radii", &radii),
    );
    let offsets_buffer = storage_buffer(&context, "offsets", &offsets);
    let (t_buffer, dt_buffer) = (buffer("t", &t), buffer("dt", &dt));
    let means_out = zeroed_storage_buffer::<f32>(&context, "means", 3 * s);
    let variances_out = zeroed_storage_buffer::<f32>(&context, "variances", 3 * s);
    let mut rec = Recorder::new(&context);
    frustums.record_marched(
        &mut rec,
        FrustumRays {
            origins: &o,
            directions: &d,
            radii: &r,
        },
        MarchedIntervals {
            ray_offsets: &offsets_buffer,
            t: &t_buffer,
            dt: &dt_buffer,
            samples: s,
        },
        rays,
        Gaussians {
            means: &means_out,
            variances: &variances_out,
        },
    );
    rec.submit();
    let equal = check_gaussians(
        (
            &read_buffer(&context, &means_out, 3 * s),
            &read_buffer(&context, &variances_out, 3 * s),
        ),
        (&means, &variances),
        &origins,
        &directions,
        &rays_of,
        &ends,
        "of marched steps",
    );
    assert!(starts[0] == 0.0 && s > 100, "{s} samples");
    eprintln!("{equal} of {} means and variances bit-equal", 6 * s);
}
