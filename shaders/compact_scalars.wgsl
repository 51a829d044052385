// Compaction, scalars: each sample's step, distance and σ (from the σ pass,
// which compositing uses so that it stops where the cut was found)
// (`compact_common.wgsl` is prepended).

@group(0) @binding(4) var<storage, read> dt: array<f32>;
@group(0) @binding(5) var<storage, read> t: array<f32>;
@group(0) @binding(6) var<storage, read> sigma: array<f32>;
@group(0) @binding(7) var<storage, read_write> out_dt: array<f32>;
@group(0) @binding(8) var<storage, read_write> out_t: array<f32>;
@group(0) @binding(9) var<storage, read_write> out_sigma: array<f32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let at = source_of(id);
    if (at.y == 0xffffffffu) {
        return;
    }
    let i = at.x;
    let s = at.y;
    out_dt[i] = dt[s];
    out_t[i] = t[s];
    out_sigma[i] = sigma[s];
}
