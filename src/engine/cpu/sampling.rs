//! Sample generation along rays for NeRF and Mip-NeRF: stratified samples
//! between the near and far planes, and hierarchical (inverse-CDF) samples
//! drawn from the weights of a first pass.
//!
//! NeRF (Mildenhall et al. 2020, section 5.2; bmild/nerf `run_nerf.py`
//! `render_rays` and `run_nerf_helpers.py` `sample_pdf`) draws N_c
//! stratified samples for the coarse network, then N_f more from the
//! piecewise-constant pdf of the coarse weights, and evaluates the fine
//! network on all N_c + N_f sorted together ([`merge_sorted`]). Mip-NeRF
//! (Barron et al. 2021, section 3; google/mipnerf `internal/mip.py`
//! `sample_along_rays`, `resample_along_rays`,
//! `sorted_piecewise_constant_pdf`) treats the samples as interval edges,
//! blurs the coarse weights ([`blur_weights`]), pads them by 0.01 and
//! resamples the edges.
//!
//! Every ray of a batch has the same sample count: R rays × N samples,
//! row-major per ray. Randomness comes from [`uniform`], a hash of
//! (seed, ray, index), so the samples do not depend on the thread count,
//! and the gpu engine (`shaders/sample_*.wgsl`) draws the same numbers.
//! The arithmetic is written so the gpu kernels can repeat it operation for
//! operation: divisions by host-side constants are multiplications by a
//! reciprocal computed once (WGSL's division is only accurate to 2.5 ulp),
//! and the bin each inverse-CDF sample falls in is decided by additions,
//! multiplications and comparisons alone, which both engines round the same.

use rayon::prelude::*;

use crate::engine::shared::march::mix32;

/// Rays per rayon task: a ray costs O(N) here, far less than the splitting,
/// so rays go in blocks (as `composite_batch`'s 64 rays per task).
const RAYS_PER_TASK: usize = 64;

/// A uniform number in [0, 1) that depends only on (seed, ray, index): both
/// engines compute the same one, whatever the thread count or dispatch order.
///
/// The hash of (seed, ray) is that of [`super::march::jitter`]; the index is
/// mixed in afterwards, so for a fixed (seed, ray) distinct indices give
/// distinct hashes (mix32 is a bijection). The top 24 bits become the
/// number, so it is exactly representable in f32 and at most 1 − 2⁻²⁴.
#[inline]
pub fn uniform(seed: u32, ray: u32, index: u32) -> f32 {
    let h = mix32(mix32(seed ^ mix32(ray.wrapping_add(0x9e37_79b9))) ^ index);
    (h >> 8) as f32 * (1.0 / 16_777_216.0)
}

/// The deterministic sample i of n between `near` and `far`
/// (run_nerf.py: z = near·(1 − s) + far·s, s = linspace(0, 1, n)).
///
/// Written as near + (far − near)·s, which is the same number up to rounding
/// but monotone in s once rounded (the reference's two products can round
/// out of order when far − near is small next to far); the last point is
/// `far` exactly and every point is clamped to it, as (far − near)·s can
/// round past it. `step` is 1/(n − 1), computed once on the host side.
#[inline]
fn linspace(near: f32, far: f32, i: usize, n: usize, step: f32) -> f32 {
    if i > 0 && i + 1 == n {
        far
    } else {
        (near + (far - near) * (i as f32 * step)).min(far)
    }
}

/// Stratified samples: for each ray, N points in [near, far] (NeRF,
/// run_nerf.py `render_rays`: z = near·(1 − s) + far·s with
/// s = linspace(0, 1, N), N points including both ends).
///
/// With `jitter = Some(seed)`, point i is drawn uniformly inside its
/// stratum, between the midpoints of its neighbours (the first stratum
/// starts at near, the last ends at far), as `perturb` does in
/// `render_rays`; the draw is [`uniform`]`(seed, ray, i)`. With `None`, the
/// deterministic linspace (rendering). N = 1 gives `near`, as linspace(0, 1,
/// 1) = [0] does.
///
/// `near`, `far`: R each, near ≤ far. `t_out`: R × N, sorted ascending per
/// ray (by construction: each point is clamped to its stratum, and strata
/// only touch).
pub fn stratified(
    near: &[f32],
    far: &[f32],
    samples_per_ray: usize,
    jitter: Option<u32>,
    t_out: &mut [f32],
) {
    let rays = near.len();
    assert_eq!(far.len(), rays, "far: {} values for {rays} rays", far.len());
    assert_eq!(
        t_out.len(),
        rays * samples_per_ray,
        "t_out: {} values for {rays} rays × {samples_per_ray} samples",
        t_out.len()
    );
    let n = samples_per_ray;
    if n == 0 {
        return;
    }
    let step = stratified_step(n);
    t_out
        .par_chunks_mut(n * RAYS_PER_TASK)
        .enumerate()
        .for_each(|(task, block)| {
            for (local, t) in block.chunks_mut(n).enumerate() {
                let ray = task * RAYS_PER_TASK + local;
                let (near, far) = (near[ray], far[ray]);
                let z = |i: usize| linspace(near, far, i, n, step);
                for (i, t) in t.iter_mut().enumerate() {
                    *t = match jitter {
                        None => z(i),
                        Some(seed) => {
                            // The stratum of point i: run_nerf.py's `lower`
                            // and `upper`. 0.5·(a + b) lies in [a, b] after
                            // rounding, so strata stay ordered.
                            let lower = if i == 0 {
                                z(0)
                            } else {
                                0.5 * (z(i - 1) + z(i))
                            };
                            let upper = if i + 1 == n {
                                z(i)
                            } else {
                                0.5 * (z(i) + z(i + 1))
                            };
                            let u = uniform(seed, ray as u32, i as u32);
                            (lower + (upper - lower) * u).min(upper)
                        }
                    };
                }
            }
        });
}

use crate::engine::shared::sampling::stratified_step;

/// A weight as the pdf uses it: non-finite, negative and subnormal weights
/// count as zero (subnormals because GPUs may flush them to zero, and the
/// engines must agree on which bins are empty), then `padding` is added.
#[inline]
fn padded_weight(w: f32, padding: f32) -> f32 {
    (if w.is_finite() && w >= f32::MIN_POSITIVE {
        w
    } else {
        0.0
    }) + padding
}

/// Inverse-CDF sampling of a piecewise-constant pdf per ray (NeRF's
/// `sample_pdf` in run_nerf_helpers.py; Mip-NeRF's
/// `sorted_piecewise_constant_pdf` in mip.py).
///
/// `edges`: R × (B + 1) bin edges, sorted per ray; `weights`: R × B.
/// Non-finite, negative and subnormal weights count as zero; `padding` (≥ 0)
/// is added to every weight before normalising (NeRF: 1e-5, as `sample_pdf`;
/// Mip-NeRF: 0.01 after [`blur_weights`], its `resample_padding`). When the
/// padded weights sum to zero (all zero, padding 0), or overflow to
/// infinity, every bin gets the same mass instead: the pdf is then uniform
/// over the bins, which is uniform over the edges' span when the bins have
/// equal widths (as the stratified edges of a first pass do), and the same
/// distribution that all-zero weights with padding > 0 give.
///
/// `count` samples per ray go to `out` (R × count), sorted ascending, each
/// inside [edges[0], edges[B]] and inside the bin its u falls in (never in a
/// bin of zero mass). Inside a bin the CDF is interpolated linearly, as both
/// references do.
///
/// The u are stratified: u_k = (k + ξ_k)/count, with ξ_k =
/// [`uniform`]`(seed, ray, k)` for `jitter = Some(seed)`, or ξ_k = ½ for
/// `None` (the midpoints, as Mip-NeRF's deterministic resampling). This is
/// Mip-NeRF's choice; NeRF's reference draws i.i.d. u and sorts afterwards.
/// Each sample has the same distribution either way, but stratified u have
/// lower variance (the empirical CDF of one ray's samples is within 1/count
/// of the pdf's CDF) and make the output sorted by construction.
pub fn sample_pdf(
    edges: &[f32],
    weights: &[f32],
    bins: usize,
    padding: f32,
    count: usize,
    jitter: Option<u32>,
    out: &mut [f32],
) {
    assert!(bins > 0, "a pdf needs at least one bin");
    assert!(
        padding.is_finite() && padding >= 0.0,
        "padding {padding} must be finite and ≥ 0"
    );
    assert_eq!(
        weights.len() % bins,
        0,
        "weights: {} values are not rows of {bins} bins",
        weights.len()
    );
    let rays = weights.len() / bins;
    assert_eq!(
        edges.len(),
        rays * (bins + 1),
        "edges: {} values for {rays} rays × {} edges",
        edges.len(),
        bins + 1
    );
    assert_eq!(
        out.len(),
        rays * count,
        "out: {} values for {rays} rays × {count} samples",
        out.len()
    );
    if count == 0 {
        return;
    }
    let inverse_count = 1.0 / count as f32;
    out.par_chunks_mut(count * RAYS_PER_TASK)
        .enumerate()
        .for_each(|(task, block)| {
            for (local, out) in block.chunks_mut(count).enumerate() {
                let ray = task * RAYS_PER_TASK + local;
                sample_pdf_ray(
                    &edges[ray * (bins + 1)..(ray + 1) * (bins + 1)],
                    &weights[ray * bins..(ray + 1) * bins],
                    padding,
                    inverse_count,
                    jitter.map(|seed| (seed, ray as u32)),
                    out,
                );
            }
        });
}

/// One ray of [`sample_pdf`]. Two passes over the bins and no scratch
/// memory (the gpu kernel has none either): the first sums the weights and
/// finds the last bin with mass, the second walks the bins and the sorted u
/// together, rebuilding the running sum in the same order, so the running
/// sum reaches the first pass's total bit for bit.
///
/// The CDF is left unnormalised: u·total is compared with the running sum.
/// That needs no division to find the bin (so both engines pick the same
/// one); the only division is the position inside the bin.
fn sample_pdf_ray(
    edges: &[f32],
    weights: &[f32],
    padding: f32,
    inverse_count: f32,
    jitter: Option<(u32, u32)>,
    out: &mut [f32],
) {
    let bins = weights.len();
    let mut total = 0.0f32;
    let mut last = 0;
    for (i, &w) in weights.iter().enumerate() {
        let w = padded_weight(w, padding);
        total += w;
        if w > 0.0 {
            last = i;
        }
    }
    // No mass to follow (or a sum past f32::MAX): equal mass per bin.
    let equal = !(total > 0.0 && total.is_finite());
    let weight = |i: usize| {
        if equal {
            1.0
        } else {
            padded_weight(weights[i], padding)
        }
    };
    if equal {
        total = bins as f32;
        last = bins - 1;
    }
    let mut bin = 0;
    let mut below = 0.0f32; // sum of the weights of bins before `bin`
    let mut above = weight(0); // … and of `bin` itself
    let mut previous = edges[0];
    for (k, t) in out.iter_mut().enumerate() {
        let xi = jitter.map_or(0.5, |(seed, ray)| uniform(seed, ray, k as u32));
        let target = ((k as f32 + xi) * inverse_count) * total;
        // The bin whose cumulative interval [below, above) holds the target;
        // never past the last bin with mass (u·total can round up to total).
        while bin < last && above <= target {
            bin += 1;
            below = above;
            above = below + weight(bin);
        }
        let mass = above - below;
        // target ≥ below always holds, so the fraction is ≥ 0; it exceeds 1
        // only in the last bin, when the target rounds up to the total.
        let fraction = if mass > 0.0 {
            ((target - below) / mass).min(1.0)
        } else {
            1.0
        };
        let (lo, hi) = (edges[bin], edges[bin + 1]);
        // Clamped to the bin ((hi − lo)·f can round past hi), and to the
        // previous sample, which the cpu's exact division already keeps
        // below; the gpu's division is only accurate to 2.5 ulp.
        *t = (lo + (hi - lo) * fraction).min(hi).max(previous);
        previous = *t;
    }
}

/// Merges two per-ray sorted sample sets (R × Na and R × Nb) into
/// R × (Na + Nb), sorted (NeRF's fine network evaluates the coarse and the
/// importance samples together: run_nerf.py `render_rays`, which
/// concatenates and sorts). Ties take the sample of `a` first.
pub fn merge_sorted(a: &[f32], na: usize, b: &[f32], nb: usize, out: &mut [f32]) {
    let n = na + nb;
    if n == 0 {
        return;
    }
    let rays = out.len() / n;
    assert_eq!(
        out.len(),
        rays * n,
        "out: {} values, not rows of {n}",
        out.len()
    );
    assert_eq!(
        a.len(),
        rays * na,
        "a: {} values for {rays} × {na}",
        a.len()
    );
    assert_eq!(
        b.len(),
        rays * nb,
        "b: {} values for {rays} × {nb}",
        b.len()
    );
    out.par_chunks_mut(n * RAYS_PER_TASK)
        .enumerate()
        .for_each(|(task, block)| {
            for (local, out) in block.chunks_mut(n).enumerate() {
                let ray = task * RAYS_PER_TASK + local;
                let a = &a[ray * na..(ray + 1) * na];
                let b = &b[ray * nb..(ray + 1) * nb];
                let (mut i, mut j) = (0, 0);
                for o in out.iter_mut() {
                    if j == nb || (i < na && a[i] <= b[j]) {
                        *o = a[i];
                        i += 1;
                    } else {
                        *o = b[j];
                        j += 1;
                    }
                }
            }
        });
}

/// Mip-NeRF's weight filter before resampling (mip.py
/// `resample_along_rays`, the "2-tap max, 2-tap blur"):
/// w'_i = ½(max(w_{i−1}, w_i) + max(w_i, w_{i+1})), with w padded by its
/// edge values. It widens every peak by a bin, so resampling also covers
/// the space just around surfaces (section 3.1 of the paper). R × B in,
/// R × B out.
pub fn blur_weights(weights: &[f32], bins: usize, out: &mut [f32]) {
    assert!(bins > 0, "blurring needs at least one bin");
    assert_eq!(
        weights.len() % bins,
        0,
        "weights: {} values, not rows of {bins}",
        weights.len()
    );
    assert_eq!(out.len(), weights.len(), "out and weights differ in length");
    out.par_chunks_mut(bins * RAYS_PER_TASK)
        .zip(weights.par_chunks(bins * RAYS_PER_TASK))
        .for_each(|(out, weights)| {
            for (out, w) in out.chunks_mut(bins).zip(weights.chunks(bins)) {
                for (i, o) in out.iter_mut().enumerate() {
                    let left = w[i.saturating_sub(1)];
                    let right = w[(i + 1).min(bins - 1)];
                    *o = 0.5 * (left.max(w[i]) + w[i].max(right));
                }
            }
        });
}

/// Intervals for compositing from sorted sample points: dt_i = t_{i+1} − t_i,
/// and the last sample's interval ends at `far` of its ray
/// (max(far − t, 0)). run_nerf.py `raw2outputs` gives the last interval
/// 1e10 instead, which makes any density at the last sample opaque; ending
/// it at the far plane integrates exactly over [t_0, far], so the
/// background shows through empty space. R × N in, R × N out.
pub fn intervals_to_far(t: &[f32], far: &[f32], samples_per_ray: usize, dt_out: &mut [f32]) {
    let n = samples_per_ray;
    let rays = far.len();
    assert_eq!(t.len(), rays * n, "t: {} values for {rays} × {n}", t.len());
    assert_eq!(dt_out.len(), t.len(), "dt_out and t differ in length");
    if n == 0 {
        return;
    }
    dt_out
        .par_chunks_mut(n * RAYS_PER_TASK)
        .zip(t.par_chunks(n * RAYS_PER_TASK))
        .enumerate()
        .for_each(|(task, (dt, t))| {
            for (local, (dt, t)) in dt.chunks_mut(n).zip(t.chunks(n)).enumerate() {
                for i in 0..n - 1 {
                    dt[i] = t[i + 1] - t[i];
                }
                dt[n - 1] = (far[task * RAYS_PER_TASK + local] - t[n - 1]).max(0.0);
            }
        });
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Pcg32;

    fn is_sorted(row: &[f32]) -> bool {
        row.windows(2).all(|w| w[0] <= w[1])
    }

    /// Runs `f` on a rayon pool of `threads` threads.
    fn with_threads<T: Send>(threads: usize, f: impl FnOnce() -> T + Send) -> T {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .expect("a thread pool")
            .install(f)
    }

    #[test]
    fn uniform_is_on_the_24_bit_grid_in_unit_interval() {
        let mut sum = 0.0f64;
        let n = 1 << 16;
        for i in 0..n {
            let u = uniform(7, i / 64, i % 64);
            assert!((0.0..1.0).contains(&u), "u = {u}");
            assert_eq!(u * 16_777_216.0, (u * 16_777_216.0).floor(), "u = {u}");
            sum += u as f64;
        }
        // The mean of n uniforms has standard deviation 1/√(12n) ≈ 0.0011;
        // 0.006 is over 5σ.
        assert!(
            (sum / n as f64 - 0.5).abs() < 0.006,
            "mean {}",
            sum / n as f64
        );
        // For one (seed, ray), distinct indices give distinct hashes (mix32
        // is a bijection), hence mostly distinct 24-bit values.
        let mut row: Vec<u32> = (0..256).map(|k| uniform(3, 11, k).to_bits()).collect();
        row.sort_unstable();
        row.dedup();
        assert!(row.len() >= 254, "{} distinct of 256", row.len());
        assert_ne!(uniform(1, 2, 3), uniform(2, 2, 3));
        assert_ne!(uniform(1, 2, 3), uniform(1, 3, 3));
    }

    #[test]
    fn stratified_without_jitter_is_the_linspace() {
        let near = [2.0f32, 0.0, 0.5, 3.0];
        let far = [6.0f32, 1.0, 0.5 + 1e-6, 3.0];
        let n = 64;
        let mut t = vec![0.0; near.len() * n];
        stratified(&near, &far, n, None, &mut t);
        let mut again = vec![0.0; t.len()];
        with_threads(1, || stratified(&near, &far, n, None, &mut again));
        assert_eq!(t, again, "deterministic, whatever the thread count");
        for (r, row) in t.chunks(n).enumerate() {
            assert!(is_sorted(row), "ray {r}: {row:?}");
            assert_eq!(row[0], near[r]);
            assert_eq!(row[n - 1], far[r]);
            for (i, &z) in row.iter().enumerate() {
                assert!(near[r] <= z && z <= far[r], "ray {r} sample {i}: {z}");
                // run_nerf.py's formula in f64; ours differs by the rounding
                // of three f32 operations on values ≤ far: 2 ulp of far.
                let s = i as f64 / (n - 1) as f64;
                let exact = near[r] as f64 * (1.0 - s) + far[r] as f64 * s;
                let ulp = far[r] as f64 * f32::EPSILON as f64;
                assert!(
                    (z as f64 - exact).abs() <= 2.0 * ulp,
                    "ray {r} sample {i}: {z} vs {exact}"
                );
            }
        }
        let mut one = [0.0; 2];
        stratified(&[1.0, 2.0], &[5.0, 7.0], 1, Some(4), &mut one);
        assert_eq!(one, [1.0, 2.0], "linspace(0, 1, 1) = [0]: the near plane");
    }

    /// The strata of run_nerf.py's `perturb`: between the midpoints of each
    /// point's neighbours, from near to far.
    fn strata(z: &[f32]) -> Vec<(f32, f32)> {
        let n = z.len();
        (0..n)
            .map(|i| {
                let lower = if i == 0 {
                    z[0]
                } else {
                    0.5 * (z[i - 1] + z[i])
                };
                let upper = if i + 1 == n {
                    z[i]
                } else {
                    0.5 * (z[i] + z[i + 1])
                };
                (lower, upper)
            })
            .collect()
    }

    #[test]
    fn stratified_jitter_stays_in_each_stratum_and_follows_the_seed() {
        let mut rng = Pcg32::new(1, 2);
        let rays = 300;
        let near: Vec<f32> = (0..rays).map(|_| 0.1 + 3.0 * rng.next_f32()).collect();
        let far: Vec<f32> = near
            .iter()
            .map(|&n| n + [0.0, 1e-5, 1.0, 100.0][rng.below(4) as usize] * rng.next_f32())
            .collect();
        let n = 33;
        let mut z = vec![0.0; rays * n];
        stratified(&near, &far, n, None, &mut z);
        let mut t = vec![0.0; rays * n];
        stratified(&near, &far, n, Some(17), &mut t);
        let mut single = vec![0.0; rays * n];
        with_threads(1, || stratified(&near, &far, n, Some(17), &mut single));
        assert_eq!(t, single, "independent of the thread count");
        for r in 0..rays {
            let row = &t[r * n..(r + 1) * n];
            assert!(is_sorted(row), "ray {r}: {row:?}");
            for (i, (&x, (lower, upper))) in
                row.iter().zip(strata(&z[r * n..(r + 1) * n])).enumerate()
            {
                assert!(near[r] <= x && x <= far[r], "ray {r} sample {i}: {x}");
                assert!(
                    lower <= x && x <= upper,
                    "ray {r} sample {i}: {x} not in [{lower}, {upper}]"
                );
            }
        }
        let mut other = vec![0.0; rays * n];
        stratified(&near, &far, n, Some(18), &mut other);
        // Points of rays with far > near move with the seed; a point stays
        // only if two 24-bit draws coincide or its stratum is a few ulps wide.
        let moved = t.iter().zip(&other).filter(|(a, b)| a != b).count();
        let movable = (0..rays).filter(|&r| far[r] - near[r] > 1e-3).count() * n;
        assert!(
            moved >= movable * 99 / 100,
            "{moved} of {movable} points moved"
        );
    }

    #[test]
    fn stratified_jitter_is_centred_in_each_stratum() {
        // One ray under many seeds: the k-th point averages to its
        // stratum's centre. A uniform on a stratum of width w has standard
        // deviation w/√12; the mean of S seeds, w/√(12 S). 5σ of that is the
        // bound (a draw biased by 1% of the width would exceed it at S =
        // 20000: 5σ ≈ 0.01 w).
        let (near, far, n, seeds) = (2.0f32, 6.0f32, 8, 20_000u32);
        let mut z = vec![0.0; n];
        stratified(&[near], &[far], n, None, &mut z);
        let strata = strata(&z);
        let mut sums = vec![0.0f64; n];
        let mut t = vec![0.0; n];
        for seed in 0..seeds {
            stratified(&[near], &[far], n, Some(seed), &mut t);
            for (s, &x) in sums.iter_mut().zip(&t) {
                *s += x as f64;
            }
        }
        for (k, (&(lower, upper), sum)) in strata.iter().zip(&sums).enumerate() {
            let width = (upper - lower) as f64;
            let centre = 0.5 * (lower as f64 + upper as f64);
            let mean = sum / seeds as f64;
            let bound = 5.0 * width / (12.0 * seeds as f64).sqrt();
            assert!(
                (mean - centre).abs() <= bound,
                "sample {k}: mean {mean}, stratum centre {centre}, bound {bound}"
            );
        }
    }

    /// The CDF of the pdf `sample_pdf` samples, in f64: weights cleaned and
    /// padded as documented, equal masses when they sum to zero, linear
    /// inside each bin.
    fn exact_cdf(edges: &[f32], weights: &[f32], padding: f32) -> impl Fn(f64) -> f64 {
        let clean = |w: f32| {
            if w.is_finite() && w >= f32::MIN_POSITIVE {
                w as f64
            } else {
                0.0
            }
        };
        let mut w: Vec<f64> = weights.iter().map(|&w| clean(w) + padding as f64).collect();
        let total: f64 = w.iter().sum();
        if total == 0.0 {
            w.iter_mut().for_each(|w| *w = 1.0);
        }
        let total: f64 = w.iter().sum();
        let edges: Vec<f64> = edges.iter().map(|&e| e as f64).collect();
        move |x: f64| {
            let mut below = 0.0;
            for (i, &m) in w.iter().enumerate() {
                let (lo, hi) = (edges[i], edges[i + 1]);
                if x < hi {
                    let inside = if x > lo && hi > lo {
                        (x - lo) / (hi - lo)
                    } else {
                        0.0
                    };
                    return ((below + m * inside) / total).min(1.0);
                }
                below += m;
            }
            1.0
        }
    }

    /// Kolmogorov–Smirnov distance between the sorted samples' empirical CDF
    /// and `cdf`.
    fn ks_distance(sorted: &[f32], cdf: &impl Fn(f64) -> f64) -> f64 {
        let n = sorted.len() as f64;
        sorted
            .iter()
            .enumerate()
            .map(|(k, &x)| {
                let f = cdf(x as f64);
                (f - k as f64 / n).max((k + 1) as f64 / n - f)
            })
            .fold(0.0, f64::max)
    }

    /// Edges 2..6 in `bins` bins of random widths (each at least a quarter
    /// of the mean width) and random weights in [0, 1).
    fn random_pdf(bins: usize, seed: u64) -> (Vec<f32>, Vec<f32>) {
        let mut rng = Pcg32::new(seed, 9);
        let widths: Vec<f32> = (0..bins).map(|_| 0.25 + rng.next_f32()).collect();
        let total: f32 = widths.iter().sum();
        let mut edges = vec![2.0f32];
        for w in &widths {
            edges.push(edges.last().unwrap() + 4.0 * w / total);
        }
        let weights = (0..bins).map(|_| rng.next_f32()).collect();
        (edges, weights)
    }

    /// Every ray's samples are finite, sorted, within its edges, and in a
    /// bin of positive (padded) mass, unless the weights sum to zero (equal
    /// masses, every bin allowed).
    fn assert_valid(
        edges: &[f32],
        weights: &[f32],
        bins: usize,
        padding: f32,
        samples: &[f32],
        count: usize,
    ) {
        for (r, row) in samples.chunks(count).enumerate() {
            let e = &edges[r * (bins + 1)..(r + 1) * (bins + 1)];
            let w: Vec<f32> = weights[r * bins..(r + 1) * bins]
                .iter()
                .map(|&w| padded_weight(w, padding))
                .collect();
            let any = w.iter().sum::<f32>() > 0.0;
            assert!(is_sorted(row), "ray {r}: not sorted: {row:?}");
            for &x in row {
                assert!(x.is_finite(), "ray {r}: {x}");
                assert!(
                    e[0] <= x && x <= e[bins],
                    "ray {r}: {x} outside [{}, {}]",
                    e[0],
                    e[bins]
                );
                let in_mass = (0..bins).any(|i| e[i] <= x && x <= e[i + 1] && (!any || w[i] > 0.0));
                assert!(in_mass, "ray {r}: {x} in no bin with mass; weights {w:?}");
            }
        }
    }

    #[test]
    fn sample_pdf_follows_the_weights() {
        // One ray, 4096 samples. With stratified u, F(x_k) = u_k ∈
        // [k/n, (k + 1)/n), so the KS distance is at most 1/n before
        // rounding. Rounding (n = 4096, B = 64, edges ≤ 6): u_k and u·total
        // are a few ε ≈ 2e-7 off; the running sums carry ≤ B·ε ≈ 4e-6 of
        // the total; a position is ≤ 2 ulp(6) ≈ 1e-6 off, which the CDF turns
        // into ≤ pdf·1e-6 ≤ 4e-6 (a bin holds at most ~6% of the mass in
        // ≥ 1/4 of the mean width, 1/64). So F(x_k) is within 1e-5 of u_k,
        // and 2e-5 leaves a factor 2. i.i.d. u would give KS ≈ 1/√n ≈ 0.016;
        // samples that ignored the weights, far more.
        let bins = 64;
        let count = 4096;
        for (seed, jitter) in [(1, None), (2, Some(5)), (3, Some(6))] {
            let (edges, weights) = random_pdf(bins, seed);
            let padding = 1e-5;
            let mut out = vec![0.0; count];
            sample_pdf(&edges, &weights, bins, padding, count, jitter, &mut out);
            assert_valid(&edges, &weights, bins, padding, &out, count);
            let cdf = exact_cdf(&edges, &weights, padding);
            let tolerance = 2e-5;
            for (k, &x) in out.iter().enumerate() {
                let xi = jitter.map_or(0.5, |s| uniform(s, 0, k as u32)) as f64;
                let u = (k as f64 + xi) / count as f64;
                assert!(
                    (cdf(x as f64) - u).abs() <= tolerance,
                    "{jitter:?} sample {k}: F(x) = {} for u = {u}",
                    cdf(x as f64)
                );
            }
            let ks = ks_distance(&out, &cdf);
            assert!(ks <= 1.0 / count as f64 + tolerance, "{jitter:?}: KS {ks}");
        }
    }

    #[test]
    fn sample_pdf_rays_are_independent_and_thread_count_free() {
        let bins = 16;
        let count = 24;
        let rays = 500;
        let mut edges = Vec::new();
        let mut weights = Vec::new();
        for r in 0..rays {
            let (e, w) = random_pdf(bins, 100 + r as u64);
            edges.extend(e);
            weights.extend(w);
        }
        let mut out = vec![0.0; rays * count];
        sample_pdf(&edges, &weights, bins, 1e-5, count, Some(9), &mut out);
        let mut single = vec![0.0; rays * count];
        with_threads(1, || {
            sample_pdf(&edges, &weights, bins, 1e-5, count, Some(9), &mut single)
        });
        assert_eq!(out, single);
        assert_valid(&edges, &weights, bins, 1e-5, &out, count);
        // Without jitter a ray's samples do not depend on its index or its
        // neighbours: ray 137 alone (as ray 0) gives what it gave in the
        // batch.
        let r = 137;
        let mut alone = vec![0.0; count];
        let e = &edges[r * (bins + 1)..(r + 1) * (bins + 1)];
        let w = &weights[r * bins..(r + 1) * bins];
        sample_pdf(e, w, bins, 1e-5, count, None, &mut alone);
        let mut batch = vec![0.0; rays * count];
        sample_pdf(&edges, &weights, bins, 1e-5, count, None, &mut batch);
        assert_eq!(
            alone,
            batch[r * count..(r + 1) * count],
            "without jitter, a ray ignores its index"
        );
    }

    /// Equal-width edges 0..B.
    fn unit_edges(bins: usize) -> Vec<f32> {
        (0..=bins).map(|i| i as f32).collect()
    }

    /// Samples per bin of equal-width edges 0..B (a sample on an edge
    /// counts for the bin it ends).
    fn per_bin(samples: &[f32], bins: usize) -> Vec<usize> {
        let mut counts = vec![0; bins];
        for &x in samples {
            counts[((x.ceil() as usize).max(1) - 1).min(bins - 1)] += 1;
        }
        counts
    }

    #[test]
    fn sample_pdf_degenerate_weights() {
        let bins = 16;
        let count = 256;
        let edges = unit_edges(bins);
        for jitter in [None, Some(3)] {
            let run = |weights: &[f32], padding: f32| {
                let mut out = vec![0.0; count];
                sample_pdf(&edges, weights, bins, padding, count, jitter, &mut out);
                assert_valid(&edges, weights, bins, padding, &out, count);
                out
            };
            // Stratified u put count/B ± 1 samples in each bin of an
            // equal-mass pdf: every bin's CDF interval of length 1/B holds
            // the u_k of count/B strata, give or take the two it cuts.
            let assert_even = |out: &[f32], what: &str| {
                for (i, &c) in per_bin(out, bins).iter().enumerate() {
                    assert!(
                        c.abs_diff(count / bins) <= 1,
                        "{what}, {jitter:?}: bin {i} has {c}"
                    );
                }
            };
            let zero = vec![0.0f32; bins];
            let fallback = run(&zero, 0.0);
            assert_even(&fallback, "all zero, no padding");
            assert_even(&run(&zero, 1e-5), "all zero, padding");
            assert_even(&run(&vec![1e-30; bins], 0.0), "1e-30 everywhere");
            // Weights past what a sum can hold fall back to equal masses.
            assert_even(&run(&vec![f32::MAX; bins], 0.0), "f32::MAX everywhere");

            // One spike: with no padding every sample lands in its bin.
            let mut spike = zero.clone();
            spike[5] = 0.7;
            for &x in &run(&spike, 0.0) {
                assert!(
                    (5.0..=6.0).contains(&x),
                    "{jitter:?}: {x} outside the spike's bin"
                );
            }
            // With padding p the spike's bin holds (0.7 + p)/(0.7 + B p) of
            // the mass, so at least that · count − 1 samples (stratified u:
            // an interval of CDF length m holds ≥ m·count − 1 of the u_k).
            let p = 0.01f32;
            let in_spike = run(&spike, p)
                .iter()
                .filter(|&&x| (5.0..=6.0).contains(&x))
                .count();
            let mass = (0.7 + p as f64) / (0.7 + bins as f64 * p as f64);
            assert!(
                in_spike as f64 >= mass * count as f64 - 1.0,
                "{jitter:?}: {in_spike} in the spike"
            );
            let unit_spike = {
                let mut w = zero.clone();
                w[5] = 1.0;
                w
            };
            let in_unit = run(&unit_spike, p)
                .iter()
                .filter(|&&x| (5.0..=6.0).contains(&x))
                .count();
            // The bound asked of a unit spike, (1 − B p/(1 + B p))·count =
            // 220.7, is below (1 + p)/(1 + B p)·count − 1 = 221.9 (B = 16,
            // p = 0.01, count = 256), so the ±1 of stratification fits.
            let bp = bins as f64 * p as f64;
            assert!(
                in_unit as f64 >= (1.0 - bp / (1.0 + bp)) * count as f64,
                "{jitter:?}: {in_unit} of {count} in a unit spike with padding {p}"
            );

            // NaN, ±∞, negative and subnormal weights count as zero: the
            // samples are those of the weights with zeros in their place.
            let mut rng = Pcg32::new(4, 4);
            let clean: Vec<f32> = (0..bins).map(|_| rng.next_f32()).collect();
            let mut dirty = clean.clone();
            let mut zeroed = clean.clone();
            for (i, bad) in [
                (1, f32::NAN),
                (4, -0.5),
                (7, f32::INFINITY),
                (8, f32::NEG_INFINITY),
                (12, 1e-40),
            ] {
                dirty[i] = bad;
                zeroed[i] = 0.0;
            }
            for padding in [0.0, 1e-5] {
                assert_eq!(
                    run(&dirty, padding),
                    run(&zeroed, padding),
                    "{jitter:?}, padding {padding}"
                );
            }
            let mut all_nan = vec![f32::NAN; bins];
            all_nan[0] = -1.0;
            assert_eq!(run(&all_nan, 0.0), fallback, "nothing valid: equal masses");
        }
    }

    #[test]
    fn sample_pdf_zero_width_bins() {
        // Repeated edges: bins of zero width, some with weight. Samples stay
        // finite, sorted and inside the edges; a zero-width bin with mass
        // puts its samples on its edge, which is where its mass is.
        let edges = [0.0f32, 1.0, 1.0, 1.0, 2.0, 3.0, 3.0, 4.0, 4.0];
        let bins = edges.len() - 1;
        let weights = [0.1f32, 0.5, 0.0, 0.2, 0.0, 0.3, 0.1, 0.0];
        let count = 200;
        for jitter in [None, Some(8)] {
            for padding in [0.0, 1e-5, 0.01] {
                let mut out = vec![0.0; count];
                sample_pdf(&edges, &weights, bins, padding, count, jitter, &mut out);
                assert_valid(&edges, &weights, bins, padding, &out, count);
                // Bin 1 (zero width at 1.0) holds 0.5/1.2 of the mass when
                // unpadded: that many samples, ± 1, sit exactly on 1.0
                // (bin 0's top edge adds at most one more).
                if padding == 0.0 {
                    let at_one = out.iter().filter(|&&x| x == 1.0).count() as f64;
                    let expected = 0.5 / 1.2 * count as f64;
                    assert!(
                        (at_one - expected).abs() <= 2.0,
                        "{jitter:?}: {at_one} at 1.0, expected {expected}"
                    );
                }
            }
        }
        // Every edge equal: one point.
        let mut out = vec![0.0; 10];
        sample_pdf(&[2.5; 4], &[0.0, 1.0, 0.0], 3, 0.0, 10, Some(1), &mut out);
        assert!(out.iter().all(|&x| x == 2.5), "{out:?}");
    }

    #[test]
    fn merge_sorted_is_a_sorted_permutation() {
        let mut rng = Pcg32::new(6, 6);
        let rays = 200;
        let (na, nb) = (13, 29);
        // Values on a coarse grid so that ties between and within the sets
        // occur.
        let mut draw = |n: usize| {
            let mut v: Vec<f32> = (0..rays * n)
                .map(|_| (rng.below(40) as f32) * 0.25)
                .collect();
            v.chunks_mut(n).for_each(|row| row.sort_by(f32::total_cmp));
            v
        };
        let a = draw(na);
        let b = draw(nb);
        let mut out = vec![0.0; rays * (na + nb)];
        merge_sorted(&a, na, &b, nb, &mut out);
        for r in 0..rays {
            let row = &out[r * (na + nb)..(r + 1) * (na + nb)];
            assert!(is_sorted(row), "ray {r}");
            let mut union: Vec<f32> = a[r * na..(r + 1) * na]
                .iter()
                .chain(&b[r * nb..(r + 1) * nb])
                .copied()
                .collect();
            union.sort_by(f32::total_cmp);
            assert_eq!(row, union, "ray {r}");
        }
        // One side empty.
        let mut copy = vec![0.0; rays * na];
        merge_sorted(&a, na, &[], 0, &mut copy);
        assert_eq!(copy, a);
    }

    #[test]
    fn blur_weights_spreads_a_spike() {
        // w = (0, 0, 1, 0, 0): maxes of neighbours (0, 0, 1, 1, 0, 0), so
        // w' = (0, ½, 1, ½, 0); exact in f32.
        let mut out = [9.0; 5];
        blur_weights(&[0.0, 0.0, 1.0, 0.0, 0.0], 5, &mut out);
        assert_eq!(out, [0.0, 0.5, 1.0, 0.5, 0.0]);
        // At the border the padding repeats the edge value.
        let mut out = [9.0; 3];
        blur_weights(&[2.0, 0.0, 0.0], 3, &mut out);
        assert_eq!(out, [2.0, 1.0, 0.0]);
        let mut out = [9.0; 8];
        blur_weights(&[0.0; 8], 4, &mut out);
        assert_eq!(out, [0.0; 8], "all zero stays zero");
        let mut out = [9.0; 2];
        blur_weights(&[0.3, 0.7], 1, &mut out);
        assert_eq!(out, [0.3, 0.7], "one bin per ray: unchanged");
        // Random rows against the formula in f64: ½(a + b) of f32 values
        // rounds once, so they agree to half an ulp.
        let mut rng = Pcg32::new(8, 8);
        let bins = 11;
        let w: Vec<f32> = (0..300 * bins).map(|_| rng.next_f32()).collect();
        let mut out = vec![0.0; w.len()];
        blur_weights(&w, bins, &mut out);
        for (row, blurred) in w.chunks(bins).zip(out.chunks(bins)) {
            for i in 0..bins {
                let at = |j: isize| row[j.clamp(0, bins as isize - 1) as usize] as f64;
                let i = i as isize;
                let expected = 0.5 * (at(i - 1).max(at(i)) + at(i).max(at(i + 1)));
                let got = blurred[i as usize] as f64;
                assert!(
                    (got - expected).abs() <= expected * f32::EPSILON as f64 / 2.0,
                    "{got} vs {expected}"
                );
            }
        }
    }

    #[test]
    fn intervals_end_at_far() {
        let mut rng = Pcg32::new(10, 10);
        let rays = 100;
        let n = 48;
        let near: Vec<f32> = (0..rays).map(|_| 1.0 + rng.next_f32()).collect();
        let far: Vec<f32> = near
            .iter()
            .map(|&n| n + 0.5 + 5.0 * rng.next_f32())
            .collect();
        let mut t = vec![0.0; rays * n];
        stratified(&near, &far, n, Some(2), &mut t);
        let mut dt = vec![0.0; rays * n];
        intervals_to_far(&t, &far, n, &mut dt);
        for r in 0..rays {
            let (t, dt) = (&t[r * n..(r + 1) * n], &dt[r * n..(r + 1) * n]);
            assert!(dt.iter().all(|&d| d >= 0.0), "ray {r}");
            assert_eq!(dt[n - 1], far[r] - t[n - 1]);
            // Each difference rounds by half an ulp of values ≤ far: the
            // telescoping sum is off by at most n/2 ulp(far).
            let sum: f64 = dt.iter().map(|&d| d as f64).sum();
            let expected = far[r] as f64 - t[0] as f64;
            let bound = n as f64 * 0.5 * f32::EPSILON as f64 * far[r] as f64;
            assert!(
                (sum - expected).abs() <= bound,
                "ray {r}: Σdt {sum}, far − t0 {expected}"
            );
        }
        // A last sample beyond far gets an empty interval, not a negative one.
        let mut dt = [0.0; 3];
        intervals_to_far(&[1.0, 2.0, 4.0], &[3.0], 3, &mut dt);
        assert_eq!(dt, [1.0, 2.0, 0.0]);
    }
}
