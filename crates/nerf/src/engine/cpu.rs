//! The CPU engine: any [`Model`] on the rayon threads.
//!
//! Work mapping: each rayon thread owns a [`Worker`] (its workspace and its gradient
//! buffer); the model's pass spreads a step's rays over them. Buffers are summed in worker
//! order (only the dirty blocks), scaled once by the loss's mean (`render::loss`), and fed to
//! Adam. Rendering cuts a batch of rays into chunks of `chunk_rays`; rayon hands chunks to
//! threads, each with a workspace from a small pool, and every chunk writes only its own
//! slice of the output.

use rayon::prelude::*;

use super::{Engine, EngineOptions, EngineState, StepSpec, StepStats};
use crate::data::Dataset;
use crate::error::Result;
use crate::model::{FastModel, Model, ModelConfig, StepInput, VanillaModel, Worker};
use crate::nn::adam::{Adam, DirtyStep};
use crate::nn::{GradBuffer, ParamLayout};
use crate::render::loss::mean_scale;
use crate::stage::finite::FiniteCheck;
use crate::stage::{RayBatch, RayOutput};
use crate::step_clock::{self, Stage};

/// Points per work unit of density queries.
const DENSITY_CHUNK: usize = 4096;

/// A model, its parameters and optimiser state, and the workers that train it.
pub struct CpuEngine<M: Model> {
    config: ModelConfig,
    model: M,
    params: Vec<f32>,
    adam: Adam,
    chunk_rays: usize,
    check_finite: bool,
    workers: Vec<Worker<M::Workspace>>,
    step_buffers: M::StepBuffers,
    /// Workspaces for rendering and queries, handed to whichever thread takes a chunk.
    pool: std::sync::Mutex<Vec<M::Workspace>>,
    touched_fraction: f64,
}

/// The CPU engine for `config`: the one place that turns a model's configuration into a
/// model type.
pub fn open(config: &ModelConfig, options: EngineOptions, seed: u64) -> Box<dyn Engine> {
    match config {
        ModelConfig::Vanilla(c) => Box::new(CpuEngine::new(
            config.clone(),
            VanillaModel::new(c.clone()),
            options,
            seed,
        )),
        ModelConfig::Fast(c) => Box::new(CpuEngine::new(
            config.clone(),
            FastModel::new(c.clone()),
            options,
            seed,
        )),
    }
}

impl<M: Model> CpuEngine<M> {
    pub fn new(config: ModelConfig, model: M, options: EngineOptions, seed: u64) -> Self {
        let params = model.init_params(seed);
        let adam = Adam::new(options.adam, params.len());
        let workers = (0..rayon::current_num_threads().max(1))
            .map(|_| Worker {
                ws: M::Workspace::default(),
                grads: GradBuffer::new(params.len()),
            })
            .collect();
        CpuEngine {
            config,
            model,
            params,
            adam,
            chunk_rays: options.chunk_rays.max(1),
            check_finite: options.check_finite,
            workers,
            step_buffers: M::StepBuffers::default(),
            pool: std::sync::Mutex::new(Vec::new()),
            touched_fraction: 0.0,
        }
    }

    /// Runs `f` with a workspace from the pool (a fresh one when none is free).
    fn with_workspace<R>(&self, f: impl FnOnce(&mut M::Workspace) -> R) -> R {
        let mut ws = self
            .pool
            .lock()
            .ok()
            .and_then(|mut p| p.pop())
            .unwrap_or_default();
        let r = f(&mut ws);
        if let Ok(mut p) = self.pool.lock() {
            p.push(ws);
        }
        r
    }
}

impl<M: Model> Engine for CpuEngine<M> {
    fn describe(&self) -> String {
        let products = match &self.config {
            ModelConfig::Fast(c) if c.bf16_products => ", networks' products in bfloat16",
            _ => "",
        };
        format!("cpu, {} threads{products}", rayon::current_num_threads())
    }

    fn kind(&self) -> super::caps::EngineKind {
        super::caps::EngineKind::Cpu
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
        // Also clears what a failed step left behind.
        for w in &mut self.workers {
            w.grads.clear();
        }
        self.model.prepare(data);
        self.model.set_progress(spec.progress);
        let check = FiniteCheck::new(self.check_finite);
        let input = StepInput {
            data,
            params: &self.params,
            sampling: spec.sampling,
            batch_rays: spec.batch_rays,
            chunk_rays: self.chunk_rays,
            check: &check,
        };
        let totals = self
            .model
            .train_pass(&input, &mut self.step_buffers, &mut self.workers);
        let mut buffers: Vec<GradBuffer> = self
            .workers
            .iter_mut()
            .map(|w| std::mem::replace(&mut w.grads, GradBuffer::new(0)))
            .collect();
        let clock = step_clock::start(Stage::Reduction);
        let finite = GradBuffer::reduce_into_first(&mut buffers);
        clock.stop();
        for (w, b) in self.workers.iter_mut().zip(buffers) {
            w.grads = b;
        }
        self.touched_fraction = self.workers[0].grads.dirty_fraction();
        check.check(
            "field.backward",
            "parameter gradients",
            &self.workers[0].grads.values,
        );
        if let Some(e) = check.take(step + 1) {
            return Err(e);
        }
        let scale = mean_scale(totals.rays);
        let loss = (totals.sse * scale) as f32;
        if !loss.is_finite() || !finite {
            return Err(super::diverged(step, loss, None));
        }
        let rule = self.model.update_rule();
        // A frozen field is a learning rate of zero: Adam leaves every parameter before
        // the camera group where it is.
        let field_lr = if spec.frozen_field { 0.0 } else { spec.lr };
        let clock = step_clock::start(Stage::Adam);
        self.adam.step_dirty(
            &mut self.params,
            &mut self.workers[0].grads,
            field_lr,
            DirtyStep {
                scale: scale as f32,
                lazy_end: rule.lazy_end,
                table_decay: rule.table_decay,
                weight_decay: rule.weight_decay,
                group: rule.group_start.map(|at| (at, spec.camera_lr)),
            },
        );
        clock.stop();
        check.check("adam", "parameters", &self.params);
        if let Some(e) = check.take(step + 1) {
            return Err(e);
        }
        if !spec.frozen_field {
            self.model
                .after_step(&self.params, step + 1, spec.sampling.seed);
        }
        Ok(StepStats {
            step: step + 1,
            loss,
            psnr: crate::metrics::psnr_from_mse(totals.final_sse * scale),
            lr: spec.lr,
            rays: totals.rays,
            samples: totals.samples,
        })
    }

    fn render_rays(
        &self,
        rays: &RayBatch,
        out: &mut [RayOutput],
        on_progress: &(dyn Fn(usize) + Sync),
    ) {
        super::render_in_chunks(rays, out, self.chunk_rays, on_progress, |part, out| {
            self.with_workspace(|ws| self.model.render_chunk(&self.params, part, ws, out))
        });
    }

    fn density(&self, positions: &[f32], time: Option<f32>, out: &mut [f32]) {
        assert_eq!(positions.len(), out.len() * 3);
        out.par_chunks_mut(DENSITY_CHUNK)
            .zip(positions.par_chunks(DENSITY_CHUNK * 3))
            .for_each(|(out, pos)| {
                self.with_workspace(|ws| self.model.density(&self.params, pos, time, ws, out))
            });
    }

    fn state(&self) -> EngineState {
        EngineState {
            params: self.params.clone(),
            adam_m: self.adam.m.clone(),
            adam_v: self.adam.v.clone(),
            adam_t: self.adam.t,
            buffers: self.model.buffers(),
        }
    }

    fn set_state(&mut self, state: EngineState) -> Result<()> {
        state.check_fits(self.params.len(), self.model.buffer_layout().total)?;
        self.params = state.params;
        self.adam.m = state.adam_m;
        self.adam.v = state.adam_v;
        self.adam.t = state.adam_t;
        self.model.load_buffers(state.buffers);
        Ok(())
    }

    fn occupancy(&self) -> Option<f64> {
        self.model.occupancy()
    }

    fn touched_fraction(&self) -> f64 {
        self.touched_fraction
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::FastModelConfig;
    use crate::nn::adam::AdamConfig;

    fn engines() -> Vec<Box<dyn Engine>> {
        let (vanilla, _) = crate::presets::build("demo").expect("preset");
        let options = EngineOptions {
            adam: AdamConfig::default(),
            chunk_rays: 64,
            check_finite: false,
        };
        [
            ModelConfig::Vanilla(vanilla),
            ModelConfig::Fast(FastModelConfig::default()),
        ]
        .iter()
        .map(|c| open(c, options, 1))
        .collect()
    }

    #[test]
    fn density_is_the_same_in_any_chunk_for_both_models() {
        let pos: Vec<f32> = (0..5000 * 3)
            .map(|i| ((i % 17) as f32 - 8.0) * 0.1)
            .collect();
        for engine in engines() {
            let mut sigma = vec![0.0; 5000];
            engine.density(&pos, None, &mut sigma);
            // The last point, evaluated alone, gives the same value.
            let mut one = [0.0];
            engine.density(&pos[4999 * 3..], None, &mut one);
            assert!((one[0] - sigma[4999]).abs() <= 1e-5 * (1.0 + one[0].abs()));
            assert!(sigma.iter().all(|s| s.is_finite() && *s >= 0.0));
        }
    }

    #[test]
    fn state_round_trips_and_wrong_sizes_are_refused() {
        for mut engine in engines() {
            let mut state = engine.state();
            state.params[0] += 1.0;
            state.adam_t = 7;
            engine.set_state(state.clone()).expect("same sizes");
            assert_eq!(engine.state(), state);
            state.params.pop();
            let err = engine.set_state(state).expect_err("short parameters");
            assert!(err.to_string().contains("parameters"), "{err}");
        }
    }

    /// NERF_CHECK_FINITE: NaN weights are caught at the first stage whose output they
    /// reach (the field's forward pass), named with its buffer and step; without the switch
    /// the same step is only reported as diverged.
    #[test]
    fn check_finite_names_the_first_stage_that_overflows() {
        use crate::data::pixels::PixelSampling;
        use crate::data::synth::{self, SynthOptions};
        use crate::data::{Background, Split};
        let opts = SynthOptions {
            size: 8,
            supersample: 1,
            ..Default::default()
        };
        let data = synth::dataset(&opts, Split::Train, 2);
        let spec = StepSpec {
            sampling: PixelSampling {
                seed: 1,
                step: 0,
                crop: 1.0,
                background: Background::White,
                appearance: crate::stage::Appearance::PerView,
            },
            lr: 1e-3,
            batch_rays: 64,
            progress: 0.0,
            camera_lr: 0.0,
            frozen_field: false,
        };
        for check_finite in [false, true] {
            for mut engine in engines() {
                let options = EngineOptions {
                    adam: AdamConfig::default(),
                    chunk_rays: 64,
                    check_finite,
                };
                let config = engine.model_config().clone();
                engine = open(&config, options, 1);
                let mut state = engine.state();
                state.params.iter_mut().for_each(|p| *p = f32::NAN);
                engine.set_state(state).expect("set");
                let err = engine
                    .train_step(&data, &spec)
                    .expect_err("NaN weights")
                    .to_string();
                if check_finite {
                    assert!(
                        err.contains("field.forward produced a non-finite value at step 1")
                            && err.contains("NERF_CHECK_FINITE"),
                        "{err}"
                    );
                } else {
                    assert!(err.contains("diverged at step 1"), "{err}");
                }
            }
        }
    }

    /// `--refine-test-poses`' step: with the field frozen, only the camera corrections
    /// move; the field's parameters and the occupancy grid stay bit for bit.
    #[test]
    fn a_frozen_field_step_moves_only_the_cameras() {
        use crate::data::pixels::PixelSampling;
        use crate::data::synth::{self, SynthOptions};
        use crate::data::{Background, Split};
        use crate::model::camera_refine::CameraRefinement;
        let opts = SynthOptions {
            size: 16,
            supersample: 1,
            ..Default::default()
        };
        let data = synth::dataset(&opts, Split::Train, 3);
        let config = ModelConfig::Fast(FastModelConfig {
            refine_cameras: Some(CameraRefinement::new(3)),
            samples_per_step: 4096,
            ..FastModelConfig::default()
        });
        let options = EngineOptions {
            adam: AdamConfig::default(),
            chunk_rays: 64,
            check_finite: false,
        };
        let mut engine = open(&config, options, 1);
        let at = crate::model::camera_refine::corrections_start(engine.param_layout())
            .expect("corrections");
        let before = engine.state();
        for step in 0..3 {
            let spec = StepSpec {
                sampling: PixelSampling {
                    seed: 1,
                    step,
                    crop: 1.0,
                    background: Background::Random,
                    appearance: crate::stage::Appearance::Mean,
                },
                lr: 1e-2,
                batch_rays: 0,
                progress: 1.0,
                camera_lr: 1e-2,
                frozen_field: true,
            };
            engine.train_step(&data, &spec).expect("step");
        }
        let after = engine.state();
        assert!(after.params[..at] == before.params[..at], "the field moved");
        assert!(after.buffers == before.buffers, "the occupancy grid moved");
        let moved = after.params[at..]
            .iter()
            .zip(&before.params[at..])
            .filter(|(a, b)| a != b)
            .count();
        assert_eq!(moved, 18, "every correction of the 3 cameras learns");
    }
}
