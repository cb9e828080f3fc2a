//! The `nerf` binary as a user runs it: every subcommand on a tiny scene, and clear errors.

use std::path::Path;
use std::process::{Command, Output};

use crate::common::{ok, synth_args, train_args};

fn nerf(args: &[&str], cwd: &Path) -> Output {
    Command::new(env!("CARGO_BIN_EXE_nerf"))
        .args(args)
        .current_dir(cwd)
        .output()
        .expect("run nerf")
}

/// The JSON file at `path` (a run's `metrics.json`, say), parsed.
fn read_json(path: &Path) -> serde_json::Value {
    let text = std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    serde_json::from_str(&text).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// `nerf points` on the run in `d/run`, using every `every`-th of its training views, which
/// must make two views.
fn points_from_two_views(d: &Path, every: &str, min_opacity: &str) {
    let args = [
        "points",
        "--run",
        "run",
        "--out",
        "p.ply",
        "--every",
        every,
        "--min-opacity",
        min_opacity,
    ];
    let text = ok(&nerf(&args, d));
    assert!(
        text.contains("points from 2 views") && d.join("p.ply").exists(),
        "{text}"
    );
}

#[test]
fn synth_train_eval_render() {
    let dir = tempfile::tempdir().expect("tempdir");
    let d = dir.path();
    ok(&nerf(&synth_args("table", ["10", "1", "4"]), d));
    assert!(
        d.join("scene/transforms_test.json").exists()
            && d.join("scene/train/r_9_depth.png").exists()
    );
    let text = ok(&nerf(
        &[
            "--threads",
            "2",
            "train",
            "--data",
            "scene",
            "--out",
            "run",
            "--preset",
            "demo",
            "--steps",
            "30",
            "--batch",
            "64",
            "--val-every",
            "10",
        ],
        d,
    ));
    assert!(
        text.contains("stopped after step 30 (all steps done)"),
        "{text}"
    );
    for f in [
        "config.json",
        "checkpoint.safetensors",
        "metrics.jsonl",
        "val/step_0000030.png",
    ] {
        assert!(d.join("run").join(f).exists(), "missing {f}");
    }
    // Resuming a finished run with a later target continues it.
    let text = ok(&nerf(
        &[
            "train", "--data", "scene", "--out", "run", "--resume", "--steps", "35",
        ],
        d,
    ));
    assert!(
        text.contains("resuming from the checkpoint at step 30")
            && text.contains("stopped after step 35"),
        "{text}"
    );
    let text = ok(&nerf(&["eval", "--run", "run", "--every", "2"], d));
    assert!(
        text.contains("2 views of test") && text.contains("mean PSNR"),
        "{text}"
    );
    let out = nerf(&["eval", "--run", "run", "--refine-test-poses"], d);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && err.contains("needs a fast-model run"),
        "{err}"
    );
    let metrics = read_json(&d.join("run/eval_test/metrics.json"));
    assert_eq!(metrics["views"].as_array().map(|v| v.len()), Some(2));
    assert!(metrics["mean_ssim"]
        .as_f64()
        .is_some_and(|s| s > 0.0 && s <= 1.0));
    ok(&nerf(
        &[
            "render", "--run", "run", "--path", "orbit", "--frames", "3", "--size", "12",
        ],
        d,
    ));
    assert!(
        d.join("run/render_orbit/frame_0002.png").exists()
            && d.join("run/render_orbit/frame_0002_depth.png").exists()
    );
    ok(&nerf(
        &[
            "render",
            "--run",
            "run",
            "--path",
            "test",
            "--out",
            "testviews",
        ],
        d,
    ));
    assert!(d.join("testviews/frame_0003.png").exists());
    // Geometry of the same run: a mesh and a point cloud.
    let text = ok(&nerf(
        &[
            "mesh",
            "--run",
            "run",
            "--out",
            "m.glb",
            "--resolution",
            "16",
            "--threshold",
            "0.05",
        ],
        d,
    ));
    assert!(
        text.contains("triangles") && d.join("m.glb").exists(),
        "{text}"
    );
    points_from_two_views(d, "5", "0.01");
}

#[test]
fn errors_name_the_file_and_exit_non_zero() {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = nerf(&["train", "--data", "nowhere", "--steps", "1"], dir.path());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(err.contains("nowhere: is not a folder"), "{err}");
    std::fs::create_dir(dir.path().join("empty")).expect("mkdir");
    let out = nerf(&["train", "--data", "empty", "--steps", "1"], dir.path());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(
        err.contains("empty: holds no scene") && err.contains("nerf capture"),
        "{err}"
    );
    let out = nerf(&["eval", "--run", "norun"], dir.path());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && err.contains("norun") && err.contains("not a run folder"),
        "{err}"
    );
    // The viewer refuses a missing run before it listens.
    let out = nerf(&["view", "--run", "norun", "--device", "cpu"], dir.path());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && err.contains("norun") && err.contains("not a run folder"),
        "{err}"
    );
    // A folder that exists but holds no run says so.
    let out = nerf(&["eval", "--run", "empty"], dir.path());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && err.contains("not a run folder (no config.json)"),
        "{err}"
    );
}

#[test]
fn train_help_lists_every_preset() {
    let dir = tempfile::tempdir().expect("tempdir");
    let help = ok(&nerf(&["train", "--help"], dir.path()));
    for p in nerf::presets::PRESETS {
        assert!(help.contains(p.name), "--help does not list {}", p.name);
    }
    assert!(help.contains("paper 31.01 dB"));
}

/// The fast model is the default and goes through the same train, resume, eval and render
/// commands; vanilla-only options are refused with a reason.
#[test]
fn fast_model_through_the_same_commands() {
    let dir = tempfile::tempdir().expect("tempdir");
    let d = dir.path();
    ok(&nerf(
        &[
            "synth",
            "--scene",
            "lamp",
            "--out",
            "scene",
            "--size",
            "16",
            "--train-views",
            "8",
            "--val-views",
            "1",
            "--test-views",
            "2",
        ],
        d,
    ));
    let fast = [
        "train",
        "--data",
        "scene",
        "--out",
        "run",
        "--steps",
        "20",
        "--samples",
        "2048",
        "--table-log2",
        "12",
        "--val-every",
        "10",
    ];
    let text = ok(&nerf(&fast, d));
    assert!(
        text.contains("training fast") && text.contains("stopped after step 20"),
        "{text}"
    );
    let config = std::fs::read_to_string(d.join("run/config.json")).expect("config");
    assert!(config.contains("\"kind\": \"fast\""), "{config}");
    assert!(d.join("run/val/step_0000020.png").exists());
    let text = ok(&nerf(
        &[
            "train", "--data", "scene", "--out", "run", "--resume", "--steps", "24",
        ],
        d,
    ));
    assert!(text.contains("stopped after step 24"), "{text}");
    let text = ok(&nerf(&["eval", "--run", "run"], d));
    assert!(text.contains("2 views of test"), "{text}");
    assert!(
        text.contains("LPIPS skipped: no --lpips-weights given"),
        "{text}"
    );
    // A multi-scale run, anti-aliased, evaluated per scale.
    let mut multiscale = fast.to_vec();
    multiscale[4] = "ms";
    multiscale.extend(["--multiscale", "2", "--antialias"]);
    let text = ok(&nerf(&multiscale, d));
    assert!(text.contains("stopped after step 20"), "{text}");
    let config = std::fs::read_to_string(d.join("ms/config.json")).expect("config");
    assert!(
        config.contains("\"multiscale\": 2") && config.contains("\"reference_footprint\""),
        "{config}"
    );
    let text = ok(&nerf(&["eval", "--run", "ms", "--multiscale", "2"], d));
    assert!(
        text.contains("scale 1/1 (16x16)") && text.contains("scale 1/2 (8x8)"),
        "{text}"
    );
    let metrics = read_json(&d.join("ms/eval_test/metrics.json"));
    let scales = metrics["scales"].as_array().expect("scales");
    assert_eq!(scales.len(), 2);
    assert_eq!(
        (scales[1]["scale"].as_u64(), scales[1]["width"].as_u64()),
        (Some(2), Some(8))
    );
    assert!(scales[1]["mean_psnr"].as_f64().is_some());
    assert!(d.join("ms/eval_test/001_d2.png").exists());
    // LPIPS weights that are not there: a clear error before any rendering.
    let out = nerf(
        &["eval", "--run", "ms", "--lpips-weights", "alex.safetensors"],
        d,
    );
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && err.contains("alex.safetensors"),
        "{err}"
    );
    // The test cameras fitted to the frozen model first, and said so.
    let text = ok(&nerf(
        &[
            "eval",
            "--run",
            "run",
            "--refine-test-poses",
            "4",
            "--out",
            "fitted",
        ],
        d,
    ));
    assert!(
        text.contains("test cameras fitted to the frozen model in 4 steps"),
        "{text}"
    );
    let metrics = read_json(&d.join("fitted/metrics.json"));
    assert_eq!(metrics["cameras"], "refined");
    assert_eq!(metrics["test_pose_refinement"]["steps"], 4);
    // A run that refined its cameras is evaluated with its test cameras fitted unless
    // told otherwise.
    let mut refined = fast.to_vec();
    refined[4] = "rf";
    refined.push("--refine-cameras");
    ok(&nerf(&refined, d));
    let text = ok(&nerf(&["eval", "--run", "rf", "--every", "2"], d));
    assert!(
        text.contains("fitted to the model first (200 steps; --no-refine-test-poses skips"),
        "{text}"
    );
    let metrics = read_json(&d.join("rf/eval_test/metrics.json"));
    assert_eq!(metrics["cameras"], "aligned+refined");
    assert_eq!(metrics["test_pose_refinement"]["steps"], 200);
    let text = ok(&nerf(
        &[
            "eval",
            "--run",
            "rf",
            "--every",
            "2",
            "--no-refine-test-poses",
            "--out",
            "as_given",
        ],
        d,
    ));
    assert!(!text.contains("fitted"), "{text}");
    let metrics = read_json(&d.join("as_given/metrics.json"));
    assert_eq!(metrics["cameras"], "aligned");
    assert!(metrics.get("test_pose_refinement").is_none(), "{metrics}");
    ok(&nerf(
        &[
            "render", "--run", "run", "--path", "orbit", "--frames", "2", "--size", "12",
        ],
        d,
    ));
    assert!(d.join("run/render_orbit/frame_0001_depth.png").exists());
    assert!(d.join("run/render_orbit/frame_0001_opacity.png").exists());
    // Videos: a GIF always, an MP4 when ffmpeg is installed (CI installs it).
    let text = ok(&nerf(
        &[
            "render", "--run", "run", "--frames", "3", "--size", "12", "--video", "o.gif",
        ],
        d,
    ));
    assert!(text.contains("video: o.gif"), "{text}");
    let gif = std::fs::read(d.join("o.gif")).expect("gif");
    assert!(gif.starts_with(b"GIF89a"));
    if nerf::app::video::ffmpeg_available() {
        ok(&nerf(
            &[
                "render", "--run", "run", "--frames", "3", "--size", "12", "--video", "o.mp4",
            ],
            d,
        ));
        let mp4 = std::fs::read(d.join("o.mp4")).expect("mp4");
        assert!(mp4.len() > 100 && &mp4[4..8] == b"ftyp", "not an MP4 file");
    } else {
        eprintln!("ffmpeg is not installed: skipping the MP4 check");
    }
    // The other camera paths.
    for path in ["spiral", "interpolate"] {
        ok(&nerf(
            &[
                "render", "--run", "run", "--path", path, "--frames", "2", "--size", "8",
            ],
            d,
        ));
        assert!(d.join(format!("run/render_{path}/frame_0001.png")).exists());
    }
    let json = r#"{"render_width": 10, "render_height": 6, "camera_path": [
        {"camera_to_world": [1,0,0,0, 0,0,-1,-4, 0,1,0,0.5, 0,0,0,1], "fov": 40, "aspect": 1.6667}]}"#;
    std::fs::write(d.join("camera_path.json"), json).expect("write");
    ok(&nerf(
        &[
            "render",
            "--run",
            "run",
            "--path",
            "file",
            "--camera-path",
            "camera_path.json",
        ],
        d,
    ));
    assert!(d.join("run/render_file/frame_0000.png").exists());
    let out = nerf(&["render", "--run", "run", "--video", "o.avi"], d);
    assert!(!out.status.success() && String::from_utf8_lossy(&out.stderr).contains("o.avi"));
    let out = nerf(&["mesh", "--run", "run", "--out", "m.stl"], d);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("m.stl"), "{err}");
    let out = nerf(
        &[
            "mesh",
            "--run",
            "run",
            "--out",
            "e.ply",
            "--resolution",
            "8",
            "--threshold",
            "1e30",
        ],
        d,
    );
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && err.contains("lower --threshold"),
        "{err}"
    );
    points_from_two_views(d, "4", "0.5");

    let out = nerf(
        &[
            "train", "--data", "scene", "--model", "fast", "--preset", "paper",
        ],
        d,
    );
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && err.contains("--preset paper"),
        "{err}"
    );
    let out = nerf(
        &["train", "--data", "scene", "--out", "r2", "--batch", "64"],
        d,
    );
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && err.contains("--model vanilla"),
        "{err}"
    );
}

/// A forward-facing LLFF scene goes through the same commands: `nerf scene` reports NDC,
/// `train` fits the box to the frusta, `eval` scores the held-out images, `render` flies
/// the spiral, and `mesh` comes back in world coordinates.
#[test]
fn llff_scene_through_the_same_commands() {
    let dir = tempfile::tempdir().expect("tempdir");
    let d = dir.path();
    ok(&nerf(
        &[
            "synth",
            "--layout",
            "llff",
            "--scene",
            "rug",
            "--size",
            "32",
            "--out",
            "ff",
            "--supersample",
            "1",
        ],
        d,
    ));
    assert!(d.join("ff/poses_bounds.npy").exists() && d.join("ff/images_2/000.png").exists());
    let info = ok(&nerf(&["scene", "--data", "ff"], d));
    assert!(
        info.contains("format: Llff")
            && info.contains("26 train, 4 val, 4 test")
            && info.contains("Ndc"),
        "{info}"
    );
    let spherified = ok(&nerf(&["scene", "--data", "ff", "--spherify"], d));
    assert!(
        spherified.contains("ray space: World") && spherified.contains("contracted"),
        "{spherified}"
    );
    ok(&nerf(
        &[
            "train",
            "--data",
            "ff",
            "--out",
            "run",
            "--steps",
            "100",
            "--samples",
            "4096",
            "--table-log2",
            "12",
            "--val-every",
            "10",
            "--device",
            "cpu",
        ],
        d,
    ));
    let config = std::fs::read_to_string(d.join("run/config.json")).expect("config");
    assert!(config.contains("\"holdout\": 8"), "{config}");
    // Forward-facing: the distortion loss against fog, by default, recorded in the run.
    assert!(config.contains("\"distortion\": 0.0001"), "{config}");
    let text = ok(&nerf(&["eval", "--run", "run"], d));
    assert!(text.contains("4 views of test"), "{text}");
    ok(&nerf(
        &[
            "render", "--run", "run", "--path", "spiral", "--frames", "2",
        ],
        d,
    ));
    assert!(d.join("run/render_spiral/frame_0001.png").exists());
    let mesh = ok(&nerf(
        &[
            "mesh",
            "--run",
            "run",
            "--out",
            "m.ply",
            "--resolution",
            "24",
            "--threshold",
            "5",
        ],
        d,
    ));
    assert!(mesh.contains("NDC space"), "{mesh}");
    // Forward-facing cameras refine too (corrected in the world, warped again),
    // and their test cameras are fitted at evaluation.
    let text = ok(&nerf(
        &[
            "train",
            "--data",
            "ff",
            "--out",
            "refined",
            "--steps",
            "30",
            "--samples",
            "4096",
            "--table-log2",
            "12",
            "--val-every",
            "0",
            "--refine-cameras",
        ],
        d,
    ));
    assert!(text.contains("stopped after step 30"), "{text}");
    let text = ok(&nerf(
        &["eval", "--run", "refined", "--refine-test-poses", "5"],
        d,
    ));
    assert!(
        text.contains("test cameras fitted to the frozen model in 5 steps")
            && text.contains("training cameras against the given poses"),
        "{text}"
    );
}

/// `--device`: `wgpu` trains both models on any adapter and says which; its checkpoint
/// renders with `--device cpu`; a device this build or machine lacks is a clear error.
#[test]
fn device_flag_trains_on_the_gpu_engine_and_names_missing_devices() {
    let dir = tempfile::tempdir().expect("tempdir");
    let d = dir.path();
    ok(&nerf(
        &[
            "synth",
            "--out",
            "scene",
            "--size",
            "12",
            "--train-views",
            "6",
            "--val-views",
            "1",
            "--test-views",
            "1",
        ],
        d,
    ));
    let train = |device: &str| {
        nerf(
            &[
                "train",
                "--data",
                "scene",
                "--out",
                "run",
                "--steps",
                "5",
                "--samples",
                "2048",
                "--table-log2",
                "12",
                "--device",
                device,
            ],
            d,
        )
    };
    // This build has no CUDA runtime (or this machine no CUDA GPU): said, with a way out.
    let out = train("cuda");
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && err.contains("CUDA") && err.contains("--device wgpu"),
        "{err}"
    );
    let out = train("wgpu");
    if !out.status.success() {
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains("no GPU adapter"), "{err}");
        eprintln!("skipping the GPU half of the test: {err}");
        return;
    }
    let text = ok(&out);
    assert!(text.contains("training on wgpu"), "{text}");
    let text = ok(&nerf(
        &[
            "render", "--run", "run", "--device", "cpu", "--frames", "2", "--size", "12",
        ],
        d,
    ));
    assert!(text.contains("2 frames"), "{text}");
    // The paper's model trains on the GPU engine too.
    let text = ok(&nerf(
        &[
            "train", "--data", "scene", "--out", "vrun", "--preset", "demo", "--steps", "2",
            "--batch", "64", "--device", "wgpu",
        ],
        d,
    ));
    assert!(text.contains("training on wgpu"), "{text}");
}

/// `--train-views` keeps the views it names (a list) or spreads a count over the split;
/// `nerf train` says which, the run's config keeps the choice, `metrics.json` records the
/// views, and a list naming a view past the split is refused by name.
#[test]
fn train_views_are_chosen_said_and_recorded() {
    let dir = tempfile::tempdir().expect("tempdir");
    let d = dir.path();
    ok(&nerf(&synth_args("table", ["9", "1", "1"]), d));
    let train = |views: &str, out: &str| nerf(&train_args(out, "2", &["--train-views", views]), d);
    let text = ok(&train("6,1", "listed"));
    assert!(
        text.contains("training on 2 of the 9 training views (--train-views 6,1): 1, 6"),
        "{text}"
    );
    let config = read_json(&d.join("listed/config.json"));
    assert_eq!(config["train_views"], serde_json::json!([6, 1]));
    ok(&nerf(&["eval", "--run", "listed"], d));
    let metrics = read_json(&d.join("listed/eval_test/metrics.json"));
    assert_eq!(metrics["train_views"], serde_json::json!([1, 6]));

    let text = ok(&train("3", "spread"));
    assert!(
        text.contains("training on 3 of the 9 training views (--train-views 3): 0, 4, 8"),
        "{text}"
    );
    assert_eq!(
        read_json(&d.join("spread/config.json"))["train_views"],
        serde_json::json!({"spread": 3})
    );

    let out = train("2,9", "past");
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "a view past the split was accepted");
    assert!(
        err.contains("view 9 is past the training split's 9 views"),
        "{err}"
    );
}
