//! The fast model through the same run, resume and evaluation code as the vanilla one: it
//! must learn a small built-in scene past a PSNR floor in seconds, carve empty space out of
//! its occupancy grid, and resume bit-exactly (grid included) across a grid refresh.

use std::path::Path;

mod common;
use common::{fast_config, small_scene};

use nerf::data::Split;
use nerf::train::run::{self, LoadedRun, RunOptions, StopReason};
use nerf::train::TrainConfig;

fn options(out: &Path, config: TrainConfig, resume: bool, pause_at: Option<u64>) -> RunOptions {
    RunOptions {
        out: out.to_path_buf(),
        config,
        minutes: None,
        resume,
        pause_at,
        stop: None,
        device: nerf::engine::Device::Cpu,
    }
}

#[test]
fn fast_model_trains_a_small_scene_past_a_psnr_floor() {
    let dir = tempfile::tempdir().expect("tempdir");
    let data = dir.path().join("chair");
    small_scene(&data, 48);
    let out = dir.path().join("run");
    let summary = run::train(
        &options(&out, fast_config(&data, 500), false, None),
        &mut |_| {},
    )
    .expect("train");
    assert_eq!((summary.steps, summary.reason), (500, StopReason::Steps));
    let loaded = LoadedRun::open(&out).expect("open run");
    // The chair fills a small part of its box: most cells must have been found empty.
    let occupied = loaded
        .engine
        .occupancy()
        .expect("the run did not reload as a fast model");
    assert!(
        occupied < 0.5,
        "{:.1}% of the grid still occupied",
        100.0 * occupied
    );
    let report =
        nerf::eval::evaluate(&loaded, Split::Test, 1, &out.join("eval"), &|_, _| {}).expect("eval");
    eprintln!(
        "fast model test PSNR {:.2} dB, SSIM {:.3}",
        report.mean_psnr, report.mean_ssim
    );
    // An all-white prediction scores about 11 dB on these views.
    assert!(
        report.mean_psnr > 22.0,
        "test PSNR {:.2} dB is below the 22 dB floor",
        report.mean_psnr
    );
    assert!(report.mean_ssim > 0.85, "test SSIM {:.3}", report.mean_ssim);
}

#[test]
fn fast_run_resumes_exactly_across_an_occupancy_refresh() {
    let dir = tempfile::tempdir().expect("tempdir");
    let data = dir.path().join("chair");
    small_scene(&data, 16);
    let config = fast_config(&data, 20);
    let straight = dir.path().join("straight");
    run::train(
        &options(&straight, config.clone(), false, None),
        &mut |_| {},
    )
    .expect("train");
    // Paused before the refresh at step 16, resumed past it.
    let split = dir.path().join("split");
    let first = run::train(
        &options(&split, config.clone(), false, Some(13)),
        &mut |_| {},
    )
    .expect("first part");
    assert_eq!(first.reason, StopReason::Paused);
    run::train(&options(&split, config, true, None), &mut |_| {}).expect("resume");
    let (a, b) = (
        LoadedRun::open(&straight).expect("a"),
        LoadedRun::open(&split).expect("b"),
    );
    assert_eq!((a.step, b.step), (20, 20));
    let (sa, sb) = (a.engine.state(), b.engine.state());
    assert!(sa.params == sb.params, "resumed weights differ");
    assert_eq!(
        a.engine.buffer_layout().tensors.len(),
        1,
        "the occupancy grid is checkpointed"
    );
    assert!(sa.buffers == sb.buffers, "resumed occupancy grid differs");
    // The refresh at step 16 ran (the grid is no longer all-occupied and fresh).
    assert!(sa.buffers.iter().any(|&v| v > 0.0));
}
