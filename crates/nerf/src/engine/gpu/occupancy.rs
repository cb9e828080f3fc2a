//! The occupancy grid's refresh on the GPU: `render::occupancy::OccupancyGrid::update`'s
//! rule (decay every cell; re-evaluate the chosen ones at a random point inside; a cell is
//! occupied while its thickness reaches `min(threshold, mean)`) with the grid's thickness
//! and occupied cells on the device. Random numbers come from a counter hash of
//! `(seed, step, cell, draw)` instead of the CPU's streams, so the points differ from the
//! CPU engine's, not their distribution.
//!
//! Work mapping: the cells are visited in chunks of [`CHUNK`]: one kernel writes a point in
//! every cell of the chunk, the field evaluates all of them (choosing on the device would
//! need a compaction; evaluating every cell costs more than the CPU's chosen few but keeps
//! the passes simple), and one kernel decays and updates the chunk's cells. Then a blocked sum
//! gives the mean and a last kernel re-derives the occupied cells, and one more the flags
//! of the blocks marching crosses whole.

use cubecl::prelude::*;
use cubecl::server::Handle;

use super::device::Gpu;
use super::launch::grid;
use super::march::grid_flags;
use crate::render::occupancy::{
    blocks_per_axis, regions_per_axis, OccupancyConfig, OccupancyGrid, BLOCK, REGION,
};

const GROUP: u32 = 256;
/// Cells per field evaluation.
pub const CHUNK: usize = 1 << 18;
/// Cells summed per thread of the mean.
const SUM_BLOCK: usize = 1024;

/// `u32` hash (a "lowbias32" mixer) of a few counters.
#[cube]
fn hash(a: u32, b: u32) -> u32 {
    let mut x = a ^ (b * 0x9e37_79b9u32);
    x ^= x >> 16;
    x *= 0x7feb_352du32;
    x ^= x >> 15;
    x *= 0x846c_a68bu32;
    x ^= x >> 16;
    x
}

/// Uniform in [0, 1) from draw `k` of cell `cell` at step `step` of a run with `seed`.
#[cube]
fn uniform(seed: u32, step: u32, cell: u32, k: u32) -> f32 {
    let h = hash(hash(hash(seed, step), cell), k);
    f32::cast_from(h >> 8) * 0.000_000_059_604_645f32 // 2^-24
}

/// A random point in each cell `first..first + n` of the grid, into `points` (`n x 3`).
#[cube(launch_unchecked)]
fn cell_points(points: &mut [f32], first: u32, n: u32, res: u32, bound: f32, seed: u32, step: u32) {
    let i = ABSOLUTE_POS;
    if i < n as usize {
        let idx = first + i as u32;
        let cs = 2.0 * bound / f32::cast_from(res);
        let cx = idx % res;
        let cy = (idx / res) % res;
        let cz = idx / (res * res);
        points[3 * i] = (f32::cast_from(cx) + uniform(seed, step, idx, 1)) * cs - bound;
        points[3 * i + 1] = (f32::cast_from(cy) + uniform(seed, step, idx, 2)) * cs - bound;
        points[3 * i + 2] = (f32::cast_from(cz) + uniform(seed, step, idx, 3)) * cs - bound;
    }
}

/// The refresh's constants.
#[derive(CubeType, CubeLaunch, Clone, Copy)]
pub struct Refresh {
    first: u32,
    n: u32,
    decay: f32,
    dt: f32,
    /// 1: every cell is re-evaluated (warm-up).
    warm: u32,
    fraction: f32,
    seed: u32,
    step: u32,
    /// 1: `possible` holds a flag per cell, and cells without it stay empty.
    masked: u32,
}

/// Whether cell `idx` may hold anything: every cell, unless `masked` says `possible` has
/// a flag per cell (a one-element buffer otherwise, never read past).
#[cube]
fn may_hold(possible: &[u32], masked: u32, idx: usize) -> bool {
    let at = select(masked == 1, idx, 0usize);
    masked == 0 || possible[at] != 0
}

/// Decays cells `first..first + n` and raises the chosen ones (warm-up, occupied, or picked
/// at random) to the thickness `sigma * dt` seen at their point; a cell that may hold
/// nothing keeps no thickness.
#[cube(launch_unchecked)]
fn update_cells(thickness: &mut [f32], occ: &[u32], sigma: &[f32], possible: &[u32], u: Refresh) {
    let i = ABSOLUTE_POS;
    if i < u.n as usize {
        let idx = (u.first + i as u32) as usize;
        let pick = uniform(u.seed, u.step, idx as u32, 0) < u.fraction;
        let chosen = u.warm == 1 || occ[idx] != 0 || pick;
        let decayed = thickness[idx] * u.decay;
        let value = select(chosen, f32::max(decayed, sigma[i] * u.dt), decayed);
        thickness[idx] = select(may_hold(possible, u.masked, idx), value, 0.0);
    }
}

/// Partial sums of the thickness over blocks of `block` cells.
#[cube(launch_unchecked)]
fn sum_blocks(values: &[f32], sums: &mut [f32], n: u32, block: u32) {
    let b = ABSOLUTE_POS;
    let first = b * block as usize;
    if first < n as usize {
        let last = usize::min(first + block as usize, n as usize);
        let mut acc = 0.0f32;
        for i in first..last {
            acc += values[i];
        }
        sums[b] = acc;
    }
}

/// `occ = thickness >= min(threshold, mean)`, the mean from `total[0]`, the sum of the
/// thickness, where the cell may hold anything.
#[cube(launch_unchecked)]
fn occupied_cells(
    thickness: &[f32],
    total: &[f32],
    possible: &[u32],
    occ: &mut [u32],
    n: u32,
    threshold: f32,
    masked: u32,
) {
    let i = ABSOLUTE_POS;
    if i < n as usize {
        let cut = f32::min(threshold, total[0] / f32::cast_from(n));
        let on = thickness[i] >= cut && may_hold(possible, masked, i);
        occ[i] = select(on, 1u32, 0u32);
    }
}

/// `flags[at + b]`: 1 where cube `b` (of `blocks^3`, each `block^3` cells of a `res^3`
/// grid) holds an occupied cell (`flags[..cells]`).
#[cube(launch_unchecked)]
fn occupied_blocks(flags: &mut [u32], res: u32, blocks: u32, block: u32, at: u32) {
    let b = ABSOLUTE_POS as u32;
    if b < blocks * blocks * blocks {
        let (bx, by, bz) = (b % blocks, (b / blocks) % blocks, b / (blocks * blocks));
        let mut any = 0u32;
        for z in bz * block..(bz + 1) * block {
            for y in by * block..(by + 1) * block {
                for x in bx * block..(bx + 1) * block {
                    any |= flags[(x + res * (y + res * z)) as usize];
                }
            }
        }
        flags[(at + b) as usize] = any;
    }
}

/// The grid's state on the device.
pub struct GpuOccupancy {
    pub thickness: Handle,
    /// 1 per occupied cell, x fastest, then 1 per block holding one (what the marcher
    /// reads, `march::grid_flags`).
    pub occupied: Handle,
    /// 1 per cell that may hold anything (`OccupancyGrid::possible`), when `masked`; one
    /// unread value otherwise.
    possible: Handle,
    masked: bool,
    pub resolution: usize,
    pub bound: f32,
}

impl GpuOccupancy {
    /// Uploads a host grid's state.
    pub fn new(gpu: &Gpu, grid: &OccupancyGrid) -> Self {
        let bits = |flags: &[bool]| -> Vec<u32> { flags.iter().map(|&o| u32::from(o)).collect() };
        let possible = grid.possible.as_deref().map_or(vec![1], bits);
        GpuOccupancy {
            thickness: gpu.upload(&grid.thickness),
            occupied: gpu.upload_u32(&grid_flags(grid)),
            possible: gpu.upload_u32(&possible),
            masked: grid.possible.is_some(),
            resolution: grid.resolution,
            bound: grid.bound,
        }
    }

    pub fn cells(&self) -> usize {
        self.resolution.pow(3)
    }

    fn possible_len(&self) -> usize {
        if self.masked {
            self.cells()
        } else {
            1
        }
    }

    /// One refresh at training step `step` (`OccupancyGrid::update`'s rule): `density`
    /// evaluates `n` device points (`n x 3`) into a device buffer of `n` densities.
    pub fn update(
        &self,
        gpu: &Gpu,
        config: &OccupancyConfig,
        step: u64,
        seed: u64,
        dt: f32,
        density: &dyn Fn(&Handle, usize) -> Handle,
    ) {
        let cells = self.cells();
        let (res, bound) = (self.resolution as u32, self.bound);
        // The counters are 32-bit: fold the 64-bit seed and step in.
        let seed32 = (seed ^ (seed >> 32)) as u32;
        let step32 = (step ^ (step >> 32)) as u32;
        for first in (0..cells).step_by(CHUNK) {
            let n = CHUNK.min(cells - first);
            let points = gpu.floats(3 * n);
            // SAFETY: `points` holds `3n` floats and the kernel writes rows `i < n`.
            unsafe {
                let (c, d) = grid(n, GROUP);
                cell_points::launch_unchecked(
                    &gpu.client,
                    c,
                    d,
                    BufferArg::from_raw_parts(points.clone(), 3 * n),
                    first as u32,
                    n as u32,
                    res,
                    bound,
                    seed32,
                    step32,
                );
            }
            let sigma = density(&points, n);
            let update = RefreshLaunch::new(
                first as u32,
                n as u32,
                config.decay,
                dt,
                u32::from(step < config.warmup_steps),
                config.recheck_fraction(step),
                seed32,
                step32,
                u32::from(self.masked),
            );
            // SAFETY: the grid's buffers hold `cells` values and `sigma` `n`; the kernel
            // touches cells `first..first + n` only, and reads `possible` past its first
            // value only when it is masked (a value per cell).
            unsafe {
                let (c, d) = grid(n, GROUP);
                update_cells::launch_unchecked(
                    &gpu.client,
                    c,
                    d,
                    BufferArg::from_raw_parts(self.thickness.clone(), cells),
                    BufferArg::from_raw_parts(self.occupied.clone(), cells),
                    BufferArg::from_raw_parts(sigma.clone(), n),
                    BufferArg::from_raw_parts(self.possible.clone(), self.possible_len()),
                    update,
                );
            }
        }
        let blocks = cells.div_ceil(SUM_BLOCK);
        let sums = gpu.floats(blocks);
        let total = gpu.floats(1);
        // SAFETY: `sums` holds one float per block and `total` one; the kernels
        // bounds-check against `cells` and `blocks`.
        unsafe {
            // Sums of `block` values of `n` a thread, into `out` (`n / block` floats).
            let sum = |values: &Handle, out: &Handle, n: usize, block: usize| {
                let (c, d) = grid(n.div_ceil(block), GROUP);
                sum_blocks::launch_unchecked(
                    &gpu.client,
                    c,
                    d,
                    BufferArg::from_raw_parts(values.clone(), n),
                    BufferArg::from_raw_parts(out.clone(), n.div_ceil(block)),
                    n as u32,
                    block as u32,
                );
            };
            sum(&self.thickness, &sums, cells, SUM_BLOCK);
            // The block sums added once, by one thread, in order: every cell's thread
            // adding them itself would load cells x blocks values.
            sum(&sums, &total, blocks, blocks);
            let (c, d) = grid(cells, GROUP);
            occupied_cells::launch_unchecked(
                &gpu.client,
                c,
                d,
                BufferArg::from_raw_parts(self.thickness.clone(), cells),
                BufferArg::from_raw_parts(total.clone(), 1),
                BufferArg::from_raw_parts(self.possible.clone(), self.possible_len()),
                BufferArg::from_raw_parts(self.occupied.clone(), cells),
                cells as u32,
                config.threshold,
                u32::from(self.masked),
            );
        }
        // Blocks, then regions, whose flags follow the cells' (`march::grid_flags`).
        let (blocks, regions) = (
            blocks_per_axis(self.resolution),
            regions_per_axis(self.resolution),
        );
        let flags = cells + blocks.pow(3) + regions.pow(3);
        for (per_axis, size, at) in [
            (blocks, BLOCK, cells),
            (regions, REGION, cells + blocks.pow(3)),
        ] {
            if per_axis == 0 {
                continue;
            }
            // SAFETY: `occupied` holds the `cells` flags and the blocks' and regions' after
            // them; the kernel reads cells of its cube only and bounds-checks the cube index.
            unsafe {
                let (c, d) = grid(per_axis.pow(3), GROUP);
                occupied_blocks::launch_unchecked(
                    &gpu.client,
                    c,
                    d,
                    BufferArg::from_raw_parts(self.occupied.clone(), flags),
                    self.resolution as u32,
                    per_axis as u32,
                    size as u32,
                    at as u32,
                );
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two refreshes of a 48^3 grid, with blocks and regions (more than one chunk is not
    /// needed for the rule; the chunk loop is exercised by `CHUNK`-independent indexing),
    /// with a density known in
    /// closed form: every cell decays, the chosen ones (all during warm-up; then the
    /// occupied ones and about `recheck_fraction` of the rest: a quarter while the field is
    /// young, then `update_fraction`) rise to `sigma * dt` at a point
    /// inside the cell, and occupancy follows `min(threshold, mean)`.
    #[test]
    fn refresh_follows_the_cpu_rule() {
        let Some(gpu) = super::super::device::test_gpu() else {
            return;
        };
        let (res, bound, dt) = (48, 1.5, 0.01);
        let config = OccupancyConfig {
            resolution: res,
            warmup_steps: 10,
            ..OccupancyConfig::default()
        };
        // A ball of density 100 of radius 1 around the origin, density 0.1 outside.
        let ball = |x: f32, y: f32, z: f32| {
            if x * x + y * y + z * z < 1.0 {
                100.0
            } else {
                0.1
            }
        };
        let host = OccupancyGrid::new(res, bound);
        let g = GpuOccupancy::new(&gpu, &host);
        let seen = std::cell::RefCell::new(Vec::new());
        let density = |points: &Handle, n: usize| {
            let p = gpu.read(points, 3 * n).expect("read");
            let sigma: Vec<f32> = p.chunks_exact(3).map(|q| ball(q[0], q[1], q[2])).collect();
            seen.borrow_mut().extend_from_slice(&p);
            gpu.upload(&sigma)
        };
        let cs = 2.0 * bound / res as f32;
        let mut expected = vec![0.0f32; res * res * res];
        let mut occupied = vec![true; res * res * res];
        for step in [5u64, 20, 50] {
            seen.borrow_mut().clear();
            g.update(&gpu, &config, step, 7, dt, &density);
            let points = seen.borrow().clone();
            let thickness = gpu.read(&g.thickness, expected.len()).expect("read");
            let mut picked_empty = (0, 0);
            for (i, e) in expected.iter_mut().enumerate() {
                let q = &points[3 * i..3 * i + 3];
                let c = [i % res, (i / res) % res, i / (res * res)];
                for a in 0..3 {
                    // Each point lies in its own cell.
                    let lo = c[a] as f32 * cs - bound;
                    assert!(
                        q[a] >= lo - 1e-5 && q[a] <= lo + cs + 1e-5,
                        "cell {i}: {q:?}"
                    );
                }
                let decayed = *e * config.decay;
                let fresh = decayed.max(ball(q[0], q[1], q[2]) * dt);
                let got = thickness[i];
                let warm = step < config.warmup_steps;
                if warm || occupied[i] {
                    assert!(
                        (got - fresh).abs() <= 1e-6 * (1.0 + fresh),
                        "cell {i}: {got} vs {fresh}"
                    );
                } else {
                    // Empty cells: re-evaluated only when picked at random.
                    assert!((got - decayed).abs() <= 1e-6 || (got - fresh).abs() <= 1e-6);
                    picked_empty.1 += 1;
                    if (got - decayed).abs() > 1e-6 {
                        picked_empty.0 += 1;
                    }
                }
                *e = got;
            }
            if step >= config.warmup_steps {
                let share = picked_empty.0 as f64 / picked_empty.1 as f64;
                assert!(
                    (share - f64::from(config.recheck_fraction(step))).abs()
                        < 0.2 * f64::from(config.recheck_fraction(step)),
                    "{share} of the empty cells picked"
                );
            }
            let mean = expected.iter().map(|&v| v as f64).sum::<f64>() / expected.len() as f64;
            let cut = config.threshold.min(mean as f32);
            let bits = gpu.read_u32(&g.occupied, expected.len()).expect("read");
            for (i, (&b, &v)) in bits.iter().zip(&expected).enumerate() {
                assert_eq!(b == 1, v >= cut, "cell {i}: thickness {v}, cut {cut}");
                occupied[i] = b == 1;
            }
            // The ball (about 15% of the box) is occupied and most of the rest is not.
            let share = bits.iter().filter(|&&b| b == 1).count() as f64 / bits.len() as f64;
            assert!((0.1..0.35).contains(&share), "{share} occupied");
            // The blocks' and regions' flags after the cells' are the host grid's for these
            // cells.
            let host = OccupancyGrid::from_parts(res, g.bound, expected.clone(), occupied.clone());
            let want = grid_flags(&host);
            assert!(!host.occupied_regions().is_empty(), "the grid has regions");
            let flags = gpu.read_u32(&g.occupied, want.len()).expect("read");
            assert_eq!(flags, want);
        }
    }

    /// Few-view training's mask on the device, as `OccupancyGrid::refresh` applies it on
    /// the host: a cell that may hold nothing keeps no thickness and is never occupied,
    /// even when nothing else is (the cut falls to a mean of zero), and the other cells
    /// follow the rule as before.
    #[test]
    fn cells_that_may_hold_nothing_stay_empty() {
        let Some(gpu) = super::super::device::test_gpu() else {
            return;
        };
        let (res, bound, dt) = (8, 1.5, 0.01);
        let config = OccupancyConfig {
            resolution: res,
            warmup_steps: 10,
            ..OccupancyConfig::default()
        };
        let cells = res * res * res;
        let density = |_: &Handle, n: usize| gpu.upload(&vec![100.0; n]);
        for every_third in [true, false] {
            let mut host = OccupancyGrid::new(res, bound);
            host.possible = Some((0..cells).map(|i| every_third && i % 3 == 0).collect());
            let g = GpuOccupancy::new(&gpu, &host);
            g.update(&gpu, &config, 5, 7, dt, &density);
            let thickness = gpu.read(&g.thickness, cells).expect("read");
            let bits = gpu.read_u32(&g.occupied, cells).expect("read");
            for i in 0..cells {
                let may = every_third && i % 3 == 0;
                let want = if may { 100.0 * dt } else { 0.0 };
                assert!(
                    (thickness[i] - want).abs() < 1e-6,
                    "cell {i}: {}",
                    thickness[i]
                );
                assert_eq!(bits[i] == 1, may, "cell {i}");
            }
        }
    }
}
