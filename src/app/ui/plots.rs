//! Loss and PSNR curves of every model trained in this session, and their
//! export as the quality report's plot and table.

use std::path::{Path, PathBuf};

use eframe::egui;
use egui_plot::{Legend, Line, Plot, PlotPoints, Points};

use crate::bench::plot::{Series, SeriesStyle, write_psnr_plot};
use crate::bench::table::{
    DEFAULT_TARGETS_DB, Table, format_mib, format_psnr, format_seconds, time_to_reach,
};
use crate::field::ModelKind;
use crate::session::protocol::TrainingStats;

/// Points kept per model before older ones are thinned: enough for a smooth
/// curve at any window width, few enough to draw every frame.
const MAX_POINTS: usize = 4096;

/// What the curves are drawn against.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PlotAxis {
    Step,
    /// Seconds since the window opened.
    WallTime,
    /// Seconds each model has spent training (rendering and evaluation
    /// excluded): the axis on which models trained in turn compare.
    TrainTime,
}

/// One logged step of one model.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HistoryPoint {
    pub step: u32,
    /// Seconds since the window opened, when the figures arrived.
    pub wall_seconds: f64,
    /// The model's training seconds at that step.
    pub train_seconds: f64,
    pub loss: f32,
    pub batch_psnr: Option<f32>,
    pub val_psnr: Option<f32>,
}

/// The curve of one model.
#[derive(Debug, Clone)]
pub struct History {
    pub model: ModelKind,
    pub points: Vec<HistoryPoint>,
    pub latest: Option<TrainingStats>,
}

impl History {
    pub fn new(model: ModelKind) -> Self {
        Self {
            model,
            points: Vec::new(),
            latest: None,
        }
    }

    pub fn record(&mut self, stats: &TrainingStats, wall_seconds: f64) {
        // A reset model starts its curve again.
        if self.points.last().is_some_and(|p| stats.step < p.step) {
            self.points.clear();
        }
        self.points.push(HistoryPoint {
            step: stats.step,
            wall_seconds,
            train_seconds: stats.train_seconds,
            loss: stats.loss,
            batch_psnr: stats.batch_psnr,
            val_psnr: stats.val_psnr,
        });
        if self.points.len() > MAX_POINTS {
            self.thin();
        }
        self.latest = Some(*stats);
    }

    /// Halves the points, keeping every held-out evaluation (they are rare
    /// and the most telling) and the newest point.
    fn thin(&mut self) {
        let last = self.points.len() - 1;
        let mut index = 0;
        self.points.retain(|p| {
            let keep = index % 2 == 0 || index == last || p.val_psnr.is_some();
            index += 1;
            keep
        });
    }

    pub fn latest_val_psnr(&self) -> Option<f32> {
        self.points.iter().rev().find_map(|p| p.val_psnr)
    }

    fn x(point: &HistoryPoint, axis: PlotAxis) -> f64 {
        match axis {
            PlotAxis::Step => point.step as f64,
            PlotAxis::WallTime => point.wall_seconds,
            PlotAxis::TrainTime => point.train_seconds,
        }
    }

    /// (training seconds, held-out PSNR) at each evaluation.
    pub fn val_curve(&self) -> Vec<(f64, f64)> {
        self.points
            .iter()
            .filter_map(|p| Some((p.train_seconds, p.val_psnr? as f64)))
            .filter(|(_, psnr)| psnr.is_finite())
            .collect()
    }
}

/// The comparison of the session's models as a table: steps, training
/// time, the latest held-out PSNR, the training time to each target
/// (interpolated between evaluations as the quality report does), speed
/// and memory.
pub fn comparison_table(histories: &[History]) -> Table {
    let mut headers = vec![
        "model".to_string(),
        "steps".to_string(),
        "training time".to_string(),
        "held-out PSNR".to_string(),
    ];
    headers.extend(DEFAULT_TARGETS_DB.iter().map(|t| format!("to {t:.0} dB")));
    headers.extend(["samples/s".to_string(), "memory".to_string()]);
    let mut table = Table::new(headers);
    for history in histories {
        let Some(latest) = history.latest else {
            continue;
        };
        let curve = history.val_curve();
        let mut row = vec![
            history.model.name().to_string(),
            latest.step.to_string(),
            format_seconds(latest.train_seconds),
            curve
                .last()
                .map_or("—".to_string(), |&(_, psnr)| format_psnr(psnr)),
        ];
        row.extend(
            DEFAULT_TARGETS_DB
                .iter()
                .map(|&t| time_to_reach(&curve, t).describe()),
        );
        row.push(format!("{:.2} M", latest.samples_per_second / 1e6));
        row.push(format_mib(Some(latest.memory_bytes as u64)));
        table.push(row);
    }
    table
}

/// Writes the session's comparison into `dir`: `psnr.png` and `psnr.svg`
/// (held-out PSNR against training time, as the quality report plots it),
/// `table.md` and `table.csv`. Returns the files written.
pub fn export_comparison(histories: &[History], dir: &Path) -> Result<Vec<PathBuf>, String> {
    let trained: Vec<&History> = histories.iter().filter(|h| h.latest.is_some()).collect();
    if trained.is_empty() {
        return Err("nothing to export yet: train a model first".into());
    }
    std::fs::create_dir_all(dir)
        .map_err(|e| format!("{}: cannot create the folder: {e}", dir.display()))?;
    let series: Vec<Series> = trained
        .iter()
        .map(|h| Series {
            label: h.model.name().to_string(),
            style: SeriesStyle::of(h.model, false),
            points: h.val_curve(),
        })
        .collect();
    let mut written = write_psnr_plot(
        "Held-out PSNR against training time",
        "training time of each model (log scale; rendering and evaluation excluded)",
        &series,
        &DEFAULT_TARGETS_DB,
        &dir.join("psnr"),
    )?;
    let table = comparison_table(histories);
    for (name, text) in [
        ("table.md", table.to_markdown()),
        ("table.csv", table.to_csv()),
    ] {
        let path = dir.join(name);
        std::fs::write(&path, text)
            .map_err(|e| format!("{}: cannot write: {e}", path.display()))?;
        written.push(path);
    }
    Ok(written)
}

/// A colour per model, stable across frames and plots, and the same in the
/// exported plots ([`crate::field::ModelSpec::colour`]).
fn model_colour(model: ModelKind) -> egui::Color32 {
    let [r, g, b] = model.spec().colour;
    egui::Color32::from_rgb(r, g, b)
}

/// The loss and PSNR plots side by side, sharing the x axis.
pub fn show(ui: &mut egui::Ui, histories: &[History], axis: PlotAxis) {
    let x_label = match axis {
        PlotAxis::Step => "step",
        PlotAxis::WallTime => "wall time (s)",
        PlotAxis::TrainTime => "training time (s)",
    };
    let link = egui::Id::unique("zrak training plots");
    let width = ((ui.available_width() - ui.spacing().item_spacing.x) / 2.0).max(50.0);
    let height = ui.available_height().max(60.0);
    ui.horizontal(|ui| {
        Plot::new("loss plot")
            .width(width)
            .height(height)
            .legend(Legend::default())
            .x_axis_label(x_label)
            .y_axis_label("loss")
            .link_axis(link, [true, false])
            .show(ui, |plot| {
                for history in histories {
                    let points: PlotPoints = history
                        .points
                        .iter()
                        .filter(|p| p.loss.is_finite())
                        .map(|p| [History::x(p, axis), p.loss as f64])
                        .collect();
                    plot.line(
                        Line::new(format!("{} loss", history.model.name()), points)
                            .color(model_colour(history.model)),
                    );
                }
            });
        Plot::new("psnr plot")
            .width(width)
            .height(height)
            .legend(Legend::default())
            .x_axis_label(x_label)
            .y_axis_label("PSNR (dB)")
            .link_axis(link, [true, false])
            .show(ui, |plot| {
                for history in histories {
                    let colour = model_colour(history.model);
                    let batch: PlotPoints = history
                        .points
                        .iter()
                        .filter_map(|p| Some([History::x(p, axis), p.batch_psnr? as f64]))
                        .filter(|p| p[1].is_finite())
                        .collect();
                    plot.line(
                        Line::new(format!("{} batch PSNR", history.model.name()), batch)
                            .color(colour.gamma_multiply(0.6)),
                    );
                    let val: Vec<[f64; 2]> = history
                        .points
                        .iter()
                        .filter_map(|p| Some([History::x(p, axis), p.val_psnr? as f64]))
                        .filter(|p| p[1].is_finite())
                        .collect();
                    if !val.is_empty() {
                        let name = format!("{} val PSNR", history.model.name());
                        plot.line(
                            Line::new(name.clone(), PlotPoints::from(val.clone()))
                                .color(colour)
                                .width(2.5),
                        );
                        plot.add(Points::new(name, val).color(colour).radius(3.0));
                    }
                }
            });
    });
}
