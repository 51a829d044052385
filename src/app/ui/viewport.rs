//! The viewport: the training thread's frames on a texture, camera input,
//! render requests, and the comparison with a training view's photograph.

use eframe::egui;
use egui::{
    Color32, PointerButton, Pos2, Rect, Sense, TextureHandle, TextureId, TextureOptions, Vec2,
};

use super::{NativeTextures, ViewerUi};
use crate::field::ModelKind;
use crate::model::{RenderMode, RenderedPixel};
use crate::scene::{Camera, Scene, to_u8};
use crate::session::camera::{FlyInput, Navigation, ViewCamera, step_view};
use crate::session::protocol::{Command, GpuFrame, RenderRequest, RenderedFrame};

/// The colour the training thread composites empty space onto (white, as
/// the reference protocol evaluates); photographs are shown over it too.
pub const BACKGROUND: [f32; 3] = crate::metrics::WHITE;

/// Mean absolute error (over the three channels) that maps to the hottest
/// colour of the error map: errors past a quarter of the range are all
/// equally wrong to the eye.
pub const ERROR_SCALE: f32 = 0.25;

/// How fast `--auto-orbit` turns, in drag points per second: one full turn
/// takes a few seconds at the camera's orbit rate.
const AUTO_ORBIT_POINTS_PER_SECOND: f32 = 150.0;

/// How the render is set against the training view's photograph.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CompareMode {
    /// The render alone.
    Off,
    SideBySide,
    /// One image, the render left of a divider and the other right of it.
    Split,
}

/// What the render is compared with.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CompareWith {
    GroundTruth,
    /// |render - truth| as a heat map.
    Error,
}

/// A training view's photograph, ready to show and compare.
struct GroundTruth {
    view: usize,
    width: u32,
    height: u32,
    rgb: Vec<[f32; 3]>,
    texture: TextureHandle,
}

/// The image on screen: pixels uploaded from the CPU (cpu engine), or a
/// texture the gpu engine drew on the window's device.
enum ViewportImage {
    Uploaded(TextureHandle),
    OnGpu {
        id: TextureId,
        size: [usize; 2],
        /// The texture `id` shows, to tell when a frame brings another.
        texture: wgpu::Texture,
    },
}

impl ViewportImage {
    fn id(&self) -> TextureId {
        match self {
            ViewportImage::Uploaded(handle) => handle.id(),
            ViewportImage::OnGpu { id, .. } => *id,
        }
    }

    fn size(&self) -> [usize; 2] {
        match self {
            ViewportImage::Uploaded(handle) => handle.size(),
            ViewportImage::OnGpu { size, .. } => *size,
        }
    }
}

/// What the viewport remembers between frames.
pub struct ViewportState {
    image: Option<ViewportImage>,
    /// Generation, model, step, downscale, mode and size of the shown frame.
    shown: Option<ShownFrame>,
    /// The last request sent, and the training view it was of (if any).
    last_request: Option<(Camera, RenderMode, bool, ModelKind, bool)>,
    requested_view: Option<usize>,
    /// The generation of the last request sent.
    pub requested_generation: u64,
    /// Frames older than this answer a model or scene no longer shown.
    min_generation: u64,
    /// True when the camera moved in the last frame.
    pub moving: bool,
    pub compare: CompareMode,
    pub compare_with: CompareWith,
    /// Where the split divider stands, as a fraction of the image width.
    pub split: f32,
    /// Pixels rendered per viewport pixel along each side, once the
    /// progressive levels reach full resolution (one of [`RENDER_SCALES`]).
    pub render_scale: f32,
    /// The training view last snapped to.
    pub view_index: Option<usize>,
    /// True while the camera still stands exactly at `view_index`.
    pub snapped: bool,
    truth: Option<GroundTruth>,
    error_texture: Option<TextureHandle>,
    /// PSNR of the last full-resolution frame of a training view.
    pub view_psnr: Option<f32>,
    /// The camera as it was last frame, to tell whether it moved.
    previous_camera: Option<ViewCamera>,
    pub frames_shown: u64,
    pub frames_dropped: u64,
    /// Where the viewport lies in the window, in physical pixels (x, y,
    /// width, height): the window test looks there in its screenshot.
    pub rect_pixels: Option<[u32; 4]>,
}

/// Facts about the frame on screen.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ShownFrame {
    pub generation: u64,
    pub model: ModelKind,
    pub step: u32,
    /// The model's training seconds when the frame's level began.
    pub train_seconds: f64,
    pub downscale: u32,
    /// False while its level is still being drawn band by band.
    pub complete: bool,
    pub width: u32,
    pub height: u32,
    pub mode: RenderMode,
}

impl Default for ViewportState {
    fn default() -> Self {
        Self {
            image: None,
            shown: None,
            last_request: None,
            requested_view: None,
            requested_generation: 0,
            min_generation: 0,
            moving: false,
            compare: CompareMode::Off,
            compare_with: CompareWith::GroundTruth,
            split: 0.5,
            render_scale: 1.0,
            view_index: None,
            snapped: false,
            truth: None,
            error_texture: None,
            view_psnr: None,
            previous_camera: None,
            frames_shown: 0,
            frames_dropped: 0,
            rect_pixels: None,
        }
    }
}

impl ViewportState {
    pub fn shown(&self) -> Option<ShownFrame> {
        self.shown
    }

    /// Whether a frame answering request `generation` is worth showing:
    /// never older than what is shown, and, while the camera rests, only
    /// the answer to the latest request. While it moves, a frame of a
    /// camera a moment old is better than a frozen picture, so any newer
    /// frame is taken.
    pub fn accepts(&mut self, generation: u64) -> bool {
        let shown_generation = self.shown.map_or(0, |s| s.generation);
        let fresh = generation >= self.min_generation
            && generation >= shown_generation
            && (generation == self.requested_generation || self.moving);
        if !fresh {
            self.frames_dropped += 1;
        }
        fresh
    }

    /// Frames still on their way answer a model or a camera no longer
    /// wanted; ask again.
    pub fn invalidate(&mut self) {
        self.min_generation = self.requested_generation + 1;
        self.last_request = None;
    }

    /// A new scene: nothing shown or compared belongs to it.
    pub fn scene_changed(&mut self) {
        self.invalidate();
        self.image = None;
        self.shown = None;
        self.truth = None;
        self.error_texture = None;
        self.view_index = None;
        self.snapped = false;
        self.view_psnr = None;
        self.previous_camera = None;
    }

    /// Uploads `frame` to the viewport's texture, in place. Returns the id
    /// of a gpu engine's texture shown before, which the caller frees
    /// ([`NativeTextures::free`]).
    #[must_use]
    pub fn show_frame(&mut self, ctx: &egui::Context, frame: RenderedFrame) -> Option<TextureId> {
        let image = frame_image(&frame);
        let mut released = None;
        match &mut self.image {
            Some(ViewportImage::Uploaded(texture)) => texture.set(image, TextureOptions::LINEAR),
            other => {
                if let Some(ViewportImage::OnGpu { id, .. }) = other {
                    released = Some(*id);
                }
                *other = Some(ViewportImage::Uploaded(ctx.load_texture(
                    "zrak viewport",
                    image,
                    TextureOptions::LINEAR,
                )));
            }
        }
        self.frames_shown += 1;
        self.shown = Some(ShownFrame {
            generation: frame.generation,
            model: frame.model,
            step: frame.step,
            train_seconds: frame.train_seconds,
            downscale: frame.downscale,
            complete: frame.complete,
            width: frame.width,
            height: frame.height,
            mode: frame.mode,
        });
        // The error map only means something for a frame of the very camera
        // the photograph was taken with.
        let of_view = frame.generation == self.requested_generation
            && self.requested_view.is_some()
            && self.requested_view == self.truth.as_ref().map(|t| t.view);
        if of_view && let Some(truth) = &self.truth {
            let (image, psnr) = error_image(&frame, truth);
            if frame.downscale == 1 {
                self.view_psnr = psnr;
            }
            match &mut self.error_texture {
                Some(texture) => texture.set(image, TextureOptions::LINEAR),
                None => {
                    self.error_texture =
                        Some(ctx.load_texture("zrak error map", image, TextureOptions::LINEAR))
                }
            }
        } else if !of_view {
            self.error_texture = None;
        }
        released
    }

    /// Shows a frame the gpu engine drew on the window's device: no pixel
    /// passes through the CPU. The egui id is kept and re-pointed when the
    /// thread's texture changes (another level size).
    pub fn show_gpu_frame(&mut self, frame: GpuFrame, native: &mut dyn NativeTextures) {
        let size = [frame.width as usize, frame.height as usize];
        match &mut self.image {
            Some(ViewportImage::OnGpu {
                id,
                size: shown_size,
                texture,
            }) => {
                if *texture != frame.texture {
                    *id = native.register(&frame.texture, Some(*id));
                    *texture = frame.texture;
                }
                *shown_size = size;
            }
            other => {
                let id = native.register(&frame.texture, None);
                *other = Some(ViewportImage::OnGpu {
                    id,
                    size,
                    texture: frame.texture,
                });
            }
        }
        self.frames_shown += 1;
        self.shown = Some(ShownFrame {
            generation: frame.generation,
            model: frame.model,
            step: frame.step,
            train_seconds: frame.train_seconds,
            downscale: frame.downscale,
            complete: frame.complete,
            width: frame.width,
            height: frame.height,
            mode: frame.mode,
        });
        // The error map needs pixels; comparing asks for them (see
        // `show`), so a texture frame is never of the compared view.
        self.error_texture = None;
    }

    /// Loads the photograph of training view `view` for comparison.
    fn load_truth(&mut self, ctx: &egui::Context, scene: &Scene, view: usize) {
        if self.truth.as_ref().is_some_and(|t| t.view == view) {
            return;
        }
        let Some(frame) = scene.train.get(view) else {
            self.truth = None;
            return;
        };
        let image = &frame.image;
        let rgb = image.to_rgb_over(BACKGROUND);
        let bytes: Vec<u8> = rgb.iter().flat_map(|c| c.map(to_u8)).collect();
        let colour =
            egui::ColorImage::from_rgb([image.width as usize, image.height as usize], &bytes);
        let texture = ctx.load_texture("zrak ground truth", colour, TextureOptions::LINEAR);
        self.truth = Some(GroundTruth {
            view,
            width: image.width,
            height: image.height,
            rgb,
            texture,
        });
        self.error_texture = None;
        self.view_psnr = None;
    }
}

/// Draws a frame in its mode: colour, depth (near white, far black, empty
/// black) or opacity.
fn frame_image(frame: &RenderedFrame) -> egui::ColorImage {
    let size = [frame.width as usize, frame.height as usize];
    let grey = |v: f32| {
        let v = to_u8(v);
        Color32::from_rgb(v, v, v)
    };
    let pixels: Vec<Color32> = match frame.mode {
        RenderMode::Rgb => frame
            .pixels
            .iter()
            .map(|p| Color32::from_rgb(to_u8(p.rgb[0]), to_u8(p.rgb[1]), to_u8(p.rgb[2])))
            .collect(),
        RenderMode::Opacity => frame.pixels.iter().map(|p| grey(p.opacity)).collect(),
        RenderMode::Depth => {
            let (near, far) = depth_range(&frame.pixels);
            frame
                .pixels
                .iter()
                .map(|p| match surface_depth(p) {
                    Some(depth) => grey(1.0 - (depth - near) / (far - near).max(1e-6)),
                    None => Color32::BLACK,
                })
                .collect()
        }
    };
    if pixels.len() == size[0] * size[1] {
        egui::ColorImage::new(size, pixels)
    } else {
        // A malformed frame must not bring the window down.
        egui::ColorImage::filled(size, Color32::DARK_RED)
    }
}

/// The depth of the surface a pixel sees, if it sees one (opacity > ½).
fn surface_depth(pixel: &RenderedPixel) -> Option<f32> {
    (pixel.opacity > 0.5).then(|| pixel.depth / pixel.opacity)
}

/// Nearest and farthest surface in a frame, so depth uses the whole grey
/// range whatever the scene's scale.
fn depth_range(pixels: &[RenderedPixel]) -> (f32, f32) {
    let (near, far) = pixels
        .iter()
        .filter_map(surface_depth)
        .filter(|d| d.is_finite())
        .fold((f32::INFINITY, f32::NEG_INFINITY), |(n, f), d| {
            (n.min(d), f.max(d))
        });
    if near.is_finite() && far.is_finite() {
        (near, far)
    } else {
        (0.0, 1.0)
    }
}

/// The heat colour of an error in [0, 1]: black, red, yellow, white.
pub fn heat_colour(value: f32) -> Color32 {
    let v = value.clamp(0.0, 1.0) * 3.0;
    let r = v.min(1.0);
    let g = (v - 1.0).clamp(0.0, 1.0);
    let b = (v - 2.0).clamp(0.0, 1.0);
    Color32::from_rgb(to_u8(r), to_u8(g), to_u8(b))
}

/// |render - truth| per pixel as a heat map, and the frame's PSNR against
/// the photograph. A coarse frame is compared with the photograph's pixel
/// at the centre of each coarse pixel.
fn error_image(frame: &RenderedFrame, truth: &GroundTruth) -> (egui::ColorImage, Option<f32>) {
    let (w, h) = (frame.width.max(1), frame.height.max(1));
    let mut squared_sum = 0.0f64;
    let mut pixels = Vec::with_capacity((w * h) as usize);
    for y in 0..h {
        let ty = (((y as f32 + 0.5) * truth.height as f32 / h as f32) as u32).min(truth.height - 1);
        for x in 0..w {
            let tx =
                (((x as f32 + 0.5) * truth.width as f32 / w as f32) as u32).min(truth.width - 1);
            let rendered = frame
                .pixels
                .get((y * w + x) as usize)
                .map_or([0.0; 3], |p| p.rgb);
            let target = truth.rgb[(ty * truth.width + tx) as usize];
            let mut absolute = 0.0;
            for c in 0..3 {
                let d = rendered[c] - target[c];
                absolute += d.abs();
                squared_sum += (d * d) as f64;
            }
            pixels.push(heat_colour(absolute / 3.0 / ERROR_SCALE));
        }
    }
    let mse = squared_sum / (3 * w * h) as f64;
    let psnr = (mse > 0.0).then(|| (-10.0 * mse.log10()) as f32);
    (
        egui::ColorImage::new([w as usize, h as usize], pixels),
        psnr,
    )
}

/// The render scales offered, as instant-ngp's testbed offers a render
/// resolution factor: below 1 for speed (the texture is stretched to the
/// viewport), 2 for supersampling.
pub const RENDER_SCALES: [f32; 4] = [0.25, 0.5, 1.0, 2.0];

/// The size to render a viewport of `width × height` pixels at: `scale`
/// times each side, whatever the training photographs' size, so that
/// moving closer shows what the field holds between their pixels (NeRF's
/// aliasing, Mip-NeRF's answer to it). The longer side stays within the
/// largest viewport the training thread accepts.
pub fn render_size(width: u32, height: u32, scale: f32) -> (u32, u32) {
    let longest = width.max(height).max(1) as f32;
    let scale = scale.min(MAX_RENDER_SIDE as f32 / longest);
    let side = |s: u32| ((s as f32 * scale).round() as u32).max(1);
    (side(width), side(height))
}

/// The longest side rendered (the training thread refuses larger ones).
const MAX_RENDER_SIDE: u32 = 8192;

/// The largest rect of aspect `width / height` centred in `outer`.
fn fit(outer: Rect, width: f32, height: f32) -> Rect {
    if width <= 0.0 || height <= 0.0 {
        return outer;
    }
    let scale = (outer.width() / width).min(outer.height() / height);
    Rect::from_center_size(outer.center(), Vec2::new(width * scale, height * scale))
}

/// Text on a dark backdrop, readable over any render (white backgrounds
/// included).
fn label(painter: &egui::Painter, at: Pos2, anchor: egui::Align2, text: &str, colour: Color32) {
    let galley = painter.layout_no_wrap(text.to_string(), egui::FontId::proportional(13.0), colour);
    let rect = anchor.anchor_size(at, galley.size());
    painter.rect_filled(rect.expand(3.0), 3, Color32::from_black_alpha(160));
    painter.galley(rect.min, galley, colour);
}

/// Snaps the camera to the training view after (`forward`) or before the
/// current one.
pub fn step_training_view(ui_state: &mut ViewerUi, forward: bool) {
    let Some(scene) = ui_state.scene.as_ref().map(|s| s.scene.clone()) else {
        return;
    };
    let Some(view) = step_view(ui_state.viewport.view_index, scene.train.len(), forward) else {
        return;
    };
    snap_to_view(ui_state, &scene, view);
}

fn snap_to_view(ui_state: &mut ViewerUi, scene: &Scene, view: usize) {
    let Some(frame) = scene.train.get(view) else {
        return;
    };
    if let Some(camera) = &mut ui_state.camera {
        camera.snap_to(&frame.camera);
        ui_state.viewport.view_index = Some(view);
        ui_state.viewport.snapped = true;
        // Snapping is not a drag: the camera did not "move" for the frame log.
        ui_state.viewport.previous_camera = Some(camera.clone());
    }
}

/// Camera input for one frame; true if the user (or the auto-orbit) moved
/// the camera with a continuous gesture.
fn handle_input(
    camera: &mut ViewCamera,
    response: &egui::Response,
    ctx: &egui::Context,
    auto_orbit: bool,
) -> bool {
    let mut moving = false;
    let delta = response.drag_delta();
    let dt = ctx.input(|i| i.stable_dt).clamp(0.0, 0.1);
    match camera.navigation() {
        Navigation::Orbit => {
            if response.dragged_by(PointerButton::Primary) && delta != Vec2::ZERO {
                camera.orbit(delta.x, delta.y);
                moving = true;
            }
            if (response.dragged_by(PointerButton::Secondary)
                || response.dragged_by(PointerButton::Middle))
                && delta != Vec2::ZERO
            {
                camera.pan(delta.x, delta.y, response.rect.height());
                moving = true;
            }
        }
        Navigation::Fly => {
            if response.dragged() && delta != Vec2::ZERO {
                camera.look(delta.x, delta.y);
                moving = true;
            }
            if !ctx.egui_wants_keyboard_input() {
                let input = ctx.input(|i| {
                    let axis = |plus: egui::Key, minus: egui::Key| {
                        i.key_down(plus) as i32 as f32 - i.key_down(minus) as i32 as f32
                    };
                    FlyInput {
                        forward: axis(egui::Key::W, egui::Key::S),
                        right: axis(egui::Key::D, egui::Key::A),
                        up: axis(egui::Key::E, egui::Key::Q),
                        fast: i.modifiers.shift,
                    }
                });
                if input.forward != 0.0 || input.right != 0.0 || input.up != 0.0 {
                    camera.fly(input, dt);
                    moving = true;
                }
            }
        }
    }
    if response.hovered() {
        let scroll = ctx.input(|i| i.smooth_scroll_delta.y);
        if scroll != 0.0 {
            camera.zoom(scroll);
            moving = true;
        }
    }
    if auto_orbit {
        camera.orbit(AUTO_ORBIT_POINTS_PER_SECOND * dt.max(1.0 / 240.0), 0.0);
        moving = true;
    }
    moving
}

/// Draws the viewport and sends a render request when what it should show
/// changed.
pub fn show(ui_state: &mut ViewerUi, ui: &mut egui::Ui) {
    let ctx = ui.ctx().clone();
    let (rect, response) = ui.allocate_exact_size(ui.available_size(), Sense::click_and_drag());
    let painter = ui.painter_at(rect);
    painter.rect_filled(rect, 0, Color32::from_gray(24));

    let Some(scene) = ui_state.scene.as_ref().map(|s| s.scene.clone()) else {
        ui_state.viewport.moving = false;
        let text = match (&ui_state.opening, &ui_state.scene_error) {
            (Some(source), _) => format!("Opening {}…", super::describe_source(source)),
            (None, Some(error)) => error.clone(),
            (None, None) => {
                "No scene: open one from the File menu, or drop a folder here".to_string()
            }
        };
        painter.text(
            rect.center(),
            egui::Align2::CENTER_CENTER,
            text,
            egui::FontId::proportional(16.0),
            Color32::LIGHT_GRAY,
        );
        return;
    };

    // Input first, so this frame's request carries this frame's camera.
    let auto_orbit = ui_state.auto_orbit;
    let moving = match &mut ui_state.camera {
        Some(camera) => handle_input(camera, &response, &ctx, auto_orbit),
        None => false,
    } || ui_state.path_editor.driving;
    ui_state.viewport.moving = moving;
    if let Some(camera) = &ui_state.camera {
        if ui_state
            .viewport
            .previous_camera
            .as_ref()
            .is_some_and(|previous| previous != camera)
        {
            ui_state.viewport.snapped = false;
        }
        ui_state.viewport.previous_camera = Some(camera.clone());
    }

    // Comparing wants the render from the photograph's own camera, at its
    // own size, so pixels line up one to one.
    let comparing = ui_state.viewport.compare != CompareMode::Off && ui_state.viewport.snapped;
    let view = ui_state.viewport.view_index.filter(|_| comparing);
    if let Some(view) = view {
        ui_state.viewport.load_truth(&ctx, &scene, view);
    }
    let pixels_per_point = ctx.pixels_per_point();
    let physical = |value: f32| (value * pixels_per_point).round().max(0.0) as u32;
    ui_state.viewport.rect_pixels = Some([
        physical(rect.min.x),
        physical(rect.min.y),
        physical(rect.width()),
        physical(rect.height()),
    ]);
    let camera = match (view.and_then(|v| scene.train.get(v)), &ui_state.camera) {
        (Some(frame), _) => Some(frame.camera),
        (None, Some(camera)) => {
            let (width, height) = render_size(
                (rect.width() * pixels_per_point).round() as u32,
                (rect.height() * pixels_per_point).round() as u32,
                ui_state.viewport.render_scale,
            );
            (width > 0 && height > 0).then(|| camera.camera(width, height))
        }
        (None, None) => None,
    };
    if let Some(camera) = camera {
        // Comparing with the photograph (ground truth, error map, PSNR)
        // needs the render's pixels: the gpu engine, which otherwise draws
        // into a texture on the GPU, then reads its render back to the CPU.
        let needs_pixels = view.is_some();
        let key = (
            camera,
            ui_state.mode,
            moving,
            ui_state.active_model,
            needs_pixels,
        );
        if ui_state.viewport.last_request.as_ref() != Some(&key) {
            ui_state.viewport.requested_generation += 1;
            ui_state.viewport.requested_view = view;
            ui_state.viewport.last_request = Some(key);
            ui_state.send(Command::Render(RenderRequest {
                generation: ui_state.viewport.requested_generation,
                camera,
                mode: ui_state.mode,
                moving,
                needs_pixels,
            }));
        }
    }

    draw_images(ui_state, &painter, rect, comparing);
    // The crop box over the picture (not over a side-by-side comparison,
    // whose two pictures are placed differently).
    if let (Some(camera), Some(crop), false) = (camera, ui_state.crop.drawn(), comparing) {
        let k = camera.intrinsics;
        let image = fit(rect, k.width as f32, k.height as f32);
        super::overlay::draw_crop_box(&painter, &camera, image, &crop);
    }
    if !comparing {
        super::path_overlay::draw(ui_state, &painter, rect);
    }

    // What is on screen, in a corner: the model, the step the picture
    // shows and how far training has gone on since, and its resolution.
    let lag = ui_state.shown_lag_seconds();
    let trained_to = ui_state
        .viewport
        .shown
        .and_then(|shown| ui_state.latest_stats(shown.model))
        .map(|stats| stats.step);
    let state = &ui_state.viewport;
    let caption = match state.shown {
        Some(shown) => {
            let mut resolution = if shown.downscale > 1 {
                format!("1/{} resolution", shown.downscale)
            } else {
                "full resolution".to_string()
            };
            if !shown.complete {
                // Its lower rows still show the picture before it.
                resolution.push_str(", drawing");
            }
            let behind = match (trained_to, lag) {
                (Some(step), Some(lag)) if step > shown.step => {
                    format!(" (trained to {step}, {lag:.1} s of training on)")
                }
                _ => String::new(),
            };
            format!(
                "{} · step {}{behind} · {resolution} · {}×{}",
                shown.model.name(),
                shown.step,
                shown.width,
                shown.height
            )
        }
        None => "waiting for the first frame…".to_string(),
    };
    label(
        &painter,
        rect.left_top() + Vec2::new(8.0, 6.0),
        egui::Align2::LEFT_TOP,
        &caption,
        Color32::from_gray(230),
    );
    if state.compare != CompareMode::Off && !state.snapped {
        label(
            &painter,
            rect.left_bottom() + Vec2::new(8.0, -6.0),
            egui::Align2::LEFT_BOTTOM,
            "Compare: snap to a training view (Prev view / Next view in the panel)",
            Color32::from_rgb(240, 200, 120),
        );
    }
}

fn draw_images(ui_state: &ViewerUi, painter: &egui::Painter, rect: Rect, comparing: bool) {
    let state = &ui_state.viewport;
    let Some(texture) = &state.image else {
        return;
    };
    let full_uv = Rect::from_min_max(Pos2::ZERO, Pos2::new(1.0, 1.0));
    let [tw, th] = texture.size().map(|s| s as f32);
    let other = match state.compare_with {
        CompareWith::GroundTruth => state.truth.as_ref().map(|t| &t.texture),
        CompareWith::Error => state.error_texture.as_ref(),
    };
    let caption = |painter: &egui::Painter, at: Pos2, text: &str| {
        label(
            painter,
            at,
            egui::Align2::CENTER_BOTTOM,
            text,
            Color32::from_gray(230),
        );
    };
    let other_name = match state.compare_with {
        CompareWith::GroundTruth => "ground truth".to_string(),
        CompareWith::Error => format!("|render - truth| (0 to {ERROR_SCALE})"),
    };
    match (comparing, state.compare, other) {
        (true, CompareMode::SideBySide, Some(other)) => {
            let half = rect.width() / 2.0;
            let left = Rect::from_min_size(rect.min, Vec2::new(half, rect.height()));
            let right = left.translate(Vec2::new(half, 0.0));
            let left_image = fit(left.shrink(4.0), tw, th);
            let [ow, oh] = other.size().map(|s| s as f32);
            let right_image = fit(right.shrink(4.0), ow, oh);
            painter.image(texture.id(), left_image, full_uv, Color32::WHITE);
            painter.image(other.id(), right_image, full_uv, Color32::WHITE);
            caption(
                painter,
                left_image.center_bottom() - Vec2::new(0.0, 4.0),
                "render",
            );
            caption(
                painter,
                right_image.center_bottom() - Vec2::new(0.0, 4.0),
                &other_name,
            );
        }
        (true, CompareMode::Split, Some(other)) => {
            let image = fit(rect, tw, th);
            painter.image(texture.id(), image, full_uv, Color32::WHITE);
            let split = state.split.clamp(0.0, 1.0);
            let x = image.left() + split * image.width();
            let right = Rect::from_min_max(Pos2::new(x, image.top()), image.max);
            let uv = Rect::from_min_max(Pos2::new(split, 0.0), Pos2::new(1.0, 1.0));
            painter.image(other.id(), right, uv, Color32::WHITE);
            painter.line_segment(
                [Pos2::new(x, image.top()), Pos2::new(x, image.bottom())],
                egui::Stroke::new(2.0, Color32::YELLOW),
            );
            caption(
                painter,
                Pos2::new((image.left() + x) / 2.0, image.bottom() - 4.0),
                "render",
            );
            caption(
                painter,
                Pos2::new((x + image.right()) / 2.0, image.bottom() - 4.0),
                &other_name,
            );
        }
        _ => {
            painter.image(texture.id(), fit(rect, tw, th), full_uv, Color32::WHITE);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn heat_colour_runs_black_to_white() {
        assert_eq!(heat_colour(0.0), Color32::BLACK);
        assert_eq!(heat_colour(1.0), Color32::WHITE);
        assert_eq!(heat_colour(1.0 / 3.0), Color32::from_rgb(255, 0, 0));
        assert_eq!(heat_colour(7.0), Color32::WHITE);
    }

    #[test]
    fn fit_keeps_aspect_and_centres() {
        let outer = Rect::from_min_size(Pos2::ZERO, Vec2::new(200.0, 100.0));
        let inner = fit(outer, 50.0, 50.0);
        assert_eq!(inner.size(), Vec2::new(100.0, 100.0));
        assert_eq!(inner.center(), outer.center());
    }

    #[test]
    fn depth_range_ignores_empty_pixels() {
        let pixel = |opacity: f32, depth: f32| RenderedPixel {
            rgb: [0.0; 3],
            opacity,
            depth,
        };
        // Depth is accumulated as Σ wᵢ tᵢ, so the surface depth is depth / opacity.
        let pixels = [pixel(1.0, 2.0), pixel(0.8, 4.0), pixel(0.1, 100.0)];
        assert_eq!(depth_range(&pixels), (2.0, 5.0));
    }
}
