//! The photometric loss (the paper's): mean squared error of rendered colours.
//!
//! The stage works on sums: [`squared_error`] returns the batch's sum of squared errors
//! and its gradient `2 (C - C_target)` per ray. The mean over the step's rays and channels
//! is taken once per step, by [`mean_scale`], on the value and on the reduced gradient:
//! the only place the loss is normalised, so chunks and threads can split a step any way.

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
}
