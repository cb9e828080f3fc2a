//! Few-view training: the built-in chair from 8 photos, with and without keeping the
//! space that fewer than half of them see empty.

use nerf::model::few_view::FewView;
use nerf::model::ModelConfig;
use nerf::train::folder::LoadedRun;
use nerf::train::run;

use crate::common::{chair_scene, cpu_run, eval_test, fast_config};

const PHOTOS: usize = 8;

/// Trains the chair's 8 photos for `steps`, few-view or not; the run and its test PSNR.
fn train(data: &std::path::Path, out: &std::path::Path, few: bool, steps: u64) -> (LoadedRun, f64) {
    let mut config = fast_config(data, steps);
    if let ModelConfig::Fast(m) = &mut config.model {
        m.few_view = few.then_some(FewView { photos: PHOTOS });
    }
    run::train(&cpu_run(out, config), &mut |_| {}).expect("train");
    let loaded = LoadedRun::open(out).expect("open run");
    let report = eval_test(&loaded, 1, &out.join("eval"));
    (loaded, f64::from(report.mean_psnr))
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
