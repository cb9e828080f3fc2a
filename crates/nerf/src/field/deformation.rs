//! D-NeRF's deformation (Pumarola et al., CVPR 2021): a network from a point and a moment to
//! the offset that carries the point into the canonical scene, `dx = D(gamma(x), gamma(t))`,
//! which the canonical field then reads at `x + dx`. The canonical scene is the one at
//! `t = 0`: there the offset is zero by construction, not learnt, which is what ties the
//! canonical field to a real moment instead of letting it drift to an average of all.
//!
//! The network is the paper's trunk (8 x 256, the input again after the 5th layer) and a
//! linear layer to the 3 offsets. The moment is encoded like the position, one coordinate.

use serde::{Deserialize, Serialize};

use crate::encoding::FrequencyEncoding;
use crate::nn::activation::col_sum_into;
use crate::nn::dense::Dense;
use crate::nn::grow;
use crate::nn::linalg::{matmul, MatRef};
use crate::nn::trunk::Trunk;
use crate::nn::ParamLayout;

/// The shape of a deformation network.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DeformationConfig {
    pub depth: usize,
    pub width: usize,
    /// The input is concatenated to this layer's output (0-based; `None`: no skip).
    pub skip: Option<usize>,
    /// Frequencies of the moment's encoding (`t, sin(2^k t), cos(2^k t)`, k < L).
    pub time_frequencies: usize,
}

impl DeformationConfig {
    /// D-NeRF's: 8 x 256, skip after the 4th layer (0-based), L = 10 for the moment.
    pub fn dnerf() -> Self {
        DeformationConfig {
            depth: 8,
            width: 256,
            skip: Some(4),
            time_frequencies: 10,
        }
    }

    /// Encoded width of one moment.
    pub fn time_dims(&self) -> usize {
        1 + 2 * self.time_frequencies
    }
}

/// Encodes moment `t` as `[t, sin(2^0 t), cos(2^0 t), ..., sin(2^(L-1) t), cos(2^(L-1) t)]`.
fn encode_time(t: f32, frequencies: usize, out: &mut [f32]) {
    out[0] = t;
    for k in 0..frequencies {
        let (sin, cos) = ((1u64 << k) as f32 * t).sin_cos();
        out[1 + 2 * k] = sin;
        out[2 + 2 * k] = cos;
    }
}

/// Where a deformation network's weights sit in its field's parameter vector.
#[derive(Clone, Debug)]
pub struct Deformation {
    pub config: DeformationConfig,
    position_encoding: FrequencyEncoding,
    trunk: Trunk,
    output: Dense,
}

impl Deformation {
    /// Lays out the network under `prefix` (e.g. `"coarse.time_"`); positions are encoded
    /// with `position_encoding` (the canonical field's own, as in D-NeRF).
    pub fn new(
        config: DeformationConfig,
        position_encoding: FrequencyEncoding,
        layout: &mut ParamLayout,
        prefix: &str,
    ) -> Self {
        let input = position_encoding.dims() + config.time_dims();
        let trunk = Trunk::new(
            layout,
            &format!("{prefix}pts_"),
            input,
            config.depth,
            config.width,
            config.skip,
        );
        let output = Dense::push(layout, &format!("{prefix}out"), config.width, 3);
        Deformation {
            config,
            position_encoding,
            trunk,
            output,
        }
    }

    /// Sets the last layer to zero in freshly initialised `params` (the field's): the model
    /// starts as a still scene and learns the motion where the photos disagree with it,
    /// instead of starting from random offsets the canonical field must first undo.
    pub fn start_still(&self, params: &mut [f32]) {
        let (weight, bias) = self.output.slices_mut(params);
        weight.fill(0.0);
        bias.fill(0.0);
    }

    pub fn macs_per_sample(&self) -> usize {
        self.trunk.macs() + self.output.macs()
    }

    /// Moves `n` points (`positions`, `n x 3`) seen at `times` (`n`) into the canonical
    /// scene: `ws.moved = x + dx`, with `dx = 0` at `t = 0`. Keeps what
    /// [`Self::backward`] needs.
    pub fn forward(
        &self,
        params: &[f32],
        positions: &[f32],
        times: &[f32],
        ws: &mut DeformationWorkspace,
    ) {
        let n = times.len();
        assert_eq!(positions.len(), n * 3, "one moment per point");
        let (in_x, in_t) = (self.position_encoding.dims(), self.config.time_dims());
        let w = self.config.width;
        ws.resize(&self.config, n, in_x + in_t);
        for ((row, p), &t) in ws
            .input
            .chunks_exact_mut(in_x + in_t)
            .zip(positions.chunks_exact(3))
            .zip(times)
        {
            self.position_encoding.encode(p, &mut row[..in_x]);
            encode_time(t, self.config.time_frequencies, &mut row[in_x..]);
        }
        self.trunk.forward(params, &ws.input, n, &mut ws.hidden);
        let offsets = &mut ws.offsets[..n * 3];
        self.output.fill_bias(params, offsets);
        let last = MatRef::new(&ws.hidden[self.config.depth - 1][..n * w], n, w);
        matmul(offsets, last, self.output.weight(params, 0, w), true);
        for ((moved, (p, dx)), &t) in ws
            .moved
            .chunks_exact_mut(3)
            .zip(positions.chunks_exact(3).zip(offsets.chunks_exact_mut(3)))
            .zip(times)
        {
            if t == 0.0 {
                dx.fill(0.0);
            }
            for c in 0..3 {
                moved[c] = p[c] + dx[c];
            }
        }
    }

    /// Backward of the last [`Self::forward`] on `ws`: given the gradient with respect to
    /// the moved points (`n x 3`), accumulates the network's parameter gradients.
    pub fn backward(
        &self,
        params: &[f32],
        times: &[f32],
        d_moved: &[f32],
        ws: &mut DeformationWorkspace,
        grads: &mut [f32],
    ) {
        let n = ws.n;
        let w = self.config.width;
        // dx is a constant zero at t = 0: no gradient flows into the network there.
        let d_offsets = &mut ws.d_offsets[..n * 3];
        d_offsets.copy_from_slice(&d_moved[..n * 3]);
        for (d, &t) in d_offsets.chunks_exact_mut(3).zip(times) {
            if t == 0.0 {
                d.fill(0.0);
            }
        }
        let last = MatRef::new(&ws.hidden[self.config.depth - 1][..n * w], n, w);
        let (gw, gb) = self.output.slices_mut(grads);
        col_sum_into(&ws.d_offsets[..n * 3], 3, gb);
        let d_offsets = MatRef::new(&ws.d_offsets[..n * 3], n, 3);
        matmul(gw, last.t(), d_offsets, true);
        matmul(
            &mut ws.d_a[..n * w],
            d_offsets,
            self.output.weight(params, 0, w).t(),
            false,
        );
        self.trunk.backward(
            params,
            &ws.input,
            &ws.hidden,
            n,
            &mut ws.d_a,
            &mut ws.d_b,
            grads,
            None,
        );
    }
}

/// A deformation's activations of one chunk, reused across calls.
#[derive(Default, Debug)]
pub struct DeformationWorkspace {
    n: usize,
    input: Vec<f32>,
    hidden: Vec<Vec<f32>>,
    offsets: Vec<f32>,
    /// The points carried into the canonical scene, `n x 3`.
    pub moved: Vec<f32>,
    d_offsets: Vec<f32>,
    d_a: Vec<f32>,
    d_b: Vec<f32>,
}

impl DeformationWorkspace {
    fn resize(&mut self, cfg: &DeformationConfig, n: usize, input: usize) {
        self.n = n;
        grow(&mut self.input, n * input);
        self.hidden.resize_with(cfg.depth, Vec::new);
        for h in &mut self.hidden {
            grow(h, n * cfg.width);
        }
        for v in [&mut self.offsets, &mut self.moved, &mut self.d_offsets] {
            grow(v, n * 3);
        }
        for v in [&mut self.d_a, &mut self.d_b] {
            grow(v, n * cfg.width);
        }
    }

    pub fn bytes(&self) -> usize {
        let vecs = [
            &self.input,
            &self.offsets,
            &self.moved,
            &self.d_offsets,
            &self.d_a,
            &self.d_b,
        ];
        4 * (vecs.iter().map(|v| v.len()).sum::<usize>()
            + self.hidden.iter().map(|v| v.len()).sum::<usize>())
    }
}
