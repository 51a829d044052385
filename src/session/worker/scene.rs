//! The scene the thread trains on: where it came from, its held-out views,
//! the crop box every model renders in, and the next scene being loaded
//! on a thread of its own.

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::mpsc::{
    Receiver, TryRecvError, {self},
};

use crate::scene::crop::CropBox;
use crate::scene::demo::{
    DemoConfig, {self},
};
use crate::scene::photographs::{self, PhotographAnalysis, Switches};
use crate::scene::{Frame, LoadOptions, Scene, SceneSpace};
use crate::session::protocol::{SceneInfo, SceneSource};
use crate::train::eval::spread_views;

/// A scene load under way: what was asked for, and where the result comes.
struct SceneLoad {
    source: SceneSource,
    result: Receiver<Result<Scene, String>>,
}

/// The current scene and the one being loaded.
pub(super) struct SceneState {
    pub(super) source: SceneSource,
    pub(super) scene: Arc<Scene>,
    /// The held-out views of the scene, downscaled for quick evaluation.
    pub(super) val_frames: Vec<Frame>,
    /// What every model renders and exports (`None`: the whole scene).
    pub(super) crop: Option<CropBox>,
    /// A scene being loaded on a thread of its own, so that reading and
    /// decoding a large one never stalls training or rendering.
    loading: Option<SceneLoad>,
    /// What the photographs call for (appearance, camera refinement,
    /// masks), as the switches leave it.
    pub(super) photographs: PhotographAnalysis,
    switches: Switches,
    /// The training image whose appearance vector the models draw with
    /// (`None`: the mean), chosen in the window.
    pub(super) render_appearance: Option<usize>,
}

impl SceneState {
    /// `scene`, loaded from `source`, with up to `val_views` held-out views.
    /// `switches` (`zrak view --appearance`, `--refine-cameras`) stand for
    /// every scene opened.
    pub(super) fn new(
        source: SceneSource,
        scene: Scene,
        val_views: usize,
        switches: Switches,
    ) -> Self {
        Self {
            val_frames: held_out_views(&scene, val_views),
            photographs: photographs::analyse(&scene, switches),
            scene: Arc::new(scene),
            source,
            crop: None,
            loading: None,
            switches,
            render_appearance: None,
        }
    }

    /// The scene as the window is told about it.
    pub(super) fn info(&self) -> SceneInfo {
        SceneInfo {
            scene: self.scene.clone(),
            source: self.source.clone(),
            photographs: self.photographs.clone(),
        }
    }

    pub(super) fn is_loading(&self) -> bool {
        self.loading.is_some()
    }

    /// Starts loading `source` (`demo` builds [`SceneSource::Demo`]) on its
    /// own thread. A later request replaces an unfinished one (whose result
    /// is then dropped). Err: the thread could not start.
    pub(super) fn start_loading(
        &mut self,
        source: SceneSource,
        demo: DemoConfig,
    ) -> Result<(), String> {
        let (sender, receiver) = mpsc::channel();
        let to_load = source.clone();
        std::thread::Builder::new()
            .name("zrak-scene-loading".into())
            .spawn(move || {
                // The receiver may be gone (another scene was asked for).
                let _ = sender.send(load_scene(&to_load, &demo));
            })
            .map_err(|e| format!("cannot start loading the scene: {e}"))?;
        self.loading = Some(SceneLoad {
            source,
            result: receiver,
        });
        Ok(())
    }

    /// The scene being loaded, once it has loaded or failed, with what was
    /// asked for.
    pub(super) fn poll_loaded(&mut self) -> Option<(SceneSource, Result<Scene, String>)> {
        let load = self.loading.take()?;
        let result = match load.result.try_recv() {
            Ok(result) => result,
            Err(TryRecvError::Empty) => {
                self.loading = Some(load);
                return None;
            }
            Err(TryRecvError::Disconnected) => {
                Err("loading the scene stopped after an internal error".to_string())
            }
        };
        Some((load.source, result))
    }

    /// Makes `scene` (from `source`) the current scene, without a crop box
    /// (the old scene's; the window clears its own).
    pub(super) fn install(&mut self, source: SceneSource, scene: Scene, val_views: usize) {
        self.scene = Arc::new(scene);
        self.crop = None;
        self.source = source;
        self.val_frames = held_out_views(&self.scene, val_views);
        self.photographs = photographs::analyse(&self.scene, self.switches);
        self.render_appearance = None;
    }
}

/// Loads `source`; `demo_config` builds [`SceneSource::Demo`]. A scene
/// without training views is refused.
pub(super) fn load_scene(source: &SceneSource, demo_config: &DemoConfig) -> Result<Scene, String> {
    let scene = match source {
        SceneSource::Demo => demo::build(demo_config),
        SceneSource::Folder(path) => {
            Scene::load(path, LoadOptions::default()).map_err(|e| e.to_string())?
        }
    };
    if scene.train.is_empty() {
        let place = match source {
            SceneSource::Demo => PathBuf::from("demo"),
            SceneSource::Folder(path) => path.clone(),
        };
        return Err(format!(
            "{}: the scene has no training views to learn from",
            place.display()
        ));
    }
    Ok(scene)
}

/// `scene` treated as `space` when one was chosen (`zrak view --space`),
/// else as its analysis decided.
pub(super) fn with_chosen_space(scene: Scene, space: Option<SceneSpace>) -> Scene {
    match space {
        Some(space) => scene.with_space(space),
        None => scene,
    }
    .in_its_space()
}

/// Up to `count` held-out views (val, else test, else train), spread over
/// the split as `zrak train` chooses them.
fn held_out_views(scene: &Scene, count: usize) -> Vec<Frame> {
    let frames = [&scene.val, &scene.test, &scene.train]
        .into_iter()
        .find(|frames| !frames.is_empty())
        .map_or(&[][..], |frames| frames.as_slice());
    spread_views(frames, count).into_iter().cloned().collect()
}

#[cfg(test)]
mod tests {
    use std::time::{Duration, Instant};

    use super::*;

    fn demo_of(train_views: usize, val_views: usize, test_views: usize) -> DemoConfig {
        DemoConfig {
            size: 8,
            train_views,
            val_views,
            test_views,
        }
    }

    #[test]
    fn held_out_views_come_from_val_else_test_else_train() {
        // How many views are chosen, and from which split (0 val, 1 test,
        // 2 train) each comes.
        let views = |config: DemoConfig, count| {
            let scene = demo::build(&config);
            held_out_views(&scene, count)
                .iter()
                .map(|chosen| {
                    [&scene.val, &scene.test, &scene.train]
                        .iter()
                        .position(|split| split.iter().any(|f| f.camera == chosen.camera))
                        .unwrap()
                })
                .collect::<Vec<usize>>()
        };
        assert_eq!(views(demo_of(4, 5, 2), 3), [0, 0, 0]);
        assert_eq!(views(demo_of(4, 0, 2), 3), [1, 1]);
        assert_eq!(views(demo_of(4, 0, 0), 3), [2, 2, 2]);
    }

    #[test]
    fn a_scene_without_training_views_is_refused() {
        let error = load_scene(&SceneSource::Demo, &demo_of(0, 1, 0)).unwrap_err();
        assert!(
            error.contains("demo: the scene has no training views"),
            "{error}"
        );
        let missing = PathBuf::from("/nonexistent/zrak-scene");
        let error = load_scene(&SceneSource::Folder(missing), &demo_of(1, 0, 0)).unwrap_err();
        assert!(error.contains("zrak-scene"), "{error}");
    }

    #[test]
    fn a_scene_loads_beside_the_current_one_and_a_later_request_replaces_it() {
        let mut state = SceneState::new(
            SceneSource::Demo,
            demo::build(&demo_of(2, 1, 0)),
            1,
            Switches::default(),
        );
        assert!(!state.is_loading());
        assert!(state.poll_loaded().is_none());
        let missing = SceneSource::Folder(PathBuf::from("/nonexistent/zrak-scene"));
        state.start_loading(missing, demo_of(3, 2, 0)).unwrap();
        state
            .start_loading(SceneSource::Demo, demo_of(3, 2, 0))
            .unwrap();
        let deadline = Instant::now() + Duration::from_secs(60);
        let (source, result) = loop {
            if let Some(loaded) = state.poll_loaded() {
                break loaded;
            }
            assert!(Instant::now() < deadline, "the scene never loaded");
            std::thread::sleep(Duration::from_millis(5));
        };
        assert!(!state.is_loading());
        assert_eq!(source, SceneSource::Demo);
        let scene = result.unwrap();
        assert_eq!(scene.train.len(), 3);
        state.crop = Some(CropBox::axis_aligned(glam::Vec3::ZERO, glam::Vec3::ONE));
        state.install(source, scene, 5);
        assert_eq!(state.crop, None);
        assert_eq!(state.val_frames.len(), 2);
        assert_eq!(state.info().scene.train.len(), 3);
    }
}
