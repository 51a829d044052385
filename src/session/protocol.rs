//! What the viewer and its training thread say to each other. The UI sends
//! [`Command`]s and never waits; the training thread, which owns the scene
//! and every model's engine state, answers with [`Event`]s.

use std::path::PathBuf;
use std::sync::Arc;

use crate::engine::EngineKind;
use crate::field::ModelKind;
use crate::mesh::MinComponent;
use crate::model::{RenderMode, RenderedPixel, StageTimes};
use crate::render::camera_path::nerfstudio::CameraPathFile;
use crate::render::export::ExportSettings;
use crate::scene::crop::CropBox;
use crate::scene::{Camera, Scene};

use super::schedule::ScheduleTrace;

/// Where a scene comes from.
#[derive(Debug, Clone, PartialEq)]
pub enum SceneSource {
    /// The built-in demo scene, built in memory.
    Demo,
    /// A folder in the NeRF-synthetic layout or with a transforms.json.
    Folder(PathBuf),
}

/// A request to draw the scene from `camera`.
#[derive(Debug, Clone)]
pub struct RenderRequest {
    /// Increases with every new request; frames answer with it, so the UI
    /// drops frames of cameras it has moved away from.
    pub generation: u64,
    /// The camera at full viewport resolution.
    pub camera: Camera,
    pub mode: RenderMode,
    /// True while the user drags or flies: the thread renders only the
    /// coarsest level and favours rendering over training.
    pub moving: bool,
    /// The UI needs the pixels themselves (to compare the render with a
    /// photograph): a thread that would draw into a texture on the shared
    /// device ([`Event::GpuFrame`]) answers with [`Event::Frame`] instead.
    pub needs_pixels: bool,
}

/// How the training thread shares its time.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Balance {
    /// Fraction of the thread's busy time given to training steps while
    /// the camera rests, in [0, 1] (at most 0.95 is honoured, so the view
    /// still refreshes); the rest draws the view and evaluates.
    pub training_share: f32,
}

impl Default for Balance {
    fn default() -> Self {
        Self {
            training_share: super::schedule::DEFAULT_TRAINING_SHARE as f32,
        }
    }
}

/// Several models trained in turn, so that one session compares them.
#[derive(Debug, Clone, PartialEq)]
pub struct InTurn {
    /// In the order they take turns.
    pub models: Vec<ModelKind>,
    /// Training seconds of each turn: every model gets the same share of
    /// training time, whatever its steps cost.
    pub slice_seconds: f64,
}

impl InTurn {
    /// Every model, two seconds of training each turn: long enough that a
    /// turn holds many of the viewer's short steps, short enough that the
    /// curves grow side by side.
    pub fn all() -> Self {
        Self {
            models: ModelKind::ALL.to_vec(),
            slice_seconds: 2.0,
        }
    }
}

// A camera path export carries its whole path; commands are sent a few
// times a second at most, so their size does not matter.
#[allow(clippy::large_enum_variant)]
#[derive(Debug, Clone)]
pub enum Command {
    /// Load a scene; every model's state of the previous scene is dropped
    /// only once the new one has loaded.
    OpenScene(SceneSource),
    /// Train the active model continuously.
    Start,
    Pause,
    /// One training step of the active model (while paused).
    StepOnce,
    /// Forget the active model's training and start it afresh.
    Reset,
    /// Make `kind` the active model (the one shown, and trained unless
    /// models take turns); each model keeps its own state.
    SelectModel(ModelKind),
    /// Train the models in turn at equal shares of training time while
    /// training runs (`None`: only the active model trains again).
    TrainInTurn(Option<InTurn>),
    SetBalance(Balance),
    Render(RenderRequest),
    SaveCheckpoint(PathBuf),
    LoadCheckpoint(PathBuf),
    ExportTurntable(ExportSettings),
    /// Render a camera path into PNG frames or an MP4 video.
    ExportCameraPath(CameraPathExport),
    /// Mesh the active model's density field inside the crop box (the
    /// scene's box when there is none).
    ExportMesh(MeshExport),
    /// A point cloud of the active model's depths from the training views.
    ExportPoints(PointsExport),
    CancelExport,
    /// Show and export only what is inside this box (`None`: everything),
    /// on every model; the thread answers with [`Event::CropSet`].
    SetCrop(Option<CropBox>),
    /// Draw every model that has appearance embeddings with training
    /// image `i`'s vector, or the mean of them all (`None`, as held-out
    /// views are evaluated); models without embeddings ignore it.
    SetAppearance(Option<usize>),
    Shutdown,
}

/// A camera path to render, as the Export window and the path editor send
/// it.
#[derive(Debug, Clone)]
pub struct CameraPathExport {
    /// The path, in zrak's world of the scene or with the transform to its
    /// original frame recorded (the thread moves it into the scene's world).
    pub file: CameraPathFile,
    /// A folder of PNG frames, or a file ending in `.mp4`.
    pub out: PathBuf,
    /// Width × height (`None`: the file's `render_width` × `render_height`).
    pub size: Option<(u32, u32)>,
    /// Frames a second (`None`: the file's; another rate bakes its
    /// keyframes again).
    pub fps: Option<f64>,
    pub mode: RenderMode,
    /// Replace an existing video, or frames of another render in the
    /// folder; without it they are refused.
    pub replace_existing: bool,
}

/// A mesh to extract, as `zrak export mesh` does.
#[derive(Debug, Clone, PartialEq)]
pub struct MeshExport {
    /// A `.ply` (binary) or `.obj` file.
    pub out: PathBuf,
    /// Grid nodes along the longest side of the box meshed.
    pub resolution: u32,
    /// The density the surface is drawn at (`None`: the model's default,
    /// [`crate::mesh::extract::default_threshold`]).
    pub threshold: Option<f32>,
    pub min_component: Option<MinComponent>,
    /// Replace an existing file; without it, it is refused.
    pub replace_existing: bool,
}

/// A point cloud to extract, as `zrak export points` does.
#[derive(Debug, Clone, PartialEq)]
pub struct PointsExport {
    /// A `.ply` file.
    pub out: PathBuf,
    /// About this many rays over all training views.
    pub max_rays: usize,
    /// Rays less opaque than this give no point.
    pub min_opacity: f32,
    pub replace_existing: bool,
}

/// A summary of a loaded scene for the UI.
#[derive(Debug, Clone)]
pub struct SceneInfo {
    pub scene: Arc<Scene>,
    pub source: SceneSource,
    /// What its photographs call for, and why.
    pub photographs: crate::scene::photographs::PhotographAnalysis,
}

/// Training figures after a step of one model.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrainingStats {
    pub model: ModelKind,
    /// Steps taken so far.
    pub step: u32,
    /// Seconds spent training this model (rendering excluded).
    pub train_seconds: f64,
    pub loss: f32,
    /// PSNR of the loss's batch (from the mean squared error), when known.
    pub batch_psnr: Option<f32>,
    /// PSNR on held-out views, when the thread evaluated this step.
    pub val_psnr: Option<f32>,
    /// The median step time over the model's last seconds of training
    /// (one long step, such as one that also updated the occupancy grid,
    /// does not swing it; time not spent training does not count).
    pub ms_per_step: f32,
    /// Samples marched per ray (what the networks' density pass ran on).
    pub samples_per_ray: f32,
    /// Of those, the samples before each ray's cut, per ray, where the
    /// engine counts them (`StepStats::samples_composited`).
    pub composited_per_ray: Option<f32>,
    /// The mean samples per step over the same steps, over the median step
    /// time.
    pub samples_per_second: f32,
    pub memory_bytes: usize,
    pub times: StageTimes,
}

/// A rendered image for the viewport.
#[derive(Debug, Clone)]
pub struct RenderedFrame {
    pub generation: u64,
    pub model: ModelKind,
    /// The model's step when the level began (chunks drawn while it
    /// trained on are of later steps).
    pub step: u32,
    /// The model's training seconds when the level began: how far behind
    /// training the picture is.
    pub train_seconds: f64,
    /// 1 = full resolution; 8 = an eighth of the viewport in each direction.
    pub downscale: u32,
    /// False for a level sent before its last row: the rows below those
    /// drawn show the picture it replaces (enlarged, if that was coarser).
    pub complete: bool,
    pub width: u32,
    pub height: u32,
    pub mode: RenderMode,
    /// Row-major, `width × height`.
    pub pixels: Vec<RenderedPixel>,
}

/// A rendered image that stays on the GPU: the gpu engine drew it into a
/// texture on the device the window draws with (the viewer hands its
/// device to the training thread), so the UI shows it without a copy
/// through the CPU.
#[derive(Debug, Clone)]
pub struct GpuFrame {
    pub generation: u64,
    pub model: ModelKind,
    /// The model's step when the level began.
    pub step: u32,
    /// The model's training seconds when the level began.
    pub train_seconds: f64,
    /// 1 = full resolution; 8 = an eighth of the viewport in each direction.
    pub downscale: u32,
    /// False for a level sent before its last band: the rows below those
    /// drawn show the picture it replaces.
    pub complete: bool,
    pub width: u32,
    pub height: u32,
    /// Already applied: the texture holds the colours to show.
    pub mode: RenderMode,
    /// Rgba8Unorm, `width × height`, usage TEXTURE_BINDING (wgpu handles
    /// are reference-counted: this is a cheap clone of the thread's
    /// texture, which it draws the next frame of this size into, so the
    /// UI should show only the newest frame).
    pub texture: wgpu::Texture,
}

#[derive(Debug, Clone)]
pub enum Event {
    SceneLoaded(SceneInfo),
    /// The scene could not be loaded; the previous one stays.
    SceneFailed {
        source: SceneSource,
        error: String,
    },
    /// The engine the thread trains on, e.g. "cpu (AMD EPYC, 2 threads)".
    Engine {
        kind: EngineKind,
        description: String,
    },
    ModelSelected(ModelKind),
    /// The models now taking turns (only those that could be built), or
    /// `None` when the active model trains alone.
    InTurn(Option<InTurn>),
    Running(bool),
    Stats(TrainingStats),
    /// Where the thread's time went over the last second or so.
    Schedule(ScheduleTrace),
    Frame(RenderedFrame),
    /// A frame on the GPU (only to a UI that shares its device with the
    /// thread, see [`crate::session::worker::WorkerOptions::gpu_device`]).
    GpuFrame(GpuFrame),
    CheckpointSaved(PathBuf),
    CheckpointLoaded {
        path: PathBuf,
        model: ModelKind,
        step: u32,
    },
    ExportProgress {
        done: usize,
        total: usize,
    },
    /// Files written, or why the export stopped.
    ExportFinished(Result<Vec<PathBuf>, String>),
    /// The crop box the models now render with, and why a model refused
    /// the one asked for (the gpu engine may not crop).
    CropSet {
        crop: Option<CropBox>,
        refused: Option<String>,
    },
    /// Anything else that went wrong, said in full.
    Error(String),
}
