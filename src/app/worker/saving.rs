//! What the worker writes: checkpoints (saved, loaded, and kept on close)
//! and turntable exports, frame by frame.

use super::*;

/// A turntable export in progress, with the model it renders.
pub(super) struct ExportJob {
    model: ModelKind,
    export: TurntableExport,
}

impl ExportJob {
    pub(super) fn start(
        scene: &Scene,
        settings: ExportSettings,
        model: ModelKind,
    ) -> Result<ExportJob, String> {
        Ok(ExportJob {
            model,
            export: TurntableExport::start(scene, settings)?,
        })
    }

    pub(super) fn progress(&self) -> (usize, usize) {
        (self.export.done(), self.export.total())
    }

    pub(super) fn render_next(&mut self, model: &dyn RadianceModel) -> Result<bool, String> {
        self.export.render_next(model)
    }

    pub(super) fn finish(self) -> Result<Vec<PathBuf>, String> {
        self.export.finish()
    }
}

impl Worker {
    pub(super) fn save_checkpoint(&mut self, path: &Path) -> Result<(), UiGone> {
        let Some(slot) = self.slot(self.active) else {
            return self.send(Event::Error(format!(
                "{}: no model to save (the {} model was not built)",
                path.display(),
                self.active.name()
            )));
        };
        let scene = match &self.source {
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
                if let Some(slot) = self.slot_mut(self.active) {
                    slot.saved_step = step;
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
        let scene_key = match &self.source {
            SceneSource::Demo => "demo".to_string(),
            SceneSource::Folder(folder) => std::fs::canonicalize(folder)
                .unwrap_or_else(|_| folder.clone())
                .display()
                .to_string(),
        };
        let stamp = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_secs());
        for slot in &self.slots {
            if slot.trainer.step <= slot.saved_step {
                continue;
            }
            // Only plain characters of the scene's name: it may be any
            // folder's name, the run folder's must be a safe one.
            let scene_name: String = self
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
                "sampling": self.options.sampling,
                "engine": self.engine.kind,
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
                });
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
                if kind != self.active {
                    self.active = kind;
                    self.send(Event::ModelSelected(kind))?;
                }
                if let Some(view) = self.view.as_mut() {
                    view.restart();
                }
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
        let checkpoint = Checkpoint::load(path).map_err(|e| e.to_string())?;
        let model_header = &checkpoint.header["model"];
        let kind: ModelKind =
            serde_json::from_value(model_header["model"].clone()).map_err(|_| {
                format!(
                    "{}: the checkpoint does not name a model this zrak knows ({})",
                    path.display(),
                    model_header["model"]
                )
            })?;
        let loss: LossKind = serde_json::from_value(model_header["loss"].clone())
            .unwrap_or(self.options.loss.unwrap_or(kind.default_loss()));
        let mut trainer = self.build_trainer(kind)?;
        trainer
            .restore(&checkpoint)
            .map_err(|e| format!("{}: {e}", path.display()))?;
        let step = trainer.step;
        self.val_job = None;
        let slot = self.new_slot(kind, trainer, loss);
        match self.slot_mut(kind) {
            Some(existing) => *existing = slot,
            None => self.slots.push(slot),
        }
        self.rebase_turns();
        Ok((kind, step))
    }

    pub(super) fn start_export(&mut self, settings: ExportSettings) -> Result<(), UiGone> {
        if self.export.is_some() {
            return self.send(Event::Error(
                "an export is already running; cancel it first".into(),
            ));
        }
        match ExportJob::start(&self.scene, settings, self.active) {
            Ok(job) => {
                let (done, total) = job.progress();
                self.export = Some(job);
                self.send(Event::ExportProgress { done, total })
            }
            Err(e) => self.send(Event::ExportFinished(Err(e))),
        }
    }

    /// Renders one export frame; training waits while an export runs.
    pub(super) fn export_unit(&mut self) -> Result<(), UiGone> {
        let Some(mut job) = self.export.take() else {
            return Ok(());
        };
        let Some(slot) = self.slot(job.model) else {
            return self.send(Event::ExportFinished(Err(format!(
                "the export stopped: the {} model is gone",
                job.model.name()
            ))));
        };
        match job.render_next(slot.trainer.model.as_ref()) {
            Ok(more) => {
                let (done, total) = job.progress();
                self.send(Event::ExportProgress { done, total })?;
                if more {
                    self.export = Some(job);
                    Ok(())
                } else {
                    self.send(Event::ExportFinished(job.finish()))
                }
            }
            Err(e) => self.send(Event::ExportFinished(Err(e))),
        }
    }
}
