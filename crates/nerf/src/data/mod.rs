//! Scenes: posed images plus the bounds rays are marched over.
//!
//! One reader per on-disk format turns files into a [`scene::Scene`] (cameras, splits,
//! bounds), which loads a split's images into a [`Dataset`]; everything downstream
//! (training, evaluation, rendering) sees only these types.

pub mod aim;
pub mod blender;
pub mod colmap;
pub mod copies;
pub mod image;
pub mod llff;
pub mod npy;
pub mod pixels;
pub mod poses;
pub mod reader;
pub mod scene;
pub mod snapshot;
pub mod synth;
pub mod time;
pub mod train_views;
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
    /// The moment the photo shows, in [0, 1], in a dynamic scene.
    pub time: Option<f32>,
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
    /// The views training rays are drawn from (`None`: all of them); camera refinement
    /// leaves out the cameras it cannot place (`train::stuck_cameras`).
    pub drawn_views: Option<Vec<usize>>,
}

pub use train_views::{evenly_kept, TrainViews};

impl Dataset {
    /// Keeps the views at `kept` (indices into the split, as `TrainViews::indices` gives
    /// them), in that order.
    pub fn keep(&mut self, kept: &[usize]) {
        let mut views: Vec<Option<View>> = std::mem::take(&mut self.views)
            .into_iter()
            .map(Some)
            .collect();
        self.views = kept
            .iter()
            .filter_map(|&i| views.get_mut(i)?.take())
            .collect();
        self.drawn_views = None;
    }

    /// Draws no more training rays from the views of `cameras` (indices among the first
    /// `count` views, each camera's photo at every scale of a multi-scale split).
    pub fn leave_out(&mut self, count: usize, cameras: &[usize]) {
        let count = count.max(1);
        let drawn: Vec<usize> = (0..self.views.len())
            .filter(|v| !cameras.contains(&(v % count)))
            .collect();
        self.drawn_views = (drawn.len() < self.views.len() && !drawn.is_empty()).then_some(drawn);
    }

    /// mip-NeRF's multi-scale variant of the split: every view also at 1/2, 1/4, ...,
    /// `1 / 2^(scales - 1)` of its resolution (area-averaged, intrinsics scaled, masks
    /// keeping a pixel where they kept any of its block), appended scale by scale after the
    /// originals. Training draws a view, then a pixel: each scale gets the same share of
    /// rays, which is mip-NeRF's loss weighted by pixel area with its variance reduced.
    pub fn add_scales(&mut self, scales: usize) -> crate::Result<()> {
        let originals = self.views.len();
        for k in 1..scales {
            let factor = 1usize << k;
            for i in 0..originals {
                let v = &self.views[i];
                let (w, h) = (v.image.width / factor, v.image.height / factor);
                if w == 0 || h == 0 {
                    return Err(crate::NerfError::Config(format!(
                        "--multiscale {scales}: {} is {}x{}, too small for 1/{factor} of it",
                        v.name, v.image.width, v.image.height
                    )));
                }
                let kept_pixels = v.kept_pixels.as_ref().map(|kept| {
                    let mut blocks: Vec<u32> = kept
                        .iter()
                        .filter_map(|&p| {
                            let (x, y) = (p as usize % v.image.width, p as usize / v.image.width);
                            let (bx, by) = (x / factor, y / factor);
                            (bx < w && by < h).then_some((by * w + bx) as u32)
                        })
                        .collect();
                    blocks.sort_unstable();
                    blocks.dedup();
                    blocks
                });
                let view = View {
                    camera: v.camera.downscaled(factor),
                    image: v.image.downscale(factor),
                    name: format!("{} (1/{factor})", v.name),
                    kept_pixels,
                    time: v.time,
                };
                self.views.push(view);
            }
        }
        Ok(())
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::{look_at, Camera};

    /// Each scale's views are area averages with intrinsics scaled, appended
    /// after the originals, and masks keep a block where they kept any of its pixels.
    #[test]
    fn scales_are_area_averaged_views_with_scaled_cameras() {
        let (w, h) = (8, 4);
        let data: Vec<f32> = (0..w * h)
            .flat_map(|i| [i as f32 / 32.0, 0.5, 1.0, 1.0])
            .collect();
        let view = View {
            camera: Camera::from_fov_x(
                w,
                h,
                0.8,
                look_at([0.0, -4.0, 0.0], [0.0; 3], [0.0, 0.0, 1.0]),
            ),
            image: RgbaImage::from_straight_alpha(w, h, data),
            name: "a.png".into(),
            // Pixels (3, 0) and (6, 3).
            kept_pixels: Some(vec![3, 3 * 8 + 6]),
            time: Some(0.25),
        };
        let mut set = Dataset {
            views: vec![view],
            near: 2.0,
            far: 6.0,
            space: Default::default(),
            drawn_views: None,
        };
        set.add_scales(3).expect("scales");
        assert_eq!(set.views.len(), 3);
        let (half, quarter) = (&set.views[1], &set.views[2]);
        assert_eq!((half.image.width, half.image.height), (4, 2));
        assert_eq!((quarter.image.width, quarter.image.height), (2, 1));
        assert_eq!(half.camera, set.views[0].camera.downscaled(2));
        assert_eq!(half.name, "a.png (1/2)");
        // Half-resolution pixel (1, 0) averages pixels 2, 3, 10, 11 of the original.
        let expected = (2.0 + 3.0 + 10.0 + 11.0) / 4.0 / 32.0;
        assert!((half.image.pixel(1)[0] - expected).abs() < 1e-6);
        assert_eq!(half.kept_pixels, Some(vec![1, 4 + 3]));
        assert_eq!(quarter.kept_pixels, Some(vec![0, 1]));
        // Each scale shows the same moment.
        assert!(set.views.iter().all(|v| v.time == Some(0.25)));
        // Too many scales for the image: a clear error.
        let err = set.add_scales(5).expect_err("1/16 of 8x4 is empty");
        assert!(err.to_string().contains("too small"), "{err}");
    }
}
