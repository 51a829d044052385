//! The fixed-count levels' samplers on the cpu engine, behind one seam.
//!
//! A recipe names each level's sampler ([`SamplerKind`], engine-neutral
//! data); [`level_sampler`] is the one place that turns a name into the
//! code that draws, and the driver only calls [`LevelSampler::draw`]. A
//! new sampler is a type here and an arm of `level_sampler` (and its twin
//! on the gpu engine), not a case in the driver. Each sampler draws a
//! level's distances along the rays: points' `t` (NeRF) or frustums' edges
//! (Mip-NeRF), from the rays' bounds or from the level before; the driver
//! turns them into the field's inputs.

use super::{LevelBuffers, RaysOfChunk, SamplingScratch, importance_samples, sampling, set_len};
use crate::field::common::{SampleShape, SamplerKind};
use crate::field::contraction::Contraction;

/// Draws a fixed-count level's sample distances.
pub(super) trait LevelSampler: Send + Sync {
    /// Draws the distances of the rays of `chunk` into `lb` (points into
    /// `t`, frustum edges into `edges`) and returns the samples per ray.
    /// `previous` is the level before, with its weights; `jitter` seeds
    /// the random offsets (`None`: the deterministic positions).
    fn draw(
        &self,
        previous: Option<&LevelBuffers>,
        chunk: &RaysOfChunk,
        jitter: Option<u32>,
        scratch: &mut SamplingScratch,
        lb: &mut LevelBuffers,
    ) -> usize;

    /// Whether it draws intervals (edges into `lb.edges`, one more than
    /// samples per ray) rather than points into `lb.t`.
    fn draws_intervals(&self) -> bool;
}

/// The sampler that draws a level named `kind` of a recipe whose samples
/// are `shape`, or `None` where the driver does not sample it level by
/// level (the occupancy grid's march) or the pair is not a sampler
/// (importance points among frustums, resampled frustums among points,
/// the proposal sampler's levels without a contraction to space them by).
pub(super) fn level_sampler(
    kind: SamplerKind,
    shape: SampleShape,
    contraction: Option<Contraction>,
) -> Option<Box<dyn LevelSampler>> {
    Some(match (shape, kind) {
        (_, SamplerKind::SpacedIntervals { count }) => Box::new(SpacedIntervals {
            count,
            contraction: contraction?,
        }),
        (_, SamplerKind::ProposalResample { count, padding }) => Box::new(ProposalResample {
            count,
            padding,
            contraction: contraction?,
        }),
        (SampleShape::Points, SamplerKind::Stratified { count }) => {
            Box::new(StratifiedPoints { count })
        }
        (SampleShape::Points, SamplerKind::Importance { count, padding }) => {
            Box::new(ImportancePoints { count, padding })
        }
        (SampleShape::ConicalFrustums, SamplerKind::Stratified { count }) => {
            Box::new(StratifiedEdges { count })
        }
        (SampleShape::ConicalFrustums, SamplerKind::Resample { count, padding }) => {
            Box::new(ResampledEdges { count, padding })
        }
        _ => return None,
    })
}

/// `count` stratified points between each ray's near and far bounds.
struct StratifiedPoints {
    count: usize,
}

impl LevelSampler for StratifiedPoints {
    fn draw(
        &self,
        _previous: Option<&LevelBuffers>,
        chunk: &RaysOfChunk,
        jitter: Option<u32>,
        _scratch: &mut SamplingScratch,
        lb: &mut LevelBuffers,
    ) -> usize {
        let n = self.count;
        set_len(&mut lb.t, chunk.near.len() * n);
        sampling::stratified(chunk.near, chunk.far, n, jitter, &mut lb.t);
        n
    }

    fn draws_intervals(&self) -> bool {
        false
    }
}

/// NeRF's fine level: `count` points drawn from the previous level's
/// weights (each padded by `padding`), merged with that level's points.
struct ImportancePoints {
    count: usize,
    padding: f32,
}

impl LevelSampler for ImportancePoints {
    fn draw(
        &self,
        previous: Option<&LevelBuffers>,
        chunk: &RaysOfChunk,
        jitter: Option<u32>,
        scratch: &mut SamplingScratch,
        lb: &mut LevelBuffers,
    ) -> usize {
        let (n, rays) = (self.count, chunk.near.len());
        let previous = previous.expect("importance sampling follows a level");
        let m = previous.t.len() / rays.max(1);
        importance_samples(
            &previous.t,
            &previous.weights,
            m,
            n,
            self.padding,
            jitter,
            &mut scratch.edges,
            &mut scratch.inner_weights,
            &mut scratch.fine_t,
        );
        set_len(&mut lb.t, rays * (m + n));
        sampling::merge_sorted(&previous.t, m, &scratch.fine_t, n, &mut lb.t);
        m + n
    }

    fn draws_intervals(&self) -> bool {
        false
    }
}

/// `count` frustums between `count` + 1 stratified edges from near to far.
struct StratifiedEdges {
    count: usize,
}

impl LevelSampler for StratifiedEdges {
    fn draw(
        &self,
        _previous: Option<&LevelBuffers>,
        chunk: &RaysOfChunk,
        jitter: Option<u32>,
        _scratch: &mut SamplingScratch,
        lb: &mut LevelBuffers,
    ) -> usize {
        let n = self.count;
        set_len(&mut lb.edges, chunk.near.len() * (n + 1));
        sampling::stratified(chunk.near, chunk.far, n + 1, jitter, &mut lb.edges);
        n
    }

    fn draws_intervals(&self) -> bool {
        true
    }
}

/// Mip-NeRF's second level: `count` + 1 edges drawn afresh from the
/// previous level's edges and its weights, blurred (2-tap max, 2-tap
/// average) and padded by `padding`.
struct ResampledEdges {
    count: usize,
    padding: f32,
}

impl LevelSampler for ResampledEdges {
    fn draw(
        &self,
        previous: Option<&LevelBuffers>,
        chunk: &RaysOfChunk,
        jitter: Option<u32>,
        scratch: &mut SamplingScratch,
        lb: &mut LevelBuffers,
    ) -> usize {
        let (n, rays) = (self.count, chunk.near.len());
        let previous = previous.expect("resampling follows a level");
        let m = previous.weights.len() / rays.max(1);
        set_len(&mut scratch.blurred, previous.weights.len());
        sampling::blur_weights(&previous.weights, m.max(1), &mut scratch.blurred);
        set_len(&mut lb.edges, rays * (n + 1));
        sampling::sample_pdf(
            &previous.edges,
            &scratch.blurred,
            m,
            self.padding,
            n + 1,
            jitter,
            &mut lb.edges,
        );
        n
    }

    fn draws_intervals(&self) -> bool {
        true
    }
}

/// A proposal sampler's first level: `count` intervals whose `count` + 1
/// edges are stratified in the contraction's spacing coordinate s between
/// each ray's near and far bounds.
struct SpacedIntervals {
    count: usize,
    contraction: Contraction,
}

impl LevelSampler for SpacedIntervals {
    fn draw(
        &self,
        _previous: Option<&LevelBuffers>,
        chunk: &RaysOfChunk,
        jitter: Option<u32>,
        scratch: &mut SamplingScratch,
        lb: &mut LevelBuffers,
    ) -> usize {
        let (n, c) = (self.count, &self.contraction);
        scratch.starts.clear();
        scratch
            .starts
            .extend(chunk.near.iter().map(|&t| c.spacing_of(t)));
        scratch.ends.clear();
        scratch
            .ends
            .extend(chunk.far.iter().map(|&t| c.spacing_of(t)));
        set_len(&mut lb.edges, chunk.near.len() * (n + 1));
        sampling::stratified(&scratch.starts, &scratch.ends, n + 1, jitter, &mut lb.edges);
        for e in lb.edges.iter_mut() {
            *e = c.distance_of(*e);
        }
        n
    }

    fn draws_intervals(&self) -> bool {
        true
    }
}

/// A proposal sampler's later levels: `count` + 1 edges drawn from the
/// previous level's intervals and weights in s (padded by `padding`, not
/// blurred), mapped back to distances.
struct ProposalResample {
    count: usize,
    padding: f32,
    contraction: Contraction,
}

impl LevelSampler for ProposalResample {
    fn draw(
        &self,
        previous: Option<&LevelBuffers>,
        chunk: &RaysOfChunk,
        jitter: Option<u32>,
        scratch: &mut SamplingScratch,
        lb: &mut LevelBuffers,
    ) -> usize {
        let (n, rays, c) = (self.count, chunk.near.len(), &self.contraction);
        let previous = previous.expect("resampling follows a level");
        let m = previous.weights.len() / rays.max(1);
        scratch.starts.clear();
        scratch
            .starts
            .extend(previous.edges.iter().map(|&t| c.spacing_of(t)));
        set_len(&mut lb.edges, rays * (n + 1));
        sampling::sample_pdf(
            &scratch.starts,
            &previous.weights,
            m,
            self.padding,
            n + 1,
            jitter,
            &mut lb.edges,
        );
        for e in lb.edges.iter_mut() {
            *e = c.distance_of(*e);
        }
        n
    }

    fn draws_intervals(&self) -> bool {
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The cpu engine draws what the gpu engine's plan accepts: each
    /// sampler for its shape of samples, and nothing else level by level.
    #[test]
    fn each_sampler_draws_its_shape_of_samples_only() {
        let importance = SamplerKind::Importance {
            count: 8,
            padding: 0.0,
        };
        let resample = SamplerKind::Resample {
            count: 8,
            padding: 0.0,
        };
        let stratified = SamplerKind::Stratified { count: 8 };
        let (points, frustums) = (SampleShape::Points, SampleShape::ConicalFrustums);
        for (kind, shape, draws) in [
            (stratified, points, true),
            (stratified, frustums, true),
            (importance, points, true),
            (importance, frustums, false),
            (resample, points, false),
            (resample, frustums, true),
            (SamplerKind::Occupancy, points, false),
            (SamplerKind::Occupancy, frustums, false),
        ] {
            assert_eq!(
                level_sampler(kind, shape, None).is_some(),
                draws,
                "{kind:?} of {shape:?}"
            );
        }
    }

    /// A stratified frustum level draws one edge more than its samples;
    /// resampling then draws the same count afresh from those edges,
    /// inside the rays' bounds and in order.
    #[test]
    fn frustum_levels_draw_count_plus_one_edges_in_order() {
        let (near, far) = ([2.0f32, 1.0], [6.0f32, 3.0]);
        let chunk = RaysOfChunk {
            origins: &[0.0; 6],
            directions: &[0.0, 0.0, 1.0, 0.0, 0.0, 1.0],
            radii: &[0.001, 0.001],
            near: &near,
            far: &far,
        };
        let mut scratch = SamplingScratch::default();
        let mut first = LevelBuffers::default();
        let stratified = level_sampler(
            SamplerKind::Stratified { count: 4 },
            SampleShape::ConicalFrustums,
            None,
        )
        .unwrap();
        assert_eq!(
            stratified.draw(None, &chunk, Some(7), &mut scratch, &mut first),
            4
        );
        assert_eq!(first.edges.len(), 2 * 5);
        first.weights = vec![0.1, 0.6, 0.2, 0.1, 0.0, 0.0, 1.0, 0.0];
        let mut second = LevelBuffers::default();
        let resample = level_sampler(
            SamplerKind::Resample {
                count: 4,
                padding: 0.01,
            },
            SampleShape::ConicalFrustums,
            None,
        )
        .unwrap();
        assert_eq!(
            resample.draw(Some(&first), &chunk, Some(8), &mut scratch, &mut second),
            4
        );
        for (r, edges) in second.edges.chunks_exact(5).enumerate() {
            assert!(edges.windows(2).all(|p| p[0] <= p[1]), "{edges:?}");
            assert!(edges[0] >= near[r] && edges[4] <= far[r], "{edges:?}");
        }
        assert_eq!(second.edges.len(), 2 * 5);
    }

    /// The proposal sampler's levels: the first spaces its edges linearly
    /// inside the contraction's unit ball and in disparity beyond; the
    /// next resamples where the previous level's weight is.
    #[test]
    fn proposal_levels_space_edges_then_resample_where_the_weight_is() {
        use crate::field::contraction::{Contraction, ContractionNorm};
        let contraction = Contraction {
            centre: glam::Vec3::ZERO,
            radius: 2.0,
            norm: ContractionNorm::LInf,
        };
        let (near, far) = ([0.1f32], [2000.0f32]);
        let chunk = RaysOfChunk {
            origins: &[0.0; 3],
            directions: &[0.0, 0.0, 1.0],
            radii: &[],
            near: &near,
            far: &far,
        };
        let mut scratch = SamplingScratch::default();
        let mut first = LevelBuffers::default();
        let spaced = level_sampler(
            SamplerKind::SpacedIntervals { count: 8 },
            SampleShape::Points,
            Some(contraction),
        )
        .unwrap();
        assert!(spaced.draws_intervals());
        assert_eq!(spaced.draw(None, &chunk, None, &mut scratch, &mut first), 8);
        // Deterministic edges: equal steps of s from s(near) to s(far).
        let s: Vec<f32> = first
            .edges
            .iter()
            .map(|&t| contraction.spacing_of(t))
            .collect();
        let step = (s[8] - s[0]) / 8.0;
        for pair in s.windows(2) {
            assert!((pair[1] - pair[0] - step).abs() < 1e-4, "{s:?}");
        }
        assert!((first.edges[0] - 0.1).abs() < 1e-5 && (first.edges[8] - 2000.0).abs() < 1.0);
        // All the weight in one interval: the resampled edges gather there,
        // but for the padding's share (0.01 per interval: 7 × 0.01 / 1.08 of
        // the mass lies elsewhere, ~7 %).
        first.weights = vec![0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0];
        let (lo, hi) = (first.edges[3], first.edges[4]);
        let mut second = LevelBuffers::default();
        let resample = level_sampler(
            SamplerKind::ProposalResample {
                count: 32,
                padding: 0.01,
            },
            SampleShape::Points,
            Some(contraction),
        )
        .unwrap();
        assert_eq!(
            resample.draw(Some(&first), &chunk, Some(3), &mut scratch, &mut second),
            32
        );
        assert_eq!(second.edges.len(), 33);
        assert!(second.edges.windows(2).all(|p| p[0] <= p[1]));
        let inside = second
            .edges
            .iter()
            .filter(|&&t| t >= lo * 0.999 && t <= hi * 1.001)
            .count();
        assert!(
            inside >= 28,
            "{inside} of 33 edges in [{lo}, {hi}]: {:?}",
            second.edges
        );
        // Without a contraction there is no spacing to draw in.
        assert!(
            level_sampler(
                SamplerKind::SpacedIntervals { count: 8 },
                SampleShape::Points,
                None
            )
            .is_none()
        );
    }
}
