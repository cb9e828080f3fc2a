//! The optimisation schedule: random rays from all training pixels, photometric MSE, Adam
//! with an exponentially decaying learning rate. The vanilla model follows the paper
//! (coarse and fine loss, a fixed number of rays, a central-crop warm-up); the fast model follows
//! Instant-NGP (a fixed number of field samples, random backgrounds, lazy updates of the
//! hash tables, occupancy-grid refreshes every few steps).
//!
//! The [`Trainer`] decides what each step does (learning rate, crop, background) and hands
//! the step to an engine (`engine`), which owns the parameters and runs the passes. The
//! rays of a step are a function of the seed and the step alone (`data::pixels`), so a run
//! gives the same rays and samples for any thread count; [`run`] adds the run folder.

pub mod defaults;
pub mod folder;
pub mod lock;
pub mod options;
pub mod pose_search;
pub mod refined_cameras;
pub mod run;
pub mod run_scene;
pub mod stuck_cameras;

use std::path::PathBuf;

use serde::{Deserialize, Serialize};

use crate::data::pixels::PixelSampling;
use crate::data::scene::{Scene, SceneOptions};
use crate::data::{Background, Dataset};
use crate::engine::{self, Engine, EngineOptions, StepSpec};
use crate::error::{NerfError, Result};
use crate::model::{FastModelConfig, ModelConfig};
use crate::nn::adam::AdamConfig;

pub use crate::engine::StepStats;

/// The largest hash table, 2^24 entries a level (Instant-NGP's largest setting is 2^24):
/// 16 levels of it hold 4 GiB of tables, gradients and Adam moments.
pub const MAX_TABLE_LOG2: u32 = 24;

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
    /// With a time schedule ([`time_budget_s`](Self::time_budget_s)) only a cap.
    pub steps: u64,
    /// A schedule by the clock: when set, the schedule (the learning-rate decay) runs over
    /// this many seconds of training time, summed over sessions, and the run ends when they
    /// are spent (`--minutes` alone). `None`: the schedule runs over `steps`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub time_budget_s: Option<f64>,
    pub lr_init: f32,
    pub lr_final: f32,
    pub adam: AdamConfig,
    /// For this many first steps, rays come from the central `precrop_fraction` of each image.
    pub precrop_steps: u64,
    pub precrop_fraction: f32,
    pub background: Background,
    /// Area-average downscale of the images.
    pub downscale: usize,
    /// Train on mip-NeRF's multi-scale variant of the scene: every training image also at
    /// 1/2, ..., `1 / 2^(multiscale - 1)` of its resolution (1: the images alone).
    #[serde(default = "one", skip_serializing_if = "is_one")]
    pub multiscale: usize,
    /// The training views kept (`--train-views`; `None`: all).
    pub train_views: Option<crate::data::TrainViews>,
    pub seed: u64,
    /// Rays per work unit (bounds memory: activations of one chunk per thread).
    pub chunk_rays: usize,
    /// Render a validation image every this many steps (0: never).
    pub val_every: u64,
    /// Validation images are rendered at 1/val_downscale of the training resolution.
    pub val_downscale: usize,
    /// Save a checkpoint every this many steps, at most one every 30 s after the first (and
    /// always at the end).
    pub checkpoint_every: u64,
    /// Move every training pose by random noise before training (BARF's synthetic test
    /// of camera refinement; `--perturb-poses`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub perturb_poses: Option<crate::model::camera_refine::PosePerturbation>,
    /// The run folder this config was read from (see `run_scene`).
    #[serde(skip)]
    pub read_from: run_scene::ReadFrom,
}

/// The most scales of `--multiscale` (down to 1/32 of the resolution).
pub const MAX_SCALES: usize = 6;

/// Serde default of counts that are 1 unless set (`multiscale`, an eval view's scale).
pub(crate) fn one() -> usize {
    1
}

/// Leaves such counts out of the JSON when they are 1, so older readers see no change.
pub(crate) fn is_one(v: &usize) -> bool {
    *v == 1
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
            time_budget_s: None,
            lr_init: 5e-4,
            lr_final: 5e-5,
            adam: AdamConfig::default(),
            precrop_steps: 500,
            precrop_fraction: 0.5,
            background: Background::White,
            downscale: 1,
            multiscale: 1,
            train_views: train_views.map(crate::data::TrainViews::Evenly),
            seed: 0,
            chunk_rays: 64,
            val_every: 1000,
            val_downscale: 4,
            checkpoint_every: 1000,
            perturb_poses: None,
            read_from: run_scene::ReadFrom::default(),
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
            time_budget_s: None,
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
            multiscale: 1,
            train_views: None,
            seed: 0,
            chunk_rays: 1024,
            val_every: 500,
            val_downscale: 4,
            checkpoint_every: 500,
            perturb_poses: None,
            read_from: run_scene::ReadFrom::default(),
        }
    }

    /// The run's scene, read at `1 / (downscale * extra)` of its resolution, wherever it
    /// is found (see `run_scene::open`).
    pub fn open_scene(&self, extra_downscale: usize) -> Result<Scene> {
        run_scene::open(self, self.downscale.max(1) * extra_downscale.max(1))
    }

    /// The indices of the training views this run trains on, of a split of `total`.
    pub fn kept_train_views(&self, total: usize) -> Result<Vec<usize>> {
        match &self.train_views {
            Some(v) => v.indices(total),
            None => Ok((0..total).collect()),
        }
    }

    /// The training split as the run trains on it: the views kept, and the poses moved by
    /// `perturb_poses` when set.
    pub fn training_data(&self) -> Result<Dataset> {
        Ok(self.training_split()?.0)
    }

    /// [`training_data`](Self::training_data) and how many views the whole split holds.
    pub fn training_split(&self) -> Result<(Dataset, usize)> {
        let mut data = self.open_scene(1)?.load(crate::data::Split::Train, 1)?;
        let total = data.views.len();
        if self.train_views.is_some() {
            let kept = self.kept_train_views(total)?;
            data.keep(&kept);
        }
        if let Some(p) = &self.perturb_poses {
            let mut poses: Vec<&mut crate::camera::Pose> =
                data.views.iter_mut().map(|v| &mut v.camera.c2w).collect();
            p.apply(&mut poses);
        }
        data.add_scales(self.multiscale)?;
        Ok((data, total))
    }

    /// Rejects settings that cannot run, naming the field. Every command checks a
    /// configuration here, whether it came from the command line or from a run's
    /// `config.json` (which may have been edited).
    pub fn validate(&self) -> Result<()> {
        let bad = |m: &str| Err(NerfError::Config(m.to_string()));
        if self.chunk_rays == 0 {
            return bad("chunk_rays must be positive");
        }
        if self.steps == 0 {
            return bad("steps must be at least 1");
        }
        if let Some(b) = self.time_budget_s {
            if !(b.is_finite() && b > 0.0) {
                return bad("time_budget_s must be a positive number of seconds");
            }
        }
        match &self.model {
            ModelConfig::Vanilla(m) => {
                if self.batch_rays == 0 {
                    return bad("batch_rays must be positive");
                }
                if m.n_coarse < 3 {
                    return bad("at least 3 coarse samples per ray are needed");
                }
                if m.net.deformation.is_some() && m.integrated {
                    return bad(
                        "a deformation (D-NeRF) cannot be combined with the integrated encoding \
                         (mip-NeRF) yet",
                    );
                }
            }
            ModelConfig::Fast(m) => {
                if m.samples_per_step == 0 || m.batch_samples == 0 {
                    return bad("samples_per_step and batch_samples must be positive");
                }
                let bound = m.field.bound;
                if !(bound.is_finite() && bound > 0.0) || m.occupancy.resolution == 0 {
                    return Err(NerfError::Config(format!(
                        "bound {bound} must be a positive number and the occupancy grid not \
                         empty"
                    )));
                }
                let grid = &m.field.grid;
                if grid.log2_table_size > MAX_TABLE_LOG2 || grid.log2_table_size < 2 {
                    // Parameters, two Adam moments and a gradient buffer per entry.
                    let bytes = grid.levels as f64
                        * 2f64.powi(grid.log2_table_size.min(64) as i32)
                        * crate::encoding::hash_grid::FEATURES as f64
                        * 4.0
                        * 4.0;
                    return Err(NerfError::Config(format!(
                        "table_log2 {} is outside 2..={MAX_TABLE_LOG2} (2^{} entries per level \
                         would need {:.1} GiB for the tables, their gradients and Adam's moments)",
                        grid.log2_table_size,
                        grid.log2_table_size,
                        bytes / f64::from(1u32 << 30)
                    )));
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
        if !(1..=MAX_SCALES).contains(&self.multiscale) {
            return bad("multiscale must be 1 (off) to 6 scales");
        }
        if self.scene.holdout < 2 {
            return bad("scene.holdout must be at least 2");
        }
        Ok(())
    }

    /// How far through its schedule the run is, in [0, 1], after `step` steps and
    /// `elapsed_s` seconds of training: by the clock with a time budget, else by steps.
    pub fn progress(&self, step: u64, elapsed_s: f64) -> f64 {
        let p = match self.time_budget_s {
            Some(budget) => elapsed_s / budget,
            None => step as f64 / self.steps.max(1) as f64,
        };
        p.clamp(0.0, 1.0)
    }

    /// Whether the schedule is over: all steps done, or the time budget spent.
    pub fn finished(&self, step: u64, elapsed_s: f64) -> bool {
        step >= self.steps || self.time_budget_s.is_some_and(|b| elapsed_s >= b)
    }

    /// `lr_init * (lr_final / lr_init)^(step / steps)`: exponential decay over the run
    /// (of a step schedule).
    pub fn learning_rate(&self, step: u64) -> f32 {
        self.learning_rate_at(step as f64 / self.steps.max(1) as f64)
    }

    /// `lr_init * (lr_final / lr_init)^progress`.
    pub fn learning_rate_at(&self, progress: f64) -> f32 {
        let progress = progress.clamp(0.0, 1.0);
        (self.lr_init as f64 * (self.lr_final as f64 / self.lr_init as f64).powf(progress)) as f32
    }
}

/// A run in memory: its configuration, its engine (model, parameters, optimiser) and its
/// training data.
pub struct Trainer {
    pub config: TrainConfig,
    pub engine: Box<dyn Engine>,
    /// Steps completed.
    pub step: u64,
    /// Seconds of training so far (all sessions): the clock of a time schedule.
    pub elapsed_s: f64,
    pub data: Dataset,
}

impl TrainConfig {
    /// How the engine is set up for this run.
    pub fn engine_options(&self) -> EngineOptions {
        EngineOptions {
            adam: self.adam,
            chunk_rays: self.chunk_rays,
            check_finite: crate::stage::finite::from_env(),
        }
    }

    /// What step `step` (0-based) does in a step schedule.
    pub fn step_spec(&self, step: u64) -> StepSpec {
        self.step_spec_at(step, step as f64 / self.steps.max(1) as f64)
    }

    /// What step `step` (0-based) does at `progress` (see [`progress`](Self::progress))
    /// through the schedule.
    pub fn step_spec_at(&self, step: u64, progress: f64) -> StepSpec {
        let refinement = match &self.model {
            ModelConfig::Fast(m) => m.refine_cameras,
            ModelConfig::Vanilla(_) => None,
        };
        StepSpec {
            sampling: PixelSampling {
                seed: self.seed,
                step,
                crop: if step < self.precrop_steps {
                    self.precrop_fraction
                } else {
                    1.0
                },
                background: self.background,
                appearance: crate::stage::Appearance::PerView,
            },
            lr: self.learning_rate_at(refinement.map_or(progress, |r| r.field_progress(progress))),
            batch_rays: self.batch_rays,
            progress: progress as f32,
            camera_lr: refinement.map_or(0.0, |r| r.learning_rate(progress as f32)),
            frozen_field: false,
        }
    }
}

impl Trainer {
    /// A fresh run on `data` (its training split), on the CPU engine.
    pub fn new(config: TrainConfig, data: Dataset) -> Result<Self> {
        Trainer::on(engine::Device::Cpu, config, data)
    }

    /// A fresh run on `data` (its training split), on `device`.
    pub fn on(device: engine::Device, config: TrainConfig, data: Dataset) -> Result<Self> {
        config.validate()?;
        if data.views.is_empty() {
            return Err(NerfError::Config("no training views".into()));
        }
        if let ModelConfig::Fast(m) = &config.model {
            let codes = m.field.appearance_images;
            if m.field.appearance_dims > 0 && codes != data.views.len() {
                return Err(NerfError::Config(format!(
                    "the model has appearance codes for {codes} training photos, and the \
                     training split holds {}: the scene changed since the run began",
                    data.views.len()
                )));
            }
        }
        let engine = engine::open_on(device, &config.model, config.engine_options(), config.seed)?;
        Ok(Trainer {
            config,
            engine,
            step: 0,
            elapsed_s: 0.0,
            data,
        })
    }

    /// One optimisation step. Fails (leaving the parameters untouched) if the loss is not finite.
    pub fn step(&mut self) -> Result<StepStats> {
        let progress = self.config.progress(self.step, self.elapsed_s);
        let spec = self.config.step_spec_at(self.step, progress);
        let stats = self.engine.train_step(&self.data, &spec)?;
        self.step += 1;
        Ok(stats)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A step schedule runs by steps; a timed one by the clock alone, and
    /// ends when its budget does, whatever the step.
    #[test]
    fn the_schedule_runs_by_steps_or_by_the_clock() {
        let mut c = TrainConfig::fast(PathBuf::from("scene"));
        c.steps = 1000;
        assert_eq!(c.progress(250, 9e9), 0.25);
        assert!(!c.finished(999, 9e9) && c.finished(1000, 0.0));
        assert_eq!(c.step_spec(500).lr, c.learning_rate_at(0.5));
        c.time_budget_s = Some(600.0);
        c.steps = u64::MAX;
        assert_eq!(c.progress(1_000_000, 150.0), 0.25);
        assert_eq!(c.progress(3, 700.0), 1.0);
        assert!(!c.finished(1_000_000, 599.0) && c.finished(3, 600.0));
        let (start, end) = (c.learning_rate_at(0.0), c.learning_rate_at(1.0));
        assert!((start - 1e-2).abs() < 1e-7 && (end - 1e-3).abs() < 1e-8);
        c.time_budget_s = Some(-1.0);
        assert!(c.validate().is_err());
    }

    /// A field restart at 0.4 leaves the first 40% of the schedule as it was, returns the
    /// field to its initial rate there, and still decays it to the final rate by the end;
    /// the cameras' own schedule does not restart.
    #[test]
    fn the_field_rate_starts_over_where_the_refinement_says() {
        use crate::model::camera_refine::CameraRefinement;
        let mut c = TrainConfig::fast(PathBuf::from("scene"));
        c.steps = 1000;
        let plain = c.clone();
        let ModelConfig::Fast(m) = &mut c.model else {
            panic!("fast")
        };
        let mut r = CameraRefinement::new(3).with_learning_rate(1e-2);
        r.field_restart = Some(0.4);
        m.refine_cameras = Some(r);
        let (init, last) = (c.learning_rate_at(0.0), c.learning_rate_at(1.0));
        for step in [0, 200, 399] {
            assert_eq!(
                c.step_spec(step).lr,
                plain.step_spec(step).lr,
                "step {step}"
            );
        }
        assert!(c.step_spec(399).lr < 0.45 * init);
        assert_eq!(c.step_spec(400).lr, init);
        assert_eq!(c.step_spec(700).lr, c.learning_rate_at(0.5));
        assert!((c.step_spec(1000).lr - last).abs() < 1e-9);
        assert_eq!(c.step_spec(700).camera_lr, r.learning_rate(0.7));
        // No restart: one decay.
        if let ModelConfig::Fast(m) = &mut c.model {
            m.refine_cameras = Some(CameraRefinement::new(3));
        }
        assert_eq!(c.step_spec(700).lr, plain.step_spec(700).lr);
    }

    /// A delay of 0.2 keeps the cameras still for the first fifth of the schedule, starts
    /// them at the initial rate there and still ends at the final rate; the field's rate
    /// does not notice.
    #[test]
    fn the_cameras_wait_for_the_delay() {
        use crate::model::camera_refine::CameraRefinement;
        let mut c = TrainConfig::fast(PathBuf::from("scene"));
        c.steps = 1000;
        let plain = c.clone();
        let mut r = CameraRefinement::new(3);
        r.delay = 0.2;
        if let ModelConfig::Fast(m) = &mut c.model {
            m.refine_cameras = Some(r);
        }
        for step in [0, 100, 199] {
            assert_eq!(c.step_spec(step).camera_lr, 0.0, "step {step}");
        }
        assert_eq!(c.step_spec(200).camera_lr, r.lr_init);
        let mid = c.step_spec(600).camera_lr;
        let geometric_mean = (r.lr_init * r.lr_final).sqrt();
        assert!(
            (mid - geometric_mean).abs() < 1e-3 * geometric_mean,
            "{mid}"
        );
        assert!((c.step_spec(1000).camera_lr - r.lr_final).abs() < 1e-9);
        for step in [0, 199, 200, 600] {
            assert_eq!(c.step_spec(step).lr, plain.step_spec(step).lr);
        }
        // Without a delay the cameras move from the first step.
        assert_eq!(CameraRefinement::new(3).learning_rate(0.0), r.lr_init);
    }
}
