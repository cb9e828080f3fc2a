//! A COLMAP reconstruction as a scene: the sparse model's registered images, with their
//! camera models, placed in a canonical frame.
//!
//! Placement: the point nearest to every optical axis (what the capture looks at) moves to
//! the origin, the cameras' mean up vector becomes +Z, and the cameras sit at RMS distance
//! [`CAMERA_RADIUS`] from the origin. Near and far come from the depths of the 3-D points
//! each image sees (1st and 99th percentiles, with a margin); the fast model's box is
//! [`INWARD_BOX`], the same as LLFF `--spherify`'s, contracted beyond its inner half.

use std::path::Path;

use super::model::{self as colmap, CameraModel, Model};
use crate::camera::distortion::{Distortion, LensModel};
use crate::camera::ray_space::RaySpace;
use crate::camera::{Camera, Pose};
use crate::data::poses::{inward_frame, Similarity, INWARD_BOX};
use crate::data::reader::{bounds_around_box, Frame, Parsed, PlacedBox, SceneOptions};
use crate::error::{NerfError, Result};

/// RMS distance of the cameras from the scene centre after placement.
pub const CAMERA_RADIUS: f32 = 1.0;

pub(crate) fn parse(dir: &Path, _opts: &SceneOptions) -> Result<Parsed> {
    let (model_dir, model) = colmap::open_model(dir)?;
    let images_dir = dir.join("images");
    let (frames, placement) = frames_of(&model, &model_dir, &images_dir)?;
    let box_ = placed_box(&model, &placement, &frames);
    Ok(Parsed {
        frames,
        splits: None,
        near: box_.near,
        far: box_.far,
        space: RaySpace::World,
        bound: box_.bound,
        contract: box_.contract,
        prescaled: 1,
        notes: Vec::new(),
        warnings: Vec::new(),
        one_size: false,
    })
}

/// The registered images in name order, placed in the canonical frame, and that frame.
pub fn frames_of(
    model: &Model,
    model_dir: &Path,
    images_dir: &Path,
) -> Result<(Vec<Frame>, Similarity)> {
    if model.images.is_empty() {
        return Err(NerfError::format(
            model_dir,
            "the COLMAP model has no registered images",
        ));
    }
    let mut images: Vec<&colmap::Image> = model.images.iter().collect();
    images.sort_by(|a, b| a.name.cmp(&b.name));
    let poses: Vec<Pose> = images.iter().map(|i| i.camera_to_world()).collect();
    let placement = inward_frame(&poses, CAMERA_RADIUS);
    let frames = images
        .iter()
        .zip(&poses)
        .map(|(img, pose)| {
            let cam = &model.cameras[&img.camera_id];
            let mut camera = camera_of(cam)
                .map_err(|m| NerfError::format(model_dir, format!("camera {}: {m}", cam.id)))?;
            camera.c2w = placement.apply_pose(pose);
            Ok(Frame {
                camera,
                image: images_dir.join(&img.name),
                mask: None,
                name: img.name.clone(),
                time: None,
            })
        })
        .collect::<Result<Vec<_>>>()?;
    Ok((frames, placement))
}

/// Our camera (intrinsics and distortion; identity pose) for a COLMAP camera.
pub fn camera_of(c: &colmap::Camera) -> std::result::Result<Camera, String> {
    let p: Vec<f32> = c.params.iter().map(|&v| v as f32).collect();
    let (fx, fy, cx, cy, k, tangential, model) = match c.model {
        CameraModel::SimplePinhole => (p[0], p[0], p[1], p[2], [0.0; 4], [0.0; 2], LensModel::Opencv),
        CameraModel::Pinhole => (p[0], p[1], p[2], p[3], [0.0; 4], [0.0; 2], LensModel::Opencv),
        CameraModel::SimpleRadial => (p[0], p[0], p[1], p[2], [p[3], 0.0, 0.0, 0.0], [0.0; 2], LensModel::Opencv),
        CameraModel::Radial => (p[0], p[0], p[1], p[2], [p[3], p[4], 0.0, 0.0], [0.0; 2], LensModel::Opencv),
        CameraModel::Opencv => (p[0], p[1], p[2], p[3], [p[4], p[5], 0.0, 0.0], [p[6], p[7]], LensModel::Opencv),
        CameraModel::OpencvFisheye => (p[0], p[1], p[2], p[3], [p[4], p[5], p[6], p[7]], [0.0; 2], LensModel::Fisheye),
        CameraModel::Other(_) => {
            return Err(format!(
                "camera model {} is not supported (use SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV or OPENCV_FISHEYE, or undistort the images with `colmap image_undistorter`)",
                c.model.name()
            ))
        }
    };
    if !(fx > 0.0 && fy > 0.0) || c.width == 0 || c.height == 0 {
        return Err(format!(
            "focal ({fx}, {fy}) and size {}x{} must be positive",
            c.width, c.height
        ));
    }
    Ok(Camera {
        width: c.width as usize,
        height: c.height as usize,
        fx,
        fy,
        cx,
        cy,
        c2w: [
            [1.0, 0.0, 0.0, 0.0],
            [0.0, 1.0, 0.0, 0.0],
            [0.0, 0.0, 1.0, 0.0],
        ],
        distortion: Distortion {
            model,
            k,
            p: tangential,
        },
    })
}

/// The `q` quantile of values sorted in increasing order.
fn quantile(sorted: &[f32], q: f32) -> Option<f32> {
    let last = sorted.len().checked_sub(1)?;
    Some(sorted[(last as f32 * q).round() as usize])
}

/// Near and far from the depths of the points each image observes, in placed units.
fn depth_bounds(model: &Model, placement: &Similarity) -> Option<(f32, f32)> {
    let index: std::collections::HashMap<u64, [f64; 3]> =
        model.points.iter().map(|p| (p.id, p.xyz)).collect();
    let mut depths: Vec<f32> = model
        .images
        .iter()
        .flat_map(|img| {
            img.point_ids
                .iter()
                .filter_map(|id| index.get(id))
                .map(|&p| img.depth_of(p) as f32 * placement.scale)
                .filter(|d| *d > 0.0)
                .collect::<Vec<_>>()
        })
        .collect();
    depths.sort_by(f32::total_cmp);
    let near = quantile(&depths, 0.01)?;
    let far = quantile(&depths, 0.99)?;
    Some((0.5 * near, 1.5 * far))
}

/// Where the fast model marches a placed capture: the cameras' box ([`INWARD_BOX`] camera
/// radii, contracted beyond its inner half) and near and far from the points' depths
/// (around the box when the model has no points).
pub fn placed_box(model: &Model, placement: &Similarity, frames: &[Frame]) -> PlacedBox {
    let bound = INWARD_BOX * CAMERA_RADIUS;
    let (near, far) = depth_bounds(model, placement).unwrap_or_else(|| {
        let cameras: Vec<Camera> = frames.iter().map(|f| f.camera.clone()).collect();
        bounds_around_box(&cameras, bound)
    });
    PlacedBox {
        bound,
        contract: true,
        near,
        far,
    }
}
