//! instant-ngp's and nerfstudio's `transforms.json`: one file for all images, with real
//! camera intrinsics and lens distortion.
//!
//! ```json
//! { "fl_x": 1375.5, "fl_y": 1374.5, "cx": 554.6, "cy": 965.3, "w": 1080, "h": 1920,
//!   "k1": 0.058, "k2": -0.081, "p1": -0.001, "p2": 0.0002, "aabb_scale": 4,
//!   "frames": [ { "file_path": "images/0001.jpg", "transform_matrix": [[...], ...] } ] }
//! ```
//!
//! * Intrinsics: `fl_x`/`fl_y` or `camera_angle_x`/`camera_angle_y`; `cx`, `cy` (default
//!   the image centre); `w`, `h` (default: read from the first image). Any of them, and the
//!   distortion, may also be given per frame, overriding the file's.
//! * Distortion: `k1 k2 k3 k4 p1 p2` with `camera_model` OPENCV (default) or
//!   OPENCV_FISHEYE; rays are undistorted (see `distortion`).
//! * `transform_matrix` is camera-to-world with OpenGL axes in both tools.
//! * `mask_path` (per frame, optional): black pixels are left out of training.
//!
//! The two tools place the world differently, so the convention matters:
//! * **instant-ngp** maps a camera position `p` to `p * scale + offset` (defaults 0.33 and
//!   (0.5, 0.5, 0.5)) and renders the cube `[0.5 - a/2, 0.5 + a/2]^3` with `a = aabb_scale`.
//!   We apply the same scale and offset, then move the cube's centre to the origin: the
//!   fast model's box has half-extent `aabb_scale / 2`.
//! * **nerfstudio** leaves placement to its data parser, which by default turns the mean
//!   camera up vector to +Z, centres the mean camera position and scales so the cameras fit
//!   in `[-1, 1]^3`. We do the same; the box is `[-1, 1]^3`.
//!
//! * **`nerf capture`** writes placed poses (instant-ngp's `scale` 1, `offset` 0.5) and
//!   records where to march as `"nerf_box": {"bound", "contract", "near", "far"}`
//!   ([`PlacedBox`]), which wins over `aabb_scale`: the scene then trains as its COLMAP
//!   model does.
//!
//! `Convention::Auto` weighs the evidence (see `TransformsJson::convention`): instant-ngp's
//! `scale`/`offset`, then nerfstudio's `applied_transform`/`ply_file_path`/`camera_model`,
//! then `aabb_scale`; the choice and its reason are printed with the flag that overrides it.

use std::path::Path;

use serde::Deserialize;

use super::poses::{centred_frame, Similarity};
use super::reader::{
    bounds_around_box, image_dimensions, resolve, Convention, Frame, Parsed, PlacedBox,
    SceneOptions,
};
use super::reader::{locate, parse_pose, pose_to_matrix, ScaledPoses};
use crate::camera::distortion::{Distortion, LensModel};
use crate::camera::ray_space::RaySpace;
use crate::camera::{Camera, Pose};
use crate::error::{NerfError, Result};

/// Intrinsics that may appear at the top level and in each frame. Per-frame layouts of
/// other tools are read too: `fx`/`fy` for `fl_x`/`fl_y`, and a 3x3 (or 4x4) matrix `K`.
#[derive(Clone, Debug, Default, Deserialize)]
pub(crate) struct Intrinsics {
    #[serde(alias = "fx")]
    fl_x: Option<f64>,
    #[serde(alias = "fy")]
    fl_y: Option<f64>,
    camera_angle_x: Option<f64>,
    camera_angle_y: Option<f64>,
    cx: Option<f64>,
    cy: Option<f64>,
    #[serde(rename = "K")]
    k_matrix: Option<Vec<Vec<f64>>>,
    w: Option<f64>,
    h: Option<f64>,
    k1: Option<f64>,
    k2: Option<f64>,
    k3: Option<f64>,
    k4: Option<f64>,
    p1: Option<f64>,
    p2: Option<f64>,
    camera_model: Option<String>,
}

/// Calls `$m!` with every field of [`Intrinsics`], so the lists cannot drift apart.
macro_rules! intrinsics_fields {
    ($m:ident) => {
        $m!(
            fl_x,
            fl_y,
            camera_angle_x,
            camera_angle_y,
            cx,
            cy,
            k_matrix,
            w,
            h,
            k1,
            k2,
            k3,
            k4,
            p1,
            p2,
            camera_model
        )
    };
}

impl Intrinsics {
    /// `self`'s values where given, `base`'s elsewhere.
    pub(crate) fn over(&self, base: &Intrinsics) -> Intrinsics {
        macro_rules! pick {
            ($($f:ident),*) => { Intrinsics { $($f: self.$f.clone().or(base.$f.clone()),)* } };
        }
        intrinsics_fields!(pick)
    }

    /// The names of the keys given beyond Blender's `camera_angle_x` (for saying what was
    /// read from another tool's layout).
    pub(crate) fn given(&self) -> Vec<&'static str> {
        let mut names = Vec::new();
        macro_rules! given {
            ($($f:ident),*) => { $(if self.$f.is_some() { names.push(stringify!($f)); })* };
        }
        intrinsics_fields!(given);
        names.retain(|n| *n != "camera_angle_x");
        names
    }

    /// The image size the intrinsics refer to, when the file gives it.
    pub(crate) fn size(&self) -> Option<(usize, usize)> {
        Some((self.w? as usize, self.h? as usize))
    }

    /// The camera angle the Blender format requires, when given.
    pub(crate) fn camera_angle_x(&self) -> Option<f64> {
        self.camera_angle_x
    }

    /// Focal lengths and principal point from a `K` matrix where not given by name.
    fn with_k(&self) -> std::result::Result<Intrinsics, String> {
        let Some(k) = &self.k_matrix else {
            return Ok(self.clone());
        };
        if !(k.len() == 3 || k.len() == 4) || k.iter().any(|r| r.len() != k.len()) {
            return Err(format!(
                "K must be a 3x3 (or 4x4) matrix, got rows of lengths {:?}",
                k.iter().map(Vec::len).collect::<Vec<_>>()
            ));
        }
        Ok(Intrinsics {
            fl_x: self.fl_x.or(Some(k[0][0])),
            fl_y: self.fl_y.or(Some(k[1][1])),
            cx: self.cx.or(Some(k[0][2])),
            cy: self.cy.or(Some(k[1][2])),
            ..self.clone()
        })
    }
}

#[derive(Debug, Deserialize)]
struct FrameJson {
    file_path: String,
    transform_matrix: Vec<Vec<f32>>,
    mask_path: Option<String>,
    /// D-NeRF's moment of the photo.
    time: Option<f32>,
    #[serde(flatten)]
    intrinsics: Intrinsics,
}

#[derive(Debug, Deserialize)]
struct TransformsJson {
    frames: Vec<FrameJson>,
    aabb_scale: Option<f32>,
    /// Where to march, as `nerf capture` recorded it.
    nerf_box: Option<PlacedBox>,
    scale: Option<f32>,
    offset: Option<[f32; 3]>,
    /// Keys only nerfstudio writes (evidence for its convention).
    applied_transform: Option<serde_json::Value>,
    ply_file_path: Option<String>,
    #[serde(flatten)]
    intrinsics: Intrinsics,
}

impl TransformsJson {
    /// Whose placement the file follows, and the evidence. instant-ngp's own keys `scale`
    /// and `offset` decide; then nerfstudio's (`applied_transform`, `ply_file_path`,
    /// `camera_model`), which outweigh an `aabb_scale` that nerfstudio files may also
    /// carry; then `aabb_scale`; nerfstudio when nothing tells.
    fn convention(&self) -> (bool, String) {
        let keys = |pairs: &[(&'static str, bool)]| -> Vec<&'static str> {
            pairs.iter().filter(|p| p.1).map(|p| p.0).collect()
        };
        let ngp_own = keys(&[
            ("scale", self.scale.is_some()),
            ("offset", self.offset.is_some()),
        ]);
        let studio = keys(&[
            ("applied_transform", self.applied_transform.is_some()),
            ("ply_file_path", self.ply_file_path.is_some()),
            ("camera_model", self.intrinsics.camera_model.is_some()),
        ]);
        if !ngp_own.is_empty() {
            (true, format!("it has instant-ngp's {}", ngp_own.join(", ")))
        } else if !studio.is_empty() {
            (false, format!("it has nerfstudio's {}", studio.join(", ")))
        } else if self.aabb_scale.is_some() {
            (true, "it has aabb_scale".into())
        } else {
            (false, "it has none of instant-ngp's keys".into())
        }
    }
}

/// Cameras farther than this many box half-extents from the box centre earn a warning.
const FAR_OUTSIDE: f32 = 10.0;

/// instant-ngp's defaults.
const NGP_SCALE: f32 = 0.33;
const NGP_OFFSET: [f32; 3] = [0.5; 3];

pub(crate) fn parse(dir: &Path, opts: &SceneOptions) -> Result<Parsed> {
    let json_path = dir.join("transforms.json");
    let mut doc: TransformsJson = crate::io::read_json(&json_path)?;
    if doc.frames.is_empty() {
        return Err(NerfError::format(&json_path, "lists no frames"));
    }
    // A stable order, so the held-out frames do not depend on how the file was written.
    doc.frames.sort_by(|a, b| a.file_path.cmp(&b.file_path));
    let bad = |k: usize, f: &FrameJson, m: String| {
        NerfError::format(&json_path, format!("frame {k} ({}): {m}", f.file_path))
    };
    let mut frames = Vec::with_capacity(doc.frames.len());
    let mut scaled = ScaledPoses::default();
    for (k, f) in doc.frames.iter().enumerate() {
        let (pose, scale) = parse_pose(&f.transform_matrix).map_err(|m| bad(k, f, m))?;
        scaled.add(scale);
        let image = resolve(dir, &f.file_path);
        let intr = f.intrinsics.over(&doc.intrinsics);
        let (w, h) = match (intr.w, intr.h) {
            (Some(w), Some(h)) => (w as usize, h as usize),
            _ => image_dimensions(&locate(dir, &image))?,
        };
        let camera = camera_from(&intr, w, h, pose).map_err(|m| bad(k, f, m))?;
        frames.push(Frame {
            camera,
            image,
            mask: f.mask_path.as_deref().map(|m| resolve(dir, m)),
            name: f.file_path.clone(),
            time: f.time,
        });
    }
    let (ngp, why) = match opts.convention {
        Convention::Ngp => (true, "--convention ngp".to_string()),
        Convention::Nerfstudio => (false, "--convention nerfstudio".to_string()),
        Convention::Auto => doc.convention(),
    };
    let mut notes = vec![format!(
        "transforms.json placed by {} rules ({why}); override with --convention {}",
        if ngp { "instant-ngp's" } else { "nerfstudio's" },
        if ngp { "nerfstudio" } else { "ngp" }
    )];
    notes.extend(scaled.note(&json_path));
    let poses: Vec<Pose> = frames.iter().map(|f| f.camera.c2w).collect();
    let (placement, bound) = if ngp {
        let s = doc.scale.unwrap_or(NGP_SCALE);
        let offset = doc.offset.unwrap_or(NGP_OFFSET);
        let aabb = doc.aabb_scale.unwrap_or(1.0);
        if !(s > 0.0 && aabb > 0.0) {
            return Err(NerfError::format(
                &json_path,
                format!("scale {s} and aabb_scale {aabb} must be positive"),
            ));
        }
        (
            Similarity {
                translation: offset.map(|o| o - 0.5),
                scale: s,
                ..Similarity::IDENTITY
            },
            0.5 * aabb,
        )
    } else {
        (centred_frame(&poses), 1.0)
    };
    for f in &mut frames {
        f.camera.c2w = placement.apply_pose(&f.camera.c2w);
    }
    let cameras: Vec<Camera> = frames.iter().map(|f| f.camera.clone()).collect();
    let far_out = cameras
        .iter()
        .filter(|c| c.origin().iter().any(|x| x.abs() > FAR_OUTSIDE * bound))
        .count();
    let mut warnings = Vec::new();
    if far_out > 0 {
        warnings.push(format!(
            "{far_out} of {} cameras sit more than {FAR_OUTSIDE} times the box's half-extent \
             ({bound}) from its centre: the object may be tiny in the box or outside it; \
             check the convention (--convention) or the box (--bound)",
            cameras.len()
        ));
    }
    let placed = match doc.nerf_box {
        Some(b) => {
            let valid = b.bound.is_finite()
                && b.bound > 0.0
                && b.near.is_finite()
                && b.far.is_finite()
                && 0.0 <= b.near
                && b.near < b.far;
            if !valid {
                return Err(NerfError::format(
                    &json_path,
                    format!(
                        "nerf_box {b:?} needs a positive bound and 0 <= near < far, all finite"
                    ),
                ));
            }
            notes.push(format!(
                "box from the file's nerf_box (as `nerf capture` placed it): half-extent {}{}",
                b.bound,
                if b.contract {
                    ", contracted beyond its inner half"
                } else {
                    ""
                }
            ));
            b
        }
        None => {
            let (near, far) = bounds_around_box(&cameras, bound);
            PlacedBox {
                bound,
                contract: false,
                near,
                far,
            }
        }
    };
    Ok(Parsed {
        frames,
        splits: None,
        near: placed.near,
        far: placed.far,
        space: RaySpace::World,
        bound: placed.bound,
        contract: placed.contract,
        prescaled: 1,
        notes,
        warnings,
        one_size: false,
    })
}

pub(crate) fn camera_from(
    intr: &Intrinsics,
    w: usize,
    h: usize,
    c2w: Pose,
) -> std::result::Result<Camera, String> {
    let intr = &intr.with_k()?;
    let focal = |fl: Option<f64>, angle: Option<f64>, size: usize| {
        fl.or(angle.map(|a| 0.5 * size as f64 / (0.5 * a).tan()))
    };
    let fx = focal(intr.fl_x, intr.camera_angle_x, w);
    let fy = focal(intr.fl_y, intr.camera_angle_y, h);
    let (fx, fy) = match (fx, fy) {
        (Some(x), Some(y)) => (x, y),
        (Some(x), None) => (x, x),
        (None, Some(y)) => (y, y),
        (None, None) => {
            return Err("no focal length (fl_x, fl_y, camera_angle_x or camera_angle_y)".into())
        }
    };
    if !(fx > 0.0 && fy > 0.0 && fx.is_finite() && fy.is_finite()) || w == 0 || h == 0 {
        return Err(format!(
            "focal lengths ({fx}, {fy}) and size {w}x{h} must be positive"
        ));
    }
    let model = match intr.camera_model.as_deref() {
        None
        | Some("OPENCV")
        | Some("PINHOLE")
        | Some("SIMPLE_PINHOLE")
        | Some("SIMPLE_RADIAL")
        | Some("RADIAL") => LensModel::Opencv,
        Some("OPENCV_FISHEYE") => LensModel::Fisheye,
        Some(m) if m.eq_ignore_ascii_case("EQUIRECTANGULAR") => {
            return Err(
                "camera_model EQUIRECTANGULAR (360-degree photos) is not supported: rays are \
                 cast through a pinhole or fisheye lens only; cut the panoramas into \
                 perspective views (e.g. nerfstudio's `ns-process-data images \
                 --camera-type equirectangular`) and train on those"
                    .into(),
            )
        }
        Some(other) => {
            return Err(format!(
                "camera_model {other:?} is not supported (OPENCV, OPENCV_FISHEYE, PINHOLE)"
            ))
        }
    };
    let c = |v: Option<f64>| v.unwrap_or(0.0) as f32;
    Ok(Camera {
        width: w,
        height: h,
        fx: fx as f32,
        fy: fy as f32,
        cx: intr.cx.map_or(0.5 * w as f32, |v| v as f32),
        cy: intr.cy.map_or(0.5 * h as f32, |v| v as f32),
        c2w,
        distortion: Distortion {
            model,
            k: [c(intr.k1), c(intr.k2), c(intr.k3), c(intr.k4)],
            p: [c(intr.p1), c(intr.p2)],
        },
    })
}

/// One frame of a `transforms.json` as `nerf capture` and `nerf export-cameras` write it:
/// the image's path, the camera-to-world matrix (OpenGL axes) and the camera's own
/// intrinsics and distortion.
pub fn frame_entry(camera: &Camera, file_path: &str) -> serde_json::Value {
    let d = &camera.distortion;
    serde_json::json!({
        "file_path": file_path,
        "transform_matrix": pose_to_matrix(&camera.c2w),
        "fl_x": camera.fx, "fl_y": camera.fy, "cx": camera.cx, "cy": camera.cy,
        "w": camera.width, "h": camera.height,
        "k1": d.k[0], "k2": d.k[1], "k3": d.k[2], "k4": d.k[3], "p1": d.p[0], "p2": d.p[1],
        "camera_model": if d.model == LensModel::Fisheye { "OPENCV_FISHEYE" } else { "OPENCV" },
    })
}

/// A whole `transforms.json` of cameras already placed in our frame (instant-ngp's
/// `scale` 1 and `offset` 0.5 keep them), with where to march (`nerf_box`); `aabb_scale`
/// is the power of two that holds the box, for instant-ngp.
pub fn placed_document(frames: Vec<serde_json::Value>, placed: &PlacedBox) -> serde_json::Value {
    serde_json::json!({
        "aabb_scale": (2.0 * placed.bound).max(1.0).log2().ceil().exp2(),
        "nerf_box": placed,
        "scale": 1.0,
        "offset": [0.5, 0.5, 0.5],
        "frames": frames,
    })
}
