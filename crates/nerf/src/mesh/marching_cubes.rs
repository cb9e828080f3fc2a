//! Marching cubes: the surface `value = threshold` of a scalar grid as a closed triangle mesh.
//!
//! Instead of the classic 256-case table, each cube's polygons are built from its faces:
//! on every face the iso-line crosses 0, 2 or 4 edges (marching squares), giving segments
//! oriented with the inside on their left as seen from outside the cube. Every crossed cube
//! edge is where one face's segment ends and the neighbouring face's begins, so segments
//! chain into closed loops: a triangle, or a fan around the loop's centre. A face with four
//! crossings is ambiguous; it is resolved by the average of its corners (inside centre: the inside
//! corners connect). Both cubes sharing a face decide alike, and vertices live on grid
//! edges shared by all their cubes, so the mesh is watertight wherever the surface does not
//! leave the grid.

use std::collections::HashMap;

use super::Mesh;

/// Values on a regular grid: `values[x + nx * (y + ny * z)]` sampled at
/// `origin + (x, y, z) * spacing`.
#[derive(Clone, Copy, Debug)]
pub struct Grid<'a> {
    pub values: &'a [f32],
    pub dims: [usize; 3],
    pub origin: [f32; 3],
    pub spacing: f32,
}

/// Cube corners by bit: x = bit 0, y = bit 1, z = bit 2.
const fn corner_offset(c: usize) -> [usize; 3] {
    [c & 1, (c >> 1) & 1, (c >> 2) & 1]
}

/// The six faces, corners counter-clockwise seen from outside the cube.
const FACES: [[usize; 4]; 6] = [
    [0, 4, 6, 2], // -x
    [1, 3, 7, 5], // +x
    [0, 1, 5, 4], // -y
    [2, 6, 7, 3], // +y
    [0, 2, 3, 1], // -z
    [4, 5, 7, 6], // +z
];

/// The twelve edges as corner pairs (lower corner first).
const EDGES: [[usize; 2]; 12] = [
    [0, 1],
    [2, 3],
    [4, 5],
    [6, 7],
    [0, 2],
    [1, 3],
    [4, 6],
    [5, 7],
    [0, 4],
    [1, 5],
    [2, 6],
    [3, 7],
];

fn edge_id(a: usize, b: usize) -> usize {
    let (lo, hi) = (a.min(b), a.max(b));
    EDGES
        .iter()
        .position(|e| *e == [lo, hi])
        .unwrap_or_else(|| unreachable!("corners {a} and {b} share no edge"))
}

/// Extracts the surface where `grid` crosses `threshold`; points above it are inside.
pub fn marching_cubes(grid: &Grid, threshold: f32) -> Mesh {
    let [nx, ny, nz] = grid.dims;
    assert_eq!(
        grid.values.len(),
        nx * ny * nz,
        "grid values do not match its size"
    );
    let mut mesh = Mesh::default();
    if nx < 2 || ny < 2 || nz < 2 {
        return mesh;
    }
    let index = |p: [usize; 3]| p[0] + nx * (p[1] + ny * p[2]);
    let mut vertex_of_edge: HashMap<(usize, usize), u32> = HashMap::new();
    let (mut rings, mut ring_ends) = (Vec::new(), Vec::new());
    let mut face_edges = [[0usize; 4]; 6];
    for (f, face) in FACES.iter().enumerate() {
        for k in 0..4 {
            face_edges[f][k] = edge_id(face[k], face[(k + 1) % 4]);
        }
    }
    for z in 0..nz - 1 {
        for y in 0..ny - 1 {
            for x in 0..nx - 1 {
                let pos = |c: usize| {
                    let o = corner_offset(c);
                    [x + o[0], y + o[1], z + o[2]]
                };
                let value: [f32; 8] = std::array::from_fn(|c| grid.values[index(pos(c))]);
                let inside: [bool; 8] = value.map(|v| v > threshold);
                if inside.iter().all(|&i| i) || inside.iter().all(|&i| !i) {
                    continue;
                }
                // next[e] = the crossed edge where the segment starting at edge e ends.
                let mut next = [usize::MAX; 12];
                for (f, face) in FACES.iter().enumerate() {
                    let mut starts = [usize::MAX; 4];
                    let mut ends = [usize::MAX; 4];
                    let mut crossings = 0;
                    for k in 0..4 {
                        let (a, b) = (face[k], face[(k + 1) % 4]);
                        match (inside[a], inside[b]) {
                            (true, false) => starts[k] = face_edges[f][k],
                            (false, true) => ends[k] = face_edges[f][k],
                            _ => continue,
                        }
                        crossings += 1;
                    }
                    if crossings == 2 {
                        let s = starts.iter().find(|&&e| e != usize::MAX);
                        let e = ends.iter().find(|&&e| e != usize::MAX);
                        if let (Some(&s), Some(&e)) = (s, e) {
                            next[s] = e;
                        }
                    } else if crossings == 4 {
                        let centre = face.iter().map(|&c| value[c]).sum::<f32>() / 4.0;
                        let step = if centre > threshold { 1 } else { 3 };
                        for k in 0..4 {
                            if starts[k] != usize::MAX {
                                next[starts[k]] = ends[(k + step) % 4];
                            }
                        }
                    }
                }
                let mut vertex = |e: usize| -> u32 {
                    let [a, b] = EDGES[e];
                    let (pa, pb) = (pos(a), pos(b));
                    let key = (index(pa), axis_of(e));
                    *vertex_of_edge.entry(key).or_insert_with(|| {
                        let (va, vb) = (value[a], value[b]);
                        let t = ((threshold - va) / (vb - va)).clamp(0.0, 1.0);
                        let p = std::array::from_fn(|i| {
                            let ca = pa[i] as f32;
                            let cb = pb[i] as f32;
                            grid.origin[i] + grid.spacing * (ca + t * (cb - ca))
                        });
                        mesh.vertices.push(p);
                        (mesh.vertices.len() - 1) as u32
                    })
                };
                let mut done = [false; 12];
                rings.clear();
                ring_ends.clear();
                for start in 0..12 {
                    if next[start] == usize::MAX || done[start] {
                        continue;
                    }
                    let mut e = start;
                    while !done[e] && next[e] != usize::MAX {
                        done[e] = true;
                        rings.push(vertex(e));
                        e = next[e];
                    }
                    ring_ends.push(rings.len());
                }
                let mut first = 0;
                for &end in &ring_ends {
                    close_ring(&mut mesh, &rings[first..end]);
                    first = end;
                }
            }
        }
    }
    mesh
}

/// Triangulates one closed loop of vertices: a triangle, or for longer loops a fan around
/// a new centre vertex. (A fan from one loop vertex could lay a diagonal along a cube face
/// that the neighbouring cube also uses; a centre private to the cube keeps every edge
/// shared by exactly two triangles.)
fn close_ring(mesh: &mut Mesh, ring: &[u32]) {
    if ring.len() == 3 {
        mesh.triangles.push([ring[0], ring[2], ring[1]]);
        return;
    }
    let mut centre = [0f32; 3];
    for &v in ring {
        let p = mesh.vertices[v as usize];
        for i in 0..3 {
            centre[i] += p[i] / ring.len() as f32;
        }
    }
    mesh.vertices.push(centre);
    let c = (mesh.vertices.len() - 1) as u32;
    for k in 0..ring.len() {
        mesh.triangles
            .push([c, ring[(k + 1) % ring.len()], ring[k]]);
    }
}

/// The axis an edge runs along (0: x, 1: y, 2: z).
fn axis_of(e: usize) -> usize {
    e / 4
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample(
        n: usize,
        lo: f32,
        hi: f32,
        f: impl Fn([f32; 3]) -> f32,
    ) -> (Vec<f32>, Grid<'static>) {
        let spacing = (hi - lo) / (n - 1) as f32;
        let mut values = Vec::with_capacity(n * n * n);
        for z in 0..n {
            for y in 0..n {
                for x in 0..n {
                    let p = [x, y, z].map(|i| lo + i as f32 * spacing);
                    values.push(f(p));
                }
            }
        }
        let grid = Grid {
            values: &[],
            dims: [n; 3],
            origin: [lo; 3],
            spacing,
        };
        (values, grid)
    }

    #[test]
    fn faces_wind_counter_clockwise_around_their_outward_normal() {
        let normals = [
            [-1, 0, 0],
            [1, 0, 0],
            [0, -1, 0],
            [0, 1, 0],
            [0, 0, -1],
            [0, 0, 1],
        ];
        for (face, n) in FACES.iter().zip(normals) {
            let p = face.map(|c| corner_offset(c).map(|v| v as i32));
            let (u, v) = (
                [p[1][0] - p[0][0], p[1][1] - p[0][1], p[1][2] - p[0][2]],
                [p[2][0] - p[1][0], p[2][1] - p[1][1], p[2][2] - p[1][2]],
            );
            let c = [
                u[1] * v[2] - u[2] * v[1],
                u[2] * v[0] - u[0] * v[2],
                u[0] * v[1] - u[1] * v[0],
            ];
            assert_eq!(c, n, "face {face:?}");
        }
    }

    #[test]
    fn sphere_has_the_right_area_and_volume_and_is_closed() {
        let r = 0.7f32;
        let (values, grid) = sample(64, -1.0, 1.0, |p| {
            r - (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt()
        });
        let grid = Grid {
            values: &values,
            ..grid
        };
        let mesh = marching_cubes(&grid, 0.0);
        let pi = std::f64::consts::PI;
        let (area, volume) = (
            4.0 * pi * (r * r) as f64,
            4.0 / 3.0 * pi * (r as f64).powi(3),
        );
        assert!(
            (mesh.area() / area - 1.0).abs() < 0.02,
            "area {} vs {area}",
            mesh.area()
        );
        assert!(
            (mesh.volume() / volume - 1.0).abs() < 0.02,
            "volume {} vs {volume}",
            mesh.volume()
        );
        assert!(mesh.is_watertight());
        for v in &mesh.vertices {
            let d = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
            assert!((d - r).abs() < 0.01, "vertex at radius {d}");
        }
    }

    /// Random values make every ambiguous case appear; the mesh must still be closed and
    /// consistently oriented (the boundary is outside, so nothing leaves the grid).
    #[test]
    fn noise_gives_a_closed_oriented_mesh() {
        let n = 20;
        for seed in [12, 13, 14] {
            let mut rng = crate::rng::Rng::new(seed);
            let (mut values, grid) = sample(n, 0.0, 1.0, |_| 0.0);
            for z in 0..n {
                for y in 0..n {
                    for x in 0..n {
                        let border = [x, y, z].iter().any(|&i| i == 0 || i == n - 1);
                        values[x + n * (y + n * z)] =
                            if border { -1.0 } else { rng.range(-1.0, 1.0) };
                    }
                }
            }
            let grid = Grid {
                values: &values,
                ..grid
            };
            let mesh = marching_cubes(&grid, 0.0);
            assert!(mesh.triangles.len() > 1000);
            assert!(
                mesh.is_watertight(),
                "seed {seed}: open or inconsistently oriented mesh"
            );
            assert!(mesh.volume() > 0.0);
        }
    }
}
