//! One function per subcommand: parse-free glue between the arguments and the library.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context, Result};
use clap::{Args, ValueEnum};
use nerf::camera::{Camera, Pose};
use nerf::data::scene::{Convention, Format, SceneOptions};
use nerf::data::synth::{self, SceneKind, SynthOptions};
use nerf::data::{blender, image::save_rgb_png, Background, Split};
use nerf::model::ModelConfig;
use nerf::train::run::{self, Event, LoadedRun, RunOptions, StopReason};
use nerf::train::TrainConfig;

use crate::progress::bar;

#[derive(Clone, Copy, ValueEnum)]
pub enum SceneArg {
    Chair,
    Table,
    Lamp,
    /// The chair on a patterned rug: texture for `nerf capture` (structure from motion).
    Rug,
}

impl SceneArg {
    fn kind(self) -> SceneKind {
        match self {
            SceneArg::Chair => SceneKind::Chair,
            SceneArg::Table => SceneKind::Table,
            SceneArg::Lamp => SceneKind::Lamp,
            SceneArg::Rug => SceneKind::Rug,
        }
    }
}

#[derive(Args)]
pub struct SynthArgs {
    /// Which piece of furniture.
    #[arg(long, value_enum, default_value = "chair")]
    scene: SceneArg,
    /// Output folder (Blender format: transforms_*.json + train/ val/ test/).
    #[arg(long)]
    out: PathBuf,
    /// `blender`: 360-degree views in Blender format. `llff`: a forward-facing capture
    /// (a 5 x 6 grid of cameras in front of the object, 4:3 images) in LLFF format, trained
    /// in NDC space.
    #[arg(long, value_enum, default_value = "blender")]
    layout: LayoutArg,
    /// Image size in pixels (square; the width for --layout llff).
    #[arg(long, default_value_t = 100)]
    size: usize,
    #[arg(long, default_value_t = 100)]
    train_views: usize,
    #[arg(long, default_value_t = 10)]
    val_views: usize,
    #[arg(long, default_value_t = 40)]
    test_views: usize,
    /// Anti-aliasing: rays per pixel along each axis.
    #[arg(long, default_value_t = 2)]
    supersample: usize,
    #[arg(long, default_value_t = 0)]
    seed: u64,
}

#[derive(Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum LayoutArg {
    Blender,
    Llff,
}

pub fn synth(a: SynthArgs) -> Result<()> {
    if a.layout == LayoutArg::Llff {
        let cameras = synth::llff::forward_facing_cameras(a.size, a.size * 3 / 4, 5, 6);
        let pb = bar(
            cameras.len() as u64,
            &format!("synth {} (LLFF)", a.scene.kind().name()),
        );
        let t0 = Instant::now();
        synth::llff::write(
            a.scene.kind(),
            &cameras,
            a.supersample,
            &nerf::data::poses::Similarity::IDENTITY,
            &a.out,
            &mut |done, _| pb.set_position(done as u64),
        )?;
        pb.finish_and_clear();
        println!(
            "wrote {} forward-facing views (LLFF) to {} in {:.1} s",
            cameras.len(),
            a.out.display(),
            t0.elapsed().as_secs_f64()
        );
        return Ok(());
    }
    let opts = SynthOptions {
        scene: a.scene.kind(),
        size: a.size,
        train_views: a.train_views,
        val_views: a.val_views,
        test_views: a.test_views,
        supersample: a.supersample,
        seed: a.seed,
    };
    synth_into(&opts, &a.out)
}

fn synth_into(opts: &SynthOptions, out: &Path) -> Result<()> {
    let total = (opts.train_views + opts.val_views + opts.test_views) as u64;
    let pb = bar(total, &format!("synth {}", opts.scene.name()));
    let t0 = Instant::now();
    let n = synth::generate(opts, out, &mut |done, _| pb.set_position(done as u64))?;
    pb.finish_and_clear();
    println!(
        "wrote {n} views of the {} ({}x{}) to {} in {:.1} s",
        opts.scene.name(),
        opts.size,
        opts.size,
        out.display(),
        t0.elapsed().as_secs_f64()
    );
    Ok(())
}

#[derive(Clone, Copy, ValueEnum)]
pub enum BackgroundArg {
    White,
    Black,
    Random,
}

#[derive(Args)]
pub struct TrainArgs {
    /// Scene folder: Blender (transforms_train.json), instant-ngp / nerfstudio
    /// (transforms.json), LLFF (poses_bounds.npy + images/) or COLMAP (sparse/0 + images/).
    #[arg(long)]
    data: PathBuf,
    #[command(flatten)]
    scene: SceneArgs,
    /// Fast: half-extent of the scene box [-B, B]^3 the hash grid covers, in scene units
    /// after the format's placement. Default: from the scene (Blender 1.5, NDC 1,
    /// instant-ngp aabb_scale / 2, COLMAP from its points).
    #[arg(long)]
    bound: Option<f32>,
    /// Fast: keep the whole scene in the box instead of contracting the space beyond its
    /// inner half (contraction is the default for 360-degree real captures: LLFF
    /// --spherify and COLMAP).
    #[arg(long)]
    no_contract: bool,
    /// Run folder (config.json, checkpoint, metrics.jsonl, val/). Default: runs/<scene>-<preset>.
    #[arg(long)]
    out: Option<PathBuf>,
    /// Which model: `fast` (hash grid + occupancy grid, minutes) or `vanilla` (the paper's
    /// MLPs, days). Default: fast, or vanilla when --preset is given.
    #[arg(long, value_enum)]
    model: Option<ModelArg>,
    /// Vanilla model configuration: the paper's, one of its ablations, or a reduced demo
    /// model (implies --model vanilla; default paper).
    #[arg(long, value_parser = crate::preset_values())]
    preset: Option<String>,
    /// Steps to train (the learning rate decays 10x over them). Default: 5000 fast,
    /// 200000 vanilla.
    #[arg(long)]
    steps: Option<u64>,
    /// Wall-clock budget in minutes: stop (with a checkpoint) when it runs out.
    #[arg(long)]
    minutes: Option<f64>,
    /// Vanilla: rays per step (default 1024; paper: 4096).
    #[arg(long)]
    batch: Option<usize>,
    /// Fast: field samples per step; the number of rays adapts (default 65536).
    #[arg(long)]
    samples: Option<usize>,
    /// Fast: log2 of the hash-table entries per level (default 19).
    #[arg(long)]
    table_log2: Option<u32>,
    /// Initial learning rate (default 1e-2 fast, 5e-4 vanilla).
    #[arg(long)]
    lr: Option<f32>,
    /// Background behind transparent pixels; random = a new colour per ray while training.
    /// Default: random for fast, white for vanilla.
    #[arg(long, value_enum)]
    background: Option<BackgroundArg>,
    /// Area-average downscale factor of the images.
    #[arg(long, default_value_t = 1)]
    downscale: usize,
    /// Steps of central-crop warm-up (rays from the central half of each image). Default:
    /// 0 fast, 500 vanilla.
    #[arg(long)]
    precrop_steps: Option<u64>,
    /// Use the paper's printed positional encoding (sin(2^k pi p), no identity term).
    #[arg(long)]
    paper_pe: bool,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Render a validation image every N steps (0: never). Default: 500 fast, 1000 vanilla.
    #[arg(long)]
    val_every: Option<u64>,
    /// Save a checkpoint every N steps.
    #[arg(long, default_value_t = 500)]
    checkpoint_every: u64,
    /// Rays per work unit per thread (vanilla memory: about 10 KB x 192 samples per ray).
    /// Default: 1024 fast, 64 vanilla.
    #[arg(long)]
    chunk: Option<usize>,
    /// Continue the run in --out from its last checkpoint.
    #[arg(long)]
    resume: bool,
    /// Stop this session after step N with a checkpoint (the learning-rate schedule still
    /// spans --steps); continue later with --resume.
    #[arg(long)]
    pause_at: Option<u64>,
}

/// How to read real captures.
#[derive(Args, Clone)]
pub struct SceneArgs {
    /// Read the scene as this format instead of detecting it.
    #[arg(long, value_enum)]
    format: Option<FormatArg>,
    /// LLFF: the capture circles the object (inward-facing 360); train in world space
    /// centred on what the cameras look at, not in NDC.
    #[arg(long)]
    spherify: bool,
    /// LLFF: train a forward-facing scene in world space instead of NDC.
    #[arg(long, conflicts_with = "spherify")]
    no_ndc: bool,
    /// Real captures: hold out every N-th image for testing (the paper's LLFF setting: 8).
    #[arg(long, default_value_t = 8, value_parser = clap::value_parser!(u64).range(2..))]
    holdout: u64,
    /// transforms.json: whose world placement to follow (auto: instant-ngp when the file
    /// has aabb_scale, scale or offset, else nerfstudio).
    #[arg(long, value_enum, default_value = "auto")]
    convention: ConventionArg,
}

#[derive(Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum FormatArg {
    Blender,
    Transforms,
    Llff,
    Colmap,
}

#[derive(Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum ConventionArg {
    Auto,
    Ngp,
    Nerfstudio,
}

impl SceneArgs {
    pub fn options(&self) -> SceneOptions {
        SceneOptions {
            format: self.format.map(|f| match f {
                FormatArg::Blender => Format::Blender,
                FormatArg::Transforms => Format::Transforms,
                FormatArg::Llff => Format::Llff,
                FormatArg::Colmap => Format::Colmap,
            }),
            spherify: self.spherify,
            ndc: self.no_ndc.then_some(false),
            holdout: self.holdout as usize,
            convention: match self.convention {
                ConventionArg::Auto => Convention::Auto,
                ConventionArg::Ngp => Convention::Ngp,
                ConventionArg::Nerfstudio => Convention::Nerfstudio,
            },
        }
    }
}

#[derive(Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum ModelArg {
    Fast,
    Vanilla,
}

impl TrainArgs {
    fn model(&self) -> Result<ModelArg> {
        match (self.model, &self.preset) {
            (Some(ModelArg::Fast), Some(p)) => {
                bail!("--preset {p} names a vanilla configuration; drop it or use --model vanilla")
            }
            (Some(m), _) => Ok(m),
            (None, Some(_)) => Ok(ModelArg::Vanilla),
            (None, None) => Ok(ModelArg::Fast),
        }
    }

    /// Name for the default run folder.
    fn label(&self) -> Result<String> {
        Ok(match self.model()? {
            ModelArg::Fast => "fast".into(),
            ModelArg::Vanilla => self.preset.clone().unwrap_or_else(|| "paper".into()),
        })
    }

    fn config(&self) -> Result<TrainConfig> {
        // Absolute, so `eval` and `render` find the scene from any working directory.
        let data = std::fs::canonicalize(&self.data).unwrap_or_else(|_| self.data.clone());
        let mut c = match self.model()? {
            ModelArg::Fast => TrainConfig::fast(data),
            ModelArg::Vanilla => {
                TrainConfig::from_preset(data, self.preset.as_deref().unwrap_or("paper"))?
            }
        };
        match &mut c.model {
            ModelConfig::Vanilla(m) => {
                m.net.position_encoding.paper_form = self.paper_pe;
                if let Some(d) = &mut m.net.direction_encoding {
                    d.paper_form = self.paper_pe;
                }
                if self.samples.is_some() || self.table_log2.is_some() {
                    bail!("--samples and --table-log2 apply to --model fast only");
                }
            }
            ModelConfig::Fast(m) => {
                if self.batch.is_some() || self.paper_pe {
                    bail!("--batch and --paper-pe apply to --model vanilla only");
                }
                m.samples_per_step = self.samples.unwrap_or(m.samples_per_step);
                m.field.grid.log2_table_size =
                    self.table_log2.unwrap_or(m.field.grid.log2_table_size);
            }
        }
        c.steps = self.steps.unwrap_or(c.steps);
        c.batch_rays = self.batch.unwrap_or(c.batch_rays);
        if let Some(lr) = self.lr {
            c.lr_final *= lr / c.lr_init;
            c.lr_init = lr;
        }
        if let Some(b) = self.background {
            c.background = match b {
                BackgroundArg::White => Background::White,
                BackgroundArg::Black => Background::Black,
                BackgroundArg::Random => Background::Random,
            };
        }
        c.downscale = self.downscale;
        c.scene = self.scene.options();
        let scene = c.open_scene(1)?;
        if let Some(w) = scene.warning() {
            eprintln!("warning: {w}");
        }
        match &mut c.model {
            ModelConfig::Fast(m) => {
                m.field.bound = self.bound.unwrap_or(scene.bound);
                m.contract = scene.contract && !self.no_contract;
            }
            ModelConfig::Vanilla(_) if self.bound.is_some() || self.no_contract => {
                bail!("--bound and --no-contract apply to --model fast only")
            }
            ModelConfig::Vanilla(_) => {}
        }
        c.precrop_steps = self.precrop_steps.unwrap_or(c.precrop_steps);
        c.seed = self.seed;
        c.val_every = self.val_every.unwrap_or(c.val_every);
        c.checkpoint_every = self.checkpoint_every;
        c.chunk_rays = self.chunk.unwrap_or(c.chunk_rays);
        Ok(c)
    }
}

pub fn train(a: TrainArgs) -> Result<()> {
    let out = a
        .out
        .clone()
        .unwrap_or_else(|| crate::default_run(&a.data, &a.label().unwrap_or_default()));
    if a.resume {
        if let Some(steps) = a.steps {
            // A new target for a resumed run: record it so the schedule and later resumes agree.
            let path = out.join(run::CONFIG_FILE);
            let mut c: TrainConfig = nerf::io::read_json(&path)?;
            c.steps = steps;
            nerf::io::write_json(&path, &c)?;
        }
    }
    let opts = RunOptions {
        out: out.clone(),
        config: a.config()?,
        minutes: a.minutes,
        resume: a.resume,
        pause_at: a.pause_at,
    };
    let summary = train_with_progress(&opts)?;
    let why = match summary.reason {
        StopReason::Steps => "all steps done".to_string(),
        StopReason::TimeBudget => format!("the {} minute budget ran out", a.minutes.unwrap_or(0.0)),
        StopReason::Paused => format!(
            "paused at step {}; continue with --resume",
            a.pause_at.unwrap_or(0)
        ),
    };
    println!(
        "stopped after step {} ({why}); {:.1} s of training; last batch PSNR {:.2} dB; checkpoint in {}",
        summary.steps,
        summary.seconds,
        summary.last_psnr,
        out.join(run::CHECKPOINT_FILE).display()
    );
    Ok(())
}

fn train_with_progress(opts: &RunOptions) -> Result<run::RunSummary> {
    let mut pb = None;
    let mut last = (Instant::now(), 0u64);
    let mut rays_per_s = 0.0;
    let mut rays_since = 0usize;
    let mut last_line = Instant::now();
    let summary = run::train(opts, &mut |event| match event {
        Event::Started {
            config,
            views,
            width,
            height,
            params,
            resumed_from,
        } => {
            println!(
                "training {} on {} ({views} views, {width}x{height}): {}{}, {params} parameters",
                config.preset,
                config.data.display(),
                config.model.describe(),
                match config.model {
                    ModelConfig::Vanilla(_) => format!(", {} rays/step", config.batch_rays),
                    ModelConfig::Fast(_) => String::new(),
                }
            );
            if let Some(step) = resumed_from {
                println!("resuming from the checkpoint at step {step}");
            }
            let p = bar(config.steps, "train");
            p.set_position(resumed_from.unwrap_or(0));
            p.reset_eta();
            last = (Instant::now(), resumed_from.unwrap_or(0));
            pb = Some(p);
        }
        Event::Step(s) => {
            if let Some(p) = &pb {
                let dt = last.0.elapsed().as_secs_f64();
                rays_since += s.rays;
                if dt > 1.0 || s.step == last.1 + 1 {
                    rays_per_s = rays_since as f64 / dt.max(1e-9);
                    rays_since = 0;
                    last = (Instant::now(), s.step);
                }
                p.set_position(s.step);
                p.set_message(format!(
                    "loss {:.4} psnr {:.2} {:.0} rays/s",
                    s.loss, s.psnr, rays_per_s
                ));
                // Without a terminal (logs, CI) the bar is hidden: print a line now and then.
                if p.is_hidden() && last_line.elapsed().as_secs_f64() >= 30.0 {
                    println!(
                        "step {}: loss {:.4}, batch PSNR {:.2} dB, {:.0} rays/s",
                        s.step, s.loss, s.psnr, rays_per_s
                    );
                    last_line = Instant::now();
                }
            }
        }
        Event::Validation { step, psnr, image } => {
            if let Some(p) = &pb {
                p.println(format!(
                    "step {step}: validation PSNR {psnr:.2} dB ({})",
                    image.display()
                ));
            }
        }
        Event::Checkpoint { .. } => {}
    });
    if let Some(p) = &pb {
        p.finish_and_clear();
    }
    Ok(summary?)
}

#[derive(Clone, Copy, ValueEnum)]
pub enum SplitArg {
    Train,
    Val,
    Test,
}

impl SplitArg {
    fn split(self) -> Split {
        match self {
            SplitArg::Train => Split::Train,
            SplitArg::Val => Split::Val,
            SplitArg::Test => Split::Test,
        }
    }
}

#[derive(Args)]
pub struct EvalArgs {
    /// Run folder written by `nerf train`.
    #[arg(long)]
    run: PathBuf,
    #[arg(long, value_enum, default_value = "test")]
    split: SplitArg,
    /// Evaluate every K-th view only (quick checks).
    #[arg(long, default_value_t = 1)]
    every: usize,
    /// Output folder for images and metrics.json. Default: <run>/eval_<split>.
    #[arg(long)]
    out: Option<PathBuf>,
}

pub fn eval(a: EvalArgs) -> Result<()> {
    let run = LoadedRun::open(&a.run)?;
    let split = a.split.split();
    let out = a
        .out
        .unwrap_or_else(|| a.run.join(format!("eval_{}", split.name())));
    eval_run(&run, split, a.every, &out)
}

fn eval_run(run: &LoadedRun, split: Split, every: usize, out: &Path) -> Result<()> {
    let pb = bar(0, &format!("eval {} rays", split.name()));
    let report = nerf::eval::evaluate(run, split, every, out, &|done, total| {
        pb.set_length(total as u64);
        pb.set_position(done as u64);
    })?;
    pb.finish_and_clear();
    for v in &report.views {
        println!(
            "  view {:3}  PSNR {:6.2} dB  SSIM {:.4}",
            v.index, v.psnr, v.ssim
        );
    }
    println!(
        "{} views of {} at step {} ({}x{}): mean PSNR {:.2} dB, mean SSIM {:.4}; images and metrics.json in {}",
        report.views.len(),
        split.name(),
        report.step,
        report.width,
        report.height,
        report.mean_psnr,
        report.mean_ssim,
        out.display()
    );
    Ok(())
}

#[derive(Clone, Copy, ValueEnum)]
pub enum PathArg {
    /// The test split's cameras.
    Test,
    /// A circle around the object, like the paper's videos.
    Orbit,
    /// A spiral in front of the average training camera (forward-facing scenes, LLFF style).
    Spiral,
    /// A smooth loop through the training cameras.
    Interpolate,
    /// The cameras of a nerfstudio camera_path.json (--camera-path).
    File,
}

#[derive(Args)]
pub struct RenderArgs {
    /// Run folder written by `nerf train`.
    #[arg(long)]
    run: PathBuf,
    #[arg(long, value_enum, default_value = "orbit")]
    path: PathArg,
    /// Frames of an orbit, spiral or interpolated path.
    #[arg(long, default_value_t = 40)]
    frames: usize,
    /// nerfstudio camera_path.json to render with `--path file`.
    #[arg(long)]
    camera_path: Option<PathBuf>,
    /// Orbit elevation in degrees.
    #[arg(long, default_value_t = 30.0)]
    elevation: f32,
    /// Orbit radius in scene units (default: the training cameras' mean distance from the
    /// scene centre).
    #[arg(long)]
    radius: Option<f32>,
    /// Output size: the width for generated paths (the height keeps the scene's aspect
    /// ratio), the height for --path file (default: the training resolution, or the
    /// file's).
    #[arg(long)]
    size: Option<usize>,
    /// Output folder for the PNG frames (RGB, turbo depth, opacity). Default:
    /// <run>/render_<path>.
    #[arg(long)]
    out: Option<PathBuf>,
    /// Also write the RGB frames as a video: .gif (built in) or .mp4 (H.264 through
    /// ffmpeg, which must be on PATH).
    #[arg(long)]
    video: Option<PathBuf>,
    /// Frames per second of the video.
    #[arg(long, default_value_t = 24.0)]
    fps: f32,
    /// Fixed depth range NEAR,FAR for the colour map (default: the first frame's 2nd-98th
    /// percentile of opaque pixels, kept for all frames).
    #[arg(long, value_parser = parse_range)]
    depth_range: Option<(f32, f32)>,
}

fn parse_range(s: &str) -> std::result::Result<(f32, f32), String> {
    let (a, b) = s
        .split_once(',')
        .ok_or_else(|| format!("{s:?}: expected NEAR,FAR such as 2.5,5"))?;
    let (a, b): (f32, f32) = (
        a.trim().parse().map_err(|e| format!("{a:?}: {e}"))?,
        b.trim().parse().map_err(|e| format!("{b:?}: {e}"))?,
    );
    if a.is_nan() || b.is_nan() || a >= b {
        return Err(format!("{s:?}: NEAR must be less than FAR"));
    }
    Ok((a, b))
}

pub fn render(a: RenderArgs) -> Result<()> {
    let run = LoadedRun::open(&a.run)?;
    let name = match a.path {
        PathArg::Test => "test",
        PathArg::Orbit => "orbit",
        PathArg::Spiral => "spiral",
        PathArg::Interpolate => "interpolate",
        PathArg::File => "file",
    };
    let out = a
        .out
        .clone()
        .unwrap_or_else(|| a.run.join(format!("render_{name}")));
    render_run(&run, &a, &out)
}

fn render_run(run: &LoadedRun, a: &RenderArgs, out: &Path) -> Result<()> {
    let cfg = &run.config;
    let scene = cfg.open_scene(1)?;
    let cameras: Vec<Camera> = match a.path {
        PathArg::Test => scene.cameras(Split::Test),
        PathArg::File => {
            let file = a
                .camera_path
                .as_ref()
                .context("--path file needs --camera-path FILE")?;
            nerf::camera_path::load_camera_path(file, a.size)?
        }
        PathArg::Orbit | PathArg::Spiral | PathArg::Interpolate => {
            let train = scene.cameras(Split::Train);
            let reference = train.first().context("the scene has no training views")?;
            let poses: Vec<Pose> = train.iter().map(|c| c.c2w).collect();
            let frames = a.frames.max(1);
            let path = match a.path {
                PathArg::Spiral => nerf::camera_path::spiral(&poses, frames, 2.0),
                PathArg::Interpolate => nerf::camera_path::interpolate(&poses, 8, frames),
                _ => {
                    let mean_distance = poses
                        .iter()
                        .map(|p| nerf::math::length([p[0][3], p[1][3], p[2][3]]))
                        .sum::<f32>()
                        / poses.len() as f32;
                    let radius = a.radius.unwrap_or(mean_distance);
                    nerf::camera::orbit(frames, radius, a.elevation.to_radians())
                }
            };
            let template = match a.size {
                Some(width) => resized(reference, width),
                None => reference.clone(),
            };
            path.into_iter()
                .map(|c2w| Camera {
                    c2w,
                    ..template.clone()
                })
                .collect()
        }
    };
    let video = a
        .video
        .as_ref()
        .map(|v| {
            let ext = v.extension().map(|e| e.to_string_lossy().to_ascii_lowercase());
            match ext.as_deref() {
                Some("gif") => Ok((v.clone(), false)),
                Some("mp4") if nerf::video::ffmpeg_available() => Ok((v.clone(), true)),
                Some("mp4") => {
                    let gif = v.with_extension("gif");
                    eprintln!(
                        "ffmpeg is not on PATH (Debian: apt-get install ffmpeg): writing {} instead of {}",
                        gif.display(),
                        v.display()
                    );
                    Ok((gif, false))
                }
                _ => bail!("{}: choose a .gif or .mp4 video file", v.display()),
            }
        })
        .transpose()?;
    nerf::io::create_dir(out)?;
    let settings = nerf::views::RenderSettings::of_scene(&scene, cfg.background.eval_colour());
    let rays: usize = cameras.iter().map(|c| c.width * c.height).sum();
    let pb = bar(rays as u64, "render rays");
    let t0 = Instant::now();
    let mut done = 0;
    let mut depth_range = a.depth_range;
    let mut frames = Vec::new();
    for (k, cam) in cameras.iter().enumerate() {
        pb.set_message(format!(
            "frame {}/{}, {:.2} frames/s",
            k + 1,
            cameras.len(),
            k as f64 / t0.elapsed().as_secs_f64().max(1e-9)
        ));
        let r = nerf::views::render_view(run.engine.as_ref(), cam, &settings, &|n| {
            pb.set_position((done + n) as u64)
        });
        done += cam.width * cam.height;
        save_rgb_png(
            &out.join(format!("frame_{k:04}.png")),
            r.width,
            r.height,
            &r.rgb,
        )?;
        let (near, far) = *depth_range.get_or_insert_with(|| {
            nerf::video::auto_depth_range(&r.depth, &r.opacity)
                .unwrap_or((settings.near, settings.far))
        });
        save_rgb_png(
            &out.join(format!("frame_{k:04}_depth.png")),
            r.width,
            r.height,
            &nerf::video::depth_turbo(&r.depth, &r.opacity, near, far),
        )?;
        let opacity: Vec<f32> = r.opacity.iter().flat_map(|&o| [o; 3]).collect();
        save_rgb_png(
            &out.join(format!("frame_{k:04}_opacity.png")),
            r.width,
            r.height,
            &opacity,
        )?;
        if matches!(video, Some((_, false))) {
            frames.push(r.rgb);
        }
    }
    pb.finish_and_clear();
    if let Some((path, mp4)) = video {
        if mp4 {
            nerf::video::write_mp4(&out.join("frame_%04d.png"), &path, a.fps)?;
        } else if let Some(c) = cameras.first() {
            nerf::video::write_gif(&path, c.width, c.height, &frames, a.fps)?;
        }
        println!("video: {}", path.display());
    }
    let secs = t0.elapsed().as_secs_f64();
    println!(
        "rendered {} frames in {:.1} s ({:.2} frames/s) to {}",
        cameras.len(),
        secs,
        cameras.len() as f64 / secs,
        out.display()
    );
    Ok(())
}

/// `camera`'s pinhole view (no lens distortion: rendered views are ideal) at `width`
/// pixels across, keeping its field of view and aspect ratio.
fn resized(camera: &Camera, width: usize) -> Camera {
    let s = width as f32 / camera.width as f32;
    Camera {
        width,
        height: ((camera.height as f32 * s).round() as usize).max(1),
        fx: camera.fx * s,
        fy: camera.fy * s,
        cx: camera.cx * s,
        cy: camera.cy * s,
        c2w: camera.c2w,
        distortion: Default::default(),
    }
}

#[derive(Args)]
pub struct DemoArgs {
    /// Folder for the scene and the run.
    #[arg(long, default_value = "demo")]
    out: PathBuf,
    /// Training steps of the fast model.
    #[arg(long, default_value_t = 1500)]
    steps: u64,
    /// Image size of the built-in scene.
    #[arg(long, default_value_t = 128)]
    size: usize,
}

pub fn demo(a: DemoArgs) -> Result<()> {
    let t0 = Instant::now();
    let data = a.out.join("chair");
    if !blender::transforms_path(&data, Split::Test).exists() {
        let opts = SynthOptions {
            scene: SceneKind::Chair,
            size: a.size,
            train_views: 100,
            val_views: 4,
            test_views: 20,
            supersample: 2,
            seed: 0,
        };
        synth_into(&opts, &data)?;
    } else {
        println!("using the existing scene in {}", data.display());
    }
    let run_dir = a.out.join("run");
    if run_dir.join(run::CHECKPOINT_FILE).exists() {
        bail!(
            "{} already holds a trained run: delete it, or use `nerf eval --run {}`",
            run_dir.display(),
            run_dir.display()
        );
    }
    let mut config = TrainConfig::fast(data.clone());
    config.steps = a.steps;
    config.val_every = 500;
    config.val_downscale = 1;
    config.checkpoint_every = 500;
    println!(
        "training the fast model (hash grid + occupancy grid, after Instant-NGP) for {} steps",
        config.steps
    );
    let opts = RunOptions {
        out: run_dir.clone(),
        config,
        minutes: None,
        resume: false,
        pause_at: None,
    };
    let summary = train_with_progress(&opts)?;
    println!(
        "trained {} steps in {:.1} s",
        summary.steps, summary.seconds
    );
    let run = LoadedRun::open(&run_dir)?;
    let eval_dir = run_dir.join("eval_test");
    eval_run(&run, Split::Test, 1, &eval_dir)?;
    let orbit = RenderArgs {
        run: run_dir.clone(),
        path: PathArg::Orbit,
        frames: 36,
        elevation: 30.0,
        radius: Some(4.0),
        camera_path: None,
        size: None,
        out: None,
        video: Some(run_dir.join("orbit.gif")),
        fps: 24.0,
        depth_range: None,
    };
    let orbit_dir = run_dir.join("render_orbit");
    render_run(&run, &orbit, &orbit_dir)?;
    println!("\ndemo finished in {:.1} s", t0.elapsed().as_secs_f64());
    println!("  scene:       {}", data.display());
    println!(
        "  run:         {} (config.json, checkpoint.safetensors, metrics.jsonl, val/)",
        run_dir.display()
    );
    println!("  test images: {} (metrics.json)", eval_dir.display());
    println!(
        "  orbit:       {} (frames), {}",
        orbit_dir.display(),
        run_dir.join("orbit.gif").display()
    );
    Ok(())
}

#[derive(Args)]
pub struct BenchArgs {
    /// Which model to measure.
    #[arg(long, value_enum, default_value = "fast")]
    model: ModelArg,
    /// Timed training steps (the median is reported). Default: 32 fast, 3 vanilla.
    #[arg(long)]
    steps: Option<usize>,
    /// Size of the rendered view (square; fast: unless --data has a test camera).
    #[arg(long, default_value_t = 400)]
    render_size: usize,
    /// Print the figures as JSON.
    #[arg(long)]
    json: bool,
    /// Fast: a Blender-format scene to train on (default: the built-in chair).
    #[arg(long)]
    data: Option<PathBuf>,
    /// Fast: untimed steps first, so the occupancy grid takes shape.
    #[arg(long, default_value_t = 300)]
    warmup_steps: u64,
    /// Fast: field samples per step.
    #[arg(long)]
    samples: Option<usize>,
    /// Fast: log2 of the hash-table entries per level.
    #[arg(long)]
    table_log2: Option<u32>,
    /// Vanilla: rays per training step.
    #[arg(long, default_value_t = 1024)]
    rays: usize,
    /// Vanilla: rows of the view actually rendered; the full-view time is extrapolated.
    #[arg(long, default_value_t = 8)]
    render_rows: usize,
    /// Vanilla: model preset to measure.
    #[arg(long, default_value = "paper", value_parser = crate::preset_values())]
    preset: String,
}

pub fn bench(a: BenchArgs) -> Result<()> {
    if a.model == ModelArg::Fast {
        return bench_fast(a);
    }
    let opts = nerf::bench_vanilla::BenchOptions {
        rays: a.rays,
        steps: a.steps.unwrap_or(3).max(1),
        render_size: a.render_size,
        render_rows: a.render_rows,
        preset: a.preset,
    };
    let report = nerf::bench_vanilla::run(&opts, &mut |line| println!("{line}"))?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
        return Ok(());
    }
    let r = &report;
    println!("\n{} threads, preset {}", r.threads, r.preset);
    println!(
        "GEMM peak (gemm crate, 16384x256x256): {:.1} GFLOP/s ({:.1} on one thread)",
        r.gemm_peak_gflops, r.gemm_gflops_one_thread
    );
    println!(
        "training step, {} rays: {:.3} s (median), {:.0} rays/s, {:.0} samples/s, {:.1} GFLOP/step, {:.1} GFLOP/s = {:.1}% of the GEMM peak",
        r.train_rays, r.train_step_seconds_median, r.train_rays_per_second, r.train_samples_per_second, r.train_gflop_per_step, r.train_gflops, r.train_percent_of_gemm_peak
    );
    println!(
        "rendering {0}x{0} (from {1} rows): {2:.1} s per view, {3:.0} rays/s, {4:.0} samples/s, {5:.1} GFLOP/s = {6:.1}% of the GEMM peak",
        r.render_size, r.render_rows_measured, r.render_seconds_full_view, r.render_rays_per_second, r.render_samples_per_second, r.render_gflops, r.render_percent_of_gemm_peak
    );
    println!("peak resident memory: {:.0} MiB", r.peak_resident_mib);
    Ok(())
}

fn bench_fast(a: BenchArgs) -> Result<()> {
    let mut model = nerf::model::FastModelConfig::default();
    model.samples_per_step = a.samples.unwrap_or(model.samples_per_step);
    model.field.grid.log2_table_size = a.table_log2.unwrap_or(model.field.grid.log2_table_size);
    let opts = nerf::bench_fast::FastBenchOptions {
        data: a.data,
        warmup_steps: a.warmup_steps,
        steps: a.steps.unwrap_or(32).max(1),
        render_size: a.render_size,
        model,
    };
    let r = nerf::bench_fast::run(&opts, &mut |line| println!("{line}"))?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&r)?);
        return Ok(());
    }
    println!(
        "\n{} threads, fast model on {}, after {} warm-up steps ({:.1}% of the occupancy grid occupied)",
        r.threads,
        r.scene,
        r.warmup_steps,
        100.0 * r.occupied_fraction
    );
    println!(
        "training step, {} samples ({:.0} rays): {:.3} s (median), {:.3} s with an occupancy refresh, {:.3} s amortised",
        r.samples_per_step, r.rays_per_step_median, r.step_seconds_median, r.refresh_step_seconds_median, r.step_seconds_amortised
    );
    println!(
        "  {:.2} M samples/s, {:.0} rays/s, {:.0} M hash-grid lookups/s (forward + backward)",
        r.train_samples_per_second / 1e6,
        r.train_rays_per_second,
        r.hash_lookups_per_second / 1e6
    );
    println!(
        "  {:.1}% of the gradient blocks touched per step (reduction and Adam skip the rest)",
        100.0 * r.touched_fraction
    );
    println!(
        "rendering {}x{}: {:.2} s per view, {:.0} rays/s",
        r.render_width, r.render_height, r.render_seconds, r.render_rays_per_second
    );
    println!("peak resident memory: {:.0} MiB", r.peak_resident_mib);
    Ok(())
}
