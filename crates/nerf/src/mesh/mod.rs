//! Triangle meshes from a trained field: density sampled on a grid ([`extract`]), the
//! surface by [`marching_cubes`], point clouds from rendered depth ([`points`]), and files
//! for other tools ([`export`]).

pub mod export;
pub mod extract;
pub mod marching_cubes;
pub mod points;

use std::collections::HashMap;

/// An indexed triangle mesh; triangles wind counter-clockwise seen from outside (normals
/// point from dense to empty space).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Mesh {
    pub vertices: Vec<[f32; 3]>,
    pub triangles: Vec<[u32; 3]>,
}

fn sub(a: [f32; 3], b: [f32; 3]) -> [f64; 3] {
    [
        (a[0] - b[0]) as f64,
        (a[1] - b[1]) as f64,
        (a[2] - b[2]) as f64,
    ]
}

fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

impl Mesh {
    fn corners(&self, t: &[u32; 3]) -> [[f32; 3]; 3] {
        t.map(|i| self.vertices[i as usize])
    }

    /// Total surface area.
    pub fn area(&self) -> f64 {
        self.triangles
            .iter()
            .map(|t| {
                let [a, b, c] = self.corners(t);
                let n = cross(sub(b, a), sub(c, a));
                0.5 * (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt()
            })
            .sum()
    }

    /// Enclosed volume (divergence theorem); positive when the winding faces outward.
    pub fn volume(&self) -> f64 {
        self.triangles
            .iter()
            .map(|t| {
                let [a, b, c] = self.corners(t);
                let a = [a[0] as f64, a[1] as f64, a[2] as f64];
                let bc = cross(sub(b, [0.0; 3]), sub(c, [0.0; 3]));
                (a[0] * bc[0] + a[1] * bc[1] + a[2] * bc[2]) / 6.0
            })
            .sum()
    }

    /// Closed and consistently oriented: every directed edge appears once and its reverse
    /// once, so every edge is shared by exactly two triangles that agree on orientation.
    pub fn is_watertight(&self) -> bool {
        let mut directed: HashMap<(u32, u32), u32> = HashMap::new();
        for t in &self.triangles {
            for k in 0..3 {
                *directed.entry((t[k], t[(k + 1) % 3])).or_default() += 1;
            }
        }
        directed
            .iter()
            .all(|(&(a, b), &n)| n == 1 && directed.get(&(b, a)) == Some(&1))
    }
}
