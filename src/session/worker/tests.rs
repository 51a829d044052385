use super::viewer_batch_samples;
use crate::engine::EngineKind;
use crate::field::ModelKind;
use crate::field::common::Sampling;

#[test]
fn viewer_batches_shrink_only_where_a_step_would_be_long() {
    use EngineKind::{Cpu, Gpu};
    use Sampling::{Occupancy, Paper};
    let batch =
        |kind, engine, software, sampling| viewer_batch_samples(kind, engine, software, sampling);
    // Instant-NGP on two cores: a quarter of its 2^18 samples, whatever
    // NeRF's sampler setting says; on any gpu adapter its own.
    for sampling in [Occupancy, Paper] {
        assert_eq!(batch(ModelKind::Ngp, Cpu, false, sampling), Some(1 << 16));
        assert_eq!(batch(ModelKind::Ngp, Gpu, true, sampling), None);
        assert_eq!(batch(ModelKind::Ngp, Gpu, false, sampling), None);
    }
    for kind in [ModelKind::Nerf, ModelKind::MipNerf] {
        // The occupancy sampler's recipe batch on the cpu engine, as
        // `zrak train` trains; the paper's sampler and lavapipe get 2^12.
        assert_eq!(batch(kind, Cpu, false, Occupancy), None);
        assert_eq!(batch(kind, Cpu, false, Paper), Some(1 << 12));
        assert_eq!(batch(kind, Gpu, true, Occupancy), Some(1 << 12));
        assert_eq!(batch(kind, Gpu, true, Paper), Some(1 << 12));
        assert_eq!(batch(kind, Gpu, false, Paper), None);
    }
}
