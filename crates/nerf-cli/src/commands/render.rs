//! `nerf render`: a camera path of a run to PNG frames and a video.

use std::path::PathBuf;

use anyhow::Result;
use clap::Args;
use nerf::app::frames::{FrameProgress, FramesOptions, FramesReport};

use crate::progress::bar;

#[derive(Args)]
pub struct RenderArgs {
    /// Run folder written by `nerf train`.
    #[arg(long)]
    run: PathBuf,
    #[command(flatten)]
    scene: nerf::train::run_scene::SceneOverride,
    #[command(flatten)]
    device: nerf::engine::DeviceArg,
    #[command(flatten)]
    frames: FramesOptions,
    /// Output folder for the PNG frames (RGB, turbo depth, opacity). Default:
    /// <run>/render_<path>.
    #[arg(long)]
    out: Option<PathBuf>,
}

pub fn run(a: RenderArgs) -> Result<()> {
    let run = super::open_run(&a.run, a.device.device, &a.scene)?;
    let out = a
        .out
        .clone()
        .unwrap_or_else(|| a.run.join(format!("render_{}", a.frames.path.name())));
    if let Some(v) = &a.frames.video {
        if let Some(why) = nerf::app::frames::video_target(v)?.fallback {
            eprintln!("{why}");
        }
    }
    let pb = bar(0, "render rays");
    let report = nerf::app::frames::render_frames(&run, &a.frames, &out, &|p| show(&pb, p))?;
    pb.finish_and_clear();
    print_report(&report, &out);
    Ok(())
}

/// Moves `pb` to `p`.
pub fn show(pb: &indicatif::ProgressBar, p: FrameProgress) {
    pb.set_length(p.rays_total as u64);
    pb.set_position(p.rays_done as u64);
    pb.set_message(format!(
        "frame {}/{}, {:.2} frames/s",
        p.frame + 1,
        p.frames,
        p.frames_per_second
    ));
}

pub fn print_report(report: &FramesReport, out: &std::path::Path) {
    if let Some(v) = &report.video {
        println!("video: {}", v.path.display());
    }
    println!(
        "rendered {} frame{} in {:.1} s ({:.2} frames/s) to {}",
        report.frames,
        if report.frames == 1 { "" } else { "s" },
        report.seconds,
        report.frames as f64 / report.seconds.max(1e-9),
        out.display()
    );
    // The engine's own pace, past the first frame (which compiles a GPU's kernels).
    if report.frames > 1 {
        let rest = (report.render_seconds - report.first_frame_seconds).max(1e-9);
        println!(
            "the engine alone: first frame {:.2} s, then {:.2} frames/s",
            report.first_frame_seconds,
            (report.frames - 1) as f64 / rest
        );
    }
}
