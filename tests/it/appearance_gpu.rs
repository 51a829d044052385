//! Per-image appearance embeddings on the gpu engine (lavapipe) against the
//! cpu engine: Instant-NGP's field alone with each kind of appearance (each
//! sample its ray's image, one image's, the mean) forward and backward;
//! one training step of Instant-NGP and of NeRF (the gradient of every
//! part, the embeddings' among them, and the table after Adam); renders
//! with the embeddings' mean and with a chosen image's vector, from a gpu
//! checkpoint loaded on the cpu engine.
//!
//! Tolerances are those of the parity tests of the same models without
//! embeddings (tests/it/ngp_gpu.rs, nerf_gpu.rs, ngp_field_gpu.rs): 1e-4
//! relative for losses and gradients, 1e-4 absolute for rendered colours
//! in [0, 1]. The embeddings add two stages, a copy (exact) and a sum of
//! each image's samples' gradients (f32, in another order on the gpu), so
//! the same bounds hold; a row added to the wrong image, a shifted column
//! or a missing mean is off by O(1).

use crate::common;

use std::ops::Range;
use std::sync::Arc;

use common::{batch, relative, relative_norm};
use glam::Vec3;
use zrak::engine::build_gpu;
use zrak::engine::cpu::fields::ngp::NgpField;
use zrak::engine::cpu::fields::{Field, Gradient};
use zrak::engine::cpu::model::CpuModel;
use zrak::engine::gpu::fields::ngp::GpuNgpField;
use zrak::engine::gpu::fields::{FieldInputs, FieldOutputs, GpuAppearance, GpuField};
use zrak::engine::gpu::kernel::{Recorder, read_buffer, storage_buffer, zeroed_storage_buffer};
use zrak::engine::gpu::model::GpuModel;
use zrak::engine::request::ModelRequest;
use zrak::field::ModelKind;
use zrak::field::appearance::{Appearance, AppearanceShape, EMBEDDING_WIDTH};
use zrak::field::common::{LossKind, Sampling};
use zrak::field::encoding::{HashGridConfig, HashGridLayout};
use zrak::field::ngp::NgpShape;
use zrak::field::params::APPEARANCE_PART;
use zrak::model::{RadianceModel, RenderedPixel};
use zrak::rng::Pcg32;
use zrak::scene::Scene;

const TOLERANCE: f64 = 1e-4;

fn uniform(rng: &mut Pcg32, lo: f32, hi: f32) -> f32 {
    lo + (hi - lo) * rng.next_f32()
}

/// The named parts of a model's parameters.
fn parts(model: &CpuModel) -> Vec<(String, Range<usize>)> {
    model
        .layout()
        .parts()
        .iter()
        .map(|part| (part.name.clone(), part.range.clone()))
        .collect()
}

/// The range of the appearance embeddings among `parts`.
fn table_range(parts: &[(String, Range<usize>)]) -> Range<usize> {
    parts
        .iter()
        .find(|(name, _)| name.ends_with(APPEARANCE_PART))
        .map(|(_, range)| range.clone())
        .expect("the model has appearance embeddings")
}

/// Each part's gradient on the gpu engine within the tolerance of the cpu
/// engine's, and the embeddings' gradient in more than one image's row
/// (the batch draws rays from several images).
fn check_gradients(cpu: &CpuModel, gpu: &GpuModel, images: usize) {
    let cpu_gradient = cpu.gradients().to_vec();
    let gpu_gradient = gpu.gradients();
    let parts = parts(cpu);
    for (name, range) in &parts {
        let g = &cpu_gradient[range.clone()];
        assert!(g.iter().any(|&x| x != 0.0), "{name}: no gradient");
        let error = relative_norm(&gpu_gradient[range.clone()], g);
        println!("gradient of the {name}: relative error {error:.2e}");
        assert!(error < TOLERANCE, "{name}: {error:e}");
    }
    let table = table_range(&parts);
    let rows_with_gradient = cpu_gradient[table]
        .chunks_exact(EMBEDDING_WIDTH)
        .filter(|row| row.iter().any(|&g| g != 0.0))
        .count();
    assert!(
        (2..=images).contains(&rows_with_gradient),
        "{rows_with_gradient} of {images} images' vectors have a gradient"
    );
}

/// After one step on both engines from the same state: the loss, and the
/// embeddings' update (Adam's first: about lr · sign(g) each) agree.
fn check_step(cpu: &mut CpuModel, gpu: &mut GpuModel, rays: &zrak::model::batch::RayBatch) {
    let before = cpu.params().to_vec();
    let table = table_range(&parts(cpu));
    let cpu_stats = cpu.step(rays, 1);
    let gpu_stats = gpu.step(rays, 1);
    assert!(
        relative(gpu_stats.loss, cpu_stats.loss) < TOLERANCE as f32,
        "loss: gpu {} cpu {}",
        gpu_stats.loss,
        cpu_stats.loss
    );
    let (cpu_after, gpu_after) = (cpu.params().to_vec(), gpu.params());
    let (mut changed, mut mismatched) = (0, 0);
    for i in table {
        let (dc, dg) = (cpu_after[i] - before[i], gpu_after[i] - before[i]);
        if dc == 0.0 && dg == 0.0 {
            continue;
        }
        changed += 1;
        // 1e-3 of the step, and one ulp of each parameter's rounding (as
        // tests/it/nerf_gpu.rs).
        let ulp = f32::EPSILON * before[i].abs().max(cpu_after[i].abs());
        if (dc - dg).abs() > 1e-3 * dc.abs().max(dg.abs()) + 2.0 * ulp {
            mismatched += 1;
        }
    }
    println!("embedding values changed: {changed}; updates beyond 1e-3: {mismatched}");
    assert!(changed >= 2 * EMBEDDING_WIDTH, "{changed}");
    // Only a gradient at the level of summation noise may differ in sign:
    // rare (see tests/it/ngp_gpu.rs).
    assert!(mismatched * 100 <= changed, "{mismatched} of {changed}");
}

/// Pixels of the first validation view (every `step`-th row) rendered by
/// `model` over white.
fn render_rows(model: &dyn RadianceModel, scene: &Scene, step: usize) -> Vec<RenderedPixel> {
    let camera = &scene.val[0].camera;
    let k = camera.intrinsics;
    let (mut origins, mut directions, mut radii) = (Vec::new(), Vec::new(), Vec::new());
    for y in (0..k.height).step_by(step) {
        for x in 0..k.width {
            let ray = camera.pixel_ray(x, y);
            origins.push(ray.origin);
            directions.push(ray.direction);
            radii.push(ray.radius());
        }
    }
    let mut out = vec![RenderedPixel::default(); origins.len()];
    model.render(
        zrak::model::RenderRays {
            origins: &origins,
            directions: &directions,
            radii: &radii,
            background: [1.0; 3],
        },
        &mut out,
    );
    out
}

/// The largest difference of colour or opacity between two renders.
fn largest_difference(a: &[RenderedPixel], b: &[RenderedPixel]) -> f32 {
    let mut worst = 0f32;
    for (a, b) in a.iter().zip(b) {
        for (x, y) in a.rgb.iter().zip(&b.rgb).chain([(&a.opacity, &b.opacity)]) {
            worst = worst.max((x - y).abs());
        }
    }
    worst
}

/// A checkpoint of the gpu model loaded on the cpu engine renders the same
/// pixels with the embeddings' mean and with a chosen image's vector; the
/// two differ by far more than the tolerance (the choice reaches the
/// colour).
fn check_renders(cpu: &mut CpuModel, gpu: &mut GpuModel, scene: &Scene, row_step: usize) {
    cpu.load(&gpu.save())
        .expect("a gpu checkpoint loads on the cpu engine");
    assert!(cpu.params() == gpu.params().as_slice());
    assert_eq!(gpu.appearance_images(), Some(scene.train.len()));
    let mean_gpu = render_rows(gpu, scene, row_step);
    let mean_cpu = render_rows(cpu, scene, row_step);
    let image = scene.train.len() as u32 - 2;
    gpu.set_render_appearance(Some(image as usize)).unwrap();
    cpu.set_render_appearance(Some(image as usize)).unwrap();
    let image_gpu = render_rows(gpu, scene, row_step);
    let image_cpu = render_rows(cpu, scene, row_step);
    let (mean_error, image_error) = (
        largest_difference(&mean_gpu, &mean_cpu),
        largest_difference(&image_gpu, &image_cpu),
    );
    let effect = largest_difference(&image_cpu, &mean_cpu);
    println!(
        "render with the mean: {mean_error:.2e}; with image {image}: {image_error:.2e}; \
         the image against the mean: {effect:.2e}"
    );
    // As tests/it/ngp_gpu.rs: colours in [0, 1], 1e-4 absolute.
    assert!(mean_error <= 1e-4, "mean: {mean_error:e}");
    assert!(image_error <= 1e-4, "image {image}: {image_error:e}");
    assert!(
        effect > 1e-2,
        "the image's vector changes nothing: {effect:e}"
    );
    assert!(
        gpu.set_render_appearance(Some(scene.train.len())).is_err(),
        "an image without a vector is refused"
    );
    gpu.set_render_appearance(None).unwrap();
    assert_eq!(
        largest_difference(&render_rows(gpu, scene, row_step), &mean_gpu),
        0.0,
        "back to the mean"
    );
}

/// Instant-NGP's field with a 2^12-entry table per level (as
/// tests/it/ngp_field_gpu.rs) and a table of appearance embeddings of
/// `images`.
fn small_ngp_shape(images: usize) -> NgpShape {
    let scene = common::small_scene(8);
    let mut shape = NgpShape::for_scene(&scene);
    shape.grid = HashGridLayout::new(&HashGridConfig {
        log2_table_size: 12,
        ..HashGridConfig::paper(scene.unit_cube.aabb_scale)
    });
    shape.with_appearance(Some(AppearanceShape::for_images(images)))
}

/// The gpu field forward and backward with `appearance` (per ray of
/// `rays_of` rows each, where per-sample), its parameters after `offset`
/// others: σ, colour and the gradient.
#[allow(clippy::too_many_arguments)]
fn gpu_field_pass(
    shape: &NgpShape,
    (params, offset): (&[f32], usize),
    positions: &[f32],
    directions: &[f32],
    ray_images: Option<(&[u32], usize)>,
    chosen: Option<u32>,
    d_sigma: &[f32],
    d_rgb: &[f32],
) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
    let context = common::gpu_context();
    let rows = d_sigma.len();
    let mut field = GpuNgpField::new(&context, shape, rows).expect("the kernels compile");
    field.set_param_offset(offset);
    let mut all = vec![0.25f32; offset];
    all.extend_from_slice(params);
    let buffer = |label, v: &[f32]| storage_buffer(&context, label, v);
    let params_buffer = buffer("params", &all);
    let gradients = zeroed_storage_buffer::<f32>(&context, "gradients", all.len());
    let (x, d) = (
        buffer("positions", positions),
        buffer("directions", directions),
    );
    let (ds, dc) = (buffer("d sigma", d_sigma), buffer("d rgb", d_rgb));
    let sigma = zeroed_storage_buffer::<f32>(&context, "sigma", rows);
    let rgb = zeroed_storage_buffer::<f32>(&context, "rgb", 3 * rows);
    let per_ray = ray_images.map(|(images, per_ray)| {
        let offsets: Vec<u32> = (0..=images.len()).map(|r| (r * per_ray) as u32).collect();
        (
            storage_buffer(&context, "ray images", images),
            storage_buffer(&context, "ray offsets", &offsets),
            images.len(),
        )
    });
    let appearance = match (&per_ray, chosen) {
        (Some((images, ray_offsets, rays)), _) => GpuAppearance::PerRay {
            images,
            ray_offsets,
            rays: *rays,
        },
        (None, Some(image)) => GpuAppearance::Image(image),
        (None, None) => GpuAppearance::Mean,
    };
    let mut rec = Recorder::new(&context);
    rec.encoder.clear_buffer(&gradients, 0, None);
    field.record_forward(
        &mut rec,
        &params_buffer,
        FieldInputs {
            positions: &x,
            variances: None,
            directions: &d,
        },
        appearance,
        rows,
        FieldOutputs {
            sigma: &sigma,
            rgb: &rgb,
        },
    );
    field.record_backward(&mut rec, &params_buffer, &ds, &dc, rows, &gradients);
    rec.submit();
    let gradient: Vec<f32> = read_buffer(&context, &gradients, all.len());
    assert!(
        gradient[..offset].iter().all(|&g| g == 0.0),
        "the gradient reached parameters before the field's"
    );
    (
        read_buffer(&context, &sigma, rows),
        read_buffer(&context, &rgb, 3 * rows),
        gradient[offset..].to_vec(),
    )
}

#[test]
fn ngp_field_with_each_appearance_matches_the_cpu_field() {
    let _cores = crate::common::shared();
    const ROWS: usize = 256;
    const PER_RAY: usize = 4;
    const IMAGES: usize = 5;
    let shape = small_ngp_shape(IMAGES);
    let mut params = shape.init_params(5);
    let mut rng = Pcg32::new(5, 3);
    // Table entries in ±0.5, so σ and colour vary from sample to sample.
    for v in &mut params[shape.grid_range()] {
        *v = uniform(&mut rng, -0.5, 0.5);
    }
    let positions: Vec<f32> = (0..3 * ROWS).map(|_| rng.next_f32()).collect();
    let directions: Vec<f32> = (0..ROWS)
        .flat_map(|_| {
            let d = Vec3::new(
                uniform(&mut rng, -1.0, 1.0),
                uniform(&mut rng, -1.0, 1.0),
                uniform(&mut rng, -1.0, 1.0),
            )
            .normalize_or(Vec3::Z);
            d.to_array()
        })
        .collect();
    let d_sigma: Vec<f32> = (0..ROWS).map(|_| uniform(&mut rng, -1.0, 1.0)).collect();
    let d_rgb: Vec<f32> = (0..3 * ROWS)
        .map(|_| uniform(&mut rng, -1.0, 1.0))
        .collect();
    // Rays of four samples, images 0..4 but never image 2 (whose row must
    // get no gradient).
    let ray_images: Vec<u32> = (0..ROWS / PER_RAY)
        .map(|r| [0, 1, 3, 4][r * 7 % 4])
        .collect();
    let sample_images: Vec<u32> = ray_images
        .iter()
        .flat_map(|&image| [image; PER_RAY])
        .collect();
    let table = shape.appearance_range();
    let cases = [
        ("per ray", Appearance::PerSample(&sample_images), None),
        ("image 3", Appearance::Image(3), Some(3)),
        ("mean", Appearance::Mean, None),
    ];
    let mut colours = Vec::new();
    for (what, appearance, chosen) in cases {
        let mut cpu = NgpField::new(shape.clone());
        let (mut sigma, mut rgb) = (vec![0.0; ROWS], vec![0.0; 3 * ROWS]);
        cpu.forward(
            &params,
            &positions,
            None,
            &directions,
            appearance,
            &mut sigma,
            &mut rgb,
        );
        let mut gradient = vec![0.0; params.len()];
        cpu.backward(&params, &d_sigma, &d_rgb, &mut gradient, Gradient::Add);
        let per_ray =
            matches!(appearance, Appearance::PerSample(_)).then_some((&ray_images[..], PER_RAY));
        // A second field's offset (not a multiple of the binding
        // alignment: the table is bound from the aligned offset below).
        for offset in [0, 37] {
            let (gpu_sigma, gpu_rgb, gpu_gradient) = gpu_field_pass(
                &shape,
                (&params, offset),
                &positions,
                &directions,
                per_ray,
                chosen,
                &d_sigma,
                &d_rgb,
            );
            let check = |part: &str, g: &[f32], c: &[f32]| {
                let error = relative_norm(g, c);
                println!("{what}, offset {offset}, {part}: relative error {error:.2e}");
                assert!(
                    error < TOLERANCE,
                    "{what}, offset {offset}, {part}: {error:e}"
                );
            };
            check("σ", &gpu_sigma, &sigma);
            check("colour", &gpu_rgb, &rgb);
            check(
                "colour network",
                &gpu_gradient[shape.colour_range()],
                &gradient[shape.colour_range()],
            );
            check(
                "density network",
                &gpu_gradient[shape.density_range()],
                &gradient[shape.density_range()],
            );
            // Each image's row on its own: a row given another image's
            // gradient is off by O(1).
            for image in 0..IMAGES {
                let row = table.start + image * EMBEDDING_WIDTH
                    ..table.start + (image + 1) * EMBEDDING_WIDTH;
                let (g, c) = (&gpu_gradient[row.clone()], &gradient[row]);
                let expect_none = match appearance {
                    Appearance::PerSample(_) => image == 2,
                    Appearance::Image(chosen) => image != chosen as usize,
                    _ => false,
                };
                if expect_none {
                    assert!(
                        c.iter().chain(g).all(|&x| x == 0.0),
                        "{what}: image {image}"
                    );
                } else {
                    assert!(c.iter().any(|&x| x != 0.0), "{what}: image {image}");
                    check(&format!("image {image}'s vector"), g, c);
                }
            }
        }
        colours.push(rgb);
    }
    // The three kinds give three different colourings.
    for (a, b) in [(0, 1), (1, 2), (0, 2)] {
        assert!(
            relative_norm(&colours[a], &colours[b]) > 1e-3,
            "cases {a} and {b} coloured alike"
        );
    }
}

/// 2^12 samples per batch, as tests/it/ngp_gpu.rs.
const NGP_BATCH_SAMPLES: usize = 1 << 12;

/// Instant-NGP with embeddings on both engines, with a grid occupied in a
/// ball around the centre (as tests/it/ngp_gpu.rs), so rays get ~20
/// samples.
fn ngp_models(scene: &Scene) -> (CpuModel, GpuModel) {
    let mut request = common::request(ModelKind::Ngp, 5, LossKind::Huber, Some(NGP_BATCH_SAMPLES))
        .with_shape(NgpShape::for_scene(scene));
    request.settings.appearance = true;
    let mut cpu = CpuModel::build(&request, scene);
    let mut gpu = build_gpu(common::gpu_context(), &request, scene).expect("gpu model");
    gpu.set_read_back_late(false);
    assert!(gpu.params() == cpu.params(), "initial parameters differ");
    {
        let grid = cpu.occupancy_mut().expect("Instant-NGP has a grid");
        let geometry = grid.geometry();
        for (i, v) in grid.values_mut().iter_mut().enumerate() {
            let centre = geometry.cell_centre(geometry.cell_at(i));
            *v = if (centre - Vec3::splat(0.5)).length() < 0.2 {
                1.0
            } else {
                0.0
            };
        }
        grid.build_bitfield();
    }
    gpu.load(&cpu.save()).unwrap();
    (cpu, gpu)
}

#[test]
fn ngp_step_with_appearance_matches_the_cpu_engine() {
    let _cores = crate::common::shared();
    let scene = common::small_scene(32);
    let (mut cpu, mut gpu) = ngp_models(&scene);
    let rays = batch(&scene, 256, 17);
    let cpu_stats = cpu.forward_backward(&rays, 1);
    let gpu_stats = gpu.forward_backward(&rays, 1);
    assert_eq!(gpu_stats.samples, cpu_stats.samples);
    assert!(cpu_stats.rays >= 20, "{cpu_stats:?}");
    assert!(
        relative(gpu_stats.loss, cpu_stats.loss) < TOLERANCE as f32,
        "loss: gpu {} cpu {}",
        gpu_stats.loss,
        cpu_stats.loss
    );
    check_gradients(&cpu, &gpu, scene.train.len());
    check_step(&mut cpu, &mut gpu, &rays);
}

#[test]
fn ngp_renders_with_the_mean_and_a_chosen_image_as_the_cpu_engine() {
    let _cores = crate::common::shared();
    let scene = common::small_scene(32);
    let (mut cpu, mut gpu) = ngp_models(&scene);
    gpu.step(&batch(&scene, 256, 23), 1);
    check_renders(&mut cpu, &mut gpu, &scene, 4);
}

/// NeRF in miniature with embeddings, the paper's sampler, chunks of 8 rays
/// (a batch of 12 spans two, each with its own rays' images), on both
/// engines.
fn nerf_models(scene: &Scene) -> (CpuModel, GpuModel) {
    let mut request: ModelRequest =
        common::request(ModelKind::Nerf, 3, LossKind::L2, Some(1 << 12))
            .with_shape(common::small_nerf_shape(common::NerfKind::Nerf));
    request.settings.sampling = Sampling::Paper;
    request.settings.appearance = true;
    let mut cpu = CpuModel::build(&request, scene);
    let mut gpu = build_gpu(common::gpu_context(), &request, scene).expect("gpu model");
    gpu.set_read_back_late(false);
    cpu.set_rays_per_chunk(8);
    gpu.set_rays_per_chunk(8).unwrap();
    assert!(gpu.params() == cpu.params(), "initial parameters differ");
    (cpu, gpu)
}

fn nerf_scene() -> Arc<Scene> {
    common::small_scene(24)
}

#[test]
fn nerf_step_with_appearance_matches_the_cpu_engine() {
    let _cores = crate::common::shared();
    let scene = nerf_scene();
    let (mut cpu, mut gpu) = nerf_models(&scene);
    let rays = batch(&scene, 12, 17);
    let cpu_stats = cpu.forward_backward(&rays, 1);
    let gpu_stats = gpu.forward_backward(&rays, 1);
    assert_eq!(gpu_stats.samples, cpu_stats.samples);
    assert!(
        relative(gpu_stats.loss, cpu_stats.loss) < TOLERANCE as f32,
        "loss: gpu {} cpu {}",
        gpu_stats.loss,
        cpu_stats.loss
    );
    check_gradients(&cpu, &gpu, scene.train.len());
    check_step(&mut cpu, &mut gpu, &rays);
}

#[test]
fn nerf_renders_with_the_mean_and_a_chosen_image_as_the_cpu_engine() {
    let _cores = crate::common::shared();
    let scene = nerf_scene();
    let (mut cpu, mut gpu) = nerf_models(&scene);
    gpu.step(&batch(&scene, 12, 23), 1);
    check_renders(&mut cpu, &mut gpu, &scene, 6);
}
