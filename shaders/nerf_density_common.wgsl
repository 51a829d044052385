// NeRF's density activations (src/engine/cpu/fields/nerf.rs,
// `DensityActivation`), prepended to nerf_density.wgsl and
// nerf_density_backward.wgsl: code 0 is max(x, 0) (NeRF's `raw2outputs`),
// code 1 softplus(x − shift) (Mip-NeRF's `density_bias`).

struct Params {
    rows: u32,
    // Invocations per row of the dispatch grid.
    row_stride: u32,
    // Floats per row of trunk B's output [σ_raw | feature].
    raw_stride: u32,
    // Feature columns (trunk B's output width − 1).
    feature_width: u32,
    // Floats per row of the colour input's gradient [d feature | d γ(d)].
    colour_stride: u32,
    activation: u32,
    shift: f32,
    _pad: u32,
}

// log(1 + z) for 0 ≤ z ≤ 1 without WGSL's log, whose error near 1 is only
// bounded absolutely (2^-21): log(1 + z) = 2 atanh(t) with t = z / (2 + z)
// ≤ 1/3, and atanh(t) = t + t³/3 + t⁵/5 + … (Abramowitz & Stegun 4.5.6 and
// 4.6.22). Nine terms leave a truncation of (1/9)^9 / 19 < 2e-10 relative,
// below f32 rounding.
fn log1p_unit(z: f32) -> f32 {
    let t = z / (2.0 + z);
    let t2 = t * t;
    var s = 1.0 / 17.0;
    for (var k = 7; k >= 0; k--) {
        s = 1.0 / f32(2 * k + 1) + t2 * s;
    }
    return 2.0 * t * s;
}

// softplus(x) = log(1 + eˣ) = max(x, 0) + log(1 + e^−|x|): the exponent is
// never positive, so nothing overflows (WGSL promises no infinities).
fn softplus(x: f32) -> f32 {
    return max(x, 0.0) + log1p_unit(exp(-abs(x)));
}

// σ(x) = 1 / (1 + e^−x), again through e^−|x| only.
fn sigmoid(x: f32) -> f32 {
    let e = exp(-abs(x));
    return select(e, 1.0, x >= 0.0) / (1.0 + e);
}

fn density(raw: f32) -> f32 {
    if (params.activation == 1u) {
        return softplus(raw - params.shift);
    }
    return max(raw, 0.0);
}

// dσ/d raw: the ReLU's step (0 at 0, as the cpu engine), or the sigmoid,
// softplus's derivative.
fn density_derivative(raw: f32) -> f32 {
    if (params.activation == 1u) {
        return sigmoid(raw - params.shift);
    }
    return select(0.0, 1.0, raw > 0.0);
}
