//! Rendering the page's views: each request is rendered first at a preview size chosen to
//! hold the frame rate, then (once the camera stops) at twice the size and again up to the
//! full resolution. A newer request cancels the one being rendered between chunks of rays,
//! so no stale frames queue up.

use std::sync::mpsc::Receiver;
use std::sync::RwLock;
use std::time::Instant;

use rayon::prelude::*;

use nerf::camera::Camera;
use nerf::data::image::to_u8;
use nerf::stage::{Appearance, RayOutput};
use nerf::train::folder::LoadedRun;
use nerf::views::RenderSettings;

use crate::protocol::{FrameHeader, Mode, ViewCamera, HEADER_BYTES};

/// The preview's time budget: 10 frames a second while the camera moves, less a margin
/// for what does not grow with the frame's size (colouring, JPEG, sending), which the
/// per-ray estimate does not see.
pub const PREVIEW_SECONDS: f64 = 0.08;
/// Smallest preview scale of the full size (and smallest preview side in pixels).
const MIN_SCALE: f64 = 1.0 / 16.0;
const MIN_SIDE: usize = 16;

/// A trained run as the viewer renders it (replaced while a run trains under the viewer).
pub struct Model {
    pub run: RwLock<LoadedRun>,
    pub settings: RenderSettings,
    /// The training cameras' mean distance from the scene's centre (the origin): where
    /// the scene's near and far bounds were meant to be seen from.
    pub camera_distance: f32,
    /// Threads of its own to render with (beside a training run, so that viewing takes
    /// at most these cores); `None`: all of them.
    pub pool: Option<rayon::ThreadPool>,
}

/// A view the page asked for.
#[derive(Clone, Debug)]
pub struct ViewRequest {
    /// The page's number for the request (its frames carry it back).
    pub seq: u32,
    pub camera: ViewCamera,
    pub mode: Mode,
    /// The camera is being dragged: render the preview level only.
    pub moving: bool,
    /// Which learned photo appearance colours it (models trained with `--appearance`).
    pub appearance: Appearance,
    /// The moment of a moving scene it shows.
    pub time: Option<f32>,
}

/// One encoded frame: header and JPEG.
pub struct Frame {
    pub header: FrameHeader,
    pub bytes: Vec<u8>,
}

/// Keeps the preview's size in step with how fast this machine renders this model.
#[derive(Default)]
pub struct Pacer {
    /// Measured seconds per ray (a running average); `None` before the first frame.
    seconds_per_ray: Option<f64>,
}

impl Pacer {
    /// The scale of the full size that renders in [`PREVIEW_SECONDS`].
    pub fn preview_scale(&self, width: usize, height: usize) -> f64 {
        let Some(spr) = self.seconds_per_ray else {
            return 0.25;
        };
        let rays = PREVIEW_SECONDS / spr.max(1e-12);
        (rays / (width * height) as f64)
            .sqrt()
            .clamp(MIN_SCALE, 1.0)
    }

    /// Records that `rays` rays took `seconds`.
    pub fn record(&mut self, rays: usize, seconds: f64) {
        if rays < 256 {
            return;
        }
        let s = seconds / rays as f64;
        self.seconds_per_ray = Some(match self.seconds_per_ray {
            Some(old) => 0.7 * old + 0.3 * s,
            None => s,
        });
    }

    pub fn seconds_per_ray(&self) -> Option<f64> {
        self.seconds_per_ray
    }
}

/// The scales a request renders at: the preview, then doubling to the full size (only
/// the preview while the camera moves).
pub fn levels(preview: f64, moving: bool) -> Vec<f64> {
    let mut out = vec![preview];
    if !moving {
        let mut s = preview;
        while s < 1.0 {
            s = (s * 2.0).min(1.0);
            out.push(s);
        }
    }
    out
}

/// The image sizes a request renders at ([`levels`] of the full size, without repeats:
/// small images reach their floor of [`MIN_SIDE`] at several scales).
pub fn level_sizes(view: &ViewCamera, preview: f64, moving: bool) -> Vec<(usize, usize)> {
    let mut sizes: Vec<(usize, usize)> = levels(preview, moving)
        .into_iter()
        .map(|s| scaled_size(view, s))
        .collect();
    sizes.dedup();
    sizes
}

impl Model {
    /// The render settings for a camera at `eye`: the scene's, with the near and far
    /// bounds moved along with the camera when it is nearer or farther than the training
    /// cameras were, so zooming out never clips the scene away (world-space scenes; NDC
    /// bounds stay as they are).
    pub fn settings_at(&self, eye: [f32; 3]) -> RenderSettings {
        bounds_at(self.settings, self.camera_distance, eye)
    }

    /// Runs `f` with its parallel work on the viewer's threads ([`Model::pool`]).
    pub fn on_its_threads<R: Send>(&self, f: impl FnOnce() -> R + Send) -> R {
        match &self.pool {
            Some(pool) => pool.install(f),
            None => f(),
        }
    }
}

/// [`Model::settings_at`] for `settings` meant for cameras `camera_distance` from the
/// origin.
pub fn bounds_at(mut s: RenderSettings, camera_distance: f32, eye: [f32; 3]) -> RenderSettings {
    if matches!(s.space, nerf::camera::ray_space::RaySpace::World) {
        let d = (eye[0] * eye[0] + eye[1] * eye[1] + eye[2] * eye[2]).sqrt();
        let (front, back) = (camera_distance - s.near, s.far - camera_distance);
        s.near = s.near.min(d - front).max(0.0);
        s.far = s.far.max(d + back);
    }
    s
}

/// The size of `camera` at `scale` (each side at least [`MIN_SIDE`] or the full side).
pub fn scaled_size(camera: &ViewCamera, scale: f64) -> (usize, usize) {
    let side = |full: usize| {
        ((full as f64 * scale).round() as usize)
            .max(MIN_SIDE.min(full))
            .min(full)
    };
    (side(camera.width), side(camera.height))
}

/// The camera of a view at `width` x `height`.
pub fn camera_at(view: &ViewCamera, width: usize, height: usize) -> Camera {
    let aspect = width as f32 / height as f32;
    let fov_x = 2.0 * (aspect * (view.fov_y.to_radians() / 2.0).tan()).atan();
    Camera::from_fov_x(width, height, fov_x, view.c2w)
}

/// Renders `camera` through `model`, or `None` as soon as `cancelled` says so.
pub fn render(
    model: &Model,
    camera: &Camera,
    appearance: Appearance,
    time: Option<f32>,
    cancelled: &(dyn Fn() -> bool + Sync),
) -> Option<Vec<RayOutput>> {
    model.on_its_threads(|| render_here(model, camera, appearance, time, cancelled))
}

fn render_here(
    model: &Model,
    camera: &Camera,
    appearance: Appearance,
    time: Option<f32>,
    cancelled: &(dyn Fn() -> bool + Sync),
) -> Option<Vec<RayOutput>> {
    let run = model.run.read().unwrap_or_else(|e| e.into_inner());
    let settings = RenderSettings {
        appearance,
        time,
        ..model.settings_at(camera.origin())
    };
    let engine = run.engine.as_ref();
    let slab = engine.interactive_slab();
    nerf::views::render_pixels(engine, camera, &settings, slab, &|_| {}, cancelled)
}

/// The image a mode shows, as 8-bit RGB.
pub fn to_rgb8(out: &[RayOutput], mode: Mode, settings: &RenderSettings) -> Vec<u8> {
    let float: Vec<f32> = match mode {
        Mode::Rgb => out.par_iter().flat_map_iter(|o| o.rgb).collect(),
        Mode::Opacity => out.par_iter().flat_map_iter(|o| [o.opacity; 3]).collect(),
        Mode::Depth => {
            let depth: Vec<f32> = out.iter().map(|o| o.depth).collect();
            let opacity: Vec<f32> = out.iter().map(|o| o.opacity).collect();
            let (near, far) = nerf::app::video::auto_depth_range(&depth, &opacity)
                .unwrap_or((settings.near, settings.far));
            nerf::app::video::depth_turbo(&depth, &opacity, near, far)
        }
    };
    float.par_iter().map(|&v| to_u8(v)).collect()
}

/// Encodes 8-bit RGB as a JPEG.
pub fn jpeg(rgb: &[u8], width: usize, height: usize) -> Vec<u8> {
    let mut bytes = Vec::new();
    let mut encoder = image::codecs::jpeg::JpegEncoder::new_with_quality(&mut bytes, 90);
    // Encoding into memory fails only for sizes the protocol already refuses.
    if let Err(e) = encoder.encode(
        rgb,
        width as u32,
        height as u32,
        image::ExtendedColorType::Rgb8,
    ) {
        eprintln!("warning: encoding a {width}x{height} frame failed: {e}");
    }
    bytes
}

/// A request rendered at one size, before it is coloured and encoded.
pub struct Level {
    header: FrameHeader,
    out: Vec<RayOutput>,
    mode: Mode,
    /// The settings the view was rendered with (depth's fallback range).
    settings: RenderSettings,
}

/// Renders a request at `w` x `h`; `None` when cancelled.
pub fn render_level(
    model: &Model,
    pacer: &mut Pacer,
    request: &ViewRequest,
    (w, h): (usize, usize),
    cancelled: &(dyn Fn() -> bool + Sync),
) -> Option<Level> {
    let ViewRequest {
        seq,
        camera: ref view,
        mode,
        appearance,
        time,
        ..
    } = *request;
    let camera = camera_at(view, w, h);
    let t0 = Instant::now();
    let out = render(model, &camera, appearance, time, cancelled)?;
    let seconds = t0.elapsed().as_secs_f64();
    pacer.record(w * h, seconds);
    let header = FrameHeader {
        seq,
        width: w as u16,
        height: h as u16,
        mode: mode.code(),
        last: w == view.width && h == view.height,
        micros: (seconds * 1e6).min(u32::MAX as f64) as u32,
    };
    Some(Level {
        header,
        out,
        mode,
        settings: model.settings_at(view.c2w.map(|r| r[3])),
    })
}

impl Level {
    /// The frame the page gets: header and JPEG of the mode's image.
    pub fn encode(&self) -> Frame {
        let (w, h) = (self.header.width as usize, self.header.height as usize);
        let rgb = to_rgb8(&self.out, self.mode, &self.settings);
        let mut bytes = Vec::with_capacity(HEADER_BYTES + w * h);
        bytes.extend_from_slice(&self.header.encode());
        bytes.extend_from_slice(&jpeg(&rgb, w, h));
        Frame {
            header: self.header,
            bytes,
        }
    }
}

/// Encodes every level that comes down `levels` (on `model`'s threads) and hands its frame
/// to `send`, until `levels` closes or `send` says the page has gone (false). Run on a
/// thread of its own, it lets the next view render while this one is coloured and
/// encoded.
pub fn encode_levels(model: &Model, levels: Receiver<Level>, mut send: impl FnMut(Frame) -> bool) {
    for level in levels {
        if !send(model.on_its_threads(|| level.encode())) {
            return;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Bounds meant for cameras 4 units out (near 2, far 6) follow a camera that zooms out
    /// to 10 (far 12) or in to 1 (near 0), and stay for one at 4; NDC bounds never move.
    #[test]
    fn bounds_follow_the_camera_in_world_space() {
        let s = RenderSettings {
            near: 2.0,
            far: 6.0,
            background: [1.0; 3],
            space: nerf::camera::ray_space::RaySpace::World,
            appearance: Default::default(),
            time: None,
        };
        let at = |d: f32| {
            let b = bounds_at(s, 4.0, [0.0, d, 0.0]);
            (b.near, b.far)
        };
        assert_eq!(at(4.0), (2.0, 6.0));
        assert_eq!(at(10.0), (2.0, 12.0));
        assert_eq!(at(1.0), (0.0, 6.0));
        let ndc = RenderSettings {
            near: 0.0,
            far: 1.0,
            space: nerf::camera::ray_space::RaySpace::Ndc(nerf::camera::ray_space::Ndc {
                ax: 1.0,
                ay: 1.0,
                near: 1.0,
            }),
            ..s
        };
        let b = bounds_at(ndc, 4.0, [0.0, 10.0, 0.0]);
        assert_eq!((b.near, b.far), (0.0, 1.0));
    }

    #[test]
    fn levels_double_up_to_the_full_size_unless_moving() {
        assert_eq!(levels(0.125, false), vec![0.125, 0.25, 0.5, 1.0]);
        assert_eq!(levels(0.3, false), vec![0.3, 0.6, 1.0]);
        assert_eq!(levels(0.3, true), vec![0.3]);
        assert_eq!(levels(1.0, false), vec![1.0]);
    }

    #[test]
    fn the_preview_shrinks_as_rendering_slows() {
        let mut pacer = Pacer::default();
        assert_eq!(pacer.preview_scale(800, 800), 0.25);
        // 1 microsecond a ray: 80,000 rays in 0.08 s, about 283x283 of 800x800.
        pacer.record(10_000, 0.01);
        let s = pacer.preview_scale(800, 800);
        assert!((s - (80_000.0f64 / 640_000.0).sqrt()).abs() < 1e-9, "{s}");
        // Ten times slower: a smaller preview, never below 1/16.
        pacer.record(10_000, 1.0);
        assert!(pacer.preview_scale(800, 800) < s);
        pacer.record(10_000, 1e6);
        assert_eq!(pacer.preview_scale(800, 800), MIN_SCALE);
    }

    #[test]
    fn scaled_sizes_stay_within_the_full_size() {
        let view = ViewCamera {
            c2w: [
                [1.0, 0.0, 0.0, 0.0],
                [0.0, 1.0, 0.0, 0.0],
                [0.0, 0.0, 1.0, 4.0],
            ],
            fov_y: 40.0,
            width: 640,
            height: 480,
        };
        assert_eq!(scaled_size(&view, 0.25), (160, 120));
        assert_eq!(scaled_size(&view, 1.0), (640, 480));
        assert_eq!(scaled_size(&view, 0.001), (16, 16));
        assert_eq!(
            level_sizes(&view, 0.25, false),
            vec![(160, 120), (320, 240), (640, 480)]
        );
        let small = ViewCamera {
            width: 32,
            height: 32,
            ..view.clone()
        };
        assert_eq!(level_sizes(&small, 0.25, false), vec![(16, 16), (32, 32)]);
        let c = camera_at(&view, 64, 48);
        // The vertical field of view is the one asked for.
        let fov_y = 2.0 * (0.5 * 48.0 / c.fy).atan();
        assert!((fov_y.to_degrees() - 40.0).abs() < 1e-3);
    }
}
