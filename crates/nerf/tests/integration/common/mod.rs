//! Scenes and configurations the integration tests share.
#![allow(dead_code)] // builds without the GPU engine use a subset

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use nerf::data::synth::{self, SceneKind, SynthOptions};
use nerf::model::ModelConfig;
use nerf::train::TrainConfig;

/// The built-in chair (`size` pixels, one val view), rendered into `dir`.
pub fn chair_scene(dir: &Path, size: usize, train_views: usize, test_views: usize, seed: u64) {
    let opts = SynthOptions {
        scene: SceneKind::Chair,
        size,
        train_views,
        val_views: 1,
        test_views,
        supersample: 2,
        seed,
        animate: false,
    };
    synth::generate(&opts, dir, &mut |_, _| {}).expect("synth");
}

/// The small chair most tests train on: 40 training views, 4 test views.
pub fn small_scene(dir: &Path, size: usize) {
    chair_scene(dir, size, 40, 4, 1);
}

/// The built-in chair trained once for every test that only reads a trained fast model
/// (its PSNR floor, its mesh, its point cloud, test-pose fitting): 64 pixels, 60 training
/// and 3 test views, [`TRAINED_CHAIR_STEPS`] steps of [`fast_config`].
pub struct TrainedChair {
    pub data: PathBuf,
    pub run: PathBuf,
    pub summary: nerf::train::run::RunSummary,
    /// Kept for the life of the test process (statics are never dropped, so the folder
    /// stays in cargo's test scratch folder under `target/`).
    _dir: tempfile::TempDir,
}

pub const TRAINED_CHAIR_STEPS: u64 = 600;

/// The shared trained chair: the first test to ask trains it, the others wait for it.
pub fn trained_chair() -> &'static TrainedChair {
    static CHAIR: OnceLock<TrainedChair> = OnceLock::new();
    CHAIR.get_or_init(|| {
        let dir = tempfile::tempdir_in(env!("CARGO_TARGET_TMPDIR")).expect("tempdir");
        let data = dir.path().join("chair");
        chair_scene(&data, 64, 60, 3, 3);
        let run = dir.path().join("run");
        let config = fast_config(&data, TRAINED_CHAIR_STEPS);
        let summary =
            nerf::train::run::train(&cpu_run(&run, config), &mut |_| {}).expect("train the chair");
        TrainedChair {
            data,
            run,
            summary,
            _dir: dir,
        }
    })
}

/// `config`'s learning rate decaying to half its start rather than to the tenth or
/// quarter a full run decays to: a run of a few hundred steps then learns more in the
/// same steps (each test that uses it says by how much).
pub fn short_schedule(mut config: TrainConfig) -> TrainConfig {
    config.lr_final = 0.5 * config.lr_init;
    config
}

/// The fast defaults, shrunk for a test: smaller tables and batches, no validation or
/// intermediate checkpoints.
pub fn fast_config(data: &Path, steps: u64) -> TrainConfig {
    let mut c = TrainConfig::fast(data.to_path_buf());
    if let ModelConfig::Fast(m) = &mut c.model {
        m.field.grid.log2_table_size = 15;
        m.samples_per_step = 1 << 13;
        m.batch_samples = 1 << 12;
        m.occupancy.resolution = 64;
        m.occupancy.warmup_steps = 64;
        // Images of a few dozen pixels need no finer steps than this; more rays instead.
        m.steps_per_diagonal = 256.0;
    }
    c.steps = steps;
    c.val_every = 0;
    c.checkpoint_every = 0;
    c.chunk_rays = 256;
    c
}

/// The vanilla demo preset, shrunk for a test: 256 rays a step, a faster schedule, no
/// validation or intermediate checkpoints.
pub fn demo_config(data: &Path, steps: u64) -> TrainConfig {
    let mut c = TrainConfig::from_preset(data.to_path_buf(), "demo").expect("preset");
    c.steps = steps;
    c.batch_rays = 256;
    c.lr_init = 2e-3;
    c.lr_final = 5e-4;
    c.precrop_steps = 50;
    c.val_every = 0;
    c.checkpoint_every = 0;
    c
}

/// A new run of `config` into `out` on the CPU: no budget, no pause, not resumed.
pub fn cpu_run(out: &Path, config: TrainConfig) -> nerf::train::run::RunOptions {
    nerf::train::run::RunOptions {
        out: out.to_path_buf(),
        config,
        minutes: None,
        resume: false,
        pause_at: None,
        stop: None,
        device: nerf::engine::Device::Cpu,
    }
}

/// `nerf eval` of `run` on every `every`-th test view into `out` (cameras as given or
/// aligned, no progress).
pub fn eval_test(
    run: &nerf::train::folder::LoadedRun,
    every: usize,
    out: &Path,
) -> nerf::app::eval::EvalReport {
    let options = nerf::app::eval::EvalOptions::new(nerf::data::Split::Test, every);
    nerf::app::eval::evaluate(run, &options, out, &|_| {}).expect("eval")
}
