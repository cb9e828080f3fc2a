//! Trains on a small built-in scene and checks what a user relies on: the picture gets good,
//! runs resume exactly, every preset trains, and a NaN stops the run cleanly.

use std::path::Path;

use crate::common::{cpu_run, demo_config, small_scene};

use nerf::data::synth::{self, SynthOptions};
use nerf::data::Split;
use nerf::train::run::{self, LoadedRun, RunOptions, StopReason};
use nerf::train::{TrainConfig, Trainer};

#[test]
fn trains_a_small_scene_past_a_psnr_floor() {
    let dir = tempfile::tempdir().expect("tempdir");
    let data = dir.path().join("chair");
    small_scene(&data, 32);
    let out = dir.path().join("run");
    let opts = cpu_run(&out, demo_config(&data, 400));
    let summary = run::train(&opts, &mut |_| {}).expect("train");
    assert_eq!((summary.steps, summary.reason), (400, StopReason::Steps));
    let loaded = LoadedRun::open(&out).expect("open run");
    let report = crate::common::eval_test(&loaded, 1, &out.join("eval"));
    // An all-white prediction scores about 11 dB on these views; an untrained net about 8.
    assert!(
        report.mean_psnr > 18.0,
        "test PSNR {:.2} dB is below the 18 dB floor",
        report.mean_psnr
    );
    assert!(report.mean_ssim > 0.6, "test SSIM {:.3}", report.mean_ssim);
    assert!(out.join("eval/metrics.json").exists() && out.join("eval/000_depth.png").exists());
}

#[test]
fn resumed_run_matches_an_uninterrupted_one_exactly() {
    let dir = tempfile::tempdir().expect("tempdir");
    let data = dir.path().join("chair");
    small_scene(&data, 16);
    let straight = dir.path().join("straight");
    let mut config = demo_config(&data, 12);
    config.checkpoint_every = 5;
    run::train(&cpu_run(&straight, config.clone()), &mut |_| {}).expect("train");

    // Stopped at step 7 (as a kill right after that step's checkpoint would leave it), with
    // a metrics line from a step past the checkpoint that the resume must drop.
    let split = dir.path().join("split");
    let first = RunOptions {
        pause_at: Some(7),
        ..cpu_run(&split, config.clone())
    };
    assert_eq!(
        run::train(&first, &mut |_| {}).expect("first half").reason,
        StopReason::Paused
    );
    let metrics = split.join(run::METRICS_FILE);
    let mut text = std::fs::read_to_string(&metrics).expect("metrics");
    text.push_str("{\"step\":8,\"loss\":1.0,\"psnr\":1.0,\"lr\":1.0,\"elapsed_s\":1.0}\n");
    std::fs::write(&metrics, text).expect("metrics");
    let summary = run::train(
        &RunOptions {
            resume: true,
            ..cpu_run(&split, config.clone())
        },
        &mut |_| {},
    )
    .expect("resume");
    assert_eq!(summary.steps, 12);

    let a = LoadedRun::open(&straight).expect("a");
    let b = LoadedRun::open(&split).expect("b");
    assert_eq!(a.step, b.step);
    assert!(
        a.engine.state().params == b.engine.state().params,
        "resumed parameters differ from the uninterrupted run"
    );
    let lines = std::fs::read_to_string(split.join(run::METRICS_FILE)).expect("metrics");
    assert_eq!(
        lines.lines().count(),
        12,
        "one metrics line per step, none duplicated by the resume"
    );

    // A second fresh run into the same folder is refused rather than overwriting it.
    let err = run::train(&cpu_run(&split, config), &mut |_| {}).expect_err("refuse");
    assert!(err.to_string().contains("--resume"), "{err}");
}

#[test]
fn time_budget_stops_with_a_checkpoint() {
    let dir = tempfile::tempdir().expect("tempdir");
    let data = dir.path().join("chair");
    small_scene(&data, 16);
    let out = dir.path().join("run");
    let opts = RunOptions {
        minutes: Some(0.02),
        ..cpu_run(&out, demo_config(&data, 1_000_000))
    };
    let summary = run::train(&opts, &mut |_| {}).expect("train");
    assert_eq!(summary.reason, StopReason::TimeBudget);
    assert!(summary.steps > 0 && summary.steps < 1_000_000);
    assert_eq!(
        LoadedRun::open(&out).expect("checkpoint").step,
        summary.steps
    );
}

/// `--minutes` alone schedules by the clock. The learning rate falls with
/// elapsed time and reaches (nearly) its final value as the budget ends, where a step
/// schedule cut short by the clock never gets there; a resume with a larger budget goes on
/// from the saved clock.
#[test]
fn a_timed_schedule_decays_with_the_clock_and_resumes() {
    let dir = tempfile::tempdir().expect("tempdir");
    let data = dir.path().join("chair");
    small_scene(&data, 16);
    let out = dir.path().join("run");
    let mut config = demo_config(&data, u64::MAX);
    config.time_budget_s = Some(1.5);
    let mut opts = cpu_run(&out, config.clone());
    let first = run::train(&opts, &mut |_| {}).expect("train");
    assert_eq!(first.reason, StopReason::TimeBudget);
    assert!(first.seconds >= 1.5 && first.steps > 3, "{first:?}");
    let lrs = learning_rates(&out);
    assert_eq!(lrs.len() as u64, first.steps);
    assert!(lrs.windows(2).all(|w| w[1] <= w[0]), "{lrs:?}");
    assert!(
        (lrs[0] - config.lr_init).abs() < 0.1 * config.lr_init,
        "{lrs:?}"
    );
    // The last step began within a step's time of the end: past 3/4 of the decay.
    let late = config.learning_rate_at(0.75);
    assert!(*lrs.last().expect("steps") < late, "{lrs:?} vs {late}");

    // Resuming a spent schedule does nothing; a larger budget goes on from its clock.
    opts.resume = true;
    let again = run::train(&opts, &mut |_| {}).expect("resume");
    assert_eq!(
        (again.steps, again.reason),
        (first.steps, StopReason::TimeBudget)
    );
    opts.config.time_budget_s = Some(2.5);
    let more = run::train(&opts, &mut |_| {}).expect("resume longer");
    assert!(more.steps > first.steps && more.seconds >= 2.5, "{more:?}");
    let saved = LoadedRun::open(&out).expect("run");
    assert_eq!(saved.config.time_budget_s, Some(2.5));
    let lrs = learning_rates(&out);
    let resumed_first = lrs[first.steps as usize];
    // The rate picks up where the clock left off (1.5 of 2.5 s), not from the start.
    assert!(
        resumed_first < config.learning_rate_at(0.5),
        "{resumed_first}"
    );
}

fn learning_rates(run: &Path) -> Vec<f32> {
    let text = std::fs::read_to_string(run.join("metrics.jsonl")).expect("metrics");
    text.lines()
        .filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok())
        .filter_map(|v| v.get("lr").and_then(|x| x.as_f64()))
        .map(|x| x as f32)
        .collect()
}

#[test]
fn every_preset_trains_a_step() {
    let opts = SynthOptions {
        size: 12,
        supersample: 1,
        ..Default::default()
    };
    let data = synth::dataset(&opts, Split::Train, 30);
    for p in nerf::presets::PRESETS {
        let mut c = TrainConfig::from_preset("mem".into(), p.name).expect("preset");
        c.batch_rays = 8;
        c.chunk_rays = 4;
        let mut d = data.clone();
        let kept = c.kept_train_views(d.views.len()).expect("views");
        d.keep(&kept);
        let mut t = Trainer::new(c, d).expect("trainer");
        let before = t.engine.state().params;
        let s = t.step().expect("step");
        assert!(
            s.loss.is_finite() && s.loss > 0.0,
            "{}: loss {}",
            p.name,
            s.loss
        );
        assert!(
            t.engine.state().params != before,
            "{}: a step changed nothing",
            p.name
        );
    }
}

#[test]
fn nan_loss_stops_without_touching_the_weights() {
    let opts = SynthOptions {
        size: 12,
        supersample: 1,
        ..Default::default()
    };
    let mut data = synth::dataset(&opts, Split::Train, 3);
    for v in &mut data.views {
        let (w, h) = (v.image.width, v.image.height);
        v.image = nerf::data::RgbaImage::from_premultiplied(w, h, vec![f32::NAN; w * h * 4]);
    }
    let mut c = TrainConfig::from_preset("mem".into(), "demo").expect("preset");
    c.batch_rays = 16;
    let mut t = Trainer::new(c, data).expect("trainer");
    let before = t.engine.state().params;
    let err = t.step().expect_err("NaN targets must stop training");
    assert!(
        matches!(err, nerf::NerfError::Diverged { step: 1, .. }),
        "{err}"
    );
    assert!(t.engine.state().params == before && t.step == 0);
}
