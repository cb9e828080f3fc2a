//! A training run on disk: `config.json`, `checkpoint.safetensors`, `metrics.jsonl` and
//! validation images in `val/`. Runs stop at a step count or a wall-clock budget, whichever
//! comes first, always leaving a checkpoint; `resume` continues from it exactly.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};

use super::folder::{load_checkpoint, save_checkpoint};
pub use super::folder::{LoadedRun, CHECKPOINT_FILE, CONFIG_FILE, METRICS_FILE};
use super::refined_cameras::{PoseError, StartingCameras};
use super::stuck_cameras::{CheckReport, Checker};
use super::{StepStats, TrainConfig, Trainer};
use crate::data::{image::save_rgb_png, Split, View};
use crate::error::{NerfError, Result};
use crate::views::RenderSettings;

/// The shortest time between two periodic checkpoints. On a GPU 500 fast-model steps take
/// about two seconds, and a checkpoint (field and Adam moments, about 200 MiB) would cost
/// as much as the steps; a killed run loses at most this much work beyond the interval.
/// The first periodic checkpoint and the final one are never held back.
const MIN_CHECKPOINT_INTERVAL: Duration = Duration::from_secs(30);

/// How often a run that perturbed its poses (`--perturb-poses`, so the true ones are
/// known) measures how far its refined cameras are from them, as BARF's training reports.
/// The measure reads the parameters once (a copy, or a download from a GPU) and aligns 100
/// cameras: far below the cost of this many steps.
pub const POSE_ERROR_EVERY: u64 = 250;

/// How to run (beyond the config that defines the run).
#[derive(Clone, Debug)]
pub struct RunOptions {
    pub out: PathBuf,
    pub config: TrainConfig,
    /// Stop after this much wall-clock time in this session (a cap on a step schedule;
    /// a time schedule is the config's `time_budget_s`).
    pub minutes: Option<f64>,
    /// Continue the run in `out` from its checkpoint (its saved config wins).
    pub resume: bool,
    /// Pause (with a checkpoint) once this step is reached, before `steps`; the learning-rate
    /// schedule still spans the whole run.
    pub pause_at: Option<u64>,
    /// Set to a non-zero value (a signal number, say) to stop after the current step with
    /// a checkpoint; the value comes back in [`StopReason::Interrupted`].
    pub stop: Option<std::sync::Arc<std::sync::atomic::AtomicUsize>>,
    /// Where the model trains (not saved: a run can resume on another device).
    pub device: crate::engine::Device,
}

/// Why a run stopped.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum StopReason {
    /// All configured steps are done.
    Steps,
    /// The `--minutes` budget ran out (a session cap, or the end of a time schedule).
    TimeBudget,
    /// `pause_at` was reached.
    Paused,
    /// [`RunOptions::stop`] was set to this value (a signal number).
    Interrupted(usize),
}

/// What a run reports as it goes.
#[derive(Debug)]
pub enum Event<'a> {
    Started {
        config: &'a TrainConfig,
        views: usize,
        width: usize,
        height: usize,
        params: usize,
        resumed_from: Option<u64>,
        /// Training seconds of earlier sessions (0 for a new run).
        elapsed_s: f64,
    },
    Step(&'a StepStats),
    Validation {
        step: u64,
        psnr: f32,
        image: &'a Path,
    },
    Checkpoint {
        step: u64,
    },
    /// How far the refined training cameras are from the true poses (runs that perturbed
    /// them), every [`POSE_ERROR_EVERY`] steps and at the end.
    PoseError {
        step: u64,
        error: &'a PoseError,
    },
    /// The model after a step, for a live view (`nerf train --view`): a listener that
    /// wants its weights takes `engine.state()`; one that does not pays nothing.
    Model {
        step: u64,
        engine: &'a dyn crate::engine::Engine,
    },
    /// Something decided about the run that a user should hear.
    Note(&'a str),
    /// Something gone wrong that training works around (a camera left out).
    Warning(&'a str),
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct RunSummary {
    pub steps: u64,
    pub reason: StopReason,
    pub seconds: f64,
    /// PSNR of the last training batch (NaN when no step ran in this session).
    pub last_psnr: f32,
    /// The latest validation PSNR of the run (this session or, after a resume, an
    /// earlier one), if any validation image was rendered.
    pub val_psnr: Option<(u64, f32)>,
}

#[derive(Serialize)]
struct MetricLine {
    step: u64,
    loss: f32,
    psnr: f32,
    lr: f32,
    rays: usize,
    samples: usize,
    elapsed_s: f64,
}

#[derive(Serialize)]
struct PoseLine<'a> {
    step: u64,
    pose_error: &'a PoseError,
}

#[derive(Serialize, Deserialize)]
struct CheckLine {
    step: u64,
    camera_check: CheckReport,
}

#[derive(Serialize)]
struct ValLine<'a> {
    step: u64,
    val_psnr: f32,
    image: &'a str,
}

/// Trains the run described by `opts`, calling `on_event` as it goes.
pub fn train(opts: &RunOptions, on_event: &mut dyn FnMut(Event)) -> Result<RunSummary> {
    let out = &opts.out;
    let config_path = out.join(CONFIG_FILE);
    let ckpt_path = out.join(CHECKPOINT_FILE);
    let metrics_path = out.join(METRICS_FILE);
    if !opts.resume {
        // Before the folder is made: a refused configuration leaves nothing behind.
        opts.config.validate()?;
    }
    let _lock = super::lock::RunLock::acquire(out)?;
    // A folder with a config but no checkpoint holds a run that died before its first
    // checkpoint: it starts again from step 0 (resumed or not), with fresh metrics.
    let from_checkpoint = ckpt_path.exists();
    let config = if opts.resume {
        if !config_path.exists() {
            return Err(NerfError::Config(format!(
                "cannot resume: {} holds no run (no {CONFIG_FILE})",
                out.display()
            )));
        }
        let mut config = super::folder::read_config(out)?;
        if from_checkpoint {
            let at = crate::checkpoint::read_step(&ckpt_path)?;
            if opts.config.steps < at {
                return Err(NerfError::Config(format!(
                    "--steps {} is below the step the run's checkpoint is at ({at})",
                    opts.config.steps
                )));
            }
        }
        if (config.steps, config.time_budget_s) != (opts.config.steps, opts.config.time_budget_s) {
            config.steps = opts.config.steps;
            config.time_budget_s = opts.config.time_budget_s;
            super::folder::write_config(out, &config)?;
        }
        config
    } else {
        if from_checkpoint {
            return Err(NerfError::Config(format!(
                "{} already holds a run; pass --resume to continue it or choose another --out",
                out.display()
            )));
        }
        super::folder::write_config(out, &opts.config)?;
        opts.config.clone()
    };
    if !out.join(super::run_scene::SCENE_FILE).exists() {
        // What rendering needs of the scene, kept in the run (see `run_scene`).
        // At full resolution: a run's downscale applies when the scene is opened.
        super::run_scene::save_snapshot(out, &super::run_scene::open(&config, 1)?)?;
    }
    if !from_checkpoint {
        if metrics_path.exists() {
            on_event(Event::Note(
                "the folder holds a run that stopped before its first checkpoint: starting it \
                 again from step 0 with fresh metrics",
            ));
        }
        remove_if_present(&metrics_path)?;
    }

    let (data, total) = config.training_split()?;
    if let Some(kept) = &config.train_views {
        if kept.is_subset(total) {
            let list: Vec<String> = config
                .kept_train_views(total)?
                .iter()
                .map(|i| i.to_string())
                .collect();
            on_event(Event::Note(&format!(
                "training on {} of the {total} training views (--train-views {kept}): {}",
                list.len(),
                list.join(", ")
            )));
        }
    }
    let val_view = validation_view(&config)?;
    let (width, height) = data.image_size();
    let views = data.views.len();
    if let crate::model::ModelConfig::Vanilla(m) = &config.model {
        let regularised = m.free_nerf.is_some() || m.reg_nerf.is_some();
        if !regularised && views <= crate::model::few_view::FEW_VIEWS && !opts.resume {
            on_event(Event::Note(&format!(
                "{views} training views: the paper's model overfits few photos (floaters, or \
                 nothing but the background from other views); --preset freenerf adds \
                 FreeNeRF's regularisers, --preset regnerf RegNeRF's"
            )));
        }
    }
    let mut trainer = Trainer::on(opts.device, config.clone(), data)?;
    // The truth is known only for poses the run moved itself.
    let true_cameras = match config.perturb_poses {
        Some(_) => Some(StartingCameras::of(&config)?),
        None => None,
    };
    on_event(Event::Note(&format!(
        "training on {}",
        trainer.engine.describe()
    )));
    // A new run heard this from its defaults (`defaults::engine_for`); a resumed one here.
    if opts.resume {
        let engine = trainer.engine.as_ref();
        if let Some(note) = crate::engine::cpu_fallback_note(opts.device, engine, &config.model) {
            on_event(Event::Note(&note));
        }
    }
    let mut elapsed_before = 0.0;
    let mut resumed_from = None;
    if opts.resume && from_checkpoint {
        let ckpt = load_checkpoint(&ckpt_path, trainer.engine.as_mut())?;
        trainer.step = ckpt.step;
        elapsed_before = ckpt.elapsed_seconds;
        resumed_from = Some(ckpt.step);
        truncate_metrics(&out.join(METRICS_FILE), ckpt.step)?;
    }
    // Refinement's checks for stuck cameras; cameras an earlier session left out stay out.
    let mut checker = Checker::of(&trainer);
    if let Some(checker) = &mut checker {
        checker.resume(&mut trainer, &camera_checks(&metrics_path));
        if !checker.left_out.is_empty() {
            let list: Vec<String> = checker.left_out.iter().map(|k| k.to_string()).collect();
            let (who, verb) = match list.len() {
                1 => ("camera", "stays"),
                _ => ("cameras", "stay"),
            };
            on_event(Event::Note(&format!(
                "{who} {} {verb} left out of training (no pose explained their photos)",
                list.join(", ")
            )));
        }
    }
    on_event(Event::Started {
        config: &config,
        views,
        width,
        height,
        params: trainer.engine.param_layout().total,
        resumed_from,
        elapsed_s: elapsed_before,
    });

    let mut val_psnr = last_validation(&metrics_path);
    let mut metrics = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(&metrics_path)
        .map_err(|e| NerfError::write(&metrics_path, e))?;
    let start = Instant::now();
    let budget = opts.minutes.map(|m| m * 60.0);
    let mut last_psnr = f32::NAN;
    let mut last_periodic_save = None;
    let save = |trainer: &Trainer, elapsed: f64| -> Result<()> {
        save_checkpoint(
            &ckpt_path,
            trainer.engine.as_ref(),
            trainer.step,
            trainer.config.seed,
            elapsed,
        )
    };
    let reason = loop {
        trainer.elapsed_s = elapsed_before + start.elapsed().as_secs_f64();
        if trainer.step >= config.steps {
            break StopReason::Steps;
        }
        if config.finished(trainer.step, trainer.elapsed_s) {
            break StopReason::TimeBudget;
        }
        if budget.is_some_and(|b| start.elapsed().as_secs_f64() >= b) {
            break StopReason::TimeBudget;
        }
        if opts.pause_at.is_some_and(|p| trainer.step >= p) {
            break StopReason::Paused;
        }
        if let Some(signal) = opts.stop.as_ref().map(|s| s.load(Ordering::Relaxed)) {
            if signal != 0 {
                break StopReason::Interrupted(signal);
            }
        }
        let before = config.progress(trainer.step, trainer.elapsed_s);
        let stats = trainer.step()?;
        last_psnr = stats.psnr;
        if let Some(checker) = &mut checker {
            let after =
                config.progress(trainer.step, elapsed_before + start.elapsed().as_secs_f64());
            if let Some(last) = Checker::due(before, after, stats.step) {
                let report = checker.run(&mut trainer, last)?;
                for s in &report.stuck {
                    let line = super::stuck_cameras::describe(s, stats.step);
                    on_event(if s.left_out {
                        Event::Warning(&line)
                    } else {
                        Event::Note(&line)
                    });
                }
                append_line(
                    &mut metrics,
                    &metrics_path,
                    &CheckLine {
                        step: stats.step,
                        camera_check: report,
                    },
                )?;
            }
        }
        let elapsed = elapsed_before + start.elapsed().as_secs_f64();
        let line = MetricLine {
            step: stats.step,
            loss: stats.loss,
            psnr: stats.psnr,
            lr: stats.lr,
            rays: stats.rays,
            samples: stats.samples,
            elapsed_s: elapsed,
        };
        append_line(&mut metrics, &metrics_path, &line)?;
        on_event(Event::Step(&stats));
        if let Some(cameras) = &true_cameras {
            if stats.step % POSE_ERROR_EVERY == 0 || stats.step == config.steps {
                let error = pose_error(cameras, &trainer);
                let line = PoseLine {
                    step: stats.step,
                    pose_error: &error,
                };
                append_line(&mut metrics, &metrics_path, &line)?;
                on_event(Event::PoseError {
                    step: stats.step,
                    error: &error,
                });
            }
        }
        on_event(Event::Model {
            step: stats.step,
            engine: trainer.engine.as_ref(),
        });
        if config.val_every > 0 && stats.step % config.val_every == 0 {
            if let Some(view) = &val_view {
                let image = out.join("val").join(format!("step_{:07}.png", stats.step));
                let psnr = validate(&trainer, view, &image)?;
                val_psnr = Some((stats.step, psnr));
                let name = image
                    .strip_prefix(out)
                    .unwrap_or(&image)
                    .to_string_lossy()
                    .into_owned();
                append_line(
                    &mut metrics,
                    &metrics_path,
                    &ValLine {
                        step: stats.step,
                        val_psnr: psnr,
                        image: &name,
                    },
                )?;
                on_event(Event::Validation {
                    step: stats.step,
                    psnr,
                    image: &image,
                });
            }
        }
        if config.checkpoint_every > 0
            && stats.step % config.checkpoint_every == 0
            && last_periodic_save.is_none_or(|t: Instant| t.elapsed() >= MIN_CHECKPOINT_INTERVAL)
        {
            save(&trainer, elapsed)?;
            last_periodic_save = Some(Instant::now());
            on_event(Event::Checkpoint { step: stats.step });
        }
    };
    let seconds = elapsed_before + start.elapsed().as_secs_f64();
    save(&trainer, seconds)?;
    on_event(Event::Checkpoint { step: trainer.step });
    Ok(RunSummary {
        steps: trainer.step,
        reason,
        seconds,
        last_psnr,
        val_psnr,
    })
}

fn pose_error(cameras: &StartingCameras, trainer: &Trainer) -> PoseError {
    let state = trainer.engine.state();
    cameras
        .corrected_by(trainer.engine.param_layout(), &state.params)
        .error()
}

/// The stuck-camera checks a metrics file records, in order.
fn camera_checks(path: &Path) -> Vec<CheckReport> {
    let Ok(text) = std::fs::read_to_string(path) else {
        return Vec::new();
    };
    text.lines()
        .filter_map(|l| serde_json::from_str::<CheckLine>(l).ok())
        .map(|c| c.camera_check)
        .collect()
}

/// The latest `val_psnr` line of a metrics file, if any.
fn last_validation(path: &Path) -> Option<(u64, f32)> {
    let text = std::fs::read_to_string(path).ok()?;
    text.lines().rev().find_map(|l| {
        let v: serde_json::Value = serde_json::from_str(l).ok()?;
        Some((
            v.get("step")?.as_u64()?,
            v.get("val_psnr")?.as_f64()? as f32,
        ))
    })
}

fn remove_if_present(path: &Path) -> Result<()> {
    match std::fs::remove_file(path) {
        Err(e) if e.kind() != std::io::ErrorKind::NotFound => Err(NerfError::write(path, e)),
        _ => Ok(()),
    }
}

/// The first validation view (first training view if the scene has no val split), at the
/// validation resolution.
fn validation_view(config: &TrainConfig) -> Result<Option<View>> {
    if config.val_every == 0 {
        return Ok(None);
    }
    let scene = config.open_scene(config.val_downscale)?;
    let split = if scene.has_val() {
        Split::Val
    } else {
        Split::Train
    };
    let data = scene.load(split, usize::MAX)?;
    Ok(data.views.into_iter().next())
}

fn validate(trainer: &Trainer, view: &View, path: &Path) -> Result<f32> {
    let bg = trainer.config.background.eval_colour();
    let settings = RenderSettings {
        time: view.time,
        ..RenderSettings::of_dataset(&trainer.data, bg)
    };
    let r = crate::views::render_view(trainer.engine.as_ref(), &view.camera, &settings, &|_| {});
    if let Some(dir) = path.parent() {
        crate::io::create_dir(dir)?;
    }
    save_rgb_png(path, r.width, r.height, &r.rgb)?;
    Ok(crate::metrics::psnr(&r.rgb, &view.image.composite(bg)))
}

fn append_line<T: Serialize>(file: &mut std::fs::File, path: &Path, value: &T) -> Result<()> {
    let mut line = serde_json::to_string(value)
        .map_err(|e| NerfError::write(path, std::io::Error::other(e)))?;
    line.push('\n');
    file.write_all(line.as_bytes())
        .map_err(|e| NerfError::write(path, e))
}

/// Drops metric lines written after the checkpoint a run resumes from.
fn truncate_metrics(path: &Path, step: u64) -> Result<()> {
    let Ok(text) = std::fs::read_to_string(path) else {
        return Ok(());
    };
    let kept: String = text
        .lines()
        .filter(|l| {
            serde_json::from_str::<serde_json::Value>(l)
                .ok()
                .and_then(|v| v.get("step").and_then(|s| s.as_u64()))
                .is_some_and(|s| s <= step)
        })
        .flat_map(|l| [l, "\n"])
        .collect();
    crate::io::write_atomic(path, kept.as_bytes())
}
