//! The LLFF format (Mildenhall et al., "Local Light Field Fusion"), used for the NeRF
//! paper's forward-facing scenes: `poses_bounds.npy` beside `images/` (and optionally
//! smaller copies in `images_4/`, `images_8/`, ...).
//!
//! `poses_bounds.npy` is an `N x 17` float64 array, one row per image in file-name order:
//! a row-major 3x5 matrix `[R | t | (h, w, f)]` (camera-to-world, rotation columns
//! *down, right, backwards*; image height, width and focal length at full resolution),
//! then the near and far depth bounds of the image's scene points.
//!
//! Loading follows the paper's code: columns are reordered to OpenGL's (right, up,
//! backwards); the scene is scaled so the nearest bound sits at `1 / 0.75`; then
//! * forward-facing scenes are recentred on the average pose (it becomes the identity)
//!   and, by default, marched in NDC space with the near plane at 1;
//! * `--spherify` (inward-facing, 360-degree captures) moves the point nearest to all
//!   optical axes to the origin and scales the cameras to unit RMS radius. Unlike the
//!   reference code, which takes "up" from the mean camera offset (right for full
//!   spheres, sideways for a half circle of cameras), up is the cameras' mean up vector.

use std::path::{Path, PathBuf};

use super::npy;
use super::poses::{average_pose, into_frame_of, inward_frame, Similarity};
use super::reader::{fit_to_image, image_dimensions, Frame, Parsed, SceneOptions};
use crate::camera::ray_space::{Ndc, RaySpace};
use crate::camera::{Camera, Pose};
use crate::error::{NerfError, Result};

/// LLFF scales scenes so the nearest bound is `1 / BD_FACTOR`.
const BD_FACTOR: f32 = 0.75;

pub const POSES_FILE: &str = "poses_bounds.npy";

/// Images of the format: JPEG or PNG files, in name order.
pub fn list_images(folder: &Path) -> Result<Vec<PathBuf>> {
    let entries = std::fs::read_dir(folder).map_err(|e| NerfError::io(folder, e))?;
    let mut files: Vec<PathBuf> = entries
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.extension()
                .map(|e| e.to_string_lossy().to_ascii_lowercase())
                .is_some_and(|e| matches!(e.as_str(), "jpg" | "jpeg" | "png"))
        })
        .collect();
    files.sort();
    Ok(files)
}

/// One row of `poses_bounds.npy` as an OpenGL camera-to-world pose, full-resolution
/// `(h, w, f)` and the `(near, far)` bounds.
pub fn parse_row(row: &[f64]) -> (Pose, [f32; 3], [f32; 2]) {
    let m = |r: usize, c: usize| row[r * 5 + c] as f32;
    let mut pose = [[0.0; 4]; 3];
    for (r, out) in pose.iter_mut().enumerate() {
        // [down, right, back] -> [right, up, back].
        *out = [m(r, 1), -m(r, 0), m(r, 2), m(r, 3)];
    }
    (
        pose,
        [m(0, 4), m(1, 4), m(2, 4)],
        [row[15] as f32, row[16] as f32],
    )
}

/// The row of an OpenGL pose (inverse of [`parse_row`]), for writing fixtures.
pub fn make_row(pose: &Pose, hwf: [f32; 3], bounds: [f32; 2]) -> Vec<f64> {
    let mut row = vec![0.0f64; 17];
    for r in 0..3 {
        let cols = [-pose[r][1], pose[r][0], pose[r][2], pose[r][3], hwf[r]];
        for (c, v) in cols.into_iter().enumerate() {
            row[r * 5 + c] = v as f64;
        }
    }
    row[15] = bounds[0] as f64;
    row[16] = bounds[1] as f64;
    row
}

/// Half-extent of the NDC box that holds every training ray: NDC spans `[-1, 1]^3` for
/// the reference (average) camera, but the other cameras' frusta reach past its sides,
/// and rays leaving the box would see only the background colour.
fn ndc_bound(space: &RaySpace, cameras: &[Camera]) -> f32 {
    let mut extent = 1.0f32;
    for c in cameras {
        let (w, h) = (c.width as f32, c.height as f32);
        for (x, y) in [(0.0, 0.0), (w, 0.0), (0.0, h), (w, h)] {
            let ray = c.ray_at(x, y);
            let (o, d) = space.warp(ray.origin, ray.dir);
            for p in [o, [o[0] + d[0], o[1] + d[1], o[2] + d[2]]] {
                extent = extent.max(p[0].abs()).max(p[1].abs());
            }
        }
    }
    // A little margin for the cell the edge falls in; never more than a few times the
    // reference frustum, whatever odd camera the capture holds.
    (1.02 * extent).min(4.0)
}

pub(crate) fn parse(dir: &Path, opts: &SceneOptions, downscale: usize) -> Result<Parsed> {
    let npy_path = dir.join(POSES_FILE);
    let array = npy::read(&npy_path)?;
    if array.cols != 17 {
        return Err(NerfError::format(
            &npy_path,
            format!(
                "has shape {}x{}, expected N x 17 (3x5 pose + near, far per image)",
                array.rows, array.cols
            ),
        ));
    }
    if array.data.iter().any(|v| !v.is_finite()) {
        return Err(NerfError::format(&npy_path, "has a non-finite entry"));
    }
    let (folder, prescaled) = match dir.join(format!("images_{downscale}")) {
        p if downscale > 1 && p.is_dir() => (p, downscale),
        _ => (dir.join("images"), 1),
    };
    let images = list_images(&folder)?;
    if images.len() != array.rows {
        return Err(NerfError::format(
            &folder,
            format!(
                "holds {} images but {} lists {} poses",
                images.len(),
                npy_path.display(),
                array.rows
            ),
        ));
    }
    let size = image_dimensions(&images[0])?;
    let mut cameras = Vec::with_capacity(array.rows);
    let (mut near, mut far) = (f32::INFINITY, 0.0f32);
    for (k, image) in images.iter().enumerate() {
        let (pose, [h, w, f], [n, fa]) = parse_row(array.row(k));
        if !(h >= 1.0 && w >= 1.0 && f > 0.0 && n > 0.0 && fa > n) {
            return Err(NerfError::format(
                &npy_path,
                format!(
                    "row {k} ({}): needs h, w, focal > 0 and 0 < near < far, got h {h} w {w} f {f} near {n} far {fa}",
                    image.display()
                ),
            ));
        }
        let full = Camera {
            width: w as usize,
            height: h as usize,
            fx: f,
            fy: f,
            cx: 0.5 * w,
            cy: 0.5 * h,
            c2w: pose,
            distortion: Default::default(),
        };
        // Cameras at the resolution of the chosen folder (focal scaled along).
        let camera =
            fit_to_image(&full, size.0, size.1).map_err(|m| NerfError::format(image, m))?;
        cameras.push(camera);
        near = near.min(n);
        far = far.max(fa);
    }
    let sc = 1.0 / (near * BD_FACTOR);
    let scaled = Similarity {
        scale: sc,
        ..Similarity::IDENTITY
    };
    let scaled_poses: Vec<Pose> = cameras.iter().map(|c| scaled.apply_pose(&c.c2w)).collect();
    let frame = if opts.spherify {
        inward_frame(&scaled_poses, 1.0)
    } else {
        into_frame_of(&average_pose(&scaled_poses))
    };
    let placement = frame.after(&scaled);
    for c in &mut cameras {
        c.c2w = placement.apply_pose(&c.c2w);
    }
    // Bounds in placed units (the recentring frame keeps the scale).
    let (near, far) = (0.9 * near * sc * frame.scale, far * sc * frame.scale);
    let (space, bound) = if opts.spherify {
        (RaySpace::World, super::poses::INWARD_BOX)
    } else if opts.ndc {
        let c = &cameras[0];
        let space = RaySpace::Ndc(Ndc {
            ax: 2.0 * c.fx / c.width as f32,
            ay: 2.0 * c.fy / c.height as f32,
            near: 1.0,
        });
        (space, ndc_bound(&space, &cameras))
    } else {
        (RaySpace::World, far)
    };
    let frames = images
        .into_iter()
        .zip(cameras)
        .map(|(image, camera)| Frame {
            name: image
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default(),
            camera,
            image,
            mask: None,
            time: None,
        })
        .collect();
    Ok(Parsed {
        frames,
        splits: None,
        near,
        far,
        space,
        bound,
        contract: opts.spherify,
        prescaled,
        notes: Vec::new(),
        warnings: Vec::new(),
        one_size: false,
    })
}
