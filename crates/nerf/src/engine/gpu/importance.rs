//! The paper model's importance sampling on the device, by the host's rule
//! (`render::sampling::sample_pdf`, then `merge_sorted`): each ray's fine depths drawn by
//! inverse transform from its coarse weights and merged with its coarse depths, then packed
//! as the fine pass's samples (positions, deltas, view directions), for training steps.
//! The coarse pass's weights stay on the device; the host sends only the uniform draws.

use cubecl::prelude::*;
use cubecl::server::Handle;

use super::device::Gpu;
use super::launch::grid;
use super::volume::GpuSamples;
use crate::render::volume::LAST_DELTA;
use crate::rng::Rng;
use crate::stage::RayBatch;

/// Threads per workgroup.
const GROUP: u32 = 64;

/// The sizes of one draw: rays, coarse and fine depths per ray.
#[derive(CubeType, CubeLaunch, Clone, Copy)]
pub struct Draw {
    rays: u32,
    n_c: u32,
    n_f: u32,
}

/// One thread per ray: its `n_f` fine depths from the piecewise-constant PDF over the bins
/// between its coarse depths' midpoints (weights `w_1 .. w_{n_c-2}`, each + 1e-5), at the
/// uniform draws `u` (sorted per ray), merged in order with its coarse depths into
/// `t_fine` (`n_c + n_f` a ray). The draws are sorted, so one pass walks the CDF and the
/// merge together.
#[cube(launch_unchecked)]
fn fine_depths(t_coarse: &[f32], weights: &[f32], u: &[f32], t_fine: &mut [f32], d: Draw) {
    let r = ABSOLUTE_POS;
    if r < d.rays as usize {
        let n_c = d.n_c as usize;
        let n_f = d.n_f as usize;
        let c0 = r * n_c;
        let o0 = r * (n_c + n_f);
        let mut total = 0.0f32;
        for i in 1..n_c - 1 {
            total += weights[c0 + i] + 1e-5;
        }
        // The CDF has `n_c - 1` entries, `cdf[0] = 0`; `p` is the first one above the
        // current draw, `cur = cdf[p]`, `prev = cdf[p - 1]`, `prev2 = cdf[p - 2]`.
        let last = n_c - 2;
        let mut p = 0usize;
        let mut acc = 0.0f32;
        let mut cur = 0.0f32;
        let mut prev = 0.0f32;
        let mut prev2 = 0.0f32;
        // The next coarse depth to merge, and where the merged row goes on.
        let mut i = 0usize;
        let mut o = o0;
        for j in 0..n_f {
            let draw = u[r * n_f + j];
            loop {
                if p > last || cur > draw {
                    break;
                }
                prev2 = prev;
                prev = cur;
                p += 1;
                if p <= last {
                    acc += (weights[c0 + p] + 1e-5) / total;
                    cur = f32::min(acc, 1.0);
                }
            }
            // `above`: the first entry above the draw, clamped into the bins.
            let inside = p <= last;
            let above = select(inside, p, last);
            let below = select(above > 0, above - 1, 0usize);
            let hi = select(inside, cur, prev);
            let lo = select(inside, select(p > 0, prev, cur), prev2);
            let width = hi - lo;
            let denom = select(width < 1e-5, 1.0f32, width);
            let frac = (draw - lo) / denom;
            let b0 = 0.5f32 * (t_coarse[c0 + below] + t_coarse[c0 + below + 1]);
            let b1 = 0.5f32 * (t_coarse[c0 + above] + t_coarse[c0 + above + 1]);
            let x = b0 + frac * (b1 - b0);
            loop {
                if i >= n_c || t_coarse[c0 + i] > x {
                    break;
                }
                t_fine[o] = t_coarse[c0 + i];
                o += 1;
                i += 1;
            }
            t_fine[o] = x;
            o += 1;
        }
        loop {
            if i >= n_c {
                break;
            }
            t_fine[o] = t_coarse[c0 + i];
            o += 1;
            i += 1;
        }
    }
}

/// One thread per sample of `spr` a ray: its position `o + t d`, its delta to the next
/// depth (`LAST_DELTA` after the last) times `|d|`, and its ray's unit view direction.
#[cube(launch_unchecked)]
#[allow(clippy::too_many_arguments)]
fn pack_samples(
    t: &[f32],
    origins: &[f32],
    dirs: &[f32],
    view_dirs: &[f32],
    positions: &mut [f32],
    dt: &mut [f32],
    sample_dirs: &mut [f32],
    n: u32,
    spr: u32,
    last_delta: f32,
) {
    let s = ABSOLUTE_POS;
    if s < n as usize {
        let spr = spr as usize;
        let k = s / spr;
        let tt = t[s];
        let (dx, dy, dz) = (dirs[3 * k], dirs[3 * k + 1], dirs[3 * k + 2]);
        positions[3 * s] = origins[3 * k] + tt * dx;
        positions[3 * s + 1] = origins[3 * k + 1] + tt * dy;
        positions[3 * s + 2] = origins[3 * k + 2] + tt * dz;
        let norm = f32::sqrt(dx * dx + dy * dy + dz * dz);
        let next = select(s % spr + 1 < spr, s + 1, s);
        dt[s] = select(s % spr + 1 < spr, (t[next] - tt) * norm, last_delta * norm);
        let (vx, vy, vz) = (view_dirs[3 * k], view_dirs[3 * k + 1], view_dirs[3 * k + 2]);
        let inv = 1.0f32 / f32::sqrt(vx * vx + vy * vy + vz * vz);
        sample_dirs[3 * s] = vx * inv;
        sample_dirs[3 * s + 1] = vy * inv;
        sample_dirs[3 * s + 2] = vz * inv;
    }
}

/// A pass's samples on the device: depths and deltas (packed per ray), positions and
/// per-sample unit view directions (`n x 3` each).
pub struct PassSamples {
    pub samples: GpuSamples,
    pub positions: Handle,
    pub dirs: Handle,
}

/// Each ray's `n_f` uniform draws from its random stream, sorted (the inverse transform is
/// monotonic, so sorted draws give the sorted depths the host sorts afterwards), drawn in
/// the order the host's `sample_pdf` draws them.
pub fn sorted_draws(rngs: &mut [Rng], n_f: usize) -> Vec<f32> {
    let mut u = Vec::with_capacity(rngs.len() * n_f);
    for rng in rngs {
        let row = u.len();
        u.extend((0..n_f).map(|_| rng.uniform()));
        u[row..].sort_unstable_by(f32::total_cmp);
    }
    u
}

/// The fine samples of `rays` (`n_c` coarse depths a ray in `t_coarse`, their compositing
/// `weights`), at the sorted uniform draws `u` (`rays x n_f`, [`sorted_draws`]).
pub fn fine_samples(
    gpu: &Gpu,
    rays: &RayBatch,
    t_coarse: &Handle,
    weights: &Handle,
    u: &[f32],
    (n_c, n_f): (usize, usize),
) -> PassSamples {
    let r = rays.len();
    let spr = n_c + n_f;
    let n = r * spr;
    assert_eq!(u.len(), r * n_f, "a draw per fine sample");
    let t = gpu.floats(n);
    let draw = DrawLaunch::new(r as u32, n_c as u32, n_f as u32);
    // SAFETY: `t_coarse` and `weights` hold `r x n_c` floats, `t` `r x spr`, `u` `r x n_f`;
    // each thread touches its own ray.
    unsafe {
        let (c, d) = grid(r, GROUP);
        fine_depths::launch_unchecked(
            &gpu.client,
            c,
            d,
            BufferArg::from_raw_parts(t_coarse.clone(), r * n_c),
            BufferArg::from_raw_parts(weights.clone(), r * n_c),
            BufferArg::from_raw_parts(gpu.upload(u), u.len()),
            BufferArg::from_raw_parts(t.clone(), n),
            draw,
        );
    }
    let (positions, dt, dirs) = (gpu.floats(3 * n), gpu.floats(n), gpu.floats(3 * n));
    let flat = |v: &[[f32; 3]]| gpu.upload(v.as_flattened());
    // SAFETY: the ray buffers hold `r x 3` floats, the sample buffers `n` (`n x 3`) with
    // `n = r x spr`; each thread writes its own sample.
    unsafe {
        let (c, d) = grid(n, GROUP);
        pack_samples::launch_unchecked(
            &gpu.client,
            c,
            d,
            BufferArg::from_raw_parts(t.clone(), n),
            BufferArg::from_raw_parts(flat(&rays.origins), 3 * r),
            BufferArg::from_raw_parts(flat(&rays.dirs), 3 * r),
            BufferArg::from_raw_parts(flat(&rays.view_dirs), 3 * r),
            BufferArg::from_raw_parts(positions.clone(), 3 * n),
            BufferArg::from_raw_parts(dt.clone(), n),
            BufferArg::from_raw_parts(dirs.clone(), 3 * n),
            n as u32,
            spr as u32,
            LAST_DELTA,
        );
    }
    let offsets: Vec<u32> = (0..=r).map(|k| (k * spr) as u32).collect();
    PassSamples {
        samples: GpuSamples {
            offsets: gpu.upload_u32(&offsets),
            t,
            dt,
            rays: r,
            len: n,
        },
        positions,
        dirs,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::Ray;
    use crate::engine::gpu::device::test_gpu;
    use crate::render::sampling::{merge_sorted, sample_pdf, stratified};
    use crate::render::volume::depth_deltas;

    /// The device's fine samples against the host's rule on the same coarse depths and
    /// weights (some rays with no weight at all, some with one spike) and the same random
    /// streams: every depth, delta, position and direction agrees (within the device's
    /// division and square root), and the streams are left where the host leaves them.
    #[test]
    fn fine_samples_follow_the_host_rule() {
        let Some(gpu) = test_gpu() else {
            return;
        };
        let (r, n_c, n_f) = (37, 8, 16);
        let mut rng = Rng::new(11);
        let mut rays = RayBatch::new(2.0, 6.0);
        for k in 0..r {
            let v = |rng: &mut Rng| [0; 3].map(|_| rng.range(-1.0, 1.0));
            let ray = Ray {
                origin: v(&mut rng),
                dir: v(&mut rng),
            };
            rays.push(ray, v(&mut rng), [1.0; 3], k as u64);
        }
        let mut t_coarse = vec![0.0; r * n_c];
        for row in t_coarse.chunks_exact_mut(n_c) {
            stratified(2.0, 6.0, Some(&mut rng), row);
        }
        let weights: Vec<f32> = (0..r * n_c)
            .map(|i| match (i / n_c) % 3 {
                0 => 0.0,
                1 => f32::from(u8::from(i % n_c == 4)),
                _ => rng.uniform(),
            })
            .collect();
        let streams: Vec<Rng> = (0..r).map(|k| Rng::new(100 + k as u64)).collect();
        {
            let (mut host_rngs, mut device_rngs) = (streams.clone(), streams.clone());
            let mut want_t = vec![0.0; r * (n_c + n_f)];
            let (mut fresh, mut cdf) = (vec![0.0; n_f], Vec::new());
            for k in 0..r {
                let tc = &t_coarse[k * n_c..][..n_c];
                let g = Some(&mut host_rngs[k]);
                sample_pdf(tc, &weights[k * n_c..][..n_c], g, &mut fresh, &mut cdf);
                fresh.sort_unstable_by(f32::total_cmp);
                merge_sorted(tc, &fresh, &mut want_t[k * (n_c + n_f)..][..n_c + n_f]);
            }
            let draws = sorted_draws(&mut device_rngs, n_f);
            let got = fine_samples(
                &gpu,
                &rays,
                &gpu.upload(&t_coarse),
                &gpu.upload(&weights),
                &draws,
                (n_c, n_f),
            );
            let n = r * (n_c + n_f);
            let read = |h: &Handle, len| gpu.read(h, len).expect("read");
            let (t, dt) = (read(&got.samples.t, n), read(&got.samples.dt, n));
            let (pos, dirs) = (read(&got.positions, 3 * n), read(&got.dirs, 3 * n));
            let close = |a: f32, b: f32| (a - b).abs() <= 1e-4 * (1.0 + b.abs());
            for s in 0..n {
                assert!(
                    close(t[s], want_t[s]),
                    "sample {s}: {} vs {}",
                    t[s],
                    want_t[s]
                );
            }
            for k in 0..r {
                let row = &want_t[k * (n_c + n_f)..][..n_c + n_f];
                let d = rays.dirs[k];
                let mut want_dt = vec![0.0; n_c + n_f];
                depth_deltas(row, crate::math::length(d), &mut want_dt);
                let unit = crate::math::scale(
                    rays.view_dirs[k],
                    1.0 / crate::math::length(rays.view_dirs[k]),
                );
                for (i, &tt) in row.iter().enumerate() {
                    let s = k * (n_c + n_f) + i;
                    assert!(
                        close(dt[s], want_dt[i]),
                        "delta {s}: {} vs {}",
                        dt[s],
                        want_dt[i]
                    );
                    for a in 0..3 {
                        let p = rays.origins[k][a] + tt * d[a];
                        assert!(close(pos[3 * s + a], p), "position {s}");
                        assert!(close(dirs[3 * s + a], unit[a]), "direction {s}");
                    }
                }
            }
            // The draws came from the same streams, as many as the host took.
            for (a, b) in device_rngs.iter_mut().zip(&mut host_rngs) {
                assert_eq!(a.uniform(), b.uniform());
            }
        }
    }
}
