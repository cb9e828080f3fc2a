//! A multiresolution hash encoding of space and time, `(x, y, z, t)`, for scenes that move.
//!
//! The hash grid's levels (see [`super::hash_grid`]) with a fourth axis: level `l` has
//! `N_l` cells per spatial axis and `T_l` along time, both growing geometrically, and a
//! point's features are the quadrilinear interpolation of its cell's sixteen corners. A
//! level whose `(N + 1)^3 (T + 1)` vertices fit its table is indexed densely, a finer one
//! through the hash `x ^ y * P1 ^ z * P2 ^ t * P3 mod T` (Instant-NGP's primes).
//!
//! The fast field adds these features to its still hash grid's (`field::fast`): what
//! stands still is learnt once from every photo by the still grid, and this grid holds
//! what changes, its coarse time cells shared by the photos of neighbouring moments.

use serde::{Deserialize, Serialize};

use super::hash_grid::{encode_levels, encode_levels_bwd, geometric, Lattice, Layout, FEATURES};
use crate::nn::{Grads, ParamLayout};
use crate::rng::Rng;

const PRIME_Y: u32 = 2_654_435_761;
const PRIME_Z: u32 = 805_459_861;
const PRIME_T: u32 = 3_674_653_429;

/// Corners of a cell in four dimensions.
const CORNERS: usize = 16;

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct SpaceTimeConfig {
    pub levels: usize,
    /// At most `2^log2_table_size` entries per level.
    pub log2_table_size: u32,
    /// Cells per spatial axis of the coarsest and the finest level.
    pub base_resolution: usize,
    pub max_resolution: usize,
    /// Cells along time of the coarsest and the finest level.
    pub base_time_resolution: usize,
    pub max_time_resolution: usize,
}

impl Default for SpaceTimeConfig {
    fn default() -> Self {
        SpaceTimeConfig {
            levels: 8,
            log2_table_size: 18,
            base_resolution: 16,
            // Coarser than the still grid's finest: one photo per moment sees a moving
            // part, and finer space-time cells fit each photo's view of it instead of a
            // shape the neighbouring moments share (the still grid keeps the fine detail).
            max_resolution: 256,
            // Neighbouring moments share the finest time cells too. A cell per moment
            // (`--time-cells`) with the prior of smoothness in time gains early on a fast
            // motion, but measured level on it from 10 minutes on and 0.5-0.7 dB worse
            // on a slow one (standup at 10 and 30 minutes; `docs/benchmarks.md`).
            base_time_resolution: 4,
            max_time_resolution: 64,
        }
    }
}

/// The most cells along time the finest level may have (`--time-cells`): more than the
/// 200 moments of the longest scene measured, few enough that the finest level's cells stay
/// in a hash table of `2^18` entries without colliding everywhere.
pub const MAX_TIME_CELLS: usize = 256;

impl SpaceTimeConfig {
    /// The default grid with `cells` along time at its finest level, within the coarsest
    /// level's cells and [`MAX_TIME_CELLS`]. A cell per moment the training photos show
    /// keeps a photo's moment from being blended with its neighbours' at the finest level.
    pub fn with_time_cells(cells: usize) -> Self {
        let base = SpaceTimeConfig::default();
        SpaceTimeConfig {
            max_time_resolution: cells.clamp(base.base_time_resolution, MAX_TIME_CELLS),
            ..base
        }
    }
}

/// One level: its resolutions and where its table sits in the parameter vector.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SpaceTimeLevel {
    /// Cells per spatial axis.
    pub resolution: u32,
    /// Cells along time.
    pub time_resolution: u32,
    /// Table entries (`FEATURES` floats each).
    pub entries: usize,
    pub dense: bool,
    /// Offset of the table (in floats) in the parameter vector.
    pub offset: usize,
}

impl SpaceTimeLevel {
    #[inline(always)]
    fn index(&self, c: [u32; 4]) -> usize {
        if self.dense {
            let s = self.resolution + 1;
            (c[0] + s * (c[1] + s * (c[2] + s * c[3]))) as usize
        } else {
            ((c[0]
                ^ c[1].wrapping_mul(PRIME_Y)
                ^ c[2].wrapping_mul(PRIME_Z)
                ^ c[3].wrapping_mul(PRIME_T)) as usize)
                & (self.entries - 1)
        }
    }

    /// The sixteen corners of the cell holding `u` (unit-cube position, time in [0, 1]):
    /// table indices and quadrilinear weights.
    #[inline(always)]
    fn corners(&self, u: [f32; 4]) -> ([u32; CORNERS], [f32; CORNERS]) {
        let res = [
            self.resolution,
            self.resolution,
            self.resolution,
            self.time_resolution,
        ];
        let mut cell = [0u32; 4];
        let mut frac = [0f32; 4];
        for a in 0..4 {
            let p = u[a].clamp(0.0, 1.0) * res[a] as f32;
            let c = (p as u32).min(res[a] - 1);
            cell[a] = c;
            frac[a] = p - c as f32;
        }
        let mut idx = [0u32; CORNERS];
        let mut w = [0f32; CORNERS];
        for k in 0..CORNERS {
            let mut corner = cell;
            let mut weight = 1.0;
            for a in 0..4 {
                if (k >> a) & 1 == 1 {
                    corner[a] += 1;
                    weight *= frac[a];
                } else {
                    weight *= 1.0 - frac[a];
                }
            }
            idx[k] = self.index(corner) as u32;
            w[k] = weight;
        }
        (idx, w)
    }
}

/// The level structure of a space-time grid, placed in a parameter layout.
#[derive(Clone, Debug, PartialEq)]
pub struct SpaceTimeGrid {
    pub config: SpaceTimeConfig,
    pub levels: Vec<SpaceTimeLevel>,
}

impl SpaceTimeGrid {
    /// Lays out the level tables as tensors `{prefix}level_NN` of shape `[entries, 2]`.
    pub fn new(config: SpaceTimeConfig, prefix: &str, layout: &mut ParamLayout) -> Self {
        let max_entries = 1usize << config.log2_table_size;
        let levels = (0..config.levels)
            .map(|l| {
                let resolution = geometric(
                    config.base_resolution,
                    config.max_resolution,
                    config.levels,
                    l,
                );
                let time_resolution = geometric(
                    config.base_time_resolution,
                    config.max_time_resolution,
                    config.levels,
                    l,
                );
                let vertices = (resolution as usize + 1).pow(3) * (time_resolution as usize + 1);
                let dense = vertices <= max_entries;
                let entries = if dense { vertices } else { max_entries };
                let offset = layout.push(format!("{prefix}level_{l:02}"), &[entries, FEATURES]);
                SpaceTimeLevel {
                    resolution,
                    time_resolution,
                    entries,
                    dense,
                    offset,
                }
            })
            .collect();
        SpaceTimeGrid { config, levels }
    }

    /// Encoded width: `levels * FEATURES`.
    pub fn dims(&self) -> usize {
        self.levels.len() * FEATURES
    }

    /// The range of the parameter vector the tables occupy.
    pub fn param_range(&self) -> std::ops::Range<usize> {
        let start = self.levels.first().map_or(0, |l| l.offset);
        let len: usize = self.levels.iter().map(|l| l.entries * FEATURES).sum();
        start..start + len
    }

    /// Table values `U(-1e-4, 1e-4)`, as the still grid's, written into `params`.
    pub fn init(&self, params: &mut [f32], rng: &mut Rng) {
        for v in &mut params[self.param_range()] {
            *v = rng.range(-1e-4, 1e-4);
        }
    }

    /// Encodes `n` points (packed `n x 4`: unit-cube position, then time) into `out`
    /// (`n x dims()`).
    pub fn encode(&self, params: &[f32], points: &[f32], out: &mut [f32]) {
        let layout = Layout::by_sample(self.levels.len());
        encode_levels(&self.levels, params, points, layout, out);
    }

    /// Backward of [`encode`](Self::encode): scatters `d_out` (`n x dims()`) into the table
    /// gradients, marking the blocks it touches.
    pub fn encode_bwd(&self, points: &[f32], d_out: &[f32], grads: &mut Grads) {
        let layout = Layout::by_sample(self.levels.len());
        encode_levels_bwd(&self.levels, points, d_out, layout, grads);
    }
}

impl Lattice<4, CORNERS> for SpaceTimeLevel {
    fn table(&self) -> (usize, usize) {
        (self.offset, self.entries)
    }
    #[inline(always)]
    fn corners(&self, u: [f32; 4]) -> ([u32; CORNERS], [f32; CORNERS]) {
        SpaceTimeLevel::corners(self, u)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::nn::GradBuffer;

    fn small() -> (SpaceTimeGrid, ParamLayout) {
        let mut layout = ParamLayout::default();
        let grid = SpaceTimeGrid::new(
            SpaceTimeConfig {
                levels: 3,
                log2_table_size: 9,
                base_resolution: 2,
                max_resolution: 12,
                base_time_resolution: 2,
                max_time_resolution: 8,
            },
            "motion.",
            &mut layout,
        );
        (grid, layout)
    }

    #[test]
    fn the_finest_time_cells_are_set_within_bounds() {
        let base = SpaceTimeConfig::default();
        for (asked, cells) in [
            (0, base.base_time_resolution),
            (3, base.base_time_resolution),
            (150, 150),
            (200, 200),
            (5000, MAX_TIME_CELLS),
        ] {
            let c = SpaceTimeConfig::with_time_cells(asked);
            assert_eq!(c.max_time_resolution, cells, "{asked} cells asked");
            // Only the time axis changes.
            assert_eq!(
                SpaceTimeConfig {
                    max_time_resolution: base.max_time_resolution,
                    ..c
                },
                base
            );
        }
    }

    #[test]
    fn levels_grow_in_space_and_time_and_hash_once_too_fine() {
        let (grid, layout) = small();
        let res: Vec<(u32, u32)> = grid
            .levels
            .iter()
            .map(|l| (l.resolution, l.time_resolution))
            .collect();
        assert_eq!(res, [(2, 2), (5, 4), (12, 8)]);
        // 3^3 * 3 = 81 and 6^3 * 5 = 1080 vertices: the first fits 512 entries, the
        // second hashes.
        assert!(grid.levels[0].dense && grid.levels[0].entries == 81);
        assert!(!grid.levels[1].dense && grid.levels[1].entries == 512);
        assert_eq!(grid.param_range(), 0..layout.total);
    }

    #[test]
    fn interpolates_linearly_in_time() {
        let (grid, layout) = small();
        let level = grid.levels[0];
        let mut params = vec![0.0; layout.total];
        // Feature 0 = the vertex's time, feature 1 = its x: both reproduced exactly.
        for t in 0..=2u32 {
            for z in 0..=2u32 {
                for y in 0..=2u32 {
                    for x in 0..=2u32 {
                        let i = level.offset + level.index([x, y, z, t]) * FEATURES;
                        params[i] = t as f32 / 2.0;
                        params[i + 1] = x as f32 / 2.0;
                    }
                }
            }
        }
        let pts = [0.3, 0.8, 0.55, 0.35, 1.0, 0.0, 0.25, 0.9];
        let mut out = vec![0.0; 2 * grid.dims()];
        grid.encode(&params, &pts, &mut out);
        for s in 0..2 {
            let f = &out[s * grid.dims()..][..2];
            let want = [pts[4 * s + 3], pts[4 * s]];
            assert!(
                (f[0] - want[0]).abs() < 1e-6 && (f[1] - want[1]).abs() < 1e-6,
                "{f:?} vs {want:?}"
            );
        }
    }

    #[test]
    fn backward_matches_finite_differences() {
        let (grid, layout) = small();
        let mut rng = Rng::new(7);
        let params: Vec<f32> = (0..layout.total).map(|_| rng.range(-1.0, 1.0)).collect();
        let n = 6;
        let pts: Vec<f32> = (0..n * 4).map(|_| rng.uniform()).collect();
        let d_out: Vec<f32> = (0..n * grid.dims()).map(|_| rng.range(-1.0, 1.0)).collect();
        let loss = |p: &[f32]| -> f64 {
            let mut out = vec![0.0; n * grid.dims()];
            grid.encode(p, &pts, &mut out);
            out.iter().zip(&d_out).map(|(a, b)| (a * b) as f64).sum()
        };
        let mut grads = GradBuffer::new(layout.total);
        grid.encode_bwd(&pts, &d_out, &mut grads.all());
        let mut checked = 0;
        for i in 0..layout.total {
            let g = grads.values[i];
            if g == 0.0 {
                continue;
            }
            assert!(grads.is_dirty(i), "gradient {i} written without its block");
            let h = 1e-2;
            let (mut a, mut b) = (params.clone(), params.clone());
            a[i] += h;
            b[i] -= h;
            let fd = (loss(&a) - loss(&b)) / (2.0 * h as f64);
            assert!((fd - g as f64).abs() < 1e-3, "param {i}: fd {fd} vs {g}");
            checked += 1;
        }
        assert!(checked > 40, "only {checked} parameters received gradient");
    }

    #[test]
    fn different_moments_read_different_features() {
        let (grid, layout) = small();
        let mut rng = Rng::new(1);
        let params: Vec<f32> = (0..layout.total).map(|_| rng.range(-1.0, 1.0)).collect();
        let pts = [0.4, 0.4, 0.4, 0.1, 0.4, 0.4, 0.4, 0.9];
        let mut out = vec![0.0; 2 * grid.dims()];
        grid.encode(&params, &pts, &mut out);
        let (a, b) = out.split_at(grid.dims());
        assert!(a.iter().zip(b).any(|(x, y)| (x - y).abs() > 1e-3));
    }

    /// The batch encoding (eight samples at a time where the CPU has AVX2) gives each
    /// sample exactly the per-sample sum of its corners.
    #[test]
    fn batch_encoding_equals_the_per_sample_sum() {
        let (grid, layout) = small();
        let mut rng = Rng::new(8);
        let params: Vec<f32> = (0..layout.total).map(|_| rng.range(-1.0, 1.0)).collect();
        let n = 37;
        let pts: Vec<f32> = (0..n * 4).map(|_| rng.range(-0.1, 1.1)).collect();
        let mut out = vec![0.0; n * grid.dims()];
        grid.encode(&params, &pts, &mut out);
        for (s, u) in pts.chunks_exact(4).enumerate() {
            for (l, level) in grid.levels.iter().enumerate() {
                let (idx, w) = level.corners([u[0], u[1], u[2], u[3]]);
                let mut f = [0f32; FEATURES];
                for k in 0..CORNERS {
                    for (c, v) in f.iter_mut().enumerate() {
                        *v += w[k] * params[level.offset + idx[k] as usize * FEATURES + c];
                    }
                }
                assert_eq!(
                    out[s * grid.dims() + l * FEATURES..][..FEATURES],
                    f,
                    "sample {s}"
                );
            }
        }
    }
}
