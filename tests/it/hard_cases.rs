//! Hard numerical cases as one table: every case runs on every model, on
//! every engine that has it, through the same [`RadianceModel`] calls the
//! trainer and the renderer make.
//!
//! The rays of every case: rays that miss the scene's box or point away
//! from it, rays starting inside it, axis-parallel rays through its centre,
//! along one of its edges and inside the plane of one of its faces (where
//! a slab test meets 0 · ∞), a ray touching only one corner (a zero-length
//! interval), cones of zero and of very wide radius (read by Mip-NeRF), and
//! target and background colours at exactly 0 and 1.
//!
//! The cases set the raw network outputs through the parameters (in a
//! checkpoint, the seam every engine shares): raw densities of +1e4 (every
//! ray opaque at its first sample) and −1e4 (every sample weight exactly
//! zero), raw colours of ±1e4 (the colour sigmoid saturated at 0 and 1),
//! and the parameters a learning-rate spike leaves behind. After each step:
//! no NaN or Inf in the loss, the gradients, the parameters or the
//! optimiser's state, and the rendered pixels are the values the case
//! implies.
//!
//! A model/engine pair is one row of [`rows`]. The occupancy grid of the
//! models that march one is a small occupied ball at the centre, so a
//! step on lavapipe stays short (a few hundred samples).

use crate::common;

use std::time::Instant;

use glam::Vec3;
use zrak::engine::cpu::model::CpuModel;
use zrak::engine::gpu::model::GpuModel;
use zrak::engine::request::{ModelRequest, ModelSettings};
use zrak::engine::shared::occupancy::GridGeometry;
use zrak::engine::{EngineKind, build_gpu};
use zrak::field::ModelKind;
use zrak::field::common::{LossKind, OccupancyConfig, Sampling};
use zrak::field::encoding::{HashGridConfig, HashGridLayout};
use zrak::field::mlp::Precision;
use zrak::field::nerf::NerfShape;
use zrak::field::ngp::NgpShape;
use zrak::model::batch::RayBatch;
use zrak::model::checkpoint::Checkpoint;
use zrak::model::{RadianceModel, RenderedPixel};
use zrak::scene::Scene;

use common::{NerfKind, small_nerf_shape};

const SEED: u64 = 3;

/// Samples per batch: several times what the hard rays take through the
/// occupied ball, so none of them is left out of a step.
const BATCH_SAMPLES: usize = 1 << 12;

/// The occupied ball's radius in world units (the demo's box is ±1.5): ~6
/// occupancy cells, ~60 marching steps along a diameter.
const BALL_RADIUS: f32 = 0.15;

/// What the cases read besides [`RadianceModel`]: the gradient the last
/// step wrote.
trait Probe: RadianceModel {
    fn gradient(&self) -> Vec<f32>;
}

impl Probe for CpuModel {
    fn gradient(&self) -> Vec<f32> {
        self.gradients().to_vec()
    }
}

impl Probe for GpuModel {
    fn gradient(&self) -> Vec<f32> {
        self.gradients()
    }
}

/// Where a model's raw density and colour outputs can be set in its flat
/// parameters (the same layout on both engines).
enum Layout {
    Ngp(NgpShape),
    /// One or more fields of this shape, one after the other.
    Nerf(NerfShape),
}

/// Weights of `layer` in `net` (an MLP's parameters): row `out`, column `input`.
fn weight(layout: &zrak::field::mlp::MlpLayout, layer: usize, out: usize, input: usize) -> usize {
    layout.weight_offset(layer) + out * layout.widths[layer] + input
}

impl Layout {
    /// The parameter ranges of each NeRF-shaped field.
    fn fields(shape: &NerfShape, params: usize) -> Vec<std::ops::Range<usize>> {
        let per_field =
            shape.trunk_a.param_count() + shape.trunk_b.param_count() + shape.colour.param_count();
        assert_eq!(params % per_field, 0, "whole fields of the shape");
        (0..params / per_field)
            .map(|f| f * per_field..(f + 1) * per_field)
            .collect()
    }

    /// Makes every raw density output exactly `raw`, wherever the sample.
    fn set_raw_density(&self, params: &mut [f32], raw: f32) {
        match self {
            Layout::Ngp(shape) => {
                // Every hash feature 1 (interpolating equal corners), the
                // first hidden unit their mean, each later one the one
                // before, and the log-density output `raw` times it: no
                // bias to set, the network has none.
                let grid = shape.grid.param_count();
                params[..grid].fill(1.0);
                let net = &mut params[grid..grid + shape.density.param_count()];
                net.fill(0.0);
                let d = &shape.density;
                let inputs = d.input_width();
                for i in 0..inputs {
                    net[weight(d, 0, 0, i)] = 1.0 / inputs as f32;
                }
                let last = d.layers() - 1;
                for layer in 1..last {
                    net[weight(d, layer, 0, 0)] = 1.0;
                }
                net[weight(d, last, 0, 0)] = raw;
            }
            Layout::Nerf(shape) => {
                // The σ head is output 0 of trunk B's last layer: its
                // weights zero, its bias `raw`.
                let b = &shape.trunk_b;
                let last = b.layers() - 1;
                let start = shape.trunk_a.param_count();
                for field in Self::fields(shape, params.len()) {
                    let net = &mut params[field.start + start..];
                    for i in 0..b.widths[last] {
                        net[weight(b, last, 0, i)] = 0.0;
                    }
                    net[b.bias_offset(last).expect("NeRF's layers have biases")] = raw;
                }
            }
        }
    }

    /// Makes the raw colour outputs exactly `raw` (per channel), wherever
    /// the sample and whatever the direction.
    fn set_raw_colour(&self, params: &mut [f32], raw: [f32; 3]) {
        match self {
            Layout::Ngp(shape) => {
                // The colour network's inputs are the density outputs and
                // the spherical harmonics of the direction, whose first
                // (band 0) is the constant 1/(2√π): the first hidden unit
                // is 1 through it, each later one the one before, and
                // channel c is raw[c] times the last.
                let start = shape.grid.param_count() + shape.density.param_count();
                let c = &shape.colour;
                let net = &mut params[start..start + c.param_count()];
                net.fill(0.0);
                let band_0 = shape.network.density_output_width;
                net[weight(c, 0, 0, band_0)] = 2.0 * std::f32::consts::PI.sqrt();
                let last = c.layers() - 1;
                for layer in 1..last {
                    net[weight(c, layer, 0, 0)] = 1.0;
                }
                for (channel, &value) in raw.iter().enumerate() {
                    net[weight(c, last, channel, 0)] = value;
                }
            }
            Layout::Nerf(shape) => {
                let c = &shape.colour;
                let last = c.layers() - 1;
                let start = shape.trunk_a.param_count() + shape.trunk_b.param_count();
                for field in Self::fields(shape, params.len()) {
                    let net = &mut params[field.start + start..];
                    for channel in 0..3 {
                        for i in 0..c.widths[last] {
                            net[weight(c, last, channel, i)] = 0.0;
                        }
                    }
                    let bias = c.bias_offset(last).expect("NeRF's layers have biases");
                    net[bias..bias + 3].copy_from_slice(&raw);
                }
            }
        }
    }

    /// Where the colour networks' parameters are.
    fn colour_params(&self, params: usize) -> Vec<std::ops::Range<usize>> {
        match self {
            Layout::Ngp(shape) => {
                let start = shape.grid.param_count() + shape.density.param_count();
                std::iter::once(start..start + shape.colour.param_count()).collect()
            }
            Layout::Nerf(shape) => {
                let start = shape.trunk_a.param_count() + shape.trunk_b.param_count();
                Self::fields(shape, params)
                    .into_iter()
                    .map(|f| f.start + start..f.end)
                    .collect()
            }
        }
    }

    /// The colours the field can give: the sigmoid's [0, 1], widened by
    /// Mip-NeRF's padding.
    fn colour_bounds(&self) -> (f32, f32) {
        match self {
            Layout::Ngp(_) => (0.0, 1.0),
            Layout::Nerf(shape) => (-shape.colour_padding, 1.0 + shape.colour_padding),
        }
    }
}

/// One model on one engine.
struct Row {
    name: &'static str,
    engine: EngineKind,
    build: fn(&Scene) -> Box<dyn Probe>,
    layout: fn(&Scene) -> Layout,
}

fn settings(sampling: Sampling) -> ModelSettings {
    ModelSettings {
        seed: SEED,
        loss: LossKind::L2,
        batch_samples: Some(BATCH_SAMPLES),
        sampling,
        precision: Precision::F32,
        refine_cameras: false,
        appearance: false,
    }
}

/// Instant-NGP's parts with a hash table of 2^12 entries per level
/// instead of 2^19: every level hashed, the networks as the paper's, and
/// 130 thousand parameters instead of 12 million to move per case.
fn small_ngp_shape(scene: &Scene) -> NgpShape {
    let mut shape = NgpShape::for_scene(scene);
    shape.grid = HashGridLayout::new(&HashGridConfig {
        log2_table_size: 12,
        ..HashGridConfig::paper(scene.unit_cube.aabb_scale)
    });
    shape
}

fn ngp_layout(scene: &Scene) -> Layout {
    Layout::Ngp(small_ngp_shape(scene))
}

fn nerf_layout(_: &Scene) -> Layout {
    Layout::Nerf(small_nerf_shape(NerfKind::Nerf))
}

fn mipnerf_layout(_: &Scene) -> Layout {
    Layout::Nerf(small_nerf_shape(NerfKind::MipNerf))
}

/// Every model on every engine, each sampler of NeRF and Mip-NeRF.
fn rows() -> Vec<Row> {
    use EngineKind::{Cpu, Gpu};
    vec![
        Row {
            name: "Instant-NGP (cpu)",
            engine: Cpu,
            build: |scene| {
                Box::new(CpuModel::build(
                    &crate::common::request(
                        ModelKind::Ngp,
                        SEED,
                        LossKind::Huber,
                        Some(BATCH_SAMPLES),
                    )
                    .with_shape(small_ngp_shape(scene)),
                    scene,
                ))
            },
            layout: ngp_layout,
        },
        Row {
            name: "NeRF, occupancy sampler (cpu)",
            engine: Cpu,
            build: |scene| {
                let shape = small_nerf_shape(NerfKind::Nerf);
                Box::new(CpuModel::build(
                    &ModelRequest::new(ModelKind::Nerf, settings(Sampling::Occupancy))
                        .with_shape(shape),
                    scene,
                ))
            },
            layout: nerf_layout,
        },
        Row {
            name: "NeRF, paper sampler (cpu)",
            engine: Cpu,
            build: |scene| {
                let shape = small_nerf_shape(NerfKind::Nerf);
                Box::new(CpuModel::build(
                    &ModelRequest::new(ModelKind::Nerf, settings(Sampling::Paper))
                        .with_shape(shape),
                    scene,
                ))
            },
            layout: nerf_layout,
        },
        Row {
            name: "Mip-NeRF, occupancy sampler (cpu)",
            engine: Cpu,
            build: |scene| {
                let shape = small_nerf_shape(NerfKind::MipNerf);
                Box::new(CpuModel::build(
                    &ModelRequest::new(ModelKind::MipNerf, settings(Sampling::Occupancy))
                        .with_shape(shape),
                    scene,
                ))
            },
            layout: mipnerf_layout,
        },
        Row {
            name: "Mip-NeRF, paper sampler (cpu)",
            engine: Cpu,
            build: |scene| {
                let shape = small_nerf_shape(NerfKind::MipNerf);
                Box::new(CpuModel::build(
                    &ModelRequest::new(ModelKind::MipNerf, settings(Sampling::Paper))
                        .with_shape(shape),
                    scene,
                ))
            },
            layout: mipnerf_layout,
        },
        // Mixed precision (bf16 products summed in f32) where the processor
        // has bf16 kernels; elsewhere these rows run the f32 kernels again.
        Row {
            name: "Instant-NGP, mixed precision (cpu)",
            engine: Cpu,
            build: |scene| {
                let mut request =
                    common::request(ModelKind::Ngp, SEED, LossKind::Huber, Some(BATCH_SAMPLES))
                        .with_shape(small_ngp_shape(scene));
                request.settings.precision = Precision::Mixed;
                Box::new(CpuModel::build(&request, scene))
            },
            layout: ngp_layout,
        },
        Row {
            name: "NeRF, occupancy sampler, mixed precision (cpu)",
            engine: Cpu,
            build: |scene| {
                let shape = small_nerf_shape(NerfKind::Nerf);
                let settings = ModelSettings {
                    precision: Precision::Mixed,
                    ..settings(Sampling::Occupancy)
                };
                Box::new(CpuModel::build(
                    &ModelRequest::new(ModelKind::Nerf, settings).with_shape(shape),
                    scene,
                ))
            },
            layout: nerf_layout,
        },
        Row {
            name: "Mip-NeRF, paper sampler, mixed precision (cpu)",
            engine: Cpu,
            build: |scene| {
                let shape = small_nerf_shape(NerfKind::MipNerf);
                let settings = ModelSettings {
                    precision: Precision::Mixed,
                    ..settings(Sampling::Paper)
                };
                Box::new(CpuModel::build(
                    &ModelRequest::new(ModelKind::MipNerf, settings).with_shape(shape),
                    scene,
                ))
            },
            layout: mipnerf_layout,
        },
        Row {
            name: "Instant-NGP (gpu)",
            engine: Gpu,
            build: |scene| {
                Box::new(
                    build_gpu(
                        common::gpu_context(),
                        &crate::common::request(
                            ModelKind::Ngp,
                            SEED,
                            LossKind::Huber,
                            Some(BATCH_SAMPLES),
                        )
                        .with_shape(small_ngp_shape(scene)),
                        scene,
                    )
                    .expect("gpu model"),
                )
            },
            layout: ngp_layout,
        },
        Row {
            name: "NeRF, occupancy sampler (gpu)",
            engine: Gpu,
            build: |scene| {
                let shape = small_nerf_shape(NerfKind::Nerf);
                let settings = settings(Sampling::Occupancy);
                Box::new(
                    build_gpu(
                        common::gpu_context(),
                        &ModelRequest::new(ModelKind::Nerf, settings).with_shape(shape),
                        scene,
                    )
                    .expect("gpu model"),
                )
            },
            layout: nerf_layout,
        },
        Row {
            name: "NeRF, paper sampler (gpu)",
            engine: Gpu,
            build: |scene| {
                let shape = small_nerf_shape(NerfKind::Nerf);
                let settings = settings(Sampling::Paper);
                Box::new(
                    build_gpu(
                        common::gpu_context(),
                        &ModelRequest::new(ModelKind::Nerf, settings).with_shape(shape),
                        scene,
                    )
                    .expect("gpu model"),
                )
            },
            layout: nerf_layout,
        },
        Row {
            name: "Mip-NeRF, occupancy sampler (gpu)",
            engine: Gpu,
            build: |scene| {
                let shape = small_nerf_shape(NerfKind::MipNerf);
                let settings = settings(Sampling::Occupancy);
                Box::new(
                    build_gpu(
                        common::gpu_context(),
                        &ModelRequest::new(ModelKind::MipNerf, settings).with_shape(shape),
                        scene,
                    )
                    .expect("gpu model"),
                )
            },
            layout: mipnerf_layout,
        },
        Row {
            name: "Mip-NeRF, paper sampler (gpu)",
            engine: Gpu,
            build: |scene| {
                let shape = small_nerf_shape(NerfKind::MipNerf);
                let settings = settings(Sampling::Paper);
                Box::new(
                    build_gpu(
                        common::gpu_context(),
                        &ModelRequest::new(ModelKind::MipNerf, settings).with_shape(shape),
                        scene,
                    )
                    .expect("gpu model"),
                )
            },
            layout: mipnerf_layout,
        },
    ]
}

/// What a hard ray should show, whatever the field.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Expect {
    /// It misses the box, or meets it in a zero-length interval: nothing
    /// along it, so exactly the background, opacity 0.
    Background,
    /// It passes the box's centre (inside the occupied ball) at distance t.
    ThroughCentre { t: f32 },
    /// Only finite, in-range values.
    Finite,
}

struct HardRay {
    what: &'static str,
    origin: Vec3,
    direction: Vec3,
    expect: Expect,
}

fn hard_rays(scene: &Scene) -> Vec<HardRay> {
    let max = scene.bounds.max;
    let ray = |what, origin, direction: Vec3, expect| HardRay {
        what,
        origin,
        direction: direction.normalize(),
        expect,
    };
    let mut rays = vec![
        ray(
            "misses the box",
            Vec3::new(10.0, 10.0, 10.0),
            Vec3::X,
            Expect::Background,
        ),
        ray(
            "points away from the box",
            Vec3::new(0.0, 0.0, 4.0),
            Vec3::Z,
            Expect::Background,
        ),
        ray(
            "starts at the centre",
            Vec3::ZERO,
            Vec3::NEG_Z,
            Expect::ThroughCentre { t: 0.0 },
        ),
        ray(
            "starts inside, off the axes",
            Vec3::new(0.2, -0.1, 0.3),
            Vec3::new(1.0, 1.0, 1.0),
            Expect::Finite,
        ),
        ray(
            "runs along an edge of the box",
            max,
            Vec3::NEG_Y,
            Expect::Finite,
        ),
        ray(
            "lies in the plane of a face",
            Vec3::new(max.x, 0.0, 3.0),
            Vec3::NEG_Z,
            Expect::Finite,
        ),
        // Through the corner `max` and out again: entry and exit distance
        // are the same, a zero-length interval.
        ray(
            "touches one corner only",
            max + Vec3::new(1.0, 1.0, -1.0),
            Vec3::new(-1.0, -1.0, 1.0),
            Expect::Background,
        ),
    ];
    // Axis-parallel through the centre, from 3 away, along each axis (with
    // both signs among them and the ray from the centre along −z).
    for direction in [Vec3::X, Vec3::NEG_Y, Vec3::Z] {
        rays.push(ray(
            "axis-parallel through the centre",
            -3.0 * direction,
            direction,
            Expect::ThroughCentre { t: 3.0 },
        ));
    }
    rays
}

/// The hard rays, then two ordinary training rays; targets and
/// backgrounds at exactly 0 and 1; cone radii of 0 and 100 on the ordinary
/// rays (a frustum of zero width, and one wider than the scene).
fn batch_of(scene: &Scene, hard: &[HardRay]) -> RayBatch {
    let ordinary = common::batch(scene, 2, 2);
    let mut batch = RayBatch::default();
    for ray in hard {
        batch.origins.push(ray.origin);
        batch.directions.push(ray.direction);
        batch.radii.push(1e-3);
    }
    batch.origins.extend(&ordinary.origins);
    batch.directions.extend(&ordinary.directions);
    batch.radii.extend([0.0, 100.0]);
    for i in 0..batch.len() {
        let (target, background) = if i % 2 == 0 {
            ([1.0, 0.0, 1.0], [1.0; 3])
        } else {
            ([0.0, 1.0, 0.0], [0.0; 3])
        };
        batch.targets.push(target);
        batch.backgrounds.push(background);
    }
    batch
}

/// The checkpoint's tensor `name`, writable.
fn tensor_mut<'a>(checkpoint: &'a mut Checkpoint, name: &str) -> &'a mut Vec<f32> {
    checkpoint
        .tensors
        .iter_mut()
        .find(|(n, _)| n == name)
        .map(|(_, t)| t)
        .unwrap_or_else(|| panic!("the checkpoint has no `{name}`"))
}

/// Makes the occupancy grid (if the model has one) a ball of
/// [`BALL_RADIUS`] around the box's centre: occupied inside, empty outside.
fn occupy_a_ball(scene: &Scene, checkpoint: &mut Checkpoint) {
    if checkpoint.tensor("occupancy").is_none() {
        return;
    }
    let mapping = scene.unit_cube;
    let values = tensor_mut(checkpoint, "occupancy");
    // Each recipe chooses its grid's resolution: it is the cube root of
    // the cells per cascade.
    let cascades = OccupancyConfig::cascades(mapping.aabb_scale);
    let resolution = (values.len() as f64 / cascades as f64).cbrt().round() as u32;
    let geometry = GridGeometry::new(resolution, cascades);
    assert_eq!(values.len(), geometry.cell_count());
    let centre = mapping.to_unit(Vec3::ZERO);
    let radius = BALL_RADIUS * mapping.scale;
    for (i, v) in values.iter_mut().enumerate() {
        let cell = geometry.cell_at(i);
        let middle = geometry.cell_centre(cell);
        *v = if (middle - centre).length() < radius {
            1.0
        } else {
            0.0
        };
    }
}

/// A case: what it does to the parameters before one training step, the
/// background it renders over afterwards, and what it checks beyond
/// [`check_every_case`].
struct Case {
    name: &'static str,
    prepare: fn(&Layout, &mut [f32]),
    background: [f32; 3],
    check: fn(&Outcome, &mut Vec<String>),
}

/// What one case produced.
struct Outcome<'a> {
    layout: &'a Layout,
    rays: &'a [HardRay],
    gradient: &'a [f32],
    pixels: &'a [RenderedPixel],
    background: [f32; 3],
    scene: &'a Scene,
}

fn cases() -> Vec<Case> {
    vec![
        Case {
            name: "raw density +1e4",
            prepare: |layout, params| layout.set_raw_density(params, 1e4),
            background: [1.0; 3],
            check: check_opaque_at_first_sample,
        },
        Case {
            name: "raw density −1e4 (every sample weight zero)",
            prepare: |layout, params| layout.set_raw_density(params, -1e4),
            background: [1.0, 0.0, 1.0],
            check: check_all_weights_zero,
        },
        Case {
            name: "raw colours ±1e4 (field colours at 0 and 1)",
            prepare: |layout, params| layout.set_raw_colour(params, [1e4, -1e4, 1e4]),
            background: [0.0, 1.0, 0.0],
            check: check_saturated_colours,
        },
        Case {
            name: "after a learning-rate spike",
            // One Adam step moves every parameter by the learning rate
            // times the sign of its gradient: with a rate of 1 (100 times
            // Instant-NGP's, 2000 times NeRF's), ±1 everywhere.
            prepare: |_, params| {
                let mut rng = zrak::rng::Pcg32::new(99, 0);
                for p in params.iter_mut() {
                    *p += if rng.next_f32() < 0.5 { -1.0 } else { 1.0 };
                }
            },
            background: [1.0; 3],
            check: |_, _| {},
        },
    ]
}

/// Raw σ of 1e4 is at least 1e4 per world unit after every model's
/// activation (ReLU, softplus, Instant-NGP's exp clamped at e^15); the
/// samples of a ray through the centre are at most 0.1 apart (the paper
/// samplers' 64 or 128 bins over a chord of at most 3√3) and at least
/// Instant-NGP's marching step (√3/1024 of the unit cube, 5e-3 world units)
/// long, so its first sample's optical thickness is ≥ 50: opaque to f32
/// precision. Its depth is then that sample's distance: past where the ray
/// enters the box, and at most one sample spacing past the centre, which
/// lies inside the occupied ball.
fn check_opaque_at_first_sample(o: &Outcome, failures: &mut Vec<String>) {
    for (ray, pixel) in o.rays.iter().zip(o.pixels) {
        if let Expect::ThroughCentre { t } = ray.expect {
            let near = o
                .scene
                .bounds
                .intersect(ray.origin, ray.direction, 0.0)
                .map_or(0.0, |(near, _)| near);
            if pixel.opacity < 1.0 - 1e-6 || !(near - 1e-4..=t + 0.1).contains(&pixel.depth) {
                failures.push(format!(
                    "ray that {}: not opaque at its first sample ({pixel:?}; box entered at {near}, centre at {t})",
                    ray.what
                ));
            }
        }
    }
}

/// With σ = 0 at every sample every weight is exactly 0: each pixel is
/// the background bit for bit, and no gradient reaches any parameter (σ's
/// activation is flat there, and colours with zero weight do not count).
fn check_all_weights_zero(o: &Outcome, failures: &mut Vec<String>) {
    for (i, pixel) in o.pixels.iter().enumerate() {
        if pixel.rgb != o.background || pixel.opacity != 0.0 {
            failures.push(format!("ray {i}: not the background: {pixel:?}"));
        }
    }
    let nonzero = o.gradient.iter().filter(|g| **g != 0.0).count();
    if nonzero > 0 {
        failures.push(format!("{nonzero} gradients are not zero"));
    }
}

/// Every sample's colour is (hi, lo, hi), the ends of the colour range, so
/// each pixel is colour · opacity + background · (1 − opacity). The two
/// sides differ by f32 rounding of the sums of weights (~100 samples, each
/// rounded at 6e-8 relative: < 1e-5); 1e-4 is ten times that. The
/// sigmoid is flat at both ends: no gradient reaches the colour networks.
fn check_saturated_colours(o: &Outcome, failures: &mut Vec<String>) {
    let (lo, hi) = o.layout.colour_bounds();
    let colour = [hi, lo, hi];
    for (i, pixel) in o.pixels.iter().enumerate() {
        for (c, end) in colour.iter().enumerate() {
            let want = end * pixel.opacity + o.background[c] * (1.0 - pixel.opacity);
            if (pixel.rgb[c] - want).abs() > 1e-4 {
                failures.push(format!(
                    "ray {i}: channel {c} is {}, saturated colours give {want} ({pixel:?})",
                    pixel.rgb[c]
                ));
            }
        }
    }
    for range in o.layout.colour_params(o.gradient.len()) {
        let nonzero = o.gradient[range].iter().filter(|g| **g != 0.0).count();
        if nonzero > 0 {
            failures.push(format!(
                "{nonzero} gradients of a colour network are not zero"
            ));
        }
    }
}

/// What every case checks: no NaN or Inf in the loss, the gradient, the
/// parameters or the optimiser's state; pixels in range; rays with nothing
/// along them show exactly the background.
fn check_every_case(
    label: &str,
    loss: f32,
    gradient: &[f32],
    checkpoint: &Checkpoint,
    outcome: &Outcome,
    failures: &mut Vec<String>,
) {
    let mut fail = |message: String| failures.push(format!("{label}: {message}"));
    if !loss.is_finite() {
        fail(format!("loss {loss}"));
    }
    let bad = gradient.iter().filter(|g| !g.is_finite()).count();
    if bad > 0 {
        fail(format!("{bad} of {} gradients not finite", gradient.len()));
    }
    for (name, values) in &checkpoint.tensors {
        let bad = values.iter().filter(|v| !v.is_finite()).count();
        if bad > 0 {
            fail(format!(
                "{bad} of {} values of `{name}` not finite",
                values.len()
            ));
        }
    }
    // A pixel is Σ wᵢ cᵢ + T · background with Σ wᵢ + T = 1, every cᵢ and
    // the background within the field's colour bounds: so is the pixel, up
    // to f32 rounding of the sums (~100 terms at 6e-8 each: < 1e-5), and
    // opacity Σ wᵢ lies in [0, 1] likewise. Depth Σ wᵢ tᵢ has tᵢ ≥ 0.
    let (lo, hi) = outcome.layout.colour_bounds();
    for ((ray, pixel), i) in outcome
        .rays
        .iter()
        .map(Some)
        .chain(std::iter::repeat(None))
        .zip(outcome.pixels)
        .zip(0..)
    {
        let what = ray.map_or_else(
            || format!("ordinary ray {i}"),
            |r| format!("ray that {}", r.what),
        );
        let in_range = pixel
            .rgb
            .iter()
            .all(|c| (lo - 1e-5..=hi + 1e-5).contains(c))
            && (0.0..=1.0 + 1e-6).contains(&pixel.opacity)
            && pixel.depth.is_finite()
            && pixel.depth >= 0.0;
        if !in_range {
            fail(format!("{what}: {pixel:?}"));
        }
        if ray.is_some_and(|r| r.expect == Expect::Background)
            && (pixel.rgb != outcome.background || pixel.opacity != 0.0)
        {
            fail(format!("{what}: not exactly the background: {pixel:?}"));
        }
    }
}

/// Runs every case on `row`; returns what failed.
fn run_row(row: &Row, scene: &Scene) -> Vec<String> {
    let clock = Instant::now();
    let mut model = (row.build)(scene);
    let layout = (row.layout)(scene);
    let mut start = model.save();
    occupy_a_ball(scene, &mut start);
    let rays = hard_rays(scene);
    let batch = batch_of(scene, &rays);
    let mut failures = Vec::new();
    for case in cases() {
        let label = format!("{} — {}", row.name, case.name);
        let mut checkpoint = start.clone();
        (case.prepare)(&layout, tensor_mut(&mut checkpoint, "params"));
        model
            .load(&checkpoint)
            .expect("the prepared checkpoint loads");
        // Step 1: no occupancy update is due (every 16 steps), so the
        // ball stays as set.
        let stats = model.step(&batch, 1);
        let gradient = model.gradient();
        let saved = model.save();
        let mut pixels = vec![RenderedPixel::default(); batch.len()];
        let view = zrak::model::RenderRays {
            origins: &batch.origins,
            directions: &batch.directions,
            radii: &batch.radii,
            background: case.background,
        };
        model.render(view, &mut pixels);
        let outcome = Outcome {
            layout: &layout,
            rays: &rays,
            gradient: &gradient,
            pixels: &pixels,
            background: case.background,
            scene,
        };
        let mut found = Vec::new();
        // The budget of samples must not have left a hard ray out.
        if stats.rays != batch.len() {
            found.push(format!(
                "{label}: {} of {} rays stepped",
                stats.rays,
                batch.len()
            ));
        }
        check_every_case(&label, stats.loss, &gradient, &saved, &outcome, &mut found);
        let mut specific = Vec::new();
        (case.check)(&outcome, &mut specific);
        found.extend(specific.into_iter().map(|f| format!("{label}: {f}")));
        failures.extend(found);
    }
    println!(
        "{}: {} cases in {:.2} s",
        row.name,
        cases().len(),
        clock.elapsed().as_secs_f64()
    );
    failures
}

fn run_rows(engine: EngineKind) {
    if engine == EngineKind::Cpu && Precision::Mixed.kernels_here() != Precision::Mixed {
        use std::io::Write;
        let _ = writeln!(
            std::io::stderr(),
            "the mixed-precision rows run f32 kernels: this processor has no AVX512-BF16"
        );
    }
    let scene = common::small_scene(24);
    let mut failures = Vec::new();
    for row in rows().iter().filter(|r| r.engine == engine) {
        failures.extend(run_row(row, &scene));
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

#[test]
fn hard_cases_on_the_cpu_engine() {
    let _cores = crate::common::shared();
    run_rows(EngineKind::Cpu);
}

#[test]
fn hard_cases_on_the_gpu_engine() {
    let _cores = crate::common::shared();
    run_rows(EngineKind::Gpu);
}
