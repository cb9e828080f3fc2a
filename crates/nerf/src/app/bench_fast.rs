//! `nerf bench --model fast`: throughput of the fast model's training step (samples, rays
//! and hash-grid lookups per second), the cost of an occupancy-grid refresh, the time to
//! render a whole view, and peak memory.
//!
//! The model first trains `warmup_steps` so the occupancy grid has carved out empty space:
//! a fresh grid marks everything occupied, which would time a sampling pattern no real run
//! spends its time in.

use std::path::PathBuf;
use std::time::Instant;

use serde::Serialize;

use crate::app::bench_vanilla::{median, peak_resident_mib};
use crate::camera::Camera;
use crate::data::scene::{Scene, SceneOptions};
use crate::data::synth::{self, SceneKind, SynthOptions};
use crate::data::Split;
use crate::error::{NerfError, Result};
use crate::model::{FastModelConfig, ModelConfig};
use crate::step_clock;
use crate::train::{TrainConfig, Trainer};
use crate::views::{render_view, RenderSettings};

#[derive(Clone, Debug)]
pub struct FastBenchOptions {
    /// A scene to train on (any format, read with its default options: LLFF in NDC); the
    /// built-in chair when `None`.
    pub data: Option<PathBuf>,
    pub warmup_steps: u64,
    /// Timed steps (at least 16, so that refreshes are among them).
    pub steps: usize,
    /// Size of the rendered view (square) when the scene has no test camera of its own.
    pub render_size: usize,
    pub model: FastModelConfig,
    /// Anti-alias (the reference footprint from the training cameras); `None`: as `nerf
    /// train` would (on the CPU engine, but not in NDC).
    pub antialias: Option<bool>,
    /// Weight of the distortion loss; `None`: as `nerf train` would (forward-facing NDC
    /// scenes on the CPU engine get it).
    pub distortion: Option<f32>,
    /// The networks' products in bfloat16; `None`: as `nerf train` would (on the CPU
    /// engine where the CPU has AVX-512 BF16).
    pub bf16: Option<bool>,
    pub device: crate::engine::Device,
}

#[derive(Clone, Debug, Serialize)]
pub struct FastBenchReport {
    pub threads: usize,
    /// The engine and its device (`cpu, 2 threads`, `wgpu/vulkan: ...`).
    pub engine: String,
    pub scene: String,
    pub antialias: bool,
    /// Weight of the distortion loss the model trained with (0: none).
    pub distortion: f32,
    /// Whether the networks' products ran in bfloat16.
    pub bf16_products: bool,
    pub warmup_steps: u64,
    pub samples_per_step: usize,
    pub rays_per_step_median: f64,
    /// A step without an occupancy refresh.
    pub step_seconds_median: f64,
    /// A step with a refresh.
    pub refresh_step_seconds_median: f64,
    /// Average over a refresh period.
    pub step_seconds_amortised: f64,
    pub train_samples_per_second: f64,
    pub train_rays_per_second: f64,
    /// Table corners read (forward) and written (backward) per second.
    pub hash_lookups_per_second: f64,
    pub occupied_fraction: f64,
    /// Fraction of gradient blocks a step wrote (reduction and Adam skip the rest).
    pub touched_fraction: f64,
    pub render_width: usize,
    pub render_height: usize,
    pub render_seconds: f64,
    pub render_rays_per_second: f64,
    pub peak_resident_mib: f64,
    /// Where the time of a step without a refresh goes, stage by stage (see
    /// [`StageTime`]), in the order a step runs them; the rest of the step last.
    pub stages: Vec<StageTime>,
}

/// One stage's share of a training step.
#[derive(Clone, Debug, Serialize)]
pub struct StageTime {
    pub stage: String,
    /// Mean wall time per step. Stages the CPU engine runs inside its workers are
    /// measured in thread time and divided by the threads (they run side by side); on the
    /// GPU engine each stage ends when the device has done its work.
    pub seconds: f64,
    /// Its fraction of the mean step (the steps timed stage by stage).
    pub share: f64,
}

pub fn run(opts: &FastBenchOptions, say: &mut dyn FnMut(String)) -> Result<FastBenchReport> {
    let threads = rayon::current_num_threads();
    // Refuse what cannot run before minutes of scene loading.
    let mut probe = TrainConfig::fast("(in memory)".into());
    probe.model = ModelConfig::Fast(opts.model.clone());
    probe.validate()?;
    crate::camera::check_image_size(opts.render_size, opts.render_size)
        .map_err(|m| NerfError::Config(format!("--render-size: {m}")))?;
    let mut model = opts.model.clone();
    let (data, scene, camera, blender) = match &opts.data {
        Some(dir) => {
            say(format!("loading {}...", dir.display()));
            let scene = Scene::open(dir, &SceneOptions::default(), 1)?;
            model.field.bound = scene.bound;
            model.contract = scene.contract;
            let train = scene.load(Split::Train, 1)?;
            let camera = scene.cameras(Split::Test).into_iter().next();
            let blender = scene.format == crate::data::scene::Format::Blender;
            (train, dir.display().to_string(), camera, blender)
        }
        None => {
            say("rendering the built-in chair to train on (100x100, 40 views)...".into());
            let synth_opts = SynthOptions {
                scene: SceneKind::Chair,
                size: 100,
                supersample: 1,
                ..Default::default()
            };
            (
                synth::dataset(&synth_opts, Split::Train, 40),
                "built-in chair".into(),
                None,
                true,
            )
        }
    };
    let camera = camera.unwrap_or_else(|| {
        Camera::from_fov_x(
            opts.render_size,
            opts.render_size,
            synth::FOV_X,
            crate::camera::look_at([0.0, -4.0, 1.5], [0.0; 3], [0.0, 0.0, 1.0]),
        )
    });
    // The step `nerf train` would take on this scene and device, less the per-photo
    // corrections (the bench measures the field's step).
    use crate::train::defaults::{self, Choice};
    let flags = defaults::Flags {
        antialias: match opts.antialias {
            Some(true) => Choice::On(()),
            Some(false) => Choice::Off,
            None => Choice::Default,
        },
        appearance: Choice::Off,
        refine_cameras: Choice::Off,
        distortion: opts.distortion.map_or(Choice::Default, Choice::On),
        few_view: Choice::Default,
        dynamic: Choice::Default,
        time_smoothness: Choice::Default,
        time_cells: None,
        depth_smoothness: Choice::Default,
        bf16: match opts.bf16 {
            Some(true) => Choice::On(()),
            Some(false) => Choice::Off,
            None => Choice::Default,
        },
    };
    let facts = defaults::SceneFacts {
        blender,
        space: data.space,
        multiscale: 1,
        contract: model.contract,
        train_views: data.views.len(),
        moments: crate::data::time::moments(data.views.iter().filter_map(|v| v.time)).len(),
    };
    let chosen = defaults::decide(opts.device, &facts, &flags);
    for note in &chosen.notes {
        say(note.clone());
    }
    let antialias = chosen.antialias;
    let cameras: Vec<Camera> = data.views.iter().map(|v| v.camera.clone()).collect();
    chosen.apply_to(&mut model, &cameras, &data.space, cameras.len());
    let mut config = TrainConfig::fast("(in memory)".into());
    let distortion = model.distortion;
    let bf16_products = model.bf16_products;
    config.model = ModelConfig::Fast(model);
    // Warm-up, the timed steps (a refresh among them) and the clocked ones.
    let every = opts.model.occupancy.update_every.max(1);
    config.steps = opts.warmup_steps + 2 * (opts.steps as u64).max(every);
    let mut trainer = Trainer::on(opts.device, config, data)?;
    say(format!("engine: {}", trainer.engine.describe()));
    say(format!(
        "training {} warm-up steps so the occupancy grid takes shape...",
        opts.warmup_steps
    ));
    for _ in 0..opts.warmup_steps {
        trainer.step()?;
    }
    let (mut plain, mut refresh, mut rays) = (Vec::new(), Vec::new(), Vec::new());
    for k in 0..opts.steps.max(every as usize) {
        let t = Instant::now();
        let s = trainer.step()?;
        let dt = t.elapsed().as_secs_f64();
        rays.push(s.rays as f64);
        if s.step % every == 0 {
            refresh.push(dt);
        } else {
            plain.push(dt);
        }
        if k % 8 == 7 {
            say(format!("  step {}: {:.3} s, {} rays", s.step, dt, s.rays));
        }
    }
    let rays_median = median(rays);
    // The stage clocks run over steps of their own, after the timed ones: on the GPU a
    // stage ends when the device has done its work, and those waits would slow the timed
    // steps. Steps with a refresh are left out (its density queries would count as the
    // networks' and the hash grid's time), unless every step refreshes.
    let per_worker = match trainer.engine.kind() {
        crate::engine::caps::EngineKind::Cpu => threads as f64,
        _ => 1.0,
    };
    step_clock::reset();
    let mut clocked = Vec::new();
    while clocked.len() < opts.steps.max(1) {
        let timed = every == 1 || (trainer.step + 1) % every != 0;
        step_clock::enable(timed);
        let t = Instant::now();
        let s = trainer.step();
        let dt = t.elapsed().as_secs_f64();
        step_clock::enable(false);
        s?;
        if timed {
            clocked.push(dt);
        }
    }
    let stages = stage_times(
        clocked.iter().sum::<f64>() / clocked.len() as f64,
        clocked.len(),
        per_worker,
    );
    let step_s = median(plain);
    let refresh_s = median(refresh);
    let amortised = ((every - 1) as f64 * step_s + refresh_s) / every as f64;
    let samples = opts.model.samples_per_step as f64;
    let levels = opts.model.field.grid.levels as f64;
    let occupied = trainer.engine.occupancy().unwrap_or(1.0);
    say(format!(
        "rendering a {}x{} view...",
        camera.width, camera.height
    ));
    let settings = RenderSettings::of_dataset(&trainer.data, [1.0; 3]);
    let t = Instant::now();
    render_view(trainer.engine.as_ref(), &camera, &settings, &|_| {});
    let render_s = t.elapsed().as_secs_f64();
    Ok(FastBenchReport {
        threads,
        scene,
        antialias,
        distortion,
        bf16_products,
        warmup_steps: opts.warmup_steps,
        samples_per_step: opts.model.samples_per_step,
        rays_per_step_median: rays_median,
        step_seconds_median: step_s,
        refresh_step_seconds_median: refresh_s,
        step_seconds_amortised: amortised,
        train_samples_per_second: samples / step_s,
        train_rays_per_second: rays_median / step_s,
        hash_lookups_per_second: 2.0 * 8.0 * levels * samples / step_s,
        occupied_fraction: occupied,
        touched_fraction: trainer.engine.touched_fraction(),
        engine: trainer.engine.describe(),
        render_width: camera.width,
        render_height: camera.height,
        render_seconds: render_s,
        render_rays_per_second: (camera.width * camera.height) as f64 / render_s,
        peak_resident_mib: peak_resident_mib(),
        stages,
    })
}

/// The stage clocks' figures over `steps` steps of `mean_step` seconds on average;
/// `workers`: what to divide the per-worker stages' thread time by.
fn stage_times(mean_step: f64, steps: usize, workers: f64) -> Vec<StageTime> {
    let steps = steps.max(1) as f64;
    let mut out: Vec<StageTime> = step_clock::read()
        .into_iter()
        .filter(|(_, d)| !d.is_zero())
        .map(|(stage, d)| {
            let divisor = if stage.per_worker() { workers } else { 1.0 };
            let seconds = d.as_secs_f64() / steps / divisor;
            StageTime {
                stage: stage.name().to_string(),
                seconds,
                share: seconds / mean_step,
            }
        })
        .collect();
    let rest = mean_step - out.iter().map(|s| s.seconds).sum::<f64>();
    out.push(StageTime {
        stage: "the rest".into(),
        seconds: rest.max(0.0),
        share: rest.max(0.0) / mean_step,
    });
    out
}
