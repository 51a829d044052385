//! The view: the levels of the resting camera's picture, drawn chunk by
//! chunk (or band by band into textures on the gpu engine), sized from the
//! model's render cost, given up when they overrun their budget.

use super::*;

/// Textures the view is drawn into, kept for reuse: level sizes change
/// with the camera and the model's cost, and bands come in a few sizes.
#[derive(Default)]
pub(super) struct TexturePool {
    /// Least recently used first.
    kept: Vec<wgpu::Texture>,
    /// The textures of the last two frames sent: the window may still
    /// show either, so neither is drawn into.
    sent: [Option<wgpu::Texture>; 2],
}

impl View {
    pub(super) fn moving(&self) -> bool {
        self.request.moving && self.received.elapsed() < MOVING_GRACE
    }

    /// Starts again from a first level: the model shown changed (another
    /// model, a reset, a loaded checkpoint), so neither the level in
    /// progress nor the refinement so far is of the model now shown. The
    /// window keeps the old picture until the first level comes.
    pub(super) fn restart(&mut self) {
        self.job = None;
        self.shown = None;
    }
}

impl LevelJob {
    pub(super) fn pixels(&self) -> usize {
        match &self.draw {
            LevelDraw::Pixels(render) => render.width() as usize * render.height() as usize,
            LevelDraw::Texture(level) => {
                level.camera.intrinsics.width as usize * level.camera.intrinsics.height as usize
            }
        }
    }

    pub(super) fn is_done(&self) -> bool {
        match &self.draw {
            LevelDraw::Pixels(render) => render.is_done(),
            LevelDraw::Texture(level) => level.next_row >= level.camera.intrinsics.height,
        }
    }

    /// Pixels drawn so far.
    pub(super) fn drawn(&self) -> usize {
        match &self.draw {
            LevelDraw::Pixels(render) => render.rendered(),
            LevelDraw::Texture(level) => {
                level.next_row as usize * level.camera.intrinsics.width as usize
            }
        }
    }

    /// True when the level has taken its whole `budget` of render seconds
    /// with a tenth or more still to draw: the cost was misjudged. Early in
    /// NeRF's training the cost of a pixel rises several times over within
    /// a few steps (on lego_400, ~90 µs at step 7 to ~470 µs at step 15) as
    /// the occupancy grid fills, and the rows drawn first, mostly
    /// background, understate the rest: a level judged by its first half
    /// ran to 3.4 s of a 1 s budget and held a 20 s old picture on screen.
    pub(super) fn overruns(&self, budget: f64) -> bool {
        let (drawn, pixels) = (self.drawn(), self.pixels());
        self.may_give_up && drawn > 0 && 10 * drawn < 9 * pixels && self.seconds > budget
    }
}

impl Picture {
    /// Whether this picture answers `request` (of the same camera): pixels
    /// are shown in any mode, while a texture holds one mode's colours.
    pub(super) fn answers(&self, request: &RenderRequest, draws_to_texture: bool) -> bool {
        match self {
            Picture::Pixels(_) => !draws_to_texture,
            Picture::Texture(frame) => draws_to_texture && frame.mode == request.mode,
        }
    }

    /// The picture as the answer to `request`, as an event.
    pub(super) fn resend(&mut self, request: &RenderRequest) -> Event {
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
    pub(super) fn take(&mut self, context: &GpuContext, width: u32, height: u32) -> wgpu::Texture {
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
    pub(super) fn sent(&mut self, texture: &wgpu::Texture) {
        self.sent = [Some(texture.clone()), self.sent[0].take()];
    }
}

/// Draws up to `rows` more rows of `level` (at least one) and returns how
/// many: the whole level at once when one band covers it, else through a
/// texture of the band's size ([`draw_band_to_texture`]).
pub(super) fn draw_band(
    gpu: &dyn crate::train::model::TextureRender,
    context: &GpuContext,
    level: &mut TextureLevel,
    rows: u32,
    mode: crate::render::RenderMode,
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
            &level.camera,
            level.next_row,
            mode,
            WHITE,
            &band,
            &level.texture,
        )?;
    }
    level.next_row += rows;
    Ok(rows)
}

impl Worker {
    /// The level the view should draw next (its downscale), if any: a
    /// first level for a camera or model not yet shown; then, once the
    /// camera rests, finer levels up to the target; then, whenever the
    /// model has changed since the shown level began, the target again.
    /// The target is the finest level whose render fits the refresh
    /// budget while the thread has other work, full resolution otherwise.
    pub(super) fn next_level(&self) -> Option<u32> {
        let view = self.view.as_ref()?;
        let slot = self.slot(self.active)?;
        let k = view.request.camera.intrinsics;
        let cost = slot.cost.seconds_per_pixel();
        let Some(shown) = &view.shown else {
            return Some(first_level(k.width, k.height, cost));
        };
        if view.moving() {
            // A moving camera gets one level per request.
            return None;
        }
        let busy = self.training_active() || self.export.is_some();
        let target = match (busy, cost) {
            (false, _) => 1,
            (true, Some(per_pixel)) => finest_within(
                k.width,
                k.height,
                per_pixel,
                refresh_budget(self.training_share()),
            ),
            // Only after a first level, which measures the cost.
            (true, None) => shown.downscale,
        };
        if shown.downscale > target
            && let Some(finer) = next_finer_level(k.width, k.height, shown.downscale, target)
        {
            return Some(finer);
        }
        (shown.revision != slot.revision).then_some(target)
    }

    pub(super) fn set_view(&mut self, request: RenderRequest) -> Result<(), UiGone> {
        if let Err(problem) = check_camera(&request.camera) {
            return self.send(Event::Error(format!(
                "render request {} refused: {problem}",
                request.generation
            )));
        }
        let now = Instant::now();
        let to_texture = self.draws_to_texture(&request);
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
                return self.send(event);
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
            gave_up_last: false,
        });
        Ok(())
    }

    /// Draws the view: one chunk of rays or band of rows, or the whole
    /// level it is on.
    pub(super) fn render_unit(&mut self, whole_level: bool) -> Result<(), UiGone> {
        if self.slot(self.active).is_none() {
            // No model to draw with (its build failed and was reported).
            self.view = None;
            return Ok(());
        }
        if self.view.as_ref().is_some_and(|v| v.job.is_none()) {
            let Some(downscale) = self.next_level() else {
                return Ok(());
            };
            let job = self.start_level(downscale);
            if let Some(view) = self.view.as_mut() {
                view.job = Some(job);
            }
        }
        loop {
            let drawn = self.draw_part()?;
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
            return self.finish_level();
        }
        // A level far over its budget while training waits on it is given
        // up for a coarser one, sized by what this one has cost so far;
        // whole levels (a new camera's first) are small and always finish.
        let budget = refresh_budget(self.training_share());
        if !whole_level
            && self.training_active()
            && let (Some(view), Some(slot)) = (
                self.view.as_mut(),
                self.slots.iter_mut().find(|s| s.kind == self.active),
            )
            && view.job.as_ref().is_some_and(|job| job.overruns(budget))
        {
            let job = view.job.take().expect("checked");
            slot.cost.replace(job.drawn(), job.seconds);
            view.gave_up_last = true;
        }
        Ok(())
    }

    /// A level of the view at `downscale` of the active model's current
    /// state: into a texture when the window shares the engine's device.
    pub(super) fn start_level(&mut self, downscale: u32) -> LevelJob {
        let view = self.view.as_ref().expect("a view to draw");
        let camera = level_camera(&view.request.camera, downscale);
        let may_give_up = !view.gave_up_last;
        let request_to_texture = self.draws_to_texture(&view.request);
        let slot = self.slot(self.active).expect("checked by the caller");
        let (model, step, train_seconds, revision) = (
            slot.kind,
            slot.trainer.step,
            slot.trainer.train_seconds,
            slot.revision,
        );
        let draw = if request_to_texture {
            let (width, height) = (camera.intrinsics.width, camera.intrinsics.height);
            LevelDraw::Texture(TextureLevel {
                texture: self.texture(width, height),
                camera,
                next_row: 0,
            })
        } else {
            LevelDraw::Pixels(LevelRender::new(&view.request.camera, downscale))
        };
        LevelJob {
            downscale,
            model,
            step,
            train_seconds,
            revision,
            seconds: 0.0,
            may_give_up,
            draw,
        }
    }

    /// Draws the next chunk or band of the level in progress; false when
    /// there was nothing to draw.
    pub(super) fn draw_part(&mut self) -> Result<bool, UiGone> {
        let active = self.active;
        let (Some(slot), Some(view)) = (
            self.slots.iter_mut().find(|s| s.kind == active),
            self.view.as_mut(),
        ) else {
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
            LevelDraw::Texture(level) => {
                let context = self.engine.gpu.as_ref();
                match (slot.trainer.model.texture_render(), context) {
                    (Some(gpu), Some(context)) => {
                        let width = level.camera.intrinsics.width.max(1);
                        // Whole rows, as many as the chunk's rays; not
                        // capped as chunks of pixels are (a real GPU draws
                        // a whole level in one band).
                        let rays = slot.pacer.uncapped_chunk_rays();
                        let rows = u32::try_from(rays / width as usize).unwrap_or(u32::MAX);
                        match draw_band(
                            gpu,
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
                }
            }
        };
        let seconds = started.elapsed().as_secs_f64();
        if let Some(error) = failure {
            // Pixels still work: this level and every later one go through
            // the CPU.
            self.textures_shared = false;
            job.draw = LevelDraw::Pixels(LevelRender::new(&view.request.camera, job.downscale));
            self.send(Event::Error(format!(
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
        self.trace.add_rendering(downscale, seconds, false);
        Ok(true)
    }

    /// Sends the finished level and keeps it as what is shown.
    pub(super) fn finish_level(&mut self) -> Result<(), UiGone> {
        let active = self.active;
        let (Some(slot), Some(view)) = (
            self.slots.iter_mut().find(|s| s.kind == active),
            self.view.as_mut(),
        ) else {
            return Ok(());
        };
        let Some(job) = view.job.take() else {
            return Ok(());
        };
        view.gave_up_last = false;
        slot.cost.record(job.pixels(), job.seconds);
        self.trace.add_rendering(job.downscale, 0.0, true);
        let picture = match job.draw {
            LevelDraw::Pixels(render) => Picture::Pixels(RenderedFrame {
                generation: view.request.generation,
                model: job.model,
                step: job.step,
                train_seconds: job.train_seconds,
                downscale: job.downscale,
                width: render.width(),
                height: render.height(),
                mode: view.request.mode,
                pixels: render.into_pixels(),
            }),
            LevelDraw::Texture(level) => {
                let texture = level.texture;
                self.textures.sent(&texture);
                Picture::Texture(GpuFrame {
                    generation: view.request.generation,
                    model: job.model,
                    step: job.step,
                    train_seconds: job.train_seconds,
                    downscale: job.downscale,
                    width: level.camera.intrinsics.width,
                    height: level.camera.intrinsics.height,
                    mode: view.request.mode,
                    texture,
                })
            }
        };
        let event = match &picture {
            Picture::Pixels(frame) => Event::Frame(frame.clone()),
            Picture::Texture(frame) => Event::GpuFrame(frame.clone()),
        };
        view.shown = Some(Shown {
            picture,
            revision: job.revision,
            downscale: job.downscale,
        });
        self.outbox.send(event)
    }

    /// Whether `request` is answered with a texture on the shared device.
    pub(super) fn draws_to_texture(&self, request: &RenderRequest) -> bool {
        self.textures_shared
            && !request.needs_pixels
            && self
                .slot(self.active)
                .is_some_and(|s| s.trainer.model.texture_render().is_some())
    }

    /// A `width × height` texture to draw a level into.
    pub(super) fn texture(&mut self, width: u32, height: u32) -> wgpu::Texture {
        let context = self.engine.gpu.as_ref().expect("textures need the device");
        self.textures.take(context, width, height)
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
