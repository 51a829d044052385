// A proposal level's points: each interval's midpoint and length from each
// ray's `samples` + 1 edges, one invocation per ray, as the cpu model's
// `sample_level` for points drawn as intervals (nerfstudio's frustums'
// positions).

@group(0) @binding(1) var<storage, read> edges: array<f32>;
@group(0) @binding(2) var<storage, read_write> t: array<f32>;
@group(0) @binding(3) var<storage, read_write> dt: array<f32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let r = invocation(id);
    if (r >= params.count) {
        return;
    }
    let n = params.samples;
    for (var i = 0u; i < n; i++) {
        let e0 = edges[r * (n + 1u) + i];
        let e1 = edges[r * (n + 1u) + i + 1u];
        t[r * n + i] = 0.5 * (e0 + e1);
        dt[r * n + i] = e1 - e0;
    }
}
