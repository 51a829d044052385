//! `zrak eval`: a trained run scored on a split, per view and on average.

use std::path::PathBuf;

use anyhow::{Context, bail};
use clap::Args;
use zrak::engine::EngineKind;
use zrak::interrupt::{
    note, {self},
};
use zrak::scene::{Frame, Split};
use zrak::train::eval::{SplitScores, evaluate_split_until};
use zrak::train::run::RunFolder;

use super::run_config::restore_run;

#[derive(Args, Debug)]
pub struct EvalArgs {
    /// The run folder written by `zrak train`.
    run: PathBuf,
    #[arg(long, value_enum, default_value_t = Split::Val)]
    split: Split,
    /// Force an engine (default: the run's own choice rules).
    #[arg(long, value_enum)]
    engine: Option<EngineKind>,
    /// Evaluate at 1/N of the views' resolution: intrinsics scaled, the
    /// photographs area-averaged (Mip-NeRF's multiscale protocol: how
    /// much a model aliases when it sees the scene from further away).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=64))]
    downscale: u32,
}

pub fn eval(args: EvalArgs) -> anyhow::Result<()> {
    let EvalArgs {
        run,
        split,
        engine,
        downscale,
    } = args;
    let folder = RunFolder::open(&run).map_err(anyhow::Error::msg)?;
    let (_, trainer) = restore_run(&folder, engine, None)?;
    let frames = trainer.scene.split(split);
    if frames.is_empty() {
        bail!("the scene has no {} views", split.name());
    }
    let smaller: Vec<Frame>;
    let frames = if downscale > 1 {
        smaller = frames.iter().map(|f| f.downscaled(downscale)).collect();
        if smaller
            .iter()
            .any(|f| f.camera.intrinsics.width == 0 || f.camera.intrinsics.height == 0)
        {
            bail!(
                "the {} views are smaller than {downscale} pixels",
                split.name()
            );
        }
        println!("at 1/{downscale} of the views' resolution");
        &smaller[..]
    } else {
        frames
    };
    println!("{:>5}  {:>8}  {:>7}  image", "view", "PSNR", "SSIM");
    let scores: SplitScores = evaluate_split_until(
        trainer.model.as_ref(),
        split.name(),
        frames,
        interrupt::flag(),
        |v| {
            println!(
                "{:>5}  {:>8.3}  {:>7.4}  {}",
                v.index, v.psnr, v.ssim, v.image
            );
        },
    );
    if interrupt::requested() {
        // A mean over some of the views is not the split's score: it is
        // shown, but not written where a finished evaluation goes.
        println!(
            "{:>5}  {:>8.3}  {:>7.4}  (interrupted: {} of {} views; nothing written)",
            "mean",
            scores.mean_psnr,
            scores.mean_ssim,
            scores.views.len(),
            frames.len()
        );
        return Ok(());
    }
    let fully_masked = |v: &&zrak::train::eval::ViewScores| {
        frames[v.index]
            .mask
            .as_ref()
            .is_some_and(|mask| mask.counted() == 0)
    };
    if let Some(view) = scores
        .views
        .iter()
        .find(|v| v.psnr.is_nan() && !fully_masked(v))
    {
        bail!(
            "view {} of the {} split ({}) renders colours that are not numbers: the model in \
             {} is broken (its training diverged); nothing written",
            view.index,
            split.name(),
            view.image,
            folder.dir.display()
        );
    }
    println!(
        "{:>5}  {:>8.3}  {:>7.4}",
        "mean", scores.mean_psnr, scores.mean_ssim
    );
    if let Some(masks) = scores.describe_masks() {
        note(&masks);
    }
    if let Some(appearance) = zrak::train::eval::describe_appearance(trainer.model.as_ref()) {
        note(&appearance);
    }
    let window = zrak::metrics::SSIM_WINDOW as u32;
    let small = frames
        .iter()
        .filter(|f| f.camera.intrinsics.width < window || f.camera.intrinsics.height < window)
        .count();
    if small > 0 {
        note(&format!(
            "SSIM is NaN for {small} of the {} views: they are smaller than its {window}×{window} \
             window (give a smaller --downscale, or read PSNR alone)",
            frames.len()
        ));
    }
    let path = folder.dir.join(scores_file_name(split, downscale));
    zrak::files::write_bytes_atomically(&path, serde_json::to_string_pretty(&scores)?.as_bytes())
        .with_context(|| format!("{}: cannot write", path.display()))?;
    println!("step {}; written to {}", trainer.step, path.display());
    Ok(())
}

/// Where in the run folder a split's scores go: one file per split and
/// resolution, so a multiscale evaluation keeps the full-size one.
fn scores_file_name(split: Split, downscale: u32) -> String {
    let suffix = if downscale > 1 {
        format!("_d{downscale}")
    } else {
        String::new()
    };
    format!("eval_{}{suffix}.json", split.name())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cli::parse_args;
    use clap::error::ErrorKind;

    #[test]
    fn eval_scores_the_val_split_at_full_size_by_default() {
        let args: EvalArgs = parse_args(&["RUN"]).unwrap();
        assert_eq!(args.run, PathBuf::from("RUN"));
        assert_eq!(args.split, Split::Val);
        assert_eq!(args.engine, None);
        assert_eq!(args.downscale, 1);
        let args: EvalArgs = parse_args(&[
            "RUN",
            "--split",
            "test",
            "--engine",
            "cpu",
            "--downscale",
            "8",
        ])
        .unwrap();
        assert_eq!(
            (args.split, args.engine, args.downscale),
            (Split::Test, Some(EngineKind::Cpu), 8)
        );
    }

    #[test]
    fn eval_refuses_a_downscale_outside_one_to_64_and_unknown_splits() {
        for downscale in ["0", "65"] {
            let error = parse_args::<EvalArgs>(&["RUN", "--downscale", downscale]).unwrap_err();
            assert_eq!(error.kind(), ErrorKind::ValueValidation);
            assert!(error.to_string().contains("1..=64"), "{error}");
        }
        let error = parse_args::<EvalArgs>(&["RUN", "--split", "holdout"]).unwrap_err();
        assert_eq!(error.kind(), ErrorKind::InvalidValue);
        assert!(
            error
                .to_string()
                .contains("[possible values: train, val, test]"),
            "{error}"
        );
    }

    #[test]
    fn each_split_and_resolution_has_its_own_scores_file() {
        assert_eq!(scores_file_name(Split::Val, 1), "eval_val.json");
        assert_eq!(scores_file_name(Split::Test, 1), "eval_test.json");
        assert_eq!(scores_file_name(Split::Test, 4), "eval_test_d4.json");
    }
}
