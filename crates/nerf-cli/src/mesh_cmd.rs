//! `nerf mesh` and `nerf points`: coloured geometry of a trained run.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{bail, Result};
use clap::Args;
use nerf::mesh::export::write_mesh;
use nerf::mesh::extract::{colour_vertices, extract, ExtractOptions, DEFAULT_THRESHOLD};
use nerf::ray_space::RaySpace;
use nerf::train::run::LoadedRun;

use crate::progress::bar;

#[derive(Args)]
pub struct MeshArgs {
    /// Run folder written by `nerf train`.
    #[arg(long)]
    run: PathBuf,
    /// Output file: .ply (binary), .obj or .glb (binary glTF, +Y up).
    #[arg(long)]
    out: PathBuf,
    /// Grid points per axis over the scene box (memory: 4 bytes each, so 64 MiB at 256).
    /// Default: 256 for the fast model, 128 for the vanilla one (its MLP is about 100x
    /// slower per point).
    #[arg(long)]
    resolution: Option<usize>,
    /// Density at the surface. Lower it (5-10) when thin parts go missing; raise it when
    /// fog or floaters wrap the object.
    #[arg(long, default_value_t = DEFAULT_THRESHOLD)]
    threshold: f32,
    /// Keep only the N largest connected pieces (N = 1 when given without a value).
    #[arg(long, num_args = 0..=1, default_missing_value = "1")]
    keep_largest: Option<usize>,
    /// Half-extent of the sampled box [-B, B]^3 (default: the fast model's box, or its
    /// undistorted inner half when space is contracted; 1.5 for vanilla runs).
    #[arg(long)]
    bound: Option<f32>,
}

pub fn mesh(a: MeshArgs) -> Result<()> {
    if a.resolution.is_some_and(|r| !(2..=2048).contains(&r)) {
        bail!("--resolution must be between 2 and 2048");
    }
    let ext = a
        .out
        .extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase());
    if !matches!(ext.as_deref(), Some("ply" | "obj" | "glb")) {
        bail!("{}: choose a .ply, .obj or .glb file", a.out.display());
    }
    let run = LoadedRun::open(&a.run)?;
    let (default_resolution, default_bound) = run.config.model.mesh_defaults();
    let resolution = a.resolution.unwrap_or(default_resolution);
    let bound = a.bound.unwrap_or(default_bound);
    if bound.is_nan() || bound <= 0.0 {
        bail!("--bound must be positive");
    }
    let options = ExtractOptions {
        resolution,
        threshold: a.threshold,
        bound,
        keep_largest: a.keep_largest,
    };
    let t0 = Instant::now();
    let pb = bar(resolution as u64, "density slabs");
    let mut mesh = extract(run.engine.as_ref(), &options, &mut |done, _| {
        pb.set_position(done as u64)
    });
    pb.finish_and_clear();
    if mesh.triangles.is_empty() {
        bail!(
            "no surface at density {} inside [-{bound}, {bound}]^3; lower --threshold",
            a.threshold
        );
    }
    // Colour from a few grid cells outside the surface.
    let offset = 4.0 * 2.0 * bound / resolution as f32;
    let colours = colour_vertices(run.engine.as_ref(), &mesh, offset);
    // Forward-facing scenes are modelled in NDC: export in world coordinates.
    let space = run.config.open_scene(1).map(|s| s.space);
    match space {
        Ok(space) if space != RaySpace::World => {
            for v in &mut mesh.vertices {
                *v = space.to_world(*v);
            }
            println!("the run is in NDC space: vertices mapped back to world coordinates");
        }
        Ok(_) => {}
        Err(e) => {
            eprintln!("warning: cannot read the run's scene ({e}); vertices are in model space")
        }
    }
    write_mesh(&a.out, &mesh, &colours)?;
    println!(
        "{} triangles, {} vertices in {:.1} s (resolution {}, threshold {}{}) -> {}",
        mesh.triangles.len(),
        mesh.vertices.len(),
        t0.elapsed().as_secs_f64(),
        resolution,
        a.threshold,
        a.keep_largest
            .map_or(String::new(), |n| format!(", largest {n} piece(s)")),
        a.out.display()
    );
    Ok(())
}

#[derive(Args)]
pub struct PointsArgs {
    /// Run folder written by `nerf train`.
    #[arg(long)]
    run: PathBuf,
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
    #[arg(long, default_value_t = 0.95)]
    min_opacity: f32,
}

pub fn points(a: PointsArgs) -> Result<()> {
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
    let run = LoadedRun::open(&a.run)?;
    let config = &run.config;
    let scene = config.open_scene(a.downscale)?;
    let cameras: Vec<_> = scene
        .cameras(nerf::data::Split::Train)
        .into_iter()
        .step_by(a.every)
        .collect();
    let settings = nerf::views::RenderSettings::of_scene(&scene, config.background.eval_colour());
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
