// Stratified samples between near and far, one invocation per ray: the
// arithmetic of `engine::cpu::sampling::stratified`, operation for
// operation (NeRF, run_nerf.py `render_rays` with `perturb`).

@group(0) @binding(1) var<storage, read> near: array<f32>;
@group(0) @binding(2) var<storage, read> far: array<f32>;
@group(0) @binding(3) var<storage, read_write> t_out: array<f32>;

// Point i of the deterministic linspace, clamped to far, far itself last.
fn linspace(n: f32, f: f32, i: u32, count: u32) -> f32 {
    if (i > 0u && i + 1u == count) {
        return f;
    }
    return min(n + unfused((f - n) * (f32(i) * params.step)), f);
}

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let r = ray_index(id);
    if (r >= params.rays) {
        return;
    }
    let count = params.samples;
    let n = near[r];
    let f = far[r];
    let ray = params.ray_base + r;
    let o = r * count;
    var previous = 0.0;
    var current = linspace(n, f, 0u, count);
    for (var i = 0u; i < count; i++) {
        var next = current;
        if (i + 1u < count) {
            next = linspace(n, f, i + 1u, count);
        }
        var t = current;
        if (params.use_jitter != 0u) {
            var lower = current;
            if (i > 0u) {
                lower = 0.5 * (previous + current);
            }
            var upper = current;
            if (i + 1u < count) {
                upper = 0.5 * (current + next);
            }
            let u = uniform01(params.seed, ray, i);
            t = min(lower + unfused((upper - lower) * u), upper);
        }
        t_out[o + i] = t;
        previous = current;
        current = next;
    }
}
