// Each sample's compositing weight wᵢ = Tᵢ (1 − e^{−σᵢ dtᵢ}), one invocation
// per ray, as the cpu engine's `engine::cpu::composite_batch::sample_weights`:
// zero from the first sample whose transmittance is below
// `min_transmittance` on. The importance sampler draws from these.

struct Params {
    ray_count: u32,
    row_stride: u32,
    min_transmittance: f32,
    _pad: u32,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> density: array<f32>;
@group(0) @binding(2) var<storage, read> dt: array<f32>;
@group(0) @binding(3) var<storage, read> ray_offsets: array<u32>;
@group(0) @binding(4) var<storage, read_write> weights: array<f32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let ray = id.x + id.y * params.row_stride;
    if (ray >= params.ray_count) {
        return;
    }
    var accumulated = 0.0;
    var cut = false;
    for (var s = ray_offsets[ray]; s < ray_offsets[ray + 1u]; s++) {
        let transmittance = exp(-accumulated);
        cut = cut || transmittance < params.min_transmittance;
        if (cut) {
            weights[s] = 0.0;
            continue;
        }
        // Negative densities are empty space, as on the cpu.
        let tau = max(density[s] * dt[s], 0.0);
        weights[s] = transmittance * one_minus_exp_neg(tau);
        accumulated += tau;
    }
}
