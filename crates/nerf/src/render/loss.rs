//! The photometric loss (the paper's): mean squared error of rendered colours.
//!
//! The stage works on sums: [`squared_error`] returns the batch's sum of squared errors
//! and its gradient `2 (C - C_target)` per ray. The mean over the step's rays and channels
//! is taken once per step, by [`mean_scale`], on the value and on the reduced gradient:
//! the only place the loss is normalised, so chunks and threads can split a step any way.

use crate::render::distortion::{distortion_bwd, weights_bwd};
use crate::render::volume::composite_packed_bwd;
use crate::stage::{FieldGrad, FieldOutput, PackedSamples, RayOutput};

/// Sum over rays and channels of `(C - C_target)^2` (returned), with its gradient
/// `dL/dC = 2 (C - C_target)` into `d_rgb` (`rays x 3`).
///
/// Example: one ray rendered `[0.5, 0.5, 0.5]` against `[0.5, 0.5, 1.0]`: value 0.25,
/// gradient `[0, 0, -1]`.
pub fn squared_error(rendered: &[RayOutput], targets: &[[f32; 3]], d_rgb: &mut [[f32; 3]]) -> f64 {
    let mut sse = 0.0f64;
    for ((out, target), d) in rendered.iter().zip(targets).zip(d_rgb.iter_mut()) {
        for c in 0..3 {
            let e = out.rgb[c] - target[c];
            sse += (e * e) as f64;
            d[c] = 2.0 * e;
        }
    }
    sse
}

/// The factor that turns summed squared errors (and their gradients) of `rays` rays into
/// the mean squared error: `1 / (3 rays)`.
pub fn mean_scale(rays: usize) -> f64 {
    1.0 / (3 * rays.max(1)) as f64
}

/// The backward from the loss to a field's outputs, with its reused buffers: `dL/dC` per
/// ray from the loss stage, then `dL/dsigma` and `dL/drgb` per sample from compositing's
/// backward (the field's `d_output`, [`field_grad`](Self::field_grad)).
#[derive(Clone, Debug, Default)]
pub struct LossBackward {
    d_out: Vec<[f32; 3]>,
    d_sigma: Vec<f32>,
    d_rgb: Vec<f32>,
    /// Per-ray scratch of [`add_distortion`](Self::add_distortion).
    middles: Vec<f32>,
    lengths: Vec<f32>,
    d_w: Vec<f32>,
}

impl LossBackward {
    /// Squared error of `rendered` (one per ray of `samples`) against `targets`, and its
    /// gradient back to the field's outputs `field`. Returns the summed squared error.
    pub fn run(
        &mut self,
        samples: &PackedSamples,
        field: FieldOutput,
        backgrounds: &[[f32; 3]],
        rendered: &[RayOutput],
        targets: &[[f32; 3]],
    ) -> f64 {
        let (r, n) = (samples.rays(), samples.len());
        self.d_out.resize(r, [0.0; 3]);
        self.d_sigma.resize(n, 0.0);
        self.d_rgb.resize(n * 3, 0.0);
        let sse = squared_error(&rendered[..r], &targets[..r], &mut self.d_out);
        composite_packed_bwd(
            samples,
            field,
            backgrounds,
            rendered,
            &self.d_out,
            &mut self.d_sigma,
            &mut self.d_rgb,
        );
        sse
    }

    /// Adds to the last [`run`](Self::run)'s density gradients those of `weight` times the
    /// mean over rays of the distortion loss (see `render::distortion`), each ray measured
    /// in its own field-space coordinate: sample middles are the distances walked from the
    /// ray's first sample (through any skipped gaps), and every sample's interval is
    /// `step` long, both divided by `scale` (the box's diagonal, so a ray spans at most 1).
    /// `weights` are compositing's. The value is not added to the returned loss, which
    /// stays the photometric error the PSNR figures come from. The middles move with the
    /// samples, but that pull is not carried back: camera refinement sees the term only
    /// through the densities.
    pub fn add_distortion(
        &mut self,
        samples: &PackedSamples,
        weights: &[f32],
        step: f32,
        scale: f32,
        weight: f32,
    ) {
        // The loss is normalised by `mean_scale`, 1 / (3 rays): scaling each ray's
        // gradient by 3 `weight` makes the term `weight` times the mean over rays.
        let per_ray = 3.0 * weight;
        for r in 0..samples.rays() {
            let s = samples.ray(r);
            let n = s.len();
            if n == 0 {
                continue;
            }
            self.middles.clear();
            let mut walked = 0.0f32;
            let points = &samples.positions[s.clone()];
            for i in 0..n {
                if i > 0 {
                    walked += crate::math::length(crate::math::sub(points[i], points[i - 1]));
                }
                self.middles.push(walked / scale);
            }
            self.lengths.clear();
            self.lengths.resize(n, step / scale);
            self.d_w.resize(n, 0.0);
            let w = &weights[s.clone()];
            distortion_bwd(&self.middles, &self.lengths, w, per_ray, &mut self.d_w[..n]);
            weights_bwd(
                &samples.dt[s.clone()],
                w,
                &self.d_w[..n],
                &mut self.d_sigma[s],
            );
        }
    }

    /// Lets a regulariser of the densities add its gradient to the last
    /// [`run`](Self::run)'s (in the photometric loss's units, see [`mean_scale`]).
    pub fn add_penalty(&mut self, add: impl FnOnce(&mut [f32])) {
        add(&mut self.d_sigma);
    }

    /// The field's `d_output` of the last [`run`](Self::run).
    pub fn field_grad(&self) -> FieldGrad<'_> {
        FieldGrad {
            d_sigma: &self.d_sigma,
            d_rgb: &self.d_rgb,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn value_and_gradient_match_the_definition() {
        let out = [RayOutput {
            rgb: [0.5, 0.5, 0.5],
            ..RayOutput::default()
        }];
        let mut d = [[9.0; 3]];
        let sse = squared_error(&out, &[[0.5, 0.5, 1.0]], &mut d);
        assert!((sse - 0.25).abs() < 1e-12);
        assert_eq!(d, [[0.0, 0.0, -1.0]]);
        // Finite differences of the value in the blue channel.
        let h = 1e-3f32;
        let at = |b: f32| {
            let o = [RayOutput {
                rgb: [0.5, 0.5, b],
                ..RayOutput::default()
            }];
            squared_error(&o, &[[0.5, 0.5, 1.0]], &mut [[0.0; 3]])
        };
        let fd = (at(0.5 + h) - at(0.5 - h)) / (2.0 * h as f64);
        assert!((fd - d[0][2] as f64).abs() < 1e-3, "{fd}");
        assert!((mean_scale(4) - 1.0 / 12.0).abs() < 1e-15);
    }

    /// The distortion term's density gradients against central differences of its value,
    /// in the coordinate `add_distortion` promises: distances walked along each ray's
    /// samples (gaps included) and a fixed interval, both over `scale`.
    #[test]
    fn distortion_gradient_matches_finite_differences() {
        use crate::render::distortion::distortion;
        use crate::render::volume::composite_packed;
        let mut rng = crate::rng::Rng::new(4);
        let mut samples = PackedSamples::default();
        samples.clear();
        for (r, n) in [9usize, 0, 14].into_iter().enumerate() {
            let mut at = [0.1 * r as f32, -0.5, 0.2];
            for _ in 0..n {
                // Unit steps along +y, with skipped gaps now and then.
                at[1] += 0.02 + if rng.range(0.0, 1.0) < 0.3 { 0.2 } else { 0.0 };
                samples.t.push(at[1]);
                samples.dt.push(0.02);
                samples.positions.push(at);
                samples.dirs.push([0.0, 1.0, 0.0]);
            }
            samples.end_ray();
        }
        let n = samples.len();
        let sigma: Vec<f32> = (0..n).map(|_| rng.range(0.0, 8.0)).collect();
        let rgb = vec![0.5f32; n * 3];
        let bgs = [[1.0f32; 3]; 3];
        let (step, scale, weight) = (0.02f32, 1.7f32, 0.3f32);
        let forward = |sigma: &[f32]| {
            let mut w = vec![0.0; n];
            let mut out = vec![RayOutput::default(); 3];
            let field = FieldOutput { sigma, rgb: &rgb };
            composite_packed(&samples, field, &bgs, &mut w, &mut out);
            (w, out)
        };
        // The value `add_distortion` stands for, summed over rays before `mean_scale`.
        let value = |sigma: &[f32]| -> f64 {
            let (w, _) = forward(sigma);
            (0..3)
                .map(|r| {
                    let s = samples.ray(r);
                    let p = &samples.positions[s.clone()];
                    let mut walked = 0.0;
                    let m: Vec<f32> = (0..p.len())
                        .map(|i| {
                            if i > 0 {
                                walked += crate::math::length(crate::math::sub(p[i], p[i - 1]));
                            }
                            walked / scale
                        })
                        .collect();
                    let l = vec![step / scale; p.len()];
                    3.0 * weight as f64 * distortion(&m, &l, &w[s]) as f64
                })
                .sum()
        };
        let (w, out) = forward(&sigma);
        let targets: Vec<[f32; 3]> = out.iter().map(|o| o.rgb).collect();
        let mut loss = LossBackward::default();
        let field = FieldOutput {
            sigma: &sigma,
            rgb: &rgb,
        };
        loss.run(&samples, field, &bgs, &out, &targets);
        assert!(
            loss.field_grad().d_sigma.iter().all(|&g| g == 0.0),
            "no colour error"
        );
        loss.add_distortion(&samples, &w, step, scale, weight);
        let grad = loss.field_grad().d_sigma.to_vec();
        assert!(grad.iter().any(|&g| g.abs() > 1e-3), "{grad:?}");
        let worst = grad.iter().fold(0.0f32, |a, g| a.max(g.abs())) as f64;
        for k in 0..n {
            let h = 1e-2 * (1.0 + sigma[k]);
            let (mut up, mut down) = (sigma.clone(), sigma.clone());
            up[k] += h;
            down[k] -= h;
            let fd = (value(&up) - value(&down)) / (2.0 * h as f64);
            let g = grad[k] as f64;
            assert!(
                (fd - g).abs() < 1e-3 * worst + 2e-2 * fd.abs(),
                "sample {k}: {fd} vs {g}"
            );
        }
    }
}
