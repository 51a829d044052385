// Volume rendering of a batch of rays, forward: one invocation per ray
// walks its samples front to back (the cpu engine's
// `engine::cpu::composite_batch::composite_forward`, same arithmetic, same
// early termination: a ray stops at the first sample whose transmittance
// is below `min_transmittance`).

struct Params {
    ray_count: u32,
    // Invocations per row of the dispatch grid (rays beyond 65535
    // workgroups continue on the next row).
    row_stride: u32,
    min_transmittance: f32,
    _pad: u32,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> density: array<f32>;
@group(0) @binding(2) var<storage, read> rgb: array<f32>;
@group(0) @binding(3) var<storage, read> dt: array<f32>;
@group(0) @binding(4) var<storage, read> t: array<f32>;
@group(0) @binding(5) var<storage, read> ray_offsets: array<u32>;
@group(0) @binding(6) var<storage, read> background: array<f32>;
@group(0) @binding(7) var<storage, read_write> out_rgb: array<f32>;
@group(0) @binding(8) var<storage, read_write> out_opacity: array<f32>;
@group(0) @binding(9) var<storage, read_write> out_depth: array<f32>;
@group(0) @binding(10) var<storage, read_write> out_samples_used: array<u32>;

// one_minus_exp_neg comes from volume_common.wgsl.

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let ray = id.x + id.y * params.row_stride;
    if (ray >= params.ray_count) {
        return;
    }
    let start = ray_offsets[ray];
    let end = ray_offsets[ray + 1u];
    var colour = vec3<f32>(0.0);
    var depth = 0.0;
    var accumulated = 0.0;
    var used = end - start;
    for (var s = start; s < end; s++) {
        let transmittance = exp(-accumulated);
        if (transmittance < params.min_transmittance) {
            used = s - start;
            break;
        }
        // Negative densities are empty space, as on the cpu.
        let tau = max(density[s] * dt[s], 0.0);
        let weight = transmittance * one_minus_exp_neg(tau);
        colour += weight * vec3<f32>(rgb[3u * s], rgb[3u * s + 1u], rgb[3u * s + 2u]);
        depth += weight * t[s];
        accumulated += tau;
    }
    let final_transmittance = exp(-accumulated);
    for (var c = 0u; c < 3u; c++) {
        out_rgb[3u * ray + c] = colour[c] + final_transmittance * background[3u * ray + c];
    }
    out_opacity[ray] = 1.0 - final_transmittance;
    out_depth[ray] = depth;
    out_samples_used[ray] = used;
}
