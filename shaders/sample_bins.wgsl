// The bins NeRF's importance sampler draws from, one invocation per ray, as
// `importance_samples` in `engine::cpu::model` (the reference's
// `sample_pdf` call in run_nerf.py): the edges are the midpoints between
// the previous level's `samples` sorted samples (samples − 1 per ray), and
// each bin's weight is that of the interior sample it surrounds (the first
// and last samples have no bin of their own), samples − 2 per ray.

@group(0) @binding(1) var<storage, read> t: array<f32>;
@group(0) @binding(2) var<storage, read> weights: array<f32>;
@group(0) @binding(3) var<storage, read_write> edges: array<f32>;
@group(0) @binding(4) var<storage, read_write> bin_weights: array<f32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let r = ray_index(id);
    if (r >= params.rays) {
        return;
    }
    let m = params.samples;
    for (var i = 0u; i + 1u < m; i++) {
        edges[r * (m - 1u) + i] = 0.5 * (t[r * m + i] + t[r * m + i + 1u]);
    }
    for (var i = 0u; i + 2u < m; i++) {
        bin_weights[r * (m - 2u) + i] = weights[r * m + i + 1u];
    }
}
