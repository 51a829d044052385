//! Rays to march through occupancy grids, shared by the march tests and
//! the probes of `benches/probes` (which include this file on its own).

use glam::Vec3;
use zrak::engine::shared::occupancy::mix64;
use zrak::scene::{Scene, UnitCubeMapping};

/// A uniform draw in [0, 1) from the hash of `key` (24 bits).
pub fn uniform(key: u64) -> f32 {
    (mix64(key) >> 40) as f32 / (1u64 << 24) as f32
}

/// Rays from a sphere of radius 4 towards the box, some from inside it,
/// and the hard cases: axis-parallel (also along cell boundaries and box
/// faces), missing, zero direction.
pub fn rays(n: usize, seed: u64) -> (Vec<f32>, Vec<f32>) {
    let mut origins = Vec::new();
    let mut directions = Vec::new();
    let mut push = |o: Vec3, d: Vec3| {
        origins.extend_from_slice(&o.to_array());
        directions.extend_from_slice(&d.to_array());
    };
    let face = UnitCubeMapping::BLENDER.to_world(Vec3::new(1.0, 0.25, 0.5));
    push(Vec3::new(0.0, 0.0, 4.0), -Vec3::Z);
    push(Vec3::new(face.x, face.y, 4.0), -Vec3::Z);
    push(Vec3::new(-4.0, 0.3, -0.2), Vec3::X);
    push(Vec3::ZERO, Vec3::Y);
    push(Vec3::new(0.0, 3.0, 4.0), -Vec3::Z);
    push(Vec3::new(0.0, 0.0, 4.0), Vec3::Z);
    push(Vec3::new(0.0, 0.0, 4.0), Vec3::ZERO);
    let u = |i: usize, j: u64| uniform(seed ^ mix64((i as u64) * 16 + j));
    for i in 0..n {
        let z = 2.0 * u(i, 0) - 1.0;
        let phi = std::f32::consts::TAU * u(i, 1);
        let r = (1.0 - z * z).sqrt();
        let radius = if i % 8 == 0 { 1.2 * u(i, 2) } else { 4.0 };
        let origin = radius * Vec3::new(r * phi.cos(), r * phi.sin(), z);
        let target = Vec3::new(u(i, 3), u(i, 4), u(i, 5)) * 2.4 - 1.2;
        push(origin, (target - origin).normalize());
    }
    (origins, directions)
}

/// Origins and directions of `rays` rays through pixels spread over the
/// training views of `scene`.
pub fn training_rays(scene: &Scene, rays: usize) -> (Vec<glam::Vec3>, Vec<glam::Vec3>) {
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
pub struct MarchedTrainingRays {
    pub origins: Vec<glam::Vec3>,
    pub directions: Vec<glam::Vec3>,
    pub samples: zrak::engine::shared::march::MarchedSamples,
    pub stats: zrak::engine::shared::march::MarchStats,
}

pub fn march_training_rays(
    scene: &Scene,
    grid: &zrak::engine::shared::occupancy::OccupancyGrid,
    config: zrak::field::common::MarchConfig,
    rays: usize,
) -> MarchedTrainingRays {
    use zrak::engine::cpu::march::{MarchWorkspace, march};
    use zrak::engine::shared::march::{MarchParams, MarchedSamples};
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
pub fn samples_per_ray(
    scene: &Scene,
    grid: &zrak::engine::shared::occupancy::OccupancyGrid,
    config: zrak::field::common::MarchConfig,
    rays: usize,
) -> f64 {
    march_training_rays(scene, grid, config, rays).stats.samples as f64 / rays as f64
}
