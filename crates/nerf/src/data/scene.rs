//! A scene on disk, in any supported format, as cameras and image files.
//!
//! Opening a scene reads only its metadata (JSON, `.npy`, COLMAP model, image headers):
//! the cameras, the splits, the bounds rays are marched over and the box the fast model
//! covers. [`Scene::load`] then reads a split's images into a [`Dataset`]. Every format
//! ends in the same frame conventions: camera-to-world poses with OpenGL axes (the camera
//! looks down -Z, +Y up in the image), so training and rendering never see the format.
//!
//! | format | detected by | splits |
//! |---|---|---|
//! | Blender | `transforms_train.json` | its three JSON files |
//! | instant-ngp / nerfstudio | `transforms.json` | every `holdout`-th frame is test |
//! | LLFF | `poses_bounds.npy` | every `holdout`-th image is test |
//! | COLMAP | `sparse/0/cameras.{bin,txt}` | every `holdout`-th image is test |

use std::path::{Path, PathBuf};

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::{Dataset, RgbaImage, Split, View};
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
}

/// A scene's cameras, splits and bounds.
#[derive(Clone, Debug)]
pub struct Scene {
    pub dir: PathBuf,
    pub format: Format,
    pub frames: Vec<Frame>,
    pub train: Vec<usize>,
    pub val: Vec<usize>,
    pub test: Vec<usize>,
    /// Marching bounds along camera rays, in world depth units.
    pub near: f32,
    pub far: f32,
    /// Where rays are marched (world, or NDC for forward-facing captures).
    pub space: RaySpace,
    /// Half-extent of the box `[-bound, bound]^3` the fast model covers, in ray space.
    pub bound: f32,
    /// Whether the scene reaches beyond the box (360-degree real captures): the fast model
    /// then keeps the cube of half-extent `bound / 2` as it is and contracts the rest of
    /// space into the box.
    pub contract: bool,
    /// Integer area-downscale still to apply to each image file on load.
    pub(crate) image_factor: usize,
    /// What reading the scene decided that a user should hear (the convention chosen and
    /// why, keys read from another tool's layout).
    pub notes: Vec<String>,
    /// What reading the scene repaired or doubts (images found elsewhere, duplicates
    /// dropped, intrinsics rescaled, cameras far outside the box); see [`Scene::warnings`].
    problems: Vec<String>,
}

/// What a format reader hands back; [`Scene::open`] adds splits and downscaling.
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
    /// What the reader decided that a user should hear (see [`Scene::notes`]).
    pub notes: Vec<String>,
    /// What the reader doubts (see [`Scene::warnings`]).
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

/// The format of the scene in `dir`, from the files it holds.
pub fn detect(dir: &Path) -> Result<Format> {
    if !dir.is_dir() {
        return Err(NerfError::format(dir, "is not a folder"));
    }
    if super::blender::transforms_path(dir, Split::Train).exists() {
        Ok(Format::Blender)
    } else if dir.join("transforms.json").exists() {
        Ok(Format::Transforms)
    } else if dir.join("poses_bounds.npy").exists() {
        Ok(Format::Llff)
    } else if super::colmap::find_model(dir).is_some() {
        Ok(Format::Colmap)
    } else {
        Err(NerfError::format(
            dir,
            "holds no scene: expected transforms_train.json (Blender), transforms.json \
             (instant-ngp / nerfstudio), poses_bounds.npy (LLFF) or sparse/0/cameras.bin|txt \
             (COLMAP); `nerf capture` makes a scene from photos",
        ))
    }
}

/// Viewing directions spread wider than this (from their mean) mark an inward-facing capture.
pub const INWARD_SPREAD_DEGREES: f32 = 45.0;

/// Training and test indices of `n` frames: every `holdout`-th frame is a test frame.
pub fn hold_out(n: usize, holdout: usize) -> (Vec<usize>, Vec<usize>) {
    let holdout = holdout.max(2);
    (0..n).partition(|i| i % holdout != 0)
}

impl Scene {
    /// Reads the scene in `dir` at `1/downscale` of its images' resolution.
    pub fn open(dir: &Path, opts: &SceneOptions, downscale: usize) -> Result<Scene> {
        let downscale = downscale.max(1);
        let format = match opts.format {
            Some(f) => f,
            None => detect(dir)?,
        };
        let parsed = match format {
            Format::Blender => super::blender::parse(dir)?,
            Format::Transforms => super::transforms::parse(dir, opts)?,
            Format::Llff => super::llff::parse(dir, opts, downscale)?,
            Format::Colmap => super::colmap::scene::parse(dir, opts)?,
        };
        if parsed.frames.is_empty() {
            return Err(NerfError::format(dir, "the scene lists no images"));
        }
        let image_factor = (downscale / parsed.prescaled.max(1)).max(1);
        let mut problems = parsed.warnings;
        let mut frames = parsed.frames;
        problems.extend(check_frames(dir, &mut frames)?);
        if parsed.one_size {
            check_one_size(&frames)?;
        }
        if let Some(f) = frames
            .iter()
            .find(|f| f.camera.width < image_factor || f.camera.height < image_factor)
        {
            return Err(NerfError::format(
                &f.image,
                format!(
                    "is {}x{}: --downscale {downscale} leaves no pixels of it",
                    f.camera.width, f.camera.height
                ),
            ));
        }
        let [train, val, test] = match parsed.splits {
            Some(splits) => dedupe_splits(&frames, splits, &mut problems),
            None => {
                let kept = dedupe_frames(&mut frames, &mut problems);
                if kept == 0 {
                    return Err(NerfError::format(dir, "the scene lists no images"));
                }
                let (train, test) = hold_out(frames.len(), opts.holdout);
                [train, test.clone(), test]
            }
        };
        Ok(Scene {
            dir: dir.to_path_buf(),
            format,
            frames,
            train,
            val,
            test,
            near: parsed.near,
            far: parsed.far,
            space: parsed.space,
            bound: parsed.bound,
            contract: parsed.contract,
            image_factor,
            notes: parsed.notes,
            problems,
        })
    }

    pub fn indices(&self, split: Split) -> &[usize] {
        match split {
            Split::Train => &self.train,
            Split::Val => &self.val,
            Split::Test => &self.test,
        }
    }

    /// Whether the scene has a validation split of its own (Blender) rather than reusing
    /// its held-out test images.
    pub fn has_val(&self) -> bool {
        !self.val.is_empty()
    }

    /// The cameras of a split at the resolution the scene is loaded at.
    pub fn cameras(&self, split: Split) -> Vec<Camera> {
        self.indices(split)
            .iter()
            .map(|&i| self.frames[i].camera.downscaled(self.image_factor))
            .collect()
    }

    /// What a user should be warned of before training on the scene: what reading it
    /// repaired or doubts, and a warning when the scene is read in a way its cameras contradict (a forward-facing
    /// treatment, NDC, of cameras that look in directions more than
    /// [`INWARD_SPREAD_DEGREES`] apart from their mean, i.e. an inward-facing capture
    /// that wants `--spherify`).
    pub fn warnings(&self) -> Vec<String> {
        let mut out = self.problems.clone();
        if matches!(self.space, RaySpace::Ndc(_)) {
            let poses: Vec<Pose> = self.frames.iter().map(|f| f.camera.c2w).collect();
            let spread = super::poses::view_spread_degrees(&poses);
            if spread > INWARD_SPREAD_DEGREES {
                out.push(format!(
                    "the cameras' viewing directions spread {spread:.0} degrees from their \
                     mean: this looks like an inward-facing capture; NDC suits forward-facing \
                     ones, so consider --spherify"
                ));
            }
        }
        out
    }

    /// Marching bounds in ray space.
    pub fn ray_bounds(&self) -> (f32, f32) {
        self.space.bounds(self.near, self.far)
    }

    /// Frames `0, every, 2 every, ...` of `split`, with their images.
    pub fn load(&self, split: Split, every: usize) -> Result<Dataset> {
        let views = self
            .indices(split)
            .par_iter()
            .step_by(every.max(1))
            .map(|&i| self.load_frame(&self.frames[i]))
            .collect::<Result<Vec<_>>>()?;
        if views.is_empty() {
            let path = match self.format {
                Format::Blender => super::blender::transforms_path(&self.dir, split),
                _ => self.dir.clone(),
            };
            return Err(NerfError::format(
                path,
                format!("the scene has no {} images", split.name()),
            ));
        }
        let (near, far) = self.ray_bounds();
        Ok(Dataset {
            views,
            near,
            far,
            space: self.space,
        })
    }

    fn load_frame(&self, frame: &Frame) -> Result<View> {
        let full = RgbaImage::load(&frame.image)?;
        let camera = fit_to_image(&frame.camera, full.width, full.height)
            .map_err(|m| NerfError::format(&frame.image, m))?
            .downscaled(self.image_factor);
        let image = full.downscale(self.image_factor);
        let kept_pixels = match &frame.mask {
            None => None,
            Some(path) => Some(load_mask(path, &image, self.image_factor)?),
        };
        Ok(View {
            camera,
            image,
            name: frame.name.clone(),
            kept_pixels,
        })
    }
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

/// Indices of the pixels a mask keeps (mean mask value over the pixel's area >= 0.5).
fn load_mask(path: &Path, image: &RgbaImage, factor: usize) -> Result<Vec<u32>> {
    let mask = RgbaImage::load(path)?;
    if (mask.width / factor, mask.height / factor) != (image.width, image.height) {
        return Err(NerfError::format(
            path,
            format!(
                "mask is {}x{} but its image is {}x{} (after --downscale {factor})",
                mask.width,
                mask.height,
                image.width * factor,
                image.height * factor
            ),
        ));
    }
    let small = mask.downscale(factor);
    let kept: Vec<u32> = small
        .data
        .chunks_exact(4)
        .enumerate()
        .filter(|(_, p)| p[0] >= 0.5)
        .map(|(i, _)| i as u32)
        .collect();
    if kept.is_empty() {
        return Err(NerfError::format(
            path,
            "the mask leaves no pixel to train on",
        ));
    }
    Ok(kept)
}

/// The path `relative` names, resolved against `base`. Backslashes are folder separators
/// (files written on Windows), and a drive letter makes no sense here: `C:\\x\\a.jpg`
/// is read as `C:/x/a.jpg` relative to `base`, which [`check_frames`] then finds by its
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
fn find_moved(dir: &Path, path: &Path) -> Option<PathBuf> {
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

/// Checks every frame before anything trains, so a problem in any split is found when the
/// scene is opened (`nerf scene`, the start of `nerf train`), not after hours of training:
/// the pose is a rotation and a sane position; the image exists (or is found by its last
/// path components) and its header is readable; the camera's size has the image's shape
/// (its intrinsics are scaled to the image's resolution, with a note when that is more
/// than rounding). Returns the notes.
fn check_frames(dir: &Path, frames: &mut [Frame]) -> Result<Vec<String>> {
    struct Fixed {
        moved: Option<PathBuf>,
        rescaled: Option<String>,
    }
    let fixes = frames
        .par_iter_mut()
        .map(|f| -> Result<Fixed> {
            crate::camera::check_pose(&f.camera.c2w)
                .map_err(|m| NerfError::format(&f.image, format!("frame {}: {m}", f.name)))?;
            let mut moved = None;
            if !f.image.exists() {
                if let Some(found) = find_moved(dir, &f.image) {
                    moved = Some(std::mem::replace(&mut f.image, found));
                }
            }
            let (w, h) = image_dimensions(&f.image)?;
            let (cw, ch) = (f.camera.width, f.camera.height);
            f.camera = fit_to_image(&f.camera, w, h).map_err(|m| NerfError::format(&f.image, m))?;
            let rescaled = (cw.abs_diff(w) > 1 || ch.abs_diff(h) > 1).then(|| {
                format!(
                    "{}: the scene file says {cw}x{ch} but the image is {w}x{h}",
                    f.image.display()
                )
            });
            Ok(Fixed { moved, rescaled })
        })
        .collect::<Result<Vec<_>>>()?;
    let mut notes = Vec::new();
    let moved: Vec<(&PathBuf, &Frame)> = fixes
        .iter()
        .zip(frames.iter())
        .filter_map(|(x, f)| x.moved.as_ref().map(|m| (m, f)))
        .collect();
    if let Some((from, f)) = moved.first() {
        notes.push(format!(
            "{} of the scene's image paths do not exist as written; found them by their last \
             path components inside {} (e.g. {} -> {})",
            moved.len(),
            dir.display(),
            from.display(),
            f.image.display()
        ));
    }
    let rescaled: Vec<&String> = fixes.iter().filter_map(|x| x.rescaled.as_ref()).collect();
    if let Some(first) = rescaled.first() {
        notes.push(format!(
            "{} images differ in size from the scene file's metadata ({first}); their \
             intrinsics are scaled to the image size, check the metadata if that is wrong",
            rescaled.len()
        ));
    }
    Ok(notes)
}

/// Every image has the first image's size (formats whose intrinsics are shared).
fn check_one_size(frames: &[Frame]) -> Result<()> {
    let Some(first) = frames.first() else {
        return Ok(());
    };
    let size = (first.camera.width, first.camera.height);
    match frames
        .iter()
        .find(|f| (f.camera.width, f.camera.height) != size)
    {
        None => Ok(()),
        Some(f) => Err(NerfError::format(
            &f.image,
            format!(
                "is {}x{} but the scene's images are {}x{} (as {} is); one camera angle is \
                 shared by all of them, so every image must have the same size",
                f.camera.width,
                f.camera.height,
                size.0,
                size.1,
                first.image.display()
            ),
        )),
    }
}

/// Drops frames that name an image already listed (kept: the first), so a file listing
/// an image twice cannot put it in both the training and the test split. Returns how many
/// frames are left.
fn dedupe_frames(frames: &mut Vec<Frame>, notes: &mut Vec<String>) -> usize {
    let before = frames.len();
    let mut seen = std::collections::HashSet::new();
    frames.retain(|f| seen.insert(f.image.clone()));
    if frames.len() < before {
        notes.push(format!(
            "the scene lists {} images more than once; each is kept once, so no test image \
             is also trained on",
            before - frames.len()
        ));
    }
    frames.len()
}

/// Explicit splits with an image listed twice in a split kept once, and a note when a
/// held-out image is also a training image.
fn dedupe_splits(
    frames: &[Frame],
    splits: [Vec<usize>; 3],
    notes: &mut Vec<String>,
) -> [Vec<usize>; 3] {
    let mut dropped = 0;
    let splits = splits.map(|split| {
        let mut seen = std::collections::HashSet::new();
        let before = split.len();
        let kept: Vec<usize> = split
            .into_iter()
            .filter(|&i| seen.insert(&frames[i].image))
            .collect();
        dropped += before - kept.len();
        kept
    });
    if dropped > 0 {
        notes.push(format!(
            "{dropped} frames repeat an image already listed in their split; each is kept once"
        ));
    }
    let train: std::collections::HashSet<&PathBuf> =
        splits[0].iter().map(|&i| &frames[i].image).collect();
    let leaked = splits[2]
        .iter()
        .filter(|&&i| train.contains(&frames[i].image))
        .count();
    if leaked > 0 {
        notes.push(format!(
            "{leaked} test images are also training images: test PSNR will be optimistic"
        ));
    }
    splits
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
