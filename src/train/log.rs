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
    /// Samples per ray of a proposal sampler's density-only levels, apart
    /// from `samples_per_ray` (the full field's).
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub proposal_samples_per_ray: Option<f32>,
    /// The interlevel loss that trains the proposal levels.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub proposal_loss: Option<f32>,
    pub samples_per_second: f64,
    pub rays_per_batch: usize,
}

pub struct MetricsLog {
    path: PathBuf,
    out: BufWriter<File>,
}

impl MetricsLog {
    /// Opens `path` for appending (a resumed run continues the same file),
    /// only if it is a regular file and not a link: a log linked to
    /// another file would have the run's lines appended to that file. The
    /// error names the path and what is there.
    pub fn open(path: &Path) -> Result<Self, String> {
        let file = crate::files::open_for_writing_no_follow(
            path,
            OpenOptions::new().create(true).append(true),
        )?;
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

    /// Cuts the log at `path` back to the lines of steps up to `step` (a
    /// checkpoint's), dropping those logged after it: a resumed run trains
    /// those steps again and logs them anew. A last line cut off mid-write
    /// goes too. The file is rewritten whole through a temporary file, and
    /// only when something is dropped; returns the lines dropped. A missing
    /// log is no error.
    ///
    /// A log that is a link, or not a regular file, or larger than
    /// [`MAX_LOG_BYTES`], is refused before anything is read: the error
    /// names the path, what is there and what to do.
    pub fn truncate_after(path: &Path, step: u32) -> Result<usize, String> {
        if !crate::files::exists_at_all(path) {
            return Ok(0);
        }
        let text = Self::read_text(path)?;
        let mut kept = String::with_capacity(text.len());
        let mut dropped = 0;
        for line in text.lines().filter(|l| !l.trim().is_empty()) {
            #[derive(Deserialize)]
            struct Step {
                step: u32,
            }
            match serde_json::from_str::<Step>(line) {
                Ok(logged) if logged.step <= step => {
                    kept.push_str(line);
                    kept.push('\n');
                }
                _ => dropped += 1,
            }
        }
        if dropped > 0 {
            crate::files::write_bytes_atomically(path, kept.as_bytes())
                .map_err(|e| format!("{}: cannot rewrite the log: {e}", path.display()))?;
        }
        Ok(dropped)
    }

    /// Reads every line of a log.
    pub fn read(path: &Path) -> Result<Vec<LogLine>, String> {
        Self::read_text(path)?
            .lines()
            .filter(|l| !l.trim().is_empty())
            .map(|l| serde_json::from_str(l).map_err(|e| format!("{}: {e}", path.display())))
            .collect()
    }

    /// The whole log as text, if it is a regular file (not a link, which a
    /// resumed run would go on to append through) of at most
    /// [`MAX_LOG_BYTES`].
    fn read_text(path: &Path) -> Result<String, String> {
        Self::check_not_a_link(path)?;
        crate::files::read_text_bounded(path, MAX_LOG_BYTES, "a run's log").map_err(|problem| {
            format!(
                "{}: cannot read the run's log: {problem}; move it away to start the log \
                 afresh",
                path.display()
            )
        })
    }

    /// Refuses a log that is a symbolic link (see [`Self::open`]).
    pub fn check_not_a_link(path: &Path) -> Result<(), String> {
        if std::fs::symlink_metadata(path).is_ok_and(|m| m.file_type().is_symlink()) {
            return Err(format!(
                "{}: a symbolic link, which zrak does not write through (it could point at \
                 any file); remove it and run again",
                path.display()
            ));
        }
        Ok(())
    }
}

/// The largest `metrics.jsonl` read back: a line of about 300 bytes every
/// 16 steps makes 512 MB some 27 million steps, far past any run's length.
pub const MAX_LOG_BYTES: u64 = 512 << 20;

#[cfg(test)]
mod tests {
    use super::*;

    fn line(step: u32) -> LogLine {
        LogLine {
            step,
            wall_seconds: step as f64,
            train_seconds: step as f64,
            loss: 0.5,
            psnr: None,
            samples_per_ray: 4.0,
            composited_per_ray: None,
            proposal_samples_per_ray: None,
            proposal_loss: None,
            samples_per_second: 1e6,
            rays_per_batch: 256,
        }
    }

    #[test]
    fn a_resumed_log_is_cut_back_to_the_checkpoints_step() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("metrics.jsonl");
        let mut log = MetricsLog::open(&path).unwrap();
        for step in [16, 32, 48, 64] {
            log.write(&line(step)).unwrap();
        }
        drop(log);
        // A line cut off by a crash mid-write.
        let mut text = std::fs::read_to_string(&path).unwrap();
        text.push_str("{\"step\":80,\"wall_");
        std::fs::write(&path, text).unwrap();
        assert_eq!(MetricsLog::truncate_after(&path, 40).unwrap(), 3);
        let steps: Vec<u32> = MetricsLog::read(&path)
            .unwrap()
            .iter()
            .map(|l| l.step)
            .collect();
        assert_eq!(steps, [16, 32]);
        assert_eq!(MetricsLog::truncate_after(&path, 40).unwrap(), 0);
        assert_eq!(
            MetricsLog::truncate_after(&dir.path().join("none"), 1).unwrap(),
            0
        );
    }

    #[cfg(unix)]
    #[test]
    fn a_log_that_is_a_link_is_neither_read_nor_appended_through() {
        let dir = tempfile::tempdir().unwrap();
        let target = dir.path().join("notes.txt");
        std::fs::write(&target, "the user's own\n").unwrap();
        let path = dir.path().join("metrics.jsonl");
        std::os::unix::fs::symlink(&target, &path).unwrap();
        let error = MetricsLog::truncate_after(&path, 0).unwrap_err();
        assert!(error.contains("symbolic link"), "{error}");
        let error = MetricsLog::open(&path).err().unwrap();
        assert!(error.contains("symbolic link"), "{error}");
        assert_eq!(
            std::fs::read_to_string(&target).unwrap(),
            "the user's own\n"
        );
        assert!(
            std::fs::symlink_metadata(&path)
                .unwrap()
                .file_type()
                .is_symlink()
        );
    }
}
