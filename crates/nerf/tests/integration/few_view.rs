//! Few-view training: the built-in chair from 8 photos, with and without keeping the
//! space that fewer than half of them see empty; from 3 photos, the paper's model with and
//! without FreeNeRF's regularisers.

use nerf::model::few_view::FewView;
use nerf::model::ModelConfig;
use nerf::train::folder::LoadedRun;
use nerf::train::run;
use nerf::train::TrainConfig;

use crate::common::{chair_scene, cpu_run, eval_test, fast_config};

const PHOTOS: usize = 8;

/// Trains `config` into `out`: the run, the losses of its steps and its held-out PSNR.
fn train_and_score(out: &std::path::Path, config: TrainConfig) -> (LoadedRun, Vec<f32>, f64) {
    let mut losses = Vec::new();
    let mut on_event = |e: run::Event| {
        if let run::Event::Step(s) = e {
            losses.push(s.loss);
        }
    };
    run::train(&cpu_run(out, config), &mut on_event).expect("train");
    let loaded = LoadedRun::open(out).expect("open run");
    let report = eval_test(&loaded, 1, &out.join("eval"));
    (loaded, losses, f64::from(report.mean_psnr))
}

/// Trains the chair's 8 photos for `steps`, few-view or not; the run and its test PSNR.
fn train(data: &std::path::Path, out: &std::path::Path, few: bool, steps: u64) -> (LoadedRun, f64) {
    let mut config = fast_config(data, steps);
    if let ModelConfig::Fast(m) = &mut config.model {
        m.few_view = few.then_some(FewView { photos: PHOTOS });
    }
    let (loaded, _, psnr) = train_and_score(out, config);
    (loaded, psnr)
}

/// The floaters that 8 photos leave in space few of them see are what few-view training
/// removes: on held-out views it scores better, and after reloading (the grid's saved
/// thickness keeps the unseen space empty) no cell outside the seen space is occupied.
#[test]
fn few_view_training_keeps_space_few_photos_see_empty_and_scores_better() {
    let dir = tempfile::tempdir().expect("tempdir");
    let data = dir.path().join("chair");
    chair_scene(&data, 64, PHOTOS, 8, 3);
    let steps = 600;
    let (plain, plain_psnr) = train(&data, &dir.path().join("plain"), false, steps);
    let (few, few_psnr) = train(&data, &dir.path().join("few"), true, steps);
    eprintln!("8 photos, held-out views: {plain_psnr:.2} dB plain, {few_psnr:.2} dB few-view");
    assert!(
        few_psnr >= plain_psnr + 1.5,
        "few-view {few_psnr:.2} dB against {plain_psnr:.2} dB"
    );
    let (Some(plain_occ), Some(few_occ)) = (plain.engine.occupancy(), few.engine.occupancy())
    else {
        panic!("the runs did not reload as fast models");
    };
    eprintln!("occupied: {plain_occ:.4} plain, {few_occ:.4} few-view");
    assert!(few_occ < plain_occ, "{few_occ} against {plain_occ}");
}

/// Trains the paper model's demo-sized networks (the full ones are hours of CPU) on the
/// photos in `data` for `steps`, with FreeNeRF's regularisers or without; the losses of its
/// steps and its held-out PSNR.
fn train_vanilla(
    data: &std::path::Path,
    out: &std::path::Path,
    free: bool,
    steps: u64,
) -> (Vec<f32>, f64) {
    let mut config = crate::common::demo_config(data, steps);
    if let ModelConfig::Vanilla(m) = &mut config.model {
        m.free_nerf = free.then(nerf::model::free_nerf::FreeNerf::default);
    }
    let (_, losses, psnr) = train_and_score(out, config);
    (losses, psnr)
}

/// FreeNeRF from 3 photos: its loss falls, and on held-out views it scores better than the
/// same networks trained without its regularisers for as many steps.
#[test]
fn free_nerf_beats_the_plain_model_from_three_photos() {
    let dir = tempfile::tempdir().expect("tempdir");
    let data = dir.path().join("chair");
    // Seed 5: the plain model does not collapse to the background here (at seeds 3 and 4
    // it does, at about 11.5 dB, and FreeNeRF's lead is 7-9 dB).
    chair_scene(&data, 32, 3, 8, 5);
    let steps = 300;
    let (losses, free) = train_vanilla(&data, &dir.path().join("free"), true, steps);
    let (_, plain) = train_vanilla(&data, &dir.path().join("plain"), false, steps);
    eprintln!("3 photos, held-out views: {plain:.2} dB plain, {free:.2} dB FreeNeRF");
    let mean = |l: &[f32]| l.iter().sum::<f32>() / l.len() as f32;
    let (first, last) = (mean(&losses[..50]), mean(&losses[losses.len() - 50..]));
    assert!(last < 0.5 * first, "loss {first} -> {last}");
    // Measured: 18.82 against 17.63 dB.
    assert!(
        free >= plain + 0.6,
        "FreeNeRF {free:.2} dB against {plain:.2} dB"
    );
}
