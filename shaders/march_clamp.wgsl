// Rays past the sample budget get empty ranges: every offset is clamped to
// the end of the kept rays.

@group(0) @binding(0) var<uniform> params: MarchParams;
@group(0) @binding(1) var<storage, read> counters: array<u32, 2>;
@group(0) @binding(2) var<storage, read_write> offsets: array<u32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let i = id.x + id.y * params.row_stride;
    if (i >= params.element_count) {
        return;
    }
    offsets[i] = min(offsets[i], counters[0]);
}
