// The sum of `values` into `total[0]`, by one workgroup: each invocation
// adds a strided share, then a tree in workgroup memory. One dispatch,
// deterministic, and fast enough for the ~10^4–10^5 per-ray losses of a
// batch (the loss value is only logged).

struct Params {
    count: u32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> values: array<f32>;
@group(0) @binding(2) var<storage, read_write> total: array<f32>;

const SIZE: u32 = 256u;
var<workgroup> partial: array<f32, SIZE>;

@compute @workgroup_size(256)
fn main(@builtin(local_invocation_index) i: u32) {
    var sum = 0.0;
    for (var k = i; k < params.count; k += SIZE) {
        sum += values[k];
    }
    partial[i] = sum;
    workgroupBarrier();
    for (var stride = SIZE / 2u; stride > 0u; stride /= 2u) {
        if (i < stride) {
            partial[i] += partial[i + stride];
        }
        workgroupBarrier();
    }
    if (i == 0u) {
        total[0] = partial[0];
    }
}
