//! Signed distance functions of the primitives the built-in scenes are made of.

use crate::math::{length, sub, V3};

/// One analytic primitive. Cylinders and tori are aligned with a world axis (0 = X, 1 = Y,
/// 2 = Z).
#[derive(Clone, Copy, Debug)]
pub enum Shape {
    /// Axis-aligned box with rounded edges of radius `round`.
    Box {
        center: V3,
        half: V3,
        round: f32,
    },
    /// Capped cylinder along `axis`.
    Cylinder {
        center: V3,
        radius: f32,
        half_height: f32,
        axis: usize,
    },
    Sphere {
        center: V3,
        radius: f32,
    },
    /// Ring around `axis`: distance `major` from the centre, tube radius `minor`.
    Torus {
        center: V3,
        major: f32,
        minor: f32,
        axis: usize,
    },
}

/// The coordinate along `axis` and the two across it.
fn split_axis(p: V3, axis: usize) -> (f32, f32, f32) {
    (p[axis], p[(axis + 1) % 3], p[(axis + 2) % 3])
}

impl Shape {
    /// Signed distance from `p` (negative inside). Exact for boxes, spheres and tori, and
    /// for cylinders; rounding shrinks the box so its outer size stays `half`.
    pub fn distance(&self, p: V3) -> f32 {
        match *self {
            Shape::Box {
                center,
                half,
                round,
            } => {
                let q = sub(p, center);
                let d = [
                    q[0].abs() - half[0] + round,
                    q[1].abs() - half[1] + round,
                    q[2].abs() - half[2] + round,
                ];
                let outside = length([d[0].max(0.0), d[1].max(0.0), d[2].max(0.0)]);
                outside + d[0].max(d[1]).max(d[2]).min(0.0) - round
            }
            Shape::Cylinder {
                center,
                radius,
                half_height,
                axis,
            } => {
                let (a, u, v) = split_axis(sub(p, center), axis);
                let d = [(u * u + v * v).sqrt() - radius, a.abs() - half_height];
                d[0].max(d[1]).min(0.0) + (d[0].max(0.0).powi(2) + d[1].max(0.0).powi(2)).sqrt()
            }
            Shape::Sphere { center, radius } => length(sub(p, center)) - radius,
            Shape::Torus {
                center,
                major,
                minor,
                axis,
            } => {
                let (a, u, v) = split_axis(sub(p, center), axis);
                let ring = (u * u + v * v).sqrt() - major;
                (ring * ring + a * a).sqrt() - minor
            }
        }
    }

    /// Axis-aligned bounds `(min, max)`.
    pub fn bounds(&self) -> (V3, V3) {
        let ext = |c: V3, e: V3| {
            (
                [c[0] - e[0], c[1] - e[1], c[2] - e[2]],
                [c[0] + e[0], c[1] + e[1], c[2] + e[2]],
            )
        };
        let around = |axis: usize, along: f32, across: f32| {
            let mut e = [across; 3];
            e[axis] = along;
            e
        };
        match *self {
            Shape::Box { center, half, .. } => ext(center, half),
            Shape::Cylinder {
                center,
                radius,
                half_height,
                axis,
            } => ext(center, around(axis, half_height, radius)),
            Shape::Sphere { center, radius } => ext(center, [radius; 3]),
            Shape::Torus {
                center,
                major,
                minor,
                axis,
            } => ext(center, around(axis, minor, major + minor)),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn distances_of_known_points() {
        let b = Shape::Box {
            center: [0.0; 3],
            half: [1.0, 2.0, 3.0],
            round: 0.0,
        };
        assert!((b.distance([2.0, 0.0, 0.0]) - 1.0).abs() < 1e-6);
        assert!((b.distance([0.0, 0.0, 0.0]) + 1.0).abs() < 1e-6);
        let c = Shape::Cylinder {
            center: [0.0; 3],
            radius: 0.5,
            half_height: 1.0,
            axis: 2,
        };
        assert!((c.distance([1.0, 0.0, 0.0]) - 0.5).abs() < 1e-6);
        assert!((c.distance([0.0, 0.0, 1.5]) - 0.5).abs() < 1e-6);
        let t = Shape::Torus {
            center: [0.0; 3],
            major: 1.0,
            minor: 0.25,
            axis: 1,
        };
        // Ring in the XZ plane: (1, 0, 0) is on its centre line.
        assert!((t.distance([1.0, 0.0, 0.0]) + 0.25).abs() < 1e-6);
        assert!((t.distance([0.0, 0.0, 0.0]) - 0.75).abs() < 1e-6);
        let s = Shape::Sphere {
            center: [1.0, 0.0, 0.0],
            radius: 0.5,
        };
        assert!((s.distance([1.0, 1.0, 0.0]) - 0.5).abs() < 1e-6);
        let (lo, hi) = t.bounds();
        assert_eq!((lo[1], hi[1], hi[0]), (-0.25, 0.25, 1.25));
    }
}
