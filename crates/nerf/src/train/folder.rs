//! A run folder on disk: `config.json` (the whole configuration), `checkpoint.safetensors`
//! (an engine's state, see `checkpoint`), `metrics.jsonl` and validation images. Loading a
//! run gives an engine ready to render, whichever engine wrote it.

use std::path::Path;

use super::{run_scene, TrainConfig};
use crate::checkpoint::{self, Checkpoint};
use crate::engine::{self, Engine, EngineState};
use crate::error::{NerfError, Result};

pub const CONFIG_FILE: &str = "config.json";
pub const CHECKPOINT_FILE: &str = "checkpoint.safetensors";
pub const METRICS_FILE: &str = "metrics.jsonl";

/// A trained model loaded from a run folder, for evaluation and rendering.
pub struct LoadedRun {
    pub config: TrainConfig,
    pub engine: Box<dyn Engine>,
    pub step: u64,
}

impl LoadedRun {
    /// The run in `dir`, on the CPU engine.
    pub fn open(dir: &Path) -> Result<LoadedRun> {
        LoadedRun::open_on(dir, engine::Device::Cpu)
    }

    /// The run in `dir`, on `device` (checkpoints are the same files on every device).
    pub fn open_on(dir: &Path, device: engine::Device) -> Result<LoadedRun> {
        LoadedRun::open_with(dir, device, &run_scene::SceneOverride::default())
    }

    /// The run in `dir`, on `device`, its scene where `scene` says when it says.
    pub fn open_with(
        dir: &Path,
        device: engine::Device,
        scene: &run_scene::SceneOverride,
    ) -> Result<LoadedRun> {
        let mut config = read_config(dir)?;
        if let Some(data) = &scene.data {
            if !data.is_dir() {
                return Err(NerfError::format(data, "--data: is not a folder"));
            }
            config.data = std::fs::canonicalize(data).unwrap_or_else(|_| data.clone());
        }
        let model = config.model.for_inference();
        let mut engine = engine::open_on(device, &model, config.engine_options(), config.seed)?;
        let ckpt = load_checkpoint(&dir.join(CHECKPOINT_FILE), engine.as_mut())?;
        Ok(LoadedRun {
            config,
            engine,
            step: ckpt.step,
        })
    }
}

/// The run's `config.json`, checked as the command line's options are (it may have been
/// edited). A folder without one is not a run.
pub fn read_config(dir: &Path) -> Result<TrainConfig> {
    let path = dir.join(CONFIG_FILE);
    if !dir.is_dir() {
        return Err(NerfError::format(
            dir,
            "is not a run folder (no such folder)",
        ));
    }
    if !path.exists() {
        return Err(NerfError::format(
            dir,
            format!("is not a run folder (no {CONFIG_FILE}); `nerf train --out` makes one"),
        ));
    }
    let mut config: TrainConfig = crate::io::read_json(&path)?;
    config
        .validate()
        .map_err(|e| NerfError::format(&path, e.to_string()))?;
    config.data = run_scene::resolved(dir, &config.data);
    config.read_from = run_scene::ReadFrom(Some(dir.to_path_buf()));
    Ok(config)
}

/// Writes the run's `config.json`, naming its scene as `run_scene::stored_form` says.
pub fn write_config(dir: &Path, config: &TrainConfig) -> Result<()> {
    let mut stored = config.clone();
    stored.data = run_scene::stored_form(dir, &config.data);
    crate::io::write_json(&dir.join(CONFIG_FILE), &stored)
}

/// Writes `engine`'s state with the run's step, seed and elapsed time to `path`.
pub fn save_checkpoint(
    path: &Path,
    engine: &dyn Engine,
    step: u64,
    seed: u64,
    elapsed_seconds: f64,
) -> Result<()> {
    let EngineState {
        params,
        adam_m,
        adam_v,
        adam_t,
        buffers,
    } = engine.state();
    checkpoint::save(
        path,
        engine.param_layout(),
        &engine.buffer_layout(),
        &Checkpoint {
            step,
            seed,
            elapsed_seconds,
            params,
            adam_m,
            adam_v,
            adam_t,
            buffers,
        },
    )
}

/// Reads the checkpoint at `path` into `engine`; returns it (its state moved out).
pub fn load_checkpoint(path: &Path, engine: &mut dyn Engine) -> Result<Checkpoint> {
    let mut ckpt = checkpoint::load(path, engine.param_layout(), &engine.buffer_layout())?;
    engine.set_state(EngineState {
        params: std::mem::take(&mut ckpt.params),
        adam_m: std::mem::take(&mut ckpt.adam_m),
        adam_v: std::mem::take(&mut ckpt.adam_v),
        adam_t: ckpt.adam_t,
        buffers: std::mem::take(&mut ckpt.buffers),
    })?;
    Ok(ckpt)
}
