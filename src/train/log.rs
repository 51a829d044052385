//! `metrics.jsonl`: one JSON object per logged step, appended and flushed
//! as training goes, so a crashed run still has its history.

use std::fs::{File, OpenOptions};
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

/// One line of `metrics.jsonl`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LogLine {
    pub step: u32,
    /// Seconds since training started, including evaluation.
    pub wall_seconds: f64,
    /// Seconds spent in training steps only (evaluation excluded), the
    /// clock instant-ngp's and the papers' training times use.
    pub train_seconds: f64,
    pub loss: f32,
    /// PSNR on the held-out views, when evaluated at this step.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub psnr: Option<f64>,
    pub samples_per_ray: f32,
    /// Samples per ray before the rays' cuts, where the engine counts them
    /// (see `StepStats::samples_composited`).
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub composited_per_ray: Option<f32>,
    pub samples_per_second: f64,
    pub rays_per_batch: usize,
}

pub struct MetricsLog {
    path: PathBuf,
    out: BufWriter<File>,
}

impl MetricsLog {
    /// Opens `path` for appending (a resumed run continues the same file).
    pub fn open(path: &Path) -> std::io::Result<Self> {
        let file = OpenOptions::new().create(true).append(true).open(path)?;
        Ok(Self {
            path: path.to_path_buf(),
            out: BufWriter::new(file),
        })
    }

    pub fn write(&mut self, line: &LogLine) -> std::io::Result<()> {
        serde_json::to_writer(&mut self.out, line)?;
        self.out.write_all(b"\n")?;
        self.out.flush()
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Reads every line of a log.
    pub fn read(path: &Path) -> std::io::Result<Vec<LogLine>> {
        let text = std::fs::read_to_string(path)?;
        text.lines()
            .filter(|l| !l.trim().is_empty())
            .map(|l| serde_json::from_str(l).map_err(std::io::Error::other))
            .collect()
    }
}
