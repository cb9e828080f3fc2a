//! `nerf capture`: photos or a video -> COLMAP -> a trainable scene (transforms.json).

use std::time::Instant;

use anyhow::Result;
use nerf::app::capture::CaptureOptions;

pub fn run(opts: CaptureOptions) -> Result<()> {
    let t0 = Instant::now();
    let report = nerf::app::capture::capture(&opts, &mut |stage| {
        println!("[{:6.1} s] {stage}", t0.elapsed().as_secs_f64());
    })?;
    println!(
        "COLMAP registered {} of {} images ({:?} matching) with {} points in {:.1} s",
        report.registered,
        report.images,
        report.matching,
        report.points,
        t0.elapsed().as_secs_f64()
    );
    if !report.unregistered.is_empty() {
        println!(
            "warning: {} images could not be placed and are left out: {}",
            report.unregistered.len(),
            report.unregistered.join(", ")
        );
        println!("{}", nerf::app::capture::FIXES);
    }
    println!(
        "scene: {} -> nerf train --data {}",
        report.transforms.display(),
        opts.out.display()
    );
    Ok(())
}
