// Activations shared by the dense-layer kernels (prepended to each of them
// by src/engine/gpu/dense.rs). Codes match the Rust side: 0 none, 1 ReLU,
// 2 sigmoid, 3 exp with the input clamped to ≤ exp_clamp.

fn activate(x: f32, kind: u32, exp_clamp: f32) -> f32 {
    switch kind {
        case 1u: { return max(x, 0.0); }
        case 2u: { return 1.0 / (1.0 + exp(-x)); }
        case 3u: { return exp(min(x, exp_clamp)); }
        default: { return x; }
    }
}

// The derivative at the input that produced output y (every activation here
// can be differentiated from its output, as on the cpu).
fn activation_derivative(y: f32, kind: u32, exp_clamp: f32) -> f32 {
    switch kind {
        case 1u: { return select(0.0, 1.0, y > 0.0); }
        case 2u: { return y * (1.0 - y); }
        case 3u: { return select(0.0, y, y < exp(exp_clamp)); }
        default: { return 1.0; }
    }
}

struct Layer {
    rows: u32,
    in_width: u32,
    out_width: u32,
    activation: u32,
    // Offsets into the parameter buffer, in f32s; bias_offset is
    // 0xffffffff without a bias.
    weight_offset: u32,
    bias_offset: u32,
    // Weight gradients: rows per partial sum, and partial sums.
    rows_per_chunk: u32,
    chunks: u32,
    exp_clamp: f32,
    // The first chunk of this dispatch among the layer's partial sums.
    first_chunk: u32,
    _pad1: u32,
    _pad2: u32,
}

const NO_BIAS: u32 = 0xffffffffu;

// Every kernel computes a BLOCK × BLOCK tile of its result with 256 threads,
// each thread a 4 × 4 piece of it held in registers, and steps through the
// reduction DEPTH at a time, staged through workgroup memory as vec4s so a
// thread reads its four rows and its four columns with one load each: 16
// multiply-adds per two loads, where one output per thread took two loads
// per multiply-add.
const BLOCK: u32 = 64u;
const DEPTH: u32 = 16u;
// vec4s per DEPTH row of a staged tile.
const QUADS: u32 = 16u;

// The partial sums of the weight gradients are taken over chunks of rows
// that are a multiple of DEPTH (src/engine/gpu/dense.rs).

// Row tiles may exceed the 65535 workgroups of one dimension: they are
// spread over y and z.
fn row_tile(workgroup: vec3<u32>, groups: vec3<u32>) -> u32 {
    return workgroup.y + workgroup.z * groups.y;
}
