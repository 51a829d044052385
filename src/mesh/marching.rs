//! Marching cubes over a scalar field sampled on a regular grid.
//!
//! The triangulation of each cube is derived from its corner values rather
//! than looked up in the classic 256-case table: on each of the cube's six
//! faces the iso-line is a set of segments between the crossings on the
//! face's edges, and the segments of the six faces join into closed loops,
//! each of which becomes a fan of triangles. A face with four crossings
//! (two inside corners on a diagonal) is resolved by the asymptotic decider
//! (Nielson and Hamann 1991): whether the bilinear interpolant's saddle is
//! inside. That decision depends only on the face's four values, so the two
//! cubes sharing a face always cut it the same way, and the surface is
//! closed with no cracks — which the classic table, resolving ambiguous
//! faces by the corner pattern alone, does not guarantee. Deriving the
//! triangulation also leaves no 4096-entry table to type in and get wrong.
//!
//! Vertices lie on grid edges and are shared: one vertex per crossed grid
//! edge, whichever cubes use it, so the mesh is indexed and its edges can be
//! counted (every edge of a closed surface is shared by exactly two faces).

use std::collections::HashMap;

use glam::Vec3;

use super::Mesh;

/// A scalar field sampled at the nodes of a regular grid: node (i, j, k) is
/// at `origin + (i, j, k) * spacing` and its value is
/// `values[i + nx * (j + ny * k)]`.
#[derive(Debug, Clone, PartialEq)]
pub struct ScalarGrid {
    pub dims: [usize; 3],
    pub origin: Vec3,
    pub spacing: Vec3,
    pub values: Vec<f32>,
}

impl ScalarGrid {
    /// Samples `field` at every node, nodes in x-fastest order.
    pub fn sample(
        dims: [usize; 3],
        origin: Vec3,
        spacing: Vec3,
        field: impl Fn(Vec3) -> f32,
    ) -> Self {
        let mut values = Vec::with_capacity(dims[0] * dims[1] * dims[2]);
        for k in 0..dims[2] {
            for j in 0..dims[1] {
                for i in 0..dims[0] {
                    values.push(field(
                        origin + Vec3::new(i as f32, j as f32, k as f32) * spacing,
                    ));
                }
            }
        }
        Self {
            dims,
            origin,
            spacing,
            values,
        }
    }

    /// The linear index of node (i, j, k).
    #[inline]
    pub fn index(&self, i: usize, j: usize, k: usize) -> usize {
        i + self.dims[0] * (j + self.dims[1] * k)
    }

    /// Where node (i, j, k) is.
    #[inline]
    pub fn position(&self, i: usize, j: usize, k: usize) -> Vec3 {
        self.origin + Vec3::new(i as f32, j as f32, k as f32) * self.spacing
    }

    /// The gradient of the field at node (i, j, k) by central differences
    /// (one-sided at the grid's faces).
    pub fn gradient(&self, i: usize, j: usize, k: usize) -> Vec3 {
        let node = [i, j, k];
        let mut gradient = Vec3::ZERO;
        for axis in 0..3 {
            let (mut lo, mut hi) = (node, node);
            lo[axis] = node[axis].saturating_sub(1);
            hi[axis] = (node[axis] + 1).min(self.dims[axis] - 1);
            if lo[axis] == hi[axis] {
                continue;
            }
            let difference = self.values[self.index(hi[0], hi[1], hi[2])]
                - self.values[self.index(lo[0], lo[1], lo[2])];
            gradient[axis] = difference / ((hi[axis] - lo[axis]) as f32 * self.spacing[axis]);
        }
        gradient
    }
}

/// The corners of each cube face, counter-clockwise seen from outside the
/// cube (so that the right-hand normal points out). A corner's number is
/// `dx + 2 dy + 4 dz` for its offset (dx, dy, dz) from the cube's lowest
/// corner.
const FACES: [[usize; 4]; 6] = [
    [0, 4, 6, 2], // x = 0
    [1, 3, 7, 5], // x = 1
    [0, 1, 5, 4], // y = 0
    [2, 6, 7, 3], // y = 1
    [0, 2, 3, 1], // z = 0
    [4, 5, 7, 6], // z = 1
];

/// The offset of corner `c` from the cube's lowest corner.
#[inline]
fn corner_offset(c: usize) -> [usize; 3] {
    [c & 1, (c >> 1) & 1, (c >> 2) & 1]
}

/// A cube edge between two corners, as the lower corner's number and the
/// axis: `lower * 3 + axis`, below 24.
#[inline]
fn edge_key(a: usize, b: usize) -> usize {
    let (lower, upper) = (a.min(b), a.max(b));
    let axis = (upper ^ lower).trailing_zeros() as usize;
    lower * 3 + axis
}

/// Extracts the surface where the grid's values cross `iso`, as an indexed
/// mesh with outward-facing triangles ("inside" is above `iso`: for a
/// density field, the solid). Vertex colours are left white.
///
/// Nodes on the grid's outer faces are treated as outside when `close` is
/// set, so a surface that leaves the grid is closed along its faces and
/// every vertex lies within the grid's box.
pub fn marching_cubes(grid: &ScalarGrid, iso: f32, close: bool) -> Mesh {
    let [nx, ny, nz] = grid.dims;
    let mut mesh = Mesh::default();
    if nx < 2 || ny < 2 || nz < 2 {
        return mesh;
    }
    let on_boundary = |i: usize, j: usize, k: usize| {
        i == 0 || j == 0 || k == 0 || i == nx - 1 || j == ny - 1 || k == nz - 1
    };
    // NaN compares false: a node without a value is outside.
    let value = |i: usize, j: usize, k: usize| -> f32 {
        if close && on_boundary(i, j, k) {
            f32::NEG_INFINITY
        } else {
            grid.values[grid.index(i, j, k)]
        }
    };
    let inside = |v: f32| v > iso;
    // One vertex per crossed grid edge: key = lower node's index · 3 + axis.
    let mut vertex_of_edge: HashMap<u64, u32> = HashMap::new();
    let mut values = [0f32; 8];
    for k in 0..nz - 1 {
        for j in 0..ny - 1 {
            for i in 0..nx - 1 {
                let mut inside_count = 0;
                for (c, v) in values.iter_mut().enumerate() {
                    let [dx, dy, dz] = corner_offset(c);
                    *v = value(i + dx, j + dy, k + dz);
                    inside_count += inside(*v) as usize;
                }
                if inside_count == 0 || inside_count == 8 {
                    continue;
                }
                // Where each crossed cube edge leads to along the iso-line,
                // following the faces' segments.
                let mut next = [u8::MAX; 24];
                for face in FACES {
                    let inside_at = face.map(|c| inside(values[c]));
                    // Edge e joins corners face[e] and face[e + 1].
                    let crossed = |e: usize| inside_at[e] != inside_at[(e + 1) % 4];
                    let leaving = |e: usize| inside_at[e] && !inside_at[(e + 1) % 4];
                    let key = |e: usize| edge_key(face[e], face[(e + 1) % 4]) as u8;
                    let crossings = (0..4).filter(|&e| crossed(e)).count();
                    match crossings {
                        0 => {}
                        2 => {
                            let from = (0..4).find(|&e| leaving(e)).expect("one edge leaves");
                            let to = (0..4)
                                .find(|&e| crossed(e) && !leaving(e))
                                .expect("one edge enters");
                            next[key(from) as usize] = key(to);
                        }
                        4 => {
                            // The asymptotic decider: the bilinear
                            // interpolant's saddle value decides whether
                            // the two inside corners are joined.
                            let [a, b, c, d] = face.map(|c| values[c] as f64);
                            let denominator = a + c - b - d;
                            let joined = if denominator == 0.0 || !denominator.is_finite() {
                                // Infinite corners (closed faces) or a flat
                                // saddle: keep the inside corners apart.
                                false
                            } else {
                                inside(((a * c - b * d) / denominator) as f32)
                            };
                            for e in (0..4).filter(|&e| leaving(e)) {
                                // Joined: around the outside corner after
                                // edge e; apart: around the inside corner
                                // before it.
                                let to = if joined { (e + 1) % 4 } else { (e + 3) % 4 };
                                next[key(e) as usize] = key(to);
                            }
                        }
                        _ => unreachable!("a face's edges are crossed an even number of times"),
                    }
                }
                // Follow the loops, each into a fan of triangles.
                let mut visited = [false; 24];
                for start in 0..24 {
                    if next[start] == u8::MAX || visited[start] {
                        continue;
                    }
                    let mut polygon = [0u32; 12];
                    let mut keys = [0usize; 12];
                    let mut length = 0;
                    let mut at = start;
                    while !visited[at] {
                        visited[at] = true;
                        keys[length] = at;
                        polygon[length] = vertex_id(
                            grid,
                            &mut mesh,
                            &mut vertex_of_edge,
                            [i, j, k],
                            at,
                            iso,
                            &value,
                        );
                        length += 1;
                        at = next[at] as usize;
                    }
                    debug_assert_eq!(at, start, "a face's segments form closed loops");
                    triangulate(&mut mesh, &polygon[..length], &keys[..length]);
                }
            }
        }
    }
    mesh.colours = vec![[255; 3]; mesh.positions.len()];
    mesh
}

/// The faces (bits of [`FACES`]) that cube edge `key` lies on.
fn faces_of_edge(key: usize) -> u8 {
    let (a, axis) = (key / 3, key % 3);
    let b = a | (1 << axis);
    let mut mask = 0;
    for (f, face) in FACES.iter().enumerate() {
        if face.contains(&a) && face.contains(&b) {
            mask |= 1 << f;
        }
    }
    mask
}

/// Splits one loop (vertices `polygon` on cube edges `keys`, clockwise
/// seen from outside) into outward-facing triangles.
///
/// A fan's diagonals must not join two vertices on a common cube face:
/// the neighbouring cube across that face may join the same two vertices
/// too (on a face with four crossings), and the edge would then belong to
/// three or four triangles. The first corner whose diagonals avoid that is
/// the fan's apex; a loop with none gets a vertex at its centroid instead.
fn triangulate(mesh: &mut Mesh, polygon: &[u32], keys: &[usize]) {
    let n = polygon.len();
    let apex = (0..n).find(|&a| {
        (2..n - 1).all(|offset| faces_of_edge(keys[a]) & faces_of_edge(keys[(a + offset) % n]) == 0)
    });
    // The loops run clockwise seen from outside the solid (each face's
    // segments keep the solid on their left seen from outside the cube):
    // the triangles reverse them.
    match apex {
        Some(a) => {
            for t in 1..n - 1 {
                let (p, q) = ((a + t) % n, (a + t + 1) % n);
                mesh.faces.push([polygon[a], polygon[q], polygon[p]]);
            }
        }
        None => {
            let centre = polygon
                .iter()
                .map(|&v| mesh.positions[v as usize])
                .sum::<Vec3>()
                / n as f32;
            mesh.positions.push(centre);
            let c = (mesh.positions.len() - 1) as u32;
            for t in 0..n {
                mesh.faces.push([c, polygon[(t + 1) % n], polygon[t]]);
            }
        }
    }
}

/// The mesh's vertex on cube edge `key` (`lower corner · 3 + axis`) of the
/// cube whose lowest node is `cube`, added at its first use.
fn vertex_id(
    grid: &ScalarGrid,
    mesh: &mut Mesh,
    vertex_of_edge: &mut HashMap<u64, u32>,
    cube: [usize; 3],
    key: usize,
    iso: f32,
    value: &impl Fn(usize, usize, usize) -> f32,
) -> u32 {
    let (corner, axis) = (key / 3, key % 3);
    let offset = corner_offset(corner);
    let lower = [
        cube[0] + offset[0],
        cube[1] + offset[1],
        cube[2] + offset[2],
    ];
    let global = grid.index(lower[0], lower[1], lower[2]) as u64 * 3 + axis as u64;
    *vertex_of_edge.entry(global).or_insert_with(|| {
        let mut upper = lower;
        upper[axis] += 1;
        let a = value(lower[0], lower[1], lower[2]);
        let b = value(upper[0], upper[1], upper[2]);
        // Where the linear interpolant crosses `iso`. An edge to a node
        // forced outside (a closed face) has no crossing to interpolate:
        // its midpoint keeps the cap half a cell inside the grid, with no
        // vertices piled on the face's nodes.
        let t = if a == f32::NEG_INFINITY || b == f32::NEG_INFINITY {
            0.5
        } else {
            ((iso - a) / (b - a)).clamp(0.0, 1.0)
        };
        let t = if t.is_finite() { t } else { 0.5 };
        let p = grid.position(lower[0], lower[1], lower[2]);
        let q = grid.position(upper[0], upper[1], upper[2]);
        mesh.positions.push(p + (q - p) * t);
        (mesh.positions.len() - 1) as u32
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn faces_are_counter_clockwise_seen_from_outside() {
        let position = |c: usize| {
            let [x, y, z] = corner_offset(c);
            Vec3::new(x as f32, y as f32, z as f32)
        };
        for face in FACES {
            let p = face.map(position);
            let normal = (p[1] - p[0]).cross(p[2] - p[1]);
            let centre = (p[0] + p[1] + p[2] + p[3]) / 4.0;
            // Outward: from the cube's centre towards the face's.
            assert!(normal.dot(centre - Vec3::splat(0.5)) > 0.0, "{face:?}");
            // Each consecutive pair is one edge of the cube.
            for e in 0..4 {
                let (a, b) = (face[e], face[(e + 1) % 4]);
                assert_eq!((a ^ b).count_ones(), 1, "{face:?}");
                assert!(edge_key(a, b) < 24);
            }
        }
    }
}
