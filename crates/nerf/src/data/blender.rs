//! The Blender ("NeRF synthetic") format: `transforms_{train,val,test}.json` beside RGBA PNGs.
//!
//! ```json
//! { "camera_angle_x": 0.69,
//!   "frames": [ { "file_path": "./train/r_0", "transform_matrix": [[...4 rows of 4...]] } ] }
//! ```
//! `file_path` is relative to the JSON file; `.png` is appended when it has no extension.
//! Matrices are camera-to-world with OpenGL axes. Rays are marched from near 2 to far 6.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::scene::{Format, Frame as SceneFrame, Parsed, Scene, SceneOptions};
use super::transforms::{camera_from, Intrinsics};
use super::{Dataset, Split};
use crate::camera::ray_space::RaySpace;
use crate::camera::{Camera, Pose};
use crate::error::{NerfError, Result};

/// The JSON document of one split.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Transforms {
    pub camera_angle_x: f32,
    pub frames: Vec<Frame>,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Frame {
    pub file_path: String,
    pub transform_matrix: Vec<Vec<f32>>,
    /// Ground-truth depth written by `nerf synth` (16-bit PNG, millimetres), if any.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub depth_file_path: Option<String>,
}

/// Near and far bounds of the Blender scenes.
pub const NEAR: f32 = 2.0;
pub const FAR: f32 = 6.0;
/// Half-extent of the box that holds every Blender scene.
pub const BOUND: f32 = 1.5;

/// Path of the JSON file of `split` in `dir`.
pub fn transforms_path(dir: &Path, split: Split) -> PathBuf {
    dir.join(format!("transforms_{}.json", split.name()))
}

/// Loads one split, area-downscaling images by `downscale` (1 = full size).
pub fn load(dir: &Path, split: Split, downscale: usize) -> Result<Dataset> {
    load_every(dir, split, downscale, 1)
}

/// Loads frames `0, every, 2 every, ...` of one split (quick evaluations, validation views),
/// reading only their images.
pub fn load_every(dir: &Path, split: Split, downscale: usize, every: usize) -> Result<Dataset> {
    let opts = SceneOptions {
        format: Some(Format::Blender),
        ..SceneOptions::default()
    };
    Scene::open(dir, &opts, downscale)?.load(split, every)
}

/// One split's JSON as read: beside `camera_angle_x`, files exported by other tools may
/// carry instant-ngp's keys (`fl_x`, `cx`, `k1`, ..., `aabb_scale`, per file or per
/// frame). instant-ngp reads them, and so do we (see `transforms`); we say so.
#[derive(Deserialize)]
struct SplitJson {
    frames: Vec<FrameJson>,
    aabb_scale: Option<f32>,
    scale: Option<f32>,
    #[serde(flatten)]
    intrinsics: Intrinsics,
}

#[derive(Deserialize)]
struct FrameJson {
    file_path: String,
    transform_matrix: Vec<Vec<f32>>,
    #[serde(flatten)]
    intrinsics: Intrinsics,
}

/// instant-ngp's default scale from scene units to its unit cube.
const NGP_SCALE: f32 = 0.33;

/// Reads the three splits' JSON files (a missing `val` or `test` split is empty) and the
/// first image's header for the image size.
pub(crate) fn parse(dir: &Path) -> Result<Parsed> {
    let mut frames = Vec::new();
    let mut splits: [Vec<usize>; 3] = Default::default();
    let mut size = None;
    let mut notes = Vec::new();
    let mut bound = BOUND;
    for (s, split) in [Split::Train, Split::Val, Split::Test]
        .into_iter()
        .enumerate()
    {
        let json_path = transforms_path(dir, split);
        if split != Split::Train && !json_path.exists() {
            continue;
        }
        let doc: SplitJson = crate::io::read_json(&json_path)?;
        if doc.frames.is_empty() {
            return Err(NerfError::format(&json_path, "lists no frames"));
        }
        if let Some(fov) = doc.intrinsics.camera_angle_x() {
            if !(fov > 0.0 && fov < std::f64::consts::PI) {
                return Err(NerfError::format(
                    &json_path,
                    format!("camera_angle_x {fov} is not an angle in (0, pi)"),
                ));
            }
        }
        let mut given = doc.intrinsics.given();
        for f in &doc.frames {
            given.extend(f.intrinsics.given());
        }
        given.sort_unstable();
        given.dedup();
        if let Some(aabb) = doc.aabb_scale {
            let scale = doc.scale.unwrap_or(NGP_SCALE);
            if !(aabb > 0.0 && scale > 0.0 && aabb.is_finite()) {
                return Err(NerfError::format(
                    &json_path,
                    format!("aabb_scale {aabb} and scale {scale} must be positive"),
                ));
            }
            // instant-ngp's cube of side `aabb_scale` in its units, in scene units.
            bound = bound.max(0.5 * aabb / scale);
            given.push("aabb_scale");
        }
        if !given.is_empty() {
            notes.push(format!(
                "{} carries instant-ngp keys ({}); they are read as instant-ngp reads them \
                 (fl_x/fl_y over camera_angle_x, principal point, distortion, the box from \
                 aabb_scale)",
                json_path.display(),
                given.join(", ")
            ));
        }
        let base = json_path.parent().unwrap_or(Path::new("."));
        for (k, frame) in doc.frames.iter().enumerate() {
            let bad = |m: String| {
                NerfError::format(&json_path, format!("frame {k} ({}): {m}", frame.file_path))
            };
            let pose = parse_pose(&frame.transform_matrix).map_err(bad)?;
            let image = image_path(base, &frame.file_path);
            let intr = frame.intrinsics.over(&doc.intrinsics);
            // The size the intrinsics refer to: the file's `w`, `h`, else the first image's
            // (every image is checked against its camera when the scene opens).
            let (w, h) = match (intr.size(), size) {
                (Some(s), _) | (None, Some(s)) => s,
                (None, None) => *size.insert(super::scene::image_dimensions(
                    &super::scene::locate(dir, &image),
                )?),
            };
            let camera = camera_from(&intr, w, h, pose).map_err(bad)?;
            splits[s].push(frames.len());
            frames.push(SceneFrame {
                camera,
                image,
                mask: None,
                name: frame.file_path.clone(),
            });
        }
    }
    let (near, far) = if bound > BOUND {
        let cameras: Vec<Camera> = frames.iter().map(|f| f.camera.clone()).collect();
        super::scene::bounds_around_box(&cameras, bound)
    } else {
        (NEAR, FAR)
    };
    Ok(Parsed {
        frames,
        splits: Some(splits),
        near,
        far,
        space: RaySpace::World,
        bound,
        contract: false,
        prescaled: 1,
        notes,
        warnings: Vec::new(),
        one_size: true,
    })
}

/// `file_path` resolved against the JSON's folder, with `.png` added when it has no extension.
pub fn image_path(base: &Path, file_path: &str) -> PathBuf {
    let p = super::scene::resolve(base, file_path);
    if p.extension().is_none() {
        p.with_extension("png")
    } else {
        p
    }
}

/// Checks a 4x4 (or 3x4) camera-to-world matrix and keeps its top three rows.
pub fn parse_pose(m: &[Vec<f32>]) -> std::result::Result<Pose, String> {
    crate::camera::pose_from_rows(m).map_err(|e| e.replace("the matrix", "transform_matrix"))
}

/// Writes the JSON of one split atomically.
pub fn save_transforms(dir: &Path, split: Split, transforms: &Transforms) -> Result<()> {
    crate::io::write_json(&transforms_path(dir, split), transforms)
}

/// The pose as the 4x4 nested list the format stores.
pub fn pose_to_matrix(pose: &Pose) -> Vec<Vec<f32>> {
    let mut m: Vec<Vec<f32>> = pose.iter().map(|r| r.to_vec()).collect();
    m.push(vec![0.0, 0.0, 0.0, 1.0]);
    m
}

/// Reads just the JSON of a split (no images).
pub fn load_transforms(dir: &Path, split: Split) -> Result<Transforms> {
    crate::io::read_json(&transforms_path(dir, split))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::data::image::save_rgba_png;

    fn write_scene(dir: &Path, matrix: Vec<Vec<f32>>, sizes: &[(usize, usize)]) {
        std::fs::create_dir_all(dir.join("train")).expect("mkdir");
        let mut frames = Vec::new();
        for (k, &(w, h)) in sizes.iter().enumerate() {
            let name = format!("./train/r_{k}");
            save_rgba_png(
                &dir.join(format!("train/r_{k}.png")),
                w,
                h,
                &vec![0.5; w * h * 4],
            )
            .expect("png");
            frames.push(Frame {
                file_path: name,
                transform_matrix: matrix.clone(),
                depth_file_path: None,
            });
        }
        let t = Transforms {
            camera_angle_x: 0.69,
            frames,
        };
        save_transforms(dir, Split::Train, &t).expect("json");
    }

    fn identity() -> Vec<Vec<f32>> {
        (0..4)
            .map(|r| (0..4).map(|c| if r == c { 1.0 } else { 0.0 }).collect())
            .collect()
    }

    #[test]
    fn loads_and_downscales() {
        let dir = tempfile::tempdir().expect("tempdir");
        write_scene(dir.path(), identity(), &[(8, 6), (8, 6)]);
        let ds = load(dir.path(), Split::Train, 2).expect("load");
        assert_eq!(ds.views.len(), 2);
        assert_eq!(ds.image_size(), (4, 3));
        let f = 0.5 * 4.0 / (0.5f32 * 0.69).tan();
        assert!((ds.views[0].camera.fx - f).abs() < 1e-4);
    }

    #[test]
    fn errors_name_the_problem() {
        let dir = tempfile::tempdir().expect("tempdir");
        let mut bad = identity();
        bad[1].pop();
        write_scene(dir.path(), bad, &[(4, 4)]);
        let err = load(dir.path(), Split::Train, 1).expect_err("3-wide row");
        assert!(err.to_string().contains("must be 4x4"), "{err}");

        let dir = tempfile::tempdir().expect("tempdir");
        write_scene(dir.path(), identity(), &[(4, 4), (5, 4)]);
        let err = load(dir.path(), Split::Train, 1).expect_err("sizes differ");
        assert!(
            err.to_string().contains("r_1.png") && err.to_string().contains("5x4"),
            "{err}"
        );

        let dir = tempfile::tempdir().expect("tempdir");
        write_scene(dir.path(), identity(), &[(4, 4)]);
        std::fs::remove_file(dir.path().join("train/r_0.png")).expect("rm");
        let err = load(dir.path(), Split::Train, 1).expect_err("missing image");
        assert!(err.to_string().contains("r_0.png"), "{err}");

        std::fs::write(transforms_path(dir.path(), Split::Train), "{ \"frames\": [")
            .expect("write");
        let err = load(dir.path(), Split::Train, 1).expect_err("bad json");
        assert!(
            err.to_string().contains("transforms_train.json") && err.to_string().contains("JSON"),
            "{err}"
        );

        let dir = tempfile::tempdir().expect("tempdir");
        write_scene(dir.path(), identity(), &[(4, 4)]);
        let err = load(dir.path(), Split::Val, 1).expect_err("missing split");
        assert!(err.to_string().contains("transforms_val.json"), "{err}");
    }

    #[test]
    fn real_lego_if_present() {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/data/lego_400");
        if !dir.exists() {
            eprintln!("skipping: {} is absent", dir.display());
            return;
        }
        let ds = load(&dir, Split::Val, 4).expect("lego val");
        assert_eq!(ds.views.len(), 100);
        assert_eq!(ds.image_size(), (100, 100));
        let v = &ds.views[0];
        // Cameras sit about 4 units from the origin and look at it.
        let o = v.camera.origin();
        let r = (o[0] * o[0] + o[1] * o[1] + o[2] * o[2]).sqrt();
        assert!((r - 4.03).abs() < 0.1, "radius {r}");
        assert!(v.image.has_transparency());
    }
}
