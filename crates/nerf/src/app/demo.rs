//! The demo pipeline (`nerf demo`): the built-in chair -> the fast model -> evaluation on
//! the test views -> an orbit video, all under one folder, no data needed; `--animate`
//! makes it a moving scene (the chair turning, trained as a field of space and time, the
//! orbit replaying the motion). Front ends show progress through [`DemoHooks`].

use std::path::PathBuf;
use std::time::Instant;

use crate::app::eval::EvalReport;
use crate::app::frames::{FrameProgress, FramesOptions, FramesReport};
use crate::data::synth::{self, SceneKind, SynthOptions};
use crate::data::{blender, Split};
use crate::error::{NerfError, Result};
use crate::train::folder::LoadedRun;
use crate::train::run::{self, Event, RunOptions, RunSummary, CHECKPOINT_FILE};
use crate::train::TrainConfig;

#[derive(Clone, Debug, clap::Args)]
pub struct DemoOptions {
    /// Folder for the scene and the run.
    #[arg(long, default_value = "demo")]
    pub out: PathBuf,
    /// Training steps of the fast model.
    #[arg(long, default_value_t = 1500)]
    pub steps: u64,
    /// Image size of the built-in scene.
    #[arg(long, default_value_t = 128)]
    pub size: usize,
    /// A moving scene: the chair turns a quarter turn over the capture, one photo per
    /// moment; the orbit video replays the motion.
    #[arg(long)]
    pub animate: bool,
    #[command(flatten)]
    pub device: crate::engine::DeviceArg,
}

/// What a front end hears while the demo runs.
pub trait DemoHooks: Sync {
    /// A line for the user.
    fn say(&self, line: &str);
    fn synth_progress(&self, done: usize, total: usize);
    fn train_event(&mut self, event: Event);
    fn eval_progress(&self, rays_done: usize, rays_total: usize);
    fn frames_progress(&self, progress: FrameProgress);
}

/// Where the demo put everything, and what it measured.
#[derive(Clone, Debug)]
pub struct DemoReport {
    pub scene: PathBuf,
    pub run: PathBuf,
    pub training: RunSummary,
    pub eval_dir: PathBuf,
    pub eval: EvalReport,
    pub orbit_dir: PathBuf,
    pub orbit: FramesReport,
    pub seconds: f64,
}

/// The built-in scene of the demo: the chair, 100 training and 20 test views, turning
/// when `animate`.
pub fn scene_options(size: usize, animate: bool) -> SynthOptions {
    SynthOptions {
        scene: SceneKind::Chair,
        size,
        train_views: 100,
        val_views: 4,
        test_views: 20,
        supersample: 2,
        seed: 0,
        animate,
    }
}

/// The fast model for `steps` steps, validating at full resolution every 500.
pub fn train_config(data: PathBuf, steps: u64) -> TrainConfig {
    let mut config = TrainConfig::fast(data);
    config.steps = steps;
    config.val_every = 500;
    config.val_downscale = 1;
    config.checkpoint_every = 500;
    config
}

/// Runs the demo (reusing the scene when it is already there; refusing to overwrite a
/// trained run).
pub fn run(opts: &DemoOptions, hooks: &mut dyn DemoHooks) -> Result<DemoReport> {
    let t0 = Instant::now();
    let scene = opts.out.join(if opts.animate {
        "chair_turning"
    } else {
        "chair"
    });
    if !blender::transforms_path(&scene, Split::Test).exists() {
        let synth = scene_options(opts.size, opts.animate);
        let n = synth::generate(&synth, &scene, &mut |done, total| {
            hooks.synth_progress(done, total)
        })?;
        hooks.say(&format!(
            "wrote {n} views of the chair ({0}x{0}) to {1}",
            opts.size,
            scene.display()
        ));
    } else {
        hooks.say(&format!("using the existing scene in {}", scene.display()));
    }
    let run_dir = opts
        .out
        .join(if opts.animate { "run_turning" } else { "run" });
    if run_dir.join(CHECKPOINT_FILE).exists() {
        return Err(NerfError::Config(format!(
            "{} already holds a trained run: delete it, or use `nerf eval --run {}`",
            run_dir.display(),
            run_dir.display()
        )));
    }
    hooks.say(&format!(
        "training the fast model (hash grid + occupancy grid, after Instant-NGP) for {} steps",
        opts.steps
    ));
    let mut config = train_config(scene.clone(), opts.steps);
    // The features `nerf train` would give the built-in chair on this device.
    let opened = config.open_scene(1)?;
    let facts = crate::train::defaults::SceneFacts {
        blender: opened.format == crate::data::scene::Format::Blender,
        space: opened.space,
        multiscale: 1,
        contract: opened.contract,
        train_views: opened.train.len(),
        moments: opened.moments(Split::Train).len(),
    };
    let flags = crate::train::defaults::Flags::default();
    let chosen = crate::train::defaults::decide(opts.device.device, &facts, &flags);
    for note in &chosen.notes {
        hooks.say(note);
    }
    if let crate::model::ModelConfig::Fast(m) = &mut config.model {
        let cameras = opened.cameras(Split::Train);
        chosen.apply_to(m, &cameras, &opened.space, cameras.len());
    }
    let run_options = RunOptions {
        out: run_dir.clone(),
        config,
        minutes: None,
        resume: false,
        pause_at: None,
        stop: None,
        device: opts.device.device,
    };
    let training = run::train(&run_options, &mut |e| hooks.train_event(e))?;
    let loaded = LoadedRun::open_on(&run_dir, opts.device.device)?;
    let eval_dir = run_dir.join("eval_test");
    let options = crate::app::eval::EvalOptions::new(Split::Test, 1);
    let eval = crate::app::eval::evaluate(&loaded, &options, &eval_dir, &|p| {
        if let crate::app::eval::EvalProgress::Rendering { rays, total } = p {
            hooks.eval_progress(rays, total)
        }
    })?;
    let orbit_dir = run_dir.join("render_orbit");
    let frames = FramesOptions {
        time_sweep: opts.animate,
        ..FramesOptions::orbit(36, 4.0, run_dir.join("orbit.gif"))
    };
    let orbit = crate::app::frames::render_frames(&loaded, &frames, &orbit_dir, &|p| {
        hooks.frames_progress(p)
    })?;
    Ok(DemoReport {
        scene,
        run: run_dir,
        training,
        eval_dir,
        eval,
        orbit_dir,
        orbit,
        seconds: t0.elapsed().as_secs_f64(),
    })
}
