//! Camera refinement with the training views on the device: each step's corrected cameras
//! are made there from the corrections in the parameter vector, the rays are cast from
//! them (`rays::GpuViews::generate`), and each camera's gradient is summed there from its
//! rays' and added to the parameter gradients, so a step neither reads the corrections
//! back nor draws, corrects and uploads its rays on the host, as it must where the views
//! are not on the device (`CameraStep` on the host).
//!
//! A camera's correction `(w, tau)` turns its camera-to-world pose `[C | c]` into
//! `[R C | R c + tau]` (world frame) or `[C R | c + C tau]` (camera frame), `R = exp([w]x)`
//! (`model::camera_refine::corrected`). A ray casts `d = M' v` from the corrected `[M' | t']`
//! (`v`: its pixel's direction in camera axes) and starts at `t'`, so the loss's gradient
//! with respect to the corrected pose is, per ray, `dL/dM' = G q^T` and `dL/dt' = g`, with
//! `g` the gradient at the world origin, `G` the gradient with respect to the world
//! direction taken at its unit vector `u` (the warp into NDC and the colour network both
//! ignore its length) and `q = M'^T u` the unit pixel direction in camera axes. Summed per
//! camera, these go through the correction by the exponential map's left Jacobian:
//! `dR/dw_k = [J e_k]x R`, `J = a I + b [w]x + c w w^T` (`a = sin t / t`,
//! `b = (1 - cos t) / t^2`, `c = (t - sin t) / t^3`, `t = |w|`).

use cubecl::prelude::*;
use cubecl::server::Handle;

use super::device::Gpu;
use super::launch::grid;
use super::pose_grad::RAY_WORDS;
use super::rays::CAM_WORDS;
use crate::camera::ray_space::RaySpace;
use crate::model::camera_refine::{Frame, PER_CAMERA};

/// Floats of a ray's gradient with respect to its corrected pose: `dL/dM'` by rows, then
/// `dL/dt'`.
const POSE_WORDS: usize = 12;
/// Threads per workgroup; the per-camera sums take one workgroup a camera.
const GROUP: u32 = 64;
const LANES: usize = GROUP as usize;
const SHARED: usize = POSE_WORDS * LANES;

/// The three coefficients of `exp([w]x) = I + a [w]x + b [w]x^2` and of its left Jacobian
/// (`c`), in series where the closed forms lose their digits in `f32`.
#[cube]
fn coefficients(wx: f32, wy: f32, wz: f32) -> (f32, f32, f32) {
    let t2 = wx * wx + wy * wy + wz * wz;
    let t = f32::sqrt(t2);
    let half = f32::sin(0.5f32 * t);
    let tiny = t < 1e-3f32;
    let a = select(tiny, 1.0f32 - t2 / 6.0f32, f32::sin(t) / t);
    let b = select(tiny, 0.5f32 - t2 / 24.0f32, 2.0f32 * half * half / t2);
    let small = t < 0.1f32;
    let series = 1.0f32 / 6.0f32 - t2 / 120.0f32 + t2 * t2 / 5040.0f32;
    let c = select(small, series, (t - f32::sin(t)) / (t2 * t));
    (a, b, c)
}

/// `R = exp([w]x)` by rows into `r` (9 floats): `cos t I + a [w]x + b w w^T`.
#[cube]
fn rotation(wx: f32, wy: f32, wz: f32, a: f32, b: f32, r: &mut Array<f32>) {
    let cos = 1.0f32 - b * (wx * wx + wy * wy + wz * wz);
    r[0] = cos + b * wx * wx;
    r[1] = b * wx * wy - a * wz;
    r[2] = b * wx * wz + a * wy;
    r[3] = b * wy * wx + a * wz;
    r[4] = cos + b * wy * wy;
    r[5] = b * wy * wz - a * wx;
    r[6] = b * wz * wx - a * wy;
    r[7] = b * wz * wy + a * wx;
    r[8] = cos + b * wz * wz;
}

/// One thread per view: its camera as corrected by its correction in `values` (6 floats a
/// camera from `at`), or as given for views past the `corrected` first.
#[cube(launch_unchecked)]
#[allow(clippy::manual_memcpy)]
fn correct_cameras(
    cams: &[f32],
    values: &[f32],
    out: &mut [f32],
    at: u32,
    views: u32,
    corrected: u32,
    #[comptime] world_frame: bool,
) {
    let v = ABSOLUTE_POS;
    if v < views as usize {
        let c = CAM_WORDS * v;
        #[unroll]
        for k in 0..4usize {
            out[c + k] = cams[c + k];
        }
        if v < corrected as usize {
            let p = at as usize + PER_CAMERA * v;
            let wx = values[p];
            let wy = values[p + 1];
            let wz = values[p + 2];
            let (a, b, _c) = coefficients(wx, wy, wz);
            let mut r = Array::<f32>::new(9usize);
            rotation(wx, wy, wz, a, b, &mut r);
            let m = c + 4;
            #[unroll]
            for i in 0..3usize {
                #[unroll]
                for j in 0..3usize {
                    let mut s = 0.0f32;
                    #[unroll]
                    for k in 0..3usize {
                        if world_frame {
                            s += r[3 * i + k] * cams[m + 4 * k + j];
                        } else {
                            s += cams[m + 4 * i + k] * r[3 * k + j];
                        }
                    }
                    out[m + 4 * i + j] = s;
                }
                let mut t = 0.0f32;
                #[unroll]
                for k in 0..3usize {
                    if world_frame {
                        t += r[3 * i + k] * cams[m + 4 * k + 3];
                    } else {
                        t += cams[m + 4 * i + k] * values[p + 3 + k];
                    }
                }
                if world_frame {
                    out[m + 4 * i + 3] = t + values[p + 3 + i];
                } else {
                    out[m + 4 * i + 3] = cams[m + 4 * i + 3] + t;
                }
            }
        } else {
            #[unroll]
            for k in 4..CAM_WORDS {
                out[c + k] = cams[c + k];
            }
        }
    }
}

/// The NDC warp's parameters (`camera::ray_space::Ndc`), `ndc` 0 for world rays.
#[derive(CubeType, CubeLaunch, Clone, Copy)]
pub struct WarpParams {
    ndc: u32,
    ax: f32,
    ay: f32,
    near: f32,
}

/// One thread per ray `r`: its gradient with respect to its corrected pose (see the module
/// docs) from its gradients at its ray-space origin, along its unit ray-space direction
/// and along its unit view direction (`grads`, [`RAY_WORDS`] a ray), its unit world
/// direction `units`, its view `of_ray` and the corrected cameras. NDC rays go back
/// through the warp (`RaySpace::warp_backward`'s closed form: the warped origin sits on
/// the near plane, `z = -near`, whatever the ray).
#[cube(launch_unchecked)]
#[allow(clippy::too_many_arguments)]
fn ray_pose_grads(
    grads: &[f32],
    units: &[f32],
    of_ray: &[u32],
    cams: &[f32],
    out: &mut [f32],
    rays: u32,
    warp: WarpParams,
) {
    let r = ABSOLUTE_POS;
    if r < rays as usize {
        let m = CAM_WORDS * of_ray[r] as usize + 4;
        let g = RAY_WORDS * r;
        let ux = units[3 * r];
        let uy = units[3 * r + 1];
        let uz = units[3 * r + 2];
        let mut gox = grads[g];
        let mut goy = grads[g + 1];
        let mut goz = grads[g + 2];
        let mut gdx = grads[g + 3];
        let mut gdy = grads[g + 4];
        let mut gdz = grads[g + 5];
        if warp.ndc == 1 {
            let n = warp.near;
            let ox = cams[m + 3];
            let oy = cams[m + 7];
            let oz = cams[m + 11];
            // The warped direction `D` and the gradient along it (not its unit vector).
            let t = -(n + oz) / uz;
            let px = ox + t * ux;
            let py = oy + t * uy;
            let pz = 0.0f32 - n;
            let dx = 0.0f32 - warp.ax * (ux / uz - px / pz);
            let dy = 0.0f32 - warp.ay * (uy / uz - py / pz);
            let dz = -2.0f32 * n / pz;
            let inv = 1.0f32 / f32::sqrt(dx * dx + dy * dy + dz * dz);
            let along = (gdx * dx + gdy * dy + gdz * dz) * inv;
            let g_dx = (gdx - along * dx * inv) * inv;
            let g_dy = (gdy - along * dy * inv) * inv;
            // Through the near-plane point `p` and the slopes `u / uz`.
            let gpx = warp.ax * (g_dx - gox) / pz;
            let gpy = warp.ay * (g_dy - goy) / pz;
            let grx = 0.0f32 - warp.ax * g_dx;
            let gry = 0.0f32 - warp.ay * g_dy;
            let across = gpx * ux + gpy * uy;
            let heading = uz < -1e-6f32;
            gox = select(heading, gpx, 0.0f32);
            goy = select(heading, gpy, 0.0f32);
            goz = select(heading, 0.0f32 - across / uz, 0.0f32);
            gdx = select(heading, gpx * t + grx / uz, 0.0f32);
            gdy = select(heading, gpy * t + gry / uz, 0.0f32);
            gdz = select(
                heading,
                0.0f32 - across * t / uz - (grx * ux + gry * uy) / (uz * uz),
                0.0f32,
            );
        }
        let gx = gdx + grads[g + 6];
        let gy = gdy + grads[g + 7];
        let gz = gdz + grads[g + 8];
        let o = POSE_WORDS * r;
        #[unroll]
        for j in 0..3usize {
            let q = cams[m + j] * ux + cams[m + 4 + j] * uy + cams[m + 8 + j] * uz;
            out[o + j] = gx * q;
            out[o + 3 + j] = gy * q;
            out[o + 6 + j] = gz * q;
        }
        out[o + 9] = gox;
        out[o + 10] = goy;
        out[o + 11] = goz;
    }
}

/// One workgroup per corrected camera: the sum of its rays' pose gradients (`pose`,
/// [`POSE_WORDS`] a ray), carried through its correction (`values` from `at`) and its
/// given pose (`cams`) into the correction's gradient, added to `grads` from `at`.
#[cube(launch_unchecked)]
#[allow(clippy::too_many_arguments)]
fn camera_grads(
    pose: &[f32],
    of_ray: &[u32],
    cams: &[f32],
    values: &[f32],
    grads: &mut [f32],
    at: u32,
    rays: u32,
    #[comptime] world_frame: bool,
) {
    let v = CUBE_POS_X;
    let lane = UNIT_POS as usize;
    let mut sum = Array::<f32>::new(POSE_WORDS);
    #[unroll]
    for k in 0..POSE_WORDS {
        sum[k] = 0.0f32;
    }
    let mut r = lane;
    while r < rays as usize {
        if of_ray[r] == v {
            #[unroll]
            for k in 0..POSE_WORDS {
                sum[k] += pose[POSE_WORDS * r + k];
            }
        }
        r += LANES;
    }
    let mut shared = Shared::<[f32]>::new_slice(SHARED);
    #[unroll]
    for k in 0..POSE_WORDS {
        shared[POSE_WORDS * lane + k] = sum[k];
    }
    sync_cube();
    if lane == 0 {
        // `dL/dM'` by rows (`gm`), `dL/dt'` (`gt`).
        let mut gm = Array::<f32>::new(POSE_WORDS);
        #[unroll]
        for k in 0..POSE_WORDS {
            let mut s = 0.0f32;
            for l in 0..LANES {
                s += shared[POSE_WORDS * l + k];
            }
            gm[k] = s;
        }
        let m = CAM_WORDS * v as usize + 4;
        let p = at as usize + PER_CAMERA * v as usize;
        let wx = values[p];
        let wy = values[p + 1];
        let wz = values[p + 2];
        let (a, b, c) = coefficients(wx, wy, wz);
        let mut rot = Array::<f32>::new(9usize);
        rotation(wx, wy, wz, a, b, &mut rot);
        // `dL/dR` and `dL/dtau` for the frame.
        let mut dr = Array::<f32>::new(9usize);
        #[unroll]
        for i in 0..3usize {
            #[unroll]
            for j in 0..3usize {
                let mut s = 0.0f32;
                if world_frame {
                    // M' = R C, t' = R c + tau.
                    #[unroll]
                    for k in 0..3usize {
                        s += gm[3 * i + k] * cams[m + 4 * j + k];
                    }
                    s += gm[9 + i] * cams[m + 4 * j + 3];
                } else {
                    // M' = C R, t' = c + C tau.
                    #[unroll]
                    for k in 0..3usize {
                        s += cams[m + 4 * k + i] * gm[3 * k + j];
                    }
                }
                dr[3 * i + j] = s;
            }
            let mut tau = 0.0f32;
            #[unroll]
            for k in 0..3usize {
                tau += cams[m + 4 * k + i] * gm[9 + k];
            }
            if world_frame {
                grads[p + 3 + i] += gm[9 + i];
            } else {
                grads[p + 3 + i] += tau;
            }
        }
        // `sum_ij ([s]x R)_ij dR_ij = s . alpha`, alpha the axial vector of `dR R^T`'s
        // antisymmetric part (twice it).
        let mut arr = Array::<f32>::new(9usize);
        #[unroll]
        for i in 0..3usize {
            #[unroll]
            for j in 0..3usize {
                let mut s = 0.0f32;
                #[unroll]
                for k in 0..3usize {
                    s += dr[3 * i + k] * rot[3 * j + k];
                }
                arr[3 * i + j] = s;
            }
        }
        let ax = arr[7] - arr[5];
        let ay = arr[2] - arr[6];
        let az = arr[3] - arr[1];
        // J^T alpha = a alpha - b (w x alpha) + c w (w . alpha).
        let dot = wx * ax + wy * ay + wz * az;
        grads[p] += a * ax - b * (wy * az - wz * ay) + c * wx * dot;
        grads[p + 1] += a * ay - b * (wz * ax - wx * az) + c * wy * dot;
        grads[p + 2] += a * az - b * (wx * ay - wy * ax) + c * wz * dot;
    }
}

/// How a run refines its cameras on the device: where the corrections sit in the
/// parameter vector, how many cameras have one, and the frame they act in.
#[derive(Clone, Copy, Debug)]
pub struct DevicePoses {
    pub at: usize,
    pub cameras: usize,
    pub frame: Frame,
}

impl DevicePoses {
    /// The `views` cameras of `cams` ([`CAM_WORDS`] each), the first
    /// [`cameras`](Self::cameras) corrected by the corrections in `values`.
    pub fn correct(&self, gpu: &Gpu, cams: &Handle, values: &Handle, views: usize) -> Handle {
        let out = gpu.floats(CAM_WORDS * views.max(1));
        if views == 0 {
            return out;
        }
        let (count, dim) = grid(views, GROUP);
        // SAFETY: `cams` and `out` hold `views` cameras, `values` the corrections of the
        // first `cameras.min(views)`; the kernel bounds-checks its view.
        unsafe {
            correct_cameras::launch_unchecked(
                &gpu.client,
                count,
                dim,
                BufferArg::from_raw_parts(cams.clone(), CAM_WORDS * views),
                BufferArg::from_raw_parts(values.clone(), self.end()),
                BufferArg::from_raw_parts(out.clone(), CAM_WORDS * views),
                self.at as u32,
                views as u32,
                self.cameras.min(views) as u32,
                self.frame == Frame::World,
            );
        }
        out
    }

    /// Adds to `grads` each corrected camera's gradient from its rays': `ray_grads`
    /// ([`RAY_WORDS`] a ray, `pose_grad::ray_gradients`), the rays' unit world directions
    /// `units` and views `of_ray` (the first `rays`), the corrected cameras `corrected`
    /// (from [`correct`](Self::correct)) and the given ones `cams`, `views` of each.
    #[allow(clippy::too_many_arguments)]
    pub fn add_gradients(
        &self,
        gpu: &Gpu,
        (values, grads): (&Handle, &Handle),
        space: &RaySpace,
        (ray_grads, units, of_ray): (&Handle, &Handle, &Handle),
        rays: usize,
        (cams, corrected): (&Handle, &Handle),
        views: usize,
    ) {
        let cameras = self.cameras.min(views);
        if rays == 0 || cameras == 0 {
            return;
        }
        let pose = gpu.floats(POSE_WORDS * rays);
        let warp = match space {
            RaySpace::World => WarpParamsLaunch::new(0, 1.0, 1.0, 1.0),
            RaySpace::Ndc(p) => WarpParamsLaunch::new(1, p.ax, p.ay, p.near),
        };
        let (count, dim) = grid(rays, GROUP);
        // SAFETY: each per-ray buffer holds `rays` rays at its width, `of_ray` names views
        // below `views`, which `cams` and `corrected` hold; `values` and `grads` hold the
        // corrections of the first `cameras`; the ray kernel bounds-checks its ray and the
        // camera kernel runs one workgroup per camera.
        unsafe {
            ray_pose_grads::launch_unchecked(
                &gpu.client,
                count,
                dim,
                BufferArg::from_raw_parts(ray_grads.clone(), RAY_WORDS * rays),
                BufferArg::from_raw_parts(units.clone(), 3 * rays),
                BufferArg::from_raw_parts(of_ray.clone(), rays),
                BufferArg::from_raw_parts(corrected.clone(), CAM_WORDS * views),
                BufferArg::from_raw_parts(pose.clone(), POSE_WORDS * rays),
                rays as u32,
                warp,
            );
            camera_grads::launch_unchecked(
                &gpu.client,
                CubeCount::Static(cameras as u32, 1, 1),
                CubeDim::new_1d(GROUP),
                BufferArg::from_raw_parts(pose.clone(), POSE_WORDS * rays),
                BufferArg::from_raw_parts(of_ray.clone(), rays),
                BufferArg::from_raw_parts(cams.clone(), CAM_WORDS * views),
                BufferArg::from_raw_parts(values.clone(), self.end()),
                BufferArg::from_raw_parts(grads.clone(), self.end()),
                self.at as u32,
                rays as u32,
                self.frame == Frame::World,
            );
        }
    }

    /// The end of the corrections in the parameter vector (buffers hold at least this).
    fn end(&self) -> usize {
        self.at + PER_CAMERA * self.cameras
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::ray_space::Ndc;
    use crate::data::pixels::{PixelChoice, PixelSampling, TrainingRays};
    use crate::data::synth::{self, SynthOptions};
    use crate::data::{Background, Dataset, Split};
    use crate::engine::gpu::device::{test_gpu, worst};
    use crate::engine::gpu::march::GpuRays;
    use crate::engine::gpu::rays::{GeneratedRays, GpuViews};
    use crate::model::camera_refine::{correct_drawn_rays, corrected, rotation, CameraStep};
    use crate::render::march::Marcher;
    use crate::render::occupancy::OccupancyGrid;
    use crate::rng::Rng;

    /// Where the corrections start in the tests' parameter vectors: past a few others.
    const AT: usize = 3;

    /// A parameter vector with corrections from `AT` on, camera `k`'s of size zero, a
    /// ten-thousandth, a hundredth or 0.4 in turn (each side of the series' switches).
    fn values_with_corrections(cameras: usize, seed: u64) -> Vec<f32> {
        let mut rng = Rng::new(seed);
        let mut values: Vec<f32> = (0..AT).map(|_| rng.range(-1.0, 1.0)).collect();
        for k in 0..cameras {
            let scale = [0.0, 1e-4, 1e-2, 0.4][k % 4];
            values.extend((0..PER_CAMERA).map(|_| scale * rng.range(-1.0, 1.0)));
        }
        values
    }

    fn steps(data: &Dataset, values: &[f32], frame: Frame) -> Vec<CameraStep> {
        data.views
            .iter()
            .zip(values[AT..].chunks_exact(PER_CAMERA))
            .map(|(v, c)| CameraStep::new(&v.camera.c2w, c, frame).in_space(data.space))
            .collect()
    }

    /// The device's corrected cameras against `camera_refine::corrected`, in either frame;
    /// views past the corrected ones keep their cameras.
    #[test]
    fn corrected_cameras_are_the_hosts() {
        let Some(gpu) = test_gpu() else {
            return;
        };
        let opts = SynthOptions {
            size: 8,
            supersample: 1,
            ..Default::default()
        };
        let data = synth::dataset(&opts, Split::Train, 9);
        let views = GpuViews::upload(&gpu, &data).expect("small enough");
        let (cams, count) = views.cameras();
        assert_eq!(count, 9);
        let cameras = 8;
        let values = values_with_corrections(cameras, 5);
        for frame in [Frame::World, Frame::Camera] {
            let poses = DevicePoses {
                at: AT,
                cameras,
                frame,
            };
            let out = poses.correct(&gpu, cams, &gpu.upload(&values), count);
            let got = gpu.read(&out, CAM_WORDS * count).expect("read");
            for (v, view) in data.views.iter().enumerate() {
                let cam = &view.camera;
                let want = match v < cameras {
                    true => corrected(&cam.c2w, &values[AT + PER_CAMERA * v..], frame),
                    false => cam.c2w,
                };
                let mut want_words = vec![cam.fx, cam.fy, cam.cx, cam.cy];
                want_words.extend(want.iter().flatten());
                let err = worst(&got[CAM_WORDS * v..][..CAM_WORDS], &want_words);
                assert!(err < 1e-5, "{frame:?} view {v}: {err}");
            }
        }
    }

    /// Each camera's gradient summed on the device against the host's
    /// (`CameraStep::accumulate_drawn` over the same rays, drawn and corrected on the host):
    /// world and NDC rays, corrections in the world frame and in the camera's, for the
    /// same gradients at each ray's origin, direction and view direction.
    #[test]
    fn camera_gradients_are_the_hosts() {
        let Some(gpu) = test_gpu() else {
            return;
        };
        let opts = SynthOptions {
            size: 12,
            supersample: 1,
            ..Default::default()
        };
        let world = synth::dataset(&opts, Split::Train, 6);
        // A forward-facing capture: cameras near the origin looking down -z.
        let mut ndc = world.clone();
        let mut rng = Rng::new(11);
        for v in &mut ndc.views {
            let turn = rotation([0.1 * rng.range(-1.0, 1.0), 0.1 * rng.range(-1.0, 1.0), 0.0]);
            for i in 0..3 {
                v.camera.c2w[i] = [
                    turn[i][0],
                    turn[i][1],
                    turn[i][2],
                    0.2 * rng.range(-1.0, 1.0),
                ];
            }
        }
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
        let n = 500;
        for (name, data) in [("world", &world), ("ndc", &ndc)] {
            let marcher = Marcher {
                dt: 0.01,
                max_samples: 64,
                near: data.near,
                far: data.far,
                contract: None,
            };
            let grid = OccupancyGrid::new(8, 1.5);
            let views = GpuViews::upload(&gpu, data).expect("small enough");
            let (cams, count) = views.cameras();
            let values = values_with_corrections(count, 9);
            let on_device = gpu.upload(&values);
            let mut rng = Rng::new(4);
            let ray_grads: Vec<f32> = (0..RAY_WORDS * n).map(|_| rng.range(-1.0, 1.0)).collect();
            for frame in [Frame::World, Frame::Camera] {
                let poses = DevicePoses {
                    at: AT,
                    cameras: count,
                    frame,
                };
                let corrected = poses.correct(&gpu, cams, &on_device, count);
                let mut choices: Vec<PixelChoice> = (0..n as u64)
                    .map(|k| PixelChoice::draw(data, &how, k))
                    .collect();
                let jitter: Vec<f32> = choices.iter_mut().map(|c| c.rng.uniform()).collect();
                let GeneratedRays { rays, of_ray, .. } = views.generate(
                    &gpu,
                    &data.space,
                    &marcher,
                    grid.bound,
                    &choices,
                    &jitter,
                    Some(&corrected),
                    false,
                );
                // The rays are the host's corrected rays.
                let steps = steps(data, &values, frame);
                let mut host = TrainingRays::default();
                host.draw(data, &how, 0..n as u64);
                correct_drawn_rays(&mut host.rays, &steps);
                let want = GpuRays::new(&gpu, &marcher, &grid, &host.rays, &jitter);
                let read = |h: &Handle, len: usize| gpu.read(h, len).expect("read");
                for (what, a, b) in [
                    ("origins", &rays.origins, &want.origins),
                    ("dirs", &rays.dirs, &want.dirs),
                    ("views", &rays.views, &want.views),
                ] {
                    let err = worst(&read(a, 3 * n), &read(b, 3 * n));
                    assert!(err < 1e-4, "{name} {frame:?} {what}: {err}");
                }
                let mut want = vec![0.0f32; PER_CAMERA * count];
                for (r, g) in ray_grads.chunks_exact(RAY_WORDS).enumerate() {
                    let view = (host.rays.pixels[r] >> 32) as usize;
                    steps[view].accumulate_drawn(
                        host.rays.dirs[r],
                        host.rays.view_dirs[r],
                        [g[0], g[1], g[2]],
                        [g[3], g[4], g[5]],
                        [g[6], g[7], g[8]],
                        &mut want[PER_CAMERA * view..][..PER_CAMERA],
                    );
                }
                let grads = gpu.zeros(values.len());
                poses.add_gradients(
                    &gpu,
                    (&on_device, &grads),
                    &data.space,
                    (&gpu.upload(&ray_grads), &rays.views, &of_ray),
                    n,
                    (cams, &corrected),
                    count,
                );
                let got = read(&grads, values.len());
                assert!(
                    got[..AT].iter().all(|&g| g == 0.0),
                    "{name}: outside the corrections"
                );
                let largest = want.iter().fold(0.0f32, |m, g| m.max(g.abs()));
                let err = worst(&got[AT..], &want);
                eprintln!("{name} {frame:?}: largest {largest:.2e}, worst difference {err:.1e}");
                assert!(
                    largest > 1.0,
                    "{name} {frame:?}: gradients too small to compare"
                );
                assert!(err < 1e-4 * largest, "{name} {frame:?}: {err} of {largest}");
            }
        }
    }
}
