//! Few-view training: the built-in chair from 8 photos, with few-view training as a new
//! run gets it (the space that fewer than half of them frame, and the space the chair
//! hides from all of them, kept empty; degree-1 view dependence; the tables' decay) and
//! without (and resumed exactly across the pass that finds hidden space); the
//! forward-facing rug from 3 photos,
//! with and without RegNeRF's depth smoothness; from 3 photos, the paper's model with and
//! without FreeNeRF's regularisers, and with and without RegNeRF's.

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

/// Trains the chair's 8 photos for `steps`, with few-view training as a new run gets it
/// by default or without; the run and its test PSNR.
fn train(data: &std::path::Path, out: &std::path::Path, few: bool, steps: u64) -> (LoadedRun, f64) {
    let mut config = fast_config(data, steps);
    if let ModelConfig::Fast(m) = &mut config.model {
        if few {
            m.train_from_few_views(PHOTOS);
        }
    }
    let (loaded, _, psnr) = train_and_score(out, config);
    (loaded, psnr)
}

/// The floaters that 8 photos leave in space few of them see are what few-view training
/// removes: on held-out views it scores better, fewer cells are occupied, and the cells
/// the chair hides from every photo, saved with the checkpoint, hold nothing.
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
    let buffers = few.engine.state().buffers;
    let (thickness, hidden) = buffers.split_at(buffers.len() / 2);
    let hidden_cells = hidden.iter().filter(|&&h| h == 1.0).count();
    eprintln!("{hidden_cells} cells hidden from every photo");
    assert!(hidden_cells > 0, "nothing hidden");
    for (i, (&t, &h)) in thickness.iter().zip(hidden).enumerate() {
        assert!(h == 0.0 || t == 0.0, "hidden cell {i} has thickness {t}");
    }
}

/// A few-view run paused between two passes that find hidden space and resumed matches
/// one trained straight through, bit for bit: the hidden cells are saved with the
/// checkpoint.
#[test]
fn few_view_run_resumes_exactly_across_a_hidden_space_pass() {
    use nerf::train::run::{RunOptions, StopReason};
    let dir = tempfile::tempdir().expect("tempdir");
    let data = dir.path().join("chair");
    chair_scene(&data, 64, PHOTOS, 1, 3);
    let mut config = fast_config(&data, 300);
    if let ModelConfig::Fast(m) = &mut config.model {
        m.train_from_few_views(PHOTOS);
        m.few_view = Some(FewView {
            photos: PHOTOS,
            hidden_every: 256,
        });
    }
    let hidden = |run: &LoadedRun| {
        let buffers = run.engine.state().buffers;
        let hidden = &buffers[buffers.len() / 2..];
        hidden.iter().filter(|&&h| h == 1.0).count()
    };
    let options = |out: &std::path::Path, resume: bool, pause_at: Option<u64>| RunOptions {
        resume,
        pause_at,
        ..cpu_run(out, config.clone())
    };
    let straight = dir.path().join("straight");
    run::train(&options(&straight, false, None), &mut |_| {}).expect("train");
    let split = dir.path().join("split");
    let first = run::train(&options(&split, false, Some(280)), &mut |_| {}).expect("first part");
    assert_eq!(first.reason, StopReason::Paused);
    let paused = hidden(&LoadedRun::open(&split).expect("paused run"));
    eprintln!("{paused} cells hidden at the pause");
    assert!(paused > 0, "nothing hidden at the pause: nothing to test");
    run::train(&options(&split, true, None), &mut |_| {}).expect("resume");
    let (a, b) = (
        LoadedRun::open(&straight).expect("a"),
        LoadedRun::open(&split).expect("b"),
    );
    let (sa, sb) = (a.engine.state(), b.engine.state());
    assert_eq!(
        a.engine.buffer_layout().tensors.len(),
        2,
        "thickness and hidden cells"
    );
    assert!(sa.params == sb.params, "resumed weights differ");
    assert!(
        sa.buffers == sb.buffers,
        "resumed grid or hidden cells differ"
    );
}

/// The built-in rug as a forward-facing LLFF capture, `width x height` (26 training and 4
/// held-out views).
fn rug_scene(data: &std::path::Path, width: usize, height: usize) {
    use nerf::data::synth::{self, SceneKind};
    let cameras = synth::llff::forward_facing_cameras(width, height, 5, 6);
    let world = nerf::data::poses::Similarity::IDENTITY;
    synth::llff::write(SceneKind::Rug, &cameras, 1, &world, data, &mut |_, _| {})
        .expect("write llff");
}

/// RegNeRF's depth smoothness on the forward-facing rug from 3 photos (RegNeRF's LLFF
/// protocol, where it is on by default): trained with it, the field's depth seen from
/// poses between the cameras (patches it never trained on) is smoother than without, and
/// its held-out views score better.
#[test]
fn depth_smoothness_smooths_the_depth_seen_from_between_the_cameras() {
    use nerf::model::unseen_patches::{draw_patch, DepthSmoothness, PatchDraw, PATCHES};
    use nerf::render::depth_smoothness::{patch_loss, PATCH_RAYS};
    let dir = tempfile::tempdir().expect("tempdir");
    let data = dir.path().join("rug");
    rug_scene(&data, 128, 96);
    let train = |name: &str, smooth: bool| {
        let mut config = fast_config(&data, STEPS);
        config.train_views = Some(nerf::data::TrainViews::Spread { spread: 3 });
        if let ModelConfig::Fast(m) = &mut config.model {
            m.depth_smoothness = smooth.then_some(DepthSmoothness {
                weight: nerf::train::defaults::FEW_VIEW_DEPTH_SMOOTHNESS,
                patches: PATCHES,
                stride: 1,
            });
        }
        let (run, _, psnr) = train_and_score(&dir.path().join(name), config);
        (run, psnr)
    };
    const STEPS: u64 = 600;
    let (plain, plain_psnr) = train("plain", false);
    let (smooth, smooth_psnr) = train("smooth", true);
    let photos = plain
        .config
        .open_scene(1)
        .expect("scene")
        .load(nerf::data::Split::Train, 1)
        .expect("photos");
    // The mean loss of 64 patches from unseen poses (other draws than training's).
    let roughness = |run: &LoadedRun| {
        let mut total = 0.0f64;
        let mut patch = nerf::data::pixels::TrainingRays::default();
        for k in 0..64 {
            let draw = PatchDraw {
                seed: 1234,
                step: 0,
                k,
            };
            draw_patch(&photos, draw, 1, &mut patch);
            let mut out = vec![nerf::stage::RayOutput::default(); PATCH_RAYS];
            run.engine.render_rays(&patch.rays, &mut out, &|_| {});
            let opacity: [f32; PATCH_RAYS] = std::array::from_fn(|i| out[i].opacity);
            let depth: [f32; PATCH_RAYS] =
                std::array::from_fn(|i| out[i].depth / out[i].opacity.max(1e-6));
            total += f64::from(patch_loss(&depth, &opacity));
        }
        total / 64.0
    };
    let (plain_rough, smooth_rough) = (roughness(&plain), roughness(&smooth));
    eprintln!(
        "rug from 3 photos: roughness {plain_rough:.6} plain, {smooth_rough:.6} with depth \
         smoothness; held-out {plain_psnr:.2} / {smooth_psnr:.2} dB"
    );
    assert!(
        smooth_rough < 0.8 * plain_rough,
        "roughness {smooth_rough} against {plain_rough}"
    );
    assert!(
        smooth_psnr > plain_psnr + 0.5,
        "{smooth_psnr:.2} dB against {plain_psnr:.2} dB"
    );
}

/// The few-view regularisers of the paper's model.
#[derive(Clone, Copy, PartialEq)]
enum Regularisers {
    None,
    FreeNerf,
    RegNerf,
}

/// Trains `config` (the paper model's demo-sized networks: the full ones are hours of CPU)
/// into `out` with `regularisers`; the losses of its steps and its held-out PSNR.
fn train_vanilla(
    mut config: TrainConfig,
    out: &std::path::Path,
    regularisers: Regularisers,
) -> (Vec<f32>, f64) {
    if let ModelConfig::Vanilla(m) = &mut config.model {
        m.free_nerf = (regularisers == Regularisers::FreeNerf)
            .then(nerf::model::free_nerf::FreeNerf::default);
        m.reg_nerf =
            (regularisers == Regularisers::RegNerf).then(nerf::model::reg_nerf::RegNerf::default);
    }
    let (_, losses, psnr) = train_and_score(out, config);
    (losses, psnr)
}

/// The mean loss of the last 50 steps is under half that of the first 50.
fn assert_loss_halves(losses: &[f32]) {
    let mean = |l: &[f32]| l.iter().sum::<f32>() / l.len() as f32;
    let (first, last) = (mean(&losses[..50]), mean(&losses[losses.len() - 50..]));
    assert!(last < 0.5 * first, "loss {first} -> {last}");
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
    let config = crate::common::short_schedule(crate::common::demo_config(&data, 250));
    let (losses, free) = train_vanilla(
        config.clone(),
        &dir.path().join("free"),
        Regularisers::FreeNerf,
    );
    let (_, plain) = train_vanilla(config, &dir.path().join("plain"), Regularisers::None);
    eprintln!("3 photos, held-out views: {plain:.2} dB plain, {free:.2} dB FreeNeRF");
    assert_loss_halves(&losses);
    // Measured: 18.80 against 17.21 dB (300 steps decaying to a quarter: 18.82 against
    // 17.63).
    assert!(
        free >= plain + 0.6,
        "FreeNeRF {free:.2} dB against {plain:.2} dB"
    );
}

/// RegNeRF on the forward-facing rug from 3 photos (its LLFF protocol): its loss falls,
/// and on held-out views it scores better than the same networks trained without its
/// regularisers for as many steps. (The chair from 3 photos, FreeNeRF's test, is a poor
/// judge of it: the paper's networks at this size empty that scene at most seeds, with
/// RegNeRF or without.)
#[test]
fn reg_nerf_beats_the_plain_model_from_three_photos() {
    let dir = tempfile::tempdir().expect("tempdir");
    let data = dir.path().join("rug");
    rug_scene(&data, 48, 36);
    let train = |name: &str, regularisers: Regularisers| {
        // 300 steps on a short schedule (the measured figures below).
        let mut config = crate::common::short_schedule(crate::common::demo_config(&data, 300));
        config.train_views = Some(nerf::data::TrainViews::Spread { spread: 3 });
        let (losses, psnr) = train_vanilla(config, &dir.path().join(name), regularisers);
        (losses, psnr)
    };
    let (losses, reg) = train("reg", Regularisers::RegNerf);
    let (_, plain) = train("plain", Regularisers::None);
    eprintln!("rug from 3 photos, held-out views: {plain:.2} dB plain, {reg:.2} dB RegNeRF");
    assert_loss_halves(&losses);
    // Measured: 21.40 against 20.11 dB (400 steps decaying to a quarter: 21.40 against
    // 20.24).
    assert!(
        reg >= plain + 0.5,
        "RegNeRF {reg:.2} dB against {plain:.2} dB"
    );
}
