//! The viewer's view drawn on the device: rounds of the lattice walk, the
//! fields and front-to-back compositing into per-ray state, then the
//! image written into the target texture, without reading pixels back.

use super::*;

impl GpuNgp {
    /// Renders `camera`'s view on the GPU into `target` (Rgba8Unorm, usage
    /// STORAGE_BINDING (| TEXTURE_BINDING to draw it), the camera's size)
    /// in `mode` over `background`: the pixels of
    /// `render::to_image(render_pixels(..))` up to rounding, without
    /// reading the image back. Returns once the work is submitted; the
    /// queue orders it before any later use of `target`.
    pub fn render_to_texture(
        &self,
        camera: &Camera,
        mode: RenderMode,
        background: [f32; 3],
        target: &wgpu::Texture,
    ) -> Result<(), GpuError> {
        let ctx = &self.context;
        let (width, height) = (camera.intrinsics.width, camera.intrinsics.height);
        check_target(target, width, height, wgpu::TextureUsages::STORAGE_BINDING)?;
        let chunk = self.batch_samples;
        if chunk < RAY_GROUP_ALIGN {
            return Err(GpuError::RenderTarget(format!(
                "batches of {chunk} samples are too small to render (at least \
                 {RAY_GROUP_ALIGN})"
            )));
        }
        let rays = camera.all_rays();
        let pixels = rays.len();
        // Which rays cross the box: the cpu's own test, so both engines
        // march the same rays (the walk kernel repeats it on the gpu for
        // the entry point).
        let config = MarchConfig::paper_or_environment();
        let marcher = Marcher::new(&self.grid, &config, &self.shape.mapping);
        let mut active: Vec<u32> = Vec::with_capacity(pixels);
        let mut origins = Vec::with_capacity(3 * pixels);
        let mut directions = Vec::with_capacity(3 * pixels);
        for (i, ray) in rays.iter().enumerate() {
            origins.extend(ray.origin.to_array());
            directions.extend(ray.direction.to_array());
            // A ray that misses the crop box shows only the background.
            let in_crop = self
                .crop
                .is_none_or(|c| c.intersect(ray.origin, ray.direction, 0.0).is_some());
            if in_crop && marcher.prepare(ray.origin, ray.direction, 0.0).is_some() {
                active.push(i as u32);
            }
        }

        let mut guard = self
            .render_buffers
            .lock()
            .unwrap_or_else(|e| e.into_inner());
        let round_rays = (chunk / 4).max(RAY_GROUP_ALIGN);
        if guard.as_ref().is_none_or(|b| b.pixels < pixels) {
            *guard = Some(RenderBuffers::new(ctx, pixels, round_rays)?);
        }
        let buffers = guard.as_ref().expect("just made");
        let queue = &ctx.queue;
        queue.write_buffer(&buffers.origins, 0, bytemuck::cast_slice(&origins));
        queue.write_buffer(&buffers.directions, 0, bytemuck::cast_slice(&directions));
        if !active.is_empty() {
            queue.write_buffer(&buffers.active[0], 0, bytemuck::cast_slice(&active));
        }

        let mut encoder = ctx.device.create_command_encoder(&Default::default());
        encoder.clear_buffer(&buffers.states, 0, None);
        let march = MarchParams {
            config,
            ..MarchParams::rendering(self.shape.mapping)
        };
        let geometry = self.grid.geometry();
        let mut count = active.len();
        let mut current = 0;
        while count > 0 {
            // The cpu's rule: few samples per ray while many rays are
            // active, more once few are left; 4 to 64 per round. Rounds
            // start at multiples of 64 rays in the list.
            let per_ray = (chunk / count).clamp(4, 64);
            let mut group = (chunk / per_ray) / RAY_GROUP_ALIGN * RAY_GROUP_ALIGN;
            let per_ray = if group == 0 {
                group = RAY_GROUP_ALIGN;
                chunk / RAY_GROUP_ALIGN
            } else {
                per_ray
            };
            let list = &buffers.active[current];
            for start in (0..count).step_by(group) {
                let n = group.min(count - start);
                let walk = GpuMarch::uniforms(
                    geometry,
                    &MarchParams {
                        sample_budget: per_ray,
                        ..march
                    },
                    n,
                    per_ray,
                );
                let walk = uniform_buffer(ctx, "render walk", &walk);
                self.stages.render.walk.record_bindings(
                    ctx,
                    &mut encoder,
                    &[
                        walk.as_entire_buffer_binding(),
                        self.bitfield.as_entire_buffer_binding(),
                        buffers.origins.as_entire_buffer_binding(),
                        buffers.directions.as_entire_buffer_binding(),
                        float_range(list, start, n),
                        buffers.states.as_entire_buffer_binding(),
                        buffers.counts.as_entire_buffer_binding(),
                        self.march_out.positions.as_entire_buffer_binding(),
                        self.march_out.directions.as_entire_buffer_binding(),
                        self.march_out.t.as_entire_buffer_binding(),
                        self.march_out.dt.as_entire_buffer_binding(),
                    ],
                    dispatch_grid(n + 1, WORKGROUP).0,
                );
                self.record_field(&mut encoder, n * per_ray, true, None);
                let (groups, row_stride) = dispatch_grid(n, WORKGROUP);
                let composite = CompositeUniforms {
                    count: n as u32,
                    row_stride,
                    per_ray: per_ray as u32,
                    max_samples: config.max_steps,
                    stop_depth: -config.min_transmittance.ln(),
                    ..bytemuck::Zeroable::zeroed()
                }
                .with_crop(self.crop.as_ref(), &self.shape.mapping);
                let composite = uniform_buffer(ctx, "render composite", &composite);
                self.stages.render.composite.record_bindings(
                    ctx,
                    &mut encoder,
                    &[
                        composite.as_entire_buffer_binding(),
                        float_range(list, start, n),
                        buffers.states.as_entire_buffer_binding(),
                        buffers.counts.as_entire_buffer_binding(),
                        self.samples.sigma.as_entire_buffer_binding(),
                        self.samples.colour.output().as_entire_buffer_binding(),
                        self.march_out.t.as_entire_buffer_binding(),
                        self.march_out.dt.as_entire_buffer_binding(),
                        self.march_out.positions.as_entire_buffer_binding(),
                    ],
                    groups,
                );
            }
            let (groups, row_stride) = dispatch_grid(count, WORKGROUP);
            let compact = CompactUniforms {
                count: count as u32,
                row_stride,
                _pad: [0; 2],
            };
            let compact = uniform_buffer(ctx, "render compact", &compact);
            encoder.clear_buffer(&buffers.counter, 0, None);
            self.stages.render.compact.record(
                ctx,
                &mut encoder,
                &[
                    &compact,
                    list,
                    &buffers.states,
                    &buffers.active[1 - current],
                    &buffers.counter,
                ],
                groups,
            );
            encoder.copy_buffer_to_buffer(&buffers.counter, 0, &buffers.counter_staging, 0, 4);
            let finished = std::mem::replace(
                &mut encoder,
                ctx.device.create_command_encoder(&Default::default()),
            );
            queue.submit([finished.finish()]);
            count = read_mapped::<u32>(ctx, &buffers.counter_staging, 1)[0] as usize;
            current = 1 - current;
        }

        let (near, far) = self.depth_range;
        let image = ImageUniforms {
            width,
            height,
            mode: match mode {
                RenderMode::Rgb => 0,
                RenderMode::Depth => 1,
                RenderMode::Opacity => 2,
            },
            _pad0: 0,
            background,
            near,
            far,
            _pad1: [0; 3],
        };
        let image = uniform_buffer(ctx, "render image", &image);
        let view = target.create_view(&Default::default());
        self.stages.render.image.record_resources(
            ctx,
            &mut encoder,
            &[
                image.as_entire_binding(),
                buffers.states.as_entire_binding(),
                wgpu::BindingResource::TextureView(&view),
            ],
            [width.div_ceil(8), height.div_ceil(8), 1],
        );
        queue.submit([encoder.finish()]);
        Ok(())
    }
}
