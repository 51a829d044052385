//! Benchmarks that print figures: training throughput per stage, and the
//! accuracy-versus-time experiment with its report. Nothing here asserts
//! on time.

pub mod gpu;
pub mod plot;
pub mod published;
pub mod quality;
pub mod report;
pub mod table;

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use crate::engine::gpu::{CounterReading, GpuCounters};
use crate::model::{Stage, StageTimes, StepStats};
use crate::scene::Scene;
use crate::train::trainer::Trainer;

/// `println!` that never panics: a report printed to a full disk ends the
/// command with an error ([`crate::interrupt::print_line`]), not a panic.
macro_rules! println {
    ($($arg:tt)*) => {
        crate::interrupt::print_line(format_args!($($arg)*))
    };
}

/// Figures of a throughput run.
#[derive(Debug, Clone)]
pub struct ThroughputReport {
    /// Unmeasured steps before the measured ones.
    pub warmup: usize,
    pub steps: usize,
    pub median_step_seconds: f64,
    pub samples_per_second: f64,
    pub rays_per_second: f64,
    pub median_samples_per_ray: f32,
    /// Median seconds per stage.
    pub stages: StageTimes,
    pub peak_memory_bytes: Option<u64>,
    /// How a gpu engine measured its stages (timestamps or wall clock);
    /// `None` on the cpu engine.
    pub stage_timing: Option<String>,
    /// The networks' achieved rate over their own (forward and backward)
    /// time, GFLOP/s, for models that count their FLOPs.
    pub network_gflops: Option<f64>,
    /// On the gpu engine: what a measured step asked of the device.
    pub device_work: Option<DeviceWork>,
}

/// Dispatches and blocking read-backs per measured training step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DeviceWork {
    /// Mean over the measured steps.
    pub dispatches_per_step: f64,
    /// Mean over the measured steps (occupancy updates included).
    pub readbacks_per_step: f64,
    /// The most any one measured step made.
    pub most_readbacks_in_a_step: u64,
}

fn median(values: &mut [f64]) -> f64 {
    if values.is_empty() {
        return f64::NAN;
    }
    values.sort_by(|a, b| a.total_cmp(b));
    let n = values.len();
    if n % 2 == 1 {
        values[n / 2]
    } else {
        0.5 * (values[n / 2 - 1] + values[n / 2])
    }
}

/// Runs `warmup` steps unmeasured (the occupancy grid's first updates and
/// the workspaces' first allocations), then `steps` measured ones, and
/// reports medians (these machines are shared: medians resist outliers).
/// Once `stop` is set no further step starts: the report then covers the
/// measured steps taken so far (`steps` says how many; 0 gives NaN figures).
///
/// `counters`: the gpu context's, to count what each measured step asks of
/// the device.
pub fn throughput(
    trainer: &mut Trainer,
    warmup: usize,
    steps: usize,
    stop: &AtomicBool,
    counters: Option<&GpuCounters>,
) -> ThroughputReport {
    let stopped = || stop.load(Ordering::SeqCst);
    for _ in 0..warmup {
        if stopped() {
            break;
        }
        trainer.step();
    }
    let mut records: Vec<(f64, StepStats)> = Vec::with_capacity(steps);
    let mut work: Vec<CounterReading> = Vec::with_capacity(steps);
    for _ in 0..steps {
        if stopped() {
            break;
        }
        let before = trainer.train_seconds;
        let counted = counters.map(GpuCounters::read);
        let stats = trainer.step();
        if let (Some(counters), Some(counted)) = (counters, counted) {
            work.push(counters.read() - counted);
        }
        records.push((trainer.train_seconds - before, stats));
    }
    let steps = records.len();
    let device_work = (!work.is_empty()).then(|| {
        let n = work.len() as f64;
        DeviceWork {
            dispatches_per_step: work.iter().map(|w| w.dispatches as f64).sum::<f64>() / n,
            readbacks_per_step: work
                .iter()
                .map(|w| w.blocking_readbacks as f64)
                .sum::<f64>()
                / n,
            most_readbacks_in_a_step: work.iter().map(|w| w.blocking_readbacks).max().unwrap_or(0),
        }
    });
    let mut step_seconds: Vec<f64> = records.iter().map(|r| r.0).collect();
    let total_seconds: f64 = step_seconds.iter().sum();
    let total_samples: usize = records.iter().map(|r| r.1.samples).sum();
    let total_rays: usize = records.iter().map(|r| r.1.rays).sum();
    let mut spr: Vec<f64> = records
        .iter()
        .map(|r| r.1.samples_per_ray() as f64)
        .collect();
    let stages = StageTimes::from_fn(|stage| {
        let mut v: Vec<f64> = records.iter().map(|r| r.1.times[stage]).collect();
        if stage == Stage::GridUpdate {
            // The grid is updated every 16 steps: its mean cost per step
            // is the fair figure, not its median (which is 0).
            v.iter().sum::<f64>() / steps.max(1) as f64
        } else {
            median(&mut v)
        }
    });
    let network_flops: f64 = records.iter().map(|r| r.1.network_flops).sum();
    let network_seconds: f64 = records
        .iter()
        .map(|r| r.1.times[Stage::NetworksForward] + r.1.times[Stage::NetworksBackward])
        .sum();
    ThroughputReport {
        network_gflops: (network_flops > 0.0 && network_seconds > 0.0)
            .then(|| network_flops / network_seconds / 1e9),
        warmup,
        steps,
        median_step_seconds: median(&mut step_seconds),
        samples_per_second: total_samples as f64 / total_seconds,
        rays_per_second: total_rays as f64 / total_seconds,
        median_samples_per_ray: median(&mut spr) as f32,
        stages,
        peak_memory_bytes: peak_memory_bytes(),
        stage_timing: trainer
            .model
            .texture_render()
            .map(|model| model.stage_timing_note()),
        device_work,
    }
}

/// The process's peak resident memory (Linux: VmHWM), if known.
pub fn peak_memory_bytes() -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib * 1024)
}

/// Starts a new peak for [`peak_memory_bytes`] at the current resident
/// memory (Linux: writing 5 to `/proc/self/clear_refs`), so that each
/// cell of the quality experiment reports its own peak rather than the
/// largest one before it. Where that is not possible the peak stays the
/// process's.
pub fn reset_peak_memory() {
    let _ = std::fs::write("/proc/self/clear_refs", "5");
}

/// The scene the benchmark uses by default: lego_400 beside the checkout
/// when present, else the built-in demo scene.
pub fn default_scene_path() -> Option<std::path::PathBuf> {
    let candidate = std::path::Path::new("../shared/data/nerf_synthetic/lego_400");
    candidate.is_dir().then(|| candidate.to_path_buf())
}

/// A rate with three significant digits, in M or k as its size asks
/// (NeRF's rays per second would read "0.000 M").
fn per_second(rate: f64) -> String {
    if rate >= 1e5 {
        format!("{:.3} M", rate / 1e6)
    } else {
        format!("{:.1} k", rate / 1e3)
    }
}

pub fn print_report(report: &ThroughputReport, scene: &Arc<Scene>, engine: &str) {
    println!(
        "scene                {} ({} training views)",
        scene.name,
        scene.train.len()
    );
    println!("engine               {engine}");
    println!(
        "steps measured       {} (after {} unmeasured)",
        report.steps, report.warmup
    );
    println!(
        "ms per step          {:.1} (median)",
        report.median_step_seconds * 1e3
    );
    println!(
        "samples/s            {}",
        per_second(report.samples_per_second)
    );
    println!(
        "rays/s               {}",
        per_second(report.rays_per_second)
    );
    println!(
        "samples per ray      {:.1} (median)",
        report.median_samples_per_ray
    );
    println!("stages (median ms per step):");
    if let Some(note) = &report.stage_timing {
        println!("  (timed by {note})");
    }
    let total = report.stages.total();
    for (name, seconds) in report.stages.named() {
        println!(
            "  {name:<20} {:>8.2}  {:>5.1}%",
            seconds * 1e3,
            100.0 * seconds / total.max(1e-12)
        );
    }
    if let Some(gflops) = report.network_gflops {
        println!(
            "networks             {gflops:.1} GFLOP/s (forward and backward, over their time)"
        );
    }
    if let Some(work) = report.device_work {
        println!("dispatches per step  {:.1}", work.dispatches_per_step);
        println!(
            "blocking readbacks per step {:.2} (mean; at most {} in a step)",
            work.readbacks_per_step, work.most_readbacks_in_a_step
        );
    }
    if let Some(bytes) = report.peak_memory_bytes {
        println!(
            "peak memory          {:.0} MiB",
            bytes as f64 / (1 << 20) as f64
        );
    }
}

/// Achieved rates of one dense network at one batch size.
#[derive(Debug, Clone)]
pub struct DenseFigures {
    pub name: String,
    pub widths: Vec<usize>,
    pub rows: usize,
    /// Median seconds of a forward pass (activations kept) and of a
    /// backward pass (parameter and input gradients).
    pub forward_seconds: f64,
    pub backward_seconds: f64,
    pub forward_gflops: f64,
    pub backward_gflops: f64,
}

/// Times NeRF's three dense networks (the trunk up to the skip, after it,
/// and the colour branch) forward and backward on `rows` rows, as a
/// training step runs them. Medians of `repeats` runs after one warm-up.
pub fn dense_throughput(
    rows: usize,
    repeats: usize,
    precision: crate::field::mlp::Precision,
) -> Vec<DenseFigures> {
    use crate::engine::cpu::dense::{
        InputGradient, MlpGradients, MlpWorkspace, mlp_backward, mlp_forward,
    };
    use crate::field::nerf::NerfShape;
    use crate::rng::Pcg32;
    let shape = NerfShape::paper().with_precision(precision);
    let networks = [
        ("trunk before the skip", &shape.trunk_a),
        ("trunk after the skip", &shape.trunk_b),
        ("colour branch", &shape.colour),
    ];
    let mut rng = Pcg32::new(7, 7);
    networks
        .iter()
        .map(|(name, layout)| {
            let params = layout.init_params(1);
            let input: Vec<f32> = (0..rows * layout.input_width())
                .map(|_| rng.next_f32() - 0.5)
                .collect();
            let d_output: Vec<f32> = (0..rows * layout.output_width())
                .map(|_| rng.next_f32() - 0.5)
                .collect();
            let mut output = vec![0f32; rows * layout.output_width()];
            let mut d_params = vec![0f32; params.len()];
            let mut d_input = vec![0f32; input.len()];
            let mut workspace = MlpWorkspace::new(layout, rows);
            let mut forward = Vec::new();
            let mut backward = Vec::new();
            for run in 0..=repeats {
                let clock = std::time::Instant::now();
                mlp_forward(layout, &params, &input, rows, &mut workspace, &mut output);
                let f = clock.elapsed().as_secs_f64();
                let clock = std::time::Instant::now();
                mlp_backward(
                    layout,
                    &params,
                    &input,
                    rows,
                    &mut workspace,
                    MlpGradients {
                        output: &d_output,
                        params: &mut d_params,
                        input: Some(InputGradient::every_column(&mut d_input, layout)),
                    },
                );
                let b = clock.elapsed().as_secs_f64();
                if run > 0 {
                    forward.push(f);
                    backward.push(b);
                }
            }
            let flop = 2.0 * (layout.macs_per_row() * rows) as f64;
            let (f, b) = (median(&mut forward), median(&mut backward));
            DenseFigures {
                name: name.to_string(),
                widths: layout.widths.clone(),
                rows,
                forward_seconds: f,
                backward_seconds: b,
                forward_gflops: flop / f / 1e9,
                // The backward pass computes two products per layer (the
                // input gradient and the weight gradient).
                backward_gflops: 2.0 * flop / b / 1e9,
            }
        })
        .collect()
}
