//! The crop box window: turn the box on and off, move and size it within
//! the scene's box, turn it about the vertical (z) axis. Every change goes
//! to the training thread ([`Command::SetCrop`]), which sets it on the
//! models and redraws the view; the box is drawn in the viewport
//! ([`super::overlay`]). An engine that cannot crop says so here.

use eframe::egui;
use egui::RichText;
use glam::{EulerRot, Quat, Vec3};

use super::ViewerUi;
use crate::scene::Aabb;
use crate::scene::crop::CropBox;
use crate::session::protocol::Command;

/// What the crop box window holds.
#[derive(Debug, Clone, PartialEq)]
pub struct CropPanel {
    pub open: bool,
    pub enabled: bool,
    pub centre: Vec3,
    pub size: Vec3,
    /// The turn about the world's z axis, degrees.
    pub yaw_degrees: f32,
    /// The turns about x and y (radians) of a box set elsewhere (`--crop`
    /// with nine numbers, a run's crop.json), kept as they are: the window
    /// edits only the turn about z.
    tilt: (f32, f32),
    /// The scene's box, which bounds the sliders.
    bounds: Option<Aabb>,
    /// What the models render with, as the thread last said.
    pub applied: Option<CropBox>,
    /// Why the engine refused the box, until one is accepted.
    pub refused: Option<String>,
}

impl Default for CropPanel {
    fn default() -> Self {
        Self {
            open: false,
            enabled: false,
            centre: Vec3::ZERO,
            size: Vec3::ONE,
            yaw_degrees: 0.0,
            tilt: (0.0, 0.0),
            bounds: None,
            applied: None,
            refused: None,
        }
    }
}

impl CropPanel {
    /// The box the window describes, when it is on.
    pub fn current(&self) -> Option<CropBox> {
        self.enabled.then(|| CropBox {
            centre: self.centre,
            size: self.size,
            rotation: Quat::from_euler(
                EulerRot::ZYX,
                self.yaw_degrees.to_radians(),
                self.tilt.1,
                self.tilt.0,
            ),
        })
    }

    /// Shows `crop` (or turns the box off).
    pub fn show_box(&mut self, crop: Option<CropBox>) {
        let Some(crop) = crop else {
            self.enabled = false;
            return;
        };
        let (yaw, pitch, roll) = crop.rotation.to_euler(EulerRot::ZYX);
        self.enabled = true;
        self.centre = crop.centre;
        self.size = crop.size;
        self.yaw_degrees = yaw.to_degrees();
        self.tilt = (roll, pitch);
    }

    /// A new scene: its box bounds the sliders; `keep` keeps the current
    /// crop box (the first scene, for `--crop`), else it is cleared.
    pub fn scene_changed(&mut self, bounds: Aabb, keep: bool) {
        self.bounds = Some(bounds);
        if !keep {
            self.reset_to_scene();
            self.enabled = false;
            self.applied = None;
            self.refused = None;
        } else if !self.enabled {
            self.reset_to_scene();
        }
    }

    /// The box that fills the scene's.
    pub fn reset_to_scene(&mut self) {
        if let Some(bounds) = self.bounds {
            self.centre = bounds.centre();
            self.size = bounds.size();
            self.yaw_degrees = 0.0;
            self.tilt = (0.0, 0.0);
        }
    }

    /// The thread's answer to [`Command::SetCrop`].
    pub fn answered(&mut self, crop: Option<CropBox>, refused: Option<String>) {
        self.applied = crop;
        self.refused = refused;
        if crop.is_some() {
            self.show_box(crop);
        }
    }

    /// The box to draw in the viewport: the one on, unless the engine
    /// refused it.
    pub fn drawn(&self) -> Option<CropBox> {
        self.current().filter(|_| self.refused.is_none())
    }
}

/// The crop box window, when open.
pub fn crop_window(state: &mut ViewerUi, ctx: &egui::Context) {
    if !state.crop.open {
        return;
    }
    let mut open = true;
    let before = state.crop.clone();
    egui::Window::new("Crop box")
        .open(&mut open)
        .resizable(false)
        .collapsible(false)
        .default_pos(egui::pos2(330.0, 80.0))
        .show(ctx, |ui| {
            let panel = &mut state.crop;
            ui.checkbox(&mut panel.enabled, "crop the scene to the box");
            let (low, high) = match panel.bounds {
                Some(b) => (b.min, b.max),
                None => (Vec3::splat(-10.0), Vec3::splat(10.0)),
            };
            let extent = (high - low).max(Vec3::splat(1e-3));
            ui.add_enabled_ui(panel.enabled, |ui| {
                egui::Grid::new("zrak crop").num_columns(2).show(ui, |ui| {
                    ui.label("centre");
                    ui.horizontal(|ui| {
                        for axis in 0..3 {
                            ui.add(
                                egui::DragValue::new(&mut panel.centre[axis])
                                    .range(low[axis]..=high[axis])
                                    .speed(extent[axis] / 200.0)
                                    .max_decimals(3)
                                    .prefix(["x ", "y ", "z "][axis]),
                            );
                        }
                    });
                    ui.end_row();
                    ui.label("size");
                    ui.horizontal(|ui| {
                        for axis in 0..3 {
                            ui.add(
                                egui::DragValue::new(&mut panel.size[axis])
                                    .range(extent[axis] / 1000.0..=extent[axis])
                                    .speed(extent[axis] / 200.0)
                                    .max_decimals(3)
                                    .prefix(["x ", "y ", "z "][axis]),
                            );
                        }
                    });
                    ui.end_row();
                    ui.label("turn about z");
                    ui.add(egui::Slider::new(&mut panel.yaw_degrees, -180.0..=180.0).suffix("°"));
                    ui.end_row();
                });
                if ui.button("Reset to scene box").clicked() {
                    panel.reset_to_scene();
                }
            });
            if let Some(problem) = &panel.refused {
                ui.label(RichText::new(problem).color(super::panels::ERROR_COLOUR));
            } else if panel.enabled {
                ui.label(
                    RichText::new(
                        "Outside the box the background shows; exports keep only the inside.",
                    )
                    .small(),
                );
            }
        });
    state.crop.open = open;
    let changed = state.crop.enabled != before.enabled
        || (state.crop.enabled && state.crop.current() != before.current());
    if changed {
        state.send(Command::SetCrop(state.crop.current()));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_panel_shows_a_box_and_gives_it_back() {
        let mut panel = CropPanel::default();
        assert_eq!(panel.current(), None);
        let crop = CropBox {
            centre: Vec3::new(0.1, -0.2, 0.3),
            size: Vec3::new(1.0, 0.5, 0.25),
            rotation: Quat::from_euler(EulerRot::ZYX, 0.5, 0.2, -0.1),
        };
        panel.show_box(Some(crop));
        let back = panel.current().unwrap();
        assert_eq!((back.centre, back.size), (crop.centre, crop.size));
        assert!(back.rotation.angle_between(crop.rotation) < 1e-5);
        // A new scene clears it and sizes it to the scene's box.
        panel.scene_changed(Aabb::new(Vec3::splat(-2.0), Vec3::splat(2.0)), false);
        assert_eq!(panel.current(), None);
        panel.enabled = true;
        assert_eq!(
            panel.current(),
            Some(CropBox::axis_aligned(Vec3::ZERO, Vec3::splat(4.0)))
        );
        // A refusal hides the drawn box.
        panel.answered(None, Some("no".into()));
        assert_eq!(panel.drawn(), None);
    }
}
