//! D-NeRF's deformation on the GPU (`field::deformation`, whose docs give the model): the
//! network from a point's encoding and its moment's to the offset that carries it into
//! the canonical scene, zero at `t = 0`; forward, and backward from the gradient with
//! respect to the moved points. The canonical network (`vanilla_net`) then reads the
//! moved points and hands their gradient back.

use cubecl::prelude::*;
use cubecl::server::Handle;

use super::device::Gpu;
use super::launch::grid;
use super::mlp::Dense;
use super::trunk::{copy, encode, trunk_backward, trunk_forward, Trunk, TrunkActs};
use crate::encoding::FrequencyEncoding;
use crate::field::deformation::DeformationConfig;
use crate::nn::ParamLayout;

/// Threads per workgroup.
const GROUP: u32 = 64;

/// `sin` and `cos` of `x` after reducing it modulo 2 pi (Cody-Waite, two constants), as the
/// position encoding's kernel does: the moment's highest frequency multiplies by 512.
#[cube]
fn reduced(x: f32) -> f32 {
    let turns = f32::round(x * 0.159_154_94f32);
    (x - turns * 6.281_25f32) - turns * 0.001_935_307_2f32
}

/// Each moment's encoding `[t, sin(2^0 t), cos(2^0 t), ...]` into columns `off..` of `out`
/// (`n x cols`), one thread per value.
#[cube(launch_unchecked)]
fn encode_times(times: &[f32], out: &mut [f32], n: u32, frequencies: u32, cols: u32, off: u32) {
    let dims = 1 + 2 * frequencies as usize;
    let idx = ABSOLUTE_POS;
    if idx < n as usize * dims {
        let s = idx / dims;
        let j = idx % dims;
        let t = times[s];
        let mut v = t;
        if j > 0 {
            let k = (j - 1) / 2;
            let r = reduced(f32::cast_from(1u32 << k as u32) * t);
            // Odd columns the sines, even ones the cosines.
            v = select(j % 2 == 1, f32::sin(r), f32::cos(r));
        }
        out[s * cols as usize + off as usize + j] = v;
    }
}

/// `moved = x + dx`, the offset zeroed (in `offsets` too) where the moment is 0.
#[cube(launch_unchecked)]
fn move_points(positions: &[f32], offsets: &mut [f32], times: &[f32], moved: &mut [f32], n: u32) {
    let i = ABSOLUTE_POS;
    if i < 3 * n as usize {
        let mut dx = offsets[i];
        if times[i / 3] == 0.0 {
            dx = 0.0f32;
            offsets[i] = 0.0f32;
        }
        moved[i] = positions[i] + dx;
    }
}

/// The offsets' gradient: the moved points', none where the moment is 0 (the offset is a
/// constant zero there).
#[cube(launch_unchecked)]
fn offsets_grad(d_moved: &[f32], times: &[f32], d_offsets: &mut [f32], n: u32) {
    let i = ABSOLUTE_POS;
    if i < 3 * n as usize {
        d_offsets[i] = select(times[i / 3] == 0.0, 0.0f32, d_moved[i]);
    }
}

/// The position encoding's backward (`FrequencyEncoding::encode_bwd`), one thread per
/// point: from `d_enc` (`n x dims`, band `k` scaled by `mask[k]` where `masked`) to the
/// points' gradient `d_points` (`n x 3`).
#[cube(launch_unchecked)]
#[allow(clippy::too_many_arguments)]
fn encode_bwd(
    points: &[f32],
    d_enc: &[f32],
    mask: &[f32],
    d_points: &mut [f32],
    n: u32,
    frequencies: u32,
    paper_form: u32,
    base: f32,
    masked: u32,
) {
    let s = ABSOLUTE_POS;
    let raw = select(paper_form == 1, 0usize, 3usize);
    let dims = 6 * frequencies as usize + raw;
    if s < n as usize {
        for c in 0..3usize {
            let mut g = 0.0f32;
            if raw == 3 {
                g = d_enc[s * dims + c];
            }
            for k in 0..frequencies as usize {
                let f = f32::cast_from(1u32 << k as u32) * base;
                let r = reduced(f * points[3 * s + c]);
                let o = s * dims + raw + 6 * k;
                let mut m = 1.0f32;
                if masked == 1 {
                    m = mask[k % mask.len()];
                }
                g += m * f * (f32::cos(r) * d_enc[o + c] - f32::sin(r) * d_enc[o + 3 + c]);
            }
            d_points[3 * s + c] = g;
        }
    }
}

/// The points' gradient from their encoding's, `d_enc` (`n x e.dims()`), band `k` scaled
/// by `mask[k]` where given (FreeNeRF's reveal, as the forward scaled it).
pub fn position_encoding_bwd(
    gpu: &Gpu,
    e: FrequencyEncoding,
    points: &Handle,
    d_enc: &Handle,
    mask: Option<&Handle>,
    n: usize,
) -> Handle {
    let d_points = gpu.floats(3 * n);
    let none = gpu.floats(1);
    let (bands, bands_len) = mask.map_or((&none, 1), |m| (m, e.frequencies.max(1)));
    // SAFETY: `points` and `d_points` hold `n x 3` floats, `d_enc` `n x dims`, the mask one
    // per band (or one, unread); one thread per point, bounds-checked.
    unsafe {
        let (c, d) = grid(n, GROUP);
        encode_bwd::launch_unchecked(
            &gpu.client,
            c,
            d,
            BufferArg::from_raw_parts(points.clone(), 3 * n),
            BufferArg::from_raw_parts(d_enc.clone(), n * e.dims()),
            BufferArg::from_raw_parts(bands.clone(), bands_len),
            BufferArg::from_raw_parts(d_points.clone(), 3 * n),
            n as u32,
            e.frequencies as u32,
            u32::from(e.paper_form),
            e.frequency(0),
            u32::from(mask.is_some()),
        );
    }
    d_points
}

/// A deformation network on the device, its layers at `base +` their offsets.
pub struct GpuDeformation {
    /// The canonical field's position encoding (D-NeRF encodes the point the same way).
    pe: FrequencyEncoding,
    time_frequencies: usize,
    trunk: Trunk,
    output: Dense,
    n_params: usize,
}

/// A deformation's activations of one batch, kept for its backward.
pub struct DeformActs {
    trunk: TrunkActs,
    /// The batch's moments, one per point.
    pub times: Handle,
    /// The points carried into the canonical scene (`n x 3`).
    pub moved: Handle,
}

impl GpuDeformation {
    /// The deformation of the net laid out in `layout` (its tensors named `...time_*`),
    /// parameters from `base` in a vector of `n_params`; `None` where it has none.
    pub fn new(
        config: Option<&DeformationConfig>,
        pe: FrequencyEncoding,
        layout: &ParamLayout,
        base: usize,
        n_params: usize,
    ) -> Option<Self> {
        let config = config?;
        let find = |name: &str, relu: bool| {
            let tensor = |part: &str| {
                layout
                    .tensors
                    .iter()
                    .find(|t| t.name.ends_with(&format!("time_{name}.{part}")))
                    .expect("every deformation layer has a weight and a bias")
            };
            let (w, b) = (tensor("weight"), tensor("bias"));
            Dense {
                inputs: w.shape[0],
                outputs: w.shape[1],
                weight: base + w.offset,
                bias: Some(base + b.offset),
                relu,
            }
        };
        let layers = (0..config.depth)
            .map(|l| find(&format!("pts_{l}"), true))
            .collect();
        Some(GpuDeformation {
            pe,
            time_frequencies: config.time_frequencies,
            trunk: Trunk {
                layers,
                width: config.width,
                skip: config.skip,
            },
            output: find("out", false),
            n_params,
        })
    }

    fn input_dims(&self) -> usize {
        self.pe.dims() + 1 + 2 * self.time_frequencies
    }

    /// Carries `n` points (`positions`, `n x 3`) seen at `times` (`n`) into the canonical
    /// scene.
    pub fn forward(
        &self,
        gpu: &Gpu,
        params: &Handle,
        positions: &Handle,
        times: &Handle,
        n: usize,
    ) -> DeformActs {
        let (in_x, cols) = (self.pe.dims(), self.input_dims());
        let enc = encode(gpu, self.pe, positions, None, None, n);
        let input = gpu.floats(n * cols);
        copy(gpu, &enc, &input, n, in_x, (in_x, 0), (cols, 0));
        // SAFETY: `times` holds `n` floats, `input` `n x cols` with the moment's columns
        // `in_x..cols`; bounds-checked.
        unsafe {
            let dims = cols - in_x;
            let (c, d) = grid(n * dims, GROUP);
            encode_times::launch_unchecked(
                &gpu.client,
                c,
                d,
                BufferArg::from_raw_parts(times.clone(), n),
                BufferArg::from_raw_parts(input.clone(), n * cols),
                n as u32,
                self.time_frequencies as u32,
                cols as u32,
                in_x as u32,
            );
        }
        let trunk = trunk_forward(gpu, params, self.n_params, &self.trunk, input, cols, n);
        let offsets = gpu.floats(n * 3);
        self.output
            .forward(gpu, params, self.n_params, &trunk.last, &offsets, n);
        let moved = gpu.floats(n * 3);
        // SAFETY: every buffer holds `n x 3` floats but `times` (`n`); bounds-checked.
        unsafe {
            let (c, d) = grid(3 * n, GROUP);
            move_points::launch_unchecked(
                &gpu.client,
                c,
                d,
                BufferArg::from_raw_parts(positions.clone(), 3 * n),
                BufferArg::from_raw_parts(offsets.clone(), 3 * n),
                BufferArg::from_raw_parts(times.clone(), n),
                BufferArg::from_raw_parts(moved.clone(), 3 * n),
                n as u32,
            );
        }
        DeformActs {
            trunk,
            times: times.clone(),
            moved,
        }
    }

    /// Backward of [`forward`](Self::forward): from the moved points' gradient
    /// `d_moved` (`n x 3`), adds the network's parameter gradients into `grads`.
    pub fn backward(
        &self,
        gpu: &Gpu,
        (params, grads): (&Handle, &Handle),
        acts: &DeformActs,
        d_moved: &Handle,
        n: usize,
    ) {
        let np = self.n_params;
        let d_offsets = gpu.floats(n * 3);
        // SAFETY: `d_moved` and `d_offsets` hold `n x 3` floats, `times` `n`.
        unsafe {
            let (c, d) = grid(3 * n, GROUP);
            offsets_grad::launch_unchecked(
                &gpu.client,
                c,
                d,
                BufferArg::from_raw_parts(d_moved.clone(), 3 * n),
                BufferArg::from_raw_parts(acts.times.clone(), n),
                BufferArg::from_raw_parts(d_offsets.clone(), 3 * n),
                n as u32,
            );
        }
        let w = self.trunk.width;
        let d_last = gpu.floats(n * w);
        let last = &acts.trunk.last;
        let dx = Some((&d_last, true));
        self.output
            .backward(gpu, params, grads, np, last, &d_offsets, dx, n);
        let input_dims = self.input_dims();
        trunk_backward(
            gpu,
            (params, grads, np),
            &self.trunk,
            &acts.trunk,
            d_last,
            (input_dims, None),
            n,
        );
    }
}
