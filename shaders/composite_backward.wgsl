// Volume rendering of a batch of rays, backward for a loss on the colours:
// one invocation per ray (the cpu engine's
// `engine::cpu::composite_batch::composite_backward`). A forward walk
// finds the cut and keeps each sample's transmittance Tₖ in `d_density`;
// the backward walk then forms, from the back of the ray,
//   ∂L/∂τₖ = Tₖ₊₁ gₖ − (Σ_{k<i<cut} wᵢ gᵢ + T_cut ∂L/∂rgb · background)
// with gₖ = ∂L/∂rgb · cₖ, so nothing large is subtracted from. With a
// distortion weight λ′ > 0, gₖ gains the distortion loss's ∂L/∂wₖ,
//   λ′ (2 (sₖ W_<k − S_<k + S_>k − sₖ W_>k) + ⅔ wₖ δₖ),  s = t · distance_scale,
// with W_<k = 1 − Tₖ, W_>k = Tₖ₊₁ − T_cut and S the sums of wⱼ sⱼ.

struct Params {
    ray_count: u32,
    row_stride: u32,
    min_transmittance: f32,
    distortion_weight: f32,
    distance_scale: f32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> density: array<f32>;
@group(0) @binding(2) var<storage, read> rgb: array<f32>;
@group(0) @binding(3) var<storage, read> dt: array<f32>;
@group(0) @binding(4) var<storage, read> ray_offsets: array<u32>;
@group(0) @binding(5) var<storage, read> background: array<f32>;
@group(0) @binding(6) var<storage, read> d_rgb: array<f32>;
@group(0) @binding(7) var<storage, read_write> d_density: array<f32>;
@group(0) @binding(8) var<storage, read_write> d_colour: array<f32>;
@group(0) @binding(9) var<storage, read_write> d_background: array<f32>;
@group(0) @binding(10) var<storage, read> t: array<f32>;

// one_minus_exp_neg comes from volume_common.wgsl.

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let ray = id.x + id.y * params.row_stride;
    if (ray >= params.ray_count) {
        return;
    }
    let start = ray_offsets[ray];
    let end = ray_offsets[ray + 1u];
    let grad = vec3<f32>(d_rgb[3u * ray], d_rgb[3u * ray + 1u], d_rgb[3u * ray + 2u]);

    let distortion = params.distortion_weight > 0.0;
    var accumulated = 0.0;
    var used = end - start;
    var moment_total = 0.0;
    for (var s = start; s < end; s++) {
        let transmittance = exp(-accumulated);
        if (transmittance < params.min_transmittance) {
            used = s - start;
            break;
        }
        d_density[s] = transmittance;
        let tau = max(density[s] * dt[s], 0.0);
        if (distortion) {
            moment_total += transmittance * one_minus_exp_neg(tau) * t[s] * params.distance_scale;
        }
        accumulated += tau;
    }
    let final_transmittance = exp(-accumulated);
    // Samples after the cut are not part of the model: zero gradient.
    for (var s = start + used; s < end; s++) {
        d_density[s] = 0.0;
        d_colour[3u * s] = 0.0;
        d_colour[3u * s + 1u] = 0.0;
        d_colour[3u * s + 2u] = 0.0;
    }

    let bg = vec3<f32>(background[3u * ray], background[3u * ray + 1u], background[3u * ray + 2u]);
    var behind = final_transmittance * (grad.x * bg.x + grad.y * bg.y + grad.z * bg.z);
    var transmittance_after = final_transmittance;
    var moment_after = 0.0;
    for (var k = used; k > 0u; k--) {
        let s = start + k - 1u;
        let transmittance = d_density[s];
        let optical = density[s] * dt[s];
        let weight = transmittance * one_minus_exp_neg(max(optical, 0.0));
        let c = vec3<f32>(rgb[3u * s], rgb[3u * s + 1u], rgb[3u * s + 2u]);
        var g = grad.x * c.x + grad.y * c.y + grad.z * c.z;
        if (distortion) {
            let distance = t[s] * params.distance_scale;
            let weight_before = 1.0 - transmittance;
            let weight_after = transmittance_after - final_transmittance;
            let moment_before = moment_total - moment_after - weight * distance;
            let spread = distance * weight_before - moment_before + moment_after
                - distance * weight_after;
            let own = 2.0 / 3.0 * weight * dt[s] * params.distance_scale;
            g += params.distortion_weight * (2.0 * spread + own);
            moment_after += weight * distance;
        }
        let d_tau = transmittance_after * g - behind;
        // Negative densities were clamped to empty space: no gradient.
        d_density[s] = select(0.0, dt[s] * d_tau, optical >= 0.0);
        d_colour[3u * s] = weight * grad.x;
        d_colour[3u * s + 1u] = weight * grad.y;
        d_colour[3u * s + 2u] = weight * grad.z;
        behind += weight * g;
        transmittance_after = transmittance;
    }
    d_background[3u * ray] = final_transmittance * grad.x;
    d_background[3u * ray + 1u] = final_transmittance * grad.y;
    d_background[3u * ray + 2u] = final_transmittance * grad.z;
}
