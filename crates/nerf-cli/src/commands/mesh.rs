//! `nerf mesh`: a coloured triangle mesh of a trained run.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{bail, Result};
use clap::Args;
use nerf::camera::ray_space::RaySpace;
use nerf::mesh::export::write_mesh;
use nerf::mesh::extract::{colour_vertices, extract, ExtractOptions, DEFAULT_THRESHOLD};

use crate::progress::bar;

#[derive(Args)]
pub struct MeshArgs {
    /// Run folder written by `nerf train`.
    #[arg(long)]
    run: PathBuf,
    #[command(flatten)]
    scene: nerf::train::run_scene::SceneOverride,
    #[command(flatten)]
    device: nerf::engine::DeviceArg,
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
    #[arg(long, default_value_t = DEFAULT_THRESHOLD, value_parser = nerf::args::positive, allow_negative_numbers = true)]
    threshold: f32,
    /// Keep only the N largest connected pieces (N = 1 when given without a value).
    #[arg(long, num_args = 0..=1, default_missing_value = "1")]
    keep_largest: Option<usize>,
    /// Half-extent of the sampled box [-B, B]^3 (default: the fast model's box, or its
    /// undistorted inner half when space is contracted; 1.5 for vanilla runs).
    #[arg(long, value_parser = nerf::args::positive, allow_negative_numbers = true)]
    bound: Option<f32>,
    /// Models of a moving scene: the moment to mesh, from 0 (the first photo's) to 1 (the
    /// last's).
    #[arg(long, default_value_t = 0.0, value_parser = nerf::args::fraction)]
    time: f32,
}

pub fn run(a: MeshArgs) -> Result<()> {
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
    let run = super::open_run(&a.run, a.device.device, &a.scene)?;
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
        time: a.time,
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
    let colours = colour_vertices(run.engine.as_ref(), &mesh, offset, a.time);
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
