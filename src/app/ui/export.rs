//! The Export window: a turntable, a camera path (PNG frames or an MP4
//! video), a mesh or a point cloud of the active model, each with progress
//! and cancel. The training thread does the work a unit at a time (see
//! `session/worker/export_jobs.rs`), with the same functions as the commands.
//! Mesh, points and renders keep to the crop box when one is on.

use eframe::egui;
use std::path::PathBuf;

use egui::RichText;

use super::panels::ERROR_COLOUR;
use super::{Notice, ViewerUi};
use crate::mesh::MinComponent;
use crate::mesh::extract::{MAX_RESOLUTION, default_threshold};
use crate::model::RenderMode;
use crate::render::camera_path::nerfstudio::CameraPathFile;
use crate::render::export::ExportSettings;
use crate::render::path::Turntable;
use crate::session::protocol::{CameraPathExport, Command, MeshExport, PointsExport};

/// What the window exports.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum ExportKind {
    Turntable,
    CameraPath,
    Mesh,
    Points,
}

impl ExportKind {
    pub const ALL: [ExportKind; 4] = [
        ExportKind::Turntable,
        ExportKind::CameraPath,
        ExportKind::Mesh,
        ExportKind::Points,
    ];

    pub fn name(self) -> &'static str {
        match self {
            ExportKind::Turntable => "Turntable",
            ExportKind::CameraPath => "Camera path",
            ExportKind::Mesh => "Mesh",
            ExportKind::Points => "Points",
        }
    }

    /// What a unit of progress counts.
    fn units(self) -> &'static str {
        match self {
            ExportKind::Turntable => "frames",
            ExportKind::CameraPath => "frames rendered and encoded",
            ExportKind::Mesh => "slabs of the grid, then the surface",
            ExportKind::Points => "training views",
        }
    }
}

/// What the export window holds.
#[derive(Debug, Clone)]
pub struct ExportDialog {
    pub open: bool,
    pub kind: ExportKind,
    // Turntable.
    pub frames: usize,
    /// Use the training images' size instead of `width` × `height`.
    pub training_size: bool,
    pub width: u32,
    pub height: u32,
    pub elevation_degrees: f32,
    /// Use the training cameras' mean distance instead of `radius`.
    pub mean_radius: bool,
    pub radius: f32,
    pub folder: String,
    pub write_gif: bool,
    // Camera path.
    pub path_file: String,
    /// The file last loaded, and its text field's path then.
    pub path_loaded: Option<(String, CameraPathFile)>,
    pub path_error: Option<String>,
    /// A folder of PNG frames, or a file ending in .mp4.
    pub path_out: String,
    /// Use the file's size and frame rate.
    pub path_file_size: bool,
    pub path_width: u32,
    pub path_height: u32,
    pub path_file_fps: bool,
    pub path_fps: f64,
    pub path_mode: RenderMode,
    // Mesh.
    pub mesh_out: String,
    pub mesh_resolution: u32,
    /// Use the model's default threshold.
    pub mesh_default_threshold: bool,
    pub mesh_threshold: f32,
    pub mesh_drop_small: bool,
    /// Pieces below this share of all faces are dropped, percent.
    pub mesh_min_percent: f64,
    // Points.
    pub points_out: String,
    pub points_max_rays: usize,
    pub points_min_opacity: f32,
    /// Write over an earlier export's files.
    pub replace_existing: bool,
    /// (units done, units in all) while an export runs.
    pub progress: Option<(usize, usize)>,
    /// The kind of the export running or last run.
    pub running_kind: ExportKind,
    pub result: Option<Notice>,
}

impl Default for ExportDialog {
    fn default() -> Self {
        let turntable = Turntable::default();
        let temp = |name: &str| std::env::temp_dir().join(name).display().to_string();
        Self {
            open: false,
            kind: ExportKind::Turntable,
            frames: turntable.frames,
            training_size: true,
            width: 400,
            height: 400,
            elevation_degrees: turntable.elevation_degrees,
            mean_radius: true,
            radius: 4.0,
            folder: temp("zrak-turntable"),
            write_gif: true,
            path_file: String::new(),
            path_loaded: None,
            path_error: None,
            path_out: temp("zrak-path.mp4"),
            path_file_size: true,
            path_width: 640,
            path_height: 480,
            path_file_fps: true,
            path_fps: 30.0,
            path_mode: RenderMode::Rgb,
            mesh_out: temp("zrak-mesh.ply"),
            mesh_resolution: 256,
            mesh_default_threshold: true,
            mesh_threshold: 10.0,
            mesh_drop_small: false,
            mesh_min_percent: 1.0,
            points_out: temp("zrak-points.ply"),
            points_max_rays: 1_000_000,
            points_min_opacity: 0.9,
            replace_existing: false,
            progress: None,
            running_kind: ExportKind::Turntable,
            result: None,
        }
    }
}

impl ExportDialog {
    /// The settings the turntable command carries.
    pub fn settings(&self, mode: RenderMode) -> ExportSettings {
        ExportSettings {
            turntable: Turntable {
                frames: self.frames.max(1),
                elevation_degrees: self.elevation_degrees,
                radius: (!self.mean_radius).then_some(self.radius),
                size: (!self.training_size).then_some((self.width.max(8), self.height.max(8))),
            },
            mode,
            out_dir: PathBuf::from(self.folder.trim()),
            write_gif: self.write_gif,
            replace_existing: self.replace_existing,
        }
    }

    /// The camera path command, once a file is loaded.
    pub fn camera_path(&self) -> Option<CameraPathExport> {
        let (_, file) = self.path_loaded.as_ref()?;
        Some(CameraPathExport {
            file: file.clone(),
            out: PathBuf::from(self.path_out.trim()),
            size: (!self.path_file_size).then_some((self.path_width, self.path_height)),
            fps: (!self.path_file_fps).then_some(self.path_fps),
            mode: self.path_mode,
            replace_existing: self.replace_existing,
        })
    }

    pub fn mesh(&self) -> MeshExport {
        MeshExport {
            out: PathBuf::from(self.mesh_out.trim()),
            resolution: self.mesh_resolution,
            threshold: (!self.mesh_default_threshold).then_some(self.mesh_threshold),
            min_component: self
                .mesh_drop_small
                .then_some(MinComponent::Fraction(self.mesh_min_percent / 100.0)),
            replace_existing: self.replace_existing,
        }
    }

    pub fn points(&self) -> PointsExport {
        PointsExport {
            out: PathBuf::from(self.points_out.trim()),
            max_rays: self.points_max_rays,
            min_opacity: self.points_min_opacity,
            replace_existing: self.replace_existing,
        }
    }

    /// Takes a path that is no file (the path editor's), named `label` in
    /// the file field.
    pub fn take_camera_path(&mut self, label: &str, file: CameraPathFile) {
        self.path_file = label.to_string();
        self.path_width = file.render_width;
        self.path_height = file.render_height;
        self.path_fps = file.fps;
        self.path_loaded = Some((label.to_string(), file));
        self.path_error = None;
    }

    /// Reads the camera path file named in the field.
    fn load_path_file(&mut self) {
        let text = self.path_file.trim().to_string();
        match CameraPathFile::load(std::path::Path::new(&text)) {
            Ok(file) => {
                self.path_width = file.render_width;
                self.path_height = file.render_height;
                self.path_fps = file.fps;
                self.path_loaded = Some((text, file));
                self.path_error = None;
            }
            Err(error) => {
                self.path_loaded = None;
                self.path_error = Some(error.to_string());
            }
        }
    }
}

pub fn export_window(state: &mut ViewerUi, ctx: &egui::Context) {
    if !state.export.open {
        return;
    }
    let mut open = true;
    let mode = state.mode;
    let threshold = state
        .scene
        .as_ref()
        .map(|info| default_threshold(state.active_model, info.scene.unit_cube.scale));
    let crop_on = state.crop.drawn().is_some();
    let mut command = None;
    let mut use_path_crop = false;
    egui::Window::new("Export")
        .open(&mut open)
        .resizable(false)
        .collapsible(false)
        .show(ctx, |ui| {
            let dialog = &mut state.export;
            let running = dialog.progress.is_some();
            ui.add_enabled_ui(!running, |ui| {
                ui.horizontal(|ui| {
                    for kind in ExportKind::ALL {
                        ui.selectable_value(&mut dialog.kind, kind, kind.name());
                    }
                });
                ui.separator();
                match dialog.kind {
                    ExportKind::Turntable => turntable_fields(dialog, ui),
                    ExportKind::CameraPath => use_path_crop = path_fields(dialog, ui),
                    ExportKind::Mesh => mesh_fields(dialog, ui, threshold),
                    ExportKind::Points => points_fields(dialog, ui),
                }
                ui.checkbox(
                    &mut dialog.replace_existing,
                    "replace existing files (an earlier export's frames, a video, a mesh)",
                );
            });
            let note = match dialog.kind {
                ExportKind::Turntable => format!("mode: {mode:?} (the viewport's)"),
                ExportKind::CameraPath => "frames go to NAME.frames/ beside a video".into(),
                // The gpu engine answers σ and colour at points for
                // Instant-NGP only; the others say so when asked.
                ExportKind::Mesh | ExportKind::Points => {
                    format!("the {} model", state.active_model.name())
                }
            };
            ui.label(RichText::new(note).small());
            if crop_on && dialog.kind != ExportKind::Turntable {
                ui.label(RichText::new("inside the crop box only").small());
            }
            ui.horizontal(|ui| {
                if running {
                    if ui.button("Cancel").clicked() {
                        command = Some(Command::CancelExport);
                    }
                    return;
                }
                let order = match dialog.kind {
                    ExportKind::Turntable => (!dialog.folder.trim().is_empty())
                        .then(|| Command::ExportTurntable(dialog.settings(mode))),
                    ExportKind::CameraPath => dialog.camera_path().map(Command::ExportCameraPath),
                    ExportKind::Mesh => Some(Command::ExportMesh(dialog.mesh())),
                    ExportKind::Points => Some(Command::ExportPoints(dialog.points())),
                };
                if ui
                    .add_enabled(order.is_some(), egui::Button::new("Export"))
                    .clicked()
                {
                    dialog.result = None;
                    dialog.progress = Some((0, 1));
                    dialog.running_kind = dialog.kind;
                    command = order;
                }
            });
            if let Some((done, total)) = dialog.progress {
                let fraction = done as f32 / total.max(1) as f32;
                ui.add(
                    egui::ProgressBar::new(fraction)
                        .text(format!("{done} / {total} {}", dialog.running_kind.units()))
                        .show_percentage(),
                );
            }
            if let Some(result) = &dialog.result {
                let text = RichText::new(&result.text);
                ui.label(if result.is_error {
                    text.color(ERROR_COLOUR)
                } else {
                    text
                });
            }
        });
    if let Some(command) = command {
        state.send(command);
    }
    if use_path_crop {
        apply_path_crop(state);
    }
    state.export.open = open;
}

/// Sets the loaded path's crop box (moved into the scene's world, as its
/// poses are when it renders) as the viewer's.
fn apply_path_crop(state: &mut ViewerUi) {
    let (Some((_, file)), Some(info)) = (&state.export.path_loaded, &state.scene) else {
        return;
    };
    let moved = crate::render::camera_path::nerfstudio::scene_to_original(&info.scene)
        .map(|to_original| file.moved_into(to_original));
    match moved {
        Ok(file) => {
            let crop = file.crop.map(|block| block.crop);
            state.crop.show_box(crop);
            state.crop.open = true;
            state.send(Command::SetCrop(crop));
        }
        Err(error) => state.export.path_error = Some(error),
    }
}

fn turntable_fields(dialog: &mut ExportDialog, ui: &mut egui::Ui) {
    egui::Grid::new("zrak export turntable")
        .num_columns(2)
        .show(ui, |ui| {
            ui.label("frames");
            ui.add(egui::DragValue::new(&mut dialog.frames).range(1..=3600));
            ui.end_row();
            ui.label("resolution");
            ui.horizontal(|ui| {
                ui.checkbox(&mut dialog.training_size, "as training");
                ui.add_enabled_ui(!dialog.training_size, |ui| {
                    ui.add(egui::DragValue::new(&mut dialog.width).range(8..=4096));
                    ui.label("×");
                    ui.add(egui::DragValue::new(&mut dialog.height).range(8..=4096));
                });
            });
            ui.end_row();
            ui.label("elevation");
            ui.add(egui::Slider::new(&mut dialog.elevation_degrees, -89.0..=89.0).suffix("°"));
            ui.end_row();
            ui.label("radius");
            ui.horizontal(|ui| {
                ui.checkbox(&mut dialog.mean_radius, "training cameras' mean");
                ui.add_enabled(
                    !dialog.mean_radius,
                    egui::DragValue::new(&mut dialog.radius)
                        .range(0.01..=1000.0)
                        .speed(0.05),
                );
            });
            ui.end_row();
            ui.label("folder");
            ui.add(egui::TextEdit::singleline(&mut dialog.folder).desired_width(220.0));
            ui.end_row();
            ui.label("GIF");
            ui.checkbox(&mut dialog.write_gif, "also write turntable.gif");
            ui.end_row();
        });
}

/// The camera path's fields; true when the file's crop box is to be used.
fn path_fields(dialog: &mut ExportDialog, ui: &mut egui::Ui) -> bool {
    let mut use_crop = false;
    egui::Grid::new("zrak export path")
        .num_columns(2)
        .show(ui, |ui| {
            ui.label("camera_path.json");
            ui.horizontal(|ui| {
                ui.add(egui::TextEdit::singleline(&mut dialog.path_file).desired_width(220.0));
                if ui.button("Load").clicked() {
                    dialog.load_path_file();
                }
            });
            ui.end_row();
            ui.label("");
            match (&dialog.path_loaded, &dialog.path_error) {
                (_, Some(error)) => ui.label(RichText::new(error).color(ERROR_COLOUR).small()),
                (Some((_, file)), None) => {
                    let has_crop = file.crop.is_some();
                    ui.horizontal(|ui| {
                        ui.label(
                            RichText::new(format!(
                                "{} frames, {}×{}, {} frames a second",
                                file.frames().map_or(0, |f| f.len()),
                                file.render_width,
                                file.render_height,
                                file.fps,
                            ))
                            .small(),
                        );
                        // Renders use the viewer's crop box; the file's
                        // becomes it on request.
                        if has_crop && ui.small_button("use its crop box").clicked() {
                            use_crop = true;
                        }
                    })
                    .response
                }
                (None, None) => ui.label(RichText::new("no path loaded").small()),
            };
            ui.end_row();
            ui.label("output");
            ui.add(egui::TextEdit::singleline(&mut dialog.path_out).desired_width(220.0))
                .on_hover_text("a folder of PNG frames, or a file ending in .mp4");
            ui.end_row();
            ui.label("size");
            ui.horizontal(|ui| {
                ui.checkbox(&mut dialog.path_file_size, "the file's");
                ui.add_enabled_ui(!dialog.path_file_size, |ui| {
                    ui.add(egui::DragValue::new(&mut dialog.path_width).range(8..=8192));
                    ui.label("×");
                    ui.add(egui::DragValue::new(&mut dialog.path_height).range(8..=8192));
                });
            });
            ui.end_row();
            ui.label("frames a second");
            ui.horizontal(|ui| {
                ui.checkbox(&mut dialog.path_file_fps, "the file's");
                ui.add_enabled(
                    !dialog.path_file_fps,
                    egui::DragValue::new(&mut dialog.path_fps).range(1.0..=240.0),
                );
            });
            ui.end_row();
            ui.label("mode");
            ui.horizontal(|ui| {
                for (mode, name) in [
                    (RenderMode::Rgb, "colour"),
                    (RenderMode::Depth, "depth"),
                    (RenderMode::Opacity, "opacity"),
                ] {
                    ui.selectable_value(&mut dialog.path_mode, mode, name);
                }
            });
            ui.end_row();
        });
    use_crop
}

fn mesh_fields(dialog: &mut ExportDialog, ui: &mut egui::Ui, threshold: Option<f32>) {
    egui::Grid::new("zrak export mesh")
        .num_columns(2)
        .show(ui, |ui| {
            ui.label("file");
            ui.add(egui::TextEdit::singleline(&mut dialog.mesh_out).desired_width(220.0))
                .on_hover_text(".ply (binary) or .obj");
            ui.end_row();
            ui.label("resolution");
            ui.add(
                egui::DragValue::new(&mut dialog.mesh_resolution)
                    .range(2..=MAX_RESOLUTION)
                    .suffix(" nodes along the longest side"),
            );
            ui.end_row();
            ui.label("threshold");
            ui.horizontal(|ui| {
                let default = threshold.map_or("the model's default".to_string(), |t| {
                    format!("the model's default, σ = {t:.3}")
                });
                ui.checkbox(&mut dialog.mesh_default_threshold, default);
                ui.add_enabled(
                    !dialog.mesh_default_threshold,
                    egui::DragValue::new(&mut dialog.mesh_threshold)
                        .range(1e-3..=1e5)
                        .speed(0.1),
                );
            });
            ui.end_row();
            ui.label("small pieces");
            ui.horizontal(|ui| {
                ui.checkbox(&mut dialog.mesh_drop_small, "drop those under");
                ui.add_enabled(
                    dialog.mesh_drop_small,
                    egui::DragValue::new(&mut dialog.mesh_min_percent)
                        .range(0.0..=100.0)
                        .speed(0.1)
                        .suffix(" % of the faces"),
                );
            });
            ui.end_row();
        });
}

fn points_fields(dialog: &mut ExportDialog, ui: &mut egui::Ui) {
    egui::Grid::new("zrak export points")
        .num_columns(2)
        .show(ui, |ui| {
            ui.label("file");
            ui.add(egui::TextEdit::singleline(&mut dialog.points_out).desired_width(220.0))
                .on_hover_text(".ply");
            ui.end_row();
            ui.label("rays");
            ui.add(
                egui::DragValue::new(&mut dialog.points_max_rays)
                    .range(1..=100_000_000)
                    .speed(10_000)
                    .suffix(" over all training views"),
            );
            ui.end_row();
            ui.label("least opacity");
            ui.add(egui::Slider::new(&mut dialog.points_min_opacity, 0.0..=1.0));
            ui.end_row();
        });
}
