//! The space rays are marched in: the world, or normalised device coordinates (NDC) for
//! forward-facing captures.
//!
//! NDC (NeRF paper, appendix C) maps the frustum of a reference camera looking down -Z,
//! from its near plane `z = -n` to infinity, onto the cube `[-1, 1]^3`:
//! `(x, y, z) -> (-ax x / z, -ay y / z, 1 + 2 n / z)` with `ax = 2 fx / W`, `ay = 2 fy / H`.
//! A world ray is first moved to start on the near plane; its image is the ray
//! `o' + t d'` with `t` in `[0, 1]` from the near plane to infinity, and
//! `o' = (-ax ox/oz, -ay oy/oz, 1 + 2n/oz)`,
//! `d' = (-ax (dx/dz - ox/oz), -ay (dy/dz - oy/oz), -2n/oz)`.
//! Sampling `t` uniformly is sampling disparity uniformly, which is what lets unbounded
//! forward-facing scenes fit a bounded grid.

use serde::{Deserialize, Serialize};

/// The reference frustum of NDC space.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Ndc {
    /// `2 fx / W` and `2 fy / H` of the reference camera.
    pub ax: f32,
    pub ay: f32,
    /// Distance of the near plane (1 in the paper, after scaling the scene so the nearest
    /// bound sits at 1 / 0.75).
    pub near: f32,
}

#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "lowercase")]
pub enum RaySpace {
    #[default]
    World,
    Ndc(Ndc),
}

impl RaySpace {
    /// The ray `(origin, dir)` in this space. World rays pass through unchanged; NDC rays
    /// that do not head into the frustum (`dz >= 0`) come back as a ray that misses the
    /// unit cube.
    #[inline]
    pub fn warp(&self, origin: [f32; 3], dir: [f32; 3]) -> ([f32; 3], [f32; 3]) {
        let RaySpace::Ndc(ndc) = self else {
            return (origin, dir);
        };
        if dir[2] >= -1e-6 {
            return ([0.0, 0.0, 10.0], [0.0, 0.0, 1.0]);
        }
        let n = ndc.near;
        let t = -(n + origin[2]) / dir[2];
        let o = [
            origin[0] + t * dir[0],
            origin[1] + t * dir[1],
            origin[2] + t * dir[2],
        ];
        let o_new = [
            -ndc.ax * o[0] / o[2],
            -ndc.ay * o[1] / o[2],
            1.0 + 2.0 * n / o[2],
        ];
        let d_new = [
            -ndc.ax * (dir[0] / dir[2] - o[0] / o[2]),
            -ndc.ay * (dir[1] / dir[2] - o[1] / o[2]),
            -2.0 * n / o[2],
        ];
        (o_new, d_new)
    }

    /// A point of this space in world coordinates (NDC depth 1 is infinitely far; it is
    /// clamped just short of it).
    pub fn to_world(&self, p: [f32; 3]) -> [f32; 3] {
        let RaySpace::Ndc(ndc) = self else {
            return p;
        };
        let z = 2.0 * ndc.near / (p[2].min(1.0 - 1e-4) - 1.0);
        [-p[0] * z / ndc.ax, -p[1] * z / ndc.ay, z]
    }

    /// Marching bounds `(near, far)` in units of the warped direction, given the scene's
    /// world bounds: NDC rays always run from the near plane (0) to infinity (1).
    pub fn bounds(&self, near: f32, far: f32) -> (f32, f32) {
        match self {
            RaySpace::World => (near, far),
            RaySpace::Ndc(_) => (0.0, 1.0),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ndc_ray_passes_through_the_warped_points_of_the_world_ray() {
        let space = RaySpace::Ndc(Ndc {
            ax: 1.3,
            ay: 1.7,
            near: 1.0,
        });
        let (o, d) = ([0.2, -0.1, 0.3], [0.15, 0.05, -1.0]);
        let (o2, d2) = space.warp(o, d);
        // The NDC origin is the world ray's point on the near plane.
        let t_near = -(1.0 + o[2]) / d[2];
        let on_near = [o[0] + t_near * d[0], o[1] + t_near * d[1], -1.0];
        let back = space.to_world(o2);
        for a in 0..3 {
            assert!(
                (back[a] - on_near[a]).abs() < 1e-5,
                "{back:?} vs {on_near:?}"
            );
        }
        assert!((o2[2] + 1.0).abs() < 1e-6, "near plane is z' = -1: {o2:?}");
        // Every world point along the ray maps onto the NDC ray's line, monotonically in t.
        let mut last_t = 0.0;
        for s in [1.5f32, 3.0, 10.0, 100.0] {
            let p = [o[0] + s * d[0], o[1] + s * d[1], o[2] + s * d[2]];
            let z = 2.0 / p[2];
            let q = [-1.3 * p[0] / p[2], -1.7 * p[1] / p[2], 1.0 + z];
            let t = (q[2] - o2[2]) / d2[2];
            assert!(t > last_t && t < 1.0, "t {t} after {last_t}");
            last_t = t;
            for a in 0..2 {
                assert!((o2[a] + t * d2[a] - q[a]).abs() < 1e-4, "axis {a} at s {s}");
            }
            let w = space.to_world(q);
            for a in 0..3 {
                assert!((w[a] - p[a]).abs() < 1e-3 * p[2].abs(), "{w:?} vs {p:?}");
            }
        }
        // A ray heading away from the frustum misses the unit cube.
        let (o3, _) = space.warp(o, [0.0, 0.0, 1.0]);
        assert!(o3[2] > 1.0);
    }

    #[test]
    fn world_space_is_the_identity() {
        let s = RaySpace::World;
        assert_eq!(s.warp([1.0, 2.0, 3.0], [0.0, 0.0, -1.0]).0, [1.0, 2.0, 3.0]);
        assert_eq!(s.to_world([1.0, 2.0, 3.0]), [1.0, 2.0, 3.0]);
        assert_eq!(s.bounds(2.0, 6.0), (2.0, 6.0));
    }
}
