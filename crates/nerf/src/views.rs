//! Rendering whole views (and arbitrary world rays) through an engine: a camera's pixels
//! become a [`RayBatch`] in the scene's ray space, the engine renders it, and the results
//! are laid out as images (colour, depth, opacity).

use rayon::prelude::*;

use crate::camera::ray_space::RaySpace;
use crate::camera::{Camera, Ray};
use crate::data::scene::Scene;
use crate::data::Dataset;
use crate::engine::{Engine, PixelRays};
use crate::stage::{Appearance, RayBatch, RayOutput};

/// How to render: marching bounds, background colour, and the space rays are marched in
/// (world rays are warped into it, e.g. NDC for LLFF scenes).
#[derive(Clone, Copy, Debug)]
pub struct RenderSettings {
    /// Bounds in ray space (see `Dataset::near`).
    pub near: f32,
    pub far: f32,
    pub background: [f32; 3],
    pub space: RaySpace,
    /// Which photo's look a model with appearance codes renders (default: the mean).
    pub appearance: Appearance,
    /// The moment in [0, 1] a model of a moving scene renders (`None`: a still scene, or
    /// the model's own moment).
    pub time: Option<f32>,
}

impl RenderSettings {
    /// Settings to render a loaded split's rays over `background`.
    pub fn of_dataset(data: &Dataset, background: [f32; 3]) -> Self {
        RenderSettings {
            near: data.near,
            far: data.far,
            background,
            space: data.space,
            appearance: Appearance::Mean,
            time: None,
        }
    }

    /// Settings to render a scene's rays over `background`.
    pub fn of_scene(scene: &Scene, background: [f32; 3]) -> Self {
        let (near, far) = scene.ray_bounds();
        RenderSettings {
            near,
            far,
            background,
            space: scene.space,
            appearance: Appearance::Mean,
            time: None,
        }
    }

    /// World rays as a batch in ray space, seen from their world directions; their pixel
    /// ids count from `first`.
    pub fn ray_batch(&self, world: &[Ray], first: usize) -> RayBatch {
        let mut batch = RayBatch::new(self.near, self.far);
        batch.appearance = self.appearance;
        if let Some(time) = self.time {
            batch.times = vec![time; world.len()];
        }
        let warped: Vec<([f32; 3], [f32; 3])> = world
            .par_iter()
            .map(|r| self.space.warp(r.origin, r.dir))
            .collect();
        for (k, (r, (origin, dir))) in world.iter().zip(warped).enumerate() {
            batch.push(
                Ray { origin, dir },
                r.dir,
                self.background,
                (first + k) as u64,
            );
        }
        batch
    }

    /// [`ray_batch`](Self::ray_batch) of camera rays with their pixels' footprints (world
    /// cone radii, see [`Camera::cone_radius`]), warped into ray space.
    pub fn ray_batch_with_cones(&self, world: &[Ray], cones: &[f32], first: usize) -> RayBatch {
        let mut batch = self.ray_batch(world, first);
        batch.cylinders = self.space.cylinders();
        batch.radii = world
            .iter()
            .zip(cones)
            .map(|(r, &cone)| self.space.footprint_radius(cone, r.dir))
            .collect();
        batch
    }
}

/// Per-pixel results of one view.
#[derive(Clone, Debug)]
pub struct RenderedView {
    pub width: usize,
    pub height: usize,
    /// Packed RGB in [0, 1], composited over the background.
    pub rgb: Vec<f32>,
    /// Expected depth `sum w_i t_i` (0 where nothing was hit).
    pub depth: Vec<f32>,
    pub opacity: Vec<f32>,
}

/// Renders `camera`'s view; `on_progress` is called with the number of rays finished so far.
pub fn render_view(
    engine: &dyn Engine,
    camera: &Camera,
    settings: &RenderSettings,
    on_progress: &(dyn Fn(usize) + Sync),
) -> RenderedView {
    let never = || false;
    let out = render_pixels(
        engine,
        camera,
        settings,
        engine.render_slab(),
        on_progress,
        &never,
    )
    .unwrap_or_default();
    let mut rgb = vec![0.0; 3 * out.len()];
    rgb.par_chunks_exact_mut(3)
        .zip(out.par_iter())
        .for_each(|(c, o)| c.copy_from_slice(&o.rgb));
    RenderedView {
        width: camera.width,
        height: camera.height,
        rgb,
        depth: out.par_iter().map(|o| o.depth).collect(),
        opacity: out.par_iter().map(|o| o.opacity).collect(),
    }
}

/// Renders every one of `cameras`' views (the `k`th with `settings(k)`), `in_flight` at a
/// time (what `engine.views_in_flight()` advises), each on a thread of its own: on a GPU
/// one view's rounds keep the device busy while the host waits on or lays out another's.
/// Each view goes to `done` with its index as it finishes (views in flight finish in any
/// order; `done` may be called from several threads, and its own work overlaps the other
/// views' rendering); `on_rays` hears the rays finished over all views so far. Stops at
/// the first error `done` returns, and returns it.
pub fn render_views<E: Send>(
    engine: &dyn Engine,
    cameras: &[Camera],
    settings: &(dyn Fn(usize) -> RenderSettings + Sync),
    in_flight: usize,
    on_rays: &(dyn Fn(usize) + Sync),
    done: &(dyn Fn(usize, RenderedView) -> Result<(), E> + Sync),
) -> Result<(), E> {
    use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
    let (next, rays_done, failed) = (
        AtomicUsize::new(0),
        AtomicUsize::new(0),
        AtomicBool::new(false),
    );
    let worker = || -> Result<(), E> {
        loop {
            let k = next.fetch_add(1, Ordering::Relaxed);
            let Some(camera) = cameras.get(k) else {
                return Ok(());
            };
            if failed.load(Ordering::Relaxed) {
                return Ok(());
            }
            // Within a view, progress counts its own rays past those of the views done.
            let before = rays_done.load(Ordering::Relaxed);
            let view = render_view(engine, camera, &settings(k), &|n| on_rays(before + n));
            let pixels = camera.width * camera.height;
            on_rays(rays_done.fetch_add(pixels, Ordering::Relaxed) + pixels);
            if let Err(e) = done(k, view) {
                failed.store(true, Ordering::Relaxed);
                return Err(e);
            }
        }
    };
    let in_flight = in_flight.clamp(1, cameras.len().max(1));
    std::thread::scope(|scope| {
        let workers: Vec<_> = (1..in_flight).map(|_| scope.spawn(worker)).collect();
        let mine = worker();
        workers
            .into_iter()
            .map(|w| {
                w.join()
                    .unwrap_or_else(|panic| std::panic::resume_unwind(panic))
            })
            .fold(mine, Result::and)
    })
}

/// Every pixel of `camera`'s view (row by row), `slab` rays per engine call; `None` as
/// soon as `cancelled` says so between calls (the viewer stops a frame its camera has
/// left). `on_progress` hears the rays finished so far.
pub fn render_pixels(
    engine: &dyn Engine,
    camera: &Camera,
    settings: &RenderSettings,
    slab: usize,
    on_progress: &(dyn Fn(usize) + Sync),
    cancelled: &dyn Fn() -> bool,
) -> Option<Vec<RayOutput>> {
    let (w, h) = (camera.width, camera.height);
    let slab = slab.max(1);
    // Made in parallel: a large view's first touch of fresh pages is most of its cost.
    let mut out: Vec<RayOutput> = (0..w * h)
        .into_par_iter()
        .map(|_| RayOutput::default())
        .collect();
    for (k, part) in out.chunks_mut(slab).enumerate() {
        if cancelled() {
            return None;
        }
        let first = k * slab;
        let pixels = PixelRays {
            camera,
            pixels: first..first + part.len(),
            space: settings.space,
            near: settings.near,
            far: settings.far,
            background: settings.background,
            appearance: settings.appearance,
            time: settings.time,
        };
        if engine.render_pixels(&pixels, part) {
            on_progress(first + part.len());
            continue;
        }
        let (world, cones): (Vec<Ray>, Vec<f32>) = (first..first + part.len())
            .into_par_iter()
            .map(|p| {
                let (x, y) = ((p % w) as f32 + 0.5, (p / w) as f32 + 0.5);
                (camera.ray_at(x, y), camera.cone_radius(x, y))
            })
            .unzip();
        let rays = settings.ray_batch_with_cones(&world, &cones, first);
        engine.render_rays(&rays, part, &|n| on_progress(first + n));
    }
    Some(out)
}

/// Renders arbitrary world rays (packed `n x 3` origins and directions) with `settings`.
pub fn render_rays(
    engine: &dyn Engine,
    origins: &[f32],
    dirs: &[f32],
    settings: &RenderSettings,
) -> Vec<RayOutput> {
    let world: Vec<Ray> = origins
        .chunks_exact(3)
        .zip(dirs.chunks_exact(3))
        .map(|(o, d)| Ray {
            origin: [o[0], o[1], o[2]],
            dir: [d[0], d[1], d[2]],
        })
        .collect();
    let rays = settings.ray_batch(&world, 0);
    let mut out = vec![RayOutput::default(); rays.len()];
    engine.render_rays(&rays, &mut out, &|_| {});
    out
}

impl RenderedView {
    /// Depth as a grey image: near is white, far is dark, empty pixels black (scaled by
    /// opacity so soft edges stay soft).
    pub fn depth_image(&self, near: f32, far: f32) -> Vec<f32> {
        self.depth
            .iter()
            .zip(&self.opacity)
            .flat_map(|(&d, &a)| {
                let z = if a > 1e-4 { d / a } else { far };
                let v = (1.0 - (z - near) / (far - near)).clamp(0.0, 1.0) * a.clamp(0.0, 1.0);
                [v, v, v]
            })
            .collect()
    }
}
