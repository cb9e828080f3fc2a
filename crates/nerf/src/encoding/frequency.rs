//! Positional (frequency) encoding of NeRF, section 5.1.
//!
//! Reference form, per coordinate p and `L` frequencies (the default: it is what produced
//! the paper's numbers):
//! `gamma(p) = (p, sin(2^0 p), cos(2^0 p), ..., sin(2^(L-1) p), cos(2^(L-1) p))`,
//! so a 3-vector becomes `3 + 6 L` values (63 for L = 10, 27 for L = 4). Output order is
//! `[p_xyz, sin(f0 p_xyz), cos(f0 p_xyz), sin(f1 p_xyz), ...]` as in the reference code.
//! Paper form: frequencies `2^k pi` and no identity term (`6 L` values).
//! `L = 0` in reference form is the identity (the "no positional encoding" ablation).

use serde::{Deserialize, Serialize};

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct FrequencyEncoding {
    pub frequencies: usize,
    /// Paper form: `sin(2^k pi p)` and no identity term.
    pub paper_form: bool,
}

impl FrequencyEncoding {
    /// Encoded width of a 3-vector.
    pub fn dims(&self) -> usize {
        if self.paper_form {
            6 * self.frequencies
        } else {
            3 + 6 * self.frequencies
        }
    }

    /// The `k`-th frequency: `2^k`, times pi in the paper's form.
    pub fn frequency(&self, k: usize) -> f32 {
        let f = (1u64 << k) as f32;
        if self.paper_form {
            f * std::f32::consts::PI
        } else {
            f
        }
    }

    /// Encodes one 3-vector into `out` (`dims()` values).
    #[inline]
    pub fn encode(&self, p: &[f32], out: &mut [f32]) {
        let mut o = 0;
        if !self.paper_form {
            out[..3].copy_from_slice(&p[..3]);
            o = 3;
        }
        for k in 0..self.frequencies {
            let s = self.frequency(k);
            for c in 0..3 {
                let (sin, cos) = (s * p[c]).sin_cos();
                out[o + c] = sin;
                out[o + 3 + c] = cos;
            }
            o += 6;
        }
    }

    /// Encodes `n` packed 3-vectors into `n x dims()` rows.
    pub fn encode_all(&self, points: &[f32], out: &mut [f32]) {
        let d = self.dims();
        for (p, o) in points.chunks_exact(3).zip(out.chunks_exact_mut(d)) {
            self.encode(p, o);
        }
    }

    /// Backward: `d_p = sum_j d_out[j] * d gamma_j / d p` for one 3-vector.
    pub fn encode_bwd(&self, p: &[f32], d_out: &[f32], d_p: &mut [f32]) {
        let mut o = 0;
        let mut g = [0.0f32; 3];
        if !self.paper_form {
            g.copy_from_slice(&d_out[..3]);
            o = 3;
        }
        for k in 0..self.frequencies {
            let s = self.frequency(k);
            for c in 0..3 {
                let (sin, cos) = (s * p[c]).sin_cos();
                g[c] += s * (cos * d_out[o + c] - sin * d_out[o + 3 + c]);
            }
            o += 6;
        }
        d_p[..3].copy_from_slice(&g);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn layout_and_widths() {
        let e = FrequencyEncoding {
            frequencies: 10,
            paper_form: false,
        };
        assert_eq!(e.dims(), 63);
        assert_eq!(
            FrequencyEncoding {
                frequencies: 4,
                paper_form: false
            }
            .dims(),
            27
        );
        let mut out = vec![0.0; 63];
        e.encode(&[0.5, -1.0, 2.0], &mut out);
        assert_eq!(&out[..3], &[0.5, -1.0, 2.0]);
        assert!((out[3] - 0.5f32.sin()).abs() < 1e-6);
        assert!((out[6 + 2] - 2.0f32.cos()).abs() < 1e-6);
        // Frequency 2^3 on y, sine slot.
        assert!((out[3 + 6 * 3 + 1] - (-8.0f32).sin()).abs() < 1e-5);
        let p = FrequencyEncoding {
            frequencies: 2,
            paper_form: true,
        };
        let mut out = vec![0.0; 12];
        p.encode(&[0.25, 0.0, 0.0], &mut out);
        assert!((out[0] - (std::f32::consts::PI * 0.25).sin()).abs() < 1e-6);
    }

    #[test]
    fn backward_matches_finite_differences() {
        for paper_form in [false, true] {
            let e = FrequencyEncoding {
                frequencies: 4,
                paper_form,
            };
            let p = [0.3f32, -0.7, 0.2];
            let d_out: Vec<f32> = (0..e.dims())
                .map(|i| ((i * 7) as f32 * 0.3).sin())
                .collect();
            let mut d_p = [0.0; 3];
            e.encode_bwd(&p, &d_out, &mut d_p);
            let loss = |q: &[f32]| -> f64 {
                let mut o = vec![0.0; e.dims()];
                e.encode(q, &mut o);
                o.iter()
                    .zip(&d_out)
                    .map(|(a, b)| (*a as f64) * (*b as f64))
                    .sum()
            };
            for c in 0..3 {
                let h = 1e-3;
                let (mut a, mut b) = (p, p);
                a[c] += h;
                b[c] -= h;
                let fd = (loss(&a) - loss(&b)) / (2.0 * h as f64);
                assert!(
                    (fd - d_p[c] as f64).abs() < 2e-2 * (1.0 + fd.abs()),
                    "c {c}: fd {fd} vs {}",
                    d_p[c]
                );
            }
        }
    }
}
