// Merges two per-ray sorted sample sets, one invocation per ray, as
// `engine::cpu::sampling::merge_sorted` (ties take `a` first).

@group(0) @binding(1) var<storage, read> a: array<f32>;
@group(0) @binding(2) var<storage, read> b: array<f32>;
@group(0) @binding(3) var<storage, read_write> merged: array<f32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let r = ray_index(id);
    if (r >= params.rays) {
        return;
    }
    let na = params.samples;
    let nb = params.bins;
    var i = 0u;
    var j = 0u;
    let o = r * (na + nb);
    for (var k = 0u; k < na + nb; k++) {
        if (j == nb || (i < na && a[r * na + i] <= b[r * nb + j])) {
            merged[o + k] = a[r * na + i];
            i += 1u;
        } else {
            merged[o + k] = b[r * nb + j];
            j += 1u;
        }
    }
}
