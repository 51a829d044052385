//! The jobs the thread does a unit at a time beside training and the
//! view: an export ([`ExportJob`]) and a held-out evaluation
//! ([`Evaluation`]). Saving and loading checkpoints are done at once
//! (`saving.rs`).

use std::sync::Arc;
use std::time::Instant;

use crate::field::ModelKind;
use crate::metrics::{WHITE, psnr_from_mse};
use crate::model::{RadianceModel, RayColumns, RenderedPixel};
use crate::scene::crop::CropBox;
use crate::scene::{Frame, Scene};
use crate::session::protocol::Event;
use crate::train::eval::pixel_grid;

use super::export_jobs::{ExportJob, ExportOrder};
use super::training::{ModelSlot, Training};
use super::{Outbox, UiGone};

/// A held-out evaluation in progress: a grid of pixels spread over each
/// held-out view, rendered in chunks like the view so that commands are
/// not held up by a slow model, scored view by view (per-view PSNR, then
/// the mean, as `train::eval::mean_psnr_sampled` scores for `zrak
/// train`). Training waits until it is done, so the PSNR belongs to one
/// step.
pub(super) struct Evaluation {
    pub(super) model: ModelKind,
    /// (held-out view, column, row) of every pixel to score, view by view.
    pixels: Vec<(usize, u32, u32)>,
    /// Pixels rendered so far.
    done: usize,
    /// Per view: Σ squared error over the three channels, and pixels.
    squared: Vec<f64>,
    counts: Vec<usize>,
    /// Render seconds so far.
    seconds: f64,
}

impl Evaluation {
    /// About `pixels` pixels spread evenly over `frames`.
    pub(super) fn new(model: ModelKind, frames: &[Frame], pixels: usize) -> Self {
        let per_view = pixels.div_ceil(frames.len().max(1));
        let mut chosen = Vec::new();
        for (view, frame) in frames.iter().enumerate() {
            let k = frame.camera.intrinsics;
            chosen.extend(
                pixel_grid(k.width, k.height, per_view)
                    .into_iter()
                    .map(|(x, y)| (view, x, y)),
            );
        }
        Self {
            model,
            pixels: chosen,
            done: 0,
            squared: vec![0.0; frames.len()],
            counts: vec![0; frames.len()],
            seconds: 0.0,
        }
    }

    fn is_done(&self) -> bool {
        self.done >= self.pixels.len()
    }

    /// Renders and scores up to `max_rays` more pixels.
    fn render_chunk(&mut self, model: &dyn RadianceModel, frames: &[Frame], max_rays: usize) {
        let end = (self.done + max_rays.max(1)).min(self.pixels.len());
        let chunk = &self.pixels[self.done..end];
        let rays: Vec<_> = chunk
            .iter()
            .map(|&(view, x, y)| frames[view].camera.pixel_ray(x, y))
            .collect();
        let mut out = vec![RenderedPixel::default(); chunk.len()];
        model.render(RayColumns::of(&rays).over(WHITE), &mut out);
        for (index, pixel) in (self.done..end).zip(&out) {
            let (view, x, y) = self.pixels[index];
            let truth = frames[view].image.rgb_over(x, y, WHITE);
            self.score(view, &pixel.rgb, &truth);
        }
        self.done = end;
    }

    /// Adds a pixel of held-out view `view` rendered as `rgb` where the
    /// photograph shows `truth`.
    fn score(&mut self, view: usize, rgb: &[f32; 3], truth: &[f32; 3]) {
        self.squared[view] += rgb
            .iter()
            .zip(truth)
            .map(|(&p, &t)| ((p - t) as f64).powi(2))
            .sum::<f64>();
        self.counts[view] += 1;
    }

    /// The mean over views of each view's PSNR.
    fn mean_psnr(&self) -> f64 {
        let scored: Vec<f64> = self
            .squared
            .iter()
            .zip(&self.counts)
            .filter(|&(_, &n)| n > 0)
            .map(|(&squared, &n)| psnr_from_mse(squared / (3 * n) as f64))
            .collect();
        if scored.is_empty() {
            return f64::NAN;
        }
        scored.iter().sum::<f64>() / scored.len() as f64
    }

    /// Renders and scores the next chunk with `slot`'s model (sized by
    /// its pacer); returns the seconds it took, and when that was the last
    /// chunk, gives the result to the slot.
    pub(super) fn render_unit(&mut self, slot: &mut ModelSlot, frames: &[Frame]) -> (f64, bool) {
        let started = Instant::now();
        let before = self.done;
        self.render_chunk(slot.trainer.model.as_ref(), frames, slot.pacer.chunk_rays());
        let seconds = started.elapsed().as_secs_f64();
        slot.pacer.record(self.done - before, seconds);
        self.seconds += seconds;
        let done = self.is_done();
        if done {
            slot.evaluated(self.mean_psnr() as f32, self.pixels.len(), self.seconds);
        }
        (seconds, done)
    }
}

/// The export and the held-out evaluation under way, if any.
#[derive(Default)]
pub(super) struct Jobs {
    export: Option<ExportJob>,
    pub(super) evaluation: Option<Evaluation>,
}

impl Jobs {
    pub(super) fn exporting(&self) -> bool {
        self.export.is_some()
    }

    /// Stops the export, if one runs; true when one did.
    pub(super) fn stop_export(&mut self) -> bool {
        self.export.take().is_some()
    }

    /// Starts exporting `model` (at `step`, in `crop`) of `scene` as
    /// `order` says; the event says how it began.
    pub(super) fn start_export(
        &mut self,
        scene: &Arc<Scene>,
        order: ExportOrder,
        model: ModelKind,
        crop: Option<CropBox>,
        step: u32,
    ) -> Event {
        if self.export.is_some() {
            return Event::Error("an export is already running; cancel it first".into());
        }
        match ExportJob::start(scene, order, model, crop, step) {
            Ok(job) => {
                let (done, total) = job.progress();
                self.export = Some(job);
                Event::ExportProgress { done, total }
            }
            Err(e) => Event::ExportFinished(Err(e)),
        }
    }

    /// Does one unit of the export with its model from `training`.
    pub(super) fn export_unit(
        &mut self,
        training: &Training,
        outbox: &Outbox,
    ) -> Result<(), UiGone> {
        let Some(mut job) = self.export.take() else {
            return Ok(());
        };
        let Some(slot) = training.slot(job.model()) else {
            return outbox.send(Event::ExportFinished(Err(format!(
                "the export stopped: the {} model is gone",
                job.model().name()
            ))));
        };
        let model = slot.trainer.model.as_ref();
        match job.step(model) {
            Ok(more) => {
                let (done, total) = job.progress();
                outbox.send(Event::ExportProgress { done, total })?;
                if more {
                    self.export = Some(job);
                    Ok(())
                } else {
                    let finished = job.finish(model);
                    outbox.send(Event::ExportFinished(finished))
                }
            }
            Err(e) => outbox.send(Event::ExportFinished(Err(e))),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::demo::{
        DemoConfig, {self},
    };

    fn frames() -> Vec<Frame> {
        let scene = demo::build(&DemoConfig {
            size: 16,
            train_views: 1,
            val_views: 3,
            test_views: 0,
        });
        scene.val
    }

    #[test]
    fn an_evaluation_spreads_its_pixels_over_the_views() {
        let frames = frames();
        // 9 a view: a 3 × 3 grid on each.
        let job = Evaluation::new(ModelKind::Ngp, &frames, 27);
        for view in 0..3 {
            let of_view: Vec<_> = job.pixels.iter().filter(|p| p.0 == view).collect();
            assert_eq!(of_view.len(), 9, "view {view}: {of_view:?}");
            assert!(of_view.iter().all(|&&(_, x, y)| x < 16 && y < 16));
        }
        assert!(!job.is_done());
        // More than the views hold: every pixel once.
        let all = Evaluation::new(ModelKind::Ngp, &frames, 10_000);
        assert_eq!(all.pixels.len(), 3 * 16 * 16);
    }

    #[test]
    fn the_psnr_is_the_mean_of_each_views() {
        let frames = frames();
        let mut job = Evaluation::new(ModelKind::Ngp, &frames, 3);
        assert!(job.mean_psnr().is_nan(), "nothing scored yet");
        // View 0: an error of 0.1 in every channel (MSE 0.01, 20 dB); view
        // 1: 0.01 (MSE 1e-4, 40 dB); view 2 not scored.
        job.score(0, &[0.6, 0.6, 0.6], &[0.5, 0.5, 0.5]);
        job.score(0, &[0.4, 0.4, 0.4], &[0.5, 0.5, 0.5]);
        job.score(1, &[0.51, 0.5, 0.5], &[0.5, 0.51, 0.5]);
        job.score(1, &[0.5, 0.5, 0.51], &[0.5, 0.5, 0.5]);
        job.score(1, &[0.5, 0.5, 0.5], &[0.5, 0.5, 0.51]);
        job.score(1, &[0.5, 0.5, 0.5], &[0.5, 0.5, 0.5]);
        // View 1: 4 pixels, 4 channel errors of 0.01 in 12: MSE 1/3 · 1e-4.
        let view1 = psnr_from_mse(1e-4 * 4.0 / 12.0);
        let expected = (20.0 + view1) / 2.0;
        assert!(
            (job.mean_psnr() - expected).abs() < 1e-4,
            "{} against {expected}",
            job.mean_psnr()
        );
    }
}
