// Photometric loss per ray and its gradient (the cpu engine's
// `engine::cpu::loss`): with d = predicted − target per channel,
//   Huber: ½ d²/δ if |d| ≤ δ, else |d| − ½ δ;  gradient d/δ or sign(d)
//   L2:    d²;                                 gradient 2d
// (instant-ngp's `huber_loss` and `l2_loss`). Everything is scaled by
// 1/(3R), so the per-ray values sum to the mean over rays × channels and
// the gradient is that of the mean. The gradient (not the value) is further
// multiplied by `gradient_weight`: a model with levels, or with rays in
// chunks, weights each part's mean (the cpu engine's `CpuModel` scales its
// `d_rgb` the same way, after the 1/(3R)).

struct Params {
    ray_count: u32,
    row_stride: u32,
    // 0: Huber, 1: L2.
    kind: u32,
    huber_delta: f32,
    scale: f32,
    gradient_weight: f32,
    _pad1: u32,
    _pad2: u32,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> predicted: array<f32>;
@group(0) @binding(2) var<storage, read> target_rgb: array<f32>;
@group(0) @binding(3) var<storage, read_write> gradient: array<f32>;
@group(0) @binding(4) var<storage, read_write> ray_loss: array<f32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let ray = id.x + id.y * params.row_stride;
    if (ray >= params.ray_count) {
        return;
    }
    var sum = 0.0;
    for (var c = 0u; c < 3u; c++) {
        let i = 3u * ray + c;
        let d = predicted[i] - target_rgb[i];
        var value: f32;
        var derivative: f32;
        if (params.kind == 1u) {
            value = d * d;
            derivative = d + d;
        } else if (abs(d) <= params.huber_delta) {
            value = 0.5 * d * d / params.huber_delta;
            derivative = d / params.huber_delta;
        } else {
            value = abs(d) - 0.5 * params.huber_delta;
            derivative = sign(d);
        }
        gradient[i] = (derivative * params.scale) * params.gradient_weight;
        sum += value;
    }
    ray_loss[ray] = sum * params.scale;
}
