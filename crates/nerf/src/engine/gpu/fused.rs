//! The fast field's inference in one kernel: one thread per sample runs the hash encoding
//! (its levels weighed by the sample's footprint in an anti-aliased field), a moving
//! field's space-time encoding, the density network, the spherical harmonics, the photo's
//! appearance code and the colour network, its activations in
//! registers and every network weight staged once per workgroup in workgroup memory. The
//! layer-by-layer path (`field`) writes each layer's activations to device memory and reads
//! them back in the next kernel; here nothing between a sample's position and its density
//! and colour leaves the thread. Rendering, evaluation, meshes and density queries can take
//! it (they need no backward; `Gpu::fused_field` says whether they do); training keeps the
//! layer-by-layer path, whose activations the backward reads.
//!
//! The shapes (levels, hidden width, geometry features, and which of those inputs the field
//! has) are compile-time constants of the kernel: each layer's outputs unroll into
//! registers, and a field without codes or motion compiles without their reads. The kernel
//! runs where the networks' weights fit in one workgroup's memory (37 KB for the default
//! field, 4 KB more for 16-wide codes or a moving field's first layer);
//! [`FusedShape::fits`] says when they do.

use cubecl::prelude::*;
use cubecl::server::Handle;

use super::antialias::level_weight;
use super::codes::{GpuCodes, SampleCodes};
use super::device::Gpu;
use super::harmonics::sh4;
use super::hash_grid::{encode_level, GpuHashGrid, LEVEL_WORDS};
use super::launch::grid;
use super::space_time_grid::{
    encode_level as encode_moving, moment_of_point, GpuSpaceTimeGrid, Moments,
    LEVEL_WORDS as ST_WORDS,
};
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

/// Where the layers' weights sit in the parameter vector: density 0, 1, colour 0, 1, 2,
/// and the space-time features' first-layer weights (moving fields; 0 otherwise).
#[derive(CubeType, CubeLaunch, Clone, Copy)]
pub(super) struct LayerOffsets {
    d0: u32,
    d1: u32,
    c0: u32,
    c1: u32,
    c2: u32,
    motion: u32,
}

/// What the networks take besides the hash grid's features, read where the field has it.
#[derive(CubeType, CubeLaunch, Clone, Copy)]
struct Feeds {
    /// Anti-aliasing: 1 where `footprints` holds a footprint a sample, 0 where every sample
    /// has the `reference` one; `to_unit` takes them into the unit cube's units.
    has_footprints: u32,
    reference: f32,
    to_unit: f32,
    /// Appearance codes: their offset in the parameter vector, how many photos have one,
    /// and 1 where `code_index` holds an index a sample (0: one for every sample).
    code_off: u32,
    images: u32,
    per_sample_codes: u32,
    /// Moving fields: `Moments` as a number (0 each sample's from `times`, 1 all at
    /// `times[0]`, 2 drawn from the point).
    moments: u32,
}

/// Where each layer's weights sit in a kernel's workgroup memory, back to back: density 0
/// at 0, then the moving features' first-layer weights, density 1, colour 0, 1, 2; and the
/// floats in all. One layout for the forward and the backward kernels.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) struct Staged {
    pub motion: usize,
    pub d1: usize,
    pub c0: usize,
    pub c1: usize,
    pub c2: usize,
    pub total: usize,
}

impl Staged {
    /// For `e` hash features, `md` space-time features, a colour input `ci` wide, layers
    /// `hidden` wide and `geo` geometry features.
    pub(super) fn new(e: usize, md: usize, ci: usize, hidden: usize, geo: usize) -> Self {
        let motion = e * hidden;
        let d1 = motion + md * hidden;
        let c0 = d1 + hidden * geo;
        let c1 = c0 + ci * hidden;
        let c2 = c1 + hidden * hidden;
        Staged {
            motion,
            d1,
            c0,
            c1,
            c2,
            total: c2 + hidden * 3,
        }
    }
}

/// `len` values of `v` into `out[row * len..]`.
#[cube]
fn keep_row(v: &Array<f32>, out: &mut [f32], row: usize, #[comptime] len: usize) {
    #[unroll]
    for k in 0..len {
        out[row * len + k] = v[k];
    }
}

/// Density (and, when `colour` is set, colour) of the first `n` samples: world `positions`
/// and unit view `dirs` (`n x 3` each) into `sigma` (`n`) and `rgb` (`n x 3`). The field's
/// optional inputs are compiled in by their sizes: anti-aliased level weights
/// (`antialias`), an appearance code of `code_dims` values, a space-time grid of
/// `motion_levels` levels, and the first `harmonics` of the view direction's 16. With
/// `keep` (training, with `colour`), what the backward reads goes into the `kept_` buffers,
/// each as the layer-by-layer path keeps it (`field::Activations`): unit positions, the
/// (weighed) hash features, the level weights, the space-time points and features, the
/// density network's hidden layer and outputs, the colour network's input and hidden
/// layers (one float each, unwritten, where the kernel does not keep them).
#[cube(launch_unchecked)]
#[allow(clippy::too_many_arguments, unused_assignments)]
fn field_fwd(
    params: &[f32],
    levels: &[u32],
    positions: &[f32],
    dirs: &[f32],
    footprints: &[f32],
    code_index: &[u32],
    mean_code: &[f32],
    motion_grid: &[u32],
    times: &[f32],
    sigma: &mut [f32],
    rgb: &mut [f32],
    kept_unit: &mut [f32],
    kept_enc: &mut [f32],
    kept_level_weights: &mut [f32],
    kept_points: &mut [f32],
    kept_motion: &mut [f32],
    kept_h: &mut [f32],
    kept_geo: &mut [f32],
    kept_colour_in: &mut [f32],
    kept_c1: &mut [f32],
    kept_c2: &mut [f32],
    at: LayerOffsets,
    feeds: Feeds,
    n: u32,
    bound: f32,
    log_max: f32,
    #[comptime] n_levels: usize,
    #[comptime] hidden: usize,
    #[comptime] geo: usize,
    #[comptime] colour: bool,
    #[comptime] harmonics: usize,
    #[comptime] antialias: bool,
    #[comptime] code_dims: usize,
    #[comptime] motion_levels: usize,
    #[comptime] keep: bool,
) {
    let e = n_levels * 2;
    let md = motion_levels * 2;
    let ci = 15 + geo + code_dims;
    let at_w = comptime!(Staged::new(e, md, ci, hidden, geo));
    let mut w = Shared::<[f32]>::new_slice(at_w.total);
    stage_weights(params, &mut w, at, e, md, ci, hidden, geo, colour);

    let s = ABSOLUTE_POS;
    if s < n as usize {
        let scale = 0.5 / bound;
        let ux = (positions[3 * s] + bound) * scale;
        let uy = (positions[3 * s + 1] + bound) * scale;
        let uz = (positions[3 * s + 2] + bound) * scale;
        if keep {
            kept_unit[3 * s] = ux;
            kept_unit[3 * s + 1] = uy;
            kept_unit[3 * s + 2] = uz;
        }
        let mut footprint = 0.0f32;
        if antialias {
            footprint = select(
                feeds.has_footprints == 1,
                footprints[s % footprints.len()],
                feeds.reference,
            ) * feeds.to_unit;
        }
        let mut enc = Array::<f32>::new(e);
        for l in 0..n_levels {
            let (f0, f1) = encode_level(params, levels, l, ux, uy, uz);
            let mut weight = 1.0f32;
            if antialias {
                weight = level_weight(levels, l, footprint);
                if keep {
                    kept_level_weights[s * n_levels + l] = weight;
                }
            }
            enc[2 * l] = f0 * weight;
            enc[2 * l + 1] = f1 * weight;
        }
        if keep {
            keep_row(&enc, kept_enc, s, e);
        }
        let mut h = Array::<f32>::new(hidden);
        if motion_levels > 0 {
            // The still and the moving features' products summed before the ReLU.
            dense(&enc, &mut h, &w, 0usize, e, hidden, false);
            let mut t = 0.0f32;
            if feeds.moments == 0 {
                t = times[s];
            } else if feeds.moments == 1 {
                t = times[0];
            } else {
                t = moment_of_point(ux, uy, uz);
            }
            let mut m = Array::<f32>::new(md);
            for l in 0..motion_levels {
                let (f0, f1) = encode_moving(params, motion_grid, l, ux, uy, uz, t);
                m[2 * l] = f0;
                m[2 * l + 1] = f1;
            }
            if keep {
                kept_points[4 * s] = ux;
                kept_points[4 * s + 1] = uy;
                kept_points[4 * s + 2] = uz;
                kept_points[4 * s + 3] = t;
                keep_row(&m, kept_motion, s, md);
            }
            let mut hm = Array::<f32>::new(hidden);
            dense(&m, &mut hm, &w, at_w.motion, md, hidden, false);
            #[unroll]
            for o in 0..hidden {
                h[o] = f32::max(h[o] + hm[o], 0.0);
            }
        } else {
            dense(&enc, &mut h, &w, 0usize, e, hidden, true);
        }
        let mut g = Array::<f32>::new(geo);
        dense(&h, &mut g, &w, at_w.d1, hidden, geo, false);
        sigma[s] = f32::exp(f32::min(g[0], log_max));
        if keep {
            keep_row(&h, kept_h, s, hidden);
            keep_row(&g, kept_geo, s, geo);
        }
        if colour {
            let mut c_in = Array::<f32>::new(ci);
            let sh = sh4(dirs[3 * s], dirs[3 * s + 1], dirs[3 * s + 2]);
            #[unroll]
            for k in 0..harmonics {
                c_in[k] = sh[k];
            }
            #[unroll]
            for k in harmonics..16usize {
                c_in[k] = 0.0;
            }
            #[unroll]
            for j in 1..geo {
                c_in[15 + j] = g[j];
            }
            if code_dims > 0 {
                let i = code_index[select(feeds.per_sample_codes == 1, s, 0usize)];
                let images = feeds.images;
                let row = feeds.code_off as usize + (i % images) as usize * code_dims;
                #[unroll]
                for j in 0..code_dims {
                    c_in[15 + geo + j] = select(i < images, params[row + j], mean_code[j]);
                }
            }
            let mut c1 = Array::<f32>::new(hidden);
            dense(&c_in, &mut c1, &w, at_w.c0, ci, hidden, true);
            let mut c2 = Array::<f32>::new(hidden);
            dense(&c1, &mut c2, &w, at_w.c1, hidden, hidden, true);
            let mut out = Array::<f32>::new(3usize);
            dense(&c2, &mut out, &w, at_w.c2, hidden, 3usize, false);
            #[unroll]
            for c in 0..3usize {
                rgb[3 * s + c] = 1.0 / (1.0 + f32::exp(-out[c]));
            }
            if keep {
                keep_row(&c_in, kept_colour_in, s, ci);
                keep_row(&c1, kept_c1, s, hidden);
                keep_row(&c2, kept_c2, s, hidden);
            }
        }
    }
}

/// Stages the layers' weights into workgroup memory (layout: density 0, the moving
/// features' weights, density 1, colour 0, 1, 2, back to back; the colour network's only
/// with `colour`), the workgroup's threads in turn, and waits for all of them.
#[cube]
#[allow(clippy::too_many_arguments)]
pub(super) fn stage_weights(
    params: &[f32],
    w: &mut [f32],
    at: LayerOffsets,
    #[comptime] e: usize,
    #[comptime] md: usize,
    #[comptime] ci: usize,
    #[comptime] hidden: usize,
    #[comptime] geo: usize,
    #[comptime] colour: bool,
) {
    let to = comptime!(Staged::new(e, md, ci, hidden, geo));
    stage(params, w, at.d0, 0usize, e * hidden);
    if md > 0 {
        stage(params, w, at.motion, to.motion, md * hidden);
    }
    stage(params, w, at.d1, to.d1, hidden * geo);
    if colour {
        stage(params, w, at.c0, to.c0, ci * hidden);
        stage(params, w, at.c1, to.c1, hidden * hidden);
        stage(params, w, at.c2, to.c2, hidden * 3);
    }
    sync_cube();
}

/// A moving field's space-time grid, as the fused kernel reads it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FusedMotion {
    pub levels: usize,
    /// Offset of its first-layer weights (`levels x 2` by the hidden width).
    pub weight: usize,
}

/// The shapes the fused kernel is compiled for, and where its weights sit.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FusedShape {
    pub levels: usize,
    pub hidden: usize,
    pub geo: usize,
    /// How many of the view direction's 16 harmonics the colour network is fed.
    pub harmonics: usize,
    /// Offsets of the five layers' weights (density 0, 1, colour 0, 1, 2).
    pub weights: [usize; 5],
    /// Half the side of the field's box (positions map to the unit cube through it).
    pub bound: f32,
    /// Anti-aliased fields: the footprint of samples that carry none.
    pub antialias: Option<f32>,
    /// Per-photo appearance codes.
    pub codes: Option<GpuCodes>,
    /// Moving fields.
    pub motion: Option<FusedMotion>,
}

/// What one fused call evaluates beyond positions: the samples' directions (colour), their
/// footprints (anti-aliased fields; `None`: the reference footprint), codes and moments
/// (fields that read them).
pub struct FusedInput<'a> {
    pub dirs: Option<&'a Handle>,
    pub footprints: Option<&'a Handle>,
    pub codes: &'a SampleCodes,
    pub times: (&'a Handle, Moments),
}

impl FusedShape {
    /// The appearance code's width (0 without codes).
    fn code_dims(&self) -> usize {
        self.codes.map_or(0, |c| c.dims)
    }

    /// Floats of workgroup memory the colour kernel stages.
    pub fn staged_floats(&self) -> usize {
        let (e, md, ci) = self.widths();
        Staged::new(e, md, ci, self.hidden, self.geo).total
    }

    /// Whether the weights fit in one workgroup's memory on `gpu`.
    pub fn fits(&self, gpu: &Gpu) -> bool {
        let limit = gpu.client.properties().hardware.max_shared_memory_size;
        self.staged_floats() * 4 <= limit
    }

    /// Densities (`n`) and, where `input.dirs` is given, colours (`n x 3`; an empty buffer
    /// otherwise) of `n` world `positions`, with the parameter vector `params` (`n_params`
    /// floats), the field's hash grid and, for a moving field, its space-time grid.
    #[allow(clippy::too_many_arguments)]
    pub fn infer(
        &self,
        gpu: &Gpu,
        grids: (&GpuHashGrid, Option<&GpuSpaceTimeGrid>),
        params: &Handle,
        n_params: usize,
        positions: &Handle,
        input: &FusedInput,
        n: usize,
    ) -> (Handle, Handle) {
        self.run(gpu, grids, (params, n_params), positions, input, None, n)
    }

    /// A training forward: [`infer`](Self::infer) with colours (`input.dirs` given), also
    /// writing into `kept` what the backward reads.
    #[allow(clippy::too_many_arguments)]
    pub fn forward(
        &self,
        gpu: &Gpu,
        grids: (&GpuHashGrid, Option<&GpuSpaceTimeGrid>),
        params: &Handle,
        n_params: usize,
        positions: &Handle,
        input: &FusedInput,
        kept: &KeptBuffers,
        n: usize,
    ) -> (Handle, Handle) {
        assert!(input.dirs.is_some(), "a training forward makes colours");
        self.run(
            gpu,
            grids,
            (params, n_params),
            positions,
            input,
            Some(kept),
            n,
        )
    }

    #[allow(clippy::too_many_arguments)]
    fn run(
        &self,
        gpu: &Gpu,
        (hash, moving): (&GpuHashGrid, Option<&GpuSpaceTimeGrid>),
        (params, n_params): (&Handle, usize),
        positions: &Handle,
        input: &FusedInput,
        kept: Option<&KeptBuffers>,
        n: usize,
    ) -> (Handle, Handle) {
        let sigma = gpu.floats(n);
        let colour = input.dirs.is_some();
        let rgb = gpu.floats(if colour { n * 3 } else { 0 });
        if n == 0 {
            return (sigma, rgb);
        }
        let at = self.offsets();
        let (code_off, images) = self.codes.map_or((0, 0), |c| (c.offset, c.images));
        let feeds = FeedsLaunch::new(
            u32::from(input.footprints.is_some()),
            self.antialias.unwrap_or(0.0),
            0.5 / self.bound,
            code_off as u32,
            images as u32,
            u32::from(input.codes.per_sample),
            input.times.1 as u32,
        );
        let one = gpu.floats(1);
        let mean = match &self.codes {
            Some(c) => c.mean(gpu, params, n_params),
            None => one.clone(),
        };
        let footprints = input.footprints.map_or((&one, 1), |f| (f, n));
        let times_len = match input.times.1 {
            Moments::Each => n,
            Moments::At | Moments::Any => 1,
        };
        let no_grid = gpu.zeros_u32(1);
        let motion_grid = moving.map_or((&no_grid, 1), |g| (&g.levels, g.n_levels * ST_WORDS));
        let (count, dim) = grid(n, GROUP);
        let dirs = input.dirs.unwrap_or(positions);
        let (e, md, ci) = self.widths();
        let rows = |h: Option<&Handle>, width: usize| {
            // SAFETY: a kept buffer holds `n` rows of its width; the stand-in one float,
            // which the kernel does not write.
            unsafe {
                match h {
                    Some(h) => BufferArg::from_raw_parts(h.clone(), n * width),
                    None => BufferArg::from_raw_parts(one.clone(), 1),
                }
            }
        };
        let k = kept;
        // SAFETY: `positions` and `dirs` hold `3n` floats, `sigma` `n` and `rgb` `3n` when
        // `colour` is set (it is not written otherwise); the parameter vector holds every
        // layer, code and table at its offset; `footprints` and `times` hold one float a
        // sample where their flags say so (else one, read at index 0 only), the code
        // indices one or `n` as `per_sample` says, `mean` the code's width where the field
        // has codes; the kept buffers hold `n` rows where `keep` writes them; the kernel
        // reads and writes sample slots below `n` only, and stages at most the workgroup
        // memory `fits` checked.
        unsafe {
            field_fwd::launch_unchecked(
                &gpu.client,
                count,
                dim,
                BufferArg::from_raw_parts(params.clone(), n_params),
                BufferArg::from_raw_parts(hash.levels.clone(), hash.n_levels * LEVEL_WORDS),
                BufferArg::from_raw_parts(positions.clone(), n * 3),
                BufferArg::from_raw_parts(dirs.clone(), n * 3),
                BufferArg::from_raw_parts(footprints.0.clone(), footprints.1),
                BufferArg::from_raw_parts(input.codes.index.clone(), input.codes.len(n)),
                BufferArg::from_raw_parts(mean.clone(), self.code_dims().max(1)),
                BufferArg::from_raw_parts(motion_grid.0.clone(), motion_grid.1),
                BufferArg::from_raw_parts(input.times.0.clone(), times_len),
                BufferArg::from_raw_parts(sigma.clone(), n),
                BufferArg::from_raw_parts(rgb.clone(), if colour { n * 3 } else { 1 }),
                rows(k.map(|k| &k.unit), 3),
                rows(k.map(|k| &k.enc), e),
                rows(k.and_then(|k| k.level_weights.as_ref()), self.levels),
                rows(k.and_then(|k| k.motion.as_ref().map(|m| &m.0)), 4),
                rows(k.and_then(|k| k.motion.as_ref().map(|m| &m.1)), md),
                rows(k.map(|k| &k.h), self.hidden),
                rows(k.map(|k| &k.geo), self.geo),
                rows(k.map(|k| &k.colour_in), ci),
                rows(k.map(|k| &k.c1), self.hidden),
                rows(k.map(|k| &k.c2), self.hidden),
                at,
                feeds,
                n as u32,
                self.bound,
                LOG_SIGMA_MAX,
                self.levels,
                self.hidden,
                self.geo,
                colour,
                self.harmonics,
                self.antialias.is_some(),
                self.code_dims(),
                self.motion.map_or(0, |m| m.levels),
                kept.is_some(),
            );
        }
        (sigma, rgb)
    }

    /// Where the layers' weights sit, for the kernels.
    pub(super) fn offsets(&self) -> LayerOffsetsLaunch {
        let [d0, d1, c0, c1, c2] = self.weights.map(|o| o as u32);
        let motion_weight = self.motion.map_or(0, |m| m.weight as u32);
        LayerOffsetsLaunch::new(d0, d1, c0, c1, c2, motion_weight)
    }

    /// The widths of the hash features, the space-time features and the colour input.
    pub(super) fn widths(&self) -> (usize, usize, usize) {
        let md = self.motion.map_or(0, |m| m.levels * FEATURES);
        let ci = SH_DIMS + self.geo - 1 + self.code_dims();
        (self.levels * FEATURES, md, ci)
    }
}

/// The buffers a training forward fills for its backward, laid out as
/// `field::Activations` holds them (each `n` rows).
pub struct KeptBuffers {
    pub unit: Handle,
    pub enc: Handle,
    /// Anti-aliased fields.
    pub level_weights: Option<Handle>,
    /// Moving fields: the space-time points and their features.
    pub motion: Option<(Handle, Handle)>,
    pub h: Handle,
    pub geo: Handle,
    pub colour_in: Handle,
    pub c1: Handle,
    pub c2: Handle,
}

#[cfg(test)]
mod tests {
    use crate::engine::gpu::codes::SampleCodes;
    use crate::engine::gpu::device::{test_gpu, worst, Gpu};
    use crate::engine::gpu::device_field::{DeviceField, DeviceInput, DeviceMoments};
    use crate::engine::gpu::field::tests::{narrow, small_field, small_field_with_every_input};
    use crate::engine::gpu::field::GpuFastField;
    use crate::field::fast::{Antialias, FastWorkspace};
    use crate::field::{FastField, FastFieldConfig};
    use crate::rng::Rng;
    use crate::stage::{Field, FieldInput, MEAN_APPEARANCE};

    /// What a check feeds the field besides positions and directions.
    #[derive(Default)]
    struct Feed {
        /// A footprint a sample (anti-aliased fields), else the reference one.
        footprints: bool,
        /// Each sample's code index (fields with codes), else the mean code.
        codes: Option<Vec<u32>>,
        /// A moment a sample (moving fields), else moment 0.
        moving: bool,
    }

    /// The fused kernel against the CPU field and against the layer-by-layer path on the
    /// same device, on `n` random samples (positions a little past the box, unit
    /// directions) with weights drawn from `±scale`: densities within `1e-4` and colours
    /// within `1e-5` relative to `1 + |value|`; the density-only kernel equal to the colour
    /// kernel's densities, and (at one moment, at any moment) to the layers' densities.
    fn matches_the_cpu_field(gpu: &Gpu, field: &FastField, scale: f32, n: usize, feed: &Feed) {
        let (fast, layers) = (fused(gpu), layered(gpu));
        let device_field = GpuFastField::new(&fast, field);
        assert!(
            device_field.is_fused(),
            "the fused kernel does not run here"
        );
        let layer_field = GpuFastField::new(&layers, field);
        assert!(!layer_field.is_fused());
        let mut rng = Rng::new(5);
        let params: Vec<f32> = (0..field.num_params())
            .map(|_| rng.range(-scale, scale))
            .collect();
        let bound = field.config.bound;
        let pos: Vec<f32> = (0..n * 3)
            .map(|_| rng.range(-1.05 * bound, 1.05 * bound))
            .collect();
        let dirs = rng.unit_directions(n);
        let fp: Vec<f32> = match feed.footprints {
            true => (0..n).map(|_| 10f32.powf(rng.range(-3.5, -0.5))).collect(),
            false => Vec::new(),
        };
        let times: Vec<f32> = match feed.moving {
            true => (0..n).map(|_| rng.uniform()).collect(),
            false => Vec::new(),
        };
        let indices = feed.codes.clone().unwrap_or_default();
        let mut ws = FastWorkspace::default();
        let input = FieldInput {
            positions: &pos,
            dirs: &dirs,
            samples_per_dir: 1,
            appearance: &indices,
            footprints: &fp,
            variances: &[],
            times: &times,
        };
        let want = field.forward(&params, input, &mut ws);
        let p = fast.upload(&params);
        let codes = match &feed.codes {
            // All the same: the one-index form the renderer passes.
            Some(a) if a.iter().all(|&i| i == a[0]) => SampleCodes::all(&fast, a[0]),
            Some(a) => SampleCodes {
                index: fast.upload_u32(a),
                per_sample: true,
            },
            None => SampleCodes::all(&fast, MEAN_APPEARANCE),
        };
        let (pos_h, dirs_h) = (fast.upload(&pos), fast.upload(&dirs));
        let fp_h = feed.footprints.then(|| fast.upload(&fp));
        let times_h = fast.upload(&times);
        let input = DeviceInput {
            positions: &pos_h,
            dirs: &dirs_h,
            codes: &codes,
            footprints: fp_h.as_ref(),
            variances: None,
            moments: match feed.moving {
                true => DeviceMoments::Each(&times_h),
                false => DeviceMoments::At(0.0),
            },
            n,
        };
        let (sigma, rgb) = device_field.infer(&fast, &p, &input);
        let sigma = fast.read(&sigma, n).expect("read");
        let rgb = fast.read(&rgb, n * 3).expect("read");
        let (e_sigma, e_rgb) = (worst(&sigma, want.sigma), worst(&rgb, want.rgb));
        let (l_sigma, l_rgb) = layer_field.infer(&layers, &p, &input);
        let l_sigma = layers.read(&l_sigma, n).expect("read");
        let l_rgb = layers.read(&l_rgb, n * 3).expect("read");
        let (f_sigma, f_rgb) = (worst(&sigma, &l_sigma), worst(&rgb, &l_rgb));
        eprintln!(
            "worst difference: against the CPU sigma {e_sigma:.1e}, rgb {e_rgb:.1e}; against \
             the layers sigma {f_sigma:.1e}, rgb {f_rgb:.1e}"
        );
        assert!(e_sigma < 1e-4, "sigma {e_sigma}");
        assert!(e_rgb < 1e-5, "rgb {e_rgb}");
        assert!(f_sigma < 1e-4, "sigma against the layers {f_sigma}");
        assert!(f_rgb < 1e-5, "rgb against the layers {f_rgb}");
        // Something to compare: densities over two orders of magnitude.
        let (lo, hi) = want
            .sigma
            .iter()
            .fold((f32::MAX, 0.0f32), |(lo, hi), &s| (lo.min(s), hi.max(s)));
        assert!(hi > 100.0 * lo, "densities from {lo} to {hi} only");
        if fp_h.is_none() {
            let alone = device_field.density(&fast, &p, &pos_h, input.moments, n);
            assert_eq!(fast.read(&alone, n).expect("read"), sigma);
        }
        for moments in [DeviceMoments::At(0.3), DeviceMoments::Any] {
            let alone = device_field.density(&fast, &p, &pos_h, moments, n);
            let plain = layer_field.density(&layers, &p, &pos_h, moments, n);
            let (alone, plain) = (
                fast.read(&alone, n).expect("read"),
                layers.read(&plain, n).expect("read"),
            );
            let e = worst(&alone, &plain);
            assert!(e < 1e-4, "density alone against the layers: {e}");
        }
    }

    /// `gpu` with the fused path switched on.
    fn fused(gpu: &Gpu) -> Gpu {
        Gpu {
            fused_field: true,
            ..gpu.clone()
        }
    }

    /// `gpu` with the fused path switched off.
    fn layered(gpu: &Gpu) -> Gpu {
        Gpu {
            fused_field: false,
            ..gpu.clone()
        }
    }

    /// A small field without the optional inputs, [`narrow`], over 1000 samples: several
    /// workgroups, the last one partly empty.
    #[test]
    fn the_fused_kernel_matches_the_cpu_field() {
        let Some(gpu) = test_gpu() else { return };
        let field = FastField::new(narrow(small_field().config));
        matches_the_cpu_field(&gpu, &field, 1.5, 1000, &Feed::default());
    }

    /// Every input a field can take, at once: anti-aliased level weights (a footprint a
    /// sample, and the reference one), appearance codes (a code a sample with the mean
    /// among them, one photo's for all, the mean for all), a moving field's space-time
    /// features (a moment a sample), and four of the view direction's harmonics.
    #[test]
    fn the_fused_kernel_takes_every_input_the_field_takes() {
        let Some(gpu) = test_gpu() else { return };
        let field = small_field_with_every_input();
        let mut rng = Rng::new(8);
        let mixed: Vec<u32> = (0..700)
            .map(|_| match (rng.uniform() * 6.0) as u32 {
                5 => MEAN_APPEARANCE,
                i => i,
            })
            .collect();
        for (footprints, codes) in [
            (true, mixed),
            (false, vec![2; 700]),
            (true, vec![MEAN_APPEARANCE; 700]),
        ] {
            let feed = Feed {
                footprints,
                codes: Some(codes),
                moving: true,
            };
            matches_the_cpu_field(&gpu, &field, 1.5, 700, &feed);
        }
    }

    /// The default field's shapes (16 levels, 64 wide, 16 geometry features, anti-aliased:
    /// 37 KB of staged weights), where the adapter's workgroup memory holds them.
    #[test]
    fn the_fused_kernel_matches_the_cpu_field_at_the_default_size() {
        let Some(gpu) = test_gpu() else { return };
        let field = FastField::new(FastFieldConfig {
            grid: crate::encoding::HashGridConfig {
                log2_table_size: 12,
                ..FastFieldConfig::default().grid
            },
            antialias: Some(Antialias {
                reference_footprint: 0.003,
            }),
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
        let feed = Feed {
            footprints: true,
            ..Feed::default()
        };
        matches_the_cpu_field(&gpu, &field, 1.0, 300, &feed);
    }

    /// The switch (`NERF_GPU_FIELD`) chooses the path.
    #[test]
    fn the_switch_chooses_the_path() {
        let Some(gpu) = test_gpu() else { return };
        assert!(!GpuFastField::new(&layered(&gpu), &small_field()).is_fused());
        assert!(GpuFastField::new(&fused(&gpu), &small_field()).is_fused());
    }
}
