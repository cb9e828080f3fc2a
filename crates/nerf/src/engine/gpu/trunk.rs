//! The paper's trunk on the GPU, shared by its network (`vanilla_net`) and D-NeRF's
//! deformation (`deformation`): the positional encoding, a stack of ReLU layers whose input
//! joins again at the skip, forward and backward (the input's gradient included), and the
//! column copies that build a concatenated input as one buffer.

use cubecl::prelude::*;
use cubecl::server::Handle;

use super::device::Gpu;
use super::launch::grid;
use super::mlp::Dense;
use crate::encoding::FrequencyEncoding;

const GROUP: u32 = 256;

/// `gamma(p)` of every 3-vector (`field::vanilla`'s encoding, both forms), one thread per
/// output value. Arguments are reduced modulo 2 pi first (Cody-Waite, two constants):
/// the highest frequency multiplies by 512, where a GPU's fast `sin` loses accuracy. With
/// `integrated` each point is a Gaussian's mean with the diagonal covariance `variances`,
/// and each frequency `s` fades by `exp(-s^2 var / 2)` (mip-NeRF's integrated encoding,
/// `encoding::integrated`). With `masked`, band `k` is scaled by `mask[k]` (FreeNeRF's
/// reveal, `field::vanilla`'s `band_mask`); the raw position passes whole.
#[cube(launch_unchecked)]
#[allow(clippy::too_many_arguments)]
fn frequency_encode(
    points: &[f32],
    variances: &[f32],
    mask: &[f32],
    out: &mut [f32],
    n: u32,
    frequencies: u32,
    paper_form: u32,
    base: f32,
    integrated: u32,
    masked: u32,
) {
    let idx = ABSOLUTE_POS;
    let id = 6 * frequencies as usize + select(paper_form == 1, 0usize, 3usize);
    if idx < n as usize * id {
        let s = idx / id;
        let mut j = idx % id;
        if paper_form == 0 && j < 3 {
            out[idx] = points[3 * s + j];
        } else {
            if paper_form == 0 {
                j -= 3;
            }
            let k = j / 6;
            let within = j % 6;
            let c = within % 3;
            // `base`: 1, or pi in the paper's form.
            let f = f32::cast_from(1u32 << k as u32) * base;
            let x = f * points[3 * s + c];
            let turns = f32::round(x * 0.159_154_94f32);
            let r = (x - turns * 6.281_25f32) - turns * 0.001_935_307_2f32;
            let mut v = select(within < 3, f32::sin(r), f32::cos(r));
            if integrated == 1 {
                v *= f32::exp(-0.5f32 * f * f * variances[(3 * s + c) % variances.len()]);
            }
            if masked == 1 {
                v *= mask[k % mask.len()];
            }
            out[idx] = v;
        }
    }
}

/// `dst[s, dst_off + j] = src[s, src_off + j]` for `j < width` of every row `s < n`.
#[cube(launch_unchecked)]
#[allow(clippy::too_many_arguments)]
fn copy_columns(
    src: &[f32],
    dst: &mut [f32],
    n: u32,
    width: u32,
    src_cols: u32,
    src_off: u32,
    dst_cols: u32,
    dst_off: u32,
) {
    let idx = ABSOLUTE_POS;
    if idx < (n * width) as usize {
        let s = idx / width as usize;
        let j = idx % width as usize;
        dst[s * dst_cols as usize + dst_off as usize + j] =
            src[s * src_cols as usize + src_off as usize + j];
    }
}

/// `a += b`.
#[cube(launch_unchecked)]
pub(super) fn add_into(a: &mut [f32], b: &[f32], n: u32) {
    let i = ABSOLUTE_POS;
    if i < n as usize {
        a[i] += b[i];
    }
}

/// `d_out = d_in * (y > 0)`: through a ReLU whose output was `y`.
#[cube(launch_unchecked)]
pub(super) fn relu_grad(d_in: &[f32], y: &[f32], d_out: &mut [f32], n: u32) {
    let i = ABSOLUTE_POS;
    if i < n as usize {
        d_out[i] = select(y[i] > 0.0, d_in[i], 0.0);
    }
}

/// A stack of ReLU layers `width` wide whose input is concatenated to layer `skip`'s
/// output (`nn::trunk`).
pub struct Trunk {
    pub layers: Vec<Dense>,
    pub width: usize,
    pub skip: Option<usize>,
}

/// A trunk's activations of one batch.
pub struct TrunkActs {
    /// The trunk's input (`n x` its width).
    input: Handle,
    /// The input of each layer after the first (`[h, input]` at the skip).
    inputs: Vec<Handle>,
    /// The last layer's output.
    pub last: Handle,
}

/// The trunk's forward on `input` (`n x in_dims`), which it keeps.
pub fn trunk_forward(
    gpu: &Gpu,
    params: &Handle,
    np: usize,
    trunk: &Trunk,
    input: Handle,
    in_dims: usize,
    n: usize,
) -> TrunkActs {
    let w = trunk.width;
    let mut inputs = Vec::new();
    let mut h = gpu.floats(n * w);
    trunk.layers[0].forward(gpu, params, np, &input, &h, n);
    for l in 1..trunk.layers.len() {
        let layer_in = if trunk.skip == Some(l - 1) {
            concat(gpu, &h, w, &input, in_dims, n)
        } else {
            h.clone()
        };
        let out = gpu.floats(n * w);
        trunk.layers[l].forward(gpu, params, np, &layer_in, &out, n);
        inputs.push(layer_in);
        h = out;
    }
    TrunkActs {
        input,
        inputs,
        last: h,
    }
}

/// The trunk's backward from `d_last` (d(last output), through its ReLU): adds the layers'
/// gradients into `grads` and, with `d_input` given, writes the input's gradient there
/// (`n x in_dims`: the first layer's plus the skip's).
pub fn trunk_backward(
    gpu: &Gpu,
    (params, grads, np): (&Handle, &Handle, usize),
    trunk: &Trunk,
    a: &TrunkActs,
    d_last: Handle,
    (in_dims, d_input): (usize, Option<&Handle>),
    n: usize,
) {
    let w = trunk.width;
    let mut d = d_last;
    let mut d_skip = None;
    for l in (1..trunk.layers.len()).rev() {
        let layer = &trunk.layers[l];
        let input = &a.inputs[l - 1];
        let d_in = gpu.floats(n * layer.inputs);
        let skip = layer.inputs != w;
        // At the skip only the hidden part of `[h, input]` came through a ReLU.
        let relu_in = !(skip && d_input.is_some());
        layer.backward(gpu, params, grads, np, input, &d, Some((&d_in, relu_in)), n);
        d = if !skip {
            d_in
        } else {
            // The skip layer: the hidden part goes on down, the input's part joins the
            // first layer's.
            let d_h = gpu.floats(n * w);
            copy(gpu, &d_in, &d_h, n, w, (layer.inputs, 0), (w, 0));
            if d_input.is_some() {
                let part = gpu.floats(n * in_dims);
                copy(
                    gpu,
                    &d_in,
                    &part,
                    n,
                    in_dims,
                    (layer.inputs, w),
                    (in_dims, 0),
                );
                d_skip = Some(part);
                let h = gpu.floats(n * w);
                copy(gpu, input, &h, n, w, (layer.inputs, 0), (w, 0));
                relu_mask(gpu, &d_h, &h, n * w);
            }
            d_h
        };
    }
    let dx = d_input.map(|d| (d, false));
    trunk.layers[0].backward(gpu, params, grads, np, &a.input, &d, dx, n);
    if let (Some(d_input), Some(part)) = (d_input, d_skip) {
        add(gpu, d_input, &part, n * in_dims);
    }
}

/// `d *= (y > 0)` over `len` floats: through the ReLU whose output was `y`.
fn relu_mask(gpu: &Gpu, d: &Handle, y: &Handle, len: usize) {
    // SAFETY: both buffers hold `len` floats; each value is read, then written, by one
    // thread.
    unsafe {
        let (c, g) = grid(len, GROUP);
        relu_grad::launch_unchecked(
            &gpu.client,
            c,
            g,
            BufferArg::from_raw_parts(d.clone(), len),
            BufferArg::from_raw_parts(y.clone(), len),
            BufferArg::from_raw_parts(d.clone(), len),
            len as u32,
        );
    }
}

/// `a += b` over `len` floats.
fn add(gpu: &Gpu, a: &Handle, b: &Handle, len: usize) {
    // SAFETY: both buffers hold `len` floats.
    unsafe {
        let (c, d) = grid(len, GROUP);
        add_into::launch_unchecked(
            &gpu.client,
            c,
            d,
            BufferArg::from_raw_parts(a.clone(), len),
            BufferArg::from_raw_parts(b.clone(), len),
            len as u32,
        );
    }
}

/// The encoding of `n` points (`n x 3`), integrated over Gaussians of diagonal
/// covariance `variances` (`n x 3`) when given.
/// With `mask`, band `k` is scaled by its `k`th value.
pub(super) fn encode(
    gpu: &Gpu,
    e: FrequencyEncoding,
    points: &Handle,
    variances: Option<&Handle>,
    mask: Option<&Handle>,
    n: usize,
) -> Handle {
    let out = gpu.floats(n * e.dims());
    let none = gpu.floats(1);
    let (var, var_len) = variances.map_or((&none, 1), |v| (v, n * 3));
    let (bands, bands_len) = mask.map_or((&none, 1), |m| (m, e.frequencies.max(1)));
    // SAFETY: `points` holds `n x 3` floats, `variances` as many (or one, unread), `out`
    // `n x dims`; bounds-checked.
    unsafe {
        let (c, d) = grid(n * e.dims(), GROUP);
        frequency_encode::launch_unchecked(
            &gpu.client,
            c,
            d,
            BufferArg::from_raw_parts(points.clone(), n * 3),
            BufferArg::from_raw_parts(var.clone(), var_len),
            BufferArg::from_raw_parts(bands.clone(), bands_len),
            BufferArg::from_raw_parts(out.clone(), n * e.dims()),
            n as u32,
            e.frequencies as u32,
            u32::from(e.paper_form),
            e.frequency(0),
            u32::from(variances.is_some()),
            u32::from(mask.is_some()),
        );
    }
    out
}

/// Copies `width` columns of `src` (`n x src_cols`, from `src_off`) into `dst`.
#[allow(clippy::too_many_arguments)]
pub(super) fn copy(
    gpu: &Gpu,
    src: &Handle,
    dst: &Handle,
    n: usize,
    width: usize,
    (src_cols, src_off): (usize, usize),
    (dst_cols, dst_off): (usize, usize),
) {
    // SAFETY: `src` holds `n x src_cols` floats and `dst` `n x dst_cols`, and the
    // columns copied lie within both rows.
    unsafe {
        let (c, d) = grid(n * width, GROUP);
        copy_columns::launch_unchecked(
            &gpu.client,
            c,
            d,
            BufferArg::from_raw_parts(src.clone(), n * src_cols),
            BufferArg::from_raw_parts(dst.clone(), n * dst_cols),
            n as u32,
            width as u32,
            src_cols as u32,
            src_off as u32,
            dst_cols as u32,
            dst_off as u32,
        );
    }
}

/// `[a, b]` row by row.
pub(super) fn concat(gpu: &Gpu, a: &Handle, wa: usize, b: &Handle, wb: usize, n: usize) -> Handle {
    let out = gpu.floats(n * (wa + wb));
    copy(gpu, a, &out, n, wa, (wa, 0), (wa + wb, 0));
    copy(gpu, b, &out, n, wb, (wb, 0), (wa + wb, wa));
    out
}
