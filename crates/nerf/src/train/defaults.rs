//! A run's defaults: the one function that turns what a scene is, the engine the run will
//! be on and the user's flags into the fast model's quality features. `nerf train`, the
//! demo and `nerf bench` all take their features from [`fast_defaults`] and write them
//! into the model with [`Defaults::apply_to`].
//!
//! The rules, in order (each feature as the user asked when they asked; otherwise):
//! 1. anti-aliasing: on, but for forward-facing (NDC) scenes, where it measured worse on
//!    the built-in rug;
//! 2. per-photo appearance codes and camera refinement, together: on for real captures (a
//!    scene not rendered in Blender, seen in world space, trained at one scale), whose
//!    poses come from structure from motion and whose photos drift in exposure; off for
//!    Blender scenes (exact poses, one look). Refinement alone would let the poses absorb
//!    exposure changes, so a default turns on both or neither;
//! 3. the distortion loss: on for forward-facing scenes, which grow fog in front of what
//!    they see ([`FORWARD_FACING_DISTORTION`]);
//! 4. few-view training: on for runs on at most `model::few_view::FEW_VIEWS` photos of a
//!    scene it applies to (bounded, in world space: `model::few_view::applies`);
//! 5. RegNeRF's depth smoothness: on for forward-facing runs on at most `FEW_VIEWS`
//!    photos ([`FEW_VIEW_DEPTH_SMOOTHNESS`]), where few-view training's visibility rule
//!    does not apply and depth from between the cameras is what few photos get wrong;
//! 6. a field of space and time: on for moving scenes (every photo has a time), which then
//!    get no appearance codes or camera refinement by default (on a moving subject they
//!    would absorb the motion). A still field would average the motion into a blur, so
//!    with `--device auto` a moving scene trains where this field runs. Its grid is
//!    `SpaceTimeConfig::default()` (4 to 64 cells along time) with no prior of smoothness
//!    in time unless asked (`--time-cells`, `--time-smoothness`): a cell per moment with
//!    the prior gains early on a fast motion but measured level on it from 10 minutes on
//!    and worse on a slow one;
//! 7. the networks' products in bfloat16 (`f32` sums): on where the CPU engine runs on a
//!    CPU with AVX-512 BF16, where they train at the same PSNR in less time.
//!
//! A default turns a feature on only where the run's engine runs it (`engine::caps`), and
//! says so when it leaves one off for that reason. With `--device auto` on a machine with a
//! GPU, a run that asks for a feature only the CPU engine runs goes to the CPU, and says so.

use crate::camera::ray_space::RaySpace;
use crate::camera::Camera;
use crate::encoding::space_time_grid::SpaceTimeConfig;
use crate::engine::caps::{EngineKind, Feature};
use crate::engine::Device;
use crate::model::fast::FastModelConfig;

/// The depth smoothness weight of forward-facing runs on few photos: the best of the
/// weights measured on 8-view lego and chair, where it gained little; on the
/// forward-facing rug from 3 photos it gained 2.4 dB (figures in `docs/benchmarks.md`).
pub const FEW_VIEW_DEPTH_SMOOTHNESS: f32 = 0.1;

/// The fast model's samples per step in a run scheduled by the clock (`--minutes` alone):
/// twice the default, since a step's fixed costs (Adam, the gradients' reduction, the
/// occupancy refresh) then spread over twice the samples: lego_400 in 10 minutes took 25%
/// more samples and reached 33.24 dB against 32.86 with 65,536 (figures in
/// `docs/benchmarks.md`). A run of a fixed number of steps keeps the default, which
/// would take twice the time.
pub const TIMED_SAMPLES_PER_STEP: usize = 1 << 17;

/// The fast model's samples per step in a run scheduled by the clock, given the run's
/// `untimed` samples per step: [`TIMED_SAMPLES_PER_STEP`], but a field of space and time
/// keeps `untimed`. Such a field learns each moment from the few photos near it in time,
/// and half the steps cost it more than the larger steps gain (jumpingjacks in 10
/// minutes; figures in `docs/benchmarks.md`).
pub fn timed_samples_per_step(dynamic: bool, untimed: usize) -> usize {
    match dynamic {
        true => untimed,
        false => TIMED_SAMPLES_PER_STEP,
    }
}

/// Appearance codes per photo when real captures get them by default.
pub const DEFAULT_APPEARANCE_DIMS: u32 = 16;

/// The distortion weight of forward-facing (NDC) scenes: the weight where rendering got
/// several times faster for a small loss of PSNR; five times it bought a little more speed
/// for about twice the loss (figures in `docs/benchmarks.md`).
pub const FORWARD_FACING_DISTORTION: f32 = 1e-4;

/// What the user said about one feature: nothing, on (with its setting), or off.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub enum Choice<T = ()> {
    #[default]
    Default,
    On(T),
    Off,
}

impl Choice {
    /// From a pair of flags (`--x`, `--no-x`; clap keeps them apart).
    pub fn from_flags(on: bool, off: bool) -> Choice {
        match (on, off) {
            (true, _) => Choice::On(()),
            (_, true) => Choice::Off,
            _ => Choice::Default,
        }
    }
}

impl<T> Choice<T> {
    /// From a flag with a value and its `--no-x` (clap keeps them apart).
    pub fn from_value(value: Option<T>, off: bool) -> Choice<T> {
        match (value, off) {
            (Some(v), _) => Choice::On(v),
            (None, true) => Choice::Off,
            (None, false) => Choice::Default,
        }
    }

    fn asked(&self) -> bool {
        matches!(self, Choice::On(_))
    }
}

impl Choice<f32> {
    /// A loss's weight: the one asked for, none when turned off, else `default` where
    /// `on_by_default` says so and none where not.
    fn weight(self, default: f32, on_by_default: impl FnOnce() -> bool) -> f32 {
        match self {
            Choice::On(w) => w,
            Choice::Off => 0.0,
            Choice::Default if on_by_default() => default,
            Choice::Default => 0.0,
        }
    }
}

/// The user's flags for the features that have defaults.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Flags {
    pub antialias: Choice,
    /// With the code's length.
    pub appearance: Choice<u32>,
    pub refine_cameras: Choice,
    /// With the loss's weight.
    pub distortion: Choice<f32>,
    pub few_view: Choice,
    pub dynamic: Choice,
    /// With the loss's weight.
    pub depth_smoothness: Choice<f32>,
    /// With the prior's weight (a field of space and time only).
    pub time_smoothness: Choice<f32>,
    /// The finest level's cells along time (a field of space and time only).
    pub time_cells: Option<usize>,
    pub bf16: Choice,
}

/// What a scene is, as far as the defaults care.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SceneFacts {
    /// Rendered in Blender (exact poses, one look), the built-in scenes included.
    pub blender: bool,
    pub space: RaySpace,
    /// Scales each photo is trained at (`--multiscale`).
    pub multiscale: usize,
    /// Space beyond the box is contracted into it (unbounded captures).
    pub contract: bool,
    /// The photos the run trains on.
    pub train_views: usize,
    /// The distinct moments the training photos show: 0 for a still scene (no times).
    pub moments: usize,
}

impl SceneFacts {
    /// The photos show moments of a moving scene (each has a time).
    pub fn dynamic(&self) -> bool {
        self.moments > 0
    }

    /// Forward-facing: marched in NDC.
    pub fn forward_facing(&self) -> bool {
        self.space != RaySpace::World
    }

    /// A real capture that learns per-photo corrections by default (a still one: on a
    /// moving subject the corrections would absorb the motion).
    pub fn real_capture(&self) -> bool {
        !self.blender && !self.forward_facing() && self.multiscale == 1 && !self.dynamic()
    }
}

/// The features a run gets.
#[derive(Clone, Debug, PartialEq)]
pub struct Defaults {
    pub antialias: bool,
    /// The appearance code's length, when there are codes.
    pub appearance: Option<u32>,
    pub refine_cameras: bool,
    /// Whether refinement was asked for (else it is a real capture's default).
    pub refine_asked: bool,
    pub distortion: f32,
    pub few_view: bool,
    /// RegNeRF's depth smoothness weight (0: off).
    pub depth_smoothness: f32,
    /// A field of space and time: its grid.
    pub motion: Option<SpaceTimeConfig>,
    /// The weight of its prior of smoothness in time (0: off, as for a still field).
    pub time_smoothness: f32,
    /// The networks' products in bfloat16.
    pub bf16_products: bool,
    /// What the user should hear: each default that turned a feature on or left one off.
    pub notes: Vec<String>,
}

impl Defaults {
    /// A field of space and time.
    pub fn dynamic(&self) -> bool {
        self.motion.is_some()
    }

    /// Writes the features into `model`, whose bound must already be the scene's (the
    /// anti-aliasing footprints are measured against it). `cameras` are the training
    /// photos' cameras in `space` (anti-aliasing's typical footprint; the first one's
    /// width spaces depth smoothness's patches) and `photos` how many of them the run
    /// trains on. Camera refinement is left to the caller: its rates follow flags that
    /// are not defaults.
    pub fn apply_to(
        &self,
        model: &mut FastModelConfig,
        cameras: &[Camera],
        space: &RaySpace,
        photos: usize,
    ) {
        if self.antialias {
            model.antialias_for(cameras, space);
        }
        model.distortion = self.distortion;
        model.bf16_products = self.bf16_products;
        model.field.motion = self.motion;
        model.time_smoothness = self.time_smoothness;
        if self.few_view {
            model.train_from_few_views(photos);
        }
        if self.depth_smoothness > 0.0 {
            use crate::model::unseen_patches::{stride_for, DepthSmoothness, PATCHES};
            let width = cameras.first().map_or(0, |c| c.width);
            model.depth_smoothness = Some(DepthSmoothness {
                weight: self.depth_smoothness,
                patches: PATCHES,
                stride: stride_for(width),
            });
        }
        if let Some(dims) = self.appearance {
            model.field.appearance_dims = dims as usize;
            model.field.appearance_images = photos;
        }
    }
}

/// The engine a run of `scene` on `device` will be on: the CPU for `cpu` and for `auto`
/// without a hardware GPU (`has_gpu`); with one, `auto` takes the GPU unless `flags` ask
/// for a feature only the CPU engine runs (or the scene moves and its field is one), which
/// is said.
pub fn engine_for(
    device: Device,
    has_gpu: bool,
    scene: &SceneFacts,
    flags: &Flags,
) -> (EngineKind, Option<String>) {
    match device {
        Device::Cpu => (EngineKind::Cpu, None),
        Device::Wgpu | Device::Cuda => (EngineKind::Gpu, None),
        Device::Auto if !has_gpu => (EngineKind::Cpu, None),
        Device::Auto => {
            let asked = [
                (flags.antialias.asked(), Feature::Antialias),
                (flags.appearance.asked(), Feature::Appearance),
                (flags.refine_cameras.asked(), Feature::CameraRefinement),
                (flags.distortion.asked(), Feature::Distortion),
                (flags.few_view.asked(), Feature::FewView),
                (flags.depth_smoothness.asked(), Feature::DepthSmoothness),
                (flags.bf16.asked(), Feature::Bf16Products),
                (
                    flags.dynamic.asked() || (scene.dynamic() && flags.dynamic == Choice::Default),
                    Feature::Dynamic,
                ),
            ];
            let cpu_only: Vec<Feature> = asked
                .into_iter()
                .filter(|&(on, f)| on && !EngineKind::Gpu.runs(f))
                .map(|(_, f)| f)
                .collect();
            if cpu_only.is_empty() {
                (EngineKind::Gpu, None)
            } else {
                let note = format!(
                    "note: training on the CPU: {} {} on the GPU engine yet",
                    crate::engine::caps::list(&cpu_only),
                    if cpu_only.len() == 1 {
                        "does not run"
                    } else {
                        "do not run"
                    }
                );
                (EngineKind::Cpu, Some(note))
            }
        }
    }
}

/// The features of a run of `scene` on `device` as `flags` ask: [`engine_for`] (probing
/// the adapters only for `auto`) and then [`fast_defaults`], the engine's note first.
pub fn decide(device: Device, scene: &SceneFacts, flags: &Flags) -> Defaults {
    let has_gpu = device == Device::Auto && crate::engine::hardware_gpu_present();
    let (engine, note) = engine_for(device, has_gpu, scene, flags);
    let mut d = fast_defaults(scene, engine, flags);
    d.notes.splice(0..0, note);
    d
}

/// The fast model's features for a run of `scene` on `engine`, as `flags` ask and the
/// rules in this module's docs give.
pub fn fast_defaults(scene: &SceneFacts, engine: EngineKind, flags: &Flags) -> Defaults {
    let mut notes = Vec::new();
    // Codes and refinement: both or neither by default, so both where the engine runs
    // both, and a note naming what it lacks where it does not.
    let corrections = [Feature::Appearance, Feature::CameraRefinement];
    let lacking: Vec<Feature> = corrections
        .into_iter()
        .filter(|&f| !engine.runs(f))
        .collect();
    let corrections_on = scene.real_capture() && lacking.is_empty();
    let asked_either =
        flags.appearance != Choice::Default || flags.refine_cameras != Choice::Default;
    if scene.real_capture() && !lacking.is_empty() && !asked_either {
        notes.push(format!(
            "note: per-photo appearance codes and camera refinement (the default for real \
             captures) are off: {} does not run {} yet (--device cpu does)",
            engine.name(),
            crate::engine::caps::list(&lacking)
        ));
    }
    let mut by_default = |feature: Feature, wanted: bool, on_note: &str| -> bool {
        if !wanted {
            return false;
        }
        if engine.runs(feature) {
            if !on_note.is_empty() {
                notes.push(format!("note: {on_note}"));
            }
            true
        } else {
            notes.push(format!(
                "note: {} is off: {} does not run it yet (--device cpu does)",
                feature.describe(),
                engine.name()
            ));
            false
        }
    };

    let antialias = match flags.antialias {
        Choice::On(()) => true,
        Choice::Off => false,
        Choice::Default => by_default(Feature::Antialias, !scene.forward_facing(), ""),
    };

    let appearance = match flags.appearance {
        Choice::On(dims) => Some(dims),
        Choice::Off => None,
        Choice::Default => by_default(
            Feature::Appearance,
            corrections_on,
            "learning a look per photo (the default for real captures; --no-appearance \
             turns it off)",
        )
        .then_some(DEFAULT_APPEARANCE_DIMS),
    };
    let refine_cameras = match flags.refine_cameras {
        Choice::On(()) => true,
        Choice::Off => false,
        Choice::Default => by_default(Feature::CameraRefinement, corrections_on, ""),
    };

    let distortion = flags.distortion.weight(FORWARD_FACING_DISTORTION, || {
        by_default(
            Feature::Distortion,
            scene.forward_facing(),
            &format!(
                "distortion loss {FORWARD_FACING_DISTORTION} against fog (the default for \
                 forward-facing scenes: views render 2-5x faster; --no-distortion turns it off)"
            ),
        )
    });

    let few = scene.train_views <= crate::model::few_view::FEW_VIEWS
        && crate::model::few_view::applies(scene.space, scene.contract);
    let few_view = match flags.few_view {
        Choice::On(()) => true,
        Choice::Off => false,
        Choice::Default => by_default(
            Feature::FewView,
            few,
            &format!(
                "few-view training: the space fewer than half of the {} training photos see, \
                 and the space the scene hides from all of them, is kept empty, colour \
                 varies with the view at degree 1 only and the hash tables' entries decay \
                 towards zero (the default for runs on at most {} \
                 photos; --no-few-view turns it off)",
                scene.train_views,
                crate::model::few_view::FEW_VIEWS
            ),
        ),
    };

    let depth_smoothness = flags
        .depth_smoothness
        .weight(FEW_VIEW_DEPTH_SMOOTHNESS, || {
            by_default(
                Feature::DepthSmoothness,
                scene.forward_facing() && scene.train_views <= crate::model::few_view::FEW_VIEWS,
                &format!(
                    "depth smoothness {FEW_VIEW_DEPTH_SMOOTHNESS} on patches from poses between \
                 the {} training photos (the default for forward-facing runs on at most {} \
                 photos; --no-depth-smoothness turns it off)",
                    scene.train_views,
                    crate::model::few_view::FEW_VIEWS
                ),
            )
        });

    // Off unless asked: the prior measured no better in long runs on the default grid.
    let time_weight = match flags.time_smoothness {
        Choice::On(w) => w,
        Choice::Off | Choice::Default => 0.0,
    };
    let motion_grid = flags
        .time_cells
        .map_or_else(SpaceTimeConfig::default, SpaceTimeConfig::with_time_cells);
    let dynamic = match flags.dynamic {
        Choice::On(()) => true,
        Choice::Off => false,
        Choice::Default => {
            let prior = if time_weight == 0.0 {
                "no prior of smoothness in time".to_string()
            } else {
                format!("smooth in time (weight {time_weight})")
            };
            by_default(
                Feature::Dynamic,
                scene.dynamic(),
                &format!(
                    "the photos show a moving scene ({} moments): training a field of space \
                     and time (the default when every photo has a time; --no-dynamic trains a \
                     still one), {} cells along time at its finest, {prior}",
                    scene.moments, motion_grid.max_time_resolution
                ),
            )
        }
    };
    let motion = dynamic.then_some(motion_grid);
    let time_smoothness = if dynamic { time_weight } else { 0.0 };

    // A speed setting, not a look: on wherever it runs, off without a word elsewhere.
    let bf16_products = match flags.bf16 {
        Choice::On(()) => true,
        Choice::Off => false,
        Choice::Default => {
            engine.runs(Feature::Bf16Products) && crate::nn::linalg::Precision::bf16().is_some()
        }
    };

    Defaults {
        antialias,
        appearance,
        refine_cameras,
        refine_asked: flags.refine_cameras.asked(),
        distortion,
        few_view,
        depth_smoothness,
        motion,
        time_smoothness,
        bf16_products,
        notes,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn facts(blender: bool, space: RaySpace) -> SceneFacts {
        SceneFacts {
            blender,
            space,
            multiscale: 1,
            contract: false,
            train_views: 100,
            moments: 0,
        }
    }

    /// Every default overridden: each feature asked on, but anti-aliasing (on by default) off.
    fn every_default_overridden() -> Flags {
        Flags {
            antialias: Choice::Off,
            appearance: Choice::On(8),
            refine_cameras: Choice::On(()),
            distortion: Choice::On(0.01),
            few_view: Choice::On(()),
            dynamic: Choice::On(()),
            depth_smoothness: Choice::On(0.1),
            time_smoothness: Choice::On(0.02),
            time_cells: Some(50),
            bf16: Choice::On(()),
        }
    }

    const CPU: EngineKind = EngineKind::Cpu;
    const NDC: RaySpace = RaySpace::Ndc(crate::camera::ray_space::Ndc {
        ax: 1.5,
        ay: 2.0,
        near: 1.0,
    });

    #[test]
    fn blender_scenes_anti_alias_and_nothing_else() {
        let d = fast_defaults(&facts(true, RaySpace::World), CPU, &Flags::default());
        assert!(d.antialias);
        assert_eq!(
            (d.appearance, d.refine_cameras, d.distortion),
            (None, false, 0.0)
        );
        assert!(d.notes.is_empty(), "{:?}", d.notes);
    }

    #[test]
    fn real_captures_learn_a_look_and_a_pose_per_photo() {
        let d = fast_defaults(&facts(false, RaySpace::World), CPU, &Flags::default());
        assert!(d.antialias && d.refine_cameras && !d.refine_asked);
        assert_eq!(d.appearance, Some(DEFAULT_APPEARANCE_DIMS));
        assert_eq!(d.distortion, 0.0);
        assert!(d.notes.iter().any(|n| n.contains("a look per photo")));
        // At several scales a photo would get a code and a pose per scale: neither.
        let multiscale = SceneFacts {
            multiscale: 2,
            ..facts(false, RaySpace::World)
        };
        let d = fast_defaults(&multiscale, CPU, &Flags::default());
        assert_eq!((d.appearance, d.refine_cameras), (None, false));
    }

    #[test]
    fn forward_facing_scenes_get_the_distortion_loss_and_no_anti_aliasing() {
        let d = fast_defaults(&facts(false, NDC), CPU, &Flags::default());
        assert!(!d.antialias);
        assert_eq!(d.distortion, FORWARD_FACING_DISTORTION);
        assert_eq!((d.appearance, d.refine_cameras), (None, false));
        assert!(d.notes.iter().any(|n| n.contains("distortion loss")));
    }

    #[test]
    fn runs_on_few_photos_keep_the_space_few_photos_see_empty() {
        for (views, on) in [(3, true), (16, true), (17, false), (100, false)] {
            let scene = SceneFacts {
                train_views: views,
                ..facts(true, RaySpace::World)
            };
            let d = fast_defaults(&scene, CPU, &Flags::default());
            assert_eq!(d.few_view, on, "{views} views");
            assert_eq!(d.notes.iter().any(|n| n.contains("few-view")), on);
        }
        // Not where it cannot act: forward-facing (NDC) and contracted captures.
        for scene in [
            SceneFacts {
                train_views: 3,
                ..facts(false, NDC)
            },
            SceneFacts {
                train_views: 3,
                contract: true,
                ..facts(false, RaySpace::World)
            },
        ] {
            let d = fast_defaults(&scene, CPU, &Flags::default());
            assert!(!d.few_view && !d.notes.iter().any(|n| n.contains("few-view")));
        }
    }

    #[test]
    fn forward_facing_runs_on_few_photos_smooth_depth_from_unseen_poses() {
        for (views, space, on) in [
            (3, NDC, true),
            (16, NDC, true),
            (17, NDC, false),
            (3, RaySpace::World, false),
        ] {
            let scene = SceneFacts {
                train_views: views,
                ..facts(false, space)
            };
            let d = fast_defaults(&scene, CPU, &Flags::default());
            let weight = if on { FEW_VIEW_DEPTH_SMOOTHNESS } else { 0.0 };
            assert_eq!(d.depth_smoothness, weight, "{views} views in {space:?}");
            assert_eq!(d.notes.iter().any(|n| n.contains("depth smoothness")), on);
        }
        let few = SceneFacts {
            train_views: 3,
            ..facts(false, NDC)
        };
        // Where the GPU engine runs it, the same default there; where not, off and said.
        let d = fast_defaults(&few, EngineKind::Gpu, &Flags::default());
        if EngineKind::Gpu.runs(Feature::DepthSmoothness) {
            assert_eq!(d.depth_smoothness, FEW_VIEW_DEPTH_SMOOTHNESS);
        } else {
            assert_eq!(d.depth_smoothness, 0.0);
            assert!(d.notes.iter().any(|n| n.contains("--depth-smoothness")));
        }
        let off = Flags {
            depth_smoothness: Choice::Off,
            ..Flags::default()
        };
        assert_eq!(fast_defaults(&few, CPU, &off).depth_smoothness, 0.0);
    }

    #[test]
    fn moving_scenes_get_a_field_of_space_and_time_and_no_corrections() {
        let capture = SceneFacts {
            moments: 50,
            ..facts(false, RaySpace::World)
        };
        let d = fast_defaults(&capture, CPU, &Flags::default());
        assert!(d.dynamic() && !d.refine_cameras && d.appearance.is_none());
        assert!(d.notes.iter().any(|n| n.contains("space and time")));
        // The default grid, no prior, and the note says both.
        assert_eq!(d.motion, Some(SpaceTimeConfig::default()));
        assert_eq!(d.time_smoothness, 0.0);
        let note = d.notes.iter().find(|n| n.contains("50 moments"));
        let note = note.expect("the moving scene's note");
        assert!(note.contains("64 cells along time") && note.contains("no prior"));
        // A cell per moment with the prior, when asked, said in the note.
        let per_moment = Flags {
            time_cells: Some(50),
            time_smoothness: Choice::On(0.4),
            ..Flags::default()
        };
        let d = fast_defaults(&capture, CPU, &per_moment);
        assert_eq!(d.motion, Some(SpaceTimeConfig::with_time_cells(50)));
        assert_eq!(d.time_smoothness, 0.4);
        assert!(d.notes.iter().any(
            |n| n.contains("50 cells along time") && n.contains("smooth in time (weight 0.4)")
        ));
        let unsmoothed = Flags {
            time_smoothness: Choice::Off,
            ..Flags::default()
        };
        let d = fast_defaults(&capture, CPU, &unsmoothed);
        assert!(d.dynamic() && d.time_smoothness == 0.0);
        let still_field = Flags {
            dynamic: Choice::Off,
            ..Flags::default()
        };
        let d = fast_defaults(&capture, CPU, &still_field);
        assert!(d.motion.is_none() && d.time_smoothness == 0.0);
        let d = fast_defaults(&facts(true, RaySpace::World), CPU, &Flags::default());
        assert!(!d.dynamic());
        // Where the engine lacks it, it is off and said.
        if !EngineKind::Gpu.runs(Feature::Dynamic) {
            let d = fast_defaults(&capture, EngineKind::Gpu, &Flags::default());
            assert!(!d.dynamic());
            assert!(d.notes.iter().any(|n| n.contains("--no-dynamic")));
        }
    }

    #[test]
    fn flags_win_over_every_rule() {
        let flags = every_default_overridden();
        let d = fast_defaults(&facts(true, RaySpace::World), CPU, &flags);
        assert!(d.dynamic() && d.bf16_products);
        assert_eq!((d.depth_smoothness, d.time_smoothness), (0.1, 0.02));
        assert_eq!(d.motion.map(|m| m.max_time_resolution), Some(50));
        assert!(!d.antialias && d.refine_cameras && d.refine_asked && d.few_view);
        assert_eq!((d.appearance, d.distortion), (Some(8), 0.01));
        let off = Flags {
            antialias: Choice::On(()),
            appearance: Choice::Off,
            refine_cameras: Choice::Off,
            distortion: Choice::Off,
            few_view: Choice::Off,
            dynamic: Choice::Off,
            depth_smoothness: Choice::Off,
            time_smoothness: Choice::Off,
            time_cells: None,
            bf16: Choice::Off,
        };
        let few = SceneFacts {
            train_views: 3,
            ..facts(false, NDC)
        };
        let d = fast_defaults(&few, CPU, &off);
        assert!(d.antialias && !d.few_view && !d.dynamic() && !d.bf16_products);
        assert_eq!(
            (d.appearance, d.refine_cameras, d.distortion),
            (None, false, 0.0)
        );
    }

    #[test]
    fn apply_to_writes_each_feature_into_the_model() {
        use crate::model::unseen_patches::stride_for;
        let pose = crate::camera::look_at([0.0, -4.0, 1.0], [0.0; 3], [0.0, 0.0, 1.0]);
        let cameras = vec![Camera::from_fov_x(64, 48, 0.7, pose); 3];
        // Refinement is the caller's to write.
        let every = Flags {
            refine_cameras: Choice::Off,
            ..every_default_overridden()
        };
        let scene = SceneFacts {
            moments: 3,
            ..facts(true, RaySpace::World)
        };
        let mut m = FastModelConfig::default();
        let d = fast_defaults(&scene, CPU, &every);
        d.apply_to(&mut m, &cameras, &RaySpace::World, 2);
        assert!(m.field.antialias.is_none() && m.bf16_products && m.few_view.is_some());
        assert_eq!(m.field.motion, d.motion);
        assert!(m.field.motion.is_some());
        assert_eq!((m.distortion, m.time_smoothness), (0.01, 0.02));
        let smooth = m.depth_smoothness.expect("depth smoothness asked for");
        assert_eq!((smooth.weight, smooth.stride), (0.1, stride_for(64)));
        assert_eq!((m.field.appearance_dims, m.field.appearance_images), (8, 2));
        // A still Blender scene's defaults: anti-aliasing and nothing else.
        let mut m = FastModelConfig::default();
        let d = fast_defaults(&facts(true, RaySpace::World), CPU, &Flags::default());
        d.apply_to(&mut m, &cameras, &RaySpace::World, 3);
        assert!(m.field.antialias.is_some() && m.field.motion.is_none());
        assert!(m.few_view.is_none() && m.depth_smoothness.is_none());
        assert_eq!((m.distortion, m.time_smoothness), (0.0, 0.0));
        assert_eq!(m.field.appearance_dims, 0);
    }

    /// On the GPU engine each default it cannot run is left off and said, by name; the
    /// features it runs follow the same rules as on the CPU (codes and refinement only
    /// together).
    #[test]
    fn the_gpu_gets_what_it_runs_and_hears_what_it_does_not() {
        let gpu = EngineKind::Gpu;
        let both = gpu.runs(Feature::Appearance) && gpu.runs(Feature::CameraRefinement);
        for (blender, space) in [
            (true, RaySpace::World),
            (false, RaySpace::World),
            (false, NDC),
        ] {
            let scene = facts(blender, space);
            let on_cpu = fast_defaults(&scene, CPU, &Flags::default());
            let on_gpu = fast_defaults(&scene, gpu, &Flags::default());
            let said = |f: Feature| {
                on_gpu.notes.iter().any(|n| {
                    n.contains(f.describe()) || n.contains(&crate::engine::caps::list(&[f]))
                })
            };
            // Anti-aliasing and the distortion loss: as on the CPU where the GPU runs them.
            for (feature, cpu_on, gpu_on) in [
                (Feature::Antialias, on_cpu.antialias, on_gpu.antialias),
                (
                    Feature::Distortion,
                    on_cpu.distortion > 0.0,
                    on_gpu.distortion > 0.0,
                ),
            ] {
                if gpu.runs(feature) {
                    assert_eq!(gpu_on, cpu_on, "{feature:?}");
                } else {
                    assert!(!gpu_on, "{feature:?}");
                    assert_eq!(said(feature), cpu_on, "{feature:?}: {:?}", on_gpu.notes);
                }
            }
            // Codes and refinement: together, where the GPU runs both.
            let cpu_corrections = on_cpu.appearance.is_some() && on_cpu.refine_cameras;
            assert_eq!(on_gpu.appearance.is_some(), cpu_corrections && both);
            assert_eq!(on_gpu.refine_cameras, cpu_corrections && both);
            if cpu_corrections && !both {
                let lacking = if gpu.runs(Feature::CameraRefinement) {
                    Feature::Appearance
                } else {
                    Feature::CameraRefinement
                };
                assert!(said(lacking), "{:?}", on_gpu.notes);
            }
        }
    }

    #[test]
    fn auto_goes_to_the_cpu_for_what_only_the_cpu_runs_and_says_so() {
        let none = Flags::default();
        let still = facts(true, RaySpace::World);
        assert_eq!(
            engine_for(Device::Auto, false, &still, &none),
            (EngineKind::Cpu, None)
        );
        assert_eq!(
            engine_for(Device::Auto, true, &still, &none),
            (EngineKind::Gpu, None)
        );
        assert_eq!(engine_for(Device::Cpu, true, &still, &none), (CPU, None));
        // A moving scene goes where its field runs, unless a still field is asked for.
        let moving = SceneFacts {
            moments: 50,
            ..still
        };
        let (kind, note) = engine_for(Device::Auto, true, &moving, &none);
        if EngineKind::Gpu.runs(Feature::Dynamic) {
            assert_eq!((kind, note), (EngineKind::Gpu, None));
        } else {
            assert_eq!(kind, EngineKind::Cpu);
            assert!(note.is_some_and(|n| n.contains("--dynamic")));
        }
        let still_field = Flags {
            dynamic: Choice::Off,
            ..none
        };
        assert_eq!(
            engine_for(Device::Auto, true, &moving, &still_field).0,
            EngineKind::Gpu
        );
        // A feature only the CPU engine runs, asked for: the CPU, and the note says why.
        let depth = Flags {
            depth_smoothness: Choice::On(0.1),
            ..Flags::default()
        };
        let (kind, note) = engine_for(Device::Auto, true, &still, &depth);
        if EngineKind::Gpu.runs(Feature::DepthSmoothness) {
            assert_eq!((kind, note), (EngineKind::Gpu, None));
        } else {
            assert_eq!(kind, EngineKind::Cpu);
            let note = note.unwrap_or_default();
            assert!(note.contains("--depth-smoothness"), "{note}");
        }
        let asks = Flags {
            antialias: Choice::On(()),
            ..Flags::default()
        };
        let (kind, note) = engine_for(Device::Auto, true, &still, &asks);
        if EngineKind::Gpu.runs(Feature::Antialias) {
            assert_eq!((kind, note), (EngineKind::Gpu, None));
        } else {
            assert_eq!(kind, EngineKind::Cpu);
            let note = note.unwrap_or_default();
            assert!(note.contains(Feature::Antialias.describe()), "{note}");
        }
        // Asked for explicitly, a device is the user's choice: `open` refuses by name.
        assert_eq!(
            engine_for(Device::Wgpu, true, &still, &asks),
            (EngineKind::Gpu, None)
        );
    }

    /// bfloat16 products: on wherever the CPU engine runs them, off on the GPU engine
    /// without a note (its products are f32), and an explicit `--bf16` with `--device
    /// auto` takes the CPU, saying why.
    #[test]
    fn bf16_products_where_the_cpu_has_them() {
        let scene = facts(true, RaySpace::World);
        let none = Flags::default();
        let has = crate::nn::linalg::Precision::bf16().is_some();
        assert_eq!(fast_defaults(&scene, CPU, &none).bf16_products, has);
        let on_gpu = fast_defaults(&scene, EngineKind::Gpu, &none);
        assert!(!on_gpu.bf16_products);
        assert!(on_gpu.notes.is_empty(), "{:?}", on_gpu.notes);
        let (asked, off) = (
            Flags {
                bf16: Choice::On(()),
                ..none
            },
            Flags {
                bf16: Choice::Off,
                ..none
            },
        );
        assert!(fast_defaults(&scene, CPU, &asked).bf16_products);
        assert!(!fast_defaults(&scene, CPU, &off).bf16_products);
        let (kind, note) = engine_for(Device::Auto, true, &scene, &asked);
        assert_eq!(kind, EngineKind::Cpu);
        assert!(note.is_some_and(|n| n.contains("--bf16")));
    }
}
