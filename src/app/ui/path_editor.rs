//! The camera-path editor window: keyframes from the viewport camera or
//! the training cameras, their list and per-keyframe settings, the path's
//! settings, a timeline to scrub and play along, and nerfstudio's
//! `camera_path.json` saved and loaded. The state and its edits live in
//! [`crate::session::path_state`]; this file draws them and moves the
//! viewport camera along the path.

use eframe::egui;
use std::path::{Path, PathBuf};
use std::time::Instant;

use egui::{Color32, RichText, Sense, Stroke};

use super::ViewerUi;
use crate::render::camera_path::nerfstudio::{CameraPathFile, scene_to_original};
use crate::render::camera_path::{CameraPath, FOV_RANGE_DEGREES, Keyframe};
use crate::session::path_state::{PathEditor, PendingLoad, keyframes_from_baked};

/// The colour of error text (as the side panel's).
const ERROR_COLOUR: Color32 = Color32::from_rgb(0xff, 0x70, 0x60);

/// How near (in screen points) a click on the timeline must fall to a
/// keyframe's tick to jump exactly to it.
const SNAP_POINTS: f32 = 8.0;

/// The longest frame step the play clock takes: after a stall (a window
/// drag, a long render on a software rasteriser) the camera moves on by at
/// most this, rather than jumping along the path.
const MAX_PLAY_STEP_SECONDS: f64 = 0.25;

/// Field of view a keyframe may be given here: what the viewport camera
/// can show (its own limits), within what a path may hold.
const KEYFRAME_FOV_DEGREES: (f64, f64) = (1.0, 170.0);

/// Hands a camera path over to the export window for a video: the window
/// opens on its camera path kind with this path loaded (its size and frame
/// rate, as a file's would be), and the export starts from there.
pub fn request_path_export(state: &mut ViewerUi, file: CameraPathFile) {
    let frames = file.baked.len();
    state.export.take_camera_path(FROM_THE_EDITOR, file);
    state.open_export(super::ExportKind::CameraPath);
    state.path_editor.message = Some((format!("In the Export window ({frames} frames)"), false));
}

/// What the export window's file field says of a path from the editor.
pub const FROM_THE_EDITOR: &str = "(the path editor's path)";

impl ViewerUi {
    /// Loads a `camera_path.json` into the editor and opens it, once a
    /// scene is open (the file's poses are placed in the scene's frame);
    /// puts the viewport camera at `load.time` of the path, and plays it
    /// if asked.
    pub fn open_camera_path(&mut self, load: PendingLoad) {
        self.path_editor.open = true;
        self.path_editor.file_text = load.file.display().to_string();
        self.path_editor.pending_load = Some(load);
    }

    pub fn path_editor(&self) -> &PathEditor {
        &self.path_editor
    }

    pub fn path_editor_mut(&mut self) -> &mut PathEditor {
        &mut self.path_editor
    }
}

/// The time at horizontal position `x` of a timeline from `left`,
/// `width` wide, over a path of `duration` seconds (clamped to the path).
pub fn time_at(x: f32, left: f32, width: f32, duration: f64) -> f64 {
    if !(width > 0.0 && duration > 0.0) {
        return 0.0;
    }
    (((x - left) / width) as f64 * duration).clamp(0.0, duration)
}

/// `time`, or the keyframe time nearest it when one lies within
/// `tolerance` seconds.
pub fn snap_to_knot(time: f64, knots: &[f64], tolerance: f64) -> f64 {
    knots
        .iter()
        .copied()
        .filter(|k| (k - time).abs() <= tolerance)
        .min_by(|a, b| (a - time).abs().total_cmp(&(b - time).abs()))
        .unwrap_or(time)
}

/// How many of `count` cameras a path through every `every`-th of them
/// has: as [`CameraPath::through_cameras`] chooses them (the last camera
/// always ends the path).
pub fn cameras_chosen(count: usize, every: usize) -> usize {
    if count == 0 {
        return 0;
    }
    let every = every.max(1);
    (count - 1) / every + 1 + usize::from(!(count - 1).is_multiple_of(every))
}

/// A keyframe at the viewport camera's pose and field of view.
fn current_keyframe(state: &ViewerUi) -> Option<Keyframe> {
    let editor = &state.path_editor;
    let camera = state.camera.as_ref()?;
    Some(Keyframe::from_camera(
        &camera.camera(editor.width.max(1), editor.height.max(1)),
    ))
}

/// Puts the viewport camera at the path's current time.
fn apply_camera(state: &mut ViewerUi) {
    if !state.path_editor.can_sample() {
        return;
    }
    let sample = state.path_editor.path.sample(state.path_editor.time);
    if let Some(camera) = &mut state.camera {
        camera.set_pose(sample.camera_to_world.as_mat4(), sample.fov_degrees as f32);
        state.path_editor.placed_camera = Some(camera.clone());
    }
}

/// Jumps the timeline (and the camera) to keyframe `index`.
fn go_to_keyframe(state: &mut ViewerUi, index: usize) {
    state.path_editor.select(index);
    if let Some(time) = state.path_editor.knot_time(index) {
        state.path_editor.time = time;
        state.path_editor.playing = false;
        apply_camera(state);
    }
}

/// The transform from zrak's world to the open scene's original frame.
fn scene_transform(state: &ViewerUi) -> Result<glam::DMat4, String> {
    let info = state
        .scene
        .as_ref()
        .ok_or("open a scene first: a camera path is placed in its scene's frame")?;
    scene_to_original(&info.scene)
}

/// The path as nerfstudio's file, baked at the editor's fps and size.
fn path_file(state: &ViewerUi) -> Result<CameraPathFile, String> {
    let editor = &state.path_editor;
    if let Some(problem) = editor.path.problem() {
        return Err(problem);
    }
    if !(editor.fps.is_finite() && editor.fps > 0.0) {
        return Err(format!(
            "the frame rate must be positive, got {}",
            editor.fps
        ));
    }
    Ok(CameraPathFile::new(
        editor.path.clone(),
        editor.width.max(1),
        editor.height.max(1),
        editor.fps,
        scene_transform(state)?,
    ))
}

/// Writes the path to `file`; what to tell the user.
pub fn save_path(state: &ViewerUi, file: &Path) -> Result<String, String> {
    let path_file = path_file(state)?;
    path_file.save(file)?;
    Ok(format!(
        "Saved {} keyframes ({} frames) to {}",
        state.path_editor.keyframes().len(),
        path_file.baked.len(),
        file.display()
    ))
}

/// Reads `file` into the editor (its keyframes, or keyframes made from
/// its baked frames when it has none); what to tell the user.
pub fn load_path(state: &mut ViewerUi, file: &Path) -> Result<String, String> {
    let to_original = scene_transform(state)?;
    let loaded = CameraPathFile::load(file)
        .map_err(|e| e.to_string())?
        .moved_into(to_original);
    let editor = &mut state.path_editor;
    let text = match &loaded.path {
        Some(path) => {
            editor.path = path.clone();
            editor.replace_keyframes(path.keyframes.clone());
            format!(
                "Loaded {} keyframes from {}",
                path.keyframes.len(),
                file.display()
            )
        }
        None => {
            let (keyframes, every) = keyframes_from_baked(&loaded);
            if keyframes.is_empty() {
                return Err(format!(
                    "{}: the file has neither keyframes nor baked frames",
                    file.display()
                ));
            }
            let count = keyframes.len();
            editor.path = CameraPath {
                is_cycle: false,
                ..CameraPath::new(Vec::new())
            };
            editor.replace_keyframes(keyframes);
            let thinned = if every > 1 {
                format!(", one in {every}")
            } else {
                String::new()
            };
            format!(
                "{} has no keyframes: made {count} from its {} baked frames{thinned}",
                file.display(),
                loaded.baked.len()
            )
        }
    };
    editor.fps = loaded.fps;
    editor.width = loaded.render_width;
    editor.height = loaded.render_height;
    if let Some(problem) = editor.path.problem() {
        return Err(format!("{}: {problem}", file.display()));
    }
    Ok(text)
}

fn report(state: &mut ViewerUi, result: Result<String, String>) {
    let is_error = result.is_err();
    let text = result.unwrap_or_else(|e| e);
    if is_error {
        state.notice(text.clone(), true);
    }
    state.path_editor.message = Some((text, is_error));
}

fn save_dialog(state: &mut ViewerUi) {
    if let Some(file) = rfd::FileDialog::new()
        .set_title("Save camera path")
        .add_filter("camera path", &["json"])
        .set_file_name("camera_path.json")
        .save_file()
    {
        state.path_editor.file_text = file.display().to_string();
        let result = save_path(state, &file);
        report(state, result);
    }
}

fn load_dialog(state: &mut ViewerUi) {
    if let Some(file) = rfd::FileDialog::new()
        .set_title("Load camera path")
        .add_filter("camera path", &["json"])
        .pick_file()
    {
        state.path_editor.file_text = file.display().to_string();
        let result = load_path(state, &file);
        report(state, result);
    }
}

/// Runs the editor for one frame: a path waiting to load, the play clock,
/// the panel (on the right of the viewport, which it narrows rather than
/// covers, so the path drawn over the view stays in sight). Call before
/// the viewport, so that the camera it moves is the one this frame
/// renders.
pub fn panel(state: &mut ViewerUi, ui: &mut egui::Ui) {
    state.path_editor.driving = false;
    load_pending(state);
    play_step(state, Instant::now());
    if !state.path_editor.open {
        return;
    }
    show_panel(state, ui);
}

/// Loads the file `zrak view --camera-path` named, once the scene is open.
fn load_pending(state: &mut ViewerUi) {
    if state.scene.is_some()
        && state.camera.is_some()
        && let Some(load) = state.path_editor.pending_load.take()
    {
        let result = load_path(state, &load.file);
        let loaded = result.is_ok();
        report(state, result);
        if loaded {
            if let Some(time) = load.time {
                state.path_editor.time = time.clamp(0.0, state.path_editor.path.duration());
            }
            if load.play {
                // From the time asked for, not from the start.
                let time = state.path_editor.time;
                state.path_editor.play();
                state.path_editor.time = time;
            }
            // Without a time the camera stays, so the whole path is seen.
            if load.time.is_some() || load.play {
                apply_camera(state);
            }
        }
    }
}

/// One frame of playing at wall-clock `now`: the clock moves on by the
/// time since the last frame and the camera follows.
fn play_step(state: &mut ViewerUi, now: Instant) {
    // A drag, scroll or key that moved the camera since the path put it
    // somewhere takes it back: playing pauses rather than fight the user.
    if state.path_editor.playing
        && state.path_editor.placed_camera.is_some()
        && state.path_editor.placed_camera != state.camera
    {
        state.path_editor.playing = false;
        state.path_editor.message = Some(("Paused: the camera was moved".into(), false));
    }
    if state.path_editor.playing {
        let dt = state
            .path_editor
            .play_clock
            .map_or(0.0, |last| now.duration_since(last).as_secs_f64())
            .min(MAX_PLAY_STEP_SECONDS);
        state.path_editor.play_clock = Some(now);
        state.path_editor.tick(dt);
        state.path_editor.driving = state.path_editor.playing;
        apply_camera(state);
    } else {
        state.path_editor.play_clock = None;
    }
}

fn show_panel(state: &mut ViewerUi, ui: &mut egui::Ui) {
    let mut open = true;
    egui::Panel::right("zrak camera path")
        .resizable(true)
        .default_size(310.0)
        .show(ui, |ui| {
            ui.horizontal(|ui| {
                ui.label(RichText::new("Camera path").strong());
                ui.with_layout(egui::Layout::right_to_left(egui::Align::Center), |ui| {
                    if ui.small_button("Close").clicked() {
                        open = false;
                    }
                });
            });
            egui::ScrollArea::vertical().show(ui, |ui| contents(state, ui));
        });
    if !open {
        state.path_editor.open = false;
        state.path_editor.playing = false;
    }
}

fn contents(state: &mut ViewerUi, ui: &mut egui::Ui) {
    keyframe_buttons(state, ui);
    ui.separator();
    keyframe_list(state, ui);
    selected_keyframe(state, ui);
    ui.separator();
    timeline(state, ui);
    ui.separator();
    path_settings(state, ui);
    ui.separator();
    files(state, ui);
    if let Some((text, is_error)) = &state.path_editor.message {
        let text = RichText::new(text).small();
        ui.label(if *is_error {
            text.color(ERROR_COLOUR)
        } else {
            text.weak()
        });
    }
}

fn keyframe_buttons(state: &mut ViewerUi, ui: &mut egui::Ui) {
    let cameras = state
        .scene
        .as_ref()
        .map(|s| s.scene.train.iter().map(|f| f.camera).collect::<Vec<_>>())
        .unwrap_or_default();
    ui.horizontal(|ui| {
        if ui
            .add_enabled(state.camera.is_some(), egui::Button::new("Add keyframe"))
            .on_hover_text("a keyframe at the viewport camera, after the selected one")
            .clicked()
            && let Some(keyframe) = current_keyframe(state)
        {
            state.path_editor.add(keyframe);
        }
        if ui
            .add_enabled(
                !state.path_editor.keyframes().is_empty(),
                egui::Button::new("Clear"),
            )
            .clicked()
        {
            state.path_editor.clear();
        }
    });
    ui.horizontal(|ui| {
        let every = state.path_editor.every.max(1);
        let label = if every == 1 {
            format!("From all {} training cameras", cameras.len())
        } else {
            format!(
                "From {} of {} training cameras",
                cameras_chosen(cameras.len(), every),
                cameras.len()
            )
        };
        if ui
            .add_enabled(!cameras.is_empty(), egui::Button::new(label))
            .on_hover_text("replaces the keyframes with the training cameras, in order")
            .clicked()
        {
            let path = CameraPath::through_cameras(&cameras, every);
            let count = path.keyframes.len();
            state.path_editor.replace_keyframes(path.keyframes);
            state.path_editor.message = Some((
                format!("{count} keyframes from the training cameras"),
                false,
            ));
        }
        ui.label("every");
        ui.add(
            egui::DragValue::new(&mut state.path_editor.every)
                .range(1..=cameras.len().max(1))
                .speed(0.1),
        );
    });
}

fn keyframe_list(state: &mut ViewerUi, ui: &mut egui::Ui) {
    let editor = &state.path_editor;
    if editor.keyframes().is_empty() {
        ui.weak("No keyframes: move the view and press Add keyframe");
        return;
    }
    let times = editor.path.knot_times();
    let mut clicked = None;
    egui::ScrollArea::vertical()
        .max_height(96.0)
        .auto_shrink([false, true])
        .show(ui, |ui| {
            for (i, k) in editor.keyframes().iter().enumerate() {
                let own = if k.transition_seconds.is_some() {
                    "*"
                } else {
                    ""
                };
                let text = format!(
                    "{:>2}   {:>6.2} s   fov {:.1}°{own}",
                    i + 1,
                    times[i],
                    k.fov_degrees
                );
                if ui
                    .selectable_label(editor.selected == Some(i), RichText::new(text).monospace())
                    .clicked()
                {
                    clicked = Some(i);
                }
            }
        });
    if let Some(i) = clicked {
        go_to_keyframe(state, i);
    }
}

fn selected_keyframe(state: &mut ViewerUi, ui: &mut egui::Ui) {
    let Some(index) = state.path_editor.selected else {
        return;
    };
    let count = state.path_editor.keyframes().len();
    ui.horizontal(|ui| {
        ui.label(RichText::new(format!("Keyframe {} of {count}", index + 1)).strong());
        if ui
            .add_enabled(index > 0, egui::Button::new("Up"))
            .on_hover_text("earlier in the path")
            .clicked()
        {
            state.path_editor.move_selected(true);
        }
        if ui
            .add_enabled(index + 1 < count, egui::Button::new("Down"))
            .on_hover_text("later in the path")
            .clicked()
        {
            state.path_editor.move_selected(false);
        }
    });
    ui.horizontal(|ui| {
        if ui
            .button("Set to current camera")
            .on_hover_text("moves this keyframe to the viewport camera")
            .clicked()
            && let Some(keyframe) = current_keyframe(state)
        {
            state.path_editor.set_selected_pose(&keyframe);
        }
        if ui.button("Duplicate").clicked() {
            state.path_editor.duplicate_selected();
        }
        if ui.button("Delete").clicked() {
            state.path_editor.delete_selected();
        }
    });
    let has_next = index + 1 < count || state.path_editor.path.is_cycle;
    let default = state.path_editor.path.default_transition_seconds;
    let mut fov_changed = false;
    if let Some(k) = state.path_editor.selected_mut() {
        egui::Grid::new("zrak keyframe")
            .num_columns(2)
            .show(ui, |ui| {
                ui.label("field of view");
                let (low, high) = KEYFRAME_FOV_DEGREES;
                let (low, high) = (low.max(FOV_RANGE_DEGREES.0), high.min(FOV_RANGE_DEGREES.1));
                fov_changed = ui
                    .add(
                        egui::DragValue::new(&mut k.fov_degrees)
                            .range(low..=high)
                            .speed(0.2)
                            .suffix("°"),
                    )
                    .changed();
                ui.end_row();
                ui.label("to the next");
                ui.add_enabled_ui(has_next, |ui| {
                    ui.horizontal(|ui| {
                        let mut own = k.transition_seconds.is_some();
                        if ui
                            .checkbox(&mut own, "own time")
                            .on_hover_text("off: the path's default transition")
                            .changed()
                        {
                            k.transition_seconds = own.then_some(default);
                        }
                        let mut seconds = k.transition_seconds.unwrap_or(default);
                        if ui
                            .add_enabled(
                                own,
                                egui::DragValue::new(&mut seconds)
                                    .range(0.05..=600.0)
                                    .speed(0.02)
                                    .suffix(" s"),
                            )
                            .changed()
                        {
                            k.transition_seconds = Some(seconds);
                        }
                    });
                });
                ui.end_row();
            });
    }
    if fov_changed {
        // Show what the new field of view frames.
        go_to_keyframe(state, index);
    }
}

fn path_settings(state: &mut ViewerUi, ui: &mut egui::Ui) {
    let editor = &mut state.path_editor;
    let training_size = state.scene.as_ref().and_then(|s| s.scene.resolution());
    egui::Grid::new("zrak path settings")
        .num_columns(2)
        .show(ui, |ui| {
            ui.label("duration");
            ui.horizontal(|ui| {
                let mut duration = editor.path.duration();
                let has_segments = duration > 0.0;
                if ui
                    .add_enabled(
                        has_segments,
                        egui::DragValue::new(&mut duration)
                            .range(0.1..=3600.0)
                            .speed(0.05)
                            .suffix(" s"),
                    )
                    .on_hover_text("scales every transition")
                    .changed()
                {
                    editor.path.set_duration(duration);
                    editor.time = editor.time.clamp(0.0, editor.path.duration());
                }
                ui.label("default step");
                ui.add(
                    egui::DragValue::new(&mut editor.path.default_transition_seconds)
                        .range(0.05..=600.0)
                        .speed(0.02)
                        .suffix(" s"),
                )
                .on_hover_text("the time to the next keyframe of keyframes without their own");
            });
            ui.end_row();
            ui.label("loop");
            ui.checkbox(&mut editor.path.is_cycle, "back to the first keyframe");
            ui.end_row();
            ui.label("tension");
            ui.add(egui::Slider::new(&mut editor.path.tension, 0.0..=1.0).fixed_decimals(2))
                .on_hover_text(
                    "the spline's smoothness: 0 is Catmull-Rom (the camera sweeps through \
                     keyframes), 1 stops it at every keyframe",
                );
            ui.end_row();
            ui.label("video");
            ui.horizontal(|ui| {
                ui.add(
                    egui::DragValue::new(&mut editor.fps)
                        .range(1.0..=240.0)
                        .speed(0.2)
                        .suffix(" fps"),
                );
                ui.add(egui::DragValue::new(&mut editor.width).range(16..=8192));
                ui.label("×");
                ui.add(egui::DragValue::new(&mut editor.height).range(16..=8192));
                if let Some((w, h)) = training_size
                    && ui
                        .small_button("as training")
                        .on_hover_text(format!("{w}×{h}"))
                        .clicked()
                {
                    editor.width = w;
                    editor.height = h;
                }
            });
            ui.end_row();
        });
    ui.checkbox(&mut editor.show_overlay, "Draw the path in the viewport");
}

fn timeline(state: &mut ViewerUi, ui: &mut egui::Ui) {
    let duration = state.path_editor.path.duration();
    let can_play = state.path_editor.can_sample() && duration > 0.0;
    ui.horizontal(|ui| {
        let label = if state.path_editor.playing {
            "Pause"
        } else {
            "Play"
        };
        if ui.add_enabled(can_play, egui::Button::new(label)).clicked() {
            if state.path_editor.playing {
                state.path_editor.playing = false;
            } else {
                state.path_editor.play();
                // A moving camera from this frame on (the clock ran
                // earlier in the frame).
                state.path_editor.driving = state.path_editor.playing;
                apply_camera(state);
            }
        }
        if ui
            .add_enabled(can_play, egui::Button::new("To start"))
            .clicked()
        {
            state.path_editor.time = 0.0;
            apply_camera(state);
        }
        ui.label(
            RichText::new(format!("{:.2} / {:.2} s", state.path_editor.time, duration)).monospace(),
        );
    });
    let width = ui.available_width().max(100.0);
    let (rect, response) = ui.allocate_exact_size(egui::vec2(width, 22.0), Sense::click_and_drag());
    let painter = ui.painter_at(rect);
    let track = rect.shrink2(egui::vec2(6.0, 0.0));
    let y = rect.center().y;
    let visuals = ui.visuals();
    painter.line_segment(
        [egui::pos2(track.left(), y), egui::pos2(track.right(), y)],
        Stroke::new(3.0, visuals.widgets.inactive.bg_fill),
    );
    let x_of = |t: f64| {
        if duration > 0.0 {
            track.left() + (t / duration) as f32 * track.width()
        } else {
            track.left()
        }
    };
    let knots = state.path_editor.path.knot_times();
    for (i, &t) in knots.iter().enumerate() {
        let selected = state.path_editor.selected == Some(i % knots.len().max(1))
            && i < state.path_editor.keyframes().len();
        let colour = if selected {
            Color32::from_rgb(255, 225, 0)
        } else {
            Color32::from_rgb(80, 170, 255)
        };
        let x = x_of(t);
        painter.line_segment(
            [
                egui::pos2(x, rect.top() + 3.0),
                egui::pos2(x, rect.bottom() - 3.0),
            ],
            Stroke::new(2.0, colour),
        );
    }
    if can_play {
        let x = x_of(state.path_editor.time);
        painter.circle(
            egui::pos2(x, y),
            6.0,
            Color32::from_rgb(240, 40, 60),
            Stroke::new(1.5, Color32::WHITE),
        );
    }
    if can_play && let Some(pointer) = response.interact_pointer_pos() {
        let t = time_at(pointer.x, track.left(), track.width(), duration);
        let editor = &mut state.path_editor;
        if response.dragged() {
            editor.time = t;
            editor.playing = false;
            editor.driving = true;
            apply_camera(state);
        } else if response.clicked() {
            let tolerance = SNAP_POINTS as f64 / track.width() as f64 * duration;
            let snapped = snap_to_knot(t, &knots, tolerance);
            editor.time = snapped;
            editor.playing = false;
            // A click on a keyframe's tick selects it too.
            if let Some(i) = knots.iter().position(|&k| k == snapped) {
                editor.select(i % editor.keyframes().len());
            }
            apply_camera(state);
        }
    }
    response.on_hover_text("drag to scrub; click a keyframe's tick to jump to it");
}

fn files(state: &mut ViewerUi, ui: &mut egui::Ui) {
    ui.horizontal(|ui| {
        let name = ui.label("File");
        ui.add(
            egui::TextEdit::singleline(&mut state.path_editor.file_text)
                .hint_text("camera_path.json")
                .desired_width(150.0),
        )
        .labelled_by(name.id)
        .on_hover_text("nerfstudio's camera_path.json");
        let file = PathBuf::from(state.path_editor.file_text.trim());
        let named = !state.path_editor.file_text.trim().is_empty();
        if ui.add_enabled(named, egui::Button::new("Save")).clicked() {
            let result = save_path(state, &file);
            report(state, result);
        }
        if ui.add_enabled(named, egui::Button::new("Load")).clicked() {
            let result = load_path(state, &file);
            report(state, result);
        }
    });
    ui.horizontal(|ui| {
        if state.dialogs_available {
            if ui.button("Save path…").clicked() {
                save_dialog(state);
            }
            if ui.button("Load path…").clicked() {
                load_dialog(state);
            }
        }
        if ui
            .add_enabled(
                state.path_editor.can_sample(),
                egui::Button::new("Render video…"),
            )
            .on_hover_text("hands the path to the export window")
            .clicked()
        {
            match path_file(state) {
                Ok(file) => request_path_export(state, file),
                Err(error) => report(state, Err(error)),
            }
        }
    });
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::field::ModelKind;
    use crate::scene::demo::{DemoConfig, build};
    use crate::session::protocol::{Event, SceneInfo, SceneSource};
    use std::sync::Arc;
    use std::time::Duration;

    /// A window's state with the small demo scene open (no thread behind
    /// it: commands go nowhere).
    fn viewer() -> ViewerUi {
        let mut state = ViewerUi::new(Box::new(super::super::ClosedLink), ModelKind::Ngp);
        let scene = build(&DemoConfig {
            size: 16,
            train_views: 6,
            val_views: 1,
            test_views: 1,
        });
        state.handle_event(Event::SceneLoaded(SceneInfo {
            scene: Arc::new(scene),
            source: SceneSource::Demo,
            photographs: Default::default(),
        }));
        state
    }

    /// Largest difference between two poses' entries.
    fn pose_error(a: glam::DMat4, b: glam::DMat4) -> f64 {
        (a - b)
            .to_cols_array()
            .iter()
            .fold(0f64, |m, x| m.max(x.abs()))
    }

    /// Three keyframes added from three orbited views.
    fn with_three_keyframes() -> ViewerUi {
        let mut state = viewer();
        for _ in 0..3 {
            state.camera.as_mut().unwrap().orbit(120.0, 10.0);
            let keyframe = current_keyframe(&state).unwrap();
            state.path_editor.add(keyframe);
        }
        state
    }

    #[test]
    fn a_keyframe_is_the_viewport_camera() {
        let state = with_three_keyframes();
        let view = state.camera.as_ref().unwrap().camera(64, 64);
        let last = state.path_editor.keyframes()[2];
        assert!(pose_error(last.camera_to_world, view.camera_to_world.as_dmat4()) < 1e-6);
        assert!((last.fov_degrees - view.intrinsics.fov_y().to_degrees() as f64).abs() < 1e-4);
    }

    #[test]
    fn saving_and_loading_give_back_the_keyframes() {
        let mut state = with_three_keyframes();
        state.path_editor.path.is_cycle = true;
        state.path_editor.path.tension = 0.25;
        state.path_editor.path.keyframes[1].transition_seconds = Some(2.5);
        let before = state.path_editor.path.clone();
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("camera_path.json");
        let said = save_path(&state, &file).unwrap();
        assert!(said.contains("Saved 3 keyframes"), "{said}");
        // The file says the demo's world is its original frame.
        let written = CameraPathFile::load(&file).unwrap();
        assert_eq!(written.to_original, Some(glam::DMat4::IDENTITY));
        assert_eq!(written.baked.len(), before.frame_count(30.0));
        state.path_editor.clear();
        let said = load_path(&mut state, &file).unwrap();
        assert!(said.contains("Loaded 3 keyframes"), "{said}");
        let after = &state.path_editor.path;
        assert_eq!((after.is_cycle, after.tension), (true, 0.25));
        assert_eq!(after.keyframes.len(), 3);
        for (a, b) in after.keyframes.iter().zip(&before.keyframes) {
            // JSON keeps f64 exactly, but loading rescales each rotation
            // axis to unit length, and these came from an f32 camera whose
            // axes are unit to a few f32 ulps (~1e-7).
            let error = pose_error(a.camera_to_world, b.camera_to_world);
            assert!(error < 1e-6, "{error}");
            assert_eq!(a.fov_degrees, b.fov_degrees);
            assert_eq!(a.transition_seconds, b.transition_seconds);
        }
        assert_eq!(state.path_editor.selected, Some(0));
    }

    #[test]
    fn a_file_with_only_baked_frames_gives_keyframes() {
        let mut state = with_three_keyframes();
        let mut file = path_file(&state).unwrap();
        file.path = None;
        file.baked.truncate(5);
        let first = file.baked[0];
        let dir = tempfile::tempdir().unwrap();
        let name = dir.path().join("baked.json");
        file.save(&name).unwrap();
        state.path_editor.clear();
        let said = load_path(&mut state, &name).unwrap();
        assert!(said.contains("has no keyframes: made 5"), "{said}");
        let k = state.path_editor.keyframes()[0];
        // As above: axes rescaled to unit length on loading.
        assert!(pose_error(k.camera_to_world, first.sample().camera_to_world) < 1e-6);
    }

    #[test]
    fn bad_files_and_no_scene_are_errors_not_panics() {
        let mut state = viewer();
        let dir = tempfile::tempdir().unwrap();
        let missing = dir.path().join("none.json");
        let error = load_path(&mut state, &missing).unwrap_err();
        assert!(error.contains("none.json"), "{error}");
        let broken = dir.path().join("broken.json");
        std::fs::write(&broken, "{\"keyframes\": [{\"matrix\": [1, 2]}]}").unwrap();
        let error = load_path(&mut state, &broken).unwrap_err();
        assert!(
            error.contains("broken.json") && error.contains("missing field `render_width`"),
            "{error}"
        );
        // Saving an empty path says why.
        let error = save_path(&state, &dir.path().join("empty.json")).unwrap_err();
        assert!(error.contains("at least one keyframe"), "{error}");
        // Without a scene there is no frame to place the path in.
        let mut bare = ViewerUi::new(Box::new(super::super::ClosedLink), ModelKind::Ngp);
        let error = load_path(&mut bare, &broken).unwrap_err();
        assert!(error.contains("open a scene first"), "{error}");
    }

    #[test]
    fn a_pending_file_loads_and_puts_the_camera_at_its_time() {
        let source = with_three_keyframes();
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("camera_path.json");
        save_path(&source, &file).unwrap();
        let mut state = viewer();
        state.open_camera_path(PendingLoad {
            file,
            time: Some(1.5),
            play: false,
        });
        assert!(state.path_editor.open);
        load_pending(&mut state);
        assert!(state.path_editor.pending_load.is_none());
        assert_eq!(state.path_editor.time, 1.5);
        let expected = source.path_editor.path.sample(1.5);
        let camera = state.camera.as_ref().unwrap().camera(64, 64);
        // f32 camera against the f64 path.
        assert!(pose_error(camera.camera_to_world.as_dmat4(), expected.camera_to_world) < 1e-5);
        assert!(
            (camera.intrinsics.fov_y().to_degrees() as f64 - expected.fov_degrees).abs() < 1e-3
        );
    }

    #[test]
    fn playing_moves_the_camera_along_the_path_in_real_time() {
        let mut state = with_three_keyframes();
        state.path_editor.play();
        let start = Instant::now();
        // The first frame starts the clock; the next moves it by the time
        // between them.
        play_step(&mut state, start);
        assert_eq!(state.path_editor.time, 0.0);
        play_step(&mut state, start + Duration::from_millis(200));
        assert!((state.path_editor.time - 0.2).abs() < 1e-9);
        assert!(state.path_editor.driving);
        let expected = state.path_editor.path.sample(0.2);
        let camera = state.camera.as_ref().unwrap().camera(64, 64);
        assert!(pose_error(camera.camera_to_world.as_dmat4(), expected.camera_to_world) < 1e-5);
        // A stalled frame moves it by at most MAX_PLAY_STEP_SECONDS.
        play_step(&mut state, start + Duration::from_secs(5));
        assert!((state.path_editor.time - 0.2 - MAX_PLAY_STEP_SECONDS).abs() < 1e-9);
        // Moving the camera by hand pauses it.
        state.camera.as_mut().unwrap().orbit(30.0, 0.0);
        play_step(&mut state, start + Duration::from_millis(5100));
        assert!(!state.path_editor.playing);
        assert!((state.path_editor.time - 0.2 - MAX_PLAY_STEP_SECONDS).abs() < 1e-9);
        // Paused: nothing moves.
        state.path_editor.playing = false;
        play_step(&mut state, start + Duration::from_secs(6));
        assert!((state.path_editor.time - 0.2 - MAX_PLAY_STEP_SECONDS).abs() < 1e-9);
        assert_eq!(state.path_editor.play_clock, None);
    }

    #[test]
    fn render_video_opens_the_export_window_with_the_path() {
        let mut state = with_three_keyframes();
        let file = path_file(&state).unwrap();
        let frames = file.baked.len();
        request_path_export(&mut state, file.clone());
        assert!(state.export.open);
        assert_eq!(state.export.kind, super::super::ExportKind::CameraPath);
        // The export command carries the editor's path unchanged, at its
        // size and frame rate.
        let order = state.export.camera_path().expect("a path is loaded");
        assert_eq!(order.file, file);
        assert_eq!((order.size, order.fps), (None, None));
        assert_eq!(
            state.path_editor.message,
            Some((format!("In the Export window ({frames} frames)"), false))
        );
    }

    #[test]
    fn the_timeline_maps_its_width_onto_the_path() {
        assert_eq!(time_at(10.0, 10.0, 200.0, 4.0), 0.0);
        assert_eq!(time_at(110.0, 10.0, 200.0, 4.0), 2.0);
        assert_eq!(time_at(210.0, 10.0, 200.0, 4.0), 4.0);
        // Beyond either end: clamped; no path or no width: the start.
        assert_eq!(time_at(500.0, 10.0, 200.0, 4.0), 4.0);
        assert_eq!(time_at(-5.0, 10.0, 200.0, 4.0), 0.0);
        assert_eq!(time_at(50.0, 10.0, 0.0, 4.0), 0.0);
        assert_eq!(time_at(50.0, 10.0, 200.0, 0.0), 0.0);
    }

    #[test]
    fn the_training_camera_count_matches_the_path_made() {
        let cameras: Vec<crate::scene::Camera> = (0..10)
            .map(|i| {
                crate::render::camera_path::PathSample {
                    camera_to_world: glam::DMat4::from_translation(glam::DVec3::X * i as f64),
                    fov_degrees: 40.0,
                }
                .camera(8, 8)
            })
            .collect();
        for count in [0, 1, 2, 7, 10] {
            for every in [1, 2, 3, 4, 9, 10, 20] {
                assert_eq!(
                    cameras_chosen(count, every),
                    CameraPath::through_cameras(&cameras[..count], every)
                        .keyframes
                        .len(),
                    "{count} cameras, every {every}"
                );
            }
        }
        assert_eq!(cameras_chosen(10, 3), 4);
        assert_eq!(cameras_chosen(10, 4), 4);
    }

    #[test]
    fn a_click_near_a_keyframe_snaps_to_it() {
        let knots = [0.0, 1.0, 2.5, 4.0];
        assert_eq!(snap_to_knot(0.97, &knots, 0.05), 1.0);
        assert_eq!(snap_to_knot(2.52, &knots, 0.05), 2.5);
        // Far from any: the time clicked.
        assert_eq!(snap_to_knot(1.7, &knots, 0.05), 1.7);
        // Two in reach: the nearer.
        assert_eq!(snap_to_knot(1.8, &[1.5, 2.0], 0.5), 2.0);
        assert_eq!(snap_to_knot(3.0, &[], 1.0), 3.0);
    }
}
