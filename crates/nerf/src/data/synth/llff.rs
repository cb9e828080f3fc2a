//! Forward-facing captures of the built-in scenes, written in LLFF format: what a phone
//! held in front of an object sees, with known cameras (tests, `nerf synth --layout llff`).
//!
//! Cameras form a `rows x cols` grid in a plane 4 units in front of the object, all looking
//! along +Y with nearly parallel axes, as LLFF captures are. Images are opaque (the
//! background is mid-grey at infinity) and go to `images/` and, halved, to `images_2/`;
//! `poses_bounds.npy` gets each image's nearest and farthest surface depth as its bounds.

use std::path::Path;

use super::{render, Scene, SceneKind};
use crate::camera::{look_at, Camera};
use crate::data::image::save_rgb_png;
use crate::data::poses::Similarity;
use crate::data::{llff, npy, RgbaImage};
use crate::error::Result;

/// Grey behind the object.
const BACKGROUND: f32 = 0.5;

/// The grid of forward-facing cameras (`width x height`, horizontal field of view 0.75).
pub fn forward_facing_cameras(
    width: usize,
    height: usize,
    rows: usize,
    cols: usize,
) -> Vec<Camera> {
    let mut out = Vec::with_capacity(rows * cols);
    for row in 0..rows {
        for col in 0..cols {
            let u = if cols > 1 {
                col as f32 / (cols - 1) as f32 - 0.5
            } else {
                0.0
            };
            let v = if rows > 1 {
                0.5 - row as f32 / (rows - 1) as f32
            } else {
                0.0
            };
            let eye = [0.8 * u, -4.0, 0.6 * v];
            let target = [0.4 * u, 0.0, 0.3 * v];
            out.push(Camera::from_fov_x(
                width,
                height,
                0.75,
                look_at(eye, target, [0.0, 0.0, 1.0]),
            ));
        }
    }
    out
}

/// Renders `scene` from `cameras` into an LLFF folder `dir`, with poses expressed in a world
/// that is `world` of ours (identity for plain use; tests pass others so the loader's
/// placement has work to do). `on_image(done, total)` reports progress.
pub fn write(
    kind: SceneKind,
    cameras: &[Camera],
    supersample: usize,
    world: &Similarity,
    dir: &Path,
    on_image: &mut dyn FnMut(usize, usize),
) -> Result<()> {
    let scene = Scene::new(kind.parts());
    crate::io::create_dir(&dir.join("images"))?;
    crate::io::create_dir(&dir.join("images_2"))?;
    let mut rows = Vec::with_capacity(cameras.len() * 17);
    for (k, camera) in cameras.iter().enumerate() {
        let (w, h) = (camera.width, camera.height);
        let img = render(&scene, camera, supersample);
        let opaque: Vec<f32> = img
            .rgba
            .chunks_exact(4)
            .flat_map(|p| {
                [
                    p[0] * p[3] + BACKGROUND * (1.0 - p[3]),
                    p[1] * p[3] + BACKGROUND * (1.0 - p[3]),
                    p[2] * p[3] + BACKGROUND * (1.0 - p[3]),
                    1.0,
                ]
            })
            .collect();
        let full = RgbaImage::from_straight_alpha(w, h, opaque);
        save_rgb_png(
            &dir.join(format!("images/{k:03}.png")),
            w,
            h,
            &full.composite([0.0; 3]),
        )?;
        let half = full.downscale(2);
        save_rgb_png(
            &dir.join(format!("images_2/{k:03}.png")),
            half.width,
            half.height,
            &half.composite([0.0; 3]),
        )?;
        let hits = img.depth.iter().copied().filter(|d| *d > 0.0);
        let (near, far) = hits.fold((f32::INFINITY, 0.0f32), |(n, f), d| (n.min(d), f.max(d)));
        let (near, far) = if far > 0.0 { (near, far) } else { (1.0, 10.0) };
        let pose = world.apply_pose(&camera.c2w);
        rows.extend(llff::make_row(
            &pose,
            [h as f32, w as f32, camera.fx],
            [near * world.scale, far * world.scale],
        ));
        on_image(k + 1, cameras.len());
    }
    npy::write(
        &dir.join(llff::POSES_FILE),
        &npy::Array2 {
            rows: cameras.len(),
            cols: 17,
            data: rows,
        },
    )
}
