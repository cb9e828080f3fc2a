//! The small trained run the viewer's tests serve.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use nerf::data::synth::{self, SceneKind, SynthOptions};
use nerf::engine::Device;
use nerf::model::ModelConfig;
use nerf::train::run::{self, RunOptions};
use nerf::train::TrainConfig;

/// Training photo whose learned look [`trained_run`] makes loud.
pub const LOUD_PHOTO: usize = 3;

/// Steps of the shared run: long enough for the occupancy grid to empty the space around
/// the chair. A younger model's rays march through the whole box, which makes each of the
/// page's frames several times slower on two cores (docs/benchmarks.md, the CI section).
pub const TRAINED_STEPS: u64 = 500;

/// A small chair, turning over the capture (a moving scene, trained as a field of space
/// and time), trained for a few steps into `dir/run`, with a code per photo
/// (`--appearance`); photo [`LOUD_PHOTO`]'s code is then set far from the others, so
/// rendering with its look visibly differs from the mean.
///
/// Trained once per test process; each test gets its own copy of the scene and the run
/// (the viewer writes camera paths and renders into the run folder).
pub fn trained_run(dir: &Path) -> PathBuf {
    static TRAINED: OnceLock<tempfile::TempDir> = OnceLock::new();
    let trained = TRAINED.get_or_init(|| {
        let folder = tempfile::tempdir_in(env!("CARGO_TARGET_TMPDIR")).expect("tempdir");
        train_into(folder.path());
        folder
    });
    copy_folder(trained.path(), dir);
    dir.join("run")
}

/// Every file under `from`, copied to the same place under `to`.
fn copy_folder(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).expect("create folder");
    for entry in std::fs::read_dir(from).expect("read folder") {
        let entry = entry.expect("folder entry");
        let target = to.join(entry.file_name());
        if entry.file_type().expect("file type").is_dir() {
            copy_folder(&entry.path(), &target);
        } else {
            std::fs::copy(entry.path(), &target).expect("copy");
        }
    }
}

/// [`trained_run`]'s scene and run, made in `dir`.
fn train_into(dir: &Path) {
    let data = dir.join("chair");
    let opts = SynthOptions {
        scene: SceneKind::Chair,
        size: 32,
        train_views: 12,
        val_views: 1,
        test_views: 2,
        supersample: 1,
        seed: 1,
        animate: true,
    };
    synth::generate(&opts, &data, &mut |_, _| {}).expect("synth");
    let mut c = TrainConfig::fast(data);
    if let ModelConfig::Fast(m) = &mut c.model {
        m.field.grid.log2_table_size = 12;
        m.samples_per_step = 1 << 12;
        m.occupancy.resolution = 32;
        // A 32-pixel scene needs no finer marching steps than this: the page's frames
        // then cost a quarter of the samples.
        m.steps_per_diagonal = 256.0;
        m.field.appearance_dims = 8;
        m.field.appearance_images = 12;
        // A coarse one: a quarter turn of a 32-pixel chair needs no more.
        m.field.motion = Some(nerf::encoding::space_time_grid::SpaceTimeConfig {
            levels: 4,
            log2_table_size: 12,
            base_resolution: 8,
            max_resolution: 32,
            base_time_resolution: 2,
            max_time_resolution: 8,
        });
    }
    c.steps = TRAINED_STEPS;
    c.val_every = 0;
    c.checkpoint_every = 0;
    let out = dir.join("run");
    let options = RunOptions {
        out: out.clone(),
        config: c,
        minutes: None,
        resume: false,
        pause_at: None,
        stop: None,
        device: Device::Cpu,
    };
    run::train(&options, &mut |_| {}).expect("train");
    let mut run = nerf::train::folder::LoadedRun::open(&out).expect("open");
    let mut state = run.engine.state();
    let codes = run
        .engine
        .param_layout()
        .tensors
        .iter()
        .find(|t| t.name == "appearance.codes")
        .expect("appearance codes")
        .clone();
    let dims = codes.shape[1];
    let row = codes.offset + LOUD_PHOTO * dims;
    state.params[row..row + dims].fill(3.0);
    run.engine.set_state(state).expect("state");
    let ckpt = out.join(nerf::train::folder::CHECKPOINT_FILE);
    nerf::train::folder::save_checkpoint(&ckpt, run.engine.as_ref(), run.step, 1, 0.0)
        .expect("checkpoint");
}
