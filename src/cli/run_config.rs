//! A run folder's `run.json` and the one way a run's trainer is built:
//! `zrak train` (new and resumed), `eval`, `render` and each cell of
//! `bench quality` all go through [`build_trainer`].

use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::{Context, bail};
use serde::{Deserialize, Serialize};
use zrak::engine::request::{ModelRequest, ModelSettings};
use zrak::engine::{EngineChoice, EngineKind, build, choose_engine};
use zrak::field::ModelKind;
use zrak::field::common::{LossKind, Sampling};
use zrak::field::mlp::Precision;
use zrak::interrupt::note;
use zrak::scene::photographs::PhotographAnalysis;
use zrak::scene::{Scene, SceneSpace};
use zrak::train::run::{
    MAX_RUN_JSON_BYTES, RUN_JSON_MARKER, RunFolder, SAVED_BY_COMMAND_LINE, load_checkpoint,
};
use zrak::train::trainer::Trainer;

use super::load_scene;

/// What a run folder records about how it was made (`run.json`), so eval,
/// render and resume rebuild the same scene and model.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RunConfig {
    /// The scene folder, or "demo".
    pub scene: String,
    pub model: ModelKind,
    pub downscale: u32,
    pub loss: LossKind,
    pub seed: u64,
    /// NeRF's sampler (absent in runs made before NeRF existed).
    #[serde(default = "default_sampling")]
    pub sampling: Sampling,
    /// The engine asked for with `--engine` (`None`: chosen by the
    /// machine's adapter), so eval, render and resume choose the same way
    /// (absent in runs made before it was recorded).
    #[serde(default)]
    pub engine: Option<EngineKind>,
    /// Samples per training batch when not the model's paper batch (runs
    /// of `bench quality --batch-samples`; absent otherwise).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub batch_samples: Option<usize>,
    /// How the cpu engine computed the networks' products (absent in runs
    /// made before mixed precision existed: those trained in f32).
    #[serde(default)]
    pub precision: Precision,
    /// Sizes of every training view trained on (1: the views as they are;
    /// see `Scene::with_training_scales`).
    #[serde(default = "single_scale", skip_serializing_if = "is_single_scale")]
    pub training_scales: u32,
    /// What the scene was treated as (object, unbounded, forward-facing),
    /// kept so that a resumed run is treated the same even where the
    /// analysis would now decide otherwise (absent in runs made before
    /// the analysis existed: the analysis decides).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub space: Option<SceneSpace>,
    /// Whether `space` was chosen with `--space` rather than by the
    /// analysis.
    #[serde(default)]
    pub space_overridden: bool,
    /// What the photographs called for when the run began (appearance
    /// vectors, camera refinement, masks) and why, kept so a resumed,
    /// evaluated or rendered run rebuilds the same model (absent in runs
    /// made before the choice existed: all off, as they trained).
    #[serde(default)]
    pub photographs: PhotographAnalysis,
}

fn single_scale() -> u32 {
    1
}

fn is_single_scale(scales: &u32) -> bool {
    *scales == 1
}

fn default_sampling() -> Sampling {
    Sampling::Occupancy
}

impl RunConfig {
    /// Records what `scene` is treated as.
    pub fn record_space(&mut self, scene: &Scene) {
        self.space = Some(scene.space.space);
        self.space_overridden = scene.space.overridden;
    }
}

/// `scene` treated as the run recorded (see [`RunConfig::space`]): by
/// hand as the run was, or as the analysis decided when the run was made
/// (said in the reasons where it now decides otherwise).
pub fn keep_recorded_space(scene: Scene, config: &RunConfig) -> Scene {
    let Some(space) = config.space else {
        return scene.in_its_space();
    };
    if config.space_overridden {
        return scene.with_space(space).in_its_space();
    }
    let mut scene = scene;
    let analysis = &mut scene.space;
    if analysis.space != space {
        analysis.reasons.insert(
            0,
            format!(
                "kept as {space} from the run's run.json (the analysis made it so when the run \
                 began; it now finds {})",
                analysis.space
            ),
        );
        analysis.space = space;
    }
    scene.in_its_space()
}

/// A run's scene: `scene` (`demo` or a folder) loaded at `downscale`, its
/// training views at `training_scales` sizes.
pub fn load_run_scene(scene: &str, downscale: u32, training_scales: u32) -> anyhow::Result<Scene> {
    let loaded = load_scene(scene, downscale)?;
    check_training_scales(&loaded, training_scales)?;
    Ok(loaded.with_training_scales(training_scales))
}

/// Refuses `--training-scales` asking for sizes the views are too small
/// to have (each size halves the last; below one pixel there is none).
fn check_training_scales(scene: &Scene, scales: u32) -> anyhow::Result<()> {
    let smallest_side = scene
        .photographed_training_views()
        .iter()
        .map(|f| f.camera.intrinsics.width.min(f.camera.intrinsics.height))
        .min()
        .unwrap_or(0);
    if scales > 1 && smallest_side > 0 {
        // Sizes full, ½, … while a side keeps at least one pixel.
        let possible = u32::BITS - smallest_side.leading_zeros();
        if scales > possible {
            bail!(
                "--training-scales {scales} needs views of at least {} pixels a side (the \
                 smallest size is 1/{}); the smallest here is {smallest_side}: give at most {possible}",
                1u64 << (scales - 1),
                1u64 << (scales - 1)
            );
        }
    }
    Ok(())
}

/// A fresh trainer of the run's model on `scene` (loaded as the run says):
/// the one place a run's model is built, for new and resumed runs alike.
pub fn build_trainer(
    config: &RunConfig,
    scene: Arc<Scene>,
    choice: EngineChoice,
) -> anyhow::Result<Trainer> {
    let settings = ModelSettings {
        seed: config.seed,
        loss: config.loss,
        batch_samples: config.batch_samples,
        sampling: config.sampling,
        precision: config.precision,
        refine_cameras: config.photographs.refine_cameras.on,
        appearance: config.photographs.appearance.on,
    };
    let model = build(&ModelRequest::new(config.model, settings), choice, &scene)?;
    Ok(Trainer::new(model, scene, config.seed))
}

/// Where camera refinement was chosen but `trainer`'s model cannot refine
/// (only Instant-NGP marching through the occupancy grid on the cpu engine
/// does so far), the choice turned off with the reason first, so
/// `run.json` and what is printed say what was trained.
pub fn settle_camera_refinement(config: &mut RunConfig, trainer: &Trainer) -> Option<String> {
    let choice = &mut config.photographs.refine_cameras;
    if !choice.on || trainer.model.camera_corrections().is_some() {
        return None;
    }
    let reason = format!(
        "{} cannot refine cameras yet (Instant-NGP with the occupancy sampler on the cpu engine \
         can): the cameras stay as given",
        trainer.model.describe()
    );
    choice.on = false;
    choice.reasons.insert(0, reason.clone());
    Some(format!("camera refinement off: {reason}"))
}

/// Reads a run's `run.json`: a regular file of at most
/// [`MAX_RUN_JSON_BYTES`], refused before reading otherwise (a named pipe
/// would block, a link to a device be read forever).
pub fn read_run_config(folder: &RunFolder) -> anyhow::Result<RunConfig> {
    let path = folder.config_path();
    let text = zrak::files::read_text_bounded(&path, MAX_RUN_JSON_BYTES, "a run's settings")
        .map_err(|problem| {
            anyhow::anyhow!(
                "{}: cannot read the run's configuration: {problem}",
                path.display()
            )
        })?;
    serde_json::from_str(&text)
        .with_context(|| format!("{}: malformed run configuration", path.display()))
}

/// Rebuilds a run's scene and model and restores its checkpoint; `engine`
/// and `precision`, when given, override the run's own.
pub fn restore_run(
    folder: &RunFolder,
    engine: Option<EngineKind>,
    precision: Option<Precision>,
) -> anyhow::Result<(RunConfig, Trainer)> {
    let mut config = read_run_config(folder)?;
    // The checkpoint's kind before the scene loads and the model is
    // built: a folder, a pipe or a device there is refused at once.
    let checkpoint = folder.checkpoint_path();
    zrak::files::check_regular_file(&checkpoint).map_err(|problem| {
        anyhow::anyhow!(
            "{}: cannot read the checkpoint: {problem}",
            checkpoint.display()
        )
    })?;
    // So is a crop box that is no regular file: it is read only once the
    // model is built, seconds later.
    let crop = folder.dir.join(zrak::scene::crop::CROP_FILE);
    if zrak::files::exists_at_all(&crop) {
        zrak::files::check_regular_file(&crop).map_err(|problem| {
            anyhow::anyhow!("{}: cannot read the crop box: {problem}", crop.display())
        })?;
    }
    if let Some(precision) = precision {
        config.precision = precision;
    }
    let scene = keep_recorded_space(
        load_run_scene(&config.scene, config.downscale, config.training_scales)?,
        &config,
    );
    let choice = choose_engine(engine.or(config.engine))?;
    note(&choice.reason);
    let mut trainer = build_trainer(&config, Arc::new(scene), choice)?;
    restore_checkpoint(folder, &mut trainer)?;
    Ok((config, trainer))
}

/// Restores the run folder's checkpoint into `trainer`.
pub fn restore_checkpoint(folder: &RunFolder, trainer: &mut Trainer) -> anyhow::Result<()> {
    let checkpoint = load_checkpoint(folder, trainer.model.as_ref()).map_err(anyhow::Error::msg)?;
    trainer
        .restore(&checkpoint)
        .map_err(|e| anyhow::anyhow!("{}: {e}", folder.checkpoint_path().display()))
}

/// Writes a new run's `run.json` and clears any earlier log: a fresh run
/// starts a fresh history. (A folder holding a checkpoint never gets here:
/// [`RunFolder::create_new`] refuses it or moves it aside.)
/// The `run.json` carries [`RUN_JSON_MARKER`], by which a folder is known
/// as a run before its first checkpoint.
pub fn start_run_folder(folder: &RunFolder, config: &RunConfig) -> anyhow::Result<()> {
    let mut json = serde_json::to_value(config)?;
    json[RUN_JSON_MARKER] = SAVED_BY_COMMAND_LINE.into();
    zrak::files::write_bytes_atomically(
        &folder.config_path(),
        serde_json::to_string_pretty(&json)?.as_bytes(),
    )
    .with_context(|| format!("{}: cannot write", folder.config_path().display()))?;
    let _ = std::fs::remove_file(folder.metrics_path());
    Ok(())
}

/// How `run.json` names a scene: `demo`, or the folder's absolute path, so
/// a run can be resumed, evaluated and rendered from any working folder.
pub fn scene_key(scene: &str) -> String {
    if scene == "demo" {
        "demo".into()
    } else {
        std::fs::canonicalize(scene)
            .unwrap_or_else(|_| PathBuf::from(scene))
            .display()
            .to_string()
    }
}

/// A SCENE given with `--resume` must be the run's own: a checkpoint only
/// continues on the scene it was trained on.
pub fn check_same_scene(given: &str, recorded: &str, run: &Path) -> anyhow::Result<()> {
    let key = scene_key(given);
    if key != recorded {
        bail!(
            "the run in {} was trained on `{recorded}`, not on `{key}`: leave SCENE out to \
             continue it on its own scene, or give --out instead of --resume to start a new run",
            run.display()
        );
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_run_json_from_before_the_later_fields_loads_with_their_defaults() {
        let config: RunConfig = serde_json::from_str(
            r#"{"scene": "demo", "model": "ngp", "downscale": 2, "loss": "Huber", "seed": 7}"#,
        )
        .unwrap();
        assert_eq!(config.scene, "demo");
        assert_eq!(config.model, ModelKind::Ngp);
        assert_eq!(config.downscale, 2);
        assert_eq!(config.loss, LossKind::Huber);
        assert_eq!(config.seed, 7);
        assert_eq!(config.sampling, Sampling::Occupancy);
        assert_eq!(config.engine, None);
        assert_eq!(config.batch_samples, None);
        assert_eq!(config.precision, Precision::F32);
        assert_eq!(config.training_scales, 1);
        assert_eq!(config.space, None);
        assert!(!config.space_overridden);
    }

    #[test]
    fn run_json_keeps_the_space_and_a_resumed_run_is_treated_the_same() {
        let mut config: RunConfig = serde_json::from_str(
            r#"{"scene": "demo", "model": "ngp", "downscale": 16, "loss": "Huber", "seed": 0}"#,
        )
        .unwrap();
        let scene = load_scene("demo", 16).unwrap();
        // An older run (no space recorded): the analysis decides.
        assert_eq!(
            keep_recorded_space(scene.clone(), &config).space,
            scene.space
        );
        // Chosen by hand: written, and chosen again on resuming.
        let chosen = scene.clone().with_space(SceneSpace::Unbounded);
        config.record_space(&chosen);
        let written = serde_json::to_value(&config).unwrap();
        assert_eq!(written["space"], "unbounded");
        assert_eq!(written["space_overridden"], true);
        let read: RunConfig = serde_json::from_value(written).unwrap();
        let resumed = keep_recorded_space(scene.clone(), &read);
        assert_eq!(resumed.space, chosen.space);
        // Decided by the analysis, which now finds otherwise: the run's
        // own kept, and said so.
        config.space = Some(SceneSpace::ForwardFacing);
        config.space_overridden = false;
        let resumed = keep_recorded_space(scene.clone(), &config);
        assert_eq!(resumed.space.space, SceneSpace::ForwardFacing);
        assert!(!resumed.space.overridden);
        assert_eq!(
            resumed.space.reasons[0],
            "kept as forward-facing from the run's run.json (the analysis made it so when the \
             run began; it now finds object)"
        );
        assert_eq!(resumed.space.reasons[1..], scene.space.reasons[..]);
        // Decided by the analysis, which still finds the same: unchanged.
        config.space = Some(SceneSpace::Object);
        assert_eq!(
            keep_recorded_space(scene.clone(), &config).space,
            scene.space
        );
    }

    #[test]
    fn run_json_leaves_out_what_a_plain_run_does_not_set() {
        let mut config: RunConfig = serde_json::from_str(
            r#"{"scene": "demo", "model": "mipnerf", "downscale": 1, "loss": "L2", "seed": 0,
                "sampling": "paper", "engine": "cpu", "precision": "mixed"}"#,
        )
        .unwrap();
        let written = serde_json::to_value(&config).unwrap();
        assert_eq!(written["model"], "mipnerf");
        assert_eq!(written["loss"], "L2");
        assert_eq!(written["sampling"], "paper");
        assert_eq!(written["engine"], "cpu");
        assert_eq!(written["precision"], "mixed");
        assert!(written.get("batch_samples").is_none(), "{written}");
        assert!(written.get("training_scales").is_none(), "{written}");
        config.batch_samples = Some(1024);
        config.training_scales = 4;
        let written = serde_json::to_value(&config).unwrap();
        assert_eq!(written["batch_samples"], 1024);
        assert_eq!(written["training_scales"], 4);
    }

    #[test]
    fn scenes_are_recorded_by_absolute_path() {
        assert_eq!(scene_key("demo"), "demo");
        let dir = tempfile::tempdir().unwrap();
        let folder = dir.path().join("lego");
        std::fs::create_dir(&folder).unwrap();
        let through_dots = dir.path().join("lego/../lego");
        assert_eq!(
            scene_key(&through_dots.display().to_string()),
            std::fs::canonicalize(&folder)
                .unwrap()
                .display()
                .to_string()
        );
        // A folder that is not there is kept as given (loading it says so).
        assert_eq!(scene_key("no/such/scene"), "no/such/scene");
    }

    #[test]
    fn a_resume_names_the_runs_own_scene_or_none() {
        assert!(check_same_scene("demo", "demo", Path::new("RUN")).is_ok());
        assert_eq!(
            check_same_scene("elsewhere", "demo", Path::new("RUN"))
                .unwrap_err()
                .to_string(),
            "the run in RUN was trained on `demo`, not on `elsewhere`: leave SCENE out to \
             continue it on its own scene, or give --out instead of --resume to start a new run"
        );
    }

    #[test]
    fn training_scales_stop_where_the_views_run_out_of_pixels() {
        // The demo's 128-pixel views at 1/16: 8 pixels a side, so sizes 8,
        // 4, 2 and 1.
        let scene = load_scene("demo", 16).unwrap();
        assert!(check_training_scales(&scene, 1).is_ok());
        assert!(check_training_scales(&scene, 4).is_ok());
        assert_eq!(
            check_training_scales(&scene, 5).unwrap_err().to_string(),
            "--training-scales 5 needs views of at least 16 pixels a side (the smallest size \
             is 1/16); the smallest here is 8: give at most 4"
        );
        // Two sizes: every training view once more at half size.
        let views = scene.train.len();
        let scene = load_run_scene("demo", 16, 2).unwrap();
        assert_eq!(scene.train.len(), 2 * views);
        assert_eq!(scene.photographed_training_views().len(), views);
    }
}
