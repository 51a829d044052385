// Ray marching through the occupancy grid, shared by `march_count.wgsl`,
// `march_write.wgsl` and `render_walk.wgsl` (prepended to each; each
// defines `emit_sample`, which `walk` calls for every sample). The same arithmetic, in the same
// order, as the cpu engine's `engine::cpu::march` and
// `engine::shared::occupancy::GridGeometry`, so both engines find the same
// samples at the same positions. `march_params.wgsl` comes first; the entry
// files declare `params`, `bitfield`, `origins` and `directions`.

struct RayMarch {
    entry: vec3<f32>,
    direction: vec3<f32>,
    inverse_direction: vec3<f32>,
    t_enter: f32,
    s_exit: f32,
    jitter: f32,
    hit: bool,
    // The ray's lattice (`engine::cpu::march::Lattice`): the step from the
    // entry point to the first octave boundary and its inverse, the lattice
    // units and the length up to that boundary (`whole_ray` when the
    // first step holds to the end: no cone, or the entry already in the
    // last octave), and the octave of the entry point.
    first_step: f32,
    inverse_first_step: f32,
    first_units: f32,
    first_length: f32,
    first_octave: i32,
    whole_ray: bool,
}

// `unfused` and `mix32` come from cpu_arithmetic.wgsl.

fn is_finite(v: vec3<f32>) -> bool {
    return all(abs(v) <= vec3<f32>(3.4028235e38));
}

fn ray_jitter(ray: u32) -> f32 {
    if (params.use_jitter == 0u) {
        return 0.0;
    }
    let h = mix32(params.jitter_seed ^ mix32(ray + 0x9e3779b9u));
    return f32(h >> 8u) * (1.0 / 16777216.0);
}

fn prepare(ray: u32) -> RayMarch {
    var m: RayMarch;
    m.hit = false;
    let world = vec3<f32>(origins[3u * ray], origins[3u * ray + 1u], origins[3u * ray + 2u]);
    let d = vec3<f32>(directions[3u * ray], directions[3u * ray + 1u], directions[3u * ray + 2u]);
    if (!is_finite(world) || !is_finite(d) || all(d == vec3<f32>(0.0))) {
        return m;
    }
    let o = vec3<f32>(
        unfused(world.x * params.scale) + params.offset.x,
        unfused(world.y * params.scale) + params.offset.y,
        unfused(world.z * params.scale) + params.offset.z,
    );
    // Slabs, as `scene::Aabb::intersect` with t_min = 0.
    var t_enter = 0.0;
    var t_exit = 3.4028235e38;
    for (var axis = 0u; axis < 3u; axis++) {
        if (d[axis] == 0.0) {
            if (o[axis] < params.box_min || o[axis] > params.box_max) {
                return m;
            }
        } else {
            let inverse = 1.0 / d[axis];
            var t0 = (params.box_min - o[axis]) * inverse;
            var t1 = (params.box_max - o[axis]) * inverse;
            if (t0 > t1) {
                let swap = t0;
                t0 = t1;
                t1 = swap;
            }
            t_enter = max(t_enter, t0);
            t_exit = min(t_exit, t1);
        }
    }
    if (!(t_enter <= t_exit)) {
        return m;
    }
    m.entry = vec3<f32>(
        o.x + unfused(d.x * t_enter),
        o.y + unfused(d.y * t_enter),
        o.z + unfused(d.z * t_enter),
    );
    m.direction = d;
    m.inverse_direction = select(vec3<f32>(1.0) / d, vec3<f32>(0.0), d == vec3<f32>(0.0));
    m.t_enter = t_enter;
    m.s_exit = t_exit - t_enter;
    m.jitter = ray_jitter(ray);
    m.hit = true;
    set_lattice(&m);
    return m;
}

fn is_nan(x: f32) -> bool {
    return (bitcast<u32>(x) & 0x7fffffffu) > 0x7f800000u;
}

// The octave of distance t: 0 below 2A, floor(log2(t / A)) above, at most
// the last; from the float's exponent, as `Cone::octave_of`.
fn octave_of(t: f32) -> i32 {
    let v = t * params.inverse_octave_start;
    if (is_nan(v) || v < 2.0) {
        return 0;
    }
    let exponent = i32((bitcast<u32>(v) >> 23u) & 0xffu) - 127;
    return min(exponent, params.last_octave);
}

// `Lattice::fixed` or `Lattice::cone` for the ray's entry distance.
fn set_lattice(m: ptr<function, RayMarch>) {
    (*m).first_step = params.dt;
    (*m).inverse_first_step = params.inverse_dt;
    (*m).first_units = 0.0;
    (*m).first_length = 0.0;
    (*m).first_octave = 0;
    (*m).whole_ray = true;
    if (params.use_cone == 0u) {
        return;
    }
    let octave = octave_of((*m).t_enter);
    (*m).first_octave = octave;
    (*m).first_step = params.dt * power_of_two(octave);
    (*m).inverse_first_step = params.inverse_dt * power_of_two(-octave);
    if (octave < params.last_octave) {
        let length = params.octave_start * power_of_two(octave + 1) - (*m).t_enter;
        (*m).first_length = length;
        (*m).first_units = length * (*m).inverse_first_step;
        (*m).whole_ray = false;
    }
}

// The octave of lattice coordinate x past the first stretch and the
// lattice coordinate where it starts (`Lattice::octave_at`).
fn octave_at(m: RayMarch, x: f32) -> vec2<f32> {
    let past = x - m.first_units;
    let whole = i32(min(past / params.points_per_octave, 1.0e9));
    let octave = min(m.first_octave + 1 + whole, params.last_octave);
    let start = m.first_units
        + unfused(f32(octave - m.first_octave - 1) * params.points_per_octave);
    return vec2<f32>(f32(octave), start);
}

fn in_first_stretch(m: RayMarch, x: f32) -> bool {
    return m.whole_ray || x < m.first_units;
}

// s(x): the distance of lattice coordinate x past the entry point.
fn lattice_s_at(m: RayMarch, x: f32) -> f32 {
    if (in_first_stretch(m, x)) {
        return x * m.first_step;
    }
    let at = octave_at(m, x);
    let scale = power_of_two(i32(at.x));
    let t = params.octave_start * scale + unfused((x - at.y) * (params.dt * scale));
    return t - m.t_enter;
}

// The step at lattice coordinate x over the smallest step: 2^octave.
fn lattice_step_scale(m: RayMarch, x: f32) -> f32 {
    if (in_first_stretch(m, x)) {
        return power_of_two(m.first_octave);
    }
    return power_of_two(i32(octave_at(m, x).x));
}

// The lattice coordinate of distance s past the entry point, the inverse
// of `lattice_s_at` to rounding (`Lattice::x`).
fn lattice_x(m: RayMarch, s: f32) -> f32 {
    if (is_nan(s) || m.whole_ray || s < m.first_length) {
        return s * m.inverse_first_step;
    }
    let t = m.t_enter + s;
    let octave = max(octave_of(t), m.first_octave + 1);
    let start = m.first_units
        + unfused(f32(octave - m.first_octave - 1) * params.points_per_octave);
    return start + unfused((t - params.octave_start * power_of_two(octave))
        * (params.inverse_dt * power_of_two(-octave)));
}

fn lattice_coordinate(m: RayMarch, k: u32) -> f32 {
    return m.jitter + f32(k);
}

fn lattice_s(m: RayMarch, k: u32) -> f32 {
    return lattice_s_at(m, lattice_coordinate(m, k));
}

fn lattice_position(m: RayMarch, s: f32) -> vec3<f32> {
    return vec3<f32>(
        m.entry.x + unfused(m.direction.x * s),
        m.entry.y + unfused(m.direction.y * s),
        m.entry.z + unfused(m.direction.z * s),
    );
}

// 2^e, exactly.
fn power_of_two(e: i32) -> f32 {
    return bitcast<f32>(u32(127 + e) << 23u);
}

// The finest cascade containing p: frexp's exponent of max|p − 0.5|, plus 1.
fn cascade_of(p: vec3<f32>) -> u32 {
    if (params.cascades == 1u) {
        return 0u;
    }
    let q = abs(p - vec3<f32>(0.5));
    let m = max(max(q.x, q.y), q.z);
    let e = i32((bitcast<u32>(m) >> 23u) & 0xffu) - 126;
    return u32(clamp(e + 1, 0, i32(params.cascades) - 1));
}

fn cell_coordinate(x: f32, scale: f32) -> u32 {
    let half = f32(params.resolution / 2u);
    let v = (x - 0.5) * scale + half;
    return u32(clamp(floor(v), 0.0, f32(params.resolution - 1u)));
}

struct Cell {
    cascade: u32,
    xyz: vec3<u32>,
}

fn cell_of(p: vec3<f32>) -> Cell {
    var c: Cell;
    c.cascade = cascade_of(p);
    let scale = f32(params.resolution) * power_of_two(-i32(c.cascade));
    c.xyz = vec3<u32>(cell_coordinate(p.x, scale), cell_coordinate(p.y, scale), cell_coordinate(p.z, scale));
    return c;
}

fn is_occupied(c: Cell) -> bool {
    let res = params.resolution;
    let index = c.cascade * res * res * res + c.xyz.x + res * (c.xyz.y + res * c.xyz.z);
    return ((bitfield[index >> 5u] >> (index & 31u)) & 1u) != 0u;
}

fn axis_exit(lo: f32, size: f32, e: f32, d: f32, inverse: f32) -> f32 {
    if (d > 0.0) {
        return (lo + size - params.margin - e) * inverse;
    }
    if (d < 0.0) {
        return (lo + params.margin - e) * inverse;
    }
    return 3.4028235e38;
}

// The first lattice index at or beyond the cell's exit face, pulled in by
// the margin: every lattice point before it lies in the cell.
fn exit_index(m: RayMarch, c: Cell) -> u32 {
    let size = power_of_two(i32(c.cascade)) / f32(params.resolution);
    let half = f32(params.resolution / 2u);
    let lo = (vec3<f32>(c.xyz) - vec3<f32>(half)) * size + vec3<f32>(0.5);
    let s_cell = min(
        axis_exit(lo.x, size, m.entry.x, m.direction.x, m.inverse_direction.x),
        min(
            axis_exit(lo.y, size, m.entry.y, m.direction.y, m.inverse_direction.y),
            axis_exit(lo.z, size, m.entry.z, m.direction.z, m.inverse_direction.z),
        ),
    );
    let v = lattice_x(m, s_cell) - m.jitter;
    return u32(clamp(ceil(v), 0.0, 4294967040.0));
}

// How a walk ended: the samples it emitted, and whether the ray left the
// box (false: it stopped at the limit, and can go on from where it stopped).
struct Walked {
    emitted: u32,
    left: bool,
}

// The walk along a ray's lattice, written once for the three walking
// kernels, as the cpu's `Marcher::walk`: from lattice index `*k`, one cell
// at a time (its exit index found once; every lattice point before it lies
// in the cell), each lattice point of an occupied cell goes to the entry
// file's `emit_sample(m, n, k, s)` (n: samples emitted so far by this
// walk), until `limit` samples or the ray leaves the box. `*k` is left at
// the next lattice point to look at. A distance that is not ≤ the exit,
// NaN included, ends the ray.
fn walk(m: RayMarch, k: ptr<function, u32>, limit: u32) -> Walked {
    var index = *k;
    var emitted = 0u;
    var left = false;
    loop {
        let s = lattice_s(m, index);
        if (!(s <= m.s_exit)) {
            left = true;
            break;
        }
        if (emitted == limit) {
            break;
        }
        let c = cell_of(lattice_position(m, s));
        let next = max(exit_index(m, c), index + 1u);
        if (!is_occupied(c)) {
            index = next;
            continue;
        }
        var stop = false;
        loop {
            if (index >= next) {
                break;
            }
            let sk = lattice_s(m, index);
            if (!(sk <= m.s_exit)) {
                left = true;
                stop = true;
                break;
            }
            if (emitted == limit) {
                stop = true;
                break;
            }
            emit_sample(m, emitted, index, sk);
            emitted += 1u;
            index += 1u;
        }
        if (stop) {
            break;
        }
    }
    *k = index;
    return Walked(emitted, left);
}
