// The cpu's arithmetic, bit for bit, for the kernels that must find the
// cpu engine's numbers (the march: march_common.wgsl; the sampling and
// frustum kernels: sample_common.wgsl), prepended to each. The including
// shader declares a uniform `params` with a `zero: u32` member that the
// host sets to 0.

// x, hidden from the shader compiler (XOR with the uniform 0), so that a
// product passed through it is rounded on its own before the sum it feeds
// and never fused into one fma, as the cpu rounds it.
fn unfused(x: f32) -> f32 {
    return bitcast<f32>(bitcast<u32>(x) ^ params.zero);
}

// The murmur3 32-bit finaliser, as `engine::cpu::march::mix32`.
fn mix32(x0: u32) -> u32 {
    var x = x0;
    x ^= x >> 16u;
    x *= 0x85ebca6bu;
    x ^= x >> 13u;
    x *= 0xc2b2ae35u;
    return x ^ (x >> 16u);
}
