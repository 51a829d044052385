// Rendering, one round of compositing: each active ray adds this round's
// samples (slots i·per_ray.., written by render_walk.wgsl) front to back,
// stopping where its optical depth passes −ln(min transmittance), as the
// cpu's `march_and_composite` does, and is marked done when it left the
// box, reached the sample cap or became opaque. With a crop box
// (`use_crop` 1), samples outside it have no density, as
// `engine::crop::crop_densities` sets them on the cpu.

// `RayState` comes from ray_state.wgsl.

struct Params {
    count: u32,
    row_stride: u32,
    per_ray: u32,
    max_samples: u32,
    stop_depth: f32,
    use_crop: u32,
    _pad0: u32,
    _pad1: u32,
    // The unit cube's offset (xyz) and scale (w): world = (unit − offset) / scale.
    mapping: vec4<f32>,
    // The crop box's centre and half size (world), and the rows of the
    // rotation from world axes to the box's own.
    crop_centre: vec4<f32>,
    crop_half: vec4<f32>,
    to_box: array<vec4<f32>, 3>,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> ray_list: array<u32>;
@group(0) @binding(2) var<storage, read_write> states: array<RayState>;
@group(0) @binding(3) var<storage, read> counts: array<u32>;
@group(0) @binding(4) var<storage, read> sigma: array<f32>;
@group(0) @binding(5) var<storage, read> rgb: array<f32>;
@group(0) @binding(6) var<storage, read> t: array<f32>;
// Each sample's step in world units (they grow with distance on large scenes).
@group(0) @binding(7) var<storage, read> dt: array<f32>;
// Each sample's unit-cube position (read with a crop box).
@group(0) @binding(8) var<storage, read> positions: array<f32>;

const LEFT_THE_BOX: u32 = 0x80000000u;

// `scene::crop::CropBox::contains` of the sample's world position.
fn inside_crop(s: u32) -> bool {
    let unit = vec3<f32>(positions[3u * s], positions[3u * s + 1u], positions[3u * s + 2u]);
    let world = (unit - params.mapping.xyz) / params.mapping.w;
    let d = world - params.crop_centre.xyz;
    let local = vec3<f32>(
        dot(params.to_box[0].xyz, d),
        dot(params.to_box[1].xyz, d),
        dot(params.to_box[2].xyz, d),
    );
    return all(abs(local) <= params.crop_half.xyz);
}

// one_minus_exp_neg comes from volume_common.wgsl.

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let i = id.x + id.y * params.row_stride;
    if (i >= params.count) {
        return;
    }
    let ray = ray_list[i];
    var state = states[ray];
    let n = counts[i] & ~LEFT_THE_BOX;
    let base = i * params.per_ray;
    for (var j = 0u; j < n; j++) {
        if (state.optical_depth > params.stop_depth) {
            break;
        }
        let s = base + j;
        // Negative densities are empty space, as on the cpu.
        var tau = max(sigma[s] * dt[s], 0.0);
        if (params.use_crop != 0u && !inside_crop(s)) {
            tau = 0.0;
        }
        let weight = exp(-state.optical_depth) * one_minus_exp_neg(tau);
        state.r += weight * rgb[3u * s];
        state.g += weight * rgb[3u * s + 1u];
        state.b += weight * rgb[3u * s + 2u];
        state.depth += weight * t[s];
        state.optical_depth += tau;
    }
    state.emitted += n;
    if ((counts[i] & LEFT_THE_BOX) != 0u || state.emitted >= params.max_samples
        || state.optical_depth > params.stop_depth) {
        state.done = 1u;
    }
    states[ray] = state;
}
