// Exclusive prefix sum of the samples per ray, step 1 of 3: each workgroup
// scans 512 counts (two per invocation) and writes its block's total. The
// scan runs over ray_count + 1 elements, the last counted as 0, so the
// final offset is the total.

@group(0) @binding(0) var<uniform> params: MarchParams;
@group(0) @binding(1) var<storage, read> counts: array<u32>;
@group(0) @binding(2) var<storage, read_write> offsets: array<u32>;
@group(0) @binding(3) var<storage, read_write> block_sums: array<u32>;

var<workgroup> sums: array<u32, 256>;

fn count_at(i: u32) -> u32 {
    return select(0u, counts[min(i, params.ray_count - 1u)], i < params.ray_count);
}

@compute @workgroup_size(256)
fn main(@builtin(local_invocation_id) local: vec3<u32>, @builtin(workgroup_id) group: vec3<u32>) {
    let lane = local.x;
    let first = group.x * 512u + 2u * lane;
    let a = count_at(first);
    let b = count_at(first + 1u);
    sums[lane] = a + b;
    workgroupBarrier();
    // Hillis–Steele: after the step with stride 2^j each lane holds the
    // sum of the 2^(j+1) lanes ending at it.
    for (var stride = 1u; stride < 256u; stride *= 2u) {
        var v = sums[lane];
        if (lane >= stride) {
            v += sums[lane - stride];
        }
        workgroupBarrier();
        sums[lane] = v;
        workgroupBarrier();
    }
    let exclusive = sums[lane] - (a + b);
    if (first < params.element_count) {
        offsets[first] = exclusive;
    }
    if (first + 1u < params.element_count) {
        offsets[first + 1u] = exclusive + a;
    }
    if (lane == 255u) {
        block_sums[group.x] = sums[255];
    }
}
