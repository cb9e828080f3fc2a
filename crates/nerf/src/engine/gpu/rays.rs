//! Training rays made on the device from pixel indices: the training images and cameras
//! live on the device ([`GpuViews`], uploaded once per dataset), the host draws only each
//! ray's random choices ([`PixelChoice`]: view, pixel, background, jitter; 6 words a ray),
//! and one thread per ray casts the camera ray (`Camera::ray`), warps it into the scene's
//! ray space (`RaySpace::warp`, NDC included), clips it to the marcher's span
//! (`Marcher::span`), gathers its target colour over its background
//! (`RgbaImage::composite_pixel`) and, for anti-aliased fields, measures its footprint
//! (`Camera::cone_radius`): the rays `data::pixels` draws on the host, made where the
//! marcher reads them. A run that refines its cameras casts them from its corrected
//! cameras (`camera_poses`).
//!
//! Lens distortion has no closed-form inverse (`camera::distortion`: Newton steps in
//! `f64`), so a view with a distorted lens reads its undistorted image coordinates from a
//! table the host computes once per distinct lens (two floats a pixel); pinhole views need
//! none.

use cubecl::prelude::*;
use cubecl::server::Handle;

use super::device::Gpu;
use super::launch::grid;
use super::march::GpuRays;
use crate::camera::footprint::PIXEL_RADIUS;
use crate::camera::ray_space::RaySpace;
use crate::camera::Camera;
use crate::data::image::unit_values;
use crate::data::pixels::PixelChoice;
use crate::data::Dataset;
use crate::render::march::Marcher;

const GROUP: u32 = 64;
/// Floats per camera: fx, fy, cx, cy, then the 3x4 camera-to-world matrix by rows.
pub const CAM_WORDS: usize = 16;
/// Words per view: image width, first float of its image, first float of its lens table.
const META_WORDS: usize = 3;
/// "No lens table": a pinhole view.
const NO_TABLE: u32 = u32::MAX;
/// Most floats the images and lens tables may take on the device (4 GiB); a larger
/// dataset's rays are drawn on the host. Offsets below it fit a `u32`.
const MAX_FLOATS: usize = 1 << 30;
const _: () = assert!(MAX_FLOATS < u32::MAX as usize);

/// The ray space, the marcher's span and the lattice, as the kernel reads them.
#[derive(CubeType, CubeLaunch, Clone, Copy)]
pub struct RayGenParams {
    /// 1: warp into NDC (`ax`, `ay`, `ndc_near`: `camera::ray_space::Ndc`).
    ndc: u32,
    ax: f32,
    ay: f32,
    ndc_near: f32,
    /// Near and far along the camera direction; the occupancy box's half-extent.
    near: f32,
    far: f32,
    bound: f32,
    /// The lattice step, and 1 when space is contracted (the span is all of near..far).
    dt: f32,
    contract: u32,
}

/// A vector in a kernel.
#[derive(CubeType, Clone, Copy)]
struct V3 {
    x: f32,
    y: f32,
    z: f32,
}

/// The world direction of camera `c`'s (in `cams`) ray through normalised, undistorted
/// image coordinates `(u, w)`: `(u, -w, -1)` in camera axes (looking down -z, y up).
#[cube]
fn world_dir(cams: &[f32], c: usize, u: f32, w: f32) -> V3 {
    let m = c + 4;
    V3 {
        x: cams[m] * u - cams[m + 1] * w - cams[m + 2],
        y: cams[m + 4] * u - cams[m + 5] * w - cams[m + 6],
        z: cams[m + 8] * u - cams[m + 9] * w - cams[m + 10],
    }
}

/// Casts camera `c`'s ray through `(u, w)` (see [`world_dir`]), warps it into the ray
/// space (`RaySpace::warp`), clips it to the marcher's span (`Marcher::span`) and writes it
/// as ray `r` of a [`GpuRays`] (warped origin, unit direction, unit view direction, span
/// start `jitter` of a step in, span end). Returns the warped direction's length.
#[cube]
#[allow(clippy::too_many_arguments)]
fn cast(
    cams: &[f32],
    c: usize,
    u: f32,
    w: f32,
    jitter: f32,
    r: usize,
    origins: &mut [f32],
    dirs: &mut [f32],
    views: &mut [f32],
    start: &mut [f32],
    end: &mut [f32],
    p: RayGenParams,
) -> f32 {
    let world = world_dir(cams, c, u, w);
    let wx = world.x;
    let wy = world.y;
    let wz = world.z;
    let m = c + 4;
    let mut ox = cams[m + 3];
    let mut oy = cams[m + 7];
    let mut oz = cams[m + 11];
    let mut dx = wx;
    let mut dy = wy;
    let mut dz = wz;
    if p.ndc == 1 {
        if wz >= -1e-6f32 {
            // Not heading into the frustum: a ray that misses everything.
            ox = 0.0f32;
            oy = 0.0f32;
            oz = 10.0f32;
            dx = 0.0f32;
            dy = 0.0f32;
            dz = 1.0f32;
        } else {
            let n = p.ndc_near;
            let t = -(n + oz) / wz;
            let px = ox + t * wx;
            let py = oy + t * wy;
            let pz = oz + t * wz;
            ox = -p.ax * px / pz;
            oy = -p.ay * py / pz;
            oz = 1.0 + 2.0 * n / pz;
            dx = -p.ax * (wx / wz - px / pz);
            dy = -p.ay * (wy / wz - py / pz);
            dz = -2.0f32 * n / pz;
        }
    }
    let norm = f32::sqrt(dx * dx + dy * dy + dz * dz);
    let inv = 1.0 / norm;
    let ux = dx * inv;
    let uy = dy * inv;
    let uz = dz * inv;
    let view_inv = 1.0 / f32::sqrt(wx * wx + wy * wy + wz * wz);
    // The span: the box between near and far (`render::occupancy::ray_box`), or all of
    // near..far in contracted space.
    let mut t0 = p.near * norm;
    let mut t1 = p.far * norm;
    if p.contract == 0 {
        let b = p.bound;
        let near_x = slab_near(ox, ux, b);
        let far_x = slab_far(ox, ux, b);
        t0 = select(near_x > t0, near_x, t0);
        t1 = select(far_x < t1, far_x, t1);
        let near_y = slab_near(oy, uy, b);
        let far_y = slab_far(oy, uy, b);
        t0 = select(near_y > t0, near_y, t0);
        t1 = select(far_y < t1, far_y, t1);
        let near_z = slab_near(oz, uz, b);
        let far_z = slab_far(oz, uz, b);
        t0 = select(near_z > t0, near_z, t0);
        t1 = select(far_z < t1, far_z, t1);
    }
    let hit = t0 < t1;
    let k = 3 * r;
    origins[k] = ox;
    origins[k + 1] = oy;
    origins[k + 2] = oz;
    dirs[k] = ux;
    dirs[k + 1] = uy;
    dirs[k + 2] = uz;
    views[k] = wx * view_inv;
    views[k + 1] = wy * view_inv;
    views[k + 2] = wz * view_inv;
    start[r] = select(hit, t0 + jitter * p.dt, 0.0f32);
    end[r] = select(hit, t1, 0.0f32);
    norm
}

/// One thread per ray: see the module docs. Outputs as `GpuRays` holds them, the target
/// colour (`rays x 3`) and, with `footprints`, the footprint radius (`Camera::cone_radius`
/// then `RaySpace::footprint_radius`) of the view's given camera `given` (`cams` may be
/// corrected: a refined run's footprints are its given cameras', as on the host).
#[cube(launch_unchecked)]
#[allow(clippy::too_many_arguments)]
fn generate(
    chosen_views: &[u32],
    chosen_pixels: &[u32],
    backgrounds: &[f32],
    jitter: &[f32],
    meta: &[u32],
    cams: &[f32],
    given: &[f32],
    tables: &[f32],
    images: &[f32],
    packed_images: &[u32],
    units: &[f32],
    origins: &mut [f32],
    dirs: &mut [f32],
    views: &mut [f32],
    start: &mut [f32],
    end: &mut [f32],
    targets: &mut [f32],
    radii: &mut [f32],
    rays: u32,
    p: RayGenParams,
    #[comptime] packed: bool,
    #[comptime] footprints: bool,
) {
    let r = ABSOLUTE_POS;
    if r < rays as usize {
        let v = chosen_views[r] as usize;
        let pix = chosen_pixels[r];
        let width = meta[META_WORDS * v];
        let image = meta[META_WORDS * v + 1] as usize;
        let table = meta[META_WORDS * v + 2];
        let c = CAM_WORDS * v;
        // Normalised image coordinates of the pixel's centre, undistorted: by the pinhole
        // formula, or from the view's lens table.
        let i = pix % width;
        let j = pix / width;
        let pinhole_u = (f32::cast_from(i) + 0.5 - cams[c + 2]) / cams[c];
        let pinhole_w = (f32::cast_from(j) + 0.5 - cams[c + 3]) / cams[c + 1];
        let lens = table != NO_TABLE;
        // Lens tables have a column and a row past the image, for the footprints.
        let stride = width as usize + 1;
        let entry = table as usize + 2 * (j as usize * stride + i as usize);
        let at = select(lens, entry, 0usize);
        let u = select(lens, tables[at], pinhole_u);
        let w = select(lens, tables[at + 1], pinhole_w);
        let ndc = p.ndc;
        let ndc_area = p.ax * p.ay;
        cast(
            cams, c, u, w, jitter[r], r, origins, dirs, views, start, end, p,
        );
        if footprints {
            // The pixel's neighbours to the right and below, as `Camera::cone_radius`.
            let right = select(lens, entry + 2, 0usize);
            let below = select(lens, entry + 2 * stride, 0usize);
            let next_u = (f32::cast_from(i + 1) + 0.5 - cams[c + 2]) / cams[c];
            let next_w = (f32::cast_from(j + 1) + 0.5 - cams[c + 3]) / cams[c + 1];
            radii[r] = footprint(
                given,
                c,
                (u, w),
                (
                    select(lens, tables[right], next_u),
                    select(lens, tables[right + 1], pinhole_w),
                ),
                (
                    select(lens, tables[below], pinhole_u),
                    select(lens, tables[below + 1], next_w),
                ),
                ndc,
                ndc_area,
            );
        }
        // The pixel, premultiplied: from its four bytes as the host reads them
        // (`RgbaImage::pixel`), or from its floats.
        let (red, green, blue, alpha) = if packed {
            let word = packed_images[image + pix as usize];
            let a = units[(word >> 24) as usize];
            (
                units[(word & 255) as usize] * a,
                units[((word >> 8) & 255) as usize] * a,
                units[((word >> 16) & 255) as usize] * a,
                a,
            )
        } else {
            let q = image + 4 * pix as usize;
            (images[q], images[q + 1], images[q + 2], images[q + 3])
        };
        let k = 3 * r;
        let clear = 1.0 - alpha;
        targets[k] = red + backgrounds[k] * clear;
        targets[k + 1] = green + backgrounds[k + 1] * clear;
        targets[k + 2] = blue + backgrounds[k + 2] * clear;
    }
}

/// The distance between two unit vectors' directions `a / |a|` and `b / |b|`.
#[cube]
fn unit_apart(a: V3, b: V3) -> f32 {
    let ia = 1.0 / f32::sqrt(a.x * a.x + a.y * a.y + a.z * a.z);
    let ib = 1.0 / f32::sqrt(b.x * b.x + b.y * b.y + b.z * b.z);
    let x = a.x * ia - b.x * ib;
    let y = a.y * ia - b.y * ib;
    let z = a.z * ia - b.z * ib;
    f32::sqrt(x * x + y * y + z * z)
}

/// One thread per pixel `first + r` of a pinhole camera (`cams`: one camera, `width`
/// pixels a row): its ray as [`cast`] writes it, lattice jitter one half (the renderer's),
/// the inverse length of its warped direction (`inv_norm`, depth's scale) and its
/// footprint radius (`Camera::cone_radius` then `RaySpace::footprint_radius`).
#[cube(launch_unchecked)]
#[allow(clippy::too_many_arguments)]
fn cast_camera_rays(
    cams: &[f32],
    origins: &mut [f32],
    dirs: &mut [f32],
    views: &mut [f32],
    start: &mut [f32],
    end: &mut [f32],
    inv_norm: &mut [f32],
    radii: &mut [f32],
    first: u32,
    width: u32,
    rays: u32,
    p: RayGenParams,
) {
    let r = ABSOLUTE_POS;
    if r < rays as usize {
        let pix = first + r as u32;
        let fx = cams[0];
        let fy = cams[1];
        let ndc = p.ndc;
        let ndc_area = p.ax * p.ay;
        let u = (f32::cast_from(pix % width) + 0.5 - cams[2]) / fx;
        let w = (f32::cast_from(pix / width) + 0.5 - cams[3]) / fy;
        let norm = cast(
            cams, 0usize, u, w, 0.5f32, r, origins, dirs, views, start, end, p,
        );
        inv_norm[r] = 1.0 / norm;
        radii[r] = footprint(
            cams,
            0usize,
            (u, w),
            (u + 1.0 / fx, w),
            (u, w + 1.0 / fy),
            ndc,
            ndc_area,
        );
    }
}

/// The footprint radius of camera `c`'s (in `cams`) pixel at normalised, undistorted
/// image coordinates `here`, from its neighbours' to the right and below
/// (`Camera::cone_radius`), in the ray space (`RaySpace::footprint_radius`: `ndc` 1 for
/// NDC, `ndc_area` its `ax * ay`).
#[cube]
fn footprint(
    cams: &[f32],
    c: usize,
    here: (f32, f32),
    right: (f32, f32),
    below: (f32, f32),
    ndc: u32,
    ndc_area: f32,
) -> f32 {
    let (u, w) = here;
    let across = unit_apart(
        world_dir(cams, c, right.0, right.1),
        world_dir(cams, c, u, w),
    );
    let down = unit_apart(
        world_dir(cams, c, below.0, below.1),
        world_dir(cams, c, u, w),
    );
    let dir = world_dir(cams, c, u, w);
    let cone = PIXEL_RADIUS * f32::sqrt(across * down);
    let len = f32::sqrt(dir.x * dir.x + dir.y * dir.y + dir.z * dir.z);
    let ndc_cone = f32::sqrt(ndc_area) * cone * len / f32::max(f32::abs(dir.z), 1e-6);
    select(ndc == 1, ndc_cone, cone)
}

/// Where a ray `o + t d` (one axis) enters the slab `-b..b`, and where it leaves it
/// (`slab_far`), as `render::occupancy::ray_box` orders them: a ray parallel to the slab
/// gives infinities or NaN, which the callers' comparisons pass over.
#[cube]
fn slab_near(o: f32, d: f32, b: f32) -> f32 {
    let inv = 1.0 / d;
    let ta = (-b - o) * inv;
    let tb = (b - o) * inv;
    select(ta > tb, tb, ta)
}

#[cube]
fn slab_far(o: f32, d: f32, b: f32) -> f32 {
    let inv = 1.0 / d;
    let ta = (-b - o) * inv;
    let tb = (b - o) * inv;
    select(ta > tb, ta, tb)
}

/// The kernels' view of the ray space and the marcher over a box of half-extent `bound`.
fn gen_params(space: &RaySpace, marcher: &Marcher, bound: f32) -> RayGenParamsLaunch {
    let (ndc, ax, ay, ndc_near) = match space {
        RaySpace::World => (0, 1.0, 1.0, 1.0),
        RaySpace::Ndc(p) => (1, p.ax, p.ay, p.near),
    };
    RayGenParamsLaunch::new(
        ndc,
        ax,
        ay,
        ndc_near,
        marcher.near,
        marcher.far,
        bound,
        marcher.dt,
        u32::from(marcher.contract.is_some()),
    )
}

/// Rays of a camera's pixels made on the device, ready to render: the rays, each one's
/// inverse direction length (depth's scale) and footprint radius.
pub struct CameraRays {
    pub rays: GpuRays,
    pub inv_norm: Handle,
    pub radii: Handle,
}

/// The rays of `camera`'s `pixels` (row-major indices) in `space`, through `marcher` and
/// a grid of half-extent `bound`, as `views::render_pixels` makes them on the host; `None`
/// for a camera with lens distortion (its undistortion runs on the host).
pub fn camera_rays(
    gpu: &Gpu,
    camera: &Camera,
    space: &RaySpace,
    marcher: &Marcher,
    bound: f32,
    pixels: std::ops::Range<usize>,
) -> Option<CameraRays> {
    if !camera.distortion.is_pinhole() || camera.width == 0 || pixels.end > u32::MAX as usize {
        return None;
    }
    let n = pixels.len();
    let (origins, dirs, views) = (gpu.floats(3 * n), gpu.floats(3 * n), gpu.floats(3 * n));
    let (start, end) = (gpu.floats(n), gpu.floats(n));
    let (inv_norm, radii) = (gpu.floats(n), gpu.floats(n));
    if n > 0 {
        let mut cam = vec![camera.fx, camera.fy, camera.cx, camera.cy];
        cam.extend(camera.c2w.iter().flatten());
        // SAFETY: every output holds `n` rays (`3n` floats for vectors); `cams` one camera.
        unsafe {
            let (c, d) = grid(n, GROUP);
            cast_camera_rays::launch_unchecked(
                &gpu.client,
                c,
                d,
                BufferArg::from_raw_parts(gpu.upload(&cam), CAM_WORDS),
                BufferArg::from_raw_parts(origins.clone(), 3 * n),
                BufferArg::from_raw_parts(dirs.clone(), 3 * n),
                BufferArg::from_raw_parts(views.clone(), 3 * n),
                BufferArg::from_raw_parts(start.clone(), n),
                BufferArg::from_raw_parts(end.clone(), n),
                BufferArg::from_raw_parts(inv_norm.clone(), n),
                BufferArg::from_raw_parts(radii.clone(), n),
                pixels.start as u32,
                camera.width as u32,
                n as u32,
                gen_params(space, marcher, bound),
            );
        }
    }
    let rays = GpuRays {
        origins,
        dirs,
        views,
        start,
        end,
        len: n,
    };
    Some(CameraRays {
        rays,
        inv_norm,
        radii,
    })
}

/// Most words (floats, or pixels of four bytes) the training views' images or lens tables
/// may take on `gpu`: the adapter's largest storage buffer (128 MiB on some, such as
/// lavapipe and WebGPU's defaults), and never past `MAX_FLOATS`.
fn max_words(gpu: &Gpu) -> usize {
    let buffer = gpu.client.properties().memory.max_page_size / 4;
    usize::try_from(buffer).map_or(MAX_FLOATS, |b| b.min(MAX_FLOATS))
}

/// The training views of one dataset on the device.
pub struct GpuViews {
    meta: Handle,
    cams: Handle,
    tables: Handle,
    /// Every view's pixels: four bytes a pixel in one word (`packed`: every photo was read
    /// from an 8-bit file), else four premultiplied floats.
    images: Handle,
    packed: bool,
    /// [`unit_values`]: what the kernel turns a byte into.
    units: Handle,
    lens: [usize; 4],
}

impl GpuViews {
    /// Uploads `data`'s images, cameras and lens tables; `None` when they would pass
    /// what one of the adapter's buffers holds (the host draws the rays then).
    pub fn upload(gpu: &Gpu, data: &Dataset) -> Option<GpuViews> {
        GpuViews::upload_within(gpu, data, max_words(gpu))
    }

    /// [`upload`](Self::upload) with at most `limit` words of images and of lens tables.
    fn upload_within(gpu: &Gpu, data: &Dataset, limit: usize) -> Option<GpuViews> {
        let pixels: usize = data
            .views
            .iter()
            .map(|v| v.image.width * v.image.height)
            .sum();
        let packed = data
            .views
            .iter()
            .all(|v| v.image.straight_bytes().is_some());
        let words = if packed { pixels } else { 4 * pixels };
        let (mut meta, mut cams) = (Vec::new(), Vec::new());
        let (mut images, mut packed_images): (Vec<f32>, Vec<u32>) = (Vec::new(), Vec::new());
        let mut tables: Vec<f32> = Vec::new();
        // Distinct distorted lenses and where their tables start.
        let mut lenses: Vec<(Camera, usize)> = Vec::new();
        if words > limit {
            return None;
        }
        if packed {
            packed_images.reserve(words);
        } else {
            images.reserve(words);
        }
        for view in &data.views {
            let cam = &view.camera;
            let table = if cam.distortion.is_pinhole() {
                NO_TABLE as usize
            } else {
                let same = |(c, _): &&(Camera, usize)| same_lens(c, cam);
                match lenses.iter().find(same) {
                    Some((_, at)) => *at,
                    None => {
                        let at = tables.len();
                        if at + 2 * (cam.width + 1) * (cam.height + 1) > limit {
                            return None;
                        }
                        tables.extend(lens_table(cam));
                        lenses.push((cam.clone(), at));
                        at
                    }
                }
            };
            // Below the limit (checked above), every offset fits the kernel's u32.
            let image_at = images.len() + packed_images.len();
            meta.extend([cam.width as u32, image_at as u32, table as u32]);
            cams.extend([cam.fx, cam.fy, cam.cx, cam.cy]);
            cams.extend(cam.c2w.iter().flatten());
            match view.image.straight_bytes() {
                Some(bytes) if packed => packed_images.extend(
                    bytes
                        .chunks_exact(4)
                        .map(|p| u32::from_le_bytes([p[0], p[1], p[2], p[3]])),
                ),
                _ => images.extend(view.image.premultiplied()),
            }
        }
        // Pinhole views read (and ignore) the first two values.
        tables.extend([0.0, 0.0]);
        let image_words = images.len() + packed_images.len();
        Some(GpuViews {
            lens: [meta.len(), cams.len(), tables.len(), image_words],
            meta: gpu.upload_u32(&meta),
            cams: gpu.upload(&cams),
            tables: gpu.upload(&tables),
            images: match packed {
                true => gpu.upload_u32(&packed_images),
                false => gpu.upload(&images),
            },
            packed,
            units: gpu.upload(&unit_values()),
        })
    }

    /// Which dataset `data` is (its views' address and count), as far as the views on the
    /// device go: a step with another dataset uploads again.
    pub fn key_of(data: &Dataset) -> (usize, usize) {
        (data.views.as_ptr() as usize, data.views.len())
    }

    /// The views' cameras as uploaded ([`CAM_WORDS`] floats a view, one per view).
    pub fn cameras(&self) -> (&Handle, usize) {
        (&self.cams, self.lens[1] / CAM_WORDS)
    }

    /// The rays of `choices` (with their lattice jitters) through `marcher` and a grid of
    /// half-extent `bound`, cast from the views' cameras or from `cams` (as
    /// [`cameras`](Self::cameras) lays them out: the corrected cameras of a run that
    /// refines them), with their targets and backgrounds, and with `footprints` their
    /// footprint radii.
    #[allow(clippy::too_many_arguments)]
    pub fn generate(
        &self,
        gpu: &Gpu,
        space: &RaySpace,
        marcher: &Marcher,
        bound: f32,
        choices: &[PixelChoice],
        jitter: &[f32],
        cams: Option<&Handle>,
        footprints: bool,
    ) -> GeneratedRays {
        let n = choices.len();
        let views: Vec<u32> = choices.iter().map(|c| c.view as u32).collect();
        let of_ray = gpu.upload_u32(&views);
        let pixels: Vec<u32> = choices.iter().map(|c| c.pixel as u32).collect();
        let backgrounds: Vec<f32> = choices.iter().flat_map(|c| c.background).collect();
        let backgrounds = gpu.upload(&backgrounds);
        let (origins, dirs, unit_views) = (gpu.floats(3 * n), gpu.floats(3 * n), gpu.floats(3 * n));
        let (start, end, targets) = (gpu.floats(n), gpu.floats(n), gpu.floats(3 * n));
        let radii = gpu.floats(n.max(1));
        if n > 0 {
            let params = gen_params(space, marcher, bound);
            let cameras = cams;
            let [meta, cams, tables, images] = self.lens;
            // SAFETY: every buffer holds the length given with it; views and pixels index
            // the uploaded views and their images (drawn from this dataset), and a view's
            // lens table covers its pixels.
            unsafe {
                let (c, d) = grid(n, GROUP);
                generate::launch_unchecked(
                    &gpu.client,
                    c,
                    d,
                    BufferArg::from_raw_parts(of_ray.clone(), n),
                    BufferArg::from_raw_parts(gpu.upload_u32(&pixels), n),
                    BufferArg::from_raw_parts(backgrounds.clone(), 3 * n),
                    BufferArg::from_raw_parts(gpu.upload(jitter), n),
                    BufferArg::from_raw_parts(self.meta.clone(), meta),
                    BufferArg::from_raw_parts(cameras.unwrap_or(&self.cams).clone(), cams),
                    BufferArg::from_raw_parts(self.cams.clone(), cams),
                    BufferArg::from_raw_parts(self.tables.clone(), tables),
                    // The images as floats or as words: the kernel reads the one `packed`
                    // names (the other is the same buffer, unread).
                    BufferArg::from_raw_parts(self.images.clone(), images),
                    BufferArg::from_raw_parts(self.images.clone(), images),
                    BufferArg::from_raw_parts(self.units.clone(), 256),
                    BufferArg::from_raw_parts(origins.clone(), 3 * n),
                    BufferArg::from_raw_parts(dirs.clone(), 3 * n),
                    BufferArg::from_raw_parts(unit_views.clone(), 3 * n),
                    BufferArg::from_raw_parts(start.clone(), n),
                    BufferArg::from_raw_parts(end.clone(), n),
                    BufferArg::from_raw_parts(targets.clone(), 3 * n),
                    BufferArg::from_raw_parts(radii.clone(), n),
                    n as u32,
                    params,
                    self.packed,
                    footprints,
                );
            }
        }
        let rays = GpuRays {
            origins,
            dirs,
            views: unit_views,
            start,
            end,
            len: n,
        };
        GeneratedRays {
            rays,
            targets,
            backgrounds,
            of_ray,
            radii: footprints.then_some(radii),
        }
    }
}

/// Training rays made on the device ([`GpuViews::generate`]).
pub struct GeneratedRays {
    pub rays: GpuRays,
    /// Each ray's target colour and background (`rays x 3` each).
    pub targets: Handle,
    pub backgrounds: Handle,
    /// Each ray's view (`u32`).
    pub of_ray: Handle,
    /// Each ray's footprint radius, where asked for.
    pub radii: Option<Handle>,
}

/// Whether two cameras undistort every pixel alike.
fn same_lens(a: &Camera, b: &Camera) -> bool {
    (a.width, a.height, a.fx, a.fy, a.cx, a.cy, a.distortion)
        == (b.width, b.height, b.fx, b.fy, b.cx, b.cy, b.distortion)
}

/// Every pixel centre's undistorted normalised coordinates, as `Camera::ray` computes
/// them, with a column and a row past the image (the last pixels' neighbours, which
/// footprints read), `width + 1` a row.
fn lens_table(cam: &Camera) -> Vec<f32> {
    let mut table = Vec::with_capacity(2 * (cam.width + 1) * (cam.height + 1));
    for j in 0..=cam.height {
        for i in 0..=cam.width {
            let (x, y) = (i as f32 + 0.5, j as f32 + 0.5);
            let (u, v) = cam
                .distortion
                .undistort((x - cam.cx) / cam.fx, (y - cam.cy) / cam.fy);
            table.extend([u, v]);
        }
    }
    table
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::distortion::{Distortion, LensModel};
    use crate::camera::ray_space::Ndc;
    use crate::data::pixels::{PixelSampling, TrainingRays};
    use crate::data::synth::{self, SynthOptions};
    use crate::data::{Background, Split};
    use crate::engine::gpu::device::{test_gpu, worst};
    use crate::render::occupancy::OccupancyGrid;

    /// The device's rays against the host's (`TrainingRays::push`, then `GpuRays::new`'s
    /// unit directions and spans) for the same pixel choices: pinhole and distorted lenses,
    /// world and NDC ray spaces, bounded and contracted marching. Values agree to rounding
    /// (the device may fuse multiply-adds and divide less exactly), targets exactly.
    #[test]
    fn device_rays_are_the_host_rays() {
        let Some(gpu) = test_gpu() else {
            return;
        };
        let opts = SynthOptions {
            size: 12,
            supersample: 1,
            ..Default::default()
        };
        let pinhole = synth::dataset(&opts, Split::Train, 4);
        let mut distorted = pinhole.clone();
        for (k, v) in distorted.views.iter_mut().enumerate() {
            v.camera.distortion = Distortion {
                model: if k % 2 == 0 {
                    LensModel::Opencv
                } else {
                    LensModel::Fisheye
                },
                k: [0.1, -0.05, 0.01, 0.0],
                p: [0.002, -0.001],
            };
        }
        // The same photos as an 8-bit file gives them: packed on the device, four bytes a
        // pixel.
        let mut bytes = pinhole.clone();
        for v in &mut bytes.views {
            let (w, h) = (v.image.width, v.image.height);
            let straight: Vec<u8> = v
                .image
                .premultiplied()
                .chunks_exact(4)
                .flat_map(|p| {
                    let a = p[3];
                    let c = |x: f32| (x / a.max(1e-6) * 255.0).round().clamp(0.0, 255.0) as u8;
                    [c(p[0]), c(p[1]), c(p[2]), (a * 255.0).round() as u8]
                })
                .collect();
            v.image = crate::data::RgbaImage::from_straight_bytes(w, h, straight);
        }
        let mut ndc = pinhole.clone();
        ndc.space = RaySpace::Ndc(Ndc {
            ax: 2.0,
            ay: 2.0,
            near: 1.0,
        });
        (ndc.near, ndc.far) = (0.0, 1.0);
        let how = PixelSampling {
            seed: 3,
            step: 7,
            crop: 1.0,
            background: Background::Random,
            appearance: crate::stage::Appearance::PerView,
        };
        let n = 600;
        for (name, data, contract) in [
            ("pinhole", &pinhole, None),
            ("bytes", &bytes, None),
            ("distorted", &distorted, None),
            ("ndc", &ndc, None),
            ("contracted", &pinhole, Some(0.75)),
        ] {
            let marcher = Marcher {
                dt: 0.01,
                max_samples: 64,
                near: data.near,
                far: data.far,
                contract,
            };
            let grid = OccupancyGrid::new(8, 1.5);
            let mut choices: Vec<PixelChoice> =
                (0..n).map(|k| PixelChoice::draw(data, &how, k)).collect();
            let jitter: Vec<f32> = choices.iter_mut().map(|c| c.rng.uniform()).collect();
            let views = GpuViews::upload(&gpu, data).expect("small enough");
            // One word short of the images, the rays are the host's; photos of bytes take
            // a word a pixel, others four.
            let pixels: usize = data
                .views
                .iter()
                .map(|v| v.image.width * v.image.height)
                .sum();
            let words = if name == "bytes" { pixels } else { 4 * pixels };
            assert_eq!(views.packed, name == "bytes", "{name}");
            assert!(GpuViews::upload_within(&gpu, data, words - 1).is_none());
            assert!(
                max_words(&gpu) >= words,
                "the adapter holds {} words",
                max_words(&gpu)
            );
            let GeneratedRays {
                rays: got,
                targets,
                backgrounds,
                of_ray,
                radii,
            } = views.generate(
                &gpu,
                &data.space,
                &marcher,
                grid.bound,
                &choices,
                &jitter,
                None,
                true,
            );
            let of_ray = gpu.read_u32(&of_ray, n as usize).expect("read");
            assert!(of_ray
                .iter()
                .zip(&choices)
                .all(|(&v, c)| v as usize == c.view));

            let mut host = TrainingRays::default();
            host.draw(data, &how, 0..n);
            let want = GpuRays::new(&gpu, &marcher, &grid, &host.rays, &jitter);
            let n = n as usize;
            let read = |h: &Handle, len: usize| gpu.read(h, len).expect("read");
            for (what, a, b, len) in [
                ("origins", &got.origins, &want.origins, 3 * n),
                ("dirs", &got.dirs, &want.dirs, 3 * n),
                ("views", &got.views, &want.views, 3 * n),
                ("start", &got.start, &want.start, n),
                ("end", &got.end, &want.end, n),
            ] {
                let (a, b) = (read(a, len), read(b, len));
                let err = worst(&a, &b);
                eprintln!("{name} {what}: worst difference {err:.1e}");
                assert!(err < 1e-4, "{name} {what}: {err}");
            }
            // Some rays hit the box, some miss it (empty spans agree above).
            let end = read(&want.end, n);
            assert!(end.iter().any(|&e| e > 0.0), "{name}: no ray hits the box");
            // Radii are small (about a thousandth): compared relative to their size.
            let radii = read(&radii.expect("asked for"), n);
            let rel = radii
                .iter()
                .zip(&host.rays.radii)
                .map(|(a, b)| (a - b).abs() / b.abs())
                .fold(0.0f32, f32::max);
            eprintln!("{name} radii: worst relative difference {rel:.1e}");
            assert!(rel < 1e-3, "{name} radii: {rel}");
            let t = read(&targets, 3 * n);
            assert_eq!(t, host.targets.as_flattened(), "{name} targets");
            let bg = read(&backgrounds, 3 * n);
            assert_eq!(
                bg,
                host.rays.backgrounds.as_flattened(),
                "{name} backgrounds"
            );
        }
    }

    /// A camera's rays cast on the device against the ones `views::render_pixels` makes on
    /// the host (`Camera::ray_at` and `cone_radius`, `RenderSettings::ray_batch_with_cones`,
    /// then `GpuRays::new` with the renderer's half-step jitter): a range of pixels not
    /// starting at the first, world and NDC ray spaces, bounded and contracted marching.
    /// A camera with lens distortion is left to the host.
    #[test]
    fn camera_rays_are_the_views_rays() {
        let Some(gpu) = test_gpu() else {
            return;
        };
        let opts = SynthOptions {
            size: 20,
            supersample: 1,
            ..Default::default()
        };
        let data = synth::dataset(&opts, Split::Test, 2);
        let camera = &data.views[1].camera;
        let ndc = RaySpace::Ndc(Ndc {
            ax: 2.0,
            ay: 2.0,
            near: 1.0,
        });
        let pixels = 37..camera.width * camera.height - 5;
        let n = pixels.len();
        for (name, space, contract) in [
            ("world", RaySpace::World, None),
            ("ndc", ndc, None),
            ("contracted", RaySpace::World, Some(0.75)),
        ] {
            let (near, far) = if name == "ndc" {
                (0.0, 1.0)
            } else {
                (data.near, data.far)
            };
            let marcher = Marcher {
                dt: 0.01,
                max_samples: 64,
                near,
                far,
                contract,
            };
            let grid = OccupancyGrid::new(8, 1.5);
            let got = camera_rays(&gpu, camera, &space, &marcher, grid.bound, pixels.clone())
                .expect("a pinhole camera");
            let settings = crate::views::RenderSettings {
                near,
                far,
                background: [1.0; 3],
                space,
                appearance: crate::stage::Appearance::Mean,
                time: None,
            };
            let (world, cones): (Vec<_>, Vec<f32>) = pixels
                .clone()
                .map(|p| {
                    let w = camera.width;
                    let (x, y) = ((p % w) as f32 + 0.5, (p / w) as f32 + 0.5);
                    (camera.ray_at(x, y), camera.cone_radius(x, y))
                })
                .unzip();
            let batch = settings.ray_batch_with_cones(&world, &cones, pixels.start);
            let want = GpuRays::new(&gpu, &marcher, &grid, &batch, &vec![0.5; n]);
            let inv_norm: Vec<f32> = batch
                .dirs
                .iter()
                .map(|&d| 1.0 / crate::math::length(d))
                .collect();
            let read = |h: &Handle, len: usize| gpu.read(h, len).expect("read");
            for (what, a, b) in [
                (
                    "origins",
                    read(&got.rays.origins, 3 * n),
                    read(&want.origins, 3 * n),
                ),
                ("dirs", read(&got.rays.dirs, 3 * n), read(&want.dirs, 3 * n)),
                (
                    "views",
                    read(&got.rays.views, 3 * n),
                    read(&want.views, 3 * n),
                ),
                ("start", read(&got.rays.start, n), read(&want.start, n)),
                ("end", read(&got.rays.end, n), read(&want.end, n)),
                ("inv_norm", read(&got.inv_norm, n), inv_norm),
            ] {
                let err = worst(&a, &b);
                eprintln!("{name} {what}: worst difference {err:.1e}");
                assert!(err < 1e-4, "{name} {what}: {err}");
            }
            // Radii are small (about a thousandth): compared relative to their size.
            let radii = read(&got.radii, n);
            let rel = radii
                .iter()
                .zip(&batch.radii)
                .map(|(a, b)| (a - b).abs() / b.abs())
                .fold(0.0f32, f32::max);
            eprintln!("{name} radii: worst relative difference {rel:.1e}");
            assert!(rel < 1e-3, "{name} radii: {rel}");
            let end = read(&want.end, n);
            assert!(end.iter().any(|&e| e > 0.0), "{name}: no ray hits the box");
        }
        let mut distorted = camera.clone();
        distorted.distortion = Distortion {
            model: LensModel::Opencv,
            k: [0.1, 0.0, 0.0, 0.0],
            p: [0.0, 0.0],
        };
        let marcher = Marcher {
            dt: 0.01,
            max_samples: 64,
            near: data.near,
            far: data.far,
            contract: None,
        };
        assert!(camera_rays(&gpu, &distorted, &RaySpace::World, &marcher, 1.5, 0..4).is_none());
    }
}
