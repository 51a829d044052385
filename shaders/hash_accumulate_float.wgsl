// Gradient accumulation with native f32 atomics (wgpu feature
// SHADER_FLOAT32_ATOMIC: `atomic<f32>` in storage, with atomicAdd). The
// kernel that appends it declares `d_params: array<GradientCell>` at its
// own binding.

alias GradientCell = atomic<f32>;

fn add_gradient(i: u32, value: f32) {
    atomicAdd(&d_params[i], value);
}
