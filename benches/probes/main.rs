//! Probes that print measurements and assert nothing, run by name:
//! `cargo bench --bench probes -- NAME...` (the bench profile is the
//! release one). Each says what it measures and which environment
//! variables set it up; without a name, the list. They were ignored tests
//! of the integration tests until issue 28 kept tests to what they assert.

#[allow(dead_code)]
#[path = "../../tests/it/common/march.rs"]
mod march;

mod cpu;
mod gpu;
mod large_demo;

/// Each probe: its name, what it prints, and the function.
const PROBES: &[(&str, &str, fn())] = &[
    (
        "large_demo_figures",
        "Instant-NGP trained on the large demo: samples per ray, step time, val PSNR",
        large_demo::large_demo_figures,
    ),
    (
        "large_demo_grid_by_cascade",
        "occupied share of each cascade of the run in ZRAK_GRID_RUN",
        large_demo::large_demo_grid_by_cascade,
    ),
    (
        "large_demo_occupied_cells_now",
        "whether the occupied cells of ZRAK_GRID_RUN's grid hold density now",
        large_demo::large_demo_occupied_cells_now,
    ),
    (
        "large_demo_weight_by_distance",
        "compositing weight by distance along training rays of ZRAK_GRID_RUN",
        large_demo::large_demo_weight_by_distance,
    ),
    (
        "dense_throughput",
        "GFLOP/s of the gpu dense layers (Instant-NGP's networks) on this adapter",
        gpu::dense_throughput,
    ),
    (
        "cpu_dense_throughput",
        "GFLOP/s of the cpu dense layers (Instant-NGP's networks, NeRF's trunk), 2^18 rows",
        cpu::cpu_dense_throughput,
    ),
    (
        "cpu_hash_grid_throughput",
        "samples per second of the cpu hash grid, forward and backward, 2^18 samples",
        cpu::cpu_hash_grid_throughput,
    ),
    (
        "cpu_march_throughput",
        "samples per second of the cpu march on a lego-like grid, 2^18 samples a batch",
        cpu::cpu_march_throughput,
    ),
    (
        "cpu_composite_throughput",
        "samples per second of cpu compositing, forward and backward, 2^18 samples",
        cpu::cpu_composite_throughput,
    ),
    (
        "cpu_adam_throughput",
        "parameters per second of the optimiser on Instant-NGP's parameter count",
        cpu::cpu_adam_throughput,
    ),
    (
        "gpu_march_throughput",
        "samples per second of the gpu march on this adapter",
        gpu::gpu_march_throughput,
    ),
];

fn main() {
    // `cargo bench` passes `--bench`; the other arguments name probes.
    let names: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| !a.starts_with("--"))
        .collect();
    if names.is_empty() {
        println!("probes (cargo bench --bench probes -- NAME...):");
        for (name, what, _) in PROBES {
            println!("  {name:<30} {what}");
        }
        return;
    }
    for name in &names {
        let Some((_, _, probe)) = PROBES.iter().find(|p| p.0 == name) else {
            eprintln!("no probe is named {name:?}: `cargo bench --bench probes` lists them");
            std::process::exit(2);
        };
        probe();
    }
}
