//! The optimisation loop: random rays from all training pixels, photometric MSE, Adam with
//! an exponentially decaying learning rate. The vanilla model follows the paper (coarse +
//! fine loss, a fixed number of rays, a central-crop warm-up); the fast model follows
//! Instant-NGP (a fixed number of field samples, random backgrounds, lazy updates of the
//! hash tables, occupancy-grid refreshes every few steps).
//!
//! Work mapping: each rayon thread owns a worker with its own workspaces and gradient
//! buffer. Vanilla: a step's rays are cut into chunks of `chunk_rays`, chunk `k` on worker
//! `k mod W`. Fast: worker `w` draws rays from its own streams until it holds its share of
//! the step's samples. Buffers are summed in worker order, so a run is reproducible for a
//! given seed and thread count. Once the workspaces have grown, a step allocates no buffer
//! that scales with the batch (only a few bookkeeping vectors).

pub mod run;

use std::path::PathBuf;

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::data::scene::{Scene, SceneOptions};
use crate::data::{Background, Dataset};
use crate::error::{NerfError, Result};
use crate::model::{FastModel, FastModelConfig, Model, ModelConfig, VanillaModel};
use crate::nn::adam::{Adam, AdamConfig, DirtyStep};
use crate::nn::grads::GradBuffer;
use crate::render::marched::{train_batch, MarchBatch, MarchWorkspace};
use crate::render::pipeline::{train_chunk, ChunkLoss, ChunkWorkspace, Rays, Targets};
use crate::rng::Rng;

/// Everything that defines a training run; saved as `config.json` in the run folder.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TrainConfig {
    /// Scene folder (any format `data::scene` reads).
    pub data: PathBuf,
    /// How to read the scene (format, LLFF treatment, held-out images).
    #[serde(default)]
    pub scene: SceneOptions,
    /// Preset the model came from (see `presets`; "fast" for the fast model).
    pub preset: String,
    pub model: ModelConfig,
    /// Vanilla model: rays per step (paper: 4096; 1024 is the common smaller setting and
    /// our default). The fast model sets samples per step instead.
    pub batch_rays: usize,
    /// Steps to train; the learning rate decays from `lr_init` to `lr_final` over them.
    pub steps: u64,
    pub lr_init: f32,
    pub lr_final: f32,
    pub adam: AdamConfig,
    /// For this many first steps, rays come from the central `precrop_fraction` of each image.
    pub precrop_steps: u64,
    pub precrop_fraction: f32,
    pub background: Background,
    /// Area-average downscale of the images.
    pub downscale: usize,
    /// Keep this many training views, spread evenly (`None`: all).
    pub train_views: Option<usize>,
    pub seed: u64,
    /// Rays per work unit (bounds memory: activations of one chunk per thread).
    pub chunk_rays: usize,
    /// Render a validation image every this many steps (0: never).
    pub val_every: u64,
    /// Validation images are rendered at 1/val_downscale of the training resolution.
    pub val_downscale: usize,
    /// Save a checkpoint every this many steps (and always at the end).
    pub checkpoint_every: u64,
}

impl TrainConfig {
    /// Defaults for a preset, following the paper / reference code.
    pub fn from_preset(data: PathBuf, preset: &str) -> Result<Self> {
        let (model, train_views) = crate::presets::build(preset)?;
        Ok(TrainConfig {
            data,
            scene: SceneOptions::default(),
            preset: preset.to_string(),
            model: ModelConfig::Vanilla(model),
            batch_rays: 1024,
            steps: 200_000,
            lr_init: 5e-4,
            lr_final: 5e-5,
            adam: AdamConfig::default(),
            precrop_steps: 500,
            precrop_fraction: 0.5,
            background: Background::White,
            downscale: 1,
            train_views,
            seed: 0,
            chunk_rays: 64,
            val_every: 1000,
            val_downscale: 4,
            checkpoint_every: 1000,
        })
    }

    /// Defaults of the fast model, after Instant-NGP: Adam (0.9, 0.99, 1e-15) at 1e-2
    /// decaying to 1e-3, random backgrounds, no crop warm-up.
    pub fn fast(data: PathBuf) -> Self {
        TrainConfig {
            data,
            scene: SceneOptions::default(),
            preset: "fast".into(),
            model: ModelConfig::Fast(FastModelConfig::default()),
            batch_rays: 0,
            steps: 5000,
            lr_init: 1e-2,
            lr_final: 1e-3,
            adam: AdamConfig {
                beta1: 0.9,
                beta2: 0.99,
                eps: 1e-15,
            },
            precrop_steps: 0,
            precrop_fraction: 1.0,
            background: Background::Random,
            downscale: 1,
            train_views: None,
            seed: 0,
            chunk_rays: 1024,
            val_every: 500,
            val_downscale: 4,
            checkpoint_every: 500,
        }
    }

    /// The run's scene, read at `1 / (downscale * extra)` of its resolution.
    pub fn open_scene(&self, extra_downscale: usize) -> Result<Scene> {
        Scene::open(
            &self.data,
            &self.scene,
            self.downscale.max(1) * extra_downscale.max(1),
        )
    }

    /// Rejects settings that cannot run, naming the field.
    pub fn validate(&self) -> Result<()> {
        let bad = |m: &str| Err(NerfError::Config(m.to_string()));
        if self.chunk_rays == 0 {
            return bad("chunk_rays must be positive");
        }
        match &self.model {
            ModelConfig::Vanilla(m) => {
                if self.batch_rays == 0 {
                    return bad("batch_rays must be positive");
                }
                if m.n_coarse < 3 {
                    return bad("at least 3 coarse samples per ray are needed");
                }
            }
            ModelConfig::Fast(m) => {
                if m.samples_per_step == 0 || m.batch_samples == 0 {
                    return bad("samples_per_step and batch_samples must be positive");
                }
                if m.field.bound.is_nan() || m.field.bound <= 0.0 || m.occupancy.resolution == 0 {
                    return bad("the scene box and occupancy grid must not be empty");
                }
                if m.steps_per_diagonal.is_nan()
                    || m.steps_per_diagonal < 1.0
                    || m.max_samples_per_ray == 0
                {
                    return bad("steps_per_diagonal must be >= 1 and max_samples_per_ray positive");
                }
            }
        }
        if !(self.lr_init > 0.0 && self.lr_final > 0.0) {
            return bad("learning rates must be positive");
        }
        if !(self.precrop_fraction > 0.0 && self.precrop_fraction <= 1.0) {
            return bad("precrop_fraction must be in (0, 1]");
        }
        if self.downscale == 0 || self.val_downscale == 0 {
            return bad("downscale factors must be at least 1");
        }
        Ok(())
    }

    /// `lr_init * (lr_final / lr_init)^(step / steps)`: exponential decay over the run.
    pub fn learning_rate(&self, step: u64) -> f32 {
        let progress = (step as f64 / self.steps.max(1) as f64).min(1.0);
        (self.lr_init as f64 * (self.lr_final as f64 / self.lr_init as f64).powf(progress)) as f32
    }
}

/// What one step did.
#[derive(Clone, Copy, Debug, Serialize, Deserialize)]
pub struct StepStats {
    /// Steps completed, this one included.
    pub step: u64,
    /// coarse MSE + fine MSE (the paper's loss).
    pub loss: f32,
    /// PSNR of the final (fine, else coarse) pass on this batch.
    pub psnr: f32,
    pub lr: f32,
    /// Rays and field samples in the step.
    pub rays: usize,
    pub samples: usize,
}

struct Worker {
    vanilla: ChunkWorkspace,
    march: MarchWorkspace,
    batch: MarchBatch,
    grads: GradBuffer,
    origins: Vec<f32>,
    dirs: Vec<f32>,
    view_dirs: Vec<f32>,
    backgrounds: Vec<f32>,
    targets: Vec<f32>,
    rngs: Vec<Rng>,
    loss: ChunkLoss,
    rays: usize,
    samples: usize,
}

/// Model, optimiser and data of a run in memory.
pub struct Trainer {
    pub config: TrainConfig,
    pub model: Model,
    pub params: Vec<f32>,
    pub adam: Adam,
    /// Steps completed.
    pub step: u64,
    pub data: Dataset,
    /// Fraction of gradient blocks the last step wrote (the rest skipped reduction and Adam).
    pub touched_fraction: f64,
    workers: Vec<Worker>,
}

/// A training ray: a random pixel, its colour over the ray's background, and the ray's
/// random stream (which also draws its sample positions).
struct DrawnRay {
    /// Origin and direction in ray space (warped for NDC scenes).
    origin: [f32; 3],
    dir: [f32; 3],
    /// The world direction, which colour is conditioned on.
    view_dir: [f32; 3],
    background: [f32; 3],
    target: [f32; 3],
    rng: Rng,
}

/// Ray `stream` of step `step`: a uniformly random training pixel (inside the central
/// `crop` fraction while warming up; among the pixels its mask keeps, if it has one),
/// warped into the scene's ray space.
fn draw_ray(data: &Dataset, cfg: &TrainConfig, step: u64, stream: u64, crop: f32) -> DrawnRay {
    let mut rng = Rng::for_stream(cfg.seed, step, stream);
    let view = &data.views[rng.below(data.views.len())];
    let (w, h) = (view.image.width, view.image.height);
    let (cw, ch) = (
        ((w as f32 * crop) as usize).max(1),
        ((h as f32 * crop) as usize).max(1),
    );
    let (x0, y0) = ((w - cw) / 2, (h - ch) / 2);
    let (i, j) = match &view.kept_pixels {
        Some(kept) => {
            let p = kept[rng.below(kept.len())] as usize;
            (p % w, p / w)
        }
        None => (x0 + rng.below(cw), y0 + rng.below(ch)),
    };
    let ray = view.camera.ray(i, j);
    let (origin, dir) = data.space.warp(ray.origin, ray.dir);
    let background = match cfg.background {
        Background::White => [1.0; 3],
        Background::Black => [0.0; 3],
        Background::Random => [rng.uniform(), rng.uniform(), rng.uniform()],
    };
    DrawnRay {
        origin,
        dir,
        view_dir: ray.dir,
        background,
        target: view.image.composite_pixel(j * w + i, background),
        rng,
    }
}

/// What the workers of one step produced, before the optimiser runs.
struct PassTotals {
    /// The loss of the step.
    loss: f64,
    /// MSE of the final rendering (fine pass for the vanilla model).
    final_mse: f64,
    /// Factor that turns the workers' summed gradients into the gradient of `loss`.
    grad_scale: f32,
    rays: usize,
    samples: usize,
}

impl Trainer {
    /// A fresh run on `data` (its training split).
    pub fn new(config: TrainConfig, data: Dataset) -> Result<Self> {
        config.validate()?;
        if data.views.is_empty() {
            return Err(NerfError::Config("no training views".into()));
        }
        let model = Model::new(config.model.clone());
        let params = model.init_params(config.seed);
        let adam = Adam::new(config.adam, params.len());
        let workers = (0..rayon::current_num_threads().max(1))
            .map(|_| Worker {
                vanilla: ChunkWorkspace::default(),
                march: MarchWorkspace::default(),
                batch: MarchBatch::default(),
                grads: GradBuffer::new(params.len()),
                origins: Vec::new(),
                dirs: Vec::new(),
                view_dirs: Vec::new(),
                backgrounds: Vec::new(),
                targets: Vec::new(),
                rngs: Vec::new(),
                loss: ChunkLoss::default(),
                rays: 0,
                samples: 0,
            })
            .collect();
        Ok(Trainer {
            config,
            model,
            params,
            adam,
            step: 0,
            data,
            touched_fraction: 0.0,
            workers,
        })
    }

    /// One optimisation step. Fails (leaving the parameters untouched) if the loss is not finite.
    pub fn step(&mut self) -> Result<StepStats> {
        let step = self.step;
        for w in &mut self.workers {
            w.grads.clear();
            w.loss = ChunkLoss::default();
            w.rays = 0;
            w.samples = 0;
        }
        let ctx = PassContext {
            cfg: &self.config,
            data: &self.data,
            params: &self.params,
            step,
            crop: if step < self.config.precrop_steps {
                self.config.precrop_fraction
            } else {
                1.0
            },
        };
        let totals = match &self.model {
            Model::Vanilla(m) => vanilla_pass(m, &ctx, &mut self.workers),
            Model::Fast(m) => fast_pass(m, &ctx, &mut self.workers),
        };
        let mut buffers: Vec<GradBuffer> = self
            .workers
            .iter_mut()
            .map(|w| std::mem::replace(&mut w.grads, GradBuffer::new(0)))
            .collect();
        let finite = GradBuffer::reduce_into_first(&mut buffers);
        for (w, b) in self.workers.iter_mut().zip(buffers) {
            w.grads = b;
        }
        self.touched_fraction = self.workers[0].grads.dirty_fraction();
        let loss = totals.loss as f32;
        if !loss.is_finite() || !finite {
            return Err(NerfError::Diverged {
                step: step + 1,
                loss,
            });
        }
        let lr = self.config.learning_rate(step);
        self.apply_gradients(lr, totals.grad_scale);
        self.step += 1;
        if let Model::Fast(m) = &mut self.model {
            let every = m.config.occupancy.update_every.max(1);
            if self.step % every == 0 {
                refresh_occupancy(m, &self.params, self.step, self.config.seed);
            }
        }
        Ok(StepStats {
            step: self.step,
            loss,
            psnr: crate::eval::psnr_from_mse(totals.final_mse),
            lr,
            rays: totals.rays,
            samples: totals.samples,
        })
    }

    /// Adam on the parameters the reduced gradient (in worker 0) touched, scaled by
    /// `scale`; clears the gradient. Hash-table entries update lazily, MLP weights densely
    /// with weight decay.
    fn apply_gradients(&mut self, lr: f32, scale: f32) {
        let (lazy_end, weight_decay) = match &self.model {
            Model::Vanilla(_) => (0, 0.0),
            Model::Fast(m) => (m.field.mlp_range().start, m.config.weight_decay),
        };
        self.adam.step_dirty(
            &mut self.params,
            &mut self.workers[0].grads,
            lr,
            DirtyStep {
                scale,
                lazy_end,
                weight_decay,
            },
        );
    }
}

/// What every worker of a step reads.
struct PassContext<'a> {
    cfg: &'a TrainConfig,
    data: &'a Dataset,
    params: &'a [f32],
    step: u64,
    crop: f32,
}

/// The paper's step: `batch_rays` rays in chunks, chunk `k` on worker `k mod W`.
fn vanilla_pass(model: &VanillaModel, ctx: &PassContext, workers: &mut [Worker]) -> PassTotals {
    let PassContext {
        cfg,
        data,
        params,
        step,
        crop,
    } = *ctx;
    let batch = cfg.batch_rays;
    let chunk = cfg.chunk_rays.min(batch);
    let n_chunks = batch.div_ceil(chunk);
    let n_workers = workers.len();
    let loss_scale = 1.0 / (3 * batch) as f32;
    workers.par_iter_mut().enumerate().for_each(|(w, worker)| {
        for c in (w..n_chunks).step_by(n_workers) {
            let rays = (c * chunk)..((c + 1) * chunk).min(batch);
            worker.draw_rays(data, cfg, step, rays, crop);
            let r = Rays {
                origins: &worker.origins,
                dirs: &worker.dirs,
                view_dirs: Some(&worker.view_dirs),
                backgrounds: &worker.backgrounds,
                near: data.near,
                far: data.far,
            };
            let l = train_chunk(
                model,
                params,
                &r,
                Targets {
                    rgb: &worker.targets,
                    loss_scale,
                },
                &mut worker.rngs,
                &mut worker.vanilla,
                &mut worker.grads.values,
            );
            worker.loss.coarse_sse += l.coarse_sse;
            worker.loss.fine_sse += l.fine_sse;
        }
        worker.grads.mark(0..worker.grads.len());
    });
    let (c, f) = workers.iter().fold((0.0, 0.0), |(c, f), w| {
        (c + w.loss.coarse_sse, f + w.loss.fine_sse)
    });
    let denom = (3 * batch) as f64;
    let (mse_c, mse_f) = (c / denom, f / denom);
    PassTotals {
        loss: mse_c + mse_f,
        final_mse: if model.fine.is_some() { mse_f } else { mse_c },
        grad_scale: 1.0,
        rays: batch,
        samples: batch * model.config.evals_per_ray(),
    }
}

/// The fast model's step: each worker draws rays from its own streams and marches them
/// until it holds its share of `samples_per_step`, evaluating the field every
/// `batch_samples`. Gradients are of the summed squared error, scaled to the mean once
/// the number of rays is known.
fn fast_pass(model: &FastModel, ctx: &PassContext, workers: &mut [Worker]) -> PassTotals {
    let PassContext {
        cfg,
        data,
        params,
        step,
        crop,
    } = *ctx;
    let n_workers = workers.len();
    let budget = model.config.samples_per_step.div_ceil(n_workers);
    // Rays that find no occupied cell add no samples: this bound ends the step when the
    // grid is (nearly) empty instead of drawing rays forever.
    let max_rays = budget.max(64);
    let marcher = model.marcher(data.near, data.far);
    workers.par_iter_mut().enumerate().for_each(|(w, worker)| {
        let mut sse = 0.0;
        worker.batch.clear();
        let mut flush = |worker: &mut Worker| {
            sse += train_batch(
                &model.field,
                params,
                &marcher,
                &worker.batch,
                1.0,
                &mut worker.march,
                &mut worker.grads,
            );
            worker.batch.clear();
        };
        while worker.samples < budget && worker.rays < max_rays {
            let stream = ((w as u64) << 32) | worker.rays as u64;
            let mut ray = draw_ray(data, cfg, step, stream, crop);
            let jitter = ray.rng.uniform();
            worker.samples += worker.batch.push(
                &model.grid,
                &marcher,
                ray.origin,
                ray.dir,
                ray.view_dir,
                ray.background,
                ray.target,
                jitter,
            );
            worker.rays += 1;
            if worker.batch.samples() >= model.config.batch_samples {
                flush(worker);
            }
        }
        if worker.batch.rays() > 0 {
            flush(worker);
        }
        worker.loss.coarse_sse = sse;
    });
    let rays: usize = workers.iter().map(|w| w.rays).sum();
    let sse: f64 = workers.iter().map(|w| w.loss.coarse_sse).sum();
    let mse = sse / (3 * rays.max(1)) as f64;
    PassTotals {
        loss: mse,
        final_mse: mse,
        grad_scale: 1.0 / (3 * rays.max(1)) as f32,
        rays,
        samples: workers.iter().map(|w| w.samples).sum(),
    }
}

/// Re-evaluates the occupancy grid with the current weights.
fn refresh_occupancy(model: &mut FastModel, params: &[f32], step: u64, seed: u64) {
    let dt = model.config.step_length();
    let FastModel {
        config,
        field,
        grid,
    } = model;
    let density = |points: &[f32], out: &mut [f32]| field.density_into(params, points, out);
    grid.update(&config.occupancy, step, seed, dt, &density);
}

impl Worker {
    /// Draws the rays `range` of this step for the vanilla model, packed.
    fn draw_rays(
        &mut self,
        data: &Dataset,
        cfg: &TrainConfig,
        step: u64,
        range: std::ops::Range<usize>,
        crop: f32,
    ) {
        for v in [
            &mut self.origins,
            &mut self.dirs,
            &mut self.view_dirs,
            &mut self.backgrounds,
            &mut self.targets,
        ] {
            v.clear();
        }
        self.rngs.clear();
        for g in range {
            let ray = draw_ray(data, cfg, step, g as u64, crop);
            self.origins.extend_from_slice(&ray.origin);
            self.dirs.extend_from_slice(&ray.dir);
            self.view_dirs.extend_from_slice(&ray.view_dir);
            self.backgrounds.extend_from_slice(&ray.background);
            self.targets.extend_from_slice(&ray.target);
            self.rngs.push(ray.rng);
        }
    }
}
