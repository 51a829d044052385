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
    /// NeRF in the Wild's protocol for a run with appearance vectors: each
    /// view's vector fitted to its left half (the field held still), its
    /// right half scored, beside the same half drawn with the training
    /// vectors' mean.
    #[arg(long)]
    appearance_from_left_half: bool,
    /// With --appearance-from-left-half: this many views spread over the
    /// split (each view's fit takes a hundred steps), all by default.
    #[arg(long, requires = "appearance_from_left_half")]
    views: Option<usize>,
}

/// Each view's right half with the training vectors' mean and with the
/// vector fitted to its left half, then the means: printed, not written
/// (the split's scores are the whole views').
fn eval_right_halves(
    model: &mut dyn zrak::model::RadianceModel,
    frames: &[Frame],
    split: Split,
) -> anyhow::Result<()> {
    println!(
        "right halves of the {} views: appearance fitted to each left half (NeRF in the Wild, \
         section 6) against the training vectors' mean",
        split.name()
    );
    println!("{:>5}  {:>10}  {:>10}  image", "view", "mean", "fitted");
    let (mut mean, mut fitted, mut count) = (0.0, None::<f64>, 0usize);
    let shown = |psnr: Option<f64>| psnr.map_or("-".to_string(), |p| format!("{p:.3}"));
    for (index, frame) in frames.iter().enumerate() {
        if interrupt::requested() {
            break;
        }
        let scores = zrak::train::eval::score_right_half(model, frame)
            .map_err(|problem| anyhow::anyhow!("view {index}: {problem}"))?;
        println!(
            "{index:>5}  {:>10.3}  {:>10}  {}",
            scores.mean_psnr,
            shown(scores.fitted_psnr),
            frame.image_path.display()
        );
        mean += scores.mean_psnr;
        if let Some(psnr) = scores.fitted_psnr {
            *fitted.get_or_insert(0.0) += psnr;
        }
        count += 1;
    }
    let count = count.max(1) as f64;
    println!(
        "{:>5}  {:>10.3}  {:>10}  (PSNR, dB, {} views)",
        "mean",
        mean / count,
        shown(fitted.map(|f| f / count)),
        count
    );
    Ok(())
}

pub fn eval(args: EvalArgs) -> anyhow::Result<()> {
    let EvalArgs {
        run,
        split,
        engine,
        downscale,
        appearance_from_left_half,
        views,
    } = args;
    let folder = RunFolder::open(&run).map_err(anyhow::Error::msg)?;
    let (_, mut trainer) = restore_run(&folder, engine, None)?;
    let scene = trainer.scene.clone();
    let frames = scene.split(split);
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
    if appearance_from_left_half {
        if trainer.model.appearance_images().is_none() {
            note(&format!(
                "{}: the run has no appearance vectors: its right halves are scored as they \
                 render, for comparison with a run that has them",
                folder.dir.display()
            ));
        }
        let chosen: Vec<Frame> = match views {
            Some(count) => zrak::train::eval::spread_views(frames, count)
                .into_iter()
                .cloned()
                .collect(),
            None => frames.to_vec(),
        };
        return eval_right_halves(trainer.model.as_mut(), &chosen, split);
    }
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
