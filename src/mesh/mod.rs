//! Triangle meshes of a scene: extraction by marching cubes
//! ([`marching`]), their topology and clean-up, and the files they are
//! written as (binary PLY, OBJ).

pub mod extract;
pub mod marching;
pub mod points;

use std::collections::HashMap;
use std::io::Write;
use std::path::Path;

use glam::Vec3;

/// An indexed triangle mesh with a colour per vertex.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Mesh {
    pub positions: Vec<Vec3>,
    /// 8-bit sRGB, one per position.
    pub colours: Vec<[u8; 3]>,
    /// Counter-clockwise seen from outside.
    pub faces: Vec<[u32; 3]>,
}

/// How many faces share each undirected edge, and what that says about the
/// surface.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Topology {
    pub vertices: usize,
    pub edges: usize,
    pub faces: usize,
    /// Edges used by one face only (holes' rims).
    pub boundary_edges: usize,
    /// Edges used by three faces or more.
    pub non_manifold_edges: usize,
    /// Edges used twice in the same direction: neighbouring faces that
    /// disagree about which side is out.
    pub misoriented_edges: usize,
}

impl Topology {
    /// V − E + F: 2 for a sphere, 0 for a torus, 2 − 2g for a closed
    /// surface of genus g (summed over components).
    pub fn euler_characteristic(&self) -> i64 {
        self.vertices as i64 - self.edges as i64 + self.faces as i64
    }

    /// Every edge is shared by exactly two faces that agree on which side
    /// is out.
    pub fn is_closed_manifold(&self) -> bool {
        self.boundary_edges == 0 && self.non_manifold_edges == 0 && self.misoriented_edges == 0
    }
}

/// What to do with small disconnected pieces of a mesh (floaters).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum MinComponent {
    /// Drop pieces of fewer faces than this.
    Faces(usize),
    /// Drop pieces holding less than this share (0 to 1) of all faces.
    Fraction(f64),
}

impl std::str::FromStr for MinComponent {
    type Err = String;

    /// `500` (faces), `0.01` or `1%` (a share of all faces).
    fn from_str(text: &str) -> Result<Self, String> {
        let text = text.trim();
        let refusal = || {
            format!(
                "`{text}` is no component size: give a face count (500) or a share of all \
                 faces (0.01 or 1%)"
            )
        };
        if let Some(percent) = text.strip_suffix('%') {
            let value: f64 = percent.trim().parse().map_err(|_| refusal())?;
            if !(0.0..=100.0).contains(&value) {
                return Err(format!("`{text}`: a share must be 0% to 100%"));
            }
            return Ok(MinComponent::Fraction(value / 100.0));
        }
        if let Ok(faces) = text.parse::<usize>() {
            return Ok(MinComponent::Faces(faces));
        }
        let value: f64 = text.parse().map_err(|_| refusal())?;
        if !(0.0..=1.0).contains(&value) {
            return Err(format!(
                "`{text}`: a share of all faces must be 0 to 1 (or a whole number of faces)"
            ));
        }
        Ok(MinComponent::Fraction(value))
    }
}

impl Mesh {
    pub fn topology(&self) -> Topology {
        // Directed uses of each undirected edge.
        let mut uses: HashMap<(u32, u32), (u32, u32)> = HashMap::new();
        for face in &self.faces {
            for e in 0..3 {
                let (a, b) = (face[e], face[(e + 1) % 3]);
                let entry = uses.entry((a.min(b), a.max(b))).or_default();
                if a < b {
                    entry.0 += 1;
                } else {
                    entry.1 += 1;
                }
            }
        }
        let mut topology = Topology {
            vertices: self.positions.len(),
            edges: uses.len(),
            faces: self.faces.len(),
            boundary_edges: 0,
            non_manifold_edges: 0,
            misoriented_edges: 0,
        };
        for &(forward, backward) in uses.values() {
            match forward + backward {
                1 => topology.boundary_edges += 1,
                2 if forward != 1 => topology.misoriented_edges += 1,
                2 => {}
                _ => topology.non_manifold_edges += 1,
            }
        }
        topology
    }

    pub fn area(&self) -> f64 {
        self.faces
            .iter()
            .map(|f| {
                let [a, b, c] = f.map(|i| self.positions[i as usize].as_dvec3());
                0.5 * (b - a).cross(c - a).length()
            })
            .sum()
    }

    /// The volume enclosed, positive when the faces face outwards (for a
    /// closed mesh).
    pub fn signed_volume(&self) -> f64 {
        self.faces
            .iter()
            .map(|f| {
                let [a, b, c] = f.map(|i| self.positions[i as usize].as_dvec3());
                a.dot(b.cross(c)) / 6.0
            })
            .sum()
    }

    /// The component (0, 1, …) each face belongs to, faces being connected
    /// through shared vertices, and the faces in each component.
    pub fn components(&self) -> (Vec<u32>, Vec<usize>) {
        let mut parent: Vec<u32> = (0..self.positions.len() as u32).collect();
        fn root(parent: &mut [u32], mut v: u32) -> u32 {
            while parent[v as usize] != v {
                // Path halving.
                parent[v as usize] = parent[parent[v as usize] as usize];
                v = parent[v as usize];
            }
            v
        }
        for face in &self.faces {
            let a = root(&mut parent, face[0]);
            for &v in &face[1..] {
                let b = root(&mut parent, v);
                if a != b {
                    parent[b as usize] = a;
                }
            }
        }
        let mut label_of_root: HashMap<u32, u32> = HashMap::new();
        let mut sizes = Vec::new();
        let labels = self
            .faces
            .iter()
            .map(|face| {
                let r = root(&mut parent, face[0]);
                let next = label_of_root.len() as u32;
                let label = *label_of_root.entry(r).or_insert(next);
                if label as usize == sizes.len() {
                    sizes.push(0);
                }
                sizes[label as usize] += 1;
                label
            })
            .collect();
        (labels, sizes)
    }

    /// Drops the components smaller than `min`, and the vertices only they
    /// used. Returns how many components were dropped.
    pub fn remove_small_components(&mut self, min: MinComponent) -> usize {
        let (labels, sizes) = self.components();
        let threshold = match min {
            MinComponent::Faces(faces) => faces as f64,
            MinComponent::Fraction(share) => share * self.faces.len() as f64,
        };
        let keep: Vec<bool> = sizes.iter().map(|&s| s as f64 >= threshold).collect();
        let dropped = keep.iter().filter(|k| !**k).count();
        if dropped == 0 {
            return 0;
        }
        let faces: Vec<[u32; 3]> = self
            .faces
            .iter()
            .zip(&labels)
            .filter(|(_, l)| keep[**l as usize])
            .map(|(f, _)| *f)
            .collect();
        self.faces = faces;
        self.drop_unused_vertices();
        dropped
    }

    /// Removes vertices no face uses, renumbering the faces.
    pub fn drop_unused_vertices(&mut self) {
        let mut new_index = vec![u32::MAX; self.positions.len()];
        let (mut positions, mut colours) = (Vec::new(), Vec::new());
        for face in &mut self.faces {
            for v in face.iter_mut() {
                let slot = &mut new_index[*v as usize];
                if *slot == u32::MAX {
                    *slot = positions.len() as u32;
                    positions.push(self.positions[*v as usize]);
                    colours.push(self.colours.get(*v as usize).copied().unwrap_or([255; 3]));
                }
                *v = *slot;
            }
        }
        self.positions = positions;
        self.colours = colours;
    }

    /// The mesh as a binary little-endian PLY file: vertices with `x y z`
    /// (float) and `red green blue` (uchar), faces as `vertex_indices`
    /// (a uchar count, then int indices). PLY's format: Greg Turk, "The PLY
    /// Polygon File Format" (1994), the header layout MeshLab, Blender and
    /// Open3D read.
    pub fn to_ply(&self) -> Vec<u8> {
        let mut out = ply_header(self.positions.len(), Some(self.faces.len())).into_bytes();
        out.reserve(self.positions.len() * 15 + self.faces.len() * 13);
        for (p, c) in self.positions.iter().zip(self.colours_or_white()) {
            for x in p.to_array() {
                out.extend_from_slice(&x.to_le_bytes());
            }
            out.extend_from_slice(&c);
        }
        for face in &self.faces {
            out.push(3);
            for &v in face {
                out.extend_from_slice(&(v as i32).to_le_bytes());
            }
        }
        out
    }

    /// The mesh as Wavefront OBJ text: `v x y z r g b` (the vertex-colour
    /// extension MeshLab and Blender read, colours 0 to 1) and `f a b c`
    /// with 1-based indices.
    pub fn to_obj(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(self.positions.len() * 48 + self.faces.len() * 24);
        out.extend_from_slice(b"# written by zrak\n");
        for (p, c) in self.positions.iter().zip(self.colours_or_white()) {
            let _ = writeln!(
                out,
                "v {} {} {} {:.4} {:.4} {:.4}",
                p.x,
                p.y,
                p.z,
                c[0] as f32 / 255.0,
                c[1] as f32 / 255.0,
                c[2] as f32 / 255.0
            );
        }
        for f in &self.faces {
            let _ = writeln!(out, "f {} {} {}", f[0] + 1, f[1] + 1, f[2] + 1);
        }
        out
    }

    fn colours_or_white(&self) -> impl Iterator<Item = [u8; 3]> + '_ {
        (0..self.positions.len()).map(|i| self.colours.get(i).copied().unwrap_or([255; 3]))
    }

    /// Writes the mesh as PLY or OBJ, by `path`'s extension.
    pub fn write(&self, path: &Path) -> Result<(), String> {
        let bytes = match MeshFormat::of_path(path)? {
            MeshFormat::Ply => self.to_ply(),
            MeshFormat::Obj => self.to_obj(),
        };
        crate::files::write_bytes_atomically(path, &bytes)
            .map_err(|e| format!("{}: cannot write the mesh: {e}", path.display()))
    }
}

/// The header of a binary PLY file with `vertices` coloured vertices and,
/// when given, that many triangle faces.
pub fn ply_header(vertices: usize, faces: Option<usize>) -> String {
    let mut header = format!(
        "ply\nformat binary_little_endian 1.0\ncomment written by zrak\nelement vertex {vertices}\n\
         property float x\nproperty float y\nproperty float z\n\
         property uchar red\nproperty uchar green\nproperty uchar blue\n"
    );
    if let Some(faces) = faces {
        header.push_str(&format!(
            "element face {faces}\nproperty list uchar int vertex_indices\n"
        ));
    }
    header.push_str("end_header\n");
    header
}

/// A coloured point cloud as a binary PLY file (vertices only).
pub fn points_to_ply(positions: &[Vec3], colours: &[[u8; 3]]) -> Vec<u8> {
    Mesh {
        positions: positions.to_vec(),
        colours: colours.to_vec(),
        faces: Vec::new(),
    }
    .to_ply_without_faces()
}

impl Mesh {
    fn to_ply_without_faces(&self) -> Vec<u8> {
        let mut out = ply_header(self.positions.len(), None).into_bytes();
        for (p, c) in self.positions.iter().zip(self.colours_or_white()) {
            for x in p.to_array() {
                out.extend_from_slice(&x.to_le_bytes());
            }
            out.extend_from_slice(&c);
        }
        out
    }
}

/// The mesh files zrak writes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MeshFormat {
    Ply,
    Obj,
}

impl MeshFormat {
    /// The format `path`'s extension names (case-insensitive).
    pub fn of_path(path: &Path) -> Result<Self, String> {
        let extension = path
            .extension()
            .map(|e| e.to_string_lossy().to_ascii_lowercase());
        match extension.as_deref() {
            Some("ply") => Ok(MeshFormat::Ply),
            Some("obj") => Ok(MeshFormat::Obj),
            Some(other) => Err(format!(
                "{}: unknown mesh format `.{other}`; give a .ply or .obj file",
                path.display()
            )),
            None => Err(format!(
                "{}: no extension to tell the mesh format by; give a .ply or .obj file",
                path.display()
            )),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::marching::{ScalarGrid, marching_cubes};
    use super::*;

    /// A binary PLY file read back: vertices (position, colour) and faces,
    /// parsed from the header's declarations as any reader would.
    fn read_ply(bytes: &[u8]) -> (Vec<Vec3>, Vec<[u8; 3]>, Vec<Vec<i32>>) {
        let end = b"end_header\n";
        let header_end = bytes
            .windows(end.len())
            .position(|w| w == end)
            .expect("an end_header line")
            + end.len();
        let header = std::str::from_utf8(&bytes[..header_end]).unwrap();
        let mut lines = header.lines();
        assert_eq!(lines.next(), Some("ply"));
        assert_eq!(lines.next(), Some("format binary_little_endian 1.0"));
        let (mut vertices, mut faces) = (0, 0);
        let mut vertex_properties = Vec::new();
        let mut current = "";
        for line in lines {
            let words: Vec<&str> = line.split_whitespace().collect();
            match words.as_slice() {
                ["element", "vertex", n] => {
                    vertices = n.parse().unwrap();
                    current = "vertex";
                }
                ["element", "face", n] => {
                    faces = n.parse().unwrap();
                    current = "face";
                }
                ["property", "list", "uchar", "int", "vertex_indices"] => {
                    assert_eq!(current, "face")
                }
                ["property", kind, name] if current == "vertex" => {
                    vertex_properties.push((kind.to_string(), name.to_string()))
                }
                ["comment", ..] | ["end_header"] => {}
                other => panic!("unexpected header line {other:?}"),
            }
        }
        let names: Vec<_> = vertex_properties
            .iter()
            .map(|(k, n)| format!("{k} {n}"))
            .collect();
        assert_eq!(
            names,
            [
                "float x",
                "float y",
                "float z",
                "uchar red",
                "uchar green",
                "uchar blue"
            ]
        );
        let mut at = header_end;
        let mut take = |n: usize| {
            let slice = &bytes[at..at + n];
            at += n;
            slice
        };
        let (mut positions, mut colours, mut face_list) = (Vec::new(), Vec::new(), Vec::new());
        for _ in 0..vertices {
            let mut p = [0f32; 3];
            for x in &mut p {
                *x = f32::from_le_bytes(take(4).try_into().unwrap());
            }
            positions.push(Vec3::from(p));
            colours.push(take(3).try_into().unwrap());
        }
        for _ in 0..faces {
            let count = take(1)[0] as usize;
            face_list.push(
                (0..count)
                    .map(|_| i32::from_le_bytes(take(4).try_into().unwrap()))
                    .collect(),
            );
        }
        assert_eq!(at, bytes.len(), "no bytes after the last face");
        (positions, colours, face_list)
    }

    fn tetrahedron() -> Mesh {
        Mesh {
            positions: vec![Vec3::ZERO, Vec3::X, Vec3::Y, Vec3::new(0.25, -1.5e-7, 1e30)],
            colours: vec![[255, 0, 0], [0, 255, 0], [0, 0, 255], [1, 2, 3]],
            faces: vec![[0, 2, 1], [0, 1, 3], [1, 2, 3], [2, 0, 3]],
        }
    }

    #[test]
    fn binary_ply_reads_back_bit_for_bit() {
        let mesh = tetrahedron();
        let (positions, colours, faces) = read_ply(&mesh.to_ply());
        assert_eq!(positions, mesh.positions);
        assert_eq!(colours, mesh.colours);
        let faces: Vec<[u32; 3]> = faces
            .iter()
            .map(|f| {
                assert_eq!(f.len(), 3);
                [f[0] as u32, f[1] as u32, f[2] as u32]
            })
            .collect();
        assert_eq!(faces, mesh.faces);

        // A point cloud: the vertex element only.
        let bytes = points_to_ply(&mesh.positions, &mesh.colours);
        let (positions, colours, faces) = read_ply(&bytes);
        assert_eq!((positions, colours), (mesh.positions, mesh.colours));
        assert!(faces.is_empty());
    }

    #[test]
    fn obj_reads_back_with_one_based_faces_and_unit_colours() {
        let mesh = tetrahedron();
        let text = String::from_utf8(mesh.to_obj()).unwrap();
        let (mut positions, mut colours, mut faces) = (Vec::new(), Vec::new(), Vec::new());
        for line in text.lines() {
            let words: Vec<&str> = line.split_whitespace().collect();
            match words.first() {
                Some(&"v") => {
                    let x: Vec<f32> = words[1..].iter().map(|w| w.parse().unwrap()).collect();
                    assert_eq!(x.len(), 6);
                    positions.push(Vec3::new(x[0], x[1], x[2]));
                    colours.push([x[3], x[4], x[5]].map(|c| (c * 255.0).round() as u8));
                }
                Some(&"f") => {
                    let f: Vec<u32> = words[1..].iter().map(|w| w.parse().unwrap()).collect();
                    faces.push([f[0] - 1, f[1] - 1, f[2] - 1]);
                }
                Some(&"#") => {}
                other => panic!("unexpected line {other:?}"),
            }
        }
        // Rust prints the shortest text that reads back as the same float.
        assert_eq!(positions, mesh.positions);
        assert_eq!(colours, mesh.colours);
        assert_eq!(faces, mesh.faces);
    }

    #[test]
    fn the_format_comes_from_the_extension() {
        assert_eq!(
            MeshFormat::of_path(Path::new("a/scene.PLY")),
            Ok(MeshFormat::Ply)
        );
        assert_eq!(
            MeshFormat::of_path(Path::new("scene.obj")),
            Ok(MeshFormat::Obj)
        );
        assert_eq!(
            MeshFormat::of_path(Path::new("scene.stl")).unwrap_err(),
            "scene.stl: unknown mesh format `.stl`; give a .ply or .obj file"
        );
        assert_eq!(
            MeshFormat::of_path(Path::new("scene")).unwrap_err(),
            "scene: no extension to tell the mesh format by; give a .ply or .obj file"
        );
    }

    /// Samples `field` on an n³ grid over [−half, half]³.
    fn grid_over(n: usize, half: f32, field: impl Fn(Vec3) -> f32) -> ScalarGrid {
        let spacing = 2.0 * half / (n - 1) as f32;
        ScalarGrid::sample([n; 3], Vec3::splat(-half), Vec3::splat(spacing), field)
    }

    #[test]
    fn a_sphere_is_a_closed_manifold_of_euler_characteristic_two_and_the_right_area() {
        // r = 1 on a 101³ grid over [−1.25, 1.25]³: 40 cells per radius.
        // The field is the signed distance (inside positive), which the
        // edges' linear interpolation follows to second order in the cell
        // size: the measured area is 0.02 % below 4πr² (12.5639 against
        // 12.5664); the test allows the 1 %.
        let r = 1.0;
        let grid = grid_over(101, 1.25, |p| r - p.length());
        let mesh = marching_cubes(&grid, 0.0, true);
        let topology = mesh.topology();
        assert!(topology.is_closed_manifold(), "{topology:?}");
        assert_eq!(topology.euler_characteristic(), 2, "{topology:?}");
        let exact = 4.0 * std::f64::consts::PI * r as f64 * r as f64;
        let area = mesh.area();
        eprintln!(
            "sphere: {topology:?}, area {area:.5} (4πr² = {exact:.5}, {:+.3} %)",
            100.0 * (area - exact) / exact
        );
        assert!(
            (area - exact).abs() < 0.01 * exact,
            "area {area}, 4πr² = {exact}"
        );
        // Faces face out: the enclosed volume is positive and near 4/3 πr³.
        let volume = mesh.signed_volume();
        let exact_volume = 4.0 / 3.0 * std::f64::consts::PI;
        assert!(
            (volume - exact_volume).abs() < 0.01 * exact_volume,
            "volume {volume}"
        );
        // Every vertex is on the sphere to a small part of a cell (0.025).
        for p in &mesh.positions {
            assert!((p.length() - r).abs() < 2e-3, "{p}");
        }
        // And a coarse grid (5 cells per radius) is still closed.
        let coarse = marching_cubes(&grid_over(13, 1.25, |p| r - p.length()), 0.0, true);
        assert!(coarse.topology().is_closed_manifold());
        assert_eq!(coarse.topology().euler_characteristic(), 2);
    }

    #[test]
    fn a_torus_has_euler_characteristic_zero() {
        // Major radius 0.8, minor 0.3, around z; 81³ grid over [−1.2, 1.2]³.
        let torus = |p: Vec3| {
            let ring = Vec3::new(p.x, p.y, 0.0).length() - 0.8;
            0.3 - (ring * ring + p.z * p.z).sqrt()
        };
        let mesh = marching_cubes(&grid_over(81, 1.2, torus), 0.0, true);
        let topology = mesh.topology();
        assert!(topology.is_closed_manifold(), "{topology:?}");
        assert_eq!(topology.euler_characteristic(), 0, "{topology:?}");
        // Area 4π²Rr.
        let exact = 4.0 * std::f64::consts::PI.powi(2) * 0.8 * 0.3;
        assert!((mesh.area() - exact).abs() < 0.01 * exact);
        // Two separate spheres are two components, χ = 4.
        let two =
            |p: Vec3| (0.4 - (p - Vec3::X * 0.6).length()).max(0.3 - (p + Vec3::X * 0.6).length());
        let mesh = marching_cubes(&grid_over(61, 1.2, two), 0.0, true);
        assert_eq!(mesh.topology().euler_characteristic(), 4);
        assert_eq!(mesh.components().1.len(), 2);
    }

    #[test]
    fn ambiguous_faces_are_cut_the_same_way_from_both_sides() {
        // Random values: every kind of cube and face, ambiguous ones
        // included. With the asymptotic decider the result must still be
        // a closed, consistently oriented surface.
        let mut state = 12345u64;
        let mut random = move || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 40) as f32 / (1u64 << 24) as f32
        };
        let n = 24;
        let values: Vec<f32> = (0..n * n * n).map(|_| random() - 0.5).collect();
        let grid = ScalarGrid {
            dims: [n; 3],
            origin: Vec3::ZERO,
            spacing: Vec3::ONE,
            values,
        };
        let mesh = marching_cubes(&grid, 0.0, true);
        assert!(mesh.faces.len() > 1000);
        let topology = mesh.topology();
        assert!(topology.is_closed_manifold(), "{topology:?}");
        // Closed and outward: each component encloses positive volume
        // (the whole: the sum).
        assert!(mesh.signed_volume() > 0.0);
    }

    #[test]
    fn a_surface_leaving_the_grid_is_closed_inside_it() {
        // A half-space z < 0.3 over the grid: open without closing, a box
        // with closing; every vertex within the grid.
        let grid = grid_over(21, 1.0, |p| 0.3 - p.z);
        let open = marching_cubes(&grid, 0.0, false);
        assert!(open.topology().boundary_edges > 0);
        let closed = marching_cubes(&grid, 0.0, true);
        let topology = closed.topology();
        assert!(topology.is_closed_manifold(), "{topology:?}");
        assert_eq!(topology.euler_characteristic(), 2);
        for p in &closed.positions {
            assert!(p.abs().max_element() <= 1.0, "{p}");
        }
    }

    #[test]
    fn small_components_are_dropped_by_face_count_or_share() {
        // A large sphere and a small one.
        let field =
            |p: Vec3| (0.6 - (p - Vec3::X * 0.3).length()).max(0.15 - (p + Vec3::X * 0.8).length());
        let mesh = marching_cubes(&grid_over(61, 1.2, field), 0.0, true);
        let (_, sizes) = mesh.components();
        assert_eq!(sizes.len(), 2);
        let (small, large) = (*sizes.iter().min().unwrap(), *sizes.iter().max().unwrap());
        assert!(small * 10 < large, "{sizes:?}");

        let mut by_count = mesh.clone();
        assert_eq!(
            by_count.remove_small_components(MinComponent::Faces(small + 1)),
            1
        );
        assert_eq!(by_count.faces.len(), large);
        assert_eq!(by_count.topology().euler_characteristic(), 2);
        assert!(by_count.topology().is_closed_manifold());
        // Every remaining vertex belongs to the large sphere.
        assert!(by_count.positions.iter().all(|p| p.x > -0.35));
        assert_eq!(by_count.colours.len(), by_count.positions.len());

        let mut by_share = mesh.clone();
        let share = (small as f64 + 1.0) / mesh.faces.len() as f64;
        assert_eq!(
            by_share.remove_small_components(MinComponent::Fraction(share)),
            1
        );
        assert_eq!(by_share, by_count);
        // A threshold at the small one's size keeps both.
        let mut kept = mesh.clone();
        assert_eq!(kept.remove_small_components(MinComponent::Faces(small)), 0);
        assert_eq!(kept, mesh);
    }

    #[test]
    fn component_sizes_parse_as_counts_or_shares() {
        assert_eq!("500".parse(), Ok(MinComponent::Faces(500)));
        assert_eq!("0.01".parse(), Ok(MinComponent::Fraction(0.01)));
        assert_eq!("5%".parse(), Ok(MinComponent::Fraction(0.05)));
        assert!(
            "1.5"
                .parse::<MinComponent>()
                .unwrap_err()
                .contains("must be 0 to 1")
        );
        assert!(
            "many"
                .parse::<MinComponent>()
                .unwrap_err()
                .contains("face count")
        );
        assert!("150%".parse::<MinComponent>().is_err());
    }
}
