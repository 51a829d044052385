//! The lattice alone (the marches that walk it are tested with the cpu
//! engine's batch march in `engine/cpu/march/tests.rs`).

use super::*;

const BLENDER: UnitCubeMapping = UnitCubeMapping::BLENDER;

/// The cone lattice: steps of dt up to 2A, then octaves of 256 points
/// whose step doubles, capped; continuous, increasing, and x inverts s.
#[test]
fn cone_lattice_grows_by_octaves_and_inverts() {
    let geometry = GridGeometry::new(128, 5);
    let mapping = UnitCubeMapping {
        aabb_scale: 16.0,
        ..BLENDER
    };
    let config = MarchConfig::PAPER;
    let cone = cone_for(&config, &mapping, &geometry).expect("aabb_scale 16 cones");
    assert!(cone_for(&config, &BLENDER, &geometry).is_none());
    let dt = config.step;
    let a = dt * 256.0;
    // 5 cascades: the largest step is dt · 2^4 · 1024/128 = 128 dt.
    assert_eq!(cone.last_octave, 7);
    for t_enter in [0.0f32, 0.3, 2.0 * a, 5.0 * a, 1000.0 * a] {
        let lattice = Lattice::cone(cone, t_enter);
        let mut previous = -1.0f32;
        for i in 0..4000 {
            let x = i as f32 * 0.75;
            let s = lattice.s(x, t_enter);
            assert!(s > previous, "t_enter {t_enter}: s not increasing at x {x}");
            previous = s;
            let t = t_enter + s;
            // The step is dt below 2A, else between t·c/2 and t·c, at
            // most 128 dt.
            let step = lattice.step(x);
            if t < 2.0 * a {
                assert_eq!(step, dt);
            } else {
                let c = 1.0 / 256.0;
                assert!(step <= (t * c).max(dt) * 1.0001 || step == 128.0 * dt);
                assert!(step >= (0.5 * t * c).min(128.0 * dt) * 0.9999);
            }
            // One step on is one step further, except across octaves.
            let next = lattice.s(x + 1.0, t_enter);
            assert!(next - s <= 2.0 * step * 1.0001 && next - s >= step * 0.9999);
            let back = lattice.x(s, t_enter);
            assert!(
                (back - x).abs() < 2e-3 * x.max(1.0),
                "{x} came back as {back}"
            );
        }
    }
    // From the camera: the first 2A at dt (512 points), then 256 per
    // octave.
    let lattice = Lattice::cone(cone, 0.0);
    assert!((lattice.s(512.0, 0.0) - 2.0 * a).abs() < 1e-5);
    assert!((lattice.s(512.0 + 256.0, 0.0) - 4.0 * a).abs() < 1e-5);
    assert!((lattice.s(512.0 + 512.0, 0.0) - 8.0 * a).abs() < 1e-4);
    assert_eq!(lattice.step(512.0 + 300.0), 4.0 * dt);
}
