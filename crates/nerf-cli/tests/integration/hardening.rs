//! The `nerf` binary under bad input, kills, full disks and concurrent runs, as a
//! new user met them. Each test names the defects it covers (#N); the scene-file defects
//! are tested in the library (`crates/nerf/tests/integration/scene_checks.rs`).

use std::path::Path;
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

use crate::common::{ok, synth_args, text, train_args};

fn cmd(args: &[&str], cwd: &Path) -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_nerf"));
    c.args(args)
        .current_dir(cwd)
        .env_remove("NERF_CHECK_FINITE");
    c
}

/// Runs `nerf`; a command that does not end within two minutes is a hang: killed, failed.
fn nerf(args: &[&str], cwd: &Path) -> Output {
    let child = cmd(args, cwd)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("run nerf");
    finish(child, Duration::from_secs(120), args)
}

fn finish(mut child: Child, limit: Duration, args: &[&str]) -> Output {
    let start = Instant::now();
    while child.try_wait().expect("wait").is_none() {
        if start.elapsed() > limit {
            let _ = child.kill();
            panic!("nerf {args:?} hung for {limit:?}");
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    child.wait_with_output().expect("output")
}

/// Fails with exit status 1 (an error, not a panic's 101 or an abort's 134) and says all
/// of `want`.
fn fails(out: &Output, want: &[&str]) -> String {
    let t = text(out);
    assert_eq!(out.status.code(), Some(1), "expected a clean error:\n{t}");
    for w in want {
        assert!(t.contains(w), "expected {w:?} in:\n{t}");
    }
    t
}

/// A 16-pixel built-in scene in `d/scene`.
fn scene(d: &Path) {
    ok(&nerf(&synth_args("lamp", ["6", "1", "2"]), d));
}

fn trained(d: &Path) {
    scene(d);
    ok(&nerf(&train_args("run", "6", &[]), d));
}

fn wait_for(what: &str, limit: Duration, mut done: impl FnMut() -> bool) {
    let start = Instant::now();
    while !done() {
        assert!(start.elapsed() < limit, "timed out waiting for {what}");
        std::thread::sleep(Duration::from_millis(50));
    }
}

fn metric_steps(run: &Path) -> Vec<u64> {
    std::fs::read_to_string(run.join("metrics.jsonl"))
        .unwrap_or_default()
        .lines()
        .filter(|l| !l.contains("val_psnr"))
        .filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok()?["step"].as_u64())
        .collect()
}

/// #2 and #3: a second writer into a run folder is refused, naming the holder; a reader
/// (`eval`) of the run being trained still works; SIGINT and SIGTERM finish the step,
/// write a checkpoint, say how to resume and exit 130 / 143; the resumed run continues
/// from that checkpoint.
#[test]
#[cfg(unix)]
fn one_writer_per_run_and_interrupts_leave_a_checkpoint() {
    let dir = tempfile::tempdir().expect("tempdir");
    let d = dir.path();
    scene(d);
    for (signal, code) in [("-INT", 130), ("-TERM", 143)] {
        let run = d.join("run");
        let _ = std::fs::remove_dir_all(&run);
        let args = train_args("run", "1000000", &["--checkpoint-every", "2"]);
        let first = cmd(&args, d)
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .expect("spawn");
        let ckpt = run.join("checkpoint.safetensors");
        wait_for("a first checkpoint", Duration::from_secs(120), || {
            ckpt.exists()
        });

        let second = nerf(&train_args("run", "10", &[]), d);
        fails(&second, &["in use", &first.id().to_string()]);
        ok(&nerf(&["eval", "--run", "run"], d));

        let status = Command::new("kill")
            .args([signal, &first.id().to_string()])
            .status()
            .expect("kill");
        assert!(status.success());
        let out = finish(first, Duration::from_secs(60), &args);
        let t = text(&out);
        assert_eq!(out.status.code(), Some(code), "{signal}:\n{t}");
        assert!(
            t.contains("interrupted by") && t.contains("--resume"),
            "{t}"
        );
        let at = *metric_steps(&run).last().expect("steps were logged");
        let saved = nerf::checkpoint::read_step(&ckpt).expect("checkpoint");
        assert_eq!(saved, at, "the checkpoint holds the last step done");

        // The command the interruption suggested, as printed (no --data needed).
        let steps = (at + 2).to_string();
        let t = ok(&nerf(
            &["train", "--out", "run", "--resume", "--steps", &steps],
            d,
        ));
        assert!(
            t.contains(&format!("resuming from the checkpoint at step {at}")),
            "{t}"
        );
        assert_eq!(*metric_steps(&run).last().expect("steps"), at + 2);
    }
}

/// #3: a run that stopped before its first checkpoint starts again from step 0 with fresh
/// metrics, with or without --resume.
#[test]
fn a_run_without_a_checkpoint_restarts_cleanly() {
    let dir = tempfile::tempdir().expect("tempdir");
    let d = dir.path();
    trained(d);
    for resume in [&["--resume"][..], &[]] {
        std::fs::remove_file(d.join("run/checkpoint.safetensors")).expect("rm");
        let t = ok(&nerf(&train_args("run", "4", resume), d));
        assert!(t.contains("starting it again from step 0"), "{t}");
        assert_eq!(metric_steps(&d.join("run")), vec![1, 2, 3, 4], "{t}");
    }
}

/// #4: a full disk: every written PNG fails loudly, naming the file (the temporary file
/// of a frame is made a link to `/dev/full`, where writes fail with ENOSPC).
#[test]
#[cfg(unix)]
fn a_full_disk_fails_the_render() {
    if !Path::new("/dev/full").exists() {
        eprintln!("skipping: /dev/full is absent");
        return;
    }
    let dir = tempfile::tempdir().expect("tempdir");
    let d = dir.path();
    trained(d);
    let frames = d.join("run/render_orbit");
    std::fs::create_dir_all(&frames).expect("mkdir");
    std::os::unix::fs::symlink("/dev/full", frames.join("frame_0001.png.tmp")).expect("link");
    let out = nerf(
        &["render", "--run", "run", "--frames", "2", "--size", "8"],
        d,
    );
    let t = fails(&out, &["frame_0001.png", "No space left"]);
    assert!(!t.contains("rendered 2 frames"), "{t}");
}

/// #5: a config edited to nonsense is refused by every command that reads it, quickly.
#[test]
fn an_edited_config_is_validated_by_every_command() {
    let dir = tempfile::tempdir().expect("tempdir");
    let d = dir.path();
    trained(d);
    let path = d.join("run/config.json");
    let good = std::fs::read_to_string(&path).expect("config");
    let edits = [
        ("bound", "/model/field/bound", -3.0),
        ("bound", "/model/field/bound", 0.0),
        ("chunk_rays", "/chunk_rays", 0.0),
        ("downscale", "/downscale", 0.0),
    ];
    for (field, pointer, value) in edits {
        let mut c: serde_json::Value = serde_json::from_str(&good).expect("json");
        let v = c.pointer_mut(pointer).expect("the field exists");
        *v = if v.is_u64() { 0.into() } else { value.into() };
        std::fs::write(&path, c.to_string()).expect("write");
        for args in [
            &["eval", "--run", "run"][..],
            &["render", "--run", "run", "--frames", "1"],
            &["points", "--run", "run", "--out", "p.ply"],
            &["mesh", "--run", "run", "--out", "m.ply"],
        ] {
            fails(&nerf(args, d), &["config.json", field]);
        }
    }
}

/// #6: NaN weights and a flipped bit in a checkpoint are refused by eval and by --resume,
/// naming the tensor and the file.
#[test]
fn corrupt_weights_are_named() {
    let dir = tempfile::tempdir().expect("tempdir");
    let d = dir.path();
    trained(d);
    let ckpt = d.join("run/checkpoint.safetensors");
    let good = std::fs::read(&ckpt).expect("read");
    // Flip a bit in the middle of the tensor data (the header is at the front).
    let mut bad = good.clone();
    let at = bad.len() - bad.len() / 3;
    bad[at] ^= 0x10;
    std::fs::write(&ckpt, &bad).expect("write");
    for args in [
        &["eval", "--run", "run"][..],
        &train_args("run", "8", &["--resume"]),
    ] {
        fails(
            &nerf(args, d),
            &["checkpoint.safetensors", "corrupt", "tensor `"],
        );
    }

    std::fs::write(&ckpt, &good).expect("write");
    let mut run = nerf::train::run::LoadedRun::open(&d.join("run")).expect("open");
    let mut state = run.engine.state();
    let last = state.params.len() - 1;
    state.params[last] = f32::NAN;
    run.engine.set_state(state).expect("set");
    nerf::train::folder::save_checkpoint(&ckpt, run.engine.as_ref(), run.step, 0, 1.0)
        .expect("save");
    for args in [
        &["eval", "--run", "run"][..],
        &train_args("run", "8", &["--resume"]),
    ] {
        fails(
            &nerf(args, d),
            &["checkpoint.safetensors", "non-finite", "tensor `"],
        );
    }
}

/// #7 and #8: absurd sizes and budgets are refused up front with the limit, never an
/// abort or a run of 0 steps.
#[test]
fn absurd_sizes_and_budgets_are_refused() {
    let dir = tempfile::tempdir().expect("tempdir");
    let d = dir.path();
    scene(d);
    let t = fails(
        &nerf(&["train", "--data", "scene", "--table-log2", "40"], d),
        &["table_log2 40", "GiB"],
    );
    assert!(!t.contains("memory allocation"), "{t}");
    fails(
        &nerf(&["bench", "--table-log2", "40"], d),
        &["table_log2 40", "GiB"],
    );
    fails(
        &nerf(&["bench", "--render-size", "200000"], d),
        &["--render-size", "larger than the limit"],
    );
    for bad in [
        &["--minutes", "0"][..],
        &["--minutes=-1"],
        &["--minutes", "NaN"],
        &["--steps", "0"],
    ] {
        let mut args = vec!["train", "--data", "scene", "--out", "r"];
        args.extend_from_slice(bad);
        let out = nerf(&args, d);
        assert_eq!(out.status.code(), Some(2), "{bad:?}: {}", text(&out));
        assert!(!d.join("r").exists(), "{bad:?} must not start a run");
    }
}

/// #11 and #23: --camera-path with another --path, and --path test without a test split.
#[test]
fn render_refuses_what_it_would_ignore() {
    let dir = tempfile::tempdir().expect("tempdir");
    let d = dir.path();
    trained(d);
    std::fs::write(d.join("path.json"), r#"{"camera_path": []}"#).expect("write");
    fails(
        &nerf(
            &[
                "render",
                "--run",
                "run",
                "--path",
                "orbit",
                "--camera-path",
                "path.json",
            ],
            d,
        ),
        &["--camera-path", "--path file"],
    );
    fails(
        &nerf(
            &[
                "render",
                "--run",
                "run",
                "--path",
                "file",
                "--camera-path",
                "path.json",
            ],
            d,
        ),
        &["path.json", "empty"],
    );
    std::fs::remove_file(d.join("scene/transforms_test.json")).expect("rm");
    fails(
        &nerf(&["render", "--run", "run", "--path", "test"], d),
        &["no test split"],
    );
}

/// #13: causes said once, missing fields named, --out naming a file, and --resume with
/// options that contradict the run.
#[test]
fn messages_say_what_is_wrong_once() {
    let dir = tempfile::tempdir().expect("tempdir");
    let d = dir.path();
    trained(d);
    let t = fails(&nerf(&["scene", "--data", "nowhere"], d), &["nowhere"]);
    assert!(t.matches("os error").count() <= 1, "{t}");

    std::fs::write(d.join("file"), "x").expect("write");
    fails(
        &nerf(&train_args("file", "2", &[]), d),
        &["--out", "file", "not a run folder"],
    );

    let t = fails(
        &nerf(
            &train_args("run", "8", &["--resume", "--lr", "0.5", "--seed", "3"]),
            d,
        ),
        &["--lr 0.5", "--seed 3", "config.json"],
    );
    assert!(!t.contains("--steps"), "{t}");
    fails(
        &nerf(&train_args("run", "3", &["--resume"]), d),
        &["--steps 3", "step the run's checkpoint is at (6)"],
    );

    let blender = d.join("scene/transforms_train.json");
    let mut doc: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&blender).expect("read")).expect("json");
    doc.as_object_mut().expect("object").remove("frames");
    std::fs::write(&blender, doc.to_string()).expect("write");
    let t = fails(
        &nerf(&["scene", "--data", "scene"], d),
        &["transforms_train.json", "missing field `frames`"],
    );
    assert!(!t.contains("malformed"), "{t}");
}

/// #14: the end of training leads with the validation PSNR and the next command; the
/// validation lines reach a log that is not a terminal.
#[test]
fn the_end_of_training_says_what_matters() {
    let dir = tempfile::tempdir().expect("tempdir");
    let d = dir.path();
    scene(d);
    let t = ok(&nerf(&train_args("run", "6", &[]), d));
    assert!(t.contains("step 6: validation PSNR"), "{t}");
    assert!(
        t.contains("latest validation PSNR") && t.contains("(step 6)") && !t.contains("last batch"),
        "{t}"
    );
    assert!(t.contains("nerf eval --run run"), "{t}");
    let mut args = train_args("run2", "2", &[]);
    let at = args.iter().position(|a| *a == "--val-every").expect("flag");
    args[at + 1] = "0";
    let t = ok(&nerf(&args, d));
    assert!(t.contains("no validation image"), "{t}");
}

/// #24: `nerf bench --json` prints JSON alone on stdout. The built-in chair is bounded: no
/// distortion loss unless asked for (forward-facing scenes get it, as in `nerf train`).
#[test]
fn bench_json_is_json() {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = nerf(
        &[
            "--threads",
            "2",
            "bench",
            "--json",
            "--steps",
            "1",
            "--warmup-steps",
            "1",
            "--samples",
            "1024",
            "--table-log2",
            "10",
            "--render-size",
            "8",
        ],
        dir.path(),
    );
    let t = ok(&out);
    let v: serde_json::Value =
        serde_json::from_slice(&out.stdout).unwrap_or_else(|e| panic!("not JSON ({e}):\n{t}"));
    assert!(v.is_object(), "{t}");
    assert_eq!(v["distortion"].as_f64(), Some(0.0), "{t}");
    // The stage clocks ran: the step's stages in the order it runs them, each timed.
    let stages: Vec<(String, f64)> = v["stages"]
        .as_array()
        .unwrap_or_else(|| panic!("no stages:\n{t}"))
        .iter()
        .map(|s| {
            let name = s["stage"].as_str().unwrap_or_default().to_string();
            (name, s["seconds"].as_f64().unwrap_or(-1.0))
        })
        .collect();
    let names: Vec<&str> = stages.iter().map(|(n, _)| n.as_str()).collect();
    let mut order = names.iter();
    for stage in [
        "marching",
        "hash grid",
        "networks",
        "compositing + loss",
        "networks backward",
        "hash grid backward",
        "Adam",
        "the rest",
    ] {
        assert!(
            order.any(|n| *n == stage),
            "{stage} missing or out of order in {names:?}"
        );
    }
    assert!(
        stages.iter().all(|(n, s)| *s > 0.0 || n == "the rest"),
        "{stages:?}"
    );
}

/// The debug switch: NERF_CHECK_FINITE=1 names the stage, step and buffer of the first
/// non-finite value, where a plain run only learns that the step diverged.
#[test]
fn check_finite_names_the_stage() {
    let dir = tempfile::tempdir().expect("tempdir");
    let d = dir.path();
    scene(d);
    // A learning rate so large that the first update overflows the weights.
    let args = train_args("run", "5", &["--lr", "1e38"]);
    // Without the switch: the step is refused, and the message says what was not finite.
    let plain = fails(&nerf(&args, d), &["training diverged at step 2"]);
    assert!(
        plain.contains("the loss is NaN") || plain.contains("gradients hold non-finite"),
        "{plain}"
    );
    assert!(!plain.contains("NERF_CHECK_FINITE"), "{plain}");
    let _ = std::fs::remove_dir_all(d.join("run"));
    let checked = cmd(&args, d)
        .env("NERF_CHECK_FINITE", "1")
        .output()
        .expect("run");
    fails(
        &checked,
        &[
            "adam produced a non-finite value at step 1",
            "parameters[",
            "NERF_CHECK_FINITE",
        ],
    );
}

/// Beyond the list: every number option refuses NaN, infinity and values outside its range
/// (clap's exit 2, the option named), where they used to render garbage or nothing.
#[test]
fn numbers_that_make_no_sense_are_refused() {
    let dir = tempfile::tempdir().expect("tempdir");
    let d = dir.path();
    for (args, option) in [
        (&["render", "--run", "r", "--fps", "0"][..], "--fps"),
        (&["render", "--run", "r", "--fps", "NaN"], "--fps"),
        (
            &["render", "--run", "r", "--elevation", "NaN"],
            "--elevation",
        ),
        (&["render", "--run", "r", "--radius", "-1"], "--radius"),
        (
            &["render", "--run", "r", "--depth-range", "1,inf"],
            "--depth-range",
        ),
        (
            &[
                "points",
                "--run",
                "r",
                "--out",
                "p.ply",
                "--min-opacity",
                "NaN",
            ],
            "--min-opacity",
        ),
        (
            &["mesh", "--run", "r", "--out", "m.ply", "--threshold", "NaN"],
            "--threshold",
        ),
        (&["train", "--data", "s", "--lr", "-1"], "--lr"),
        (&["train", "--data", "s", "--bound", "inf"], "--bound"),
        (
            &["capture", "--video", "v.mp4", "--out", "s", "--fps", "0"],
            "--fps",
        ),
    ] {
        let out = nerf(args, d);
        let t = text(&out);
        assert_eq!(out.status.code(), Some(2), "{args:?}: {t}");
        assert!(t.contains(option), "{args:?}: {t}");
    }
}

/// A run folder used from another directory, after the run and its scene moved together,
/// and after the scene is gone: the scene is named relative to the run when it sits
/// beside it; rendering needs only the run; evaluation, which reads the photos, names
/// every place it looked and `--data`, which then finds the scene anywhere.
#[test]
fn run_folders_work_from_anywhere_and_after_moving() {
    let dir = tempfile::tempdir().expect("tempdir");
    let home = dir.path().join("home");
    std::fs::create_dir_all(&home).expect("mkdir");
    trained(&home);
    let config: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(home.join("run/config.json")).expect("config"),
    )
    .expect("json");
    assert_eq!(config["data"], "../scene", "stored beside the run");
    assert!(
        home.join("run/scene.json").is_file(),
        "the run keeps its cameras"
    );

    // From another directory, by an absolute path and by a relative one.
    let elsewhere = dir.path();
    let run = home.join("run");
    let run = run.to_str().expect("utf-8");
    ok(&nerf(&["eval", "--run", run, "--every", "2"], elsewhere));
    ok(&nerf(
        &[
            "render", "--run", "home/run", "--frames", "1", "--size", "8",
        ],
        elsewhere,
    ));

    // The run and its scene moved together.
    let moved = dir.path().join("moved");
    std::fs::rename(&home, &moved).expect("move");
    ok(&nerf(&["eval", "--run", "run", "--every", "2"], &moved));

    // The scene gone: rendering and the cameras from the run alone, and said.
    let away = dir.path().join("scene_elsewhere");
    std::fs::rename(moved.join("scene"), &away).expect("move the scene");
    let t = ok(&nerf(
        &["render", "--run", "run", "--frames", "1", "--size", "8"],
        &moved,
    ));
    assert!(t.contains("not found") && t.contains("scene.json"), "{t}");
    ok(&nerf(
        &["export-cameras", "--run", "run", "--out", "cams.json"],
        &moved,
    ));
    let t = fails(
        &nerf(&["eval", "--run", "run"], &moved),
        &["not found", "looked in", "--data"],
    );
    assert!(t.contains("scene"), "{t}");
    let away = away.to_str().expect("utf-8");
    ok(&nerf(
        &["eval", "--run", "run", "--every", "2", "--data", away],
        &moved,
    ));
    fails(
        &nerf(
            &["eval", "--run", "run", "--data", "no/such/folder"],
            &moved,
        ),
        &["no/such/folder", "not a folder"],
    );
}
