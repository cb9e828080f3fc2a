//! The training cameras of a run that refined them (`--refine-cameras`): the poses it
//! ended with, how far they are from the given ones (BARF's evaluation), and where the
//! test cameras sit in the frame the model learned.
//!
//! A refined model is free to drift as a whole (any similarity of all cameras and the
//! scene explains the photos equally well), so the refined cameras are first aligned to
//! the given ones by a similarity (its rotation from the cameras' orientations, Horn's
//! method; its scale and translation from their centres: BARF aligns the centres alone,
//! which leaves a flat grid's rotation loose), and the
//! errors are measured after it: mean rotation error in degrees, mean centre distance in
//! scene units and in percent of the cameras' radius (their RMS distance from their
//! centroid). Test cameras, given in the scene's frame, are mapped into the model's by
//! the inverse of that similarity.

use serde::{Deserialize, Serialize};

use super::folder::LoadedRun;
use super::TrainConfig;
use crate::camera::Pose;
use crate::data::poses::{fit_similarity_of_poses, origin, rotation_error_degrees, Similarity};
use crate::data::Split;
use crate::error::Result;
use crate::math::{length, sub};
use crate::model::camera_refine::{corrected, corrections, Frame, PER_CAMERA};
use crate::nn::ParamLayout;

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

    /// The similarity that best maps the refined cameras onto the given ones
    /// ([`fit_similarity_of_poses`]: orientations for the rotation, centres for the rest).
    pub fn alignment(&self) -> Similarity {
        fit_similarity_of_poses(&self.refined, &self.given)
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
        let kept = config.kept_train_views(all.len())?;
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::look_at;
    use crate::data::poses::fit_similarity;
    use crate::math::add;
    use crate::rng::Rng;

    /// A forward-facing 5x6 grid whose cameras are each turned by about a degree and moved
    /// by a sixth of the grid's spread, then the whole set moved by a similarity (the drift
    /// a refined model is free to take). The errors after alignment are the ones put in:
    /// aligning on the centres alone turns the grid to fit the centres' noise, and the
    /// rotation error it reports is several times too large.
    #[test]
    fn alignment_recovers_the_errors_of_a_flat_grid() {
        let mut rng = Rng::new(4);
        let given: Vec<Pose> = (0..30)
            .map(|k| {
                let eye = [0.1 * (k % 6) as f32, 0.1 * (k / 6) as f32, 0.0];
                look_at(eye, add(eye, [0.0, 0.0, -1.0]), [0.0, 1.0, 0.0])
            })
            .collect();
        let drift = Similarity {
            rotation: crate::model::camera_refine::rotation([0.2, -0.1, 0.3]),
            translation: [1.0, 2.0, -0.5],
            scale: 1.7,
        };
        let mut turned_by = Vec::new();
        let refined: Vec<Pose> = given
            .iter()
            .map(|g| {
                let w = [0.0; 3].map(|_: f32| rng.range(-0.02, 0.02));
                let noise = Similarity {
                    rotation: crate::model::camera_refine::rotation(w),
                    ..Similarity::IDENTITY
                };
                let mut p = noise.apply_pose(g);
                let shift = [0.0; 3].map(|_: f32| rng.range(-0.05, 0.05));
                let o = add(origin(g), shift);
                for r in 0..3 {
                    p[r][3] = o[r];
                }
                turned_by.push(rotation_error_degrees(&p, g));
                drift.apply_pose(&p)
            })
            .collect();
        let put_in = turned_by.iter().sum::<f32>() / turned_by.len() as f32;
        let cameras = RunCameras {
            given: given.clone(),
            refined: refined.clone(),
            refined_by_model: true,
        };
        let measured = cameras.error().rotation_deg;
        assert!(
            (measured - put_in).abs() < 0.15 * put_in,
            "{measured} degrees measured, {put_in} put in"
        );
        let by_centres = {
            let from: Vec<_> = refined.iter().map(origin).collect();
            let to: Vec<_> = given.iter().map(origin).collect();
            let align = fit_similarity(&from, &to).0;
            let n = given.len() as f32;
            given
                .iter()
                .zip(&refined)
                .map(|(g, r)| rotation_error_degrees(&align.apply_pose(r), g))
                .sum::<f32>()
                / n
        };
        eprintln!(
            "{put_in:.3} degrees put in, {measured:.3} measured, {by_centres:.3} by the centres"
        );
        assert!(
            by_centres > 2.0 * put_in,
            "{by_centres} by the centres alone"
        );
        // Exact cameras under a drift: no error at all.
        let drifted: Vec<Pose> = given.iter().map(|g| drift.apply_pose(g)).collect();
        let exact = RunCameras {
            given,
            refined: drifted,
            refined_by_model: true,
        }
        .error();
        assert!(exact.rotation_deg < 0.05 && exact.translation_percent_of_radius < 0.05);
    }
}
