// Exclusive prefix sum of the samples per ray, step 3 of 3: adds each
// block's offset, then finds what fits the sample budget. Offsets only grow
// along the rays, so the largest offset within the budget is where the kept
// rays end, and the offsets within it count the kept rays (both by integer
// atomics, whose result does not depend on the order they run in).

@group(0) @binding(0) var<uniform> params: MarchParams;
@group(0) @binding(1) var<storage, read> block_sums: array<u32>;
@group(0) @binding(2) var<storage, read_write> offsets: array<u32>;
// [0]: samples kept, [1]: rays kept.
@group(0) @binding(3) var<storage, read_write> counters: array<atomic<u32>, 2>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let i = id.x + id.y * params.row_stride;
    if (i >= params.element_count) {
        return;
    }
    let value = offsets[i] + block_sums[i / 512u];
    offsets[i] = value;
    if (value <= params.budget) {
        atomicMax(&counters[0], value);
        if (i > 0u) {
            atomicAdd(&counters[1], 1u);
        }
    }
}
