//! FreeNeRF (Yang et al., CVPR 2023): the paper's model trained from a few photos with two
//! regularisers and nothing downloaded.
//!
//! - **Frequency regularisation.** With few photos, the positional encoding's high
//!   frequencies let the network fit each photo with detail that no other view confirms.
//!   The encoding's bands are revealed over the first part of training, lowest first: at
//!   progress `p` of a reveal lasting `reveal_until`, `L p / reveal_until + 1` bands are
//!   visible (the last one partly), all of them after it. The raw position always passes.
//! - **Occlusion regularisation.** Floaters right in front of the cameras explain a photo
//!   from its own viewpoint only; a penalty on the density of each ray's first samples
//!   removes them.

use serde::{Deserialize, Serialize};

/// FreeNeRF's settings (`--preset freenerf`).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct FreeNerf {
    /// Fraction of training over which the bands are revealed (FreeNeRF: 0.9).
    pub reveal_until: f32,
    /// Samples nearest the camera whose density is penalised on every ray (FreeNeRF: 10).
    pub occlusion_samples: usize,
    /// The penalty's weight against the mean squared error (FreeNeRF: 0.01).
    pub occlusion_weight: f32,
}

impl Default for FreeNerf {
    fn default() -> Self {
        FreeNerf {
            reveal_until: 0.9,
            occlusion_samples: 10,
            occlusion_weight: 0.01,
        }
    }
}

impl FreeNerf {
    /// Each of `bands` frequency bands' visibility in [0, 1] at `progress` in [0, 1].
    pub fn band_mask(&self, bands: usize, progress: f32) -> Vec<f32> {
        if progress >= self.reveal_until || self.reveal_until <= 0.0 {
            return vec![1.0; bands];
        }
        let visible = (bands as f32 * progress / self.reveal_until + 1.0).min(bands as f32);
        (0..bands)
            .map(|k| (visible - k as f32).clamp(0.0, 1.0))
            .collect()
    }

    /// Adds the occlusion penalty's gradient to `d_sigma` (rays of `samples_per_ray`
    /// samples, sorted by depth) and returns the penalty: `occlusion_weight` times the mean
    /// over rays and over their first `occlusion_samples` samples of the density `sigma`.
    /// The gradients are in the photometric loss's units before its normalisation
    /// (`render::loss::mean_scale`, `1 / (3 rays)`), so they are scaled by 3 to come out as
    /// the mean over rays.
    pub fn add_occlusion(&self, sigma: &[f32], samples_per_ray: usize, d_sigma: &mut [f32]) -> f64 {
        let m = self.occlusion_samples.min(samples_per_ray);
        if m == 0 {
            return 0.0;
        }
        let rays = sigma.len() / samples_per_ray;
        let per_sample = self.occlusion_weight / m as f32;
        let mut sum = 0.0f64;
        for (s, d) in sigma
            .chunks_exact(samples_per_ray)
            .zip(d_sigma.chunks_exact_mut(samples_per_ray))
        {
            for (&v, g) in s[..m].iter().zip(&mut d[..m]) {
                sum += (per_sample * v) as f64;
                *g += 3.0 * per_sample;
            }
        }
        sum / rays.max(1) as f64
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bands_are_revealed_lowest_first_until_the_reveal_ends() {
        let f = FreeNerf::default();
        assert_eq!(f.band_mask(4, 0.0), [1.0, 0.0, 0.0, 0.0]);
        // Half-way through the reveal: 4 * 0.5 + 1 = 3 bands.
        let half = f.band_mask(4, 0.45);
        assert!(
            (half[2] - 1.0).abs() < 1e-6 && half[3].abs() < 1e-5,
            "{half:?}"
        );
        let part = f.band_mask(4, 0.5625); // 3.5 bands
        assert!((part[3] - 0.5).abs() < 1e-5, "{part:?}");
        assert_eq!(f.band_mask(4, 0.9), [1.0; 4]);
        assert_eq!(f.band_mask(4, 1.0), [1.0; 4]);
        let masks: Vec<Vec<f32>> = (0..=20).map(|i| f.band_mask(10, i as f32 / 20.0)).collect();
        for pair in masks.windows(2) {
            assert!(pair[0].iter().zip(&pair[1]).all(|(a, b)| a <= b));
        }
    }

    /// The penalty's gradient against central differences, after the normalisation the
    /// engine applies (`1 / (3 rays)`).
    #[test]
    fn occlusion_gradient_matches_finite_differences() {
        let f = FreeNerf {
            occlusion_samples: 3,
            ..FreeNerf::default()
        };
        let (rays, spr) = (4, 5);
        let sigma: Vec<f32> = (0..rays * spr)
            .map(|i| (i as f32 * 0.7).sin().abs())
            .collect();
        let mut d = vec![0.0; sigma.len()];
        f.add_occlusion(&sigma, spr, &mut d);
        let scale = crate::render::loss::mean_scale(rays) as f32;
        for i in 0..sigma.len() {
            let at = |x: f32| {
                let mut s = sigma.clone();
                s[i] = x;
                f.add_occlusion(&s, spr, &mut vec![0.0; s.len()])
            };
            let fd = ((at(sigma[i] + 1e-2) - at(sigma[i] - 1e-2)) / 2e-2) as f32;
            assert!(
                (d[i] * scale - fd).abs() < 1e-6,
                "sample {i}: {} vs {fd}",
                d[i] * scale
            );
            assert_eq!(
                d[i] != 0.0,
                i % spr < 3,
                "only the first samples are penalised"
            );
        }
    }
}
