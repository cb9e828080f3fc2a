//! What a user sets for a training run (the command line's `nerf train` options, whose doc
//! comments are its `--help`), merged into a [`TrainConfig`] in one place: the model's
//! defaults come from its preset ([`TrainConfig::fast`], [`TrainConfig::from_preset`]) and
//! every option given replaces one value.

use crate::nn::linalg::Precision;
use std::path::{Path, PathBuf};

use super::defaults;
use super::run::{RunOptions, CONFIG_FILE};
use super::TrainConfig;
use crate::data::scene::SceneOptions;
use crate::data::Background;
use crate::error::{NerfError, Result};
use crate::model::{ModelConfig, ModelKind};

#[derive(Clone, Debug, clap::Args)]
pub struct TrainOptions {
    /// Scene folder: Blender (transforms_train.json), instant-ngp / nerfstudio
    /// (transforms.json), LLFF (poses_bounds.npy + images/) or COLMAP (sparse/0 + images/).
    /// Not needed with --resume --out RUN (the run's config names its scene).
    #[arg(long, required_unless_present = "resume")]
    pub data: Option<PathBuf>,
    #[command(flatten)]
    pub scene: SceneOptions,
    #[command(flatten)]
    pub device: crate::engine::DeviceArg,
    /// Fast: half-extent of the scene box [-B, B]^3 the hash grid covers, in scene units
    /// after the format's placement. Default: from the scene (Blender 1.5, NDC 1,
    /// instant-ngp aabb_scale / 2, COLMAP from its points).
    #[arg(long, value_parser = crate::args::positive, allow_negative_numbers = true)]
    pub bound: Option<f32>,
    /// Fast: keep the whole scene in the box instead of contracting the space beyond its
    /// inner half (contraction is the default for 360-degree real captures: LLFF
    /// --spherify and COLMAP).
    #[arg(long)]
    pub no_contract: bool,
    /// Run folder (config.json, checkpoint, metrics.jsonl, val/). Default: runs/<scene>-<preset>.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Which model: `fast` (hash grid + occupancy grid, minutes) or `vanilla` (the paper's
    /// MLPs, days). Default: fast, or vanilla when --preset is given.
    #[arg(long, value_enum)]
    pub model: Option<ModelKind>,
    /// Vanilla model configuration: the paper's, one of its ablations, or a reduced demo
    /// model (implies --model vanilla; default paper).
    #[arg(long, value_parser = crate::presets::possible_values())]
    pub preset: Option<String>,
    /// Steps to train (the learning rate decays 10x over them). Default: 5000 fast,
    /// 200000 vanilla; none with --minutes alone (the clock sets the schedule).
    #[arg(long, value_parser = clap::value_parser!(u64).range(1..))]
    pub steps: Option<u64>,
    /// Watch the model train in the web browser (`nerf view` on the run as it trains;
    /// the address is printed). Costs training nothing while no page is open.
    #[arg(long)]
    pub view: bool,
    /// Port of the --view page.
    #[arg(long, default_value_t = 7007)]
    pub view_port: u16,
    /// Train for this many minutes: alone, the whole schedule (the learning-rate decay)
    /// runs by the clock and ends with the budget, so the run is the best that fits it;
    /// with --steps, the schedule spans the steps and the minutes only cap this session.
    /// On --resume of a timed run, sets its new total.
    #[arg(long, value_parser = crate::args::positive_f64, allow_negative_numbers = true)]
    pub minutes: Option<f64>,
    /// Fast: learn a code of N values (16 when N is left out) per training photo for
    /// its exposure and white balance, fed to the colour network only (after NeRF in the
    /// Wild); render uses the mean code, or one photo's with --appearance-of; eval gives
    /// each view the look of the training photo taken nearest to it (--look).
    /// For captures whose photos change look from shot to shot: the default for real
    /// captures, with --refine-cameras (see there).
    #[arg(long, num_args = 0..=1, default_missing_value = "16", conflicts_with = "no_appearance",
          value_parser = clap::value_parser!(u32).range(1..=256))]
    pub appearance: Option<u32>,
    /// Fast: no per-photo appearance codes (the default for Blender scenes).
    #[arg(long)]
    pub no_appearance: bool,
    /// Fast: weight of mip-NeRF 360's distortion loss, which gathers each ray's weight
    /// into a short stretch and so clears the thin fog that makes forward-facing and
    /// unbounded captures slow to render. Default: 1e-4 for forward-facing
    /// (NDC) scenes, which then render several times faster for a fraction of a dB; none
    /// for others.
    #[arg(long, value_name = "WEIGHT", value_parser = crate::args::positive_f64,
          conflicts_with = "no_distortion")]
    pub distortion: Option<f64>,
    /// Fast: no distortion loss (the default but for forward-facing NDC scenes).
    #[arg(long)]
    pub no_distortion: bool,
    /// Fast: learn a correction of every training camera's pose with the field (after
    /// BARF), for poses that are a little off. With 16 appearance codes per photo, the
    /// default for real captures (instant-ngp / nerfstudio transforms.json, COLMAP, LLFF
    /// with --spherify), on either engine: without codes, the poses soak up the photos'
    /// changes of exposure. Not for Blender scenes or forward-facing (NDC) scenes unless
    /// asked for.
    /// A camera stuck far from where its photo fits is found and searched for, and left
    /// out of training if no pose explains its photo (the log names it).
    /// `nerf eval` then fits each test camera to the model first, as BARF evaluates.
    #[arg(long, conflicts_with = "no_refine_cameras")]
    pub refine_cameras: bool,
    /// The pose corrections' learning rate, decaying to a hundredth of it over the
    /// schedule (default 6e-4, for poses a fraction of a degree off, which start to move
    /// a fifth of the way in, once the field has taken shape; with --perturb-poses, for
    /// errors of degrees, 1e-2 from the first step, decaying to a thousandth of it, or
    /// 3e-3 on forward-facing NDC captures). Implies --refine-cameras.
    #[arg(long, conflicts_with = "no_refine_cameras", value_name = "LR")]
    pub camera_lr: Option<f32>,
    /// Fast: trust the given poses as they are (the default for Blender scenes).
    #[arg(long)]
    pub no_refine_cameras: bool,
    /// Move every training pose by random rigid noise of this standard deviation
    /// (rotation in radians about the scene's centre, translation in scene units) before
    /// training: BARF's test of camera refinement. `SIGMA[,SEED]`. Refinement then expects
    /// errors of degrees: the cameras move from the first step; outside NDC, the
    /// coarse-to-fine schedule weighs only the cameras' gradient, and the field's learning
    /// rate starts over where it ends.
    #[arg(long, value_parser = crate::model::camera_refine::parse_perturbation)]
    pub perturb_poses: Option<crate::model::camera_refine::PosePerturbation>,
    /// Train on some of the training views: a count (`3`: the first, the last and the
    /// rest evenly between, RegNeRF's and FreeNeRF's choice) or indices into the training
    /// split (`1,10,19`; a single index as `5,`). `nerf train` and `metrics.json` say which.
    #[arg(long, value_name = "N|LIST", value_parser = crate::data::train_views::parse_train_views)]
    pub train_views: Option<crate::data::TrainViews>,
    /// Vanilla: rays per step (default 1024; paper: 4096).
    #[arg(long)]
    pub batch: Option<usize>,
    /// Fast: field samples per step; the number of rays adapts (default 65536, and 131072
    /// for a run scheduled by the clock, --minutes alone, on a still scene).
    #[arg(long)]
    pub samples: Option<usize>,
    /// Fast: log2 of the hash-table entries per level (default 19).
    #[arg(long)]
    pub table_log2: Option<u32>,
    /// Initial learning rate (default 1e-2 fast, 5e-4 vanilla).
    #[arg(long, value_parser = crate::args::positive, allow_negative_numbers = true)]
    pub lr: Option<f32>,
    /// Background behind transparent pixels; random = a new colour per ray while training.
    /// Default: random for fast, white for vanilla.
    #[arg(long, value_enum)]
    pub background: Option<Background>,
    /// Train on the multi-scale variant of the scene (mip-NeRF's benchmark): every
    /// training image also at 1/2, 1/4, ... of its resolution, N scales in all (4: down
    /// to 1/8), area-averaged, each scale drawing the same share of rays. Evaluate it with
    /// `nerf eval --multiscale N`.
    #[arg(long, value_name = "N",
          value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(1..=6))]
    pub multiscale: Option<usize>,
    /// Fast: anti-alias (after Zip-NeRF): each sample reads no hash-grid detail finer
    /// than its pixel's footprint, so views from far away or at low resolution do not
    /// alias, nor close ones blur. The default on both engines, but for forward-facing
    /// (NDC) captures.
    #[arg(long, conflicts_with = "no_antialias")]
    pub antialias: bool,
    /// Fast: point samples, as Instant-NGP (the default for forward-facing NDC captures).
    #[arg(long)]
    pub no_antialias: bool,
    /// Fast: train the networks with their products' inputs rounded to bfloat16 and their
    /// sums in f32 (mixed precision, as GPU trainers run half precision): the same PSNR in
    /// less time. The default on the CPU engine where the CPU has AVX-512 BF16 (Intel
    /// Cooper Lake and Sapphire Rapids on, AMD Zen 4 on); the GPU engine runs f32.
    #[arg(long, conflicts_with = "no_bf16")]
    pub bf16: bool,
    /// Fast: train the networks' products in f32.
    #[arg(long)]
    pub no_bf16: bool,
    /// Fast: few-view training (the space fewer than half of the training photos see, and
    /// the space the scene hides from all of them, is kept empty; colour varies with the
    /// view at degree 1 only; the hash tables' entries decay towards zero), the default
    /// for runs on at most 16 training views of a bounded scene.
    /// The paper's model has `--preset freenerf` and `--preset regnerf` for few views.
    #[arg(long, conflicts_with = "no_few_view")]
    pub few_view: bool,
    /// Fast: train as on many views, however few there are.
    #[arg(long)]
    pub no_few_view: bool,
    /// Fast: a field of space and time for a moving scene (each photo at its own moment),
    /// the default when every photo has a time.
    #[arg(long, conflicts_with = "no_dynamic")]
    pub dynamic: bool,
    /// Fast: a still field, even where the photos have times.
    #[arg(long)]
    pub no_dynamic: bool,
    /// Fast, moving scenes: weight of a prior that the space-time features change smoothly
    /// over time (per ray, over one finest time cell). Default: none. With a cell per
    /// moment (--time-cells), 0.4 shares what neighbouring moments agree on
    /// (docs/benchmarks.md, "Moving scenes").
    #[arg(long, value_name = "WEIGHT", value_parser = crate::args::positive,
          allow_negative_numbers = true, conflicts_with = "no_time_smoothness")]
    pub time_smoothness: Option<f32>,
    /// Fast, moving scenes: no prior of smoothness in time (the default).
    #[arg(long)]
    pub no_time_smoothness: bool,
    /// Fast, moving scenes: cells along time at the space-time grid's finest level, 4 to
    /// 256. Default: 64, shared by neighbouring moments. One per moment (`nerf scene`
    /// counts them) with --time-smoothness 0.4 gains early on a fast motion, and measured
    /// level on it from 10 minutes on and worse on a slow one (docs/benchmarks.md).
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u16)
          .range(4..=crate::encoding::space_time_grid::MAX_TIME_CELLS as i64))]
    pub time_cells: Option<u16>,
    /// Fast: weight of RegNeRF's depth smoothness, on 4 patches of 4x4 rays
    /// per step rendered from poses between the training cameras, against geometry that
    /// only looks right from where the photos were taken. Default: 0.1 for forward-facing
    /// (NDC) runs on at most 16 photos (+2.35 dB on the rug from 3); none for others (on
    /// 8-view lego and chair it gained 0.05-0.19 dB; docs/benchmarks.md, "Few views").
    #[arg(long, value_name = "WEIGHT", value_parser = crate::args::positive,
          allow_negative_numbers = true, conflicts_with = "no_depth_smoothness")]
    pub depth_smoothness: Option<f32>,
    /// Fast: no depth smoothness (the default but for forward-facing runs on few photos).
    #[arg(long)]
    pub no_depth_smoothness: bool,
    /// Area-average downscale factor of the images (default 1).
    #[arg(long, value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(1..=64))]
    pub downscale: Option<usize>,
    /// Steps of central-crop warm-up (rays from the central half of each image). Default:
    /// 0 fast, 500 vanilla.
    #[arg(long)]
    pub precrop_steps: Option<u64>,
    /// Use the paper's printed positional encoding (sin(2^k pi p), no identity term).
    #[arg(long)]
    pub paper_pe: bool,
    /// Seed of the initial weights and of the rays each step draws (default 0).
    #[arg(long)]
    pub seed: Option<u64>,
    /// Render a validation image every N steps (0: never). Default: 500 fast, 1000 vanilla.
    #[arg(long)]
    pub val_every: Option<u64>,
    /// Save a checkpoint every N steps, at most one every 30 s after the first (default: 500
    /// fast, 1000 vanilla).
    #[arg(long)]
    pub checkpoint_every: Option<u64>,
    /// Rays per work unit per thread (vanilla memory: about 10 KB x 192 samples per ray).
    /// Default: 1024 fast, 64 vanilla.
    #[arg(long)]
    pub chunk: Option<usize>,
    /// Continue the run in --out from its last checkpoint, as its config.json says (options
    /// that would change it are refused; --steps may extend it). A run that stopped before
    /// its first checkpoint starts again from step 0.
    #[arg(long)]
    pub resume: bool,
    /// Stop this session after step N with a checkpoint (the learning-rate schedule still
    /// spans --steps); continue later with --resume.
    #[arg(long)]
    pub pause_at: Option<u64>,
}

/// `runs/<scene>-<label>`: the default run folder of a scene.
pub fn default_run(data: &Path, label: &str) -> PathBuf {
    let scene = data
        .file_name()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "scene".into());
    PathBuf::from("runs").join(format!("{scene}-{label}"))
}

fn world_space(scene: &crate::data::scene::Scene) -> bool {
    scene.space == crate::camera::ray_space::RaySpace::World
}

/// Why `--bf16` cannot run here.
const NO_BF16: &str = "this CPU has no AVX-512 BF16, which the bfloat16 products need \
                       (--no-bf16 trains in f32)";

fn refuse<T>(message: String) -> Result<T> {
    Err(NerfError::Config(message))
}

impl TrainOptions {
    /// The flags of the features whose defaults `defaults::fast_defaults` decides.
    /// Whether any setting of a field of space and time's grid or prior was given.
    fn asks_time_settings(&self) -> bool {
        self.time_smoothness.is_some() || self.no_time_smoothness || self.time_cells.is_some()
    }

    fn feature_flags(&self) -> defaults::Flags {
        use defaults::Choice;
        defaults::Flags {
            antialias: Choice::from_flags(self.antialias, self.no_antialias),
            appearance: Choice::from_value(self.appearance, self.no_appearance),
            // A camera learning rate asks for refinement.
            refine_cameras: Choice::from_flags(
                self.refine_cameras || self.camera_lr.is_some(),
                self.no_refine_cameras,
            ),
            distortion: Choice::from_value(self.distortion.map(|w| w as f32), self.no_distortion),
            few_view: Choice::from_flags(self.few_view, self.no_few_view),
            dynamic: Choice::from_flags(self.dynamic, self.no_dynamic),
            depth_smoothness: Choice::from_value(self.depth_smoothness, self.no_depth_smoothness),
            time_smoothness: Choice::from_value(self.time_smoothness, self.no_time_smoothness),
            time_cells: self.time_cells.map(usize::from),
            bf16: Choice::from_flags(self.bf16, self.no_bf16),
        }
    }

    /// The model: `--model`, else vanilla when a preset is named, else fast.
    pub fn model(&self) -> Result<ModelKind> {
        match (self.model, &self.preset) {
            (Some(ModelKind::Fast), Some(p)) => refuse(format!(
                "--preset {p} names a vanilla configuration; drop it or use --model vanilla"
            )),
            (Some(m), _) => Ok(m),
            (None, Some(_)) => Ok(ModelKind::Vanilla),
            (None, None) => Ok(ModelKind::Fast),
        }
    }

    /// Name for the default run folder: `fast`, or the vanilla preset.
    pub fn label(&self) -> Result<String> {
        Ok(match self.model()? {
            ModelKind::Fast => "fast".into(),
            ModelKind::Vanilla => self.preset.clone().unwrap_or_else(|| "paper".into()),
        })
    }

    /// The run folder: `--out`, else [`default_run`].
    pub fn out(&self) -> Result<PathBuf> {
        match &self.out {
            Some(out) => Ok(out.clone()),
            None => match &self.data {
                Some(data) => Ok(default_run(data, &self.label()?)),
                None => refuse("--resume without --data needs --out RUN, the run folder".into()),
            },
        }
    }

    /// The whole configuration: the model's defaults with every given option applied.
    /// Reads the scene (its box and contraction are the defaults of the fast model);
    /// `on_notice` hears the scene reader's notes and warnings (`note: ...`, `warning: ...`).
    pub fn config(&self, on_notice: &mut dyn FnMut(&str)) -> Result<TrainConfig> {
        // Absolute, so `eval` and `render` find the scene from any working directory.
        let data = self
            .data
            .as_ref()
            .ok_or_else(|| NerfError::Config("--data is needed to start a run".into()))?;
        let data = std::fs::canonicalize(data).unwrap_or_else(|_| data.clone());
        let mut c = match self.model()? {
            ModelKind::Fast => TrainConfig::fast(data),
            ModelKind::Vanilla => {
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
                    return refuse("--samples and --table-log2 apply to --model fast only".into());
                }
            }
            ModelConfig::Fast(m) => {
                if self.batch.is_some() || self.paper_pe {
                    return refuse("--batch and --paper-pe apply to --model vanilla only".into());
                }
                m.samples_per_step = self.samples.unwrap_or(m.samples_per_step);
                m.field.grid.log2_table_size =
                    self.table_log2.unwrap_or(m.field.grid.log2_table_size);
            }
        }
        c.steps = self.steps.unwrap_or(c.steps);
        if let (Some(minutes), None) = (self.minutes, self.steps) {
            c.time_budget_s = Some(minutes * 60.0);
            c.steps = u64::MAX;
        }
        c.batch_rays = self.batch.unwrap_or(c.batch_rays);
        if let Some(lr) = self.lr {
            c.lr_final *= lr / c.lr_init;
            c.lr_init = lr;
        }
        c.background = self.background.unwrap_or(c.background);
        c.downscale = self.downscale.unwrap_or(c.downscale);
        c.multiscale = self.multiscale.unwrap_or(c.multiscale);
        c.scene = self.scene.clone();
        let scene = c.open_scene(1)?;
        for n in &scene.notes {
            on_notice(&format!("note: {n}"));
        }
        for w in scene
            .warnings()
            .into_iter()
            .chain(scene.copied_held_out_images()?)
        {
            on_notice(&format!("warning: {w}"));
        }
        let still_field = match &c.model {
            ModelConfig::Fast(_) => self.no_dynamic,
            ModelConfig::Vanilla(_) => !c.model.is_dynamic(),
        };
        if scene.is_dynamic() && still_field {
            on_notice(
                "warning: the scene's photos show a moving subject (each frame has a time): \
                 a still field averages the motion into a blur (the fast model's default \
                 field of space and time and --preset dnerf do not)",
            );
        }
        match &mut c.model {
            ModelConfig::Fast(m) => {
                m.field.bound = self.bound.unwrap_or(scene.bound);
                m.contract = scene.contract && !self.no_contract;
                let ndc = !world_space(&scene);
                if c.multiscale > 1
                    && (self.appearance.is_some()
                        || self.refine_cameras
                        || self.camera_lr.is_some())
                {
                    return refuse(
                        "--multiscale cannot be combined with --appearance or \
                         --refine-cameras yet (each scale of a photo would get its own code \
                         and pose)"
                            .into(),
                    );
                }
                let chosen = match self.train_views.as_ref().or(c.train_views.as_ref()) {
                    Some(v) => v.indices(scene.train.len())?,
                    None => (0..scene.train.len()).collect(),
                };
                let photos = chosen.len();
                let moments = scene
                    .moments_of(chosen.iter().filter_map(|&k| scene.train.get(k).copied()))
                    .len();
                if self.bf16 && Precision::bf16().is_none() {
                    return refuse(NO_BF16.into());
                }
                if self.few_view && !crate::model::few_view::applies(scene.space, m.contract) {
                    return refuse(
                        "--few-view applies to bounded scenes in world space, not to \
                         forward-facing or contracted captures"
                            .into(),
                    );
                }
                let facts = defaults::SceneFacts {
                    blender: scene.format == crate::data::scene::Format::Blender,
                    space: scene.space,
                    multiscale: c.multiscale,
                    contract: m.contract,
                    train_views: photos,
                    moments,
                };
                let d = defaults::decide(self.device.device, &facts, &self.feature_flags());
                for note in &d.notes {
                    on_notice(note);
                }
                let timed = self.minutes.is_some() && self.steps.is_none();
                if timed && self.samples.is_none() {
                    m.samples_per_step =
                        defaults::timed_samples_per_step(d.dynamic(), m.samples_per_step);
                }
                if self.asks_time_settings() && !d.dynamic() {
                    return refuse(
                        "--time-smoothness, --no-time-smoothness and --time-cells apply to a \
                         field of space and time (a scene whose photos have times, or --dynamic)"
                            .into(),
                    );
                }
                if d.dynamic() {
                    if d.refine_cameras {
                        return refuse(
                            "--refine-cameras cannot be combined with a field of space and \
                             time yet (--no-dynamic trains a still one)"
                                .into(),
                        );
                    }
                    if !scene.is_dynamic() {
                        on_notice(
                            "warning: --dynamic on a scene without times: every photo is seen \
                             at moment 0, so the field learns a still scene",
                        );
                    }
                }
                d.apply_to(
                    m,
                    &scene.cameras(crate::data::Split::Train),
                    &scene.space,
                    photos,
                );
                let asked = d.refine_asked;
                if d.refine_cameras {
                    let mut r = crate::model::camera_refine::CameraRefinement::new(photos);
                    r.frame = crate::model::camera_refine::Frame::for_space(scene.space);
                    if let Some(lr) = self.camera_lr {
                        if !(lr.is_finite() && lr > 0.0) {
                            return refuse(format!(
                                "--camera-lr {lr}: the learning rate must be a positive number"
                            ));
                        }
                        r = r.with_learning_rate(lr);
                    } else if self.perturb_poses.is_some() {
                        use crate::model::camera_refine::{LARGE_ERROR_LR, LARGE_ERROR_LR_NDC};
                        r = r.with_learning_rate(if ndc {
                            LARGE_ERROR_LR_NDC
                        } else {
                            LARGE_ERROR_LR
                        });
                    }
                    // Poses degrees off about the scene's centre: the field learns every
                    // level from the start (better on lego; the forward-facing rug measured
                    // better with BARF's schedule, as real captures do).
                    r.pose_gradient_only = self.perturb_poses.is_some() && !ndc;
                    // ... and the field's learning rate starts over when the cameras have
                    // settled, at the coarse-to-fine window's end (better on lego).
                    if r.pose_gradient_only {
                        r.field_restart = Some(r.anneal[1]);
                        // ... and the cameras' rate decays further, so they settle closer.
                        if self.camera_lr.is_none() {
                            r.lr_final =
                                r.lr_init * crate::model::camera_refine::LARGE_ERROR_FINAL_FRACTION;
                        }
                    }
                    // Poses a fraction of a degree off move once the field has taken shape.
                    if self.perturb_poses.is_none() {
                        r.delay = crate::model::camera_refine::SMALL_ERROR_DELAY;
                    }
                    m.refine_cameras = Some(r);
                    on_notice(if asked {
                        "note: refining the training cameras' poses with the field"
                    } else {
                        "note: refining the training cameras' poses with the field (the default \
                         for real captures; --no-refine-cameras trusts them as given)"
                    });
                }
            }
            ModelConfig::Vanilla(m) if m.net.deformation.is_some() && !scene.is_dynamic() => {
                return refuse(format!(
                    "--preset dnerf models a moving scene, and no frame of {} has a time",
                    scene.dir.display()
                ));
            }
            ModelConfig::Vanilla(_) if self.bound.is_some() || self.no_contract => {
                return refuse("--bound and --no-contract apply to --model fast only".into());
            }
            ModelConfig::Vanilla(_) if self.antialias => {
                return refuse("--antialias applies to --model fast only".into());
            }
            ModelConfig::Vanilla(_) if self.bf16 => {
                return refuse("--bf16 applies to --model fast only".into());
            }
            ModelConfig::Vanilla(_) if self.few_view => {
                return refuse(
                    "--few-view applies to --model fast only; for the paper's model on few \
                     views use --preset freenerf or --preset regnerf"
                        .into(),
                );
            }
            ModelConfig::Vanilla(_) if self.depth_smoothness.is_some() => {
                return refuse(
                    "--depth-smoothness applies to --model fast only; for the paper's model on \
                     few views use --preset regnerf (RegNeRF's depth smoothness) or --preset \
                     freenerf"
                        .into(),
                );
            }
            ModelConfig::Vanilla(_) if self.dynamic || self.asks_time_settings() => {
                return refuse(
                    "--dynamic, --time-smoothness, --no-time-smoothness and --time-cells apply \
                     to --model fast only"
                        .into(),
                );
            }
            ModelConfig::Vanilla(_)
                if self.appearance.is_some()
                    || self.refine_cameras
                    || self.camera_lr.is_some()
                    || self.distortion.is_some() =>
            {
                return refuse(
                    "--appearance, --refine-cameras and --distortion apply to --model fast only"
                        .into(),
                );
            }
            ModelConfig::Vanilla(_) => {}
        }
        c.precrop_steps = self.precrop_steps.unwrap_or(c.precrop_steps);
        c.seed = self.seed.unwrap_or(c.seed);
        c.val_every = self.val_every.unwrap_or(c.val_every);
        c.checkpoint_every = self.checkpoint_every.unwrap_or(c.checkpoint_every);
        c.chunk_rays = self.chunk.unwrap_or(c.chunk_rays);
        c.perturb_poses = self.perturb_poses;
        if self.train_views.is_some() {
            c.train_views = self.train_views.clone();
        }
        Ok(c)
    }

    /// How to run: the configuration and the session's budget. Resuming continues the run
    /// as its `config.json` says; options that would change it are refused by name, but
    /// for `--steps`, which may extend the run (the target is recorded in the config, so
    /// the schedule and later resumes agree).
    pub fn run_options(&self, on_notice: &mut dyn FnMut(&str)) -> Result<RunOptions> {
        let out = self.out()?;
        if out.exists() && !out.is_dir() {
            return refuse(format!(
                "--out {} is an existing file, not a run folder; choose another --out",
                out.display()
            ));
        }
        if self.resume && !out.join(CONFIG_FILE).exists() {
            return refuse(format!(
                "cannot resume: {} holds no run (no {CONFIG_FILE}); drop --resume to start one",
                out.display()
            ));
        }
        let config = if self.resume {
            let mut saved = super::folder::read_config(&out)?;
            let conflicts = self.conflicts_with(&saved);
            if !conflicts.is_empty() {
                return refuse(format!(
                    "--resume continues the run in {} as its {CONFIG_FILE} says, and these \
                     options differ from it: {}; drop them, or train a new run into another --out",
                    out.display(),
                    conflicts.join(", ")
                ));
            }
            match (saved.time_budget_s, self.steps, self.minutes) {
                (Some(_), Some(_), _) => {
                    return refuse(format!(
                        "the run in {} is scheduled by the clock (--minutes), not by steps; \
                         give --minutes with --resume to change its total",
                        out.display()
                    ))
                }
                (Some(_), None, Some(minutes)) => saved.time_budget_s = Some(minutes * 60.0),
                _ => saved.steps = self.steps.unwrap_or(saved.steps),
            }
            if let ModelConfig::Fast(m) = &mut saved.model {
                // A speed setting: a run begun in bfloat16 may go on in f32.
                if self.no_bf16 {
                    m.bf16_products = false;
                }
                if m.bf16_products && Precision::bf16().is_none() {
                    return refuse(format!(
                        "the run in {} trains its networks' products in bfloat16: {NO_BF16}; \
                         resume it with --no-bf16 to go on in f32",
                        out.display()
                    ));
                }
            }
            saved
        } else {
            self.config(on_notice)?
        };
        // A timed schedule carries its budget in the config; minutes cap only a step schedule.
        let minutes = self.minutes.filter(|_| config.time_budget_s.is_none());
        Ok(RunOptions {
            out,
            config,
            minutes,
            resume: self.resume,
            pause_at: self.pause_at,
            stop: None,
            device: self.device.device,
        })
    }

    /// The options given that would change `saved` (a run's config), as `--flag value
    /// (the run's: value)`.
    pub fn conflicts_with(&self, saved: &TrainConfig) -> Vec<String> {
        let mut out = Vec::new();
        let mut check = |flag: &str, given: Option<String>, theirs: String| {
            if let Some(given) = given.filter(|g| *g != theirs) {
                out.push(format!("{flag} {given} (the run's: {theirs})"));
            }
        };
        let data = self
            .data
            .as_ref()
            .map(|d| std::fs::canonicalize(d).unwrap_or_else(|_| d.clone()));
        let theirs = std::fs::canonicalize(&saved.data).unwrap_or_else(|_| saved.data.clone());
        check(
            "--data",
            data.map(|d| d.display().to_string()),
            theirs.display().to_string(),
        );
        let fast = match &saved.model {
            ModelConfig::Fast(m) => Some(m),
            ModelConfig::Vanilla(_) => None,
        };
        let model = if fast.is_some() { "fast" } else { "vanilla" };
        check(
            "--model",
            self.model.map(|m| format!("{m:?}").to_lowercase()),
            model.into(),
        );
        check("--preset", self.preset.clone(), saved.preset.clone());
        check(
            "--samples",
            self.samples.map(|v| v.to_string()),
            fast.map_or("none (vanilla)".into(), |m| m.samples_per_step.to_string()),
        );
        check(
            "--table-log2",
            self.table_log2.map(|v| v.to_string()),
            fast.map_or("none (vanilla)".into(), |m| {
                m.field.grid.log2_table_size.to_string()
            }),
        );
        check(
            "--bound",
            self.bound.map(|v| v.to_string()),
            fast.map_or("none (vanilla)".into(), |m| m.field.bound.to_string()),
        );
        check(
            "--lr",
            self.lr.map(|v| v.to_string()),
            saved.lr_init.to_string(),
        );
        check(
            "--seed",
            self.seed.map(|v| v.to_string()),
            saved.seed.to_string(),
        );
        check(
            "--batch",
            self.batch.map(|v| v.to_string()),
            saved.batch_rays.to_string(),
        );
        check(
            "--downscale",
            self.downscale.map(|v| v.to_string()),
            saved.downscale.to_string(),
        );
        check(
            "--multiscale",
            self.multiscale.map(|v| v.to_string()),
            saved.multiscale.to_string(),
        );
        check(
            "--background",
            self.background.map(|b| format!("{b:?}").to_lowercase()),
            format!("{:?}", saved.background).to_lowercase(),
        );
        check(
            "--precrop-steps",
            self.precrop_steps.map(|v| v.to_string()),
            saved.precrop_steps.to_string(),
        );
        check(
            "--val-every",
            self.val_every.map(|v| v.to_string()),
            saved.val_every.to_string(),
        );
        check(
            "--checkpoint-every",
            self.checkpoint_every.map(|v| v.to_string()),
            saved.checkpoint_every.to_string(),
        );
        check(
            "--chunk",
            self.chunk.map(|v| v.to_string()),
            saved.chunk_rays.to_string(),
        );
        check(
            "--train-views",
            self.train_views.as_ref().map(|v| v.to_string()),
            saved
                .train_views
                .as_ref()
                .map_or_else(|| "all".to_string(), |v| v.to_string()),
        );
        if self.paper_pe
            || self.no_contract
            || self.appearance.is_some()
            || self.no_appearance
            || self.refine_cameras
            || self.no_refine_cameras
            || self.camera_lr.is_some()
            || self.perturb_poses.is_some()
            || self.antialias
            || self.no_antialias
            || self.distortion.is_some()
            || self.no_distortion
            || self.few_view
            || self.no_few_view
            || self.dynamic
            || self.no_dynamic
            || self.asks_time_settings()
            || self.depth_smoothness.is_some()
            || self.no_depth_smoothness
            || self.bf16
        {
            out.push(
                "--paper-pe / --no-contract / --appearance / --no-appearance / \
                 --refine-cameras / --no-refine-cameras / --camera-lr / --perturb-poses / \
                 --antialias / --no-antialias / --distortion / --no-distortion / --few-view / \
                 --no-few-view / --dynamic / --no-dynamic / --time-smoothness / \
                 --no-time-smoothness / --time-cells / --depth-smoothness / \
                 --no-depth-smoothness / --bf16 \
                 (set when the run was made)"
                    .into(),
            );
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::encoding::space_time_grid::SpaceTimeConfig;
    use clap::Parser;

    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        train: TrainOptions,
    }

    fn config(args: &[&str], dir: &Path) -> Result<TrainConfig> {
        let data = dir.to_string_lossy().to_string();
        let mut all = vec!["nerf", "--data", &data];
        all.extend_from_slice(args);
        let cli = Cli::try_parse_from(all).map_err(|e| NerfError::Config(e.to_string()))?;
        cli.train.config(&mut |_| {})
    }

    /// The built-in chair at `size` pixels, 3 training views, in a fresh folder.
    fn tiny_scene(size: usize) -> tempfile::TempDir {
        let dir = tempfile::tempdir().expect("tempdir");
        let opts = crate::data::synth::SynthOptions {
            size,
            supersample: 1,
            train_views: 3,
            val_views: 1,
            test_views: 1,
            ..Default::default()
        };
        crate::data::synth::generate(&opts, dir.path(), &mut |_, _| {}).expect("synth");
        dir
    }

    /// The built-in rug as a forward-facing LLFF capture (NDC), 8x6 pixels.
    fn tiny_llff() -> tempfile::TempDir {
        let llff = tempfile::tempdir().expect("tempdir");
        let cameras = crate::data::synth::llff::forward_facing_cameras(8, 6, 2, 2);
        crate::data::synth::llff::write(
            crate::data::synth::SceneKind::Rug,
            &cameras,
            1,
            &crate::data::poses::Similarity::IDENTITY,
            llff.path(),
            &mut |_, _| {},
        )
        .expect("llff");
        llff
    }

    /// Corrections turn cameras about the scene's centre where the world's origin is it
    /// (here a Blender scene), and about each camera's own centre in a forward-facing NDC
    /// capture, whose origin is its mean camera.
    #[test]
    fn the_frame_of_the_corrections_follows_the_scene() {
        use crate::model::camera_refine::Frame;
        let blender = tiny_scene(8);
        let c = config(&["--refine-cameras"], blender.path()).expect("blender");
        assert_eq!(refinement(&c).map(|r| r.frame), Some(Frame::World));
        let llff = tiny_llff();
        let c = config(&["--refine-cameras"], llff.path()).expect("llff");
        assert_eq!(refinement(&c).map(|r| r.frame), Some(Frame::Camera));
        // Perturbed: the large-error rate of forward-facing captures.
        let c = config(
            &["--refine-cameras", "--perturb-poses", "0.02"],
            llff.path(),
        )
        .expect("p");
        assert_eq!(
            refinement(&c).map(|r| (r.lr_init, r.pose_gradient_only, r.field_restart)),
            Some((crate::model::camera_refine::LARGE_ERROR_LR_NDC, false, None))
        );
    }

    /// `--camera-lr` sets the corrections' schedule (to a hundredth of it), implies
    /// `--refine-cameras`, and refuses a learning rate that is not positive.
    #[test]
    fn the_camera_learning_rate_is_set_and_checked() {
        let dir = tiny_scene(8);
        let c = config(&["--refine-cameras", "--camera-lr", "6e-4"], dir.path()).expect("ok");
        assert_eq!(
            refinement(&c).map(|r| (r.lr_init, r.lr_final, r.cameras)),
            Some((6e-4, 6e-6, 3))
        );
        let err =
            config(&["--refine-cameras", "--camera-lr=-1"], dir.path()).expect_err("negative");
        assert!(
            err.to_string().contains("must be a positive number"),
            "{err}"
        );
        let c = config(&["--camera-lr", "1e-3"], dir.path()).expect("alone");
        assert_eq!(refinement(&c).map(|r| r.lr_init), Some(1e-3));
        // Perturbed poses are degrees off: the large-error rate unless one is given.
        let perturbed = ["--refine-cameras", "--perturb-poses", "0.1"];
        let c = config(&perturbed, dir.path()).expect("perturbed");
        // ... the straight-through schedule, and the field's rate starts over at the
        // window's end.
        assert_eq!(
            refinement(&c).map(|r| (
                r.lr_init,
                r.lr_final,
                r.pose_gradient_only,
                r.field_restart,
                r.anneal[1],
                r.delay
            )),
            Some((
                crate::model::camera_refine::LARGE_ERROR_LR,
                crate::model::camera_refine::LARGE_ERROR_LR
                    * crate::model::camera_refine::LARGE_ERROR_FINAL_FRACTION,
                true,
                Some(0.4),
                0.4,
                0.0
            ))
        );
        // Small errors (real captures): BARF's schedule, one field decay, and the
        // cameras wait for the field to take shape.
        let c = config(&["--refine-cameras"], dir.path()).expect("plain");
        assert_eq!(
            refinement(&c).map(|r| (r.pose_gradient_only, r.field_restart, r.delay)),
            Some((false, None, crate::model::camera_refine::SMALL_ERROR_DELAY))
        );
        let c = config(
            &["--perturb-poses", "0.1", "--camera-lr", "1e-3"],
            dir.path(),
        )
        .expect("given");
        // A given rate decays to a hundredth of it, as always.
        assert_eq!(
            refinement(&c).map(|r| (r.lr_init, r.lr_final, r.pose_gradient_only)),
            Some((1e-3, 1e-3 / 100.0, true))
        );
        config(&["--camera-lr", "1e-3", "--no-refine-cameras"], dir.path()).expect_err("both");
    }

    /// `--depth-smoothness` reaches the fast model with the patches' spacing for the
    /// photos' width; unasked, it is on for forward-facing runs on few photos only;
    /// `--no-depth-smoothness` turns it off; it is refused where it cannot apply.
    #[test]
    fn depth_smoothness_is_set_and_checked() {
        use crate::model::unseen_patches::{stride_for, DepthSmoothness, PATCHES};
        let dir = tiny_scene(8);
        let smoothness = |c: &TrainConfig| match &c.model {
            ModelConfig::Fast(m) => m.depth_smoothness,
            ModelConfig::Vanilla(_) => None,
        };
        let c = config(&[], dir.path()).expect("default");
        assert_eq!(smoothness(&c), None);
        let c = config(&["--depth-smoothness", "0.1"], dir.path()).expect("given");
        let width = c
            .open_scene(1)
            .expect("scene")
            .cameras(crate::data::Split::Train)[0]
            .width;
        assert_eq!(
            smoothness(&c),
            Some(DepthSmoothness {
                weight: 0.1,
                patches: PATCHES,
                stride: stride_for(width),
            })
        );
        config(&["--depth-smoothness", "0"], dir.path()).expect_err("zero");
        // Forward-facing on few photos (4 here): on by default on the CPU engine.
        let llff = tiny_llff();
        let c = config(&["--device", "cpu"], llff.path()).expect("llff");
        assert_eq!(
            smoothness(&c).map(|d| d.weight),
            Some(defaults::FEW_VIEW_DEPTH_SMOOTHNESS)
        );
        let c = config(&["--no-depth-smoothness"], llff.path()).expect("off");
        assert_eq!(smoothness(&c), None);
        config(
            &["--depth-smoothness", "1", "--no-depth-smoothness"],
            llff.path(),
        )
        .expect_err("both");
        let err = config(
            &["--depth-smoothness", "0.1", "--preset", "demo"],
            dir.path(),
        )
        .expect_err("vanilla");
        assert!(err.to_string().contains("--depth-smoothness"), "{err}");
    }

    /// `--distortion` reaches the fast model, and is refused where it cannot apply: a
    /// weight that is not positive, the vanilla model. Unasked, forward-facing NDC scenes
    /// get the loss and others none; `--no-distortion` and `--no-ndc` turn it off.
    #[test]
    fn the_distortion_weight_is_set_and_checked() {
        let dir = tiny_scene(8);
        let weight = |c: &TrainConfig| match &c.model {
            ModelConfig::Fast(m) => Some(m.distortion),
            ModelConfig::Vanilla(_) => None,
        };
        let c = config(&[], dir.path()).expect("default");
        assert_eq!(weight(&c), Some(0.0));
        let llff = tiny_llff();
        let c = config(&["--device", "cpu"], llff.path()).expect("llff");
        assert_eq!(weight(&c), Some(defaults::FORWARD_FACING_DISTORTION));
        assert!(weight(&c) > Some(0.0), "on by default");
        // The same default on the GPU engine, which runs the loss too.
        let c = config(&["--device", "wgpu"], llff.path()).expect("gpu");
        assert_eq!(weight(&c), Some(defaults::FORWARD_FACING_DISTORTION));
        let c = config(&["--no-distortion"], llff.path()).expect("off");
        assert_eq!(weight(&c), Some(0.0));
        let c = config(&["--no-ndc"], llff.path()).expect("world space");
        assert_eq!(weight(&c), Some(0.0));
        let c = config(&["--distortion", "0.01"], llff.path()).expect("given");
        assert_eq!(weight(&c), Some(0.01));
        config(&["--distortion", "0.01", "--no-distortion"], llff.path()).expect_err("both");
        let c = config(&["--distortion", "0.002"], dir.path()).expect("set");
        assert_eq!(weight(&c), Some(0.002));
        config(&["--distortion", "0"], dir.path()).expect_err("zero");
        let err =
            config(&["--distortion", "0.01", "--preset", "demo"], dir.path()).expect_err("vanilla");
        assert!(err.to_string().contains("--distortion"), "{err}");
    }

    fn refinement(c: &TrainConfig) -> Option<crate::model::camera_refine::CameraRefinement> {
        match &c.model {
            ModelConfig::Fast(m) => m.refine_cameras,
            ModelConfig::Vanilla(_) => None,
        }
    }

    /// A real capture (here the tiny chair's photos and poses as an
    /// instant-ngp `transforms.json`) refines its cameras and learns a look per photo by
    /// default on the CPU engine; a Blender scene does neither; `--no-refine-cameras`,
    /// `--no-appearance` and `--multiscale` turn the defaults off.
    #[test]
    fn real_captures_refine_their_cameras_by_default() {
        let blender = tiny_scene(8);
        let cpu = ["--device", "cpu"];
        assert!(refinement(&config(&cpu, blender.path()).expect("blender")).is_none());
        let real = tempfile::tempdir().expect("tempdir");
        let mut frames = Vec::new();
        let mut angle = serde_json::Value::Null;
        for split in ["train", "val", "test"] {
            let text =
                std::fs::read_to_string(blender.path().join(format!("transforms_{split}.json")))
                    .expect("read");
            let doc: serde_json::Value = serde_json::from_str(&text).expect("json");
            angle = doc["camera_angle_x"].clone();
            for f in doc["frames"].as_array().expect("frames") {
                let name = format!("{}.png", f["file_path"].as_str().expect("path"));
                let to = format!("{split}_{}", name.rsplit('/').next().expect("name"));
                std::fs::copy(blender.path().join(&name), real.path().join(&to)).expect("copy");
                frames.push(serde_json::json!({
                    "file_path": to,
                    "transform_matrix": f["transform_matrix"],
                }));
            }
        }
        let doc = serde_json::json!({"camera_angle_x": angle, "aabb_scale": 4, "frames": frames});
        std::fs::write(real.path().join("transforms.json"), doc.to_string()).expect("write");
        let codes = |c: &TrainConfig| match &c.model {
            ModelConfig::Fast(m) => (m.field.appearance_dims, m.field.appearance_images),
            ModelConfig::Vanilla(_) => (0, 0),
        };
        let c = config(&cpu, real.path()).expect("real");
        let r = refinement(&c).expect("refined by default");
        assert_eq!(r.lr_init, crate::model::camera_refine::DEFAULT_LR);
        assert_eq!(r.delay, crate::model::camera_refine::SMALL_ERROR_DELAY);
        let train = c.open_scene(1).expect("scene").train.len();
        assert_eq!(
            codes(&c),
            (defaults::DEFAULT_APPEARANCE_DIMS as usize, train)
        );
        assert_eq!(codes(&config(&cpu, blender.path()).expect("blender")).0, 0);
        let off = config(&["--device", "cpu", "--no-refine-cameras"], real.path()).expect("off");
        assert!(refinement(&off).is_none());
        assert_eq!(codes(&off).0, 16, "the codes stay");
        let plain = config(&["--device", "cpu", "--no-appearance"], real.path()).expect("plain");
        assert!(refinement(&plain).is_some() && codes(&plain).0 == 0);
        let eight = config(&["--device", "cpu", "--appearance", "8"], real.path()).expect("8");
        assert_eq!(codes(&eight).0, 8);
        let ms = config(&["--device", "cpu", "--multiscale", "2"], real.path()).expect("ms");
        assert!(refinement(&ms).is_none() && codes(&ms).0 == 0);
        // On some of the photos: a code and a correction for each photo it trains on.
        let few = config(&["--device", "cpu", "--train-views", "3"], real.path()).expect("3");
        assert_eq!(codes(&few).1, 3);
        assert_eq!(refinement(&few).map(|r| r.cameras), Some(3));
    }

    /// `--multiscale` and `--antialias` reach the config (anti-aliasing with the
    /// training cameras' footprint as its reference); `--no-antialias` leaves point
    /// samples; a multi-scale run refuses per-photo codes and poses.
    #[test]
    fn multiscale_and_antialias_options_reach_the_config() {
        let dir = tiny_scene(16);
        let c = config(&["--multiscale", "3", "--antialias"], dir.path()).expect("ok");
        let ModelConfig::Fast(m) = &c.model else {
            panic!("fast model expected")
        };
        assert_eq!(c.multiscale, 3);
        let reference = m.field.antialias.expect("anti-aliased").reference_footprint;
        // The built-in cameras sit 4 units away with a 16-pixel image: about 0.5 units
        // per pixel there.
        assert!(reference > 0.02 && reference < 0.5, "{reference}");
        assert_eq!(c.training_data().expect("data").views.len(), 9);
        let c = config(&["--no-antialias"], dir.path()).expect("ok");
        let ModelConfig::Fast(m) = &c.model else {
            panic!("fast model expected")
        };
        assert!(m.field.antialias.is_none() && c.multiscale == 1);
        let err = config(&["--multiscale", "2", "--appearance"], dir.path()).expect_err("codes");
        assert!(
            err.to_string().contains("--multiscale cannot be combined"),
            "{err}"
        );
        let err = config(&["--preset", "demo", "--antialias"], dir.path()).expect_err("vanilla");
        assert!(err.to_string().contains("--model fast only"), "{err}");
        // Few-view training: on for at most 16 photos (the kept ones), off when asked;
        // with it, the colour sees the view direction's first four harmonics, else all.
        let few_in = |args: &[&str], dir: &Path| match config(args, dir).expect("ok").model {
            ModelConfig::Fast(m) => {
                let harmonics = m.field.view_harmonics;
                assert_eq!(
                    harmonics == 4,
                    m.few_view.is_some(),
                    "{harmonics} harmonics"
                );
                assert!(harmonics == 4 || harmonics == 16, "{harmonics} harmonics");
                m.few_view
            }
            ModelConfig::Vanilla(_) => panic!("fast model expected"),
        };
        let few = |args: &[&str]| few_in(args, dir.path());
        use crate::model::few_view::FewView;
        assert_eq!(few(&["--train-views", "2"]), Some(FewView::new(2)));
        assert_eq!(few(&[]), Some(FewView::new(3)));
        assert_eq!(few(&["--no-few-view"]), None);
        let err = config(&["--preset", "demo", "--few-view"], dir.path()).expect_err("vanilla");
        assert!(err.to_string().contains("--model fast only"), "{err}");
        // Not where it cannot act: a forward-facing capture of 6 photos trains as before,
        // and asking for it there is refused.
        let llff = tiny_llff();
        assert_eq!(few_in(&[], llff.path()), None);
        let err = config(&["--few-view"], llff.path()).expect_err("ndc");
        assert!(err.to_string().contains("world space"), "{err}");
    }

    /// A run scheduled by the clock takes twice the samples per step unless told (a still
    /// scene; moving scenes are tested with their field); a run of steps, capped by
    /// minutes or not, keeps the default. `--bf16` and `--no-bf16`
    /// reach the config (the default: where the CPU has the kernels), for the fast model
    /// only.
    #[test]
    fn timed_runs_take_larger_steps_and_the_products_precision_is_chosen() {
        let dir = tiny_scene(16);
        let fast = |args: &[&str]| match config(args, dir.path()).expect("ok").model {
            ModelConfig::Fast(m) => m,
            ModelConfig::Vanilla(_) => panic!("fast model expected"),
        };
        let default = crate::model::FastModelConfig::default().samples_per_step;
        assert_eq!(fast(&[]).samples_per_step, default);
        assert_eq!(
            fast(&["--minutes", "10"]).samples_per_step,
            defaults::TIMED_SAMPLES_PER_STEP
        );
        assert_eq!(
            fast(&["--minutes", "10", "--steps", "100"]).samples_per_step,
            default
        );
        assert_eq!(
            fast(&["--minutes", "10", "--samples", "4096"]).samples_per_step,
            4096
        );
        let cpu = ["--device", "cpu"];
        let has = Precision::bf16().is_some();
        assert_eq!(fast(&cpu).bf16_products, has);
        assert!(!fast(&["--device", "cpu", "--no-bf16"]).bf16_products);
        match config(&["--device", "cpu", "--bf16"], dir.path()) {
            Ok(c) => assert!(has && matches!(c.model, ModelConfig::Fast(m) if m.bf16_products)),
            Err(e) => assert!(!has && e.to_string().contains("AVX-512 BF16"), "{e}"),
        }
        let err = config(&["--preset", "demo", "--bf16"], dir.path()).expect_err("vanilla");
        assert!(err.to_string().contains("--model fast only"), "{err}");
    }

    /// A scene whose photos have times trains a field of space and time unless asked not
    /// to, in steps of the default size even when timed; `--time-smoothness` and
    /// `--time-cells` reach it, and are refused where there is none.
    #[test]
    fn moving_scenes_get_a_field_of_space_and_time() {
        let still = tiny_scene(8);
        let moving = tempfile::tempdir().expect("tempdir");
        let opts = crate::data::synth::SynthOptions {
            size: 8,
            supersample: 1,
            train_views: 3,
            val_views: 1,
            test_views: 1,
            animate: true,
            ..Default::default()
        };
        crate::data::synth::generate(&opts, moving.path(), &mut |_, _| {}).expect("synth");
        let fast = |args: &[&str], dir: &Path| match config(args, dir).expect("ok").model {
            ModelConfig::Fast(m) => m,
            ModelConfig::Vanilla(_) => panic!("fast model expected"),
        };
        let m = fast(&["--device", "cpu"], moving.path());
        // The default grid, with no prior.
        let motion = m.field.motion.expect("a field of space and time");
        assert_eq!(motion, SpaceTimeConfig::default());
        assert_eq!(m.time_smoothness, 0.0);
        let m = fast(
            &["--time-cells", "30", "--time-smoothness", "0.4"],
            moving.path(),
        );
        assert_eq!(m.field.motion, Some(SpaceTimeConfig::with_time_cells(30)));
        assert_eq!(m.time_smoothness, 0.4);
        for bad in ["3", "257", "many"] {
            let err = config(&["--time-cells", bad], moving.path()).expect_err(bad);
            assert!(err.to_string().contains("--time-cells"), "{bad}: {err}");
        }
        // A timed run keeps the default step size on a moving scene, unless told.
        let default = crate::model::FastModelConfig::default().samples_per_step;
        assert_eq!(
            fast(&["--minutes", "10"], moving.path()).samples_per_step,
            default
        );
        let told = fast(&["--minutes", "10", "--samples", "4096"], moving.path());
        assert_eq!(told.samples_per_step, 4096);
        let still_timed = fast(&["--minutes", "10"], still.path());
        assert_eq!(
            still_timed.samples_per_step,
            defaults::TIMED_SAMPLES_PER_STEP
        );
        assert!(fast(&["--no-dynamic"], moving.path())
            .field
            .motion
            .is_none());
        assert!(fast(&[], still.path()).field.motion.is_none());
        let m = fast(&["--time-smoothness", "0.01"], moving.path());
        assert_eq!(m.time_smoothness, 0.01);
        let m = fast(&["--no-time-smoothness"], moving.path());
        assert_eq!(m.time_smoothness, 0.0);
        for asked in [["--time-smoothness", "0.01"], ["--time-cells", "100"]] {
            let err = config(&asked, still.path()).expect_err("still");
            assert!(err.to_string().contains("space and time"), "{err}");
        }
        let err = config(&["--refine-cameras"], moving.path()).expect_err("refine");
        assert!(err.to_string().contains("--no-dynamic"), "{err}");
        // D-NeRF's vanilla model: for moving scenes only.
        let c = config(&["--preset", "dnerf"], moving.path()).expect("dnerf");
        assert!(c.model.is_dynamic() && c.model.kind() == "vanilla");
        let err = config(&["--preset", "dnerf"], still.path()).expect_err("still");
        assert!(err.to_string().contains("no frame"), "{err}");
    }
}
