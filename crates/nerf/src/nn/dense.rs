//! One dense layer's place in a flat parameter vector: an `in x out` row-major weight and a
//! bias, with views of its rows and of its gradients.

use super::linalg::MatRef;
use super::ParamLayout;

#[derive(Clone, Copy, Debug)]
pub struct Dense {
    pub w: usize,
    pub b: usize,
    pub fan_in: usize,
    pub fan_out: usize,
}

impl Dense {
    /// Lays out `{name}.weight` and `{name}.bias`.
    pub fn push(layout: &mut ParamLayout, name: &str, fan_in: usize, fan_out: usize) -> Dense {
        let w = layout.push(format!("{name}.weight"), &[fan_in, fan_out]);
        let b = layout.push(format!("{name}.bias"), &[fan_out]);
        Dense {
            w,
            b,
            fan_in,
            fan_out,
        }
    }

    /// Multiply-adds of one row through the layer.
    pub fn macs(&self) -> usize {
        self.fan_in * self.fan_out
    }

    /// Rows `[row0, row0 + rows)` of the weight (a concatenated input's part).
    pub fn weight<'a>(&self, params: &'a [f32], row0: usize, rows: usize) -> MatRef<'a> {
        MatRef::new(
            &params[self.w + row0 * self.fan_out..][..rows * self.fan_out],
            rows,
            self.fan_out,
        )
    }

    pub fn bias<'a>(&self, params: &'a [f32]) -> &'a [f32] {
        &params[self.b..][..self.fan_out]
    }

    /// The weight's and the bias's slices of a vector laid out as the parameters are (their
    /// gradients, or the parameters themselves); the bias follows the weight.
    pub fn slices_mut<'a>(&self, values: &'a mut [f32]) -> (&'a mut [f32], &'a mut [f32]) {
        let (head, tail) = values.split_at_mut(self.b);
        (
            &mut head[self.w..][..self.fan_in * self.fan_out],
            &mut tail[..self.fan_out],
        )
    }

    /// Every row of `out` (`rows x fan_out`) set to the bias.
    pub fn fill_bias(&self, params: &[f32], out: &mut [f32]) {
        let bias = self.bias(params);
        for row in out.chunks_exact_mut(self.fan_out) {
            row.copy_from_slice(bias);
        }
    }
}
