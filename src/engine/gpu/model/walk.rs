//! The viewer's view drawn on the device for a recipe that marches through
//! the occupancy grid (Instant-NGP; NeRF and Mip-NeRF with the occupancy
//! sampler): rounds of the lattice walk, the level's field and
//! front-to-back compositing into per-ray state, then the image written
//! into the target texture, without reading pixels back (see
//! [`super::super::render`]). Whatever the field, the walk and compositing
//! are the same; as in a training step, a field of world positions gets
//! the walk's unit-cube points mapped to the world first, and a field of
//! frustums gets the Gaussian of each sample's step on its pixel's cone.

use super::*;
use crate::engine::gpu::fields::{FieldInputs, FieldOutputs};
use crate::engine::gpu::frustum::{Gaussians, WalkedIntervals};
use crate::engine::gpu::kernel::{float_range, uniform_buffer};
use crate::engine::gpu::march::dispatch_grid;
use crate::engine::gpu::render::{
    CompactUniforms, CompositeUniforms, ImageUniforms, RAY_GROUP_ALIGN, RenderBuffers,
};
use crate::engine::shared::march::Marcher;

/// Threads per workgroup of the render kernels.
const WORKGROUP: u32 = 64;

impl GpuModel {
    /// Whether [`Self::walk_to_texture`] can draw this model: a recipe
    /// marching through the grid, with batches large enough for a round of
    /// rays.
    pub fn walks_on_device(&self) -> bool {
        self.render.is_some()
            && self
                .grid
                .as_ref()
                .is_some_and(|g| g.samples >= RAY_GROUP_ALIGN)
    }

    /// Renders `camera`'s view on the device into `target` (Rgba8Unorm,
    /// usage STORAGE_BINDING, the camera's size) in `mode` over
    /// `background`: the pixels of `to_image(render_pixels(..))` up to
    /// rounding. Returns once the work is submitted; the queue orders it
    /// before any later use of `target`.
    pub(super) fn walk_to_texture(
        &self,
        camera: &Camera,
        mode: RenderMode,
        background: [f32; 3],
        target: &wgpu::Texture,
    ) -> Result<(), GpuError> {
        let ctx = &self.context;
        let grid = self.grid.as_ref().expect("a marched recipe has a grid");
        let kernels = self.render.as_ref().expect("a walking recipe has kernels");
        let (width, height) = (camera.intrinsics.width, camera.intrinsics.height);
        check_target(target, width, height, wgpu::TextureUsages::STORAGE_BINDING)?;
        let chunk = grid.samples;
        let rays = camera.all_rays();
        let pixels = rays.len();
        // Which rays cross the box: the cpu's own test, so both engines
        // march the same rays (the walk kernel repeats it on the device for
        // the entry point).
        let config = self.core.recipe.march;
        let marcher = Marcher::new(&grid.grid, &config, &grid.mapping);
        let mut active: Vec<u32> = Vec::with_capacity(pixels);
        let mut origins = Vec::with_capacity(3 * pixels);
        let mut directions = Vec::with_capacity(3 * pixels);
        let frustums = self.core.recipe.samples == SampleShape::ConicalFrustums;
        let radii: Vec<f32> = if frustums {
            rays.iter().map(|ray| ray.radius()).collect()
        } else {
            Vec::new()
        };
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

        let mut buffers_guard = self
            .render_buffers
            .lock()
            .unwrap_or_else(|e| e.into_inner());
        let round_rays = (chunk / 4).max(RAY_GROUP_ALIGN);
        if buffers_guard.as_ref().is_none_or(|b| b.pixels < pixels) {
            *buffers_guard = Some(RenderBuffers::new(ctx, pixels, round_rays)?);
        }
        let buffers = buffers_guard.as_ref().expect("just made");
        let queue = &ctx.queue;
        queue.write_buffer(&buffers.origins, 0, bytemuck::cast_slice(&origins));
        queue.write_buffer(&buffers.directions, 0, bytemuck::cast_slice(&directions));
        if frustums {
            queue.write_buffer(&buffers.radii, 0, bytemuck::cast_slice(&radii));
        }
        if !active.is_empty() {
            queue.write_buffer(&buffers.active[0], 0, bytemuck::cast_slice(&active));
        }

        let mut guard = self.work();
        let work = &mut *guard;
        let field = &mut work.fields[self.core.recipe.levels[0].field];
        let unit_cube = field.coordinates() == Coordinates::UnitCube;
        let marched = work.marched.as_ref().expect("a marched recipe has buffers");
        let out = &marched.out;
        let mut rec = Recorder::new(ctx);
        rec.encoder.clear_buffer(&buffers.states, 0, None);
        let march = MarchParams {
            config,
            ..MarchParams::rendering(grid.mapping)
        };
        let geometry = grid.grid.geometry();
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
                kernels.walk.record_bindings(
                    &mut rec,
                    &[
                        walk.as_entire_buffer_binding(),
                        grid.bitfield.as_entire_buffer_binding(),
                        buffers.origins.as_entire_buffer_binding(),
                        buffers.directions.as_entire_buffer_binding(),
                        float_range(list, start, n),
                        buffers.states.as_entire_buffer_binding(),
                        buffers.counts.as_entire_buffer_binding(),
                        out.positions.as_entire_buffer_binding(),
                        out.directions.as_entire_buffer_binding(),
                        out.t.as_entire_buffer_binding(),
                        out.dt.as_entire_buffer_binding(),
                    ],
                    dispatch_grid(n + 1, WORKGROUP).0,
                );
                let samples = n * per_ray;
                if frustums {
                    self.stages.frustums.record_walked(
                        &mut rec,
                        FrustumRays {
                            origins: &buffers.origins,
                            directions: &buffers.directions,
                            radii: &buffers.radii,
                        },
                        float_range(list, start, n),
                        n,
                        WalkedIntervals {
                            t: &out.t,
                            dt: &out.dt,
                            per_ray,
                        },
                        Gaussians {
                            means: &marched.world,
                            variances: &marched.variances,
                        },
                    );
                } else if !unit_cube {
                    self.stages.sampling.record_to_world(
                        &mut rec,
                        &grid.mapping,
                        &out.positions,
                        samples,
                        &marched.world,
                    );
                }
                field.record_forward(
                    &mut rec,
                    &self.params,
                    FieldInputs {
                        positions: if unit_cube {
                            &out.positions
                        } else {
                            &marched.world
                        },
                        variances: frustums.then_some(&marched.variances),
                        directions: &out.directions,
                    },
                    self.rendered_appearance(),
                    samples,
                    FieldOutputs {
                        sigma: &marched.sigma,
                        rgb: &marched.rgb,
                    },
                );
                let (groups, row_stride) = dispatch_grid(n, WORKGROUP);
                let composite = CompositeUniforms {
                    count: n as u32,
                    row_stride,
                    per_ray: per_ray as u32,
                    max_samples: config.max_steps,
                    stop_depth: -config.min_transmittance.ln(),
                    ..bytemuck::Zeroable::zeroed()
                }
                .with_crop(self.crop.as_ref(), &grid.mapping);
                let composite = uniform_buffer(ctx, "render composite", &composite);
                kernels.composite.record_bindings(
                    &mut rec,
                    &[
                        composite.as_entire_buffer_binding(),
                        float_range(list, start, n),
                        buffers.states.as_entire_buffer_binding(),
                        buffers.counts.as_entire_buffer_binding(),
                        marched.sigma.as_entire_buffer_binding(),
                        marched.rgb.as_entire_buffer_binding(),
                        out.t.as_entire_buffer_binding(),
                        out.dt.as_entire_buffer_binding(),
                        out.positions.as_entire_buffer_binding(),
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
            rec.encoder.clear_buffer(&buffers.counter, 0, None);
            kernels.compact.record(
                &mut rec,
                &[
                    &compact,
                    list,
                    &buffers.states,
                    &buffers.active[1 - current],
                    &buffers.counter,
                ],
                groups,
            );
            rec.encoder
                .copy_buffer_to_buffer(&buffers.counter, 0, &buffers.counter_staging, 0, 4);
            rec.submit_so_far();
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
        kernels.image.record_resources(
            &mut rec,
            &[
                image.as_entire_binding(),
                buffers.states.as_entire_binding(),
                wgpu::BindingResource::TextureView(&view),
            ],
            [width.div_ceil(8), height.div_ceil(8), 1],
        );
        rec.submit();
        Ok(())
    }
}
