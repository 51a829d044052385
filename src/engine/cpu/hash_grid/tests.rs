use super::*;
use crate::field::encoding::HashGridConfig;
use crate::rng::splitmix64;

/// A small deterministic stream of uniforms in [0, 1) for tests.
struct Uniforms(u64);

impl Uniforms {
    fn next(&mut self) -> f64 {
        self.0 += 1;
        (splitmix64(self.0) >> 11) as f64 / (1u64 << 53) as f64
    }

    fn symmetric(&mut self) -> f64 {
        2.0 * self.next() - 1.0
    }

    fn position(&mut self) -> [f64; 3] {
        [self.next(), self.next(), self.next()]
    }
}

/// Three levels, the first dense and the others hashed into a table small
/// enough that vertices collide: every code path in a few thousand
/// parameters.
fn small_config() -> HashGridConfig {
    HashGridConfig {
        levels: 3,
        features_per_level: 2,
        log2_table_size: 8,
        base_resolution: 4,
        finest_resolution: 16,
        init_range: 1.0,
        extent: 1.0,
    }
}

fn random_params(layout: &HashGridLayout, seed: u64) -> Vec<f64> {
    let mut u = Uniforms(seed);
    (0..layout.param_count()).map(|_| u.symmetric()).collect()
}

/// Coordinates that sit on faces, vertices and cell boundaries of every
/// level, and a few just inside the faces.
fn hard_coordinates(layout: &HashGridLayout) -> Vec<f64> {
    let mut values = vec![0.0, 1.0, 0.5, f64::EPSILON, 1.0 - f64::EPSILON, 1e-30];
    for level in layout.levels() {
        let n = level.resolution as f64;
        values.extend([1.0 / n, (n - 1.0) / n, (n / 2.0).floor() / n, 1.0 - 0.5 / n]);
    }
    values
}

fn hard_positions(layout: &HashGridLayout) -> Vec<[f64; 3]> {
    let values = hard_coordinates(layout);
    let mut positions = Vec::new();
    for (i, &x) in values.iter().enumerate() {
        for (j, &y) in values.iter().enumerate() {
            let z = values[(i * 7 + j * 3) % values.len()];
            positions.push([x, y, z]);
        }
    }
    positions
}

#[test]
fn hash_matches_hand_computed_values() {
    assert_eq!(spatial_hash(0, 0, 0), 0);
    assert_eq!(spatial_hash(1, 0, 0), 1);
    assert_eq!(spatial_hash(0, 1, 0), 2_654_435_761);
    assert_eq!(spatial_hash(0, 0, 1), 805_459_861);
    // 2 · 2654435761 = 5308871522 wraps to 5308871522 − 2^32.
    assert_eq!(spatial_hash(0, 2, 0), 1_013_904_226);
    // 0x9E3779B1 ⊕ 0x30025795 ⊕ 1 = 0xAE352E25.
    assert_eq!(spatial_hash(1, 1, 1), 0xAE35_2E25);
    // 5·π₂ mod 2^32 = 387276917, 7·π₃ mod 2^32 = 1343251731;
    // 3 ⊕ 387276917 ⊕ 1343251731 = 1191511397, and mod 2^19 = 329061.
    assert_eq!(spatial_hash(3, 5, 7), 1_191_511_397);
    assert_eq!(spatial_hash(3, 5, 7) & ((1 << 19) - 1), 329_061);
}

#[test]
fn paper_layout_has_five_dense_levels() {
    let layout = HashGridLayout::new(&HashGridConfig::paper(1.0));
    let resolutions: Vec<u32> = layout.levels().iter().map(|l| l.resolution).collect();
    // ⌊16 · b^l⌋ with b = 128^(1/15) ≈ 1.3819.
    assert_eq!(
        resolutions,
        [
            16, 22, 30, 42, 58, 80, 111, 153, 212, 294, 406, 561, 776, 1072, 1482, 2048
        ]
    );
    // 59³ = 205379 ≤ 2^19 = 524288 < 81³ = 531441: levels 0-4 are dense.
    let dense: Vec<bool> = layout.levels().iter().map(|l| l.dense).collect();
    assert_eq!(dense, [[true; 5].as_slice(), &[false; 11]].concat());
    let dense_entries =
        17usize.pow(3) + 23usize.pow(3) + 31usize.pow(3) + 43usize.pow(3) + 59usize.pow(3);
    assert_eq!(layout.entry_count(), dense_entries + 11 * (1 << 19));
    assert_eq!(layout.param_count(), 2 * layout.entry_count());
    assert_eq!(layout.output_width(), 32);
    let mut offset = 0;
    for level in layout.levels() {
        assert_eq!(level.offset, offset);
        offset += level.entries;
    }
    // The table stays under a 128 MiB storage binding (64 MiB at most).
    assert!(layout.param_count() * 4 <= 64 << 20);

    // aabb_scale 16: N_max = 32768, b = 2048^(1/15); the finest level must
    // reach N_max exactly although 16 · b^15 rounds to 32767.99…
    let layout = HashGridLayout::new(&HashGridConfig::paper(16.0));
    let levels = layout.levels();
    assert_eq!(levels[15].resolution, 32768);
    // 74³ = 405224 fits, 123³ does not: four dense levels.
    assert_eq!(levels[3].resolution, 73);
    assert_eq!(levels[4].resolution, 122);
    assert!(levels[3].dense && !levels[4].dense);
}

#[test]
fn dense_and_hashed_vertices_read_their_entries() {
    // N = 16, 32, 64: vertex coordinates k/N are exact in binary, so a
    // vertex reads exactly one entry. 17³ ≤ 2^13 < 33³: level 0 dense.
    let config = HashGridConfig {
        levels: 3,
        features_per_level: 2,
        log2_table_size: 13,
        base_resolution: 16,
        finest_resolution: 64,
        init_range: 1.0,
        extent: 1.0,
    };
    let layout = HashGridLayout::new(&config);
    let levels = layout.levels();
    assert_eq!(
        levels
            .iter()
            .map(|l| (l.resolution, l.dense))
            .collect::<Vec<_>>(),
        [(16, true), (32, false), (64, false)]
    );
    let params = random_params(&layout, 3);
    let vertices = [
        [0u32, 0, 0],
        [16, 16, 16],
        [3, 9, 16],
        [16, 0, 5],
        [7, 7, 7],
    ];
    for v in vertices {
        let p = v.map(|c| c as f64 / 16.0);
        let mut out = [0.0; 6];
        encode(&layout, &params, &[p], &mut out);
        for (l, level) in levels.iter().enumerate() {
            let scale = level.resolution / 16;
            let [x, y, z] = v.map(|c| c * scale);
            let side = level.resolution + 1;
            let entry = if level.dense {
                x + y * side + z * side * side
            } else {
                spatial_hash(x, y, z) & ((1 << 13) - 1)
            } as usize;
            let want = &params[(level.offset + entry) * 2..][..2];
            assert_eq!(&out[2 * l..2 * l + 2], want, "vertex {v:?}, level {l}");
        }
    }
}

/// The corners of one position, through the group code the passes use.
fn corners_of<T: Real>(math: &LevelMath<T>, dense: bool, p: [T; 3]) -> ([u32; 8], [T; 8]) {
    let mut corners = Corners::new();
    if dense {
        math.corners::<true>(&[p], &mut corners);
    } else {
        math.corners::<false>(&[p], &mut corners);
    }
    (corners.index.map(|i| i[0]), corners.weight.map(|w| w[0]))
}

/// The encoding written plainly from the paper's description, one
/// sample, one level and one corner at a time.
fn naive_encode(layout: &HashGridLayout, params: &[f64], p: [f64; 3]) -> Vec<f64> {
    let f = layout.features();
    let t = layout.config().table_size();
    let mut out = Vec::new();
    for level in layout.levels() {
        let n = level.resolution as f64;
        let x = p.map(|v| v.clamp(0.0, 1.0) * n);
        let cell = x.map(|v| (v.floor() as u32).min(level.resolution - 1));
        let mut features = vec![0.0; f];
        for dz in 0..2u32 {
            for dy in 0..2u32 {
                for dx in 0..2u32 {
                    let v = [cell[0] + dx, cell[1] + dy, cell[2] + dz];
                    let weight: f64 = (0..3)
                        .map(|a| {
                            let frac = x[a] - cell[a] as f64;
                            if v[a] > cell[a] { frac } else { 1.0 - frac }
                        })
                        .product();
                    let side = level.resolution as usize + 1;
                    let entry = if level.dense {
                        v[0] as usize + v[1] as usize * side + v[2] as usize * side * side
                    } else {
                        spatial_hash(v[0], v[1], v[2]) as usize % t
                    };
                    for (k, feature) in features.iter_mut().enumerate() {
                        *feature += weight * params[(level.offset + entry) * f + k];
                    }
                }
            }
        }
        out.extend(features);
    }
    out
}

#[test]
fn encoding_matches_a_plain_transcription_of_the_paper() {
    let layout = HashGridLayout::new(&HashGridConfig::paper(1.0));
    let params: Vec<f64> = layout
        .init_params(12)
        .iter()
        .map(|&p| p as f64 * 1e4)
        .collect();
    let mut u = Uniforms(13);
    let mut positions: Vec<[f64; 3]> = (0..200).map(|_| u.position()).collect();
    positions.extend(hard_positions(&layout).into_iter().step_by(7));
    let width = layout.output_width();
    let mut out = vec![0.0; positions.len() * width];
    encode(&layout, &params, &positions, &mut out);
    for (p, row) in positions.iter().zip(out.chunks_exact(width)) {
        let want = naive_encode(&layout, &params, *p);
        for (l, (a, b)) in row.iter().zip(&want).enumerate() {
            // Same terms, summed in another order and with the weight
            // products associated differently: |θ| ≤ 1, so a few ε.
            assert!((a - b).abs() < 1e-14, "{p:?}, column {l}: {a} vs {b}");
        }
    }
}

#[test]
fn faces_and_cell_boundaries_stay_in_the_table_with_unit_weights() {
    for config in [HashGridConfig::paper(1.0), small_config()] {
        let layout = HashGridLayout::new(&config);
        let positions = hard_positions(&layout);
        for level in layout.levels() {
            let math64 = LevelMath::<f64>::new(&layout, level);
            let math32 = LevelMath::<f32>::new(&layout, level);
            for p in &positions {
                let (index, weight) = corners_of(&math64, level.dense, *p);
                let sum: f64 = weight.iter().sum();
                assert!((sum - 1.0).abs() < 1e-12, "{p:?}: Σw = {sum}");
                assert!(weight.iter().all(|&w| (0.0..=1.0).contains(&w)));
                assert!(
                    index.iter().all(|&i| (i as usize) < level.entries),
                    "{p:?}: {index:?}"
                );

                let p32 = p.map(|x| x as f32);
                let (index, weight) = corners_of(&math32, level.dense, p32);
                let sum: f32 = weight.iter().sum();
                // Each weight is a product of three factors in [0, 1], each
                // rounded once: Σw is within a few ulps of 1.
                assert!((sum - 1.0).abs() < 1e-6, "{p32:?}: Σw = {sum}");
                assert!(weight.iter().all(|&w| (0.0..=1.0).contains(&w)));
                assert!(
                    index.iter().all(|&i| (i as usize) < level.entries),
                    "{p32:?}: {index:?}"
                );
            }
        }
        // The far corner of the box is the last vertex of a dense level.
        let level = layout.levels()[0];
        let (index, weight) = corners_of(&LevelMath::<f32>::new(&layout, &level), true, [1.0; 3]);
        assert_eq!(weight[7], 1.0);
        assert_eq!(index[7] as usize, level.entries - 1);
    }
}

#[test]
fn positions_outside_the_box_are_clamped() {
    let layout = HashGridLayout::new(&HashGridConfig::paper(1.0));
    let params = layout.init_params(11);
    let width = layout.output_width();
    let cases: [([f32; 3], [f32; 3]); 6] = [
        ([-1e-7, 0.3, 0.7], [0.0, 0.3, 0.7]),
        ([1.0 + 1e-7, 0.3, 1.0 + 2e-7], [1.0, 0.3, 1.0]),
        ([-5.0, 7.0, 0.25], [0.0, 1.0, 0.25]),
        ([f32::NEG_INFINITY, f32::INFINITY, 0.5], [0.0, 1.0, 0.5]),
        ([f32::NAN, 0.5, 0.5], [0.0, 0.5, 0.5]),
        ([0.2, 0.4, -f32::MIN_POSITIVE], [0.2, 0.4, 0.0]),
    ];
    let outside: Vec<[f32; 3]> = cases.iter().map(|c| c.0).collect();
    let inside: Vec<[f32; 3]> = cases.iter().map(|c| c.1).collect();
    let mut a = vec![0.0f32; cases.len() * width];
    let mut b = vec![0.0f32; cases.len() * width];
    encode(&layout, &params, &outside, &mut a);
    encode(&layout, &params, &inside, &mut b);
    assert!(a.iter().all(|v| v.is_finite()));
    assert_eq!(a, b);
}

/// A large scene's grid spans its whole box (side aabb_scale around the
/// unit cube's centre), not the unit cube: a position x encodes as
/// (x − box_min) / extent does on a unit-cube grid with the same tables,
/// so points outside the unit cube but inside the box keep their own
/// features (clamping them to the unit cube's faces made the whole far
/// field of a large scene an extrusion of those faces), and only points
/// outside the box are clamped.
#[test]
fn a_grid_spans_its_box() {
    let boxed = HashGridConfig::paper(8.0);
    assert_eq!(boxed.extent, 8.0);
    let unit = HashGridConfig {
        extent: 1.0,
        ..boxed
    };
    let (boxed, unit) = (HashGridLayout::new(&boxed), HashGridLayout::new(&unit));
    let params = boxed.init_params(3);
    let width = boxed.output_width();
    // Unit-cube coordinates; the box is [−3.5, 4.5]³, and −3.5 + 8k/16 is
    // exactly representable, so the mapped points are exact too.
    let positions: Vec<[f32; 3]> = vec![
        [0.5, 0.5, 0.5],
        [2.0, 0.5, 0.5],
        [3.0, 0.5, 0.5],
        [-3.0, 4.0, 1.25],
        [4.5, -3.5, 4.5],
        [9.0, 0.5, 0.5],
    ];
    let mapped: Vec<[f32; 3]> = positions
        .iter()
        .map(|p| p.map(|x| ((x + 3.5) / 8.0).clamp(0.0, 1.0)))
        .collect();
    let mut from_box = vec![0.0f32; positions.len() * width];
    let mut from_unit = vec![0.0f32; positions.len() * width];
    encode(&boxed, &params, &positions, &mut from_box);
    encode(&unit, &params, &mapped, &mut from_unit);
    assert_eq!(from_box, from_unit);
    let row = |i: usize| &from_box[i * width..(i + 1) * width];
    // Two points past the unit cube's face along x differ (they were
    // equal when the grid spanned the unit cube), as do the centre
    // and a point beyond it.
    assert_ne!(row(1), row(2));
    assert_ne!(row(0), row(1));
    // Past the box's face, the face's value.
    let face = [[4.5f32, 0.5, 0.5]];
    let mut on_face = vec![0.0f32; width];
    encode(&boxed, &params, &face, &mut on_face);
    assert_eq!(row(5), on_face.as_slice());
}

/// ⟨encode(θ, p), d_out⟩ as a function of θ.
fn loss(layout: &HashGridLayout, params: &[f64], positions: &[[f64; 3]], d_out: &[f64]) -> f64 {
    let mut out = vec![0.0; d_out.len()];
    encode(layout, params, positions, &mut out);
    out.iter().zip(d_out).map(|(o, g)| o * g).sum()
}

#[test]
fn gradients_match_central_differences() {
    let layout = HashGridLayout::new(&small_config());
    let mut u = Uniforms(21);
    let mut positions: Vec<[f64; 3]> = (0..40).map(|_| u.position()).collect();
    positions.extend(hard_positions(&layout).into_iter().step_by(17));
    let d_out: Vec<f64> = (0..positions.len() * layout.output_width())
        .map(|_| u.symmetric())
        .collect();
    let mut params = random_params(&layout, 5);
    let mut d_params = vec![0.0; layout.param_count()];
    encode_backward(&layout, &positions, &d_out, &mut d_params);
    let mut touched = 0;
    for i in 0..params.len() {
        // The loss is linear in θ, so a central difference has no
        // truncation error at any step: h = 1 leaves only rounding,
        // about ε · Σ|terms| ≈ 1e-16 · 100.
        let h = 1.0;
        let saved = params[i];
        params[i] = saved + h;
        let plus = loss(&layout, &params, &positions, &d_out);
        params[i] = saved - h;
        let minus = loss(&layout, &params, &positions, &d_out);
        params[i] = saved;
        let numeric = (plus - minus) / (2.0 * h);
        assert!(
            (d_params[i] - numeric).abs() < 1e-9,
            "param {i}: analytic {} numeric {numeric}",
            d_params[i]
        );
        touched += (d_params[i] != 0.0) as usize;
    }
    // The check means something only if many entries got gradient.
    assert!(touched > params.len() / 4, "{touched} of {}", params.len());
}

#[test]
fn gradients_match_central_differences_on_the_paper_grid() {
    let layout = HashGridLayout::new(&HashGridConfig::paper(1.0));
    let mut u = Uniforms(31);
    let mut positions: Vec<[f64; 3]> = (0..12).map(|_| u.position()).collect();
    positions.extend([[0.0; 3], [1.0; 3], [1.0, 0.0, 0.5]]);
    let d_out: Vec<f64> = (0..positions.len() * layout.output_width())
        .map(|_| u.symmetric())
        .collect();
    let mut params: Vec<f64> = layout
        .init_params(2)
        .iter()
        .map(|&p| p as f64 * 1e4)
        .collect();
    let mut d_params = vec![0.0; layout.param_count()];
    encode_backward(&layout, &positions, &d_out, &mut d_params);
    // Every entry that got gradient (all 16 levels, dense and hashed),
    // and as many that got none.
    let touched: Vec<usize> = (0..params.len()).filter(|&i| d_params[i] != 0.0).collect();
    assert!(touched.len() > 8 * 16, "{}", touched.len());
    let count = params.len() as f64;
    let untouched: Vec<usize> = (0..touched.len())
        .map(|_| (u.next() * count) as usize)
        .collect();
    for i in touched.into_iter().chain(untouched) {
        // Linear in θ: h = 1 is exact up to rounding (see above).
        let saved = params[i];
        params[i] = saved + 1.0;
        let plus = loss(&layout, &params, &positions, &d_out);
        params[i] = saved - 1.0;
        let minus = loss(&layout, &params, &positions, &d_out);
        params[i] = saved;
        let numeric = (plus - minus) / 2.0;
        assert!(
            (d_params[i] - numeric).abs() < 1e-9,
            "param {i}: analytic {} numeric {numeric}",
            d_params[i]
        );
    }
}

#[test]
fn gather_path_gives_the_portable_bits() {
    // f32 with F = 2 takes the AVX-512 gather path where the CPU has
    // it; every level must match the portable loop bit for bit, on
    // full groups, a short last group, faces, corners and NaN.
    for config in [HashGridConfig::paper(1.0), small_config()] {
        let layout = HashGridLayout::new(&config);
        let params = layout.init_params(3);
        let mut u = Uniforms(41);
        let mut positions: Vec<[f32; 3]> = hard_positions(&layout)
            .iter()
            .map(|p| p.map(|x| x as f32))
            .collect();
        positions.extend((0..1000).map(|_| u.position().map(|x| x as f32)));
        positions.push([f32::NAN, 1.0, -0.5]);
        let n = positions.len();
        assert_ne!(n % GROUP, 0, "a short last group");
        let width = layout.output_width();
        let mut out = vec![0.0f32; n * width];
        encode(&layout, &params, &positions, &mut out);
        for (l, level) in layout.levels().iter().enumerate() {
            let math = LevelMath::<f32>::new(&layout, level);
            let table = &params[level.offset * 2..][..level.entries * 2];
            let mut expected = vec![0.0f32; n * 2];
            if level.dense {
                forward_level_portable::<f32, 2, true>(&math, table, &positions, &mut expected);
            } else {
                forward_level_portable::<f32, 2, false>(&math, table, &positions, &mut expected);
            }
            for (k, pair) in expected.chunks_exact(2).enumerate() {
                let got = &out[k * width + 2 * l..][..2];
                assert_eq!(
                    [got[0].to_bits(), got[1].to_bits()],
                    [pair[0].to_bits(), pair[1].to_bits()],
                    "level {l} sample {k}"
                );
            }
        }
    }
}

#[test]
fn backward_accumulates() {
    let layout = HashGridLayout::new(&small_config());
    let mut u = Uniforms(8);
    let positions: Vec<[f64; 3]> = (0..50).map(|_| u.position()).collect();
    let d_out: Vec<f64> = (0..50 * layout.output_width())
        .map(|_| u.symmetric())
        .collect();
    let mut fresh = vec![0.0; layout.param_count()];
    encode_backward(&layout, &positions, &d_out, &mut fresh);
    let before = random_params(&layout, 9);
    let mut accumulated = before.clone();
    encode_backward(&layout, &positions, &d_out, &mut accumulated);
    for ((b, f), a) in before.iter().zip(&fresh).zip(&accumulated) {
        // Same terms, summed onto a different start: equal up to the
        // rounding of a few dozen additions of O(1) values.
        assert!((a - (b + f)).abs() < 1e-13, "{a} vs {b} + {f}");
    }
    // The writing variant gives the fresh gradient whatever was there.
    let mut written = before.clone();
    encode_gradient_with_scratch(&layout, &positions, &d_out, &mut written, &mut Vec::new());
    assert_eq!(written, fresh);
    let mut empty = before;
    encode_gradient_with_scratch(&layout, &[], &[], &mut empty, &mut Vec::new());
    assert!(empty.iter().all(|&g| g == 0.0));
}

/// ⟨encode(θ, p), g⟩ and ⟨θ, backward(g)⟩ (both accumulated in f64), and
/// the scale of either: ⟨encode(|θ|, p), |g|⟩ = Σ over all terms of
/// |w · θ · g|, since the weights are ≥ 0.
fn adjoint_sides<T: Real>(
    layout: &HashGridLayout,
    params: &[T],
    positions: &[[T; 3]],
    d_out: &[T],
) -> (f64, f64, f64) {
    let to64 = |x: T| x.to_f64().unwrap();
    let mut out = vec![T::zero(); d_out.len()];
    encode(layout, params, positions, &mut out);
    let forward: f64 = out
        .iter()
        .zip(d_out)
        .map(|(&o, &g)| to64(o) * to64(g))
        .sum();
    let mut d_params = vec![T::zero(); params.len()];
    encode_backward(layout, positions, d_out, &mut d_params);
    let backward: f64 = params
        .iter()
        .zip(&d_params)
        .map(|(&p, &d)| to64(p) * to64(d))
        .sum();
    let abs_params: Vec<T> = params.iter().map(|p| p.abs()).collect();
    encode(layout, &abs_params, positions, &mut out);
    let scale: f64 = out
        .iter()
        .zip(d_out)
        .map(|(&o, &g)| to64(o) * to64(g).abs())
        .sum();
    (forward, backward, scale)
}

#[test]
fn backward_is_the_transpose_of_forward() {
    let layout = HashGridLayout::new(&HashGridConfig::paper(1.0));
    let mut u = Uniforms(99);
    let mut positions: Vec<[f64; 3]> = (0..4096).map(|_| u.position()).collect();
    positions.extend(hard_positions(&layout).into_iter().step_by(5));
    let d_out: Vec<f64> = (0..positions.len() * layout.output_width())
        .map(|_| u.symmetric())
        .collect();
    let params: Vec<f64> = layout
        .init_params(4)
        .iter()
        .map(|&p| p as f64 * 1e4)
        .collect();

    // f64: every output and every gradient entry is a short sum (8 terms;
    // at most a few hundred contributions per coarse entry), so both
    // sides agree to a few hundred ε of the scale.
    let (forward, backward, scale) = adjoint_sides(&layout, &params, &positions, &d_out);
    assert!(scale > 1.0);
    let error = (forward - backward).abs() / scale;
    eprintln!("adjoint identity, f64: {error:e} of the scale");
    assert!(
        error < 1e-12,
        "f64: {forward} vs {backward} (scale {scale}): {error:e}"
    );

    // f32: the same sums rounded to 2^-24 each; random rounding errors
    // partly cancel, but the bound is ~ (contributions per entry) · ε.
    let params32: Vec<f32> = params.iter().map(|&p| p as f32).collect();
    let positions32: Vec<[f32; 3]> = positions.iter().map(|p| p.map(|x| x as f32)).collect();
    let d_out32: Vec<f32> = d_out.iter().map(|&g| g as f32).collect();
    let (forward, backward, scale) = adjoint_sides(&layout, &params32, &positions32, &d_out32);
    let error = (forward - backward).abs() / scale;
    eprintln!("adjoint identity, f32: {error:e} of the scale");
    assert!(
        error < 1e-6,
        "f32: {forward} vs {backward} (scale {scale}): {error:e}"
    );
}

#[test]
fn f32_and_f64_encodings_agree() {
    let layout = HashGridLayout::new(&HashGridConfig::paper(1.0));
    let params = layout.init_params(6);
    let params64: Vec<f64> = params.iter().map(|&p| p as f64).collect();
    let mut u = Uniforms(17);
    let positions: Vec<[f32; 3]> = (0..3000).map(|_| u.position().map(|x| x as f32)).collect();
    let positions64: Vec<[f64; 3]> = positions.iter().map(|p| p.map(|x| x as f64)).collect();
    let width = layout.output_width();
    let mut out = vec![0.0f32; positions.len() * width];
    let mut out64 = vec![0.0f64; positions.len() * width];
    encode(&layout, &params, &positions, &mut out);
    encode(&layout, &params64, &positions64, &mut out64);
    for (a, b) in out.iter().zip(&out64) {
        // |θ| ≤ 1e-4 and the weights sum to 1; the f32 fractional part of
        // x · N carries an absolute error up to ε · N_max ≈ 2.4e-4, which
        // moves the output by at most that times the spread of θ.
        assert!(
            (*a as f64 - b).abs() < 1e-4 * 2.4e-4 * 4.0 + 1e-11,
            "{a} vs {b}"
        );
    }
}

#[test]
fn init_is_deterministic_and_in_range() {
    let layout = HashGridLayout::new(&small_config());
    let a = layout.init_params(1);
    assert_eq!(a, layout.init_params(1));
    assert_ne!(a, layout.init_params(2));
    let layout = HashGridLayout::new(&HashGridConfig::paper(1.0));
    let params = layout.init_params(1);
    let r = layout.config().init_range;
    assert!(params.iter().all(|&p| p >= -r && p < r));
    let n = params.len() as f64;
    let mean = params.iter().map(|&p| p as f64).sum::<f64>() / n;
    let mean_square = params.iter().map(|&p| (p as f64).powi(2)).sum::<f64>() / n;
    // U(−r, r): mean 0 with standard error r/√(3n) ≈ 1.7e-8; variance r²/3.
    assert!(mean.abs() < 1e-7, "{mean}");
    assert!((mean_square / (r as f64).powi(2) - 1.0 / 3.0).abs() < 1e-3);
}

/// The positions' gradient against central differences in f64, on random
/// positions inside cells and a grid spanning a box larger than the unit
/// cube: the encoding is trilinear inside a cell, so the difference of a
/// step that stays in the cell has only rounding and second-order terms
/// of the products of two axes' weights, which cancel in a central
/// difference; h = 1e-7 of the box, far from any of the finest level's
/// cell edges (1/16) for these positions, leaves ~1e-9.
#[test]
fn position_gradients_match_central_differences() {
    let config = HashGridConfig {
        extent: 2.0,
        ..small_config()
    };
    let layout = HashGridLayout::new(&config);
    let mut u = Uniforms(77);
    let positions: Vec<[f64; 3]> = (0..60)
        .map(|_| u.position().map(|x| 2.0 * x - 0.5))
        .collect();
    let d_out: Vec<f64> = (0..positions.len() * layout.output_width())
        .map(|_| u.symmetric())
        .collect();
    let params = random_params(&layout, 9);
    let mut d_positions = vec![[0.0; 3]; positions.len()];
    position_gradient(&layout, &params, &positions, &d_out, &mut d_positions);
    let h = 1e-7;
    let mut largest = 0f64;
    for (s, position) in positions.iter().enumerate() {
        let row = &d_out[s * layout.output_width()..][..layout.output_width()];
        for axis in 0..3 {
            let at = |offset: f64| {
                let mut p = *position;
                p[axis] += offset;
                loss(&layout, &params, &[p], row)
            };
            let numeric = (at(h) - at(-h)) / (2.0 * h);
            let analytic = d_positions[s][axis];
            assert!(
                (analytic - numeric).abs() < 1e-6 * (1.0 + numeric.abs()),
                "sample {s} axis {axis}: analytic {analytic} numeric {numeric}"
            );
            largest = largest.max(analytic.abs());
        }
    }
    // A gradient of zero everywhere would pass the comparison.
    assert!(largest > 1.0, "{largest}");
}

/// A coordinate clamped onto the box's face does not move the features.
#[test]
fn positions_outside_the_box_have_no_gradient_along_the_clamped_axis() {
    let layout = HashGridLayout::new(&small_config());
    let params = random_params(&layout, 3);
    let d_out = vec![1.0; layout.output_width()];
    let mut d_positions = vec![[0.0; 3]];
    position_gradient(
        &layout,
        &params,
        &[[1.5, 0.3, 0.6]],
        &d_out,
        &mut d_positions,
    );
    assert_eq!(d_positions[0][0], 0.0);
    assert!(d_positions[0][1] != 0.0 && d_positions[0][2] != 0.0);
}
