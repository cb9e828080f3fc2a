//! One file per subcommand: argument glue between the command line and the library.

pub mod bench;
pub mod capture;
pub mod demo;
pub mod eval;
pub mod export_cameras;
pub mod mesh;
pub mod points;
pub mod render;
pub mod scene;
pub mod synth;
pub mod train;

use std::path::Path;

use nerf::train::folder::LoadedRun;
use nerf::train::run_scene::SceneOverride;

/// The run in `dir` on `device`, its scene where `--data` says, and a `note:` when the
/// scene was found somewhere other than where the run says, or not at all.
pub fn open_run(
    dir: &Path,
    device: nerf::engine::Device,
    scene: &SceneOverride,
) -> anyhow::Result<LoadedRun> {
    let run = LoadedRun::open_with(dir, device, scene)?;
    if let Some(note) = nerf::train::run_scene::missing_note(&run.config) {
        eprintln!("note: {note}");
    }
    let model = &run.config.model;
    if let Some(note) = nerf::engine::cpu_fallback_note(device, run.engine.as_ref(), model) {
        eprintln!("note: {note}");
    }
    Ok(run)
}
