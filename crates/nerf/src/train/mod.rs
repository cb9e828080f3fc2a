//! The optimisation loop of the paper: random rays from all training pixels, coarse + fine
//! photometric MSE, Adam with an exponentially decaying learning rate, and a central-crop
//! warm-up on the first steps.
//!
//! Work mapping: a step's rays are cut into chunks of `chunk_rays`; chunk `k` goes to worker
//! `k mod W` (W = rayon threads), which runs it forward and backward in its own workspace and
//! accumulates into its own gradient buffer. Buffers are summed in worker order, so a run is
//! reproducible for a given seed and thread count. Nothing is allocated per step once the
//! workspaces have grown.

pub mod run;

use std::path::PathBuf;

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::data::{Background, Dataset};
use crate::error::{NerfError, Result};
use crate::model::{Model, ModelConfig};
use crate::nn::adam::{Adam, AdamConfig};
use crate::render::pipeline::{train_chunk, ChunkLoss, ChunkWorkspace, Rays, Targets};
use crate::rng::Rng;

/// Everything that defines a training run; saved as `config.json` in the run folder.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TrainConfig {
    /// Scene folder (Blender format).
    pub data: PathBuf,
    /// Preset the model came from (see `presets`).
    pub preset: String,
    pub model: ModelConfig,
    /// Rays per step (paper: 4096; 1024 is the common smaller setting and our default).
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
            preset: preset.to_string(),
            model,
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

    /// Rejects settings that cannot run, naming the field.
    pub fn validate(&self) -> Result<()> {
        let bad = |m: &str| Err(NerfError::Config(m.to_string()));
        if self.batch_rays == 0 {
            return bad("batch_rays must be positive");
        }
        if self.chunk_rays == 0 {
            return bad("chunk_rays must be positive");
        }
        if self.model.n_coarse < 3 {
            return bad("at least 3 coarse samples per ray are needed");
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
}

struct Worker {
    ws: ChunkWorkspace,
    grads: Vec<f32>,
    origins: Vec<f32>,
    dirs: Vec<f32>,
    backgrounds: Vec<f32>,
    targets: Vec<f32>,
    rngs: Vec<Rng>,
    loss: ChunkLoss,
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
    workers: Vec<Worker>,
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
                ws: ChunkWorkspace::default(),
                grads: vec![0.0; params.len()],
                origins: Vec::new(),
                dirs: Vec::new(),
                backgrounds: Vec::new(),
                targets: Vec::new(),
                rngs: Vec::new(),
                loss: ChunkLoss::default(),
            })
            .collect();
        Ok(Trainer {
            config,
            model,
            params,
            adam,
            step: 0,
            data,
            workers,
        })
    }

    /// One optimisation step. Fails (leaving the parameters untouched) if the loss is not finite.
    pub fn step(&mut self) -> Result<StepStats> {
        let cfg = &self.config;
        let step = self.step;
        let batch = cfg.batch_rays;
        let chunk = cfg.chunk_rays.min(batch);
        let n_chunks = batch.div_ceil(chunk);
        let n_workers = self.workers.len();
        let loss_scale = 1.0 / (3 * batch) as f32;
        let crop = if step < cfg.precrop_steps {
            cfg.precrop_fraction
        } else {
            1.0
        };
        let (model, params, data) = (&self.model, &self.params, &self.data);
        self.workers
            .par_iter_mut()
            .enumerate()
            .for_each(|(w, worker)| {
                worker.grads.fill(0.0);
                worker.loss = ChunkLoss::default();
                for c in (w..n_chunks).step_by(n_workers) {
                    let rays = (c * chunk)..((c + 1) * chunk).min(batch);
                    worker.sample_rays(data, cfg, step, rays, crop);
                    let r = Rays {
                        origins: &worker.origins,
                        dirs: &worker.dirs,
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
                        &mut worker.ws,
                        &mut worker.grads,
                    );
                    worker.loss.coarse_sse += l.coarse_sse;
                    worker.loss.fine_sse += l.fine_sse;
                }
            });
        let (first, rest) = self.workers.split_at_mut(1);
        let grads = &mut first[0].grads;
        let mut total = first[0].loss;
        for w in rest.iter() {
            for (a, b) in grads.iter_mut().zip(&w.grads) {
                *a += b;
            }
            total.coarse_sse += w.loss.coarse_sse;
            total.fine_sse += w.loss.fine_sse;
        }
        let denom = (3 * batch) as f64;
        let (mse_c, mse_f) = (total.coarse_sse / denom, total.fine_sse / denom);
        let loss = (mse_c + mse_f) as f32;
        if !loss.is_finite() || grads.iter().any(|g| !g.is_finite()) {
            return Err(NerfError::Diverged {
                step: step + 1,
                loss,
            });
        }
        let lr = cfg.learning_rate(step);
        self.adam.step(&mut self.params, grads, lr);
        self.step += 1;
        let final_mse = if self.model.fine.is_some() {
            mse_f
        } else {
            mse_c
        };
        Ok(StepStats {
            step: self.step,
            loss,
            psnr: crate::eval::psnr_from_mse(final_mse),
            lr,
        })
    }
}

impl Worker {
    /// Picks the rays `range` of this step: a uniformly random training pixel each (inside
    /// the central crop while warming up), its target colour over the ray's background, and
    /// the ray's random stream, which later also draws its sample positions.
    fn sample_rays(
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
            &mut self.backgrounds,
            &mut self.targets,
        ] {
            v.clear();
        }
        self.rngs.clear();
        for g in range {
            let mut rng = Rng::for_stream(cfg.seed, step, g as u64);
            let view = &data.views[rng.below(data.views.len())];
            let (w, h) = (view.image.width, view.image.height);
            let (cw, ch) = (
                ((w as f32 * crop) as usize).max(1),
                ((h as f32 * crop) as usize).max(1),
            );
            let (x0, y0) = ((w - cw) / 2, (h - ch) / 2);
            let (i, j) = (x0 + rng.below(cw), y0 + rng.below(ch));
            let ray = view.camera.ray(i, j);
            let bg = match cfg.background {
                Background::White => [1.0; 3],
                Background::Black => [0.0; 3],
                Background::Random => [rng.uniform(), rng.uniform(), rng.uniform()],
            };
            self.origins.extend_from_slice(&ray.origin);
            self.dirs.extend_from_slice(&ray.dir);
            self.backgrounds.extend_from_slice(&bg);
            self.targets
                .extend_from_slice(&view.image.composite_pixel(j * w + i, bg));
            self.rngs.push(rng);
        }
    }
}
