//! The wgpu device every `gpu` stage runs on: the adapter chosen, the limits
//! and optional features requested, and what kind of adapter it is.

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

use wgpu::{Adapter, AdapterInfo, Backends, Device, DeviceType, Features, Limits, Queue};

/// Optional features the engine uses when the adapter has them:
/// float atomics for the hash-grid backward pass (a fallback exists for
/// adapters without them), timestamps for per-stage timing, and f16.
pub const WANTED_FEATURES: Features = Features::SHADER_FLOAT32_ATOMIC
    .union(Features::TIMESTAMP_QUERY)
    .union(Features::SHADER_F16);

/// Storage buffers one kernel binds at most (`composite_forward.wgsl`,
/// `render_walk.wgsl`).
pub const REQUIRED_STORAGE_BUFFERS: u32 = 10;

/// Why no GPU context could be made.
#[derive(Debug, thiserror::Error)]
pub enum GpuError {
    #[error(
        "no graphics adapter found (backends tried: {backends:?}); install a Vulkan, Metal or \
         DX12 driver, or on Linux without a GPU `apt-get install mesa-vulkan-drivers \
         libvulkan1`, or use `--engine cpu`"
    )]
    NoAdapter { backends: Backends },
    #[error(
        "the gpu engine was asked for, but the only adapter found is {software}, a software \
         rasteriser, while this machine has {hardware}: its Vulkan driver was not found (for \
         NVIDIA, install the driver's Vulkan ICD or point VK_DRIVER_FILES at its \
         nvidia_icd.json). Use --engine cpu, or set ZRAK_ALLOW_SOFTWARE_GPU=1 to run the gpu \
         engine on the software adapter anyway"
    )]
    SoftwareInsteadOfHardware { software: String, hardware: String },
    #[error("WGSL kernel `{name}` failed to compile: {message}")]
    Shader { name: String, message: String },
    #[error(
        "{what} needs one storage binding of {bytes} bytes, over the device's limit of {limit} \
         bytes (max_storage_buffer_binding_size), and cannot be split further"
    )]
    BindingTooLarge {
        what: String,
        bytes: u64,
        limit: u64,
    },
    #[error(
        "the device lacks limits or features the engine needs: {missing}; create it with the \
         adapter's limits (`adapter.limits()`) and `GpuContext::device_descriptor(&adapter)`"
    )]
    DeviceTooSmall { missing: String },
    #[error("cannot render into this texture: {0}")]
    RenderTarget(String),
    #[error("{0}")]
    Unsupported(String),
    #[error("the adapter {adapter} refused to create a device: {source}")]
    RequestDevice {
        adapter: String,
        #[source]
        source: wgpu::RequestDeviceError,
    },
}

/// A device and queue on the best adapter available, with what it offers.
pub struct GpuContext {
    pub adapter: Adapter,
    pub device: Device,
    pub queue: Queue,
    pub info: AdapterInfo,
    /// The optional features (of [`WANTED_FEATURES`]) the device has.
    pub features: Features,
    pub limits: Limits,
    /// Dispatches recorded and blocking read-backs made on this context.
    pub counters: Arc<GpuCounters>,
}

/// What the engine asked of the device, counted as it goes: compute
/// dispatches recorded, and read-backs that wait for the device (each one
/// drains the queue, so inside a training step it is a bubble the GPU
/// sits idle in while the host catches up).
#[derive(Debug, Default)]
pub struct GpuCounters {
    dispatches: AtomicU64,
    blocking_readbacks: AtomicU64,
}

/// A reading of [`GpuCounters`].
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct CounterReading {
    pub dispatches: u64,
    pub blocking_readbacks: u64,
}

impl std::ops::Sub for CounterReading {
    type Output = CounterReading;
    fn sub(self, earlier: CounterReading) -> CounterReading {
        CounterReading {
            dispatches: self.dispatches - earlier.dispatches,
            blocking_readbacks: self.blocking_readbacks - earlier.blocking_readbacks,
        }
    }
}

impl GpuCounters {
    pub fn count_dispatch(&self) {
        self.dispatches.fetch_add(1, Ordering::Relaxed);
    }

    pub fn count_blocking_readback(&self) {
        self.blocking_readbacks.fetch_add(1, Ordering::Relaxed);
    }

    pub fn read(&self) -> CounterReading {
        CounterReading {
            dispatches: self.dispatches.load(Ordering::Relaxed),
            blocking_readbacks: self.blocking_readbacks.load(Ordering::Relaxed),
        }
    }
}

impl std::fmt::Debug for GpuContext {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GpuContext")
            .field("info", &self.info)
            .field("features", &self.features)
            .finish_non_exhaustive()
    }
}

impl GpuContext {
    /// A context on the best adapter of any backend wgpu was built with
    /// (`WGPU_BACKEND` narrows the search, as in every wgpu program).
    pub fn new() -> Result<Self, GpuError> {
        let descriptor = wgpu::InstanceDescriptor::new_without_display_handle_from_env();
        let backends = if descriptor.backends.is_empty() {
            Backends::all()
        } else {
            descriptor.backends
        };
        Self::with_backends(descriptor, backends)
    }

    /// A context on the best adapter among `backends`.
    pub fn with_backends(
        descriptor: wgpu::InstanceDescriptor,
        backends: Backends,
    ) -> Result<Self, GpuError> {
        let instance = wgpu::Instance::new(descriptor);
        let adapters = pollster::block_on(instance.enumerate_adapters(backends));
        let adapter = adapters
            .into_iter()
            .max_by_key(|a| {
                let info = a.get_info();
                adapter_preference(info.device_type, info.backend)
            })
            .ok_or(GpuError::NoAdapter { backends })?;
        Self::on_adapter(adapter)
    }

    /// A device on `adapter` with the adapter's own limits (egui-wgpu and
    /// wgpu default to `Limits::default()`, which caps storage bindings well
    /// below what the engine's large buffers need) and every wanted feature
    /// it supports.
    pub fn on_adapter(adapter: Adapter) -> Result<Self, GpuError> {
        let info = adapter.get_info();
        let descriptor = Self::device_descriptor(&adapter);
        let (device, queue) =
            pollster::block_on(adapter.request_device(&descriptor)).map_err(|source| {
                GpuError::RequestDevice {
                    adapter: info.name.clone(),
                    source,
                }
            })?;
        Self::from_existing(&adapter, device, queue)
    }

    /// The device the engine wants on `adapter`: the adapter's own limits
    /// and every feature of [`WANTED_FEATURES`] it has. A program that
    /// makes the device itself (eframe: `WgpuSetupCreateNew::
    /// device_descriptor`) asks for this, then hands the device to
    /// [`Self::from_existing`].
    pub fn device_descriptor(adapter: &Adapter) -> wgpu::DeviceDescriptor<'static> {
        wgpu::DeviceDescriptor {
            label: Some("zrak"),
            required_features: adapter.features() & WANTED_FEATURES,
            required_limits: adapter.limits(),
            ..Default::default()
        }
    }

    /// A context on a device made elsewhere (e.g. eframe's, from
    /// `egui_wgpu::RenderState`), so the engine's textures can be drawn
    /// there. The device must have at least [`REQUIRED_STORAGE_BUFFERS`]
    /// storage buffers per shader stage (wgpu's default limits allow 8:
    /// create it with the adapter's limits, [`Self::device_descriptor`]);
    /// the optional features it has are used, and the engine plans with the
    /// device's limits.
    pub fn from_existing(
        adapter: &Adapter,
        device: Device,
        queue: Queue,
    ) -> Result<Self, GpuError> {
        let limits = device.limits();
        let mut missing = Vec::new();
        if limits.max_storage_buffers_per_shader_stage < REQUIRED_STORAGE_BUFFERS {
            missing.push(format!(
                "max_storage_buffers_per_shader_stage {} < {REQUIRED_STORAGE_BUFFERS}",
                limits.max_storage_buffers_per_shader_stage
            ));
        }
        if limits.max_storage_textures_per_shader_stage < 1 {
            missing.push("max_storage_textures_per_shader_stage 0 < 1".into());
        }
        if limits.max_compute_invocations_per_workgroup < 256 {
            missing.push(format!(
                "max_compute_invocations_per_workgroup {} < 256",
                limits.max_compute_invocations_per_workgroup
            ));
        }
        if !missing.is_empty() {
            return Err(GpuError::DeviceTooSmall {
                missing: missing.join(", "),
            });
        }
        Ok(Self {
            adapter: adapter.clone(),
            features: device.features() & WANTED_FEATURES,
            info: adapter.get_info(),
            device,
            queue,
            limits,
            counters: Arc::default(),
        })
    }

    /// Lowers the storage-binding limit the engine plans with (never
    /// raises it), so buffers larger than `bytes` are bound and processed a
    /// piece at a time. For tests that exercise that splitting on a device
    /// whose real limit is large; the device itself is unchanged.
    pub fn cap_storage_binding_size(&mut self, bytes: u64) {
        let limit = &mut self.limits.max_storage_buffer_binding_size;
        *limit = (*limit).min(bytes);
    }

    /// The largest storage binding the engine plans with.
    pub fn storage_binding_limit(&self) -> u64 {
        self.limits.max_storage_buffer_binding_size
    }

    /// True when the adapter is a software rasteriser (e.g. Mesa lavapipe or
    /// llvmpipe), where the `cpu` engine is much faster.
    pub fn is_software(&self) -> bool {
        self.info.device_type == DeviceType::Cpu
    }

    /// One line for logs and the viewer's stats panel.
    pub fn describe(&self) -> String {
        format!(
            "{} ({:?}, {:?}{})",
            self.info.name,
            self.info.backend,
            self.info.device_type,
            if self.is_software() { ", software" } else { "" }
        )
    }

    pub fn has_float_atomics(&self) -> bool {
        self.features.contains(Features::SHADER_FLOAT32_ATOMIC)
    }
}

/// Higher is better: real GPUs before virtual and software ones, and among
/// equals the native APIs before OpenGL.
fn adapter_preference(device_type: DeviceType, backend: wgpu::Backend) -> (u8, u8) {
    let kind = match device_type {
        DeviceType::DiscreteGpu => 4,
        DeviceType::IntegratedGpu => 3,
        DeviceType::VirtualGpu => 2,
        DeviceType::Other => 1,
        DeviceType::Cpu => 0,
    };
    let api = match backend {
        wgpu::Backend::Vulkan | wgpu::Backend::Metal | wgpu::Backend::Dx12 => 1,
        _ => 0,
    };
    (kind, api)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn no_backend_gives_a_clear_error() {
        let descriptor = wgpu::InstanceDescriptor::new_without_display_handle();
        let error = GpuContext::with_backends(descriptor, Backends::empty()).unwrap_err();
        let message = error.to_string();
        assert!(message.contains("no graphics adapter found"), "{message}");
        assert!(message.contains("mesa-vulkan-drivers"), "{message}");
    }

    #[test]
    fn real_gpus_rank_above_software() {
        use wgpu::Backend::{Gl, Vulkan};
        let software = adapter_preference(DeviceType::Cpu, Vulkan);
        assert!(adapter_preference(DeviceType::IntegratedGpu, Gl) > software);
        assert!(
            adapter_preference(DeviceType::DiscreteGpu, Vulkan)
                > adapter_preference(DeviceType::IntegratedGpu, Vulkan)
        );
        assert!(
            adapter_preference(DeviceType::Cpu, Vulkan) > adapter_preference(DeviceType::Cpu, Gl)
        );
    }
}
