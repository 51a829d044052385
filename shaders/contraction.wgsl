// Scene contraction (Mip-NeRF 360, eq. 10) and the spacing coordinate
// along rays (section 2.3, eq. 11), as src/field/contraction.rs computes
// them, operation for operation: the one WGSL helper of the kernels that
// make samples into a contracted field's inputs or weigh intervals in s.
// Prepended after proposal_common.wgsl (its `params`: norm, radius,
// centre) and cpu_arithmetic.wgsl (`unfused`).

// ‖x‖ in the contraction's norm: glam's length (x·x + y·y + z·z, each
// product rounded, then the square root) or the largest |x_k|.
fn contraction_norm(x: vec3<f32>) -> f32 {
    if (params.norm == 0u) {
        return sqrt(unfused(x.x * x.x) + unfused(x.y * x.y) + unfused(x.z * x.z));
    }
    let a = abs(x);
    return max(a.x, max(a.y, a.z));
}

// ∇‖x‖ for x ≠ 0 (the L∞ norm's: the sign of its largest axis, ties to the
// first, as the cpu's).
fn contraction_norm_gradient(x: vec3<f32>) -> vec3<f32> {
    if (params.norm == 0u) {
        return x / contraction_norm(x);
    }
    let a = abs(x);
    var g = vec3<f32>(0.0);
    if (a.x >= a.y && a.x >= a.z) {
        g.x = sign(x.x);
    } else if (a.y >= a.z) {
        g.y = sign(x.y);
    } else {
        g.z = sign(x.z);
    }
    return g;
}

// A world position in the frame's units.
fn to_frame(world: vec3<f32>) -> vec3<f32> {
    return (world - params.centre) / params.radius;
}

// contract(x): x inside the unit ball, (2 − 1/‖x‖)·x/‖x‖ beyond.
fn contract(x: vec3<f32>) -> vec3<f32> {
    let r = contraction_norm(x);
    if (r <= 1.0) {
        return x;
    }
    return x * ((2.0 - 1.0 / r) / r);
}

// The contracted cube [−2, 2]³ onto [0, 1]³ (a hash grid's inputs).
fn to_unit_cube(world: vec3<f32>) -> vec3<f32> {
    return contract(to_frame(world)) * 0.25 + vec3<f32>(0.5);
}

// Column j of the Jacobian of `contract` at x: s·e_j + s′·g_j·x.
fn contraction_jacobian(x: vec3<f32>) -> mat3x3<f32> {
    let r = contraction_norm(x);
    if (r <= 1.0) {
        return mat3x3<f32>(vec3<f32>(1.0, 0.0, 0.0), vec3<f32>(0.0, 1.0, 0.0), vec3<f32>(0.0, 0.0, 1.0));
    }
    let s = 2.0 / r - 1.0 / (r * r);
    let ds = -2.0 / (r * r) + 2.0 / (r * r * r);
    let g = contraction_norm_gradient(x);
    return mat3x3<f32>(
        vec3<f32>(s, 0.0, 0.0) + x * (ds * g.x),
        vec3<f32>(0.0, s, 0.0) + x * (ds * g.y),
        vec3<f32>(0.0, 0.0, s) + x * (ds * g.z),
    );
}

// g(t): t/2 inside the unit ball, 1 − 1/(2t) beyond.
fn spacing(t: f32) -> f32 {
    if (t < 1.0) {
        return 0.5 * max(t, 0.0);
    }
    return 1.0 - 0.5 / t;
}

// g⁻¹(s): 2s up to ½, 1/(2 − 2s) beyond, f32::MAX from s = 1 on.
fn inverse_spacing(s: f32) -> f32 {
    if (s < 0.5) {
        return 2.0 * max(s, 0.0);
    }
    if (s < 1.0) {
        return 1.0 / (2.0 - 2.0 * s);
    }
    return 3.40282347e38;
}

// The spacing coordinate of a world distance, and back.
fn spacing_of(t: f32) -> f32 {
    return spacing(t / params.radius);
}

fn distance_of(s: f32) -> f32 {
    return inverse_spacing(s) * params.radius;
}
