//! The moving field's hash encoding of space and time on the GPU: the same levels, hash
//! and quadrilinear weights as `encoding::space_time_grid` (whose docs give the maths), one
//! thread per (sample, level). The backward scatters each sample's gradient into the
//! sixteen corners it read, through the hash grid's float atomics or compare-and-swap.

use cubecl::prelude::*;
use cubecl::server::Handle;

use super::device::Gpu;
use super::hash_grid::{Scatter, ScatterAdd};
use super::launch::grid;
use crate::encoding::hash_grid::FEATURES;
use crate::encoding::space_time_grid::SpaceTimeGrid;

// The space-time hash's primes, as in `encoding::space_time_grid`.
const PRIME_Y: u32 = 2_654_435_761;
const PRIME_Z: u32 = 805_459_861;
const PRIME_T: u32 = 3_674_653_429;
/// Threads per workgroup.
const GROUP: u32 = 256;
/// `u32`s describing one level: resolution, time resolution, entries, dense (0/1), offset.
pub(super) const LEVEL_WORDS: usize = 5;

/// Where a sample lies in one level: its cell's first corner and its fractions, per axis
/// (`x, y, z`, then time).
#[derive(CubeType)]
struct Cell {
    c: Array<u32>,
    f: Array<f32>,
}

/// The cell (first corner, per axis) and fractions of the point `(x, y, z, t)` (unit
/// cube, then time) in a level of `res` cells a side and `time_res` along time.
#[cube]
fn cell_at(x: f32, y: f32, z: f32, t: f32, res: u32, time_res: u32) -> Cell {
    let mut c = Array::<u32>::new(4usize);
    let mut f = Array::<f32>::new(4usize);
    let mut p = Array::<f32>::new(4usize);
    p[0] = x;
    p[1] = y;
    p[2] = z;
    p[3] = t;
    #[unroll]
    for a in 0..4usize {
        let cells = select(a == 3, time_res, res);
        let q = f32::clamp(p[a], 0.0, 1.0) * f32::cast_from(cells);
        let k = u32::min(u32::cast_from(q), cells - 1);
        c[a] = k;
        f[a] = q - f32::cast_from(k);
    }
    Cell { c, f }
}

/// [`cell_at`] for sample `s` of `points` (`x, y, z, t` each).
#[cube]
fn cell_of(points: &[f32], s: usize, res: u32, time_res: u32) -> Cell {
    cell_at(
        points[4 * s],
        points[4 * s + 1],
        points[4 * s + 2],
        points[4 * s + 3],
        res,
        time_res,
    )
}

/// Table slot of corner `k` (bit `a` set: one step up axis `a`, time last) of `cell`.
#[cube]
fn corner_slot(cell: &Cell, k: u32, res: u32, entries: u32, dense: u32) -> usize {
    let x = cell.c[0] + (k & 1);
    let y = cell.c[1] + ((k >> 1) & 1);
    let z = cell.c[2] + ((k >> 2) & 1);
    let t = cell.c[3] + ((k >> 3) & 1);
    let s = res + 1;
    let indexed = x + s * (y + s * (z + s * t));
    // u32 products wrap on every backend, as `wrapping_mul` does on the CPU.
    let hashed = (x ^ (y * PRIME_Y) ^ (z * PRIME_Z) ^ (t * PRIME_T)) & (entries - 1);
    select(dense == 1, indexed, hashed) as usize
}

/// Quadrilinear weight of corner `k` of `cell`, multiplied x, y, z, then time, as the CPU
/// multiplies it.
#[cube]
fn corner_weight(cell: &Cell, k: u32) -> f32 {
    let mut w = 1.0f32;
    #[unroll]
    for a in 0..4u32 {
        let up = ((k >> a) & 1) == 1;
        let f = cell.f[a as usize];
        w *= select(up, f, 1.0 - f);
    }
    w
}

/// Level `l`'s words in the table `levels` ([`LEVEL_WORDS`] each): resolution, time
/// resolution, entries, dense (0/1), and the offset of its table in the parameter vector.
#[cube]
fn level_words(levels: &[u32], l: usize) -> (u32, u32, u32, u32, usize) {
    let at = LEVEL_WORDS * l;
    (
        levels[at],
        levels[at + 1],
        levels[at + 2],
        levels[at + 3],
        levels[at + 4] as usize,
    )
}

/// The two features of level `l` (of the table `levels`) at the point `(x, y, z, t)`:
/// the quadrilinear blend of its cell's sixteen corners.
#[cube]
#[allow(clippy::too_many_arguments)]
pub(super) fn encode_level(
    params: &[f32],
    levels: &[u32],
    l: usize,
    x: f32,
    y: f32,
    z: f32,
    t: f32,
) -> (f32, f32) {
    let (res, time_res, entries, dense, offset) = level_words(levels, l);
    let cell = cell_at(x, y, z, t, res, time_res);
    let mut f0 = 0.0f32;
    let mut f1 = 0.0f32;
    #[unroll]
    for k in 0..16u32 {
        let w = corner_weight(&cell, k);
        let v = corner_slot(&cell, k, res, entries, dense);
        f0 += w * params[offset + 2 * v];
        f1 += w * params[offset + 2 * v + 1];
    }
    (f0, f1)
}

#[cube(launch_unchecked)]
fn encode_fwd(params: &[f32], levels: &[u32], points: &[f32], out: &mut [f32], n_levels: u32) {
    let nl = n_levels as usize;
    let s = ABSOLUTE_POS / nl;
    let l = ABSOLUTE_POS % nl;
    if s * 4 < points.len() {
        let (x, y, z, t) = (
            points[4 * s],
            points[4 * s + 1],
            points[4 * s + 2],
            points[4 * s + 3],
        );
        let (f0, f1) = encode_level(params, levels, l, x, y, z, t);
        out[(s * nl + l) * 2] = f0;
        out[(s * nl + l) * 2 + 1] = f1;
    }
}

/// Backward: `grads[corner] += w * d_out` for each sample's sixteen corners, through `S`
/// (a thread a sample and level; corners whose share is exactly zero are skipped).
#[cube(launch_unchecked)]
fn encode_bwd<S: ScatterAdd>(
    levels: &[u32],
    points: &[f32],
    d_out: &[f32],
    grads: &mut [Atomic<S>],
    n_levels: u32,
    samples: u32,
) {
    let nl = n_levels as usize;
    let s = ABSOLUTE_POS / nl;
    let l = ABSOLUTE_POS % nl;
    if s < samples as usize {
        let g0 = d_out[(s * nl + l) * 2];
        let g1 = d_out[(s * nl + l) * 2 + 1];
        if g0 != 0.0 || g1 != 0.0 {
            let (res, time_res, entries, dense, offset) = level_words(levels, l);
            let cell = cell_of(points, s, res, time_res);
            #[unroll]
            for k in 0..16u32 {
                let w = corner_weight(&cell, k);
                if w != 0.0 {
                    let v = corner_slot(&cell, k, res, entries, dense);
                    S::scatter_add(&grads[offset + 2 * v], w * g0);
                    S::scatter_add(&grads[offset + 2 * v + 1], w * g1);
                }
            }
        }
    }
}

/// When the samples of a call are: each its own moment (`times`, one per sample), all the
/// one moment `times[0]`, or any (a moment drawn from each point's coordinates, so that
/// the occupancy grid's refreshes see every moment), as the CPU field's `Moments`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Moments {
    Each,
    At,
    Any,
}

/// `field::fast::moment_of_point` of the unit-cube point `(x, y, z)` (rotations written
/// out: cube code has no `rotate_left`).
#[cube]
#[allow(clippy::manual_rotate)]
pub(super) fn moment_of_point(x: f32, y: f32, z: f32) -> f32 {
    let bx = u32::reinterpret(x);
    let by = u32::reinterpret(y);
    let bz = u32::reinterpret(z);
    let bits = bx ^ ((by << 11) | (by >> 21)) ^ ((bz << 22) | (bz >> 10));
    let h = (bits * 0x9e37_79b1u32) ^ (bits >> 15);
    f32::cast_from((h * 0x85eb_ca6bu32) >> 8) / 16_777_216.0f32
}

/// Each sample's point of space and time (`out`: `n x 4`) from its unit-cube position
/// (`unit`: `n x 3`) and `moments` (0: each its own from `times`, 1: `times[0]`, 2: any).
#[cube(launch_unchecked)]
#[allow(unused_assignments)]
fn space_time_points(unit: &[f32], times: &[f32], out: &mut [f32], n: u32, moments: u32) {
    let s = ABSOLUTE_POS;
    if s < n as usize {
        let x = unit[3 * s];
        let y = unit[3 * s + 1];
        let z = unit[3 * s + 2];
        let mut t = 0.0f32;
        if moments == 0 {
            t = times[s];
        } else if moments == 1 {
            t = times[0];
        } else {
            t = moment_of_point(x, y, z);
        }
        out[4 * s] = x;
        out[4 * s + 1] = y;
        out[4 * s + 2] = z;
        out[4 * s + 3] = t;
    }
}

/// Each ray's value (`per_ray`) copied to its samples (`offsets`: CSR, `rays + 1`).
#[cube(launch_unchecked)]
fn spread_to_samples(per_ray: &[f32], offsets: &[u32], out: &mut [f32], rays: u32) {
    let r = ABSOLUTE_POS;
    if r < rays as usize {
        let v = per_ray[r];
        for s in offsets[r] as usize..offsets[r + 1] as usize {
            out[s] = v;
        }
    }
}

/// The points of space and time of `n` samples at unit-cube positions `unit` (`n x 3`):
/// `times` holds one moment per sample (`Moments::Each`), or one for all (`At`), or is
/// not read (`Any`).
pub fn points_in_time(
    gpu: &Gpu,
    unit: &Handle,
    (times, moments): (&Handle, Moments),
    n: usize,
) -> Handle {
    let out = gpu.floats(4 * n.max(1));
    if n == 0 {
        return out;
    }
    let (count, dim) = grid(n, GROUP);
    let times_len = match moments {
        Moments::Each => n,
        Moments::At | Moments::Any => 1,
    };
    // SAFETY: `unit` holds 3 floats a sample, `out` 4, `times` what `moments` reads; the
    // kernel bounds-checks its sample.
    unsafe {
        space_time_points::launch_unchecked(
            &gpu.client,
            count,
            dim,
            BufferArg::from_raw_parts(unit.clone(), 3 * n),
            BufferArg::from_raw_parts(times.clone(), times_len),
            BufferArg::from_raw_parts(out.clone(), 4 * n),
            n as u32,
            moments as u32,
        );
    }
    out
}

/// Each of `rays` rays' value in `per_ray` given to each of its samples (`offsets`: CSR,
/// `rays + 1` slots ending at `samples`).
pub fn per_sample(
    gpu: &Gpu,
    per_ray: &Handle,
    offsets: &Handle,
    rays: usize,
    samples: usize,
) -> Handle {
    let out = gpu.floats(samples.max(1));
    if rays == 0 {
        return out;
    }
    let (count, dim) = grid(rays, GROUP);
    // SAFETY: `per_ray` holds `rays` floats, `offsets` `rays + 1` ending at `samples`, the
    // length of `out`; the kernel bounds-checks its ray.
    unsafe {
        spread_to_samples::launch_unchecked(
            &gpu.client,
            count,
            dim,
            BufferArg::from_raw_parts(per_ray.clone(), rays),
            BufferArg::from_raw_parts(offsets.clone(), rays + 1),
            BufferArg::from_raw_parts(out.clone(), samples.max(1)),
            rays as u32,
        );
    }
    out
}

/// A space-time grid's level table on the device.
pub struct GpuSpaceTimeGrid {
    /// [`LEVEL_WORDS`] a level.
    pub(super) levels: Handle,
    pub(super) n_levels: usize,
}

impl GpuSpaceTimeGrid {
    /// Uploads `grid`'s level structure.
    pub fn new(gpu: &Gpu, grid: &SpaceTimeGrid) -> Self {
        let words: Vec<u32> = grid
            .levels
            .iter()
            .flat_map(|l| {
                [
                    l.resolution,
                    l.time_resolution,
                    l.entries as u32,
                    u32::from(l.dense),
                    l.offset as u32,
                ]
            })
            .collect();
        GpuSpaceTimeGrid {
            levels: gpu.upload_u32(&words),
            n_levels: grid.levels.len(),
        }
    }

    /// Encodes `samples` points (`points`: `samples x 4`, unit-cube position then time)
    /// with the tables in `params` (the whole parameter vector, `num_params` floats) into
    /// `out` (`samples x levels x 2`).
    pub fn encode(
        &self,
        gpu: &Gpu,
        (params, num_params): (&Handle, usize),
        points: &Handle,
        samples: usize,
        out: &Handle,
    ) {
        if samples == 0 {
            return;
        }
        let nl = self.n_levels;
        let (count, dim) = grid(samples * nl, GROUP);
        // SAFETY: the lengths given are those the buffers were made with (the parameter
        // vector holds every level's table, `points` 4 floats per sample, `out` one pair
        // per sample and level); the kernel bounds-checks its sample.
        unsafe {
            encode_fwd::launch_unchecked(
                &gpu.client,
                count,
                dim,
                BufferArg::from_raw_parts(params.clone(), num_params),
                BufferArg::from_raw_parts(self.levels.clone(), nl * LEVEL_WORDS),
                BufferArg::from_raw_parts(points.clone(), samples * 4),
                BufferArg::from_raw_parts(out.clone(), samples * nl * FEATURES),
                nl as u32,
            );
        }
    }

    /// Backward of [`encode`](Self::encode): adds `d_out` (`samples x levels x 2`), spread
    /// over each sample's corners, into `grads` (laid out as the parameter vector,
    /// `num_params` floats).
    pub fn encode_bwd(
        &self,
        gpu: &Gpu,
        scatter: Scatter,
        points: &Handle,
        d_out: &Handle,
        samples: usize,
        (grads, num_params): (&Handle, usize),
    ) {
        if samples == 0 {
            return;
        }
        let nl = self.n_levels;
        let (count, dim) = grid(samples * nl, GROUP);
        // SAFETY: as in `encode`; `grads` has one slot per parameter.
        unsafe {
            let levels = || BufferArg::from_raw_parts(self.levels.clone(), nl * LEVEL_WORDS);
            let points = || BufferArg::from_raw_parts(points.clone(), samples * 4);
            let d_out = || BufferArg::from_raw_parts(d_out.clone(), samples * nl * FEATURES);
            let grads = || BufferArg::from_raw_parts(grads.clone(), num_params);
            match scatter {
                Scatter::FloatAtomic => encode_bwd::launch_unchecked::<f32>(
                    &gpu.client,
                    count,
                    dim,
                    levels(),
                    points(),
                    d_out(),
                    grads(),
                    nl as u32,
                    samples as u32,
                ),
                Scatter::CompareAndSwap => encode_bwd::launch_unchecked::<u32>(
                    &gpu.client,
                    count,
                    dim,
                    levels(),
                    points(),
                    d_out(),
                    grads(),
                    nl as u32,
                    samples as u32,
                ),
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::encoding::space_time_grid::SpaceTimeConfig;
    use crate::engine::gpu::device::{test_gpu, worst};
    use crate::field::fast::moment_of_point as cpu_moment;
    use crate::nn::{GradBuffer, ParamLayout};
    use crate::rng::Rng;

    /// A grid with a dense coarse level and hashed finer ones, something before it in the
    /// parameter vector, random tables and points (some outside the unit range, clamped).
    fn setup() -> (SpaceTimeGrid, Vec<f32>, Vec<f32>) {
        let mut layout = ParamLayout::default();
        layout.push("before", &[9]);
        let grid = SpaceTimeGrid::new(
            SpaceTimeConfig {
                levels: 4,
                log2_table_size: 10,
                base_resolution: 2,
                max_resolution: 24,
                base_time_resolution: 2,
                max_time_resolution: 16,
            },
            "motion.",
            &mut layout,
        );
        assert!(grid.levels[0].dense && !grid.levels[3].dense);
        let mut rng = Rng::new(21);
        let params: Vec<f32> = (0..layout.total).map(|_| rng.range(-1.0, 1.0)).collect();
        let points: Vec<f32> = (0..800 * 4).map(|_| rng.range(-0.05, 1.05)).collect();
        (grid, params, points)
    }

    /// The kernel against the CPU encoding on the same inputs.
    #[test]
    fn encode_matches_the_cpu() {
        let Some(gpu) = test_gpu() else { return };
        let (grid, params, points) = setup();
        let n = points.len() / 4;
        let mut want = vec![0.0; n * grid.dims()];
        grid.encode(&params, &points, &mut want);
        let g = GpuSpaceTimeGrid::new(&gpu, &grid);
        let out = gpu.floats(n * grid.dims());
        g.encode(
            &gpu,
            (&gpu.upload(&params), params.len()),
            &gpu.upload(&points),
            n,
            &out,
        );
        let got = gpu.read(&out, n * grid.dims()).expect("read");
        let e = worst(&got, &want);
        assert!(e < 1e-5, "largest difference {e}");
    }

    /// Both scatter paths against the CPU backward (some samples' gradients zero):
    /// gradients within 1e-4 (atomic adds run in any order).
    #[test]
    fn encode_bwd_matches_the_cpu_with_both_scatters() {
        let Some(gpu) = test_gpu() else { return };
        let (grid, params, points) = setup();
        let n = points.len() / 4;
        let mut rng = Rng::new(22);
        let mut d_out: Vec<f32> = (0..n * grid.dims()).map(|_| rng.range(-1.0, 1.0)).collect();
        d_out[..5 * grid.dims()].fill(0.0);
        let mut want = GradBuffer::new(params.len());
        grid.encode_bwd(&points, &d_out, &mut want.all());
        assert!(want.values[..9].iter().all(|&v| v == 0.0));
        let g = GpuSpaceTimeGrid::new(&gpu, &grid);
        for scatter in [Scatter::FloatAtomic, Scatter::CompareAndSwap] {
            if scatter == Scatter::FloatAtomic && !gpu.float_atomics {
                continue;
            }
            let grads = gpu.zeros(params.len());
            g.encode_bwd(
                &gpu,
                scatter,
                &gpu.upload(&points),
                &gpu.upload(&d_out),
                n,
                (&grads, params.len()),
            );
            let got = gpu.read(&grads, params.len()).expect("read");
            let e = worst(&got, &want.values);
            assert!(e < 1e-4, "{scatter:?}: largest difference {e}");
        }
    }

    /// The points of space and time in each of the three ways against the CPU's: each
    /// sample's moment, one moment, and the moment drawn from the point (to the bit).
    #[test]
    fn points_in_time_match_the_cpu() {
        let Some(gpu) = test_gpu() else { return };
        let mut rng = Rng::new(23);
        let n = 500;
        let unit: Vec<f32> = (0..n * 3).map(|_| rng.range(-0.1, 1.1)).collect();
        let times: Vec<f32> = (0..n).map(|_| rng.uniform()).collect();
        let u = gpu.upload(&unit);
        for moments in [Moments::Each, Moments::At, Moments::Any] {
            let got = points_in_time(&gpu, &u, (&gpu.upload(&times), moments), n);
            let got = gpu.read(&got, 4 * n).expect("read");
            for (s, p) in got.chunks_exact(4).enumerate() {
                let xyz = &unit[3 * s..][..3];
                let t = match moments {
                    Moments::Each => times[s],
                    Moments::At => times[0],
                    Moments::Any => cpu_moment(xyz),
                };
                assert_eq!(p, [xyz[0], xyz[1], xyz[2], t], "{moments:?}, sample {s}");
            }
        }
    }

    /// Each ray's value reaches its samples and no others; a ray without samples is
    /// skipped.
    #[test]
    fn rays_values_reach_their_samples() {
        let Some(gpu) = test_gpu() else { return };
        let counts = [3usize, 0, 1, 5, 2];
        let mut offsets = vec![0u32];
        for c in counts {
            offsets.push(offsets.last().copied().unwrap_or(0) + c as u32);
        }
        let values = [0.5f32, 9.0, 0.25, 0.75, 1.0];
        let got = per_sample(
            &gpu,
            &gpu.upload(&values),
            &gpu.upload_u32(&offsets),
            counts.len(),
            11,
        );
        let want: Vec<f32> = counts
            .iter()
            .zip(values)
            .flat_map(|(&c, v)| std::iter::repeat_n(v, c))
            .collect();
        assert_eq!(gpu.read(&got, 11).expect("read"), want);
    }
}
