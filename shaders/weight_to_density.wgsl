// The gradient a loss on compositing weights gives the densities, added to
// `d_sigma`, one invocation per ray, as
// `engine::cpu::weight_losses::weights_to_densities`:
// ∂L/∂σ_k = δ_k (T_{k+1} g_k − Σ_{i>k} g_i w_i), the suffix sums from the
// back into `suffix` first.

@group(0) @binding(1) var<storage, read> sigma: array<f32>;
@group(0) @binding(2) var<storage, read> dt: array<f32>;
@group(0) @binding(3) var<storage, read> weights: array<f32>;
@group(0) @binding(4) var<storage, read> d_weights: array<f32>;
@group(0) @binding(5) var<storage, read_write> suffix: array<f32>;
@group(0) @binding(6) var<storage, read_write> d_sigma: array<f32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let r = invocation(id);
    if (r >= params.count) {
        return;
    }
    let n = params.samples;
    let o = r * n;
    var later = 0.0;
    for (var k = n; k > 0u; k--) {
        suffix[o + k - 1u] = later;
        later += d_weights[o + k - 1u] * weights[o + k - 1u];
    }
    var optical_depth = 0.0;
    for (var k = 0u; k < n; k++) {
        optical_depth += max(sigma[o + k], 0.0) * dt[o + k];
        let transmittance_after = exp(-optical_depth);
        d_sigma[o + k] += dt[o + k] * (transmittance_after * d_weights[o + k] - suffix[o + k]);
    }
}
