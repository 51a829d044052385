// Volume-rendering helpers shared by the compositing kernels
// (composite_forward, composite_backward, composite_weights, prepended to
// each by `engine::gpu::composite`; render_composite, by
// `engine::gpu::render`).

// 1 − e^{−τ} for τ ≥ 0. WGSL has no expm1, and 1 − exp(−τ) loses all
// digits as τ → 0 (τ = 1e-6 would be 6% off), so small τ use the Taylor
// series to τ⁸: the first term left out, τ⁹/9!, is below 4e-11 of the
// result for τ < 0.25, and from τ = 0.25 on the subtraction loses at most
// a factor 1/(1 − e^{−0.25}) ≈ 4.5 on exp's error.
fn one_minus_exp_neg(tau: f32) -> f32 {
    if (tau < 0.25) {
        return tau * (1.0 - tau / 2.0 * (1.0 - tau / 3.0 * (1.0 - tau / 4.0 * (1.0 - tau / 5.0
            * (1.0 - tau / 6.0 * (1.0 - tau / 7.0 * (1.0 - tau / 8.0)))))));
    }
    return 1.0 - exp(-tau);
}
