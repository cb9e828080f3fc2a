//! `nerf synth`: renders a built-in scene (procedural furniture) into a Blender-format
//! dataset, with ground-truth depth. Deterministic for a seed.
//!
//! Train views lie on the upper hemisphere at radius 4, test views on a circle at 30 degrees
//! elevation, val views on the hemisphere; all look at the origin with lego's field of view.
//! Each pixel averages `supersample^2` jittered rays (anti-aliasing); alpha is the fraction
//! of them that hit the object, colour the mean of the hits (straight alpha, as Blender
//! writes it). Depth is the mean z-depth of the hits, as a 16-bit PNG in millimetres
//! (0 = background), listed per frame as `depth_file_path`.
//!
//! Animated (`--animate`), the furniture turns a quarter turn about +Z over the capture,
//! one photo per moment as D-NeRF's scenes are made: training photos from moment 0 to 1,
//! the other splits' at the moments between them, each frame with its `time`.

pub mod llff;
pub mod materials;
pub mod scenes;
pub mod shapes;
pub mod trace;

use std::path::Path;

use rayon::prelude::*;

use super::blender::{save_transforms, Frame, Transforms};
use super::image::{save_gray16_png, save_rgba_png};
use super::reader::pose_to_matrix;
use super::Split;
use crate::camera::{look_at, spherical, Camera, Pose};
use crate::error::{NerfError, Result};
use crate::math::{length, scale};
use crate::rng::Rng;
pub use scenes::SceneKind;
pub use trace::Scene;

/// Lego's horizontal field of view, so built-in scenes frame like the real data.
pub const FOV_X: f32 = 0.691_111_2;
/// Distance of all cameras from the origin.
pub const RADIUS: f32 = 4.0;

/// What to render.
#[derive(Clone, Debug)]
pub struct SynthOptions {
    pub scene: SceneKind,
    /// Square image size in pixels.
    pub size: usize,
    pub train_views: usize,
    pub val_views: usize,
    pub test_views: usize,
    /// Rays per pixel along each axis.
    pub supersample: usize,
    pub seed: u64,
    /// The scene turns over the capture (a moving scene, each frame at its own moment).
    pub animate: bool,
}

impl Default for SynthOptions {
    fn default() -> Self {
        SynthOptions {
            scene: SceneKind::Chair,
            size: 100,
            train_views: 100,
            val_views: 10,
            test_views: 40,
            supersample: 2,
            seed: 0,
            animate: false,
        }
    }
}

/// Camera poses of one split.
pub fn poses(split: Split, count: usize, seed: u64) -> Vec<Pose> {
    let mut rng = Rng::new(seed ^ ((split as u64 + 1) * 0x51f1));
    (0..count)
        .map(|k| {
            let (az, el) = match split {
                Split::Test => (
                    std::f32::consts::TAU * k as f32 / count as f32,
                    30f32.to_radians(),
                ),
                // Uniform on the hemisphere above 5 degrees.
                _ => (
                    rng.range(0.0, std::f32::consts::TAU),
                    rng.range(5f32.to_radians().sin(), 1.0).asin(),
                ),
            };
            look_at(spherical(RADIUS, az, el), [0.0; 3], [0.0, 0.0, 1.0])
        })
        .collect()
}

/// How far an animated scene turns about +Z (radians) from its first moment to its last.
pub const TURN: f32 = std::f32::consts::FRAC_PI_2;

/// The moment of photo `k` of the `count` of `split` in an animated scene: the training
/// photos' from 0 to 1, the other splits' between them (moments no training photo shows).
pub fn moment(split: Split, k: usize, count: usize) -> f32 {
    match split {
        Split::Train => k as f32 / count.saturating_sub(1).max(1) as f32,
        _ => (k as f32 + 0.5) / count.max(1) as f32,
    }
}

/// The pose from which the still scene looks as the scene turned for moment `time` does
/// from `pose`: the camera turned back about +Z by the scene's turn.
pub fn seen_at(pose: &Pose, time: f32) -> Pose {
    let (s, c) = (-TURN * time).sin_cos();
    let mut turned = *pose;
    for j in 0..4 {
        turned[0][j] = c * pose[0][j] - s * pose[1][j];
        turned[1][j] = s * pose[0][j] + c * pose[1][j];
    }
    turned
}

/// Split `split`'s photo `k` of `count` at `pose`: the camera as recorded, the one to
/// render the still scene from, and the moment (animated scenes).
fn shot(opts: &SynthOptions, split: Split, k: usize, count: usize, pose: Pose) -> Shot {
    let time = opts.animate.then(|| moment(split, k, count));
    let recorded = Camera::from_fov_x(opts.size, opts.size, FOV_X, pose);
    let mut rendered = recorded.clone();
    if let Some(t) = time {
        rendered.c2w = seen_at(&pose, t);
    }
    Shot {
        recorded,
        rendered,
        time,
    }
}

struct Shot {
    recorded: Camera,
    rendered: Camera,
    time: Option<f32>,
}

/// One rendered view: straight-alpha RGBA and z-depth (0 where empty).
pub struct SynthImage {
    pub rgba: Vec<f32>,
    pub depth: Vec<f32>,
}

/// Renders `camera`'s view of `scene`.
pub fn render(scene: &Scene, camera: &Camera, supersample: usize) -> SynthImage {
    let (w, h) = (camera.width, camera.height);
    let ss = supersample.max(1);
    let rows: Vec<(Vec<f32>, Vec<f32>)> = (0..h)
        .into_par_iter()
        .map(|j| {
            let mut rgba = vec![0.0f32; w * 4];
            let mut depth = vec![0.0f32; w];
            for i in 0..w {
                let (mut sum, mut hits, mut z) = ([0.0f32; 3], 0usize, 0.0f32);
                for sy in 0..ss {
                    for sx in 0..ss {
                        let x = i as f32 + (sx as f32 + 0.5) / ss as f32;
                        let y = j as f32 + (sy as f32 + 0.5) / ss as f32;
                        let ray = camera.ray_at(x, y);
                        let norm = length(ray.dir);
                        if let Some(hit) = scene.trace(ray.origin, scale(ray.dir, 1.0 / norm)) {
                            hits += 1;
                            z += hit.t / norm;
                            for c in 0..3 {
                                sum[c] += hit.colour[c];
                            }
                        }
                    }
                }
                if hits > 0 {
                    let px = &mut rgba[i * 4..][..4];
                    for c in 0..3 {
                        px[c] = sum[c] / hits as f32;
                    }
                    px[3] = hits as f32 / (ss * ss) as f32;
                    depth[i] = z / hits as f32;
                }
            }
            (rgba, depth)
        })
        .collect();
    let mut img = SynthImage {
        rgba: Vec::with_capacity(w * h * 4),
        depth: Vec::with_capacity(w * h),
    };
    for (r, d) in rows {
        img.rgba.extend(r);
        img.depth.extend(d);
    }
    img
}

/// Renders all splits into `out` (creating it). Returns the number of images written.
pub fn generate(
    opts: &SynthOptions,
    out: &Path,
    on_image: &mut dyn FnMut(usize, usize),
) -> Result<usize> {
    if opts.size < 8 {
        return Err(NerfError::Config(format!(
            "image size {} is too small (minimum 8)",
            opts.size
        )));
    }
    let scene = Scene::new(opts.scene.parts());
    let splits = [
        (Split::Train, opts.train_views),
        (Split::Val, opts.val_views),
        (Split::Test, opts.test_views),
    ];
    let total: usize = splits.iter().map(|s| s.1).sum();
    let mut done = 0;
    for (split, count) in splits {
        let dir = out.join(split.name());
        crate::io::create_dir(&dir)?;
        let mut frames = Vec::new();
        for (k, pose) in poses(split, count, opts.seed).into_iter().enumerate() {
            let shot = shot(opts, split, k, count, pose);
            let img = render(&scene, &shot.rendered, opts.supersample);
            save_rgba_png(
                &dir.join(format!("r_{k}.png")),
                opts.size,
                opts.size,
                &img.rgba,
            )?;
            let mm: Vec<u16> = img
                .depth
                .iter()
                .map(|&d| (d * 1000.0).round().clamp(0.0, 65535.0) as u16)
                .collect();
            save_gray16_png(
                &dir.join(format!("r_{k}_depth.png")),
                opts.size,
                opts.size,
                mm,
            )?;
            frames.push(Frame {
                file_path: format!("./{}/r_{k}", split.name()),
                transform_matrix: pose_to_matrix(&shot.recorded.c2w),
                depth_file_path: Some(format!("./{}/r_{k}_depth.png", split.name())),
                time: shot.time,
            });
            done += 1;
            on_image(done, total);
        }
        save_transforms(
            out,
            split,
            &Transforms {
                camera_angle_x: FOV_X,
                frames,
            },
        )?;
    }
    Ok(total)
}

/// One split of a built-in scene rendered in memory (no files), for benchmarks and tests.
pub fn dataset(opts: &SynthOptions, split: Split, count: usize) -> super::Dataset {
    let scene = Scene::new(opts.scene.parts());
    let views = poses(split, count, opts.seed)
        .into_iter()
        .enumerate()
        .map(|(k, pose)| {
            let shot = shot(opts, split, k, count, pose);
            let rgba = render(&scene, &shot.rendered, opts.supersample).rgba;
            let image = super::RgbaImage::from_straight_alpha(opts.size, opts.size, rgba);
            super::View {
                camera: shot.recorded,
                image,
                name: format!("{}/r_{k}", split.name()),
                kept_pixels: None,
                time: shot.time,
            }
        })
        .collect();
    super::Dataset {
        views,
        near: super::blender::NEAR,
        far: super::blender::FAR,
        space: Default::default(),
        drawn_views: None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::normalize_or_zero;

    #[test]
    fn generates_a_loadable_deterministic_dataset_with_true_depth() {
        let dir = tempfile::tempdir().expect("tempdir");
        let opts = SynthOptions {
            size: 24,
            train_views: 3,
            val_views: 1,
            test_views: 2,
            supersample: 2,
            ..Default::default()
        };
        assert_eq!(
            generate(&opts, dir.path(), &mut |_, _| {}).expect("synth"),
            6
        );
        let train =
            crate::data::scene::load_blender(dir.path(), Split::Train, 1, 1).expect("load train");
        assert_eq!(train.views.len(), 3);
        let img = &train.views[0].image;
        let coverage = (0..24 * 24).filter(|&i| img.pixel(i)[3] > 0.5).count();
        assert!(
            coverage > 24 * 24 / 20 && coverage < 24 * 24 * 3 / 4,
            "object covers {coverage} pixels"
        );
        // Same seed, same pixels.
        let again = tempfile::tempdir().expect("tempdir");
        generate(&opts, again.path(), &mut |_, _| {}).expect("synth");
        let a = std::fs::read(dir.path().join("train/r_1.png")).expect("read");
        let b = std::fs::read(again.path().join("train/r_1.png")).expect("read");
        assert_eq!(a, b);
        // Depth agrees with a directly traced ray at the image centre.
        let cam = &train.views[0].camera;
        let scene = Scene::new(SceneKind::Chair.parts());
        let depth = image::open(dir.path().join("train/r_0_depth.png"))
            .expect("depth")
            .to_luma16();
        let ray = cam.ray(12, 12);
        let norm = length(ray.dir);
        if let Some(hit) = scene.trace(ray.origin, scale(ray.dir, 1.0 / norm)) {
            let stored = depth.get_pixel(12, 12).0[0] as f32 / 1000.0;
            assert!(
                (stored - hit.t / norm).abs() < 0.05,
                "{stored} vs {}",
                hit.t / norm
            );
        }
        // Test views on the 30-degree circle, all at radius 4.
        for p in poses(Split::Test, 8, 0) {
            let d = normalize_or_zero([p[0][3], p[1][3], p[2][3]]);
            assert!((d[2] - 0.5).abs() < 1e-5);
        }
    }
}
