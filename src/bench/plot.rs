//! The quality experiment's plots, PNG and SVG from one drawing: PSNR
//! against training time with every model overlaid, and the time each
//! model took to reach each PSNR target. The viewer's export draws with
//! the same functions.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use plotters::coord::{CoordTranslate, Shift};
use plotters::prelude::*;
use plotters::style::FontStyle;
use plotters::style::text_anchor::{HPos, Pos, VPos};

use super::table::{Reached, format_seconds};
use crate::field::ModelKind;

/// The plots' font, embedded so that text draws the same everywhere (see
/// `assets/fonts/DejaVuSans-LICENSE.txt`).
const FONT: &[u8] = include_bytes!("../../assets/fonts/DejaVuSans.ttf");
const FAMILY: &str = "sans-serif";

/// Pixels of a PNG; the SVG has the same size in user units.
const SIZE: (u32, u32) = (1000, 620);

fn register_font() -> Result<(), String> {
    static REGISTERED: OnceLock<bool> = OnceLock::new();
    let registered = *REGISTERED
        .get_or_init(|| plotters::style::register_font(FAMILY, FontStyle::Normal, FONT).is_ok());
    if registered {
        Ok(())
    } else {
        Err("the embedded plot font could not be read".into())
    }
}

/// How a curve or a bar is drawn.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SeriesStyle {
    pub colour: (u8, u8, u8),
    /// Dashed line and hollow markers: NeRF and Mip-NeRF with the paper's
    /// sampler, beside the same model (same colour) on the occupancy grid.
    pub dashed: bool,
}

impl SeriesStyle {
    /// A model's colour (the viewer's, so the export matches the window),
    /// dashed for the paper's sampler.
    pub fn of(model: ModelKind, paper_sampler: bool) -> Self {
        let [r, g, b] = model.spec().colour;
        let colour = (r, g, b);
        Self {
            colour,
            dashed: paper_sampler,
        }
    }

    fn colour(&self) -> RGBColor {
        RGBColor(self.colour.0, self.colour.1, self.colour.2)
    }
}

/// One model's PSNR at increasing training times.
#[derive(Debug, Clone, PartialEq)]
pub struct Series {
    pub label: String,
    pub style: SeriesStyle,
    /// (training seconds, PSNR in dB); points with a non-positive time or a
    /// non-finite PSNR are left out (a log axis has no 0).
    pub points: Vec<(f64, f64)>,
}

/// One model's times to each target, for the bar chart.
#[derive(Debug, Clone, PartialEq)]
pub struct Bars {
    pub label: String,
    pub style: SeriesStyle,
    /// One per target, in the targets' order.
    pub reached: Vec<Reached>,
}

/// Writes `<base>.png` and `<base>.svg`; returns their paths.
fn write_both(
    base: &Path,
    draw: impl Fn(DrawingArea<BitMapBackend, Shift>) -> Result<(), String>,
    draw_svg: impl Fn(DrawingArea<SVGBackend, Shift>) -> Result<(), String>,
) -> Result<Vec<PathBuf>, String> {
    register_font()?;
    let png = base.with_extension("png");
    let svg = base.with_extension("svg");
    let mut pixels = vec![0u8; (SIZE.0 * SIZE.1 * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut pixels, SIZE).into_drawing_area();
        draw(root.clone())?;
        root.present()
            .map_err(|e| format!("drawing {}: {e}", png.display()))?;
    }
    let image = image::RgbImage::from_raw(SIZE.0, SIZE.1, pixels)
        .ok_or_else(|| "the plot image has the wrong size".to_string())?;
    image
        .save_with_format(&png, image::ImageFormat::Png)
        .map_err(|e| format!("{}: cannot write: {e}", png.display()))?;
    let mut text = String::new();
    {
        let root = SVGBackend::with_string(&mut text, SIZE).into_drawing_area();
        draw_svg(root.clone())?;
        root.present()
            .map_err(|e| format!("drawing {}: {e}", svg.display()))?;
    }
    std::fs::write(&svg, text).map_err(|e| format!("{}: cannot write: {e}", svg.display()))?;
    Ok(vec![png, svg])
}

fn err(e: impl std::fmt::Display) -> String {
    format!("drawing the plot: {e}")
}

/// A time for an axis tick: `30 s`, `2 min`.
fn tick(seconds: f64) -> String {
    format_seconds(seconds)
}

/// Round times for the ticks of a log time axis between `low` and `high`
/// seconds (plotters' own log ticks are powers of ten only, too few for a
/// range like 30 s to 10 min): at most eight.
fn time_ticks(low: f64, high: f64) -> Vec<f64> {
    const NICE: [f64; 22] = [
        0.1, 0.2, 0.5, 1.0, 2.0, 5.0, 10.0, 20.0, 30.0, 60.0, 120.0, 300.0, 600.0, 1200.0, 1800.0,
        3600.0, 7200.0, 14_400.0, 28_800.0, 57_600.0, 86_400.0, 172_800.0,
    ];
    let inside: Vec<f64> = NICE
        .iter()
        .copied()
        .filter(|t| (low..=high).contains(t))
        .collect();
    let stride = inside.len().div_ceil(8).max(1);
    inside.into_iter().step_by(stride).collect()
}

/// The lower and upper ends of a log axis around `values`, a little wider
/// so that markers at the ends are not cut.
fn log_range(values: impl Iterator<Item = f64>, fallback: (f64, f64)) -> (f64, f64) {
    let (mut low, mut high) = (f64::INFINITY, 0f64);
    for v in values.filter(|v| v.is_finite() && *v > 0.0) {
        low = low.min(v);
        high = high.max(v);
    }
    if !(low.is_finite() && high > 0.0) {
        (low, high) = fallback;
    }
    if high <= low {
        high = low * 2.0;
    }
    (low / 1.25, high * 1.25)
}

/// A grey note, right-aligned, just above the pixel `at`.
fn note_above<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    at: (i32, i32),
    text: String,
) -> Result<(), String> {
    root.draw(&Text::new(
        text,
        (at.0 - 4, at.1 - 3),
        (FAMILY, 14)
            .into_font()
            .color(&GREY)
            .pos(Pos::new(HPos::Right, VPos::Bottom)),
    ))
    .map_err(err)
}

/// The legend of the series drawn with labels, in a framed box.
fn draw_legend<'a, DB: DrawingBackend + 'a, CT: CoordTranslate>(
    chart: &mut ChartContext<'a, DB, CT>,
    position: SeriesLabelPosition,
) -> Result<(), String> {
    chart
        .configure_series_labels()
        .position(position)
        .background_style(WHITE.mix(0.9))
        .border_style(RGBColor(0xbb, 0xbb, 0xbb))
        .label_font((FAMILY, 16))
        .draw()
        .map_err(err)
}

/// The colour of reference lines and their notes.
const GREY: RGBColor = RGBColor(0x88, 0x88, 0x88);

/// PSNR against training time (log axis), every series overlaid, with a
/// dotted line at each target; writes `<base>.png` and `<base>.svg`.
pub fn write_psnr_plot(
    title: &str,
    x_label: &str,
    series: &[Series],
    targets: &[f64],
    base: &Path,
) -> Result<Vec<PathBuf>, String> {
    write_both(
        base,
        |root| draw_psnr(root, title, x_label, series, targets),
        |root| draw_psnr(root, title, x_label, series, targets),
    )
}

fn draw_psnr<DB: DrawingBackend>(
    root: DrawingArea<DB, Shift>,
    title: &str,
    x_label: &str,
    series: &[Series],
    targets: &[f64],
) -> Result<(), String> {
    root.fill(&WHITE).map_err(err)?;
    let points = || {
        series
            .iter()
            .flat_map(|s| s.points.iter())
            .filter(|(t, p)| *t > 0.0 && t.is_finite() && p.is_finite())
    };
    let (x_low, x_high) = log_range(points().map(|p| p.0), (1.0, 600.0));
    let psnrs: Vec<f64> = points().map(|p| p.1).collect();
    let low = psnrs.iter().copied().fold(f64::INFINITY, f64::min);
    let high = psnrs
        .iter()
        .copied()
        .chain(targets.iter().copied())
        .fold(f64::NEG_INFINITY, f64::max);
    let (y_low, y_high) = if low.is_finite() && high.is_finite() {
        ((low - 1.0).floor(), (high + 1.0).ceil())
    } else {
        (0.0, 40.0)
    };
    let mut chart = ChartBuilder::on(&root)
        .caption(title, (FAMILY, 24))
        .margin(16)
        .x_label_area_size(52)
        .y_label_area_size(64)
        .build_cartesian_2d(
            (x_low..x_high)
                .log_scale()
                .with_key_points(time_ticks(x_low, x_high)),
            y_low..y_high,
        )
        .map_err(err)?;
    chart
        .configure_mesh()
        .x_desc(x_label)
        .y_desc("PSNR (dB)")
        .x_label_formatter(&|v| tick(*v))
        .y_label_formatter(&|v| format!("{v:.0}"))
        .label_style((FAMILY, 16))
        .axis_desc_style((FAMILY, 18))
        .light_line_style(RGBColor(0xee, 0xee, 0xee))
        .draw()
        .map_err(err)?;
    for &target in targets.iter().filter(|t| (y_low..=y_high).contains(*t)) {
        chart
            .draw_series(DashedLineSeries::new(
                [(x_low, target), (x_high, target)],
                4,
                6,
                GREY.stroke_width(1),
            ))
            .map_err(err)?;
        // At the right edge, where the legend (upper left) is not.
        note_above(
            &root,
            chart.backend_coord(&(x_high, target)),
            format!("{target:.0} dB"),
        )?;
    }
    for s in series {
        let colour = s.style.colour();
        let points: Vec<(f64, f64)> = s
            .points
            .iter()
            .copied()
            .filter(|(t, p)| *t > 0.0 && t.is_finite() && p.is_finite())
            .collect();
        let line = colour.stroke_width(2);
        let annotated = if s.style.dashed {
            chart
                .draw_series(DashedLineSeries::new(points.clone(), 8, 5, line))
                .map_err(err)?
        } else {
            chart
                .draw_series(LineSeries::new(points.clone(), line))
                .map_err(err)?
        };
        let dashed = s.style.dashed;
        annotated.label(s.label.clone()).legend(move |(x, y)| {
            let style = if dashed {
                colour.stroke_width(2)
            } else {
                colour.filled()
            };
            EmptyElement::at((x, y))
                + PathElement::new([(-6, 0), (18, 0)], colour.stroke_width(2))
                + Circle::new((6, 0), 4, style)
        });
        let marker = if s.style.dashed {
            colour.stroke_width(2)
        } else {
            colour.filled()
        };
        chart
            .draw_series(points.iter().map(|&p| Circle::new(p, 4, marker)))
            .map_err(err)?;
    }
    if !series.is_empty() {
        draw_legend(&mut chart, SeriesLabelPosition::UpperLeft)?;
    }
    Ok(())
}

/// Grouped bars: for each PSNR target, the training time each model took
/// to reach it (log axis), under a dashed line at the budget. A target
/// reached by the first mark is drawn to that mark and labelled "≤"; one
/// never reached is an empty outline up to the budget line, labelled "not
/// reached". Writes `<base>.png` and `<base>.svg`.
pub fn write_time_to_quality_plot(
    title: &str,
    targets: &[f64],
    bars: &[Bars],
    budget_seconds: f64,
    base: &Path,
) -> Result<Vec<PathBuf>, String> {
    write_both(
        base,
        |root| draw_bars(root, title, targets, bars, budget_seconds),
        |root| draw_bars(root, title, targets, bars, budget_seconds),
    )
}

fn draw_bars<DB: DrawingBackend>(
    root: DrawingArea<DB, Shift>,
    title: &str,
    targets: &[f64],
    bars: &[Bars],
    budget_seconds: f64,
) -> Result<(), String> {
    root.fill(&WHITE).map_err(err)?;
    // From a twentyfifth of the budget (below the first default mark) to
    // the budget, wider if a bar needs it, with room above for the bars'
    // labels and, above those, the legend (at 1.8× the legend covered the
    // labels and tops of the first group's bars).
    let reached = bars
        .iter()
        .flat_map(|b| b.reached.iter().filter_map(Reached::seconds));
    let (y_low, y_high) = log_range(
        reached.chain([budget_seconds / 25.0, budget_seconds]),
        (1.0, 600.0),
    );
    let y_high = y_high * 8.0;
    let groups = targets.len().max(1) as f64;
    let mut chart = ChartBuilder::on(&root)
        .caption(title, (FAMILY, 24))
        .margin(16)
        .x_label_area_size(40)
        // Wide enough for the rotated axis title beside tick labels as long
        // as "20 min" (at 64 pixels the title ran over them).
        .y_label_area_size(88)
        .build_cartesian_2d(
            0f64..groups,
            (y_low..y_high)
                .log_scale()
                .with_key_points(time_ticks(y_low, y_high)),
        )
        .map_err(err)?;
    chart
        .configure_mesh()
        .disable_x_mesh()
        .x_labels(0)
        .y_desc("training time to reach the PSNR (log scale)")
        .y_label_formatter(&|v| tick(*v))
        .label_style((FAMILY, 16))
        .axis_desc_style((FAMILY, 18))
        .light_line_style(RGBColor(0xee, 0xee, 0xee))
        .draw()
        .map_err(err)?;
    chart
        .draw_series(DashedLineSeries::new(
            [(0.0, budget_seconds), (groups, budget_seconds)],
            4,
            6,
            GREY.stroke_width(1),
        ))
        .map_err(err)?;
    note_above(
        &root,
        chart.backend_coord(&(groups, budget_seconds)),
        format!("budget {}", format_seconds(budget_seconds)),
    )?;
    let per_group = bars.len().max(1) as f64;
    let width = 0.8 / per_group;
    let text = |size: i32, colour: RGBColor| (FAMILY, size).into_font().color(&colour);
    let black = RGBColor(0x22, 0x22, 0x22);
    for (g, target) in targets.iter().enumerate() {
        let centre = chart.backend_coord(&(g as f64 + 0.5, y_low));
        root.draw(&Text::new(
            format!("{target:.0} dB"),
            (centre.0 - 20, centre.1 + 10),
            text(18, black),
        ))
        .map_err(err)?;
        for (j, b) in bars.iter().enumerate() {
            let x0 = g as f64 + 0.1 + j as f64 * width;
            let x1 = x0 + width * 0.9;
            let colour = b.style.colour();
            let (top, filled, label) = match b.reached.get(g) {
                Some(&Reached::Interpolated { seconds }) => {
                    (seconds, true, format_seconds(seconds))
                }
                Some(&Reached::AtMost { seconds }) => {
                    (seconds, true, format!("≤ {}", format_seconds(seconds)))
                }
                Some(&Reached::NotReached { .. }) => (budget_seconds, false, "not reached".into()),
                Some(Reached::NoMarks) | None => continue,
            };
            // The paper's sampler in a lighter shade of its model's colour.
            let shade = if b.style.dashed {
                colour.mix(0.45)
            } else {
                colour.mix(1.0)
            };
            let style = if filled {
                shade.filled()
            } else {
                shade.stroke_width(2)
            };
            chart
                .draw_series(std::iter::once(Rectangle::new(
                    [(x0, y_low), (x1, top)],
                    style,
                )))
                .map_err(err)?;
            let at = chart.backend_coord(&((x0 + x1) / 2.0, top));
            // Labels stand upright above their bar, rotated to fit narrow bars.
            root.draw(&Text::new(
                label,
                (at.0 - 7, at.1 - 6),
                (FAMILY, 14)
                    .into_font()
                    .transform(FontTransform::Rotate270)
                    .color(&black),
            ))
            .map_err(err)?;
        }
    }
    // A legend: one swatch per model, drawn as invisible series so that
    // plotters lays it out.
    for b in bars {
        let colour = b.style.colour();
        let dashed = b.style.dashed;
        chart
            .draw_series(std::iter::empty::<Rectangle<(f64, f64)>>())
            .map_err(err)?
            .label(b.label.clone())
            .legend(move |(x, y)| {
                let style = if dashed {
                    colour.mix(0.45).filled()
                } else {
                    colour.filled()
                };
                Rectangle::new([(x - 6, y - 6), (x + 12, y + 6)], style)
            });
    }
    if !bars.is_empty() {
        draw_legend(&mut chart, SeriesLabelPosition::UpperLeft)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn time_ticks_are_round_and_few() {
        assert_eq!(time_ticks(24.0, 750.0), [30.0, 60.0, 120.0, 300.0, 600.0]);
        assert_eq!(time_ticks(2.5, 25.0), [5.0, 10.0, 20.0]);
        let wide = time_ticks(0.1, 200_000.0);
        assert!(wide.len() <= 8 && wide[0] == 0.1, "{wide:?}");
    }

    #[test]
    fn both_files_are_written_and_the_png_is_drawn_on() {
        let dir = tempfile::tempdir().unwrap();
        let series = [Series {
            label: "Instant-NGP".into(),
            style: SeriesStyle::of(ModelKind::Ngp, false),
            points: vec![(30.0, 20.0), (60.0, 26.0), (120.0, 29.0)],
        }];
        let written = write_psnr_plot(
            "demo",
            "training time",
            &series,
            &[25.0],
            &dir.path().join("p"),
        )
        .unwrap();
        assert_eq!(written.len(), 2);
        let png = image::open(&written[0]).unwrap().to_rgb8();
        assert_eq!((png.width(), png.height()), SIZE);
        // The curve's colour is on the canvas (not only white and greys).
        let blue = image::Rgb(ModelKind::Ngp.spec().colour);
        assert!(png.pixels().filter(|p| **p == blue).count() > 50);
        let svg = std::fs::read_to_string(&written[1]).unwrap();
        assert!(
            svg.starts_with("<svg") && svg.contains("Instant-NGP"),
            "{svg:.200}"
        );

        let bars = [Bars {
            label: "NeRF".into(),
            style: SeriesStyle::of(ModelKind::Nerf, false),
            reached: vec![
                Reached::Interpolated { seconds: 50.0 },
                Reached::NotReached { seconds: 120.0 },
            ],
        }];
        let written =
            write_time_to_quality_plot("demo", &[25.0, 30.0], &bars, 120.0, &dir.path().join("b"))
                .unwrap();
        let svg = std::fs::read_to_string(&written[1]).unwrap();
        assert!(
            svg.contains("not reached") && svg.contains("50 s"),
            "{svg:.200}"
        );
    }
}
