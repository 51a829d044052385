//! `zrak demo`: the built-in demo scene written to a folder.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, bail};
use clap::Args;
use zrak::scene::demo::{
    DemoConfig, {self},
};

use super::{MAX_IMAGE_SIDE, render_bytes_per_view};

#[derive(Args, Debug)]
pub struct DemoArgs {
    /// The folder to write (created if missing).
    #[arg(long)]
    out: PathBuf,
    /// Width and height of every image, in pixels.
    #[arg(long, default_value_t = DemoConfig::default().size)]
    size: u32,
    /// Number of training views (val and test get a tenth each, at least one).
    #[arg(long, default_value_t = DemoConfig::default().train_views)]
    views: usize,
    /// The large-extent variant: an opaque backdrop sphere around the
    /// objects, aabb_scale 8, written as an instant-ngp transforms.json.
    #[arg(long, conflicts_with = "unbounded")]
    large: bool,
    /// The unbounded variant: the objects on a ground plane that runs to
    /// the horizon under a sky at infinity, every pixel opaque, aabb_scale
    /// 16, written as an instant-ngp transforms.json.
    #[arg(long)]
    unbounded: bool,
    /// The forward-facing variant: --views cameras on a plane, all looking
    /// at the objects in front of an opaque, textured wall, written as an
    /// LLFF folder (poses_bounds.npy and images/, 4:3 photographs --size
    /// wide).
    #[arg(long, conflicts_with_all = ["large", "unbounded"])]
    forward_facing: bool,
    /// The demo with a ball that floats above the stand at another place
    /// in each training view, and each training image's
    /// dynamic_mask_r_N.png marking it (instant-ngp's masks), written as an
    /// instant-ngp transforms.json; the held-out views are without it.
    #[arg(long, conflicts_with_all = ["large", "unbounded", "forward_facing"])]
    moving_object: bool,
    /// The demo with each training camera off by a known amount, for
    /// camera refinement: turned by DEGREES about a random axis and moved
    /// by FRACTION of the scene's box side in a random direction (the same
    /// each time), e.g. `1,0.02`. The images are rendered from the true
    /// cameras, which go to cameras_truth.json; held-out views keep theirs.
    #[arg(
        long,
        value_name = "DEGREES,FRACTION",
        value_parser = parse_perturbation,
        allow_hyphen_values = true,
        conflicts_with_all = ["large", "unbounded", "forward_facing", "moving_object"]
    )]
    perturb_cameras: Option<demo::CameraPerturbation>,
    /// Each training view's exposure scaled by up to this many stops
    /// either way (held-out views keep the rendered exposure, the training
    /// views' mean), the true factors written to appearance_truth.json
    /// beside transforms.json (instant-ngp layout).
    #[arg(long, value_name = "STOPS", conflicts_with_all = ["large", "unbounded", "forward_facing", "moving_object", "perturb_cameras"])]
    exposure_jitter: Option<f32>,
    /// Each training view's channels scaled by up to this share either
    /// way (0.15: ±15 %), written as --exposure-jitter's are.
    #[arg(long, value_name = "SHARE", conflicts_with_all = ["large", "unbounded", "forward_facing", "moving_object", "perturb_cameras"])]
    white_balance_jitter: Option<f32>,
    /// Write into a folder that is not empty, replacing the scene's
    /// files there (others are left alone).
    #[arg(long)]
    force: bool,
}

/// The demo scene's settings for `--size` and `--views`, refused when out
/// of range or when its photographs would not fit in memory.
fn demo_config(size: u32, views: usize) -> anyhow::Result<DemoConfig> {
    anyhow::ensure!(
        (8..=MAX_IMAGE_SIDE).contains(&size),
        "--size must be 8 to {MAX_IMAGE_SIDE} pixels, got {size}"
    );
    anyhow::ensure!(
        (1..=100_000).contains(&views),
        "--views must be 1 to 100000, got {views}"
    );
    let held_out = (views / 10).max(1);
    // Every view's photograph is held in memory (4 bytes a pixel) and
    // rendered on every thread at once.
    let pixels = size as u64 * size as u64;
    let bytes = (views + 2 * held_out) as u64 * pixels * 4
        + rayon::current_num_threads() as u64 * render_bytes_per_view(size, size);
    zrak::files::check_memory(
        &format!(
            "the demo scene at --size {size} with {} views",
            views + 2 * held_out
        ),
        bytes,
    )
    .map_err(anyhow::Error::msg)?;
    Ok(DemoConfig {
        size,
        train_views: views,
        val_views: held_out,
        test_views: held_out,
    })
}

/// The forward-facing demo's settings: `views` photographs in all, 4:3,
/// `size` wide (sizes and counts checked by [`demo_config`]).
fn forward_facing_config(size: u32, views: usize) -> demo::ForwardFacingConfig {
    demo::ForwardFacingConfig {
        width: size,
        height: (size * 3 / 4).max(1),
        views,
    }
}

pub fn write_demo(args: DemoArgs) -> anyhow::Result<()> {
    let DemoArgs {
        out,
        size,
        views,
        large,
        unbounded,
        forward_facing,
        moving_object,
        perturb_cameras,
        exposure_jitter,
        white_balance_jitter,
        force,
    } = args;
    let config = demo_config(size, views)?;
    if !force {
        refuse_a_folder_in_use(&out)?;
    }
    let started = Instant::now();
    if forward_facing {
        let config = forward_facing_config(size, views);
        demo::write_forward_facing_llff(&config, &out)
            .context("writing the forward-facing demo scene")?;
        println!(
            "wrote the forward-facing demo scene to {} ({} views at {}×{}, every {}th held \
             out) in {:.2} s",
            out.display(),
            config.views,
            config.width,
            config.height,
            zrak::scene::llff::HOLD_OUT_EVERY,
            started.elapsed().as_secs_f64()
        );
        return Ok(());
    }
    if large {
        demo::write_large(&config, &out).context("writing the large demo scene")?;
    } else if unbounded {
        demo::write_unbounded(&config, &out).context("writing the unbounded demo scene")?;
    } else if let Some(perturbation) = perturb_cameras {
        demo::write_with_perturbed_cameras(&config, perturbation, &out)
            .context("writing the demo scene with perturbed cameras")?;
    } else if exposure_jitter.is_some() || white_balance_jitter.is_some() {
        let jitter = appearance_jitter(exposure_jitter, white_balance_jitter)?;
        demo::write_appearance_jitter(&config, &jitter, &out)
            .context("writing the demo scene with jittered appearance")?;
    } else if moving_object {
        demo::write_moving_object(&config, &out)
            .context("writing the demo scene with a moving object")?;
    } else {
        demo::write(&config, &out).context("writing the demo scene")?;
    }
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

/// `--perturb-cameras`' DEGREES,FRACTION: an angle of 0 to 180 degrees and
/// a share of the box's side of 0 to 1.
fn parse_perturbation(text: &str) -> Result<demo::CameraPerturbation, String> {
    let (degrees, fraction) = text
        .split_once(',')
        .ok_or_else(|| format!("`{text}` is not DEGREES,FRACTION (e.g. 1,0.02)"))?;
    let number = |part: &str, what: &str, max: f32| {
        part.trim()
            .parse::<f32>()
            .ok()
            .filter(|v| (0.0..=max).contains(v))
            .ok_or_else(|| format!("{what} `{part}` is not a number from 0 to {max}"))
    };
    Ok(demo::CameraPerturbation {
        degrees: number(degrees, "the angle", 180.0)?,
        offset_fraction: number(fraction, "the offset", 1.0)?,
    })
}

/// The seed of `--exposure-jitter` and `--white-balance-jitter`'s draws:
/// fixed, so a demo folder is the same wherever it is written.
const APPEARANCE_JITTER_SEED: u64 = 46;

/// The jitter `--exposure-jitter` and `--white-balance-jitter` ask for (an
/// absent one is none), refused outside the ranges that keep every factor
/// positive and every image visible.
fn appearance_jitter(
    exposure: Option<f32>,
    white_balance: Option<f32>,
) -> anyhow::Result<demo::AppearanceJitter> {
    let (exposure_stops, white_balance) = (exposure.unwrap_or(0.0), white_balance.unwrap_or(0.0));
    anyhow::ensure!(
        (0.0..=4.0).contains(&exposure_stops),
        "--exposure-jitter must be 0 to 4 stops, got {exposure_stops}"
    );
    anyhow::ensure!(
        (0.0..=0.9).contains(&white_balance),
        "--white-balance-jitter must be 0 to 0.9, got {white_balance}"
    );
    Ok(demo::AppearanceJitter {
        exposure_stops,
        white_balance,
        seed: APPEARANCE_JITTER_SEED,
    })
}

/// Refuses an `--out` that holds files, or that is something other than a
/// folder; one that is missing is made when the scene is written.
fn refuse_a_folder_in_use(out: &Path) -> anyhow::Result<()> {
    match std::fs::read_dir(out) {
        Ok(mut entries) => {
            if entries.next().is_some() {
                bail!(
                    "{} is not empty; give another --out, or --force to write the demo \
                     scene's files over those of the same names there",
                    out.display()
                );
            }
        }
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
        Err(_) if zrak::files::exists_at_all(out) => bail!(
            "{}: cannot write the demo scene there: {}",
            out.display(),
            zrak::files::describe_not_a_folder(out)
        ),
        Err(_) => {}
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cli::parse_args;

    #[test]
    fn the_demo_defaults_are_the_built_in_scenes() {
        let args: DemoArgs = parse_args(&["--out", "scene"]).unwrap();
        assert_eq!(args.out, PathBuf::from("scene"));
        assert_eq!(args.size, DemoConfig::default().size);
        assert_eq!(args.views, DemoConfig::default().train_views);
        assert!(!args.large && !args.unbounded && !args.force);
        let args: DemoArgs = parse_args(&["--out", "scene", "--unbounded"]).unwrap();
        assert!(args.unbounded);
        let error = parse_args::<DemoArgs>(&["--out", "s", "--unbounded", "--large"]).unwrap_err();
        assert_eq!(error.kind(), clap::error::ErrorKind::ArgumentConflict);
        assert!(!args.forward_facing);
        let args: DemoArgs = parse_args(&["--out", "s", "--forward-facing"]).unwrap();
        assert!(args.forward_facing);
        let error =
            parse_args::<DemoArgs>(&["--out", "s", "--forward-facing", "--large"]).unwrap_err();
        assert_eq!(error.kind(), clap::error::ErrorKind::ArgumentConflict);
        let error =
            parse_args::<DemoArgs>(&["--out", "s", "--forward-facing", "--unbounded"]).unwrap_err();
        assert_eq!(error.kind(), clap::error::ErrorKind::ArgumentConflict);
        let args: DemoArgs = parse_args(&["--out", "s", "--perturb-cameras", "1,0.02"]).unwrap();
        let perturbation = args.perturb_cameras.unwrap();
        assert_eq!(
            (perturbation.degrees, perturbation.offset_fraction),
            (1.0, 0.02)
        );
        for bad in ["1", "1,x", "-1,0.02", "1,2"] {
            let error = parse_args::<DemoArgs>(&["--out", "s", "--perturb-cameras", bad])
                .unwrap_err()
                .to_string();
            assert!(error.contains("--perturb-cameras"), "{bad}: {error}");
        }
        let args: DemoArgs = parse_args(&["--out", "s", "--moving-object"]).unwrap();
        assert!(args.moving_object && !args.large);
        let error =
            parse_args::<DemoArgs>(&["--out", "s", "--moving-object", "--large"]).unwrap_err();
        assert_eq!(error.kind(), clap::error::ErrorKind::ArgumentConflict);
        let config = forward_facing_config(64, 20);
        assert_eq!((config.width, config.height, config.views), (64, 48, 20));
        let error = parse_args::<DemoArgs>(&["--size", "64"]).unwrap_err();
        assert_eq!(
            error.kind(),
            clap::error::ErrorKind::MissingRequiredArgument
        );
        assert!(error.to_string().contains("--out <OUT>"), "{error}");
    }

    #[test]
    fn held_out_splits_get_a_tenth_of_the_views_and_at_least_one() {
        let config = demo_config(32, 30).unwrap();
        assert_eq!(
            (config.train_views, config.val_views, config.test_views),
            (30, 3, 3)
        );
        let config = demo_config(32, 5).unwrap();
        assert_eq!((config.val_views, config.test_views), (1, 1));
    }

    #[test]
    fn demo_sizes_and_view_counts_out_of_range_are_refused() {
        assert_eq!(
            demo_config(7, 10).unwrap_err().to_string(),
            "--size must be 8 to 16384 pixels, got 7"
        );
        assert_eq!(
            demo_config(16385, 10).unwrap_err().to_string(),
            "--size must be 8 to 16384 pixels, got 16385"
        );
        assert_eq!(
            demo_config(32, 0).unwrap_err().to_string(),
            "--views must be 1 to 100000, got 0"
        );
        assert!(demo_config(8, 100_000).is_ok());
    }

    #[test]
    fn only_an_empty_or_missing_folder_takes_the_demo_without_force() {
        let dir = tempfile::tempdir().unwrap();
        assert!(refuse_a_folder_in_use(&dir.path().join("new")).is_ok());
        assert!(refuse_a_folder_in_use(dir.path()).is_ok());
        std::fs::write(dir.path().join("notes.txt"), "mine").unwrap();
        let error = refuse_a_folder_in_use(dir.path()).unwrap_err().to_string();
        assert!(error.ends_with("is not empty; give another --out, or --force to write the demo scene's files over those of the same names there"), "{error}");
        let error = refuse_a_folder_in_use(&dir.path().join("notes.txt"))
            .unwrap_err()
            .to_string();
        assert!(
            error.contains("cannot write the demo scene there"),
            "{error}"
        );
    }
}
