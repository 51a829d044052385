//! The gpu compositing and loss kernels against the cpu engine on lavapipe.

// Loops index several parallel arrays (per ray, per sample) at once.
#![allow(clippy::needless_range_loop)]

use zrak::engine::cpu::composite_batch::{
    CompositeGradients, CompositeOutputs, composite_backward, composite_forward,
};
use zrak::engine::cpu::loss::loss_and_gradient;
use zrak::engine::gpu::GpuContext;
use zrak::engine::gpu::composite::{
    CompositeGradientBuffers, CompositeOutputBuffers, GpuComposite, RayBatchBuffers,
};
use zrak::engine::gpu::kernel::{Recorder, read_buffer, storage_buffer, zeroed_storage_buffer};
use zrak::engine::gpu::loss::{GpuLoss, LossBuffers};
use zrak::engine::shared::composite::{Distortion, RayBatch};
use zrak::field::common::{LossKind, MarchConfig};
use zrak::rng::Pcg32;

const CUT: f32 = MarchConfig::PAPER.min_transmittance;

/// An owned batch of rays.
struct Batch {
    density: Vec<f32>,
    rgb: Vec<f32>,
    dt: Vec<f32>,
    t: Vec<f32>,
    ray_offsets: Vec<u32>,
    background: Vec<f32>,
}

impl Batch {
    /// `rays` rays of 0..=120 samples (every 23rd empty), densities from
    /// nearly empty (τ ~ 1e-7, where 1 − e^{−τ} needs care in f32) to
    /// opaque in one sample, step lengths around the Blender scenes' world
    /// step (√3/1024 in the unit cube, ×3 for scale 0.33).
    fn random(rays: usize, seed: u64) -> Self {
        let mut rng = Pcg32::new(seed, 3);
        let scales = [1e-5f32, 0.3, 5.0, 60.0, 600.0, 3e4];
        let mut batch = Batch {
            density: Vec::new(),
            rgb: Vec::new(),
            dt: Vec::new(),
            t: Vec::new(),
            ray_offsets: vec![0],
            background: Vec::new(),
        };
        for ray in 0..rays {
            let count = if ray % 23 == 0 {
                0
            } else {
                rng.below(121) as usize
            };
            let scale = scales[ray % scales.len()];
            let mut far = 2.0f32;
            for _ in 0..count {
                let dt = 0.002 + 0.01 * rng.next_f32();
                batch.dt.push(dt);
                batch.t.push(far + 0.5 * dt);
                far += dt;
                batch.density.push(scale * rng.next_f32());
                batch
                    .rgb
                    .extend([rng.next_f32(), rng.next_f32(), rng.next_f32()]);
            }
            batch.ray_offsets.push(batch.density.len() as u32);
            batch
                .background
                .extend([rng.next_f32(), rng.next_f32(), rng.next_f32()]);
        }
        batch
    }

    fn view(&self) -> RayBatch<'_, f32> {
        RayBatch {
            density: &self.density,
            rgb: &self.rgb,
            dt: &self.dt,
            t: &self.t,
            ray_offsets: &self.ray_offsets,
            background: &self.background,
        }
    }

    fn rays(&self) -> usize {
        self.ray_offsets.len() - 1
    }

    fn samples(&self, ray: usize) -> std::ops::Range<usize> {
        self.ray_offsets[ray] as usize..self.ray_offsets[ray + 1] as usize
    }

    /// Rays whose cut is decided by a transmittance within 1e-4 (relative)
    /// of the threshold: f32 exp on two engines may legitimately put the
    /// cut one sample apart there. Found in f64.
    fn cut_is_ambiguous(&self, ray: usize) -> bool {
        let mut accumulated = 0f64;
        for s in self.samples(ray) {
            let transmittance = (-accumulated).exp();
            if ((transmittance - CUT as f64) / CUT as f64).abs() < 1e-4 {
                return true;
            }
            if transmittance < CUT as f64 {
                return false;
            }
            accumulated += (self.density[s] as f64 * self.dt[s] as f64).max(0.0);
        }
        false
    }

    /// Per sample, the size of the terms ∂L/∂σ is a difference of:
    /// δₖ (Tₖ₊₁ |gₖ| + Σ_{i>k} wᵢ |gᵢ| + T_cut |∂L/∂rgb · bg|), in f64 on
    /// the samples before the cut.
    fn density_gradient_scale(&self, d_rgb: &[f32], used: &[u32]) -> Vec<f64> {
        self.density_gradient_scale_with(d_rgb, used, None)
    }

    /// As [`Self::density_gradient_scale`], with |gₖ| grown by the size of
    /// the distortion loss's terms, λ′ (2 (sₖ W + S) + ⅔ wₖ δₖ) (W and S
    /// the ray's sums of wᵢ and wᵢ sᵢ).
    fn density_gradient_scale_with(
        &self,
        d_rgb: &[f32],
        used: &[u32],
        distortion: Option<Distortion<f32>>,
    ) -> Vec<f64> {
        let mut scale = vec![0f64; self.density.len()];
        for ray in 0..self.rays() {
            let samples = self.samples(ray);
            let n = used[ray] as usize;
            let grad: Vec<f64> = (0..3).map(|c| d_rgb[3 * ray + c] as f64).collect();
            let mut transmittance = vec![1f64; n + 1];
            let mut accumulated = 0f64;
            for k in 0..n {
                let s = samples.start + k;
                transmittance[k] = (-accumulated).exp();
                accumulated += (self.density[s] as f64 * self.dt[s] as f64).max(0.0);
            }
            transmittance[n] = (-accumulated).exp();
            let bg: f64 = (0..3)
                .map(|c| grad[c] * self.background[3 * ray + c] as f64)
                .sum();
            let mut behind = transmittance[n] * bg.abs();
            let weight = |k: usize| transmittance[k] - transmittance[k + 1];
            let (weight_sum, moment_sum) = distortion.map_or((0.0, 0.0), |d| {
                (0..n).fold((0.0, 0.0), |(w, m), k| {
                    let distance = self.t[samples.start + k] as f64 * d.distance_scale as f64;
                    (w + weight(k), m + weight(k) * distance)
                })
            });
            for k in (0..n).rev() {
                let s = samples.start + k;
                let mut g: f64 = (0..3)
                    .map(|c| grad[c] * self.rgb[3 * s + c] as f64)
                    .sum::<f64>()
                    .abs();
                if let Some(d) = distortion {
                    let scale = d.distance_scale as f64;
                    let distance = self.t[s] as f64 * scale;
                    g += d.weight_per_ray as f64
                        * (2.0 * (distance * weight_sum + moment_sum)
                            + 2.0 / 3.0 * weight(k) * self.dt[s] as f64 * scale);
                }
                scale[s] = self.dt[s] as f64 * (transmittance[k + 1] * g + behind);
                behind += (transmittance[k] - transmittance[k + 1]) * g;
            }
        }
        scale
    }
}

struct CpuForward {
    rgb: Vec<f32>,
    opacity: Vec<f32>,
    depth: Vec<f32>,
    used: Vec<u32>,
}

fn cpu_forward(batch: &Batch) -> CpuForward {
    let rays = batch.rays();
    let mut out = CpuForward {
        rgb: vec![0.0; 3 * rays],
        opacity: vec![0.0; rays],
        depth: vec![0.0; rays],
        used: vec![0; rays],
    };
    composite_forward(
        &batch.view(),
        CUT,
        CompositeOutputs {
            rgb: &mut out.rgb,
            opacity: &mut out.opacity,
            depth: &mut out.depth,
            samples_used: &mut out.used,
        },
    );
    out
}

fn cpu_backward(batch: &Batch, d_rgb: &[f32]) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
    cpu_backward_with(batch, d_rgb, None)
}

fn cpu_backward_with(
    batch: &Batch,
    d_rgb: &[f32],
    distortion: Option<Distortion<f32>>,
) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
    let n = batch.density.len();
    let (mut density, mut rgb, mut background) =
        (vec![0.0; n], vec![0.0; 3 * n], vec![0.0; 3 * batch.rays()]);
    composite_backward(
        &batch.view(),
        CUT,
        d_rgb,
        distortion,
        CompositeGradients {
            density: &mut density,
            rgb: &mut rgb,
            background: Some(&mut background),
        },
    );
    (density, rgb, background)
}

/// Error bounds, from the accuracy WGSL promises: exp is within 3 + 2|x|
/// ulp, so Tᵢ = exp(−Σ τ) with Σ τ ≤ ln 1e4 ≈ 9.2 (the cut) is within
/// ~21 ulp ≈ 2.5e-6 relative, and 1 − e^{−τ} (series below τ = 0.25,
/// 1 − exp(−τ) above, which magnifies exp's error by at most 4.5) within
/// ~2e-6. Every forward output and every ∂L/∂c is a sum of non-negative
/// products of these, so relative errors of ~5e-6 plus summation rounding
/// (~120 terms · 6e-8): well inside 1e-4 relative. Opacity 1 − T_N is
/// computed from T_N ≈ 1 for nearly empty rays on both engines, which
/// leaves only an absolute accuracy of a few ulp of 1; hence the 1e-6
/// absolute floor.
fn close(gpu: f32, cpu: f32, floor: f64) -> bool {
    let (gpu, cpu) = (gpu as f64, cpu as f64);
    (gpu - cpu).abs() <= 1e-4 * cpu.abs() + floor
}

fn d_rgb_for(rays: usize, seed: u64) -> Vec<f32> {
    let mut rng = Pcg32::new(seed, 9);
    (0..3 * rays).map(|_| 2.0 * rng.next_f32() - 1.0).collect()
}

#[test]
fn compositing_matches_cpu() {
    let _cores = crate::common::shared();
    let context = GpuContext::new().expect("CI installs mesa-vulkan-drivers, so an adapter exists");
    let composite = GpuComposite::new(&context).expect("the kernels compile");
    let batch = Batch::random(3000, 1);
    let rays = batch.rays();
    eprintln!("{} rays, {} samples", rays, batch.density.len());

    let cpu = cpu_forward(&batch);
    let start = std::time::Instant::now();
    let gpu = composite.forward(&context, &batch.view(), CUT);
    eprintln!(
        "gpu forward (with upload and read-back): {:?}",
        start.elapsed()
    );

    let ambiguous: Vec<bool> = (0..rays).map(|r| batch.cut_is_ambiguous(r)).collect();
    let cut_rays = (0..rays)
        .filter(|&r| (cpu.used[r] as usize) < batch.samples(r).len())
        .count();
    let empty_rays = (0..rays).filter(|&r| batch.samples(r).is_empty()).count();
    assert!(
        cut_rays > 500 && empty_rays > 100,
        "cut {cut_rays}, empty {empty_rays}"
    );
    assert!(ambiguous.iter().filter(|&&a| a).count() < rays / 100);

    let mut worst = 0f64;
    let mut track = |gpu: f32, cpu: f32| {
        worst = worst.max((gpu as f64 - cpu as f64).abs() / (cpu as f64).abs().max(1e-3));
    };
    for ray in 0..rays {
        if ambiguous[ray] {
            continue;
        }
        track(gpu.rgb[3 * ray], cpu.rgb[3 * ray]);
        track(gpu.depth[ray], cpu.depth[ray]);
        assert_eq!(gpu.samples_used[ray], cpu.used[ray], "ray {ray}");
        for c in 0..3 {
            let i = 3 * ray + c;
            assert!(
                close(gpu.rgb[i], cpu.rgb[i], 1e-7),
                "ray {ray} colour: gpu {} cpu {}",
                gpu.rgb[i],
                cpu.rgb[i]
            );
        }
        assert!(
            close(gpu.opacity[ray], cpu.opacity[ray], 1e-6),
            "ray {ray} opacity: gpu {} cpu {}",
            gpu.opacity[ray],
            cpu.opacity[ray]
        );
        assert!(
            close(gpu.depth[ray], cpu.depth[ray], 1e-7),
            "ray {ray} depth: gpu {} cpu {}",
            gpu.depth[ray],
            cpu.depth[ray]
        );
    }

    eprintln!("worst forward error (relative, floor 1e-3): {worst:e}");
    let d_rgb = d_rgb_for(rays, 2);
    let (cpu_density, cpu_colour, cpu_background) = cpu_backward(&batch, &d_rgb);
    let start = std::time::Instant::now();
    let grads = composite.backward(&context, &batch.view(), CUT, &d_rgb, None);
    eprintln!(
        "gpu backward (with upload and read-back): {:?}",
        start.elapsed()
    );
    let scale = batch.density_gradient_scale(&d_rgb, &cpu.used);
    let (mut worst_density, mut worst_colour) = (0f64, 0f64);
    for ray in 0..rays {
        if ambiguous[ray] {
            continue;
        }
        for s in batch.samples(ray) {
            // ∂L/∂σ is a difference; its error is relative to the size of
            // the terms (see density_gradient_scale), not to the result.
            let error = (grads.density[s] as f64 - cpu_density[s] as f64).abs();
            worst_density = worst_density.max(error / scale[s].max(1e-12));
            worst_colour = worst_colour.max(
                (grads.rgb[3 * s] as f64 - cpu_colour[3 * s] as f64).abs()
                    / (cpu_colour[3 * s].abs() as f64).max(1e-12),
            );
            assert!(
                error <= 1e-4 * scale[s] + 1e-12,
                "ray {ray} sample {s}: ∂σ gpu {} cpu {} (terms {:e})",
                grads.density[s],
                cpu_density[s],
                scale[s]
            );
            for c in 0..3 {
                let i = 3 * s + c;
                assert!(
                    close(grads.rgb[i], cpu_colour[i], 1e-12),
                    "ray {ray} sample {s}: ∂c gpu {} cpu {}",
                    grads.rgb[i],
                    cpu_colour[i]
                );
            }
            if s - batch.samples(ray).start >= cpu.used[ray] as usize {
                assert_eq!(
                    (grads.density[s], &grads.rgb[3 * s..3 * s + 3]),
                    (0.0, &[0.0f32; 3][..])
                );
            }
        }
        for c in 0..3 {
            let i = 3 * ray + c;
            assert!(close(grads.background[i], cpu_background[i], 1e-12));
        }
    }
    eprintln!(
        "worst ∂σ error relative to its terms: {worst_density:e}; worst ∂c error: {worst_colour:e}"
    );
}

#[test]
fn backward_with_the_distortion_loss_matches_cpu() {
    let _cores = crate::common::shared();
    let context = GpuContext::new().expect("an adapter exists");
    let composite = GpuComposite::new(&context).expect("the kernels compile");
    let batch = Batch::random(2000, 5);
    let rays = batch.rays();
    let cpu = cpu_forward(&batch);
    let ambiguous: Vec<bool> = (0..rays).map(|r| batch.cut_is_ambiguous(r)).collect();
    // Distances 2…3.5 become s ≈ 0.6…1; λ′ = 0.5 makes the distortion
    // terms as large as the colour's (d_rgb in [−1, 1]).
    let distortion = Some(Distortion {
        weight_per_ray: 0.5,
        distance_scale: 0.3,
    });
    let d_rgb = d_rgb_for(rays, 6);
    let (cpu_density, cpu_colour, _) = cpu_backward_with(&batch, &d_rgb, distortion);
    let (plain_density, _, _) = cpu_backward(&batch, &d_rgb);
    let grads = composite.backward(&context, &batch.view(), CUT, &d_rgb, distortion);
    // The error bound of `compositing_matches_cpu`, on terms grown by the
    // distortion's; the moments S_<k are differences of sums of at most
    // ~120 terms ≤ 1, a few ulp of S each: inside the same 1e-4.
    let scale = batch.density_gradient_scale_with(&d_rgb, &cpu.used, distortion);
    let mut changed = 0;
    for ray in (0..rays).filter(|&r| !ambiguous[r]) {
        for s in batch.samples(ray) {
            let error = (grads.density[s] as f64 - cpu_density[s] as f64).abs();
            assert!(
                error <= 1e-4 * scale[s] + 1e-12,
                "ray {ray} sample {s}: ∂σ gpu {} cpu {} (terms {:e})",
                grads.density[s],
                cpu_density[s],
                scale[s]
            );
            // The loss on the weights leaves ∂L/∂c alone.
            for i in 3 * s..3 * s + 3 {
                assert!(close(grads.rgb[i], cpu_colour[i], 1e-12));
            }
            let shift = (cpu_density[s] as f64 - plain_density[s] as f64).abs();
            changed += usize::from(shift > 1e-2 * scale[s] && shift > 1e-9);
        }
    }
    // The distortion must move many gradients of the samples before the
    // cuts by 100 times the tolerance, or a kernel that ignored it would
    // pass (14 % of them here; the bound's terms are sums of absolute
    // values, so most shifts are smaller than that against them).
    let used: usize = cpu.used.iter().map(|&n| n as usize).sum();
    assert!(changed > used / 10, "{changed} of {used} gradients changed");
}

#[test]
fn loss_matches_cpu() {
    let _cores = crate::common::shared();
    let context = GpuContext::new().expect("an adapter exists");
    let loss = GpuLoss::new(&context).expect("the kernels compile");
    let rays = 5000;
    let mut rng = Pcg32::new(4, 1);
    let target: Vec<f32> = (0..3 * rays).map(|_| rng.next_f32()).collect();
    // Differences in both Huber zones.
    let predicted: Vec<f32> = target
        .iter()
        .map(|&t| t + 0.6 * (rng.next_f32() - 0.5))
        .collect();
    for kind in [LossKind::Huber, LossKind::L2] {
        let mut cpu_gradient = vec![0f32; 3 * rays];
        let cpu_value = loss_and_gradient(kind, &predicted, &target, &mut cpu_gradient);
        let (gpu_value, gpu_gradient) = loss.loss_and_gradient(&context, kind, &predicted, &target);
        // The gradient: one subtraction (exact alike), one division by δ
        // (WGSL: 2.5 ulp) and one scaling, so within ~5 ulp ≈ 3e-7.
        for i in 0..3 * rays {
            let (g, c) = (gpu_gradient[i] as f64, cpu_gradient[i] as f64);
            assert!(
                (g - c).abs() <= 1e-6 * c.abs() + 1e-12,
                "{kind:?} {i}: gpu {g} cpu {c}"
            );
        }
        // The value: f32 sums of ~20 terms per invocation and an 8-level
        // tree on the gpu against f64 on the cpu: (20 + 8 + 5) ε ≈ 2e-6.
        assert!(
            ((gpu_value as f64 - cpu_value) / cpu_value).abs() < 1e-5,
            "{kind:?}: gpu {gpu_value} cpu {cpu_value}"
        );
    }
    let (empty, _) = loss.loss_and_gradient(&context, LossKind::Huber, &[], &[]);
    assert_eq!(empty, 0.0);
}

#[test]
fn forward_loss_backward_chain_in_one_submission() {
    let _cores = crate::common::shared();
    // The training step's order, recorded into one encoder: composite,
    // loss on the composited colours, composite backward from the loss
    // gradient. Against the same chain on the cpu.
    let context = GpuContext::new().expect("an adapter exists");
    let composite = GpuComposite::new(&context).expect("the kernels compile");
    let loss = GpuLoss::new(&context).expect("the kernels compile");
    let batch = Batch::random(1000, 7);
    let rays = batch.rays();
    let samples = batch.density.len();
    let mut rng = Pcg32::new(8, 2);
    let target: Vec<f32> = (0..3 * rays).map(|_| rng.next_f32()).collect();

    let upload = |label: &str, data: &[f32]| storage_buffer(&context, label, data);
    let (density, rgb, dt, t, background) = (
        upload("density", &batch.density),
        upload("rgb", &batch.rgb),
        upload("dt", &batch.dt),
        upload("t", &batch.t),
        upload("background", &batch.background),
    );
    let ray_offsets = storage_buffer(&context, "ray offsets", &batch.ray_offsets);
    let target_buffer = upload("target", &target);
    let zeroed = |label: &str, n: usize| zeroed_storage_buffer::<f32>(&context, label, n);
    let (out_rgb, opacity, depth) = (
        zeroed("out rgb", 3 * rays),
        zeroed("opacity", rays),
        zeroed("depth", rays),
    );
    let used = zeroed_storage_buffer::<u32>(&context, "used", rays);
    let (d_rgb, ray_loss, total) = (
        zeroed("d_rgb", 3 * rays),
        zeroed("ray loss", rays),
        zeroed("total", 1),
    );
    let (d_density, d_colour, d_background) = (
        zeroed("d_density", samples),
        zeroed("d_colour", 3 * samples),
        zeroed("d_background", 3 * rays),
    );
    let buffers = RayBatchBuffers {
        density: &density,
        rgb: &rgb,
        dt: &dt,
        t: &t,
        ray_offsets: &ray_offsets,
        background: &background,
        ray_count: rays,
    };
    let mut rec = Recorder::new(&context);
    composite.record_forward(
        &mut rec,
        &buffers,
        CUT,
        &CompositeOutputBuffers {
            rgb: &out_rgb,
            opacity: &opacity,
            depth: &depth,
            samples_used: &used,
        },
    );
    loss.record(
        &mut rec,
        LossKind::Huber,
        &LossBuffers {
            predicted: &out_rgb,
            target: &target_buffer,
            gradient: &d_rgb,
            ray_loss: &ray_loss,
            total: &total,
            ray_count: rays,
        },
    );
    composite.record_backward(
        &mut rec,
        &buffers,
        CUT,
        &d_rgb,
        None,
        &CompositeGradientBuffers {
            density: &d_density,
            rgb: &d_colour,
            background: &d_background,
        },
    );
    rec.submit();
    let gpu_rgb: Vec<f32> = read_buffer(&context, &out_rgb, 3 * rays);
    let gpu_d_rgb: Vec<f32> = read_buffer(&context, &d_rgb, 3 * rays);
    let gpu_loss = read_buffer::<f32>(&context, &total, 1)[0];
    let gpu_d_colour: Vec<f32> = read_buffer(&context, &d_colour, 3 * samples);
    let gpu_d_density: Vec<f32> = read_buffer(&context, &d_density, samples);

    // Each link against the cpu given the gpu's input to that link, so
    // the bounds are those of the stand-alone tests above (the chain
    // checks the wiring: every buffer read where it was written).
    let cpu = cpu_forward(&batch);
    for i in 0..3 * rays {
        if !batch.cut_is_ambiguous(i / 3) {
            assert!(close(gpu_rgb[i], cpu.rgb[i], 1e-7), "colour {i}");
        }
    }
    let mut cpu_d_rgb = vec![0f32; 3 * rays];
    let cpu_loss = loss_and_gradient(LossKind::Huber, &gpu_rgb, &target, &mut cpu_d_rgb);
    assert!(
        ((gpu_loss as f64 - cpu_loss) / cpu_loss).abs() < 1e-5,
        "gpu {gpu_loss} cpu {cpu_loss}"
    );
    for i in 0..3 * rays {
        assert!(
            ((gpu_d_rgb[i] - cpu_d_rgb[i]) as f64).abs()
                <= 1e-6 * cpu_d_rgb[i].abs() as f64 + 1e-12
        );
    }
    let (cpu_d_density, cpu_d_colour, _) = cpu_backward(&batch, &gpu_d_rgb);
    let scale = batch.density_gradient_scale(&gpu_d_rgb, &cpu.used);
    let mut compared = 0;
    for ray in 0..rays {
        if batch.cut_is_ambiguous(ray) {
            continue;
        }
        for s in batch.samples(ray) {
            compared += 1;
            let error = (gpu_d_density[s] as f64 - cpu_d_density[s] as f64).abs();
            assert!(error <= 1e-4 * scale[s] + 1e-12, "sample {s}");
            for c in 0..3 {
                let i = 3 * s + c;
                assert!(close(gpu_d_colour[i], cpu_d_colour[i], 1e-12), "sample {s}");
            }
        }
    }
    assert!(compared > samples / 2);
}
