//! RegNeRF's depth smoothness (Niemeyer et al. 2022): small patches of rays rendered
//! from poses no photo was taken from, whose depths should vary smoothly from pixel to
//! pixel. With few photos a field can explain each of them with geometry that only looks
//! right from where it was taken (speckle, skirts of density behind surfaces); seen from
//! between the cameras, such geometry is a jagged depth map, and this loss pays for it.
//!
//! A patch is `PATCH_SIDE x PATCH_SIDE` rays in rows. Each ray's depth is its expected
//! depth along it, `d = sum_k w_k t_k / A` with opacity `A = sum_k w_k`, and the loss is
//!
//! `L = sum over neighbouring rays i, j of A_i A_j (d_i - d_j)^2`,
//!
//! with the opacities in the factor `A_i A_j` held constant (no gradient through them).
//! The factor leaves out the pairs a silhouette splits (a ray that misses the object has
//! no depth to agree with): the loss shapes surfaces, not outlines, which the photos'
//! colours already place.

use crate::render::distortion::weights_bwd;
use crate::stage::PackedSamples;

/// Rays along a patch's side.
pub const PATCH_SIDE: usize = 4;
/// Rays in a patch, row by row.
pub const PATCH_RAYS: usize = PATCH_SIDE * PATCH_SIDE;

/// Opacities below this carry no depth (their pairs weigh at most this much).
pub const NO_DEPTH: f32 = 1e-6;

/// One ray's opacity `A` and expected depth `d` from its samples' depths `t` and
/// compositing weights `w` (`d = 0` where nothing is hit).
pub fn ray_depth(t: &[f32], w: &[f32]) -> (f32, f32) {
    let (a, dw) = t
        .iter()
        .zip(w)
        .fold((0.0f32, 0.0f32), |(a, d), (t, w)| (a + w, d + w * t));
    (a, if a > NO_DEPTH { dw / a } else { 0.0 })
}

/// The neighbouring pairs of a patch: each ray with the one to its right and below.
fn neighbours() -> impl Iterator<Item = (usize, usize)> {
    (0..PATCH_RAYS).flat_map(|i| {
        let (row, col) = (i / PATCH_SIDE, i % PATCH_SIDE);
        let right = (col + 1 < PATCH_SIDE).then_some((i, i + 1));
        let below = (row + 1 < PATCH_SIDE).then_some((i, i + PATCH_SIDE));
        right.into_iter().chain(below)
    })
}

/// The loss of one patch: depths `depth`, pairs weighed by `opacity` (see the module docs).
pub fn patch_loss(depth: &[f32; PATCH_RAYS], opacity: &[f32; PATCH_RAYS]) -> f32 {
    neighbours()
        .filter(|&(i, j)| opacity[i] > NO_DEPTH && opacity[j] > NO_DEPTH)
        .map(|(i, j)| opacity[i] * opacity[j] * (depth[i] - depth[j]).powi(2))
        .sum()
}

/// `dL/dd_i / A_i` for each ray of a patch: `sum_j 2 A_j (d_i - d_j)` over its
/// neighbours (the opacity in `dd_i/dw` divides the `A_i` of the pair's factor out).
fn depth_pulls(depth: &[f32; PATCH_RAYS], opacity: &[f32; PATCH_RAYS]) -> [f32; PATCH_RAYS] {
    let mut pull = [0.0f32; PATCH_RAYS];
    for (i, j) in neighbours() {
        if opacity[i] > NO_DEPTH && opacity[j] > NO_DEPTH {
            let e = 2.0 * (depth[i] - depth[j]);
            pull[i] += opacity[j] * e;
            pull[j] -= opacity[i] * e;
        }
    }
    pull
}

/// The steps to differentiate the weights by, for rays of `samples_per_ray` samples whose
/// last step is the paper's "to infinity" (`volume::LAST_DELTA`): that sample's weight is
/// all the light left whatever its density (where positive), so its step is 0 in the
/// backward, which gives it no gradient and leaves every other sample's as it is.
pub fn steps_for_backward(dt: &[f32], samples_per_ray: usize, out: &mut Vec<f32>) {
    out.clear();
    out.extend_from_slice(dt);
    for steps in out.chunks_exact_mut(samples_per_ray) {
        steps[samples_per_ray - 1] = 0.0;
    }
}

/// Per-patch buffers of the backward.
#[derive(Clone, Debug, Default)]
pub struct PatchBackward {
    d_w: Vec<f32>,
}

impl PatchBackward {
    /// The loss of the patch whose rays' samples are `rays` (ranges into the packed
    /// `t`, `dt`, `weights` and `d_sigma`), depths measured in units of `unit`; adds its
    /// gradient times `scale` into `d_sigma`. Returns the loss.
    pub fn add(
        &mut self,
        rays: &[std::ops::Range<usize>; PATCH_RAYS],
        (t, dt, weights): (&[f32], &[f32], &[f32]),
        unit: f32,
        scale: f32,
        d_sigma: &mut [f32],
    ) -> f32 {
        let (mut depth, mut opacity) = ([0.0f32; PATCH_RAYS], [0.0f32; PATCH_RAYS]);
        for (r, s) in rays.iter().enumerate() {
            let (a, d) = ray_depth(&t[s.clone()], &weights[s.clone()]);
            (opacity[r], depth[r]) = (a, d / unit);
        }
        let pulls = depth_pulls(&depth, &opacity);
        for (r, s) in rays.iter().enumerate() {
            if pulls[r] == 0.0 {
                continue;
            }
            // dd/dw_k = (t_k - d) / A; the A is inside the pull.
            self.d_w.clear();
            self.d_w.extend(
                t[s.clone()]
                    .iter()
                    .map(|&tk| scale * pulls[r] * (tk / unit - depth[r])),
            );
            weights_bwd(
                &dt[s.clone()],
                &weights[s.clone()],
                &self.d_w,
                &mut d_sigma[s.clone()],
            );
        }
        patch_loss(&depth, &opacity)
    }

    /// [`add`](Self::add) for every patch of `samples`' rays from ray `first` on (whole
    /// patches, one after another), their weights differentiated by the steps `dt`.
    pub fn add_patches(
        &mut self,
        samples: &PackedSamples,
        first: usize,
        (dt, weights): (&[f32], &[f32]),
        unit: f32,
        scale: f32,
        d_sigma: &mut [f32],
    ) {
        for p in (first..samples.rays()).step_by(PATCH_RAYS) {
            let rays: [_; PATCH_RAYS] = std::array::from_fn(|i| samples.ray(p + i));
            self.add(&rays, (&samples.t, dt, weights), unit, scale, d_sigma);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::volume::composite;
    use crate::rng::Rng;

    /// A patch of rays with random samples: depths, steps and densities.
    struct Patch {
        rays: Vec<std::ops::Range<usize>>,
        t: Vec<f32>,
        dt: Vec<f32>,
        sigma: Vec<f32>,
    }

    /// Random rays of 3 to 8 samples, one empty and one nearly transparent; `fixed`: every
    /// ray of that many samples.
    fn patch_of(rng: &mut Rng, fixed: Option<usize>) -> Patch {
        let (mut rays, mut t, mut dt, mut sigma) = (vec![], vec![], vec![], vec![]);
        for r in 0..PATCH_RAYS {
            let start = t.len();
            let n = match fixed {
                Some(n) => n,
                None if r == 5 => 0,
                None => 3 + rng.below(6),
            };
            let mut at = 2.0 + rng.uniform();
            for _ in 0..n {
                at += 0.05 + 0.1 * rng.uniform();
                t.push(at);
                dt.push(0.05);
                sigma.push(if r == 9 { 0.01 } else { 20.0 * rng.uniform() });
            }
            rays.push(start..t.len());
        }
        Patch { rays, t, dt, sigma }
    }

    fn patch(rng: &mut Rng) -> Patch {
        patch_of(rng, None)
    }

    fn weights_of(p: &Patch, sigma: &[f32]) -> Vec<f32> {
        let mut w = vec![0.0; sigma.len()];
        for s in &p.rays {
            let rgb = vec![0.5; s.len() * 3];
            composite(
                &p.t[s.clone()],
                &p.dt[s.clone()],
                &sigma[s.clone()],
                &rgb,
                [0.0; 3],
                &mut w[s.clone()],
            );
        }
        w
    }

    /// The loss with the pairs' factors those of `frozen` densities: what the gradient
    /// differentiates.
    fn loss_at(p: &Patch, sigma: &[f32], frozen: &[f32], unit: f32) -> f64 {
        let (w, w0) = (weights_of(p, sigma), weights_of(p, frozen));
        let (mut depth, mut opacity) = ([0.0f32; PATCH_RAYS], [0.0f32; PATCH_RAYS]);
        for (r, s) in p.rays.iter().enumerate() {
            depth[r] = ray_depth(&p.t[s.clone()], &w[s.clone()]).1 / unit;
            opacity[r] = ray_depth(&p.t[s.clone()], &w0[s.clone()]).0;
        }
        patch_loss(&depth, &opacity) as f64
    }

    #[test]
    fn gradient_matches_finite_differences() {
        let mut rng = Rng::new(11);
        for _ in 0..3 {
            let p = patch(&mut rng);
            let (unit, scale) = (1.7, 0.6);
            let w = weights_of(&p, &p.sigma);
            let rays: [_; PATCH_RAYS] = p.rays.clone().try_into().expect("a whole patch");
            let mut d_sigma = vec![0.0; p.sigma.len()];
            let loss =
                PatchBackward::default().add(&rays, (&p.t, &p.dt, &w), unit, scale, &mut d_sigma);
            assert!((loss as f64 - loss_at(&p, &p.sigma, &p.sigma, unit)).abs() < 1e-6);
            assert!(loss > 0.0);
            let h = 1e-2f32;
            for k in 0..p.sigma.len() {
                let mut plus = p.sigma.clone();
                plus[k] += h;
                let mut minus = p.sigma.clone();
                minus[k] -= h;
                let fd = (loss_at(&p, &plus, &p.sigma, unit) - loss_at(&p, &minus, &p.sigma, unit))
                    / (2.0 * h as f64);
                let got = d_sigma[k] as f64 / scale as f64;
                assert!(
                    (fd - got).abs() < 2e-3 * (1.0 + fd.abs()),
                    "sample {k}: finite differences {fd}, backward {got}"
                );
            }
        }
    }

    /// The paper model's rays end with a step "to infinity": differentiated with that step
    /// zeroed, the gradient is still the loss's (the last sample's weight does not move
    /// with its density).
    #[test]
    fn rays_ending_at_infinity_differentiate_with_their_last_step_zeroed() {
        let mut rng = Rng::new(12);
        let spr = 6;
        let mut p = patch_of(&mut rng, Some(spr));
        for steps in p.dt.chunks_exact_mut(spr) {
            steps[spr - 1] = crate::render::volume::LAST_DELTA;
        }
        // Densities stay positive under the differences' steps (at 0 the last weight jumps).
        let h = 1e-2f32;
        p.sigma.iter_mut().for_each(|s| *s = s.max(3.0 * h));
        let w = weights_of(&p, &p.sigma);
        let mut steps = Vec::new();
        steps_for_backward(&p.dt, spr, &mut steps);
        let rays: [_; PATCH_RAYS] = p.rays.clone().try_into().expect("a whole patch");
        let mut d_sigma = vec![0.0; p.sigma.len()];
        PatchBackward::default().add(&rays, (&p.t, &steps, &w), 1.0, 1.0, &mut d_sigma);
        for k in 0..p.sigma.len() {
            let (mut plus, mut minus) = (p.sigma.clone(), p.sigma.clone());
            plus[k] += h;
            minus[k] -= h;
            let fd = (loss_at(&p, &plus, &p.sigma, 1.0) - loss_at(&p, &minus, &p.sigma, 1.0))
                / (2.0 * h as f64);
            let got = d_sigma[k] as f64;
            assert!(
                (fd - got).abs() < 2e-3 * (1.0 + fd.abs()),
                "sample {k}: finite differences {fd}, backward {got}"
            );
        }
        assert!(d_sigma.iter().any(|&g| g != 0.0));
    }

    #[test]
    fn a_flat_patch_costs_nothing_and_a_step_in_it_costs_by_its_height() {
        let opacity = [1.0; PATCH_RAYS];
        assert_eq!(patch_loss(&[3.0; PATCH_RAYS], &opacity), 0.0);
        // The right half one unit deeper: 4 rows cross the step once each.
        let step: [f32; PATCH_RAYS] =
            std::array::from_fn(|i| if i % PATCH_SIDE >= 2 { 4.0 } else { 3.0 });
        assert!((patch_loss(&step, &opacity) - 4.0).abs() < 1e-6);
        // Rays that see nothing have no depth to disagree with.
        let mut missed = opacity;
        for (i, a) in missed.iter_mut().enumerate() {
            if i % PATCH_SIDE >= 2 {
                *a = 0.0;
            }
        }
        assert_eq!(patch_loss(&step, &missed), 0.0);
        // A half-opaque neighbour counts half.
        missed.iter_mut().for_each(|a| *a = a.max(0.5));
        assert!((patch_loss(&step, &missed) - 2.0).abs() < 1e-6);
    }
}
