// Multiresolution hash encoding (Müller et al. 2022, section 3): what the
// forward and backward kernels share. The same arithmetic, in the same
// order, as src/engine/cpu/hash_grid.rs, which documents the layouts.

struct Params {
    // Samples in the batch.
    count: u32,
    // F, features per entry; the row width is levels · F.
    features: u32,
    width: u32,
    // Workgroups along x: large batches fold into z (see sample_index).
    groups_x: u32,
    // This dispatch covers levels first_level.. (its workgroup y counts
    // from there); the table is bound from parameter table_base on, so
    // tables larger than one storage binding go a group of levels at a time.
    first_level: u32,
    table_base: u32,
    // The grid's box (side extent around the unit cube's centre): a
    // position x maps to (x − box_min) · inverse_extent in [0, 1], as on
    // the cpu (0 and 1 for the unit cube).
    box_min: f32,
    inverse_extent: f32,
}

struct Level {
    // N_l: cells per side.
    resolution: u32,
    // The level's first entry in the parameter array (in entries).
    offset: u32,
    // 1 for dense indexing, 0 for the spatial hash.
    dense: u32,
    // T − 1 (T is a power of two, so mod T is a mask).
    mask: u32,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> levels: array<Level>;

const WORKGROUP: u32 = 64u;

// π₂ and π₃ of the spatial hash (paper, eq. 4); π₁ = 1.
const PRIME_Y: u32 = 2654435761u;
const PRIME_Z: u32 = 805459861u;

struct Corners {
    // Entry indices, absolute (the level's offset included).
    index: array<u32, 8>,
    weight: array<f32, 8>,
}

// One invocation per (sample, level): the level is the workgroup's y, the
// sample its x (and z, past 65535 workgroups) times 64 plus the lane.
fn sample_index(group: vec3<u32>, lane: u32) -> u32 {
    return (group.z * params.groups_x + group.x) * WORKGROUP + lane;
}

// The 8 corners of the cell holding p at `level`; corner c is offset by
// (c & 1, (c >> 1) & 1, c >> 2). Coordinates outside the box are clamped to
// it, as on the cpu (a NaN coordinate gives an unspecified corner of
// the grid, still inside the table: the cpu reads it as 0).
fn corners(level: Level, p: vec3<f32>) -> Corners {
    let n = level.resolution;
    let q = (p - vec3<f32>(params.box_min)) * params.inverse_extent;
    let scaled = clamp(q, vec3<f32>(0.0), vec3<f32>(1.0)) * f32(n);
    // scaled ≥ 0, so truncation is floor; x = 1 lands in the last cell with
    // fraction 1 rather than one cell beyond the grid.
    let cell = min(vec3<u32>(scaled), vec3<u32>(n - 1u));
    let frac = scaled - vec3<f32>(cell);
    let side = n + 1u;
    var result: Corners;
    for (var c = 0u; c < 8u; c++) {
        let offset = vec3<u32>(c & 1u, (c >> 1u) & 1u, c >> 2u);
        let v = cell + offset;
        var index: u32;
        if (level.dense != 0u) {
            index = v.x + v.y * side + v.z * side * side;
        } else {
            index = (v.x ^ (v.y * PRIME_Y) ^ (v.z * PRIME_Z)) & level.mask;
        }
        result.index[c] = level.offset + index;
        let w = select(vec3<f32>(1.0) - frac, frac, offset == vec3<u32>(1u));
        result.weight[c] = w.x * w.y * w.z;
    }
    return result;
}
