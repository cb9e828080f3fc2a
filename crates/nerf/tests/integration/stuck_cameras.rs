//! Refinement's checks for stuck cameras (`train::stuck_cameras`): a camera given far off
//! is found and brought back by the pose search, a photo no pose explains is left out of
//! training, and a resumed run keeps it out.

use std::path::Path;

use crate::common::{cpu_run, fast_config};
use nerf::data::synth::{self, SceneKind, SynthOptions};
use nerf::model::camera_refine::{corrected, corrections, rotation, CameraRefinement, Frame};
use nerf::model::ModelConfig;
use nerf::train::folder::LoadedRun;
use nerf::train::run::{self, Event, RunOptions};

const VIEWS: usize = 40;
/// The camera given 25 degrees off (as a bad structure-from-motion pose would be).
const TURNED: usize = 7;
/// The camera whose photo is noise: no pose explains it.
const NOISE: usize = 21;

/// The built-in rug (a chair on a patterned rug: at a few dozen pixels the chair alone looks
/// alike from several sides) with camera [`TURNED`] turned 25 degrees about the scene's
/// vertical axis and photo [`NOISE`] replaced by noise; returns the true pose of the turned
/// camera.
fn damaged_scene(dir: &Path) -> nerf::camera::Pose {
    let opts = SynthOptions {
        scene: SceneKind::Rug,
        size: 48,
        train_views: VIEWS,
        val_views: 1,
        test_views: 2,
        supersample: 2,
        seed: 1,
        animate: false,
    };
    synth::generate(&opts, dir, &mut |_, _| {}).expect("synth");
    let path = dir.join("transforms_train.json");
    let mut scene: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&path).expect("read")).expect("json");
    let frame = &mut scene["frames"][TURNED];
    let matrix: Vec<Vec<f32>> =
        serde_json::from_value(frame["transform_matrix"].clone()).expect("matrix");
    let truth: nerf::camera::Pose = std::array::from_fn(|i| std::array::from_fn(|j| matrix[i][j]));
    let turn = rotation([0.0, 0.0, 25f32.to_radians()]);
    let turned: Vec<Vec<f32>> = (0..4)
        .map(|i| {
            (0..4)
                .map(|j| match i {
                    3 => matrix[3][j],
                    _ => (0..3).map(|m| turn[i][m] * matrix[m][j]).sum(),
                })
                .collect()
        })
        .collect();
    frame["transform_matrix"] = serde_json::to_value(turned).expect("value");
    std::fs::write(&path, serde_json::to_string(&scene).expect("text")).expect("write");
    let photo = dir.join(
        scene["frames"][NOISE]["file_path"]
            .as_str()
            .expect("file path")
            .to_string()
            + ".png",
    );
    let mut rng = nerf::rng::Rng::for_stream(9, 0, 0);
    let noise: Vec<f32> = (0..48 * 48 * 3).map(|_| rng.uniform()).collect();
    nerf::data::image::save_rgb_png(&photo, 48, 48, &noise).expect("png");
    truth
}

#[test]
fn a_camera_given_far_off_comes_back_and_a_photo_no_pose_explains_is_left_out() {
    let dir = tempfile::tempdir().expect("tempdir");
    let data = dir.path().join("rug");
    let truth = damaged_scene(&data);
    let mut config = fast_config(&data, 500);
    if let ModelConfig::Fast(m) = &mut config.model {
        // As `nerf train --refine-cameras` sets it up for a capture's poses.
        let mut refinement = CameraRefinement::new(VIEWS);
        refinement.frame = Frame::World;
        refinement.delay = nerf::model::camera_refine::SMALL_ERROR_DELAY;
        assert!(refinement.recover_stuck, "on by default");
        m.refine_cameras = Some(refinement);
    }
    let out = dir.path().join("run");
    let mut notes = Vec::new();
    let options = RunOptions {
        pause_at: Some(400),
        ..cpu_run(&out, config)
    };
    run::train(&options, &mut |e| match e {
        Event::Note(n) => notes.push(n.to_string()),
        Event::Warning(w) => notes.push(format!("warning: {w}")),
        _ => {}
    })
    .expect("train");
    let log = notes.join("\n");
    eprintln!("{log}");

    let loaded = LoadedRun::open(&out).expect("open");
    let params = loaded.engine.state().params;
    let fixes = corrections(loaded.engine.param_layout(), &params).expect("refined");
    let given = loaded.config.training_data().expect("data").views[TURNED]
        .camera
        .c2w;
    let found = corrected(&given, &fixes[6 * TURNED..6 * TURNED + 6], Frame::World);
    let off = nerf::data::poses::rotation_error_degrees(&found, &truth);
    eprintln!("camera {TURNED}: 25 degrees off as given, {off:.2} after training");
    assert!(
        off < 3.0,
        "camera {TURNED} is still {off} degrees off\n{log}"
    );
    assert!(
        log.contains(&format!("camera {TURNED} looks stuck")) && log.contains("turned it"),
        "{log}"
    );
    assert!(
        log.contains(&format!("warning: step 300: camera {NOISE} looks stuck"))
            && log.contains("left out"),
        "{log}"
    );

    // metrics.json records the checks; the resumed run keeps the photo out.
    let metrics = std::fs::read_to_string(out.join(run::METRICS_FILE)).expect("metrics");
    let left_out: Vec<u64> = metrics
        .lines()
        .filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok())
        .filter_map(|v| v.get("camera_check").cloned())
        .flat_map(|c| c["stuck"].as_array().cloned().unwrap_or_default())
        .filter(|s| s["left_out"] == true)
        .filter_map(|s| s["camera"].as_u64())
        .collect();
    assert_eq!(left_out, vec![NOISE as u64], "{metrics}");
    let resumed = RunOptions {
        resume: true,
        pause_at: None,
        ..cpu_run(&out, loaded.config.clone())
    };
    let mut notes = Vec::new();
    run::train(&resumed, &mut |e| {
        if let Event::Note(n) = e {
            notes.push(n.to_string());
        }
    })
    .expect("resume");
    assert!(
        notes
            .iter()
            .any(|n| n.contains(&format!("camera {NOISE} stays left out"))),
        "{notes:?}"
    );
}
