//! How fields are computed: the `cpu` engine (Rust, rayon), which is also the
//! reference for tests, and the `gpu` engine (wgpu).

pub mod cpu;
pub mod gpu;

use gpu::GpuContext;

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

/// Chooses an engine: `requested` when given; otherwise `gpu` on a real GPU
/// and `cpu` when the only adapter is a software one (lavapipe runs the
/// engine's WGSL 40–150× slower than the `cpu` engine, DESIGN.md) or there
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
                    "cpu engine: the only adapter is {}, a software rasteriser",
                    context.describe()
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
