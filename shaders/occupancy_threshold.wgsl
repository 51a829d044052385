// The occupancy threshold, step 2 of 2: one workgroup adds the partial sums
// and writes min(min_optical_thickness, mean), or min_optical_thickness
// when no cell has been sampled (testbed `grid_to_bitfield`).

@group(0) @binding(0) var<uniform> params: OccupancyParams;
@group(0) @binding(1) var<storage, read> partial_sums: array<f32>;
@group(0) @binding(2) var<storage, read> partial_counts: array<u32>;
@group(0) @binding(3) var<storage, read_write> threshold: array<f32>;

var<workgroup> sums: array<f32, 256>;
var<workgroup> counts: array<u32, 256>;

@compute @workgroup_size(256)
fn main(@builtin(local_invocation_id) local: vec3<u32>) {
    let lane = local.x;
    var sum = 0.0;
    var count = 0u;
    for (var i = lane; i < params.partial_count; i += 256u) {
        sum += partial_sums[i];
        count += partial_counts[i];
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
        var t = params.min_optical_thickness;
        if (counts[0] > 0u) {
            t = min(t, sums[0] / f32(counts[0]));
        }
        threshold[0] = t;
    }
}
