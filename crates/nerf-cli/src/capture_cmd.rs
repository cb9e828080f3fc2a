//! `nerf capture` (photos or a video -> COLMAP -> transforms.json) and `nerf scene` (what
//! a scene folder holds, as training will read it).

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Result;
use clap::{Args, ValueEnum};
use nerf::capture::{CaptureOptions, Matching};
use nerf::data::scene::Scene;
use nerf::data::Split;

#[derive(Clone, Copy, ValueEnum)]
pub enum MatchingArg {
    /// Exhaustive for up to 150 photos, sequential for more and for video frames.
    Auto,
    Exhaustive,
    Sequential,
}

#[derive(Args)]
pub struct CaptureArgs {
    /// Folder of photos (JPEG or PNG) of the object or scene.
    #[arg(long, conflicts_with = "video", required_unless_present = "video")]
    images: Option<PathBuf>,
    /// A video to sample frames from instead (needs ffmpeg).
    #[arg(long)]
    video: Option<PathBuf>,
    /// Frames per second taken from --video.
    #[arg(long, default_value_t = 2.0)]
    fps: f32,
    /// Output scene folder: images/, colmap/ (database, logs, models), sparse/0/ and
    /// transforms.json, ready for `nerf train --data`.
    #[arg(long)]
    out: PathBuf,
    #[arg(long, value_enum, default_value = "auto")]
    matching: MatchingArg,
    /// COLMAP camera model shared by all photos: OPENCV suits phone and DSLR photos;
    /// PINHOLE suits undistorted or synthetic images.
    #[arg(long, default_value = "OPENCV")]
    camera_model: String,
    /// Longest image side used for features (smaller is faster).
    #[arg(long, default_value_t = 1600)]
    max_image_size: usize,
}

pub fn capture(a: CaptureArgs) -> Result<()> {
    let t0 = Instant::now();
    let opts = CaptureOptions {
        images: a.images,
        video: a.video,
        fps: a.fps,
        out: a.out.clone(),
        matching: match a.matching {
            MatchingArg::Auto => Matching::Auto,
            MatchingArg::Exhaustive => Matching::Exhaustive,
            MatchingArg::Sequential => Matching::Sequential,
        },
        camera_model: a.camera_model.to_ascii_uppercase(),
        max_image_size: a.max_image_size,
    };
    let report = nerf::capture::capture(&opts, &mut |stage| {
        println!("[{:6.1} s] {stage}", t0.elapsed().as_secs_f64());
    })?;
    println!(
        "COLMAP registered {} of {} images ({:?} matching) with {} points in {:.1} s",
        report.registered,
        report.images,
        report.matching,
        report.points,
        t0.elapsed().as_secs_f64()
    );
    if !report.unregistered.is_empty() {
        println!(
            "warning: {} images could not be placed and are left out: {}",
            report.unregistered.len(),
            report.unregistered.join(", ")
        );
        println!("{}", nerf::capture::FIXES);
    }
    println!(
        "scene: {} -> nerf train --data {}",
        report.transforms.display(),
        a.out.display()
    );
    Ok(())
}

#[derive(Args)]
pub struct SceneArgs {
    /// Scene folder (any supported format).
    #[arg(long)]
    data: PathBuf,
    #[command(flatten)]
    scene: crate::commands::SceneArgs,
    #[arg(long, default_value_t = 1)]
    downscale: usize,
}

/// Prints what training would read: format, splits, image size, bounds, box.
pub fn scene(a: SceneArgs) -> Result<()> {
    let s = Scene::open(&a.data, &a.scene.options(), a.downscale)?;
    let train = s.cameras(Split::Train);
    let first = train.first();
    println!("format: {:?}", s.format);
    println!(
        "images: {} train, {} val, {} test",
        s.train.len(),
        s.val.len(),
        s.test.len()
    );
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
    if let Some(w) = s.warning() {
        println!("warning: {w}");
    }
    Ok(())
}
