// Compaction of marched samples to those before each ray's cut (σ first):
// compacted sample i belongs to the ray r whose compacted range
// offsets[r] .. offsets[r + 1] holds it (a binary search: the offsets only
// grow), and is that ray's sample i − offsets[r] of the march, in order.
// One invocation per compacted sample; the count is `counters[0]`, written
// on the device by the prefix sum of the samples used, so the dispatch
// covers the march's capacity and the rest return at once.

struct Params {
    ray_count: u32,
    row_stride: u32,
    // Frustum recipes: variances are gathered too.
    with_variances: u32,
    _pad: u32,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> compact_offsets: array<u32>;
@group(0) @binding(2) var<storage, read> march_offsets: array<u32>;
@group(0) @binding(3) var<storage, read> counters: array<u32>;

// The march's index of compacted sample `i`, or 0xffffffff past the count.
fn source_of(id: vec3<u32>) -> vec2<u32> {
    let i = id.x + id.y * params.row_stride;
    if (i >= counters[0]) {
        return vec2<u32>(i, 0xffffffffu);
    }
    // compact_offsets[lo] <= i < compact_offsets[hi] throughout.
    var lo = 0u;
    var hi = params.ray_count;
    while (hi - lo > 1u) {
        let mid = (lo + hi) / 2u;
        if (compact_offsets[mid] <= i) {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    return vec2<u32>(i, march_offsets[lo] + (i - compact_offsets[lo]));
}
