//! `nerf eval`: PSNR / SSIM of a run on a split, with the rendered images.

use std::path::PathBuf;

use anyhow::Result;
use clap::Args;
use nerf::app::eval::{EvalOptions, EvalProgress, EvalReport};
use nerf::app::test_poses::TestPoseFit;
use nerf::data::Split;

use crate::progress::bar;

#[derive(Args)]
pub struct EvalArgs {
    /// Run folder written by `nerf train`.
    #[arg(long)]
    run: PathBuf,
    #[command(flatten)]
    scene: nerf::train::run_scene::SceneOverride,
    #[command(flatten)]
    device: nerf::engine::DeviceArg,
    #[arg(long, value_enum, default_value = "test")]
    split: Split,
    /// Evaluate every K-th view only (quick checks).
    #[arg(long, default_value_t = 1)]
    every: usize,
    /// Output folder for images and metrics.json. Default: <run>/eval_<split>.
    #[arg(long)]
    out: Option<PathBuf>,
    /// Fit each evaluated camera's pose to the frozen model first, in STEPS optimisation
    /// steps on its own photo (BARF's protocol; fast model, CPU; metrics.json says
    /// "cameras": "...refined" and what moved). The default, with 200 steps, for runs that
    /// refined their training cameras: their model's frame has moved a little from the
    /// given poses', so the test photos' poses must follow it.
    #[arg(long, value_name = "STEPS", num_args = 0..=1, default_missing_value = "200",
          conflicts_with = "no_refine_test_poses")]
    refine_test_poses: Option<u64>,
    /// Render the test cameras where the scene puts them (after the alignment of a
    /// refined run), without fitting them first.
    #[arg(long)]
    no_refine_test_poses: bool,
    /// Also evaluate every view at 1/2, 1/4, ... of its resolution, N scales in all
    /// (mip-NeRF's multi-scale benchmark: 4 goes down to 1/8); metrics.json gets the means
    /// of each scale under "scales".
    #[arg(long, value_name = "N", default_value_t = 1,
          value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(1..=6))]
    multiscale: usize,
    /// Runs with per-photo appearance codes: render each view with the look of the
    /// training photo taken nearest to it (a phone's auto-exposure follows where it
    /// points; no pixel of the evaluated photo is read) or with the mean code (the look
    /// of render and the viewer). metrics.json names each view's photo under "look".
    #[arg(long, value_enum, default_value = "nearest")]
    look: nerf::app::looks::EvalLook,
    /// Also report LPIPS (AlexNet, lower is better) with these weights: a safetensors file
    /// made by scripts/lpips_weights.py (the weights cannot ship with nerf).
    #[arg(long, value_name = "FILE")]
    lpips_weights: Option<PathBuf>,
}

/// Test-pose fitting steps of a refined run's evaluation (and of a bare
/// `--refine-test-poses`).
const DEFAULT_FIT_STEPS: u64 = 200;

pub fn run(a: EvalArgs) -> Result<()> {
    // Read first: a wrong file fails before minutes of rendering.
    let lpips = match &a.lpips_weights {
        Some(path) => Some(std::sync::Arc::new(nerf::metrics::lpips::Lpips::load(
            path,
        )?)),
        None => None,
    };
    let run = super::open_run(&a.run, a.device.device, &a.scene)?;
    let out = a
        .out
        .unwrap_or_else(|| a.run.join(format!("eval_{}", a.split.name())));
    let refined = matches!(&run.config.model,
        nerf::model::ModelConfig::Fast(m) if m.refine_cameras.is_some());
    let fit_steps = match a.refine_test_poses {
        Some(steps) => Some(steps),
        None if refined && !a.no_refine_test_poses => {
            println!(
                "the run refined its training cameras, so each {} camera is fitted to the \
                 model first ({DEFAULT_FIT_STEPS} steps; --no-refine-test-poses skips this)",
                a.split.name()
            );
            Some(DEFAULT_FIT_STEPS)
        }
        None => None,
    };
    let options = EvalOptions {
        refine_poses: fit_steps.map(TestPoseFit::new),
        multiscale: a.multiscale,
        lpips,
        looks: a.look,
        ..EvalOptions::new(a.split, a.every)
    };
    let fit = bar(0, &format!("fit {} cameras, steps", a.split.name()));
    let pb = bar(0, &format!("eval {} rays", a.split.name()));
    let report = nerf::app::eval::evaluate(&run, &options, &out, &|p| match p {
        EvalProgress::FittingCameras { step, steps } => {
            fit.set_length(steps);
            fit.set_position(step);
        }
        EvalProgress::Rendering { rays, total } => {
            if !fit.is_finished() {
                fit.finish_and_clear();
            }
            pb.set_length(total as u64);
            pb.set_position(rays as u64);
        }
    })?;
    fit.finish_and_clear();
    pb.finish_and_clear();
    print_report(&report, &out);
    Ok(())
}

/// The per-view table and the means.
pub fn print_report(report: &EvalReport, out: &std::path::Path) {
    for v in &report.views {
        let scale = match v.scale {
            1 => String::new(),
            s => format!(" at 1/{s}"),
        };
        let lpips = v
            .lpips
            .map(|l| format!("  LPIPS {l:.4}"))
            .unwrap_or_default();
        println!(
            "  view {:3}{scale}  PSNR {:6.2} dB  SSIM {:.4}{lpips}",
            v.index, v.psnr, v.ssim
        );
    }
    for s in &report.scales {
        let lpips = s
            .mean_lpips
            .map(|l| format!(", mean LPIPS {l:.4}"))
            .unwrap_or_default();
        println!(
            "  scale 1/{} ({}x{}): mean PSNR {:.2} dB, mean SSIM {:.4}{lpips}",
            s.scale, s.width, s.height, s.mean_psnr, s.mean_ssim
        );
    }
    let lpips = report
        .mean_lpips
        .map(|l| format!(", mean LPIPS {l:.4}"))
        .unwrap_or_default();
    println!(
        "{} views of {} at step {} ({}x{}): mean PSNR {:.2} dB, mean SSIM {:.4}{lpips}; images and metrics.json in {}",
        report.views.len(),
        report.split.name(),
        report.step,
        report.width,
        report.height,
        report.mean_psnr,
        report.mean_ssim,
        out.display()
    );
    if let Some(why) = &report.lpips_skipped {
        println!("LPIPS skipped: {why}");
    }
    match report.looks {
        Some(nerf::app::looks::EvalLook::Nearest) => println!(
            "each view rendered with the look (appearance code) of the training photo taken \
             nearest to it (--look mean: the mean code)"
        ),
        Some(nerf::app::looks::EvalLook::Mean) => {
            println!("views rendered with the mean of the photos' looks (appearance codes)")
        }
        None => {}
    }
    if let Some(e) = &report.pose_error {
        println!(
            "training cameras against the given poses, after a similarity alignment: {:.3} \
             degrees (median {:.3}, worst {:.3}), {:.4} units ({:.2}% of the camera radius); \
             the {} cameras were mapped through it",
            e.rotation_deg,
            e.rotation_deg_median,
            e.rotation_deg_max,
            e.translation,
            e.translation_percent_of_radius,
            report.split.name()
        );
    }
    if let Some(f) = &report.test_pose_refinement {
        println!(
            "{} cameras fitted to the frozen model in {} steps: moved {:.3} degrees and {:.4} \
             units on average; batch PSNR {:.2} -> {:.2} dB",
            report.split.name(),
            f.steps,
            f.mean_rotation_deg,
            f.mean_translation,
            f.batch_psnr_before,
            f.batch_psnr_after
        );
    }
}
