//! The multiresolution hash encoding on the GPU: the same levels, hash and trilinear
//! weights as `encoding::hash_grid` (whose docs give the maths), one thread per (sample,
//! level). The backward scatters each sample's gradient into the eight corners it read,
//! with a float atomic add where the adapter has one and a compare-and-swap loop on the
//! value's bits where it does not.

use cubecl::prelude::*;
use cubecl::server::Handle;

use super::device::Gpu;
use crate::encoding::hash_grid::{HashGrid, FEATURES};

// The spatial hash's primes, as in `encoding::hash_grid`.
const PRIME_Y: u32 = 2_654_435_761;
const PRIME_Z: u32 = 805_459_861;
/// Threads per workgroup.
const GROUP: u32 = 256;
/// `u32`s describing one level to the kernels: resolution, entries, dense (0/1), offset.
pub(super) const LEVEL_WORDS: usize = 4;

/// Table index of grid vertex `(x, y, z)` of a level.
#[cube]
fn vertex(x: u32, y: u32, z: u32, res: u32, entries: u32, dense: u32) -> usize {
    let s = res + 1;
    let indexed = x + s * (y + s * z);
    // u32 products wrap on every backend, as `wrapping_mul` does on the CPU.
    let hashed = (x ^ (y * PRIME_Y) ^ (z * PRIME_Z)) & (entries - 1);
    select(dense == 1, indexed, hashed) as usize
}

/// The table slot of corner `k` (bit 0: +x, bit 1: +y, bit 2: +z) of the cell at
/// `(cx, cy, cz)`.
#[cube]
pub(super) fn corner(
    k: u32,
    cx: u32,
    cy: u32,
    cz: u32,
    res: u32,
    entries: u32,
    dense: u32,
) -> usize {
    vertex(
        cx + (k & 1),
        cy + ((k >> 1) & 1),
        cz + ((k >> 2) & 1),
        res,
        entries,
        dense,
    )
}

/// Where sample `s` of `points` sits in a level's grid of `res` cells a side: the cell's
/// corner and the fractions.
#[cube]
fn cell(points: &[f32], s: usize, res: u32) -> (u32, u32, u32, f32, f32, f32) {
    cell_at(points[3 * s], points[3 * s + 1], points[3 * s + 2], res)
}

/// [`cell`] of the unit-cube point `(x, y, z)`.
#[cube]
pub(super) fn cell_at(x: f32, y: f32, z: f32, res: u32) -> (u32, u32, u32, f32, f32, f32) {
    let rf = f32::cast_from(res);
    let px = f32::clamp(x, 0.0, 1.0) * rf;
    let py = f32::clamp(y, 0.0, 1.0) * rf;
    let pz = f32::clamp(z, 0.0, 1.0) * rf;
    let cx = u32::min(u32::cast_from(px), res - 1);
    let cy = u32::min(u32::cast_from(py), res - 1);
    let cz = u32::min(u32::cast_from(pz), res - 1);
    (
        cx,
        cy,
        cz,
        px - f32::cast_from(cx),
        py - f32::cast_from(cy),
        pz - f32::cast_from(cz),
    )
}

/// Level `l`'s words in the table `levels`: resolution, entries, dense (0/1), and the
/// offset of its table in the parameter vector.
#[cube]
pub(super) fn level_words(levels: &[u32], l: usize) -> (u32, u32, u32, usize) {
    let at = LEVEL_WORDS * l;
    (
        levels[at],
        levels[at + 1],
        levels[at + 2],
        levels[at + 3] as usize,
    )
}

/// Trilinear weight of corner `k` (bit 0: +x, bit 1: +y, bit 2: +z).
#[cube]
fn weight(k: u32, fx: f32, fy: f32, fz: f32) -> f32 {
    let wx = select((k & 1) == 1, fx, 1.0 - fx);
    let wy = select(((k >> 1) & 1) == 1, fy, 1.0 - fy);
    let wz = select(((k >> 2) & 1) == 1, fz, 1.0 - fz);
    wx * wy * wz
}

/// The two features of level `l` (of the table `levels`) at the unit-cube point
/// `(x, y, z)`: the trilinear blend of its cell's eight corners.
#[cube]
pub(super) fn encode_level(
    params: &[f32],
    levels: &[u32],
    l: usize,
    x: f32,
    y: f32,
    z: f32,
) -> (f32, f32) {
    let (res, entries, dense, offset) = level_words(levels, l);
    let (cx, cy, cz, fx, fy, fz) = cell_at(x, y, z, res);
    let mut f0 = 0.0f32;
    let mut f1 = 0.0f32;
    #[unroll]
    for k in 0..8u32 {
        let w = weight(k, fx, fy, fz);
        let v = corner(k, cx, cy, cz, res, entries, dense);
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
    if s * 3 < points.len() {
        let (x, y, z) = (points[3 * s], points[3 * s + 1], points[3 * s + 2]);
        let (f0, f1) = encode_level(params, levels, l, x, y, z);
        out[(s * nl + l) * 2] = f0;
        out[(s * nl + l) * 2 + 1] = f1;
    }
}

/// How a backward kernel adds into a gradient slot: the slot's element type picks it.
#[cube]
pub(super) trait ScatterAdd: CubePrimitive {
    fn scatter_add(slot: &Atomic<Self>, v: f32);
}

/// Hardware float atomics.
#[cube]
impl ScatterAdd for f32 {
    fn scatter_add(slot: &Atomic<f32>, v: f32) {
        slot.fetch_add(v);
    }
}

/// An `f32` stored as its bits, added by compare-and-swap: for adapters without float
/// atomics (WebGPU's baseline, older drivers).
#[cube]
impl ScatterAdd for u32 {
    fn scatter_add(slot: &Atomic<u32>, v: f32) {
        let mut old = slot.load();
        loop {
            let new = u32::reinterpret(f32::reinterpret(old) + v);
            let seen = slot.compare_exchange_weak(old, new);
            if seen == old {
                break;
            }
            old = seen;
        }
    }
}

/// Adds a cell's eight corners' summed gradients (`acc`: two features a corner) into
/// `grads` through `S`, skipping corners whose sums are exactly zero, and clears `acc`.
#[cube]
#[allow(clippy::too_many_arguments)]
fn flush_cell<S: ScatterAdd>(
    grads: &mut [Atomic<S>],
    acc: &mut Array<f32>,
    cx: u32,
    cy: u32,
    cz: u32,
    res: u32,
    entries: u32,
    dense: u32,
    offset: usize,
) {
    #[unroll]
    for k in 0..8u32 {
        let (a0, a1) = (acc[2 * k as usize], acc[2 * k as usize + 1]);
        if a0 != 0.0 || a1 != 0.0 {
            let v = corner(k, cx, cy, cz, res, entries, dense);
            S::scatter_add(&grads[offset + 2 * v], a0);
            S::scatter_add(&grads[offset + 2 * v + 1], a1);
        }
        acc[2 * k as usize] = 0.0;
        acc[2 * k as usize + 1] = 0.0;
    }
}

/// Backward: `grads[corner] += w * d_out` for each sample's eight corners, through `S`.
/// A thread takes one level of `run` consecutive samples and sums in registers while they
/// stay in one cell, adding to the table once per cell rather than once per sample:
/// samples along a ray share the coarse levels' cells for many steps, and those cells'
/// few entries are where the atomic adds of many threads would queue.
#[cube(launch_unchecked)]
fn encode_bwd<S: ScatterAdd>(
    levels: &[u32],
    points: &[f32],
    d_out: &[f32],
    grads: &mut [Atomic<S>],
    n_levels: u32,
    samples: u32,
    run: u32,
) {
    let nl = n_levels as usize;
    let first = (ABSOLUTE_POS / nl) * run as usize;
    let l = ABSOLUTE_POS % nl;
    if first < samples as usize {
        let last = usize::min(first + run as usize, samples as usize);
        let (res, entries, dense, offset) = level_words(levels, l);
        let mut acc = Array::<f32>::new(16usize);
        #[unroll]
        for k in 0..16usize {
            acc[k] = 0.0;
        }
        // The cell whose sums `acc` holds; `res` on x: none yet.
        let mut held_x = res;
        let mut held_y = 0u32;
        let mut held_z = 0u32;
        for s in first..last {
            let g0 = d_out[(s * nl + l) * 2];
            let g1 = d_out[(s * nl + l) * 2 + 1];
            if g0 != 0.0 || g1 != 0.0 {
                let (cx, cy, cz, fx, fy, fz) = cell(points, s, res);
                if held_x != res && (cx != held_x || cy != held_y || cz != held_z) {
                    flush_cell::<S>(
                        grads, &mut acc, held_x, held_y, held_z, res, entries, dense, offset,
                    );
                }
                held_x = cx;
                held_y = cy;
                held_z = cz;
                #[unroll]
                for k in 0..8u32 {
                    let w = weight(k, fx, fy, fz);
                    acc[2 * k as usize] += w * g0;
                    acc[2 * k as usize + 1] += w * g1;
                }
            }
        }
        if held_x != res {
            flush_cell::<S>(
                grads, &mut acc, held_x, held_y, held_z, res, entries, dense, offset,
            );
        }
    }
}

/// How gradients are scattered.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Scatter {
    /// Hardware `f32` atomic add.
    FloatAtomic,
    /// A compare-and-swap loop on the bits.
    CompareAndSwap,
}

/// A hash grid's level table on the device.
pub struct GpuHashGrid {
    pub(super) levels: Handle,
    pub(super) n_levels: usize,
    num_params: usize,
}

impl GpuHashGrid {
    /// Uploads `grid`'s level structure.
    pub fn new(gpu: &Gpu, grid: &HashGrid) -> Self {
        let words: Vec<u32> = grid
            .levels
            .iter()
            .flat_map(|l| {
                [
                    l.resolution,
                    l.entries as u32,
                    u32::from(l.dense),
                    l.offset as u32,
                ]
            })
            .collect();
        debug_assert_eq!(words.len(), grid.levels.len() * LEVEL_WORDS);
        let end = grid.param_range().end;
        GpuHashGrid {
            levels: gpu.upload_u32(&words),
            n_levels: grid.levels.len(),
            num_params: end,
        }
    }

    fn launch_size(&self, samples: usize) -> (CubeCount, CubeDim) {
        let threads = (samples * self.n_levels) as u32;
        (
            CubeCount::Static(threads.div_ceil(GROUP), 1, 1),
            CubeDim::new_1d(GROUP),
        )
    }

    /// Encodes `samples` unit-cube points (`points`: `samples x 3`) with the tables in
    /// `params` (the whole parameter vector, as the CPU layout places it) into `out`
    /// (`samples x levels x 2`).
    pub fn encode(
        &self,
        gpu: &Gpu,
        params: &Handle,
        points: &Handle,
        samples: usize,
        out: &Handle,
    ) {
        if samples == 0 {
            return;
        }
        let (count, dim) = self.launch_size(samples);
        // SAFETY: the lengths given are those the buffers were made with (the parameter
        // vector holds every level's table, `points` 3 floats per sample, `out` one pair
        // per sample and level), and the kernel bounds-checks its sample index.
        unsafe {
            encode_fwd::launch_unchecked(
                &gpu.client,
                count,
                dim,
                BufferArg::from_raw_parts(params.clone(), self.num_params),
                BufferArg::from_raw_parts(self.levels.clone(), self.n_levels * LEVEL_WORDS),
                BufferArg::from_raw_parts(points.clone(), samples * 3),
                BufferArg::from_raw_parts(out.clone(), samples * self.n_levels * FEATURES),
                self.n_levels as u32,
            );
        }
    }

    /// Backward of [`encode`](Self::encode): adds `d_out` (`samples x levels x 2`), spread
    /// over each sample's corners, into `grads` (laid out as the parameter vector), a thread
    /// a level of `run` consecutive samples (1: a thread a sample and level).
    #[allow(clippy::too_many_arguments)]
    pub fn encode_bwd(
        &self,
        gpu: &Gpu,
        scatter: Scatter,
        points: &Handle,
        d_out: &Handle,
        samples: usize,
        grads: &Handle,
        run: usize,
    ) {
        if samples == 0 {
            return;
        }
        let run = run.max(1);
        let (count, dim) = self.launch_size(samples.div_ceil(run));
        let (nl, np) = (self.n_levels, self.num_params);
        // SAFETY: as in `encode`; `grads` has one slot per parameter.
        unsafe {
            let levels = || BufferArg::from_raw_parts(self.levels.clone(), nl * LEVEL_WORDS);
            let points = || BufferArg::from_raw_parts(points.clone(), samples * 3);
            let d_out = || BufferArg::from_raw_parts(d_out.clone(), samples * nl * FEATURES);
            let grads = || BufferArg::from_raw_parts(grads.clone(), np);
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
                    run as u32,
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
                    run as u32,
                ),
            }
        }
    }
}

#[cfg(test)]
pub(super) mod tests {
    use super::*;
    use crate::encoding::hash_grid::HashGridConfig;
    use crate::engine::gpu::device::{test_gpu, worst};
    use crate::nn::{GradBuffer, ParamLayout};
    use crate::rng::Rng;

    fn read(gpu: &Gpu, h: Handle) -> Vec<f32> {
        gpu.read(&h, usize::MAX).expect("read back")
    }

    /// A small grid with dense coarse levels and hashed fine ones (table of 2^10), random
    /// tables and points, some outside the unit cube (clamped).
    pub(in crate::engine::gpu) fn setup() -> (HashGrid, Vec<f32>, Vec<f32>) {
        let mut layout = ParamLayout::default();
        layout.push("before", &[7]);
        let grid = HashGrid::new(
            HashGridConfig {
                levels: 6,
                log2_table_size: 10,
                base_resolution: 4,
                max_resolution: 128,
            },
            "grid.",
            &mut layout,
        );
        assert!(grid.levels[0].dense && !grid.levels[5].dense);
        let mut rng = Rng::new(3);
        let params: Vec<f32> = (0..layout.total).map(|_| rng.range(-1.0, 1.0)).collect();
        let points: Vec<f32> = (0..1000 * 3).map(|_| rng.range(-0.05, 1.05)).collect();
        (grid, params, points)
    }

    /// The kernel against the CPU reference on the same inputs: values within 1e-5.
    #[test]
    fn encode_matches_the_cpu() {
        let Some(gpu) = test_gpu() else { return };
        let (grid, params, points) = setup();
        let n = points.len() / 3;
        let mut want = vec![0.0; n * grid.dims()];
        grid.encode_reference(&params, &points, &mut want);
        let g = GpuHashGrid::new(&gpu, &grid);
        let p = gpu.upload(&params);
        let x = gpu.upload(&points);
        let out = gpu.client.empty(n * grid.dims() * 4);
        g.encode(&gpu, &p, &x, n, &out);
        let got = read(&gpu, out);
        let worst = got
            .iter()
            .zip(&want)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0f32, f32::max);
        assert!(worst < 1e-5, "largest difference {worst}");
    }

    /// Both scatter paths against the CPU backward, a thread a sample and a thread a run of
    /// samples: gradients within 1e-4 (atomic adds run in any order, so the sums are
    /// rounded differently). The points are random ones, then points along rays in short
    /// steps (consecutive samples sharing cells, as a training step's do), with some
    /// samples' gradients exactly zero and the runs not dividing the samples.
    #[test]
    fn encode_bwd_matches_the_cpu_with_both_scatters() {
        let Some(gpu) = test_gpu() else { return };
        let (grid, params, random) = setup();
        let mut rng = Rng::new(5);
        let mut along_rays = Vec::new();
        for _ in 0..40 {
            let o: Vec<f32> = (0..3).map(|_| rng.range(0.0, 1.0)).collect();
            let d: Vec<f32> = (0..3).map(|_| rng.range(-1.0, 1.0)).collect();
            let steps = 5 + (rng.uniform() * 40.0) as usize;
            for k in 0..steps {
                along_rays.extend((0..3).map(|a| o[a] + 0.004 * k as f32 * d[a]));
            }
        }
        let mut scatters = vec![Scatter::CompareAndSwap];
        if gpu.float_atomics {
            scatters.push(Scatter::FloatAtomic);
        } else {
            eprintln!(
                "{}: no float atomics; testing the compare-and-swap path only",
                gpu.name
            );
        }
        for points in [random, along_rays] {
            let n = points.len() / 3;
            let mut d_out: Vec<f32> = (0..n * grid.dims()).map(|_| rng.range(-1.0, 1.0)).collect();
            for s in (0..n).step_by(7) {
                d_out[s * grid.dims()..(s + 1) * grid.dims()].fill(0.0);
            }
            let mut buffer = GradBuffer::new(params.len());
            grid.encode_bwd(&points, &d_out, &mut buffer.all());
            let want = buffer.values.clone();
            let g = GpuHashGrid::new(&gpu, &grid);
            let x = gpu.upload(&points);
            let d = gpu.upload(&d_out);
            for &scatter in &scatters {
                for run in [1, 3, 8, 64] {
                    let grads = gpu.zeros(params.len());
                    g.encode_bwd(&gpu, scatter, &x, &d, n, &grads, run);
                    let got = read(&gpu, grads);
                    let worst = worst(&got[..want.len()], &want);
                    assert!(
                        worst < 1e-4,
                        "{scatter:?}, runs of {run}: largest relative difference {worst}"
                    );
                    assert!(
                        got[..7].iter().all(|&v| v == 0.0),
                        "{scatter:?} wrote outside the grid"
                    );
                }
            }
        }
    }

    /// Many samples in one coarse cell, summed in registers over whole runs and added
    /// once, give the CPU's gradients: the run's flush at its end and at a cell change.
    #[test]
    fn runs_sum_many_samples_of_one_cell() {
        let Some(gpu) = test_gpu() else { return };
        let (grid, params, _) = setup();
        // 64 samples in one level-0 cell (4 cells a side), each with gradient 1 on both
        // features of every level: every corner of that cell sums 64 trilinear weights.
        let n = 64;
        let points: Vec<f32> = (0..n)
            .flat_map(|k| [0.05 + 0.002 * k as f32, 0.1, 0.1])
            .collect();
        let d_out = vec![1.0; n * grid.dims()];
        let mut buffer = GradBuffer::new(params.len());
        grid.encode_bwd(&points, &d_out, &mut buffer.all());
        let g = GpuHashGrid::new(&gpu, &grid);
        for run in [1, 16, 64] {
            let grads = gpu.zeros(params.len());
            let scatter = if gpu.float_atomics {
                Scatter::FloatAtomic
            } else {
                Scatter::CompareAndSwap
            };
            g.encode_bwd(
                &gpu,
                scatter,
                &gpu.upload(&points),
                &gpu.upload(&d_out),
                n,
                &grads,
                run,
            );
            let got = read(&gpu, grads);
            let worst = worst(&got[..buffer.values.len()], &buffer.values);
            assert!(
                worst < 1e-5,
                "runs of {run}: largest relative difference {worst}"
            );
        }
    }
}
