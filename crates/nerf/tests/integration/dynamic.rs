//! Moving scenes: the built-in chair turning over the capture, one photo per moment, and
//! the fast model's field of space and time against a still field.

use nerf::data::synth::{self, SceneKind, SynthOptions};
use nerf::encoding::space_time_grid::SpaceTimeConfig;
use nerf::model::ModelConfig;
use nerf::train::folder::LoadedRun;
use nerf::train::run;

use crate::common::{cpu_run, eval_test, fast_config};

const SIZE: usize = 48;
const STEPS: u64 = 500;

/// The chair, turning (`animate`) or still, 40 training photos and 6 held-out ones (at
/// moments between the training photos' when it turns).
fn scene(dir: &std::path::Path, animate: bool) {
    let opts = SynthOptions {
        scene: SceneKind::Chair,
        size: SIZE,
        train_views: 40,
        val_views: 1,
        test_views: 6,
        supersample: 2,
        seed: 2,
        animate,
    };
    synth::generate(&opts, dir, &mut |_, _| {}).expect("synth");
}

/// Trains `data` for [`STEPS`] with a field of space and time or a still one; the test
/// split's mean PSNR.
fn psnr(data: &std::path::Path, out: &std::path::Path, dynamic: bool) -> f64 {
    let mut config = fast_config(data, STEPS);
    if let ModelConfig::Fast(m) = &mut config.model {
        m.field.motion = dynamic.then_some(SpaceTimeConfig {
            log2_table_size: 15,
            ..SpaceTimeConfig::default()
        });
    }
    run::train(&cpu_run(out, config), &mut |_| {}).expect("train");
    let loaded = LoadedRun::open(out).expect("open run");
    f64::from(eval_test(&loaded, 1, &out.join("eval")).mean_psnr)
}

/// On moments no training photo shows, the field of space and time renders the chair
/// where it has turned to; a still field averages the turn into a blur. On a still chair
/// the moving field costs next to nothing.
#[test]
fn a_field_of_space_and_time_follows_the_motion_and_costs_little_when_still() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (turning, still) = (dir.path().join("turning"), dir.path().join("still"));
    scene(&turning, true);
    scene(&still, false);
    let opened = nerf::data::scene::Scene::open(&turning, &Default::default(), 1)
        .expect("open the turning chair");
    assert!(opened.is_dynamic());
    let moving = psnr(&turning, &dir.path().join("moving"), true);
    let blurred = psnr(&turning, &dir.path().join("blurred"), false);
    eprintln!(
        "turning chair, held-out moments: {moving:.2} dB moving field, {blurred:.2} dB still"
    );
    assert!(
        moving >= blurred + 3.0,
        "moving field {moving:.2} dB against still {blurred:.2} dB"
    );
    let moving_on_still = psnr(&still, &dir.path().join("moving_on_still"), true);
    let still_on_still = psnr(&still, &dir.path().join("still_on_still"), false);
    eprintln!("still chair: {moving_on_still:.2} dB moving field, {still_on_still:.2} dB still");
    assert!(
        moving_on_still >= still_on_still - 0.5,
        "moving field {moving_on_still:.2} dB against still {still_on_still:.2} dB"
    );
}
