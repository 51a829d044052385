//! What both engines' stratified samplers share: the step between a ray's
//! evenly spaced samples, computed once on the host so the `cpu` engine's
//! `engine::cpu::sampling::stratified` and the `gpu` engine's kernel space
//! their samples with the same number.

/// 1/(N − 1), the linspace step (0 for a single sample); the gpu engine
/// passes this same value to its kernel.
pub fn stratified_step(samples_per_ray: usize) -> f32 {
    if samples_per_ray > 1 {
        1.0 / (samples_per_ray - 1) as f32
    } else {
        0.0
    }
}
