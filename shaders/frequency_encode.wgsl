// Frequency (positional) encoding of 3-D points, and its integrated form for
// Gaussians: the formulas, sources, layout and accuracy argument are in
// src/engine/cpu/frequency.rs. Row r of the output: [x y z] when
// include_input, then for l = 0 .. L-1 the six values
// [sin(2^l x), sin(2^l y), sin(2^l z), cos(2^l x), cos(2^l y), cos(2^l z)],
// each multiplied by exp(-1/2 * 4^l * var) in `main_integrated`
// (Mip-NeRF, internal/mip.py `integrated_pos_enc`).

struct Params {
    rows: u32,
    frequencies: u32,
    include_input: u32,
    width: u32,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> inputs: array<f32>;
@group(0) @binding(2) var<storage, read_write> output: array<f32>;
// Only bound for main_integrated (the pipelines' layouts are derived from
// the entry points, so main has no binding 3).
@group(0) @binding(3) var<storage, read> variance: array<f32>;

// 2^e for -126 <= e <= 127, built from its bits: exact, where WGSL's exp2
// only promises 3 + 2|e| ulp. Multiplying by it is exact too, so the angle
// 2^l * x is the exact real number, as on the cpu engine.
fn power_of_two(e: i32) -> f32 {
    return bitcast<f32>(u32(e + 127) << 23u);
}

// exp(-t) for t >= 0, with t clamped: WGSL does not promise IEEE infinities
// (an implementation may assume there are none), so an overflowing
// 1/2 * 4^l * var must not reach exp as +inf. exp(-104) is already below
// the smallest f32 subnormal, so the clamp changes no result.
fn damping(t: f32) -> f32 {
    return exp(-min(t, 104.0));
}

fn row_index(id: vec3<u32>, groups: vec3<u32>) -> u32 {
    return id.x + id.y * groups.x * 64u;
}

// Row r; `v` is only read when `integrated`. The variance is read by the
// caller, so that `main` does not use binding 3 at all.
fn encode(r: u32, integrated: bool, v: vec3<f32>) {
    let x = vec3<f32>(inputs[3u * r], inputs[3u * r + 1u], inputs[3u * r + 2u]);
    var o = r * params.width;
    if (params.include_input != 0u) {
        output[o] = x.x;
        output[o + 1u] = x.y;
        output[o + 2u] = x.z;
        o += 3u;
    }
    for (var l = 0u; l < params.frequencies; l++) {
        let angle = x * power_of_two(i32(l));
        var s = sin(angle);
        var c = cos(angle);
        if (integrated) {
            // 1/2 * 4^l = 2^(2l - 1): exact, as is its product with var.
            let t = v * power_of_two(2 * i32(l) - 1);
            let w = vec3<f32>(damping(t.x), damping(t.y), damping(t.z));
            s *= w;
            c *= w;
        }
        output[o] = s.x;
        output[o + 1u] = s.y;
        output[o + 2u] = s.z;
        output[o + 3u] = c.x;
        output[o + 4u] = c.y;
        output[o + 5u] = c.z;
        o += 6u;
    }
}

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let r = row_index(id, groups);
    if (r >= params.rows) {
        return;
    }
    encode(r, false, vec3<f32>(0.0));
}

@compute @workgroup_size(64)
fn main_integrated(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let r = row_index(id, groups);
    if (r >= params.rows) {
        return;
    }
    encode(r, true, vec3<f32>(variance[3u * r], variance[3u * r + 1u], variance[3u * r + 2u]));
}
