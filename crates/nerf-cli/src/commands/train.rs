//! `nerf train`: the options (declared once, in the library) -> a run folder.

use std::sync::atomic::AtomicUsize;
use std::sync::Arc;

use anyhow::Result;
use nerf::train::options::TrainOptions;
use nerf::train::run::{self, RunSummary, StopReason, CHECKPOINT_FILE};

use crate::progress::TrainProgress;

pub fn run(a: TrainOptions) -> Result<()> {
    let mut opts = a.run_options(&mut |line| eprintln!("{line}"))?;
    let stop = Arc::new(AtomicUsize::new(0));
    crate::signals::stop_on_interrupt(&stop)?;
    opts.stop = Some(stop);
    let mut progress = TrainProgress::default();
    let mut live = match a.view {
        true => {
            let live = nerf_view::live::LiveView::start(&opts.config, &opts.out, a.view_port)?;
            eprintln!("watch it train at {}", live.running.url);
            Some(live)
        }
        false => None,
    };
    let summary = run::train(&opts, &mut |e| {
        if let Some(live) = &mut live {
            live.on_event(&e);
        }
        progress.on_event(e)
    });
    progress.finish();
    let summary = summary?;
    if let Some(live) = &live {
        live.show_checkpoint(&opts.out)?;
    }
    let out = opts.out.display();
    let resume = format!("nerf train --out {out} --resume");
    let why = match summary.reason {
        StopReason::Steps => "all steps done".to_string(),
        StopReason::TimeBudget => match opts.config.time_budget_s {
            Some(s) => format!("the {:.1} minute schedule is done", s / 60.0),
            None => format!("the {} minute budget ran out", a.minutes.unwrap_or(0.0)),
        },
        StopReason::Paused => format!(
            "paused at step {}; continue with `{resume}`",
            a.pause_at.unwrap_or(0)
        ),
        StopReason::Interrupted(signal) => format!(
            "interrupted by {}; continue with `{resume}`",
            crate::signals::name(signal)
        ),
    };
    println!(
        "stopped after step {} ({why}); {:.1} s of training; {}",
        summary.steps,
        summary.seconds,
        headline(&summary)
    );
    println!(
        "checkpoint: {}\nnext: nerf eval --run {out}   (test-split PSNR / SSIM per view)",
        opts.out.join(CHECKPOINT_FILE).display()
    );
    if let StopReason::Interrupted(signal) = summary.reason {
        std::process::exit(crate::signals::exit_code(signal));
    }
    if let (Some(live), Some(stop)) = (&live, &opts.stop) {
        eprintln!(
            "the viewer stays open at {} with the final model: press Ctrl-C to leave",
            live.running.url
        );
        while stop.load(std::sync::atomic::Ordering::SeqCst) == 0 {
            std::thread::sleep(std::time::Duration::from_millis(200));
        }
    }
    Ok(())
}

/// The figure to lead with: the latest validation PSNR (a held-out view), not the last
/// training batch's, which flatters the model.
fn headline(s: &RunSummary) -> String {
    match s.val_psnr {
        Some((step, psnr)) => format!("latest validation PSNR {psnr:.2} dB (step {step})"),
        None => "no validation image yet (see --val-every)".to_string(),
    }
}
