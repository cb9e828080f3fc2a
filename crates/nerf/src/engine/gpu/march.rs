//! Occupancy-grid marching on the GPU with sample compaction: `render::march`'s lattice
//! (see `render::occupancy` for the grid and the skipping rule, `render::contraction` for
//! unbounded scenes), one thread per ray, in three passes:
//!
//! 1. count: each ray marches and counts its samples;
//! 2. scan: an exclusive prefix sum of the counts gives every ray its first slot (a
//!    workgroup per block of [`SCAN_BLOCK`] rays, one workgroup over the block totals, then
//!    the block offsets added; rays with samples are counted on the way), and one thread
//!    finds where the step's sample budget is reached;
//! 3. write: the kept rays march again and write their samples (depth, step length,
//!    field-space position, unit view direction) at their slots, packed with no gaps.
//!
//! The host reads back four numbers (rays kept, samples, whether the budget cut them, rays
//! with samples) and never sees the samples.

use cubecl::prelude::*;
use cubecl::server::Handle;
use rayon::iter::{IntoParallelIterator, ParallelIterator};

use super::device::Gpu;
use super::launch::{grid, PendingRead};
use super::volume::GpuSamples;
use crate::error::{NerfError, Result};
use crate::math::{length, scale};
use crate::render::contraction::FAR_N;
use crate::render::march::{Marcher, MIN_TRANSMITTANCE};
use crate::render::occupancy::{blocks_per_axis, regions_per_axis, OccupancyGrid, BLOCK, REGION};
use crate::stage::RayBatch;

const GROUP: u32 = 64;

/// The marcher's constants, in the order the kernels read them.
#[derive(CubeType, CubeLaunch, Clone, Copy)]
pub struct MarchParams {
    /// Occupancy cells per axis, the box's half-extent and the cell size.
    res: u32,
    bound: f32,
    cell: f32,
    /// Step length (metric; in contracted space when contracting).
    dt: f32,
    max_samples: u32,
    /// 1: contract space outside the cube of half-extent `inner`.
    contract: u32,
    inner: f32,
    /// `contraction::FAR_N`: rays end past this many inner half-extents.
    far_n: f32,
    /// Blocks per axis (0: none) of `BLOCK^3` cells, whose flags (1 where any of its cells
    /// is occupied) follow the cells' in the grid's buffer: an empty block is crossed in
    /// one skip, as `OccupancyGrid::march` does.
    blocks: u32,
    /// `log2(BLOCK)`: a cell's block is its index shifted right by this.
    block_shift: u32,
    /// Regions per axis (0: none) of `REGION^3` cells, whose flags follow the blocks'.
    regions: u32,
    region_shift: u32,
}

#[cube]
fn cell_of(x: f32, bound: f32, cell: f32, res: u32) -> u32 {
    let c = u32::cast_from(f32::max((x + bound) * (1.0 / cell), 0.0));
    u32::min(c, res - 1)
}

#[cube]
fn is_occupied(occ: &[u32], x: f32, y: f32, z: f32, bound: f32, cell: f32, res: u32) -> bool {
    let cx = cell_of(x, bound, cell, res);
    let cy = cell_of(y, bound, cell, res);
    let cz = cell_of(z, bound, cell, res);
    occ[(cx + res * (cy + res * cz)) as usize] != 0
}

/// `max(|p|) / inner`: where a point sits relative to the inner cube.
#[cube]
fn norm_inf(x: f32, y: f32, z: f32, inner: f32) -> f32 {
    f32::max(f32::max(f32::abs(x), f32::abs(y)), f32::abs(z)) / inner
}

/// Contraction's scale of a point at `n = norm_inf` (1 inside the inner cube).
#[cube]
fn contract_scale(n: f32) -> f32 {
    select(n <= 1.0, 1.0, (2.0 - 1.0 / n) / n)
}

/// Marches ray `r` from depth `t0` to `t_end`, taking at most `max_samples` samples; with
/// `write`, stores them from slot `first`, and with `resume`, stores in `next[r]` the depth
/// at which a later march of the same ray goes on. Returns the samples taken.
#[cube]
#[allow(clippy::too_many_arguments)]
fn march_ray(
    r: usize,
    origins: &[f32],
    dirs: &[f32],
    views: &[f32],
    t0: f32,
    t_end: f32,
    max_samples: u32,
    occ: &[u32],
    p: MarchParams,
    first: usize,
    t_out: &mut [f32],
    dt_out: &mut [f32],
    pos_out: &mut [f32],
    dir_out: &mut [f32],
    next: &mut [f32],
    #[comptime] write: bool,
    #[comptime] resume: bool,
) -> u32 {
    let ox = origins[3 * r];
    let oy = origins[3 * r + 1];
    let oz = origins[3 * r + 2];
    let dx = dirs[3 * r];
    let dy = dirs[3 * r + 1];
    let dz = dirs[3 * r + 2];
    let res = p.res;
    let bound = p.bound;
    let cell = p.cell;
    let dt = p.dt;
    let contract = p.contract;
    let inner = p.inner;
    let far_n = p.far_n;
    let mut t = t0;
    let mut added = 0u32;
    let mut running = t < t_end && max_samples > 0;
    while running {
        let x = ox + t * dx;
        let y = oy + t * dy;
        let z = oz + t * dz;
        let mut take = false;
        let mut step = dt;
        let mut sx = x;
        let mut sy = y;
        let mut sz = z;
        if contract == 1 {
            let n = norm_inf(x, y, z, inner);
            if n > far_n {
                // Past the contracted far shell: the ray is done.
                running = false;
            } else {
                step = dt * f32::max(n * n, 1.0);
                let s = contract_scale(n);
                sx = x * s;
                sy = y * s;
                sz = z * s;
                take = is_occupied(occ, sx, sy, sz, bound, cell, res);
            }
        } else {
            let cx = cell_of(x, bound, cell, res);
            let cy = cell_of(y, bound, cell, res);
            let cz = cell_of(z, bound, cell, res);
            take = occ[(cx + res * (cy + res * cz)) as usize] != 0;
            if !take {
                // Whole steps past the far wall of this empty cell, or of its block if
                // that is empty too: walls found by shifts (0 for a cell), where a
                // division by a launch value costs a GPU tens of instructions a step.
                let mut shift = 0u32;
                if p.regions > 0 {
                    let (s, nr) = (p.region_shift, p.regions);
                    let ri = (cx >> s) + nr * ((cy >> s) + nr * (cz >> s));
                    let at = res * res * res + p.blocks * p.blocks * p.blocks + ri;
                    if occ[at as usize] == 0 {
                        shift = s;
                    }
                }
                if p.blocks > 0 && shift == 0 {
                    let (s, nb) = (p.block_shift, p.blocks);
                    let bi = (cx >> s) + nb * ((cy >> s) + nb * (cz >> s));
                    if occ[(res * res * res + bi) as usize] == 0 {
                        shift = s;
                    }
                }
                let k = 1u32 << shift;
                let mut exit = 3.4e38f32; // "no wall": larger than any depth
                if dx != 0.0 {
                    let low = (cx >> shift) << shift;
                    let wall = f32::cast_from(select(dx > 0.0, low + k, low)) * cell - bound;
                    exit = f32::min(exit, (wall - x) / dx);
                }
                if dy != 0.0 {
                    let low = (cy >> shift) << shift;
                    let wall = f32::cast_from(select(dy > 0.0, low + k, low)) * cell - bound;
                    exit = f32::min(exit, (wall - y) / dy);
                }
                if dz != 0.0 {
                    let low = (cz >> shift) << shift;
                    let wall = f32::cast_from(select(dz > 0.0, low + k, low)) * cell - bound;
                    exit = f32::min(exit, (wall - z) / dz);
                }
                step = (f32::floor(f32::max(exit, 0.0) / dt) + 1.0) * dt;
            }
        }
        if running {
            if take {
                if write {
                    let k = first + added as usize;
                    t_out[k] = t;
                    dt_out[k] = step;
                    pos_out[3 * k] = sx;
                    pos_out[3 * k + 1] = sy;
                    pos_out[3 * k + 2] = sz;
                    dir_out[3 * k] = views[3 * r];
                    dir_out[3 * k + 1] = views[3 * r + 1];
                    dir_out[3 * k + 2] = views[3 * r + 2];
                }
                added += 1;
            }
            t += step;
            running = t < t_end && added < max_samples;
        }
    }
    if resume {
        next[r] = t;
    }
    added
}

/// Count (`write` false: `counts[r]`) or write (`write` true: the samples of rays
/// `r < rays` from `offsets[r]`) pass.
#[cube(launch_unchecked)]
#[allow(clippy::too_many_arguments)]
fn march_rays(
    origins: &[f32],
    dirs: &[f32],
    views: &[f32],
    start: &[f32],
    end: &[f32],
    occ: &[u32],
    offsets: &[u32],
    counts: &mut [u32],
    t_out: &mut [f32],
    dt_out: &mut [f32],
    pos_out: &mut [f32],
    dir_out: &mut [f32],
    next: &mut [f32],
    rays: u32,
    p: MarchParams,
    #[comptime] write: bool,
) {
    let r = ABSOLUTE_POS;
    if r < rays as usize {
        let mut first = 0usize;
        if write {
            first = offsets[r] as usize;
        }
        let n = march_ray(
            r,
            origins,
            dirs,
            views,
            start[r],
            end[r],
            p.max_samples,
            occ,
            p,
            first,
            t_out,
            dt_out,
            pos_out,
            dir_out,
            next,
            write,
            false,
        );
        if !write {
            counts[r] = n;
        }
    }
}

/// A rendering round over rays `r < rays`: count (`write` false: `counts[r]`) or write
/// (`write` true: from slot `offsets[r]`, then the ray's resume depth in `next[r]` and its
/// running sample count in `taken[r]`) the ray's next samples, at most `per_ray`. A ray is
/// done once its transmittance (`state[STATE_WORDS r]`) falls below `min_trans`, its
/// samples reach the marcher's cap, or it leaves its span.
#[cube(launch_unchecked)]
#[allow(clippy::too_many_arguments)]
fn march_round(
    origins: &[f32],
    dirs: &[f32],
    views: &[f32],
    next: &mut [f32],
    end: &[f32],
    state: &[f32],
    taken: &mut [u32],
    occ: &[u32],
    offsets: &[u32],
    counts: &mut [u32],
    t_out: &mut [f32],
    dt_out: &mut [f32],
    pos_out: &mut [f32],
    dir_out: &mut [f32],
    rays: u32,
    per_ray: u32,
    min_trans: f32,
    p: MarchParams,
    #[comptime] write: bool,
) {
    let r = ABSOLUTE_POS;
    if r < rays as usize {
        let used = taken[r];
        let mut budget = 0u32;
        if state[STATE_WORDS * r] >= min_trans && used < p.max_samples {
            budget = u32::min(per_ray, p.max_samples - used);
        }
        let mut first = 0usize;
        if write {
            first = offsets[r] as usize;
        }
        let n = march_ray(
            r, origins, dirs, views, next[r], end[r], budget, occ, p, first, t_out, dt_out,
            pos_out, dir_out, next, write, write,
        );
        if write {
            taken[r] = used + n;
        } else {
            counts[r] = n;
        }
    }
}

/// Threads per workgroup of the scan; each takes `SCAN_ITEMS` consecutive counts.
const SCAN_THREADS: usize = 256;
const SCAN_ITEMS: usize = 4;
/// Hillis-Steele steps over `SCAN_THREADS` values.
const SCAN_STEPS: usize = 8;
/// Rays per block of the scan's first pass (one workgroup each).
pub const SCAN_BLOCK: usize = SCAN_THREADS * SCAN_ITEMS;

/// Inclusive prefix sums of the workgroup's `sums` and `alive` (one value per thread, `t`
/// this thread's), in place: log2 steps, each thread adding the value `d` before its own.
#[cube]
fn scan_workgroup(sums: &mut [u32], alive: &mut [u32], t: usize) {
    let mut d = 1usize;
    #[unroll]
    for _ in 0..SCAN_STEPS {
        let mut add = 0u32;
        let mut add_alive = 0u32;
        if t >= d {
            add = sums[t - d];
            add_alive = alive[t - d];
        }
        sync_cube();
        sums[t] += add;
        alive[t] += add_alive;
        sync_cube();
        d *= 2;
    }
}

/// Scan, pass 1: per block of `SCAN_BLOCK` counts (one workgroup), the exclusive prefix
/// sums within the block (into `offsets`), the block's total and its rays with samples.
#[cube(launch_unchecked)]
fn scan_blocks(counts: &[u32], offsets: &mut [u32], totals: &mut [u32], live: &mut [u32], n: u32) {
    let mut sums = Shared::<[u32]>::new_slice(SCAN_THREADS);
    let mut alive = Shared::<[u32]>::new_slice(SCAN_THREADS);
    let t = UNIT_POS as usize;
    let block = CUBE_POS;
    let first = block * SCAN_BLOCK + t * SCAN_ITEMS;
    let mut sum = 0u32;
    let mut lives = 0u32;
    #[unroll]
    for k in 0..SCAN_ITEMS {
        let i = first + k;
        if i < n as usize {
            let c = counts[i];
            sum += c;
            lives += select(c > 0, 1u32, 0u32);
        }
    }
    sums[t] = sum;
    alive[t] = lives;
    sync_cube();
    scan_workgroup(&mut sums, &mut alive, t);
    let mut run = sums[t] - sum;
    #[unroll]
    for k in 0..SCAN_ITEMS {
        let i = first + k;
        if i < n as usize {
            offsets[i] = run;
            run += counts[i];
        }
    }
    if t == SCAN_THREADS - 1 {
        totals[block] = sums[t];
        live[block] = alive[t];
    }
}

/// Scan, pass 2 (one workgroup): the exclusive prefix sums of the `blocks` block totals,
/// in place, with the grand total after them; the same slot of `live` gets the rays with
/// samples.
#[cube(launch_unchecked)]
#[allow(clippy::manual_div_ceil)] // kernels have no `div_ceil`
fn scan_totals(totals: &mut [u32], live: &mut [u32], blocks: u32) {
    let mut sums = Shared::<[u32]>::new_slice(SCAN_THREADS);
    let mut alive = Shared::<[u32]>::new_slice(SCAN_THREADS);
    let t = UNIT_POS as usize;
    let blocks = blocks as usize;
    let per = (blocks + SCAN_THREADS - 1) / SCAN_THREADS;
    let first = usize::min(t * per, blocks);
    let last = usize::min(first + per, blocks);
    let mut sum = 0u32;
    let mut lives = 0u32;
    for b in first..last {
        sum += totals[b];
        lives += live[b];
    }
    sums[t] = sum;
    alive[t] = lives;
    sync_cube();
    scan_workgroup(&mut sums, &mut alive, t);
    let mut run = sums[t] - sum;
    for b in first..last {
        let v = totals[b];
        totals[b] = run;
        run += v;
    }
    if t == SCAN_THREADS - 1 {
        totals[blocks] = sums[t];
        live[blocks] = alive[t];
    }
}

/// Scan, pass 3: each ray's block offset added.
#[cube(launch_unchecked)]
fn scan_add(offsets: &mut [u32], totals: &[u32], n: u32) {
    let i = ABSOLUTE_POS;
    if i < n as usize {
        offsets[i] += totals[i / SCAN_BLOCK];
    }
}

/// The cut (one thread): the rays a step keeps, as the CPU engine keeps them: up to and
/// including the first ray at which the running sample count reaches `budget` (to the end
/// of its block of `block` rays), or `max_rays` rays. Writes `[rays kept, their samples, 1 if the cut was found, rays with
/// samples]`; without a cut (too few rays marched) `[n, all samples, 0, ...]`.
#[cube(launch_unchecked)]
fn find_cut(
    offsets: &[u32],
    counts: &[u32],
    live: &[u32],
    cut: &mut [u32],
    n: u32,
    budget: u32,
    max_rays: u32,
    block: u32,
) {
    if ABSOLUTE_POS == 0 {
        // The inclusive sums grow with the ray index: the first one >= budget by bisection.
        let mut lo = 0u32;
        let mut hi = n;
        while lo < hi {
            let mid = (lo + hi) / 2;
            if offsets[mid as usize] + counts[mid as usize] >= budget {
                hi = mid;
            } else {
                lo = mid + 1;
            }
        }
        // `lo` is that ray (n if none), its block's end the cut (unless too few rays were
        // marched to end it); the ray cap may come first.
        let mut kept = n;
        let mut found = 0u32;
        let whole = (lo + block) / block * block;
        if whole <= n {
            kept = whole;
            found = 1;
        }
        if max_rays <= kept {
            kept = max_rays;
            found = 1;
        }
        cut[0] = kept;
        cut[1] = 0u32;
        if kept > 0 {
            cut[1] = offsets[(kept - 1) as usize] + counts[(kept - 1) as usize];
        }
        cut[2] = found;
        cut[3] = live[(n as usize - 1) / SCAN_BLOCK + 1];
    }
}

/// Rays on the device, ready to march: unit directions, unit view directions, and the span
/// each marches over (its first lattice depth, jittered, to its exit; empty when it
/// misses the box).
pub struct GpuRays {
    pub(super) origins: Handle,
    pub(super) dirs: Handle,
    pub(super) views: Handle,
    pub(super) start: Handle,
    pub(super) end: Handle,
    pub len: usize,
}

impl GpuRays {
    /// Rays `rays` with their jitters (`[0, 1)`, one per ray), as `Marcher::pack_ray`
    /// starts them.
    pub fn new(
        gpu: &Gpu,
        marcher: &Marcher,
        grid: &OccupancyGrid,
        rays: &RayBatch,
        jitter: &[f32],
    ) -> Self {
        let n = rays.len();
        // Per ray: unit direction, unit view direction, span; in parallel (a frame is a
        // million rays, made while the device waits).
        let per_ray: Vec<([f32; 3], [f32; 3], [f32; 2])> = (0..n)
            .into_par_iter()
            .map(|r| {
                let (o, dir) = (rays.origins[r], rays.dirs[r]);
                let norm = length(dir);
                let d = scale(dir, 1.0 / norm);
                let view = scale(rays.view_dirs[r], 1.0 / length(rays.view_dirs[r]));
                let span = match marcher.span(grid, o, d, norm) {
                    Some((t0, t1)) => [t0 + jitter[r] * marcher.dt, t1],
                    None => [0.0, 0.0],
                };
                (d, view, span)
            })
            .collect();
        let dirs: Vec<f32> = per_ray.iter().flat_map(|p| p.0).collect();
        let views: Vec<f32> = per_ray.iter().flat_map(|p| p.1).collect();
        let start: Vec<f32> = per_ray.iter().map(|p| p.2[0]).collect();
        let end: Vec<f32> = per_ray.iter().map(|p| p.2[1]).collect();
        GpuRays {
            origins: gpu.upload(rays.origins.as_flattened()),
            dirs: gpu.upload(&dirs),
            views: gpu.upload(&views),
            start: gpu.upload(&start),
            end: gpu.upload(&end),
            len: n,
        }
    }
}

/// Floats of a ray's running result while rendering: transmittance, rgb, depth, opacity.
pub const STATE_WORDS: usize = 6;

/// Rays being rendered in rounds on the device: the rays (whose `start` is each ray's resume
/// depth, advanced by every round), each ray's running result (`STATE_WORDS` floats,
/// transmittance first) and its samples so far.
pub struct RoundState<'a> {
    pub rays: &'a GpuRays,
    pub state: Handle,
    pub taken: Handle,
}

/// Each of `rays` rays' running result before its first sample: transmittance 1, the
/// rest 0.
#[cube(launch_unchecked)]
#[allow(clippy::manual_is_multiple_of)] // kernels have no `is_multiple_of`
fn fresh_state(state: &mut [f32], rays: u32) {
    let i = ABSOLUTE_POS;
    if i < rays as usize * STATE_WORDS {
        state[i] = select(i % STATE_WORDS == 0, 1.0f32, 0.0f32);
    }
}

impl<'a> RoundState<'a> {
    /// Rays that have taken no samples yet.
    pub fn new(gpu: &Gpu, rays: &'a GpuRays) -> Self {
        let n = rays.len;
        let state = gpu.floats(STATE_WORDS * n.max(1));
        // SAFETY: `state` holds `STATE_WORDS` floats for each of the `n` rays.
        unsafe {
            let (c, d) = grid(STATE_WORDS * n, GROUP);
            fresh_state::launch_unchecked(
                &gpu.client,
                c,
                d,
                BufferArg::from_raw_parts(state.clone(), STATE_WORDS * n.max(1)),
                n as u32,
            );
        }
        RoundState {
            state,
            taken: gpu.zeros_u32(n),
            rays,
        }
    }
}

/// Where a step's sample budget cut its rays.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Cut {
    /// Rays kept (a prefix of the rays marched) and their samples.
    pub rays: usize,
    pub samples: usize,
    /// False when the rays marched ran out before the budget (or the ray cap) was reached.
    pub found: bool,
    /// Rays marched that have samples, kept or not (a ray without any is done).
    pub live: usize,
}

/// A [`Cut`] known on the host, or on its way back from the device.
pub enum PendingCut<'a> {
    Known(Cut),
    Reading(PendingRead<'a>),
}

impl PendingCut<'_> {
    /// The cut, once its four numbers are back.
    pub fn wait(self) -> Result<Cut> {
        match self {
            PendingCut::Known(cut) => Ok(cut),
            PendingCut::Reading(read) => {
                let v = read.wait()?;
                if v.len() < 4 {
                    return Err(NerfError::Device(format!(
                        "a marching cut read back {} of 4 numbers",
                        v.len()
                    )));
                }
                Ok(Cut {
                    rays: v[0] as usize,
                    samples: v[1] as usize,
                    found: v[2] == 1,
                    live: v[3] as usize,
                })
            }
        }
    }
}

/// A host grid's flags as the device marcher reads them: 1 per occupied cell (x fastest),
/// then 1 per block of `BLOCK^3` cells holding an occupied one, then 1 per region of
/// `REGION^3` cells.
pub fn grid_flags(grid: &OccupancyGrid) -> Vec<u32> {
    let flags = grid.occupied_cells().iter();
    let (blocks, regions) = (grid.occupied_blocks(), grid.occupied_regions());
    flags
        .chain(&blocks)
        .chain(&regions)
        .map(|&o| u32::from(o))
        .collect()
}

/// Rays marched and counted, with their slots: what [`GpuMarcher::write`] packs.
pub struct Counted {
    counts: Handle,
    offsets: Handle,
    /// Rays with samples: per scan block, then the total (`blocks + 1` slots).
    live: Handle,
}

/// The occupancy grid on the device and the marcher's constants.
pub struct GpuMarcher {
    /// The grid's flags: its cells', then its blocks' ([`grid_flags`]).
    occ: Handle,
    res: usize,
    /// Blocks per axis whose flags follow the cells', and regions whose flags follow the
    /// blocks' (0: none).
    blocks: usize,
    regions: usize,
    bound: f32,
    dt: f32,
    max_samples: usize,
    contract: Option<f32>,
}

impl GpuMarcher {
    /// A marcher over the device grid `occupied` (laid out as [`grid_flags`], read at every
    /// march, so refreshes in place are seen).
    pub fn new(marcher: &Marcher, occupied: Handle, res: usize, bound: f32) -> Self {
        GpuMarcher {
            occ: occupied,
            res,
            blocks: blocks_per_axis(res),
            regions: regions_per_axis(res),
            bound,
            dt: marcher.dt,
            max_samples: marcher.max_samples,
            contract: marcher.contract,
        }
    }

    /// A marcher over a copy of a host grid.
    pub fn with_grid(gpu: &Gpu, marcher: &Marcher, grid: &OccupancyGrid) -> Self {
        let flags = grid_flags(grid);
        let m = GpuMarcher::new(marcher, gpu.upload_u32(&flags), grid.resolution, grid.bound);
        // A grid without block or region flags (as tests make them) goes without.
        let (blocks, regions) = grid.skip_cubes_per_axis();
        GpuMarcher {
            blocks,
            regions,
            ..m
        }
    }

    fn params(&self) -> MarchParamsLaunch {
        MarchParamsLaunch::new(
            self.res as u32,
            self.bound,
            2.0 * self.bound / self.res as f32,
            self.dt,
            self.max_samples as u32,
            u32::from(self.contract.is_some()),
            self.contract.unwrap_or(1.0),
            FAR_N,
            self.blocks as u32,
            BLOCK.trailing_zeros(),
            self.regions as u32,
            REGION.trailing_zeros(),
        )
    }

    /// Passes 1 and 2: counts every ray's samples and scans them into slots.
    pub fn count(&self, gpu: &Gpu, rays: &GpuRays) -> Counted {
        let n = rays.len;
        let counts = gpu.zeros_u32(n);
        if n > 0 {
            let none = gpu.floats(1);
            let unused = gpu.upload_u32(&[0]);
            // SAFETY: every buffer holds the length given with it (rays: `n` or `3n` floats,
            // the grid `res^3` cells); the count pass writes only `counts[r]` for `r < n`
            // (its sample outputs and `next` are never touched).
            unsafe {
                let (c, d) = grid(n, GROUP);
                march_rays::launch_unchecked(
                    &gpu.client,
                    c,
                    d,
                    BufferArg::from_raw_parts(rays.origins.clone(), 3 * n),
                    BufferArg::from_raw_parts(rays.dirs.clone(), 3 * n),
                    BufferArg::from_raw_parts(rays.views.clone(), 3 * n),
                    BufferArg::from_raw_parts(rays.start.clone(), n),
                    BufferArg::from_raw_parts(rays.end.clone(), n),
                    BufferArg::from_raw_parts(self.occ.clone(), self.cells()),
                    BufferArg::from_raw_parts(unused.clone(), 1),
                    BufferArg::from_raw_parts(counts.clone(), n),
                    BufferArg::from_raw_parts(none.clone(), 1),
                    BufferArg::from_raw_parts(none.clone(), 1),
                    BufferArg::from_raw_parts(none.clone(), 1),
                    BufferArg::from_raw_parts(none.clone(), 1),
                    BufferArg::from_raw_parts(none.clone(), 1),
                    n as u32,
                    self.params(),
                    false,
                );
            }
        }
        scan(gpu, counts, n)
    }

    /// The grid buffer's flags: cells, blocks and regions.
    fn cells(&self) -> usize {
        self.res.pow(3) + self.blocks.pow(3) + self.regions.pow(3)
    }

    /// Where the budget of `budget` samples (or `max_rays` rays) cuts `n` counted rays;
    /// reads back four numbers.
    pub fn cut(
        &self,
        gpu: &Gpu,
        counted: &Counted,
        n: usize,
        budget: usize,
        max_rays: usize,
    ) -> Result<Cut> {
        self.cut_later(gpu, counted, n, budget, max_rays).wait()
    }

    /// [`GpuMarcher::cut`] at the end of a block of `block` rays: the one whose ray
    /// reaches the budget (as the CPU engine keeps its photo rays when patches from
    /// unseen poses follow them).
    pub fn cut_in_blocks(
        &self,
        gpu: &Gpu,
        counted: &Counted,
        n: usize,
        (budget, max_rays): (usize, usize),
        block: usize,
    ) -> Result<Cut> {
        self.cut_blocks_later(gpu, counted, n, (budget, max_rays), block)
            .wait()
    }

    /// [`GpuMarcher::cut`] on its way back: the cut is found and its copy sent to the
    /// device now, and the host may queue other work before it waits for the numbers.
    pub fn cut_later<'g>(
        &self,
        gpu: &'g Gpu,
        counted: &Counted,
        n: usize,
        budget: usize,
        max_rays: usize,
    ) -> PendingCut<'g> {
        self.cut_blocks_later(gpu, counted, n, (budget, max_rays), 1)
    }

    fn cut_blocks_later<'g>(
        &self,
        gpu: &'g Gpu,
        counted: &Counted,
        n: usize,
        (budget, max_rays): (usize, usize),
        block: usize,
    ) -> PendingCut<'g> {
        if n == 0 {
            return PendingCut::Known(Cut {
                rays: 0,
                samples: 0,
                found: max_rays == 0,
                live: 0,
            });
        }
        let cut = gpu.zeros_u32(4);
        let blocks = n.div_ceil(SCAN_BLOCK);
        // SAFETY: `offsets` and `counts` hold `n` values, `live` `blocks + 1`; `cut` four.
        unsafe {
            let (c, d) = grid(1, 1);
            find_cut::launch_unchecked(
                &gpu.client,
                c,
                d,
                BufferArg::from_raw_parts(counted.offsets.clone(), n),
                BufferArg::from_raw_parts(counted.counts.clone(), n),
                BufferArg::from_raw_parts(counted.live.clone(), blocks + 1),
                BufferArg::from_raw_parts(cut.clone(), 4),
                n as u32,
                budget.min(u32::MAX as usize) as u32,
                max_rays.min(u32::MAX as usize) as u32,
                block.max(1) as u32,
            );
        }
        PendingCut::Reading(gpu.read_u32_later(&cut, 4))
    }

    /// Pass 3: the samples of the first `cut.rays` rays, packed: their CSR offsets, depths
    /// and step lengths, and the field-space positions and unit view directions.
    pub fn write(
        &self,
        gpu: &Gpu,
        rays: &GpuRays,
        counted: &Counted,
        cut: Cut,
    ) -> (GpuSamples, Handle, Handle) {
        let none = gpu.upload_u32(&[0]);
        let unused = gpu.floats(1);
        self.pack(gpu, rays.len, counted, cut, |out: &PackOutputs| {
            let k = cut.rays as u32;
            // SAFETY: as in `count`; the kept rays' slots end at `cut.samples`, the output
            // buffers' length.
            unsafe {
                let [t, dt, positions, dirs] = out.args();
                let (c, d) = grid(cut.rays, GROUP);
                march_rays::launch_unchecked(
                    &gpu.client,
                    c,
                    d,
                    BufferArg::from_raw_parts(rays.origins.clone(), 3 * rays.len),
                    BufferArg::from_raw_parts(rays.dirs.clone(), 3 * rays.len),
                    BufferArg::from_raw_parts(rays.views.clone(), 3 * rays.len),
                    BufferArg::from_raw_parts(rays.start.clone(), rays.len),
                    BufferArg::from_raw_parts(rays.end.clone(), rays.len),
                    BufferArg::from_raw_parts(self.occ.clone(), self.cells()),
                    BufferArg::from_raw_parts(counted.offsets.clone(), rays.len),
                    BufferArg::from_raw_parts(none.clone(), 1),
                    t,
                    dt,
                    positions,
                    dirs,
                    BufferArg::from_raw_parts(unused.clone(), 1),
                    k,
                    self.params(),
                    true,
                );
            }
        })
    }

    /// Allocates the packed outputs of `cut`, runs `march` (the write pass of the kept
    /// rays) into them, and adds the kept rays' CSR offsets.
    fn pack(
        &self,
        gpu: &Gpu,
        marched: usize,
        counted: &Counted,
        cut: Cut,
        march: impl FnOnce(&PackOutputs),
    ) -> (GpuSamples, Handle, Handle) {
        let (k, n) = (cut.rays, cut.samples);
        let (t, dt) = (gpu.floats(n), gpu.floats(n));
        let (positions, dirs) = (gpu.floats(3 * n), gpu.floats(3 * n));
        // CSR offsets of the kept rays: their slots, then the total.
        let offsets = gpu.zeros_u32(k + 1);
        if k > 0 {
            let out = PackOutputs {
                t: t.clone(),
                dt: dt.clone(),
                positions: positions.clone(),
                dirs: dirs.clone(),
                n,
            };
            march(&out);
            // SAFETY: `counted.offsets` holds a slot per marched ray, `offsets` `k + 1`.
            unsafe {
                let (c, d) = grid(k + 1, GROUP);
                csr_offsets::launch_unchecked(
                    &gpu.client,
                    c,
                    d,
                    BufferArg::from_raw_parts(counted.offsets.clone(), marched),
                    BufferArg::from_raw_parts(offsets.clone(), k + 1),
                    k as u32,
                    n as u32,
                );
            }
        }
        let samples = GpuSamples {
            offsets,
            t,
            dt,
            rays: k,
            len: n,
        };
        (samples, positions, dirs)
    }

    /// A rendering round, pass 1 and 2: every ray still worth marching (transmittance at
    /// least `min_trans` in `state`, under its sample cap `taken`) counts its next samples,
    /// at most `per_ray`, from where its last round stopped; then the counts are scanned.
    pub fn count_round(&self, gpu: &Gpu, round: &RoundState, per_ray: usize) -> Counted {
        let n = round.rays.len;
        let counts = gpu.zeros_u32(n);
        if n > 0 {
            // SAFETY: `count` plus the round's state (`taken`: `n`, `state`: `STATE_WORDS n`);
            // the count pass writes only `counts[r]` for `r < n`.
            unsafe {
                self.launch_round(
                    gpu,
                    round,
                    n,
                    per_ray,
                    &counts,
                    &counts,
                    &PackOutputs::none(gpu),
                    false,
                );
            }
        }
        scan(gpu, counts, n)
    }

    /// A rendering round, pass 3: the first `cut.rays` rays write their samples (packed as
    /// [`GpuMarcher::write`] packs them), advance their resume depths and add to `taken`.
    pub fn write_round(
        &self,
        gpu: &Gpu,
        round: &RoundState,
        counted: &Counted,
        cut: Cut,
        per_ray: usize,
    ) -> (GpuSamples, Handle, Handle) {
        let unused = gpu.upload_u32(&[0]);
        self.pack(gpu, round.rays.len, counted, cut, |out: &PackOutputs| {
            // SAFETY: as in `count_round`; the kept rays' slots end at `cut.samples`.
            unsafe {
                self.launch_round(
                    gpu,
                    round,
                    cut.rays,
                    per_ray,
                    &counted.offsets,
                    &unused,
                    out,
                    true,
                );
            }
        })
    }

    /// Launches `march_round` over the first `k` rays of `round`.
    ///
    /// # Safety
    /// `offsets` holds a slot per ray of `round` when `write`, `counts` one per ray when
    /// not, and the outputs hold every slot written.
    #[allow(clippy::too_many_arguments)]
    unsafe fn launch_round(
        &self,
        gpu: &Gpu,
        round: &RoundState,
        k: usize,
        per_ray: usize,
        offsets: &Handle,
        counts: &Handle,
        out: &PackOutputs,
        write: bool,
    ) {
        let (n, rays) = (round.rays.len, &round.rays);
        let (c, d) = grid(k, GROUP);
        // SAFETY: see the function's contract; the rays' buffers hold `n` or `3n` floats.
        unsafe {
            let [t, dt, positions, dirs] = out.args();
            march_round::launch_unchecked(
                &gpu.client,
                c,
                d,
                BufferArg::from_raw_parts(rays.origins.clone(), 3 * n),
                BufferArg::from_raw_parts(rays.dirs.clone(), 3 * n),
                BufferArg::from_raw_parts(rays.views.clone(), 3 * n),
                BufferArg::from_raw_parts(rays.start.clone(), n),
                BufferArg::from_raw_parts(rays.end.clone(), n),
                BufferArg::from_raw_parts(round.state.clone(), STATE_WORDS * n),
                BufferArg::from_raw_parts(round.taken.clone(), n),
                BufferArg::from_raw_parts(self.occ.clone(), self.cells()),
                BufferArg::from_raw_parts(offsets.clone(), if write { n } else { 1 }),
                BufferArg::from_raw_parts(counts.clone(), if write { 1 } else { n }),
                t,
                dt,
                positions,
                dirs,
                k as u32,
                per_ray.min(u32::MAX as usize) as u32,
                MIN_TRANSMITTANCE,
                self.params(),
                write,
            );
        }
    }
}

/// The four packed sample outputs of a write pass (`n` samples; placeholders of one
/// value in a count pass).
struct PackOutputs {
    t: Handle,
    dt: Handle,
    positions: Handle,
    dirs: Handle,
    n: usize,
}

impl PackOutputs {
    fn none(gpu: &Gpu) -> PackOutputs {
        let none = gpu.floats(1);
        PackOutputs {
            t: none.clone(),
            dt: none.clone(),
            positions: none.clone(),
            dirs: none,
            n: 0,
        }
    }

    /// The kernel arguments: depths, step lengths, positions, directions.
    ///
    /// # Safety
    /// The handles hold `n` (or one) and `3n` (or three) floats.
    unsafe fn args(&self) -> [BufferArg; 4] {
        let n = self.n.max(1);
        let p = if self.n == 0 { 1 } else { 3 * n };
        // SAFETY: see the function's contract.
        unsafe {
            [
                BufferArg::from_raw_parts(self.t.clone(), n),
                BufferArg::from_raw_parts(self.dt.clone(), n),
                BufferArg::from_raw_parts(self.positions.clone(), p),
                BufferArg::from_raw_parts(self.dirs.clone(), p),
            ]
        }
    }
}

/// The exclusive prefix sums of `n` counts (passes 1 to 3 of the scan).
/// Scans `counts` (`n`) into the rays' slots, counting the rays with samples.
fn scan(gpu: &Gpu, counts: Handle, n: usize) -> Counted {
    let offsets = gpu.zeros_u32(n);
    let blocks = n.div_ceil(SCAN_BLOCK);
    let totals = gpu.zeros_u32(blocks + 1);
    let live = gpu.zeros_u32(blocks + 1);
    if n > 0 {
        // SAFETY: `counts` and `offsets` hold `n` values, `totals` and `live` a slot per
        // block and one for the total; a block's workgroup touches only its own rays.
        unsafe {
            scan_blocks::launch_unchecked(
                &gpu.client,
                grid(blocks, 1).0,
                CubeDim::new_1d(SCAN_THREADS as u32),
                BufferArg::from_raw_parts(counts.clone(), n),
                BufferArg::from_raw_parts(offsets.clone(), n),
                BufferArg::from_raw_parts(totals.clone(), blocks + 1),
                BufferArg::from_raw_parts(live.clone(), blocks + 1),
                n as u32,
            );
            scan_totals::launch_unchecked(
                &gpu.client,
                CubeCount::Static(1, 1, 1),
                CubeDim::new_1d(SCAN_THREADS as u32),
                BufferArg::from_raw_parts(totals.clone(), blocks + 1),
                BufferArg::from_raw_parts(live.clone(), blocks + 1),
                blocks as u32,
            );
            let (c, d) = grid(n, GROUP);
            scan_add::launch_unchecked(
                &gpu.client,
                c,
                d,
                BufferArg::from_raw_parts(offsets.clone(), n),
                BufferArg::from_raw_parts(totals.clone(), blocks + 1),
                n as u32,
            );
        }
    }
    Counted {
        counts,
        offsets,
        live,
    }
}

#[cube(launch_unchecked)]
fn csr_offsets(slots: &[u32], offsets: &mut [u32], kept: u32, total: u32) {
    let i = ABSOLUTE_POS;
    if i < kept as usize {
        offsets[i] = slots[i];
    } else if i == kept as usize {
        offsets[i] = total;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;
    use crate::stage::PackedSamples;

    /// A grid with a random third of its cells occupied, 500 rays from outside the box in
    /// every direction (some missing it), with and without contraction, and a sparse grid
    /// (most blocks empty): the device's counts,
    /// slots, cut (at a ray and at the end of its block) and packed samples against `Marcher::pack_ray` on the host. Positions
    /// may differ by rounding (the device may fuse multiply-adds), so a ray agrees when its
    /// sample count matches and its depths are within 1e-4; at most 1% may not (a point
    /// that rounds across a cell wall).
    #[test]
    fn marching_matches_the_cpu_marcher() {
        let Some(gpu) = super::super::device::test_gpu() else {
            return;
        };
        // The sparse grids: most blocks empty (32^3), regions empty too (64^3).
        let cases = [
            (None, false, None),
            (Some(0.75), false, None),
            (None, true, None),
            (None, false, Some(32)),
            (None, false, Some(64)),
        ];
        for (contract, cylinders, sparse) in cases {
            let mut rng = Rng::new(9);
            let (res, bound) = (16, 1.5);
            let thickness: Vec<f32> = (0..res * res * res)
                .map(|_| if rng.uniform() < 0.33 { 1.0 } else { 0.0 })
                .collect();
            // The sparse grids' empty blocks and regions are crossed in one skip.
            let grid = match sparse {
                Some(32) => OccupancyGrid::sparse_for_tests(32, 3),
                Some(r) => OccupancyGrid::ball_for_tests(r, 3, 2e-5),
                None => OccupancyGrid::from_thickness(res, bound, thickness, 0.5),
            };
            if sparse == Some(64) {
                assert!(grid.occupied_regions().contains(&false));
            }
            let sparse = sparse.is_some();
            let bound = grid.bound;
            let marcher = Marcher {
                dt: 3f32.sqrt() * 2.0 * bound / 128.0,
                max_samples: 90,
                near: 0.5,
                far: if contract.is_some() { 200.0 } else { 8.0 },
                contract,
            };
            let mut rays = RayBatch::new(marcher.near, marcher.far);
            let mut jitter = Vec::new();
            for k in 0..500 {
                let origin = [rng.range(-4.0, 4.0), -4.0, rng.range(-1.0, 1.0)];
                let target = [rng.range(-2.0, 2.0), 0.0, rng.range(-2.0, 2.0)];
                let dir = [target[0] - origin[0], 4.0, target[2] - origin[2]];
                let ray = crate::camera::Ray { origin, dir };
                rays.push_with_radius(ray, dir, [1.0; 3], k, rng.range(1e-4, 1e-2));
                jitter.push(rng.uniform());
            }
            rays.cylinders = cylinders;
            let mut want = PackedSamples::default();
            want.clear();
            for (r, &j) in jitter.iter().enumerate() {
                marcher.pack_ray(&grid, &rays, r, j, &mut want);
            }

            let gm = GpuMarcher::with_grid(&gpu, &marcher, &grid);
            let on_device = GpuRays::new(&gpu, &marcher, &grid, &rays, &jitter);
            let counted = gm.count(&gpu, &on_device);
            let counts = gpu.read_u32(&counted.counts, 500).expect("read");
            let slots = gpu.read_u32(&counted.offsets, 500).expect("read");
            // The slots are the exclusive prefix sums of the device's own counts.
            let mut sum = 0;
            for (c, s) in counts.iter().zip(&slots) {
                assert_eq!(*s, sum);
                sum += c;
            }
            // The cut: the first ray at which the running count reaches the budget.
            let budget = (sum / 2) as usize;
            let cut = gm.cut(&gpu, &counted, 500, budget, 10_000).expect("cut");
            let mut running = 0;
            let first = counts
                .iter()
                .position(|&c| {
                    running += c as usize;
                    running >= budget
                })
                .expect("reached");
            assert_eq!(
                cut,
                Cut {
                    rays: first + 1,
                    samples: running,
                    found: true,
                    live: counts.iter().filter(|&&c| c > 0).count(),
                }
            );
            assert!(
                !gm.cut(&gpu, &counted, 500, 1 << 30, 10_000)
                    .expect("cut")
                    .found
            );
            assert_eq!(
                gm.cut(&gpu, &counted, 500, 1 << 30, 7).expect("cut").rays,
                7
            );
            // In blocks of 16: to the end of the block holding that ray, its samples
            // counted; a block that would end past the rays marched is no cut.
            let whole = (first / 16 + 1) * 16;
            let blocks = gm
                .cut_in_blocks(&gpu, &counted, 500, (budget, 10_000), 16)
                .expect("cut");
            let whole_samples: u32 = counts[..whole].iter().sum();
            assert_eq!(
                (blocks.rays, blocks.samples, blocks.found),
                (whole, whole_samples as usize, true)
            );
            assert!(
                !gm.cut_in_blocks(&gpu, &counted, whole - 1, (budget, 10_000), 16)
                    .expect("cut")
                    .found
            );

            let all = Cut {
                rays: 500,
                samples: sum as usize,
                found: true,
                live: 0,
            };
            let (packed, positions, _dirs) = gm.write(&gpu, &on_device, &counted, all);
            let t = gpu.read(&packed.t, all.samples).expect("read");
            let pos = gpu.read(&positions, 3 * all.samples).expect("read");
            // Each sample's footprint (anti-aliasing), from the rays' cone radii.
            let footprints = crate::engine::gpu::antialias::sample_footprints(
                &gpu,
                &on_device,
                &gpu.upload(&rays.radii),
                cylinders,
                contract,
                (&packed.offsets, &packed.t),
                500,
                all.samples,
            );
            let footprints = gpu.read(&footprints, all.samples).expect("read");
            let mut disagree = 0;
            for r in 0..500 {
                let w = want.ray(r);
                let got = slots[r] as usize..slots[r] as usize + counts[r] as usize;
                let same = w.len() == got.len()
                    && w.clone().zip(got.clone()).all(|(a, b)| {
                        (want.t[a] - t[b]).abs() < 1e-4 * (1.0 + want.t[a].abs())
                            && (0..3).all(|c| (want.positions[a][c] - pos[3 * b + c]).abs() < 1e-3)
                            && (want.footprints[a] - footprints[b]).abs()
                                < 1e-4 * want.footprints[a]
                    });
                if !same {
                    disagree += 1;
                }
            }
            assert!(
                disagree * 100 <= 500,
                "{disagree} of 500 rays disagree (contract {contract:?}, cylinders {cylinders})"
            );
            // The sparse grid's ball is small against the rays' spread.
            let enough = if sparse { 800 } else { 2000 };
            assert!(
                want.len() > enough,
                "too few samples to test: {}",
                want.len()
            );
        }
    }

    /// The workgroup scan against a serial one: sizes around the block and past
    /// `SCAN_THREADS` blocks (where each thread of the totals' pass takes several), counts
    /// with zeros among them (rays without samples are not live).
    #[test]
    fn the_scan_matches_a_serial_prefix_sum() {
        let Some(gpu) = super::super::device::test_gpu() else {
            return;
        };
        let mut rng = Rng::new(5);
        for n in [1, 5, SCAN_BLOCK, SCAN_BLOCK + 1, 300 * SCAN_BLOCK + 17] {
            let counts: Vec<u32> = (0..n)
                .map(|_| {
                    if rng.uniform() < 0.3 {
                        0
                    } else {
                        (rng.uniform() * 64.0) as u32
                    }
                })
                .collect();
            let counted = scan(&gpu, gpu.upload_u32(&counts), n);
            let slots = gpu.read_u32(&counted.offsets, n).expect("read");
            let mut sum = 0;
            for (r, (c, s)) in counts.iter().zip(&slots).enumerate() {
                assert_eq!(*s, sum, "ray {r} of {n}");
                sum += c;
            }
            let gm = GpuMarcher::with_grid(
                &gpu,
                &Marcher {
                    dt: 0.1,
                    max_samples: 64,
                    near: 0.0,
                    far: 1.0,
                    contract: None,
                },
                &OccupancyGrid::from_thickness(2, 1.0, vec![1.0; 8], 0.5),
            );
            let cut = gm.cut(&gpu, &counted, n, usize::MAX, n).expect("cut");
            assert_eq!(cut.samples, sum as usize, "{n} rays");
            assert_eq!(
                cut.live,
                counts.iter().filter(|&&c| c > 0).count(),
                "{n} rays"
            );
        }
    }
}
