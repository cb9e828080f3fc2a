//! Where to evaluate the field along a ray (NeRF, sections 4 and 5.2). Sampling is not
//! differentiated: sample positions are constants to the backward pass.

use crate::rng::Rng;

/// Stratified sampling: `[near, far]` split into `out.len()` equal bins, one uniform draw per
/// bin when `rng` is given (training), the bin midpoints otherwise (evaluation).
///
/// Example: near 2, far 6, 4 samples, no rng -> `[2.5, 3.5, 4.5, 5.5]`.
pub fn stratified(near: f32, far: f32, rng: Option<&mut Rng>, out: &mut [f32]) {
    let n = out.len();
    let bin = (far - near) / n as f32;
    match rng {
        Some(rng) => {
            for (i, t) in out.iter_mut().enumerate() {
                *t = near + bin * (i as f32 + rng.uniform());
            }
        }
        None => {
            for (i, t) in out.iter_mut().enumerate() {
                *t = near + bin * (i as f32 + 0.5);
            }
        }
    }
}

/// Hierarchical sampling by inverse transform (NeRF eq. 5, as the reference code does it).
///
/// `t` are the coarse sample depths (sorted) and `weights` their rendering weights. The PDF
/// is piecewise constant over the bins between consecutive midpoints of `t`, with weights
/// `w_2 .. w_{N-1}` (+1e-5, so empty rays still sample uniformly). Draws `out.len()`
/// samples, uniform `u` with `rng`, evenly spaced `u` in [0, 1] without. Output is sorted
/// when `rng` is `None`; callers sort the union anyway.
pub fn sample_pdf(
    t: &[f32],
    weights: &[f32],
    rng: Option<&mut Rng>,
    out: &mut [f32],
    cdf: &mut Vec<f32>,
) {
    let n = t.len();
    assert!(
        n >= 3,
        "importance sampling needs at least 3 coarse samples"
    );
    assert_eq!(weights.len(), n);
    // Bin edges: the n-1 midpoints; bin k = [mid_k, mid_{k+1}] has weight w_{k+1}.
    let mid = |k: usize| 0.5 * (t[k] + t[k + 1]);
    cdf.clear();
    cdf.push(0.0);
    let total: f32 = weights[1..n - 1].iter().map(|w| w + 1e-5).sum();
    let mut acc = 0.0;
    for w in &weights[1..n - 1] {
        acc += (w + 1e-5) / total;
        cdf.push(acc.min(1.0));
    }
    let m = out.len();
    let mut rng = rng;
    for (j, sample) in out.iter_mut().enumerate() {
        let u = match rng.as_deref_mut() {
            Some(r) => r.uniform(),
            None if m > 1 => j as f32 / (m - 1) as f32,
            None => 0.5,
        };
        // First index with cdf > u (searchsorted, side = right), clamped into the bins.
        let above = cdf.partition_point(|&c| c <= u).min(cdf.len() - 1);
        let below = above.saturating_sub(1);
        let (c0, c1) = (cdf[below], cdf[above]);
        let denom = if c1 - c0 < 1e-5 { 1.0 } else { c1 - c0 };
        let frac = (u - c0) / denom;
        let (b0, b1) = (mid(below), mid(above));
        *sample = b0 + frac * (b1 - b0);
    }
}

/// Merges two sorted lists into `out` (`a.len() + b.len()` values), sorted.
pub fn merge_sorted(a: &[f32], b: &[f32], out: &mut [f32]) {
    let (mut i, mut j) = (0, 0);
    for o in out.iter_mut() {
        if j >= b.len() || (i < a.len() && a[i] <= b[j]) {
            *o = a[i];
            i += 1;
        } else {
            *o = b[j];
            j += 1;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stratified_midpoints_and_bins() {
        let mut t = [0.0; 4];
        stratified(2.0, 6.0, None, &mut t);
        assert_eq!(t, [2.5, 3.5, 4.5, 5.5]);
        let mut rng = Rng::new(1);
        for _ in 0..100 {
            stratified(2.0, 6.0, Some(&mut rng), &mut t);
            for (i, v) in t.iter().enumerate() {
                assert!(*v >= 2.0 + i as f32 && *v < 3.0 + i as f32);
            }
        }
    }

    #[test]
    fn pdf_samples_concentrate_where_weight_is() {
        let mut t = [0.0; 64];
        stratified(2.0, 6.0, None, &mut t);
        // All weight on the sample at index 40 (t = 4.53): bin [mid_39, mid_40] ... the
        // reference pairs weight w_k with the bin between midpoints k-1 and k.
        let mut w = [0.0; 64];
        w[40] = 1.0;
        let mut out = [0.0; 128];
        let mut cdf = Vec::new();
        sample_pdf(&t, &w, Some(&mut Rng::new(3)), &mut out, &mut cdf);
        let (lo, hi) = (0.5 * (t[39] + t[40]), 0.5 * (t[40] + t[41]));
        let inside = out.iter().filter(|&&s| s >= lo && s <= hi).count();
        assert!(inside > 110, "{inside} of 128 in the heavy bin");
        // Uniform weights: samples spread evenly over [mid_0, mid_62].
        sample_pdf(&t, &[1.0; 64], None, &mut out, &mut cdf);
        assert!((out[0] - 0.5 * (t[0] + t[1])).abs() < 1e-4);
        assert!((out[127] - 0.5 * (t[62] + t[63])).abs() < 1e-4);
        assert!(out.windows(2).all(|p| p[0] <= p[1]));
        let mean: f32 = out.iter().sum::<f32>() / 128.0;
        assert!((mean - 4.0).abs() < 0.01, "{mean}");
    }

    #[test]
    fn merge_keeps_order() {
        let mut out = [0.0; 5];
        merge_sorted(&[1.0, 3.0, 5.0], &[2.0, 4.0], &mut out);
        assert_eq!(out, [1.0, 2.0, 3.0, 4.0, 5.0]);
    }
}
