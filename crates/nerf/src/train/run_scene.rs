//! Where a run finds its scene. `config.json` names the scene relative to the run folder
//! when the scene sits beside it (inside the folder that holds the run, as `nerf demo`
//! lays them out), and absolutely otherwise, so a run works from any directory and after
//! the run and its scene move together. A scene not where the run says is looked for
//! beside the run and inside it; `--data` on the command line overrides. A run also keeps
//! its cameras (`scene.json`, see `data::snapshot`), so rendering works without the photos.

use std::path::{Path, PathBuf};

use super::TrainConfig;
use crate::data::scene::Scene;
use crate::data::snapshot::SceneSnapshot;
use crate::error::{NerfError, Result};

/// The run's record of its scene's cameras and bounds.
pub const SCENE_FILE: &str = "scene.json";

/// Where a config was read from (its run folder), when it was. Not part of the
/// configuration: never saved, and equal to any other.
#[derive(Clone, Debug, Default)]
pub struct ReadFrom(pub Option<PathBuf>);

impl PartialEq for ReadFrom {
    fn eq(&self, _: &ReadFrom) -> bool {
        true
    }
}

/// `--data` of the commands that read a run: the scene, when it is not where the run says.
#[derive(Clone, Debug, Default, clap::Args)]
pub struct SceneOverride {
    /// The run's scene folder, when it is not where the run says (moved, or the run copied
    /// to another machine). Rendering, meshes, points and the viewer work without it (the
    /// run keeps its cameras); evaluation reads the photos.
    #[arg(long = "data", value_name = "DIR")]
    pub data: Option<PathBuf>,
}

/// How `config.json` names the scene at `scene` of the run in `run_dir`: relative to the
/// run folder when the scene lies inside the run folder's parent, absolute otherwise.
pub fn stored_form(run_dir: &Path, scene: &Path) -> PathBuf {
    let (Ok(run), Ok(scene)) = (std::fs::canonicalize(run_dir), std::fs::canonicalize(scene))
    else {
        return scene.to_path_buf();
    };
    if let Ok(inside) = scene.strip_prefix(&run) {
        return inside.to_path_buf();
    }
    match run.parent().map(|p| scene.strip_prefix(p)) {
        Some(Ok(beside)) => Path::new("..").join(beside),
        _ => scene,
    }
}

/// The scene path `stored` in the config of the run in `run_dir`, as a path to open.
pub fn resolved(run_dir: &Path, stored: &Path) -> PathBuf {
    if stored.is_absolute() {
        stored.to_path_buf()
    } else {
        run_dir.join(stored)
    }
}

/// The places a run's scene is looked for, in order: where the config says, then a
/// folder of the same name beside the run folder and inside it (a run and its scene moved
/// or copied together; configs written before paths were stored relative).
pub fn candidates(config: &TrainConfig) -> Vec<PathBuf> {
    let mut out = vec![config.data.clone()];
    if let (Some(run), Some(name)) = (&config.read_from.0, config.data.file_name()) {
        let beside = run.parent().map(|p| p.join(name));
        out.extend(beside.into_iter().chain([run.join(name)]));
    }
    let mut seen = Vec::new();
    out.retain(|p| {
        let key = std::fs::canonicalize(p).unwrap_or_else(|_| p.clone());
        let new = !seen.contains(&key);
        seen.push(key);
        new
    });
    out
}

/// The run's scene at `1/downscale` of its resolution. For a config read from a run folder:
/// from the scene's folder when it is found, else rebuilt from the run's `scene.json`
/// (without photos), else an error that names every place looked and the way out.
pub fn open(config: &TrainConfig, downscale: usize) -> Result<Scene> {
    if config.read_from.0.is_none() {
        // A run being made: the scene is where the command line says, or an error says
        // what is wrong with that folder.
        return Scene::open(&config.data, &config.scene, downscale);
    }
    let looked = candidates(config);
    if let Some(dir) = looked.iter().find(|d| d.is_dir()) {
        return Scene::open(dir, &config.scene, downscale);
    }
    let run = config.read_from.0.as_deref().unwrap_or(Path::new("."));
    let missing = format!("{}: {}", run.display(), not_found(&looked));
    if run.join(SCENE_FILE).is_file() {
        return Ok(SceneSnapshot::load(&run.join(SCENE_FILE))?.scene(downscale, missing));
    }
    Err(NerfError::NotFound(format!(
        "{missing}; pass --data DIR to say where it is"
    )))
}

/// What to tell a user about where a run's scene was found, for a config read from a run
/// folder: `None` when it is where the config says; else the folder used instead, or that
/// the run renders from the cameras it keeps (`open` rebuilds the scene from them).
pub fn missing_note(config: &TrainConfig) -> Option<String> {
    let run = config.read_from.0.as_deref()?;
    let looked = candidates(config);
    let first = looked.first()?;
    if first.is_dir() {
        return None;
    }
    if let Some(found) = looked.iter().find(|d| d.is_dir()) {
        return Some(format!(
            "the run's scene is not at {}: using {} (--data DIR says where it is)",
            first.display(),
            found.display()
        ));
    }
    if !run.join(SCENE_FILE).is_file() {
        return None;
    }
    Some(format!(
        "{}: using the cameras the run keeps in {SCENE_FILE}; --data DIR says where the \
         scene is",
        not_found(&looked)
    ))
}

/// "the run's scene is not found (looked in A, B, C)".
fn not_found(looked: &[PathBuf]) -> String {
    let places: Vec<String> = looked.iter().map(|p| p.display().to_string()).collect();
    format!(
        "the run's scene is not found (looked in {})",
        places.join(", ")
    )
}

/// Records the scene's cameras in the run folder (see [`SCENE_FILE`]).
pub fn save_snapshot(run_dir: &Path, scene: &Scene) -> Result<()> {
    SceneSnapshot::of(scene).save(&run_dir.join(SCENE_FILE))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn beside_is_relative_and_elsewhere_absolute() {
        let root = tempfile::tempdir().expect("tempdir");
        let (run, scene, far) = (
            root.path().join("demo/run"),
            root.path().join("demo/chair"),
            root.path().join("data/lego"),
        );
        for d in [&run, &scene, &far, &run.join("inner")] {
            std::fs::create_dir_all(d).expect("mkdir");
        }
        assert_eq!(stored_form(&run, &scene), Path::new("../chair"));
        assert_eq!(stored_form(&run, &run.join("inner")), Path::new("inner"));
        let stored = stored_form(&run, &far);
        assert!(stored.is_absolute(), "{}", stored.display());
        assert_eq!(
            std::fs::canonicalize(resolved(&run, Path::new("../chair"))).expect("exists"),
            std::fs::canonicalize(&scene).expect("exists")
        );
        assert_eq!(resolved(&run, &stored), stored);
    }
}
