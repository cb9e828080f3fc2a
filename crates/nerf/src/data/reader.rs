//! What every scene format's reader shares: the options a scene is read with, the frame a
//! reader hands back ([`Parsed`]), and the helpers for the paths, image sizes, poses and
//! bounds they all meet. [`crate::data::scene`] picks a reader and assembles a scene from
//! what it returns; the readers import this file and never the scene.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::camera::ray_space::RaySpace;
use crate::camera::{Camera, Pose};
use crate::error::{NerfError, Result};

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum Format {
    /// `transforms_{train,val,test}.json`.
    Blender,
    /// instant-ngp's or nerfstudio's `transforms.json`.
    Transforms,
    Llff,
    Colmap,
}

/// Axis and scale conventions of a `transforms.json` (see `data::transforms`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum Convention {
    /// instant-ngp when the file has `aabb_scale`, `scale` or `offset`; else nerfstudio.
    #[default]
    Auto,
    Ngp,
    Nerfstudio,
}

/// How to read a scene; saved in the run's config so evaluation reads it the same way, and
/// the scene options of the command line (the doc comments are their `--help`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, clap::Args)]
#[serde(default)]
pub struct SceneOptions {
    /// Read the scene as this format instead of detecting it.
    #[arg(long, value_enum)]
    pub format: Option<Format>,
    /// LLFF: the capture circles the object (inward-facing 360); train in world space
    /// centred on what the cameras look at, not in NDC.
    #[arg(long)]
    pub spherify: bool,
    /// LLFF: train a forward-facing scene in world space instead of NDC (the paper's
    /// choice; `"ndc": false` in config.json).
    #[arg(long = "no-ndc", action = clap::ArgAction::SetFalse, conflicts_with = "spherify")]
    #[serde(deserialize_with = "ndc_or_default")]
    pub ndc: bool,
    /// Real captures: hold out every N-th image for testing (the paper's LLFF setting: 8).
    #[arg(long, default_value_t = 8, value_parser = at_least_two)]
    pub holdout: usize,
    /// transforms.json: whose world placement to follow (auto: instant-ngp's keys scale or
    /// offset, else nerfstudio's keys, else aabb_scale; the choice is printed).
    #[arg(long, value_enum, default_value = "auto")]
    pub convention: Convention,
}

impl Default for SceneOptions {
    fn default() -> Self {
        SceneOptions {
            format: None,
            spherify: false,
            ndc: true,
            holdout: 8,
            convention: Convention::Auto,
        }
    }
}

/// `ndc` of configs written before it was a plain flag: `null` meant the default (NDC).
fn ndc_or_default<'de, D: serde::Deserializer<'de>>(d: D) -> std::result::Result<bool, D::Error> {
    Ok(Option::<bool>::deserialize(d)?.unwrap_or(true))
}

fn at_least_two(s: &str) -> std::result::Result<usize, String> {
    match s.parse::<usize>() {
        Ok(n) if n >= 2 => Ok(n),
        Ok(n) => Err(format!("{n} is too small: at least 2")),
        Err(e) => Err(e.to_string()),
    }
}

/// One image of a scene with its camera (at the resolution of the image file).
#[derive(Clone, Debug)]
pub struct Frame {
    pub camera: Camera,
    pub image: PathBuf,
    /// Optional mask: black pixels are left out of training (nerfstudio's convention).
    pub mask: Option<PathBuf>,
    pub name: String,
    /// The moment the photo shows, in a dynamic scene (D-NeRF's `time` key): as the file
    /// gives it until the scene opens, then in [0, 1] (`data::time`).
    pub time: Option<f32>,
}

/// What a format reader hands back; `Scene::open` adds splits and downscaling.
pub(crate) struct Parsed {
    pub frames: Vec<Frame>,
    /// Explicit splits (Blender); `None` holds out every `holdout`-th frame.
    pub splits: Option<[Vec<usize>; 3]>,
    pub near: f32,
    pub far: f32,
    pub space: RaySpace,
    pub bound: f32,
    pub contract: bool,
    /// Downscale already applied by picking a smaller image folder (LLFF `images_N`).
    pub prescaled: usize,
    /// What the reader decided that a user should hear (see `Scene::notes`).
    pub notes: Vec<String>,
    /// What the reader doubts (see `Scene::warnings`).
    pub warnings: Vec<String>,
    /// The format has one image size for every frame (Blender: `camera_angle_x` is shared).
    pub one_size: bool,
}

/// Where a scene's rays are marched, as a writer of a scene records it so that every
/// reader agrees (`nerf capture` puts it in `transforms.json` as `"nerf_box"`): the fast
/// model's box (half-extent `bound`, in the placed frame), whether space beyond its inner
/// half is contracted, and the rays' near and far.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct PlacedBox {
    pub bound: f32,
    pub contract: bool,
    pub near: f32,
    pub far: f32,
}

/// `camera` for an image of `width x height`: itself, or its intrinsics scaled when the
/// image was resized since the metadata was written (same shape, another resolution).
pub(crate) fn fit_to_image(
    camera: &Camera,
    width: usize,
    height: usize,
) -> std::result::Result<Camera, String> {
    let (cw, ch) = (camera.width, camera.height);
    if (cw, ch) == (width, height) {
        return Ok(camera.clone());
    }
    let (sx, sy) = (width as f32 / cw as f32, height as f32 / ch as f32);
    // Same shape: scaling the camera's height by the width ratio lands within a pixel.
    if (ch as f32 * sx - height as f32).abs() >= 1.0 {
        return Err(format!(
            "image is {width}x{height} but its camera is {cw}x{ch} (a different shape)"
        ));
    }
    Ok(Camera {
        width,
        height,
        fx: camera.fx * sx,
        fy: camera.fy * sy,
        cx: camera.cx * sx,
        cy: camera.cy * sy,
        ..camera.clone()
    })
}

/// The path `relative` names, resolved against `base`. Backslashes are folder separators
/// (files written on Windows), and a drive letter makes no sense here: `C:\\x\\a.jpg`
/// is read as `C:/x/a.jpg` relative to `base`, which the scene's frame check then finds by its
/// last components.
pub(crate) fn resolve(base: &Path, relative: &str) -> PathBuf {
    let text = if std::path::MAIN_SEPARATOR == '/' {
        relative.replace('\\', "/")
    } else {
        relative.to_string()
    };
    let p = Path::new(&text);
    if p.is_absolute() {
        p.to_path_buf()
    } else {
        base.join(p)
    }
}

/// `path`, or where [`find_moved`] finds it when it is not there.
pub(crate) fn locate(dir: &Path, path: &Path) -> PathBuf {
    if path.exists() {
        return path.to_path_buf();
    }
    find_moved(dir, path).unwrap_or_else(|| path.to_path_buf())
}

/// A file named by a scene that is not where it says (an absolute path from another
/// machine, a Windows path), looked up in `dir` by its last one, two or three components.
pub(crate) fn find_moved(dir: &Path, path: &Path) -> Option<PathBuf> {
    let parts: Vec<&std::ffi::OsStr> = path
        .components()
        .filter_map(|c| match c {
            std::path::Component::Normal(p) => Some(p),
            _ => None,
        })
        .collect();
    (1..=parts.len().min(3)).rev().find_map(|n| {
        let candidate = parts[parts.len() - n..]
            .iter()
            .fold(dir.to_path_buf(), |p, c| p.join(c));
        candidate.is_file().then_some(candidate)
    })
}

/// Width and height from an image file's header.
pub(crate) fn image_dimensions(path: &Path) -> Result<(usize, usize)> {
    image::image_dimensions(path)
        .map(|(w, h)| (w as usize, h as usize))
        .map_err(|e| match e {
            image::ImageError::IoError(io) => NerfError::io(path, io),
            e => NerfError::Image {
                path: path.to_path_buf(),
                message: e.to_string(),
            },
        })
}

/// Near and far bounds that see the whole box `[-bound, bound]^3` from every camera.
pub(crate) fn bounds_around_box(cameras: &[Camera], bound: f32) -> (f32, f32) {
    let far = cameras
        .iter()
        .map(|c| {
            let o = c.origin();
            let corner = o.map(|x| x.abs() + bound);
            crate::math::length(corner)
        })
        .fold(0.0f32, f32::max);
    (0.01 * bound, far.max(2.0 * bound))
}

/// Checks a 4x4 (or 3x4) camera-to-world matrix and keeps its top three rows; a 3x3 part
/// that is a rotation scaled uniformly is normalised, and the scale returned (see
/// [`ScaledPoses`]).
pub fn parse_pose(m: &[Vec<f32>]) -> std::result::Result<(Pose, Option<f32>), String> {
    let named = |e: String| e.replace("the matrix", "transform_matrix");
    let mut pose = crate::camera::pose_from_rows_unchecked(m).map_err(named)?;
    let scale = crate::camera::remove_uniform_scale(&mut pose);
    crate::camera::check_pose(&pose).map_err(named)?;
    Ok((pose, scale))
}

/// The poses a reader normalised (a rotation scaled uniformly), for one note.
#[derive(Default)]
pub struct ScaledPoses {
    count: usize,
    first: Option<f32>,
}

impl ScaledPoses {
    /// Counts one pose's scale, if it had one.
    pub fn add(&mut self, scale: Option<f32>) {
        if let Some(s) = scale {
            self.count += 1;
            self.first.get_or_insert(s);
        }
    }

    /// The note to say, when any pose was normalised.
    pub fn note(&self, file: &Path) -> Option<String> {
        let first = self.first?;
        Some(format!(
            "{}: {} poses have a rotation scaled uniformly (by {first:.4} for the first, as \
             exporters that write a scale factor into the matrix do); read as rotations",
            file.display(),
            self.count
        ))
    }
}

/// The pose as the 4x4 nested list the format stores.
pub fn pose_to_matrix(pose: &Pose) -> Vec<Vec<f32>> {
    let mut m: Vec<Vec<f32>> = pose.iter().map(|r| r.to_vec()).collect();
    m.push(vec![0.0, 0.0, 0.0, 1.0]);
    m
}
