//! `nerf eval`: PSNR / SSIM of a run on a split, with the rendered images.

use std::path::PathBuf;

use anyhow::Result;
use clap::Args;
use nerf::data::Split;
use nerf::eval::EvalReport;
use nerf::train::folder::LoadedRun;

use crate::progress::bar;

#[derive(Args)]
pub struct EvalArgs {
    /// Run folder written by `nerf train`.
    #[arg(long)]
    run: PathBuf,
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
}

pub fn run(a: EvalArgs) -> Result<()> {
    let run = LoadedRun::open_on(&a.run, a.device.device)?;
    let out = a
        .out
        .unwrap_or_else(|| a.run.join(format!("eval_{}", a.split.name())));
    let pb = bar(0, &format!("eval {} rays", a.split.name()));
    let report = nerf::eval::evaluate(&run, a.split, a.every, &out, &|done, total| {
        pb.set_length(total as u64);
        pb.set_position(done as u64);
    })?;
    pb.finish_and_clear();
    print_report(&report, &out);
    Ok(())
}

/// The per-view table and the means.
pub fn print_report(report: &EvalReport, out: &std::path::Path) {
    for v in &report.views {
        println!(
            "  view {:3}  PSNR {:6.2} dB  SSIM {:.4}",
            v.index, v.psnr, v.ssim
        );
    }
    println!(
        "{} views of {} at step {} ({}x{}): mean PSNR {:.2} dB, mean SSIM {:.4}; images and metrics.json in {}",
        report.views.len(),
        report.split.name(),
        report.step,
        report.width,
        report.height,
        report.mean_psnr,
        report.mean_ssim,
        out.display()
    );
    if let Some(e) = &report.pose_error {
        println!(
            "training cameras against the given poses, after a similarity alignment: {:.3} \
             degrees, {:.4} units ({:.2}% of the camera radius); the {} cameras were mapped \
             through it",
            e.rotation_deg,
            e.translation,
            e.translation_percent_of_radius,
            report.split.name()
        );
    }
}
