//! Throughput of the gpu engine's dense layers and march on this adapter.

use glam::Vec3;
use zrak::engine::gpu::GpuContext;
use zrak::engine::gpu::dense::GpuDense;
use zrak::engine::gpu::march::GpuMarch;
use zrak::engine::shared::march::MarchParams;
use zrak::engine::shared::occupancy::OccupancyGrid;
use zrak::field::common::{MarchConfig, OccupancyConfig};
use zrak::field::encoding::HashGridConfig;
use zrak::field::mlp::{MlpLayout, NetworkConfig};
use zrak::rng::Pcg32;
use zrak::scene::UnitCubeMapping;

use crate::march::rays;

/// `n` values drawn uniformly from [-scale, scale).
fn random(rng: &mut Pcg32, n: usize, scale: f32) -> Vec<f32> {
    (0..n)
        .map(|_| (2.0 * rng.next_f32() - 1.0) * scale)
        .collect()
}

/// Throughput of the Instant-NGP networks on this adapter (lavapipe here:
/// slow, which is why software adapters get the cpu engine). Run with
/// `cargo bench --bench probes -- dense_throughput`.
pub fn dense_throughput() {
    use zrak::engine::gpu::dense::{GpuMlpWorkspace, MlpGradients};
    use zrak::engine::gpu::kernel::{
        FloatsAt, Recorder, read_buffer, storage_buffer, zeroed_storage_buffer,
    };
    let context = GpuContext::new().expect("an adapter exists");
    eprintln!("adapter: {}", context.describe());
    let dense = GpuDense::new(&context).unwrap();
    let rows = 1 << 16;
    let ngp = NetworkConfig::PAPER;
    for layout in [
        MlpLayout::ngp_density(&ngp, &HashGridConfig::paper(1.0)),
        MlpLayout::ngp_colour(&ngp),
    ] {
        let mut rng = Pcg32::new(1, 1);
        let params = storage_buffer(&context, "params", &layout.init_params(1));
        let input = storage_buffer(
            &context,
            "input",
            &random(&mut rng, rows * layout.input_width(), 1.0),
        );
        let d_output = storage_buffer(
            &context,
            "d_out",
            &random(&mut rng, rows * layout.output_width(), 1.0),
        );
        let d_params = zeroed_storage_buffer::<f32>(&context, "d_params", layout.param_count());
        let d_input =
            zeroed_storage_buffer::<f32>(&context, "d_input", rows * layout.input_width());
        let workspace = GpuMlpWorkspace::new(&context, &layout, rows);
        let run = |backward: bool| {
            let start = std::time::Instant::now();
            let mut rec = Recorder::new(&context);
            let network = FloatsAt::start(&params);
            dense.record_forward(&mut rec, network, &input, &workspace, rows);
            if backward {
                let gradients = MlpGradients {
                    output: &d_output,
                    params: &d_params,
                    input: Some(&d_input),
                };
                dense.record_backward(&mut rec, network, &input, &workspace, gradients, rows);
            }
            rec.submit();
            let _: Vec<f32> = read_buffer(&context, &d_params, 1);
            start.elapsed().as_secs_f64()
        };
        run(true);
        let forward = run(false);
        let both = run(true);
        let flop = 2.0 * (layout.macs_per_row() * rows) as f64;
        eprintln!(
            "{:?}: forward {:.0} ms ({:.2} GFLOP/s), forward+backward {:.0} ms ({:.2} GFLOP/s)",
            layout.widths,
            forward * 1e3,
            flop / forward / 1e9,
            both * 1e3,
            3.0 * flop / both / 1e9
        );
    }
}

/// Throughput of the gpu march (on lavapipe here): about 2^18 samples over
/// a ball of radius 0.35. Run with
/// `cargo bench --bench probes -- gpu_march_throughput`.
pub fn gpu_march_throughput() {
    let context = GpuContext::new().expect("lavapipe or a GPU");
    eprintln!("adapter: {}", context.describe());
    let gpu = GpuMarch::new(&context).unwrap();
    let mut grid = OccupancyGrid::new(OccupancyConfig::PAPER, 1, MarchConfig::PAPER.step);
    let geometry = grid.geometry();
    for (i, v) in grid.values_mut().iter_mut().enumerate() {
        let centre = geometry.cell_min(geometry.cell_at(i)) + Vec3::splat(0.5 / 128.0);
        *v = if centre.distance(Vec3::splat(0.5)) < 0.35 {
            1.0
        } else {
            0.0
        };
    }
    grid.build_bitfield();
    let (origins, directions) = rays(1400, 3);
    let ray_count = origins.len() / 3;
    let params = MarchParams::training(UnitCubeMapping::BLENDER, 1);
    let (_, stats) = gpu.march(&context, &grid, &origins, &directions, &params, 1 << 20);
    let iterations = 10;
    let started = std::time::Instant::now();
    for _ in 0..iterations {
        gpu.march(&context, &grid, &origins, &directions, &params, 1 << 20);
    }
    let seconds = started.elapsed().as_secs_f64() / iterations as f64;
    eprintln!(
        "{ray_count} rays, {} samples: {:.1} ms per march with upload and read-back, {:.2} M samples/s",
        stats.samples,
        1e3 * seconds,
        stats.samples as f64 / seconds / 1e6
    );
}
