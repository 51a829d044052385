//! Adam (Kingma & Ba 2015) over one flat parameter vector, as tiny-cuda-nn
//! runs it for instant-ngp (`optimizers/adam.h`, `adam_step`):
//!
//! ```text
//! g ← g + λ·p                      network weights only (λ = 1e-6)
//! skip the parameter if g = 0      everything else (hash-table entries)
//! m ← β₁ m + (1 − β₁) g            a ← β₁ a + (1 − β₁)   (a = 1 − β₁ˢ)
//! v ← β₂ v + (1 − β₂) g²           b ← β₂ b + (1 − β₂)   (b = 1 − β₂ˢ)
//! p ← p − lr · m̂ / (√v̂ + ε)       m̂ = m / a, v̂ = v / b
//! ```
//!
//! Two things differ from textbook Adam, both from tiny-cuda-nn:
//!
//! - **Sparse updates.** A hash-table entry that no sample touched this
//!   step has a gradient of exactly zero; it is left alone (value, moments
//!   and bias correction), instead of drifting on stale momentum. Network
//!   weights are always updated, as in tiny-cuda-nn (a zero gradient there
//!   is a dead unit; its momentum and decay still apply).
//! - **Per-parameter bias correction.** Because entries skip steps, each is
//!   debiased with its own step count s: an entry first touched at step
//!   5000 takes the same careful first steps as one touched at step 1.
//!   tiny-cuda-nn keeps s and evaluates β₁ˢ, β₂ˢ per parameter; zrak keeps
//!   the two denominators a = 1 − β₁ˢ and b = 1 − β₂ˢ instead, updated by
//!   the same recurrence as the moments (they are the moments of a
//!   gradient that is always 1). That needs no powers and no table lookup,
//!   so the update vectorises, and it has no cancellation (1 − β₂ˢ computed
//!   from β₂ˢ loses digits for small s; the recurrence only adds positive
//!   terms).
//!
//! The learning rate follows the global step count through
//! `OptimiserConfig::learning_rate_at`. ε is added to √v̂ as in the paper's
//! algorithm 1 (tiny-cuda-nn adds it to √v; at ε = 1e-15 the two differ
//! only for gradients below ~1e-14).

use std::ops::Range;

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::field::common::OptimiserConfig;
use crate::field::params::{ParamLayout, Update};

/// Parameters per rayon task: big enough that the scheduling cost vanishes
/// against a memory-bound loop of ~16k elements, small enough to balance.
const CHUNK: usize = 1 << 14;

/// Parameters handled together in the sparse path: one cache line of
/// gradients. A block without gradient is skipped after reading it; a block
/// with any is updated without branches (keeping the old values where the
/// gradient is zero), which the compiler vectorises. Public for the
/// throughput probe (`benches/probes/cpu.rs`), which empties whole blocks.
#[doc(hidden)]
pub const BLOCK: usize = 16;

/// The optimiser's state: what a checkpoint stores.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Adam {
    /// First moments, one per parameter.
    pub m: Vec<f32>,
    /// Second moments, one per parameter.
    pub v: Vec<f32>,
    /// 1 − β₁ˢ per parameter, s its own number of updates (0 until its
    /// first): the first moment's bias-correction denominator.
    pub m_norm: Vec<f32>,
    /// 1 − β₂ˢ per parameter: the second moment's.
    pub v_norm: Vec<f32>,
    /// Optimiser steps taken (for the learning-rate schedule).
    pub step: u32,
}

/// The per-step constants of the update.
#[derive(Clone, Copy)]
struct Hyper {
    learning_rate: f32,
    beta1: f32,
    beta2: f32,
    /// 1 − β, rounded once, so every use sees the same value.
    one_minus_beta1: f32,
    one_minus_beta2: f32,
    epsilon: f32,
    l2: f32,
}

/// Equal-length slices of the parameters and the state, for one range.
struct Slices<'a> {
    p: &'a mut [f32],
    g: &'a [f32],
    m: &'a mut [f32],
    v: &'a mut [f32],
    m_norm: &'a mut [f32],
    v_norm: &'a mut [f32],
}

impl<'a> Slices<'a> {
    fn split_at(self, k: usize) -> (Slices<'a>, Slices<'a>) {
        let (p0, p1) = self.p.split_at_mut(k);
        let (g0, g1) = self.g.split_at(k);
        let (m0, m1) = self.m.split_at_mut(k);
        let (v0, v1) = self.v.split_at_mut(k);
        let (a0, a1) = self.m_norm.split_at_mut(k);
        let (b0, b1) = self.v_norm.split_at_mut(k);
        (
            Slices {
                p: p0,
                g: g0,
                m: m0,
                v: v0,
                m_norm: a0,
                v_norm: b0,
            },
            Slices {
                p: p1,
                g: g1,
                m: m1,
                v: v1,
                m_norm: a1,
                v_norm: b1,
            },
        )
    }
}

impl Adam {
    /// Fresh state for `count` parameters.
    pub fn new(count: usize) -> Self {
        Self {
            m: vec![0.0; count],
            v: vec![0.0; count],
            m_norm: vec![0.0; count],
            v_norm: vec![0.0; count],
            step: 0,
        }
    }

    pub fn len(&self) -> usize {
        self.m.len()
    }

    pub fn is_empty(&self) -> bool {
        self.m.is_empty()
    }

    /// The learning rate the next [`Adam::step`] will use.
    pub fn learning_rate(&self, config: &OptimiserConfig) -> f32 {
        config.learning_rate_at(self.step)
    }

    /// One update of `params` from `gradients`. `network_weights` is the
    /// index range of the network weights: they get L2 regularisation and
    /// are updated even where the gradient is zero; every other parameter
    /// is a hash-table entry, skipped where its gradient is exactly zero.
    pub fn step(
        &mut self,
        config: &OptimiserConfig,
        network_weights: Range<usize>,
        params: &mut [f32],
        gradients: &[f32],
    ) {
        let n = self.len();
        assert!(network_weights.start <= network_weights.end && network_weights.end <= n);
        let layout = ParamLayout::new()
            .with("entries before", network_weights.start, Update::Sparse)
            .with(
                "network weights",
                network_weights.len(),
                Update::Dense { l2: true },
            )
            .with("entries after", n - network_weights.end, Update::Sparse);
        self.step_layout(config, &layout, params, gradients);
    }

    /// One update of `params` from `gradients`, each part of `layout` as
    /// its [`Update`] says: dense parts every step (with the config's L2
    /// where the part asks for it), sparse parts only where the gradient is
    /// non-zero.
    pub fn step_layout(
        &mut self,
        config: &OptimiserConfig,
        layout: &ParamLayout,
        params: &mut [f32],
        gradients: &[f32],
    ) {
        let n = self.len();
        assert!(
            params.len() == n && gradients.len() == n && layout.len() == n,
            "Adam holds {n} parameters"
        );
        assert!(
            self.v.len() == n && self.m_norm.len() == n && self.v_norm.len() == n,
            "inconsistent optimiser state"
        );
        let hyper = Hyper {
            learning_rate: config.learning_rate_at(self.step),
            beta1: config.beta1,
            beta2: config.beta2,
            one_minus_beta1: 1.0 - config.beta1,
            one_minus_beta2: 1.0 - config.beta2,
            epsilon: config.epsilon,
            l2: config.l2_weights,
        };
        let no_decay = Hyper { l2: 0.0, ..hyper };
        self.step += 1;
        let parts = layout.parts();

        params
            .par_chunks_mut(CHUNK)
            .zip(gradients.par_chunks(CHUNK))
            .zip(self.m.par_chunks_mut(CHUNK))
            .zip(self.v.par_chunks_mut(CHUNK))
            .zip(self.m_norm.par_chunks_mut(CHUNK))
            .zip(self.v_norm.par_chunks_mut(CHUNK))
            .enumerate()
            .for_each(|(chunk, (((((p, g), m), v), m_norm), v_norm))| {
                let start = chunk * CHUNK;
                let end = start + p.len();
                let mut rest = Slices {
                    p,
                    g,
                    m,
                    v,
                    m_norm,
                    v_norm,
                };
                // The chunk's piece of each part it overlaps, in order.
                for part in parts {
                    let lo = part.range.start.clamp(start, end);
                    let hi = part.range.end.clamp(start, end);
                    if lo == hi {
                        continue;
                    }
                    let (piece, after) = rest.split_at(hi - lo);
                    rest = after;
                    match part.update {
                        Update::Dense { l2: true } => update::<true>(&hyper, piece),
                        Update::Dense { l2: false } => update::<true>(&no_decay, piece),
                        Update::Sparse => update::<false>(&hyper, piece),
                    }
                }
            });
    }
}

/// The update of one range, with the widest vector instructions the
/// processor has. Rust does not contract a·b + c into fused multiply-adds
/// on its own, and + − × ÷ √ are correctly rounded in every instruction
/// set, so every path gives bit-identical results.
fn update<const NETWORK: bool>(hyper: &Hyper, slices: Slices) {
    #[cfg(target_arch = "x86_64")]
    {
        if crate::isa::avx512() {
            // SAFETY: the processor has the feature, checked just above.
            return unsafe { update_avx512::<NETWORK>(hyper, slices) };
        }
        if crate::isa::avx2_fma() {
            // SAFETY: as above.
            return unsafe { update_avx2::<NETWORK>(hyper, slices) };
        }
    }
    update_blocks::<NETWORK>(hyper, slices)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
fn update_avx512<const NETWORK: bool>(hyper: &Hyper, slices: Slices) {
    update_blocks::<NETWORK>(hyper, slices)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn update_avx2<const NETWORK: bool>(hyper: &Hyper, slices: Slices) {
    update_blocks::<NETWORK>(hyper, slices)
}

#[inline(always)]
fn update_blocks<const NETWORK: bool>(hyper: &Hyper, slices: Slices) {
    let full = slices.p.len() / BLOCK * BLOCK;
    let (blocks, tail) = slices.split_at(full);
    for (((((p, g), m), v), a), b) in blocks
        .p
        .chunks_exact_mut(BLOCK)
        .zip(blocks.g.chunks_exact(BLOCK))
        .zip(blocks.m.chunks_exact_mut(BLOCK))
        .zip(blocks.v.chunks_exact_mut(BLOCK))
        .zip(blocks.m_norm.chunks_exact_mut(BLOCK))
        .zip(blocks.v_norm.chunks_exact_mut(BLOCK))
    {
        // Fixed-size arrays, so the inner loop has a known trip count.
        let g: &[f32; BLOCK] = g.try_into().expect("exact chunk");
        let p: &mut [f32; BLOCK] = p.try_into().expect("exact chunk");
        let m: &mut [f32; BLOCK] = m.try_into().expect("exact chunk");
        let v: &mut [f32; BLOCK] = v.try_into().expect("exact chunk");
        let a: &mut [f32; BLOCK] = a.try_into().expect("exact chunk");
        let b: &mut [f32; BLOCK] = b.try_into().expect("exact chunk");
        if !NETWORK && g.iter().all(|&g| g == 0.0) {
            continue;
        }
        for i in 0..BLOCK {
            element::<NETWORK>(
                hyper, &mut p[i], g[i], &mut m[i], &mut v[i], &mut a[i], &mut b[i],
            );
        }
    }
    for i in 0..tail.p.len() {
        element::<NETWORK>(
            hyper,
            &mut tail.p[i],
            tail.g[i],
            &mut tail.m[i],
            &mut tail.v[i],
            &mut tail.m_norm[i],
            &mut tail.v_norm[i],
        );
    }
}

/// One parameter's update, without branches: for a hash entry with zero
/// gradient the new values are computed and discarded.
#[inline(always)]
fn element<const NETWORK: bool>(
    hyper: &Hyper,
    p: &mut f32,
    g: f32,
    m: &mut f32,
    v: &mut f32,
    m_norm: &mut f32,
    v_norm: &mut f32,
) {
    let active = NETWORK || g != 0.0;
    let g = if NETWORK { g + hyper.l2 * *p } else { g };
    let m_new = hyper.beta1 * *m + hyper.one_minus_beta1 * g;
    let v_new = hyper.beta2 * *v + hyper.one_minus_beta2 * (g * g);
    let m_norm_new = hyper.beta1 * *m_norm + hyper.one_minus_beta1;
    let v_norm_new = hyper.beta2 * *v_norm + hyper.one_minus_beta2;
    let p_new = *p
        - hyper.learning_rate * (m_new / m_norm_new)
            / ((v_new / v_norm_new).sqrt() + hyper.epsilon);
    *p = if active { p_new } else { *p };
    *m = if active { m_new } else { *m };
    *v = if active { v_new } else { *v };
    *m_norm = if active { m_norm_new } else { *m_norm };
    *v_norm = if active { v_norm_new } else { *v_norm };
}

#[cfg(test)]
mod tests {
    use super::*;

    const PAPER: OptimiserConfig = OptimiserConfig::PAPER;

    fn sequence(seed: u64, n: usize) -> Vec<f64> {
        let mut state = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (0..n)
            .map(|_| {
                state = state
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                (state >> 11) as f64 / (1u64 << 53) as f64
            })
            .collect()
    }

    #[test]
    fn norms_are_one_minus_beta_to_the_step_count() {
        // The recurrence a ← β a + (1 − β) from 0 gives 1 − βˢ exactly in
        // real arithmetic; in f32 each step adds ≤ ½ ulp and earlier errors
        // shrink by β, so the error stays below ε/(1 − β) relative: 1.2e-6
        // for β₁ and 1.2e-5 for β₂ at worst (in practice far less).
        let mut adam = Adam::new(1);
        let mut p = [0.0f32];
        for s in 1..=3000 {
            adam.step(&PAPER, 0..0, &mut p, &[1.0]);
            let want1 = 1.0 - (PAPER.beta1 as f64).powi(s);
            let want2 = 1.0 - (PAPER.beta2 as f64).powi(s);
            assert!(
                (adam.m_norm[0] as f64 - want1).abs() <= 1.2e-6 * want1,
                "s {s}"
            );
            assert!(
                (adam.v_norm[0] as f64 - want2).abs() <= 1.2e-5 * want2,
                "s {s}"
            );
        }
        // At s = 1 there is no accumulated error: exactly 1 − β.
        let mut adam = Adam::new(1);
        adam.step(&PAPER, 0..0, &mut p, &[1.0]);
        assert_eq!(
            (adam.m_norm[0], adam.v_norm[0]),
            (1.0 - PAPER.beta1, 1.0 - PAPER.beta2)
        );
    }

    #[test]
    fn first_step_moves_each_parameter_by_lr_sign_g() {
        // First step: m̂ = g and v̂ = g², so the step is lr · g/(|g| + ε) =
        // lr · sign(g) up to ε/|g| ≤ 1e-7 and f32 rounding of ~6 operations
        // (≤ 1e-6 relative); the readback of p − p₀ adds half an ulp of
        // |p| ≤ 1 (≤ 6e-8, i.e. 6e-6 of lr = 1e-2). So 1e-5 · lr.
        let n = 1000;
        let r = sequence(3, 3 * n);
        let params0: Vec<f32> = (0..n).map(|i| (2.0 * r[i] - 1.0) as f32).collect();
        // Magnitudes from 1e-8 to 1e3, both signs.
        let gradients: Vec<f32> = (0..n)
            .map(|i| ((r[n + i] - 0.5).signum() * 10f64.powf(-8.0 + 11.0 * r[2 * n + i])) as f32)
            .collect();
        for network in [0..0, 0..n, 300..700] {
            let mut params = params0.clone();
            let mut adam = Adam::new(n);
            adam.step(&PAPER, network.clone(), &mut params, &gradients);
            let lr = PAPER.learning_rate_at(0) as f64;
            for i in 0..n {
                let moved = params[i] as f64 - params0[i] as f64;
                // The L2 term (1e-6 · |p| ≤ 1e-6) changes the sign only for
                // gradients below it.
                let g = gradients[i] as f64
                    + if network.contains(&i) {
                        1e-6 * params0[i] as f64
                    } else {
                        0.0
                    };
                let want = -lr * g.signum();
                assert!(
                    (moved - want).abs() <= 1e-5 * lr,
                    "{i}: moved {moved:e}, want {want:e}"
                );
            }
            assert_eq!(adam.step, 1);
            assert!(adam.m_norm.iter().all(|&a| a == 1.0 - PAPER.beta1));
        }
    }

    #[test]
    fn tiny_gradients_give_tiny_finite_steps() {
        // g = 1e-30 (issue 3's hard case): g² = 1e-60 underflows to 0 in
        // f32, so v = 0 and √v̂ + ε = ε. m̂ = 1e-30, so the step is
        // lr · 1e-30 / 1e-15 = 1e-17: tiny, finite, in the right direction.
        let n = 4;
        let mut params = vec![0.0f32, 0.5, -0.25, 0.0];
        let gradients = vec![1e-30f32, -1e-30, 1e-30, -1e-30];
        let mut adam = Adam::new(n);
        adam.step(&PAPER, 0..0, &mut params, &gradients);
        assert!(
            params
                .iter()
                .chain(&adam.m)
                .chain(&adam.v)
                .all(|x| x.is_finite())
        );
        let step = PAPER.learning_rate as f64 * 1e-30 / 1e-15;
        assert!(
            (params[0] as f64 + step).abs() < 1e-3 * step,
            "{:e}",
            params[0]
        );
        assert!(
            (params[3] as f64 - step).abs() < 1e-3 * step,
            "{:e}",
            params[3]
        );
        // Too small to move a parameter of order 1 at all.
        assert_eq!((params[1], params[2]), (0.5, -0.25));
        // Many steps stay bounded: |Δp| ≤ lr · |m̂|/ε with |m̂| ≤ max |g|.
        for _ in 0..1000 {
            adam.step(&PAPER, 0..0, &mut params, &gradients);
        }
        assert!(
            params
                .iter()
                .chain(&adam.m)
                .chain(&adam.v)
                .all(|x| x.is_finite())
        );
        assert!(params[0].abs() as f64 <= 1001.0 * step * 1.001);
    }

    #[test]
    fn zero_gradients_leave_hash_entries_alone() {
        let n = 6;
        let mut params = vec![0.1f32, -0.2, 0.3, 0.4, -0.5, 0.6];
        let mut adam = Adam::new(n);
        // Step 1: everything has a gradient.
        adam.step(&PAPER, 0..2, &mut params, &[1.0, -1.0, 0.5, -0.5, 2.0, 3.0]);
        let (after_one, state_one) = (params.clone(), adam.clone());
        // Step 2: hash entries 2 and 4 and network weight 1 see nothing.
        adam.step(&PAPER, 0..2, &mut params, &[1.0, 0.0, 0.0, -0.5, 0.0, 3.0]);
        for i in [2, 4] {
            assert_eq!(params[i], after_one[i]);
            assert_eq!(
                (adam.m[i], adam.v[i], adam.m_norm[i], adam.v_norm[i]),
                (
                    state_one.m[i],
                    state_one.v[i],
                    state_one.m_norm[i],
                    state_one.v_norm[i]
                )
            );
        }
        for i in [0, 1, 3, 5] {
            assert_ne!(params[i], after_one[i], "{i} must move");
            assert_ne!(adam.m_norm[i], state_one.m_norm[i]);
        }
        // The network weight moved on momentum and decay alone.
        assert_ne!(adam.m[1], state_one.m[1]);
        // A network weight with no gradient ever is pulled towards 0 by the
        // L2 term (whose gradient Adam normalises to a full lr step).
        let mut params = vec![0.5f32, 0.5];
        let mut adam = Adam::new(2);
        adam.step(&PAPER, 0..1, &mut params, &[0.0, 0.0]);
        assert!(
            (params[0] - (0.5 - PAPER.learning_rate)).abs() < 1e-6,
            "{}",
            params[0]
        );
        assert_eq!(params[1], 0.5);
    }

    #[test]
    fn own_step_counts_debias_late_entries() {
        // An entry first touched at global step 10 takes the same first step
        // (lr · sign g) as at step 1, and its second step matches a fresh
        // optimiser's second step exactly: same state, same arithmetic.
        let mut late = vec![0.3f32];
        let mut adam_late = Adam::new(1);
        for _ in 0..10 {
            adam_late.step(&PAPER, 0..0, &mut late, &[0.0]);
        }
        assert_eq!(
            (late[0], adam_late.step, adam_late.m_norm[0]),
            (0.3, 10, 0.0)
        );
        let mut fresh = vec![0.3f32];
        let mut adam_fresh = Adam::new(1);
        for g in [0.7f32, -0.2, 0.4] {
            adam_late.step(&PAPER, 0..0, &mut late, &[g]);
            adam_fresh.step(&PAPER, 0..0, &mut fresh, &[g]);
            assert_eq!(late, fresh);
        }
        assert_eq!(adam_late.m_norm, adam_fresh.m_norm);
    }

    #[test]
    fn quadratic_bowl_converges() {
        // L = Σ aᵢ (pᵢ − cᵢ)² with curvatures over three decades. Adam's
        // steps are ~lr near the minimum only while the gradient's sign is
        // consistent; once it oscillates, m̂/√v̂ shrinks, so the iterates
        // settle well within a few lr of cᵢ.
        let n = 100;
        let r = sequence(7, 3 * n);
        let centre: Vec<f32> = (0..n).map(|i| (4.0 * r[i] - 2.0) as f32).collect();
        let curvature: Vec<f32> = (0..n)
            .map(|i| 10f64.powf(-1.0 + 3.0 * r[n + i]) as f32)
            .collect();
        let mut params = vec![0.0f32; n];
        let mut gradients = vec![0.0f32; n];
        let mut adam = Adam::new(n);
        let initial: f32 = (0..n).map(|i| curvature[i] * centre[i] * centre[i]).sum();
        for _ in 0..3000 {
            for i in 0..n {
                gradients[i] = 2.0 * curvature[i] * (params[i] - centre[i]);
            }
            adam.step(&PAPER, 0..0, &mut params, &gradients);
        }
        let worst = (0..n)
            .map(|i| (params[i] - centre[i]).abs())
            .fold(0.0, f32::max);
        let loss: f32 = (0..n)
            .map(|i| curvature[i] * (params[i] - centre[i]).powi(2))
            .sum();
        assert!(worst < 2.0 * PAPER.learning_rate, "worst distance {worst}");
        assert!(loss < 1e-4 * initial, "{loss} of {initial}");
    }

    /// A layout of several parts, crossing rayon chunks, updates each part
    /// as a one-part step of its kind would: sparse parts skip zero
    /// gradients, dense parts decay only where they ask for L2.
    #[test]
    fn each_part_of_a_layout_is_updated_by_its_own_rule() {
        let n = 2 * CHUNK + 100;
        let r = sequence(5, 2 * n);
        let initial: Vec<f32> = (0..n).map(|i| (r[i] - 0.5) as f32).collect();
        // Every third gradient zero, so sparse parts show their skipping.
        let gradients: Vec<f32> = (0..n)
            .map(|i| {
                if i % 3 == 0 {
                    0.0
                } else {
                    (r[n + i] - 0.5) as f32
                }
            })
            .collect();
        let cuts = [CHUNK - 7, CHUNK + 9, 2 * CHUNK + 50];
        let layout = ParamLayout::new()
            .with("grid", cuts[0], Update::Sparse)
            .with("decayed", cuts[1] - cuts[0], Update::Dense { l2: true })
            .with("plain", cuts[2] - cuts[1], Update::Dense { l2: false })
            .with("grid 2", n - cuts[2], Update::Sparse);
        let config = OptimiserConfig {
            l2_weights: 0.25,
            ..PAPER
        };
        let mut params = initial.clone();
        let mut adam = Adam::new(n);
        adam.step_layout(&config, &layout, &mut params, &gradients);
        // Each part alone, through the range-based step: dense with the
        // config's decay, or without it (λ = 0), or sparse.
        for part in layout.parts() {
            let range = part.range.clone();
            let mut alone = initial[range.clone()].to_vec();
            let mut adam_alone = Adam::new(range.len());
            let (config, dense) = match part.update {
                Update::Dense { l2: true } => (config, 0..range.len()),
                Update::Dense { l2: false } => (
                    OptimiserConfig {
                        l2_weights: 0.0,
                        ..config
                    },
                    0..range.len(),
                ),
                Update::Sparse => (config, 0..0),
            };
            adam_alone.step(&config, dense, &mut alone, &gradients[range.clone()]);
            let same = alone
                .iter()
                .zip(&params[range.clone()])
                .all(|(a, b)| a.to_bits() == b.to_bits());
            assert!(same, "part {} differs", part.name);
            assert_eq!(adam_alone.m_norm, adam.m_norm[range]);
        }
    }

    #[test]
    fn state_round_trips_and_resumes_identically() {
        let n = 3 * CHUNK + 17; // several chunks, the last partial
        let r = sequence(11, 2 * n);
        let mut params: Vec<f32> = r[..n].iter().map(|&x| x as f32 - 0.5).collect();
        let grad = |step: usize| -> Vec<f32> {
            (0..n)
                .map(|i| {
                    if (i + step).is_multiple_of(3) {
                        0.0
                    } else {
                        (r[n + i] - 0.5) as f32 * (1 + step) as f32
                    }
                })
                .collect()
        };
        let network = 1000..5000;
        let mut adam = Adam::new(n);
        for step in 0..3 {
            adam.step(&PAPER, network.clone(), &mut params, &grad(step));
        }
        let saved = serde_json::to_string(&adam).unwrap();
        let mut resumed: Adam = serde_json::from_str(&saved).unwrap();
        assert_eq!(resumed, adam);
        let mut params_resumed = params.clone();
        for step in 3..6 {
            adam.step(&PAPER, network.clone(), &mut params, &grad(step));
            resumed.step(&PAPER, network.clone(), &mut params_resumed, &grad(step));
        }
        assert_eq!(params, params_resumed);
        assert_eq!(resumed, adam);
        assert_eq!(adam.step, 6);
    }

    #[test]
    fn learning_rate_follows_the_schedule() {
        let mut adam = Adam::new(1);
        let crate::field::common::LrSchedule::Stepwise {
            start,
            interval,
            base,
        } = PAPER.schedule
        else {
            panic!("Instant-NGP decays in steps");
        };
        adam.step = start + interval;
        let mut p = [0.0f32];
        adam.step(&PAPER, 0..0, &mut p, &[1.0]);
        // First step of this entry: lr · sign(g) with the decayed lr.
        let lr = PAPER.learning_rate * base;
        assert!((p[0] + lr).abs() < 1e-5 * lr, "{} vs {}", p[0], -lr);
    }

    #[test]
    fn every_instruction_set_gives_the_same_bits() {
        // The dispatched (vectorised) path against the plain one, on sparse
        // gradients, a partial last block and values of all sizes.
        let n = 1000 + 7;
        let r = sequence(13, 2 * n);
        let gradients: Vec<f32> = (0..n)
            .map(|i| {
                if r[i] < 0.3 {
                    0.0
                } else {
                    (r[n + i] - 0.5) as f32 * 10f32.powi(i as i32 % 9 - 4)
                }
            })
            .collect();
        let hyper = Hyper {
            learning_rate: 1e-2,
            beta1: PAPER.beta1,
            beta2: PAPER.beta2,
            one_minus_beta1: 1.0 - PAPER.beta1,
            one_minus_beta2: 1.0 - PAPER.beta2,
            epsilon: PAPER.epsilon,
            l2: PAPER.l2_weights,
        };
        let fresh = || {
            let p: Vec<f32> = r[..n].iter().map(|&x| x as f32).collect();
            (
                p,
                vec![0.01f32; n],
                vec![1e-4f32; n],
                vec![0.5f32; n],
                vec![0.3f32; n],
            )
        };
        for network in [false, true] {
            let (mut p1, mut m1, mut v1, mut a1, mut b1) = fresh();
            let (mut p2, mut m2, mut v2, mut a2, mut b2) = fresh();
            let s1 = Slices {
                p: &mut p1,
                g: &gradients,
                m: &mut m1,
                v: &mut v1,
                m_norm: &mut a1,
                v_norm: &mut b1,
            };
            let s2 = Slices {
                p: &mut p2,
                g: &gradients,
                m: &mut m2,
                v: &mut v2,
                m_norm: &mut a2,
                v_norm: &mut b2,
            };
            if network {
                update::<true>(&hyper, s1);
                update_blocks::<true>(&hyper, s2);
            } else {
                update::<false>(&hyper, s1);
                update_blocks::<false>(&hyper, s2);
            }
            assert_eq!((p1, m1, v1, a1, b1), (p2, m2, v2, a2, b2));
        }
    }
}
