//! The occupancy grid and the ray marcher that uses it to skip empty space.
//!
//! The scene box `[-bound, bound]^3` is cut into `resolution^3` cells. Each cell keeps a
//! decaying maximum of the optical thickness `sigma * dt` seen at random points inside it;
//! a cell is occupied while that value exceeds `min(threshold, mean over cells)` (the mean
//! keeps a young, uniformly thin field from being switched off entirely). Until the first
//! refresh every cell is occupied.
//!
//! Rays march with a fixed step `dt` on a lattice `t0 + (k + jitter) dt`: a sample is
//! taken in occupied cells, and an empty cell is crossed in whole steps, so skipping changes
//! only which lattice points are visited, never where they are. Where the whole block of
//! [`BLOCK`]^3 cells around an empty cell is empty, the block is crossed in one skip, and
//! where the whole region of [`REGION`]^3 cells around it is empty, the region: a ray
//! through empty space looks up a flag per region or block instead of one per cell, and
//! lands on the lattice point the cell-by-cell walk would reach (the first past the wall).

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::rng::Rng;

/// Cells per axis of the blocks that marching crosses in one skip when all of their cells
/// are empty (grids whose resolution it does not divide skip cell by cell).
pub const BLOCK: usize = 4;

/// Cells per axis of the regions (of blocks) crossed in one skip when all of their cells
/// are empty: far from the scene a ray crosses a 128^3 grid in a few skips.
pub const REGION: usize = 16;

// The GPU marcher finds a cell's block by a shift.
const _: () = assert!(BLOCK.is_power_of_two());
const _: () = assert!(REGION.is_power_of_two() && REGION.is_multiple_of(BLOCK));

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct OccupancyConfig {
    /// Cells per axis (128).
    pub resolution: usize,
    /// Refresh every this many steps (16).
    pub update_every: u64,
    /// Per-refresh decay of a cell's remembered thickness (0.95).
    pub decay: f32,
    /// Optical thickness `sigma * dt` above which a cell is occupied (0.01).
    pub threshold: f32,
    /// During the first steps every cell is re-evaluated at each refresh (256).
    pub warmup_steps: u64,
    /// After warm-up, this fraction of the cells, chosen at random, is re-evaluated, plus
    /// every occupied cell (1/16: an empty cell is looked at again every 256 steps on
    /// average; Instant-NGP's quarter trained no better per step and cost the CPU engine
    /// far more time, see docs/benchmarks.md). A young field still moves fast: until
    /// [`YOUNG_WARMUPS`] warm-ups have passed, at least a quarter is re-evaluated.
    pub update_fraction: f32,
}

/// For this many warm-ups' steps a field counts as young (see
/// [`OccupancyConfig::recheck_fraction`]).
pub const YOUNG_WARMUPS: u64 = 4;

impl OccupancyConfig {
    /// The share of cells re-evaluated at random by the refresh at step `step` (after the
    /// warm-up, which re-evaluates every cell): `update_fraction`, but at least a quarter
    /// while the field is young.
    pub fn recheck_fraction(&self, step: u64) -> f32 {
        if step < YOUNG_WARMUPS * self.warmup_steps {
            self.update_fraction.max(0.25)
        } else {
            self.update_fraction
        }
    }
}

impl Default for OccupancyConfig {
    fn default() -> Self {
        OccupancyConfig {
            resolution: 128,
            update_every: 16,
            decay: 0.95,
            threshold: 0.01,
            warmup_steps: 256,
            update_fraction: 0.0625,
        }
    }
}

#[derive(Clone, Debug, PartialEq)]
pub struct OccupancyGrid {
    pub resolution: usize,
    pub bound: f32,
    /// Remembered optical thickness per cell, x fastest.
    pub thickness: Vec<f32>,
    occupied: Vec<bool>,
    /// `occupied` packed 64 cells a word, for marching: an eighth of the bytes, so a
    /// 128^3 grid's lookups (one per cell a ray crosses) stay in a core's L2 cache.
    bits: Vec<u64>,
    /// Per block of `BLOCK^3` cells, and per region of `REGION^3`, whether any of its cells
    /// is occupied.
    blocks: Cubes,
    regions: Cubes,
    /// Cells that may hold anything (`None`: all): few-view training keeps the space the
    /// training cameras do not see empty (`model::few_view`).
    pub possible: Option<Vec<bool>>,
}

/// Entry and exit distances of a ray (unit direction) through `[-bound, bound]^3`,
/// clipped to `[near, far]`; `None` when it misses.
pub fn ray_box(o: [f32; 3], d: [f32; 3], bound: f32, near: f32, far: f32) -> Option<(f32, f32)> {
    let (mut t0, mut t1) = (near, far);
    for a in 0..3 {
        let inv = 1.0 / d[a];
        let (mut ta, mut tb) = ((-bound - o[a]) * inv, (bound - o[a]) * inv);
        if ta > tb {
            std::mem::swap(&mut ta, &mut tb);
        }
        // NaN (ray parallel to a slab, starting on its plane) compares false: keep bounds.
        if ta > t0 {
            t0 = ta;
        }
        if tb < t1 {
            t1 = tb;
        }
    }
    (t0 < t1).then_some((t0, t1))
}

/// The centre of cell `i` (x fastest) of a `resolution^3` grid over `[-bound, bound]^3`.
pub fn cell_centre(resolution: usize, bound: f32, i: usize) -> [f32; 3] {
    let cell = 2.0 * bound / resolution as f32;
    let c = [
        i % resolution,
        (i / resolution) % resolution,
        i / (resolution * resolution),
    ];
    c.map(|k| (k as f32 + 0.5) * cell - bound)
}

impl OccupancyGrid {
    /// A grid with every cell occupied.
    pub fn new(resolution: usize, bound: f32) -> Self {
        let n = resolution.pow(3);
        let (blocks, regions) = skip_cubes(&vec![true; n], resolution);
        OccupancyGrid {
            resolution,
            bound,
            thickness: vec![0.0; n],
            occupied: vec![true; n],
            bits: pack(&vec![true; n]),
            blocks,
            regions,
            possible: None,
        }
    }

    /// A grid with the given per-cell thickness, occupancy derived from it.
    pub fn from_thickness(
        resolution: usize,
        bound: f32,
        thickness: Vec<f32>,
        threshold: f32,
    ) -> Self {
        let mut g = OccupancyGrid::new(resolution, bound);
        g.thickness = thickness;
        g.refresh(threshold);
        g
    }

    fn cell_size(&self) -> f32 {
        2.0 * self.bound / self.resolution as f32
    }

    /// Cell coordinates of a point (clamped into the grid).
    #[inline]
    fn cell(&self, p: [f32; 3]) -> [usize; 3] {
        let inv = 1.0 / self.cell_size();
        let max = self.resolution - 1;
        p.map(|x| (((x + self.bound) * inv).max(0.0) as usize).min(max))
    }

    #[inline]
    fn index(&self, c: [usize; 3]) -> usize {
        c[0] + self.resolution * (c[1] + self.resolution * c[2])
    }

    /// The cell holding `p` (x fastest); `None` outside the grid.
    pub fn cell_index(&self, p: [f32; 3]) -> Option<usize> {
        let (res, cell) = (self.resolution as f32, self.cell_size());
        let k = p.map(|x| ((x + self.bound) / cell).floor());
        k.iter()
            .all(|k| (0.0..res).contains(k))
            .then(|| self.index(k.map(|k| k as usize)))
    }

    pub fn is_occupied(&self, p: [f32; 3]) -> bool {
        self.occupied_at(self.index(self.cell(p)))
    }

    /// A grid with the given per-cell thickness and occupied cells (as a GPU refresh
    /// derived them).
    pub fn from_parts(
        resolution: usize,
        bound: f32,
        thickness: Vec<f32>,
        occupied: Vec<bool>,
    ) -> Self {
        assert_eq!(thickness.len(), occupied.len());
        let (blocks, regions) = skip_cubes(&occupied, resolution);
        OccupancyGrid {
            resolution,
            bound,
            thickness,
            bits: pack(&occupied),
            blocks,
            regions,
            occupied,
            possible: None,
        }
    }

    /// Which cells are occupied, x fastest (what a GPU marcher uploads).
    pub fn occupied_cells(&self) -> &[bool] {
        &self.occupied
    }

    /// Fraction of cells occupied.
    pub fn occupancy(&self) -> f64 {
        self.occupied.iter().filter(|&&o| o).count() as f64 / self.occupied.len() as f64
    }

    /// Re-derives occupancy from the remembered thickness.
    pub fn refresh(&mut self, threshold: f32) {
        if let Some(possible) = &self.possible {
            // Kept in the thickness too, so a saved grid stays empty there when loaded;
            // before the mean, so a loaded grid derives the same cut (as a device's
            // refresh, which never stores thickness there).
            for (v, &p) in self.thickness.iter_mut().zip(possible) {
                if !p {
                    *v = 0.0;
                }
            }
        }
        let mean = self.thickness.iter().map(|&v| v as f64).sum::<f64>()
            / self.thickness.len().max(1) as f64;
        let cut = threshold.min(mean as f32);
        for (i, (o, &v)) in self.occupied.iter_mut().zip(&self.thickness).enumerate() {
            *o = v >= cut && self.possible.as_ref().is_none_or(|p| p[i]);
        }
        self.bits = pack(&self.occupied);
        (self.blocks, self.regions) = skip_cubes(&self.occupied, self.resolution);
    }

    /// Per block of `BLOCK^3` cells (x fastest), whether any of its cells is occupied;
    /// empty when `BLOCK` does not divide the resolution (what a GPU marcher uploads).
    pub fn occupied_blocks(&self) -> Vec<bool> {
        self.blocks.unpacked()
    }

    /// Per region of `REGION^3` cells (x fastest), whether any of its cells is occupied;
    /// empty when `REGION` does not divide the resolution (what a GPU marcher uploads).
    pub fn occupied_regions(&self) -> Vec<bool> {
        self.regions.unpacked()
    }

    /// Blocks and regions per axis that marching skips by (0 for none).
    pub fn skip_cubes_per_axis(&self) -> (usize, usize) {
        (self.blocks.per_axis, self.regions.per_axis)
    }

    /// The same grid marched cell by cell (the plain walk the skips are tested against).
    #[cfg(test)]
    pub(crate) fn without_blocks(mut self) -> Self {
        self.blocks = Cubes::none();
        self.regions = Cubes::none();
        self
    }

    /// The same grid with blocks but no regions.
    #[cfg(test)]
    pub(crate) fn without_regions(mut self) -> Self {
        self.regions = Cubes::none();
        self
    }

    /// A sparse grid (a ball and a few scattered cells, most blocks empty) for marching
    /// tests, at a resolution `BLOCK` divides.
    #[cfg(test)]
    pub(crate) fn sparse_for_tests(res: usize, seed: u64) -> OccupancyGrid {
        Self::ball_for_tests(res, seed, 0.003)
    }

    /// A ball and cells scattered with probability `scatter`, at a resolution `BLOCK`
    /// divides.
    #[cfg(test)]
    pub(crate) fn ball_for_tests(res: usize, seed: u64, scatter: f32) -> OccupancyGrid {
        let mut rng = Rng::new(seed);
        let cell = 2.0 / res as f32;
        let flags: Vec<bool> = (0..res * res * res)
            .map(|i| {
                let c = [i % res, (i / res) % res, i / (res * res)];
                let p = c.map(|k| (k as f32 + 0.5) * cell - 1.0);
                let r2 = p[0] * p[0] + 0.5 * p[1] * p[1] + p[2] * p[2];
                r2 < 0.25 || rng.uniform() < scatter
            })
            .collect();
        let thickness = flags.iter().map(|&o| f32::from(u8::from(o))).collect();
        OccupancyGrid::from_parts(res, 1.0, thickness, flags)
    }

    #[inline]
    fn occupied_at(&self, index: usize) -> bool {
        bit(&self.bits, index)
    }

    /// Marches a ray (unit direction `d`) over `span` (from a lattice depth to the exit),
    /// appending sample depths in occupied cells to `out` until `max` samples were added.
    /// Returns the depth to continue from (`>= span.end` when the ray is done).
    pub fn march(
        &self,
        o: [f32; 3],
        d: [f32; 3],
        span: std::ops::Range<f32>,
        dt: f32,
        max: usize,
        out: &mut Vec<f32>,
    ) -> f32 {
        let (mut t, t_end) = (span.start, span.end);
        let cs = self.cell_size();
        let mut added = 0;
        while t < t_end && added < max {
            let p = [o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2]];
            let c = self.cell(p);
            if self.occupied_at(self.index(c)) {
                out.push(t);
                added += 1;
                t += dt;
                continue;
            }
            // Distance to the far wall of the cell, or of its block or region if that is
            // empty too, along the ray, then whole steps past it.
            let k = if self.regions.empty_at(c) {
                self.regions.shift
            } else if self.blocks.empty_at(c) {
                self.blocks.shift
            } else {
                0
            };
            let mut exit = f32::INFINITY;
            for a in 0..3 {
                if d[a] != 0.0 {
                    let low = c[a] >> k << k;
                    let wall =
                        if d[a] > 0.0 { low + (1 << k) } else { low } as f32 * cs - self.bound;
                    exit = exit.min((wall - p[a]) / d[a]);
                }
            }
            t += (whole_steps(exit.max(0.0) / dt) + 1.0) * dt;
        }
        t
    }

    /// One refresh at training step `step`: decays every cell, re-evaluates the chosen ones
    /// at a random point inside each (`density` maps packed positions to sigmas and is
    /// called from several threads), and re-derives occupancy.
    pub fn update(
        &mut self,
        config: &OccupancyConfig,
        step: u64,
        seed: u64,
        dt: f32,
        density: &(dyn Fn(&[f32], &mut [f32]) + Sync),
    ) {
        const CELLS_PER_TASK: usize = 4096;
        let warm = step < config.warmup_steps;
        let fraction = config.recheck_fraction(step);
        let (res, cs, bound) = (self.resolution, self.cell_size(), self.bound);
        let occupied = &self.occupied;
        self.thickness
            .par_chunks_mut(CELLS_PER_TASK)
            .enumerate()
            .for_each(|(task, cells)| {
                let mut rng = Rng::for_stream(seed ^ 0x0cc, step, task as u64);
                let first = task * CELLS_PER_TASK;
                let mut chosen = Vec::with_capacity(cells.len());
                let mut points = Vec::with_capacity(cells.len() * 3);
                for i in 0..cells.len() {
                    let idx = first + i;
                    let pick = rng.uniform() < fraction;
                    if !(warm || occupied[idx] || pick) {
                        continue;
                    }
                    let c = [idx % res, (idx / res) % res, idx / (res * res)];
                    chosen.push(i);
                    for a in 0..3 {
                        points.push((c[a] as f32 + rng.uniform()) * cs - bound);
                    }
                }
                let mut sigma = vec![0.0; chosen.len()];
                if !chosen.is_empty() {
                    density(&points, &mut sigma);
                }
                for v in cells.iter_mut() {
                    *v *= config.decay;
                }
                for (&i, &s) in chosen.iter().zip(&sigma) {
                    cells[i] = cells[i].max(s * dt);
                }
            });
        self.refresh(config.threshold);
    }
}

/// Occupancy flags packed 64 to a word, the first flag in the lowest bit.
fn pack(occupied: &[bool]) -> Vec<u64> {
    occupied
        .chunks(64)
        .map(|flags| {
            flags
                .iter()
                .enumerate()
                .fold(0u64, |word, (i, &o)| word | (u64::from(o) << i))
        })
        .collect()
}

/// Flag `i` of flags packed by [`pack`].
#[inline]
fn bit(words: &[u64], i: usize) -> bool {
    (words[i >> 6] >> (i & 63)) & 1 == 1
}

/// Blocks per axis of a `resolution^3` grid: 0 where `BLOCK` does not divide it (such a
/// grid is marched cell by cell, on both engines).
pub fn blocks_per_axis(resolution: usize) -> usize {
    cubes_per_axis(resolution, BLOCK)
}

/// Regions per axis of a `resolution^3` grid: 0 where `REGION` does not divide it.
pub fn regions_per_axis(resolution: usize) -> usize {
    cubes_per_axis(resolution, REGION)
}

fn cubes_per_axis(resolution: usize, size: usize) -> usize {
    if resolution.is_multiple_of(size) {
        resolution / size
    } else {
        0
    }
}

/// The flags marching skips empty space by: blocks from the cells, regions from the blocks.
fn skip_cubes(occupied: &[bool], resolution: usize) -> (Cubes, Cubes) {
    let blocks = Cubes::new(occupied, resolution, BLOCK);
    let regions = blocks.grouped(REGION);
    (blocks, regions)
}

/// Per cube of `size^3` cells of a grid (x fastest), whether any of its cells is occupied,
/// packed as [`pack`]; none when `size` does not divide the resolution.
#[derive(Clone, Debug, PartialEq)]
struct Cubes {
    /// log2 of the cells per axis of a cube.
    shift: u32,
    per_axis: usize,
    flags: Vec<u64>,
}

impl Cubes {
    fn new(occupied: &[bool], resolution: usize, size: usize) -> Self {
        debug_assert!(size.is_power_of_two());
        let r = cubes_per_axis(resolution, size);
        let mut any = vec![false; r * r * r];
        if r > 0 {
            for (i, _) in occupied.iter().enumerate().filter(|(_, &o)| o) {
                let c = [
                    i % resolution,
                    (i / resolution) % resolution,
                    i / (resolution * resolution),
                ];
                any[c[0] / size + r * (c[1] / size + r * (c[2] / size))] = true;
            }
        }
        Cubes {
            shift: size.trailing_zeros(),
            per_axis: r,
            flags: pack(&any),
        }
    }

    /// Cubes of `size` cells (a multiple of these cubes'), each flagged where any of the
    /// cubes inside it is: the coarser flags without another pass over the cells.
    fn grouped(&self, size: usize) -> Self {
        let mut coarser = Cubes::new(&self.unpacked(), self.per_axis, size >> self.shift);
        coarser.shift = size.trailing_zeros();
        coarser
    }

    #[cfg(test)]
    fn none() -> Self {
        Cubes {
            shift: 0,
            per_axis: 0,
            flags: Vec::new(),
        }
    }

    fn unpacked(&self) -> Vec<bool> {
        (0..self.per_axis.pow(3))
            .map(|i| bit(&self.flags, i))
            .collect()
    }

    /// Whether the cube around cell `c` holds no occupied cell (false without cubes).
    #[inline]
    fn empty_at(&self, c: [usize; 3]) -> bool {
        let (r, k) = (self.per_axis, self.shift);
        r > 0
            && !bit(
                &self.flags,
                (c[0] >> k) + r * ((c[1] >> k) + r * (c[2] >> k)),
            )
    }
}

/// The floor of a quotient that is not negative, as the truncating cast computes it: one
/// instruction, where `f32::floor` is a library call on the baseline x86-64 target (and
/// marching calls it once per empty cell a ray crosses). Exact for every finite value below
/// 2^63 (f32 values from 2^24 up are whole already); larger or infinite quotients saturate
/// there, which still lands past the end of any span.
#[inline]
fn whole_steps(x: f32) -> f32 {
    x as i64 as f32
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Cells marked impossible stay empty whatever their thickness, and lose it, so a grid
    /// saved and loaded without the mark is empty there too.
    #[test]
    fn impossible_cells_are_never_occupied_and_keep_no_thickness() {
        let mut g = OccupancyGrid::from_thickness(2, 1.0, vec![1.0; 8], 0.01);
        assert!((g.occupancy() - 1.0).abs() < 1e-12);
        g.possible = Some((0..8).map(|i| i % 2 == 0).collect());
        g.refresh(0.01);
        assert!((g.occupancy() - 0.5).abs() < 1e-12);
        assert_eq!(g.thickness, [1.0, 0.0, 1.0, 0.0, 1.0, 0.0, 1.0, 0.0]);
        // Even before any thickness (all cells at zero pass a zero cut).
        let mut fresh = OccupancyGrid::new(2, 1.0);
        fresh.possible = Some(vec![false; 8]);
        fresh.refresh(0.01);
        assert_eq!(fresh.occupancy(), 0.0);
        let loaded = OccupancyGrid::from_thickness(2, 1.0, g.thickness.clone(), 0.01);
        assert!((loaded.occupancy() - 0.5).abs() < 1e-12);
    }

    /// The cut (the mean thickness, when below the threshold) is taken over the cells
    /// that may hold anything, so a grid reloaded from its saved thickness derives the
    /// same cells as the grid that saved it (a resumed run continues exactly).
    #[test]
    fn impossible_cells_do_not_move_the_cut() {
        let mut g = OccupancyGrid::new(2, 1.0);
        g.thickness = vec![0.2, 5.0, 0.4, 5.0, 0.2, 5.0, 0.4, 5.0];
        let possible: Vec<bool> = (0..8).map(|i| i % 2 == 0).collect();
        g.possible = Some(possible.clone());
        g.refresh(10.0);
        assert_eq!(g.occupied_cells(), possible.as_slice());
        let mut loaded = OccupancyGrid::from_thickness(2, 1.0, g.thickness.clone(), 10.0);
        loaded.possible = Some(possible);
        loaded.refresh(10.0);
        assert_eq!(loaded.occupied_cells(), g.occupied_cells());
    }

    #[test]
    fn ray_box_clips_to_the_box_and_misses_outside() {
        let (t0, t1) = ray_box([0.0, -4.0, 0.0], [0.0, 1.0, 0.0], 1.5, 2.0, 6.0).expect("hit");
        assert!((t0 - 2.5).abs() < 1e-6 && (t1 - 5.5).abs() < 1e-6);
        assert!(ray_box([3.0, -4.0, 0.0], [0.0, 1.0, 0.0], 1.5, 2.0, 6.0).is_none());
        // Near/far clip inside the box.
        let (t0, t1) = ray_box([0.0, -4.0, 0.0], [0.0, 1.0, 0.0], 1.5, 3.0, 4.0).expect("hit");
        assert_eq!((t0, t1), (3.0, 4.0));
    }

    #[test]
    fn march_samples_only_occupied_cells_on_the_step_lattice() {
        // Only the cells around the origin are occupied.
        let res = 16;
        let mut thickness = vec![0.0; res * res * res];
        let mut g = OccupancyGrid::new(res, 1.0);
        for z in 7..9 {
            for y in 7..9 {
                for x in 7..9 {
                    thickness[g.index([x, y, z])] = 1.0;
                }
            }
        }
        g.thickness = thickness;
        g.refresh(0.01);
        assert!((g.occupancy() - 8.0 / 4096.0).abs() < 1e-9);
        let (o, d) = ([-3.0, 0.01, 0.02], [1.0, 0.0, 0.0]);
        let (t0, t1) = ray_box(o, d, 1.0, 0.0, 10.0).expect("hit");
        let dt = 0.01;
        let start = t0 + 0.3 * dt;
        let mut ts = Vec::new();
        let end = g.march(o, d, start..t1, dt, usize::MAX, &mut ts);
        assert!(end >= t1);
        // Occupied x range is [-0.125, 0.125): 25 lattice points.
        assert!((24..=26).contains(&ts.len()), "{} samples", ts.len());
        for &t in &ts {
            let x = o[0] + t * d[0];
            assert!((-0.126..0.126).contains(&x), "sample at x = {x}");
            let k = (t - start) / dt;
            assert!(
                (k - k.round()).abs() < 1e-2,
                "sample off the lattice: k = {k}"
            );
        }
        // Resuming in pieces gives the same samples.
        let mut pieces = Vec::new();
        let mut t = start;
        while t < t1 {
            t = g.march(o, d, t..t1, dt, 4, &mut pieces);
        }
        assert_eq!(pieces, ts);
    }

    /// A quarter of the cells is rechecked while the field is young, the configured share
    /// after; a larger configured share (runs saved with a quarter) is kept throughout.
    #[test]
    fn young_fields_recheck_a_quarter() {
        let c = OccupancyConfig::default();
        let young = YOUNG_WARMUPS * c.warmup_steps;
        assert_eq!(c.recheck_fraction(c.warmup_steps), 0.25);
        assert_eq!(c.recheck_fraction(young - 1), 0.25);
        assert_eq!(c.recheck_fraction(young), c.update_fraction);
        assert!(c.update_fraction < 0.25);
        let old = OccupancyConfig {
            update_fraction: 0.25,
            ..c
        };
        assert_eq!(old.recheck_fraction(0), 0.25);
        assert_eq!(old.recheck_fraction(10 * young), 0.25);
    }

    #[test]
    fn update_keeps_dense_cells_and_drops_empty_ones() {
        let mut g = OccupancyGrid::new(8, 1.0);
        let config = OccupancyConfig {
            resolution: 8,
            warmup_steps: 0,
            update_fraction: 1.0,
            ..OccupancyConfig::default()
        };
        // A ball of density 100 of radius 0.5 in empty space.
        let ball = |p: &[f32], s: &mut [f32]| {
            for (k, v) in s.iter_mut().enumerate() {
                let r2: f32 = p[3 * k..3 * k + 3].iter().map(|x| x * x).sum();
                *v = if r2 < 0.25 { 100.0 } else { 0.0 };
            }
        };
        g.update(&config, 0, 1, 0.01, &ball);
        assert!(g.is_occupied([0.0, 0.0, 0.0]));
        assert!(!g.is_occupied([0.9, 0.9, 0.9]));
        let occ = g.occupancy();
        assert!(occ > 0.0 && occ < 0.3, "{occ}");
        // A young field that is thin everywhere is not switched off: the threshold drops to
        // the mean, so the thicker half of the cells stays occupied.
        let thin: Vec<f32> = (0..512).map(|i| 1e-4 * (i % 2 + 1) as f32).collect();
        let young = OccupancyGrid::from_thickness(8, 1.0, thin, 0.01);
        assert!((young.occupancy() - 0.5).abs() < 1e-9);
        // The remembered thickness decays when the density goes away.
        let empty = |_: &[f32], s: &mut [f32]| s.fill(0.0);
        let before = g.thickness.iter().cloned().fold(0.0, f32::max);
        g.update(&config, 16, 1, 0.01, &empty);
        let after = g.thickness.iter().cloned().fold(0.0, f32::max);
        assert!((after - before * 0.95).abs() < 1e-6);
    }

    /// The cast floors like `f32::floor` for every quotient marching forms, and saturates
    /// beyond (still past any span).
    #[test]
    fn whole_steps_floor_every_quotient() {
        let mut x = 0.0f32;
        while x < 1e7 {
            for v in [x, x.next_up(), (x + 1.0).next_down()] {
                assert_eq!(whole_steps(v), v.floor(), "{v}");
            }
            x = x * 1.37 + 0.01;
        }
        for v in [
            0.0, 0.49999997, 0.5, 0.99999994, 1.0, 16777215.5, 16777216.0, 3.0e18,
        ] {
            assert_eq!(whole_steps(v), v.floor(), "{v}");
        }
        assert!(whole_steps(f32::INFINITY) > 9.0e18 && whole_steps(f32::MAX) > 9.0e18);
    }

    /// The packed flags marching reads say what the flags say, cell by cell, for a grid
    /// whose cell count is not a multiple of 64, after a refresh as well.
    #[test]
    fn packed_flags_match_the_cells() {
        let res = 5;
        let flags: Vec<bool> = (0..res * res * res).map(|i| (i * 7919) % 3 == 0).collect();
        let thickness: Vec<f32> = flags.iter().map(|&o| if o { 1.0 } else { 0.0 }).collect();
        let mut g = OccupancyGrid::from_parts(res, 1.0, thickness, flags.clone());
        let check = |g: &OccupancyGrid, want: &[bool]| {
            for (i, &o) in want.iter().enumerate() {
                assert_eq!(g.occupied_at(i), o, "cell {i}");
                let centre = cell_centre(res, g.bound, i);
                assert_eq!(g.is_occupied(centre), o, "cell {i}");
                assert_eq!(g.cell_index(centre), Some(i), "cell {i}");
            }
        };
        check(&g, &flags);
        g.thickness.iter_mut().for_each(|v| *v = 1.0 - *v);
        g.refresh(0.5);
        let flipped: Vec<bool> = flags.iter().map(|&o| !o).collect();
        check(&g, &flipped);
    }

    /// Crossing empty blocks and regions in one skip visits the lattice points the
    /// cell-by-cell walk visits: the same samples (depths equal to rounding) on rays through
    /// sparse grids (with empty blocks; with empty regions too), whole and resumed in pieces,
    /// with regions and blocks, blocks alone, and cell by cell.
    #[test]
    fn block_and_region_skips_take_the_samples_of_the_cell_walk() {
        for grid in [
            OccupancyGrid::sparse_for_tests(32, 3),
            OccupancyGrid::ball_for_tests(64, 3, 2e-5),
        ] {
            let empty = |flags: Vec<bool>| flags.iter().filter(|&&b| !b).count() * 2 > flags.len();
            assert!(empty(grid.occupied_blocks()), "most blocks empty");
            if grid.resolution == 64 {
                let regions = grid.occupied_regions();
                let empty = regions.iter().filter(|&&b| !b).count();
                assert!(
                    (16..regions.len()).contains(&empty),
                    "{empty} of {} regions empty",
                    regions.len()
                );
            }
            // Regions grouped from the blocks are those the cells give.
            assert_eq!(
                grid.regions,
                Cubes::new(&grid.occupied, grid.resolution, REGION)
            );
            let plain = grid.clone().without_blocks();
            assert!(plain.occupied_blocks().is_empty() && plain.occupied_regions().is_empty());
            let no_regions = grid.clone().without_regions();
            check_skips(&grid, &no_regions, &plain);
        }
    }

    fn check_skips(grid: &OccupancyGrid, no_regions: &OccupancyGrid, plain: &OccupancyGrid) {
        let mut rng = Rng::new(9);
        let (mut rays, mut samples) = (0, 0);
        for _ in 0..400 {
            let o = [0; 3].map(|_| rng.range(-3.0, 3.0));
            let to = [0; 3].map(|_| rng.range(-0.5, 0.5));
            let v = crate::math::sub(to, o);
            let d = crate::math::scale(v, 1.0 / crate::math::length(v));
            let Some((t0, t1)) = ray_box(o, d, 1.0, 0.0, 10.0) else {
                continue;
            };
            let dt = 2.0 * 3f32.sqrt() / 256.0;
            let start = t0 + rng.uniform() * dt;
            let (mut fast, mut blocks, mut slow) = (Vec::new(), Vec::new(), Vec::new());
            grid.march(o, d, start..t1, dt, usize::MAX, &mut fast);
            no_regions.march(o, d, start..t1, dt, usize::MAX, &mut blocks);
            plain.march(o, d, start..t1, dt, usize::MAX, &mut slow);
            for walk in [&fast, &blocks] {
                assert_eq!(walk.len(), slow.len(), "ray from {o:?}");
                for (a, b) in walk.iter().zip(&slow) {
                    assert!((a - b).abs() < 1e-4, "{a} vs {b}");
                }
            }
            let mut pieces = Vec::new();
            let mut t = start;
            while t < t1 {
                t = grid.march(o, d, t..t1, dt, 3, &mut pieces);
            }
            assert_eq!(pieces, fast);
            rays += 1;
            samples += fast.len();
        }
        assert!(
            rays > 300 && samples > 1000,
            "{rays} rays, {samples} samples"
        );
    }
}
