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

use super::reader::{find_moved, fit_to_image, image_dimensions};
pub use super::reader::{Convention, Format, Frame, PlacedBox, SceneOptions};
use super::{Dataset, RgbaImage, Split, View};
use crate::camera::ray_space::RaySpace;
use crate::camera::{Camera, Pose};
use crate::error::{NerfError, Result};
use rayon::prelude::*;

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
    pub(crate) problems: Vec<String>,
    /// Why the photos cannot be read, for a scene rebuilt from a run's snapshot of it (see
    /// `data::snapshot`); `None` for a scene read from its folder.
    pub(crate) photos_missing: Option<String>,
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
        let mut notes = parsed.notes;
        notes.extend(super::time::normalise(dir, &mut frames)?);
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
        if parsed.space == RaySpace::World {
            problems.extend(facing_away(
                format,
                &frames,
                &train,
                parsed.bound,
                parsed.far,
            ));
        }
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
            notes,
            problems,
            photos_missing: None,
        })
    }

    /// Whether the photos show moments of a moving scene (each frame has a time).
    pub fn is_dynamic(&self) -> bool {
        self.frames.iter().any(|f| f.time.is_some())
    }

    /// The distinct moments of `split`'s photos, in order (none in a static scene).
    pub fn moments(&self, split: Split) -> Vec<f32> {
        self.moments_of(self.indices(split).iter().copied())
    }

    /// The distinct moments of the photos `frames` (indices into [`Scene::frames`]), in
    /// order (none in a static scene).
    pub fn moments_of(&self, frames: impl IntoIterator<Item = usize>) -> Vec<f32> {
        let times = frames
            .into_iter()
            .filter_map(|i| self.frames.get(i).and_then(|f| f.time));
        super::time::moments(times)
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

    /// Why the photos cannot be read, for a scene rebuilt from a run's record of it.
    pub fn photos_missing(&self) -> Option<&str> {
        self.photos_missing.as_deref()
    }

    /// The cameras of a split at the resolution the scene is loaded at.
    pub fn cameras(&self, split: Split) -> Vec<Camera> {
        self.indices(split)
            .iter()
            .map(|&i| self.frames[i].camera.downscaled(self.image_factor))
            .collect()
    }

    /// A warning when held-out images (test or validation) of a scene with its own splits
    /// are copies of training images under other names (compared by content, so copies
    /// saved again match too): their scores would be measured on photos the model trained
    /// on. Reads every image of those splits, so it runs when a run starts and in
    /// `nerf scene`, not on every open.
    pub fn copied_held_out_images(&self) -> Result<Option<String>> {
        if self.format != Format::Blender || self.train.is_empty() || self.photos_missing.is_some()
        {
            return Ok(None);
        }
        let paths = |ids: &[usize]| -> Vec<&Path> {
            ids.iter()
                .map(|&i| self.frames[i].image.as_path())
                .collect()
        };
        let mut held_out: Vec<usize> = self.test.iter().chain(&self.val).copied().collect();
        held_out.sort_unstable();
        held_out.dedup();
        let copies = super::copies::copies_among(&paths(&held_out), &paths(&self.train))?;
        Ok((copies > 0).then(|| {
            format!(
                "{copies} of {} test and validation images are copies of training images \
                 under other names: their scores will be measured on photos the model \
                 trained on",
                held_out.len()
            )
        }))
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
        if let Some(missing) = &self.photos_missing {
            return Err(NerfError::NotFound(format!(
                "{missing}, and its {} photos are needed; pass --data DIR to say where it is",
                split.name()
            )));
        }
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
            drawn_views: None,
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
            time: frame.time,
        })
    }
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
    let kept: Vec<u32> = (0..small.width * small.height)
        .filter(|&i| small.pixel(i)[0] >= 0.5)
        .map(|i| i as u32)
        .collect();
    if kept.is_empty() {
        return Err(NerfError::format(
            path,
            "the mask leaves no pixel to train on",
        ));
    }
    Ok(kept)
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

/// A warning when most training cameras see no part of the box: a file read in another
/// convention than it was written in (OpenCV's axes read as OpenGL's, world-to-camera
/// matrices read as camera-to-world) has every camera looking away from the scene.
fn facing_away(
    format: Format,
    frames: &[Frame],
    train: &[usize],
    bound: f32,
    far: f32,
) -> Option<String> {
    let cameras: Vec<Camera> = train.iter().map(|&i| frames[i].camera.clone()).collect();
    let blind = super::aim::cameras_blind_to_box(&cameras, bound, far);
    if blind * 2 <= cameras.len() {
        return None;
    }
    let fix = match format {
        Format::Transforms => "try the other placement (--convention ngp or nerfstudio); ",
        _ => "",
    };
    Some(format!(
        "{blind} of {} training cameras see no part of the scene box ([-{bound}, {bound}]^3 \
         within {far} of them): they look away from it. The poses may be in another \
         convention than the file says (OpenCV axes, world-to-camera matrices) or placed \
         around another centre; {fix}check that they are camera-to-world matrices with \
         OpenGL axes (the camera looks down -Z, +Y up)",
        cameras.len()
    ))
}

/// Loads frames `0, every, 2 every, ...` (every one for 1) of one split of a Blender scene,
/// area-downscaling images by `downscale` (1 = full size).
pub fn load_blender(dir: &Path, split: Split, downscale: usize, every: usize) -> Result<Dataset> {
    let opts = SceneOptions {
        format: Some(Format::Blender),
        ..SceneOptions::default()
    };
    Scene::open(dir, &opts, downscale)?.load(split, every)
}
