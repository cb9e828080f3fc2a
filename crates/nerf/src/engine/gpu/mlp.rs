//! Dense layers on the GPU, the building block of both models' networks: `y = x W` with an
//! optional ReLU (and bias, for the paper's MLP), and its backward. Weights live in the
//! model's parameter vector exactly as the CPU lays them out (`in x out`, row-major, the
//! bias after them), so one offset names a layer.
//!
//! Work mapping: the forward, the input gradient and the weight gradient are tiled
//! products (`gemm`: output tiles staged through workgroup memory, a block of outputs a
//! thread or one); the plain kernels here (one thread per output value, a dot product from
//! global memory) are the reference the tiled paths are tested against and the fallback
//! for grids too tall for one launch (`Gpu::matmul` chooses). The weight gradient
//! `dW = x^T dy` is a reduction over samples: it is split
//! into slices of [`ROWS_PER_PARTIAL`] samples (more for the wide kernel:
//! `rows_per_partial`), each writing a partial sum, and a second
//! kernel adds the partials into the gradient buffer in a fixed order, so a step's
//! gradients do not depend on thread timing.

use cubecl::prelude::*;
use cubecl::server::Handle;

use super::device::{Gpu, Path};
use super::gemm::{self, Epilogue, View};
use super::launch::grid;

/// Threads per workgroup.
const GROUP: u32 = 256;
/// Samples summed by one thread of the weight-gradient kernel.
pub const ROWS_PER_PARTIAL: usize = 256;

/// Samples summed into one partial weight gradient by the tiled products of `path`: the
/// wide kernel sums more, since its partials (a whole `ni x no` matrix each) are written
/// and read again, and their count bounds how many threads add them.
fn rows_per_partial(path: Path) -> usize {
    match path {
        Path::Wide => 4 * ROWS_PER_PARTIAL,
        _ => ROWS_PER_PARTIAL,
    }
}

/// A layer's shape and where it sits in the parameter vector.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Dense {
    pub inputs: usize,
    pub outputs: usize,
    /// Offset of the `inputs x outputs` weights.
    pub weight: usize,
    /// Offset of the `outputs` biases, when the layer has them.
    pub bias: Option<usize>,
    pub relu: bool,
}

#[cube(launch_unchecked)]
fn dense_fwd(
    x: &[f32],
    params: &[f32],
    y: &mut [f32],
    n_in: u32,
    n_out: u32,
    w_off: u32,
    b_off: u32,
    has_bias: u32,
    relu: u32,
) {
    let idx = ABSOLUTE_POS;
    if idx < y.len() {
        let (ni, no) = (n_in as usize, n_out as usize);
        let s = idx / no;
        let o = idx % no;
        let w = w_off as usize;
        let mut acc = select(has_bias == 1, params[b_off as usize + o], 0.0);
        for i in 0..ni {
            acc += x[s * ni + i] * params[w + i * no + o];
        }
        y[idx] = select(relu == 1, f32::max(acc, 0.0), acc);
    }
}

/// `dx = dy W^T`, masked by the ReLU that produced `x` when `relu_in` is set.
#[cube(launch_unchecked)]
fn dense_bwd_input(
    dy: &[f32],
    params: &[f32],
    x: &[f32],
    dx: &mut [f32],
    n_in: u32,
    n_out: u32,
    w_off: u32,
    relu_in: u32,
) {
    let idx = ABSOLUTE_POS;
    if idx < dx.len() {
        let (ni, no) = (n_in as usize, n_out as usize);
        let s = idx / ni;
        let i = idx % ni;
        let w = w_off as usize + i * no;
        let mut acc = 0.0f32;
        for o in 0..no {
            acc += dy[s * no + o] * params[w + o];
        }
        dx[idx] = select(relu_in == 1 && x[idx] <= 0.0, 0.0, acc);
    }
}

/// Partial sums of `dW[i, o] = sum_s x[s, i] dy[s, o]` (and `db[o] = sum_s dy[s, o]` in the
/// extra row `i = n_in` when `bias` is set) over slices of `ROWS_PER_PARTIAL` samples.
#[cube(launch_unchecked)]
fn dense_bwd_weight_partial(
    x: &[f32],
    dy: &[f32],
    partial: &mut [f32],
    n: u32,
    n_in: u32,
    n_out: u32,
    bias: u32,
    rows: u32,
) {
    let idx = ABSOLUTE_POS;
    if idx < partial.len() {
        let (ni, no) = (n_in as usize, n_out as usize);
        let rows_w = ni + bias as usize;
        let per = rows_w * no;
        let k = idx / per;
        let j = idx % per;
        let i = j / no;
        let o = j % no;
        let first = k * rows as usize;
        let last = usize::min(first + rows as usize, n as usize);
        let mut acc = 0.0f32;
        if i < ni {
            for s in first..last {
                acc += x[s * ni + i] * dy[s * no + o];
            }
        } else {
            for s in first..last {
                acc += dy[s * no + o];
            }
        }
        partial[idx] = acc;
    }
}

/// `grads[off + j] += sum_k partial[k * stride + first + j]` for `j < len`, in `k` order.
#[cube(launch_unchecked)]
fn add_partials(
    partial: &[f32],
    grads: &mut [f32],
    len: u32,
    stride: u32,
    first: u32,
    parts: u32,
    off: u32,
) {
    let j = ABSOLUTE_POS;
    if j < len as usize {
        let mut acc = 0.0f32;
        for k in 0..parts as usize {
            acc += partial[k * stride as usize + first as usize + j];
        }
        grads[off as usize + j] += acc;
    }
}

impl Dense {
    /// `y` (`n x outputs`) from `x` (`n x inputs`).
    pub fn forward(
        &self,
        gpu: &Gpu,
        params: &Handle,
        n_params: usize,
        x: &Handle,
        y: &Handle,
        n: usize,
    ) {
        self.forward_with(gpu.matmul, gpu, params, n_params, x, y, n)
    }

    /// [`forward`](Self::forward) through the kernels of `path`.
    #[allow(clippy::too_many_arguments)]
    pub fn forward_with(
        &self,
        path: Path,
        gpu: &Gpu,
        params: &Handle,
        n_params: usize,
        x: &Handle,
        y: &Handle,
        n: usize,
    ) {
        if n == 0 {
            return;
        }
        if path != Path::Plain {
            let (ni, no) = (self.inputs, self.outputs);
            let a = View {
                buf: x,
                len: n * ni,
                off: 0,
                outer: ni,
                reduce: 1,
            };
            let b = View {
                buf: params,
                len: n_params,
                off: self.weight,
                outer: 1,
                reduce: no,
            };
            let epilogue = Epilogue {
                bias: self.bias.map(|off| (params, n_params, off)),
                relu: self.relu,
                mask: None,
            };
            if gemm::matmul(gpu, (n, no, ni), a, b, y, ni, epilogue, path) {
                return;
            }
        }
        let (count, dim) = grid(n * self.outputs, GROUP);
        // SAFETY: `x` holds `n x inputs` floats, `y` `n x outputs`, and the parameter
        // vector (`n_params`) holds the layer at its offsets; the kernel bounds-checks `y`.
        unsafe {
            dense_fwd::launch_unchecked(
                &gpu.client,
                count,
                dim,
                BufferArg::from_raw_parts(x.clone(), n * self.inputs),
                BufferArg::from_raw_parts(params.clone(), n_params),
                BufferArg::from_raw_parts(y.clone(), n * self.outputs),
                self.inputs as u32,
                self.outputs as u32,
                self.weight as u32,
                self.bias.unwrap_or(0) as u32,
                u32::from(self.bias.is_some()),
                u32::from(self.relu),
            );
        }
    }

    /// Backward of [`forward`](Self::forward): from `dy` (`n x outputs`, already through
    /// this layer's ReLU), adds `dW` (and `db`) into `grads` and, when `dx` is given,
    /// writes `dx = dy W^T`, masked by the ReLU that produced `x` when `relu_in` is set.
    #[allow(clippy::too_many_arguments)]
    pub fn backward(
        &self,
        gpu: &Gpu,
        params: &Handle,
        grads: &Handle,
        n_params: usize,
        x: &Handle,
        dy: &Handle,
        dx: Option<(&Handle, bool)>,
        n: usize,
    ) {
        let io = (x, dy, dx);
        self.backward_with(gpu.matmul, gpu, params, grads, n_params, io, n)
    }

    /// [`backward`](Self::backward) through the kernels of `path`.
    #[allow(clippy::too_many_arguments, clippy::type_complexity)]
    pub fn backward_with(
        &self,
        path: Path,
        gpu: &Gpu,
        params: &Handle,
        grads: &Handle,
        n_params: usize,
        (x, dy, dx): (&Handle, &Handle, Option<(&Handle, bool)>),
        n: usize,
    ) {
        if n == 0 {
            return;
        }
        // Gradients keep `f32` operands: tensor cores multiplying them in `f16` measured
        // slower than the wide kernel, and small gradients lose their bits in `f16`.
        let path = if path == Path::Cmma { Path::Wide } else { path };
        let (ni, no) = (self.inputs, self.outputs);
        // Partial sums of dW (`parts x ni x no`), from a tiled product where its grid
        // fits, else from the plain kernel.
        let tiled_rows = rows_per_partial(path);
        let tiled_parts = n.div_ceil(tiled_rows);
        let x_view = View {
            buf: x,
            len: n * ni,
            off: 0,
            outer: 1,
            reduce: ni,
        };
        let dy_view = View {
            buf: dy,
            len: n * no,
            off: 0,
            outer: 1,
            reduce: no,
        };
        let tiled_w = (path != Path::Plain).then(|| gpu.floats(tiled_parts * ni * no));
        // The partials from the tiled product, unless its grid does not fit.
        let tiled_w = tiled_w.filter(|w| {
            let epilogue = Epilogue::default();
            gemm::matmul(
                gpu,
                (ni, no, n),
                x_view,
                dy_view,
                w,
                tiled_rows,
                epilogue,
                path,
            )
        });
        let plain_parts = n.div_ceil(ROWS_PER_PARTIAL);
        // SAFETY: shapes as in `forward`; the partial buffers hold `parts x ni x no` and
        // `parts x no` floats, and each kernel bounds-checks the buffer it writes.
        unsafe {
            let weight_partials = |inputs: usize, out: &Handle, len: usize| {
                let (count, dim) = grid(len, GROUP);
                dense_bwd_weight_partial::launch_unchecked(
                    &gpu.client,
                    count,
                    dim,
                    BufferArg::from_raw_parts(x.clone(), n * ni),
                    BufferArg::from_raw_parts(dy.clone(), n * no),
                    BufferArg::from_raw_parts(out.clone(), len),
                    n as u32,
                    inputs as u32,
                    no as u32,
                    u32::from(inputs == 0),
                    ROWS_PER_PARTIAL as u32,
                )
            };
            let add = |partial: &Handle, parts: usize, len: usize, off: usize| {
                let (count, dim) = grid(len, GROUP);
                add_partials::launch_unchecked(
                    &gpu.client,
                    count,
                    dim,
                    BufferArg::from_raw_parts(partial.clone(), parts * len),
                    BufferArg::from_raw_parts(grads.clone(), n_params),
                    len as u32,
                    len as u32,
                    0,
                    parts as u32,
                    off as u32,
                )
            };
            if let Some(tiled_w) = &tiled_w {
                add(tiled_w, tiled_parts, ni * no, self.weight);
            } else {
                let partial_w = gpu.floats(plain_parts * ni * no);
                weight_partials(ni, &partial_w, plain_parts * ni * no);
                add(&partial_w, plain_parts, ni * no, self.weight);
            }
            if let Some(b) = self.bias {
                // With no input rows the partial kernel sums `dy` alone: the bias row.
                let partial_b = gpu.floats(plain_parts * no);
                weight_partials(0, &partial_b, plain_parts * no);
                add(&partial_b, plain_parts, no, b);
            }
        }
        let Some((dx, relu_in)) = dx else { return };
        if path != Path::Plain {
            let a = View {
                buf: dy,
                len: n * no,
                off: 0,
                outer: no,
                reduce: 1,
            };
            let b = View {
                buf: params,
                len: n_params,
                off: self.weight,
                outer: no,
                reduce: 1,
            };
            let epilogue = Epilogue {
                mask: relu_in.then_some((x, n * ni)),
                ..Epilogue::default()
            };
            if gemm::matmul(gpu, (n, ni, no), a, b, dx, no, epilogue, path) {
                return;
            }
        }
        // SAFETY: as above; `dx` holds `n x ni` floats.
        unsafe {
            let (count, dim) = grid(n * ni, GROUP);
            dense_bwd_input::launch_unchecked(
                &gpu.client,
                count,
                dim,
                BufferArg::from_raw_parts(dy.clone(), n * no),
                BufferArg::from_raw_parts(params.clone(), n_params),
                BufferArg::from_raw_parts(x.clone(), n * ni),
                BufferArg::from_raw_parts(dx.clone(), n * ni),
                ni as u32,
                no as u32,
                self.weight as u32,
                u32::from(relu_in),
            );
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::gpu::device::worst;
    use crate::nn::linalg::{matmul, MatRef};
    use crate::rng::Rng;

    /// A layer with bias and ReLU over 600 samples (three weight-gradient slices, the last
    /// partial; tiles cut by every edge) against plain loops on the CPU, through both the
    /// plain and the tiled kernels: outputs and dx within 1e-5, dW and db within 1e-4.
    #[test]
    fn dense_layer_matches_the_cpu_forward_and_backward() {
        let Some(gpu) = super::super::device::test_gpu() else {
            return;
        };
        let (n, ni, no) = (600, 7, 5);
        let mut rng = Rng::new(3);
        let layer = Dense {
            inputs: ni,
            outputs: no,
            weight: 4,
            bias: Some(4 + ni * no),
            relu: true,
        };
        let n_params = 4 + ni * no + no + 3;
        let params: Vec<f32> = (0..n_params).map(|_| rng.range(-1.0, 1.0)).collect();
        // x as a ReLU output: some exact zeros.
        let x: Vec<f32> = (0..n * ni).map(|_| rng.range(-0.5, 1.0).max(0.0)).collect();
        let dy: Vec<f32> = (0..n * no).map(|_| rng.range(-1.0, 1.0)).collect();

        let mut want_y = vec![0.0; n * no];
        matmul(
            &mut want_y,
            MatRef::new(&x, n, ni),
            MatRef::new(&params[4..4 + ni * no], ni, no),
            false,
        );
        for (k, y) in want_y.iter_mut().enumerate() {
            *y = (*y + params[4 + ni * no + k % no]).max(0.0);
        }
        let mut want_dw = vec![0.0; ni * no];
        matmul(
            &mut want_dw,
            MatRef::new(&x, n, ni).t(),
            MatRef::new(&dy, n, no),
            false,
        );
        let want_db: Vec<f32> = (0..no)
            .map(|o| (0..n).map(|s| dy[s * no + o]).sum())
            .collect();
        let mut want_dx = vec![0.0; n * ni];
        matmul(
            &mut want_dx,
            MatRef::new(&dy, n, no),
            MatRef::new(&params[4..4 + ni * no], ni, no).t(),
            false,
        );
        for (d, &xv) in want_dx.iter_mut().zip(&x) {
            if xv <= 0.0 {
                *d = 0.0;
            }
        }

        let (p, xh, dyh) = (gpu.upload(&params), gpu.upload(&x), gpu.upload(&dy));
        for path in [Path::Plain, Path::Tiled, Path::Blocked, Path::Wide] {
            let (y, dx) = (gpu.floats(n * no), gpu.floats(n * ni));
            // Gradients start non-zero: the layer adds into them.
            let start: Vec<f32> = (0..n_params).map(|i| i as f32 * 0.01).collect();
            let grads = gpu.upload(&start);
            layer.forward_with(path, &gpu, &p, n_params, &xh, &y, n);
            let io = (&xh, &dyh, Some((&dx, true)));
            layer.backward_with(path, &gpu, &p, &grads, n_params, io, n);
            let g = gpu.read(&grads, n_params).expect("read");
            let got_y = gpu.read(&y, n * no).expect("read");
            assert!(worst(&got_y, &want_y) < 1e-5, "y ({path:?})");
            let got_dx = gpu.read(&dx, n * ni).expect("read");
            assert!(worst(&got_dx, &want_dx) < 1e-5, "dx ({path:?})");
            let got_dw: Vec<f32> = (0..ni * no).map(|j| g[4 + j] - start[4 + j]).collect();
            assert!(worst(&got_dw, &want_dw) < 1e-4, "dW ({path:?})");
            let got_db: Vec<f32> = (0..no)
                .map(|o| g[4 + ni * no + o] - start[4 + ni * no + o])
                .collect();
            assert!(worst(&got_db, &want_db) < 1e-4, "db ({path:?})");
            // Slots outside the layer are untouched.
            assert_eq!(&g[..4], &start[..4]);
            assert_eq!(&g[n_params - 3..], &start[n_params - 3..]);
        }
    }
}
