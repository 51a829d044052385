// The mean of the table's rows (nerfacto's average appearance embedding,
// what a view that is no training image's takes). One invocation per
// column; the sum is compensated (Kahan) to stay close to the cpu
// engine's f64 sum whatever the number of images.

@group(0) @binding(1) var<storage, read> table: array<f32>;
@group(0) @binding(2) var<storage, read_write> mean: array<f32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let j = id.x;
    if (j >= params.width) {
        return;
    }
    var sum = 0.0;
    var lost = 0.0;
    for (var i = 0u; i < params.images; i++) {
        let y = table[params.table_base + i * params.width + j] - lost;
        let t = sum + y;
        lost = (t - sum) - y;
        sum = t;
    }
    mean[j] = sum / f32(params.images);
}
