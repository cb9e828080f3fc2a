//! Scenes: posed images plus the bounds rays are marched over.
//!
//! One reader per on-disk format turns files into a [`scene::Scene`] (cameras, splits,
//! bounds), which loads a split's images into a [`Dataset`]; everything downstream
//! (training, evaluation, rendering) sees only these types.

pub mod blender;
pub mod colmap;
pub mod image;
pub mod llff;
pub mod npy;
pub mod pixels;
pub mod poses;
pub mod scene;
pub mod synth;
pub mod transforms;

use serde::{Deserialize, Serialize};

use crate::camera::Camera;
pub use image::RgbaImage;

/// One posed photograph.
#[derive(Clone, Debug)]
pub struct View {
    pub camera: Camera,
    pub image: RgbaImage,
    /// Where the image came from, for messages and output names.
    pub name: String,
    /// Pixels that count in training (`None`: all); from a mask image.
    pub kept_pixels: Option<Vec<u32>>,
}

/// The posed images of one split of a scene.
#[derive(Clone, Debug)]
pub struct Dataset {
    pub views: Vec<View>,
    /// Ray marching bounds along the (unnormalised) ray direction in ray space: depth
    /// units in world space, `0..1` in NDC.
    pub near: f32,
    pub far: f32,
    /// The space rays are marched in.
    pub space: crate::camera::ray_space::RaySpace,
}

impl Dataset {
    /// Keeps `n` views spread evenly over the split (the paper's 25 / 50 image ablations).
    pub fn keep_evenly(&mut self, n: usize) {
        let total = self.views.len();
        if n == 0 || n >= total {
            return;
        }
        let mut keep = vec![false; total];
        for k in 0..n {
            keep[k * total / n] = true;
        }
        let views = std::mem::take(&mut self.views);
        self.views = views
            .into_iter()
            .zip(keep)
            .filter_map(|(v, k)| k.then_some(v))
            .collect();
    }

    pub fn image_size(&self) -> (usize, usize) {
        self.views
            .first()
            .map(|v| (v.image.width, v.image.height))
            .unwrap_or((0, 0))
    }
}

/// Which part of a scene to load.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum Split {
    Train,
    Val,
    Test,
}

impl Split {
    pub fn name(self) -> &'static str {
        match self {
            Split::Train => "train",
            Split::Val => "val",
            Split::Test => "test",
        }
    }
}

/// The colour seen through transparent pixels.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum Background {
    White,
    Black,
    /// A fresh uniform colour per ray during training (white when evaluating), which stops
    /// the field from explaining the background with density.
    Random,
}

impl Background {
    /// The background used when evaluating and rendering.
    pub fn eval_colour(self) -> [f32; 3] {
        match self {
            Background::Black => [0.0; 3],
            Background::White | Background::Random => [1.0; 3],
        }
    }
}
