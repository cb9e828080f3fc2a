//! `nerf export-cameras`: a run's training cameras, refined, as a `transforms.json`.

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::Args;
use nerf::data::scene::PlacedBox;
use nerf::data::Split;
use nerf::train::refined_cameras::RunCameras;

#[derive(Args)]
pub struct ExportCamerasArgs {
    /// Run folder written by `nerf train`.
    #[arg(long)]
    run: PathBuf,
    #[command(flatten)]
    scene: nerf::train::run_scene::SceneOverride,
    /// The transforms.json to write (instant-ngp format, in the scene's placed frame, with
    /// absolute image paths): the training cameras as the run refined them.
    #[arg(long)]
    out: PathBuf,
}

pub fn run(a: ExportCamerasArgs) -> Result<()> {
    let run = super::open_run(&a.run, nerf::engine::Device::Cpu, &a.scene)?;
    let scene = run.config.open_scene(1)?;
    let cameras = RunCameras::of(&run)?;
    let mut entries = Vec::new();
    for (k, &f) in scene.train.iter().enumerate() {
        let frame = &scene.frames[f];
        let mut camera = frame.camera.clone();
        if let Some(c) = &cameras {
            camera.c2w = c.refined[k];
        }
        let image = std::fs::canonicalize(&frame.image).unwrap_or(frame.image.clone());
        entries.push(nerf::data::transforms::frame_entry(
            &camera,
            &image.display().to_string(),
        ));
    }
    let placed = PlacedBox {
        bound: scene.bound,
        contract: scene.contract,
        near: scene.near,
        far: scene.far,
    };
    let doc = nerf::data::transforms::placed_document(entries, &placed);
    nerf::io::write_json(&a.out, &doc).with_context(|| format!("writing {}", a.out.display()))?;
    match &cameras {
        Some(c) => {
            let e = c.error();
            let kind = if c.refined_by_model {
                "refined"
            } else {
                "perturbed (not refined)"
            };
            println!(
                "wrote {} {kind} training cameras to {}; against the given poses (after a \
                 similarity alignment): {:.3} degrees (median {:.3}, worst {:.3}), {:.4} units \
                 ({:.2}% of the camera radius)",
                scene.cameras(Split::Train).len(),
                a.out.display(),
                e.rotation_deg,
                e.rotation_deg_median,
                e.rotation_deg_max,
                e.translation,
                e.translation_percent_of_radius
            );
        }
        None => println!(
            "wrote {} training cameras (the run did not refine them) to {}",
            scene.train.len(),
            a.out.display()
        ),
    }
    Ok(())
}
