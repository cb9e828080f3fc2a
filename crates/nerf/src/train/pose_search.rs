//! The pose search that brings a stuck camera back: the field is rendered from turns of the
//! camera's pose at a low resolution and compared with its photo ([`Probe`]); a wide sweep
//! of turns up to tens of degrees, about the scene's centre and about the camera's own
//! centre, scored on a coarse probe, its best few rescored on a finer one, then a local
//! search from the best of them.

use std::collections::HashSet;

use rayon::prelude::*;

use crate::camera::{Camera, Pose, Ray};
use crate::data::poses::origin;
use crate::data::Dataset;
use crate::engine::Engine;
use crate::model::camera_refine::{corrected, rotation, turned, Frame, PER_CAMERA};
use crate::stage::{Appearance, RayOutput};
use crate::views::RenderSettings;

/// The probes' longest sides in pixels: the coarse one scores the search's wide sweep
/// (smooth enough that a pose tens of degrees off still sees the way back), the fine one
/// finds stuck cameras and places them to a degree.
const COARSE_SIDE: usize = 12;
const FINE_SIDE: usize = 40;

/// The wide sweep: turns whose rotation vectors lie on a cubic lattice of spacing
/// [`SWEEP_STEP`] degrees within [`SWEEP_MAX`] degrees (even far out, unlike turns by a few
/// angles about a few axes); its [`SWEEP_KEPT`] best go on to the fine probe.
const SWEEP_STEP: f32 = 5.0;
const SWEEP_MAX: f32 = 40.0;
const SWEEP_KEPT: usize = 16;

/// The sweep scores the lattice at twice its spacing first (an eighth of its turns), then
/// the lattice's neighbours of the [`SWEEP_SEEDS`] best of those: on the coarse probe a
/// turn 9 degrees from the true pose still ranks among the best, and the full lattice costs
/// several times more renders.
const SWEEP_SEEDS: usize = 16;

/// The local search after the sweep (degrees): at each angle it moves to the best turn
/// about any of [`AXES`] axes while one is better (at most [`MOVES`] times), then halves
/// the angle.
const DEGREES: [f32; 3] = [4.0, 2.0, 1.0];
const MOVES: usize = 3;

/// Axes of the local search's turns: this many directions spread over the sphere.
const AXES: usize = 26;

/// The training photos at a low resolution, to score poses against the field.
pub struct Probe {
    /// The cameras' intrinsics at the probe's resolution (poses come from the caller).
    cameras: Vec<Camera>,
    /// Packed RGB over [`Probe::BACKGROUND`].
    targets: Vec<Vec<f32>>,
    settings: RenderSettings,
}

impl Probe {
    const BACKGROUND: [f32; 3] = [1.0; 3];

    /// The probe of the first `cameras` views of `data` (a multi-scale split appends its
    /// smaller copies after them) at about `side` pixels on their longest side; `codes`:
    /// whether the model renders each photo's look.
    pub fn new(data: &Dataset, cameras: usize, codes: bool, side: usize) -> Probe {
        let (cams, targets) = data.views[..cameras.min(data.views.len())]
            .iter()
            .map(|v| {
                let longest = v.image.width.max(v.image.height);
                let factor = longest.div_ceil(side.max(1)).max(1);
                let image = v.image.downscale(factor);
                let target = (0..image.width * image.height)
                    .flat_map(|p| image.composite_pixel(p, Probe::BACKGROUND))
                    .collect();
                (v.camera.downscaled(factor), target)
            })
            .unzip();
        let mut settings = RenderSettings::of_dataset(data, Probe::BACKGROUND);
        settings.appearance = if codes {
            Appearance::PerView
        } else {
            Appearance::Mean
        };
        Probe {
            cameras: cams,
            targets,
            settings,
        }
    }

    /// Mean squared error of camera `k`'s photo against the field seen from each of
    /// `poses`, all rendered in one batch.
    pub fn errors(&self, engine: &dyn Engine, k: usize, poses: &[Pose]) -> Vec<f32> {
        let jobs: Vec<(usize, Pose)> = poses.iter().map(|p| (k, *p)).collect();
        self.scored(engine, &jobs)
    }

    /// Mean squared error of every camera's photo against the field seen from its pose in
    /// `poses` (one per camera), all rendered in one batch.
    pub fn each_error(&self, engine: &dyn Engine, poses: &[Pose]) -> Vec<f32> {
        let jobs: Vec<(usize, Pose)> = poses.iter().copied().enumerate().collect();
        self.scored(engine, &jobs)
    }

    /// The error of each `(camera, pose)` job: the photo of that camera against the field
    /// seen from that pose. One batch, so that small probes still fill every core.
    fn scored(&self, engine: &dyn Engine, jobs: &[(usize, Pose)]) -> Vec<f32> {
        if jobs.is_empty() {
            return Vec::new();
        }
        let sizes: Vec<usize> = jobs
            .iter()
            .map(|&(k, _)| self.cameras[k].width * self.cameras[k].height)
            .collect();
        let (world, cones): (Vec<Ray>, Vec<f32>) = jobs
            .par_iter()
            .flat_map_iter(|&(k, pose)| {
                let cam = Camera {
                    c2w: pose,
                    ..self.cameras[k].clone()
                };
                let w = cam.width;
                (0..w * cam.height).map(move |p| {
                    let (x, y) = ((p % w) as f32 + 0.5, (p / w) as f32 + 0.5);
                    (cam.ray_at(x, y), cam.cone_radius(x, y))
                })
            })
            .unzip();
        let mut rays = self.settings.ray_batch_with_cones(&world, &cones, 0);
        // Every ray is its job's photo's (`PerView` reads the view from the pixel id).
        let mut ids = rays.pixels.iter_mut();
        for (&(k, _), &n) in jobs.iter().zip(&sizes) {
            for (p, id) in ids.by_ref().take(n).enumerate() {
                *id = ((k as u64) << 32) | p as u64;
            }
        }
        let mut out = vec![RayOutput::default(); rays.len()];
        engine.render_rays(&rays, &mut out, &|_| {});
        let mut pictures = out.as_slice();
        jobs.iter()
            .zip(&sizes)
            .map(|(&(k, _), &n)| {
                let (picture, rest) = pictures.split_at(n);
                pictures = rest;
                let target = &self.targets[k];
                let sum: f64 = picture
                    .iter()
                    .enumerate()
                    .map(|(p, o)| {
                        (0..3)
                            .map(|c| f64::from(o.rgb[c] - target[3 * p + c]).powi(2))
                            .sum::<f64>()
                    })
                    .sum();
                (sum / (3 * n).max(1) as f64) as f32
            })
            .collect()
    }
}

/// The coarse and the fine probe.
pub struct Probes {
    pub coarse: Probe,
    pub fine: Probe,
}

impl Probes {
    /// The probes of the first `cameras` views of `data` ([`Probe::new`]).
    pub fn new(data: &Dataset, cameras: usize, codes: bool) -> Probes {
        Probes {
            coarse: Probe::new(data, cameras, codes, COARSE_SIDE),
            fine: Probe::new(data, cameras, codes, FINE_SIDE),
        }
    }
}

/// `n` unit vectors spread evenly over the sphere (a Fibonacci lattice).
fn axes(n: usize) -> Vec<[f32; 3]> {
    let golden = std::f32::consts::PI * (3.0 - 5f32.sqrt());
    (0..n)
        .map(|i| {
            let z = 1.0 - 2.0 * (i as f32 + 0.5) / n as f32;
            let r = (1.0 - z * z).max(0.0).sqrt();
            let a = golden * i as f32;
            [r * a.cos(), r * a.sin(), z]
        })
        .collect()
}

/// A turn of the sweep: a point of its lattice (in steps of [`SWEEP_STEP`]) and whether it
/// turns the camera about its own centre rather than the scene's.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
struct LatticeTurn {
    at: [i32; 3],
    own_centre: bool,
}

impl LatticeTurn {
    /// The turn's rotation vector (radians).
    fn vector(&self) -> [f32; 3] {
        self.at.map(|i| i as f32 * SWEEP_STEP.to_radians())
    }
}

/// The lattice's radius in steps.
fn lattice_radius() -> i32 {
    (SWEEP_MAX / SWEEP_STEP).floor() as i32
}

/// Whether lattice point `at` is a turn of the sweep: not the identity, within
/// [`SWEEP_MAX`].
fn in_sweep(at: [i32; 3]) -> bool {
    let n = lattice_radius();
    let squared: i32 = at.iter().map(|v| v * v).sum();
    squared > 0 && squared <= n * n
}

/// Every lattice point of the sweep whose coordinates are multiples of `spacing` steps.
fn lattice(spacing: i32) -> Vec<[i32; 3]> {
    let n = lattice_radius() / spacing * spacing;
    let range = || (-n..=n).step_by(spacing as usize);
    range()
        .flat_map(|i| range().flat_map(move |j| range().map(move |k| [i, j, k])))
        .filter(|&at| in_sweep(at))
        .collect()
}

/// The sweep: every turn scored by `score` (lower is better) with the pivots in
/// `own_centres`, the lattice at twice its spacing first, then the unscored neighbours of
/// its [`SWEEP_SEEDS`] best and of the identity. Returns every scored turn with its score.
fn sweep(
    own_centres: &[bool],
    score: &mut dyn FnMut(&[LatticeTurn]) -> Vec<f32>,
) -> Vec<(LatticeTurn, f32)> {
    let first: Vec<LatticeTurn> = lattice(2)
        .into_iter()
        .flat_map(|at| {
            own_centres
                .iter()
                .map(move |&own_centre| LatticeTurn { at, own_centre })
        })
        .collect();
    let mut scored: Vec<(LatticeTurn, f32)> = first.iter().copied().zip(score(&first)).collect();
    let mut seen: HashSet<LatticeTurn> = first.into_iter().collect();
    let mut order: Vec<usize> = (0..scored.len()).collect();
    order.sort_by(|&a, &b| scored[a].1.total_cmp(&scored[b].1));
    // The pose as it is (the identity, which the sweep does not score) seeds the second
    // pass too: the turns next to it are the lattice's nearest, and the twice-spaced
    // lattice leaves the identity's neighbours unscored.
    let here = own_centres.iter().map(|&own_centre| LatticeTurn {
        at: [0; 3],
        own_centre,
    });
    let seeds: Vec<LatticeTurn> = order
        .iter()
        .take(SWEEP_SEEDS)
        .map(|&i| scored[i].0)
        .chain(here)
        .collect();
    let mut second = Vec::new();
    for seed in seeds {
        for d in lattice_neighbours() {
            let at = std::array::from_fn(|a| seed.at[a] + d[a]);
            let turn = LatticeTurn { at, ..seed };
            if in_sweep(at) && seen.insert(turn) {
                second.push(turn);
            }
        }
    }
    scored.extend(second.iter().copied().zip(score(&second)));
    scored
}

/// The 26 offsets to a lattice point's neighbours (sides, edges and corners).
fn lattice_neighbours() -> impl Iterator<Item = [i32; 3]> {
    (-1..=1)
        .flat_map(|i| (-1..=1).flat_map(move |j| (-1..=1).map(move |k| [i, j, k])))
        .filter(|d| *d != [0, 0, 0])
}

/// The correction that leaves the camera turned by `w` (a rotation vector) beyond
/// `correction`: about the world's origin (the scene's centre) or, in the world frame,
/// about the camera's own centre `centre`.
fn turned_by(
    correction: &[f32],
    w: [f32; 3],
    own_centre: bool,
    centre: [f32; 3],
    frame: Frame,
) -> [f32; PER_CAMERA] {
    let pivot = if own_centre { centre } else { [0.0; 3] };
    turned(correction, &rotation(w), pivot, frame)
}

/// The pivots a frame's search turns about: in the world frame the scene's centre and the
/// camera's own; in the camera frame a turn is about the camera's centre already.
fn own_centres(frame: Frame) -> &'static [bool] {
    match frame {
        Frame::World => &[false, true],
        Frame::Camera => &[false],
    }
}

/// The corrections the local search tries around `correction`: turns by `degrees` about
/// each of [`AXES`] axes, about each pivot of the frame.
fn local_candidates(
    correction: &[f32],
    start: &Pose,
    frame: Frame,
    degrees: f32,
) -> Vec<[f32; PER_CAMERA]> {
    let centre = origin(&corrected(start, correction, frame));
    axes(AXES)
        .into_iter()
        .flat_map(|a| {
            let w = a.map(|v| v * degrees.to_radians());
            own_centres(frame)
                .iter()
                .map(move |&own| turned_by(correction, w, own, centre, frame))
        })
        .collect()
}

/// The best correction for camera `k` found from `now` (its error on the fine probe and
/// its correction): a wide sweep on the coarse probe, its best few scored on the fine one,
/// then, from the best of them if it beats `now`, a local search there.
pub fn search(
    engine: &dyn Engine,
    probes: &Probes,
    k: usize,
    start: &Pose,
    frame: Frame,
    now: (f32, [f32; PER_CAMERA]),
) -> (f32, [f32; PER_CAMERA]) {
    let posed = |tried: &[[f32; PER_CAMERA]]| -> Vec<Pose> {
        tried.iter().map(|c| corrected(start, c, frame)).collect()
    };
    let centre = origin(&corrected(start, &now.1, frame));
    let correction_of =
        |t: &LatticeTurn| turned_by(&now.1, t.vector(), t.own_centre, centre, frame);
    let mut swept = sweep(own_centres(frame), &mut |turns| {
        let tried: Vec<_> = turns.iter().map(correction_of).collect();
        probes.coarse.errors(engine, k, &posed(&tried))
    });
    swept.sort_by(|a, b| a.1.total_cmp(&b.1));
    let kept: Vec<[f32; PER_CAMERA]> = swept
        .iter()
        .take(SWEEP_KEPT)
        .map(|(t, _)| correction_of(t))
        .collect();
    let fine = probes.fine.errors(engine, k, &posed(&kept));
    let mut best = now;
    for (e, c) in fine.into_iter().zip(kept) {
        if e < best.0 {
            best = (e, c);
        }
    }
    // Nothing far off explains the photo better: close by is the gradient's work.
    if best.0 >= now.0 {
        return now;
    }
    for degrees in DEGREES {
        for _ in 0..MOVES {
            let tried = local_candidates(&best.1, start, frame, degrees);
            let scores = probes.fine.errors(engine, k, &posed(&tried));
            match scores.iter().enumerate().min_by(|a, b| a.1.total_cmp(b.1)) {
                Some((i, &e)) if e < best.0 => best = (e, tried[i]),
                _ => break,
            }
        }
    }
    best
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_sweep_fills_a_ball_of_turns() {
        let turns: Vec<[f32; 3]> = lattice(1)
            .into_iter()
            .map(|at| {
                LatticeTurn {
                    at,
                    own_centre: false,
                }
                .vector()
            })
            .collect();
        let max = SWEEP_MAX.to_radians() + 1e-6;
        assert!(turns.iter().all(|w| crate::math::length(*w) <= max));
        assert!(turns.iter().all(|w| crate::math::length(*w) > 0.0));
        // Any turn within the ball is within half a lattice diagonal of a lattice turn.
        let reach = 0.5 * 3f32.sqrt() * SWEEP_STEP.to_radians() + 1e-6;
        for a in axes(200) {
            let w = a.map(|v| v * 0.9 * max);
            let nearest = turns
                .iter()
                .map(|t| crate::math::length(crate::math::sub(*t, w)))
                .fold(f32::INFINITY, f32::min);
            assert!(nearest <= reach, "{w:?}: {nearest}");
        }
    }

    /// A score with its best at rotation vector `target` about the camera's own centre, a
    /// second, shallower dip far from it about the scene's, and ripples over both.
    fn bumpy(target: [f32; 3]) -> impl Fn(&LatticeTurn) -> f32 {
        let decoy = target.map(|v| -0.6 * v);
        move |t: &LatticeTurn| {
            let w = t.vector();
            let to = |p: [f32; 3]| crate::math::length(crate::math::sub(w, p));
            let ripple = 0.02 * (7.0 * w[0]).sin() * (5.0 * w[1]).cos();
            let main = if t.own_centre {
                to(target)
            } else {
                0.1 + to(target)
            };
            let second = if t.own_centre {
                0.3 + to(decoy)
            } else {
                0.05 + to(decoy)
            };
            main.min(second) + ripple
        }
    }

    #[test]
    fn the_two_pass_sweep_finds_the_full_lattices_best_at_a_fraction_of_its_renders() {
        let both = own_centres(Frame::World);
        let full: Vec<LatticeTurn> = lattice(1)
            .into_iter()
            .flat_map(|at| {
                both.iter()
                    .map(move |&own_centre| LatticeTurn { at, own_centre })
            })
            .collect();
        for target_deg in [
            [0.0, 0.0, 23.3],
            [12.0, -17.0, 4.0],
            [-31.0, 9.5, -14.0],
            [2.0, 3.0, -1.5],
        ] {
            let score = bumpy(target_deg.map(f32::to_radians));
            let best_of = |scored: &[(LatticeTurn, f32)]| {
                scored
                    .iter()
                    .min_by(|a, b| a.1.total_cmp(&b.1))
                    .map(|s| s.0)
            };
            let plain: Vec<(LatticeTurn, f32)> = full.iter().map(|t| (*t, score(t))).collect();
            let mut renders = 0;
            let two_pass = sweep(both, &mut |turns| {
                renders += turns.len();
                turns.iter().map(&score).collect()
            });
            assert_eq!(best_of(&two_pass), best_of(&plain), "{target_deg:?}");
            assert_eq!(renders, two_pass.len(), "each turn scored once");
            assert!(
                renders * 5 < full.len(),
                "{renders} renders of {} turns",
                full.len()
            );
        }
    }

    #[test]
    fn the_search_axes_cover_the_sphere() {
        let a = axes(AXES);
        for v in &a {
            assert!((crate::math::length(*v) - 1.0).abs() < 1e-5);
        }
        // Every direction is within 40 degrees of an axis.
        for probe in axes(500) {
            let nearest = a
                .iter()
                .map(|v| crate::math::dot(*v, probe).clamp(-1.0, 1.0))
                .fold(-1.0f32, f32::max)
                .acos()
                .to_degrees();
            assert!(nearest < 40.0, "{probe:?}: {nearest}");
        }
    }
}
