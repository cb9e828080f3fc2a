//! Evaluation of a trained run on a split: renders every `every`-th view, writes the
//! images and `metrics.json` with per-view and mean PSNR / SSIM.

use std::path::{Path, PathBuf};
use std::sync::Mutex;

use serde::{Deserialize, Serialize};

use crate::app::looks::{looks_of, EvalLook};
use crate::app::test_poses::{refine_test_poses, TestPoseFit, TestPoseReport};
use crate::camera::Camera;
use crate::data::{image::save_rgb_png, Split};
use crate::error::Result;
use crate::metrics::lpips::Lpips;
use crate::metrics::{psnr, ssim};
use crate::stage::Appearance;
use crate::train::folder::LoadedRun;
use crate::train::refined_cameras::{PoseError, RunCameras};
use crate::views::{RenderSettings, RenderedView};

/// Metrics of one view.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ViewMetrics {
    pub index: usize,
    pub name: String,
    pub psnr: f32,
    pub ssim: f32,
    /// LPIPS (AlexNet; lower is better), with `--lpips-weights` and views of at least 32
    /// pixels a side.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lpips: Option<f32>,
    pub image: PathBuf,
    pub depth: PathBuf,
    /// The training photo whose look (appearance code) the view was rendered with
    /// (models with codes, `EvalLook::Nearest`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub look: Option<String>,
    /// The view's downscale factor (1, 2, 4, 8: `--multiscale`).
    #[serde(
        default = "crate::train::one",
        skip_serializing_if = "crate::train::is_one"
    )]
    pub scale: usize,
}

/// Means over the views of one scale (`--multiscale`).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ScaleMetrics {
    /// The downscale factor: 1, 2, 4, 8, ...
    pub scale: usize,
    pub width: usize,
    pub height: usize,
    pub mean_psnr: f32,
    pub mean_ssim: f32,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mean_lpips: Option<f32>,
}

/// The mean of the views' LPIPS, when every one has it.
fn mean_lpips(views: &[ViewMetrics]) -> Option<f32> {
    let all: Option<Vec<f32>> = views.iter().map(|v| v.lpips).collect();
    all.filter(|a| !a.is_empty())
        .map(|a| a.iter().sum::<f32>() / a.len() as f32)
}

/// `metrics.json` of an evaluation.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct EvalReport {
    pub split: Split,
    pub step: u64,
    pub every: usize,
    pub width: usize,
    pub height: usize,
    /// Means over every view (of every scale, which all hold as many views: the average of
    /// the scales' means, as mip-NeRF reports).
    pub mean_psnr: f32,
    pub mean_ssim: f32,
    /// Mean LPIPS (AlexNet), with `--lpips-weights`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mean_lpips: Option<f32>,
    /// Why there is no LPIPS (no weights given, views too small).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lpips_skipped: Option<String>,
    /// Per scale, with `--multiscale` (empty: one scale).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub scales: Vec<ScaleMetrics>,
    /// Runs that refined (or perturbed) their training cameras: how far those ended from
    /// the given ones, after a similarity alignment (see `refined_cameras`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pose_error: Option<PoseError>,
    /// How the split's cameras were placed: `"aligned"` (mapped into the model's frame
    /// by that alignment), `"refined"` (each fitted to the frozen model,
    /// `--refine-test-poses`), `"aligned+refined"` (both); absent: used as given.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cameras: Option<String>,
    /// What fitting the split's cameras did (`--refine-test-poses`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub test_pose_refinement: Option<TestPoseReport>,
    /// The training views the run trained on (indices into the training split), when it
    /// kept only some (`--train-views`): few-view scores are not full ones.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub train_views: Option<Vec<usize>>,
    /// Models with appearance codes: which look the views were rendered with.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub looks: Option<EvalLook>,
    pub views: Vec<ViewMetrics>,
}

/// What to evaluate.
#[derive(Clone, Debug)]
pub struct EvalOptions {
    pub split: Split,
    /// Every `every`-th view of the split.
    pub every: usize,
    /// Fit each camera of the split to the frozen model first (BARF's protocol).
    pub refine_poses: Option<TestPoseFit>,
    /// Evaluate every view also at 1/2, ..., `1 / 2^(multiscale - 1)` of its resolution
    /// (1: full resolution alone).
    pub multiscale: usize,
    /// The LPIPS network (`--lpips-weights`); `None`: LPIPS is skipped, and the report
    /// says why.
    pub lpips: Option<std::sync::Arc<Lpips>>,
    /// Models with appearance codes: the look each view is rendered with.
    pub looks: EvalLook,
}

/// Why LPIPS is missing without weights.
pub const LPIPS_WITHOUT_WEIGHTS: &str = "no --lpips-weights given: AlexNet's and the LPIPS \
     heads' weights cannot ship with nerf; scripts/lpips_weights.py makes the file";

impl EvalOptions {
    /// Every `every`-th view of `split`, cameras as given (or aligned).
    pub fn new(split: Split, every: usize) -> Self {
        EvalOptions {
            split,
            every,
            refine_poses: None,
            multiscale: 1,
            lpips: None,
            looks: EvalLook::default(),
        }
    }
}

/// How far an evaluation is.
#[derive(Clone, Copy, Debug)]
pub enum EvalProgress {
    /// `--refine-test-poses`: optimisation steps done of `steps`.
    FittingCameras { step: u64, steps: u64 },
    /// Rays rendered of `total`.
    Rendering { rays: usize, total: usize },
}

/// Renders every `every`-th view of the split, writes `NNN.png` and `NNN_depth.png` into
/// `out_dir`, and `metrics.json` with per-view and mean PSNR / SSIM.
pub fn evaluate(
    run: &LoadedRun,
    options: &EvalOptions,
    out_dir: &Path,
    on_progress: &(dyn Fn(EvalProgress) + Sync),
) -> Result<EvalReport> {
    let cfg = &run.config;
    let (split, every) = (options.split, options.every.max(1));
    let scene = cfg.open_scene(1)?;
    let train_total = scene.indices(Split::Train).len();
    let train_views = match &cfg.train_views {
        Some(v) if v.is_subset(train_total) => Some(cfg.kept_train_views(train_total)?),
        _ => None,
    };
    let mut data = scene.load(split, every)?;
    // Picked where the scene puts the cameras, before any alignment, as the training
    // photos' are.
    let given: Vec<_> = data.views.iter().map(|v| v.camera.c2w).collect();
    let looks = looks_of(cfg, &scene, &given, options.looks);
    let appearance: Vec<Appearance> = looks.iter().flatten().map(|l| l.appearance).collect();
    let run_cameras = RunCameras::of(run)?;
    if let Some(c) = &run_cameras {
        let to_model = c.to_model_frame();
        for v in &mut data.views {
            v.camera.c2w = to_model.apply_pose(&v.camera.c2w);
        }
    }
    let test_pose_refinement = match options.refine_poses {
        Some(fit) => Some(refine_test_poses(
            run,
            &mut data,
            fit,
            &appearance,
            &|step, steps| on_progress(EvalProgress::FittingCameras { step, steps }),
        )?),
        None => None,
    };
    let cameras = match (run_cameras.is_some(), test_pose_refinement.is_some()) {
        (true, true) => Some("aligned+refined"),
        (true, false) => Some("aligned"),
        (false, true) => Some("refined"),
        (false, false) => None,
    };
    crate::io::create_dir(out_dir)?;
    let bg = cfg.background.eval_colour();
    let settings = RenderSettings::of_dataset(&data, bg);
    let (width, height) = data.image_size();
    let originals = data.views.len();
    data.add_scales(options.multiscale.max(1))?;
    let pixels = |v: &crate::data::View| v.image.width * v.image.height;
    let total_rays = data.views.iter().map(pixels).sum();
    let look_of = |k: usize| looks.as_ref().map(|l| &l[k % originals]);
    let view_cameras: Vec<Camera> = data.views.iter().map(|v| v.camera.clone()).collect();
    // Each view at its own look and, in a moving scene, its own moment.
    let settings_of = |k: usize| RenderSettings {
        appearance: look_of(k).map_or(Appearance::Mean, |l| l.appearance),
        time: data.views[k].time,
        ..settings
    };
    // Each view's scores and pictures, made while the next views render.
    let scored: Vec<Mutex<Option<ViewMetrics>>> =
        data.views.iter().map(|_| Mutex::new(None)).collect();
    let score = |k: usize, r: RenderedView| -> Result<()> {
        let view = &data.views[k];
        let i = (k % originals) * every;
        let scale = 1usize << (k / originals);
        let suffix = match scale {
            1 => String::new(),
            s => format!("_d{s}"),
        };
        let truth = view.image.composite(bg);
        let image = out_dir.join(format!("{i:03}{suffix}.png"));
        let depth = out_dir.join(format!("{i:03}{suffix}_depth.png"));
        save_rgb_png(&image, r.width, r.height, &r.rgb)?;
        save_rgb_png(
            &depth,
            r.width,
            r.height,
            &r.depth_image(data.near, data.far),
        )?;
        // Scored as saved, in 8 bits (the protocol of the papers' figures).
        let shown: Vec<f32> = r
            .rgb
            .iter()
            .map(|&v| f32::from(crate::data::image::to_u8(v)) / 255.0)
            .collect();
        let lpips = match &options.lpips {
            Some(net) => net.distance(&shown, &truth, r.width, r.height).ok(),
            None => None,
        };
        let metrics = ViewMetrics {
            index: i,
            name: view.name.clone(),
            psnr: psnr(&shown, &truth),
            ssim: ssim(&shown, &truth, r.width, r.height),
            lpips,
            image,
            depth,
            look: look_of(k).and_then(|l| l.photo.clone()),
            scale,
        };
        *scored[k].lock().unwrap_or_else(|e| e.into_inner()) = Some(metrics);
        Ok(())
    };
    crate::views::render_views(
        run.engine.as_ref(),
        &view_cameras,
        &settings_of,
        run.engine.views_in_flight(),
        &|rays| {
            on_progress(EvalProgress::Rendering {
                rays,
                total: total_rays,
            })
        },
        &score,
    )?;
    let views: Vec<ViewMetrics> = scored
        .into_iter()
        .filter_map(|m| m.into_inner().unwrap_or_else(|e| e.into_inner()))
        .collect();
    let n = views.len().max(1) as f32;
    let scales = match options.multiscale {
        0 | 1 => Vec::new(),
        _ => views
            .chunks(originals)
            .zip(data.views.chunks(originals))
            .map(|(m, v)| ScaleMetrics {
                scale: m[0].scale,
                width: v[0].image.width,
                height: v[0].image.height,
                mean_psnr: m.iter().map(|v| v.psnr).sum::<f32>() / m.len() as f32,
                mean_ssim: m.iter().map(|v| v.ssim).sum::<f32>() / m.len() as f32,
                mean_lpips: mean_lpips(m),
            })
            .collect(),
    };
    let overall_lpips = mean_lpips(&views);
    let report = EvalReport {
        split,
        step: run.step,
        every,
        width,
        height,
        mean_psnr: views.iter().map(|v| v.psnr).sum::<f32>() / n,
        mean_ssim: views.iter().map(|v| v.ssim).sum::<f32>() / n,
        mean_lpips: overall_lpips,
        lpips_skipped: match (&options.lpips, overall_lpips) {
            (None, _) => Some(LPIPS_WITHOUT_WEIGHTS.to_string()),
            (Some(_), None) => {
                Some("some views are smaller than the 32x32 pixels LPIPS needs".to_string())
            }
            (Some(_), Some(_)) => None,
        },
        scales,
        pose_error: run_cameras.as_ref().map(RunCameras::error),
        cameras: cameras.map(str::to_string),
        test_pose_refinement,
        train_views,
        looks: looks.is_some().then_some(options.looks),
        views,
    };
    crate::io::write_json(&out_dir.join("metrics.json"), &report)?;
    Ok(report)
}
