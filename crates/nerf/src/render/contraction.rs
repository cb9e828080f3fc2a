//! Scene contraction for unbounded captures (after mip-NeRF 360, with the L-infinity norm
//! as in nerfstudio's nerfacto): the cube of half-extent `r` is kept as it is, and all of
//! space outside it is squeezed into the shell between `r` and `2 r`,
//! `p -> (2 - 1 / n) p / n` with `n = |p|_inf / r`. The hash grid and occupancy grid then
//! cover `[-2r, 2r]^3` and hold the far background too, at a resolution that falls with
//! distance, which is what a camera sees of it.
//!
//! Marching stays in the world, with steps that grow as `n^2` outside the inner cube, so
//! each step advances about the same distance in contracted space.

use crate::math::V3;

/// `|p|_inf / r`: 1 on the inner cube's surface.
#[inline]
fn norm(p: V3, r: f32) -> f32 {
    p[0].abs().max(p[1].abs()).max(p[2].abs()) / r
}

/// The contracted point of world point `p`.
#[inline]
pub fn contract(p: V3, r: f32) -> V3 {
    let n = norm(p, r);
    if n <= 1.0 {
        p
    } else {
        let s = (2.0 - 1.0 / n) / n;
        [p[0] * s, p[1] * s, p[2] * s]
    }
}

/// World step length at `p` that moves about `dt` in contracted space (exact along rays
/// through the centre: `d|q| = d|p| / n^2`).
#[inline]
pub fn world_step(p: V3, r: f32, dt: f32) -> f32 {
    let n = norm(p, r);
    dt * (n * n).max(1.0)
}

/// How much contraction shrinks a small region around world point `p`: the geometric
/// mean of its scale along the contracted axis (`d(2 - 1/n)/dn = 1/n^2`) and across it
/// (`s = (2 - 1/n)/n`, twice), `(s^2 / n^2)^(1/3)` (the cube root of the Jacobian's
/// determinant, as Zip-NeRF scales its Gaussians); 1 inside the inner cube.
#[inline]
pub fn footprint_scale(p: V3, r: f32) -> f32 {
    let n = norm(p, r);
    if n <= 1.0 {
        1.0
    } else {
        let s = (2.0 - 1.0 / n) / n;
        (s * s / (n * n)).cbrt()
    }
}

/// Beyond this `n` a point lies within `r / FAR_N` of the contracted box's surface: rays
/// stop there.
pub const FAR_N: f32 = 64.0;

/// Whether a world point is so far out that marching further adds nothing.
#[inline]
pub fn beyond(p: V3, r: f32) -> bool {
    norm(p, r) > FAR_N
}

/// Backward of [`contract`]: `dL/dp` from `dL/dq` at world point `p` (camera refinement
/// differentiates sample positions). Outside the inner cube `q = s(n) p` with
/// `s = 2/n - 1/n^2`, and `n` follows the largest coordinate alone.
#[inline]
pub fn contract_bwd(p: V3, r: f32, d_q: V3) -> V3 {
    let n = norm(p, r);
    if n <= 1.0 {
        return d_q;
    }
    let s = (2.0 - 1.0 / n) / n;
    let ds_dn = -2.0 / (n * n) + 2.0 / (n * n * n);
    let a = (0..3)
        .max_by(|&i, &j| p[i].abs().total_cmp(&p[j].abs()))
        .unwrap_or(0);
    let along = d_q[0] * p[0] + d_q[1] * p[1] + d_q[2] * p[2];
    let mut d_p = [s * d_q[0], s * d_q[1], s * d_q[2]];
    d_p[a] += along * ds_dn * p[a].signum() / r;
    d_p
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The backward against central differences, inside, just outside and far out.
    #[test]
    fn contract_bwd_matches_finite_differences() {
        let r = 1.5;
        let d_q = [0.7, -0.4, 0.9];
        for p in [
            [0.3f32, -1.2, 1.0],
            [0.3, -1.2, 1.7],
            [-4.0, 2.5, 1.0],
            [10.0, -30.0, 5.0],
        ] {
            let g = contract_bwd(p, r, d_q);
            for a in 0..3 {
                let h = 1e-3 * p[a].abs().max(1.0);
                let (mut lo, mut hi) = (p, p);
                lo[a] -= h;
                hi[a] += h;
                let f = |x: V3| {
                    let q = contract(x, r);
                    (0..3).map(|i| (q[i] * d_q[i]) as f64).sum::<f64>()
                };
                let fd = (f(hi) - f(lo)) / (2.0 * h as f64);
                assert!(
                    (fd - g[a] as f64).abs() < 2e-3 * (1.0 + fd.abs()),
                    "{p:?} axis {a}: {fd} vs {}",
                    g[a]
                );
            }
        }
    }

    #[test]
    fn contraction_is_continuous_bounded_and_monotone() {
        let r = 1.5;
        // Identity inside, continuous across the inner cube's surface.
        assert_eq!(contract([0.3, -1.2, 1.5], r), [0.3, -1.2, 1.5]);
        let just_out = contract([0.3, -1.2, 1.5001], r);
        assert!((just_out[2] - 1.5).abs() < 1e-3, "{just_out:?}");
        // Far points approach, never reach, the 2r cube; order along a ray is kept.
        let mut last = 0.0;
        for k in 1..60 {
            let s = 1.3f32.powi(k);
            let q = contract([0.2 * s, 0.5 * s, -0.1 * s], r);
            let m = q.iter().fold(0.0f32, |m, v| m.max(v.abs()));
            assert!(m < 2.0 * r && m >= last, "{q:?} after {last}");
            last = m;
        }
        assert!(last > 2.0 * r - 1e-3);
    }

    #[test]
    fn world_step_moves_a_fixed_contracted_distance() {
        let r = 1.0;
        for x in [2.0f32, 5.0, 20.0] {
            let p = [x, 0.3, -0.2];
            let dt = 1e-3;
            let step = world_step(p, r, dt);
            let q0 = contract(p, r);
            let q1 = contract([x + step, 0.3, -0.2], r);
            // First order: a step of 0.4 at x = 20 lands within 2%.
            assert!(
                ((q1[0] - q0[0]) / dt - 1.0).abs() < 0.03,
                "x {x}: {}",
                (q1[0] - q0[0]) / dt
            );
        }
        assert_eq!(world_step([0.5, 0.0, 0.0], r, 0.01), 0.01);
    }
}
