//! How many rays a training batch takes, so that it holds about the
//! target number of samples as the samples per ray change.

/// Chooses how many rays the next training batch takes so that it holds
/// about `target_samples` samples (instant-ngp measures batches in samples:
/// 2^18, paper section 5.4).
///
/// After each step, [`Self::record`] takes the rays and samples the step
/// had; the samples per ray are smoothed by an exponential moving average
/// (weight `smoothing` on the past, so about 1/(1 − smoothing) recent steps
/// count), which keeps one unusual batch from swinging the next one while
/// still following the grid as it empties during training. The next batch
/// is target / average rays, rounded up to a multiple of `granularity` and
/// clamped to [min_rays, max_rays]. With no samples at all (an empty grid)
/// the average goes to zero and the batch grows to max_rays.
#[derive(Debug, Clone, PartialEq)]
pub struct BatchSizer {
    pub target_samples: usize,
    pub smoothing: f64,
    pub min_rays: usize,
    pub max_rays: usize,
    pub granularity: usize,
    initial_rays: usize,
    samples_per_ray: Option<f64>,
}

impl BatchSizer {
    /// Batches of about `target_samples` samples, as instant-ngp's testbed
    /// sizes them: it starts at 2^12 rays, rounds to multiples of 256 rays
    /// (BATCH_SIZE_GRANULARITY) and caps at one sample per ray. The
    /// smoothing 0.8 averages over about 5 steps.
    pub fn new(target_samples: usize) -> Self {
        Self {
            target_samples,
            smoothing: 0.8,
            min_rays: 256.min(target_samples).max(1),
            max_rays: target_samples.max(1),
            granularity: 256,
            initial_rays: 4096,
            samples_per_ray: None,
        }
    }

    /// Rays for the next batch.
    pub fn rays(&self) -> usize {
        let raw = match self.samples_per_ray {
            None => self.initial_rays as f64,
            Some(spr) if spr > 0.0 => self.target_samples as f64 / spr,
            Some(_) => self.max_rays as f64,
        };
        let granularity = self.granularity.max(1);
        let rounded =
            (raw.min(self.max_rays as f64).ceil() as usize).div_ceil(granularity) * granularity;
        rounded.clamp(self.min_rays, self.max_rays)
    }

    /// The smoothed samples per ray, once a step was recorded.
    pub fn samples_per_ray(&self) -> Option<f64> {
        self.samples_per_ray
    }

    /// Restores the smoothed samples per ray (e.g. from a checkpoint, so a
    /// resumed run sizes its next batch as the uninterrupted run would).
    pub fn set_samples_per_ray(&mut self, samples_per_ray: Option<f64>) {
        self.samples_per_ray = samples_per_ray;
    }

    /// Records a step whose `rays` rays held `samples` samples. Count only
    /// rays that were marched to their end: a ray dropped at the budget
    /// holds no samples, and counting it makes rays look shorter than they
    /// are (the sizer then asked for three times the rays that fit).
    pub fn record(&mut self, rays: usize, samples: usize) {
        if rays == 0 {
            return;
        }
        let measured = samples as f64 / rays as f64;
        self.samples_per_ray = Some(match self.samples_per_ray {
            None => measured,
            Some(old) => self.smoothing * old + (1.0 - self.smoothing) * measured,
        });
    }
}
