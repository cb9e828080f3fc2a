//! Per-photo appearance codes on the GPU (`field::fast`'s `--appearance`): each sample's
//! code, its photo's or the mean of all of them, appended to the colour network's input,
//! and the backward that adds each sample's share to its photo's code (or, for the mean
//! code, to every code in equal parts), as the CPU field does.

use cubecl::prelude::*;
use cubecl::server::Handle;

use super::device::Gpu;
use super::hash_grid::{Scatter, ScatterAdd};
use super::launch::grid;

/// Threads per workgroup.
const GROUP: u32 = 256;

/// Which code each sample takes: an index into the training photos, or
/// [`MEAN_APPEARANCE`](crate::stage::MEAN_APPEARANCE).
#[derive(Clone)]
pub struct SampleCodes {
    /// `n` indices, or one for every sample.
    pub index: Handle,
    pub per_sample: bool,
}

impl SampleCodes {
    /// Every sample the same code: photo `index`'s, or the mean
    /// ([`MEAN_APPEARANCE`](crate::stage::MEAN_APPEARANCE)).
    pub fn all(gpu: &Gpu, index: u32) -> SampleCodes {
        SampleCodes {
            index: gpu.upload_u32(&[index]),
            per_sample: false,
        }
    }

    /// Each ray's code for each of its samples: `per_ray` holds an index per ray, the
    /// samples of the first `rays` rays sit at their CSR `offsets` (`rays + 1` slots), `n`
    /// samples in all.
    pub fn of_rays(
        gpu: &Gpu,
        per_ray: &Handle,
        offsets: &Handle,
        rays: usize,
        n: usize,
    ) -> SampleCodes {
        let index = gpu.zeros_u32(n);
        if rays > 0 && n > 0 {
            let (count, dim) = grid(rays, GROUP);
            // SAFETY: `offsets` holds `rays + 1` slots ending at `n`, `per_ray` at least
            // `rays` indices, `index` `n`; the kernel reads and writes below those.
            unsafe {
                expand_per_ray::launch_unchecked(
                    &gpu.client,
                    count,
                    dim,
                    BufferArg::from_raw_parts(offsets.clone(), rays + 1),
                    BufferArg::from_raw_parts(per_ray.clone(), rays),
                    BufferArg::from_raw_parts(index.clone(), n),
                    rays as u32,
                );
            }
        }
        SampleCodes {
            index,
            per_sample: true,
        }
    }

    pub(super) fn len(&self, n: usize) -> usize {
        if self.per_sample {
            n
        } else {
            1
        }
    }
}

/// `index[i] = per_ray[r]` for each sample `i` of ray `r < rays`.
#[cube(launch_unchecked)]
fn expand_per_ray(offsets: &[u32], per_ray: &[u32], index: &mut [u32], rays: u32) {
    let r = ABSOLUTE_POS;
    if r < rays as usize {
        let v = per_ray[r];
        for i in offsets[r] as usize..offsets[r + 1] as usize {
            index[i] = v;
        }
    }
}

/// `mean[j]` = the mean over the `images` codes at `off` (`dims` each) of entry `j`,
/// summed in photo order as `field::fast::mean_code` sums.
#[cube(launch_unchecked)]
fn mean_code(params: &[f32], mean: &mut [f32], off: u32, dims: u32, images: u32) {
    let j = ABSOLUTE_POS;
    if j < dims as usize {
        let n = f32::cast_from(images);
        let mut m = 0.0f32;
        for i in 0..images as usize {
            m += params[off as usize + i * dims as usize + j] / n;
        }
        mean[j] = m;
    }
}

/// Where the codes sit and whom they serve, in the order the kernels read them.
#[derive(CubeType, CubeLaunch, Clone, Copy)]
struct CodeLayout {
    /// Samples.
    n: u32,
    /// The colour input's width, and the column its code starts at.
    ci: u32,
    first: u32,
    /// Offset of the `images x dims` codes in the parameter vector.
    off: u32,
    dims: u32,
    images: u32,
    /// 1: one index per sample; 0: one for every sample.
    per_sample: u32,
}

/// Thread `t`'s sample, the entry of its code it handles, and its code's index.
#[cube]
fn sample_code(index: &[u32], at: &CodeLayout, t: usize) -> (usize, usize, u32) {
    let s = t / at.dims as usize;
    let j = t % at.dims as usize;
    let i = index[select(at.per_sample == 1, s, 0usize)];
    (s, j, i)
}

/// Writes each sample's code into its colour-network input row.
#[cube(launch_unchecked)]
fn write_codes(params: &[f32], mean: &[f32], index: &[u32], colour_in: &mut [f32], at: CodeLayout) {
    let t = ABSOLUTE_POS;
    if t < at.n as usize * at.dims as usize {
        let (s, j, i) = sample_code(index, &at, t);
        let (off, dims, images) = (at.off as usize, at.dims as usize, at.images);
        let v = select(
            i < images,
            params[off + (i as usize % images as usize) * dims + j],
            mean[j],
        );
        colour_in[s * at.ci as usize + at.first as usize + j] = v;
    }
}

/// Adds each sample's code gradient (its colour-input gradient's code columns) to its
/// photo's code, or `1 / images` of it to every code for the mean code.
#[cube(launch_unchecked)]
fn codes_bwd<S: ScatterAdd>(
    index: &[u32],
    d_colour_in: &[f32],
    grads: &mut [Atomic<S>],
    at: CodeLayout,
) {
    let t = ABSOLUTE_POS;
    if t < at.n as usize * at.dims as usize {
        let (s, j, i) = sample_code(index, &at, t);
        let (off, dims, images) = (at.off as usize, at.dims as usize, at.images);
        let d = d_colour_in[s * at.ci as usize + at.first as usize + j];
        if i < images {
            S::scatter_add(&grads[off + i as usize * dims + j], d);
        } else {
            let share = d / f32::cast_from(images);
            for k in 0..images as usize {
                S::scatter_add(&grads[off + k * dims + j], share);
            }
        }
    }
}

/// Where a field's codes sit and how long they are.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct GpuCodes {
    /// Offset of the `images x dims` codes in the parameter vector.
    pub offset: usize,
    pub dims: usize,
    pub images: usize,
}

impl GpuCodes {
    /// The mean of the photos' codes (`dims` floats), the code of
    /// [`MEAN_APPEARANCE`](crate::stage::MEAN_APPEARANCE).
    pub fn mean(&self, gpu: &Gpu, params: &Handle, n_params: usize) -> Handle {
        let mean = gpu.floats(self.dims);
        let (count, dim) = grid(self.dims, GROUP);
        // SAFETY: the codes sit inside the parameter vector (`offset + images x dims <=
        // n_params`), `mean` holds `dims` floats; the kernel bounds-checks its entry.
        unsafe {
            mean_code::launch_unchecked(
                &gpu.client,
                count,
                dim,
                BufferArg::from_raw_parts(params.clone(), n_params),
                BufferArg::from_raw_parts(mean.clone(), self.dims),
                self.offset as u32,
                self.dims as u32,
                self.images as u32,
            );
        }
        mean
    }

    /// Writes the codes of `codes` into columns `first..first + dims` of the `n` rows of
    /// `colour_in` (`ci` wide); `params` holds `n_params` floats.
    #[allow(clippy::too_many_arguments)]
    pub fn write(
        &self,
        gpu: &Gpu,
        params: &Handle,
        n_params: usize,
        codes: &SampleCodes,
        colour_in: &Handle,
        (ci, first): (usize, usize),
        n: usize,
    ) {
        if n == 0 {
            return;
        }
        let mean = self.mean(gpu, params, n_params);
        // SAFETY: the codes sit inside the parameter vector (`offset + images x dims <=
        // n_params`), `mean` holds `dims` floats, `index` one or `n` indices as
        // `per_sample` says, `colour_in` `n x ci` with the code columns inside a row; the
        // kernel bounds-checks its thread index.
        unsafe {
            let (count, dim) = grid(n * self.dims, GROUP);
            write_codes::launch_unchecked(
                &gpu.client,
                count,
                dim,
                BufferArg::from_raw_parts(params.clone(), n_params),
                BufferArg::from_raw_parts(mean.clone(), self.dims),
                BufferArg::from_raw_parts(codes.index.clone(), codes.len(n)),
                BufferArg::from_raw_parts(colour_in.clone(), n * ci),
                self.layout(codes, (ci, first), n),
            );
        }
    }

    /// Backward of [`write`](Self::write): adds the code columns of `d_colour_in` into
    /// `grads` (laid out as the parameter vector, `n_params` floats) through `scatter`.
    #[allow(clippy::too_many_arguments)]
    pub fn backward(
        &self,
        gpu: &Gpu,
        scatter: Scatter,
        codes: &SampleCodes,
        d_colour_in: &Handle,
        (ci, first): (usize, usize),
        grads: &Handle,
        n_params: usize,
        n: usize,
    ) {
        if n == 0 {
            return;
        }
        let (count, dim) = grid(n * self.dims, GROUP);
        // SAFETY: as in `write`; `grads` holds a slot per parameter.
        unsafe {
            let index = || BufferArg::from_raw_parts(codes.index.clone(), codes.len(n));
            let d = || BufferArg::from_raw_parts(d_colour_in.clone(), n * ci);
            let g = || BufferArg::from_raw_parts(grads.clone(), n_params);
            let at = || self.layout(codes, (ci, first), n);
            match scatter {
                Scatter::FloatAtomic => codes_bwd::launch_unchecked::<f32>(
                    &gpu.client,
                    count,
                    dim,
                    index(),
                    d(),
                    g(),
                    at(),
                ),
                Scatter::CompareAndSwap => codes_bwd::launch_unchecked::<u32>(
                    &gpu.client,
                    count,
                    dim,
                    index(),
                    d(),
                    g(),
                    at(),
                ),
            }
        }
    }

    /// The kernels' view of these codes for `n` samples of `codes`, written to columns
    /// `first..` of `ci`-wide rows.
    fn layout(
        &self,
        codes: &SampleCodes,
        (ci, first): (usize, usize),
        n: usize,
    ) -> CodeLayoutLaunch {
        CodeLayoutLaunch::new(
            n as u32,
            ci as u32,
            first as u32,
            self.offset as u32,
            self.dims as u32,
            self.images as u32,
            u32::from(codes.per_sample),
        )
    }
}
