// Pass 1 of the march: samples per ray (`march_common.wgsl` is prepended).

@group(0) @binding(0) var<uniform> params: MarchParams;
@group(0) @binding(1) var<storage, read> bitfield: array<u32>;
@group(0) @binding(2) var<storage, read> origins: array<f32>;
@group(0) @binding(3) var<storage, read> directions: array<f32>;
@group(0) @binding(4) var<storage, read_write> counts: array<u32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let ray = id.x + id.y * params.row_stride;
    if (ray >= params.ray_count) {
        return;
    }
    let m = prepare(ray);
    var emitted = 0u;
    if (m.hit) {
        var k = 0u;
        loop {
            let s = lattice_s(m, k);
            if (!(s <= m.s_exit) || emitted == params.max_samples) {
                break;
            }
            let c = cell_of(lattice_position(m, s));
            let next = max(exit_index(m, c), k + 1u);
            if (is_occupied(c)) {
                // Lattice points k..next all lie in this cell: count those
                // inside the box, up to the limit.
                loop {
                    if (k >= next || !(lattice_s(m, k) <= m.s_exit) || emitted == params.max_samples) {
                        break;
                    }
                    emitted += 1u;
                    k += 1u;
                }
            }
            k = max(k, next);
        }
    }
    counts[ray] = emitted;
}
