// Occupancy update, step 2 of 2: each sample raises its cell to its optical
// thickness σ · min_step · 2^cascade; an untrained cell takes it outright.
// Several samples may hit one cell, so the value is updated by
// compare-and-swap on its bits; the result, the largest thickness (or the
// decayed value), does not depend on the order.

@group(0) @binding(0) var<uniform> params: OccupancyParams;
@group(0) @binding(1) var<storage, read> cells: array<u32>;
@group(0) @binding(2) var<storage, read> sigma: array<f32>;
@group(0) @binding(3) var<storage, read_write> values: array<atomic<u32>>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let i = id.x + id.y * params.row_stride;
    if (i >= params.sample_count) {
        return;
    }
    let cell = cells[i];
    let cascade = cell / params.cells_per_cascade;
    let step = params.min_step * f32(1u << cascade);
    // A negative or NaN density counts as empty space, as on the cpu.
    let raw = sigma[i] * step;
    let tau = select(0.0, min(raw, 3.4028235e38), raw > 0.0);
    var old = atomicLoad(&values[cell]);
    loop {
        let v = bitcast<f32>(old);
        let updated = bitcast<u32>(select(max(v, tau), tau, v < 0.0));
        if (updated == old) {
            break;
        }
        let result = atomicCompareExchangeWeak(&values[cell], old, updated);
        if (result.exchanged) {
            break;
        }
        old = result.old_value;
    }
}
