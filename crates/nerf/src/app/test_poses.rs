//! Fitting the test cameras to a trained model (`nerf eval --refine-test-poses`, BARF's
//! evaluation): with the field frozen, each test camera gets a rigid correction learned
//! from its own photo, so the metrics measure the model and not what is left of the pose
//! error after the similarity alignment.
//!
//! It is the training step with a different dataset and nothing but the cameras free: a
//! fast model whose corrections are the test cameras' (`camera_refine`), every hash-grid
//! level on, on the CPU engine, `StepSpec::frozen_field` set. A model with appearance
//! codes renders each photo with the look it is evaluated with (`looks`): the fit's code
//! table holds one row per test photo, copied from the trained codes, so a camera is not
//! moved to make up for a look.

use serde::{Deserialize, Serialize};

use crate::data::pixels::PixelSampling;
use crate::data::Dataset;
use crate::engine::{EngineState, StepSpec};
use crate::error::{NerfError, Result};
use crate::model::camera_refine::{self, corrected, CameraRefinement, Frame, PER_CAMERA};
use crate::model::ModelConfig;
use crate::stage::Appearance;
use crate::train::folder::LoadedRun;

/// How long and how fast the test cameras are fitted.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct TestPoseFit {
    pub steps: u64,
    /// Learning rate of the corrections, decaying exponentially to `lr_final`.
    pub lr_init: f32,
    pub lr_final: f32,
}

impl TestPoseFit {
    /// `steps` steps at a learning rate from 2e-3 down to 2e-5: on the chair a lower start
    /// leaves more of a test camera's error, a higher one scores its views lower.
    pub fn new(steps: u64) -> Self {
        TestPoseFit {
            steps,
            lr_init: 2e-3,
            lr_final: 2e-5,
        }
    }
}

/// What the fit did, for `metrics.json`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct TestPoseReport {
    pub steps: u64,
    /// Mean size of the corrections: rotation in degrees, translation in scene units.
    pub mean_rotation_deg: f32,
    pub mean_translation: f32,
    /// Mean PSNR of the fit's training batches over its first and last tenth of steps.
    pub batch_psnr_before: f32,
    pub batch_psnr_after: f32,
}

/// Moves every camera of `data` to where `run`'s frozen field explains its photo best,
/// photo `k` seen with look `looks[k]` (the mean code where `looks` is shorter).
/// `on_step(done, total)` reports progress.
pub fn refine_test_poses(
    run: &LoadedRun,
    data: &mut Dataset,
    fit: TestPoseFit,
    looks: &[Appearance],
    on_step: &dyn Fn(u64, u64),
) -> Result<TestPoseReport> {
    let cfg = &run.config;
    let ModelConfig::Fast(model) = &cfg.model else {
        return Err(NerfError::Config(
            "--refine-test-poses needs a fast-model run (the vanilla model does not refine \
             cameras)"
                .into(),
        ));
    };
    if data.views.is_empty() || fit.steps == 0 {
        return Ok(TestPoseReport {
            steps: 0,
            mean_rotation_deg: 0.0,
            mean_translation: 0.0,
            batch_psnr_before: 0.0,
            batch_psnr_after: 0.0,
        });
    }
    let levels = model.field.grid.levels;
    let refinement = CameraRefinement {
        cameras: data.views.len(),
        lr_init: fit.lr_init,
        lr_final: fit.lr_final,
        anneal: [0.0, 0.0],
        start_levels: levels as f32,
        // As training corrects.
        frame: Frame::for_space(data.space),
        // All levels from the start either way.
        pose_gradient_only: false,
        // The field is frozen.
        field_restart: None,
        // Moving from the first step: the field is trained.
        delay: 0.0,
        // Fitted by their gradient alone (no training run checks them).
        recover_stuck: false,
    };
    let mut fit_model = model.clone();
    fit_model.refine_cameras = Some(refinement);
    let trained = run.engine.state();
    // The field's parameters: all of them, less the run's own camera corrections.
    let field_len =
        camera_refine::corrections_start(run.engine.param_layout()).unwrap_or(trained.params.len());
    let mut params = trained.params[..field_len].to_vec();
    // Codes last in the field: one row per test photo, its look's.
    let codes = run
        .engine
        .param_layout()
        .tensors
        .iter()
        .find(|t| t.name == crate::field::fast::APPEARANCE_CODES)
        .map(|t| t.range());
    if let Some(codes) = codes.filter(|r| r.end == field_len) {
        let trained_codes = params.split_off(codes.start);
        let dims = model.field.appearance_dims;
        let rows = looks_as_rows(&trained_codes, dims, looks, data.views.len());
        params.extend(rows);
        fit_model.field.appearance_images = data.views.len();
    }
    let config = ModelConfig::Fast(fit_model).for_inference();
    // On the run's own kind of engine (camera refinement runs on both).
    let device = match run.engine.kind() {
        crate::engine::caps::EngineKind::Cpu => crate::engine::Device::Cpu,
        crate::engine::caps::EngineKind::Gpu => crate::engine::Device::Wgpu,
    };
    let mut engine = crate::engine::open_on(device, &config, cfg.engine_options(), cfg.seed)?;
    params.resize(engine.param_layout().total, 0.0);
    let n = params.len();
    engine.set_state(EngineState {
        params,
        adam_m: vec![0.0; n],
        adam_v: vec![0.0; n],
        adam_t: 0,
        buffers: trained.buffers,
    })?;
    let tenth = (fit.steps / 10).max(1);
    let (mut before, mut after) = (Vec::new(), Vec::new());
    for step in 0..fit.steps {
        let progress = step as f32 / fit.steps as f32;
        let spec = StepSpec {
            sampling: PixelSampling {
                seed: cfg.seed ^ 0x7e57,
                step,
                crop: 1.0,
                background: cfg.background,
                // Each photo its row of the fit's code table (ignored without codes).
                appearance: Appearance::PerView,
            },
            lr: 0.0,
            batch_rays: cfg.batch_rays,
            progress: 1.0,
            camera_lr: refinement.learning_rate(progress),
            frozen_field: true,
        };
        let stats = engine.train_step(data, &spec)?;
        if step < tenth {
            before.push(stats.psnr);
        }
        if step >= fit.steps - tenth {
            after.push(stats.psnr);
        }
        on_step(step + 1, fit.steps);
    }
    let state = engine.state();
    let learned = camera_refine::corrections(engine.param_layout(), &state.params)
        .ok_or_else(|| NerfError::Config("the fitted model lost its camera corrections".into()))?;
    let (mut rot, mut trans) = (0.0f32, 0.0f32);
    for (view, c) in data.views.iter_mut().zip(learned.chunks_exact(PER_CAMERA)) {
        let moved = corrected(&view.camera.c2w, c, refinement.frame);
        // The turn's angle is |w| in either frame; the centre's move is not |tau| in the
        // world frame (the turn about the origin moves it too).
        rot += crate::math::length([c[0], c[1], c[2]]).to_degrees();
        trans += crate::math::length(std::array::from_fn(|i| moved[i][3] - view.camera.c2w[i][3]));
        view.camera.c2w = moved;
    }
    let k = data.views.len() as f32;
    let mean = |v: &[f32]| v.iter().sum::<f32>() / v.len().max(1) as f32;
    Ok(TestPoseReport {
        steps: fit.steps,
        mean_rotation_deg: rot / k,
        mean_translation: trans / k,
        batch_psnr_before: mean(&before),
        batch_psnr_after: mean(&after),
    })
}

/// One code row of `dims` values per photo: `codes`' row `i` for `Appearance::Of(i)`, their
/// mean for `Appearance::Mean` (and photos past the end of `looks`).
fn looks_as_rows(codes: &[f32], dims: usize, looks: &[Appearance], photos: usize) -> Vec<f32> {
    let images = codes.len() / dims.max(1);
    let mut mean = Vec::new();
    crate::field::fast::mean_code(codes, dims, &mut mean);
    (0..photos)
        .flat_map(|k| match looks.get(k) {
            Some(Appearance::Of(i)) if (*i as usize) < images => {
                codes[*i as usize * dims..][..dims].to_vec()
            }
            _ => mean.clone(),
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_photo_gets_the_row_of_its_look() {
        let codes = [1.0, 2.0, 3.0, 6.0];
        let looks = [Appearance::Of(1), Appearance::Mean, Appearance::Of(0)];
        assert_eq!(
            looks_as_rows(&codes, 2, &looks, 4),
            vec![3.0, 6.0, 2.0, 4.0, 1.0, 2.0, 2.0, 4.0]
        );
    }
}
