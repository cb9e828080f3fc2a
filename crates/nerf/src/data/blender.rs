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

use super::aim::central_ray_hits_box;
use super::reader::{bounds_around_box, image_dimensions, locate, parse_pose, resolve};
use super::reader::{Frame as SceneFrame, Parsed, ScaledPoses};
use super::transforms::{camera_from, Intrinsics};
use super::Split;
use crate::camera::ray_space::RaySpace;
use crate::camera::Camera;
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
    /// The moment the photo shows, in a dynamic scene (D-NeRF's key, in [0, 1]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub time: Option<f32>,
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

/// One split's JSON as read: beside `camera_angle_x`, files exported by other tools may
/// carry instant-ngp's keys (`fl_x`, `cx`, `k1`, ..., `aabb_scale`, per file or per
/// frame). instant-ngp reads them, and so do we (see `transforms`); we say so.
#[derive(Deserialize)]
struct SplitJson {
    frames: Vec<FrameJson>,
    /// Marching bounds, as DS-NeRF's and other exporters write them.
    near: Option<f32>,
    far: Option<f32>,
    aabb_scale: Option<f32>,
    scale: Option<f32>,
    #[serde(flatten)]
    intrinsics: Intrinsics,
}

#[derive(Deserialize)]
struct FrameJson {
    file_path: String,
    transform_matrix: Vec<Vec<f32>>,
    /// D-NeRF's moment of the photo.
    time: Option<f32>,
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
    let mut scaled = ScaledPoses::default();
    let mut given_bounds: Option<(f32, f32, PathBuf)> = None;
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
        if let (Some(near), Some(far)) = (doc.near, doc.far) {
            if !(near.is_finite() && far.is_finite() && near >= 0.0 && near < far) {
                return Err(NerfError::format(
                    &json_path,
                    format!("near {near} and far {far} must be finite with 0 <= near < far"),
                ));
            }
            given_bounds.get_or_insert((near, far, json_path.clone()));
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
            let (pose, scale) = parse_pose(&frame.transform_matrix).map_err(bad)?;
            scaled.add(scale);
            let image = image_path(base, &frame.file_path);
            let intr = frame.intrinsics.over(&doc.intrinsics);
            // The size the intrinsics refer to: the file's `w`, `h`, else the first image's
            // (every image is checked against its camera when the scene opens).
            let (w, h) = match (intr.size(), size) {
                (Some(s), _) | (None, Some(s)) => s,
                (None, None) => *size.insert(image_dimensions(&locate(dir, &image))?),
            };
            let camera = camera_from(&intr, w, h, pose).map_err(bad)?;
            splits[s].push(frames.len());
            frames.push(SceneFrame {
                camera,
                image,
                mask: None,
                name: frame.file_path.clone(),
                time: frame.time,
            });
        }
    }
    notes.extend(scaled.note(&transforms_path(dir, Split::Train)));
    let (mut near, mut far) = if bound > BOUND {
        let cameras: Vec<Camera> = frames.iter().map(|f| f.camera.clone()).collect();
        bounds_around_box(&cameras, bound)
    } else {
        (NEAR, FAR)
    };
    if let Some((n, f, path)) = given_bounds {
        (near, far) = (n, f);
        if (n, f) != (NEAR, FAR) {
            notes.push(format!(
                "{}: near {n} and far {f} read from the file",
                path.display()
            ));
        }
    }
    if let Some(placed) = centre_on_what_cameras_see(&mut frames, bound, near, far) {
        bound = placed.bound;
        notes.push(placed.note);
    }
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

/// A box moved onto what the cameras look at, and what to tell the user.
struct Recentred {
    bound: f32,
    note: String,
}

/// Blender scenes are made around the origin, but files of the format written by other
/// tools may circle another point: when most central rays miss the box, the frames are
/// moved so that the point nearest every optical axis is the origin, and the box is sized
/// to what lies between `near` and `far` around it.
fn centre_on_what_cameras_see(
    frames: &mut [SceneFrame],
    bound: f32,
    near: f32,
    far: f32,
) -> Option<Recentred> {
    let missing = frames
        .iter()
        .filter(|f| !central_ray_hits_box(&f.camera, bound, far))
        .count();
    if missing * 2 <= frames.len() {
        return None;
    }
    let poses: Vec<crate::camera::Pose> = frames.iter().map(|f| f.camera.c2w).collect();
    let focus = super::poses::focus_point(&poses);
    // Each camera sees the focus at some depth; nothing nearer than `near` is in view,
    // so the subject reaches at most that depth minus `near` from the focus.
    let mut reach: Vec<f32> = frames
        .iter()
        .map(|f| {
            let depth = crate::math::length(crate::math::sub(focus, f.camera.origin()));
            (depth - near).clamp(0.1 * depth, depth)
        })
        .collect();
    reach.sort_by(f32::total_cmp);
    let new_bound = reach[reach.len() / 2];
    if !(new_bound.is_finite() && new_bound > 0.0) {
        return None;
    }
    for f in frames.iter_mut() {
        for (r, row) in f.camera.c2w.iter_mut().enumerate() {
            row[3] -= focus[r];
        }
    }
    Some(Recentred {
        bound: new_bound,
        note: format!(
            "{missing} of {} cameras look past the box around the origin: the scene is \
             moved by ({:.3}, {:.3}, {:.3}) so that what they look at is the origin, in a \
             box of half-extent {new_bound:.3} (--bound overrides)",
            frames.len(),
            -focus[0],
            -focus[1],
            -focus[2]
        ),
    })
}

/// `file_path` resolved against the JSON's folder, with `.png` added when it has no extension.
pub fn image_path(base: &Path, file_path: &str) -> PathBuf {
    let p = resolve(base, file_path);
    if p.extension().is_none() {
        p.with_extension("png")
    } else {
        p
    }
}

/// Writes the JSON of one split atomically.
pub fn save_transforms(dir: &Path, split: Split, transforms: &Transforms) -> Result<()> {
    crate::io::write_json(&transforms_path(dir, split), transforms)
}

/// Reads just the JSON of a split (no images).
pub fn load_transforms(dir: &Path, split: Split) -> Result<Transforms> {
    crate::io::read_json(&transforms_path(dir, split))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn load(dir: &Path, split: Split, downscale: usize) -> Result<crate::data::Dataset> {
        crate::data::scene::load_blender(dir, split, downscale, 1)
    }
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
                time: None,
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
