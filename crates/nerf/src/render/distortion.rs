//! The distortion loss of mip-NeRF 360 (Barron et al. 2022): a ray's compositing weights
//! pay for being spread out along it,
//!
//! `L = sum_i sum_j w_i w_j |m_i - m_j| + 1/3 sum_i w_i^2 l_i`,
//!
//! with `m_i` the middle and `l_i` the length of sample `i`'s interval in a normalised
//! coordinate along the ray. It is least when the weight sits in one short stretch (a
//! surface), and it is what removes the thin fog that fills a field's empty space where
//! no photo objects: fog that rays must march through until their transmittance runs out
//! (forward-facing and unbounded captures render several times slower for it).
//!
//! Samples are sorted along the ray, so the double sum is `O(n)` by prefix sums:
//! `sum_{i,j} w_i w_j |m_i - m_j| = 2 sum_i w_i (m_i W_<i - M_<i)`, where `W_<i` and `M_<i`
//! are the sums of `w_j` and `w_j m_j` over the samples before `i`.

/// The distortion of one ray: weights `w` of samples with interval middles `m` (sorted)
/// and lengths `l`.
pub fn distortion(m: &[f32], l: &[f32], w: &[f32]) -> f32 {
    let (mut w_before, mut wm_before, mut total) = (0.0f32, 0.0f32, 0.0f32);
    for i in 0..w.len() {
        total += 2.0 * w[i] * (m[i] * w_before - wm_before) + w[i] * w[i] * l[i] / 3.0;
        w_before += w[i];
        wm_before += w[i] * m[i];
    }
    total
}

/// Gradient of [`distortion`] with respect to the weights, times `scale`, into `d_w`:
/// `dL/dw_k = 2 sum_j w_j |m_k - m_j| + 2/3 w_k l_k`.
pub fn distortion_bwd(m: &[f32], l: &[f32], w: &[f32], scale: f32, d_w: &mut [f32]) {
    let (w_all, wm_all) = w
        .iter()
        .zip(m)
        .fold((0.0f32, 0.0f32), |(a, b), (wi, mi)| (a + wi, b + wi * mi));
    let (mut w_before, mut wm_before) = (0.0f32, 0.0f32);
    for k in 0..w.len() {
        let (w_after, wm_after) = (w_all - w_before - w[k], wm_all - wm_before - w[k] * m[k]);
        let spread = m[k] * w_before - wm_before + wm_after - m[k] * w_after;
        d_w[k] = scale * (2.0 * spread + 2.0 / 3.0 * w[k] * l[k]);
        w_before += w[k];
        wm_before += w[k] * m[k];
    }
}

/// Carries `d_w = dL/dw` (per sample of one ray) back to the densities, adding to
/// `d_sigma`; `weights` are the forward's. With `w_i = T_i (1 - exp(-sigma_i delta_i))`
/// and `T_i = exp(-sum_{j<i} sigma_j delta_j)`, a sample's density dims everything behind
/// it: `dL/dsigma_k = delta_k (d_w_k T_{k+1} - sum_{i>k} d_w_i w_i)`, where
/// `T_{k+1} = 1 - sum_{i<=k} w_i`.
pub fn weights_bwd(deltas: &[f32], weights: &[f32], d_w: &[f32], d_sigma: &mut [f32]) {
    let all: f32 = d_w.iter().zip(weights).map(|(g, w)| g * w).sum();
    let (mut w_so_far, mut dw_so_far) = (0.0f32, 0.0f32);
    for k in 0..deltas.len() {
        w_so_far += weights[k];
        dw_so_far += d_w[k] * weights[k];
        d_sigma[k] += deltas[k] * (d_w[k] * (1.0 - w_so_far) - (all - dw_so_far));
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    /// The definition, term by term.
    fn by_definition(m: &[f32], l: &[f32], w: &[f32]) -> f64 {
        let mut total = 0.0f64;
        for i in 0..w.len() {
            for j in 0..w.len() {
                total += (w[i] * w[j] * (m[i] - m[j]).abs()) as f64;
            }
            total += (w[i] * w[i] * l[i]) as f64 / 3.0;
        }
        total
    }

    /// A ray of `n` samples with random gaps (as occupancy skipping leaves them).
    fn ray(rng: &mut Rng, n: usize) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
        let (mut m, mut l, mut sigma) = (Vec::new(), Vec::new(), Vec::new());
        let mut at = 0.0;
        for _ in 0..n {
            let len = rng.range(0.01, 0.05);
            at += rng.range(0.0, 0.1);
            m.push(at + len / 2.0);
            l.push(len);
            at += len;
            sigma.push(rng.range(0.0, 30.0));
        }
        (m, l, sigma)
    }

    fn weights_of(l: &[f32], sigma: &[f32]) -> Vec<f32> {
        let mut trans = 1.0f32;
        sigma
            .iter()
            .zip(l)
            .map(|(s, d)| {
                let alpha = 1.0 - (-s * d).exp();
                let w = trans * alpha;
                trans *= 1.0 - alpha;
                w
            })
            .collect()
    }

    #[test]
    fn prefix_sums_give_the_definition() {
        let mut rng = Rng::new(3);
        for n in [0, 1, 2, 7, 40] {
            let (m, l, sigma) = ray(&mut rng, n);
            let w = weights_of(&l, &sigma);
            let fast = distortion(&m, &l, &w) as f64;
            let slow = by_definition(&m, &l, &w);
            assert!(
                (fast - slow).abs() < 1e-5 * (1.0 + slow),
                "{n}: {fast} vs {slow}"
            );
        }
        // One opaque thin slab costs little; the same weight spread along the ray costs more.
        let m: Vec<f32> = (0..10).map(|i| 0.05 + 0.1 * i as f32).collect();
        let l = vec![0.1; 10];
        let mut w = vec![0.0; 10];
        w[4] = 1.0;
        let spread = vec![0.1; 10];
        assert!(distortion(&m, &l, &w) * 5.0 < distortion(&m, &l, &spread));
    }

    #[test]
    fn gradient_through_the_weights_to_the_densities_matches_finite_differences() {
        let mut rng = Rng::new(11);
        let (m, l, sigma) = ray(&mut rng, 12);
        let loss = |s: &[f32]| by_definition(&m, &l, &weights_of(&l, s));
        let w = weights_of(&l, &sigma);
        let mut d_w = vec![0.0; 12];
        distortion_bwd(&m, &l, &w, 1.0, &mut d_w);
        // dL/dw against finite differences of the weights themselves.
        for k in 0..12 {
            let h = 1e-3f32;
            let mut up = w.clone();
            up[k] += h;
            let mut down = w.clone();
            down[k] -= h;
            let fd = (by_definition(&m, &l, &up) - by_definition(&m, &l, &down)) / (2.0 * h as f64);
            assert!(
                (fd - d_w[k] as f64).abs() < 1e-3 * (1.0 + fd.abs()),
                "w{k}: {fd} vs {}",
                d_w[k]
            );
        }
        let mut d_sigma = vec![0.5; 12];
        weights_bwd(&l, &w, &d_w, &mut d_sigma);
        for k in 0..12 {
            let h = 1e-2 * (1.0 + sigma[k]);
            let mut up = sigma.clone();
            up[k] += h;
            let mut down = sigma.clone();
            down[k] -= h;
            let fd = (loss(&up) - loss(&down)) / (2.0 * h as f64);
            let got = (d_sigma[k] - 0.5) as f64;
            assert!(
                (fd - got).abs() < 1e-3 + 2e-2 * fd.abs(),
                "sigma{k}: {fd} vs {got}"
            );
        }
    }
}
