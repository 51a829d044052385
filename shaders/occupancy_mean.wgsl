// The occupancy threshold, step 1 of 2: each workgroup sums the sampled
// values (≥ 0; untrained cells hold a negative marker and are left out)
// of 4096 cells of cascade 0 and counts them.

@group(0) @binding(0) var<uniform> params: OccupancyParams;
@group(0) @binding(1) var<storage, read> values: array<f32>;
@group(0) @binding(2) var<storage, read_write> partial_sums: array<f32>;
@group(0) @binding(3) var<storage, read_write> partial_counts: array<u32>;

var<workgroup> sums: array<f32, 256>;
var<workgroup> counts: array<u32, 256>;

@compute @workgroup_size(256)
fn main(@builtin(local_invocation_id) local: vec3<u32>, @builtin(workgroup_id) group: vec3<u32>) {
    let lane = local.x;
    var sum = 0.0;
    var count = 0u;
    for (var j = 0u; j < 16u; j++) {
        let i = group.x * 4096u + j * 256u + lane;
        if (i < params.cells_per_cascade) {
            let v = values[i];
            if (v >= 0.0) {
                sum += v;
                count += 1u;
            }
        }
    }
    sums[lane] = sum;
    counts[lane] = count;
    workgroupBarrier();
    for (var half = 128u; half > 0u; half /= 2u) {
        if (lane < half) {
            sums[lane] += sums[lane + half];
            counts[lane] += counts[lane + half];
        }
        workgroupBarrier();
    }
    if (lane == 0u) {
        partial_sums[group.x] = sums[0];
        partial_counts[group.x] = counts[0];
    }
}
