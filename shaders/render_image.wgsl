// Rendering, last pass: each pixel's colour over the background, its
// opacity or its depth, into an rgba8unorm storage texture, with
// `render::to_image`'s mapping (depth: near white, far black, pixels of
// opacity ≤ 0.5 black).

// `RayState` comes from ray_state.wgsl.

struct Params {
    width: u32,
    height: u32,
    // 0 colour, 1 depth, 2 opacity.
    mode: u32,
    _pad0: u32,
    background: vec3<f32>,
    near: f32,
    far: f32,
    _pad1: u32,
    _pad2: u32,
    _pad3: u32,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> states: array<RayState>;
@group(0) @binding(2) var output_image: texture_storage_2d<rgba8unorm, write>;

@compute @workgroup_size(8, 8)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    if (id.x >= params.width || id.y >= params.height) {
        return;
    }
    let state = states[id.y * params.width + id.x];
    let transmittance = exp(-state.optical_depth);
    let opacity = 1.0 - transmittance;
    var colour: vec3<f32>;
    switch params.mode {
        case 1u: {
            var shade = 0.0;
            if (opacity > 0.5) {
                let depth = state.depth / opacity;
                shade = 1.0 - clamp((depth - params.near) / (params.far - params.near), 0.0, 1.0);
            }
            colour = vec3<f32>(shade);
        }
        case 2u: {
            colour = vec3<f32>(opacity);
        }
        default: {
            colour = vec3<f32>(state.r, state.g, state.b) + transmittance * params.background;
        }
    }
    textureStore(output_image, vec2<u32>(id.x, id.y), vec4<f32>(clamp(colour, vec3<f32>(0.0), vec3<f32>(1.0)), 1.0));
}
