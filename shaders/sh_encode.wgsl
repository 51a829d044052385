// Real spherical harmonics of unit directions, bands l < degree (degree ≤ 4,
// degree² coefficients), the basis, order and constants of
// src/engine/cpu/sh.rs (which derives them). Row r's coefficients go to
// output[r · stride + offset ...], so they can land inside a wider matrix.

struct Params {
    rows: u32,
    degree: u32,
    stride: u32,
    offset: u32,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> directions: array<f32>;
@group(0) @binding(2) var<storage, read_write> output: array<f32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let r = id.x + id.y * groups.x * 64u;
    if (r >= params.rows) {
        return;
    }
    let x = directions[3u * r];
    let y = directions[3u * r + 1u];
    let z = directions[3u * r + 2u];
    let o = r * params.stride + params.offset;
    output[o] = 0.28209479177387814;
    if (params.degree <= 1u) {
        return;
    }
    output[o + 1u] = -0.4886025119029199 * y;
    output[o + 2u] = 0.4886025119029199 * z;
    output[o + 3u] = -0.4886025119029199 * x;
    if (params.degree <= 2u) {
        return;
    }
    let xx = x * x;
    let yy = y * y;
    let zz = z * z;
    output[o + 4u] = 1.0925484305920792 * x * y;
    output[o + 5u] = -1.0925484305920792 * y * z;
    output[o + 6u] = 0.9461746957575601 * zz - 0.31539156525252005;
    output[o + 7u] = -1.0925484305920792 * x * z;
    output[o + 8u] = 0.5462742152960395 * (xx - yy);
    if (params.degree <= 3u) {
        return;
    }
    output[o + 9u] = 0.5900435899266435 * y * (yy - 3.0 * xx);
    output[o + 10u] = 2.890611442640554 * x * y * z;
    output[o + 11u] = 0.4570457994644658 * y * (1.0 - 5.0 * zz);
    output[o + 12u] = 0.3731763325901154 * z * (5.0 * zz - 3.0);
    output[o + 13u] = 0.4570457994644658 * x * (1.0 - 5.0 * zz);
    output[o + 14u] = 1.445305721320277 * z * (xx - yy);
    output[o + 15u] = 0.5900435899266435 * x * (3.0 * yy - xx);
}
