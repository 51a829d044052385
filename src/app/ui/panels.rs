//! The menu bar, the control panel on the left, the stats and plots at the
//! bottom.

use eframe::egui;
use std::path::PathBuf;

use egui::{Color32, RichText};

use super::viewport::{
    CompareMode, CompareWith, {self},
};
use super::{PlotAxis, ViewerUi, describe_source, plots};
use crate::field::ModelKind;
use crate::model::RenderMode;
use crate::scene::SpaceAnalysis;
use crate::scene::photographs::PhotographAnalysis;
use crate::session::camera::Navigation;
use crate::session::protocol::{Balance, Command, SceneSource};

/// The colour of error text.
pub(super) const ERROR_COLOUR: Color32 = Color32::from_rgb(0xff, 0x70, 0x60);

/// Whether a native file dialog can open: rfd asks the XDG desktop portal
/// over D-Bus and falls back to zenity; with neither it silently returns
/// nothing, which would look like a cancelled dialog.
pub fn file_dialog_available() -> bool {
    if !cfg!(target_os = "linux") {
        return true;
    }
    let has_bus = std::env::var_os("DBUS_SESSION_BUS_ADDRESS").is_some_and(|v| !v.is_empty());
    let has_zenity = std::env::var_os("PATH")
        .is_some_and(|paths| std::env::split_paths(&paths).any(|dir| dir.join("zenity").is_file()));
    has_bus || has_zenity
}

const NO_DIALOG: &str = "No file dialog can open here (no desktop portal or zenity): type the path in the field and press the button beside it.";

pub fn menu_bar(state: &mut ViewerUi, ui: &mut egui::Ui) {
    egui::Panel::top("zrak menu").show(ui, |ui| {
        egui::MenuBar::new().ui(ui, |ui| {
            ui.menu_button("File", |ui| {
                if ui.button("Open scene…").clicked() {
                    pick_scene_folder(state);
                }
                if ui.button("Open demo scene").clicked() {
                    state.opening = Some(SceneSource::Demo);
                    state.scene_error = None;
                    state.send(Command::OpenScene(SceneSource::Demo));
                }
                ui.separator();
                if ui.button("Save checkpoint…").clicked() {
                    save_checkpoint_dialog(state);
                }
                if ui.button("Load checkpoint…").clicked() {
                    load_checkpoint_dialog(state);
                }
                ui.menu_button("Recent runs", |ui| recent_runs_menu(state, ui));
                ui.separator();
                if ui.button("Export…").clicked() {
                    state.export.open = true;
                }
                if ui.button("Crop box…").clicked() {
                    state.crop.open = true;
                }
                if ui.button("Camera path…").clicked() {
                    state.path_editor.open = true;
                }
                ui.separator();
                if ui.button("Quit").clicked() {
                    ui.ctx().send_viewport_cmd(egui::ViewportCommand::Close);
                }
            });
            ui.menu_button("View", |ui| {
                if let Some(camera) = &mut state.camera {
                    let mut navigation = camera.navigation();
                    ui.radio_value(&mut navigation, Navigation::Orbit, "Orbit");
                    ui.radio_value(&mut navigation, Navigation::Fly, "Fly");
                    camera.set_navigation(navigation);
                }
                if ui.button("Reset view").clicked() {
                    reset_view(state);
                }
            });
        });
    });
}

/// The runs kept when the viewer closed, newest first, each with its size:
/// a click loads its checkpoint, "Remove" deletes its folder.
fn recent_runs_menu(state: &mut ViewerUi, ui: &mut egui::Ui) {
    use crate::train::kept;
    let Some(base) = crate::session::worker::default_autosave_folder() else {
        ui.label("No data folder ($XDG_DATA_HOME or $HOME is unset)");
        return;
    };
    let runs = kept::list(&base);
    if runs.is_empty() {
        ui.label(format!("No kept runs in {}", base.display()));
        return;
    }
    let total: u64 = runs.iter().map(|r| r.bytes).sum();
    ui.label(format!(
        "{} runs, {} in {}",
        runs.len(),
        crate::files::human_bytes(total),
        base.display()
    ));
    ui.separator();
    for run in runs {
        ui.horizontal(|ui| {
            if ui
                .button(run.describe())
                .on_hover_text("Load this run's checkpoint")
                .clicked()
            {
                let path = run.folder.join(crate::train::run::CHECKPOINT_FILE);
                state.checkpoint_path_text = path.display().to_string();
                state.send(Command::LoadCheckpoint(path));
                ui.close();
            }
            if ui
                .small_button("Remove")
                .on_hover_text("Delete this run's folder")
                .clicked()
            {
                match kept::remove(&base, &run.folder) {
                    Ok(()) => state.notice(format!("removed {}", run.folder.display()), false),
                    Err(error) => state.notice(&error, true),
                }
            }
        });
    }
}

fn pick_scene_folder(state: &mut ViewerUi) {
    if !state.dialogs_available {
        state.notice(NO_DIALOG, true);
        return;
    }
    if let Some(folder) = rfd::FileDialog::new()
        .set_title("Open a scene folder")
        .pick_folder()
    {
        state.open_scene(folder);
    }
}

fn save_checkpoint_dialog(state: &mut ViewerUi) {
    if !state.dialogs_available {
        state.notice(NO_DIALOG, true);
        return;
    }
    if let Some(path) = rfd::FileDialog::new()
        .set_title("Save checkpoint")
        .set_file_name("checkpoint.zrak")
        .save_file()
    {
        state.checkpoint_path_text = path.display().to_string();
        state.send(Command::SaveCheckpoint(path));
    }
}

fn load_checkpoint_dialog(state: &mut ViewerUi) {
    if !state.dialogs_available {
        state.notice(NO_DIALOG, true);
        return;
    }
    if let Some(path) = rfd::FileDialog::new()
        .set_title("Load checkpoint")
        .add_filter("zrak checkpoint", &["zrak"])
        .pick_file()
    {
        state.checkpoint_path_text = path.display().to_string();
        state.send(Command::LoadCheckpoint(path));
    }
}

fn reset_view(state: &mut ViewerUi) {
    if let (Some(camera), Some(info)) = (&mut state.camera, &state.scene) {
        camera.reset(&info.scene);
        state.viewport.snapped = false;
        state.viewport.view_index = None;
    }
}

fn section(ui: &mut egui::Ui, title: &str) {
    ui.add_space(6.0);
    ui.label(RichText::new(title).strong());
}

pub fn controls_panel(state: &mut ViewerUi, ui: &mut egui::Ui) {
    egui::Panel::left("zrak controls")
        .resizable(true)
        .default_size(280.0)
        .show(ui, |ui| {
            egui::ScrollArea::vertical().show(ui, |ui| {
                scene_section(state, ui);
                ui.separator();
                training_section(state, ui);
                ui.separator();
                render_section(state, ui);
                ui.separator();
                camera_section(state, ui);
                ui.separator();
                checkpoint_section(state, ui);
                ui.separator();
                ui.horizontal(|ui| {
                    if ui.button("Export…").clicked() {
                        state.export.open = true;
                    }
                    if ui.button("Crop box…").clicked() {
                        state.crop.open = true;
                    }
                    if ui.button("Camera path…").clicked() {
                        state.path_editor.open = true;
                    }
                });
                if !state.notices.is_empty() {
                    ui.separator();
                    for notice in state.notices.iter().rev() {
                        let text = RichText::new(&notice.text).small();
                        if notice.is_error {
                            ui.label(text.color(ERROR_COLOUR));
                        } else {
                            ui.label(text.weak());
                        }
                    }
                }
            });
        });
}

fn scene_section(state: &mut ViewerUi, ui: &mut egui::Ui) {
    section(ui, "Scene");
    match &state.scene {
        Some(info) => {
            ui.label(format!(
                "{} — {} train / {} val views",
                info.scene.name,
                info.scene.train.len(),
                info.scene.val.len()
            ));
            if let Some((w, h)) = info.scene.resolution() {
                ui.label(
                    RichText::new(format!("{w}×{h}, {}", describe_source(&info.source))).small(),
                );
            }
            space_line(ui, &info.scene.space);
            photograph_lines(ui, &info.photographs);
        }
        None => {
            ui.label("No scene loaded yet");
        }
    }
    if let Some(source) = &state.opening {
        ui.horizontal(|ui| {
            ui.spinner();
            ui.label(format!("Opening {}…", describe_source(source)));
        });
    }
    if let Some(error) = &state.scene_error {
        ui.label(RichText::new(error).color(ERROR_COLOUR));
    }
    ui.horizontal(|ui| {
        if ui.button("Open scene…").clicked() {
            pick_scene_folder(state);
        }
        ui.weak("or drop a folder on the window");
    });
    ui.horizontal(|ui| {
        let name = ui.label("Folder");
        let field = ui
            .add(
                egui::TextEdit::singleline(&mut state.scene_path_text)
                    .hint_text("path to a scene")
                    .desired_width(150.0),
            )
            .labelled_by(name.id);
        let entered = field.lost_focus() && ui.input(|i| i.key_pressed(egui::Key::Enter));
        if (ui.button("Open").clicked() || entered) && !state.scene_path_text.trim().is_empty() {
            let path = PathBuf::from(state.scene_path_text.trim());
            state.open_scene(path);
        }
    });
}

/// What the scene is treated as: a line, its reasons on hover and, opened,
/// under it.
fn space_line(ui: &mut egui::Ui, analysis: &SpaceAnalysis) {
    let label = ui.label(space_summary(analysis));
    if !analysis.reasons.is_empty() {
        label.on_hover_text(analysis.reasons.join("\n\n"));
        egui::CollapsingHeader::new(RichText::new("Why").small())
            .id_salt("scene space reasons")
            .show(ui, |ui| {
                for reason in &analysis.reasons {
                    ui.label(RichText::new(format!("• {reason}")).small());
                }
            });
    }
}

/// Appearance vectors, camera refinement and masks: a line each, its
/// reasons on hover.
fn photograph_lines(ui: &mut egui::Ui, analysis: &PhotographAnalysis) {
    for (name, choice) in [
        ("Appearance", &analysis.appearance),
        ("Camera refinement", &analysis.refine_cameras),
        ("Masks", &analysis.masks),
    ] {
        let label = ui.label(format!("{name}: {}", choice.summary()));
        if !choice.reasons.is_empty() {
            label.on_hover_text(choice.reasons.join("\n\n"));
        }
    }
}

/// The space line's text, e.g. "Space: unbounded (from the scene)".
fn space_summary(analysis: &SpaceAnalysis) -> String {
    let how = if analysis.overridden {
        "chosen with --space"
    } else {
        "from the scene"
    };
    format!("Space: {} ({how})", analysis.space)
}

fn training_section(state: &mut ViewerUi, ui: &mut egui::Ui) {
    section(ui, "Training");
    ui.horizontal(|ui| {
        let label = if state.running { "Pause" } else { "Start" };
        if ui.button(label).clicked() {
            state.toggle_running();
        }
        if ui
            .add_enabled(!state.running, egui::Button::new("Step"))
            .clicked()
        {
            state.send(Command::StepOnce);
        }
        if ui.button("Reset").clicked() {
            state.send(Command::Reset);
            if let Some(history) = state
                .histories
                .iter_mut()
                .find(|h| h.model == state.active_model)
            {
                history.points.clear();
                history.latest = None;
            }
        }
    });
    ui.horizontal(|ui| {
        ui.label("Model");
        for kind in ModelKind::ALL {
            if ui
                .selectable_label(state.active_model == kind, kind.name())
                .clicked()
            {
                state.select_model(kind);
            }
        }
    });
    let in_turn = state.in_turn.is_some();
    if ui
        .selectable_label(in_turn, "Train all models in turn")
        .on_hover_text(
            "every model trains in turn, at equal shares of training time, so the \
             plots compare them; the view shows the model selected above",
        )
        .clicked()
    {
        state.toggle_in_turn();
    }
    if let Some(turns) = &state.in_turn {
        // The model whose figures came last is the one training now.
        let now = state
            .histories
            .iter()
            .filter_map(|h| h.points.last().map(|p| (p.wall_seconds, h.model)))
            .max_by(|a, b| a.0.total_cmp(&b.0))
            .map(|(_, m)| m);
        let names: Vec<&str> = turns.models.iter().map(|m| m.name()).collect();
        ui.label(
            RichText::new(format!(
                "{} take turns of {} s of training{}",
                names.join(", "),
                turns.slice_seconds,
                now.map_or(String::new(), |m| format!("; now {}", m.name()))
            ))
            .small(),
        );
    }
    let mut share = state.balance.training_share;
    let slider = ui.add(
        egui::Slider::new(&mut share, 0.0..=1.0)
            .text("training share")
            .fixed_decimals(2),
    );
    if slider.changed() {
        state.balance = Balance {
            training_share: share,
        };
        state.send(Command::SetBalance(state.balance));
    }
    match &state.engine {
        Some((kind, description)) => {
            ui.label(format!("Engine: {}", kind.name()));
            ui.label(RichText::new(description).small());
        }
        None => {
            ui.label("Engine: starting…");
        }
    }
}

fn render_section(state: &mut ViewerUi, ui: &mut egui::Ui) {
    section(ui, "Render");
    ui.horizontal(|ui| {
        ui.label("Mode");
        for (mode, name) in [
            (RenderMode::Rgb, "RGB"),
            (RenderMode::Depth, "Depth"),
            (RenderMode::Opacity, "Opacity"),
        ] {
            if ui.selectable_label(state.mode == mode, name).clicked() {
                state.set_render_mode(mode);
            }
        }
    });
    appearance_row(state, ui);
    ui.horizontal(|ui| {
        ui.label("Resolution");
        for scale in viewport::RENDER_SCALES {
            let name = match scale {
                0.25 => "¼×".to_string(),
                0.5 => "½×".to_string(),
                _ => format!("{scale}×"),
            };
            ui.selectable_value(&mut state.viewport.render_scale, scale, name)
                .on_hover_text("pixels rendered per viewport pixel, once the view rests");
        }
    });
    ui.horizontal(|ui| {
        ui.label("Compare");
        let compare = &mut state.viewport.compare;
        ui.selectable_value(compare, CompareMode::Off, "Render only");
        ui.selectable_value(compare, CompareMode::SideBySide, "Side by side");
        ui.selectable_value(compare, CompareMode::Split, "Split");
    });
    if state.viewport.compare != CompareMode::Off {
        ui.horizontal(|ui| {
            ui.label("with");
            let with = &mut state.viewport.compare_with;
            ui.selectable_value(with, CompareWith::GroundTruth, "Ground truth");
            ui.selectable_value(with, CompareWith::Error, "Error");
        });
        if state.viewport.compare == CompareMode::Split {
            ui.add(egui::Slider::new(&mut state.viewport.split, 0.0..=1.0).text("split"));
        }
        if let Some(psnr) = state.viewport.view_psnr.filter(|_| state.viewport.snapped) {
            ui.label(format!("PSNR of this view: {psnr:.2} dB"));
        }
    }
}

/// Which appearance vector the models draw with, where the scene's
/// photographs have them: the mean (as held-out views are scored) or a
/// training image's.
fn appearance_row(state: &mut ViewerUi, ui: &mut egui::Ui) {
    let Some(images) = state
        .scene
        .as_ref()
        .filter(|info| info.photographs.appearance.on)
        .map(|info| info.scene.train.len())
        .filter(|&n| n > 0)
    else {
        return;
    };
    let mut chosen = state.appearance_view();
    ui.horizontal(|ui| {
        ui.label("Appearance");
        if ui
            .selectable_label(chosen.is_none(), "Mean")
            .on_hover_text("the mean of the training images' vectors, as held-out views are scored")
            .clicked()
        {
            chosen = None;
        }
        let mut image = chosen.unwrap_or(0);
        let picker = ui
            .add(
                egui::DragValue::new(&mut image)
                    .range(0..=images - 1)
                    .prefix("image "),
            )
            .on_hover_text("draw with this training image's appearance vector");
        if picker.changed() || (picker.clicked() && chosen.is_none()) {
            chosen = Some(image);
        }
    });
    state.set_appearance_view(chosen);
}

fn camera_section(state: &mut ViewerUi, ui: &mut egui::Ui) {
    section(ui, "Camera");
    let count = state.scene.as_ref().map_or(0, |s| s.scene.train.len());
    if let Some(camera) = &mut state.camera {
        ui.horizontal(|ui| {
            let mut navigation = camera.navigation();
            ui.selectable_value(&mut navigation, Navigation::Orbit, "Orbit");
            ui.selectable_value(&mut navigation, Navigation::Fly, "Fly");
            camera.set_navigation(navigation);
        });
        let hint = match camera.navigation() {
            Navigation::Orbit => "drag: rotate · right/middle drag: pan · scroll: zoom",
            Navigation::Fly => "WASD: move · Q/E: down/up · drag: look · Shift: faster",
        };
        ui.label(RichText::new(hint).small().weak());
        ui.add(
            egui::Slider::new(&mut camera.fov_y_degrees, 10.0..=120.0)
                .text("field of view")
                .suffix("°"),
        );
    }
    ui.horizontal(|ui| {
        if ui.button("< Prev view").clicked() {
            viewport::step_training_view(state, false);
        }
        if ui.button("Next view >").clicked() {
            viewport::step_training_view(state, true);
        }
        if ui.button("Reset view").clicked() {
            reset_view(state);
        }
    });
    let at = match (state.viewport.view_index, state.viewport.snapped) {
        (Some(view), true) => format!("at training view {} of {count}", view + 1),
        (Some(view), false) => format!("moved from training view {} of {count}", view + 1),
        (None, _) => format!("{count} training views"),
    };
    ui.label(RichText::new(at).small());
}

fn checkpoint_section(state: &mut ViewerUi, ui: &mut egui::Ui) {
    section(ui, "Checkpoint");
    ui.horizontal(|ui| {
        if ui.button("Save…").clicked() {
            save_checkpoint_dialog(state);
        }
        if ui.button("Load…").clicked() {
            load_checkpoint_dialog(state);
        }
    });
    ui.horizontal(|ui| {
        let name = ui.label("Path");
        ui.add(
            egui::TextEdit::singleline(&mut state.checkpoint_path_text)
                .hint_text("checkpoint.zrak")
                .desired_width(100.0),
        )
        .labelled_by(name.id);
        let path = state.checkpoint_path_text.trim().to_string();
        if ui
            .add_enabled(!path.is_empty(), egui::Button::new("Save to path"))
            .clicked()
        {
            state.send(Command::SaveCheckpoint(PathBuf::from(&path)));
        }
        if ui
            .add_enabled(!path.is_empty(), egui::Button::new("Load path"))
            .clicked()
        {
            state.send(Command::LoadCheckpoint(PathBuf::from(&path)));
        }
    });
}

pub fn bottom_panel(state: &mut ViewerUi, ui: &mut egui::Ui) {
    egui::Panel::bottom("zrak plots")
        .resizable(true)
        .default_size(250.0)
        .show(ui, |ui| {
            ui.horizontal_top(|ui| {
                ui.vertical(|ui| {
                    ui.set_width(250.0);
                    stats(state, ui);
                });
                ui.separator();
                ui.vertical(|ui| {
                    ui.set_width(200.0);
                    ui.horizontal(|ui| {
                        ui.selectable_value(
                            &mut state.timing,
                            super::TimingView::Stages,
                            RichText::new("Time per stage").strong(),
                        )
                        .on_hover_text("The stages of a training step");
                        ui.selectable_value(
                            &mut state.timing,
                            super::TimingView::Thread,
                            RichText::new("Where the time goes").strong(),
                        )
                        .on_hover_text(format!(
                            "The training thread's wall time over the last {:.0} s. While \
                             the camera rests, training gets the training share of it; the \
                             view and the held-out evaluation the rest.",
                            super::SCHEDULE_WINDOW_SECONDS
                        ));
                    });
                    match state.timing {
                        super::TimingView::Stages => stage_times(state, ui),
                        super::TimingView::Thread => thread_time(state, ui),
                    }
                });
                ui.separator();
                ui.vertical(|ui| {
                    // Wrapped so the export stays on screen in a narrow window.
                    ui.horizontal_wrapped(|ui| {
                        ui.label(RichText::new("Loss and PSNR").strong());
                        ui.label("against");
                        ui.selectable_value(&mut state.plot_axis, PlotAxis::Step, "steps");
                        ui.selectable_value(&mut state.plot_axis, PlotAxis::WallTime, "wall time");
                        ui.selectable_value(
                            &mut state.plot_axis,
                            PlotAxis::TrainTime,
                            "training time",
                        );
                        ui.separator();
                        let name = ui.label("Export to");
                        ui.add(
                            egui::TextEdit::singleline(&mut state.comparison_folder)
                                .desired_width(140.0),
                        )
                        .labelled_by(name.id);
                        if ui
                            .button("Export plot and table")
                            .on_hover_text(
                                "psnr.png, psnr.svg, table.md and table.csv: held-out PSNR \
                                 against training time and each model's figures",
                            )
                            .clicked()
                        {
                            let _ = state.export_comparison();
                        }
                    });
                    plots::show(ui, &state.histories, state.plot_axis);
                });
            });
        });
}

fn stats(state: &ViewerUi, ui: &mut egui::Ui) {
    ui.label(RichText::new("Stats").strong());
    let latest = state.latest_stats(state.active_model);
    let engine = state
        .engine
        .as_ref()
        .map_or("—".to_string(), |(kind, description)| {
            format!("{}: {description}", kind.name())
        });
    let figure = |value: Option<String>| value.unwrap_or_else(|| "—".to_string());
    let psnr = state
        .history(state.active_model)
        .and_then(|h| h.latest_val_psnr())
        .map(|v| format!("{v:.2} dB (val)"))
        .or_else(|| {
            latest
                .and_then(|s| s.batch_psnr)
                .map(|v| format!("{v:.2} dB (batch)"))
        });
    let rows = [
        ("model", state.active_model.name().to_string()),
        ("step", figure(latest.map(|s| s.step.to_string()))),
        (
            "ms/step",
            figure(latest.map(|s| format!("{:.1}", s.ms_per_step))),
        ),
        (
            // Marched, and where the engine counts them, composited (before
            // each ray's cut): one row, so the panel keeps its height.
            "samples/ray",
            figure(latest.map(|s| match s.composited_per_ray {
                Some(composited) => {
                    format!("{:.1} ({composited:.1} composited)", s.samples_per_ray)
                }
                None => format!("{:.1}", s.samples_per_ray),
            })),
        ),
        (
            "samples/s",
            figure(latest.map(|s| format!("{:.2} M", s.samples_per_second / 1e6))),
        ),
        (
            "memory",
            figure(latest.map(|s| format!("{:.1} MiB", s.memory_bytes as f64 / 1048576.0))),
        ),
        ("loss", figure(latest.map(|s| format!("{:.5}", s.loss)))),
        ("PSNR", figure(psnr)),
        ("engine", engine),
        ("display", figure(state.display_adapter.clone())),
    ];
    egui::Grid::new("zrak stats")
        .num_columns(2)
        .spacing([10.0, 1.0])
        .max_col_width(170.0)
        .show(ui, |ui| {
            for (name, value) in rows {
                ui.label(RichText::new(name).small());
                // Long adapter names are cut; the whole text shows on hover.
                ui.add(egui::Label::new(RichText::new(&value).small()).truncate())
                    .on_hover_text(value);
                ui.end_row();
            }
        });
}

fn stage_times(state: &ViewerUi, ui: &mut egui::Ui) {
    let Some(stats) = state.latest_stats(state.active_model) else {
        ui.weak("no step yet");
        return;
    };
    let total = stats.times.total();
    egui::Grid::new("zrak stage times")
        .num_columns(3)
        .spacing([10.0, 1.0])
        .striped(true)
        .show(ui, |ui| {
            for (name, seconds) in stats.times.named() {
                ui.label(RichText::new(name).small());
                ui.label(RichText::new(format!("{:.2} ms", seconds * 1e3)).small());
                let share = if total > 0.0 {
                    seconds / total * 100.0
                } else {
                    0.0
                };
                ui.label(RichText::new(format!("{share:.0}%")).small());
                ui.end_row();
            }
            ui.label(RichText::new("total").small().strong());
            ui.label(
                RichText::new(format!("{:.2} ms", total * 1e3))
                    .small()
                    .strong(),
            );
            ui.end_row();
        });
}

/// Where the training thread's wall time went over the last seconds:
/// training (and of it the occupancy-grid updates), drawing each level of
/// the view, held-out evaluation, waiting, and the rest.
fn thread_time(state: &ViewerUi, ui: &mut egui::Ui) {
    let Some(trace) = state.recent_schedule().filter(|t| t.wall_seconds > 0.0) else {
        ui.weak("nothing yet");
        return;
    };
    let wall = trace.wall_seconds;
    let mut rows: Vec<(String, f64)> = vec![
        (
            format!("training ({} steps)", trace.steps),
            trace.training_seconds,
        ),
        (
            "  of it grid updates".to_string(),
            trace.grid_update_seconds,
        ),
    ];
    // The two levels that took the most time, coarse first, and the rest
    // in one row: the column keeps its height (a taller one would grow
    // the panel into the viewport), however many sizes the levels had.
    let mut levels = trace.rendering.clone();
    levels.sort_by(|a, b| b.seconds.total_cmp(&a.seconds));
    let rest = levels.split_off(levels.len().min(2));
    levels.sort_by_key(|level| std::cmp::Reverse(level.downscale));
    for level in &levels {
        let name = if level.downscale > 1 {
            format!("render 1/{} (×{})", level.downscale, level.finished)
        } else {
            format!("render full (×{})", level.finished)
        };
        rows.push((name, level.seconds));
    }
    if !rest.is_empty() {
        rows.push((
            format!(
                "render, {} other sizes (×{})",
                rest.len(),
                rest.iter().map(|l| l.finished).sum::<u32>()
            ),
            rest.iter().map(|l| l.seconds).sum(),
        ));
    }
    rows.push((
        format!("evaluation (×{})", trace.evaluations),
        trace.evaluation_seconds,
    ));
    rows.push(("idle".to_string(), trace.idle_seconds));
    rows.push(("other".to_string(), trace.other_seconds()));
    egui::Grid::new("zrak thread time")
        .num_columns(3)
        .spacing([10.0, 1.0])
        .striped(true)
        .show(ui, |ui| {
            for (name, seconds) in rows {
                ui.label(RichText::new(name).small());
                ui.label(RichText::new(format!("{seconds:.2} s")).small());
                ui.label(RichText::new(format!("{:.0}%", 100.0 * seconds / wall)).small());
                ui.end_row();
            }
            ui.label(RichText::new("wall").small().strong());
            ui.label(RichText::new(format!("{wall:.1} s")).small().strong());
            ui.end_row();
        });
}
