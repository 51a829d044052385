// One Adam step, one invocation per parameter (the host's reference,
// `engine::shared::adam`, as tiny-cuda-nn runs it for instant-ngp):
// network weights [network_start, network_end) get L2 regularisation and
// are always updated; every other parameter is a hash-table entry, left
// alone (value, moments, bias-correction denominators) where its gradient
// is exactly zero. m_norm = 1 − β₁ˢ and v_norm = 1 − β₂ˢ follow the
// parameter's own step count s by the moments' own recurrence.

struct Params {
    count: u32,
    row_stride: u32,
    network_start: u32,
    network_end: u32,
    learning_rate: f32,
    beta1: f32,
    beta2: f32,
    one_minus_beta1: f32,
    one_minus_beta2: f32,
    epsilon: f32,
    l2: f32,
    // Elements at the binding's start that belong to the span before (a
    // span off the storage-binding alignment is bound from the aligned
    // offset below it): left alone.
    first: u32,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read_write> weights: array<f32>;
@group(0) @binding(2) var<storage, read> gradients: array<f32>;
@group(0) @binding(3) var<storage, read_write> m: array<f32>;
@group(0) @binding(4) var<storage, read_write> v: array<f32>;
@group(0) @binding(5) var<storage, read_write> m_norm: array<f32>;
@group(0) @binding(6) var<storage, read_write> v_norm: array<f32>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let i = id.x + id.y * params.row_stride;
    if (i < params.first || i >= params.count) {
        return;
    }
    var g = gradients[i];
    let p = weights[i];
    if (i >= params.network_start && i < params.network_end) {
        g += params.l2 * p;
    } else if (g == 0.0) {
        return;
    }
    let m_new = params.beta1 * m[i] + params.one_minus_beta1 * g;
    let v_new = params.beta2 * v[i] + params.one_minus_beta2 * (g * g);
    let m_norm_new = params.beta1 * m_norm[i] + params.one_minus_beta1;
    let v_norm_new = params.beta2 * v_norm[i] + params.one_minus_beta2;
    weights[i] = p - params.learning_rate * (m_new / m_norm_new) / (sqrt(v_new / v_norm_new) + params.epsilon);
    m[i] = m_new;
    v[i] = v_new;
    m_norm[i] = m_norm_new;
    v_norm[i] = v_norm_new;
}
