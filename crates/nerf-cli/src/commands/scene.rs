//! `nerf scene`: what a scene folder holds, as training will read it.

use std::path::PathBuf;

use anyhow::Result;
use clap::Args;
use nerf::data::scene::{Scene, SceneOptions};
use nerf::data::Split;

#[derive(Args)]
pub struct SceneArgs {
    /// Scene folder (any supported format).
    #[arg(long)]
    data: PathBuf,
    #[command(flatten)]
    scene: SceneOptions,
    #[arg(long, default_value_t = 1)]
    downscale: usize,
    /// Write the folder's COLMAP model (sparse/0 + images/) as the placed transforms.json
    /// that `nerf capture` writes, to this file (refuses to overwrite one).
    #[arg(long)]
    write_transforms: Option<PathBuf>,
}

/// Prints what training would read: format, splits, image size, bounds, box.
pub fn run(a: SceneArgs) -> Result<()> {
    if let Some(path) = &a.write_transforms {
        if path.exists() {
            anyhow::bail!(
                "{} exists; choose another --write-transforms file",
                path.display()
            );
        }
        nerf::app::capture::transforms_from_colmap(&a.data, path)?;
        println!("wrote {}", path.display());
        return Ok(());
    }
    let s = Scene::open(&a.data, &a.scene, a.downscale)?;
    let train = s.cameras(Split::Train);
    let first = train.first();
    println!("format: {:?}", s.format);
    println!(
        "images: {} train, {} val, {} test",
        s.train.len(),
        s.val.len(),
        s.test.len()
    );
    if s.is_dynamic() {
        println!("{}", moments_line(&s));
    }
    if let Some(c) = first {
        println!(
            "first camera: {}x{}, focal {:.1} x {:.1}, centre ({:.1}, {:.1}), {}",
            c.width,
            c.height,
            c.fx,
            c.fy,
            c.cx,
            c.cy,
            if c.distortion.is_pinhole() {
                "no distortion".to_string()
            } else {
                format!("{:?}", c.distortion)
            }
        );
    }
    let distances: Vec<f32> = train
        .iter()
        .map(|c| nerf::math::length(c.origin()))
        .collect();
    let (lo, hi) = distances
        .iter()
        .fold((f32::INFINITY, 0.0f32), |(l, h), &d| (l.min(d), h.max(d)));
    println!("camera distance from the origin: {lo:.3} .. {hi:.3}");
    println!("near {:.3}, far {:.3} (world depth)", s.near, s.far);
    println!("ray space: {:?}", s.space);
    if s.contract {
        println!(
            "fast-model box: [-{0:.3}, {0:.3}]^3, holding the cube [-{1:.3}, {1:.3}]^3 as it is and all space beyond it contracted",
            s.bound,
            0.5 * s.bound
        );
    } else {
        println!("fast-model box: [-{0:.3}, {0:.3}]^3", s.bound);
    }
    for n in &s.notes {
        println!("note: {n}");
    }
    for w in s.warnings().into_iter().chain(s.copied_held_out_images()?) {
        println!("warning: {w}");
    }
    Ok(())
}

/// A dynamic scene's time range and how many distinct moments each split shows.
fn moments_line(s: &Scene) -> String {
    let [train, val, test] = [Split::Train, Split::Val, Split::Test].map(|k| s.moments(k));
    let all = nerf::data::time::moments(train.iter().chain(&val).chain(&test).copied());
    let (first, last) = (all.first().copied(), all.last().copied());
    format!(
        "time: a dynamic scene, moments {:.3} to {:.3}; {} distinct in train, {} in val, {} in test",
        first.unwrap_or(0.0),
        last.unwrap_or(0.0),
        train.len(),
        val.len(),
        test.len()
    )
}
