//! The proposal sampler on the gpu engine (lavapipe) against the cpu
//! engine: each new kernel against its cpu twin (the spacing coordinate,
//! the contraction of the fields' inputs, the interlevel and distortion
//! losses' gradients and their way to the densities), then one whole step
//! of Instant-NGP and of NeRF with proposals on the unbounded demo: the
//! same samples per level, losses and gradients.
//!
//! Tolerances. The spacing and the contraction repeat the cpu's f32
//! operations; WGSL's division and square root may round differently (2.5
//! ulp), so they agree to a few ulps (4 ε relative; 1e-6 for the
//! contraction, whose two divisions and a square root compound). The weight
//! losses sum in f32 where the cpu sums in f64: over ≤ 64 intervals of
//! weights ≤ 1 that is ~64 ε ≈ 1e-5 of the sums, so 1e-4 relative (of the
//! largest entry) holds with room and a wrong overlap, sign or scale is off
//! by O(1). A step chains these with the stages whose parity the other
//! *_gpu.rs tests hold to ~1e-6 (sampling bit-equal, the hash grids'
//! and networks' f32 sums in another order), and the resampled edges move
//! continuously with the proposal weights they are drawn from; as in
//! tests/it/nerf_gpu.rs, ~1e-5 of each quantity, asserted at 1e-4.

use std::sync::Arc;

use glam::Vec3;
use zrak::engine::build_gpu;
use zrak::engine::cpu::model::CpuModel;
use zrak::engine::cpu::weight_losses::{self, Intervals};
use zrak::engine::gpu::model::GpuModel;
use zrak::engine::gpu::proposal::{ContractedInputs, GpuProposal};
use zrak::engine::request::ModelRequest;
use zrak::field::ModelKind;
use zrak::field::common::{LossKind, Sampling};
use zrak::field::contraction::{Contraction, ContractionNorm};
use zrak::model::RadianceModel;
use zrak::scene::Scene;
use zrak::scene::demo::{DemoConfig, build_unbounded};

use crate::common::{NerfKind, batch, gpu_context, relative, relative_norm, request};

/// A reproducible uniform in [0, 1) for key `i`.
fn uniform(i: u64) -> f32 {
    (zrak::rng::splitmix64(i ^ 0x5eed) >> 40) as f32 / (1u64 << 24) as f32
}

fn frame(norm: ContractionNorm) -> Contraction {
    Contraction {
        centre: Vec3::new(0.3, -0.2, 0.1),
        radius: 2.5,
        norm,
    }
}

#[test]
fn spacing_and_contraction_match_the_cpu_gpu() {
    let _cores = crate::common::shared();
    let context = gpu_context();
    let kernels = GpuProposal::new(&context).expect("proposal kernels");
    for norm in [ContractionNorm::L2, ContractionNorm::LInf] {
        let c = frame(norm);
        // Distances over six octaves, inside the unit ball and far beyond.
        let t: Vec<f32> = (0..500)
            .map(|i| c.radius * 10f32.powf(6.0 * uniform(i) - 3.0))
            .collect();
        let s = kernels.spacing_once(&context, &c, &t, false);
        let back = kernels.spacing_once(&context, &c, &s, true);
        for ((&t, &s), &back) in t.iter().zip(&s).zip(&back) {
            let expected = c.spacing_of(t);
            assert!(
                (s - expected).abs() <= 4.0 * f32::EPSILON * expected,
                "{norm:?}: s({t}) = {s}, cpu {expected}"
            );
            let expected = c.distance_of(s);
            assert!(
                (back - expected).abs() <= 4.0 * f32::EPSILON * expected,
                "{norm:?}: t({s}) = {back}, cpu {expected}"
            );
        }
        let points: Vec<Vec3> = (0..500u64)
            .map(|i| {
                let direction =
                    Vec3::new(uniform(3 * i), uniform(3 * i + 1), uniform(3 * i + 2)) - 0.5;
                c.centre + direction.normalize() * c.radius * 10f32.powf(3.0 * uniform(i) - 1.0)
            })
            .collect();
        let flat: Vec<f32> = points.iter().flat_map(|p| p.to_array()).collect();
        for inputs in [ContractedInputs::Contracted, ContractedInputs::UnitCube] {
            let gpu = kernels.contract_once(&context, &c, inputs, &flat);
            for (p, g) in points.iter().zip(gpu.chunks_exact(3)) {
                let expected = match inputs {
                    ContractedInputs::Contracted => c.contract_world(*p),
                    ContractedInputs::UnitCube => c.to_unit_cube(*p),
                };
                assert!(
                    (Vec3::from_slice(g) - expected).abs().max_element() <= 1e-6 * 2.0,
                    "{norm:?} {inputs:?} at {p}: {g:?} vs {expected}"
                );
            }
        }
    }
}

/// Each ray's sorted edges (distances) and weights: `n` intervals from
/// near 0.1 to far ~1000 radii, weights of a random profile.
fn intervals(rays: usize, n: usize, key: u64) -> (Vec<f32>, Vec<f32>) {
    let mut edges = Vec::new();
    let mut weights = Vec::new();
    for r in 0..rays {
        let mut t = 0.1f32;
        for i in 0..=n {
            edges.push(t);
            t *= 1.0 + 0.4 * uniform(key + (r * 1000 + i) as u64);
        }
        let raw: Vec<f32> = (0..n)
            .map(|i| uniform(key + 7 + (r * 1000 + i) as u64).powi(3))
            .collect();
        let total: f32 = raw.iter().sum::<f32>().max(1e-6);
        weights.extend(raw.iter().map(|w| w / total * 0.9));
    }
    (edges, weights)
}

fn assert_close(label: &str, gpu: &[f32], cpu: &[f32]) {
    assert_eq!(gpu.len(), cpu.len(), "{label}");
    let largest = cpu.iter().fold(0f32, |m, x| m.max(x.abs()));
    assert!(largest > 0.0, "{label}: all zero");
    for (i, (g, c)) in gpu.iter().zip(cpu).enumerate() {
        assert!(
            (g - c).abs() <= 1e-4 * largest,
            "{label} [{i}]: gpu {g}, cpu {c} (largest {largest})"
        );
    }
}

#[test]
fn weight_losses_and_their_density_gradients_match_the_cpu_gpu() {
    let _cores = crate::common::shared();
    let context = gpu_context();
    let kernels = GpuProposal::new(&context).expect("proposal kernels");
    let c = frame(ContractionNorm::LInf);
    let rays = 5;
    let (fine_edges, fine_weights) = intervals(rays, 24, 1);
    let (edges, weights) = intervals(rays, 40, 2);
    let in_s = |edges: &[f32]| edges.iter().map(|&t| c.spacing_of(t)).collect::<Vec<_>>();
    let (fine_s, s) = (in_s(&fine_edges), in_s(&edges));

    // The interlevel loss of coarse proposals against the fine weights.
    let scale = 0.25;
    let mut cpu_gradient = vec![0f32; weights.len()];
    let cpu_loss = weight_losses::interlevel(
        Intervals {
            edges: &fine_s,
            weights: &fine_weights,
        },
        Intervals {
            edges: &s,
            weights: &weights,
        },
        rays,
        scale,
        &mut cpu_gradient,
    );
    let (ray_loss, gpu_gradient) = kernels.interlevel_once(
        &context,
        &c,
        (&fine_edges, &fine_weights),
        (&edges, &weights),
        rays,
        scale,
    );
    let gpu_loss: f64 = ray_loss.iter().map(|&l| l as f64).sum();
    assert!(cpu_loss > 0.0, "no excess to test");
    assert!(
        relative(gpu_loss as f32, cpu_loss as f32) < 1e-4,
        "interlevel loss: gpu {gpu_loss}, cpu {cpu_loss}"
    );
    assert_close("interlevel gradient", &gpu_gradient, &cpu_gradient);

    // The distortion loss's gradient on the fine weights.
    let mut cpu_gradient = vec![0f32; fine_weights.len()];
    weight_losses::distortion(
        Intervals {
            edges: &fine_s,
            weights: &fine_weights,
        },
        rays,
        scale,
        &mut cpu_gradient,
    );
    let gpu_gradient =
        kernels.distortion_once(&context, &c, (&fine_edges, &fine_weights), rays, scale);
    assert_close("distortion gradient", &gpu_gradient, &cpu_gradient);

    // Through the weights to the densities, added to what is there.
    let n = 24;
    let sigma: Vec<f32> = (0..rays * n)
        .map(|i| 3.0 * uniform(40 + i as u64))
        .collect();
    let dt: Vec<f32> = (0..rays * n)
        .map(|i| 0.05 + 0.3 * uniform(90 + i as u64))
        .collect();
    let composited: Vec<f32> = sigma
        .chunks(n)
        .zip(dt.chunks(n))
        .flat_map(|(sigma, dt)| {
            let mut transmittance = 1.0f32;
            sigma
                .iter()
                .zip(dt)
                .map(|(s, d)| {
                    let alpha = 1.0 - (-s * d).exp();
                    let w = transmittance * alpha;
                    transmittance *= 1.0 - alpha;
                    w
                })
                .collect::<Vec<_>>()
        })
        .collect();
    let start: Vec<f32> = (0..rays * n)
        .map(|i| uniform(200 + i as u64) - 0.5)
        .collect();
    let mut cpu_sigma = start.clone();
    weight_losses::weights_to_densities(&sigma, &dt, &composited, &cpu_gradient, n, &mut cpu_sigma);
    let gpu_sigma = kernels.weights_to_densities_once(
        &context,
        (&sigma, &dt, &composited),
        &cpu_gradient,
        rays,
        &start,
    );
    assert_close("density gradient", &gpu_sigma, &cpu_sigma);
}

/// The unbounded demo in miniature.
fn unbounded_scene() -> Arc<Scene> {
    Arc::new(build_unbounded(&DemoConfig {
        size: 16,
        train_views: 8,
        val_views: 2,
        test_views: 1,
    }))
}

/// Rays per chunk in the step tests, so 12 rays span two chunks (8 and 4):
/// the chunk shares and each chunk's jitter seed are exercised.
const RAYS_PER_CHUNK: usize = 8;

/// `kind` with the proposal sampler on both engines, from one request.
fn engines(kind: ModelKind, scene: &Scene) -> (CpuModel, GpuModel) {
    let mut request: ModelRequest = request(kind, 3, LossKind::L2, None);
    request.settings.sampling = Sampling::Proposal;
    if kind == ModelKind::Nerf {
        request = request.with_shape(crate::common::small_nerf_shape(NerfKind::Nerf));
    }
    if kind == ModelKind::MipNerf {
        request = request.with_shape(crate::common::small_nerf_shape(NerfKind::MipNerf));
    }
    let mut cpu = CpuModel::build(&request, scene);
    let mut gpu = build_gpu(gpu_context(), &request, scene).expect("gpu model");
    gpu.set_read_back_late(false);
    cpu.set_rays_per_chunk(RAYS_PER_CHUNK);
    gpu.set_rays_per_chunk(RAYS_PER_CHUNK).unwrap();
    (cpu, gpu)
}

/// One step of `kind` from the same state on both engines, after
/// `warm_up` steps on the cpu engine (moved to the gpu engine through a
/// checkpoint). Instant-NGP's fresh proposal grids nearly bound the final
/// weights (interlevel loss ~2e-6): its excesses w − bound are then
/// differences of weights within ~1e-4 of each other, which keep only
/// ~1e-3 of their digits through f32 (measured: 3e-4 on the loss, 8e-4 on
/// a grid's gradient); after 30 steps the excesses are ~100 × larger and
/// the chain's 1e-4 holds (measured ~2e-5).
fn one_proposal_step_matches_the_cpu_engine(kind: ModelKind, warm_up: u32) {
    let scene = unbounded_scene();
    let (mut cpu, mut gpu) = engines(kind, &scene);
    assert!(
        gpu.params() == cpu.params(),
        "initial parameters differ: the engines must start identical"
    );
    for step in 0..warm_up {
        cpu.step(&batch(&scene, 32, 100 + step as u64), step);
    }
    if warm_up > 0 {
        gpu.load(&cpu.save()).expect("the cpu engine's checkpoint");
        assert!(gpu.params() == cpu.params());
    }
    let rays = batch(&scene, 12, 17);
    let cpu_stats = cpu.forward_backward(&rays, 1);
    let gpu_stats = gpu.forward_backward(&rays, 1);
    println!("{kind:?}: cpu {cpu_stats:?}\ngpu {gpu_stats:?}");
    assert_eq!(gpu_stats.samples, cpu_stats.samples);
    assert_eq!(gpu_stats.proposal_samples, cpu_stats.proposal_samples);
    assert!(cpu_stats.proposal_samples > cpu_stats.samples);

    // The same samples at every level (the last chunk's 4 rays).
    // Two proposal levels and the full field's, for every model.
    for level in 0..3 {
        let (c, g) = (cpu.level_distances(level), gpu.level_distances(level, 4));
        assert_eq!(c.len(), g.len(), "level {level}");
        let worst = c
            .iter()
            .zip(&g)
            .map(|(c, g)| (c - g).abs() / c.abs().max(1e-6))
            .fold(0f32, f32::max);
        println!("level {level}: distances differ by {worst:.2e} at most (relative)");
        assert!(worst < 1e-4, "level {level}: {worst}");
    }

    assert!(
        relative(gpu_stats.loss, cpu_stats.loss) < 1e-4,
        "loss: gpu {} cpu {}",
        gpu_stats.loss,
        cpu_stats.loss
    );
    assert!(cpu_stats.proposal_loss > 0.0, "{cpu_stats:?}");
    assert!(
        relative(gpu_stats.proposal_loss, cpu_stats.proposal_loss) < 1e-4,
        "interlevel loss: gpu {} cpu {}",
        gpu_stats.proposal_loss,
        cpu_stats.proposal_loss
    );
    let cpu_gradient = cpu.gradients().to_vec();
    let gpu_gradient = gpu.gradients();
    let ranges = cpu.parameter_ranges().to_vec();
    assert_eq!(ranges, gpu.parameter_ranges());
    for (field, range) in ranges.iter().enumerate() {
        let g = &cpu_gradient[range.clone()];
        assert!(g.iter().any(|&x| x != 0.0), "field {field} has no gradient");
        let error = relative_norm(&gpu_gradient[range.clone()], g);
        println!("gradient of field {field}: relative error {error:.2e}");
        assert!(error < 1e-4, "field {field}: {error:e}");
    }

    // The whole step: Adam over every field's parts (a part after another
    // starts off the storage-binding alignment), compared as each field's
    // update after − before. Adam maps each gradient entry through its
    // moments, m/√v: after the warm-up an entry whose new gradient nearly
    // cancels its moment moves by far more than its gradient's relative
    // difference (seen: 4e-3 from 2e-4), so the update is compared as a
    // whole, by its norm, at ten times the gradients' 1e-4; a part left
    // out or updated with another part's settings is off by O(1).
    let before = cpu.params().to_vec();
    let cpu_stats = cpu.step(&rays, 1);
    let gpu_stats = gpu.step(&rays, 1);
    assert!(relative(gpu_stats.loss, cpu_stats.loss) < 1e-4);
    let (cpu_after, gpu_after) = (cpu.params().to_vec(), gpu.params());
    // Adam's sparse rule leaves a hash entry alone where its gradient is
    // exactly 0 and moves it by its moments (~the learning rate) where it
    // is not, however small: an entry first touched now moves by ±the
    // learning rate whatever its gradient's size. The gradients agree to
    // 1e-4 of the largest, so an entry below that may differ in sign
    // between the engines or be 0 on one of them (the cpu sums the
    // weights' chain rule in f64: seen 1e-22 where the gpu's f32 cancels to
    // 0, and subnormals a GPU may flush; with the contracted fields' small
    // initial density most of the first proposal's entries are that
    // small) and move the other way or on one engine only: those entries
    // are left out.
    for (field, range) in ranges.iter().enumerate() {
        let largest = range
            .clone()
            .map(|i| cpu_gradient[i].abs())
            .fold(0f32, f32::max);
        let floor = 1e-4 * largest;
        let resolved = |i: usize| {
            let (c, g) = (cpu_gradient[i].abs(), gpu_gradient[i].abs());
            (c > floor && g > floor) || (c == 0.0 && g == 0.0)
        };
        let update = |after: &[f32]| -> Vec<f32> {
            range
                .clone()
                .filter(|&i| resolved(i))
                .map(|i| after[i] - before[i])
                .collect()
        };
        let (c, g) = (update(&cpu_after), update(&gpu_after));
        assert!(c.iter().any(|&x| x != 0.0), "field {field} did not move");
        let error = relative_norm(&g, &c);
        println!("update of field {field}: relative error {error:.2e}");
        assert!(error < 1e-3, "field {field}'s update: {error:e}");
    }
}

#[test]
fn ngp_proposal_step_matches_the_cpu_engine_gpu() {
    let _cores = crate::common::shared();
    one_proposal_step_matches_the_cpu_engine(ModelKind::Ngp, 30);
}

#[test]
fn nerf_proposal_step_matches_the_cpu_engine_gpu() {
    let _cores = crate::common::shared();
    one_proposal_step_matches_the_cpu_engine(ModelKind::Nerf, 0);
}

#[test]
fn mipnerf_proposal_step_matches_the_cpu_engine_gpu() {
    let _cores = crate::common::shared();
    one_proposal_step_matches_the_cpu_engine(ModelKind::MipNerf, 0);
}

/// A validation view rendered with the proposal sampler (no jitter: each
/// level's deterministic edges), gpu against cpu, for each model: the same
/// chain as a step's forward pass, so the same 1e-4 on colour and opacity.
/// Depth is Σ wᵢ tᵢ with the far field's tᵢ up to 1000 frame radii out:
/// weights that agree to f32's ~1e-7 there move a depth of about one
/// radius by ~1e-4 relative, and the resampled levels' edges (an inverse
/// CDF of those weights) add as much again at each level; 1e-3 relative.
#[test]
fn proposal_renders_match_the_cpu_engine_gpu() {
    let _cores = crate::common::shared();
    let scene = unbounded_scene();
    for kind in [ModelKind::Ngp, ModelKind::Nerf, ModelKind::MipNerf] {
        let (cpu, gpu) = engines(kind, &scene);
        let expected = crate::common::render_first_val_view(&cpu, &scene);
        let drawn = crate::common::render_first_val_view(&gpu, &scene);
        let (mut colour, mut depth) = (0f32, 0f32);
        for (g, c) in drawn.iter().zip(&expected) {
            for k in 0..3 {
                colour = colour.max((g.rgb[k] - c.rgb[k]).abs());
            }
            colour = colour.max((g.opacity - c.opacity).abs());
            depth = depth.max((g.depth - c.depth).abs() / c.depth.abs().max(1e-3));
        }
        println!("{kind:?}: colour and opacity within {colour:.2e}, depth {depth:.2e}");
        assert!(
            expected.iter().any(|p| p.opacity > 0.01),
            "{kind:?}: nothing drawn"
        );
        assert!(colour < 1e-4 && depth < 1e-3, "{kind:?}: {colour} {depth}");
    }
}
