//! Real-capture features end to end on scenes whose truth is known exactly:
//! the demo photographed through distorting lenses (training with the lens
//! modelled matches the undistorted demo; ignoring it is clearly worse), and
//! the large-extent demo marched with cone steps.

use std::sync::Arc;
use std::time::Instant;

use zrak::engine::cpu::model::CpuModel;
use zrak::field::ngp::LossKind;
use zrak::scene::demo::{self, DemoConfig};
use zrak::scene::{Lens, Scene};
use zrak::train::eval::score_view;
use zrak::train::trainer::Trainer;

fn env_or<T: std::str::FromStr>(name: &str, default: T) -> T {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

/// Small views and few steps: each run takes ~10 s on two idle cores.
fn config() -> DemoConfig {
    DemoConfig {
        size: env_or("ZRAK_CAPTURES_SIZE", 40u32),
        train_views: 60,
        val_views: 4,
        test_views: 1,
    }
}

/// Trains Instant-NGP on `scene` for a fixed number of steps; the mean
/// PSNR on the validation views of `held_out`.
fn train_and_score(scene: Scene, held_out: &Scene) -> f64 {
    let steps = env_or("ZRAK_CAPTURES_STEPS", 120u32);
    let batch = env_or("ZRAK_CAPTURES_BATCH", 1usize << 14);
    let scene = Arc::new(scene);
    let model = zrak::train::cpu_ngp_with_shape(
        &scene,
        zrak::engine::cpu::fields::ngp::NgpShape::for_scene(&scene),
        0,
        LossKind::Huber,
        Some(batch),
    );
    let mut trainer = Trainer::new(Box::new(model), scene.clone(), 0);
    let started = Instant::now();
    while trainer.step < steps {
        trainer.step();
    }
    let psnr = held_out
        .val
        .iter()
        .map(|f| score_view(trainer.model.as_ref(), f, false).psnr)
        .sum::<f64>()
        / held_out.val.len() as f64;
    eprintln!(
        "{}: {psnr:.2} dB after {steps} steps ({:.1} s)",
        scene.name,
        started.elapsed().as_secs_f64()
    );
    psnr
}

/// `scene` with every camera's lens replaced by a pinhole: the photographs
/// as a loader that ignores distortion would see them.
fn ignoring_the_lens(scene: &Scene) -> Scene {
    let mut ignored = scene.clone();
    for frame in ignored
        .train
        .iter_mut()
        .chain(&mut ignored.val)
        .chain(&mut ignored.test)
    {
        frame.camera.intrinsics.lens = Lens::Pinhole;
    }
    ignored.name = format!("{} (lens ignored)", scene.name);
    ignored
}

/// The undistorted reference is the demo photographed by the same cameras
/// at the same size without the lens, so the lens is the only difference.
/// Measured before (40 px reference, 120 steps of 2^14 samples, seed 0, a
/// loaded 2-core machine) against the demo at the held-out views' own 40 px:
/// undistorted 18.32 dB; the barrel lens modelled 17.34 dB (photographs at
/// 40 px), 17.68 dB (60 px), 17.61 dB (80 px), a steady ~0.7 dB short. That
/// reference differed in two ways besides the lens: its photographs were
/// taken at the held-out views' own resolution (a field trained on larger
/// photographs renders 40-pixel views sharper than their area-averaged
/// pixels), and it had fewer pixels to learn from.
#[test]
fn modelled_lens_distortion_trains_as_well_as_no_distortion() {
    let config = config();
    // Distortion is third order in the angle off axis, and the demo's
    // objects span only ~0.2 (normalised) from the centre of its narrow
    // views: the lenses must be strong for the bend to reach pixels there.
    // Barrel (k1 < 0), so the distorted views see more than the undistorted
    // ones and every part of the held-out views is trained (a pincushion
    // lens, k1 = 4, left the edges of the held-out views unseen and scored
    // 1.4 dB lower); k2 > 0.45 k1² keeps the mapping from folding
    // (1 + 3 k1 r² + 5 k2 r⁴ > 0). At r = 0.2 the bend is 0.023, 1.3 px at
    // 40 px.
    let radial = Lens::RadialTangential {
        k1: -3.0,
        k2: 4.1,
        k3: 0.0,
        k4: 0.0,
        p1: 0.01,
        p2: -0.01,
    };
    let fisheye = Lens::Fisheye {
        k1: -3.0,
        k2: 4.1,
        k3: 0.0,
        k4: 0.0,
    };
    let plain = demo::build(&config);
    // The barrel lens shrinks the objects' image to f'(0.2) = 0.67 of the
    // pinhole's across: the photographs are taken at twice the held-out
    // views' pixels (focal length in pixels too, the same field of view at
    // the centre) so that the objects get at least as many pixels as in
    // the held-out views. Training costs the same (batches are counted in
    // samples).
    let photographed = DemoConfig {
        size: config.size * 2,
        ..config
    };
    let reference = train_and_score(demo::build(&photographed), &plain);
    // Ignoring the lens is checked for one model only: each run costs
    // ~10 s on two idle cores.
    for (lens, check_ignored) in [(radial, true), (fisheye, false)] {
        let distorted = demo::build_distorted(&photographed, lens);
        // Every model is scored on the undistorted demo's held-out views:
        // a field that learned the true scene renders them as well as one
        // trained on undistorted photographs; a field warped by an
        // ignored lens does not.
        let modelled = train_and_score(distorted.clone(), &plain);
        eprintln!("{lens:?}: undistorted {reference:.2} dB, modelled {modelled:.2} dB");
        assert!(
            modelled > reference - 0.5,
            "{lens:?}: modelled {modelled:.2} dB vs undistorted {reference:.2} dB"
        );
        if check_ignored {
            let ignored_scene = ignoring_the_lens(&distorted);
            let ignored = train_and_score(ignored_scene, &plain);
            eprintln!("{lens:?}: ignored {ignored:.2} dB");
            assert!(
                ignored < modelled - 1.0,
                "{lens:?}: ignored {ignored:.2} dB vs modelled {modelled:.2} dB"
            );
        }
    }
}

/// Origins and directions of `rays` rays through pixels spread over the
/// training views of `scene`.
fn training_rays(scene: &Scene, rays: usize) -> (Vec<glam::Vec3>, Vec<glam::Vec3>) {
    (0..rays)
        .map(|r| {
            let frame = &scene.train[r % scene.train.len()];
            let k = frame.camera.intrinsics;
            let i = (r * 7919) as u32;
            let ray = frame
                .camera
                .pixel_ray(i % k.width, (i / k.width) % k.height);
            (ray.origin, ray.direction)
        })
        .unzip()
}

/// `rays` training rays of `scene` ([`training_rays`]) marched through
/// `grid` with `config` and the first-sample offsets of training, no budget.
struct MarchedTrainingRays {
    origins: Vec<glam::Vec3>,
    directions: Vec<glam::Vec3>,
    samples: zrak::engine::cpu::march::MarchedSamples,
    stats: zrak::engine::cpu::march::MarchStats,
}

fn march_training_rays(
    scene: &Scene,
    grid: &zrak::engine::cpu::occupancy::OccupancyGrid,
    config: zrak::field::ngp::MarchConfig,
    rays: usize,
) -> MarchedTrainingRays {
    use zrak::engine::cpu::march::{MarchParams, MarchWorkspace, MarchedSamples, march};
    let (origins, directions) = training_rays(scene, rays);
    let flat = |v: &[glam::Vec3]| v.iter().flat_map(|p| p.to_array()).collect::<Vec<f32>>();
    let params = MarchParams {
        config,
        ..MarchParams::training(scene.unit_cube, 1)
    };
    let mut samples = MarchedSamples::default();
    let stats = march(
        grid,
        &flat(&origins),
        &flat(&directions),
        &params,
        &mut MarchWorkspace::default(),
        &mut samples,
    );
    MarchedTrainingRays {
        origins,
        directions,
        samples,
        stats,
    }
}

/// Mean samples per ray of `rays` training rays of `scene` marched through
/// `grid` with `config`.
fn samples_per_ray(
    scene: &Scene,
    grid: &zrak::engine::cpu::occupancy::OccupancyGrid,
    config: zrak::field::ngp::MarchConfig,
    rays: usize,
) -> f64 {
    march_training_rays(scene, grid, config, rays).stats.samples as f64 / rays as f64
}

/// Mean samples per ray, and of them those beyond the large demo's
/// backdrop sphere (where no training ray's gradient reaches: every ray
/// that gets there is opaque), of `rays` training rays marched through
/// `grid` with `config`.
fn samples_beyond_backdrop(
    scene: &Scene,
    grid: &zrak::engine::cpu::occupancy::OccupancyGrid,
    config: zrak::field::ngp::MarchConfig,
    rays: usize,
) -> (f64, f64) {
    let marched = march_training_rays(scene, grid, config, rays);
    let (out, stats) = (&marched.samples, marched.stats);
    let mut beyond = 0usize;
    for r in 0..stats.rays_kept {
        for s in out.ray(r) {
            let p = marched.origins[r] + out.t[s] * marched.directions[r];
            beyond += usize::from(p.length() > demo::BACKDROP_RADIUS);
        }
    }
    let kept = stats.rays_kept.max(1) as f64;
    (stats.samples as f64 / kept, beyond as f64 / kept)
}

/// On the large-extent demo (aabb_scale 8), with a grid occupied only near
/// the objects and the backdrop, cone steps take a third of the fixed
/// step's samples.
#[test]
fn cone_steps_march_the_large_demo_in_proportion() {
    use zrak::engine::cpu::occupancy::{Cell, OccupancyGrid};
    use zrak::field::ngp::MarchConfig;
    let scene = demo::build_large(&DemoConfig {
        size: 16,
        train_views: 20,
        val_views: 1,
        test_views: 1,
    });
    assert_eq!(scene.unit_cube.aabb_scale, demo::LARGE_AABB_SCALE);
    let fixed = MarchConfig {
        cone_angle: 0.0,
        ..MarchConfig::PAPER
    };
    let untrained = OccupancyGrid::for_scene(&scene.unit_cube);
    let fixed_untrained = samples_per_ray(&scene, &untrained, fixed, 2000);
    let cone_untrained = samples_per_ray(&scene, &untrained, MarchConfig::PAPER, 2000);
    // A grid that knows the scene: occupied within 1.2 world units of the
    // centre (the objects) and in a shell around the backdrop's radius.
    let mapping = scene.unit_cube;
    let mut trained = OccupancyGrid::for_scene(&mapping);
    let geometry = trained.geometry();
    let n = geometry.resolution;
    for cascade in 0..geometry.cascades {
        for x in 0..n {
            for y in 0..n {
                for z in 0..n {
                    let cell = Cell {
                        cascade,
                        xyz: [x, y, z],
                    };
                    let centre = geometry.cell_min(cell)
                        + glam::Vec3::splat(0.5 * geometry.cell_size(cascade));
                    let world = mapping.to_world(centre).length();
                    let near_something = world < 1.2 || (world - demo::BACKDROP_RADIUS).abs() < 0.5;
                    trained.values_mut()[geometry.linear_index(cell)] =
                        if near_something { 1.0 } else { 0.0 };
                }
            }
        }
    }
    trained.build_bitfield();
    let fixed_trained = samples_per_ray(&scene, &trained, fixed, 2000);
    let cone_trained = samples_per_ray(&scene, &trained, MarchConfig::PAPER, 2000);
    eprintln!(
        "samples per ray, fixed step / cone: untrained grid {fixed_untrained:.0} / \
         {cone_untrained:.0}, scene-shaped grid {fixed_trained:.0} / {cone_trained:.0}"
    );
    // Every cell occupied, both reach the cap on most rays (the box is
    // 24 world units across; 256 samples per doubling still need more).
    assert!(fixed_untrained > 900.0, "{fixed_untrained}");
    assert!(cone_untrained <= fixed_untrained, "{cone_untrained}");
    // Measured: 379 with the fixed step, 116 with cones (the object ball
    // here is solid; a trained grid holds surfaces only).
    assert!(
        cone_trained < 0.4 * fixed_trained,
        "{cone_trained} vs {fixed_trained}"
    );
}

/// The figures issue 14 asks for, not run by default (two minutes of
/// training): Instant-NGP on the large-extent demo for
/// `ZRAK_CAPTURES_SECONDS` (120) training seconds, printing samples per
/// ray, step time and held-out PSNR. Run it twice, with
/// `ZRAK_CONE_ANGLE=0` (fixed step) and without (cone steps):
/// `cargo test --test captures large_demo_figures -- --ignored --nocapture`.
#[test]
#[ignore]
fn large_demo_figures() {
    let seconds = env_or("ZRAK_CAPTURES_SECONDS", 120.0f64);
    let scene = Arc::new(demo::build_large(&DemoConfig {
        size: env_or("ZRAK_CAPTURES_SIZE", 64u32),
        train_views: 100,
        val_views: 5,
        test_views: 1,
    }));
    let model = zrak::train::cpu_ngp_with_shape(
        &scene,
        zrak::engine::cpu::fields::ngp::NgpShape::for_scene(&scene),
        0,
        LossKind::Huber,
        Some(1 << 18),
    );
    let mut trainer = Trainer::new(Box::new(model), scene.clone(), 0);
    let mut window = (0usize, 0usize, 0u32, 0f64);
    let mut next_report = 15.0;
    while trainer.train_seconds < seconds {
        let before = trainer.train_seconds;
        let stats = trainer.step();
        window.0 += stats.samples;
        window.1 += stats.rays;
        window.2 += 1;
        window.3 += trainer.train_seconds - before;
        if trainer.train_seconds >= next_report || trainer.train_seconds >= seconds {
            next_report += 15.0;
            let clock = Instant::now();
            let psnr = scene
                .val
                .iter()
                .map(|f| score_view(trainer.model.as_ref(), f, false).psnr)
                .sum::<f64>()
                / scene.val.len() as f64;
            eprintln!(
                "step {} train {:.0} s: {:.1} samples/ray, {} rays/step, {:.0} ms/step, \
                 val PSNR {psnr:.2} dB (eval {:.1} s)",
                trainer.step,
                trainer.train_seconds,
                window.0 as f64 / window.1.max(1) as f64,
                window.1 / window.2.max(1) as usize,
                1000.0 * window.3 / window.2.max(1) as f64,
                clock.elapsed().as_secs_f64()
            );
            window = (0, 0, 0, 0.0);
        }
    }
}

/// The Instant-NGP model of the run in `ZRAK_GRID_RUN` (a run of `zrak
/// train` on the scene `zrak demo --large` writes), loaded for `scene`.
fn model_of_run(scene: &Scene) -> CpuModel {
    use zrak::train::checkpoint::Checkpoint;
    use zrak::train::model::RadianceModel;
    let run = std::path::PathBuf::from(std::env::var("ZRAK_GRID_RUN").expect("ZRAK_GRID_RUN"));
    let mut checkpoint = Checkpoint::load(&run.join("checkpoint.zrak")).expect("checkpoint");
    // A run's checkpoint holds the trainer's state beside the model's.
    checkpoint.header = checkpoint.header["model"].clone();
    let mut model = zrak::train::cpu_ngp_with_shape(
        scene,
        zrak::engine::cpu::fields::ngp::NgpShape::for_scene(scene),
        0,
        LossKind::Huber,
        Some(1 << 18),
    );
    model
        .load(&checkpoint)
        .expect("an Instant-NGP checkpoint of this scene");
    model
}

/// Where a trained grid on the large-extent demo keeps its samples, not run
/// by default: the occupied share of each cascade and the samples per ray
/// of training rays, from the checkpoint of a run of `zrak train` on the
/// scene `zrak demo --large` writes (`ZRAK_GRID_RUN=RUN cargo test --test
/// captures large_demo_grid_by_cascade -- --ignored --nocapture`).
#[test]
#[ignore]
fn large_demo_grid_by_cascade() {
    use zrak::field::ngp::MarchConfig;
    let scene = demo::build_large(&DemoConfig::default());
    let model = model_of_run(&scene);
    let grid = model.occupancy().expect("Instant-NGP has a grid");
    let geometry = grid.geometry();
    let per = geometry.cells_per_cascade();
    for cascade in 0..geometry.cascades as usize {
        let occupied = (cascade * per..(cascade + 1) * per)
            .filter(|&i| grid.is_occupied(geometry.cell_at(i)))
            .count();
        eprintln!(
            "cascade {cascade}: {:.2} % of cells occupied",
            100.0 * occupied as f64 / per as f64
        );
    }
    let fixed = MarchConfig {
        cone_angle: 0.0,
        ..MarchConfig::PAPER
    };
    eprintln!(
        "threshold {:.4}; samples per ray: fixed step {:.0}, cone steps {:.0}",
        grid.threshold(),
        samples_per_ray(&scene, grid, fixed, 4000),
        samples_per_ray(&scene, grid, MarchConfig::PAPER, 4000)
    );
    let (marched, beyond) = samples_beyond_backdrop(&scene, grid, MarchConfig::PAPER, 4000);
    eprintln!("cone steps: {marched:.0} samples per ray, {beyond:.0} of them beyond the backdrop");
}

/// Whether the large demo's occupied cells hold density now or only held it
/// once, not run by default: for each cascade, among the cells inside the
/// backdrop sphere that the grid marks occupied, the share whose density at
/// 16 random points (σ times the cascade's step, the grid's own measure)
/// exceeds the threshold at the mean, at the median and at the largest of
/// them, with the quartiles of those medians; then the share of each
/// spherical shell around the objects that occupied cells fill (while
/// the hash grid spanned only the unit cube, after `zrak train large
/// --time 2m`: 23 % inside the objects' sphere, 22 %
/// between it and the cameras, 61, 78, 92, 96 % in the shells out to the
/// backdrop; after 10 minutes 26, 28, 71, 85, 95, 98 %).
/// `ZRAK_GRID_RUN=RUN cargo test --release --test captures
/// large_demo_occupied_cells_now -- --ignored --nocapture`.
#[test]
#[ignore]
fn large_demo_occupied_cells_now() {
    let scene = demo::build_large(&DemoConfig {
        size: 16,
        train_views: 100,
        val_views: 1,
        test_views: 1,
    });
    let model = model_of_run(&scene);
    let grid = model.occupancy().expect("Instant-NGP has a grid");
    let geometry = grid.geometry();
    let per = geometry.cells_per_cascade();
    let backdrop = demo::BACKDROP_RADIUS * scene.unit_cube.scale;
    let centre = scene.unit_cube.offset;
    const POINTS: usize = 16;
    let mut state = 1u64;
    let mut uniform = || {
        state = zrak::engine::cpu::occupancy::mix64(state.wrapping_add(0x9E37_79B9_7F4A_7C15));
        (state >> 40) as f32 / (1u64 << 24) as f32
    };
    for cascade in 0..geometry.cascades {
        let size = geometry.cell_size(cascade);
        let cells: Vec<_> = (cascade as usize * per..(cascade as usize + 1) * per)
            .map(|i| geometry.cell_at(i))
            .filter(|&cell| {
                let middle = geometry.cell_centre(cell);
                grid.is_occupied(cell) && (middle - centre).length() < backdrop - size
            })
            .collect();
        let mut positions = Vec::with_capacity(cells.len() * POINTS * 3);
        for &cell in &cells {
            let min = geometry.cell_min(cell);
            for _ in 0..POINTS {
                let p = min + size * glam::Vec3::new(uniform(), uniform(), uniform());
                positions.extend_from_slice(&p.to_array());
            }
        }
        let sigma = model.densities(&positions);
        let step = grid.cascade_step(cascade);
        let threshold = grid.threshold();
        let (mut by_mean, mut by_median, mut by_max) = (0usize, 0usize, 0usize);
        let mut medians = Vec::with_capacity(cells.len());
        for values in sigma.chunks_exact(POINTS) {
            let mut thickness: Vec<f32> = values.iter().map(|s| s * step).collect();
            thickness.sort_by(f32::total_cmp);
            let mean = thickness.iter().sum::<f32>() / POINTS as f32;
            by_mean += usize::from(mean > threshold);
            by_median += usize::from(thickness[POINTS / 2] > threshold);
            by_max += usize::from(thickness[POINTS - 1] > threshold);
            medians.push(thickness[POINTS / 2]);
        }
        medians.sort_by(f32::total_cmp);
        let quantile = |q: f64| {
            medians
                .get(((medians.len() as f64 - 1.0) * q) as usize)
                .copied()
                .unwrap_or(f32::NAN)
        };
        let share = |n: usize| 100.0 * n as f64 / cells.len().max(1) as f64;
        eprintln!(
            "cascade {cascade}: {} occupied cells inside the backdrop; above the threshold \
             now ({threshold:.2e}): mean {:.1} %, median {:.1} %, largest of {POINTS} points \
             {:.1} %; the cells' median thickness at quartiles 1, 2, 3: {:.2e}, {:.2e}, {:.2e}",
            cells.len(),
            share(by_mean),
            share(by_median),
            share(by_max),
            quantile(0.25),
            quantile(0.5),
            quantile(0.75)
        );
    }
    // Where the occupied space lies: the share of each spherical shell
    // around the objects (world units; the cameras are 4 from the centre,
    // the backdrop 10) that occupied cells fill, each cell counted once,
    // in the finest cascade that holds it.
    let shells = [0.0, 1.25, 3.0, 5.0, 7.0, 9.0, 10.0, f32::INFINITY];
    let mut filled = vec![0f64; shells.len() - 1];
    let mut volume = vec![0f64; shells.len() - 1];
    for cell in (0..geometry.cell_count()).map(|i| geometry.cell_at(i)) {
        let size = geometry.cell_size(cell.cascade);
        let middle = geometry.cell_centre(cell);
        // A cell a finer cascade covers is counted there.
        if geometry.cascade_of(middle) != cell.cascade {
            continue;
        }
        let radius = (middle - centre).length() / scene.unit_cube.scale;
        let shell = shells
            .windows(2)
            .position(|w| radius >= w[0] && radius < w[1]);
        if let Some(shell) = shell {
            let v = f64::from(size).powi(3);
            volume[shell] += v;
            if grid.is_occupied(cell) {
                filled[shell] += v;
            }
        }
    }
    for (i, w) in shells.windows(2).enumerate() {
        eprintln!(
            "shell {:>4.2}–{:<4.2} world units from the centre: {:.1} % occupied",
            w[0],
            w[1],
            100.0 * filled[i] / volume[i].max(f64::MIN_POSITIVE)
        );
    }
}

/// Where along training rays the large demo's field puts its weight, not
/// run by default: for 4000 training rays marched through a run's grid
/// (cone steps), the samples marched and composited per ray (those before
/// the transmittance falls below 1e-4) and the compositing weight in bands
/// of distance from the camera, with the band holding each ray's median
/// depth. The cameras are 4 world units from the objects' centre, look at
/// it with a 40° field of view, and the objects lie within 1.25 of it, so
/// a ray meets an object 2.75 to 5.25 units out or the backdrop (radius
/// 10) 13.4 to 14 units out, and nothing in between. After `zrak train
/// large --time 2m`, 67 % of the rays have their median depth 11 to 14
/// units out and 0.3 % 6 to 11 units out. While the hash grid spanned only
/// the unit cube, 46 % had it 6 to 11 units out and 0.9 % beyond 11: the
/// backdrop was drawn as a thick cloud behind and under the objects, where
/// the extruded faces of the unit cube could draw it, and each ray
/// composited ~150 of its ~195 samples in it.
/// `ZRAK_GRID_RUN=RUN cargo test --release --test captures
/// large_demo_weight_by_distance -- --ignored --nocapture`.
#[test]
#[ignore]
fn large_demo_weight_by_distance() {
    use zrak::field::ngp::MarchConfig;
    let scene = demo::build_large(&DemoConfig::default());
    let model = model_of_run(&scene);
    let marched = march_training_rays(&scene, model.occupancy().unwrap(), MarchConfig::PAPER, 4000);
    let (out, stats) = (&marched.samples, marched.stats);
    let sigma = model.densities(&out.positions);
    let edges = [
        0.0f32,
        0.25,
        0.5,
        1.0,
        1.5,
        2.0,
        3.0,
        4.0,
        6.0,
        8.0,
        11.0,
        14.0,
        f32::INFINITY,
    ];
    let bands = edges.len() - 1;
    let band_of = |t: f32| {
        edges
            .windows(2)
            .position(|w| t >= w[0] && t < w[1])
            .unwrap_or(bands - 1)
    };
    let mut marched = vec![0usize; bands];
    let mut composited = vec![0usize; bands];
    let mut weight = vec![0f64; bands];
    let mut median_depths = vec![0usize; bands];
    let min_transmittance = MarchConfig::PAPER.min_transmittance;
    for r in 0..stats.rays_kept {
        let mut transmittance = 1f32;
        let mut weight_so_far = 0f32;
        let mut median_found = false;
        for s in out.ray(r) {
            let band = band_of(out.t[s]);
            marched[band] += 1;
            if transmittance < min_transmittance {
                continue;
            }
            composited[band] += 1;
            let alpha = 1.0 - (-sigma[s] * out.dt[s]).exp();
            let w = transmittance * alpha;
            weight[band] += w as f64;
            weight_so_far += w;
            if !median_found && weight_so_far > 0.5 {
                median_depths[band] += 1;
                median_found = true;
            }
            transmittance *= 1.0 - alpha;
        }
    }
    let kept = stats.rays_kept.max(1) as f64;
    eprintln!(
        "{} rays, {:.0} samples marched per ray",
        stats.rays_kept,
        stats.samples as f64 / kept
    );
    for band in 0..bands {
        eprintln!(
            "{:5.2} to {:5.2} world units out: marched {:6.1}, composited {:6.1}, weight {:.3}, \
             median depth of {:4.1} % of the rays",
            edges[band],
            edges[band + 1],
            marched[band] as f64 / kept,
            composited[band] as f64 / kept,
            weight[band] / kept,
            100.0 * median_depths[band] as f64 / kept
        );
    }
}
