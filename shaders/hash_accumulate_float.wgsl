// Gradient accumulation with native f32 atomics (wgpu feature
// SHADER_FLOAT32_ATOMIC: `atomic<f32>` in storage, with atomicAdd).

@group(0) @binding(4) var<storage, read_write> d_params: array<atomic<f32>>;

fn add_gradient(i: u32, value: f32) {
    atomicAdd(&d_params[i], value);
}
