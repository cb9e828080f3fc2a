//! Volume rendering by quadrature (NeRF eq. 3) and its closed-form backward.
//!
//! For samples at depths `t_i` with lengths `delta_i` along a ray:
//! `alpha_i = 1 - exp(-sigma_i delta_i)`, `T_i = prod_{j<i} (1 - alpha_j)`, `w_i = T_i alpha_i`,
//! `C = sum w_i c_i + (1 - sum w_i) bg`, depth `= sum w_i t_i`, opacity `A = sum w_i`.
//! The paper's sampler takes `delta_i = (t_{i+1} - t_i) |d|` (the last `1e10 |d|`, see
//! [`depth_deltas`]); the fast field's ray marcher uses its fixed step, skipped space excluded.
//!
//! Backward (one forward sweep, O(1) memory): with `S_i = sum_{j>i} w_j c_j + T_{N+1} bg`,
//! the colour still to come after sample i,
//! `dC/dc_i = w_i` and `dC/dsigma_i = delta_i (T_{i+1} c_i - S_i)`. `S_i` is the final colour
//! minus the prefix sum up to i, so nothing per sample is stored (instant-ngp's trick).

/// Distance that stands for "to infinity" after the last sample (the reference's 1e10).
pub const LAST_DELTA: f32 = 1e10;

pub use crate::stage::RayOutput;
use crate::stage::{FieldOutput, PackedSamples};

/// The paper's sample lengths: gaps between depths `t`, scaled by `|d|`, the last one
/// "infinite".
pub fn depth_deltas(t: &[f32], dir_norm: f32, deltas: &mut [f32]) {
    for i in 0..t.len() {
        deltas[i] = if i + 1 < t.len() {
            (t[i + 1] - t[i]) * dir_norm
        } else {
            LAST_DELTA * dir_norm
        };
    }
}

/// Front-to-back compositing of one ray, sample by sample, so a renderer can stop a ray
/// once it is opaque ([`Accumulator::transmittance`] small).
#[derive(Clone, Copy, Debug)]
pub struct Accumulator {
    trans: f32,
    out: RayOutput,
}

impl Default for Accumulator {
    fn default() -> Self {
        Accumulator {
            trans: 1.0,
            out: RayOutput::default(),
        }
    }
}

impl Accumulator {
    /// Adds a sample at depth `t` of length `delta`; returns its weight `w_i`.
    #[inline]
    pub fn add(&mut self, t: f32, delta: f32, sigma: f32, rgb: &[f32]) -> f32 {
        let alpha = 1.0 - (-sigma * delta).exp();
        let w = self.trans * alpha;
        for c in 0..3 {
            self.out.rgb[c] += w * rgb[c];
        }
        self.out.depth += w * t;
        self.out.opacity += w;
        self.trans *= 1.0 - alpha;
        w
    }

    /// Transmittance past the samples added so far.
    pub fn transmittance(&self) -> f32 {
        self.trans
    }

    /// The ray's result over background `bg`.
    pub fn finish(self, bg: [f32; 3]) -> RayOutput {
        let mut out = self.out;
        for c in 0..3 {
            out.rgb[c] += (1.0 - out.opacity) * bg[c];
        }
        out
    }
}

/// Composites one ray. `t`, `deltas` and `sigma` have one value per sample, `rgb` three.
/// Writes the per-sample weights `w_i` into `weights` (for hierarchical sampling).
///
/// Example: one sample, sigma large, colour red, white bg -> rgb `[1, 0, 0]`, opacity 1.
pub fn composite(
    t: &[f32],
    deltas: &[f32],
    sigma: &[f32],
    rgb: &[f32],
    bg: [f32; 3],
    weights: &mut [f32],
) -> RayOutput {
    let mut acc = Accumulator::default();
    for i in 0..t.len() {
        weights[i] = acc.add(t[i], deltas[i], sigma[i], &rgb[i * 3..][..3]);
    }
    acc.finish(bg)
}

/// Backward of [`composite`] for the colour output: given `d_rgb_out = dL/dC`, writes
/// `d_sigma` (per sample) and `d_rgb` (three per sample). `rendered` is the forward's colour.
/// The last sample's suffix is `T_{N+1} bg` computed directly: a delta of 1e10 would
/// magnify the rounding error of `rendered - prefix` into a huge false gradient.
#[allow(clippy::too_many_arguments)]
pub fn composite_bwd(
    deltas: &[f32],
    sigma: &[f32],
    rgb: &[f32],
    bg: [f32; 3],
    rendered: [f32; 3],
    d_rgb_out: [f32; 3],
    d_sigma: &mut [f32],
    d_rgb: &mut [f32],
) {
    let mut trans = 1.0f32;
    let mut prefix = [0.0f32; 3];
    let n = deltas.len();
    for i in 0..n {
        let dl = deltas[i];
        let alpha = 1.0 - (-sigma[i] * dl).exp();
        let w = trans * alpha;
        trans *= 1.0 - alpha;
        let mut ds = 0.0;
        for c in 0..3 {
            let ci = rgb[i * 3 + c];
            prefix[c] += w * ci;
            let suffix = if i + 1 == n {
                trans * bg[c]
            } else {
                rendered[c] - prefix[c]
            };
            ds += d_rgb_out[c] * (trans * ci - suffix);
            d_rgb[i * 3 + c] = w * d_rgb_out[c];
        }
        d_sigma[i] = dl * ds;
    }
}

/// Compositing as a stage over packed samples (forward): every ray of `samples` with its
/// field output (`sigma`: `n`, `rgb`: `n x 3`) over its background (`rays x 3`) into `out`
/// (`rays`), depth in the units of `samples.t`. Its context is the field output itself:
/// the backward recomputes transmittance instead of storing it.
pub fn composite_packed(
    samples: &PackedSamples,
    field: FieldOutput,
    backgrounds: &[[f32; 3]],
    weights: &mut [f32],
    out: &mut [RayOutput],
) {
    for (r, o) in out.iter_mut().enumerate().take(samples.rays()) {
        let s = samples.ray(r);
        *o = composite(
            &samples.t[s.clone()],
            &samples.dt[s.clone()],
            &field.sigma[s.clone()],
            &field.rgb[s.start * 3..s.end * 3],
            backgrounds[r],
            &mut weights[s],
        );
    }
}

/// Backward of [`composite_packed`]: from `d_out` (`dL/dC`, `rays x 3`) writes `d_sigma`
/// (`n`) and `d_rgb` (`n x 3`), the field's `d_output`.
pub fn composite_packed_bwd(
    samples: &PackedSamples,
    field: FieldOutput,
    backgrounds: &[[f32; 3]],
    rendered: &[RayOutput],
    d_out: &[[f32; 3]],
    d_sigma: &mut [f32],
    d_rgb: &mut [f32],
) {
    for r in 0..samples.rays() {
        let s = samples.ray(r);
        composite_bwd(
            &samples.dt[s.clone()],
            &field.sigma[s.clone()],
            &field.rgb[s.start * 3..s.end * 3],
            backgrounds[r],
            rendered[r].rgb,
            d_out[r],
            &mut d_sigma[s.clone()],
            &mut d_rgb[s.start * 3..s.end * 3],
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    fn deltas(t: &[f32], dir_norm: f32) -> Vec<f32> {
        let mut d = vec![0.0; t.len()];
        depth_deltas(t, dir_norm, &mut d);
        d
    }

    #[test]
    fn constant_slab_transmits_exp_minus_sigma_length() {
        // A slab of density 0.7 from t = 2 to 4 (samples every 0.01) then empty space: the
        // background shows through with weight exp(-0.7 * 2).
        let n = 400;
        let t: Vec<f32> = (0..n).map(|i| 2.0 + 0.01 * i as f32).collect();
        let sigma: Vec<f32> = t
            .iter()
            .map(|&x| if x < 3.995 { 0.7 } else { 0.0 })
            .collect();
        let rgb = vec![0.0; n * 3];
        let mut w = vec![0.0; n];
        let out = composite(&t, &deltas(&t, 1.0), &sigma, &rgb, [1.0; 3], &mut w);
        let want = (-0.7f32 * 2.0).exp();
        assert!((out.rgb[0] - want).abs() < 1e-4, "{} vs {want}", out.rgb[0]);
        assert!((1.0 - out.opacity - want).abs() < 1e-4);
        // |d| = 2 doubles the optical depth.
        let out2 = composite(&t, &deltas(&t, 2.0), &sigma, &rgb, [1.0; 3], &mut w);
        assert!((out2.rgb[0] - want * want).abs() < 1e-4);
    }

    #[test]
    fn opaque_surface_gives_its_colour_and_depth() {
        let t = [2.0, 3.0, 4.0];
        let mut w = [0.0; 3];
        let out = composite(
            &t,
            &deltas(&t, 1.0),
            &[0.0, 1e4, 0.0],
            &[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0],
            [1.0; 3],
            &mut w,
        );
        assert!((out.rgb[0] - 1.0).abs() < 1e-6 && out.rgb[1].abs() < 1e-6);
        assert!((out.depth - 3.0).abs() < 1e-5 && (out.opacity - 1.0).abs() < 1e-6);
    }

    #[test]
    fn backward_matches_finite_differences() {
        let mut rng = Rng::new(5);
        let n = 12;
        let mut t: Vec<f32> = (0..n).map(|_| rng.range(2.0, 6.0)).collect();
        t.sort_by(f32::total_cmp);
        // Last sample's delta is 1e10: keep its sigma clear of 0 so exp underflows cleanly.
        let sigma: Vec<f32> = (0..n)
            .map(|i| if i + 1 == n { 1.0 } else { rng.range(0.0, 2.0) })
            .collect();
        let rgb: Vec<f32> = (0..n * 3).map(|_| rng.uniform()).collect();
        let (bg, g) = ([0.2, 0.5, 0.9], [0.7, -1.1, 0.4]);
        let dl = deltas(&t, 1.3);
        let loss = |s: &[f32], c: &[f32]| -> f64 {
            let mut w = vec![0.0; n];
            let o = composite(&t, &dl, s, c, bg, &mut w);
            (0..3).map(|k| (g[k] * o.rgb[k]) as f64).sum()
        };
        let mut w = vec![0.0; n];
        let out = composite(&t, &dl, &sigma, &rgb, bg, &mut w);
        let (mut ds, mut dc) = (vec![0.0; n], vec![0.0; n * 3]);
        composite_bwd(&dl, &sigma, &rgb, bg, out.rgb, g, &mut ds, &mut dc);
        let h = 1e-3;
        for i in 0..n {
            let (mut a, mut b) = (sigma.clone(), sigma.clone());
            a[i] += h;
            b[i] -= h;
            let fd = (loss(&a, &rgb) - loss(&b, &rgb)) / (2.0 * h as f64);
            assert!(
                (fd - ds[i] as f64).abs() < 2e-3 * (1.0 + fd.abs()),
                "sigma {i}: fd {fd} vs {}",
                ds[i]
            );
        }
        for i in 0..n * 3 {
            let (mut a, mut b) = (rgb.clone(), rgb.clone());
            a[i] += h;
            b[i] -= h;
            let fd = (loss(&sigma, &a) - loss(&sigma, &b)) / (2.0 * h as f64);
            assert!(
                (fd - dc[i] as f64).abs() < 2e-3,
                "rgb {i}: fd {fd} vs {}",
                dc[i]
            );
        }
    }
}
