//! The runs the viewer keeps when it closes (one run folder per model
//! trained since its last save, under `$XDG_DATA_HOME/zrak/runs`): listed
//! newest first with their size, removable one by one, and capped so that
//! closing the viewer again and again does not fill the disk (each
//! Instant-NGP run's checkpoint is a few hundred MB).

use std::path::{Path, PathBuf};
use std::time::SystemTime;

use super::run::{CHECKPOINT_FILE, RunFolder};
use crate::model::checkpoint::Checkpoint;

/// How many kept runs the viewer leaves in place by default: the newest
/// ten; older ones are removed when it keeps a new one.
pub const DEFAULT_KEPT_RUNS: usize = 10;

/// One kept run.
#[derive(Debug, Clone, PartialEq)]
pub struct KeptRun {
    pub folder: PathBuf,
    /// When its checkpoint was written.
    pub modified: SystemTime,
    /// Bytes of every file in the folder.
    pub bytes: u64,
    /// The step and model its checkpoint header names, when readable.
    pub step: Option<u64>,
    pub model: Option<String>,
}

impl KeptRun {
    /// One line for a menu: "demo-ngp-1764… · Ngp · step 512 · 252 MB".
    pub fn describe(&self) -> String {
        let name = self
            .folder
            .file_name()
            .map_or_else(String::new, |n| n.to_string_lossy().into_owned());
        let mut parts = vec![name];
        if let Some(model) = &self.model {
            parts.push(model.clone());
        }
        if let Some(step) = self.step {
            parts.push(format!("step {step}"));
        }
        parts.push(crate::files::human_bytes(self.bytes));
        parts.join(" · ")
    }
}

/// Bytes of the regular files directly in `folder` (run folders are flat).
fn folder_bytes(folder: &Path) -> u64 {
    std::fs::read_dir(folder)
        .into_iter()
        .flatten()
        .flatten()
        .filter_map(|entry| entry.metadata().ok())
        .filter(|meta| meta.is_file())
        .map(|meta| meta.len())
        .sum()
}

/// The run folders under `base` (those holding a checkpoint), newest
/// first. A missing `base` has none.
pub fn list(base: &Path) -> Vec<KeptRun> {
    let mut runs: Vec<KeptRun> = std::fs::read_dir(base)
        .into_iter()
        .flatten()
        .flatten()
        .filter_map(|entry| {
            let folder = entry.path();
            let checkpoint = folder.join(CHECKPOINT_FILE);
            let modified = std::fs::metadata(&checkpoint).ok()?.modified().ok()?;
            let header = Checkpoint::load_header(&checkpoint).ok();
            Some(KeptRun {
                bytes: folder_bytes(&folder),
                step: header.as_ref().and_then(|h| h["trainer"]["step"].as_u64()),
                model: header
                    .as_ref()
                    .and_then(|h| h["run"]["model"].as_str().map(str::to_string)),
                modified,
                folder,
            })
        })
        .collect();
    runs.sort_by(|a, b| b.modified.cmp(&a.modified).then(a.folder.cmp(&b.folder)));
    runs
}

/// Removes one kept run's folder. Refused when another process is
/// training in it (its lock), or when it is not a run folder under `base`:
/// this deletes, so it deletes only what the viewer itself kept.
pub fn remove(base: &Path, folder: &Path) -> Result<(), String> {
    let inside = folder.parent() == Some(base) && folder.join(CHECKPOINT_FILE).is_file();
    if !inside {
        return Err(format!(
            "{}: not one of the viewer's kept runs in {}",
            folder.display(),
            base.display()
        ));
    }
    let lock = RunFolder::create(folder).map_err(|e| e.to_string())?;
    std::fs::remove_dir_all(folder)
        .map_err(|e| format!("{}: cannot remove: {e}", folder.display()))?;
    drop(lock);
    Ok(())
}

/// Removes the oldest kept runs beyond the newest `keep`; returns those
/// removed. Runs another process is using are left alone.
pub fn prune(base: &Path, keep: usize) -> Vec<PathBuf> {
    list(base)
        .into_iter()
        .skip(keep)
        .filter(|run| remove(base, &run.folder).is_ok())
        .map(|run| run.folder)
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn keep_run(base: &Path, name: &str, step: u64, age_seconds: u64) -> PathBuf {
        let folder = base.join(name);
        std::fs::create_dir_all(&folder).unwrap();
        let checkpoint = Checkpoint {
            header: serde_json::json!({"trainer": {"step": step}, "run": {"model": "Ngp"}}),
            tensors: vec![("params".into(), (0..1000).map(|i| i as f32).collect())],
        };
        let path = folder.join(CHECKPOINT_FILE);
        checkpoint.save(&path).unwrap();
        let when = SystemTime::now() - std::time::Duration::from_secs(age_seconds);
        std::fs::File::options()
            .write(true)
            .open(&path)
            .unwrap()
            .set_modified(when)
            .unwrap();
        folder
    }

    #[test]
    fn kept_runs_are_listed_newest_first_with_their_size_and_capped() {
        let dir = tempfile::tempdir().unwrap();
        let base = dir.path().join("runs");
        assert!(list(&base).is_empty());
        for (i, age) in [30, 10, 20, 40].iter().enumerate() {
            keep_run(&base, &format!("demo-ngp-{i}"), i as u64 * 100, *age);
        }
        // Not a run: left alone.
        std::fs::create_dir_all(base.join("notes")).unwrap();
        let runs = list(&base);
        let names: Vec<String> = runs
            .iter()
            .map(|r| r.folder.file_name().unwrap().to_string_lossy().into_owned())
            .collect();
        assert_eq!(
            names,
            ["demo-ngp-1", "demo-ngp-2", "demo-ngp-0", "demo-ngp-3"]
        );
        assert_eq!(runs[0].step, Some(100));
        assert!(runs[0].bytes > 4000, "{}", runs[0].bytes);
        assert!(
            runs[0]
                .describe()
                .contains("demo-ngp-1 · Ngp · step 100 · ")
        );
        let removed = prune(&base, 2);
        assert_eq!(removed.len(), 2);
        assert_eq!(list(&base).len(), 2);
        assert!(base.join("notes").is_dir());
        assert!(base.join("demo-ngp-1").is_dir() && !base.join("demo-ngp-3").exists());
        // Only the viewer's own runs can be removed.
        let error = remove(&base, &base.join("notes")).unwrap_err();
        assert!(
            error.contains("not one of the viewer's kept runs"),
            "{error}"
        );
        remove(&base, &base.join("demo-ngp-2")).unwrap();
        assert_eq!(list(&base).len(), 1);
    }
}
