//! What a run keeps of its scene, so that rendering needs no photos: every camera of every
//! split, the bounds, the ray space and the box (`scene.json` in the run folder). A run
//! whose scene was moved away or never copied along still renders, meshes, exports its
//! cameras and opens in the viewer; evaluation and training, which read the photos, say
//! where the scene was looked for.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::reader::Frame;
use super::scene::{Format, Scene};
use crate::camera::distortion::Distortion;
use crate::camera::ray_space::RaySpace;
use crate::camera::{Camera, Pose};
use crate::error::Result;

/// One camera and the name of its photo.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
struct SavedFrame {
    name: String,
    /// The photo's path as the scene named it (for messages only).
    image: PathBuf,
    width: usize,
    height: usize,
    fx: f32,
    fy: f32,
    cx: f32,
    cy: f32,
    c2w: Pose,
    #[serde(default)]
    distortion: Distortion,
    /// The photo's moment, in a dynamic scene.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    time: Option<f32>,
}

/// A scene's cameras and bounds, at its images' full resolution.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SceneSnapshot {
    /// Where the scene was when the run was made.
    dir: PathBuf,
    format: Format,
    frames: Vec<SavedFrame>,
    train: Vec<usize>,
    val: Vec<usize>,
    test: Vec<usize>,
    near: f32,
    far: f32,
    space: RaySpace,
    bound: f32,
    contract: bool,
}

impl SceneSnapshot {
    /// The snapshot of `scene`, opened at full resolution (`downscale` 1).
    pub fn of(scene: &Scene) -> SceneSnapshot {
        let frames = scene
            .frames
            .iter()
            .map(|f| {
                let c = &f.camera;
                SavedFrame {
                    name: f.name.clone(),
                    image: f.image.clone(),
                    width: c.width,
                    height: c.height,
                    fx: c.fx,
                    fy: c.fy,
                    cx: c.cx,
                    cy: c.cy,
                    c2w: c.c2w,
                    distortion: c.distortion,
                    time: f.time,
                }
            })
            .collect();
        SceneSnapshot {
            dir: scene.dir.clone(),
            format: scene.format,
            frames,
            train: scene.train.clone(),
            val: scene.val.clone(),
            test: scene.test.clone(),
            near: scene.near,
            far: scene.far,
            space: scene.space,
            bound: scene.bound,
            contract: scene.contract,
        }
    }

    pub fn save(&self, path: &Path) -> Result<()> {
        crate::io::write_json(path, self)
    }

    pub fn load(path: &Path) -> Result<SceneSnapshot> {
        crate::io::read_json(path)
    }

    /// The scene the snapshot holds, at `1/downscale` of its resolution, whose photos
    /// cannot be read: `missing` says why, when something asks for them.
    pub fn scene(&self, downscale: usize, missing: String) -> Scene {
        let frames = self
            .frames
            .iter()
            .map(|f| Frame {
                camera: Camera {
                    width: f.width,
                    height: f.height,
                    fx: f.fx,
                    fy: f.fy,
                    cx: f.cx,
                    cy: f.cy,
                    c2w: f.c2w,
                    distortion: f.distortion,
                },
                image: f.image.clone(),
                mask: None,
                name: f.name.clone(),
                time: f.time,
            })
            .collect();
        Scene {
            dir: self.dir.clone(),
            format: self.format,
            frames,
            train: self.train.clone(),
            val: self.val.clone(),
            test: self.test.clone(),
            near: self.near,
            far: self.far,
            space: self.space,
            bound: self.bound,
            contract: self.contract,
            image_factor: downscale.max(1),
            notes: Vec::new(),
            problems: Vec::new(),
            photos_missing: Some(missing),
        }
    }
}
