//! What `zrak bench quality` writes: `results.json` (every measurement
//! with the machine, engine and settings), `results.csv` (one row per
//! mark), `report.md` (the tables, with the papers' figures beside them)
//! and the plots, from the cells' records.

use std::path::{Path, PathBuf};

use serde::Serialize;

use super::plot::{
    Bars, Series, SeriesStyle, {self},
};
use super::published::{PUBLISHED, blender_scene, figures};
use super::quality::{CellRecord, CellSpec, MarkResult, Protocol, safe_name};
use super::table::{
    Reached, Table, format_mark, format_mib, format_psnr, format_seconds, format_ssim,
    time_to_reach,
};
use crate::field::ModelKind;
use crate::field::common::Sampling;

pub const RESULTS_JSON: &str = "results.json";
pub const RESULTS_CSV: &str = "results.csv";
pub const REPORT_MD: &str = "report.md";

/// The machine the experiment ran on.
#[derive(Debug, Clone, Serialize)]
pub struct Machine {
    pub cpu: String,
    pub threads: usize,
    pub os: String,
    /// The vector and matrix extensions that matter to the cpu engine.
    pub cpu_features: Vec<String>,
}

/// This machine, as far as it can be read.
pub fn machine() -> Machine {
    let cpuinfo = std::fs::read_to_string("/proc/cpuinfo").unwrap_or_default();
    let field = |name: &str| {
        cpuinfo
            .lines()
            .find(|l| l.starts_with(name))
            .and_then(|l| l.split_once(':'))
            .map(|(_, v)| v.trim().to_string())
    };
    let flags = field("flags").unwrap_or_default();
    let cpu_features = [
        "avx2",
        "fma",
        "avx512f",
        "avx512_bf16",
        "amx_tile",
        "amx_bf16",
    ]
    .iter()
    .filter(|f| flags.split_whitespace().any(|g| g == **f))
    .map(|f| f.to_string())
    .collect();
    let release = std::fs::read_to_string("/proc/sys/kernel/osrelease").unwrap_or_default();
    Machine {
        cpu: field("model name").unwrap_or_else(|| std::env::consts::ARCH.to_string()),
        threads: rayon::current_num_threads(),
        os: format!("{} {}", std::env::consts::OS, release.trim())
            .trim()
            .to_string(),
        cpu_features,
    }
}

/// The engine every cell trained on.
#[derive(Debug, Clone, Serialize)]
pub struct EngineInfo {
    /// `cpu` or `gpu`.
    pub engine: String,
    /// Why it was chosen and on what adapter.
    pub description: String,
    /// The compute kernels (the cpu engine's instruction set, or WGSL).
    pub kernels: String,
    /// Number formats of the networks' products and sums.
    pub precision: String,
}

/// A scene of the experiment.
#[derive(Debug, Clone, Serialize)]
pub struct SceneEntry {
    pub name: String,
    /// The folder, or `demo`.
    pub source: String,
    /// Views in the scored split, and which are scored.
    pub split_views: usize,
    pub scored: String,
}

/// The settings of the experiment.
#[derive(Debug, Clone, Serialize)]
pub struct Settings {
    #[serde(flatten)]
    pub protocol: Protocol,
    pub models: Vec<ModelKind>,
    pub samplings: Vec<Sampling>,
    pub scenes: Vec<SceneEntry>,
    pub targets_db: Vec<f64>,
    /// What held-out renders and photographs are composited on.
    pub background: String,
    /// The command that made (and resumes) the experiment.
    pub command: String,
}

/// The time to one target.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct TargetTime {
    pub target_db: f64,
    #[serde(flatten)]
    pub reached: Reached,
}

/// One cell's measurements and what follows from them.
#[derive(Debug, Clone, Serialize)]
pub struct CellResult {
    pub scene: String,
    pub model: ModelKind,
    pub sampling: Sampling,
    pub label: String,
    /// The cell's run folder, relative to the experiment's (`zrak eval`,
    /// `render` and `train --resume` take it).
    pub run_folder: String,
    pub finished: bool,
    pub engine: String,
    /// At the last mark scored.
    pub steps: u32,
    pub train_seconds: f64,
    /// Samples the networks trained on per training second, over the
    /// segments measured.
    pub samples_per_second: Option<f64>,
    /// The largest at any mark.
    pub memory_bytes: Option<u64>,
    pub peak_rss_bytes: Option<u64>,
    pub time_to_targets: Vec<TargetTime>,
    pub marks: Vec<MarkResult>,
}

impl CellResult {
    pub fn new(spec: &CellSpec, record: &CellRecord, folder: &Path, targets: &[f64]) -> Self {
        let curve = record.curve();
        let last = record.marks.last();
        let samples: u64 = record.marks.iter().map(|m| m.samples).sum();
        let seconds: f64 = record.marks.iter().map(|m| m.sample_seconds).sum();
        Self {
            scene: spec.scene.clone(),
            model: spec.model,
            sampling: spec.sampling,
            label: spec.label(),
            run_folder: folder.display().to_string(),
            finished: record.finished(),
            engine: record.engine.clone(),
            steps: last.map_or(0, |m| m.step),
            train_seconds: last.map_or(0.0, |m| m.train_seconds),
            samples_per_second: (seconds > 0.0).then(|| samples as f64 / seconds),
            memory_bytes: record.marks.iter().map(|m| m.memory_bytes).max(),
            peak_rss_bytes: record.marks.iter().filter_map(|m| m.peak_rss_bytes).max(),
            time_to_targets: targets
                .iter()
                .map(|&target_db| TargetTime {
                    target_db,
                    reached: time_to_reach(&curve, target_db),
                })
                .collect(),
            marks: record.marks.clone(),
        }
    }

    fn style(&self) -> SeriesStyle {
        SeriesStyle::of(
            self.model,
            self.model.has_paper_sampler() && self.sampling == Sampling::Paper,
        )
    }
}

/// A paper's figure for a scene of the experiment.
#[derive(Debug, Clone, Serialize)]
pub struct PublishedRow {
    pub model: ModelKind,
    /// The NeRF-synthetic scene, or `mean of 8 scenes`.
    pub scene: String,
    pub psnr: f64,
    pub ssim: Option<f64>,
    pub split: &'static str,
    pub training: &'static str,
    pub source: &'static str,
}

/// Everything `results.json` holds.
#[derive(Debug, Clone, Serialize)]
pub struct Results {
    pub zrak_version: &'static str,
    pub written_unix_seconds: u64,
    pub written_utc: String,
    pub machine: Machine,
    pub engine: EngineInfo,
    pub settings: Settings,
    pub cells: Vec<CellResult>,
    pub published: Vec<PublishedRow>,
}

impl Results {
    pub fn new(
        machine: Machine,
        engine: EngineInfo,
        settings: Settings,
        cells: Vec<CellResult>,
    ) -> Self {
        let now = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_secs());
        let models: Vec<ModelKind> = {
            let mut models = Vec::new();
            for cell in &cells {
                if !models.contains(&cell.model) {
                    models.push(cell.model);
                }
            }
            models
        };
        let mut published = Vec::new();
        let mut scenes: Vec<&'static str> = settings
            .scenes
            .iter()
            .filter_map(|s| blender_scene(&s.name))
            .collect();
        scenes.dedup();
        for &model in &models {
            for scene in &scenes {
                if let Some((psnr, ssim, paper)) = figures(model, scene) {
                    published.push(PublishedRow {
                        model,
                        scene: scene.to_string(),
                        psnr,
                        ssim,
                        split: "test",
                        training: paper.training,
                        source: paper.source,
                    });
                }
            }
            if let Some(paper) = PUBLISHED.iter().find(|p| p.model == model) {
                published.push(PublishedRow {
                    model,
                    scene: "mean of 8 scenes".into(),
                    psnr: paper.mean_psnr,
                    ssim: paper.mean_ssim,
                    split: "test",
                    training: paper.training,
                    source: paper.source,
                });
            }
        }
        Self {
            zrak_version: env!("CARGO_PKG_VERSION"),
            written_unix_seconds: now,
            written_utc: utc_date_time(now),
            machine,
            engine,
            settings,
            cells,
            published,
        }
    }

    fn scene_names(&self) -> Vec<&str> {
        self.settings
            .scenes
            .iter()
            .map(|s| s.name.as_str())
            .collect()
    }

    fn cells_of<'a>(&'a self, scene: &'a str) -> impl Iterator<Item = &'a CellResult> + 'a {
        self.cells.iter().filter(move |c| c.scene == scene)
    }
}

/// `2025-11-24 21:30 UTC` from Unix seconds (days to a civil date by
/// Howard Hinnant's algorithm, so no calendar crate is needed).
pub fn utc_date_time(unix_seconds: u64) -> String {
    let days = (unix_seconds / 86_400) as i64;
    let minutes_of_day = (unix_seconds % 86_400) / 60;
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let day_of_era = z.rem_euclid(146_097);
    let year_of_era =
        (day_of_era - day_of_era / 1460 + day_of_era / 36_524 - day_of_era / 146_096) / 365;
    let day_of_year = day_of_era - (365 * year_of_era + year_of_era / 4 - year_of_era / 100);
    let month_index = (5 * day_of_year + 2) / 153;
    let day = day_of_year - (153 * month_index + 2) / 5 + 1;
    let month = if month_index < 10 {
        month_index + 3
    } else {
        month_index - 9
    };
    let year = year_of_era + era * 400 + i64::from(month <= 2);
    format!(
        "{year:04}-{month:02}-{day:02} {:02}:{:02} UTC",
        minutes_of_day / 60,
        minutes_of_day % 60
    )
}

/// Samples per second as `2.05 M` or `17.8 k`.
fn format_rate(rate: Option<f64>) -> String {
    match rate {
        Some(r) if r >= 1e6 => format!("{:.2} M", r / 1e6),
        Some(r) if r >= 1e3 => format!("{:.1} k", r / 1e3),
        Some(r) => format!("{r:.0}"),
        None => "—".to_string(),
    }
}

/// PSNR and SSIM at each mark, one row per cell of `scene`.
pub fn marks_table(results: &Results, scene: &str) -> Table {
    let marks = &results.settings.protocol.marks_seconds;
    let mut table = Table::new(
        std::iter::once("model".to_string()).chain(marks.iter().map(|&m| format_mark(m))),
    );
    for cell in results.cells_of(scene) {
        let mut row = vec![cell.label.clone()];
        for i in 0..marks.len() {
            row.push(match cell.marks.get(i) {
                Some(m) => format!("{} / {}", format_psnr(m.psnr), format_ssim(m.ssim)),
                None => "…".to_string(),
            });
        }
        table.push(row);
    }
    table
}

/// Time to each target, steps, throughput and memory, one row per cell.
pub fn cost_table(results: &Results, scene: &str) -> Table {
    let mut headers = vec!["model".to_string()];
    headers.extend(
        results
            .settings
            .targets_db
            .iter()
            .map(|t| format!("to {t:.0} dB")),
    );
    headers.extend(
        ["steps", "samples/s", "model memory", "peak memory"]
            .iter()
            .map(|s| s.to_string()),
    );
    let mut table = Table::new(headers);
    for cell in results.cells_of(scene) {
        let mut row = vec![cell.label.clone()];
        row.extend(cell.time_to_targets.iter().map(|t| t.reached.describe()));
        row.push(if cell.finished {
            cell.steps.to_string()
        } else {
            format!("{} (unfinished)", cell.steps)
        });
        row.push(format_rate(cell.samples_per_second));
        row.push(format_mib(cell.memory_bytes));
        row.push(format_mib(cell.peak_rss_bytes));
        table.push(row);
    }
    table
}

/// The papers' figures for `scene` (and their means).
fn published_table(results: &Results, scene: &str) -> Table {
    let own = blender_scene(scene);
    let mut table = Table::new(["model", "scene", "PSNR", "SSIM", "trained", "source"]);
    for row in &results.published {
        if Some(row.scene.as_str()) != own && row.scene != "mean of 8 scenes" {
            continue;
        }
        table.push([
            row.model.name().to_string(),
            row.scene.clone(),
            format_psnr(row.psnr),
            row.ssim.map_or("—".into(), format_ssim),
            row.training.to_string(),
            row.source.to_string(),
        ]);
    }
    table
}

/// One row per scored mark: the machine-readable form of the report.
pub fn results_table(results: &Results) -> Table {
    let mut table = Table::new([
        "scene",
        "model",
        "sampling",
        "mark_seconds",
        "train_seconds",
        "step",
        "psnr",
        "ssim",
        "views",
        "eval_downscale",
        "eval_pixels",
        "eval_seconds",
        "samples_per_second",
    ]);
    for cell in &results.cells {
        for m in &cell.marks {
            table.push([
                cell.scene.clone(),
                cell.model.key().to_string(),
                cell.sampling.name().to_string(),
                m.mark_seconds.to_string(),
                format!("{:.3}", m.train_seconds),
                m.step.to_string(),
                format!("{:.4}", m.psnr),
                format!("{:.5}", m.ssim),
                m.views.len().to_string(),
                results.settings.protocol.eval_downscale.to_string(),
                format!("{:?}", results.settings.protocol.eval_pixels).to_lowercase(),
                format!("{:.2}", m.eval_seconds),
                if m.sample_seconds > 0.0 {
                    format!("{:.0}", m.samples as f64 / m.sample_seconds)
                } else {
                    String::new()
                },
            ]);
        }
    }
    table
}

/// The Markdown report.
pub fn report_markdown(results: &Results) -> String {
    let p = &results.settings.protocol;
    let m = &results.machine;
    let mut out = String::new();
    out.push_str("# What accuracy costs in time\n\n");
    out.push_str(&format!(
        "zrak {} on {} ({} threads{}; {}), {}; kernels: {}; precision: {}. Written {}.\n\n",
        results.zrak_version,
        m.cpu,
        m.threads,
        if m.cpu_features.is_empty() {
            String::new()
        } else {
            format!(", {}", m.cpu_features.join(" "))
        },
        m.os,
        results.engine.description,
        results.engine.kernels,
        results.engine.precision,
        results.written_utc,
    ));
    out.push_str(&format!(
        "Each model trained for {} of training time on each scene; the clock \
         stops while a mark is scored, so evaluation is not counted. At each \
         mark ({}) PSNR and SSIM are the means over the views scored, rendered \
         on white and compared with the photographs composited on white (the \
         reference protocol). Training images {}; seed {}; {}.\n\n",
        format_seconds(p.budget_seconds),
        p.marks_seconds
            .iter()
            .map(|&s| format_mark(s))
            .collect::<Vec<_>>()
            .join(", "),
        if p.downscale == 1 {
            "at full resolution".to_string()
        } else {
            format!("at 1/{} resolution", p.downscale)
        },
        p.seed,
        match p.batch_samples {
            None => "each model's own batch (the papers')".to_string(),
            Some(n) => format!("batches of {n} samples, not the papers'"),
        },
    ));
    if p.split != "test" {
        out.push_str(&format!(
            "The papers score the test split; these scores are on the **{}** split \
             (for the NeRF-synthetic folders here the test split is not present), so \
             they are close to, but not the same as, a test score.\n\n",
            p.split
        ));
    }
    out.push_str(&format!("Command: `{}`\n\n", results.settings.command));
    for scene in results.scene_names() {
        let entry = results
            .settings
            .scenes
            .iter()
            .find(|s| s.name == scene)
            .expect("a scene of the settings");
        let file = safe_name(scene);
        out.push_str(&format!("## {scene}\n\n"));
        out.push_str(&format!("Scored: {}.\n\n", entry.scored));
        out.push_str(&format!(
            "![PSNR against training time, {scene}](psnr_{file}.png)\n\n"
        ));
        out.push_str("PSNR (dB) / SSIM at each mark of training time:\n\n");
        out.push_str(&marks_table(results, scene).to_markdown());
        out.push('\n');
        out.push_str("Training time to reach each PSNR, and what the training cost:\n\n");
        out.push_str(&cost_table(results, scene).to_markdown());
        out.push('\n');
        out.push_str(&format!(
            "![Training time to reach each PSNR, {scene}](time_to_quality_{file}.png)\n\n"
        ));
        let published = published_table(results, scene);
        if !published.rows.is_empty() {
            out.push_str(
                "Published figures for reference (test split at 800×800, after the \
                 papers' own training on GPUs):\n\n",
            );
            out.push_str(&published.to_markdown());
            out.push('\n');
        }
    }
    out.push_str("## How to read this\n\n");
    out.push_str(
        "- **to N dB**: the training time at which the PSNR first reaches N dB, \
         interpolated between the two marks around the crossing along a straight \
         line of PSNR against the logarithm of training time (the plots' axis). \
         `≤ 30 s` means the first mark already reached it, so only a bound is \
         known; `not in 10 min` means no mark reached it.\n",
    );
    out.push_str(
        "- A mark is scored at the end of the step that passes it, so its training \
         time is a little past the mark; `results.json` and `results.csv` hold the \
         exact time and step of each.\n",
    );
    out.push_str(
        "- **samples/s**: samples the networks trained on per second of training, \
         over the whole budget.\n",
    );
    out.push_str(
        "- **model memory**: parameters, optimiser state and workspaces as the model \
         counts them (allocated, so it can exceed what is resident); **peak memory**: \
         the process's peak resident memory while the cell trained and was scored \
         (Linux VmHWM, reset when each segment between marks starts), which includes \
         the loaded scene.\n",
    );
    out.push_str(
        "- Each cell is a run folder under `runs/`: `zrak eval`, `zrak render` and \
         `zrak train --resume` take it. Running the same command again continues an \
         interrupted experiment and scores nothing twice.\n",
    );
    if results.cells.iter().any(|c| !c.finished) {
        out.push_str(
            "\n**Unfinished**: some cells have not reached their budget (marked `…` \
             and `(unfinished)`); run the command again to continue them.\n",
        );
    }
    out
}

/// Writes every output into `dir`; returns the files written.
pub fn write_outputs(dir: &Path, results: &Results) -> Result<Vec<PathBuf>, String> {
    let write = |name: &str, text: &str| -> Result<PathBuf, String> {
        let path = dir.join(name);
        crate::files::write_bytes_atomically(&path, text.as_bytes())
            .map_err(|e| format!("{}: cannot write: {e}", path.display()))?;
        Ok(path)
    };
    let mut written = Vec::new();
    let json = serde_json::to_string_pretty(results).map_err(|e| e.to_string())?;
    written.push(write(RESULTS_JSON, &json)?);
    written.push(write(RESULTS_CSV, &results_table(results).to_csv())?);
    written.push(write(REPORT_MD, &report_markdown(results))?);
    let budget = format_seconds(results.settings.protocol.budget_seconds);
    for scene in results.scene_names() {
        let file = safe_name(scene);
        let series: Vec<Series> = results
            .cells_of(scene)
            .map(|c| Series {
                label: c.label.clone(),
                style: c.style(),
                points: c.marks.iter().map(|m| (m.train_seconds, m.psnr)).collect(),
            })
            .collect();
        written.extend(plot::write_psnr_plot(
            &format!("{scene}: PSNR against training time ({budget} budget)"),
            "training time (log scale; evaluation excluded)",
            &series,
            &results.settings.targets_db,
            &dir.join(format!("psnr_{file}")),
        )?);
        let bars: Vec<Bars> = results
            .cells_of(scene)
            .map(|c| Bars {
                label: c.label.clone(),
                style: c.style(),
                reached: c.time_to_targets.iter().map(|t| t.reached).collect(),
            })
            .collect();
        written.extend(plot::write_time_to_quality_plot(
            &format!("{scene}: training time to reach each PSNR"),
            &results.settings.targets_db,
            &bars,
            results.settings.protocol.budget_seconds,
            &dir.join(format!("time_to_quality_{file}")),
        )?);
    }
    Ok(written)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dates_are_civil_utc() {
        assert_eq!(utc_date_time(0), "1970-01-01 00:00 UTC");
        // 2000-02-29 12:34 UTC, a leap day.
        assert_eq!(utc_date_time(951_827_640), "2000-02-29 12:34 UTC");
        assert_eq!(utc_date_time(1_764_019_800), "2025-11-24 21:30 UTC");
    }

    fn mark(seconds: f64, psnr: f64, step: u32) -> MarkResult {
        MarkResult {
            mark_seconds: seconds,
            train_seconds: seconds + 0.25,
            step,
            psnr,
            ssim: psnr / 40.0,
            views: Vec::new(),
            eval_seconds: 1.0,
            samples: 1_000_000,
            sample_seconds: 2.0,
            memory_bytes: 5 << 20,
            peak_rss_bytes: Some(100 << 20),
        }
    }

    fn results() -> Results {
        let protocol = Protocol::new(60.0, Some(&[15.0, 30.0]), "val", 25, 4, 1, 0).unwrap();
        let spec = |model, sampling| CellSpec {
            scene: "lego_400".into(),
            model,
            sampling,
        };
        let record = |spec: &CellSpec, marks: Vec<MarkResult>| CellRecord {
            protocol: protocol.clone(),
            scene: spec.scene.clone(),
            model: spec.model,
            sampling: spec.sampling,
            engine: "cpu".into(),
            marks,
        };
        let ngp = spec(ModelKind::Ngp, Sampling::Occupancy);
        let nerf = spec(ModelKind::Nerf, Sampling::Paper);
        let targets = [25.0, 30.0];
        let cells = vec![
            CellResult::new(
                &ngp,
                &record(
                    &ngp,
                    vec![
                        mark(15.0, 20.0, 10),
                        mark(30.0, 30.0, 20),
                        mark(60.0, 31.0, 40),
                    ],
                ),
                Path::new("runs/lego_400-ngp"),
                &targets,
            ),
            CellResult::new(
                &nerf,
                &record(&nerf, vec![mark(15.0, 12.0, 2)]),
                Path::new("runs/lego_400-nerf-paper"),
                &targets,
            ),
        ];
        let settings = Settings {
            protocol,
            models: vec![ModelKind::Ngp, ModelKind::Nerf],
            samplings: vec![Sampling::Paper],
            scenes: vec![SceneEntry {
                name: "lego_400".into(),
                source: "/data/lego_400".into(),
                split_views: 100,
                scored: "every 25th view".into(),
            }],
            targets_db: targets.to_vec(),
            background: "white".into(),
            command: "zrak bench quality".into(),
        };
        let engine = EngineInfo {
            engine: "cpu".into(),
            description: "cpu engine (requested)".into(),
            kernels: "Avx512".into(),
            precision: "f32".into(),
        };
        Results::new(machine(), engine, settings, cells)
    }

    #[test]
    fn the_tables_hold_each_mark_and_the_times_to_quality() {
        let results = results();
        let marks = marks_table(&results, "lego_400");
        assert_eq!(marks.headers, ["model", "15 s", "30 s", "1 min"]);
        assert_eq!(
            marks.rows[0],
            [
                "Instant-NGP",
                "20.00 / 0.500",
                "30.00 / 0.750",
                "31.00 / 0.775"
            ]
        );
        assert_eq!(
            marks.rows[1],
            ["NeRF (paper sampler)", "12.00 / 0.300", "…", "…"]
        );

        let cost = cost_table(&results, "lego_400");
        assert_eq!(
            cost.headers,
            [
                "model",
                "to 25 dB",
                "to 30 dB",
                "steps",
                "samples/s",
                "model memory",
                "peak memory"
            ]
        );
        // 25 dB half-way between 20 dB at 15.25 s and 30 dB at 30.25 s in
        // log time: √(15.25 · 30.25) = 21.5 s; 30 dB exactly at the second
        // mark.
        assert_eq!(
            cost.rows[0],
            [
                "Instant-NGP",
                "21 s",
                "30 s",
                "40",
                "500.0 k",
                "5 MiB",
                "100 MiB"
            ]
        );
        assert_eq!(
            cost.rows[1],
            [
                "NeRF (paper sampler)",
                "not in 15 s",
                "not in 15 s",
                "2 (unfinished)",
                "500.0 k",
                "5 MiB",
                "100 MiB"
            ]
        );
        match results.cells[0].time_to_targets[0].reached {
            Reached::Interpolated { seconds } => {
                assert!((seconds - (15.25f64 * 30.25).sqrt()).abs() < 1e-9)
            }
            other => panic!("{other:?}"),
        }

        let csv = results_table(&results).to_csv();
        let lines: Vec<&str> = csv.lines().collect();
        assert_eq!(lines.len(), 1 + 3 + 1);
        assert_eq!(
            lines[2],
            "lego_400,ngp,occupancy,30,30.250,20,30.0000,0.75000,0,4,tiles,1.00,500000"
        );

        let report = report_markdown(&results);
        assert!(report.contains("| Instant-NGP | 20.00 / 0.500 | 30.00 / 0.750 | 31.00 / 0.775 |"));
        assert!(report.contains("**val** split"));
        // The papers' lego figures, with their sources.
        assert!(report.contains("| Instant-NGP | lego | 36.39 | — |"));
        assert!(report.contains("| NeRF | lego | 32.54 | 0.961 |"));
        assert!(report.contains("Mildenhall"));
        assert!(report.contains("**Unfinished**"));
    }

    #[test]
    fn outputs_are_written_and_results_json_parses() {
        let dir = tempfile::tempdir().unwrap();
        let written = write_outputs(dir.path(), &results()).unwrap();
        let names: Vec<String> = written
            .iter()
            .map(|p| p.file_name().unwrap().to_string_lossy().into_owned())
            .collect();
        for name in [
            "results.json",
            "results.csv",
            "report.md",
            "psnr_lego_400.png",
            "psnr_lego_400.svg",
            "time_to_quality_lego_400.png",
            "time_to_quality_lego_400.svg",
        ] {
            assert!(names.contains(&name.to_string()), "{name} in {names:?}");
            assert!(dir.path().join(name).is_file());
        }
        let json: serde_json::Value = serde_json::from_str(
            &std::fs::read_to_string(dir.path().join("results.json")).unwrap(),
        )
        .unwrap();
        assert_eq!(
            json["settings"]["marks_seconds"],
            serde_json::json!([15.0, 30.0, 60.0])
        );
        assert_eq!(
            json["cells"][0]["time_to_targets"][1]["status"],
            "interpolated"
        );
        assert_eq!(
            json["cells"][1]["time_to_targets"][0]["status"],
            "not_reached"
        );
        assert_eq!(json["cells"][0]["marks"][2]["step"], 40);
    }
}
