// Exclusive prefix sum of the samples per ray, step 2 of 3: one workgroup
// turns the block totals into exclusive block offsets, 256 at a time with a
// running carry.

@group(0) @binding(0) var<uniform> params: MarchParams;
@group(0) @binding(1) var<storage, read_write> block_sums: array<u32>;

var<workgroup> sums: array<u32, 256>;

@compute @workgroup_size(256)
fn main(@builtin(local_invocation_id) local: vec3<u32>) {
    let lane = local.x;
    var carry = 0u;
    let tiles = (params.block_count + 255u) / 256u;
    for (var tile = 0u; tile < tiles; tile++) {
        let i = tile * 256u + lane;
        var own = 0u;
        if (i < params.block_count) {
            own = block_sums[i];
        }
        sums[lane] = own;
        workgroupBarrier();
        for (var stride = 1u; stride < 256u; stride *= 2u) {
            var v = sums[lane];
            if (lane >= stride) {
                v += sums[lane - stride];
            }
            workgroupBarrier();
            sums[lane] = v;
            workgroupBarrier();
        }
        if (i < params.block_count) {
            block_sums[i] = carry + sums[lane] - own;
        }
        carry += sums[255];
        workgroupBarrier();
    }
}
