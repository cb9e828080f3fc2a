//! Rendering whole images from a trained model.
//!
//! Work mapping: the image's rays are cut into chunks; rayon hands chunks to threads, each
//! with its own workspace, and every chunk writes only its own slice of the output.

use rayon::prelude::*;

use crate::camera::Camera;
use crate::model::Model;
use crate::ray_space::RaySpace;
use crate::render::marched::{self, MarchWorkspace};
use crate::render::pipeline::{render_chunk, ChunkWorkspace, Rays};
use crate::render::volume::RayOutput;

/// How to render: marching bounds, background colour, rays per work unit, and the space
/// rays are marched in (world rays are warped into it, e.g. NDC for LLFF scenes).
#[derive(Clone, Copy, Debug)]
pub struct RenderSettings {
    /// Bounds in ray space (see `Dataset::near`).
    pub near: f32,
    pub far: f32,
    pub background: [f32; 3],
    pub chunk_rays: usize,
    pub space: RaySpace,
}

#[derive(Default)]
struct Scratch {
    ws: ChunkWorkspace,
    march: MarchWorkspace,
    origins: Vec<f32>,
    dirs: Vec<f32>,
    view_dirs: Vec<f32>,
    backgrounds: Vec<f32>,
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
    model: &Model,
    params: &[f32],
    camera: &Camera,
    settings: &RenderSettings,
    on_progress: &(dyn Fn(usize) + Sync),
) -> RenderedView {
    let (w, h) = (camera.width, camera.height);
    let out = render_in_chunks(
        model,
        params,
        settings,
        w * h,
        &|pixels, origins, dirs| {
            for p in pixels {
                let ray = camera.ray(p % w, p / w);
                origins.extend_from_slice(&ray.origin);
                dirs.extend_from_slice(&ray.dir);
            }
        },
        on_progress,
    );
    RenderedView {
        width: w,
        height: h,
        rgb: out.iter().flat_map(|o| o.rgb).collect(),
        depth: out.iter().map(|o| o.depth).collect(),
        opacity: out.iter().map(|o| o.opacity).collect(),
    }
}

/// Renders arbitrary world rays (packed `n x 3` origins and directions) with `settings`:
/// the same per-chunk renderers as whole views.
pub fn render_rays(
    model: &Model,
    params: &[f32],
    origins: &[f32],
    dirs: &[f32],
    settings: &RenderSettings,
) -> Vec<RayOutput> {
    render_in_chunks(
        model,
        params,
        settings,
        origins.len() / 3,
        &|r, o, d| {
            o.extend_from_slice(&origins[r.start * 3..r.end * 3]);
            d.extend_from_slice(&dirs[r.start * 3..r.end * 3]);
        },
        &|_| {},
    )
}

/// Appends the packed origins and directions of a range of rays.
type RaysOf<'a> = dyn Fn(std::ops::Range<usize>, &mut Vec<f32>, &mut Vec<f32>) + Sync + 'a;

/// Renders `n` rays in chunks of `settings.chunk_rays` on the rayon threads. `rays_of`
/// appends the origins and directions of a range of rays; `on_progress` gets the number of
/// rays finished so far.
fn render_in_chunks(
    model: &Model,
    params: &[f32],
    settings: &RenderSettings,
    n: usize,
    rays_of: &RaysOf<'_>,
    on_progress: &(dyn Fn(usize) + Sync),
) -> Vec<RayOutput> {
    let mut out = vec![RayOutput::default(); n];
    let chunk = settings.chunk_rays.max(1);
    let done = std::sync::atomic::AtomicUsize::new(0);
    // Workspaces grow to ~100 MB for the paper's model; a small pool hands the same few to
    // whichever thread takes the next chunk instead of building one per rayon job.
    let pool = std::sync::Mutex::new(Vec::<Scratch>::new());
    out.par_chunks_mut(chunk).enumerate().for_each(|(c, out)| {
        let mut s = pool
            .lock()
            .ok()
            .and_then(|mut p| p.pop())
            .unwrap_or_default();
        s.origins.clear();
        s.dirs.clear();
        s.backgrounds.clear();
        rays_of(
            c * chunk..c * chunk + out.len(),
            &mut s.origins,
            &mut s.dirs,
        );
        let warped = settings.space != RaySpace::World;
        if warped {
            // Colour stays conditioned on the world directions.
            s.view_dirs.clear();
            s.view_dirs.extend_from_slice(&s.dirs);
            for (o, d) in s
                .origins
                .chunks_exact_mut(3)
                .zip(s.dirs.chunks_exact_mut(3))
            {
                let (o2, d2) = settings.space.warp([o[0], o[1], o[2]], [d[0], d[1], d[2]]);
                o.copy_from_slice(&o2);
                d.copy_from_slice(&d2);
            }
        }
        for _ in 0..out.len() {
            s.backgrounds.extend_from_slice(&settings.background);
        }
        let rays = Rays {
            origins: &s.origins,
            dirs: &s.dirs,
            view_dirs: warped.then_some(&s.view_dirs[..]),
            backgrounds: &s.backgrounds,
            near: settings.near,
            far: settings.far,
        };
        render_any(model, params, &rays, (&mut s.ws, &mut s.march), out);
        if let Ok(mut p) = pool.lock() {
            p.push(s);
        }
        let n = done.fetch_add(out.len(), std::sync::atomic::Ordering::Relaxed) + out.len();
        on_progress(n);
    });
    out
}

/// One chunk through the model's own renderer.
fn render_any(
    model: &Model,
    params: &[f32],
    rays: &Rays,
    (vanilla, march): (&mut ChunkWorkspace, &mut MarchWorkspace),
    out: &mut [RayOutput],
) {
    match model {
        Model::Vanilla(m) => render_chunk(m, params, rays, vanilla, out),
        Model::Fast(m) => marched::render_chunk(m, params, rays, march, out),
    }
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
