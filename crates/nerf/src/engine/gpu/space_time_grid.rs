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
const LEVEL_WORDS: usize = 5;

/// Where a sample lies in one level: its cell's first corner and its fractions, per axis
/// (`x, y, z`, then time).
#[derive(CubeType)]
struct Cell {
    c: Array<u32>,
    f: Array<f32>,
}

/// The cell (first corner, per axis) and fractions of sample `s` in a level of `res`
/// cells a side and `time_res` along time.
#[cube]
fn cell_of(points: &[f32], s: usize, res: u32, time_res: u32) -> Cell {
    let mut c = Array::<u32>::new(4usize);
    let mut f = Array::<f32>::new(4usize);
    #[unroll]
    for a in 0..4usize {
        let cells = select(a == 3, time_res, res);
        let p = f32::clamp(points[4 * s + a], 0.0, 1.0) * f32::cast_from(cells);
        let k = u32::min(u32::cast_from(p), cells - 1);
        c[a] = k;
        f[a] = p - f32::cast_from(k);
    }
    Cell { c, f }
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

#[cube(launch_unchecked)]
fn encode_fwd(params: &[f32], levels: &[u32], points: &[f32], out: &mut [f32], n_levels: u32) {
    let nl = n_levels as usize;
    let s = ABSOLUTE_POS / nl;
    let l = ABSOLUTE_POS % nl;
    if s * 4 < points.len() {
        let res = levels[5 * l];
        let time_res = levels[5 * l + 1];
        let entries = levels[5 * l + 2];
        let dense = levels[5 * l + 3];
        let offset = levels[5 * l + 4] as usize;
        let cell = cell_of(points, s, res, time_res);
        let mut f0 = 0.0f32;
        let mut f1 = 0.0f32;
        #[unroll]
        for k in 0..16u32 {
            let w = corner_weight(&cell, k);
            let v = corner_slot(&cell, k, res, entries, dense);
            f0 += w * params[offset + 2 * v];
            f1 += w * params[offset + 2 * v + 1];
        }
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
            let res = levels[5 * l];
            let time_res = levels[5 * l + 1];
            let entries = levels[5 * l + 2];
            let dense = levels[5 * l + 3];
            let offset = levels[5 * l + 4] as usize;
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

/// A space-time grid's level table on the device.
pub struct GpuSpaceTimeGrid {
    levels: Handle,
    n_levels: usize,
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
}
