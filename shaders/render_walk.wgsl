// Rendering, one round of the march (after `march_params.wgsl` and
// `march_common.wgsl`): each active ray walks on from where its last round
// stopped and writes up to `budget` (samples per ray this round) samples
// into its own slots, ray i of the round at slots i·budget.., with the
// cpu's `Marcher::walk` logic (engine::cpu::march), so both engines find
// the same samples. `ray_count` is the rays of this round, `max_samples`
// the cap per ray over all rounds.

// `RayState` comes from ray_state.wgsl.

@group(0) @binding(0) var<uniform> params: MarchParams;
@group(0) @binding(1) var<storage, read> bitfield: array<u32>;
@group(0) @binding(2) var<storage, read> origins: array<f32>;
@group(0) @binding(3) var<storage, read> directions: array<f32>;
@group(0) @binding(4) var<storage, read> ray_list: array<u32>;
@group(0) @binding(5) var<storage, read_write> states: array<RayState>;
// Samples written this round, with bit 31 set when the ray left the box.
@group(0) @binding(6) var<storage, read_write> counts: array<u32>;
@group(0) @binding(7) var<storage, read_write> out_positions: array<f32>;
@group(0) @binding(8) var<storage, read_write> out_directions: array<f32>;
@group(0) @binding(9) var<storage, read_write> out_t: array<f32>;
@group(0) @binding(10) var<storage, read_write> out_dt: array<f32>;

const LEFT_THE_BOX: u32 = 0x80000000u;

// Ray i of the round writes from slot i·budget, set by `main` before its
// walk.
var<private> base: u32;

fn emit_sample(m: RayMarch, n: u32, k: u32, s: f32) {
    let slot = base + n;
    let p = lattice_position(m, s);
    out_positions[3u * slot] = p.x;
    out_positions[3u * slot + 1u] = p.y;
    out_positions[3u * slot + 2u] = p.z;
    out_directions[3u * slot] = m.direction.x;
    out_directions[3u * slot + 1u] = m.direction.y;
    out_directions[3u * slot + 2u] = m.direction.z;
    out_t[slot] = (m.t_enter + s) * params.inverse_scale;
    out_dt[slot] = params.world_dt * lattice_step_scale(m, lattice_coordinate(m, k));
}

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let i = id.x + id.y * params.row_stride;
    if (i >= params.ray_count) {
        return;
    }
    let ray = ray_list[i];
    let m = prepare(ray);
    if (!m.hit) {
        counts[i] = LEFT_THE_BOX;
        return;
    }
    let limit = min(params.budget, params.max_samples - states[ray].emitted);
    base = i * params.budget;
    var k = states[ray].k;
    let walked = walk(m, &k, limit);
    states[ray].k = k;
    counts[i] = walked.emitted | select(0u, LEFT_THE_BOX, walked.left);
}
