//! The view: the levels of the resting camera's picture, drawn chunk by
//! chunk (or band by band into textures on the gpu engine) between
//! training steps, the first sized from the model's render cost, the rest
//! refining to full resolution; a redraw slower than the refresh budget is
//! sent band by band as it goes. [`Viewing`] owns the view, the share of
//! the time it gets ([`Ledger`], [`Balance`]) and the textures it is drawn
//! into.

use std::time::{Duration, Instant};

use crate::engine::gpu::GpuContext;
use crate::engine::gpu::render::render_target;
use crate::field::ModelKind;
use crate::metrics::WHITE;
use crate::model::{RenderMode, TextureRender};
use crate::scene::Camera;
use crate::session::progressive::{Band, LevelRender, draw_band_to_texture, level_camera};
use crate::session::protocol::{Balance, Event, GpuFrame, RenderRequest, RenderedFrame};
use crate::session::schedule::{
    Ledger, ScheduleTrace, first_level, next_finer_level, refresh_budget,
};

use super::training::ModelSlot;
use super::{Outbox, UiGone};

/// A moving request counts as moving for this long after it arrived: the UI
/// sends one per frame while the user drags, so a gap this long means the
/// camera came to rest even if no resting request followed.
const MOVING_GRACE: Duration = Duration::from_millis(300);

/// The largest training share honoured while a view still refines: at 1.0
/// the viewport would never sharpen.
const MAX_TRAINING_SHARE: f32 = 0.95;

/// Textures the gpu engine's view is drawn into, kept for reuse (levels of
/// several sizes, two of each size that is shown).
const MAX_KEPT_TEXTURES: usize = 8;

/// The largest viewport side accepted (8K); anything above is a bad
/// request, refused before it allocates gigabytes of pixels.
const MAX_VIEWPORT_SIDE: u32 = 8_192;

/// What the viewport asked for and how far it has been drawn.
struct View {
    request: RenderRequest,
    received: Instant,
    /// The level being drawn.
    job: Option<LevelJob>,
    /// The last finished level of this camera and model (re-sent when the
    /// same camera is requested again).
    shown: Option<Shown>,
}

/// A finished level on screen.
struct Shown {
    picture: Picture,
    /// The model revision the level began from.
    revision: u64,
    downscale: u32,
}

/// A level of the view being drawn.
struct LevelJob {
    downscale: u32,
    /// The model drawn, its step and training seconds when the level began.
    model: ModelKind,
    step: u32,
    train_seconds: f64,
    revision: u64,
    /// Render seconds spent on it so far.
    seconds: f64,
    /// Whether it may be sent before its last row over the rest of the
    /// picture on screen (a redraw of that level, or a finer level over it).
    over_shown: bool,
    /// Whether the rows not drawn yet hold the picture on screen (copied
    /// when the level is first sent unfinished).
    holds_shown_rest: bool,
    /// Render seconds spent on it when it was last sent unfinished.
    seconds_at_last_send: f64,
    draw: LevelDraw,
}

enum LevelDraw {
    /// Chunks of rays composited on the host, sent as pixels.
    Pixels(LevelRender),
    /// Bands of rows drawn by the gpu engine into a texture on the
    /// window's device.
    Texture(TextureLevel),
}

/// A level drawn into a texture band by band, so that a level slower
/// than a unit of work (NeRF on lavapipe: seconds) never holds the thread.
struct TextureLevel {
    camera: Camera,
    texture: wgpu::Texture,
    /// Rows above this one are drawn.
    next_row: u32,
}

/// A finished frame of the view, as sent.
enum Picture {
    /// Pixels read back to the CPU (the cpu engine, or a request that
    /// needs the pixels).
    Pixels(RenderedFrame),
    /// A texture on the device shared with the window.
    Texture(GpuFrame),
}

/// Textures the view is drawn into, kept for reuse: level sizes change
/// with the camera and the model's cost, and bands come in a few sizes.
#[derive(Default)]
struct TexturePool {
    /// Least recently used first.
    kept: Vec<wgpu::Texture>,
    /// The textures of the last two frames sent: the window may still
    /// show either, so neither is drawn into.
    sent: [Option<wgpu::Texture>; 2],
}

/// A view with something to draw, as the loop sees it when it picks its
/// next unit of work.
pub(super) struct Pending {
    /// Nothing of this camera and model is on screen yet.
    pub(super) first_level: bool,
    /// While the camera moves: how long until it counts as resting.
    pub(super) moving_for: Option<Duration>,
}

/// The view, its part of the thread's time, and the textures it is drawn
/// into.
pub(super) struct Viewing {
    view: Option<View>,
    /// Training's part of the time while the camera rests.
    ledger: Ledger,
    balance: Balance,
    /// True when the engine trains on the window's own device
    /// ([`super::WorkerOptions::gpu_device`]): the view is then drawn into
    /// textures there.
    textures_shared: bool,
    /// Textures the view's levels and bands are drawn into.
    textures: TexturePool,
}

impl View {
    fn moving(&self) -> bool {
        self.request.moving && self.received.elapsed() < MOVING_GRACE
    }

    /// Starts again from a first level: the model shown changed (another
    /// model, a reset, a loaded checkpoint), so neither the level in
    /// progress nor the refinement so far is of the model now shown. The
    /// window keeps the old picture until the first level comes.
    fn restart(&mut self) {
        self.job = None;
        self.shown = None;
    }
}

impl LevelJob {
    fn pixels(&self) -> usize {
        match &self.draw {
            LevelDraw::Pixels(render) => render.width() as usize * render.height() as usize,
            LevelDraw::Texture(level) => {
                level.camera.intrinsics.width as usize * level.camera.intrinsics.height as usize
            }
        }
    }

    fn is_done(&self) -> bool {
        match &self.draw {
            LevelDraw::Pixels(render) => render.is_done(),
            LevelDraw::Texture(level) => level.next_row >= level.camera.intrinsics.height,
        }
    }

    /// The level as it stands, as the answer to `request`: its pixels
    /// (those drawn, and below them what [`LevelRender::fill_rest_from`]
    /// put there) or its texture; `complete` once its last row is drawn.
    fn picture(&self, request: &RenderRequest, complete: bool) -> Picture {
        match &self.draw {
            LevelDraw::Pixels(render) => Picture::Pixels(RenderedFrame {
                generation: request.generation,
                model: self.model,
                step: self.step,
                train_seconds: self.train_seconds,
                downscale: self.downscale,
                complete,
                width: render.width(),
                height: render.height(),
                mode: request.mode,
                pixels: render.pixels_so_far().to_vec(),
            }),
            LevelDraw::Texture(level) => Picture::Texture(GpuFrame {
                generation: request.generation,
                model: self.model,
                step: self.step,
                train_seconds: self.train_seconds,
                downscale: self.downscale,
                complete,
                width: level.camera.intrinsics.width,
                height: level.camera.intrinsics.height,
                mode: request.mode,
                texture: level.texture.clone(),
            }),
        }
    }
}

impl Picture {
    /// The picture as an event for the window.
    fn event(&self) -> Event {
        match self {
            Picture::Pixels(frame) => Event::Frame(frame.clone()),
            Picture::Texture(frame) => Event::GpuFrame(frame.clone()),
        }
    }

    /// Whether this picture answers `request` (of the same camera): pixels
    /// are shown in any mode, while a texture holds one mode's colours.
    fn answers(&self, request: &RenderRequest, draws_to_texture: bool) -> bool {
        match self {
            Picture::Pixels(_) => !draws_to_texture,
            Picture::Texture(frame) => draws_to_texture && frame.mode == request.mode,
        }
    }

    /// The picture as the answer to `request`, as an event.
    fn resend(&mut self, request: &RenderRequest) -> Event {
        match self {
            Picture::Pixels(frame) => {
                frame.generation = request.generation;
                frame.mode = request.mode;
                Event::Frame(frame.clone())
            }
            Picture::Texture(frame) => {
                frame.generation = request.generation;
                Event::GpuFrame(frame.clone())
            }
        }
    }
}

impl TexturePool {
    /// A `width × height` texture no frame the window may still show
    /// holds: a kept one, else a new one.
    fn take(&mut self, context: &GpuContext, width: u32, height: u32) -> wgpu::Texture {
        let sent = &self.sent;
        let free = self.kept.iter().position(|t| {
            (t.width(), t.height()) == (width, height) && !sent.iter().flatten().any(|s| s == t)
        });
        let texture = match free {
            Some(index) => self.kept.remove(index),
            None => render_target(&context.device, width, height),
        };
        self.kept.push(texture.clone());
        if self.kept.len() > MAX_KEPT_TEXTURES
            && let Some(oldest) = self
                .kept
                .iter()
                .position(|t| !self.sent.iter().flatten().any(|s| s == t))
        {
            self.kept.remove(oldest);
        }
        texture
    }

    /// `texture` went to the window in a frame.
    fn sent(&mut self, texture: &wgpu::Texture) {
        self.sent = [Some(texture.clone()), self.sent[0].take()];
    }
}

/// Draws up to `rows` more rows of `level` (at least one) and returns how
/// many: the whole level at once when one band covers it, else through a
/// texture of the band's size ([`draw_band_to_texture`]).
fn draw_band(
    gpu: &dyn TextureRender,
    context: &GpuContext,
    level: &mut TextureLevel,
    rows: u32,
    mode: RenderMode,
    textures: &mut TexturePool,
) -> Result<u32, String> {
    let k = level.camera.intrinsics;
    let rows = rows.clamp(1, k.height.saturating_sub(level.next_row).max(1));
    if level.next_row == 0 && rows == k.height {
        gpu.render_to_texture(&level.camera, mode, WHITE, &level.texture)?;
    } else {
        let band = textures.take(context, k.width, rows);
        draw_band_to_texture(
            gpu,
            context,
            Band {
                camera: &level.camera,
                first: level.next_row,
                mode,
                background: WHITE,
            },
            &band,
            &level.texture,
        )?;
    }
    level.next_row += rows;
    Ok(rows)
}

/// Copies the rows of `shown` that `level` has not drawn yet into its
/// texture, so that sent before its last band it shows the old picture
/// below the new rows; false when the two differ in size.
fn copy_rest_of_level(context: &GpuContext, level: &TextureLevel, shown: &wgpu::Texture) -> bool {
    let (width, height) = (level.texture.width(), level.texture.height());
    if (shown.width(), shown.height()) != (width, height) {
        return false;
    }
    let first = level.next_row.min(height);
    if first == height {
        return true;
    }
    let origin = wgpu::Origin3d {
        x: 0,
        y: first,
        z: 0,
    };
    let mut encoder = context.device.create_command_encoder(&Default::default());
    encoder.copy_texture_to_texture(
        wgpu::TexelCopyTextureInfo {
            origin,
            ..shown.as_image_copy()
        },
        wgpu::TexelCopyTextureInfo {
            origin,
            ..level.texture.as_image_copy()
        },
        wgpu::Extent3d {
            width,
            height: height - first,
            depth_or_array_layers: 1,
        },
    );
    context.queue.submit([encoder.finish()]);
    true
}

impl Viewing {
    /// No view yet; `textures_shared` when the engine trains on the
    /// window's device.
    pub(super) fn new(textures_shared: bool) -> Self {
        Self {
            view: None,
            ledger: Ledger::default(),
            balance: Balance::default(),
            textures_shared,
            textures: TexturePool::default(),
        }
    }

    /// Training's share of the time while the view refines.
    pub(super) fn training_share(&self) -> f64 {
        self.balance.training_share.clamp(0.0, MAX_TRAINING_SHARE) as f64
    }

    /// Sets the balance the window asked for (a share that is not a
    /// number gives the default).
    pub(super) fn set_balance(&mut self, balance: Balance) {
        let share = if balance.training_share.is_finite() {
            balance.training_share.clamp(0.0, 1.0)
        } else {
            Balance::default().training_share
        };
        self.balance = Balance {
            training_share: share,
        };
    }

    /// Whether training is due for its share of the time.
    pub(super) fn training_due(&self) -> bool {
        self.ledger.training_due(self.training_share())
    }

    /// Whether the camera moves (then the ledger keeps no accounts).
    pub(super) fn camera_moving(&self) -> bool {
        self.view.as_ref().is_some_and(View::moving)
    }

    /// A training step of `seconds`, while the camera rests.
    pub(super) fn record_training(&mut self, seconds: f64) {
        if !self.camera_moving() {
            self.ledger.record_training(seconds);
        }
    }

    /// `seconds` of the view's kind of work (drawing, evaluating), while
    /// the camera rests.
    pub(super) fn record_other(&mut self, seconds: f64) {
        if !self.camera_moving() {
            self.ledger.record_other(seconds);
        }
    }

    /// The model shown changed: the view starts again from a first level.
    pub(super) fn restart(&mut self) {
        if let Some(view) = self.view.as_mut() {
            view.restart();
        }
    }

    /// The camera belongs to a scene that is gone; the window sends a new
    /// one.
    pub(super) fn forget_camera(&mut self) {
        self.view = None;
    }

    /// The view's work, if it has any, with `slot` the shown model's.
    pub(super) fn pending(&self, slot: Option<&ModelSlot>) -> Option<Pending> {
        let view = self.view.as_ref()?;
        if view.job.is_none() && self.next_level(slot).is_none() {
            return None;
        }
        Some(Pending {
            first_level: view.shown.is_none(),
            moving_for: view
                .moving()
                .then(|| MOVING_GRACE.saturating_sub(view.received.elapsed())),
        })
    }

    /// The level the view should draw next (its downscale), if any: a
    /// first level for a camera or model not yet shown; then, once the
    /// camera rests, finer levels up to full resolution, however long
    /// each takes (it is drawn a chunk or band at a time between training
    /// steps, at the view's share of the thread); then, whenever the model
    /// has changed since the shown level began, that level again. A resting
    /// picture never gets coarser: a redraw slower than the refresh budget
    /// is shown band by band as it goes ([`Self::send_partial_if_due`]).
    fn next_level(&self, slot: Option<&ModelSlot>) -> Option<u32> {
        let view = self.view.as_ref()?;
        let slot = slot?;
        let k = view.request.camera.intrinsics;
        let Some(shown) = &view.shown else {
            let cost = slot.cost.seconds_per_pixel();
            return Some(first_level(k.width, k.height, cost));
        };
        if view.moving() {
            // A moving camera gets one level per request.
            return None;
        }
        if let Some(finer) = next_finer_level(k.width, k.height, shown.downscale, 1) {
            return Some(finer);
        }
        (shown.revision != slot.revision).then_some(shown.downscale)
    }

    /// Takes the window's camera; `slot` is the shown model's.
    pub(super) fn set_view(
        &mut self,
        request: RenderRequest,
        slot: Option<&ModelSlot>,
        outbox: &Outbox,
    ) -> Result<(), UiGone> {
        if let Err(problem) = check_camera(&request.camera) {
            return outbox.send(Event::Error(format!(
                "render request {} refused: {problem}",
                request.generation
            )));
        }
        let now = Instant::now();
        let to_texture = self.draws_to_texture(&request, slot);
        let same_picture = self.view.as_ref().is_some_and(|v| {
            v.request.camera == request.camera
                && v.shown
                    .as_ref()
                    .is_none_or(|shown| shown.picture.answers(&request, to_texture))
        });
        if same_picture {
            // The same picture (perhaps in another mode, which only changes
            // how pixels are shown): keep what was drawn and continue.
            let view = self.view.as_mut().expect("checked above");
            if view.request.moving && !request.moving {
                // The camera came to rest: the share starts from here, not
                // from the quarter training had while it moved.
                self.ledger = Ledger::default();
            }
            view.request = request;
            view.received = now;
            if let Some(shown) = view.shown.as_mut() {
                let event = shown.picture.resend(&view.request);
                return outbox.send(event);
            }
            return Ok(());
        }
        // A new camera: the time shared since the last one says nothing
        // about this one's refinement.
        self.ledger = Ledger::default();
        self.view = Some(View {
            request,
            received: now,
            job: None,
            shown: None,
        });
        Ok(())
    }

    /// Draws the view with the shown model's `slot`: one chunk of rays or
    /// band of rows, or the whole level it is on.
    pub(super) fn render_unit(
        &mut self,
        whole_level: bool,
        slot: Option<&mut ModelSlot>,
        gpu: Option<&GpuContext>,
        trace: &mut ScheduleTrace,
        outbox: &Outbox,
    ) -> Result<(), UiGone> {
        let Some(slot) = slot else {
            // No model to draw with (its build failed and was reported).
            self.view = None;
            return Ok(());
        };
        if self.view.as_ref().is_some_and(|v| v.job.is_none()) {
            let Some(downscale) = self.next_level(Some(slot)) else {
                return Ok(());
            };
            let job = self.start_level(downscale, slot, gpu);
            if let Some(view) = self.view.as_mut() {
                view.job = Some(job);
            }
        }
        loop {
            let drawn = self.draw_part(slot, gpu, trace, outbox)?;
            let done = self
                .view
                .as_ref()
                .and_then(|v| v.job.as_ref())
                .is_none_or(LevelJob::is_done);
            if !drawn || done || !whole_level {
                break;
            }
        }
        let finished = self
            .view
            .as_ref()
            .and_then(|v| v.job.as_ref())
            .is_some_and(LevelJob::is_done);
        if finished {
            return self.finish_level(slot, trace, outbox);
        }
        self.send_partial_if_due(gpu, outbox)
    }

    /// Sends a level as far as it has gone, once it has taken another
    /// refresh budget of render seconds: the rows drawn so far over the
    /// rest of the picture on screen (a redraw of that level, or a finer
    /// level over it enlarged). A level that takes many budgets (NeRF at
    /// full resolution on a slow machine) then shows its progress band by
    /// band instead of holding an old picture until its last row. The rest
    /// is copied from the picture on screen only then, so a level within
    /// the budget costs nothing more.
    fn send_partial_if_due(
        &mut self,
        gpu: Option<&GpuContext>,
        outbox: &Outbox,
    ) -> Result<(), UiGone> {
        let budget = refresh_budget(self.training_share());
        let started = Instant::now();
        let Some(view) = self.view.as_mut() else {
            return Ok(());
        };
        let Some(job) = view.job.as_mut() else {
            return Ok(());
        };
        if !job.over_shown || job.seconds - job.seconds_at_last_send < budget.max(1e-3) {
            return Ok(());
        }
        if !job.holds_shown_rest {
            let shown = view.shown.as_ref().map(|shown| &shown.picture);
            job.holds_shown_rest = match (&mut job.draw, shown) {
                (LevelDraw::Pixels(render), Some(Picture::Pixels(frame))) => {
                    render.fill_rest_from(&frame.pixels, frame.width, frame.height)
                }
                (LevelDraw::Texture(level), Some(Picture::Texture(frame))) => match gpu {
                    Some(context) => copy_rest_of_level(context, level, &frame.texture),
                    None => false,
                },
                _ => false,
            };
            if !job.holds_shown_rest {
                // Not the picture's size or kind: drawn to the end instead.
                job.over_shown = false;
                return Ok(());
            }
        }
        job.seconds_at_last_send = job.seconds;
        let picture = job.picture(&view.request, false);
        if let Picture::Texture(frame) = &picture {
            self.textures.sent(&frame.texture);
        }
        let event = picture.event();
        // The copy and the pixels sent are the view's time too.
        let seconds = started.elapsed().as_secs_f64();
        self.ledger.record_other(seconds);
        outbox.send(event)
    }

    /// A level of the view at `downscale` of `slot`'s model as it is now:
    /// into a texture when the window shares the engine's device.
    fn start_level(
        &mut self,
        downscale: u32,
        slot: &ModelSlot,
        gpu: Option<&GpuContext>,
    ) -> LevelJob {
        let view = self.view.as_ref().expect("a view to draw");
        let camera = level_camera(&view.request.camera, downscale);
        let request_to_texture = self.draws_to_texture(&view.request, Some(slot));
        // A redraw of the level on screen, or on the cpu's pixels a finer
        // level over it (its rows not drawn yet show the coarser picture
        // enlarged), may be sent before its last row.
        let over_shown = view.shown.as_ref().is_some_and(|shown| {
            shown.downscale == downscale || matches!(shown.picture, Picture::Pixels(_))
        });
        let draw = if request_to_texture {
            let (width, height) = (camera.intrinsics.width, camera.intrinsics.height);
            let context = gpu.expect("textures need the device");
            LevelDraw::Texture(TextureLevel {
                texture: self.textures.take(context, width, height),
                camera,
                next_row: 0,
            })
        } else {
            LevelDraw::Pixels(LevelRender::new(&view.request.camera, downscale))
        };
        LevelJob {
            downscale,
            model: slot.kind,
            step: slot.trainer.step,
            train_seconds: slot.trainer.train_seconds,
            revision: slot.revision,
            seconds: 0.0,
            over_shown,
            holds_shown_rest: false,
            seconds_at_last_send: 0.0,
            draw,
        }
    }

    /// Draws the next chunk or band of the level in progress; false when
    /// there was nothing to draw.
    fn draw_part(
        &mut self,
        slot: &mut ModelSlot,
        gpu: Option<&GpuContext>,
        trace: &mut ScheduleTrace,
        outbox: &Outbox,
    ) -> Result<bool, UiGone> {
        let Some(view) = self.view.as_mut() else {
            return Ok(false);
        };
        let Some(job) = view.job.as_mut() else {
            return Ok(false);
        };
        let started = Instant::now();
        let (rays, failure) = match &mut job.draw {
            LevelDraw::Pixels(render) => (
                render.render_chunk(slot.trainer.model.as_ref(), slot.pacer.chunk_rays(), WHITE),
                None,
            ),
            LevelDraw::Texture(level) => match (slot.trainer.model.texture_render(), gpu) {
                (Some(model), Some(context)) => {
                    let width = level.camera.intrinsics.width.max(1);
                    // Whole rows, as many as the chunk's rays; not capped as
                    // chunks of pixels are (a real GPU draws a whole level in
                    // one band).
                    let rays = slot.pacer.uncapped_chunk_rays();
                    let rows = u32::try_from(rays / width as usize).unwrap_or(u32::MAX);
                    match draw_band(
                        model,
                        context,
                        level,
                        rows,
                        view.request.mode,
                        &mut self.textures,
                    ) {
                        Ok(drawn) => ((drawn * width) as usize, None),
                        Err(error) => (0, Some(error)),
                    }
                }
                _ => (0, Some("the model cannot draw into textures".to_string())),
            },
        };
        let seconds = started.elapsed().as_secs_f64();
        if let Some(error) = failure {
            // Pixels still work: this level and every later one go through
            // the CPU.
            self.textures_shared = false;
            job.draw = LevelDraw::Pixels(LevelRender::new(&view.request.camera, job.downscale));
            job.over_shown = false;
            outbox.send(Event::Error(format!(
                "drawing the view on the gpu failed ({error}); the view now comes \
                 through the CPU"
            )))?;
            return Ok(true);
        }
        slot.pacer.record(rays, seconds);
        job.seconds += seconds;
        let downscale = job.downscale;
        if !view.moving() {
            self.ledger.record_other(seconds);
        }
        trace.add_rendering(downscale, seconds, false);
        Ok(true)
    }

    /// Sends the finished level and keeps it as what is shown.
    fn finish_level(
        &mut self,
        slot: &mut ModelSlot,
        trace: &mut ScheduleTrace,
        outbox: &Outbox,
    ) -> Result<(), UiGone> {
        let Some(view) = self.view.as_mut() else {
            return Ok(());
        };
        let Some(job) = view.job.take() else {
            return Ok(());
        };
        slot.cost.record(job.pixels(), job.seconds);
        trace.add_rendering(job.downscale, 0.0, true);
        let picture = job.picture(&view.request, true);
        if let Picture::Texture(frame) = &picture {
            self.textures.sent(&frame.texture);
        }
        let event = picture.event();
        view.shown = Some(Shown {
            picture,
            revision: job.revision,
            downscale: job.downscale,
        });
        outbox.send(event)
    }

    /// Whether `request` is answered with a texture on the shared device,
    /// `slot` being the shown model's.
    fn draws_to_texture(&self, request: &RenderRequest, slot: Option<&ModelSlot>) -> bool {
        self.textures_shared
            && !request.needs_pixels
            && slot.is_some_and(|s| s.trainer.model.texture_render().is_some())
    }
}

/// Why a camera cannot be rendered, if it cannot.
fn check_camera(camera: &Camera) -> Result<(), String> {
    let k = camera.intrinsics;
    if k.width == 0 || k.height == 0 || k.width > MAX_VIEWPORT_SIDE || k.height > MAX_VIEWPORT_SIDE
    {
        return Err(format!(
            "the viewport is {}×{} pixels (each side must be 1 to {MAX_VIEWPORT_SIDE})",
            k.width, k.height
        ));
    }
    let focal_ok = [k.fx, k.fy].iter().all(|f| f.is_finite() && *f > 0.0);
    let centre_ok = k.cx.is_finite() && k.cy.is_finite();
    if !focal_ok || !centre_ok {
        return Err(format!(
            "the intrinsics are not usable (fx {}, fy {}, cx {}, cy {})",
            k.fx, k.fy, k.cx, k.cy
        ));
    }
    if !camera
        .camera_to_world
        .to_cols_array()
        .iter()
        .all(|v| v.is_finite())
    {
        return Err("the camera pose holds a non-finite number".into());
    }
    Ok(())
}

#[cfg(test)]
#[path = "view_tests.rs"]
mod tests;
