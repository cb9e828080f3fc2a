//! The paper's trunk: `depth` ReLU layers of one width over an encoded input, with the input
//! concatenated again after one layer (the skip). NeRF's field and D-NeRF's deformation are
//! both built on it.
//!
//! A skip layer stores one weight whose first rows multiply the hidden state and whose last
//! rows multiply the input.

use super::activation::relu;
use super::activation::relu_bwd_bias;
use super::dense::Dense;
use super::linalg::{matmul, MatRef};
use super::ParamLayout;

#[derive(Clone, Debug)]
pub struct Trunk {
    pub layers: Vec<Dense>,
    /// The input is concatenated to the output of this layer (0-based).
    pub skip: Option<usize>,
    pub width: usize,
    /// Width of the encoded input.
    pub input: usize,
}

impl Trunk {
    /// Lays out layers `{prefix}0..{prefix}{depth - 1}`.
    pub fn new(
        layout: &mut ParamLayout,
        prefix: &str,
        input: usize,
        depth: usize,
        width: usize,
        skip: Option<usize>,
    ) -> Trunk {
        let layers = (0..depth)
            .map(|l| {
                let mut fan_in = if l == 0 { input } else { width };
                if l > 0 && skip == Some(l - 1) {
                    fan_in += input;
                }
                Dense::push(layout, &format!("{prefix}{l}"), fan_in, width)
            })
            .collect();
        Trunk {
            layers,
            skip,
            width,
            input,
        }
    }

    pub fn macs(&self) -> usize {
        self.layers.iter().map(Dense::macs).sum()
    }

    /// The hidden states of `n` rows of `input` (`n x self.input`) into `hidden` (one
    /// `n x width` buffer per layer, after ReLU).
    pub fn forward(&self, params: &[f32], input: &[f32], n: usize, hidden: &mut [Vec<f32>]) {
        let (w, in_x) = (self.width, self.input);
        let input = MatRef::new(&input[..n * in_x], n, in_x);
        for (l, layer) in self.layers.iter().enumerate() {
            let (before, rest) = hidden.split_at_mut(l);
            let out = &mut rest[0][..n * w];
            layer.fill_bias(params, out);
            if l == 0 {
                matmul(out, input, layer.weight(params, 0, in_x), true);
            } else {
                let below = MatRef::new(&before[l - 1][..n * w], n, w);
                matmul(out, below, layer.weight(params, 0, w), true);
                if self.skip == Some(l - 1) {
                    matmul(out, input, layer.weight(params, w, in_x), true);
                }
            }
            relu(out);
        }
    }

    /// Backward of [`Self::forward`]: `d_a` holds d(last layer's output) (`n x width`, it is
    /// consumed; `d_b` is scratch of the same size). Accumulates parameter gradients into
    /// `grads`; with `d_input` (`n x self.input`) also sets the input's gradient.
    #[allow(clippy::too_many_arguments)]
    pub fn backward(
        &self,
        params: &[f32],
        input: &[f32],
        hidden: &[Vec<f32>],
        n: usize,
        d_a: &mut Vec<f32>,
        d_b: &mut Vec<f32>,
        grads: &mut [f32],
        mut d_input: Option<&mut [f32]>,
    ) {
        let (w, in_x) = (self.width, self.input);
        let input = MatRef::new(&input[..n * in_x], n, in_x);
        let mut input_grad_set = false;
        for l in (0..self.layers.len()).rev() {
            let layer = &self.layers[l];
            let dz = &mut d_a[..n * w];
            let (gw, gb) = layer.slices_mut(grads);
            relu_bwd_bias(dz, &hidden[l][..n * w], w, gb);
            let dz = MatRef::new(dz, n, w);
            // The input's rows of this layer, if it reads the input.
            let input_rows = match l {
                0 => Some(0),
                _ if self.skip == Some(l - 1) => Some(w),
                _ => None,
            };
            if let Some(row0) = input_rows {
                matmul(&mut gw[row0 * w..][..in_x * w], input.t(), dz, true);
                if let Some(d_in) = d_input.as_deref_mut() {
                    let d_in = &mut d_in[..n * in_x];
                    matmul(
                        d_in,
                        dz,
                        layer.weight(params, row0, in_x).t(),
                        input_grad_set,
                    );
                    input_grad_set = true;
                }
            }
            if l == 0 {
                break;
            }
            let below = MatRef::new(&hidden[l - 1][..n * w], n, w);
            matmul(&mut gw[..w * w], below.t(), dz, true);
            matmul(&mut d_b[..n * w], dz, layer.weight(params, 0, w).t(), false);
            std::mem::swap(d_a, d_b);
        }
    }
}
