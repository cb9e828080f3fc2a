//! The GPU engine for the paper's model: both networks' forward and backward, compositing,
//! the loss and Adam on the device, where the parameters, gradients and moments live.
//!
//! Work mapping of a step: the host draws the rays and their stratified depths (the CPU
//! engine's code: the same rays and samples) and uploads the packed samples; the device
//! runs the coarse pass forward and backward, draws the importance samples from its
//! compositing weights by the host's rule (`importance`: the host sends only each ray's
//! uniform draws, from the CPU engine's random streams), runs the fine pass forward and
//! backward, and Adam. mip-NeRF's frustums, and rendering's fine samples (measured
//! faster there), are made on the host from weights read back. The host reads back one
//! float per ray per pass (the loss) and one count (non-finite gradients). Rendering goes
//! through the same two passes in chunks of rays. FreeNeRF's band mask is applied by the
//! device's encoding and its occlusion penalty by a kernel beside the loss. RegNeRF's
//! annealed range is the host's sampling; its patches from unseen poses go through both
//! passes after the photo rays, their depth smoothness's gradient from the device's
//! kernel (`depth_smoothness`). D-NeRF's deformation runs inside each network's forward
//! and backward (`vanilla_net`, `deformation`), each sample at its ray's moment.

use cubecl::server::Handle;

use super::depth_smoothness::{add_depth_smoothness, LastStep};
use super::device::Gpu;
use super::device_field::{DeviceField, DeviceMoments};
use super::importance::{self, PassSamples};
use super::loss;
use super::params::{check_device, density_in_chunks, fail_rays, DeviceParams};
use super::space_time_grid::per_sample;
use super::vanilla_net::{GpuVanillaNet, VanillaActs};
use super::volume::{self, GpuSamples, OUT_WORDS};
use crate::data::pixels::TrainingRays;
use crate::data::Dataset;
use crate::engine::{render_in_chunks, Engine, EngineOptions, EngineState, StepSpec, StepStats};
use crate::error::Result;
use crate::model::reg_nerf::RegNerf;
use crate::model::unseen_patches;
use crate::model::vanilla::ChunkWorkspace;
use crate::model::{Model, ModelConfig, VanillaModel, VanillaModelConfig};
use crate::nn::ParamLayout;
use crate::render::loss::mean_scale;
use crate::rng::Rng;
use crate::stage::finite::FiniteCheck;
use crate::stage::{PackedSamples, RayBatch, RayOutput};

/// Points per device call of density queries.
const DENSITY_CHUNK: usize = 1 << 15;

/// The paper's model on one GPU.
pub struct GpuVanillaEngine {
    gpu: Gpu,
    config: ModelConfig,
    /// The host side: layout, sampling.
    model: VanillaModel,
    coarse: GpuVanillaNet,
    fine: Option<GpuVanillaNet>,
    state: DeviceParams,
    check_finite: bool,
    chunk_rays: usize,
    rays: TrainingRays,
    ws: ChunkWorkspace,
}

/// One pass (coarse or fine) of a batch of rays, forward done.
struct Pass {
    samples: GpuSamples,
    acts: VanillaActs,
    weights: Handle,
    out: Handle,
}

impl GpuVanillaEngine {
    pub fn new(gpu: Gpu, config: VanillaModelConfig, options: EngineOptions, seed: u64) -> Self {
        let model = VanillaModel::new(config.clone());
        let n = model.layout.total;
        let coarse = GpuVanillaNet::new(&model.coarse, 0, n);
        let fine = model
            .fine
            .as_ref()
            .map(|f| GpuVanillaNet::new(f, model.coarse.num_params(), n));
        GpuVanillaEngine {
            state: DeviceParams::new(&gpu, &model.init_params(seed), options.adam),
            check_finite: options.check_finite,
            chunk_rays: options.chunk_rays.max(1),
            config: ModelConfig::Vanilla(config),
            model,
            coarse,
            fine,
            gpu,
            rays: TrainingRays::default(),
            ws: ChunkWorkspace::default(),
        }
    }

    /// The network of the fine pass: its own, or the coarse one when they are shared
    /// (mip-NeRF); `None` without a fine pass (`VanillaModel::fine_pass`).
    fn fine_net(&self) -> Option<&GpuVanillaNet> {
        match &self.fine {
            Some(fine) => Some(fine),
            None if self.model.config.hierarchical() => Some(&self.coarse),
            None => None,
        }
    }

    /// Uploads packed `samples` and runs `net` forward and compositing over `backgrounds`.
    fn pass(&self, net: &GpuVanillaNet, samples: &PackedSamples, backgrounds: &Handle) -> Pass {
        let gpu = &self.gpu;
        let (rays, n) = (samples.rays(), samples.len());
        let offsets: Vec<u32> = samples.offsets.iter().map(|&o| o as u32).collect();
        let spd = samples.samples_per_dir.max(1);
        let dirs: Vec<f32> = (0..n).flat_map(|s| samples.dirs[s / spd]).collect();
        let on_device = PassSamples {
            samples: GpuSamples {
                offsets: gpu.upload_u32(&offsets),
                t: gpu.upload(&samples.t),
                dt: gpu.upload(&samples.dt),
                rays,
                len: n,
            },
            positions: gpu.upload(samples.positions.as_flattened()),
            dirs: gpu.upload(&dirs),
        };
        let variances = (!samples.variances.is_empty()).then(|| gpu.upload(&samples.variances));
        let times = (!samples.times.is_empty()).then(|| gpu.upload(&samples.times));
        let extra = (variances.as_ref(), times.as_ref());
        self.pass_on_device(net, on_device, extra, backgrounds)
    }

    /// Runs `net` forward on `samples` already on the device (each a Gaussian of diagonal
    /// covariance `variances`, each at its moment in `times`, where given), and compositing
    /// over `backgrounds`.
    fn pass_on_device(
        &self,
        net: &GpuVanillaNet,
        samples: PassSamples,
        (variances, times): (Option<&Handle>, Option<&Handle>),
        backgrounds: &Handle,
    ) -> Pass {
        let gpu = &self.gpu;
        let PassSamples {
            samples: on_device,
            positions,
            dirs,
        } = samples;
        let (rays, n) = (on_device.rays, on_device.len);
        let params = &self.state.values;
        let acts = net.forward_points(gpu, params, &positions, variances, times, &dirs, n);
        let (weights, out) = (gpu.floats(n), gpu.floats(rays * OUT_WORDS));
        volume::composite(
            gpu,
            &on_device,
            &acts.sigma,
            &acts.rgb,
            backgrounds,
            &weights,
            &out,
        );
        Pass {
            samples: on_device,
            acts,
            weights,
            out,
        }
    }

    /// The loss of `pass` against `targets` and its backward into the gradients; returns
    /// the pass's summed squared error.
    fn backward(
        &self,
        net: &GpuVanillaNet,
        pass: &Pass,
        backgrounds: &Handle,
        targets: &Handle,
        check: &FiniteCheck,
    ) -> Result<f64> {
        let gpu = &self.gpu;
        let (rays, n) = (pass.samples.rays, pass.samples.len);
        let (sse, d_out) = (gpu.floats(rays), gpu.floats(rays * 3));
        loss::squared_error_per_ray(gpu, rays, &pass.out, targets, &sse, &d_out);
        let (d_sigma, d_rgb) = (gpu.floats(n), gpu.floats(n * 3));
        volume::composite_backward(
            gpu,
            &pass.samples,
            &pass.acts.sigma,
            &pass.acts.rgb,
            backgrounds,
            &pass.out,
            &d_out,
            &d_sigma,
            &d_rgb,
        );
        if let Some(free) = &self.model.config.free_nerf {
            loss::add_occlusion(gpu, free, &pass.samples, &d_sigma);
        }
        check_device(gpu, check, "loss.backward", "d_sigma", &d_sigma, n)?;
        check_device(gpu, check, "loss.backward", "d_rgb", &d_rgb, n * 3)?;
        net.backward(
            gpu,
            &self.state.values,
            &self.state.grads,
            &pass.acts,
            &d_sigma,
            &d_rgb,
        );
        // Per ray, summed in ray order in f64: the CPU engine's loss to rounding.
        Ok(gpu.read(&sse, rays)?.iter().map(|&e| e as f64).sum())
    }

    /// RegNeRF's patches from poses between the training cameras (the CPU engine's, all in
    /// one batch), through both passes with the photo rays' annealed range: no colour to
    /// match, only the depth smoothness (and FreeNeRF's occlusion penalty where it is on, as
    /// the CPU engine adds it to every ray), whose gradient joins the step's.
    /// `photo_rays`: the rays the step's loss is a mean over.
    fn train_patches(
        &self,
        data: &Dataset,
        spec: &StepSpec,
        reg: &RegNerf,
        photo_rays: usize,
        ws: &mut ChunkWorkspace,
        check: &FiniteCheck,
    ) -> Result<()> {
        let step = spec.sampling.step;
        let patches = reg.patches(photo_rays);
        let stride = unseen_patches::stride_for(data.views[0].camera.width);
        let draw = (spec.sampling.seed, step);
        let mut rays = unseen_patches::draw_patches(data, draw, patches, stride);
        self.model.anneal(&mut rays, step);
        let backgrounds = self.gpu.upload(rays.rays.backgrounds.as_flattened());
        let smoothness = (
            reg.smoothness_scale(step, photo_rays, patches),
            data.far - data.near,
        );
        let samples = self.model.pack_coarse(ws, &rays.rays, Some(&mut rays.rngs));
        let coarse = self.pass(&self.coarse, samples, &backgrounds);
        self.check_forward(check, &coarse)?;
        self.patch_backward(&self.coarse, &coarse, smoothness, check)?;
        if let Some(fine) = self.fine_net() {
            let rngs = Some(&mut rays.rngs[..]);
            let pass = self.fine_pass(fine, ws, &rays.rays, &coarse, rngs, &backgrounds)?;
            self.check_forward(check, &pass)?;
            self.patch_backward(fine, &pass, smoothness, check)?;
        }
        Ok(())
    }

    /// The backward of a pass of patches: the depth smoothness's gradient times `scale`
    /// (depths in units of `unit`) and no colour loss.
    fn patch_backward(
        &self,
        net: &GpuVanillaNet,
        pass: &Pass,
        (scale, unit): (f32, f32),
        check: &FiniteCheck,
    ) -> Result<()> {
        let gpu = &self.gpu;
        let n = pass.samples.len;
        let (d_sigma, d_rgb) = (gpu.zeros(n), gpu.zeros(n * 3));
        let buffers = (&pass.weights, &d_sigma);
        add_depth_smoothness(gpu, &pass.samples, buffers, unit, scale, LastStep::Infinite);
        if let Some(free) = &self.model.config.free_nerf {
            loss::add_occlusion(gpu, free, &pass.samples, &d_sigma);
        }
        check_device(gpu, check, "loss.backward", "d_sigma", &d_sigma, n)?;
        let state = (&self.state.values, &self.state.grads);
        net.backward(gpu, state.0, state.1, &pass.acts, &d_sigma, &d_rgb);
        Ok(())
    }

    /// The fine pass of `rays` after their `coarse` one: its samples drawn from the coarse
    /// weights, with `rngs` (training's random draws) on the device; without them
    /// (rendering's evenly spaced draws) and for mip-NeRF's frustums on the host, from
    /// weights read back. Rendering's many small chunks measured faster on the host
    /// (docs/benchmarks.md), a training step faster on the device.
    fn fine_pass(
        &self,
        net: &GpuVanillaNet,
        ws: &mut ChunkWorkspace,
        rays: &RayBatch,
        coarse: &Pass,
        rngs: Option<&mut [Rng]>,
        backgrounds: &Handle,
    ) -> Result<Pass> {
        let gpu = &self.gpu;
        let config = &self.model.config;
        let rngs = match rngs {
            Some(rngs) if !config.integrated => rngs,
            rngs => {
                let weights = gpu.read(&coarse.weights, coarse.samples.len)?;
                let samples = self.model.pack_fine(ws, rays, &weights, rngs);
                return Ok(self.pass(net, samples, backgrounds));
            }
        };
        let (n_c, n_f) = (config.n_coarse, config.n_fine);
        let draws = importance::sorted_draws(rngs, n_f);
        let samples = importance::fine_samples(
            gpu,
            rays,
            &coarse.samples.t,
            &coarse.weights,
            &draws,
            (n_c, n_f),
        );
        // Each sample at its ray's moment (a moving scene's rays carry one).
        let times = (!rays.times.is_empty()).then(|| {
            let per_ray = gpu.upload(&rays.times);
            let s = &samples.samples;
            per_sample(gpu, &per_ray, &s.offsets, s.rays, s.len)
        });
        Ok(self.pass_on_device(net, samples, (None, times.as_ref()), backgrounds))
    }

    /// FreeNeRF: the position encoding's bands visible at `progress` of training, as the
    /// CPU engine's `Model::set_progress` sets them.
    fn set_progress(&mut self, progress: f32) {
        let Some(free) = self.model.config.free_nerf else {
            return;
        };
        let mask = free.band_mask(
            self.model.config.net.position_encoding.frequencies,
            progress,
        );
        self.coarse.set_band_mask(&self.gpu, &mask);
        if let Some(fine) = &mut self.fine {
            fine.set_band_mask(&self.gpu, &mask);
        }
    }

    fn check_forward(&self, check: &FiniteCheck, pass: &Pass) -> Result<()> {
        let n = pass.samples.len;
        check_device(
            &self.gpu,
            check,
            "field.forward",
            "sigma",
            &pass.acts.sigma,
            n,
        )?;
        check_device(
            &self.gpu,
            check,
            "field.forward",
            "rgb",
            &pass.acts.rgb,
            n * 3,
        )
    }

    /// Renders one chunk of rays (bin-midpoint coarse samples, evenly spaced importance
    /// samples, as the CPU engine renders).
    fn render_chunk(&self, rays: &RayBatch, out: &mut [RayOutput]) -> Result<()> {
        let gpu = &self.gpu;
        let mut ws = ChunkWorkspace::default();
        let backgrounds = gpu.upload(rays.backgrounds.as_flattened());
        let samples = self.model.pack_coarse(&mut ws, rays, None);
        let mut pass = self.pass(&self.coarse, samples, &backgrounds);
        if let Some(fine) = self.fine_net() {
            pass = self.fine_pass(fine, &mut ws, rays, &pass, None, &backgrounds)?;
        }
        let values = gpu.read(&pass.out, rays.len() * OUT_WORDS)?;
        for (o, v) in out.iter_mut().zip(values.chunks_exact(OUT_WORDS)) {
            *o = RayOutput {
                rgb: [v[0], v[1], v[2]],
                depth: v[3],
                opacity: v[4],
            };
        }
        Ok(())
    }
}

impl Engine for GpuVanillaEngine {
    fn kind(&self) -> crate::engine::caps::EngineKind {
        crate::engine::caps::EngineKind::Gpu
    }

    fn describe(&self) -> String {
        self.gpu.name.clone()
    }

    fn model_config(&self) -> &ModelConfig {
        &self.config
    }

    fn param_layout(&self) -> &ParamLayout {
        self.model.layout()
    }

    fn buffer_layout(&self) -> ParamLayout {
        self.model.buffer_layout()
    }

    fn train_step(&mut self, data: &Dataset, spec: &StepSpec) -> Result<StepStats> {
        let step = spec.sampling.step;
        self.set_progress(spec.progress);
        let batch = spec.batch_rays.max(1);
        let mut rays = std::mem::take(&mut self.rays);
        let mut ws = std::mem::take(&mut self.ws);
        rays.draw_parallel(data, &spec.sampling, 0..batch as u64);
        self.model.anneal(&mut rays, step);
        let result = (|| -> Result<(f64, f64, usize)> {
            let gpu = &self.gpu;
            let check = FiniteCheck::new(self.check_finite);
            let backgrounds = gpu.upload(rays.rays.backgrounds.as_flattened());
            let targets = gpu.upload(rays.targets.as_flattened());
            let samples = self
                .model
                .pack_coarse(&mut ws, &rays.rays, Some(&mut rays.rngs));
            let coarse = self.pass(&self.coarse, samples, &backgrounds);
            self.check_forward(&check, &coarse)?;
            let coarse_sse =
                self.backward(&self.coarse, &coarse, &backgrounds, &targets, &check)?;
            let mut evaluated = coarse.samples.len;
            let mut fine_sse = None;
            if let Some(fine) = self.fine_net() {
                let rngs = Some(&mut rays.rngs[..]);
                let pass =
                    self.fine_pass(fine, &mut ws, &rays.rays, &coarse, rngs, &backgrounds)?;
                self.check_forward(&check, &pass)?;
                fine_sse = Some(self.backward(fine, &pass, &backgrounds, &targets, &check)?);
                evaluated += pass.samples.len;
            }
            if let Some(reg) = &self.model.config.reg_nerf {
                self.train_patches(data, spec, reg, batch, &mut ws, &check)?;
            }
            check_device(
                gpu,
                &check,
                "field.backward",
                "parameter gradients",
                &self.state.grads,
                self.state.n,
            )?;
            if let Some(e) = check.take(step + 1) {
                return Err(e);
            }
            Ok((
                coarse_sse + fine_sse.unwrap_or(0.0),
                fine_sse.unwrap_or(coarse_sse),
                evaluated,
            ))
        })();
        self.rays = rays;
        self.ws = ws;
        let (sse, final_sse, samples) = match result {
            Ok(r) => r,
            Err(e) => {
                self.state.clear_grads(&self.gpu);
                return Err(e);
            }
        };
        let scale = mean_scale(batch);
        let loss = (sse * scale) as f32;
        let rule = self.model.update_rule();
        // The loss, summed on the host already, is the one error the update checks.
        let errors = self.gpu.upload(&[sse as f32]);
        self.state.finish_step(
            &self.gpu,
            step,
            &errors,
            1,
            (spec.lr, spec.lr),
            scale as f32,
            rule,
        )?;
        let check = FiniteCheck::new(self.check_finite);
        check_device(
            &self.gpu,
            &check,
            "adam",
            "parameters",
            &self.state.values,
            self.state.n,
        )?;
        if let Some(e) = check.take(step + 1) {
            return Err(e);
        }
        Ok(StepStats {
            step: step + 1,
            loss,
            psnr: crate::metrics::psnr_from_mse(final_sse * scale),
            lr: spec.lr,
            rays: batch,
            samples,
        })
    }

    fn render_rays(
        &self,
        rays: &RayBatch,
        out: &mut [RayOutput],
        on_progress: &(dyn Fn(usize) + Sync),
    ) {
        render_in_chunks(rays, out, self.chunk_rays, on_progress, |part, out| {
            if let Err(e) = self.render_chunk(part, out) {
                fail_rays(&e, out);
            }
        });
    }

    /// The fine network's density (the coarse one's without a fine network).
    fn density(&self, positions: &[f32], time: Option<f32>, out: &mut [f32]) {
        let net = self.fine.as_ref().unwrap_or(&self.coarse);
        density_in_chunks(positions, out, DENSITY_CHUNK, |p, o| {
            let (gpu, n) = (&self.gpu, o.len());
            let at = DeviceMoments::At(time.unwrap_or(0.0));
            let sigma = net.density(gpu, &self.state.values, &gpu.upload(p), at, n);
            o.copy_from_slice(&gpu.read(&sigma, n)?);
            Ok(())
        });
    }

    fn state(&self) -> EngineState {
        self.state.state(&self.gpu, Vec::new())
    }

    fn set_state(&mut self, state: EngineState) -> Result<()> {
        self.state.set_state(&self.gpu, &state, 0)
    }

    fn occupancy(&self) -> Option<f64> {
        None
    }

    /// Every parameter goes through the device's dense Adam pass.
    fn touched_fraction(&self) -> f64 {
        1.0
    }
}
