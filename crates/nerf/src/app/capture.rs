//! `nerf capture`: from a folder of photos (or a video) to a trainable scene, through the
//! `colmap` program (structure from motion) and, for videos, `ffmpeg`.
//!
//! Steps, each logged to `<out>/colmap/<step>.log`:
//! 1. the photos are copied to `<out>/images/` (video frames are extracted there);
//! 2. `colmap feature_extractor`: SIFT features, one shared camera (CPU);
//! 3. `colmap exhaustive_matcher` for small sets, `sequential_matcher` for video frames;
//! 4. `colmap mapper`: the sparse reconstruction, in `<out>/colmap/sparse/N/`;
//! 5. the largest model becomes `<out>/transforms.json` (instant-ngp format, poses already
//!    placed by [`crate::data::colmap::scene`]: `scale` 1, `offset` 0.5), and is kept as
//!    text in `<out>/sparse/0/`. The file records where to march (`"nerf_box"`: the
//!    cameras' box, contracted beyond its inner half, and near / far from the points), so
//!    the folder trains the same read as `transforms.json` or as COLMAP; `aabb_scale` is
//!    the power of two that holds that box, for instant-ngp.
//!
//! Images COLMAP could not register are reported with the fixes that usually work.

use std::path::{Path, PathBuf};
use std::process::Command;

use crate::data::colmap::{self, scene as colmap_scene};
use crate::data::llff::list_images;
use crate::error::{NerfError, Result};

/// How images are matched against each other.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Matching {
    /// Exhaustive for up to 150 images (`EXHAUSTIVE_LIMIT`), sequential above (and for
    /// video).
    Auto,
    Exhaustive,
    Sequential,
}

/// Above this many images, exhaustive matching (quadratic) gives way to sequential.
pub const EXHAUSTIVE_LIMIT: usize = 150;

#[derive(Clone, Debug, clap::Args)]
pub struct CaptureOptions {
    /// Folder of photos (JPEG or PNG) of the object or scene.
    #[arg(long, conflicts_with = "video", required_unless_present = "video")]
    pub images: Option<PathBuf>,
    /// A video to sample frames from instead (needs ffmpeg).
    #[arg(long)]
    pub video: Option<PathBuf>,
    /// Frames per second taken from --video.
    #[arg(long, default_value_t = 2.0, value_parser = crate::args::positive, allow_negative_numbers = true)]
    pub fps: f32,
    /// Output scene folder: images/, colmap/ (database, logs, models), sparse/0/ and
    /// transforms.json, ready for `nerf train --data`.
    #[arg(long)]
    pub out: PathBuf,
    /// How photos are matched: auto is exhaustive up to 150 photos, sequential for more and
    /// for video frames.
    #[arg(long, value_enum, default_value = "auto")]
    pub matching: Matching,
    /// COLMAP camera model shared by all photos (SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL,
    /// RADIAL, OPENCV): OPENCV suits phone and DSLR photos; PINHOLE suits undistorted or
    /// synthetic images.
    #[arg(long, default_value = "OPENCV")]
    pub camera_model: String,
    /// Longest image side used for features (smaller is faster; COLMAP's default is 3200).
    #[arg(long, default_value_t = 1600)]
    pub max_image_size: usize,
}

/// What a capture produced.
#[derive(Clone, Debug)]
pub struct CaptureReport {
    pub images: usize,
    pub registered: usize,
    /// Names of the images COLMAP could not place.
    pub unregistered: Vec<String>,
    pub points: usize,
    pub transforms: PathBuf,
    pub matching: Matching,
}

/// The `colmap` program, or an error that says how to install it.
pub fn colmap_available() -> Result<()> {
    match Command::new("colmap").arg("help").output() {
        Ok(o) if o.status.success() || !o.stdout.is_empty() => Ok(()),
        _ => Err(NerfError::Config(
            "`colmap` is not on PATH: install it (Debian/Ubuntu: apt-get install colmap; \
             macOS: brew install colmap; others: https://colmap.github.io/install.html)"
                .into(),
        )),
    }
}

/// Runs one external step, its output logged to `log`; a failure shows the log's end.
fn run_step(program: &str, args: &[String], log: &Path) -> Result<()> {
    let output = Command::new(program)
        .args(args)
        .output()
        .map_err(|e| NerfError::Config(format!("cannot run {program}: {e}")))?;
    let mut text = output.stdout.clone();
    text.extend_from_slice(&output.stderr);
    crate::io::write_atomic(log, &text)?;
    if !output.status.success() {
        let text = String::from_utf8_lossy(&text);
        let tail: Vec<&str> = text.lines().rev().take(12).collect();
        let tail: Vec<&str> = tail.into_iter().rev().collect();
        return Err(NerfError::Config(format!(
            "`{program} {}` failed ({}); the end of {}:\n{}",
            args.first().map_or("", |s| s.as_str()),
            output.status,
            log.display(),
            tail.join("\n")
        )));
    }
    Ok(())
}

fn arg(s: impl Into<String>) -> String {
    s.into()
}

/// Runs the whole capture; `on_stage` hears each step's name as it starts.
pub fn capture(opts: &CaptureOptions, on_stage: &mut dyn FnMut(&str)) -> Result<CaptureReport> {
    colmap_available()?;
    // COLMAP's model names are upper case; accept `opencv` as well.
    let opts = &CaptureOptions {
        camera_model: opts.camera_model.to_ascii_uppercase(),
        ..opts.clone()
    };
    if !matches!(
        colmap::CameraModel::from_name(&opts.camera_model),
        Some(m) if !matches!(m, colmap::CameraModel::Other(_))
    ) {
        return Err(NerfError::Config(format!(
            "--camera-model {}: choose SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV or OPENCV_FISHEYE",
            opts.camera_model
        )));
    }
    let out = &opts.out;
    let images_dir = out.join("images");
    let work = out.join("colmap");
    crate::io::create_dir(&images_dir)?;
    crate::io::create_dir(&work)?;
    if !list_images(&images_dir)?.is_empty() {
        return Err(NerfError::Config(format!(
            "{} already holds images: choose an empty --out",
            images_dir.display()
        )));
    }
    let from_video = match (&opts.images, &opts.video) {
        (Some(dir), None) => {
            on_stage("copying photos");
            let photos = list_images(dir)?;
            if photos.len() < 3 {
                return Err(NerfError::format(dir, format!("holds {} JPEG/PNG photos; a capture needs at least 3 (20-100 with good overlap is typical)", photos.len())));
            }
            for p in &photos {
                let name = p
                    .file_name()
                    .map(|n| images_dir.join(n))
                    .ok_or_else(|| NerfError::format(p, "has no file name"))?;
                std::fs::copy(p, &name).map_err(|e| NerfError::write(&name, e))?;
            }
            false
        }
        (None, Some(video)) => {
            on_stage("extracting video frames");
            if !crate::app::video::ffmpeg_available() {
                return Err(NerfError::Config(
                    "--video needs ffmpeg on PATH (Debian: apt-get install ffmpeg)".into(),
                ));
            }
            if !video.is_file() {
                return Err(NerfError::format(video, "does not exist"));
            }
            if opts.fps.is_nan() || opts.fps <= 0.0 {
                return Err(NerfError::Config(format!(
                    "--fps {} must be positive",
                    opts.fps
                )));
            }
            run_step(
                "ffmpeg",
                &[
                    arg("-nostdin"),
                    arg("-i"),
                    video.display().to_string(),
                    arg("-vf"),
                    format!("fps={}", opts.fps),
                    arg("-qscale:v"),
                    arg("2"),
                    images_dir.join("%04d.jpg").display().to_string(),
                ],
                &work.join("ffmpeg.log"),
            )?;
            true
        }
        _ => {
            return Err(NerfError::Config(
                "give exactly one of --images DIR and --video FILE".into(),
            ))
        }
    };
    let names: Vec<String> = list_images(&images_dir)?
        .iter()
        .filter_map(|p| p.file_name().map(|n| n.to_string_lossy().into_owned()))
        .collect();
    if names.len() < 3 {
        return Err(NerfError::format(
            &images_dir,
            format!(
                "holds {} frames; lower the video's length or raise --fps",
                names.len()
            ),
        ));
    }
    let database = work.join("database.db");
    let _ = std::fs::remove_file(&database);
    let db = database.display().to_string();
    let img = images_dir.display().to_string();
    on_stage("colmap: extracting features");
    run_step(
        "colmap",
        &[
            arg("feature_extractor"),
            arg("--database_path"),
            db.clone(),
            arg("--image_path"),
            img.clone(),
            arg("--ImageReader.single_camera"),
            arg("1"),
            arg("--ImageReader.camera_model"),
            opts.camera_model.clone(),
            arg("--SiftExtraction.use_gpu"),
            arg("0"),
            arg("--SiftExtraction.max_image_size"),
            opts.max_image_size.to_string(),
        ],
        &work.join("feature_extractor.log"),
    )?;
    let matching = match opts.matching {
        Matching::Auto if from_video || names.len() > EXHAUSTIVE_LIMIT => Matching::Sequential,
        Matching::Auto => Matching::Exhaustive,
        m => m,
    };
    let matcher = if matching == Matching::Sequential {
        "sequential_matcher"
    } else {
        "exhaustive_matcher"
    };
    on_stage(&format!("colmap: matching ({matcher})"));
    run_step(
        "colmap",
        &[
            arg(matcher),
            arg("--database_path"),
            db.clone(),
            arg("--SiftMatching.use_gpu"),
            arg("0"),
        ],
        &work.join("matcher.log"),
    )?;
    on_stage("colmap: mapping");
    let sparse = work.join("sparse");
    let _ = std::fs::remove_dir_all(&sparse);
    crate::io::create_dir(&sparse)?;
    run_step(
        "colmap",
        &[
            arg("mapper"),
            arg("--database_path"),
            db,
            arg("--image_path"),
            img,
            arg("--output_path"),
            sparse.display().to_string(),
        ],
        &work.join("mapper.log"),
    )?;
    on_stage("writing transforms.json");
    let model = largest_model(&sparse)?.ok_or_else(|| {
        NerfError::Config(format!(
            "COLMAP registered none of the {} images (see {}). {}",
            names.len(),
            work.join("mapper.log").display(),
            FIXES
        ))
    })?;
    let registered: std::collections::HashSet<&str> =
        model.images.iter().map(|i| i.name.as_str()).collect();
    let unregistered: Vec<String> = names
        .iter()
        .filter(|n| !registered.contains(n.as_str()))
        .cloned()
        .collect();
    if model.images.len() < 3 {
        return Err(NerfError::Config(format!(
            "COLMAP registered only {} of {} images ({}). {}",
            model.images.len(),
            names.len(),
            work.join("mapper.log").display(),
            FIXES
        )));
    }
    colmap::write_text_model(&out.join("sparse/0"), &model)?;
    let transforms = out.join("transforms.json");
    write_transforms(&model, out, &transforms)?;
    Ok(CaptureReport {
        images: names.len(),
        registered: model.images.len(),
        unregistered,
        points: model.points.len(),
        transforms,
        matching,
    })
}

/// What usually helps when COLMAP cannot place images.
pub const FIXES: &str =
    "What usually helps: more overlap between neighbouring photos (about 60-80%, \
    small steps around the object, no blurry frames); `--camera-model PINHOLE` for photos \
    without lens distortion or with a fixed zoom; `--matching sequential` for frames of one \
    continuous video; more texture in view (a patterned cloth under the object).";

/// The model with the most registered images among `sparse/0`, `sparse/1`, ...
fn largest_model(sparse: &Path) -> Result<Option<colmap::Model>> {
    let mut best: Option<colmap::Model> = None;
    let entries = std::fs::read_dir(sparse).map_err(|e| NerfError::io(sparse, e))?;
    for e in entries.flatten() {
        let dir = e.path();
        if colmap::find_model(&dir).is_none() {
            continue;
        }
        let m = colmap::read_model(&dir)?;
        if best
            .as_ref()
            .is_none_or(|b| m.images.len() > b.images.len())
        {
            best = Some(m);
        }
    }
    Ok(best)
}

/// Writes the COLMAP model of scene folder `dir` (`sparse/0` and `images/`) as the
/// `transforms.json` that `nerf capture` would write, to `path` (`nerf scene
/// --write-transforms`). Image paths are relative when `path` is in `dir`, else absolute.
pub fn transforms_from_colmap(dir: &Path, path: &Path) -> Result<()> {
    let (_, model) = colmap::open_model(dir)?;
    write_transforms(&model, dir, path)
}

/// Writes the model as an instant-ngp `transforms.json` whose poses are already placed
/// (so `scale` 1 and `offset` 0.5 leave them unchanged) with per-frame intrinsics; the
/// images are in `out/images`.
fn write_transforms(model: &colmap::Model, out: &Path, path: &Path) -> Result<()> {
    let images = out.join("images");
    let (frames, placement) = colmap_scene::frames_of(model, &out.join("sparse/0"), &images)?;
    let beside = path.parent().map(|p| p.to_path_buf()).unwrap_or_default();
    let same_folder = std::fs::canonicalize(&beside).ok() == std::fs::canonicalize(out).ok();
    let image_path = |name: &str| {
        if same_folder {
            format!("images/{name}")
        } else {
            let image = images.join(name);
            std::fs::canonicalize(&image)
                .unwrap_or(image)
                .display()
                .to_string()
        }
    };
    let placed = colmap_scene::placed_box(model, &placement, &frames);
    let frames: Vec<serde_json::Value> = frames
        .iter()
        .map(|f| crate::data::transforms::frame_entry(&f.camera, &image_path(&f.name)))
        .collect();
    let doc = crate::data::transforms::placed_document(frames, &placed);
    crate::io::write_json(path, &doc)
}
