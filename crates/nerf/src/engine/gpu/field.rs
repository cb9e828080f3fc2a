//! The fast field (`field::fast`, whose docs draw the network) on the GPU: the hash
//! encoding, the density network, the spherical harmonics of the view direction, the colour
//! network, and the backward of all of it, as a sequence of kernels over one batch of
//! samples. Parameters and gradients are the model's whole vectors on the device, laid out
//! as on the CPU.

use cubecl::prelude::*;
use cubecl::server::Handle;

use super::antialias::LevelWeights;
use super::codes::{GpuCodes, SampleCodes};
use super::device::Gpu;
use super::device_field::{DeviceField, DeviceInput, DeviceMoments, DeviceOutput, FieldNeeds};
use super::fused::{FusedInput, FusedMotion, FusedShape, KeptBuffers};
use super::fused_backward::Forward as FusedForward;
use super::harmonics::sh4_at;
use super::hash_grid::{GpuHashGrid, Scatter};
use super::launch::grid;
use super::mlp::Dense;
use super::space_time_grid::{points_in_time, GpuSpaceTimeGrid, Moments};
use super::time_smoothness::{add_time_smoothness, MotionForward};
use crate::encoding::spherical_harmonics::SH_DIMS;
use crate::field::fast::LOG_SIGMA_MAX;
use crate::field::FastField;
use crate::step_clock::{self, Stage};

/// Threads per workgroup.
const GROUP: u32 = 256;

#[cube(launch_unchecked)]
fn to_unit(positions: &[f32], unit: &mut [f32], bound: f32) {
    let i = ABSOLUTE_POS;
    if i < unit.len() {
        unit[i] = (positions[i] + bound) * (0.5 / bound);
    }
}

/// `h = max(h + m, 0)`: the density network's first layer, its still and moving parts
/// summed before the ReLU.
#[cube(launch_unchecked)]
fn add_relu(h: &mut [f32], m: &[f32]) {
    let i = ABSOLUTE_POS;
    if i < h.len() {
        h[i] = f32::max(h[i] + m[i], 0.0);
    }
}

/// Each level's two features (`values`: `levels x 2` per sample) times the level's weight.
#[cube(launch_unchecked)]
fn scale_levels(values: &mut [f32], scale: &[f32], levels: u32) {
    let i = ABSOLUTE_POS;
    if i < values.len() {
        values[i] *= scale[(i / 2) % levels as usize];
    }
}

/// `sigma = exp(min(o_0, LOG_SIGMA_MAX))` from the density network's first output.
#[cube(launch_unchecked)]
fn density_head(geo: &[f32], sigma: &mut [f32], g: u32, log_max: f32) {
    let s = ABSOLUTE_POS;
    if s < sigma.len() {
        sigma[s] = f32::exp(f32::min(geo[s * g as usize], log_max));
    }
}

/// The colour network's input (rows `ci` wide): the 16 spherical harmonics of the sample's
/// unit view direction (as `encoding::spherical_harmonics::sh4`; those past the first
/// `harmonics` 0, as `FastField::view_harmonics` says), then the geometry
/// features; an appearance code, if any, follows (`codes`). A thread per value of the
/// first `15 + g` columns (`rows` rows), so that a warp's writes fill whole rows.
#[cube(launch_unchecked)]
fn colour_input(
    dirs: &[f32],
    geo: &[f32],
    colour_in: &mut [f32],
    g: u32,
    ci: u32,
    rows: u32,
    harmonics: u32,
) {
    let i = ABSOLUTE_POS;
    let (gw, ci) = (g as usize, ci as usize);
    let width = 15 + gw;
    if i < rows as usize * width {
        let s = i / width;
        let k = i % width;
        let value = if k < harmonics as usize {
            sh4_at(k, dirs[3 * s], dirs[3 * s + 1], dirs[3 * s + 2])
        } else if k < 16 {
            0.0f32
        } else {
            geo[s * gw + k - 15]
        };
        colour_in[s * ci + k] = value;
    }
}

#[cube(launch_unchecked)]
pub(super) fn sigmoid_in_place(v: &mut [f32]) {
    let i = ABSOLUTE_POS;
    if i < v.len() {
        v[i] = 1.0 / (1.0 + f32::exp(-v[i]));
    }
}

/// `d_logit = d_rgb * y (1 - y)` through the output sigmoid.
#[cube(launch_unchecked)]
pub(super) fn sigmoid_bwd(d_rgb: &[f32], rgb: &[f32], d_logit: &mut [f32]) {
    let i = ABSOLUTE_POS;
    if i < d_logit.len() {
        let y = rgb[i];
        d_logit[i] = d_rgb[i] * y * (1.0 - y);
    }
}

/// The density network's output gradient: `d o_0` through `exp(min(o_0, max))`, and the
/// geometry features' gradients from the colour network's input gradient. A thread per
/// value of `d_geo` (`g` a row), so that a warp's reads and writes are neighbours.
#[cube(launch_unchecked)]
fn geo_bwd(
    geo: &[f32],
    sigma: &[f32],
    d_sigma: &[f32],
    d_colour_in: &[f32],
    d_geo: &mut [f32],
    g: u32,
    ci: u32,
    log_max: f32,
) {
    let i = ABSOLUTE_POS;
    let (gw, ci) = (g as usize, ci as usize);
    if i < sigma.len() * gw {
        let s = i / gw;
        let j = i % gw;
        if j == 0 {
            d_geo[i] = select(geo[i] < log_max, d_sigma[s] * sigma[s], 0.0);
        } else {
            d_geo[i] = d_colour_in[s * ci + 15 + j];
        }
    }
}

impl DeviceInput<'_> {
    /// The batch as the fused kernels take it, its moments as `times` holds them
    /// ([`DeviceMoments::times`]).
    fn fused<'b>(&'b self, times: &'b (Handle, Moments)) -> FusedInput<'b> {
        FusedInput {
            dirs: Some(self.dirs),
            footprints: self.footprints,
            codes: self.codes,
            times: (&times.0, times.1),
        }
    }
}

/// The field's activations for one batch, kept by the forward for the backward.
pub struct Activations {
    pub n: usize,
    unit: Handle,
    enc: Handle,
    h: Handle,
    geo: Handle,
    /// Densities (`n`).
    pub sigma: Handle,
    colour_in: Handle,
    c1: Handle,
    c2: Handle,
    /// Colours (`n x 3`).
    pub rgb: Handle,
    /// Each sample's level weights (anti-aliased fields).
    level_weights: Option<Handle>,
    /// A moving field's points of space and time (`n x 4`) and their encoding.
    motion: Option<(Handle, Handle)>,
    /// Made by the fused forward, so the fused backward reads them.
    fused: bool,
    /// The samples' appearance codes (a forward's; the density network has none), for
    /// the codes' gradients.
    codes: Option<SampleCodes>,
}

impl DeviceOutput for Activations {
    fn sigma(&self) -> &Handle {
        &self.sigma
    }
    fn rgb(&self) -> &Handle {
        &self.rgb
    }
}

impl Activations {
    /// The samples' positions in the hash grid's unit cube (`n x 3`).
    pub fn unit(&self) -> &Handle {
        &self.unit
    }
}

/// The fast field's shapes and kernels on one device.
pub struct GpuFastField {
    grid: GpuHashGrid,
    enc_dims: usize,
    geo: usize,
    bound: f32,
    /// The view direction's harmonics the colour network is fed (`FastField::view_harmonics`).
    harmonics: usize,
    n_params: usize,
    /// density 0, 1, colour 0, 1, 2.
    layers: [Dense; 5],
    scatter: Scatter,
    /// The one-kernel field (`fused`), where its weights fit the adapter's workgroup memory.
    fused: Option<FusedShape>,
    /// Whether rendering and density queries take it (`Gpu::fused_field`), and training
    /// (`Gpu::fused_training`).
    fused_inference: bool,
    fused_training: bool,
    /// Per-photo appearance codes, when the field has them.
    codes: Option<GpuCodes>,
    /// The level weighting of an anti-aliased field.
    antialias: Option<LevelWeights>,
    /// Each hash-grid level's weight (camera refinement's coarse-to-fine schedule, as the
    /// CPU field's `level_weights`), or `None` where every level weighs 1.
    level_scale: Option<Handle>,
    /// A moving field's space-time encoding and its first-layer weights.
    motion: Option<GpuMotion>,
}

/// The moving part of a field of space and time (`field::fast`'s `motion`): its encoding,
/// whose features join the density network's first layer through their own weights.
struct GpuMotion {
    grid: GpuSpaceTimeGrid,
    /// `features x hidden`, no bias, no ReLU (summed before the first layer's).
    layer: Dense,
    features: usize,
    /// One cell of the finest time level: the time-smoothness prior's step.
    dt: f32,
}

/// What the field's backward leaves besides the parameters' gradients: the gradients of
/// the hash-grid features (`n x levels x 2`, before any level weighting) and of the colour
/// network's input (`n x` its width), which camera refinement carries on to the samples'
/// positions and view directions (`pose_grad`).
pub struct InputGradients {
    pub d_enc: Handle,
    pub d_colour_in: Handle,
    /// The colour network's input width.
    pub colour_columns: usize,
}

impl GpuFastField {
    pub fn new(gpu: &Gpu, field: &FastField) -> Self {
        let c = &field.config;
        let (e, w, g, ci) = (
            field.grid.dims(),
            c.hidden,
            c.geo_features,
            field.colour_in_dims(),
        );
        let off = field.weight_offsets();
        let codes = field.codes_offset().map(|offset| GpuCodes {
            offset,
            dims: field.appearance_dims(),
            images: c.appearance_images,
        });
        let shape = FusedShape {
            levels: field.grid.levels.len(),
            hidden: w,
            geo: g,
            harmonics: field.view_harmonics(),
            weights: off,
            bound: c.bound,
            antialias: c.antialias.map(|aa| aa.reference_footprint),
            codes,
            motion: field.motion.as_ref().zip(field.motion_weight_offset()).map(
                |(grid, weight)| FusedMotion {
                    levels: grid.levels.len(),
                    weight,
                },
            ),
        };
        let fused = shape.fits(gpu).then_some(shape);
        if (gpu.fused_field || gpu.fused_training) && fused.is_none() {
            eprintln!(
                "NERF_GPU_FIELD / NERF_GPU_TRAIN=fused: this field's weights ({} KB) do not \
                 fit this adapter's workgroup memory ({} KB); it runs layer by layer",
                shape.staged_floats() * 4 / 1024,
                gpu.client.properties().hardware.max_shared_memory_size / 1024
            );
        }
        let layer = |k: usize, inputs, outputs, relu| Dense {
            inputs,
            outputs,
            weight: off[k],
            bias: None,
            relu,
        };
        GpuFastField {
            grid: GpuHashGrid::new(gpu, &field.grid),
            enc_dims: e,
            geo: g,
            bound: c.bound,
            harmonics: field.view_harmonics(),
            n_params: field.num_params(),
            layers: [
                layer(0, e, w, true),
                layer(1, w, g, false),
                layer(2, ci, w, true),
                layer(3, w, w, true),
                layer(4, w, 3, false),
            ],
            scatter: if gpu.float_atomics {
                Scatter::FloatAtomic
            } else {
                Scatter::CompareAndSwap
            },
            fused,
            fused_inference: gpu.fused_field,
            fused_training: gpu.fused_training,
            codes,
            antialias: c.antialias.map(|aa| LevelWeights {
                reference: aa.reference_footprint,
                bound: c.bound,
            }),
            level_scale: None,
            motion: field.motion.as_ref().zip(field.motion_weight_offset()).map(
                |(grid, weight)| GpuMotion {
                    grid: GpuSpaceTimeGrid::new(gpu, grid),
                    layer: Dense {
                        inputs: grid.dims(),
                        outputs: w,
                        weight,
                        bias: None,
                        relu: false,
                    },
                    features: grid.dims(),
                    dt: 1.0 / grid.config.max_time_resolution.max(1) as f32,
                },
            ),
        }
    }

    /// Sets each hash-grid level's weight (empty, or all 1: none), as `set_progress` sets
    /// the CPU field's `level_weights`; while any is not 1, rendering runs layer by layer
    /// (the fused kernel has no weights).
    pub fn set_level_scale(&mut self, gpu: &Gpu, weights: &[f32]) {
        self.level_scale = weights
            .iter()
            .any(|&w| w != 1.0)
            .then(|| gpu.upload(weights));
    }

    /// The hash grid on the device.
    pub fn hash_grid(&self) -> &GpuHashGrid {
        &self.grid
    }

    /// `values` (`n` samples of the features' layout) times each level's weight, if any.
    fn apply_level_scale(&self, gpu: &Gpu, values: &Handle, n: usize) {
        let Some(scale) = &self.level_scale else {
            return;
        };
        let len = n * self.enc_dims;
        let (count, dim) = Self::launch(len);
        // SAFETY: `values` holds `n` rows of `enc_dims` floats, `scale` one per level.
        unsafe {
            scale_levels::launch_unchecked(
                &gpu.client,
                count,
                dim,
                BufferArg::from_raw_parts(values.clone(), len),
                BufferArg::from_raw_parts(scale.clone(), self.grid.n_levels),
                self.grid.n_levels as u32,
            );
        }
    }

    /// The colour network's input width, and the column its appearance code starts at.
    fn colour_columns(&self) -> (usize, usize) {
        let first = SH_DIMS + self.geo - 1;
        (self.layers[2].inputs, first)
    }

    /// Whether [`infer`](Self::infer) runs the one-kernel path now: where the adapter and
    /// the switch allow it and no level weight is below 1 (the kernel has none). The
    /// renderer sizes its rounds by this, so a round never outgrows the layer path.
    pub fn is_fused(&self) -> bool {
        self.fused_now().is_some()
    }

    /// The fused kernel's shapes, where [`infer`](Self::infer) runs it now.
    fn fused_now(&self) -> Option<&FusedShape> {
        self.fused
            .as_ref()
            .filter(|_| self.fused_inference && self.level_scale.is_none())
    }

    /// The fused kernels' shapes, where [`forward`](Self::forward) runs them now (no
    /// level weight below 1, as for inference).
    fn fused_training_now(&self) -> Option<&FusedShape> {
        self.fused
            .as_ref()
            .filter(|_| self.fused_training && self.level_scale.is_none())
    }

    /// The hash grid, and the space-time grid of a moving field.
    fn grids(&self) -> (&GpuHashGrid, Option<&GpuSpaceTimeGrid>) {
        (&self.grid, self.motion.as_ref().map(|m| &m.grid))
    }

    /// Moving fields: adds into `grads` the gradient of `weight` times the prior that the
    /// scene changes smoothly in time, over the samples of the forward that made `acts`
    /// (`time_smoothness`); nothing for still fields.
    pub fn time_smoothness_bwd(
        &self,
        gpu: &Gpu,
        (params, grads): (&Handle, &Handle),
        acts: &Activations,
        weight: f32,
    ) {
        let (Some(m), Some((points, enc))) = (&self.motion, &acts.motion) else {
            return;
        };
        let forward = MotionForward {
            grid: &m.grid,
            scatter: self.scatter,
            points,
            enc,
            features: m.features,
            n: acts.n,
            dt: m.dt,
        };
        add_time_smoothness(gpu, &forward, (params, grads, self.n_params), weight);
    }

    fn launch(n: usize) -> (CubeCount, CubeDim) {
        grid(n, GROUP)
    }

    /// Density network only, for `n` world `positions` (`n x 3`) with their `footprints`
    /// (anti-aliased fields; `None`: the reference footprint): fills everything up to
    /// `sigma` (the colour buffers are left empty).
    fn density_network(
        &self,
        gpu: &Gpu,
        params: &Handle,
        positions: &Handle,
        footprints: Option<&Handle>,
        moments: DeviceMoments,
        n: usize,
    ) -> Activations {
        let [d0, d1, ..] = &self.layers;
        let acts = Activations {
            n,
            unit: gpu.floats(n * 3),
            enc: gpu.floats(n * self.enc_dims),
            h: gpu.floats(n * d0.outputs),
            geo: gpu.floats(n * self.geo),
            sigma: gpu.floats(n),
            colour_in: gpu.floats(0),
            c1: gpu.floats(0),
            c2: gpu.floats(0),
            rgb: gpu.floats(0),
            level_weights: None,
            motion: None,
            fused: false,
            codes: None,
        };
        if n == 0 {
            return acts;
        }
        let np = self.n_params;
        let clock = step_clock::start(Stage::Encoding);
        // SAFETY: every buffer was made above with the length given here; the kernels
        // bounds-check the buffer they write.
        unsafe {
            let (count, dim) = Self::launch(n * 3);
            to_unit::launch_unchecked(
                &gpu.client,
                count,
                dim,
                BufferArg::from_raw_parts(positions.clone(), n * 3),
                BufferArg::from_raw_parts(acts.unit.clone(), n * 3),
                self.bound,
            );
        }
        self.grid.encode(gpu, params, &acts.unit, n, &acts.enc);
        gpu.stage_done(clock);
        let mut acts = acts;
        if let Some(aa) = &self.antialias {
            let clock = step_clock::start(Stage::LevelWeights);
            acts.level_weights = Some(aa.forward(gpu, &self.grid, footprints, &acts.enc, n));
            gpu.stage_done(clock);
        }
        self.apply_level_scale(gpu, &acts.enc, n);
        match &self.motion {
            None => {
                let clock = step_clock::start(Stage::Networks);
                d0.forward(gpu, params, np, &acts.enc, &acts.h, n);
                gpu.stage_done(clock);
            }
            Some(m) => {
                let clock = step_clock::start(Stage::Encoding);
                let (times, kind) = moments.times(gpu);
                let points = points_in_time(gpu, &acts.unit, (&times, kind), n);
                let enc = gpu.floats(n * m.features);
                m.grid.encode(gpu, (params, np), &points, n, &enc);
                gpu.stage_done(clock);
                let clock = step_clock::start(Stage::Networks);
                let still = Dense { relu: false, ..*d0 };
                still.forward(gpu, params, np, &acts.enc, &acts.h, n);
                let moving = gpu.floats(n * d0.outputs);
                m.layer.forward(gpu, params, np, &enc, &moving, n);
                let (count, dim) = Self::launch(n * d0.outputs);
                // SAFETY: both buffers hold `n x hidden` floats; the kernel bounds-checks.
                unsafe {
                    add_relu::launch_unchecked(
                        &gpu.client,
                        count,
                        dim,
                        BufferArg::from_raw_parts(acts.h.clone(), n * d0.outputs),
                        BufferArg::from_raw_parts(moving.clone(), n * d0.outputs),
                    );
                }
                gpu.stage_done(clock);
                acts.motion = Some((points, enc));
            }
        }
        let clock = step_clock::start(Stage::Networks);
        d1.forward(gpu, params, np, &acts.h, &acts.geo, n);
        // SAFETY: as above.
        unsafe {
            let (count, dim) = Self::launch(n);
            density_head::launch_unchecked(
                &gpu.client,
                count,
                dim,
                BufferArg::from_raw_parts(acts.geo.clone(), n * self.geo),
                BufferArg::from_raw_parts(acts.sigma.clone(), n),
                self.geo as u32,
                LOG_SIGMA_MAX,
            );
        }
        gpu.stage_done(clock);
        acts
    }

    /// [`forward`](Self::forward) through the fused kernel, keeping what the layers keep.
    fn fused_forward(
        &self,
        gpu: &Gpu,
        params: &Handle,
        shape: &FusedShape,
        input: &DeviceInput,
    ) -> Activations {
        let n = input.n;
        let (e, md, ci) = shape.widths();
        let w = self.layers[0].outputs;
        let rows = |width: usize| gpu.floats(n * width);
        let kept = KeptBuffers {
            unit: rows(3),
            enc: rows(e),
            level_weights: self.antialias.as_ref().map(|_| rows(self.grid.n_levels)),
            motion: self.motion.as_ref().map(|_| (rows(4), rows(md))),
            h: rows(w),
            geo: rows(self.geo),
            colour_in: rows(ci),
            c1: rows(w),
            c2: rows(w),
        };
        let clock = step_clock::start(Stage::Networks);
        let times = input.moments.times(gpu);
        let fused = input.fused(&times);
        let (sigma, rgb) = shape.forward(
            gpu,
            self.grids(),
            params,
            self.n_params,
            input.positions,
            &fused,
            &kept,
            n,
        );
        gpu.stage_done(clock);
        Activations {
            n,
            unit: kept.unit,
            enc: kept.enc,
            h: kept.h,
            geo: kept.geo,
            sigma,
            colour_in: kept.colour_in,
            c1: kept.c1,
            c2: kept.c2,
            rgb,
            level_weights: kept.level_weights,
            motion: kept.motion,
            fused: true,
            codes: Some(input.codes.clone()),
        }
    }

    /// Backward of [`fused_forward`](Self::fused_forward): the layers' input and output
    /// gradients from the fused kernel, the weights' from their products, then the codes,
    /// the space-time grid and the hash grid as the layers' backward does them.
    #[allow(clippy::too_many_arguments)]
    fn fused_backward(
        &self,
        gpu: &Gpu,
        (params, grads): (&Handle, &Handle),
        shape: &FusedShape,
        acts: &Activations,
        d_sigma: &Handle,
        d_rgb: &Handle,
    ) -> InputGradients {
        let n = acts.n;
        let np = self.n_params;
        let [d0, d1, c0, c1, c2] = &self.layers;
        let networks = step_clock::start(Stage::NetworksBackward);
        let forward = FusedForward {
            sigma: &acts.sigma,
            rgb: &acts.rgb,
            h: &acts.h,
            geo: &acts.geo,
            c1: &acts.c1,
            c2: &acts.c2,
            level_weights: acts.level_weights.as_ref(),
        };
        let g = shape.backward(gpu, params, np, &forward, d_sigma, d_rgb, n);
        // The weights' gradients, `x^T dy` layer by layer.
        let layers = [
            (c2, &acts.c2, &g.d_logit),
            (c1, &acts.c1, &g.d_c2),
            (c0, &acts.colour_in, &g.d_c1),
            (d1, &acts.h, &g.d_geo),
            (d0, &acts.enc, &g.d_h),
        ];
        for (layer, x, dy) in layers {
            layer.backward(gpu, params, grads, np, x, dy, None, n);
        }
        if let (Some(c), Some(codes)) = (&self.codes, &acts.codes) {
            let columns = self.colour_columns();
            let scatter = self.scatter;
            c.backward(gpu, scatter, codes, &g.d_colour_in, columns, grads, np, n);
        }
        if let (Some(m), Some((points, enc)), Some(d_motion)) =
            (&self.motion, &acts.motion, &g.d_motion)
        {
            m.layer
                .backward(gpu, params, grads, np, enc, &g.d_h, None, n);
            m.grid
                .encode_bwd(gpu, self.scatter, points, d_motion, n, (grads, np));
        }
        gpu.stage_done(networks);
        let clock = step_clock::start(Stage::EncodingBackward);
        self.grid.encode_bwd(
            gpu,
            self.scatter,
            &acts.unit,
            &g.d_enc,
            n,
            grads,
            gpu.grid_run,
        );
        gpu.stage_done(clock);
        InputGradients {
            d_enc: g.d_enc,
            d_colour_in: g.d_colour_in,
            colour_columns: c0.inputs,
        }
    }
}

impl DeviceField for GpuFastField {
    type Activations = Activations;
    type InputGradients = InputGradients;

    fn num_params(&self) -> usize {
        self.n_params
    }

    fn needs(&self) -> FieldNeeds {
        FieldNeeds {
            codes: self.codes.is_some(),
            footprints: self.antialias.is_some(),
            moments: self.motion.is_some(),
        }
    }

    /// Density and colour of the samples of `input`.
    fn forward(&self, gpu: &Gpu, params: &Handle, input: &DeviceInput) -> Activations {
        let DeviceInput {
            positions,
            dirs,
            codes,
            footprints,
            moments,
            n,
            ..
        } = *input;
        if let Some(shape) = self.fused_training_now() {
            return self.fused_forward(gpu, params, shape, input);
        }
        let mut acts = self.density_network(gpu, params, positions, footprints, moments, n);
        let [_, _, c0, c1, c2] = &self.layers;
        acts.colour_in = gpu.floats(n * c0.inputs);
        acts.c1 = gpu.floats(n * c0.outputs);
        acts.c2 = gpu.floats(n * c1.outputs);
        acts.rgb = gpu.floats(n * 3);
        acts.codes = Some(codes.clone());
        if n == 0 {
            return acts;
        }
        let np = self.n_params;
        let clock = step_clock::start(Stage::Networks);
        // SAFETY: as in `density`.
        unsafe {
            let (count, dim) = Self::launch(n * (15 + self.geo));
            colour_input::launch_unchecked(
                &gpu.client,
                count,
                dim,
                BufferArg::from_raw_parts(dirs.clone(), n * 3),
                BufferArg::from_raw_parts(acts.geo.clone(), n * self.geo),
                BufferArg::from_raw_parts(acts.colour_in.clone(), n * c0.inputs),
                self.geo as u32,
                c0.inputs as u32,
                n as u32,
                self.harmonics as u32,
            );
        }
        if let Some(c) = &self.codes {
            c.write(
                gpu,
                params,
                np,
                codes,
                &acts.colour_in,
                self.colour_columns(),
                n,
            );
        }
        c0.forward(gpu, params, np, &acts.colour_in, &acts.c1, n);
        c1.forward(gpu, params, np, &acts.c1, &acts.c2, n);
        c2.forward(gpu, params, np, &acts.c2, &acts.rgb, n);
        // SAFETY: as in `density`.
        unsafe {
            let (count, dim) = Self::launch(n * 3);
            sigmoid_in_place::launch_unchecked(
                &gpu.client,
                count,
                dim,
                BufferArg::from_raw_parts(acts.rgb.clone(), n * 3),
            );
        }
        gpu.stage_done(clock);
        acts
    }

    /// Backward of [`forward`](Self::forward): from `d_sigma` (`n`) and `d_rgb`
    /// (`n x 3`), adds every parameter's gradient into `grads`; returns the inputs'
    /// gradients it made on the way.
    fn backward(
        &self,
        gpu: &Gpu,
        params: &Handle,
        grads: &Handle,
        acts: &Activations,
        d_sigma: &Handle,
        d_rgb: &Handle,
    ) -> InputGradients {
        let n = acts.n;
        let [d0, d1, c0, c1, c2] = &self.layers;
        if n == 0 {
            return InputGradients {
                d_enc: gpu.floats(1),
                d_colour_in: gpu.floats(1),
                colour_columns: c0.inputs,
            };
        }
        if let Some(shape) = self.fused.as_ref().filter(|_| acts.fused) {
            let state = (params, grads);
            return self.fused_backward(gpu, state, shape, acts, d_sigma, d_rgb);
        }
        let np = self.n_params;
        let networks = step_clock::start(Stage::NetworksBackward);
        let d_logit = gpu.floats(n * 3);
        // SAFETY: as in `density`.
        unsafe {
            let (count, dim) = Self::launch(n * 3);
            sigmoid_bwd::launch_unchecked(
                &gpu.client,
                count,
                dim,
                BufferArg::from_raw_parts(d_rgb.clone(), n * 3),
                BufferArg::from_raw_parts(acts.rgb.clone(), n * 3),
                BufferArg::from_raw_parts(d_logit.clone(), n * 3),
            );
        }
        let d_c2 = gpu.floats(n * c2.inputs);
        c2.backward(
            gpu,
            params,
            grads,
            np,
            &acts.c2,
            &d_logit,
            Some((&d_c2, true)),
            n,
        );
        let d_c1 = gpu.floats(n * c1.inputs);
        c1.backward(
            gpu,
            params,
            grads,
            np,
            &acts.c1,
            &d_c2,
            Some((&d_c1, true)),
            n,
        );
        let d_colour_in = gpu.floats(n * c0.inputs);
        c0.backward(
            gpu,
            params,
            grads,
            np,
            &acts.colour_in,
            &d_c1,
            Some((&d_colour_in, false)),
            n,
        );
        let d_geo = gpu.floats(n * self.geo);
        // SAFETY: as in `density`.
        unsafe {
            let (count, dim) = Self::launch(n * self.geo);
            geo_bwd::launch_unchecked(
                &gpu.client,
                count,
                dim,
                BufferArg::from_raw_parts(acts.geo.clone(), n * self.geo),
                BufferArg::from_raw_parts(acts.sigma.clone(), n),
                BufferArg::from_raw_parts(d_sigma.clone(), n),
                BufferArg::from_raw_parts(d_colour_in.clone(), n * c0.inputs),
                BufferArg::from_raw_parts(d_geo.clone(), n * self.geo),
                self.geo as u32,
                c0.inputs as u32,
                LOG_SIGMA_MAX,
            );
        }
        if let (Some(c), Some(codes)) = (&self.codes, &acts.codes) {
            let columns = self.colour_columns();
            c.backward(
                gpu,
                self.scatter,
                codes,
                &d_colour_in,
                columns,
                grads,
                np,
                n,
            );
        }
        let d_h = gpu.floats(n * d1.inputs);
        d1.backward(
            gpu,
            params,
            grads,
            np,
            &acts.h,
            &d_geo,
            Some((&d_h, true)),
            n,
        );
        let d_enc = gpu.floats(n * self.enc_dims);
        d0.backward(
            gpu,
            params,
            grads,
            np,
            &acts.enc,
            &d_h,
            Some((&d_enc, false)),
            n,
        );
        if let (Some(m), Some((points, enc))) = (&self.motion, &acts.motion) {
            let d_motion = gpu.floats(n * m.features);
            m.layer.backward(
                gpu,
                params,
                grads,
                np,
                enc,
                &d_h,
                Some((&d_motion, false)),
                n,
            );
            m.grid
                .encode_bwd(gpu, self.scatter, points, &d_motion, n, (grads, np));
        }
        gpu.stage_done(networks);
        if let Some(weights) = &acts.level_weights {
            let clock = step_clock::start(Stage::LevelWeights);
            LevelWeights::backward(gpu, weights, &d_enc, n, self.grid.n_levels);
            gpu.stage_done(clock);
        }
        self.apply_level_scale(gpu, &d_enc, n);
        let clock = step_clock::start(Stage::EncodingBackward);
        self.grid.encode_bwd(
            gpu,
            self.scatter,
            &acts.unit,
            &d_enc,
            n,
            grads,
            gpu.grid_run,
        );
        gpu.stage_done(clock);
        InputGradients {
            d_enc,
            d_colour_in,
            colour_columns: c0.inputs,
        }
    }

    /// Densities (`n`) and colours (`n x 3`) for rendering, with no activations kept: the
    /// fused kernel where it runs, else [`forward`](Self::forward).
    fn infer(&self, gpu: &Gpu, params: &Handle, input: &DeviceInput) -> (Handle, Handle) {
        match self.fused_now() {
            Some(f) => {
                let times = input.moments.times(gpu);
                let fused = input.fused(&times);
                f.infer(
                    gpu,
                    self.grids(),
                    params,
                    self.n_params,
                    input.positions,
                    &fused,
                    input.n,
                )
            }
            None => {
                let acts = self.forward(gpu, params, input);
                (acts.sigma, acts.rgb)
            }
        }
    }

    /// Densities (`n`) of `n` world `positions`, as [`infer`](Self::infer) does.
    fn density(
        &self,
        gpu: &Gpu,
        params: &Handle,
        positions: &Handle,
        moments: DeviceMoments,
        n: usize,
    ) -> Handle {
        match self.fused_now() {
            Some(f) => {
                let times = moments.times(gpu);
                let codes = SampleCodes::all(gpu, crate::stage::MEAN_APPEARANCE);
                let fused = FusedInput {
                    dirs: None,
                    footprints: None,
                    codes: &codes,
                    times: (&times.0, times.1),
                };
                let grids = self.grids();
                f.infer(gpu, grids, params, self.n_params, positions, &fused, n)
                    .0
            }
            None => {
                self.density_network(gpu, params, positions, None, moments, n)
                    .sigma
            }
        }
    }
}

#[cfg(test)]
pub(super) mod tests {
    use super::*;
    use crate::encoding::HashGridConfig;
    use crate::engine::gpu::device::worst;
    use crate::engine::gpu::device::Path;
    use crate::field::fast::FastWorkspace;
    use crate::field::FastFieldConfig;
    use crate::nn::GradBuffer;
    use crate::rng::Rng;
    use crate::stage::{Field, FieldGrad, FieldInput};

    /// A field small enough for kernel tests: 4 levels of 2^8 entries, 16-wide layers.
    pub fn small_field() -> FastField {
        FastField::new(FastFieldConfig {
            grid: HashGridConfig {
                levels: 4,
                log2_table_size: 8,
                base_resolution: 2,
                max_resolution: 32,
            },
            hidden: 16,
            geo_features: 5,
            bound: 1.5,
            ..FastFieldConfig::default()
        })
    }

    /// A moving field with every other input a field can take: anti-aliased level
    /// weights, appearance codes (3 values for 5 photos) and four view harmonics. The
    /// fused kernels' tests take this one field, [`narrow`] and with one moving level:
    /// each field shape is a kernel to compile.
    pub fn small_field_with_every_input() -> FastField {
        let moving = narrow(small_moving_field().config);
        FastField::new(FastFieldConfig {
            motion: moving
                .motion
                .map(|m| crate::encoding::space_time_grid::SpaceTimeConfig { levels: 1, ..m }),
            antialias: Some(crate::field::fast::Antialias {
                reference_footprint: 0.02,
            }),
            appearance_dims: 3,
            appearance_images: 5,
            view_harmonics: 4,
            geo_features: 3,
            ..moving
        })
    }

    /// `config` with two still levels and 8 hidden units: the fused kernels' tests take
    /// narrow, shallow fields, since lavapipe's compile time grows faster than a kernel's
    /// size and the shapes' sizes are not what they test.
    pub fn narrow(config: FastFieldConfig) -> FastFieldConfig {
        FastFieldConfig {
            grid: HashGridConfig {
                levels: 2,
                ..config.grid
            },
            hidden: 8,
            ..config
        }
    }

    /// A small field with large random weights (every path carries signal) over 700
    /// samples: sigma, rgb and every parameter's gradient against the CPU field, within
    /// 1e-4 relative to (1 + |value|) (sums of 700 terms in another order).
    #[test]
    fn the_field_matches_the_cpu_forward_and_backward() {
        matches_the_cpu(&small_field(), None, false, false);
    }

    /// A field fed the view direction's first four harmonics (few-view training): the
    /// colour network's other inputs are 0 on the device too.
    #[test]
    fn the_field_fed_four_harmonics_matches_the_cpu() {
        let field = FastField::new(FastFieldConfig {
            view_harmonics: 4,
            ..small_field().config
        });
        matches_the_cpu(&field, None, false, false);
    }

    /// A moving field (a space-time grid of 3 levels beside the still one): each sample at
    /// its own moment, forward and backward, and the density pass at one moment.
    #[test]
    fn the_moving_field_matches_the_cpu() {
        matches_the_cpu(&small_moving_field(), None, false, true);
    }

    /// [`small_field`] with a small space-time grid beside its hash grid.
    pub fn small_moving_field() -> FastField {
        FastField::new(FastFieldConfig {
            motion: Some(crate::encoding::space_time_grid::SpaceTimeConfig {
                levels: 3,
                log2_table_size: 8,
                base_resolution: 4,
                max_resolution: 24,
                base_time_resolution: 2,
                max_time_resolution: 8,
            }),
            ..small_field().config
        })
    }

    /// An anti-aliased field: each sample's footprint (from well under a fine cell to
    /// several coarse ones) weighs its levels, or the reference footprint where samples
    /// carry none.
    #[test]
    fn the_anti_aliased_field_matches_the_cpu() {
        let field = FastField::new(FastFieldConfig {
            antialias: Some(crate::field::fast::Antialias {
                reference_footprint: 0.02,
            }),
            ..small_field().config
        });
        matches_the_cpu(&field, None, true, false);
        matches_the_cpu(&field, None, false, false);
    }

    /// The same with per-photo appearance codes (3 values for 5 photos): each sample its
    /// photo's code, the mean code for some, and every sample the same code.
    #[test]
    fn the_field_with_appearance_codes_matches_the_cpu() {
        let field = FastField::new(FastFieldConfig {
            appearance_dims: 3,
            appearance_images: 5,
            ..small_field().config
        });
        assert_eq!(field.appearance_dims(), 3);
        let mut rng = Rng::new(8);
        let per_sample: Vec<u32> = (0..700)
            .map(|_| match (rng.uniform() * 6.0) as u32 {
                5 => crate::stage::MEAN_APPEARANCE,
                i => i,
            })
            .collect();
        matches_the_cpu(&field, Some(per_sample), false, false);
        matches_the_cpu(&field, Some(vec![2; 700]), false, false);
        matches_the_cpu(
            &field,
            Some(vec![crate::stage::MEAN_APPEARANCE; 700]),
            false,
            false,
        );
    }

    /// `field` on the device against the CPU, with each sample's code index
    /// (`appearance`) where the field has codes, random footprints with `footprints`, and
    /// random moments with `moving` (else none: moment 0 on both).
    fn matches_the_cpu(
        field: &FastField,
        appearance: Option<Vec<u32>>,
        footprints: bool,
        moving: bool,
    ) {
        let Some(gpu) = super::super::device::test_gpu() else {
            return;
        };
        let mut rng = Rng::new(21);
        let params: Vec<f32> = (0..field.num_params())
            .map(|_| rng.range(-0.5, 0.5))
            .collect();
        let n = 700;
        let pos: Vec<f32> = (0..n * 3).map(|_| rng.range(-1.6, 1.6)).collect();
        let dirs = rng.unit_directions(n);
        let d_sigma: Vec<f32> = (0..n).map(|_| rng.range(-1.0, 1.0)).collect();
        let d_rgb: Vec<f32> = (0..n * 3).map(|_| rng.range(-1.0, 1.0)).collect();
        let times: Vec<f32> = if moving {
            (0..n).map(|_| rng.uniform()).collect()
        } else {
            Vec::new()
        };
        let indices = appearance.clone().unwrap_or_default();
        let fp: Vec<f32> = if footprints {
            (0..n).map(|_| 10f32.powf(rng.range(-3.5, -0.5))).collect()
        } else {
            Vec::new()
        };
        let codes = |gpu: &Gpu| match &appearance {
            // All the same: the one-index form the renderer passes.
            Some(a) if a.iter().all(|&i| i == a[0]) => SampleCodes::all(gpu, a[0]),
            Some(a) => SampleCodes {
                index: gpu.upload_u32(a),
                per_sample: true,
            },
            None => SampleCodes::all(gpu, crate::stage::MEAN_APPEARANCE),
        };

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
        let out = field.forward(&params, input, &mut ws);
        let (want_sigma, want_rgb) = (out.sigma.to_vec(), out.rgb.to_vec());
        let mut grads = GradBuffer::new(field.num_params());
        let d = FieldGrad {
            d_sigma: &d_sigma,
            d_rgb: &d_rgb,
        };
        field.backward(&params, &mut ws, d, &mut grads.all());

        for path in [Path::Plain, Path::Tiled, Path::Blocked, Path::Wide] {
            let gpu = Gpu {
                matmul: path,
                ..gpu.clone()
            };
            let gf = GpuFastField::new(&gpu, field);
            assert_eq!(gf.needs().moments, moving);
            let p = gpu.upload(&params);
            let g = gpu.zeros(field.num_params());
            let codes = codes(&gpu);
            let (pos_h, dirs_h) = (gpu.upload(&pos), gpu.upload(&dirs));
            let fp_h = footprints.then(|| gpu.upload(&fp));
            let times_h = gpu.upload(&times);
            let moments = match moving {
                true => DeviceMoments::Each(&times_h),
                false => DeviceMoments::At(0.0),
            };
            let input = DeviceInput {
                positions: &pos_h,
                dirs: &dirs_h,
                codes: &codes,
                footprints: fp_h.as_ref(),
                variances: None,
                moments,
                n,
            };
            let acts = gf.forward(&gpu, &p, &input);
            gf.backward(
                &gpu,
                &p,
                &g,
                &acts,
                &gpu.upload(&d_sigma),
                &gpu.upload(&d_rgb),
            );
            let sigma = gpu.read(&acts.sigma, n).expect("read");
            let rgb = gpu.read(&acts.rgb, n * 3).expect("read");
            let got = gpu.read(&g, field.num_params()).expect("read");
            assert!(
                worst(&sigma, &want_sigma) < 1e-4,
                "sigma {}",
                worst(&sigma, &want_sigma)
            );
            assert!(
                worst(&rgb, &want_rgb) < 1e-5,
                "rgb {}",
                worst(&rgb, &want_rgb)
            );
            for t in &field.layout.tensors {
                let e = worst(&got[t.range()], &grads.values[t.range()]);
                assert!(e < 1e-4, "gradient of {}: {e}", t.name);
            }
            // The density-only pass gives the same densities.
            let alone = gf.density_network(&gpu, &p, &pos_h, fp_h.as_ref(), moments, n);
            assert_eq!(gpu.read(&alone.sigma, n).expect("read"), sigma);
            if moving {
                // At one moment, as the CPU field's density query.
                let mut want = vec![0.0; n];
                field.density_at(&params, &pos, Some(0.3), &mut ws, &mut want);
                let at = gf.density_network(&gpu, &p, &pos_h, None, DeviceMoments::At(0.3), n);
                let e = worst(&gpu.read(&at.sigma, n).expect("read"), &want);
                assert!(e < 1e-4, "density at a moment: {e}");
            }
        }
    }
}
