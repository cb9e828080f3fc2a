//! Multiresolution hash encoding (Mueller et al., "Instant Neural Graphics Primitives", 2022).
//!
//! `L` levels of grids over the unit cube, resolutions growing geometrically from
//! `base_resolution` to `max_resolution` cells per axis. Each level stores `FEATURES`
//! trainable values per grid vertex, in a table of at most `2^log2_table_size` entries:
//! a level whose `(N + 1)^3` vertices fit is indexed densely, a finer one through the spatial
//! hash `x ^ (y * 2654435761) ^ (z * 805459861) mod T` (collisions are left to the MLP to
//! resolve). A point's encoding is, per level, the trilinear interpolation of its cell's
//! eight corner features, concatenated into `L * FEATURES` values.
//!
//! Work mapping: loops run level by level over the whole batch, so one level's table (at most
//! 4 MiB at the default size) stays in cache while every sample reads it; the backward
//! recomputes corners and weights instead of storing them (cheaper than the memory traffic).

use serde::{Deserialize, Serialize};

use crate::nn::Grads;
use crate::nn::ParamLayout;
use crate::rng::Rng;

#[cfg(target_arch = "x86_64")]
use super::grid_simd;

/// Features per level (the paper's choice, and what the kernels are written for).
pub const FEATURES: usize = 2;

const PRIME_Y: u32 = 2_654_435_761;
const PRIME_Z: u32 = 805_459_861;

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct HashGridConfig {
    pub levels: usize,
    /// At most `2^log2_table_size` entries per level.
    pub log2_table_size: u32,
    pub base_resolution: usize,
    pub max_resolution: usize,
}

impl Default for HashGridConfig {
    /// The paper's NeRF setting: 16 levels, 2^19 entries, 16 to 2048 cells per axis.
    fn default() -> Self {
        HashGridConfig {
            levels: 16,
            log2_table_size: 19,
            base_resolution: 16,
            max_resolution: 2048,
        }
    }
}

/// One level: its resolution and where its table sits in the parameter vector.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Level {
    /// Cells per axis.
    pub resolution: u32,
    /// Table entries (`FEATURES` floats each).
    pub entries: usize,
    /// Vertices are indexed densely (`true`) or hashed.
    pub dense: bool,
    /// Offset of the table (in floats) in the parameter vector.
    pub offset: usize,
}

impl Level {
    #[inline(always)]
    fn index(&self, x: u32, y: u32, z: u32) -> usize {
        if self.dense {
            let s = self.resolution + 1;
            (x + s * (y + s * z)) as usize
        } else {
            ((x ^ y.wrapping_mul(PRIME_Y) ^ z.wrapping_mul(PRIME_Z)) as usize) & (self.entries - 1)
        }
    }

    /// What the vectorised corners need of the level.
    #[cfg(target_arch = "x86_64")]
    fn shape(&self) -> grid_simd::LevelShape {
        grid_simd::LevelShape {
            resolution: self.resolution,
            entries: self.entries,
            dense: self.dense,
            primes: [PRIME_Y, PRIME_Z],
        }
    }

    /// The eight corners of the cell holding unit-cube point `u`: table indices and
    /// trilinear weights.
    #[inline(always)]
    pub(crate) fn corners(&self, u: [f32; 3]) -> ([u32; 8], [f32; 8]) {
        let n = self.resolution;
        let mut cell = [0u32; 3];
        let mut frac = [0f32; 3];
        for a in 0..3 {
            let p = u[a].clamp(0.0, 1.0) * n as f32;
            let c = (p as u32).min(n - 1);
            cell[a] = c;
            frac[a] = p - c as f32;
        }
        let mut idx = [0u32; 8];
        let mut w = [0f32; 8];
        for k in 0..8 {
            let (bx, by, bz) = ((k & 1) as u32, ((k >> 1) & 1) as u32, ((k >> 2) & 1) as u32);
            idx[k] = self.index(cell[0] + bx, cell[1] + by, cell[2] + bz) as u32;
            let wx = if bx == 1 { frac[0] } else { 1.0 - frac[0] };
            let wy = if by == 1 { frac[1] } else { 1.0 - frac[1] };
            let wz = if bz == 1 { frac[2] } else { 1.0 - frac[2] };
            w[k] = wx * wy * wz;
        }
        (idx, w)
    }
}

/// The level structure of a hash grid, placed in a parameter layout.
#[derive(Clone, Debug, PartialEq)]
pub struct HashGrid {
    pub config: HashGridConfig,
    pub levels: Vec<Level>,
}

impl HashGrid {
    /// Lays out the level tables as tensors `{prefix}level_NN` of shape `[entries, 2]`.
    pub fn new(config: HashGridConfig, prefix: &str, layout: &mut ParamLayout) -> Self {
        let max_entries = 1usize << config.log2_table_size;
        let levels = (0..config.levels)
            .map(|l| {
                let resolution = geometric(
                    config.base_resolution,
                    config.max_resolution,
                    config.levels,
                    l,
                );
                let vertices = (resolution as usize + 1).pow(3);
                let dense = vertices <= max_entries;
                let entries = if dense { vertices } else { max_entries };
                let offset = layout.push(format!("{prefix}level_{l:02}"), &[entries, FEATURES]);
                Level {
                    resolution,
                    entries,
                    dense,
                    offset,
                }
            })
            .collect();
        HashGrid { config, levels }
    }

    /// Encoded width: `levels * FEATURES`.
    pub fn dims(&self) -> usize {
        self.levels.len() * FEATURES
    }

    /// Number of parameters of all tables.
    pub fn num_params(&self) -> usize {
        self.levels.iter().map(|l| l.entries * FEATURES).sum()
    }

    /// The range of the parameter vector the tables occupy.
    pub fn param_range(&self) -> std::ops::Range<usize> {
        let start = self.levels.first().map_or(0, |l| l.offset);
        start..start + self.num_params()
    }

    /// Table values `U(-1e-4, 1e-4)` (the paper's initialisation) written into `params`.
    pub fn init(&self, params: &mut [f32], rng: &mut Rng) {
        for v in &mut params[self.param_range()] {
            *v = rng.range(-1e-4, 1e-4);
        }
    }

    /// Encodes `n` unit-cube points (packed `n x 3`) into `out` (`n x dims()`).
    pub fn encode(&self, params: &[f32], points: &[f32], out: &mut [f32]) {
        let layout = Layout::by_sample(self.levels.len());
        encode_levels(&self.levels, params, points, layout, out);
    }

    /// [`encode`](Self::encode) into `out` laid out level by level (level `l`'s features of
    /// every point, then level `l + 1`'s), as [`encode_bwd_by_level`](Self::encode_bwd_by_level)
    /// reads gradients.
    pub fn encode_by_level(&self, params: &[f32], points: &[f32], out: &mut [f32]) {
        let layout = Layout::by_level(points.len() / 3);
        encode_levels(&self.levels, params, points, layout, out);
    }

    /// [`encode`](Self::encode) one sample at a time (its grouping and prefetch, without
    /// the AVX2 loops): their reference and their benchmark's baseline.
    pub fn encode_scalar(&self, params: &[f32], points: &[f32], out: &mut [f32]) {
        let levels: Vec<Scalar> = self.levels.iter().map(Scalar).collect();
        let layout = Layout::by_sample(levels.len());
        encode_levels(&levels, params, points, layout, out);
    }

    /// The plain per-sample loop that [`encode`](Self::encode) replaced (no grouping, no
    /// prefetch); kept as its reference and for `cargo bench --bench kernels`.
    pub fn encode_reference(&self, params: &[f32], points: &[f32], out: &mut [f32]) {
        let d = self.dims();
        for (l, level) in self.levels.iter().enumerate() {
            let table = &params[level.offset..][..level.entries * FEATURES];
            for (s, u) in points.chunks_exact(3).enumerate() {
                let (idx, w) = level.corners([u[0], u[1], u[2]]);
                let mut f = [0f32; FEATURES];
                for k in 0..8 {
                    let e = &table[idx[k] as usize * FEATURES..][..FEATURES];
                    f[0] += w[k] * e[0];
                    f[1] += w[k] * e[1];
                }
                out[s * d + l * FEATURES..][..FEATURES].copy_from_slice(&f);
            }
        }
    }

    /// Backward of [`encode`](Self::encode): scatters `d_out` (`n x dims()`) into the table
    /// gradients, marking the blocks it touches.
    pub fn encode_bwd(&self, points: &[f32], d_out: &[f32], grads: &mut Grads) {
        let layout = Layout::by_sample(self.levels.len());
        encode_levels_bwd(&self.levels, points, d_out, layout, grads);
    }

    /// [`encode_bwd`](Self::encode_bwd) with `d_out` laid out level by level (level `l`'s
    /// gradients in a plane of `plane` points, [`FEATURES`] each, the first of them the
    /// gradients of `points`, then level `l + 1`'s plane): a pass over one level then reads
    /// its gradients in sequence.
    pub fn encode_bwd_by_level(
        &self,
        points: &[f32],
        d_out: &[f32],
        plane: usize,
        grads: &mut Grads,
    ) {
        assert!(points.len() / 3 <= plane, "more points than a plane holds");
        let layout = Layout::by_level(plane);
        encode_levels_bwd(&self.levels, points, d_out, layout, grads);
    }
}

impl HashGrid {
    /// Backward of [`encode`](Self::encode) with respect to the input points: adds
    /// `dL/d point` (`n x 3`, unit-cube coordinates) to `d_points`, given `d_out`. Camera
    /// refinement needs it: a pose moves the samples, and the trilinear weights carry the
    /// gradient (`dw/du = +-res * product of the other two axes' weights`); points clamped
    /// at the cube's faces get none along the clamped axis.
    pub fn encode_input_bwd(
        &self,
        params: &[f32],
        points: &[f32],
        d_out: &[f32],
        d_points: &mut [f32],
    ) {
        let d = self.dims();
        for (l, level) in self.levels.iter().enumerate() {
            let table = &params[level.offset..][..level.entries * FEATURES];
            let res = level.resolution as f32;
            for (s, u) in points.chunks_exact(3).enumerate() {
                let g = &d_out[s * d + l * FEATURES..][..FEATURES];
                if g[0] == 0.0 && g[1] == 0.0 {
                    continue;
                }
                let (idx, _) = level.corners([u[0], u[1], u[2]]);
                let mut frac = [0f32; 3];
                let mut inside = [0f32; 3];
                for a in 0..3 {
                    let p = u[a].clamp(0.0, 1.0) * res;
                    let c = (p as u32).min(level.resolution - 1);
                    frac[a] = p - c as f32;
                    inside[a] = if (0.0..=1.0).contains(&u[a]) {
                        res
                    } else {
                        0.0
                    };
                }
                for k in 0..8 {
                    let e = &table[idx[k] as usize * FEATURES..][..FEATURES];
                    let ge = g[0] * e[0] + g[1] * e[1];
                    let b = [k & 1, (k >> 1) & 1, (k >> 2) & 1];
                    let w: [f32; 3] =
                        std::array::from_fn(|a| if b[a] == 1 { frac[a] } else { 1.0 - frac[a] });
                    for a in 0..3 {
                        let sign = if b[a] == 1 { 1.0 } else { -1.0 };
                        let others = w[(a + 1) % 3] * w[(a + 2) % 3];
                        d_points[s * 3 + a] += ge * sign * others * inside[a];
                    }
                }
            }
        }
    }
}

/// Level `l`'s resolution of `levels` growing geometrically from `base` to `max` (at
/// least `base`, at least 1).
pub(crate) fn geometric(base: usize, max: usize, levels: usize, l: usize) -> u32 {
    let (lo, hi) = (base as f64, max.max(base) as f64);
    let growth = if levels > 1 {
        ((hi.ln() - lo.ln()) / (levels - 1) as f64).exp()
    } else {
        1.0
    };
    ((lo * growth.powi(l as i32)).round() as u32).max(1)
}

/// Samples whose corners are computed (and their table lines prefetched) before any is
/// read: the tables of fine levels are far larger than the caches, so the gathers are
/// memory-bound, and issuing a group's loads early lets them overlap.
const GROUP: usize = 32;

/// A group's corners, corner-major (`idx[k][j]`: corner `k` of sample `j`), so that a
/// vectorised lattice writes one corner of several samples at once.
pub(crate) struct Corners<const C: usize> {
    pub(crate) idx: [[u32; GROUP]; C],
    pub(crate) w: [[f32; GROUP]; C],
}

impl<const C: usize> Default for Corners<C> {
    fn default() -> Self {
        Corners {
            idx: [[0; GROUP]; C],
            w: [[0.0; GROUP]; C],
        }
    }
}

impl<const C: usize> Corners<C> {
    /// The corners of `points` (packed `D` coordinates each, at most [`GROUP`] points) in
    /// `level`, their table lines prefetched.
    #[inline(always)]
    fn compute<const D: usize, L: Lattice<D, C>>(
        &mut self,
        level: &L,
        table: &[f32],
        points: &[f32],
    ) {
        level.group_corners(points, self);
        for k in 0..C {
            for &i in &self.idx[k][..points.len() / D] {
                prefetch(table, i as usize * FEATURES);
            }
        }
    }

    /// Sample `j`'s corners, as one sample's [`Lattice::corners`] gives them.
    #[inline(always)]
    pub(crate) fn set(&mut self, j: usize, idx: [u32; C], w: [f32; C]) {
        for k in 0..C {
            self.idx[k][j] = idx[k];
            self.w[k][j] = w[k];
        }
    }
}

/// A level of a hash grid over `D` coordinates (cells of `C = 2^D` corners): the
/// interpolation shared by the still grid and the space-time one.
pub(crate) trait Lattice<const D: usize, const C: usize> {
    /// Whether encoding through this lattice may use the vectorised loops where the CPU
    /// has them (off only for the scalar reference).
    #[cfg_attr(not(target_arch = "x86_64"), allow(dead_code))]
    const VECTORISED: bool = true;
    /// Where the level's table starts in the parameter vector (floats), and its entries.
    fn table(&self) -> (usize, usize);
    /// The corners of the cell holding `u` (coordinates in [0, 1]): table indices and
    /// interpolation weights.
    fn corners(&self, u: [f32; D]) -> ([u32; C], [f32; C]);
    /// The corners of a group of points (packed `D` coordinates each) into `out`: one at a
    /// time unless a lattice has a vectorised path.
    #[inline(always)]
    fn group_corners(&self, points: &[f32], out: &mut Corners<C>) {
        for (j, u) in points.chunks_exact(D).enumerate() {
            let (idx, w) = self.corners(std::array::from_fn(|a| u[a]));
            out.set(j, idx, w);
        }
    }
}

impl Lattice<3, 8> for Level {
    fn table(&self) -> (usize, usize) {
        (self.offset, self.entries)
    }
    #[inline(always)]
    fn corners(&self, u: [f32; 3]) -> ([u32; 8], [f32; 8]) {
        Level::corners(self, u)
    }
    /// Eight samples at a time where the CPU has AVX2 (the same numbers, [`grid_simd`]).
    #[inline(always)]
    fn group_corners(&self, points: &[f32], out: &mut Corners<8>) {
        #[cfg_attr(not(target_arch = "x86_64"), allow(unused_mut))]
        let mut done = 0;
        #[cfg(target_arch = "x86_64")]
        if grid_simd::available() {
            use grid_simd::LANES;
            let shape = self.shape();
            for (g, group) in points.chunks_exact(3 * LANES).enumerate() {
                let group: &[f32; 3 * LANES] = group.try_into().expect("chunks_exact");
                // SAFETY: AVX2 is present (checked above).
                unsafe { grid_simd::corners8(shape, group, &mut out.idx, &mut out.w, g * LANES) };
            }
            done = points.len() / (3 * LANES) * LANES;
        }
        for (j, u) in points.chunks_exact(3).enumerate().skip(done) {
            let (idx, w) = self.corners([u[0], u[1], u[2]]);
            out.set(j, idx, w);
        }
    }
}

/// A level encoded one sample at a time: see [`HashGrid::encode_scalar`].
struct Scalar<'a>(&'a Level);

impl Lattice<3, 8> for Scalar<'_> {
    const VECTORISED: bool = false;
    fn table(&self) -> (usize, usize) {
        self.0.table()
    }
    #[inline(always)]
    fn corners(&self, u: [f32; 3]) -> ([u32; 8], [f32; 8]) {
        self.0.corners(u)
    }
}

/// Encodes `n` points (packed `n x D`) into `out` (`n x levels x FEATURES`), level by level
/// (one table in cache at a time), a [`GROUP`] of samples' corners computed before any is
/// read.
pub(crate) fn encode_levels<const D: usize, const C: usize, L: Lattice<D, C>, const B: bool>(
    levels: &[L],
    params: &[f32],
    points: &[f32],
    layout: Layout<B>,
    out: &mut [f32],
) {
    let n = points.len() / D;
    assert!(out.len() >= n * levels.len() * FEATURES);
    #[cfg(target_arch = "x86_64")]
    let vectorised = L::VECTORISED && grid_simd::available();
    let mut corners = Corners::<C>::default();
    for (l, level) in levels.iter().enumerate() {
        let (offset, entries) = level.table();
        let table = &params[offset..][..entries * FEATURES];
        for first in (0..n).step_by(GROUP) {
            let len = GROUP.min(n - first);
            corners.compute(level, table, &points[first * D..(first + len) * D]);
            #[cfg_attr(not(target_arch = "x86_64"), allow(unused_mut))]
            let mut j = 0;
            #[cfg(target_arch = "x86_64")]
            if vectorised {
                use grid_simd::LANES;
                while j + LANES <= len {
                    // SAFETY: AVX2 is present; the corners index this level's table.
                    let f = unsafe { grid_simd::interpolate8(table, &corners.idx, &corners.w, j) };
                    for i in 0..LANES {
                        let row = &mut out[layout.at(l, first + j + i)..][..FEATURES];
                        row.copy_from_slice(&[f[0][i], f[1][i]]);
                    }
                    j += LANES;
                }
            }
            for j in j..len {
                let mut f = [0f32; FEATURES];
                for k in 0..C {
                    let (i, w) = (corners.idx[k][j], corners.w[k][j]);
                    let e = &table[i as usize * FEATURES..][..FEATURES];
                    f[0] += w * e[0];
                    f[1] += w * e[1];
                }
                out[layout.at(l, first + j)..][..FEATURES].copy_from_slice(&f);
            }
        }
    }
}

/// Backward of [`encode_levels`]: scatters `d_out` into the tables' gradients, marking
/// the blocks it touches.
pub(crate) fn encode_levels_bwd<const D: usize, const C: usize, L: Lattice<D, C>, const B: bool>(
    levels: &[L],
    points: &[f32],
    d_out: &[f32],
    layout: Layout<B>,
    grads: &mut Grads,
) {
    let n = points.len() / D;
    let mut corners = Corners::<C>::default();
    for (l, level) in levels.iter().enumerate() {
        let (offset, entries) = level.table();
        for first in (0..n).step_by(GROUP) {
            let len = GROUP.min(n - first);
            let table = &grads.values_mut()[offset..][..entries * FEATURES];
            corners.compute(level, table, &points[first * D..(first + len) * D]);
            for j in 0..len {
                let g = &d_out[layout.at(l, first + j)..][..FEATURES];
                if g[0] == 0.0 && g[1] == 0.0 {
                    continue;
                }
                for k in 0..C {
                    let at = offset + corners.idx[k][j] as usize * FEATURES;
                    let w = corners.w[k][j];
                    grads.add_pair(at, [w * g[0], w * g[1]]);
                }
            }
        }
    }
}

/// Where level `l` of point `s` starts in a buffer of encodings (or of their gradients):
/// each point's levels together (`BY_LEVEL = false`, as the encoding writes them) or each
/// level's points together. A constant, so each loop is compiled for its own arithmetic.
#[derive(Clone, Copy)]
pub(crate) struct Layout<const BY_LEVEL: bool> {
    /// Levels (by point) or points (by level).
    count: usize,
}

impl Layout<false> {
    /// Each point's levels together (`n x levels x FEATURES`).
    pub(crate) fn by_sample(levels: usize) -> Self {
        Layout { count: levels }
    }
}

impl Layout<true> {
    /// Each level's points together (`levels x n x FEATURES`).
    pub(crate) fn by_level(n: usize) -> Self {
        Layout { count: n }
    }
}

impl<const BY_LEVEL: bool> Layout<BY_LEVEL> {
    #[inline(always)]
    fn at(self, l: usize, s: usize) -> usize {
        if BY_LEVEL {
            (l * self.count + s) * FEATURES
        } else {
            (s * self.count + l) * FEATURES
        }
    }
}

/// Hints the cache to fetch `data[at]`; a no-op off x86-64 and out of bounds.
#[inline(always)]
fn prefetch(data: &[f32], at: usize) {
    #[cfg(target_arch = "x86_64")]
    if let Some(v) = data.get(at) {
        // SAFETY: prefetching has no architectural effect; the address is inside `data`.
        unsafe {
            std::arch::x86_64::_mm_prefetch::<{ std::arch::x86_64::_MM_HINT_T0 }>(
                (v as *const f32).cast::<i8>(),
            )
        };
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The gradient with respect to the input point against central
    /// differences, on dense and hashed levels, away from cell faces.
    #[test]
    fn input_gradient_matches_finite_differences() {
        let mut layout = ParamLayout::default();
        let grid = HashGrid::new(
            HashGridConfig {
                levels: 4,
                log2_table_size: 8,
                base_resolution: 3,
                max_resolution: 40,
            },
            "h.",
            &mut layout,
        );
        let mut rng = Rng::new(4);
        let params: Vec<f32> = (0..layout.total).map(|_| rng.range(-1.0, 1.0)).collect();
        let n = 20;
        let points: Vec<f32> = (0..n * 3).map(|_| rng.range(0.05, 0.95)).collect();
        let d_out: Vec<f32> = (0..n * grid.dims()).map(|_| rng.range(-1.0, 1.0)).collect();
        let mut d_points = vec![0.0; n * 3];
        grid.encode_input_bwd(&params, &points, &d_out, &mut d_points);
        let loss = |pts: &[f32]| {
            let mut out = vec![0.0; n * grid.dims()];
            grid.encode(&params, pts, &mut out);
            out.iter()
                .zip(&d_out)
                .map(|(a, b)| (a * b) as f64)
                .sum::<f64>()
        };
        let (mut err, mut norm) = (0.0f64, 0.0f64);
        for i in 0..n * 3 {
            // Steps far smaller than the finest cell (1/40), so no face is crossed.
            let h = 1e-4;
            let (mut lo, mut hi) = (points.clone(), points.clone());
            lo[i] -= h;
            hi[i] += h;
            let fd = (loss(&hi) - loss(&lo)) / (2.0 * h as f64);
            err += (fd - d_points[i] as f64).powi(2);
            norm += fd * fd;
        }
        let rel = (err / norm).sqrt();
        assert!(rel < 2e-2, "relative error {rel}");
    }

    fn small() -> (HashGrid, ParamLayout) {
        let mut layout = ParamLayout::default();
        let grid = HashGrid::new(
            HashGridConfig {
                levels: 4,
                log2_table_size: 8,
                base_resolution: 2,
                max_resolution: 16,
            },
            "hash.",
            &mut layout,
        );
        (grid, layout)
    }

    #[test]
    fn levels_grow_geometrically_and_hash_once_too_fine() {
        let mut layout = ParamLayout::default();
        let grid = HashGrid::new(HashGridConfig::default(), "hash.", &mut layout);
        let res: Vec<u32> = grid.levels.iter().map(|l| l.resolution).collect();
        assert_eq!((res[0], res[15]), (16, 2048));
        assert!(res.windows(2).all(|w| w[1] > w[0]), "{res:?}");
        // Resolutions 16 .. 58 fit their (N+1)^3 vertices in 2^19 entries; 81 and up hash.
        assert!(grid.levels[0].dense && grid.levels[0].entries == 17 * 17 * 17);
        assert!(!grid.levels[15].dense && grid.levels[15].entries == 1 << 19);
        assert_eq!(layout.total, grid.num_params());
        assert_eq!(grid.param_range(), 0..layout.total);
    }

    #[test]
    fn interpolates_vertex_values_exactly_at_vertices_and_linearly_between() {
        let (grid, layout) = small();
        let mut params = vec![0.0; layout.total];
        let level = grid.levels[0]; // resolution 2, dense
        assert!(level.dense);
        // Feature 0 = x coordinate of the vertex, feature 1 = 1: the encoding of level 0
        // must then be exactly (x, 1) for any point (trilinear reproduces linear functions).
        for z in 0..=2u32 {
            for y in 0..=2u32 {
                for x in 0..=2u32 {
                    let i = level.offset + level.index(x, y, z) * FEATURES;
                    params[i] = x as f32 / 2.0;
                    params[i + 1] = 1.0;
                }
            }
        }
        let pts = [0.3, 0.8, 0.55, 1.0, 0.0, 0.25];
        let mut out = vec![0.0; 2 * grid.dims()];
        grid.encode(&params, &pts, &mut out);
        for s in 0..2 {
            let f = &out[s * grid.dims()..][..2];
            assert!(
                (f[0] - pts[3 * s]).abs() < 1e-6 && (f[1] - 1.0).abs() < 1e-6,
                "{f:?}"
            );
        }
    }

    /// Eight lanes of the AVX2 corners against the scalar corners, bit for bit, on dense
    /// and hashed levels, with points on the faces, outside the cube and at its corners.
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn eight_lanes_equal_the_scalar_corners() {
        use grid_simd::LANES;
        if !grid_simd::available() {
            eprintln!("skipped: this CPU has no AVX2");
            return;
        }
        let mut layout = ParamLayout::default();
        let grid = HashGrid::new(HashGridConfig::default(), "hash.", &mut layout);
        assert!(grid.levels.iter().any(|l| l.dense) && grid.levels.iter().any(|l| !l.dense));
        let mut rng = Rng::new(5);
        let mut points: Vec<f32> = (0..64 * 3).map(|_| rng.range(-0.2, 1.2)).collect();
        points[..12]
            .copy_from_slice(&[0.0, 1.0, 0.5, 1.0, 1.0, 1.0, 0.0, 0.0, 0.0, -0.0, 2.0, 0.25]);
        for level in &grid.levels {
            for group in points.chunks_exact(3 * LANES) {
                let mut idx = [[0u32; LANES]; 8];
                let mut w = [[0f32; LANES]; 8];
                let group: &[f32; 3 * LANES] = group.try_into().expect("a group");
                // SAFETY: AVX2 was checked above.
                unsafe { grid_simd::corners8(level.shape(), group, &mut idx, &mut w, 0) };
                for j in 0..LANES {
                    let (want_idx, want_w) =
                        level.corners([group[3 * j], group[3 * j + 1], group[3 * j + 2]]);
                    for k in 0..8 {
                        assert_eq!(idx[k][j], want_idx[k], "level {level:?}, point {j}");
                        // Equal as numbers (a face's -0 weight may come out +0).
                        assert_eq!(w[k][j], want_w[k], "level {level:?}, point {j}");
                    }
                }
            }
        }
    }

    #[test]
    fn grouped_encoding_equals_the_reference_loop() {
        let mut layout = ParamLayout::default();
        let grid = HashGrid::new(HashGridConfig::default(), "hash.", &mut layout);
        let mut rng = Rng::new(3);
        let params: Vec<f32> = (0..layout.total).map(|_| rng.range(-1.0, 1.0)).collect();
        // Not a multiple of the group size, points on the faces included.
        let mut pts: Vec<f32> = (0..77 * 3).map(|_| rng.uniform()).collect();
        pts[..3].copy_from_slice(&[0.0, 1.0, 0.5]);
        let (mut a, mut b) = (vec![0.0; 77 * 32], vec![1.0; 77 * 32]);
        grid.encode(&params, &pts, &mut a);
        grid.encode_reference(&params, &pts, &mut b);
        assert_eq!(a, b);
        grid.encode_scalar(&params, &pts, &mut b);
        assert_eq!(a, b);
    }

    /// The backward with vectorised corners scatters exactly what the per-sample loop does.
    #[test]
    fn backward_with_grouped_corners_equals_the_per_sample_loop() {
        let mut layout = ParamLayout::default();
        let grid = HashGrid::new(HashGridConfig::default(), "hash.", &mut layout);
        let mut rng = Rng::new(6);
        let n = 45;
        let pts: Vec<f32> = (0..n * 3).map(|_| rng.range(-0.1, 1.1)).collect();
        let d_out: Vec<f32> = (0..n * grid.dims()).map(|_| rng.range(-1.0, 1.0)).collect();
        let mut grouped = crate::nn::GradBuffer::new(layout.total);
        grid.encode_bwd(&pts, &d_out, &mut grouped.all());
        let mut plain = vec![0f32; layout.total];
        let d = grid.dims();
        for (l, level) in grid.levels.iter().enumerate() {
            for (s, u) in pts.chunks_exact(3).enumerate() {
                let (idx, w) = level.corners([u[0], u[1], u[2]]);
                for k in 0..8 {
                    for f in 0..FEATURES {
                        plain[level.offset + idx[k] as usize * FEATURES + f] +=
                            w[k] * d_out[s * d + l * FEATURES + f];
                    }
                }
            }
        }
        assert_eq!(grouped.values, plain);
    }

    #[test]
    fn backward_matches_finite_differences() {
        let (grid, layout) = small();
        let mut rng = Rng::new(4);
        let params: Vec<f32> = (0..layout.total).map(|_| rng.range(-1.0, 1.0)).collect();
        let n = 5;
        let pts: Vec<f32> = (0..n * 3).map(|_| rng.uniform()).collect();
        let d_out: Vec<f32> = (0..n * grid.dims()).map(|_| rng.range(-1.0, 1.0)).collect();
        let loss = |p: &[f32]| -> f64 {
            let mut out = vec![0.0; n * grid.dims()];
            grid.encode(p, &pts, &mut out);
            out.iter().zip(&d_out).map(|(a, b)| (a * b) as f64).sum()
        };
        let mut grads = crate::nn::GradBuffer::new(layout.total);
        grid.encode_bwd(&pts, &d_out, &mut grads.all());
        let mut checked = 0;
        for i in 0..layout.total {
            let g = grads.values[i];
            if g == 0.0 {
                continue;
            }
            assert!(
                grads.is_dirty(i),
                "gradient {i} written without marking its block"
            );
            let h = 1e-2;
            let (mut a, mut b) = (params.clone(), params.clone());
            a[i] += h;
            b[i] -= h;
            let fd = (loss(&a) - loss(&b)) / (2.0 * h as f64);
            assert!((fd - g as f64).abs() < 1e-3, "param {i}: fd {fd} vs {g}");
            checked += 1;
        }
        assert!(checked > 20, "only {checked} parameters received gradient");
        // Parameters the points never touch get exactly zero gradient.
        let untouched = (0..layout.total)
            .filter(|&i| grads.values[i] == 0.0)
            .count();
        assert!(untouched > 0);
    }
}
