//! How fields are computed: the `cpu` engine (Rust, rayon), which is also the
//! reference for tests, and the `gpu` engine (wgpu).

pub mod cpu;
pub mod crop;
pub mod gpu;
pub mod request;
pub mod shared;

use gpu::GpuContext;
use request::{BuildError, ModelRequest};

use crate::model::RadianceModel;
use crate::scene::Scene;

/// Which engine computes a model.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "lowercase")]
pub enum EngineKind {
    Cpu,
    Gpu,
}

impl EngineKind {
    pub fn name(self) -> &'static str {
        match self {
            EngineKind::Cpu => "cpu",
            EngineKind::Gpu => "gpu",
        }
    }
}

/// The engine to use and why, with the GPU context when the choice is `gpu`.
pub struct EngineChoice {
    pub kind: EngineKind,
    pub gpu: Option<GpuContext>,
    /// One line for the user: the adapter found and the reason for the
    /// choice.
    pub reason: String,
}

impl EngineChoice {
    /// The same choice for one more model, on the same device (wgpu's
    /// handles are reference-counted clones), without looking for an
    /// adapter again.
    pub fn share(&self) -> Result<EngineChoice, gpu::GpuError> {
        Ok(EngineChoice {
            kind: self.kind,
            gpu: self
                .gpu
                .as_ref()
                .map(|c| GpuContext::from_existing(&c.adapter, c.device.clone(), c.queue.clone()))
                .transpose()?,
            reason: self.reason.clone(),
        })
    }
}

/// The composition root: a fresh model of `request` on the chosen engine.
/// Each engine has one `fields_for` that turns the request's
/// [`crate::field::FieldShape`] into its fields, the only place an
/// engine tells the kinds of field apart.
pub fn build(
    request: &ModelRequest,
    engine: EngineChoice,
    scene: &Scene,
) -> Result<Box<dyn RadianceModel>, BuildError> {
    match engine.kind {
        EngineKind::Cpu => Ok(Box::new(cpu::model::CpuModel::build(request, scene))),
        EngineKind::Gpu => {
            let context = engine.gpu.ok_or(BuildError::NoGpuContext)?;
            build_gpu(context, request, scene).map(|m| Box::new(m) as Box<dyn RadianceModel>)
        }
    }
}

/// A fresh model on the `gpu` engine with the context's device (tests
/// that look inside the driver take it so).
pub fn build_gpu(
    context: GpuContext,
    request: &ModelRequest,
    scene: &Scene,
) -> Result<gpu::model::GpuModel, BuildError> {
    gpu::model::GpuModel::build(context, request, scene).map_err(|problem| BuildError::Gpu {
        model: request.kind.name(),
        problem,
    })
}

/// Chooses an engine: `requested` when given; otherwise `gpu` on a real GPU
/// and `cpu` when the only adapter is a software one (lavapipe runs the
/// engine's WGSL 40–150× slower than the `cpu` engine, docs/design.md) or there
/// is none.
pub fn choose_engine(requested: Option<EngineKind>) -> Result<EngineChoice, gpu::GpuError> {
    match requested {
        Some(EngineKind::Cpu) => Ok(EngineChoice {
            kind: EngineKind::Cpu,
            gpu: None,
            reason: "cpu engine (requested)".into(),
        }),
        Some(EngineKind::Gpu) => {
            let context = GpuContext::new()?;
            let allowed = std::env::var_os(ALLOW_SOFTWARE_GPU).is_some_and(|v| v == "1");
            if context.is_software()
                && !allowed
                && let Some(hardware) = hardware_gpu()
            {
                return Err(gpu::GpuError::SoftwareInsteadOfHardware {
                    software: context.describe(),
                    hardware,
                });
            }
            let reason = format!("gpu engine on {} (requested)", context.describe());
            Ok(EngineChoice {
                kind: EngineKind::Gpu,
                gpu: Some(context),
                reason,
            })
        }
        None => Ok(match GpuContext::new() {
            Ok(context) if !context.is_software() => EngineChoice {
                kind: EngineKind::Gpu,
                reason: format!("gpu engine on {}", context.describe()),
                gpu: Some(context),
            },
            Ok(context) => EngineChoice {
                kind: EngineKind::Cpu,
                reason: format!(
                    "cpu engine: the only adapter is {}, a software rasteriser{}",
                    context.describe(),
                    hardware_gpu().map_or(String::new(), |hardware| format!(
                        " (this machine has {hardware}, whose Vulkan driver was not found)"
                    ))
                ),
                gpu: None,
            },
            Err(_) => EngineChoice {
                kind: EngineKind::Cpu,
                gpu: None,
                reason: "cpu engine: no graphics adapter found".into(),
            },
        }),
    }
}

/// Set to 1, lets `--engine gpu` run on a software adapter although the
/// machine has a GPU (to compare the two, or to test the engine there).
pub const ALLOW_SOFTWARE_GPU: &str = "ZRAK_ALLOW_SOFTWARE_GPU";

/// A GPU the operating system shows, in words, whatever graphics API can
/// reach it: NVIDIA's device node, or a DRM device of a GPU vendor. Used
/// to tell a missing driver apart from a machine without a GPU.
pub fn hardware_gpu() -> Option<String> {
    hardware_gpu_in(std::path::Path::new("/"))
}

/// PCI vendors of GPUs that have Vulkan drivers.
const GPU_VENDORS: [(&str, &str); 3] =
    [("0x10de", "NVIDIA"), ("0x1002", "AMD"), ("0x8086", "Intel")];

/// [`hardware_gpu`] under `root` (a test's own tree).
fn hardware_gpu_in(root: &std::path::Path) -> Option<String> {
    let nvidia = root.join("dev/nvidia0");
    if nvidia.exists() {
        return Some("an NVIDIA GPU (/dev/nvidia0)".into());
    }
    let drm = root.join("sys/class/drm");
    let mut cards: Vec<_> = std::fs::read_dir(&drm)
        .ok()?
        .flatten()
        .map(|entry| entry.file_name().to_string_lossy().into_owned())
        .filter(|name| name.starts_with("card") && !name.contains('-'))
        .collect();
    cards.sort();
    cards.into_iter().find_map(|card| {
        let vendor = std::fs::read_to_string(drm.join(&card).join("device/vendor")).ok()?;
        let (_, name) = GPU_VENDORS.iter().find(|(id, _)| vendor.trim() == *id)?;
        Some(format!("an {name} GPU (/sys/class/drm/{card})"))
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_gpu_is_found_by_its_device_node_or_its_drm_vendor() {
        let root = tempfile::tempdir().unwrap();
        assert_eq!(hardware_gpu_in(root.path()), None);
        // A virtual display (QEMU's) is no GPU.
        let card = root.path().join("sys/class/drm/card0/device");
        std::fs::create_dir_all(&card).unwrap();
        std::fs::write(card.join("vendor"), "0x1234\n").unwrap();
        assert_eq!(hardware_gpu_in(root.path()), None);
        let card = root.path().join("sys/class/drm/card1/device");
        std::fs::create_dir_all(&card).unwrap();
        std::fs::write(card.join("vendor"), "0x1002\n").unwrap();
        assert_eq!(
            hardware_gpu_in(root.path()).as_deref(),
            Some("an AMD GPU (/sys/class/drm/card1)")
        );
        std::fs::create_dir_all(root.path().join("dev")).unwrap();
        std::fs::write(root.path().join("dev/nvidia0"), "").unwrap();
        assert_eq!(
            hardware_gpu_in(root.path()).as_deref(),
            Some("an NVIDIA GPU (/dev/nvidia0)")
        );
    }

    #[test]
    fn the_refusal_names_both_adapters_and_the_ways_on() {
        let message = gpu::GpuError::SoftwareInsteadOfHardware {
            software: "llvmpipe (Vulkan, Cpu, software)".into(),
            hardware: "an NVIDIA GPU (/dev/nvidia0)".into(),
        }
        .to_string();
        for part in [
            "llvmpipe",
            "/dev/nvidia0",
            "--engine cpu",
            ALLOW_SOFTWARE_GPU,
        ] {
            assert!(message.contains(part), "{part}: {message}");
        }
    }
}
