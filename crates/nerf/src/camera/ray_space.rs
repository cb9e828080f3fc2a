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

    /// Backward of [`warp`](Self::warp) for camera refinement: given `dL/d origin'` and
    /// `dL/d unit(dir')` of the warped ray, `(dL/d origin, dL/d dir)` of the world ray.
    /// World rays pass both through. NDC: by central differences of the warp in f64 (errors
    /// near 1e-9, far below f32's resolution; no closed form of the six-by-six Jacobian to
    /// get wrong), twelve warps per ray, a few per step's ray.
    pub fn warp_backward(
        &self,
        origin: [f32; 3],
        dir: [f32; 3],
        d_origin: [f32; 3],
        d_unit_dir: [f32; 3],
    ) -> ([f32; 3], [f32; 3]) {
        let RaySpace::Ndc(ndc) = self else {
            return (d_origin, d_unit_dir);
        };
        let x: [f64; 6] =
            std::array::from_fn(|i| f64::from(if i < 3 { origin[i] } else { dir[i - 3] }));
        let g = |x: &[f64; 6]| -> f64 {
            let (o, d) = warp_f64(ndc, [x[0], x[1], x[2]], [x[3], x[4], x[5]]);
            let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt().max(1e-300);
            (0..3)
                .map(|a| f64::from(d_origin[a]) * o[a] + f64::from(d_unit_dir[a]) * d[a] / n)
                .sum()
        };
        let grad: [f32; 6] = std::array::from_fn(|i| {
            let h = 1e-6 * x[i].abs().max(1.0);
            let (mut lo, mut hi) = (x, x);
            lo[i] -= h;
            hi[i] += h;
            ((g(&hi) - g(&lo)) / (2.0 * h)) as f32
        });
        ([grad[0], grad[1], grad[2]], [grad[3], grad[4], grad[5]])
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

/// [`RaySpace::warp`] into NDC in f64 (for its derivative).
fn warp_f64(ndc: &Ndc, origin: [f64; 3], dir: [f64; 3]) -> ([f64; 3], [f64; 3]) {
    if dir[2] >= -1e-6 {
        return ([0.0, 0.0, 10.0], [0.0, 0.0, 1.0]);
    }
    let (ax, ay, n) = (f64::from(ndc.ax), f64::from(ndc.ay), f64::from(ndc.near));
    let t = -(n + origin[2]) / dir[2];
    let o: [f64; 3] = std::array::from_fn(|a| origin[a] + t * dir[a]);
    (
        [-ax * o[0] / o[2], -ay * o[1] / o[2], 1.0 + 2.0 * n / o[2]],
        [
            -ax * (dir[0] / dir[2] - o[0] / o[2]),
            -ay * (dir[1] / dir[2] - o[1] / o[2]),
            -2.0 * n / o[2],
        ],
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The f64 warp behind the backward is the f32 warp, and the backward matches central
    /// differences of the f32 warp (coarse steps: f32).
    #[test]
    fn warp_backward_matches_finite_differences() {
        let space = RaySpace::Ndc(Ndc {
            ax: 1.3,
            ay: 1.7,
            near: 1.0,
        });
        let (o, d) = ([0.2f32, -0.1, 0.3], [0.15f32, 0.05, -1.0]);
        let (o32, d32) = space.warp(o, d);
        let RaySpace::Ndc(ndc) = &space else {
            unreachable!()
        };
        let (o64, d64) = warp_f64(ndc, o.map(f64::from), d.map(f64::from));
        for a in 0..3 {
            assert!((o64[a] as f32 - o32[a]).abs() < 1e-5 && (d64[a] as f32 - d32[a]).abs() < 1e-5);
        }
        let (g_o, g_d) = ([0.3f32, -0.5, 0.8], [-0.4f32, 0.9, 0.2]);
        let loss = |o: [f32; 3], d: [f32; 3]| -> f64 {
            let (o2, d2) = space.warp(o, d);
            let n = crate::math::length(d2);
            (0..3)
                .map(|a| f64::from(g_o[a] * o2[a] + g_d[a] * d2[a] / n))
                .sum()
        };
        let (b_o, b_d) = space.warp_backward(o, d, g_o, g_d);
        for i in 0..6 {
            let h = 1e-2;
            let (mut lo, mut hi) = ((o, d), (o, d));
            if i < 3 {
                lo.0[i] -= h;
                hi.0[i] += h;
            } else {
                lo.1[i - 3] -= h;
                hi.1[i - 3] += h;
            }
            let fd = (loss(hi.0, hi.1) - loss(lo.0, lo.1)) / (2.0 * h as f64);
            let got = if i < 3 { b_o[i] } else { b_d[i - 3] };
            assert!(
                (fd - got as f64).abs() < 1e-2 * (1.0 + fd.abs()),
                "input {i}: {fd} vs {got}"
            );
        }
        // The warp does not depend on the direction's length: no gradient along it.
        let along: f32 = (0..3).map(|a| b_d[a] * d[a]).sum();
        assert!(along.abs() < 1e-4, "{along}");
        // World rays pass the gradient through.
        assert_eq!(RaySpace::World.warp_backward(o, d, g_o, g_d), (g_o, g_d));
    }

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
