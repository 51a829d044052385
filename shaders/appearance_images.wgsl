// Each sample's training image, its ray's: ray r's image goes to rows
// ray_offsets[r] .. ray_offsets[r + 1] (`params.rows` rays). One invocation
// per ray.

@group(0) @binding(1) var<storage, read> ray_images: array<u32>;
@group(0) @binding(2) var<storage, read> ray_offsets: array<u32>;
@group(0) @binding(3) var<storage, read_write> images: array<u32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let r = id.x + id.y * params.row_stride;
    if (r >= params.rows) {
        return;
    }
    let image = ray_images[r];
    for (var s = ray_offsets[r]; s < ray_offsets[r + 1u]; s++) {
        images[s] = image;
    }
}
