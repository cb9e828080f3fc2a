//! The small trained run the viewer's tests serve.

use std::path::{Path, PathBuf};

use nerf::data::synth::{self, SceneKind, SynthOptions};
use nerf::engine::Device;
use nerf::model::ModelConfig;
use nerf::train::run::{self, RunOptions};
use nerf::train::TrainConfig;

/// A small chair trained for a few steps into `dir/run`.
pub fn trained_run(dir: &Path) -> PathBuf {
    let data = dir.join("chair");
    let opts = SynthOptions {
        scene: SceneKind::Chair,
        size: 32,
        train_views: 12,
        val_views: 1,
        test_views: 2,
        supersample: 1,
        seed: 1,
    };
    synth::generate(&opts, &data, &mut |_, _| {}).expect("synth");
    let mut c = TrainConfig::fast(data);
    if let ModelConfig::Fast(m) = &mut c.model {
        m.field.grid.log2_table_size = 12;
        m.samples_per_step = 1 << 12;
        m.occupancy.resolution = 32;
    }
    c.steps = 60;
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
    out
}
