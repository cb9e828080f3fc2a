//! The anti-aliased fast field's weight of each hash-grid level per sample (see
//! [`super::fast::Antialias`]): `erf(1 / sqrt(8 sigma^2 N_l^2))` for a footprint of standard
//! deviation `sigma` and a level of `N_l` cells per axis.
//!
//! A step weighs every level of every sample (a million values), so the loop is
//! branch-free arithmetic that vectorises, and on x86-64 runs in the widest vectors the CPU
//! has: the same operations in the same order, so the same bits on every CPU.

use crate::math::erf_of_inv_sqrt;
use crate::simd::{in_width, Width};

/// The weight of a level of `resolution` cells per axis for a footprint of standard
/// deviation `sigma` in unit-cube units.
#[inline]
pub fn level_weight(sigma: f32, resolution: u32) -> f32 {
    erf_of_inv_sqrt(sigma * sigma * cell_factor(resolution))
}

/// `8 N^2` of a level of `N` cells per axis: a level's weight is
/// `erf(1 / sqrt(sigma^2 8 N^2))`.
pub(crate) fn cell_factor(resolution: u32) -> f32 {
    8.0 * (resolution as f32).powi(2)
}

/// Rows of `factors.len()` weights into `out`, one row per sample's squared footprint in
/// `sigma2`, each level's weight times its `schedule` factor, in the widest vectors the CPU
/// has.
pub(crate) fn fill_level_weights(
    out: &mut [f32],
    sigma2: &[f32],
    factors: &[f32],
    schedule: &[f32],
) {
    fill_level_weights_in(Width::widest(), out, sigma2, factors, schedule);
}

in_width! {
    /// [`fill_level_weights`] in the vectors of `width`.
    fn fill_level_weights_in(out: &mut [f32], sigma2: &[f32], factors: &[f32], schedule: &[f32]) => fill_baseline
}

/// [`fill_level_weights`] in the vectors of whatever function it is inlined into.
#[inline(always)]
fn fill_baseline(out: &mut [f32], sigma2: &[f32], factors: &[f32], schedule: &[f32]) {
    for (row, &s2) in out.chunks_exact_mut(factors.len()).zip(sigma2) {
        for ((w, &factor), &schedule) in row.iter_mut().zip(factors).zip(schedule) {
            *w = schedule * erf_of_inv_sqrt(s2 * factor);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A level is weighed by how many of its cells a footprint covers: all of it for a
    /// point, less for finer levels and wider footprints, nothing in the limit.
    #[test]
    fn level_weights_fall_with_footprint_and_resolution() {
        assert_eq!(level_weight(0.0, 2048), 1.0);
        assert!(level_weight(1e-5, 16) > 0.999_999);
        let by_level: Vec<f32> = [16, 64, 256, 1024, 4096]
            .iter()
            .map(|&n| level_weight(1e-3, n))
            .collect();
        assert!(by_level.windows(2).all(|w| w[1] <= w[0]), "{by_level:?}");
        assert!(by_level[0] > 0.999 && by_level[4] < 0.2, "{by_level:?}");
        // One cell as wide as the footprint's standard deviation: erf(1 / sqrt(8)).
        assert!((level_weight(0.01, 100) - 0.383_8).abs() < 1e-3);
        assert!(level_weight(1.0, 4096) < 1e-3);
    }

    /// Every vector width gives the per-value function's bits (rows of 16 levels and of 5,
    /// so tails are covered), with the schedule applied.
    #[test]
    fn every_width_matches_the_per_value_weight() {
        for levels in [16usize, 5] {
            let resolutions: Vec<u32> = (0..levels as u32).map(|l| 16 << (l / 2)).collect();
            let factors: Vec<f32> = resolutions.iter().map(|&r| cell_factor(r)).collect();
            let schedule: Vec<f32> = (0..levels).map(|l| 1.0 - l as f32 / 32.0).collect();
            let sigmas: Vec<f32> = (0..37).map(|i| i as f32 * 1e-4).collect();
            let sigma2: Vec<f32> = sigmas.iter().map(|s| s * s).collect();
            let mut want = vec![0.0; sigmas.len() * levels];
            for (row, &s) in want.chunks_exact_mut(levels).zip(&sigmas) {
                for (l, w) in row.iter_mut().enumerate() {
                    *w = schedule[l] * level_weight(s, resolutions[l]);
                }
            }
            type Fill = Box<dyn Fn(&mut [f32], &[f32], &[f32], &[f32])>;
            let mut variants: Vec<(String, Fill)> = vec![
                ("dispatched".into(), Box::new(fill_level_weights)),
                ("plain".into(), Box::new(fill_baseline)),
            ];
            for width in Width::available() {
                let fill = move |o: &mut [f32], s: &[f32], f: &[f32], w: &[f32]| {
                    fill_level_weights_in(width, o, s, f, w)
                };
                variants.push((format!("{width:?}"), Box::new(fill)));
            }
            for (name, fill) in variants {
                let mut got = vec![f32::NAN; want.len()];
                fill(&mut got, &sigma2, &factors, &schedule);
                let same = got
                    .iter()
                    .zip(&want)
                    .all(|(a, b)| a.to_bits() == b.to_bits());
                assert!(same, "{name} with {levels} levels: {got:?} vs {want:?}");
            }
        }
    }
}
