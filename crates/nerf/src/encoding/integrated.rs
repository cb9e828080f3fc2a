//! mip-NeRF's integrated positional encoding (Barron et al., ICCV 2021, section 3.1): a
//! pixel's ray is a cone, each sample stands for the conical frustum between two depths,
//! and the frustum is encoded by the expected positional encoding over a Gaussian with its
//! mean and covariance. Frequencies whose period is smaller than the frustum fade out:
//! `E[sin(s x)] = sin(s mu) exp(-s^2 var / 2)` for `x ~ N(mu, var)`, per coordinate, with
//! the covariance's diagonal (what mip-NeRF encodes). With zero variance it is exactly the
//! positional encoding, identity term (the mean) included.

use super::FrequencyEncoding;

/// The Gaussian of the conical frustum between depths `t0 < t1` along a ray whose cone
/// has radius `radius` per unit of `t` (mip-NeRF's equation 7, in its stable form): the
/// mean depth, the variance along the ray (in `t^2`) and across it (per perpendicular
/// axis, in world units^2 when the direction has unit length... or `|d|`-free: `radius` is
/// per unit of `t`, and so is the result). `cylinder`: the radius is the same at every depth
/// (NDC rays), a disc's variance `radius^2 / 4` across.
pub fn frustum_gaussian(t0: f32, t1: f32, radius: f32, cylinder: bool) -> (f32, f32, f32) {
    let (mu, hw) = (0.5 * (t0 + t1), 0.5 * (t1 - t0));
    let (mu2, hw2) = (mu * mu, hw * hw);
    let denom = 3.0 * mu2 + hw2;
    if cylinder || denom <= 0.0 {
        // A cylinder's slice is uniform along the ray.
        return (mu, hw2 / 3.0, 0.25 * radius * radius);
    }
    let mean = mu + 2.0 * mu * hw2 / denom;
    let var_t = hw2 / 3.0 - (4.0 / 15.0) * (hw2 * hw2 * (12.0 * mu2 - hw2)) / (denom * denom);
    let var_r =
        radius * radius * (mu2 / 4.0 + (5.0 / 12.0) * hw2 - (4.0 / 15.0) * hw2 * hw2 / denom);
    (mean, var_t, var_r)
}

/// The diagonal of the frustum's covariance in space for direction `d` (unnormalised;
/// `t` runs along it): `var_t d d^T + var_r (I - d d^T / |d|^2)`.
pub fn diagonal_covariance(d: [f32; 3], var_t: f32, var_r: f32) -> [f32; 3] {
    let norm2 = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).max(1e-12);
    std::array::from_fn(|c| var_t * d[c] * d[c] + var_r * (1.0 - d[c] * d[c] / norm2))
}

impl FrequencyEncoding {
    /// The integrated encoding of a Gaussian with mean `mean` and diagonal covariance `var`
    /// (each a 3-vector) into `out` (`dims()` values, the layout of [`encode`](Self::encode)).
    #[inline]
    pub fn encode_integrated(&self, mean: &[f32], var: &[f32], out: &mut [f32]) {
        let mut o = 0;
        if !self.paper_form {
            out[..3].copy_from_slice(&mean[..3]);
            o = 3;
        }
        for k in 0..self.frequencies {
            let s = self.frequency(k);
            for c in 0..3 {
                let fade = (-0.5 * s * s * var[c]).exp();
                let (sin, cos) = (s * mean[c]).sin_cos();
                out[o + c] = sin * fade;
                out[o + 3 + c] = cos * fade;
            }
            o += 6;
        }
    }

    /// Backward of [`encode_integrated`](Self::encode_integrated) for one Gaussian: writes
    /// `dL/d mean` into `d_mean` and `dL/d var` into `d_var` (3 values each).
    pub fn encode_integrated_bwd(
        &self,
        mean: &[f32],
        var: &[f32],
        d_out: &[f32],
        d_mean: &mut [f32],
        d_var: &mut [f32],
    ) {
        let mut o = 0;
        let (mut gm, mut gv) = ([0.0f32; 3], [0.0f32; 3]);
        if !self.paper_form {
            gm.copy_from_slice(&d_out[..3]);
            o = 3;
        }
        for k in 0..self.frequencies {
            let s = self.frequency(k);
            for c in 0..3 {
                let fade = (-0.5 * s * s * var[c]).exp();
                let (sin, cos) = (s * mean[c]).sin_cos();
                let (ds, dc) = (d_out[o + c], d_out[o + 3 + c]);
                gm[c] += s * fade * (cos * ds - sin * dc);
                gv[c] += -0.5 * s * s * fade * (sin * ds + cos * dc);
            }
            o += 6;
        }
        d_mean[..3].copy_from_slice(&gm);
        d_var[..3].copy_from_slice(&gv);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    fn encoding(paper_form: bool) -> FrequencyEncoding {
        FrequencyEncoding {
            frequencies: 6,
            paper_form,
        }
    }

    /// Points drawn uniformly from the conical frustum `t0..t1` of the cone from `o` along
    /// `d` with radius `r` per unit `t` (density in `t` grows as `t^2`, discs uniform).
    fn frustum_points(
        o: [f32; 3],
        d: [f32; 3],
        t0: f32,
        t1: f32,
        r: f32,
        n: usize,
    ) -> Vec<[f64; 3]> {
        let len = crate::math::length(d);
        let axis = crate::math::scale(d, 1.0 / len);
        let helper = if axis[0].abs() < 0.9 {
            [1.0, 0.0, 0.0]
        } else {
            [0.0, 1.0, 0.0]
        };
        let e1 = crate::math::normalize_or_zero(crate::math::cross(axis, helper));
        let e2 = crate::math::cross(axis, e1);
        let mut rng = Rng::new(7);
        let (a, b) = ((t0 as f64).powi(3), (t1 as f64).powi(3));
        (0..n)
            .map(|_| {
                let t = (a + rng.uniform() as f64 * (b - a)).cbrt();
                let rho = r as f64 * t * (rng.uniform() as f64).sqrt();
                let phi = std::f64::consts::TAU * rng.uniform() as f64;
                let (c, s) = (rho * phi.cos(), rho * phi.sin());
                std::array::from_fn(|k| {
                    o[k] as f64 + t * d[k] as f64 + c * e1[k] as f64 + s * e2[k] as f64
                })
            })
            .collect()
    }

    /// Against Monte Carlo averages over 200k points: the frustum's Gaussian
    /// has the frustum's mean and per-axis variance (to 1% of the variance); the
    /// integrated encoding is the positional encoding's expectation under that Gaussian
    /// (to 0.01); and against the average over the frustum's own points, the Gaussian's
    /// stand-in error that mip-NeRF accepts: 0.03 on average, at most 0.25 (a uniform
    /// segment's `sinc` side lobes, up to 0.22, are what a Gaussian smooths away).
    #[test]
    fn matches_a_monte_carlo_average_over_the_frustum() {
        let (o, d) = ([0.3f32, -0.2, 0.1], [0.4f32, 1.1, -0.5]);
        for &(t0, t1, r) in &[
            (2.0f32, 2.3f32, 0.02f32),
            (1.0, 1.6, 0.08),
            (3.0, 3.05, 0.004),
        ] {
            let pts = frustum_points(o, d, t0, t1, r, 200_000);
            let n = pts.len() as f64;
            let mean: [f64; 3] = std::array::from_fn(|c| pts.iter().map(|p| p[c]).sum::<f64>() / n);
            let var: [f64; 3] = std::array::from_fn(|c| {
                pts.iter().map(|p| (p[c] - mean[c]).powi(2)).sum::<f64>() / n
            });
            let (mt, vt, vr) = frustum_gaussian(t0, t1, r, false);
            let g_mean: [f32; 3] = std::array::from_fn(|c| o[c] + mt * d[c]);
            let g_var = diagonal_covariance(d, vt, vr);
            for c in 0..3 {
                // Four standard errors of the sample mean.
                let tolerance = 4.0 * (var[c] / n).sqrt();
                assert!(
                    (g_mean[c] as f64 - mean[c]).abs() < tolerance,
                    "mean {g_mean:?} vs {mean:?}"
                );
                assert!(
                    (g_var[c] as f64 - var[c]).abs() < 0.01 * var[c] + 1e-9,
                    "var {g_var:?} vs {var:?} for {t0}..{t1}, r {r}"
                );
            }
            // The Gaussian's own points, for the encoding's expectation.
            let mut rng = Rng::new(9);
            let gauss: Vec<[f64; 3]> = (0..pts.len())
                .map(|_| {
                    std::array::from_fn(|c| {
                        let (u1, u2) = (1.0 - rng.uniform() as f64, rng.uniform() as f64);
                        let z = (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos();
                        g_mean[c] as f64 + z * (g_var[c] as f64).sqrt()
                    })
                })
                .collect();
            for paper_form in [false, true] {
                let e = encoding(paper_form);
                let mut ipe = vec![0.0; e.dims()];
                e.encode_integrated(&g_mean, &g_var, &mut ipe);
                let average = |points: &[[f64; 3]]| {
                    let mut avg = vec![0.0f64; e.dims()];
                    let mut one = vec![0.0f32; e.dims()];
                    for p in points {
                        e.encode(&[p[0] as f32, p[1] as f32, p[2] as f32], &mut one);
                        for (a, v) in avg.iter_mut().zip(&one) {
                            *a += *v as f64 / points.len() as f64;
                        }
                    }
                    avg
                };
                let diffs = |avg: &[f64]| -> (f64, f64) {
                    let d: Vec<f64> = ipe
                        .iter()
                        .zip(avg)
                        .map(|(a, b)| (*a as f64 - b).abs())
                        .collect();
                    (
                        d.iter().cloned().fold(0.0, f64::max),
                        d.iter().sum::<f64>() / d.len() as f64,
                    )
                };
                let (gauss_worst, _) = diffs(&average(&gauss));
                assert!(gauss_worst < 0.01, "Gaussian: worst {gauss_worst}");
                let (worst, mean) = diffs(&average(&pts));
                assert!(
                    worst < 0.25 && mean < 0.03,
                    "frustum: worst {worst}, mean {mean} for {t0}..{t1}, r {r}"
                );
            }
        }
    }

    /// No variance: exactly the positional encoding.
    #[test]
    fn zero_variance_is_the_positional_encoding() {
        for paper_form in [false, true] {
            let e = encoding(paper_form);
            let p = [0.3f32, -1.2, 2.0];
            let (mut a, mut b) = (vec![0.0; e.dims()], vec![0.0; e.dims()]);
            e.encode(&p, &mut a);
            e.encode_integrated(&p, &[0.0; 3], &mut b);
            for (x, y) in a.iter().zip(&b) {
                assert!((x - y).abs() < 1e-6, "{a:?} vs {b:?}");
            }
        }
    }

    #[test]
    fn backward_matches_finite_differences() {
        for paper_form in [false, true] {
            let e = encoding(paper_form);
            let mean = [0.3f32, -0.7, 0.2];
            let var = [0.01f32, 0.002, 0.03];
            let d_out: Vec<f32> = (0..e.dims())
                .map(|i| ((i * 7) as f32 * 0.3).sin())
                .collect();
            let (mut dm, mut dv) = ([0.0; 3], [0.0; 3]);
            e.encode_integrated_bwd(&mean, &var, &d_out, &mut dm, &mut dv);
            let loss = |m: &[f32], v: &[f32]| -> f64 {
                let mut o = vec![0.0; e.dims()];
                e.encode_integrated(m, v, &mut o);
                o.iter()
                    .zip(&d_out)
                    .map(|(a, b)| (*a as f64) * (*b as f64))
                    .sum()
            };
            // Central differences of `loss` along coordinate `c` of the mean or the
            // variance, against the backward's `grad`.
            let check = |what: &str, c: usize, h: f32, grad: f32| {
                let shifted = |s: f32| {
                    let (mut m, mut v) = (mean, var);
                    match what {
                        "mean" => m[c] += s,
                        _ => v[c] += s,
                    }
                    loss(&m, &v)
                };
                let fd = (shifted(h) - shifted(-h)) / (2.0 * h as f64);
                assert!(
                    (fd - grad as f64).abs() < 2e-2 * (1.0 + fd.abs()),
                    "{what} {c}: {fd} vs {grad}"
                );
            };
            for c in 0..3 {
                check("mean", c, 1e-3, dm[c]);
                check("var", c, 1e-4, dv[c]);
            }
        }
    }
}
