//! Cameras that refinement leaves stuck: found by how badly the field explains their
//! photo, brought back by a pose search against the field, left out of training when no
//! pose explains it.
//!
//! Refinement follows the photometric gradient, and a camera that starts tens of degrees
//! off can settle in a pose from which every small step looks worse, while the others
//! converge around it (on lego with BARF's noise, one draw in a few leaves one camera 24
//! degrees off). Such a camera stands out: the field, shaped by the cameras that did
//! converge, explains its photo several times worse than the median camera's. So at a few
//! points of the schedule ([`CHECKS`]) every training photo is compared with the field's
//! picture from its current pose, at a low resolution; a camera [`SEARCH_RATIO`] times
//! worse than the median is searched for (`pose_search`). The best pose is kept if it
//! explains the photo clearly better ([`BETTER`]), and the camera's optimiser state is reset
//! so the gradient takes over from there. A camera still [`STUCK_RATIO`] times worse after
//! the last check is left out of training, so its photo stops smearing the field.

use serde::{Deserialize, Serialize};

use super::pose_search::{search, Probes};
use crate::camera::Pose;
use crate::engine::{Engine, EngineState};
use crate::model::camera_refine::{corrected, Frame, PER_CAMERA};

/// A camera whose photo's error is this many times the median camera's is searched for.
pub const SEARCH_RATIO: f32 = 2.5;

/// A camera whose photo's error is still this many times the median camera's after the
/// last check's search is left out.
pub const STUCK_RATIO: f32 = 4.0;

/// A searched pose replaces a stuck camera's when its error is below this fraction of
/// the current one: a clear gain, not the noise of a low-resolution probe.
pub const BETTER: f32 = 0.7;

/// Where in the schedule (fractions of it) the cameras are checked. The last check
/// leaves out the cameras still stuck.
pub const CHECKS: [f32; 5] = [0.2, 0.3, 0.4, 0.5, 0.6];

/// Checks falling before this step are skipped: the field is still fog that explains every
/// photo about equally badly, so a ratio to the median says nothing yet, and a search
/// would cost far more than the few steps a run this short trains.
pub const FIRST_CHECK_STEP: u64 = 100;

/// What one check found and did, for the training log and `metrics.json`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct CheckReport {
    pub step: u64,
    /// The median camera's error (MSE on the probe).
    pub median_error: f32,
    /// The worst camera's error, in multiples of the median's.
    #[serde(default)]
    pub worst_ratio: f32,
    /// Each stuck camera: its index and what was done.
    pub stuck: Vec<StuckCamera>,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StuckCamera {
    pub camera: usize,
    /// Its error before and after the search, in multiples of the median camera's.
    pub ratio_before: f32,
    pub ratio_after: f32,
    /// The turn the search applied, in degrees (0: none better was found).
    pub turned_deg: f32,
    /// Left out of training from this check on.
    pub left_out: bool,
}

/// The median of `errors` and the cameras whose error is [`SEARCH_RATIO`] times it or more.
pub fn stuck(errors: &[f32]) -> (f32, Vec<usize>) {
    let mut sorted = errors.to_vec();
    sorted.sort_by(f32::total_cmp);
    let median = sorted.get(sorted.len() / 2).copied().unwrap_or(0.0);
    let floor = median.max(1e-6);
    let found = errors
        .iter()
        .enumerate()
        .filter(|(_, &e)| e >= SEARCH_RATIO * floor)
        .map(|(k, _)| k)
        .collect();
    (median, found)
}

/// Whether a camera is left out at the last check: still [`STUCK_RATIO`] times worse than
/// the median after the search (`after`), and not better than at the previous check
/// (`now` against `previous`, ratios before the searches).
fn unexplained(after: f32, now: f32, previous: f32) -> bool {
    after >= STUCK_RATIO && now >= previous
}

/// The camera corrections in an engine's state: their offset, the frame they act in.
pub struct Corrections {
    pub start: usize,
    pub frame: Frame,
}

/// Checks every camera at `step` against the field and searches for the stuck ones;
/// `starts`: the cameras' poses before correction (the training split's, perturbed);
/// `last`: whether cameras still stuck are left out (listed in the report);
/// `previous`: each camera's ratio at the previous check (0 where it was not stuck). A
/// camera is left out only if its ratio has not fallen since: a photo at the edge of a
/// capture, seen by few others, starts worse than the rest and catches up as the field
/// learns its part of the scene, while a photo no pose explains falls further behind.
/// Updates the engine's corrections (and resets their optimiser state) where a search
/// found better.
pub fn check(
    engine: &mut dyn Engine,
    probes: &Probes,
    starts: &[Pose],
    at: &Corrections,
    step: u64,
    last: bool,
    previous: &[f32],
) -> crate::error::Result<CheckReport> {
    let mut state: EngineState = engine.state();
    let correction = |params: &[f32], k: usize| -> [f32; PER_CAMERA] {
        std::array::from_fn(|i| params[at.start + PER_CAMERA * k + i])
    };
    let poses: Vec<Pose> = (0..starts.len())
        .map(|k| corrected(&starts[k], &correction(&state.params, k), at.frame))
        .collect();
    let errors = probes.fine.each_error(engine, &poses);
    let (median, stuck_cameras) = stuck(&errors);
    let floor = median.max(1e-6);
    let mut report = CheckReport {
        step,
        median_error: median,
        worst_ratio: errors.iter().fold(0.0f32, |m, &e| m.max(e / floor)),
        stuck: Vec::new(),
    };
    let mut changed = false;
    for k in stuck_cameras {
        let now = correction(&state.params, k);
        let best = search(engine, probes, k, &starts[k], at.frame, (errors[k], now));
        let improved = best.0 < BETTER * errors[k];
        let turned_deg = if improved {
            let range = at.start + PER_CAMERA * k..at.start + PER_CAMERA * (k + 1);
            state.params[range.clone()].copy_from_slice(&best.1);
            state.adam_m[range.clone()].fill(0.0);
            state.adam_v[range].fill(0.0);
            changed = true;
            crate::data::poses::rotation_error_degrees(
                &corrected(&starts[k], &now, at.frame),
                &corrected(&starts[k], &best.1, at.frame),
            )
        } else {
            0.0
        };
        let after = if improved { best.0 } else { errors[k] };
        report.stuck.push(StuckCamera {
            camera: k,
            ratio_before: errors[k] / floor,
            ratio_after: after / floor,
            turned_deg,
            left_out: last
                && unexplained(
                    after / floor,
                    errors[k] / floor,
                    previous.get(k).copied().unwrap_or(0.0),
                ),
        });
    }
    if changed {
        engine.set_state(state)?;
    }
    Ok(report)
}

/// The checks of one training run: when they are due and what they compare against.
pub struct Checker {
    probes: Option<Probes>,
    starts: Vec<Pose>,
    at: Corrections,
    codes: bool,
    /// Cameras left out so far.
    pub left_out: Vec<usize>,
    /// Each camera's ratio at the last check (0 where it was not stuck).
    previous: Vec<f32>,
}

impl Checker {
    /// The checker of `trainer`'s run; `None` when it refines no camera.
    pub fn of(trainer: &super::Trainer) -> Option<Checker> {
        let crate::model::ModelConfig::Fast(m) = &trainer.config.model else {
            return None;
        };
        let refinement = m.refine_cameras.filter(|r| r.recover_stuck)?;
        let start = crate::model::camera_refine::corrections_start(trainer.engine.param_layout())?;
        let cameras = refinement.cameras.min(trainer.data.views.len());
        Some(Checker {
            probes: None,
            starts: trainer.data.views[..cameras]
                .iter()
                .map(|v| v.camera.c2w)
                .collect(),
            at: Corrections {
                start,
                frame: refinement.frame,
            },
            codes: m.field.appearance_dims > 0,
            left_out: Vec::new(),
            previous: vec![0.0; cameras],
        })
    }

    /// Whether a check falls between schedule fractions `before` and `after` (a step's
    /// progress before and after it) of the step that ends at `step`, and whether it is
    /// the last; none before [`FIRST_CHECK_STEP`].
    pub fn due(before: f64, after: f64, step: u64) -> Option<bool> {
        if step < FIRST_CHECK_STEP {
            return None;
        }
        CHECKS
            .iter()
            .rposition(|&f| (before as f32) < f && f <= after as f32)
            .map(|i| i + 1 == CHECKS.len())
    }

    /// Takes up where an earlier session's checks left off: their last report (the
    /// cameras' ratios then) and every camera they left out, which stays out.
    pub fn resume(&mut self, trainer: &mut super::Trainer, reports: &[CheckReport]) {
        if let Some(last) = reports.last() {
            self.remember(last);
        }
        let out: Vec<usize> = reports
            .iter()
            .flat_map(|r| &r.stuck)
            .filter(|s| s.left_out)
            .map(|s| s.camera)
            .collect();
        if !out.is_empty() {
            self.leave_out(trainer, &out);
        }
    }

    fn remember(&mut self, report: &CheckReport) {
        self.previous.iter_mut().for_each(|r| *r = 0.0);
        for s in &report.stuck {
            if let Some(r) = self.previous.get_mut(s.camera) {
                *r = s.ratio_before;
            }
        }
    }

    /// Leaves `cameras` out of `trainer`'s training.
    fn leave_out(&mut self, trainer: &mut super::Trainer, cameras: &[usize]) {
        for &k in cameras {
            if k < self.starts.len() && !self.left_out.contains(&k) {
                self.left_out.push(k);
            }
        }
        trainer.data.leave_out(self.starts.len(), &self.left_out);
    }

    /// Checks the cameras now ([`check`]) and leaves out those the report says to.
    pub fn run(
        &mut self,
        trainer: &mut super::Trainer,
        last: bool,
    ) -> crate::error::Result<CheckReport> {
        let (cameras, codes) = (self.starts.len(), self.codes);
        let probes = self
            .probes
            .get_or_insert_with(|| Probes::new(&trainer.data, cameras, codes));
        let report = check(
            trainer.engine.as_mut(),
            probes,
            &self.starts,
            &self.at,
            trainer.step,
            last,
            &self.previous,
        )?;
        self.remember(&report);
        let out: Vec<usize> = report
            .stuck
            .iter()
            .filter(|s| s.left_out)
            .map(|s| s.camera)
            .collect();
        if !out.is_empty() {
            self.leave_out(trainer, &out);
        }
        Ok(report)
    }
}

/// The training log's line for a stuck camera.
pub fn describe(s: &StuckCamera, step: u64) -> String {
    let found = if s.turned_deg > 0.0 {
        format!(
            "a pose search turned it {:.1} degrees, to {:.1}x",
            s.turned_deg, s.ratio_after
        )
    } else {
        "a pose search found none better".to_string()
    };
    let fate = if s.left_out {
        "; left out of training from here on, so its photo does not smear the field"
    } else {
        ""
    };
    format!(
        "step {step}: camera {} looks stuck (its photo {:.1}x the median camera's error); {found}{fate}",
        s.camera, s.ratio_before
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_camera_far_worse_than_the_median_is_stuck() {
        let errors = [0.010, 0.012, 0.011, 0.009, 0.050, 0.029, 0.013];
        let (median, found) = stuck(&errors);
        assert_eq!(median, 0.012);
        assert_eq!(found, vec![4]);
        assert!(stuck(&[0.0; 5]).1.is_empty());
    }

    #[test]
    fn only_a_photo_falling_behind_is_left_out() {
        // Noise: worse and worse as the rest converge.
        assert!(unexplained(25.0, 25.0, 20.0));
        // Not stuck at the check before: rising.
        assert!(unexplained(4.5, 4.5, 0.0));
        // The edge of a capture: bad, catching up.
        assert!(!unexplained(4.5, 4.5, 5.0));
        // Recovered by the search.
        assert!(!unexplained(1.5, 6.0, 5.0));
    }

    #[test]
    fn checks_fall_where_a_step_crosses_their_fraction() {
        let step = FIRST_CHECK_STEP;
        assert_eq!(Checker::due(0.0, 0.1, step), None);
        assert_eq!(Checker::due(0.19, 0.2, step), Some(false));
        // A step that starts on a check's fraction comes after it (a resumed run).
        assert_eq!(Checker::due(0.2, 0.21, step), None);
        assert_eq!(Checker::due(0.59, 0.61, step), Some(true));
        assert_eq!(Checker::due(0.6, 1.0, step), None);
        // One step of a short run crosses several fractions: one check, the last if it
        // crosses the last.
        assert_eq!(Checker::due(0.0, 0.5, step), Some(false));
        assert_eq!(Checker::due(0.0, 0.7, step), Some(true));
        // A run too short for the field to explain any photo yet is not checked.
        assert_eq!(Checker::due(0.19, 0.2, FIRST_CHECK_STEP - 1), None);
        assert_eq!(Checker::due(0.59, 0.61, 50), None);
    }
}
