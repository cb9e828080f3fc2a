//! The vanilla NeRF model: a coarse and (optionally) a fine network of the same shape with
//! separate weights, sharing one flat parameter vector `[coarse | fine]`.

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::free_nerf::FreeNerf;
use super::reg_nerf::RegNerf;
use super::unseen_patches::{self, PatchDraw};
use super::{Model, PassTotals, StepInput, Worker};
use crate::data::pixels::TrainingRays;
use crate::field::{VanillaConfig, VanillaNet, VanillaWorkspace};
use crate::math::{length, scale};
use crate::nn::{GradBuffer, Grads, ParamLayout};
use crate::render::depth_smoothness::{steps_for_backward, PatchBackward};
use crate::render::loss::LossBackward;
use crate::render::sampling::{merge_sorted, sample_pdf, stratified};
use crate::render::volume::{composite_packed, depth_deltas};
use crate::rng::Rng;
use crate::stage::finite::{check_outputs, FiniteCheck};
use crate::stage::{Field, FieldOutput, PackedSamples, RayBatch, RayOutput};

/// Network shape and samples per ray.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct VanillaModelConfig {
    pub net: VanillaConfig,
    /// Stratified samples per ray for the coarse network (paper: 64).
    pub n_coarse: usize,
    /// Importance samples per ray for the fine network (paper: 128); 0 disables the fine
    /// network (the "no hierarchical sampling" ablation).
    pub n_fine: usize,
    /// mip-NeRF: every sample is the conical frustum of its pixel between it and its
    /// neighbours, encoded by the integrated positional encoding (see
    /// `encoding::integrated`), so no sample reads detail finer than its pixel.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub integrated: bool,
    /// mip-NeRF: one network answers both the coarse and the fine samples (its
    /// integrated encoding tells the scales apart); else a fine network of its own.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub shared_network: bool,
    /// FreeNeRF's few-view regularisers (`--preset freenerf`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub free_nerf: Option<FreeNerf>,
    /// RegNeRF's few-view regularisers (`--preset regnerf`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reg_nerf: Option<RegNerf>,
}

impl VanillaModelConfig {
    pub fn hierarchical(&self) -> bool {
        self.n_fine > 0
    }
    /// Field evaluations per ray: coarse samples plus, with a fine network, all of them again.
    pub fn evals_per_ray(&self) -> usize {
        if self.hierarchical() {
            2 * self.n_coarse + self.n_fine
        } else {
            self.n_coarse
        }
    }
}

#[derive(Clone, Debug)]
pub struct VanillaModel {
    pub config: VanillaModelConfig,
    pub coarse: VanillaNet,
    pub fine: Option<VanillaNet>,
    /// Names of all tensors, with offsets into the flat vector.
    pub layout: ParamLayout,
}

impl VanillaModel {
    pub fn new(config: VanillaModelConfig) -> Self {
        let coarse = VanillaNet::new(config.net.clone(), "coarse.");
        let fine = (config.hierarchical() && !config.shared_network)
            .then(|| VanillaNet::new(config.net.clone(), "fine."));
        let mut layout = coarse.layout.clone();
        if let Some(f) = &fine {
            for t in &f.layout.tensors {
                layout.push(t.name.clone(), &t.shape);
            }
        }
        VanillaModel {
            config,
            coarse,
            fine,
            layout,
        }
    }

    /// Fresh weights: Glorot-uniform, zero biases, a deformation's last layer zero;
    /// deterministic in `seed`.
    pub fn init_params(&self, seed: u64) -> Vec<f32> {
        let mut params = self.layout.init_glorot(&mut Rng::new(seed ^ 0x5eed));
        let coarse = self.coarse_range();
        self.coarse.finish_init(&mut params[coarse]);
        if let Some(fine) = &self.fine {
            fine.finish_init(&mut params[self.coarse.num_params()..]);
        }
        params
    }

    /// Forward multiply-adds per ray.
    pub fn macs_per_ray(&self) -> usize {
        self.coarse.macs_per_sample() * self.config.evals_per_ray()
    }
}

// ---------------------------------------------------------------------------------------
// The paper's two-pass renderer for a chunk of rays: stratified samples through the coarse
// network, importance samples from its weights, then the fine network on the sorted union.
//
// Work mapping: a chunk of `r` rays is processed by one thread start to finish, in its own
// [`ChunkWorkspace`]; in training the coarse pass runs forward and backward before the fine
// pass runs, so both share one set of activation buffers. Every ray carries its own random
// stream, so results do not depend on how rays are grouped into chunks or threads.

/// Reused buffers of one thread.
#[derive(Default, Debug)]
pub struct ChunkWorkspace {
    /// Training: the chunk's rays, targets and random streams.
    pub rays: TrainingRays,
    net: VanillaWorkspace,
    samples: PackedSamples,
    t_coarse: Vec<f32>,
    t_fine: Vec<f32>,
    t_new: Vec<f32>,
    weights: Vec<f32>,
    cdf: Vec<f32>,
    outputs: Vec<RayOutput>,
    loss: LossBackward,
    patch: PatchBackward,
    /// A patch's sample steps as its backward takes them (`steps_for_backward`).
    patch_dt: Vec<f32>,
}

/// What a training chunk's rays are.
#[derive(Clone, Copy, Debug)]
enum ChunkRays {
    /// Photo rays, matched to their pixels.
    Photos,
    /// Whole patches from poses no photo was taken from (RegNeRF): no colour to match,
    /// their depths kept smooth, the gradient times `scale`, depths in units of `unit`.
    Patches { scale: f32, unit: f32 },
}

/// Stratified depths of every ray (`r x n`, bin midpoints without random streams).
fn coarse_samples(
    ws: &mut ChunkWorkspace,
    rays: &RayBatch,
    n: usize,
    mut rngs: Option<&mut [Rng]>,
) {
    ws.t_coarse.resize(rays.len() * n, 0.0);
    for (k, t) in ws.t_coarse.chunks_exact_mut(n).enumerate() {
        stratified(
            rays.near,
            rays.far,
            rngs.as_deref_mut().map(|g| &mut g[k]),
            t,
        );
    }
}

/// Draws the importance samples from the coarse weights (in `ws.weights`) and merges them
/// with the coarse samples into `ws.t_fine`.
fn fine_samples(
    ws: &mut ChunkWorkspace,
    r: usize,
    n_c: usize,
    n_f: usize,
    mut rngs: Option<&mut [Rng]>,
) {
    ws.t_fine.resize(r * (n_c + n_f), 0.0);
    ws.t_new.resize(n_f, 0.0);
    for k in 0..r {
        let tc = &ws.t_coarse[k * n_c..][..n_c];
        sample_pdf(
            tc,
            &ws.weights[k * n_c..][..n_c],
            rngs.as_deref_mut().map(|g| &mut g[k]),
            &mut ws.t_new,
            &mut ws.cdf,
        );
        ws.t_new.sort_unstable_by(f32::total_cmp);
        merge_sorted(
            tc,
            &ws.t_new,
            &mut ws.t_fine[k * (n_c + n_f)..][..n_c + n_f],
        );
    }
}

/// Packs depths `t` (`r x spr`) of `rays` as samples: positions `o + t d`, the paper's
/// deltas, one unit view direction per ray; `integrated`: each sample the Gaussian of its
/// conical frustum (mean as position, covariance diagonal in `variances`).
fn pack(samples: &mut PackedSamples, rays: &RayBatch, t: &[f32], spr: usize, integrated: bool) {
    let r = rays.len();
    samples.clear();
    samples.samples_per_dir = spr;
    samples.t.extend_from_slice(&t[..r * spr]);
    samples.dt.resize(r * spr, 0.0);
    for k in 0..r {
        let (o, d) = (rays.origins[k], rays.dirs[k]);
        let tk = &t[k * spr..][..spr];
        depth_deltas(tk, length(d), &mut samples.dt[k * spr..][..spr]);
        if integrated {
            push_frustums(samples, rays, k, tk);
        } else {
            for &tt in tk {
                samples
                    .positions
                    .push([o[0] + tt * d[0], o[1] + tt * d[1], o[2] + tt * d[2]]);
            }
        }
        if let Some(&time) = rays.times.get(k) {
            samples.times.extend(std::iter::repeat_n(time, spr));
        }
        let v = rays.view_dirs[k];
        samples.dirs.push(scale(v, 1.0 / length(v)));
        samples.offsets.push((k + 1) * spr);
    }
}

/// mip-NeRF's samples of ray `k` at depths `tk` (sorted): each is the frustum from its
/// depth to the next one's (the interval compositing gives it; the last as long as the
/// one before), with the ray's pixel radius (per unit of `t`: the metric radius times
/// `|d|`; none for rays without footprints).
fn push_frustums(samples: &mut PackedSamples, rays: &RayBatch, k: usize, tk: &[f32]) {
    use crate::encoding::integrated::{diagonal_covariance, frustum_gaussian};
    let (o, d) = (rays.origins[k], rays.dirs[k]);
    let radius = rays.radii.get(k).map_or(0.0, |r| match rays.cylinders {
        true => *r,
        false => r * length(d),
    });
    let n = tk.len();
    for i in 0..n {
        let length = match i + 1 < n {
            true => tk[i + 1] - tk[i],
            false if n > 1 => tk[i] - tk[i - 1],
            false => 0.0,
        };
        let (t0, t1) = (tk[i], tk[i] + length);
        let (mean, var_t, var_r) = frustum_gaussian(t0, t1, radius, rays.cylinders);
        samples
            .positions
            .push([o[0] + mean * d[0], o[1] + mean * d[1], o[2] + mean * d[2]]);
        samples
            .variances
            .extend_from_slice(&diagonal_covariance(d, var_t, var_r));
    }
}

/// Evaluates `net` at depths `t` (`r x spr`) and composites each ray into `ws.outputs`,
/// leaving the weights in `ws.weights` and the activations (the context) in `ws.net`.
#[allow(clippy::too_many_arguments)]
fn pass_forward(
    net: &VanillaNet,
    params: &[f32],
    rays: &RayBatch,
    t: &[f32],
    spr: usize,
    integrated: bool,
    ws: &mut ChunkWorkspace,
    check: &FiniteCheck,
) {
    let r = rays.len();
    pack(&mut ws.samples, rays, t, spr, integrated);
    ws.weights.resize(r * spr, 0.0);
    ws.outputs.resize(r, RayOutput::default());
    let field = net.forward(params, ws.samples.field_input(), &mut ws.net);
    check.check("field.forward", "sigma", field.sigma);
    check.check("field.forward", "rgb", field.rgb);
    composite_packed(
        &ws.samples,
        field,
        &rays.backgrounds,
        &mut ws.weights,
        &mut ws.outputs,
    );
    check_outputs(check, &ws.weights, &ws.outputs);
}

/// Loss of the last pass against `targets`, its backward through compositing and the
/// network (gradients of the summed squared error, of FreeNeRF's occlusion penalty when
/// given, and of RegNeRF's depth smoothness for patches, into `grads`). Returns the pass's
/// sum of squared errors.
#[allow(clippy::too_many_arguments)]
fn pass_backward(
    net: &VanillaNet,
    params: &[f32],
    rays: &RayBatch,
    targets: &[[f32; 3]],
    (occlusion, rays_are): (Option<&FreeNerf>, ChunkRays),
    ws: &mut ChunkWorkspace,
    grads: &mut Grads,
    check: &FiniteCheck,
) -> f64 {
    let n = ws.samples.len();
    let field = FieldOutput {
        sigma: &ws.net.sigma[..n],
        rgb: &ws.net.rgb[..n * 3],
    };
    let sse = ws
        .loss
        .run(&ws.samples, field, &rays.backgrounds, &ws.outputs, targets);
    if let Some(free) = occlusion {
        let spr = ws.samples.samples_per_dir;
        ws.loss.add_penalty(|d_sigma| {
            free.add_occlusion(field.sigma, spr, d_sigma);
        });
    }
    if let ChunkRays::Patches { scale, unit } = rays_are {
        add_patch_smoothness(ws, scale, unit);
    }
    check.check("loss.backward", "d_sigma", ws.loss.field_grad().d_sigma);
    check.check("loss.backward", "d_rgb", ws.loss.field_grad().d_rgb);
    net.backward(params, &mut ws.net, ws.loss.field_grad(), grads);
    sse
}

/// Patches have no photo: each ray's target is what the last pass rendered, so they add
/// no colour loss.
fn keep_patch_colours(rays_are: ChunkRays, batch: &mut TrainingRays, ws: &ChunkWorkspace) {
    if let ChunkRays::Patches { .. } = rays_are {
        for (target, out) in batch.targets.iter_mut().zip(&ws.outputs) {
            *target = out.rgb;
        }
    }
}

/// RegNeRF's depth smoothness of the last pass's rays (whole patches, in order), its
/// gradient times `scale` into the loss's density gradient.
fn add_patch_smoothness(ws: &mut ChunkWorkspace, scale: f32, unit: f32) {
    let ChunkWorkspace {
        samples,
        weights,
        loss,
        patch,
        patch_dt,
        ..
    } = ws;
    let spr = samples.samples_per_dir;
    steps_for_backward(&samples.dt, spr, patch_dt);
    loss.add_penalty(|d_sigma| {
        patch.add_patches(samples, 0, (patch_dt, weights), unit, scale, d_sigma);
    });
}

impl VanillaModel {
    /// For an engine that runs the networks elsewhere (the GPU engine): the paper's coarse
    /// samples of `rays` (stratified with the rays' own streams when given, bin midpoints
    /// otherwise), packed with one unit view direction per ray.
    pub fn pack_coarse<'w>(
        &self,
        ws: &'w mut ChunkWorkspace,
        rays: &RayBatch,
        rngs: Option<&mut [Rng]>,
    ) -> &'w PackedSamples {
        let n_c = self.config.n_coarse;
        coarse_samples(ws, rays, n_c, rngs);
        pack(
            &mut ws.samples,
            rays,
            &ws.t_coarse,
            n_c,
            self.config.integrated,
        );
        &ws.samples
    }

    /// After [`pack_coarse`](Self::pack_coarse): the fine pass's samples (importance
    /// samples from the coarse compositing weights `coarse_weights`, `rays x n_coarse`,
    /// merged with the coarse ones), packed.
    pub fn pack_fine<'w>(
        &self,
        ws: &'w mut ChunkWorkspace,
        rays: &RayBatch,
        coarse_weights: &[f32],
        rngs: Option<&mut [Rng]>,
    ) -> &'w PackedSamples {
        let (n_c, n_f) = (self.config.n_coarse, self.config.n_fine);
        ws.weights.clear();
        ws.weights.extend_from_slice(coarse_weights);
        fine_samples(ws, rays.len(), n_c, n_f, rngs);
        pack(
            &mut ws.samples,
            rays,
            &ws.t_fine,
            n_c + n_f,
            self.config.integrated,
        );
        &ws.samples
    }

    /// RegNeRF's sample-space annealing: training rays at `step` sample a range shrunk
    /// about the middle of `[near, far]`.
    pub fn anneal(&self, rays: &mut TrainingRays, step: u64) {
        if let Some(reg) = &self.config.reg_nerf {
            (rays.rays.near, rays.rays.far) =
                reg.sampled_range(rays.rays.near, rays.rays.far, step);
        }
    }

    fn coarse_range(&self) -> std::ops::Range<usize> {
        0..self.coarse.num_params()
    }

    /// The network of the fine pass and its parameters' range: its own, or the coarse
    /// one's when they are shared (`None`: no fine pass).
    pub fn fine_pass(&self) -> Option<(&VanillaNet, std::ops::Range<usize>)> {
        match &self.fine {
            Some(fine) => Some((fine, self.coarse.num_params()..self.layout.total)),
            None if self.config.hierarchical() => Some((&self.coarse, self.coarse_range())),
            None => None,
        }
    }

    /// One training chunk of photo rays (the rays in `ws.rays`): forward and backward of
    /// both passes, gradients of the summed squared errors into `grads`. Returns the
    /// squared-error sums of the coarse and the fine pass.
    pub fn train_chunk(
        &self,
        params: &[f32],
        ws: &mut ChunkWorkspace,
        grads: &mut GradBuffer,
        check: &FiniteCheck,
    ) -> (f64, f64) {
        self.train_rays(params, ws, grads, check, ChunkRays::Photos)
    }

    /// [`train_chunk`](Self::train_chunk) for photo rays or patches.
    fn train_rays(
        &self,
        params: &[f32],
        ws: &mut ChunkWorkspace,
        grads: &mut GradBuffer,
        check: &FiniteCheck,
        rays_are: ChunkRays,
    ) -> (f64, f64) {
        let (n_c, n_f) = (self.config.n_coarse, self.config.n_fine);
        let integrated = self.config.integrated;
        let p_coarse = &params[self.coarse_range()];
        let mut batch = std::mem::take(&mut ws.rays);
        let r = batch.len();
        coarse_samples(ws, &batch.rays, n_c, Some(&mut batch.rngs));
        let t = std::mem::take(&mut ws.t_coarse);
        pass_forward(
            &self.coarse,
            p_coarse,
            &batch.rays,
            &t,
            n_c,
            integrated,
            ws,
            check,
        );
        let penalties = (self.config.free_nerf.as_ref(), rays_are);
        keep_patch_colours(rays_are, &mut batch, ws);
        let coarse_sse = pass_backward(
            &self.coarse,
            p_coarse,
            &batch.rays,
            &batch.targets,
            penalties,
            ws,
            &mut grads.window(self.coarse_range()),
            check,
        );
        ws.t_coarse = t;
        let mut fine_sse = 0.0;
        if let Some((fine, range)) = self.fine_pass() {
            let p_fine = &params[range.clone()];
            fine_samples(ws, r, n_c, n_f, Some(&mut batch.rngs));
            let t = std::mem::take(&mut ws.t_fine);
            let spr = n_c + n_f;
            pass_forward(fine, p_fine, &batch.rays, &t, spr, integrated, ws, check);
            keep_patch_colours(rays_are, &mut batch, ws);
            fine_sse = pass_backward(
                fine,
                p_fine,
                &batch.rays,
                &batch.targets,
                penalties,
                ws,
                &mut grads.window(range),
                check,
            );
            ws.t_fine = t;
        }
        ws.rays = batch;
        (coarse_sse, fine_sse)
    }
}

impl Model for VanillaModel {
    type Workspace = ChunkWorkspace;
    type StepBuffers = ();

    fn layout(&self) -> &ParamLayout {
        &self.layout
    }

    fn init_params(&self, seed: u64) -> Vec<f32> {
        VanillaModel::init_params(self, seed)
    }

    /// FreeNeRF: the position encoding's bands visible at this point of training.
    fn set_progress(&mut self, progress: f32) {
        let Some(free) = self.config.free_nerf else {
            return;
        };
        let bands = self.config.net.position_encoding.frequencies;
        let mask = free.band_mask(bands, progress);
        if let Some(fine) = &mut self.fine {
            fine.band_mask.clone_from(&mask);
        }
        self.coarse.band_mask = mask;
    }

    /// The paper's step: `batch_rays` rays in chunks of `chunk_rays`, chunk `k` on worker
    /// `k mod W`; ray `g` of the step is the same ray whatever the chunking.
    fn train_pass(
        &self,
        input: &StepInput,
        _: &mut (),
        workers: &mut [Worker<ChunkWorkspace>],
    ) -> PassTotals {
        let batch = input.batch_rays;
        let chunk = input.chunk_rays.min(batch).max(1);
        let n_chunks = batch.div_ceil(chunk);
        let n_workers = workers.len();
        let step = input.sampling.step;
        let sums: Vec<(f64, f64)> = workers
            .par_iter_mut()
            .enumerate()
            .map(|(w, worker)| {
                let (mut coarse, mut fine) = (0.0, 0.0);
                for c in (w..n_chunks).step_by(n_workers) {
                    let rays = (c * chunk) as u64..((c + 1) * chunk).min(batch) as u64;
                    worker.ws.rays.draw(input.data, &input.sampling, rays);
                    self.anneal(&mut worker.ws.rays, step);
                    let (a, b) = self.train_chunk(
                        input.params,
                        &mut worker.ws,
                        &mut worker.grads,
                        input.check,
                    );
                    coarse += a;
                    fine += b;
                }
                if let Some(reg) = &self.config.reg_nerf {
                    let patches = reg.patches(batch);
                    let rays_are = ChunkRays::Patches {
                        scale: reg.smoothness_scale(step, batch, patches),
                        unit: input.data.far - input.data.near,
                    };
                    let stride = unseen_patches::stride_for(input.data.views[0].camera.width);
                    for k in (w..patches).step_by(n_workers) {
                        let draw = PatchDraw {
                            seed: input.sampling.seed,
                            step,
                            k: k as u64,
                        };
                        unseen_patches::draw_patch(input.data, draw, stride, &mut worker.ws.rays);
                        self.anneal(&mut worker.ws.rays, step);
                        self.train_rays(
                            input.params,
                            &mut worker.ws,
                            &mut worker.grads,
                            input.check,
                            rays_are,
                        );
                    }
                }
                (coarse, fine)
            })
            .collect();
        let (coarse, fine) = sums.iter().fold((0.0, 0.0), |(c, f), s| (c + s.0, f + s.1));
        PassTotals {
            sse: coarse + fine,
            final_sse: if self.config.hierarchical() {
                fine
            } else {
                coarse
            },
            rays: batch,
            samples: batch * self.config.evals_per_ray(),
        }
    }

    /// Bin-midpoint coarse samples, evenly spaced importance samples, the fine network's
    /// result (the coarse one without a fine network).
    fn render_chunk(
        &self,
        params: &[f32],
        rays: &RayBatch,
        ws: &mut ChunkWorkspace,
        out: &mut [RayOutput],
    ) {
        let r = rays.len();
        let (n_c, n_f) = (self.config.n_coarse, self.config.n_fine);
        let integrated = self.config.integrated;
        let check = FiniteCheck::default();
        coarse_samples(ws, rays, n_c, None);
        let t = std::mem::take(&mut ws.t_coarse);
        let p_coarse = &params[self.coarse_range()];
        pass_forward(
            &self.coarse,
            p_coarse,
            rays,
            &t,
            n_c,
            integrated,
            ws,
            &check,
        );
        ws.t_coarse = t;
        if let Some((fine, range)) = self.fine_pass() {
            fine_samples(ws, r, n_c, n_f, None);
            let t = std::mem::take(&mut ws.t_fine);
            let spr = n_c + n_f;
            pass_forward(fine, &params[range], rays, &t, spr, integrated, ws, &check);
            ws.t_fine = t;
        }
        out[..r].copy_from_slice(&ws.outputs[..r]);
    }

    /// The fine pass's density (the coarse one's without a fine pass), at points.
    fn density(
        &self,
        params: &[f32],
        positions: &[f32],
        time: Option<f32>,
        ws: &mut ChunkWorkspace,
        out: &mut [f32],
    ) {
        let (net, range) = self
            .fine_pass()
            .unwrap_or((&self.coarse, self.coarse_range()));
        net.density_at(&params[range], positions, time, &mut ws.net, out);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::depth_smoothness::PATCH_RAYS;

    fn tiny_model() -> VanillaModel {
        tiny_model_of("demo")
    }

    fn tiny_model_of(preset: &str) -> VanillaModel {
        let (mut config, _) = crate::presets::build(preset).expect("preset");
        config.net.depth = 4;
        config.net.skip = Some(1);
        config.net.width = 16;
        config.net.view_width = 8;
        config.n_coarse = 8;
        config.n_fine = 8;
        VanillaModel::new(config)
    }

    fn rays(n: usize) -> TrainingRays {
        let mut rng = Rng::new(9);
        let mut t = TrainingRays {
            rays: RayBatch::new(2.0, 6.0),
            ..TrainingRays::default()
        };
        for k in 0..n {
            let dir = [rng.range(-0.3, 0.3), 1.0, rng.range(-0.3, 0.3)];
            let bg = [rng.uniform(), rng.uniform(), rng.uniform()];
            let ray = crate::camera::Ray {
                origin: [0.0, -4.0, 0.5],
                dir,
            };
            t.rays
                .push_with_radius(ray, dir, bg, k as u64, 0.002 * (1 + k % 3) as f32);
            t.targets
                .push([(k % 5) as f32 * 0.2, (k % 3) as f32 * 0.3, 0.5]);
            t.rngs.push(Rng::for_stream(1, 2, k as u64));
        }
        t
    }

    /// Chunking is an implementation detail: one chunk of 8 rays and two of 4 give the same
    /// loss and gradients, in training and in rendering.
    #[test]
    fn results_do_not_depend_on_chunking() {
        results_do_not_depend_on_chunking_of(&tiny_model());
        results_do_not_depend_on_chunking_of(&tiny_model_of("mip"));
    }

    /// mip-NeRF's model is one network (the fine pass asks the coarse one),
    /// and its samples are frustums: means on the ray, variances growing with the pixel's
    /// radius, the depth and the gap to the neighbours.
    #[test]
    fn mip_model_shares_one_network_and_samples_frustums() {
        let (mip, paper) = (tiny_model_of("mip"), tiny_model_of("paper"));
        assert!(mip.fine.is_none() && mip.config.hierarchical());
        assert_eq!(mip.layout.total, mip.coarse.num_params());
        assert_eq!(paper.layout.total, 2 * paper.coarse.num_params());
        let params = mip.init_params(1);
        let mut ws = ChunkWorkspace {
            rays: rays(4),
            ..ChunkWorkspace::default()
        };
        let mut grads = GradBuffer::new(params.len());
        let (coarse, fine) = mip.train_chunk(&params, &mut ws, &mut grads, &FiniteCheck::default());
        assert!(coarse > 0.0 && fine > 0.0);
        assert!(grads.values.iter().any(|g| *g != 0.0));

        let batch = rays(3).rays;
        let t = [2.5f32, 3.0, 3.5, 5.0];
        let mut samples = PackedSamples::default();
        pack(&mut samples, &batch, &[t, t, t].concat(), 4, true);
        assert_eq!(samples.variances.len(), 12 * 3);
        for k in 0..3 {
            let (o, d) = (batch.origins[k], batch.dirs[k]);
            for (i, tt) in t.iter().enumerate() {
                let p = samples.positions[k * 4 + i];
                // The mean sits a little beyond the middle of the interval (its far end
                // is wider).
                let along = crate::math::dot(crate::math::sub(p, o), d) / crate::math::dot(d, d);
                let end = t.get(i + 1).copied().unwrap_or(6.5);
                let middle = 0.5 * (tt + end);
                assert!(along >= middle && along < end, "{along} in {tt}..{end}");
            }
            let var = |i: usize| -> f32 { samples.variances[(k * 4 + i) * 3..][..3].iter().sum() };
            // Wider gaps, larger frustums; the wider pixel of ray 2 too.
            assert!(var(3) > var(1) && var(0) < var(3));
        }
        let trace = |k: usize| -> f32 { samples.variances[k * 12..][..3].iter().sum() };
        assert!(trace(2) > trace(0), "a wider pixel, a wider frustum");
        pack(&mut samples, &batch, &[t, t, t].concat(), 4, false);
        assert!(samples.variances.is_empty());
    }

    /// FreeNeRF hides the fine bands early in training (other outputs than the paper
    /// model's with the same weights) and shows them all after its reveal (the same
    /// photometric error), while its occlusion penalty still adds to the gradients.
    #[test]
    fn free_nerf_masks_bands_early_and_penalises_near_density() {
        let mut free = tiny_model_of("freenerf");
        let plain = tiny_model_of("paper");
        let params = plain.init_params(4);
        assert_eq!(free.layout.total, params.len());
        let run = |m: &VanillaModel| {
            let mut ws = ChunkWorkspace {
                rays: rays(6),
                ..ChunkWorkspace::default()
            };
            let mut grads = GradBuffer::new(params.len());
            let (c, f) = m.train_chunk(&params, &mut ws, &mut grads, &FiniteCheck::default());
            (c + f, grads.values)
        };
        let (plain_sse, plain_grads) = run(&plain);
        free.set_progress(0.0);
        assert_eq!(free.coarse.band_mask[0], 1.0);
        assert!(free.coarse.band_mask[1..].iter().all(|&m| m == 0.0));
        assert_eq!(
            free.fine.as_ref().map(|f| &f.band_mask),
            Some(&free.coarse.band_mask)
        );
        let (early_sse, _) = run(&free);
        assert_ne!(early_sse, plain_sse);
        free.set_progress(0.95);
        assert!(free.coarse.band_mask.iter().all(|&m| m == 1.0));
        let (late_sse, late_grads) = run(&free);
        assert_eq!(late_sse, plain_sse);
        assert_ne!(late_grads, plain_grads);
    }

    fn results_do_not_depend_on_chunking_of(model: &VanillaModel) {
        let params = model.init_params(3);
        let all = rays(8);
        let run = |ranges: &[std::ops::Range<usize>]| {
            let mut grads = GradBuffer::new(params.len());
            let mut ws = ChunkWorkspace::default();
            let mut sse = 0.0;
            let mut rendered = vec![RayOutput::default(); 8];
            for r in ranges {
                ws.rays = TrainingRays {
                    rays: all.rays.slice(r.clone()),
                    targets: all.targets[r.clone()].to_vec(),
                    rngs: all.rngs[r.clone()].to_vec(),
                };
                let (c, f) =
                    model.train_chunk(&params, &mut ws, &mut grads, &FiniteCheck::default());
                sse += c + f;
                let chunk = all.rays.slice(r.clone());
                model.render_chunk(&params, &chunk, &mut ws, &mut rendered[r.clone()]);
            }
            (sse, grads.values, rendered)
        };
        let (sse_a, grads_a, out_a) = run(std::slice::from_ref(&(0..8)));
        let (sse_b, grads_b, out_b) = run(&[0..4, 4..8]);
        assert!(
            (sse_a - sse_b).abs() < 1e-6 * sse_a.max(1.0),
            "{sse_a} vs {sse_b}"
        );
        let norm: f32 = grads_a.iter().map(|g| g * g).sum::<f32>().sqrt();
        let diff: f32 = grads_a
            .iter()
            .zip(&grads_b)
            .map(|(x, y)| (x - y) * (x - y))
            .sum::<f32>()
            .sqrt();
        assert!(
            norm > 0.0 && diff <= 1e-5 * norm,
            "gradient differs by {diff} (norm {norm})"
        );
        for (x, y) in out_a.iter().zip(&out_b) {
            for c in 0..3 {
                assert!((x.rgb[c] - y.rgb[c]).abs() < 1e-6);
            }
        }
    }

    /// A patch adds no colour loss: at weight 0 its gradient is zero, at a positive one it
    /// is not (the depth smoothness's own gradient is tested in `render::depth_smoothness`).
    #[test]
    fn patches_add_depth_smoothness_alone() {
        let model = tiny_model_of("regnerf");
        let params = model.init_params(5);
        let mut ws = ChunkWorkspace::default();
        let mut grads = GradBuffer::new(params.len());
        ws.rays = rays(PATCH_RAYS);
        let check = FiniteCheck::default();
        let zero = ChunkRays::Patches {
            scale: 0.0,
            unit: 4.0,
        };
        model.train_rays(&params, &mut ws, &mut grads, &check, zero);
        let worst = |g: &GradBuffer| g.values.iter().fold(0.0f32, |m, g| m.max(g.abs()));
        assert_eq!(worst(&grads), 0.0);
        let mut grads = GradBuffer::new(params.len());
        ws.rays = rays(PATCH_RAYS);
        let smooth = ChunkRays::Patches {
            scale: 1.0,
            unit: 4.0,
        };
        model.train_rays(&params, &mut ws, &mut grads, &check, smooth);
        assert!(worst(&grads) > 0.0);
    }
}
