//! The proposal sampler's stages on the GPU (`shaders/proposal_*.wgsl`,
//! `shaders/weight_*.wgsl`, the contraction in `shaders/contraction.wgsl`):
//! the gpu twins of the cpu engine's scene contraction of the fields'
//! inputs (`engine::cpu::model::InputMap`), of the spacing coordinate the
//! proposal levels sample in ([`crate::field::contraction`]), and of the
//! losses on compositing weights that train the proposals
//! ([`crate::engine::cpu::weight_losses`]).
//!
//! One invocation per ray for the per-ray kernels (a ray's work is
//! O(N log M) with N, M ≤ a few hundred, a chunk has hundreds of rays), one
//! per value for the element-wise ones. The contraction and the spacing
//! repeat the cpu's f32 operations (products kept apart from the sums they
//! feed where the cpu rounds twice; WGSL's division and square root may
//! differ by their few ulps); the weight losses sum in f32 where the cpu
//! sums in f64, so they agree to f32 rounding of the sums (~1e-6 relative).
//!
//! The buffers of a training chunk hold a few hundred rays, far below any
//! storage-binding limit: the kernels bind them whole.

use super::frustum::{FrustumRays, FrustumSamples};
use super::kernel::{Kernel, Recorder, float_range, read_buffer, storage_buffer, uniform_buffer};
use super::march::{CPU_ARITHMETIC, dispatch_grid, source};
use crate::engine::gpu::{GpuContext, GpuError};
use crate::field::contraction::{Contraction, ContractionNorm};

/// Threads per workgroup of every proposal kernel.
const WORKGROUP: u32 = 64;

const COMMON: &str = include_str!("../../../shaders/proposal_common.wgsl");
const CONTRACTION: &str = include_str!("../../../shaders/contraction.wgsl");
const FRUSTUM_COMMON: &str = include_str!("../../../shaders/frustum_common.wgsl");

/// `ProposalParams` in `shaders/proposal_common.wgsl`.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, bytemuck::Pod, bytemuck::Zeroable)]
struct ProposalUniforms {
    count: u32,
    row_stride: u32,
    samples: u32,
    bins: u32,
    norm: u32,
    mode: u32,
    zero: u32,
    scale: f32,
    radius: f32,
    _pad0: [u32; 3],
    centre: [f32; 3],
    _pad3: u32,
}

/// Where a contracted field's inputs live: the contracted ball or cube
/// (NeRF's and Mip-NeRF's fields) or its image on [0, 1]³ (hash grids).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ContractedInputs {
    Contracted,
    UnitCube,
}

/// Each ray's intervals of one level on the device: R × (n + 1) sorted
/// `edges` (world distances along the ray) and R × n `weights`.
#[derive(Debug, Clone, Copy)]
pub struct IntervalBuffers<'a> {
    pub edges: &'a wgpu::Buffer,
    pub weights: &'a wgpu::Buffer,
    pub per_ray: usize,
}

/// A level's samples as compositing saw them, for the gradient a loss on
/// its weights gives its densities: R × n each.
#[derive(Debug, Clone, Copy)]
pub struct CompositedSamples<'a> {
    pub sigma: &'a wgpu::Buffer,
    pub dt: &'a wgpu::Buffer,
    pub weights: &'a wgpu::Buffer,
    pub per_ray: usize,
}

/// The compiled proposal kernels.
pub struct GpuProposal {
    spacing: Kernel,
    midpoints: Kernel,
    contract: Kernel,
    interlevel: Kernel,
    distortion: Kernel,
    to_density: Kernel,
    frustums: Kernel,
}

impl GpuProposal {
    pub fn new(context: &GpuContext) -> Result<Self, GpuError> {
        let kernel = |name: &str, entry: &str| {
            Kernel::new(
                context,
                name,
                &source(&[COMMON, CPU_ARITHMETIC, CONTRACTION, entry]),
                "main",
            )
        };
        Ok(Self {
            spacing: kernel(
                "proposal_spacing",
                include_str!("../../../shaders/proposal_spacing.wgsl"),
            )?,
            midpoints: kernel(
                "proposal_midpoints",
                include_str!("../../../shaders/proposal_midpoints.wgsl"),
            )?,
            contract: kernel(
                "proposal_contract",
                include_str!("../../../shaders/proposal_contract.wgsl"),
            )?,
            interlevel: kernel(
                "weight_interlevel",
                include_str!("../../../shaders/weight_interlevel.wgsl"),
            )?,
            distortion: kernel(
                "weight_distortion",
                include_str!("../../../shaders/weight_distortion.wgsl"),
            )?,
            to_density: kernel(
                "weight_to_density",
                include_str!("../../../shaders/weight_to_density.wgsl"),
            )?,
            frustums: kernel(
                "proposal_frustums",
                &source(&[
                    FRUSTUM_COMMON,
                    include_str!("../../../shaders/proposal_frustums.wgsl"),
                ]),
            )?,
        })
    }

    /// The uniform over `count` invocations, in `contraction`'s frame (a
    /// frame of radius 1 at the origin where none is needed).
    fn uniforms(
        count: usize,
        contraction: Option<&Contraction>,
        fill: ProposalUniforms,
    ) -> ([u32; 3], ProposalUniforms) {
        let (groups, row_stride) = dispatch_grid(count, WORKGROUP);
        let (norm, radius, centre) = match contraction {
            Some(c) => (
                match c.norm {
                    ContractionNorm::L2 => 0,
                    ContractionNorm::LInf => 1,
                },
                c.radius,
                c.centre.to_array(),
            ),
            None => (0, 1.0, [0.0; 3]),
        };
        (
            groups,
            ProposalUniforms {
                count: u32::try_from(count).expect("a chunk's values fit in u32"),
                row_stride,
                norm,
                radius,
                centre,
                ..fill
            },
        )
    }

    fn dispatch(
        &self,
        rec: &mut Recorder,
        kernel: &Kernel,
        (groups, uniforms): ([u32; 3], ProposalUniforms),
        buffers: &[wgpu::BufferBinding],
    ) {
        let uniform = uniform_buffer(rec.context, &kernel.name, &uniforms);
        let mut bindings = vec![uniform.as_entire_buffer_binding()];
        bindings.extend_from_slice(buffers);
        kernel.record_bindings(rec, &bindings, groups);
    }

    /// Records `values` (the first `count`) mapped in place from world
    /// distances along rays to `contraction`'s spacing coordinate s, or
    /// with `inverse` from s back to distances.
    pub fn record_spacing(
        &self,
        rec: &mut Recorder,
        contraction: &Contraction,
        values: &wgpu::Buffer,
        count: usize,
        inverse: bool,
    ) {
        if count == 0 {
            return;
        }
        let fill = ProposalUniforms {
            mode: inverse as u32,
            ..Default::default()
        };
        self.dispatch(
            rec,
            &self.spacing,
            Self::uniforms(count, Some(contraction), fill),
            &[float_range(values, 0, count)],
        );
    }

    /// Records each interval's midpoint `t` and length `dt` (R × n) from
    /// each ray's n + 1 `edges`.
    pub fn record_midpoints(
        &self,
        rec: &mut Recorder,
        edges: &wgpu::Buffer,
        rays: usize,
        per_ray: usize,
        t: &wgpu::Buffer,
        dt: &wgpu::Buffer,
    ) {
        if rays == 0 || per_ray == 0 {
            return;
        }
        let fill = ProposalUniforms {
            samples: per_ray as u32,
            ..Default::default()
        };
        self.dispatch(
            rec,
            &self.midpoints,
            Self::uniforms(rays, None, fill),
            &[
                float_range(edges, 0, rays * (per_ray + 1)),
                float_range(t, 0, rays * per_ray),
                float_range(dt, 0, rays * per_ray),
            ],
        );
    }

    /// Records `count` world positions (count × 3) made, in place, into
    /// the inputs of a field behind `contraction`.
    pub fn record_contract(
        &self,
        rec: &mut Recorder,
        contraction: &Contraction,
        inputs: ContractedInputs,
        positions: &wgpu::Buffer,
        count: usize,
    ) {
        if count == 0 {
            return;
        }
        let fill = ProposalUniforms {
            mode: (inputs == ContractedInputs::UnitCube) as u32,
            ..Default::default()
        };
        self.dispatch(
            rec,
            &self.contract,
            Self::uniforms(count, Some(contraction), fill),
            &[float_range(positions, 0, 3 * count)],
        );
    }

    /// Records the frustums between each ray's `per_ray` + 1 `edges` in
    /// `contraction`'s contracted space (as [`super::frustum::GpuFrustums::record_edges`]
    /// in world space): midpoints and lengths for compositing, contracted
    /// means and covariance diagonals for the field.
    #[allow(clippy::too_many_arguments)]
    pub fn record_contracted_frustums(
        &self,
        rec: &mut Recorder,
        contraction: &Contraction,
        on: FrustumRays,
        edges: &wgpu::Buffer,
        rays: usize,
        per_ray: usize,
        out: FrustumSamples,
    ) {
        if rays == 0 || per_ray == 0 {
            return;
        }
        let fill = ProposalUniforms {
            samples: per_ray as u32,
            ..Default::default()
        };
        let n = rays * per_ray;
        self.dispatch(
            rec,
            &self.frustums,
            Self::uniforms(rays, Some(contraction), fill),
            &[
                float_range(on.origins, 0, 3 * rays),
                float_range(on.directions, 0, 3 * rays),
                float_range(on.radii, 0, rays),
                float_range(edges, 0, rays * (per_ray + 1)),
                float_range(out.t, 0, n),
                float_range(out.dt, 0, n),
                float_range(out.means, 0, 3 * n),
                float_range(out.variances, 0, 3 * n),
                float_range(out.directions, 0, 3 * n),
            ],
        );
    }

    /// Records the interlevel loss of `proposal` against `fine` (held
    /// still) over `rays` rays, edges in `contraction`'s s: each ray's loss
    /// into `ray_loss`, `scale` × its gradient on the proposal's weights
    /// into `d_weights` (written, R × m); `cumulative` is scratch of
    /// R × (m + 1).
    #[allow(clippy::too_many_arguments)]
    pub fn record_interlevel(
        &self,
        rec: &mut Recorder,
        contraction: &Contraction,
        fine: IntervalBuffers,
        proposal: IntervalBuffers,
        rays: usize,
        scale: f32,
        cumulative: &wgpu::Buffer,
        d_weights: &wgpu::Buffer,
        ray_loss: &wgpu::Buffer,
    ) {
        let (n, m) = (fine.per_ray, proposal.per_ray);
        if rays == 0 || m == 0 {
            return;
        }
        let fill = ProposalUniforms {
            samples: n as u32,
            bins: m as u32,
            scale,
            ..Default::default()
        };
        self.dispatch(
            rec,
            &self.interlevel,
            Self::uniforms(rays, Some(contraction), fill),
            &[
                float_range(fine.edges, 0, rays * (n + 1)),
                float_range(fine.weights, 0, (rays * n).max(1)),
                float_range(proposal.edges, 0, rays * (m + 1)),
                float_range(proposal.weights, 0, rays * m),
                float_range(cumulative, 0, rays * (m + 1)),
                float_range(d_weights, 0, rays * m),
                float_range(ray_loss, 0, rays),
            ],
        );
    }

    /// Records `scale` × the gradient of the distortion loss of
    /// `intervals` (in `contraction`'s s) on their weights into `d_weights`
    /// (written, R × n).
    pub fn record_distortion(
        &self,
        rec: &mut Recorder,
        contraction: &Contraction,
        intervals: IntervalBuffers,
        rays: usize,
        scale: f32,
        d_weights: &wgpu::Buffer,
    ) {
        let n = intervals.per_ray;
        if rays == 0 || n == 0 {
            return;
        }
        let fill = ProposalUniforms {
            samples: n as u32,
            scale,
            ..Default::default()
        };
        self.dispatch(
            rec,
            &self.distortion,
            Self::uniforms(rays, Some(contraction), fill),
            &[
                float_range(intervals.edges, 0, rays * (n + 1)),
                float_range(intervals.weights, 0, rays * n),
                float_range(d_weights, 0, rays * n),
            ],
        );
    }

    /// Records the gradient `d_weights` (R × n) gives the densities of
    /// `samples`, added (+=) to `d_sigma`; `suffix` is scratch of R × n.
    pub fn record_weights_to_densities(
        &self,
        rec: &mut Recorder,
        samples: CompositedSamples,
        rays: usize,
        d_weights: &wgpu::Buffer,
        suffix: &wgpu::Buffer,
        d_sigma: &wgpu::Buffer,
    ) {
        let n = samples.per_ray;
        if rays == 0 || n == 0 {
            return;
        }
        let fill = ProposalUniforms {
            samples: n as u32,
            ..Default::default()
        };
        let rows = |buffer| float_range(buffer, 0, rays * n);
        self.dispatch(
            rec,
            &self.to_density,
            Self::uniforms(rays, None, fill),
            &[
                rows(samples.sigma),
                rows(samples.dt),
                rows(samples.weights),
                rows(d_weights),
                rows(suffix),
                rows(d_sigma),
            ],
        );
    }

    /// Uploads, records [`Self::record_interlevel`] and reads back (each
    /// ray's loss, the gradient on the proposal's weights) (tests and
    /// tools): `fine` and `proposal` are (edges, weights) of `rays` rays.
    pub fn interlevel_once(
        &self,
        context: &GpuContext,
        contraction: &Contraction,
        fine: (&[f32], &[f32]),
        proposal: (&[f32], &[f32]),
        rays: usize,
        scale: f32,
    ) -> (Vec<f32>, Vec<f32>) {
        let upload = |label: &str, values: &[f32]| {
            storage_buffer(
                context,
                label,
                if values.is_empty() { &[0.0] } else { values },
            )
        };
        let (n, m) = (fine.1.len() / rays, proposal.1.len() / rays);
        let fine_edges = upload("fine edges", fine.0);
        let fine_weights = upload("fine weights", fine.1);
        let edges = upload("proposal edges", proposal.0);
        let weights = upload("proposal weights", proposal.1);
        let cumulative = upload("cumulative", &vec![0.0; rays * (m + 1)]);
        let d_weights = upload("d weights", &vec![0.0; rays * m]);
        let ray_loss = upload("ray loss", &vec![0.0; rays]);
        let mut rec = Recorder::new(context);
        self.record_interlevel(
            &mut rec,
            contraction,
            IntervalBuffers {
                edges: &fine_edges,
                weights: &fine_weights,
                per_ray: n,
            },
            IntervalBuffers {
                edges: &edges,
                weights: &weights,
                per_ray: m,
            },
            rays,
            scale,
            &cumulative,
            &d_weights,
            &ray_loss,
        );
        rec.submit();
        (
            read_buffer(context, &ray_loss, rays),
            read_buffer(context, &d_weights, rays * m),
        )
    }

    /// Uploads, records [`Self::record_distortion`] and reads back the
    /// gradient on the weights (tests and tools).
    pub fn distortion_once(
        &self,
        context: &GpuContext,
        contraction: &Contraction,
        (edges, weights): (&[f32], &[f32]),
        rays: usize,
        scale: f32,
    ) -> Vec<f32> {
        let n = weights.len() / rays;
        let edges = storage_buffer(context, "edges", edges);
        let weights = storage_buffer(context, "weights", weights);
        let d_weights = storage_buffer(context, "d weights", &vec![0f32; rays * n]);
        let mut rec = Recorder::new(context);
        self.record_distortion(
            &mut rec,
            contraction,
            IntervalBuffers {
                edges: &edges,
                weights: &weights,
                per_ray: n,
            },
            rays,
            scale,
            &d_weights,
        );
        rec.submit();
        read_buffer(context, &d_weights, rays * n)
    }

    /// Uploads, records [`Self::record_weights_to_densities`] onto
    /// `d_sigma` and reads it back (tests and tools).
    pub fn weights_to_densities_once(
        &self,
        context: &GpuContext,
        (sigma, dt, weights): (&[f32], &[f32], &[f32]),
        d_weights: &[f32],
        rays: usize,
        d_sigma: &[f32],
    ) -> Vec<f32> {
        let n = sigma.len() / rays;
        let sigma = storage_buffer(context, "sigma", sigma);
        let dt = storage_buffer(context, "dt", dt);
        let weights = storage_buffer(context, "weights", weights);
        let d_weights = storage_buffer(context, "d weights", d_weights);
        let suffix = storage_buffer(context, "suffix", &vec![0f32; rays * n]);
        let d_sigma = storage_buffer(context, "d sigma", d_sigma);
        let mut rec = Recorder::new(context);
        self.record_weights_to_densities(
            &mut rec,
            CompositedSamples {
                sigma: &sigma,
                dt: &dt,
                weights: &weights,
                per_ray: n,
            },
            rays,
            &d_weights,
            &suffix,
            &d_sigma,
        );
        rec.submit();
        read_buffer(context, &d_sigma, rays * n)
    }

    /// Uploads `values`, maps them to s (or back, with `inverse`) and
    /// reads them back (tests and tools).
    pub fn spacing_once(
        &self,
        context: &GpuContext,
        contraction: &Contraction,
        values: &[f32],
        inverse: bool,
    ) -> Vec<f32> {
        let buffer = storage_buffer(context, "values", values);
        let mut rec = Recorder::new(context);
        self.record_spacing(&mut rec, contraction, &buffer, values.len(), inverse);
        rec.submit();
        read_buffer(context, &buffer, values.len())
    }

    /// Uploads world `positions` (n × 3), makes them a contracted field's
    /// inputs and reads them back (tests and tools).
    pub fn contract_once(
        &self,
        context: &GpuContext,
        contraction: &Contraction,
        inputs: ContractedInputs,
        positions: &[f32],
    ) -> Vec<f32> {
        let buffer = storage_buffer(context, "positions", positions);
        let mut rec = Recorder::new(context);
        self.record_contract(&mut rec, contraction, inputs, &buffer, positions.len() / 3);
        rec.submit();
        read_buffer(context, &buffer, positions.len())
    }
}

/// The uniforms as the shaders declare them (`engine::gpu::mirror`).
#[cfg(test)]
mod uniform_mirrors {
    use super::*;
    use crate::engine::gpu::mirror::assert_mirrors;

    #[test]
    fn proposaluniforms_of_proposal_common_mirror_the_shader() {
        assert_mirrors!(
            include_str!("../../../shaders/proposal_common.wgsl"),
            "ProposalParams",
            ProposalUniforms,
            [
                count, row_stride, samples, bins, norm, mode, zero, scale, radius, centre
            ]
        );
    }
}
