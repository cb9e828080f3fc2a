//! The fast field's inference in one kernel: one thread per sample runs the hash encoding,
//! the density network, the spherical harmonics and the colour network, its activations in
//! registers and every network weight staged once per workgroup in workgroup memory. The
//! layer-by-layer path (`field`) writes each layer's activations to device memory and reads
//! them back in the next kernel; here nothing between a sample's position and its density
//! and colour leaves the thread. Rendering, evaluation, meshes and density queries can take
//! it (they need no backward; `Gpu::fused_field` says whether they do); training keeps the
//! layer-by-layer path, whose activations the backward reads.
//!
//! The shapes (levels, hidden width, geometry features) are compile-time constants of the
//! kernel: each layer's outputs unroll into registers. The kernel runs
//! where the networks' weights fit in one workgroup's memory (37 KB for the default
//! field); [`FusedShape::fits`] says when they do.

use cubecl::prelude::*;
use cubecl::server::Handle;

use super::device::Gpu;
use super::harmonics::sh4;
use super::hash_grid::{encode_level, GpuHashGrid, LEVEL_WORDS};
use super::launch::grid;
use crate::encoding::hash_grid::FEATURES;
use crate::encoding::spherical_harmonics::SH_DIMS;
use crate::field::fast::LOG_SIGMA_MAX;

/// Threads (samples) per workgroup: the weights are staged once for this many samples.
const GROUP: u32 = 128;

/// `y = x W` for one sample, through a ReLU when `relu` is set; `W` (`n_in x n_out`,
/// row-major) sits at `off` in `w`. The loop over inputs stays a loop (each input read once,
/// from the thread's own memory); the outputs unroll into registers, which read one weight
/// row side by side.
#[cube]
fn dense(
    x: &Array<f32>,
    y: &mut Array<f32>,
    w: &[f32],
    #[comptime] off: usize,
    #[comptime] n_in: usize,
    #[comptime] n_out: usize,
    #[comptime] relu: bool,
) {
    let mut acc = Array::<f32>::new(n_out);
    #[unroll]
    for o in 0..n_out {
        acc[o] = 0.0;
    }
    for i in 0..n_in {
        let xi = x[i];
        let row = off + i * n_out;
        #[unroll]
        for o in 0..n_out {
            acc[o] += xi * w[row + o];
        }
    }
    #[unroll]
    for o in 0..n_out {
        if relu {
            y[o] = f32::max(acc[o], 0.0);
        } else {
            y[o] = acc[o];
        }
    }
}

/// Copies `len` floats from `src[from..]` to `dst[to..]`, the workgroup's threads in turn.
#[cube]
fn stage(src: &[f32], dst: &mut [f32], from: u32, #[comptime] to: usize, #[comptime] len: usize) {
    let mut k = UNIT_POS as usize;
    while k < len {
        dst[to + k] = src[from as usize + k];
        k += CUBE_DIM as usize;
    }
}

/// Where the five layers' weights sit in the parameter vector: density 0, 1, colour 0, 1, 2.
#[derive(CubeType, CubeLaunch, Clone, Copy)]
struct LayerOffsets {
    d0: u32,
    d1: u32,
    c0: u32,
    c1: u32,
    c2: u32,
}

/// Density (and, when `colour` is set, colour) of the first `n` samples: world `positions`
/// and unit view `dirs` (`n x 3` each) into `sigma` (`n`) and `rgb` (`n x 3`).
#[cube(launch_unchecked)]
#[allow(clippy::too_many_arguments)]
fn field_infer(
    params: &[f32],
    levels: &[u32],
    positions: &[f32],
    dirs: &[f32],
    sigma: &mut [f32],
    rgb: &mut [f32],
    at: LayerOffsets,
    n: u32,
    bound: f32,
    log_max: f32,
    #[comptime] n_levels: usize,
    #[comptime] hidden: usize,
    #[comptime] geo: usize,
    #[comptime] colour: bool,
) {
    let e = n_levels * 2;
    let ci = 16 + geo - 1;
    // Workgroup-memory layout: density 0, 1, colour 0, 1, 2, back to back.
    let w_d1 = e * hidden;
    let w_c0 = w_d1 + hidden * geo;
    let w_c1 = w_c0 + ci * hidden;
    let w_c2 = w_c1 + hidden * hidden;
    let total = w_c2 + hidden * 3;
    let mut w = Shared::<[f32]>::new_slice(total);
    stage(params, &mut w, at.d0, 0usize, e * hidden);
    stage(params, &mut w, at.d1, w_d1, hidden * geo);
    if colour {
        stage(params, &mut w, at.c0, w_c0, ci * hidden);
        stage(params, &mut w, at.c1, w_c1, hidden * hidden);
        stage(params, &mut w, at.c2, w_c2, hidden * 3);
    }
    sync_cube();

    let s = ABSOLUTE_POS;
    if s < n as usize {
        let scale = 0.5 / bound;
        let ux = (positions[3 * s] + bound) * scale;
        let uy = (positions[3 * s + 1] + bound) * scale;
        let uz = (positions[3 * s + 2] + bound) * scale;
        let mut enc = Array::<f32>::new(e);
        for l in 0..n_levels {
            let (f0, f1) = encode_level(params, levels, l, ux, uy, uz);
            enc[2 * l] = f0;
            enc[2 * l + 1] = f1;
        }
        let mut h = Array::<f32>::new(hidden);
        dense(&enc, &mut h, &w, 0usize, e, hidden, true);
        let mut g = Array::<f32>::new(geo);
        dense(&h, &mut g, &w, w_d1, hidden, geo, false);
        sigma[s] = f32::exp(f32::min(g[0], log_max));
        if colour {
            let mut c_in = Array::<f32>::new(ci);
            let sh = sh4(dirs[3 * s], dirs[3 * s + 1], dirs[3 * s + 2]);
            #[unroll]
            for k in 0..16usize {
                c_in[k] = sh[k];
            }
            #[unroll]
            for j in 1..geo {
                c_in[15 + j] = g[j];
            }
            let mut c1 = Array::<f32>::new(hidden);
            dense(&c_in, &mut c1, &w, w_c0, ci, hidden, true);
            let mut c2 = Array::<f32>::new(hidden);
            dense(&c1, &mut c2, &w, w_c1, hidden, hidden, true);
            let mut out = Array::<f32>::new(3usize);
            dense(&c2, &mut out, &w, w_c2, hidden, 3usize, false);
            #[unroll]
            for c in 0..3usize {
                rgb[3 * s + c] = 1.0 / (1.0 + f32::exp(-out[c]));
            }
        }
    }
}

/// The shapes the fused kernel is compiled for, and where its weights sit.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FusedShape {
    pub levels: usize,
    pub hidden: usize,
    pub geo: usize,
    /// Offsets of the five layers' weights (density 0, 1, colour 0, 1, 2).
    pub weights: [usize; 5],
    /// Half the side of the field's box (positions map to the unit cube through it).
    pub bound: f32,
}

impl FusedShape {
    /// Floats of workgroup memory the colour kernel stages.
    pub fn staged_floats(&self) -> usize {
        let (e, w, g) = (self.levels * FEATURES, self.hidden, self.geo);
        let ci = SH_DIMS + g - 1;
        e * w + w * g + ci * w + w * w + w * 3
    }

    /// Whether the weights fit in one workgroup's memory on `gpu`.
    pub fn fits(&self, gpu: &Gpu) -> bool {
        let limit = gpu.client.properties().hardware.max_shared_memory_size;
        self.staged_floats() * 4 <= limit
    }

    /// Densities (`n`) and, when `colour` is set, colours (`n x 3`; an empty buffer
    /// otherwise) of `n` world `positions` seen along unit `dirs` (`n x 3` each; ignored
    /// without `colour`), with the parameter vector `params` (`n_params` floats).
    #[allow(clippy::too_many_arguments)]
    pub fn infer(
        &self,
        gpu: &Gpu,
        hash: &GpuHashGrid,
        params: &Handle,
        n_params: usize,
        positions: &Handle,
        dirs: Option<&Handle>,
        n: usize,
    ) -> (Handle, Handle) {
        let sigma = gpu.floats(n);
        let colour = dirs.is_some();
        let rgb = gpu.floats(if colour { n * 3 } else { 0 });
        if n == 0 {
            return (sigma, rgb);
        }
        let [d0, d1, c0, c1, c2] = self.weights.map(|o| o as u32);
        let at = LayerOffsetsLaunch::new(d0, d1, c0, c1, c2);
        let (count, dim) = grid(n, GROUP);
        let dirs = dirs.unwrap_or(positions);
        // SAFETY: `positions` and `dirs` hold `3n` floats, `sigma` `n` and `rgb` `3n` when
        // `colour` is set (it is not written otherwise); the parameter vector holds every
        // layer at its offset and every hash level's table; the kernel reads and writes
        // sample slots below `n` only, and stages at most the workgroup memory `fits`
        // checked.
        unsafe {
            field_infer::launch_unchecked(
                &gpu.client,
                count,
                dim,
                BufferArg::from_raw_parts(params.clone(), n_params),
                BufferArg::from_raw_parts(hash.levels.clone(), hash.n_levels * LEVEL_WORDS),
                BufferArg::from_raw_parts(positions.clone(), n * 3),
                BufferArg::from_raw_parts(dirs.clone(), n * 3),
                BufferArg::from_raw_parts(sigma.clone(), n),
                BufferArg::from_raw_parts(rgb.clone(), if colour { n * 3 } else { 1 }),
                at,
                n as u32,
                self.bound,
                LOG_SIGMA_MAX,
                self.levels,
                self.hidden,
                self.geo,
                colour,
            );
        }
        (sigma, rgb)
    }
}

#[cfg(test)]
mod tests {
    use crate::engine::gpu::codes::SampleCodes;
    use crate::engine::gpu::device::{test_gpu, worst, Gpu};
    use crate::engine::gpu::field::tests::small_field;
    use crate::engine::gpu::field::{DeviceInput, GpuFastField};
    use crate::field::fast::FastWorkspace;
    use crate::field::{FastField, FastFieldConfig};
    use crate::rng::Rng;
    use crate::stage::{Field, FieldInput};

    /// The fused kernel against the CPU field on `n` random samples (positions a little
    /// past the box, unit directions) with weights drawn from `±scale`: densities within
    /// `1e-4` and colours within `1e-5` relative to `1 + |value|`, and the density-only
    /// kernel equal to the colour kernel's densities.
    fn matches_the_cpu_field(gpu: &Gpu, field: &FastField, scale: f32, n: usize) {
        let gpu = &fused(gpu);
        let device_field = GpuFastField::new(gpu, field);
        assert!(
            device_field.is_fused(),
            "the fused kernel does not run here"
        );
        let mut rng = Rng::new(5);
        let params: Vec<f32> = (0..field.num_params())
            .map(|_| rng.range(-scale, scale))
            .collect();
        let bound = field.config.bound;
        let pos: Vec<f32> = (0..n * 3)
            .map(|_| rng.range(-1.05 * bound, 1.05 * bound))
            .collect();
        let dirs = rng.unit_directions(n);
        let mut ws = FastWorkspace::default();
        let input = FieldInput {
            positions: &pos,
            dirs: &dirs,
            samples_per_dir: 1,
            appearance: &[],
            footprints: &[],
            variances: &[],
            times: &[],
        };
        let want = field.forward(&params, input, &mut ws);
        let p = gpu.upload(&params);
        let codes = SampleCodes::all(gpu, crate::stage::MEAN_APPEARANCE);
        let (pos_h, dirs_h) = (gpu.upload(&pos), gpu.upload(&dirs));
        let input = DeviceInput {
            positions: &pos_h,
            dirs: &dirs_h,
            codes: &codes,
            footprints: None,
            moments: crate::engine::gpu::field::DeviceMoments::Any,
            n,
        };
        let (sigma, rgb) = device_field.infer(gpu, &p, &input);
        let sigma = gpu.read(&sigma, n).expect("read");
        let rgb = gpu.read(&rgb, n * 3).expect("read");
        let (e_sigma, e_rgb) = (worst(&sigma, want.sigma), worst(&rgb, want.rgb));
        eprintln!("worst difference: sigma {e_sigma:.1e}, rgb {e_rgb:.1e}");
        assert!(e_sigma < 1e-4, "sigma {e_sigma}");
        assert!(e_rgb < 1e-5, "rgb {e_rgb}");
        // Something to compare: densities over two orders of magnitude.
        let (lo, hi) = want
            .sigma
            .iter()
            .fold((f32::MAX, 0.0f32), |(lo, hi), &s| (lo.min(s), hi.max(s)));
        assert!(hi > 100.0 * lo, "densities from {lo} to {hi} only");
        let any = crate::engine::gpu::field::DeviceMoments::Any;
        let alone = device_field.infer_density(gpu, &p, &gpu.upload(&pos), any, n);
        assert_eq!(gpu.read(&alone, n).expect("read"), sigma);
    }

    /// `gpu` with the fused path switched on.
    fn fused(gpu: &Gpu) -> Gpu {
        Gpu {
            fused_field: true,
            ..gpu.clone()
        }
    }

    /// A small field over 1000 samples: several workgroups, the last one partly empty.
    #[test]
    fn the_fused_kernel_matches_the_cpu_field() {
        let Some(gpu) = test_gpu() else { return };
        matches_the_cpu_field(&gpu, &small_field(), 1.5, 1000);
    }

    /// The default field's shapes (16 levels, 64 wide, 16 geometry features: 37 KB of
    /// staged weights), where the adapter's workgroup memory holds them.
    #[test]
    fn the_fused_kernel_matches_the_cpu_field_at_the_default_size() {
        let Some(gpu) = test_gpu() else { return };
        let field = FastField::new(FastFieldConfig {
            grid: crate::encoding::HashGridConfig {
                log2_table_size: 12,
                ..FastFieldConfig::default().grid
            },
            ..FastFieldConfig::default()
        });
        let device_field = GpuFastField::new(&fused(&gpu), &field);
        if !device_field.is_fused() {
            eprintln!(
                "skipping: the default field's weights do not fit this adapter's workgroup memory"
            );
            return;
        }
        // Weights in [-1, 1]: densities over six orders of magnitude at this depth and
        // width (in [-0.3, 0.3] they stay within 0.8 to 1.2).
        matches_the_cpu_field(&gpu, &field, 1.0, 300);
    }

    /// The switch (`NERF_GPU_FIELD`) chooses the path.
    #[test]
    fn the_switch_chooses_the_path() {
        let Some(gpu) = test_gpu() else { return };
        let layers = Gpu {
            fused_field: false,
            ..gpu.clone()
        };
        assert!(!GpuFastField::new(&layers, &small_field()).is_fused());
        assert!(GpuFastField::new(&fused(&gpu), &small_field()).is_fused());
    }
}
