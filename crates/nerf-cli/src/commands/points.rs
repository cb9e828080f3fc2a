//! `nerf points`: a coloured point cloud from rendered depth of the training views.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{bail, Result};
use clap::Args;
use nerf::mesh::export::write_mesh;

use crate::progress::bar;

#[derive(Args)]
pub struct PointsArgs {
    /// Run folder written by `nerf train`.
    #[arg(long)]
    run: PathBuf,
    #[command(flatten)]
    scene: nerf::train::run_scene::SceneOverride,
    #[command(flatten)]
    device: nerf::engine::DeviceArg,
    /// Output file (.ply, binary, coloured vertices).
    #[arg(long)]
    out: PathBuf,
    /// Use every K-th training view.
    #[arg(long, default_value_t = 10)]
    every: usize,
    /// Render the views at 1/N of the training resolution.
    #[arg(long, default_value_t = 2)]
    downscale: usize,
    /// Keep pixels at least this opaque (drops background and soft edges).
    #[arg(long, default_value_t = 0.95, value_parser = nerf::args::fraction, allow_negative_numbers = true)]
    min_opacity: f32,
    /// Models of a moving scene: the moment every view is rendered at, from 0 (the first
    /// photo's) to 1 (the last's).
    #[arg(long, default_value_t = 0.0, value_parser = nerf::args::fraction)]
    time: f32,
}

pub fn run(a: PointsArgs) -> Result<()> {
    if a.every == 0 || a.downscale == 0 {
        bail!("--every and --downscale must be at least 1");
    }
    if !a
        .out
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("ply"))
    {
        bail!("{}: point clouds are written as .ply", a.out.display());
    }
    let run = super::open_run(&a.run, a.device.device, &a.scene)?;
    let config = &run.config;
    let scene = config.open_scene(a.downscale)?;
    let mut cameras = scene.cameras(nerf::data::Split::Train);
    // A run that refined its cameras sees the training views from where it put them.
    if let Some(refined) = nerf::train::refined_cameras::RunCameras::of(&run)? {
        for (c, pose) in cameras.iter_mut().zip(&refined.refined) {
            c.c2w = *pose;
        }
    }
    let cameras: Vec<_> = cameras.into_iter().step_by(a.every).collect();
    let settings = nerf::views::RenderSettings {
        time: Some(a.time),
        ..nerf::views::RenderSettings::of_scene(&scene, config.background.eval_colour())
    };
    let t0 = Instant::now();
    let pb = bar(cameras.len() as u64, "views");
    let (points, colours) = nerf::mesh::points::from_views(
        run.engine.as_ref(),
        &cameras,
        &settings,
        a.min_opacity,
        &mut |done| pb.set_position(done as u64),
    );
    pb.finish_and_clear();
    if points.is_empty() {
        bail!(
            "no pixel reached opacity {}; lower --min-opacity",
            a.min_opacity
        );
    }
    let cloud = nerf::mesh::Mesh {
        vertices: points,
        triangles: Vec::new(),
    };
    if !a
        .out
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("ply"))
    {
        bail!("{}: point clouds are written as .ply", a.out.display());
    }
    write_mesh(&a.out, &cloud, &colours)?;
    println!(
        "{} points from {} views in {:.1} s -> {}",
        cloud.vertices.len(),
        cameras.len(),
        t0.elapsed().as_secs_f64(),
        a.out.display()
    );
    Ok(())
}
