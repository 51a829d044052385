//! The accuracy-versus-time experiment behind `zrak bench quality`: each
//! model trains on each scene for a budget of training time and is scored
//! at fixed marks along the way.
//!
//! A cell (one model on one scene) is an ordinary run folder (`run.json`,
//! `metrics.jsonl`, `checkpoint.zrak`) with one more file, `marks.json`,
//! the scores recorded so far. The checkpoint is written at every mark and
//! at an interrupt, so an experiment that stops continues from its folders:
//! finished marks and cells are never trained or scored again.

use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;

use serde::{Deserialize, Serialize};

use crate::field::ModelKind;
use crate::field::common::Sampling;
use crate::metrics::psnr_from_mse;
use crate::model::RadianceModel;
use crate::scene::Frame;
use crate::train::eval::{ViewScores, score_view};
use crate::train::run::{Limits, RunFolder, Schedule, run};
use crate::train::trainer::Trainer;

/// The experiment's settings, in its output folder.
pub const PROTOCOL_FILE: &str = "experiment.json";
/// A cell's scores, in its run folder.
pub const MARKS_FILE: &str = "marks.json";
/// Where the cells' run folders go inside the output folder.
pub const RUNS_FOLDER: &str = "runs";

/// Evaluate every this-many-th view of the split by default: 4 of the
/// 100 views of a NeRF-synthetic val or test split. NeRF renders a
/// 400×400 view in minutes on two cores, so all 100 at every mark would
/// cost hours; a fixed, stated subset keeps the cost bounded.
pub const DEFAULT_EVERY: usize = 25;
/// Score 1/this² of each view's pixels by default, for the same reason (a
/// sixteenth of the pixels).
pub const DEFAULT_EVAL_DOWNSCALE: u32 = 4;
/// Side of the full-resolution tiles scored ([`EvalPixels::Tiles`]): SSIM's
/// 11-pixel window slides over 22 × 22 places in each.
pub const TILE_SIDE: u32 = 32;

/// Which pixels of a view are scored when only 1/N² of them are
/// (`--eval-downscale N`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum EvalPixels {
    /// Tiles of the view at full resolution, one drawn from each block of
    /// N × N tiles: PSNR and SSIM estimate the full-resolution scores the
    /// papers report, whatever the model's anti-aliasing.
    Tiles,
    /// The whole view at 1/N of its resolution, the photographs
    /// area-averaged: Mip-NeRF's multiscale protocol, which measures how a
    /// model renders the scene seen from further away; a model without
    /// anti-aliasing scores lower there the sharper it gets.
    Downscaled,
}

impl EvalPixels {
    /// What experiments written before tiles existed used.
    fn before_tiles() -> Self {
        Self::Downscaled
    }
}

/// A view as it is scored: the parts rendered and compared (the whole view,
/// or tiles of it), all of one size.
#[derive(Debug, Clone)]
pub struct ScoredView {
    pub parts: Vec<Frame>,
}

impl ScoredView {
    /// The view's photograph's file.
    pub fn image_path(&self) -> &Path {
        &self.parts[0].image_path
    }

    /// Pixels scored.
    pub fn pixels(&self) -> usize {
        self.parts
            .iter()
            .map(|p| p.camera.intrinsics.width as usize * p.camera.intrinsics.height as usize)
            .sum()
    }
}

/// Up to `side`-pixel square tiles of `frame` at full resolution, one from
/// each block of `n` × `n` tiles (blocks centred in the view), the tile
/// within its block drawn from `seed` and the view's `index`: about 1/n² of
/// the pixels, spread over the whole view.
pub fn tiles(frame: &Frame, n: u32, side: u32, index: usize, seed: u64) -> Vec<Frame> {
    let (width, height) = (
        frame.camera.intrinsics.width,
        frame.camera.intrinsics.height,
    );
    if n <= 1 {
        return vec![frame.clone()];
    }
    let side = side.min(width / n).min(height / n).max(1);
    let (blocks_x, blocks_y) = (width / (side * n), height / (side * n));
    let (x0, y0) = (
        (width - blocks_x * side * n) / 2,
        (height - blocks_y * side * n) / 2,
    );
    let mut parts = Vec::with_capacity((blocks_x * blocks_y) as usize);
    for by in 0..blocks_y {
        for bx in 0..blocks_x {
            let block = u64::from(by * blocks_x + bx);
            let draw = crate::engine::shared::occupancy::mix64(
                seed ^ crate::engine::shared::occupancy::mix64(((index as u64) << 32) | block),
            );
            let pick = (draw % u64::from(n * n)) as u32;
            let (tx, ty) = (bx * n + pick % n, by * n + pick / n);
            parts.push(frame.cropped(x0 + tx * side, y0 + ty * side, side, side));
        }
    }
    parts
}

/// The marks as fractions of the budget: for 10 minutes, the issue's
/// 30 s, 1, 2, 5 and 10 minutes.
pub const DEFAULT_MARK_FRACTIONS: [f64; 5] = [0.05, 0.1, 0.2, 0.5, 1.0];

/// What every cell of an experiment shares. A folder holds one protocol:
/// its scores are only comparable under the same one.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Protocol {
    /// Training seconds per cell (evaluation excluded).
    pub budget_seconds: f64,
    /// Training seconds at which each cell is scored, increasing, the last
    /// equal to the budget.
    pub marks_seconds: Vec<f64>,
    /// The split scored ("val" or "test").
    pub split: String,
    /// Every this-many-th view of the split is scored, from the first.
    pub every: usize,
    /// 1/this² of each view's pixels are scored, chosen by `eval_pixels`.
    pub eval_downscale: u32,
    /// Which pixels: full-resolution tiles, or the whole view downscaled.
    #[serde(default = "EvalPixels::before_tiles")]
    pub eval_pixels: EvalPixels,
    /// Training images are loaded at 1/this of their resolution.
    pub downscale: u32,
    pub seed: u64,
    /// Samples per training batch, when not each model's own (the papers').
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub batch_samples: Option<usize>,
}

impl Protocol {
    /// The same protocol with training batches of `samples` (`None`: each
    /// model's own).
    pub fn with_batch_samples(mut self, samples: Option<usize>) -> Self {
        self.batch_samples = samples;
        self
    }

    /// Checks the settings; `marks` `None` takes [`DEFAULT_MARK_FRACTIONS`]
    /// of the budget. The budget is always the last mark.
    pub fn new(
        budget_seconds: f64,
        marks: Option<&[f64]>,
        split: &str,
        every: usize,
        eval_downscale: u32,
        downscale: u32,
        seed: u64,
    ) -> Result<Self, String> {
        if !(budget_seconds.is_finite() && budget_seconds > 0.0) {
            return Err(format!(
                "--budget must be a positive duration, got {budget_seconds} s"
            ));
        }
        let mut marks_seconds: Vec<f64> = match marks {
            None => DEFAULT_MARK_FRACTIONS
                .iter()
                .map(|f| f * budget_seconds)
                .collect(),
            Some(marks) => {
                if marks.is_empty() {
                    return Err("--marks needs at least one time, e.g. 30s,1m,2m".into());
                }
                for &mark in marks {
                    if !(mark.is_finite() && mark > 0.0) {
                        return Err(format!("--marks: {mark} s is not a positive duration"));
                    }
                    if mark > budget_seconds {
                        return Err(format!(
                            "--marks: {} is past the budget of {}; raise --budget or drop the mark",
                            super::table::format_mark(mark),
                            super::table::format_mark(budget_seconds)
                        ));
                    }
                }
                marks.to_vec()
            }
        };
        marks_seconds.sort_by(f64::total_cmp);
        marks_seconds.dedup();
        if marks_seconds.last() != Some(&budget_seconds) {
            marks_seconds.push(budget_seconds);
        }
        if every == 0 {
            return Err("--every must be at least 1 (1 scores every view)".into());
        }
        if eval_downscale == 0 || downscale == 0 {
            return Err("--downscale and --eval-downscale must be at least 1".into());
        }
        Ok(Self {
            budget_seconds,
            marks_seconds,
            split: split.to_string(),
            every,
            eval_downscale,
            eval_pixels: EvalPixels::Tiles,
            downscale,
            seed,
            batch_samples: None,
        })
    }

    /// The same protocol scoring `pixels`.
    pub fn with_eval_pixels(mut self, pixels: EvalPixels) -> Self {
        self.eval_pixels = pixels;
        self
    }

    /// The indices in the split of the views scored, out of `count`.
    pub fn view_indices(&self, count: usize) -> Vec<usize> {
        (0..count).step_by(self.every.max(1)).collect()
    }

    /// The views scored, as the parts of each that are rendered.
    pub fn views(&self, frames: &[Frame]) -> Result<Vec<ScoredView>, String> {
        let views: Vec<ScoredView> = self
            .view_indices(frames.len())
            .into_iter()
            .map(|i| ScoredView {
                parts: match self.eval_pixels {
                    EvalPixels::Downscaled => vec![frames[i].downscaled(self.eval_downscale)],
                    EvalPixels::Tiles => {
                        tiles(&frames[i], self.eval_downscale, TILE_SIDE, i, self.seed)
                    }
                },
            })
            .collect();
        // Views of a split may differ in size: name the one left without
        // pixels to score.
        if let Some(position) = views.iter().position(|v| v.parts.is_empty()) {
            let k = frames[position * self.every.max(1)].camera.intrinsics;
            return Err(format!(
                "--eval-downscale {} is larger than the views ({}×{} pixels)",
                self.eval_downscale, k.width, k.height
            ));
        }
        let least = crate::metrics::SSIM_WINDOW as u32;
        if let Some(small) = views
            .iter()
            .flat_map(|v| &v.parts)
            .find(|f| f.camera.intrinsics.width < least || f.camera.intrinsics.height < least)
        {
            let what = match self.eval_pixels {
                EvalPixels::Downscaled => "a view",
                EvalPixels::Tiles => "a tile",
            };
            return Err(format!(
                "--eval-downscale {} leaves {}×{} pixels {what}: too few to score (SSIM's \
                 window needs {least} or more a side)",
                self.eval_downscale, small.camera.intrinsics.width, small.camera.intrinsics.height
            ));
        }
        Ok(views)
    }

    /// One sentence: which views are scored and how.
    pub fn describe_views(&self, count: usize) -> String {
        let indices = self.view_indices(count);
        let which = if self.every == 1 {
            format!("all {count} views of the {} split", self.split)
        } else {
            let shown: Vec<String> = indices.iter().take(12).map(|i| i.to_string()).collect();
            let more = if indices.len() > 12 { ", …" } else { "" };
            format!(
                "every {}th view of the {} split ({} of {count}: views {}{more})",
                self.every,
                self.split,
                indices.len(),
                shown.join(", ")
            )
        };
        let n = self.eval_downscale;
        let resolution = match self.eval_pixels {
            _ if n == 1 => "at full resolution".to_string(),
            EvalPixels::Downscaled => {
                format!("at 1/{n} of the views' resolution (the photographs area-averaged)")
            }
            EvalPixels::Tiles => format!(
                "at full resolution on 1/{} of their pixels: tiles of up to {TILE_SIDE}×{TILE_SIDE} \
                 pixels, one drawn from each block of {n}×{n} tiles",
                n * n
            ),
        };
        format!("{which}, {resolution}")
    }
}

/// One model (with one sampler) on one scene.
#[derive(Debug, Clone, PartialEq)]
pub struct CellSpec {
    /// The scene's short name (its folder's name, or `demo`).
    pub scene: String,
    pub model: ModelKind,
    pub sampling: Sampling,
}

impl CellSpec {
    /// True for NeRF and Mip-NeRF with the paper's sampler (Instant-NGP
    /// has only the occupancy grid).
    pub fn paper_sampler(&self) -> bool {
        self.model.has_paper_sampler() && self.sampling == Sampling::Paper
    }

    /// Whether it uses another sampler than its model's default, which
    /// its label and folder then name.
    fn names_sampler(&self) -> bool {
        self.sampling != self.model.spec().samplings[0]
    }

    /// `NeRF`, `NeRF (paper sampler)`, `Instant-NGP (proposal sampler)`.
    pub fn label(&self) -> String {
        if self.names_sampler() {
            format!("{} ({} sampler)", self.model.name(), self.sampling.name())
        } else {
            self.model.name().to_string()
        }
    }

    /// The run folder's name: `lego_400-nerf-paper`.
    pub fn folder_name(&self) -> String {
        let scene = safe_name(&self.scene);
        if self.names_sampler() {
            format!("{scene}-{}-{}", self.model.key(), self.sampling.name())
        } else {
            format!("{scene}-{}", self.model.key())
        }
    }
}

/// A name fit for a file: letters, digits, `-` and `_` kept, anything
/// else (a scene folder may be called anything) made `_`.
pub fn safe_name(name: &str) -> String {
    name.chars()
        .map(|c| {
            if c.is_alphanumeric() || c == '-' || c == '_' {
                c
            } else {
                '_'
            }
        })
        .collect()
}

/// The cells of an experiment, scene by scene: each model with each of the
/// samplers it has; a model with none of them once, with its default
/// (Instant-NGP has no paper sampler).
pub fn cells_for(scenes: &[String], models: &[ModelKind], samplings: &[Sampling]) -> Vec<CellSpec> {
    let mut cells = Vec::new();
    for scene in scenes {
        for &model in models {
            let spec = model.spec();
            let mut own: Vec<Sampling> = samplings
                .iter()
                .copied()
                .filter(|s| spec.samplings.contains(s))
                .collect();
            if own.is_empty() {
                own.push(spec.samplings[0]);
            }
            for sampling in own {
                let cell = CellSpec {
                    scene: scene.clone(),
                    model,
                    sampling,
                };
                if !cells.contains(&cell) {
                    cells.push(cell);
                }
            }
        }
    }
    cells
}

/// The scores at one mark.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MarkResult {
    /// The mark (training seconds).
    pub mark_seconds: f64,
    /// Training seconds when scored: the end of the step that passed the
    /// mark, so a little past it.
    pub train_seconds: f64,
    pub step: u32,
    /// Means over the views (per-view PSNR, then the mean).
    pub psnr: f64,
    pub ssim: f64,
    pub views: Vec<ViewScores>,
    /// Wall seconds the scoring took (not training time).
    pub eval_seconds: f64,
    /// Samples the networks were trained on since the previous mark, and
    /// the training seconds they took (after a resume: since the resume).
    pub samples: u64,
    pub sample_seconds: f64,
    /// What the model holds (parameters, optimiser state, workspaces).
    pub memory_bytes: u64,
    /// The process's peak resident memory since the segment before this
    /// mark began (Linux), including the loaded scene.
    pub peak_rss_bytes: Option<u64>,
}

/// A cell's `marks.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CellRecord {
    pub protocol: Protocol,
    pub scene: String,
    pub model: ModelKind,
    pub sampling: Sampling,
    /// The engine the cell trained on, as chosen then.
    pub engine: String,
    pub marks: Vec<MarkResult>,
}

impl CellRecord {
    pub fn path(folder: &Path) -> PathBuf {
        folder.join(MARKS_FILE)
    }

    /// The record in `folder`, if one was written.
    pub fn load(folder: &Path) -> Result<Option<CellRecord>, String> {
        let path = Self::path(folder);
        let text = match std::fs::read_to_string(&path) {
            Ok(text) => text,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(format!("{}: cannot read: {e}", path.display())),
        };
        serde_json::from_str(&text)
            .map(Some)
            .map_err(|e| format!("{}: not a cell record: {e}", path.display()))
    }

    /// Writes the record through a temporary file, so that a crash leaves
    /// the previous one whole.
    pub fn save(&self, folder: &Path) -> Result<(), String> {
        let path = Self::path(folder);
        let text = serde_json::to_string_pretty(self).map_err(|e| e.to_string())?;
        crate::files::write_bytes_atomically(&path, text.as_bytes())
            .map_err(|e| format!("{}: cannot write: {e}", path.display()))
    }

    pub fn finished(&self) -> bool {
        self.marks.len() >= self.protocol.marks_seconds.len()
    }

    /// (training seconds, PSNR) at each mark scored.
    pub fn curve(&self) -> Vec<(f64, f64)> {
        self.marks
            .iter()
            .map(|m| (m.train_seconds, m.psnr))
            .collect()
    }
}

/// What a cell is doing, for a progress bar.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum CellProgress {
    Training {
        /// The mark being trained towards.
        mark: usize,
        train_seconds: f64,
        step: u32,
        samples_per_second: f64,
    },
    Scoring {
        mark: usize,
        /// Views scored so far, and in all.
        view: usize,
        views: usize,
        /// The last view's PSNR.
        psnr: f64,
    },
}

/// How a cell's run ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CellOutcome {
    Finished,
    /// `stop` was set: the checkpoint holds the training so far and the
    /// record every mark scored.
    Interrupted,
}

/// The progress evaluations inside each training segment: only the one
/// `run` makes when the segment ends (the marks are the scores that
/// count), of 256 pixels of one view, so that it costs a second or two
/// even for NeRF with the paper's 256 samples a ray.
fn schedule() -> Schedule {
    Schedule {
        eval_every_seconds: f64::INFINITY,
        eval_views: 1,
        eval_rays: 1 << 8,
        ..Schedule::default()
    }
}

/// Renders and scores the parts of `view` (the `index`-th of its split):
/// PSNR of the mean squared error over all its pixels, SSIM the mean over
/// its parts weighted by their pixels (the mean of SSIM's local windows over
/// the parts), so that tiles estimate the whole view's scores.
pub fn score_parts(model: &dyn RadianceModel, view: &ScoredView, index: usize) -> ViewScores {
    let total = view.pixels().max(1) as f64;
    let (mut squared_error, mut ssim) = (0.0, 0.0);
    for part in &view.parts {
        let scores = score_view(model, part, true);
        let share = (part.camera.intrinsics.width * part.camera.intrinsics.height) as f64 / total;
        // The PSNR's own mean squared error (data range 1); the cap at
        // 100 dB stands for an error below 1e-10.
        squared_error += share * 10f64.powf(-scores.psnr / 10.0);
        ssim += share * scores.ssim;
    }
    ViewScores {
        index,
        image: view.image_path().display().to_string(),
        psnr: psnr_from_mse(squared_error),
        ssim,
        masked_pixels: view
            .parts
            .iter()
            .filter_map(|part| part.mask.as_ref())
            .map(|mask| mask.hidden())
            .sum(),
    }
}

/// Trains `trainer` through each mark of `record` not yet scored, scoring
/// `views` at each (the training clock stands still meanwhile) and saving
/// the record after each. Returns early, with the checkpoint written, once
/// `stop` is set: after the current step, or after the current view.
pub fn run_cell(
    trainer: &mut Trainer,
    record: &mut CellRecord,
    folder: &RunFolder,
    run_config: &serde_json::Value,
    views: &[ScoredView],
    stop: &AtomicBool,
    mut on_progress: impl FnMut(CellProgress),
) -> Result<CellOutcome, String> {
    let marks = record.protocol.marks_seconds.clone();
    for (index, &mark) in marks.iter().enumerate().skip(record.marks.len()) {
        super::reset_peak_memory();
        let mut samples = 0u64;
        let mut sample_seconds = 0f64;
        let mut last_seconds = trainer.train_seconds;
        run(
            trainer,
            Limits {
                steps: None,
                seconds: Some(mark),
            },
            schedule(),
            folder,
            run_config,
            stop,
            |p| {
                samples += p.stats.samples as u64;
                sample_seconds += p.trainer.train_seconds - last_seconds;
                last_seconds = p.trainer.train_seconds;
                on_progress(CellProgress::Training {
                    mark: index,
                    train_seconds: p.trainer.train_seconds,
                    step: p.trainer.step,
                    samples_per_second: p.samples_per_second,
                });
            },
        )?;
        if stop.load(std::sync::atomic::Ordering::SeqCst) {
            return Ok(CellOutcome::Interrupted);
        }
        let started = std::time::Instant::now();
        let mut view_scores = Vec::with_capacity(views.len());
        for (i, view) in views.iter().enumerate() {
            if stop.load(std::sync::atomic::Ordering::SeqCst) {
                // Interrupted: a mean over some of the views is not the
                // mark's score; the mark is scored again on resume.
                return Ok(CellOutcome::Interrupted);
            }
            // Scored views are every `every`-th of the split: each keeps
            // its index in the split, not in the subset.
            let scores = score_parts(trainer.model.as_ref(), view, i * record.protocol.every);
            on_progress(CellProgress::Scoring {
                mark: index,
                view: i + 1,
                views: views.len(),
                psnr: scores.psnr,
            });
            view_scores.push(scores);
        }
        let n = view_scores.len().max(1) as f64;
        let mean_psnr = view_scores.iter().map(|v| v.psnr).sum::<f64>() / n;
        let mean_ssim = view_scores.iter().map(|v| v.ssim).sum::<f64>() / n;
        record.marks.push(MarkResult {
            mark_seconds: mark,
            train_seconds: trainer.train_seconds,
            step: trainer.step,
            psnr: mean_psnr,
            ssim: mean_ssim,
            views: view_scores,
            eval_seconds: started.elapsed().as_secs_f64(),
            samples,
            sample_seconds,
            memory_bytes: trainer.model.memory_bytes() as u64,
            peak_rss_bytes: super::peak_memory_bytes(),
        });
        record.save(&folder.dir)?;
    }
    Ok(CellOutcome::Finished)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A finished cell's results are computed again from `marks.json` on a
    /// later run, so every number must come back bit for bit (serde_json's
    /// default float parser misses the last bit of about one value in ten;
    /// its `float_roundtrip` feature does not).
    #[test]
    fn marks_come_back_from_json_bit_for_bit() {
        let mut state: u64 = 0x9E37_79B9_7F4A_7C15;
        let mut missed = Vec::new();
        for _ in 0..20_000 {
            state = state
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            let value = (state >> 11) as f64 / (1u64 << 53) as f64 * 50.0;
            let text = serde_json::to_string(&value).unwrap();
            let back: f64 = serde_json::from_str(&text).unwrap();
            if back.to_bits() != value.to_bits() {
                missed.push((value, back));
            }
        }
        assert!(
            missed.is_empty(),
            "{} missed, e.g. {:?}",
            missed.len(),
            missed.first()
        );
    }

    #[test]
    fn default_marks_are_fractions_of_the_budget_ending_at_it() {
        let p = Protocol::new(600.0, None, "val", 25, 4, 1, 0).unwrap();
        assert_eq!(p.marks_seconds, vec![30.0, 60.0, 120.0, 300.0, 600.0]);
        let p = Protocol::new(20.0, Some(&[10.0, 5.0, 5.0]), "val", 1, 1, 1, 0).unwrap();
        assert_eq!(p.marks_seconds, vec![5.0, 10.0, 20.0]);
    }

    #[test]
    fn bad_settings_are_refused_by_name() {
        let e = Protocol::new(60.0, Some(&[30.0, 120.0]), "val", 1, 1, 1, 0).unwrap_err();
        assert!(e.contains("2 min is past the budget of 1 min"), "{e}");
        let e = Protocol::new(60.0, Some(&[]), "val", 1, 1, 1, 0).unwrap_err();
        assert!(e.contains("--marks"), "{e}");
        let e = Protocol::new(60.0, None, "val", 0, 1, 1, 0).unwrap_err();
        assert!(e.contains("--every"), "{e}");
        let e = Protocol::new(f64::NAN, None, "val", 1, 1, 1, 0).unwrap_err();
        assert!(e.contains("--budget"), "{e}");
    }

    #[test]
    fn every_nth_view_from_the_first_is_scored_and_said_so() {
        let p = Protocol::new(600.0, None, "val", 25, 4, 1, 0).unwrap();
        assert_eq!(p.view_indices(100), vec![0, 25, 50, 75]);
        assert_eq!(p.view_indices(10), vec![0]);
        assert_eq!(
            p.describe_views(100),
            "every 25th view of the val split (4 of 100: views 0, 25, 50, 75), \
             at full resolution on 1/16 of their pixels: tiles of up to 32×32 pixels, \
             one drawn from each block of 4×4 tiles"
        );
        assert_eq!(
            p.with_eval_pixels(EvalPixels::Downscaled).describe_views(4),
            "every 25th view of the val split (1 of 4: views 0), \
             at 1/4 of the views' resolution (the photographs area-averaged)"
        );
        let all = Protocol::new(600.0, None, "test", 1, 1, 1, 0).unwrap();
        assert_eq!(
            all.describe_views(3),
            "all 3 views of the test split, at full resolution"
        );
    }

    /// A `width` × `height` view through a pinhole whose photograph is
    /// white on the left half and black on the right.
    fn half_white_view(width: u32, height: u32) -> Frame {
        let mut data = Vec::with_capacity((width * height * 4) as usize);
        for _y in 0..height {
            for x in 0..width {
                let v = if x < width / 2 { 255 } else { 0 };
                data.extend([v, v, v, 255]);
            }
        }
        Frame {
            camera: crate::scene::Camera::new(
                crate::scene::Intrinsics::from_fov_x(width, height, 1.0),
                glam::Mat4::IDENTITY,
            ),
            image: crate::scene::ImageRgba8::new(width, height, data),
            image_path: "view.png".into(),
            mask: None,
        }
    }

    #[test]
    fn tiles_are_full_resolution_pieces_of_the_view_spread_over_it() {
        let frame = half_white_view(400, 300);
        let parts = tiles(&frame, 4, TILE_SIDE, 7, 0);
        // Blocks of 4 × 4 tiles of 32 px: 3 across, 2 down.
        assert_eq!(parts.len(), 6);
        let pixels: u32 = parts.iter().map(|p| p.image.width * p.image.height).sum();
        let share = pixels as f64 / (400.0 * 300.0);
        assert!((0.04..=1.0 / 16.0).contains(&share), "{share}");
        let mut corners = Vec::new();
        for part in &parts {
            let k = part.camera.intrinsics;
            assert_eq!((k.width, k.height), (32, 32));
            // The crop's corner in the view, from its principal point.
            let x0 = (frame.camera.intrinsics.cx - k.cx).round() as u32;
            let y0 = (frame.camera.intrinsics.cy - k.cy).round() as u32;
            corners.push((x0, y0));
            for (i, j) in [(0, 0), (31, 0), (5, 17), (31, 31)] {
                // The same pixel of the photograph and the same ray.
                assert_eq!(part.image.rgba(i, j), frame.image.rgba(x0 + i, y0 + j));
                let (a, b) = (
                    part.camera.pixel_ray(i, j),
                    frame.camera.pixel_ray(x0 + i, y0 + j),
                );
                assert!((a.direction - b.direction).length() < 1e-5);
                assert_eq!(a.cone_radius, b.cone_radius);
            }
        }
        // One tile in each block (blocks start 8 px and 22 px in).
        let mut blocks: Vec<(u32, u32)> = corners
            .iter()
            .map(|&(x, y)| ((x - 8) / 128, (y - 22) / 128))
            .collect();
        blocks.sort();
        assert_eq!(blocks, [(0, 0), (0, 1), (1, 0), (1, 1), (2, 0), (2, 1)]);
        // The draw is the view's own and repeats; another view draws anew.
        let again: Vec<_> = tiles(&frame, 4, TILE_SIDE, 7, 0)
            .iter()
            .map(|p| (p.camera.intrinsics.cx, p.camera.intrinsics.cy))
            .collect();
        let other: Vec<_> = tiles(&frame, 4, TILE_SIDE, 8, 0)
            .iter()
            .map(|p| (p.camera.intrinsics.cx, p.camera.intrinsics.cy))
            .collect();
        let first: Vec<_> = parts
            .iter()
            .map(|p| (p.camera.intrinsics.cx, p.camera.intrinsics.cy))
            .collect();
        assert_eq!(first, again);
        assert_ne!(first, other);
        // Every pixel when nothing is to be saved.
        assert_eq!(tiles(&frame, 1, TILE_SIDE, 7, 0)[0].image, frame.image);
        // More blocks than pixels: no tile, and the protocol says so.
        assert!(tiles(&frame, 400, TILE_SIDE, 7, 0).is_empty());
        let p = Protocol::new(60.0, None, "val", 1, 400, 1, 0).unwrap();
        let e = p.views(std::slice::from_ref(&frame)).unwrap_err();
        assert_eq!(
            e,
            "--eval-downscale 400 is larger than the views (400×300 pixels)"
        );
    }

    /// Renders every ray white.
    struct White;

    impl RadianceModel for White {
        fn describe(&self) -> String {
            "white".into()
        }

        fn rays_for_next_batch(&self) -> usize {
            0
        }

        fn step(&mut self, _: &crate::model::batch::RayBatch, _: u32) -> crate::model::StepStats {
            Default::default()
        }

        fn render(&self, _: crate::model::RenderRays, out: &mut [crate::model::RenderedPixel]) {
            for pixel in out {
                *pixel = crate::model::RenderedPixel {
                    rgb: [1.0; 3],
                    opacity: 1.0,
                    depth: 1.0,
                };
            }
        }

        fn save(&self) -> crate::model::checkpoint::Checkpoint {
            crate::model::checkpoint::Checkpoint {
                header: serde_json::Value::Null,
                tensors: Vec::new(),
            }
        }

        fn load(&mut self, _: &crate::model::checkpoint::Checkpoint) -> Result<(), String> {
            Ok(())
        }

        fn memory_bytes(&self) -> usize {
            0
        }
    }

    #[test]
    fn a_views_psnr_pools_the_squared_error_of_its_tiles() {
        // 128 × 64 in tiles of 16 with blocks of 2 × 2: 4 blocks across,
        // 2 down; the left two columns of blocks lie in the white half,
        // the right two in the black. A white render is exact on half the
        // tiles and wrong by 1 on the others: mean squared error 1/2,
        // 3.01 dB, as for the whole view (a mean of the tiles' PSNRs, 100
        // and 0 dB, would say 50).
        let frame = half_white_view(128, 64);
        let view = ScoredView {
            parts: tiles(&frame, 2, 16, 0, 0),
        };
        assert_eq!(view.parts.len(), 8);
        let tiled = score_parts(&White, &view, 3);
        let whole = score_view(&White, &frame, true);
        assert!((tiled.psnr - 10.0 * 2f64.log10()).abs() < 1e-9, "{tiled:?}");
        assert!(
            (tiled.psnr - whole.psnr).abs() < 1e-9,
            "{tiled:?} {whole:?}"
        );
        assert_eq!(tiled.index, 3);
        assert_eq!(tiled.image, "view.png");
        // SSIM: 1 on the white tiles, about 0 on the black ones.
        assert!((tiled.ssim - 0.5).abs() < 1e-3, "{tiled:?}");
    }

    #[test]
    fn instant_ngp_has_one_cell_whatever_the_samplers() {
        let cells = cells_for(
            &["lego_400".into()],
            &[ModelKind::Ngp, ModelKind::Nerf, ModelKind::MipNerf],
            &[Sampling::Occupancy, Sampling::Paper],
        );
        let names: Vec<String> = cells.iter().map(|c| c.folder_name()).collect();
        assert_eq!(
            names,
            [
                "lego_400-ngp",
                "lego_400-nerf",
                "lego_400-nerf-paper",
                "lego_400-mipnerf",
                "lego_400-mipnerf-paper"
            ]
        );
        assert_eq!(cells[2].label(), "NeRF (paper sampler)");
        assert_eq!(cells[0].label(), "Instant-NGP");
    }
}
