//! The training cameras of a run that refined them (`--refine-cameras`): the poses it
//! ended with, how far they are from the given ones (BARF's evaluation), and where the
//! test cameras sit in the frame the model learned.
//!
//! A refined model is free to drift as a whole (any similarity of all cameras and the
//! scene explains the photos equally well), so the refined cameras are first aligned to
//! the given ones by the similarity that best maps their centres (Horn's method), and the
//! errors are measured after it: mean rotation error in degrees, mean centre distance in
//! scene units and in percent of the cameras' radius (their RMS distance from their
//! centroid). Test cameras, given in the scene's frame, are mapped into the model's by
//! the inverse of that similarity.

use serde::{Deserialize, Serialize};

use crate::camera::Pose;
use crate::data::poses::{fit_similarity, origin, rotation_error_degrees, Similarity};
use crate::data::{evenly_kept, Split};
use crate::error::Result;
use crate::math::{length, sub};
use crate::model::camera_refine::{corrected, corrections, Frame, PER_CAMERA};
use crate::nn::ParamLayout;
use crate::train::folder::LoadedRun;
use crate::train::TrainConfig;

/// How far a run's training cameras are from the given ones, after alignment.
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq)]
pub struct PoseError {
    /// Mean over the cameras.
    pub rotation_deg: f32,
    pub translation: f32,
    pub translation_percent_of_radius: f32,
    /// The median and the worst camera's rotation error: a mean can hide a few cameras
    /// stuck far off while the rest have converged.
    #[serde(default)]
    pub rotation_deg_median: f32,
    #[serde(default)]
    pub rotation_deg_max: f32,
}

/// The training cameras as the run trained them, and as the scene gives them.
#[derive(Clone, Debug)]
pub struct RunCameras {
    /// As given by the scene (before any `--perturb-poses`).
    pub given: Vec<Pose>,
    /// As the model ended with them: given, perturbed, then corrected.
    pub refined: Vec<Pose>,
    /// Whether the run learned corrections.
    pub refined_by_model: bool,
}

impl RunCameras {
    /// The cameras of `run`; `None` when the run neither perturbed nor refined them.
    pub fn of(run: &LoadedRun) -> Result<Option<RunCameras>> {
        let state = run.engine.state();
        let layout = run.engine.param_layout();
        if corrections(layout, &state.params).is_none() && run.config.perturb_poses.is_none() {
            return Ok(None);
        }
        Ok(Some(
            StartingCameras::of(&run.config)?.corrected_by(layout, &state.params),
        ))
    }

    /// The similarity that best maps the refined centres onto the given ones.
    pub fn alignment(&self) -> Similarity {
        let from: Vec<_> = self.refined.iter().map(origin).collect();
        let to: Vec<_> = self.given.iter().map(origin).collect();
        fit_similarity(&from, &to).0
    }

    /// The errors of the refined cameras against the given ones after [`alignment`](Self::alignment).
    pub fn error(&self) -> PoseError {
        let align = self.alignment();
        let n = self.given.len().max(1) as f32;
        let (mut rotations, mut trans) = (Vec::with_capacity(self.given.len()), 0.0);
        for (g, r) in self.given.iter().zip(&self.refined) {
            let a = align.apply_pose(r);
            rotations.push(rotation_error_degrees(&a, g));
            trans += length(sub(origin(&a), origin(g)));
        }
        let rot: f32 = rotations.iter().sum();
        rotations.sort_by(f32::total_cmp);
        let median = match rotations.len() {
            0 => 0.0,
            k if k % 2 == 1 => rotations[k / 2],
            k => 0.5 * (rotations[k / 2 - 1] + rotations[k / 2]),
        };
        let centres: Vec<_> = self.given.iter().map(origin).collect();
        let mean = centres.iter().fold([0.0f32; 3], |m, c| {
            [m[0] + c[0] / n, m[1] + c[1] / n, m[2] + c[2] / n]
        });
        let radius = (centres
            .iter()
            .map(|c| length(sub(*c, mean)).powi(2))
            .sum::<f32>()
            / n)
            .sqrt()
            .max(1e-9);
        PoseError {
            rotation_deg: rot / n,
            translation: trans / n,
            translation_percent_of_radius: 100.0 * trans / n / radius,
            rotation_deg_median: median,
            rotation_deg_max: rotations.last().copied().unwrap_or(0.0),
        }
    }

    /// The similarity that moves a camera given in the scene's frame into the frame the
    /// model learned (the alignment's inverse): fit once, applied to every camera.
    pub fn to_model_frame(&self) -> Similarity {
        self.alignment().inverse()
    }
}

/// The training cameras of a run before any correction: as the scene gives them, and as
/// the run starts from (moved by `--perturb-poses`). Read once, then corrected by any
/// state of the run's parameters (training tracks the pose error as it goes).
#[derive(Clone, Debug)]
pub struct StartingCameras {
    given: Vec<Pose>,
    start: Vec<Pose>,
    frame: Option<Frame>,
}

impl StartingCameras {
    pub fn of(config: &TrainConfig) -> Result<StartingCameras> {
        let scene = config.open_scene(1)?;
        let all = scene.cameras(Split::Train);
        // The views the run trained on (`--train-views`): correction k belongs to the k-th.
        let kept = evenly_kept(all.len(), config.train_views.unwrap_or(0));
        let given: Vec<Pose> = kept.iter().map(|&i| all[i].c2w).collect();
        let mut start = given.clone();
        if let Some(p) = &config.perturb_poses {
            p.apply(&mut start.iter_mut().collect::<Vec<_>>());
        }
        let frame = match &config.model {
            crate::model::ModelConfig::Fast(m) => m.refine_cameras.map(|r| r.frame),
            crate::model::ModelConfig::Vanilla(_) => None,
        };
        Ok(StartingCameras {
            given,
            start,
            frame,
        })
    }

    /// The cameras with the corrections held in `params` (laid out by `layout`) applied.
    pub fn corrected_by(&self, layout: &ParamLayout, params: &[f32]) -> RunCameras {
        let learned = corrections(layout, params);
        let mut refined = self.start.clone();
        if let (Some(c), Some(frame)) = (learned, self.frame) {
            for (pose, corr) in refined.iter_mut().zip(c.chunks_exact(PER_CAMERA)) {
                *pose = corrected(pose, corr, frame);
            }
        }
        RunCameras {
            given: self.given.clone(),
            refined,
            refined_by_model: learned.is_some(),
        }
    }
}
