//! The `zrak` command line.

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

use anyhow::Context;
use clap::{Parser, Subcommand};
use zrak::scene::demo::{self, DemoConfig};
use zrak::scene::{LoadOptions, Scene, Split};

/// Train neural radiance fields (NeRF, Mip-NeRF, Instant-NGP) while you watch.
#[derive(Parser)]
#[command(name = "zrak", version, about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Option<Command>,
}

#[derive(Subcommand)]
enum Command {
    /// Print a scene's splits, resolution, intrinsics and bounds.
    Info {
        /// A folder in the NeRF-synthetic layout or with a transforms.json.
        scene: PathBuf,
        /// Integer image downscale, as training would load it.
        #[arg(long, default_value_t = 1)]
        downscale: u32,
    },
    /// Write the built-in demo scene to a folder in the NeRF-synthetic layout.
    Demo {
        /// The folder to write (created if missing).
        #[arg(long)]
        out: PathBuf,
        /// Width and height of every image, in pixels.
        #[arg(long, default_value_t = DemoConfig::default().size)]
        size: u32,
        /// Number of training views (val and test get a tenth each, at least one).
        #[arg(long, default_value_t = DemoConfig::default().train_views)]
        views: usize,
    },
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        Some(Command::Info { scene, downscale }) => info(&scene, downscale),
        Some(Command::Demo { out, size, views }) => write_demo(&out, size, views),
        None => show_demo(),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(error) => {
            eprintln!("error: {error:#}");
            ExitCode::FAILURE
        }
    }
}

fn info(path: &Path, downscale: u32) -> anyhow::Result<()> {
    let started = Instant::now();
    let scene = Scene::load(path, LoadOptions { downscale })?;
    print_info(&scene);
    println!("loaded in {:.2} s", started.elapsed().as_secs_f64());
    Ok(())
}

fn demo_config(size: u32, views: usize) -> anyhow::Result<DemoConfig> {
    anyhow::ensure!(size >= 8, "--size must be at least 8 pixels, got {size}");
    anyhow::ensure!(views >= 1, "--views must be at least 1");
    let held_out = (views / 10).max(1);
    Ok(DemoConfig {
        size,
        train_views: views,
        val_views: held_out,
        test_views: held_out,
    })
}

fn write_demo(out: &Path, size: u32, views: usize) -> anyhow::Result<()> {
    let config = demo_config(size, views)?;
    let started = Instant::now();
    demo::write(&config, out).with_context(|| "writing the demo scene".to_string())?;
    println!(
        "wrote the demo scene to {} ({} / {} / {} views at {size}×{size}) in {:.2} s",
        out.display(),
        config.train_views,
        config.val_views,
        config.test_views,
        started.elapsed().as_secs_f64()
    );
    Ok(())
}

/// Until the viewer lands, running zrak without a subcommand describes the
/// built-in demo scene it will open.
fn show_demo() -> anyhow::Result<()> {
    let scene = demo::build(&DemoConfig::default());
    print_info(&scene);
    println!();
    println!("The viewer is not built yet; see `zrak --help` for what runs today.");
    Ok(())
}

fn print_info(scene: &Scene) {
    let source = if scene.root.as_os_str().is_empty() {
        "built in".to_string()
    } else {
        scene.root.display().to_string()
    };
    println!("scene       {} ({:?}, {source})", scene.name, scene.format);
    let counts: Vec<String> = Split::ALL
        .iter()
        .map(|&s| format!("{} {}", s.name(), scene.split(s).len()))
        .collect();
    println!("frames      {}", counts.join(", "));
    let Some(first) = scene.frames().next() else {
        return;
    };
    let k = first.camera.intrinsics;
    println!(
        "images      {}×{}, {}",
        k.width,
        k.height,
        if scene.has_alpha {
            "RGBA"
        } else {
            "RGB (no alpha)"
        }
    );
    println!(
        "intrinsics  fx {:.4}  fy {:.4}  cx {:.3}  cy {:.3}  (field of view {:.2}° × {:.2}°)",
        k.fx,
        k.fy,
        k.cx,
        k.cy,
        k.fov_x().to_degrees(),
        k.fov_y().to_degrees()
    );
    let b = scene.bounds;
    println!(
        "bounds      [{:.3}, {:.3}, {:.3}] to [{:.3}, {:.3}, {:.3}]",
        b.min.x, b.min.y, b.min.z, b.max.x, b.max.y, b.max.z
    );
    let m = scene.unit_cube;
    println!(
        "unit cube   scale {}  offset [{}, {}, {}]  aabb_scale {}",
        m.scale, m.offset.x, m.offset.y, m.offset.z, m.aabb_scale
    );
    if let Some((near, far)) = near_far_range(scene) {
        println!("near/far    {near:.3} to {far:.3} (where camera rays cross the bounds)");
    }
}

/// The smallest near and largest far distance over the rays through the
/// corners and centre of every frame that hit the scene box.
fn near_far_range(scene: &Scene) -> Option<(f32, f32)> {
    let mut range: Option<(f32, f32)> = None;
    for frame in scene.frames() {
        let k = frame.camera.intrinsics;
        let (w, h) = (k.width as f32, k.height as f32);
        for (u, v) in [
            (0.5, 0.5),
            (w - 0.5, 0.5),
            (0.5, h - 0.5),
            (w - 0.5, h - 0.5),
            (0.5 * w, 0.5 * h),
        ] {
            if let Some((near, far)) = scene.ray_near_far(&frame.camera.ray_through(u, v)) {
                range = Some(match range {
                    Some((n, f)) => (n.min(near), f.max(far)),
                    None => (near, far),
                });
            }
        }
    }
    range
}
