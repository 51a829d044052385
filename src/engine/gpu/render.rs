//! Rendering that stays on the GPU: the round-by-round march with early
//! termination of the cpu's `march_and_composite`, and a last pass that
//! writes colour, depth or opacity into an rgba8unorm storage texture the
//! viewer draws directly.
//!
//! Each round, every ray still marching walks on from where it stopped and
//! writes up to `per_ray` samples into its own slots
//! (`render_walk.wgsl`), the field is evaluated on all slots of the round,
//! and each ray composites its samples and notes whether it is done
//! (`render_composite.wgsl`). The rays still marching are then gathered
//! into the next round's list (`render_compact.wgsl`); only that count is
//! read back, to size the next round. `per_ray` follows the cpu's rule
//! (4 while many rays are active, up to 64 when few are), and the samples
//! are the cpu's, so the pixels are the cpu's up to rounding.

use super::composite::VOLUME_COMMON;
use super::kernel::{Kernel, zeroed_storage_buffer};
use super::march::{CPU_ARITHMETIC, MARCH_COMMON, MARCH_PARAMS, source};
use crate::engine::gpu::{GpuContext, GpuError};
use crate::scene::UnitCubeMapping;
use crate::scene::crop::CropBox;

/// `RayState`, prepended to every render kernel.
const RAY_STATE: &str = include_str!("../../../shaders/ray_state.wgsl");

/// Rays of a round start at multiples of this in the list of active rays
/// (so the list's sub-range bindings are 256-byte aligned).
pub(crate) const RAY_GROUP_ALIGN: usize = 64;
/// u32s per ray of `RayState` in the render shaders.
const STATE_WORDS: usize = 8;

/// `Params` in render_composite.wgsl.
#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct CompositeUniforms {
    pub count: u32,
    pub row_stride: u32,
    pub per_ray: u32,
    pub max_samples: u32,
    pub stop_depth: f32,
    /// 1 with a crop box: samples outside it have no density.
    pub use_crop: u32,
    pub _pad: [u32; 2],
    /// The unit cube's offset and (fourth) scale.
    pub mapping: [f32; 4],
    pub crop_centre: [f32; 4],
    pub crop_half: [f32; 4],
    /// Rows of the rotation from world axes to the crop box's.
    pub to_box: [[f32; 4]; 3],
}

impl CompositeUniforms {
    /// The uniforms' crop fields for `crop` (none: `use_crop` 0) over the
    /// unit cube of `mapping`; the other fields as given.
    pub fn with_crop(self, crop: Option<&CropBox>, mapping: &UnitCubeMapping) -> Self {
        let Some(crop) = crop else {
            return Self {
                use_crop: 0,
                ..self
            };
        };
        let to_box = glam::Mat3::from_quat(crop.rotation.inverse()).transpose();
        let row = |v: glam::Vec3| [v.x, v.y, v.z, 0.0];
        let half = 0.5 * crop.size;
        Self {
            use_crop: 1,
            mapping: [
                mapping.offset.x,
                mapping.offset.y,
                mapping.offset.z,
                mapping.scale,
            ],
            crop_centre: row(crop.centre),
            crop_half: row(half),
            to_box: [row(to_box.x_axis), row(to_box.y_axis), row(to_box.z_axis)],
            ..self
        }
    }
}

/// `Params` in render_compact.wgsl.
#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct CompactUniforms {
    pub count: u32,
    pub row_stride: u32,
    pub _pad: [u32; 2],
}

/// `Params` in render_image.wgsl.
#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct ImageUniforms {
    pub width: u32,
    pub height: u32,
    /// 0 colour, 1 depth, 2 opacity.
    pub mode: u32,
    pub _pad0: u32,
    pub background: [f32; 3],
    pub near: f32,
    pub far: f32,
    pub _pad1: [u32; 3],
}

/// The compiled render kernels.
pub(crate) struct RenderKernels {
    pub walk: Kernel,
    pub composite: Kernel,
    pub compact: Kernel,
    pub image: Kernel,
}

impl RenderKernels {
    pub fn new(context: &GpuContext) -> Result<Self, GpuError> {
        Ok(Self {
            walk: Kernel::new(
                context,
                "render_walk",
                &source(&[
                    MARCH_PARAMS,
                    CPU_ARITHMETIC,
                    MARCH_COMMON,
                    RAY_STATE,
                    include_str!("../../../shaders/render_walk.wgsl"),
                ]),
                "main",
            )?,
            composite: Kernel::new(
                context,
                "render_composite",
                &source(&[
                    RAY_STATE,
                    VOLUME_COMMON,
                    include_str!("../../../shaders/render_composite.wgsl"),
                ]),
                "main",
            )?,
            compact: Kernel::new(
                context,
                "render_compact",
                &source(&[
                    RAY_STATE,
                    include_str!("../../../shaders/render_compact.wgsl"),
                ]),
                "main",
            )?,
            image: Kernel::new(
                context,
                "render_image",
                &source(&[
                    RAY_STATE,
                    include_str!("../../../shaders/render_image.wgsl"),
                ]),
                "main",
            )?,
        })
    }
}

/// Per-pixel state and the lists of active rays, for up to `pixels` rays.
pub(crate) struct RenderBuffers {
    pub pixels: usize,
    /// pixels × 3 f32 each, world space.
    pub origins: wgpu::Buffer,
    pub directions: wgpu::Buffer,
    /// pixels cone radii at unit distance (Mip-NeRF's frustums).
    pub radii: wgpu::Buffer,
    /// pixels × `RayState`.
    pub states: wgpu::Buffer,
    /// The active rays of this round and of the next.
    pub active: [wgpu::Buffer; 2],
    /// Per ray of a round: samples written, bit 31 when it left the box.
    pub counts: wgpu::Buffer,
    /// Rays gathered into the next list (u32), and its mappable copy.
    pub counter: wgpu::Buffer,
    pub counter_staging: wgpu::Buffer,
}

impl RenderBuffers {
    /// Buffers for `pixels` rays and rounds of at most `round_rays` rays.
    pub fn new(context: &GpuContext, pixels: usize, round_rays: usize) -> Result<Self, GpuError> {
        let state_bytes = (pixels * STATE_WORDS * 4) as u64;
        let limit = context.storage_binding_limit();
        if state_bytes > limit {
            return Err(GpuError::BindingTooLarge {
                what: format!("the render state of {pixels} pixels"),
                bytes: state_bytes,
                limit,
            });
        }
        let f = |label: &str, n: usize| zeroed_storage_buffer::<f32>(context, label, n);
        let u = |label: &str, n: usize| zeroed_storage_buffer::<u32>(context, label, n);
        Ok(Self {
            pixels,
            origins: f("render origins", 3 * pixels),
            directions: f("render directions", 3 * pixels),
            radii: f("render radii", pixels),
            states: u("render states", STATE_WORDS * pixels),
            active: [u("render active 0", pixels), u("render active 1", pixels)],
            counts: u("render counts", round_rays),
            counter: u("render counter", 1),
            counter_staging: context.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("render counter read-back"),
                size: 4,
                usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            }),
        })
    }
}

/// Checks that `target` is a texture a `render_to_texture` can write: 2-D,
/// rgba8unorm, `width` × `height`, with the `usage` its writer needs
/// (storage binding for a shader, copy destination for an upload).
pub(crate) fn check_target(
    target: &wgpu::Texture,
    width: u32,
    height: u32,
    usage: wgpu::TextureUsages,
) -> Result<(), GpuError> {
    let mut problems = Vec::new();
    if target.format() != wgpu::TextureFormat::Rgba8Unorm {
        problems.push(format!("format {:?}, not Rgba8Unorm", target.format()));
    }
    if !target.usage().contains(usage) {
        problems.push(format!("usage {:?} lacks {usage:?}", target.usage()));
    }
    if target.dimension() != wgpu::TextureDimension::D2 {
        problems.push(format!("dimension {:?}, not D2", target.dimension()));
    }
    if (target.width(), target.height()) != (width, height) {
        problems.push(format!(
            "{}×{} pixels, the camera has {width}×{height}",
            target.width(),
            target.height()
        ));
    }
    if problems.is_empty() {
        Ok(())
    } else {
        Err(GpuError::RenderTarget(problems.join("; ")))
    }
}

/// A texture any model on the gpu engine can draw a `width × height` image
/// into (Rgba8Unorm; storage binding for Instant-NGP's render shader, copy
/// destination for the models that composite on the host), a window can
/// sample (texture binding), and a test can read back (copy source).
pub fn render_target(device: &wgpu::Device, width: u32, height: u32) -> wgpu::Texture {
    device.create_texture(&wgpu::TextureDescriptor {
        label: Some("zrak render target"),
        size: wgpu::Extent3d {
            width,
            height,
            depth_or_array_layers: 1,
        },
        mip_level_count: 1,
        sample_count: 1,
        dimension: wgpu::TextureDimension::D2,
        format: wgpu::TextureFormat::Rgba8Unorm,
        usage: wgpu::TextureUsages::STORAGE_BINDING
            | wgpu::TextureUsages::TEXTURE_BINDING
            | wgpu::TextureUsages::COPY_SRC
            | wgpu::TextureUsages::COPY_DST,
        view_formats: &[],
    })
}

/// The RGBA bytes of an Rgba8Unorm texture, row-major without padding,
/// copied out through a buffer (rows padded to wgpu's copy alignment).
pub fn read_texture_rgba8(context: &GpuContext, texture: &wgpu::Texture) -> Vec<u8> {
    let (width, height) = (texture.width(), texture.height());
    let row = (4 * width).next_multiple_of(wgpu::COPY_BYTES_PER_ROW_ALIGNMENT);
    let buffer = context.device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("texture read-back"),
        size: (row * height) as u64,
        usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });
    let mut encoder = context.device.create_command_encoder(&Default::default());
    encoder.copy_texture_to_buffer(
        texture.as_image_copy(),
        wgpu::TexelCopyBufferInfo {
            buffer: &buffer,
            layout: wgpu::TexelCopyBufferLayout {
                offset: 0,
                bytes_per_row: Some(row),
                rows_per_image: Some(height),
            },
        },
        texture.size(),
    );
    context.queue.submit([encoder.finish()]);
    let padded: Vec<u8> = super::kernel::read_mapped(context, &buffer, (row * height) as usize);
    padded
        .chunks(row as usize)
        .flat_map(|r| r[..4 * width as usize].to_vec())
        .collect()
}

/// The uniforms as the shaders declare them (`engine::gpu::mirror`).
#[cfg(test)]
mod uniform_mirrors {
    use super::*;
    use crate::engine::gpu::mirror::assert_mirrors;

    #[test]
    fn compositeuniforms_of_render_composite_mirror_the_shader() {
        assert_mirrors!(
            include_str!("../../../shaders/render_composite.wgsl"),
            "Params",
            CompositeUniforms,
            [
                count,
                row_stride,
                per_ray,
                max_samples,
                stop_depth,
                use_crop,
                mapping,
                crop_centre,
                crop_half,
                to_box
            ]
        );
    }
    #[test]
    fn compactuniforms_of_render_compact_mirror_the_shader() {
        assert_mirrors!(
            include_str!("../../../shaders/render_compact.wgsl"),
            "Params",
            CompactUniforms,
            [count, row_stride]
        );
    }
    /// `RayState` is no uniform, but the host sizes its buffer:
    /// [`STATE_WORDS`] words per pixel.
    #[test]
    fn state_words_hold_a_ray_state() {
        #[repr(C)]
        struct RayState {
            k: u32,
            emitted: u32,
            done: u32,
            optical_depth: f32,
            depth: f32,
            r: f32,
            g: f32,
            b: f32,
        }
        assert_mirrors!(
            RAY_STATE,
            "RayState",
            RayState,
            [k, emitted, done, optical_depth, depth, r, g, b]
        );
        assert_eq!(std::mem::size_of::<RayState>(), 4 * STATE_WORDS);
    }
    #[test]
    fn imageuniforms_of_render_image_mirror_the_shader() {
        assert_mirrors!(
            include_str!("../../../shaders/render_image.wgsl"),
            "Params",
            ImageUniforms,
            [width, height, mode, background, near, far]
        );
    }
}
