//! `nerf train`: the options (declared once, in the library) -> a run folder.

use anyhow::Result;
use nerf::train::options::TrainOptions;
use nerf::train::run::{self, StopReason, CHECKPOINT_FILE};

use crate::progress::TrainProgress;

pub fn run(a: TrainOptions) -> Result<()> {
    let opts = a.run_options(&mut |w| eprintln!("warning: {w}"))?;
    let mut progress = TrainProgress::default();
    let summary = run::train(&opts, &mut |e| progress.on_event(e));
    progress.finish();
    let summary = summary?;
    let why = match summary.reason {
        StopReason::Steps => "all steps done".to_string(),
        StopReason::TimeBudget => format!("the {} minute budget ran out", a.minutes.unwrap_or(0.0)),
        StopReason::Paused => format!(
            "paused at step {}; continue with --resume",
            a.pause_at.unwrap_or(0)
        ),
    };
    println!(
        "stopped after step {} ({why}); {:.1} s of training; last batch PSNR {:.2} dB; checkpoint in {}",
        summary.steps,
        summary.seconds,
        summary.last_psnr,
        opts.out.join(CHECKPOINT_FILE).display()
    );
    Ok(())
}
