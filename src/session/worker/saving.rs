//! What the worker writes: checkpoints (saved, loaded, and kept on close)
//! and the crop box beside them.

use std::path::Path;

use crate::field::ModelKind;
use crate::field::common::LossKind;
use crate::model::checkpoint::Checkpoint;
use crate::scene::crop::CropBox;
use crate::session::protocol::{Event, SceneSource};

use super::{UiGone, Worker};

impl Worker {
    pub(super) fn save_checkpoint(&mut self, path: &Path) -> Result<(), UiGone> {
        let Some(slot) = self.training.shown() else {
            return self.send(Event::Error(format!(
                "{}: no model to save (the {} model was not built)",
                path.display(),
                self.training.active.name()
            )));
        };
        let scene = match &self.scene.source {
            SceneSource::Demo => "demo".to_string(),
            SceneSource::Folder(folder) => folder.display().to_string(),
        };
        let checkpoint = slot.trainer.checkpoint(serde_json::json!({
            "scene": scene,
            "model": slot.kind,
            "engine": self.engine.kind,
            "loss": slot.loss,
            "saved_by": "viewer",
        }));
        let step = slot.trainer.step;
        match checkpoint.save(path) {
            Ok(()) => {
                if let Some(slot) = self.training.shown_mut() {
                    slot.saved_step = step;
                }
                if let Some(run) = run_folder_of(path)
                    && let Err(e) = CropBox::save_to_run(self.scene.crop.as_ref(), run)
                {
                    self.send(Event::Error(e))?;
                }
                self.send(Event::CheckpointSaved(path.to_path_buf()))
            }
            Err(e) => self.send(Event::Error(e.to_string())),
        }
    }

    /// Keeps every model trained since it was last saved or loaded in a run
    /// folder of its own under [`WorkerOptions::autosave`], and says where
    /// on standard error (the window is closing: nobody reads events).
    ///
    /// Why save rather than ask: the window is closing because the user
    /// asked it to, and a prompt would make closing (and logging out, and
    /// a script's `--quit-after`) wait for an answer; editors and Blender
    /// keep unsaved work silently on quit for the same reason. Minutes of
    /// training cost more to redo than the disk they take.
    pub(super) fn autosave(&mut self) {
        let Some(base) = self.options.autosave.clone() else {
            return;
        };
        // `--keep-runs 0` keeps nothing of this session, and removes
        // nothing kept by earlier ones: older runs go only to make room for
        // a newer one.
        if self.options.kept_runs == 0 {
            return;
        }
        let scene_key = match &self.scene.source {
            SceneSource::Demo => "demo".to_string(),
            SceneSource::Folder(folder) => std::fs::canonicalize(folder)
                .unwrap_or_else(|_| folder.clone())
                .display()
                .to_string(),
        };
        let stamp = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_secs());
        for slot in self.training.slots() {
            if slot.trainer.step <= slot.saved_step {
                continue;
            }
            // Only plain characters of the scene's name: it may be any
            // folder's name, the run folder's must be a safe one.
            let scene_name: String = self
                .scene
                .scene
                .name
                .chars()
                .map(|c| {
                    if c.is_alphanumeric() || c == '-' {
                        c
                    } else {
                        '_'
                    }
                })
                .collect();
            let folder = base.join(format!("{scene_name}-{}-{stamp}", slot.kind.key()));
            // The same keys as the command line's run.json, so `zrak train
            // --resume` rebuilds this scene and model.
            let run = serde_json::json!({
                "scene": scene_key,
                "model": slot.kind,
                "downscale": 1,
                "loss": slot.loss,
                "seed": slot.trainer.seed,
                "sampling": self.sampling_of(slot.kind),
                "engine": self.engine.kind,
                "space": self.scene.scene.space.space,
                "space_overridden": self.scene.scene.space.overridden,
                "precision": self.options.precision,
                "saved_by": "viewer",
            });
            let saved = std::fs::create_dir_all(&folder)
                .map_err(|e| format!("{}: cannot create the folder: {e}", folder.display()))
                .and_then(|()| {
                    let path = folder.join(crate::train::run::CONFIG_FILE);
                    crate::files::write_bytes_atomically(&path, format!("{run:#}").as_bytes())
                        .map_err(|e| format!("{}: cannot write: {e}", path.display()))
                })
                .and_then(|()| {
                    slot.trainer
                        .checkpoint(run.clone())
                        .save(&folder.join(crate::train::run::CHECKPOINT_FILE))
                        .map_err(|e| e.to_string())
                })
                .and_then(|()| CropBox::save_to_run(self.scene.crop.as_ref(), &folder));
            match saved {
                Ok(()) => crate::interrupt::note(&format!(
                    "zrak view: kept {} at step {} in {}; continue it with \
                     `zrak train --resume {}` or load its checkpoint.zrak in the viewer",
                    slot.kind.name(),
                    slot.trainer.step,
                    folder.display(),
                    folder.display()
                )),
                Err(error) => crate::interrupt::note(&format!(
                    "zrak view: could not keep {} at step {}: {error}",
                    slot.kind.name(),
                    slot.trainer.step
                )),
            }
        }
        for removed in crate::train::kept::prune(&base, self.options.kept_runs) {
            crate::interrupt::note(&format!(
                "zrak view: removed the kept run {} (more than the newest {}; \
                 `zrak view --keep-runs N` keeps more)",
                removed.display(),
                self.options.kept_runs
            ));
        }
    }

    pub(super) fn load_checkpoint(&mut self, path: &Path) -> Result<(), UiGone> {
        match self.restore_checkpoint(path) {
            Ok((kind, step)) => {
                if kind != self.training.active {
                    self.training.active = kind;
                    self.send(Event::ModelSelected(kind))?;
                }
                // A run's crop box comes back with it.
                match run_folder_of(path).map(CropBox::load_from_run) {
                    Some(Ok(Some(crop))) => self.set_crop(Some(crop))?,
                    Some(Err(e)) => self.send(Event::Error(e))?,
                    _ => {}
                }
                self.viewing.restart();
                self.send(Event::CheckpointLoaded {
                    path: path.to_path_buf(),
                    model: kind,
                    step,
                })
            }
            Err(e) => self.send(Event::Error(e)),
        }
    }

    /// Restores a checkpoint into its model's slot. The state is restored
    /// into a fresh trainer first, so a refused checkpoint changes nothing.
    pub(super) fn restore_checkpoint(&mut self, path: &Path) -> Result<(ModelKind, u32), String> {
        // The header names the model; the tensors are matched against that
        // model's before any is decoded, as the command line does, so a
        // crafted table cannot make the thread allocate what it claims.
        let header = Checkpoint::load_header(path).map_err(|e| e.to_string())?;
        let model_header = &header["model"];
        let kind: ModelKind =
            serde_json::from_value(model_header["model"].clone()).map_err(|_| {
                format!(
                    "{}: the checkpoint does not name a model this zrak knows ({})",
                    path.display(),
                    model_header["model"]
                )
            })?;
        let loss: LossKind =
            serde_json::from_value(model_header["loss"].clone()).unwrap_or(self.loss_of(kind));
        let mut trainer = self.build_trainer(kind)?;
        let needed = crate::train::run::tensors_needed(trainer.model.as_ref());
        let checkpoint = Checkpoint::load_for(path, &needed).map_err(|e| e.to_string())?;
        crate::train::run::checked_step(&checkpoint.header)
            .map_err(|e| format!("{}: {e}", path.display()))?;
        trainer
            .restore(&checkpoint)
            .map_err(|e| format!("{}: {e}", path.display()))?;
        let step = trainer.step;
        self.jobs.evaluation = None;
        let slot = self.new_slot(kind, trainer, loss);
        self.training.install(slot);
        self.training.rebase_turns();
        Ok((kind, step))
    }
}

/// The run folder a checkpoint lies in, whose crop box (`crop.json`) goes
/// with it: the folder of a `checkpoint.zrak`, or of any checkpoint beside
/// a `run.json` (what `zrak train` and the viewer's kept runs write). A
/// checkpoint saved anywhere else leaves its folder alone.
fn run_folder_of(checkpoint: &Path) -> Option<&Path> {
    let folder = checkpoint.parent()?;
    let folder = if folder.as_os_str().is_empty() {
        Path::new(".")
    } else {
        folder
    };
    let named = checkpoint.file_name()? == crate::train::run::CHECKPOINT_FILE;
    (named || folder.join(crate::train::run::CONFIG_FILE).is_file()).then_some(folder)
}
