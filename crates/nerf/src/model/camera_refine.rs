//! Camera refinement (after BARF, Lin et al. 2021): every training camera carries a learned
//! rigid correction, optimised with the field, so poses from structure from motion that
//! are a little off stop blurring the model.
//!
//! A correction is 6 numbers `(w, tau)`: the rotation `R = exp([w]x)` (Rodrigues) and the
//! translation `tau`, applied in one of two frames ([`Frame`]):
//!
//! - **World** (BARF's, the default where the world's origin is the scene's centre: every
//!   format but forward-facing NDC captures): the rigid motion
//!   `[R | tau]` moves the camera in the world, `camera_to_world' = [R | tau] *
//!   camera_to_world`. A ray `(o, d)` becomes `o' = R o + tau`, `d' = R d`. The rotation
//!   turns the camera about the world's origin, the scene's centre: it changes the angle
//!   the object is seen from while the object stays where it is in the picture, and `tau`
//!   shifts the picture. The two barely compete, so the corrections converge.
//! - **Camera** (forward-facing NDC captures, whose origin is their mean camera, and runs
//!   saved before the world frame): `camera_to_world' = camera_to_world *
//!   [R | tau]`, turning the camera about its own centre: `o' = o + C tau`,
//!   `d' = C R C^T d` (`C` the camera's rotation). A turn and a sideways move shift the
//!   picture alike; on lego with BARF's noise this frame ended 11.1 degrees off on average
//!   against the world frame's 2.7 (100 px, 3000 steps).
//!
//! Either way the ray's direction in the camera frame is untouched, so any lens works
//! (undistortion happens there).
//!
//! Gradients: the field gives `dL/d sample position`; a sample sits at `o' + t d'/|d'|`
//! (its depth `t` is held fixed, as sampling is not differentiated), so a ray collects
//! `dL/do' = sum dL/dp` and `dL/dd^ = sum t dL/dp`, and the view direction (the same unit
//! `d'`) adds its own `dL/dd^` from the colour network's spherical harmonics. Then, with
//! `dR/dw_k` from [`rotation_jacobian`]:
//!
//! - world: `dL/dtau = dL/do'` and `dL/dw_k = sum_ij (dR/dw_k)_ij (dL/do'_i o_j +
//!   dL/dd^_i u_j)`, `o` the camera's centre and `u = R^T d^` the direction before the turn;
//! - camera: `dL/dtau = C^T dL/do'` and `dL/dw_k = sum_ij (dR/dw_k)_ij (C^T dL/dd^)_i v_j`,
//!   `v = R^T C^T d^`;
//!
//! summed over the camera's rays.
//!
//! Forward-facing scenes march in NDC: there the camera's world ray is corrected, then
//! warped into NDC again, and the gradient goes back through the warp
//! (`RaySpace::warp_backward`) before reaching the pose.
//!
//! Coarse to fine: early on, the fine hash-grid levels are switched off and weighted in
//! smoothly as training goes (BARF's schedule, on levels instead of frequencies), so the
//! first pose gradients come from a smooth field. Runs with errors of degrees (outside
//! NDC) weight only the cameras' gradient (`pose_gradient_only`): the field learns every
//! level from the first step.

use serde::{Deserialize, Serialize};

use crate::camera::ray_space::RaySpace;
use crate::camera::Pose;
use crate::math::V3;

/// Parameters per camera.
pub const PER_CAMERA: usize = 6;
/// Name of the corrections in checkpoints (`cameras x 6`).
pub const TENSOR: &str = "camera.corrections";

/// The corrections' default learning rate, for real captures (COLMAP poses a fraction of a
/// degree off): a higher rate lets the cameras wander from COLMAP's further than their
/// error, and held-out views get worse (figures in `docs/benchmarks.md`). Large errors
/// need [`LARGE_ERROR_LR`].
pub const DEFAULT_LR: f32 = 6e-4;

/// The [`CameraRefinement::delay`] of runs whose poses are a fraction of a degree off
/// (real captures): before the field has taken shape, the few rays a camera gets per step
/// pull it every which way and Adam turns that into full steps, so the cameras drift from
/// COLMAP's by more than their error; starting a fifth of the way in keeps them close
/// (ngp_fox, `docs/benchmarks.md`).
pub const SMALL_ERROR_DELAY: f32 = 0.2;

/// The learning rate for errors of degrees, the default of runs that `--perturb-poses`:
/// at the real-capture rate, cameras degrees off do not come back within the schedule.
pub const LARGE_ERROR_LR: f32 = 1e-2;

/// Where the corrections' rate decays to for errors of degrees outside NDC, as a fraction
/// of [`LARGE_ERROR_LR`] (a hundredth elsewhere): each camera gets a few dozen rays a step,
/// so its gradient is mostly noise and Adam turns noise into steps of about the rate. A
/// hundredth leaves the cameras wandering about 0.06 degrees from their poses at the end;
/// a thousandth settles them sooner and closer (figures in `docs/benchmarks.md`).
pub const LARGE_ERROR_FINAL_FRACTION: f32 = 1e-3;

/// [`LARGE_ERROR_LR`] for forward-facing NDC captures, whose cameras all look one way: at
/// the larger rate they drift together to a pose set that fits the training photos and
/// not the held-out ones.
pub const LARGE_ERROR_LR_NDC: f32 = 3e-3;

/// Where a correction acts (see the module's documentation). A run's `config.json` names
/// it; runs saved before it existed corrected in the camera's frame.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Frame {
    /// `camera_to_world * [R | tau]`: about the camera's centre, in its own axes.
    #[default]
    Camera,
    /// `[R | tau] * camera_to_world`: about the world's origin, in world axes (BARF).
    World,
}

impl Frame {
    /// The frame new corrections of cameras marching in `space` act in: the world where
    /// its origin is the scene's centre, each camera's own in a forward-facing NDC capture,
    /// whose origin is its mean camera, not what the cameras look at (there the world frame
    /// measured worse held out).
    pub fn for_space(space: RaySpace) -> Frame {
        match space {
            RaySpace::World => Frame::World,
            RaySpace::Ndc(_) => Frame::Camera,
        }
    }
}

/// How the training cameras are refined.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CameraRefinement {
    /// Training cameras with a correction (the training split's size).
    pub cameras: usize,
    /// Learning rate of the corrections, decaying exponentially from `lr_init` to
    /// `lr_final` over the schedule (their own Adam group).
    pub lr_init: f32,
    pub lr_final: f32,
    /// Coarse to fine: the hash-grid levels beyond the first `start_levels` are weighted
    /// in between these two fractions of the schedule.
    pub anneal: [f32; 2],
    pub start_levels: f32,
    /// Where the corrections act.
    #[serde(default)]
    pub frame: Frame,
    /// The coarse-to-fine weights act on the pose gradient only: the field renders and
    /// learns every level from the first step, and the cameras are moved by the gradient
    /// of its coarse levels (a straight-through schedule, after Heo et al., ICML 2023).
    /// On for errors of degrees (`--perturb-poses`) outside NDC, where it measured better
    /// than BARF's schedule. Off: BARF's schedule, which also holds the field's fine levels
    /// back, and so regularises it: better on real captures, whose poses are a fraction of
    /// a degree off, and on forward-facing ones. Runs saved before this existed used BARF's.
    #[serde(default)]
    pub pose_gradient_only: bool,
    /// Where (a fraction of the schedule) the field's learning-rate decay starts over from
    /// its initial rate, or `None`. Set at the coarse-to-fine window's end for runs with
    /// errors of degrees: by then the cameras are within a fraction of a degree, and the
    /// field relearns at full rate what it had learned through cameras degrees off.
    /// Runs saved before this existed had none.
    #[serde(default)]
    pub field_restart: Option<f32>,
    /// Where (a fraction of the schedule) the corrections start to move; their decay then
    /// runs over the rest. Until the field has taken shape, the few rays each camera gets
    /// per step pull it every which way, and Adam turns even a pointless gradient into a
    /// full step: at the schedule's start, where the rate is highest, cameras a fraction
    /// of a degree off drift further than they were off. Set for such errors (real
    /// captures, [`SMALL_ERROR_DELAY`]); errors of degrees need the coarse field's pull
    /// from the start. Runs saved before this existed had none.
    #[serde(default)]
    pub delay: f32,
    /// Cameras that stall far from the rest are searched for and, if that fails, left
    /// out (`train::stuck_cameras`). Runs saved before this existed had no such checks.
    #[serde(default)]
    pub recover_stuck: bool,
}

impl CameraRefinement {
    pub fn new(cameras: usize) -> Self {
        CameraRefinement {
            cameras,
            lr_init: 0.0,
            lr_final: 0.0,
            anneal: [0.05, 0.4],
            start_levels: 4.0,
            frame: Frame::World,
            pose_gradient_only: false,
            field_restart: None,
            delay: 0.0,
            recover_stuck: true,
        }
        .with_learning_rate(DEFAULT_LR)
    }

    /// The same refinement at learning rate `lr`, decaying to a hundredth of it
    /// (`--camera-lr`).
    pub fn with_learning_rate(self, lr: f32) -> Self {
        CameraRefinement {
            lr_init: lr,
            lr_final: lr / 100.0,
            ..self
        }
    }

    /// The corrections' learning rate at `progress` in [0, 1]: zero before the
    /// [`delay`](Self::delay), then decaying exponentially from `lr_init` to `lr_final`.
    pub fn learning_rate(&self, progress: f32) -> f32 {
        let p = progress.clamp(0.0, 1.0);
        if p < self.delay {
            return 0.0;
        }
        let p = ((p - self.delay) / (1.0 - self.delay).max(1e-6)).clamp(0.0, 1.0);
        self.lr_init * (self.lr_final / self.lr_init).powf(p)
    }

    /// Where the field's learning-rate schedule stands at `progress`: `progress` itself,
    /// or, past a [`field_restart`](Self::field_restart) at `r`, `(progress - r) / (1 - r)`
    /// (the decay starts over and still ends with the schedule).
    pub fn field_progress(&self, progress: f64) -> f64 {
        match self.field_restart {
            // Compared in f32, as `r` was written: 0.4f32 is a hair above 0.4f64.
            Some(r) if progress as f32 >= r && r < 1.0 => {
                ((progress - r as f64) / (1.0 - r as f64)).max(0.0)
            }
            _ => progress,
        }
    }

    /// Weight of each of `levels` hash-grid levels at `progress`: 1 for the first
    /// `start_levels`, then `(1 - cos(pi * clamp(a - l, 0, 1))) / 2` with `a` growing
    /// linearly to `levels` over the anneal window (BARF's weights).
    pub fn level_weights(&self, levels: usize, progress: f32) -> Vec<f32> {
        let [p0, p1] = self.anneal;
        let ramp = ((progress - p0) / (p1 - p0).max(1e-6)).clamp(0.0, 1.0);
        let start = self.start_levels.min(levels as f32);
        let a = start + ramp * (levels as f32 - start);
        (0..levels)
            .map(|l| {
                let x = (a - l as f32).clamp(0.0, 1.0);
                0.5 * (1.0 - (std::f32::consts::PI * x).cos())
            })
            .collect()
    }
}

/// BARF's synthetic test of refinement: every training pose moved by a random rigid
/// motion, `w` and `tau` normal with standard deviation `sigma` (`--perturb-poses`).
///
/// BARF moves the world before each camera (about the world's origin), so the object
/// stays near the middle of every photo: `frame` World. (BARF draws its translation
/// through the se(3) exponential, `V(w) tau`, and we draw `tau` itself: the rotations'
/// distribution is the same, the translations' differs by a small skew.) Runs saved
/// before the frame was recorded moved each camera about its own centre, which shifts
/// the object by up to a third of the picture at sigma 0.15.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct PosePerturbation {
    pub sigma: f32,
    pub seed: u64,
    #[serde(default)]
    pub frame: Frame,
}

impl PosePerturbation {
    /// The correction that moves training camera `k`.
    pub fn noise(&self, k: usize) -> [f32; PER_CAMERA] {
        let mut rng = crate::rng::Rng::for_stream(self.seed ^ 0x9e3779b9, 0, k as u64);
        // Box-Muller.
        std::array::from_fn(|_| {
            let (u1, u2) = (rng.uniform().max(1e-7), rng.uniform());
            self.sigma * (-2.0 * u1.ln()).sqrt() * (std::f32::consts::TAU * u2).cos()
        })
    }

    /// Moves every pose of `poses` (in the split's order).
    pub fn apply(&self, poses: &mut [&mut Pose]) {
        for (k, p) in poses.iter_mut().enumerate() {
            **p = corrected(p, &self.noise(k), self.frame);
        }
    }
}

/// `SIGMA[,SEED]` of `--perturb-poses`.
pub fn parse_perturbation(s: &str) -> Result<PosePerturbation, String> {
    let (sigma, seed) = match s.split_once(',') {
        Some((a, b)) => (a, Some(b)),
        None => (s, None),
    };
    let sigma: f32 = sigma
        .trim()
        .parse()
        .map_err(|_| format!("{sigma:?} is not a number (SIGMA[,SEED])"))?;
    if !(sigma.is_finite() && sigma >= 0.0) {
        return Err(format!("sigma {sigma} must be a finite number >= 0"));
    }
    let seed = match seed {
        Some(t) => t
            .trim()
            .parse()
            .map_err(|_| format!("{t:?} is not a whole number (SIGMA[,SEED])"))?,
        None => 0,
    };
    Ok(PosePerturbation {
        sigma,
        seed,
        frame: Frame::World,
    })
}

/// `exp([w]x)`, Rodrigues' formula (a series near zero).
pub fn rotation(w: V3) -> [[f32; 3]; 3] {
    rotation_f64(w.map(f64::from)).map(|r| r.map(|v| v as f32))
}

fn rotation_f64(w: [f64; 3]) -> [[f64; 3]; 3] {
    let theta2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2];
    let theta = theta2.sqrt();
    let (a, b) = if theta < 1e-6 {
        (1.0 - theta2 / 6.0, 0.5 - theta2 / 24.0)
    } else {
        (theta.sin() / theta, (1.0 - theta.cos()) / theta2)
    };
    let k = [[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]];
    let mut r = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            let k2: f64 = (0..3).map(|m| k[i][m] * k[m][j]).sum();
            r[i][j] = if i == j { 1.0 } else { 0.0 } + a * k[i][j] + b * k2;
        }
    }
    r
}

/// `dR/dw_k` for k = 0, 1, 2, by central differences in f64 (errors near 1e-10: far below
/// f32's resolution), so no closed form of the exponential map's Jacobian is needed.
pub fn rotation_jacobian(w: V3) -> [[[f32; 3]; 3]; 3] {
    let w = w.map(f64::from);
    std::array::from_fn(|k| {
        let h = 1e-6;
        let (mut lo, mut hi) = (w, w);
        lo[k] -= h;
        hi[k] += h;
        let (a, b) = (rotation_f64(hi), rotation_f64(lo));
        std::array::from_fn(|i| std::array::from_fn(|j| ((a[i][j] - b[i][j]) / (2.0 * h)) as f32))
    })
}

/// A camera-to-world pose with its correction applied in `frame`: `[R(w) | tau] * pose`
/// (world) or `pose * [R(w) | tau]` (camera).
pub fn corrected(pose: &Pose, correction: &[f32], frame: Frame) -> Pose {
    let r = rotation([correction[0], correction[1], correction[2]]);
    let tau = [correction[3], correction[4], correction[5]];
    let mut out = *pose;
    for i in 0..3 {
        match frame {
            Frame::World => {
                for j in 0..4 {
                    out[i][j] = (0..3).map(|m| r[i][m] * pose[m][j]).sum();
                }
                out[i][3] += tau[i];
            }
            Frame::Camera => {
                for j in 0..3 {
                    out[i][j] = (0..3).map(|m| pose[i][m] * r[m][j]).sum();
                }
                out[i][3] = pose[i][3] + (0..3).map(|m| pose[i][m] * tau[m]).sum::<f32>();
            }
        }
    }
    out
}

/// `w` with `exp([w]x) = r` and `|w|` in [0, pi]: the inverse of [`rotation`] for a
/// rotation matrix `r`. Near a half turn the axis comes from `r + r^T`, where the
/// antisymmetric part vanishes.
pub fn rotation_log(r: &[[f32; 3]; 3]) -> V3 {
    let r = r.map(|row| row.map(f64::from));
    let skew = [r[2][1] - r[1][2], r[0][2] - r[2][0], r[1][0] - r[0][1]];
    let sin = 0.5 * skew.iter().map(|v| v * v).sum::<f64>().sqrt();
    let cos = (r[0][0] + r[1][1] + r[2][2] - 1.0) / 2.0;
    // atan2 keeps the angle well conditioned where acos of the trace is not (near 0, pi).
    let theta = sin.atan2(cos);
    let w = if theta < 1e-6 {
        skew.map(|v| 0.5 * v)
    } else if sin > 1e-2 {
        skew.map(|v| v * theta / (2.0 * sin))
    } else {
        // r = 2 a a^T - I at a half turn: the axis is the largest column of (r + I) / 2.
        let k = (0..3)
            .max_by(|&a, &b| r[a][a].total_cmp(&r[b][b]))
            .unwrap_or(0);
        let col: [f64; 3] = std::array::from_fn(|i| (r[i][k] + r[k][i]) / 2.0 + f64::from(i == k));
        let norm = col.iter().map(|v| v * v).sum::<f64>().sqrt().max(1e-12);
        // Pick the sign the antisymmetric part still shows.
        let sign = if col.iter().zip(&skew).map(|(a, b)| a * b).sum::<f64>() < 0.0 {
            -1.0
        } else {
            1.0
        };
        col.map(|v| sign * theta * v / norm)
    };
    w.map(|v| v as f32)
}

/// The correction that leaves a camera turned by `turn` beyond where `correction` puts it:
/// about the world point `pivot` (`[turn | pivot - turn pivot] * corrected`) in the world
/// frame, about the camera's own centre in its own axes (`corrected * [turn | 0]`, `pivot`
/// unused) in the camera frame.
pub fn turned(
    correction: &[f32],
    turn: &[[f32; 3]; 3],
    pivot: V3,
    frame: Frame,
) -> [f32; PER_CAMERA] {
    let r = rotation([correction[0], correction[1], correction[2]]);
    let tau = [correction[3], correction[4], correction[5]];
    let product = |a: &[[f32; 3]; 3], b: &[[f32; 3]; 3]| -> [[f32; 3]; 3] {
        std::array::from_fn(|i| std::array::from_fn(|j| (0..3).map(|m| a[i][m] * b[m][j]).sum()))
    };
    let (rotation, tau) = match frame {
        Frame::World => {
            let (t, p) = (mat_vec(turn, tau), mat_vec(turn, pivot));
            (
                product(turn, &r),
                std::array::from_fn(|i| t[i] + pivot[i] - p[i]),
            )
        }
        Frame::Camera => (product(&r, turn), tau),
    };
    let w = rotation_log(&rotation);
    [w[0], w[1], w[2], tau[0], tau[1], tau[2]]
}

fn mat_vec(m: &[[f32; 3]; 3], v: V3) -> V3 {
    std::array::from_fn(|i| m[i][0] * v[0] + m[i][1] * v[1] + m[i][2] * v[2])
}

fn mat_t_vec(m: &[[f32; 3]; 3], v: V3) -> V3 {
    std::array::from_fn(|i| m[0][i] * v[0] + m[1][i] * v[1] + m[2][i] * v[2])
}

/// One camera's correction for a step: its given rotation `C`, the correction's rotation
/// and translation, and `dR/dw`.
#[derive(Clone, Copy, Debug)]
pub struct CameraStep {
    c: [[f32; 3]; 3],
    /// The camera's centre (where its world rays start).
    centre: V3,
    r: [[f32; 3]; 3],
    tau: V3,
    jacobian: [[[f32; 3]; 3]; 3],
    frame: Frame,
    /// The space its training rays are marched in.
    space: RaySpace,
}

impl CameraStep {
    /// Camera `pose` (given) with `correction` (6 values) acting in `frame`. Its rays must
    /// start at the camera's centre (every lens here is central).
    pub fn new(pose: &Pose, correction: &[f32], frame: Frame) -> Self {
        let w = [correction[0], correction[1], correction[2]];
        CameraStep {
            frame,
            c: std::array::from_fn(|i| [pose[i][0], pose[i][1], pose[i][2]]),
            centre: [pose[0][3], pose[1][3], pose[2][3]],
            r: rotation(w),
            tau: [correction[3], correction[4], correction[5]],
            jacobian: rotation_jacobian(w),
            space: RaySpace::World,
        }
    }

    /// The same step for rays marched in `space`: NDC rays are corrected in the world,
    /// then warped again.
    pub fn in_space(self, space: RaySpace) -> Self {
        CameraStep { space, ..self }
    }

    /// The corrected form of a drawn training ray: `(origin, dir)` in ray space and
    /// `view`, its direction in the world. Returns the three corrected.
    pub fn correct_drawn(&self, origin: V3, dir: V3, view: V3) -> (V3, V3, V3) {
        match self.space {
            RaySpace::World => {
                let (o, d) = self.correct(origin, dir);
                (o, d, self.correct(o, view).1)
            }
            RaySpace::Ndc(_) => {
                let (o, d) = self.correct(self.centre, view);
                let (o2, d2) = self.space.warp(o, d);
                (o2, d2, d)
            }
        }
    }

    /// Adds to `grad` the gradient of a ray corrected by
    /// [`correct_drawn`](Self::correct_drawn), marched along `dir` (ray space, any length)
    /// with world direction `view` (both as corrected), given `dL/d origin` and
    /// `dL/d unit(dir)` in ray space and `dL/d unit(view)`.
    pub fn accumulate_drawn(
        &self,
        dir: V3,
        view: V3,
        d_o: V3,
        d_dir: V3,
        d_view: V3,
        grad: &mut [f32],
    ) {
        let add = |a: V3, b: V3| -> V3 { std::array::from_fn(|i| a[i] + b[i]) };
        match self.space {
            RaySpace::World => {
                let unit = crate::math::scale(dir, 1.0 / crate::math::length(dir));
                self.accumulate(unit, d_o, add(d_dir, d_view), grad);
            }
            RaySpace::Ndc(_) => {
                let origin = self.correct(self.centre, view).0;
                let (g_o, g_d) = self.space.warp_backward(origin, view, d_o, d_dir);
                // The warp ignores the direction's length: its gradient with respect to
                // the unit direction is |view| times that with respect to `view`.
                let norm = crate::math::length(view);
                let unit = crate::math::scale(view, 1.0 / norm);
                self.accumulate(unit, g_o, add(crate::math::scale(g_d, norm), d_view), grad);
            }
        }
    }

    /// The corrected ray of a given world ray `(o, d)` of this camera.
    pub fn correct(&self, o: V3, d: V3) -> (V3, V3) {
        match self.frame {
            Frame::World => {
                let turned = mat_vec(&self.r, o);
                (
                    std::array::from_fn(|i| turned[i] + self.tau[i]),
                    mat_vec(&self.r, d),
                )
            }
            Frame::Camera => {
                let shift = mat_vec(&self.c, self.tau);
                let v = mat_t_vec(&self.c, d);
                let d2 = mat_vec(&self.c, mat_vec(&self.r, v));
                (std::array::from_fn(|i| o[i] + shift[i]), d2)
            }
        }
    }

    /// Adds to `grad` (6 values) the gradient of a corrected ray with unit direction
    /// `dir` (as marched) given `dL/do` and `dL/d dir`.
    pub fn accumulate(&self, dir: V3, d_o: V3, d_dir: V3, grad: &mut [f32]) {
        // Per frame: the rotation's gradient is sum_ij (dR/dw_k)_ij sum_pairs g_i x_j over
        // (gradient, vector it turned) pairs, and the translation's gradient.
        let (pairs, d_tau) = match self.frame {
            // o' = R o + tau and d' = R u: u the world direction before the turn.
            Frame::World => ([(d_o, self.centre), (d_dir, mat_t_vec(&self.r, dir))], d_o),
            // d' = C R v: v the camera-frame direction before the turn; o' = o + C tau.
            Frame::Camera => {
                let v = mat_t_vec(&self.r, mat_t_vec(&self.c, dir));
                (
                    [([0.0; 3], [0.0; 3]), (mat_t_vec(&self.c, d_dir), v)],
                    mat_t_vec(&self.c, d_o),
                )
            }
        };
        for (k, jk) in self.jacobian.iter().enumerate() {
            let mut s = 0.0;
            for (g, x) in pairs {
                for i in 0..3 {
                    for j in 0..3 {
                        s += jk[i][j] * g[i] * x[j];
                    }
                }
            }
            grad[k] += s;
        }
        for a in 0..3 {
            grad[3 + a] += d_tau[a];
        }
    }
}

/// Corrects each drawn training ray of `rays` by its camera's step (the view a ray's pixel
/// index names; rays of views without a step stay as drawn).
pub fn correct_drawn_rays(rays: &mut crate::stage::RayBatch, cameras: &[CameraStep]) {
    for r in 0..rays.len() {
        if let Some(camera) = cameras.get((rays.pixels[r] >> 32) as usize) {
            (rays.origins[r], rays.dirs[r], rays.view_dirs[r]) =
                camera.correct_drawn(rays.origins[r], rays.dirs[r], rays.view_dirs[r]);
        }
    }
}

/// The corrections of a parameter vector laid out by `layout`, one 6-vector per camera
/// (none when the model refines no camera).
pub fn corrections<'a>(layout: &crate::nn::ParamLayout, params: &'a [f32]) -> Option<&'a [f32]> {
    let t = layout.tensors.iter().find(|t| t.name == TENSOR)?;
    params.get(t.range())
}

/// Where the corrections begin in a parameter vector laid out by `layout` (they come
/// last: everything before them is the field's); `None` when no camera is refined.
pub fn corrections_start(layout: &crate::nn::ParamLayout) -> Option<usize> {
    layout
        .tensors
        .iter()
        .find(|t| t.name == TENSOR)
        .map(|t| t.offset)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    #[test]
    fn the_rotation_log_inverts_the_exponential() {
        let mut rng = Rng::for_stream(3, 0, 0);
        let mut cases: Vec<V3> = vec![
            [0.0; 3],
            [1e-7, 0.0, -2e-7],
            [0.0, 0.0, 3.1],
            [-3.139, 0.01, 0.0],
        ];
        for _ in 0..50 {
            let axis = [
                rng.uniform() - 0.5,
                rng.uniform() - 0.5,
                rng.uniform() - 0.5,
            ];
            let n = crate::math::length(axis).max(1e-6);
            let angle = 3.1 * rng.uniform();
            cases.push(axis.map(|v| v / n * angle));
        }
        for w in cases {
            let back = rotation_log(&rotation(w));
            let (a, b) = (rotation(w), rotation(back));
            for i in 0..3 {
                for j in 0..3 {
                    assert!((a[i][j] - b[i][j]).abs() < 1e-4, "{w:?} -> {back:?}");
                }
            }
            if crate::math::length(w) < 3.0 {
                for k in 0..3 {
                    assert!((w[k] - back[k]).abs() < 1e-4, "{w:?} -> {back:?}");
                }
            }
        }
    }

    #[test]
    fn a_turned_correction_turns_the_corrected_camera() {
        let pose = crate::camera::look_at([1.0, -3.0, 2.0], [0.0; 3], [0.0, 0.0, 1.0]);
        let correction = [0.1, -0.2, 0.05, 0.3, 0.0, -0.1];
        let turn = rotation([0.0, 0.4, -0.3]);
        let pivot = [0.5, -1.0, 0.25];
        for frame in [Frame::World, Frame::Camera] {
            let now = corrected(&pose, &correction, frame);
            let want: Pose = match frame {
                // Turned about the pivot: x -> turn (x - pivot) + pivot.
                Frame::World => std::array::from_fn(|i| {
                    std::array::from_fn(|j| {
                        let turned: f32 = (0..3)
                            .map(|m| turn[i][m] * (now[m][j] - if j == 3 { pivot[m] } else { 0.0 }))
                            .sum();
                        turned + if j == 3 { pivot[i] } else { 0.0 }
                    })
                }),
                Frame::Camera => std::array::from_fn(|i| {
                    std::array::from_fn(|j| match j {
                        3 => now[i][3],
                        _ => (0..3).map(|m| now[i][m] * turn[m][j]).sum(),
                    })
                }),
            };
            let got = corrected(&pose, &turned(&correction, &turn, pivot, frame), frame);
            for i in 0..3 {
                for j in 0..4 {
                    assert!(
                        (got[i][j] - want[i][j]).abs() < 1e-4,
                        "{frame:?}: {got:?} vs {want:?}"
                    );
                }
            }
        }
    }

    #[test]
    fn rotation_is_orthonormal_and_the_jacobian_matches_differences() {
        for w in [[0.0f32, 0.0, 0.0], [0.1, -0.2, 0.05], [1.0, 0.5, -0.7]] {
            let r = rotation(w);
            for i in 0..3 {
                for j in 0..3 {
                    let dot: f32 = (0..3).map(|m| r[m][i] * r[m][j]).sum();
                    assert!((dot - if i == j { 1.0 } else { 0.0 }).abs() < 1e-6);
                }
            }
            let jac = rotation_jacobian(w);
            // At zero, dR/dw_k is the generator [e_k]x.
            if w == [0.0; 3] {
                assert!((jac[2][1][0] - 1.0).abs() < 1e-5 && (jac[2][0][1] + 1.0).abs() < 1e-5);
            }
        }
    }

    /// Asserts that `grad` (6 values) is the gradient of `loss` at `corr`: central
    /// differences with step 1e-3, within `tolerance * (1 + |difference|)`.
    fn check_correction_gradient(
        corr: &[f32],
        grad: &[f32; 6],
        loss: impl Fn(&[f32]) -> f64,
        tolerance: f64,
    ) {
        for k in 0..6 {
            let h = 1e-3;
            let (mut lo, mut hi) = (corr.to_vec(), corr.to_vec());
            lo[k] -= h;
            hi[k] += h;
            let fd = (loss(&hi) - loss(&lo)) / (2.0 * h as f64);
            assert!(
                (fd - grad[k] as f64).abs() < tolerance * (1.0 + fd.abs()),
                "param {k}: {fd} vs {}",
                grad[k]
            );
        }
        assert!(grad.iter().any(|g| g.abs() > 0.1), "{grad:?}");
    }

    /// In either frame, correcting a ray equals casting it from the corrected pose, and
    /// the gradient of a linear function of the corrected ray matches central differences.
    #[test]
    fn corrected_rays_and_their_gradient() {
        let mut rng = Rng::new(3);
        let pose = crate::camera::look_at([1.0, -3.0, 1.5], [0.0; 3], [0.0, 0.0, 1.0]);
        let corr: Vec<f32> = (0..6).map(|_| rng.range(-0.2, 0.2)).collect();
        let v = [0.1f32, -0.2, -1.0];
        let d = mat_vec(
            &std::array::from_fn(|i| [pose[i][0], pose[i][1], pose[i][2]]),
            v,
        );
        let o = [pose[0][3], pose[1][3], pose[2][3]];
        for frame in [Frame::World, Frame::Camera] {
            let step = CameraStep::new(&pose, &corr, frame);
            let (o2, d2) = step.correct(o, d);
            let fixed = corrected(&pose, &corr, frame);
            let want_d: V3 = std::array::from_fn(|i| (0..3).map(|m| fixed[i][m] * v[m]).sum());
            for a in 0..3 {
                assert!(
                    (o2[a] - fixed[a][3]).abs() < 1e-5 && (d2[a] - want_d[a]).abs() < 1e-5,
                    "{frame:?}"
                );
            }
            // L = a . o' + b . unit(d').
            let (a, b) = ([0.3f32, -0.7, 0.2], [0.5f32, 0.4, -0.9]);
            let loss = |c: &[f32]| {
                let (o2, d2) = CameraStep::new(&pose, c, frame).correct(o, d);
                let n = crate::math::length(d2);
                (0..3)
                    .map(|i| (a[i] * o2[i] + b[i] * d2[i] / n) as f64)
                    .sum::<f64>()
            };
            let unit = crate::math::scale(d2, 1.0 / crate::math::length(d2));
            // dL/d unit(d') = b projected off the direction (a unit vector moves
            // tangentially); the rotation keeps the length, so the plain b works as well.
            let mut grad = [0.0f32; 6];
            step.accumulate(unit, a, b, &mut grad);
            check_correction_gradient(&corr, &grad, loss, 2e-3);
        }
        // The two frames differ: the world frame turns the camera about the origin.
        let (world, camera) = (
            corrected(&pose, &corr, Frame::World),
            corrected(&pose, &corr, Frame::Camera),
        );
        assert!(
            (world[0][3] - camera[0][3]).abs() > 0.1,
            "{world:?} {camera:?}"
        );
    }

    /// Forward-facing scenes: a drawn NDC ray is corrected in the world and warped again,
    /// and the gradient of `L = a . o' + b . unit(d') + c . unit(view')` (the NDC ray and
    /// the world view direction) matches central differences in either frame; in world
    /// space `correct_drawn` is `correct`.
    #[test]
    fn drawn_rays_are_corrected_and_differentiated_in_either_space() {
        use crate::camera::ray_space::Ndc;
        let mut rng = Rng::new(5);
        let pose = crate::camera::look_at([0.1, -0.05, 0.0], [0.2, 0.1, -4.0], [0.0, 1.0, 0.0]);
        let corr: Vec<f32> = (0..6).map(|_| rng.range(-0.05, 0.05)).collect();
        let c: [[f32; 3]; 3] = std::array::from_fn(|i| [pose[i][0], pose[i][1], pose[i][2]]);
        // Not of unit length, as drawn rays are not.
        let view = crate::math::scale(mat_vec(&c, [0.1, -0.15, -1.0]), 2.5);
        let centre = [pose[0][3], pose[1][3], pose[2][3]];
        let space = RaySpace::Ndc(Ndc {
            ax: 1.2,
            ay: 1.6,
            near: 1.0,
        });
        let (o_n, d_n) = space.warp(centre, view);
        let (a, b, cv) = (
            [0.3f32, -0.7, 0.2],
            [0.5f32, 0.4, -0.9],
            [-0.2f32, 0.6, 0.3],
        );
        let unit = |x: V3| crate::math::scale(x, 1.0 / crate::math::length(x));
        for frame in [Frame::World, Frame::Camera] {
            let world = CameraStep::new(&pose, &corr, frame);
            let (o, d, v) = world.correct_drawn(centre, view, view);
            let (o2, d2) = world.correct(centre, view);
            assert_eq!((o, d, v), (o2, d2, d2));
            let loss = |corr: &[f32]| -> f64 {
                let step = CameraStep::new(&pose, corr, frame).in_space(space);
                let (o, d, v) = step.correct_drawn(o_n, d_n, view);
                let (d, v) = (unit(d), unit(v));
                (0..3)
                    .map(|i| f64::from(a[i] * o[i] + b[i] * d[i] + cv[i] * v[i]))
                    .sum()
            };
            let step = CameraStep::new(&pose, &corr, frame).in_space(space);
            let (_, d, v) = step.correct_drawn(o_n, d_n, view);
            let mut grad = [0.0f32; 6];
            step.accumulate_drawn(d, v, a, b, cv, &mut grad);
            check_correction_gradient(&corr, &grad, loss, 2e-2);
        }
    }

    #[test]
    fn levels_are_weighted_in_over_the_window() {
        let c = CameraRefinement::new(10);
        assert_eq!(c.level_weights(16, 0.0)[..5], [1.0, 1.0, 1.0, 1.0, 0.0]);
        assert!(c.level_weights(16, 0.4).iter().all(|&w| w == 1.0));
        let mid = c.level_weights(16, 0.2);
        assert!(mid[8] > 0.0 && mid[15] == 0.0, "{mid:?}");
    }
}
