//! The viewer's exports: a turntable, a camera path (PNG frames or an MP4
//! video), a mesh or a point cloud, each done one unit per turn of the
//! training thread (a frame, a slab of the density grid, a view), so the
//! window shows progress and a cancel stops the job between two units.
//! Training waits while an export runs. Each kind calls the same functions
//! as its command (`zrak render --turntable|--camera-path`, `zrak export
//! mesh|points`), so both make the same files.

use std::path::PathBuf;
use std::sync::Arc;

use crate::field::ModelKind;
use crate::model::RadianceModel;
use crate::render::camera_path::export::{PathRender, PathRenderSettings};
use crate::render::camera_path::frames::RenderSource;
use crate::render::camera_path::nerfstudio::scene_to_original;
use crate::render::export::{ExportSettings, TurntableExport};
use crate::scene::Scene;
use crate::scene::crop::CropBox;
use crate::session::protocol::{CameraPathExport, MeshExport, PointsExport};

use super::export_mesh::{MeshJob, PointsJob};

/// What the window asked to export (one at a time: its size does not
/// matter).
#[allow(clippy::large_enum_variant)]
pub(super) enum ExportOrder {
    Turntable(ExportSettings),
    CameraPath(CameraPathExport),
    Mesh(MeshExport),
    Points(PointsExport),
}

/// An export in progress, with the model it exports.
pub(super) struct ExportJob {
    model: ModelKind,
    work: JobWork,
}

enum JobWork {
    Turntable(TurntableExport),
    CameraPath(Box<PathRender>),
    Mesh(MeshJob),
    Points(PointsJob),
}

impl ExportJob {
    /// Checks the order and its output before any work.
    pub(super) fn start(
        scene: &Arc<Scene>,
        order: ExportOrder,
        model: ModelKind,
        crop: Option<CropBox>,
        step: u32,
    ) -> Result<ExportJob, String> {
        let work = match order {
            ExportOrder::Turntable(settings) => {
                JobWork::Turntable(TurntableExport::start(scene, settings)?)
            }
            ExportOrder::CameraPath(order) => {
                // The frames' record: which model, trained how far, in
                // which box, so a later job never continues over frames of
                // another model or step.
                let source = RenderSource {
                    run: format!("the viewer on {}", scene.name),
                    weights: format!("the viewer's model at step {step}"),
                    model: model.name().to_string(),
                    crop,
                };
                JobWork::CameraPath(Box::new(PathRender::start(path_settings(
                    scene, order, source,
                )?)?))
            }
            ExportOrder::Mesh(order) => JobWork::Mesh(MeshJob::start(scene, order, model, crop)?),
            ExportOrder::Points(order) => {
                JobWork::Points(PointsJob::start(scene.clone(), order, crop)?)
            }
        };
        Ok(ExportJob { model, work })
    }

    /// The model it exports.
    pub(super) fn model(&self) -> ModelKind {
        self.model
    }

    /// (units done, units in all).
    pub(super) fn progress(&self) -> (usize, usize) {
        match &self.work {
            JobWork::Turntable(export) => (export.done(), export.total()),
            JobWork::CameraPath(render) => render.progress(),
            JobWork::Mesh(job) => job.progress(),
            JobWork::Points(job) => job.progress(),
        }
    }

    /// Does the next unit; false when the job is ready to finish.
    pub(super) fn step(&mut self, model: &dyn RadianceModel) -> Result<bool, String> {
        match &mut self.work {
            JobWork::Turntable(export) => export.render_next(model),
            JobWork::CameraPath(render) => render.step(model),
            JobWork::Mesh(job) => job.step(model),
            JobWork::Points(job) => job.step(model),
        }
    }

    /// The files written.
    pub(super) fn finish(self, model: &dyn RadianceModel) -> Result<Vec<PathBuf>, String> {
        match self.work {
            JobWork::Turntable(export) => export.finish(),
            JobWork::CameraPath(render) => {
                let output = render.finish(model)?;
                Ok(match output.video {
                    Some(video) => vec![video.path],
                    None => output.frame_files,
                })
            }
            JobWork::Mesh(job) => job.finish(model),
            JobWork::Points(job) => job.finish(),
        }
    }
}

/// The render settings of a camera path order: the path moved into the
/// scene's world, baked at the order's rate, at its size.
fn path_settings(
    scene: &Scene,
    order: CameraPathExport,
    source: RenderSource,
) -> Result<PathRenderSettings, String> {
    let file = order.file.moved_into(scene_to_original(scene)?);
    let samples = match order.fps {
        Some(fps) => file.frames_at(fps),
        None => file.frames(),
    }?;
    let (width, height) = order
        .size
        .unwrap_or((file.render_width, file.render_height));
    // The command line's bounds (`MAX_IMAGE_SIDE`, `render_bytes_per_view`:
    // 5 floats a pixel as it renders and the 8-bit image with the PNG
    // encoder's copy).
    if !(1..=16384).contains(&width) || !(1..=16384).contains(&height) {
        return Err(format!(
            "a frame of {width}×{height} pixels: each side must be 1 to 16384"
        ));
    }
    crate::files::check_memory(
        &format!("a {width}×{height} frame"),
        width as u64 * height as u64 * (5 * 4 + 2 * 4),
    )?;
    Ok(PathRenderSettings {
        range: 0..samples.len(),
        samples,
        width,
        height,
        fps: order.fps.unwrap_or(file.fps),
        mode: order.mode,
        out: order.out,
        replace_existing: order.replace_existing,
        keep_frames: false,
        depth_range: scene.depth_range(),
        source,
        ndc: scene.ndc(),
    })
}
