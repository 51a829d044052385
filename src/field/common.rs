//! Settings of stages that every model uses, with each model's values in
//! its own file (`ngp.rs`, `nerf.rs`).

/// How the learning rate changes with the optimiser's step count.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum LrSchedule {
    /// From `start` on, the rate is multiplied by
    /// base^⌊(step − start) / interval⌋ (Instant-NGP).
    Stepwise {
        start: u32,
        interval: u32,
        base: f32,
    },
    /// rate · (final/rate)^(step / steps): exponential decay that reaches
    /// `final_rate` at `steps` and keeps decaying after (NeRF,
    /// `run_nerf.py`: lrate · 0.1^(step / (lrate_decay · 1000))).
    Exponential { final_rate: f32, steps: u32 },
}

/// Adam and its schedule.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OptimiserConfig {
    pub learning_rate: f32,
    pub beta1: f32,
    pub beta2: f32,
    pub epsilon: f32,
    /// L2 regularisation on network weights only, not on hash entries.
    pub l2_weights: f32,
    pub schedule: LrSchedule,
}

impl OptimiserConfig {
    /// The learning rate at `step`.
    pub fn learning_rate_at(&self, step: u32) -> f32 {
        match self.schedule {
            LrSchedule::Stepwise {
                start,
                interval,
                base,
            } => {
                if step < start {
                    return self.learning_rate;
                }
                let decays = (step - start) / interval.max(1);
                self.learning_rate * base.powi(decays as i32)
            }
            LrSchedule::Exponential { final_rate, steps } => {
                // In f64: the exponent's small steps would round away in f32
                // over hundreds of thousands of steps.
                let ratio = final_rate as f64 / self.learning_rate as f64;
                let progress = step as f64 / steps.max(1) as f64;
                (self.learning_rate as f64 * ratio.powf(progress)) as f32
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exponential_decay_reaches_its_final_rate() {
        let config = OptimiserConfig {
            learning_rate: 5e-4,
            beta1: 0.9,
            beta2: 0.999,
            epsilon: 1e-7,
            l2_weights: 0.0,
            schedule: LrSchedule::Exponential {
                final_rate: 5e-5,
                steps: 500_000,
            },
        };
        assert_eq!(config.learning_rate_at(0), 5e-4);
        let half = config.learning_rate_at(250_000);
        // Half way in log space: √(5e-4 · 5e-5).
        assert!((half - (5e-4f32 * 5e-5).sqrt()).abs() < 1e-9, "{half}");
        assert!((config.learning_rate_at(500_000) - 5e-5).abs() < 1e-10);
        assert!(config.learning_rate_at(1_000_000) < 5e-5);
    }
}

/// Where a level of a model puts its samples along each ray.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum SamplerKind {
    /// Marching through the occupancy grid: samples only in occupied cells,
    /// at a fixed step, until the ray is opaque.
    Occupancy,
    /// `count` stratified samples between the ray's near and far bounds.
    Stratified { count: usize },
    /// `count` samples drawn from the previous level's weights (inverse
    /// CDF, `padding` added to each weight), evaluated together with the
    /// previous level's samples.
    Importance { count: usize, padding: f32 },
}

/// One level of a model: a sampler and the field that evaluates its
/// samples, with the weight of its loss.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Level {
    pub sampler: SamplerKind,
    /// Index of the model's field this level evaluates.
    pub field: usize,
    pub loss_weight: f32,
}

/// How big a training batch is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BatchSize {
    /// A fixed number of rays.
    Rays(usize),
    /// As many rays as fill this many samples (grid marching, where rays
    /// hold very different numbers of samples).
    Samples(usize),
}

/// Where sampling along a ray starts and ends.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum RayBounds {
    /// The same near and far distance for every ray (NeRF's Blender scenes).
    Fixed { near: f32, far: f32 },
    /// Where the ray enters and leaves the scene's box.
    SceneBox,
}
