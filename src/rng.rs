//! A small, fast, seedable random number generator (PCG-XSH-RR 32, O'Neill
//! 2014) so that every random choice in training can be replayed from a
//! seed and a step number, which is what makes resumed runs match
//! uninterrupted ones.

/// SplitMix64 (Steele, Lea, Flood 2014): a bijective 64-bit mixer, good
/// enough to turn a counter into independent-looking uniform bits.
pub fn splitmix64(x: u64) -> u64 {
    let mut z = x.wrapping_add(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// PCG32: 64-bit state, 32-bit output.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Pcg32 {
    state: u64,
    increment: u64,
}

const MULTIPLIER: u64 = 6_364_136_223_846_793_005;

impl Pcg32 {
    /// A generator for `seed` on `stream`: different streams give unrelated
    /// sequences for the same seed.
    pub fn new(seed: u64, stream: u64) -> Self {
        let mut rng = Self {
            state: 0,
            increment: (stream << 1) | 1,
        };
        rng.next_u32();
        rng.state = rng.state.wrapping_add(seed);
        rng.next_u32();
        rng
    }

    /// A generator for one purpose at one training step, independent of
    /// every other (seed, step, purpose).
    pub fn for_step(seed: u64, step: u64, purpose: u64) -> Self {
        Self::new(
            seed ^ step.wrapping_mul(0x9E37_79B9_7F4A_7C15),
            purpose.wrapping_mul(0xD1B5_4A32_D192_ED03) ^ step,
        )
    }

    pub fn next_u32(&mut self) -> u32 {
        let old = self.state;
        self.state = old.wrapping_mul(MULTIPLIER).wrapping_add(self.increment);
        let xorshifted = (((old >> 18) ^ old) >> 27) as u32;
        let rotation = (old >> 59) as u32;
        xorshifted.rotate_right(rotation)
    }

    /// Uniform in [0, 1), 24 bits of resolution (every value exactly
    /// representable in f32, so 1.0 is never returned).
    pub fn next_f32(&mut self) -> f32 {
        (self.next_u32() >> 8) as f32 * (1.0 / (1u32 << 24) as f32)
    }

    /// Uniform in [0, n) without modulo bias (Lemire's multiply-shift with
    /// rejection).
    pub fn below(&mut self, n: u32) -> u32 {
        assert!(n > 0);
        let threshold = n.wrapping_neg() % n;
        loop {
            let product = self.next_u32() as u64 * n as u64;
            if (product as u32) >= threshold {
                return (product >> 32) as u32;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn same_seed_same_sequence_different_stream_different_sequence() {
        let a: Vec<u32> = (0..8)
            .map({
                let mut r = Pcg32::new(7, 1);
                move |_| r.next_u32()
            })
            .collect();
        let b: Vec<u32> = (0..8)
            .map({
                let mut r = Pcg32::new(7, 1);
                move |_| r.next_u32()
            })
            .collect();
        let c: Vec<u32> = (0..8)
            .map({
                let mut r = Pcg32::new(7, 2);
                move |_| r.next_u32()
            })
            .collect();
        assert_eq!(a, b);
        assert_ne!(a, c);
    }

    #[test]
    fn uniform_floats_have_the_right_mean_and_range() {
        let mut rng = Pcg32::new(1, 0);
        let n = 100_000;
        let values: Vec<f32> = (0..n).map(|_| rng.next_f32()).collect();
        assert!(values.iter().all(|v| (0.0..1.0).contains(v)));
        let mean = values.iter().map(|&v| v as f64).sum::<f64>() / n as f64;
        // Standard error of the mean of U(0,1): 1/sqrt(12 n) ≈ 9e-4; 5σ.
        assert!((mean - 0.5).abs() < 5.0 * 9.2e-4, "{mean}");
    }

    #[test]
    fn below_covers_its_range_evenly() {
        let mut rng = Pcg32::new(3, 0);
        let mut counts = [0u32; 7];
        for _ in 0..70_000 {
            counts[rng.below(7) as usize] += 1;
        }
        // Expected 10 000 each, standard deviation ≈ 93; 6σ.
        assert!(
            counts.iter().all(|&c| (c as i32 - 10_000).abs() < 560),
            "{counts:?}"
        );
    }
}
