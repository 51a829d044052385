//! `zrak info`: what a scene folder holds, as training would load it.

use std::path::PathBuf;
use std::time::Instant;

use clap::Args;
use zrak::scene::{LoadOptions, Scene, Split};

use super::{PhotographSwitches, SpaceChoice, load_scene, photograph_lines};

#[derive(Args, Debug)]
pub struct InfoArgs {
    /// A folder in the NeRF-synthetic layout, with a transforms.json, or
    /// with a COLMAP model; `demo` for the built-in demo scene.
    scene: PathBuf,
    /// Integer image downscale, as training would load it.
    #[arg(long, default_value_t = 1)]
    downscale: u32,
    /// What the scene is treated as, as `zrak train --space` would: auto
    /// leaves it to the scene analysis, whose reasons are printed either
    /// way.
    #[arg(long, value_enum, default_value_t = SpaceChoice::Auto)]
    space: SpaceChoice,
    #[command(flatten)]
    photographs: PhotographSwitches,
}

pub fn info(args: InfoArgs) -> anyhow::Result<()> {
    let started = Instant::now();
    let scene = if args.scene.as_os_str() == "demo" {
        load_scene("demo", args.downscale)?
    } else {
        Scene::load(
            &args.scene,
            LoadOptions {
                downscale: args.downscale,
            },
        )?
    };
    let scene = args.space.apply(scene);
    print_info(&scene);
    for line in photograph_lines(&args.photographs.analyse(&scene)) {
        println!("{line}");
    }
    println!("loaded in {:.2} s", started.elapsed().as_secs_f64());
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
    if k.lens != zrak::scene::Lens::Pinhole {
        println!("lens        {}", k.lens.describe());
    }
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
    match scene.describe_masks() {
        Some(masks) => println!("masks       {masks}"),
        None => println!("masks       none (every pixel counts)"),
    }
    if let Some((near, far)) = scene.seen_depth_range() {
        println!("near/far    {near:.3} to {far:.3} (where camera rays cross the bounds)");
    }
    for line in space_lines(scene) {
        println!("{line}");
    }
}

/// The space the scene is treated as and why: a line for the choice, one
/// per reason under it.
fn space_lines(scene: &Scene) -> Vec<String> {
    let analysis = &scene.space;
    let how = if analysis.overridden {
        "chosen with --space"
    } else {
        "from the scene analysis; --space overrides it"
    };
    let mut lines = vec![format!("space       {} ({how})", analysis.space)];
    lines.extend(
        analysis
            .reasons
            .iter()
            .map(|reason| format!("  - {reason}")),
    );
    lines
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cli::parse_args;

    #[test]
    fn info_takes_a_folder_and_a_downscale() {
        let args: InfoArgs = parse_args(&["lego", "--downscale", "4"]).unwrap();
        assert_eq!(args.scene, PathBuf::from("lego"));
        assert_eq!(args.downscale, 4);
        let args: InfoArgs = parse_args(&["lego"]).unwrap();
        assert_eq!(args.downscale, 1);
        assert_eq!(args.space, SpaceChoice::Auto);
        let args: InfoArgs = parse_args(&["lego", "--space", "unbounded"]).unwrap();
        assert_eq!(args.space, SpaceChoice::Unbounded);
        let error = parse_args::<InfoArgs>(&[]).unwrap_err();
        assert_eq!(
            error.kind(),
            clap::error::ErrorKind::MissingRequiredArgument
        );
        assert!(error.to_string().contains("<SCENE>"), "{error}");
    }

    #[test]
    fn the_space_is_printed_with_its_reasons_and_whether_it_was_chosen() {
        let scene = load_scene("demo", 16).unwrap();
        let lines = space_lines(&scene);
        assert_eq!(
            lines[0],
            "space       object (from the scene analysis; --space overrides it)"
        );
        assert_eq!(lines.len(), 1 + scene.space.reasons.len());
        assert_eq!(lines[1], format!("  - {}", scene.space.reasons[0]));
        let chosen = SpaceChoice::ForwardFacing.apply(scene);
        let lines = space_lines(&chosen);
        assert_eq!(lines[0], "space       forward-facing (chosen with --space)");
        assert_eq!(
            lines[1],
            "  - chosen by hand as forward-facing; the analysis found object"
        );
    }
}
