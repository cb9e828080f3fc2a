//! The fast radiance field (after Instant-NGP): a multiresolution hash encoding of the
//! position, a one-hidden-layer density network whose first output is log-density, and a
//! colour network fed by the spherical harmonics of the view direction and the density
//! network's other outputs.
//!
//! ```text
//! x -> hash grid (16 x 2) -> [64, ReLU] -> 16 outputs: sigma = exp(o_0), geo = o_1..o_15
//! d -> SH degree 4 (16) ---------------------------------------+
//! [SH(d), geo] (31) -> [64, ReLU] -> [64, ReLU] -> 3, sigmoid -> rgb
//! ```
//!
//! Work mapping: a call evaluates a batch of `n` samples of any rays (the caller packs them),
//! one stage at a time: the encoding level by level, then each layer as one single-threaded
//! GEMM with its activation applied in the same pass over the output. The layers have no
//! biases (as in tiny-cuda-nn's fully fused MLPs). Every buffer lives in a [`FastWorkspace`]
//! reused across calls, so a training step allocates nothing once it has warmed up.

use serde::{Deserialize, Serialize};

pub use super::level_weights::level_weight;
use super::level_weights::{cell_factor, fill_level_weights};
use crate::encoding::hash_grid::{HashGrid, HashGridConfig, FEATURES};
use crate::encoding::space_time_grid::{SpaceTimeConfig, SpaceTimeGrid};
use crate::encoding::spherical_harmonics::{sh4, sh4_bwd, SH_DIMS};
use crate::nn::activation::{relu, sigmoid};
use crate::nn::linalg::{matmul_in, MatRef, Precision};
use crate::nn::Grads;
use crate::nn::ParamLayout;
use crate::nn::{grow, resize_reused};
use crate::rng::Rng;
use crate::stage::{Field, FieldGrad, FieldInput, FieldOutput};
use crate::step_clock::{self, Stage};

/// Log-densities are clamped here before `exp` so one bad step cannot overflow to infinity.
pub const LOG_SIGMA_MAX: f32 = 15.0;

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FastFieldConfig {
    pub grid: HashGridConfig,
    /// Width of every hidden layer (64).
    pub hidden: usize,
    /// Outputs of the density network: log-density plus `geo_features - 1` features for the
    /// colour network (16).
    pub geo_features: usize,
    /// Half-extent of the scene box `[-bound, bound]^3` the grid covers (Blender: 1.5).
    pub bound: f32,
    /// Per-photo appearance (after NeRF in the Wild): a learned code of this many values
    /// per training photo, fed to the colour network only, so exposure and white balance
    /// that change from shot to shot do not bend the geometry. 0: none.
    #[serde(default)]
    pub appearance_dims: usize,
    /// Training photos with a code (the training split's size).
    #[serde(default)]
    pub appearance_images: usize,
    /// Anti-aliasing (after Zip-NeRF): each sample reads no hash-grid detail finer than
    /// its footprint. `None`: point samples, as Instant-NGP.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub antialias: Option<Antialias>,
    /// A moving scene (`--dynamic`): a hash grid of space and time whose features join the
    /// still grid's in the density network's first layer. `None`: a still scene.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub motion: Option<SpaceTimeConfig>,
    /// How many of the view direction's 16 spherical harmonics (degrees 0 to 3) reach the
    /// colour network: 16, or 4 (degrees 0 and 1: colour that changes only slowly with
    /// the view) for few-view training, where the finer harmonics let a photo's colours
    /// be explained by the view instead of the geometry. The others are fed as 0 and
    /// their weights start (and so stay) at 0.
    #[serde(default = "all_harmonics", skip_serializing_if = "is_all_harmonics")]
    pub view_harmonics: usize,
}

/// Every spherical harmonic of the view direction (the default).
fn all_harmonics() -> usize {
    SH_DIMS
}

fn is_all_harmonics(n: &usize) -> bool {
    *n >= SH_DIMS
}

/// Zip-NeRF's feature down-weighting: level `l` (`N_l` cells per axis) of a sample whose
/// footprint has standard deviation `sigma` (unit-cube units) is scaled by
/// `erf(1 / sqrt(8 sigma^2 N_l^2))`: about 1 where a cell is much larger than the
/// footprint, falling towards 0 where many cells fall inside it (their features would
/// average out over the footprint, and a point sample would alias instead).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Antialias {
    /// The footprint (field units) of samples that carry none: density queries of the
    /// occupancy grid and of meshes. The training rays' typical footprint, so those see
    /// what the training saw.
    pub reference_footprint: f32,
}

impl Default for FastFieldConfig {
    fn default() -> Self {
        FastFieldConfig {
            grid: HashGridConfig::default(),
            hidden: 64,
            geo_features: 16,
            bound: 1.5,
            appearance_dims: 0,
            appearance_images: 0,
            antialias: None,
            motion: None,
            view_harmonics: SH_DIMS,
        }
    }
}

#[derive(Clone, Debug, PartialEq)]
pub struct FastField {
    pub config: FastFieldConfig,
    pub grid: HashGrid,
    pub layout: ParamLayout,
    /// Offsets of the weight matrices, in order: density 0, 1, colour 0, 1, 2.
    weights: [usize; 5],
    /// Offset of the appearance codes (`images x dims`, row-major), when there are any.
    codes: Option<usize>,
    /// Weight of each hash-grid level's features (empty: all 1): camera refinement's
    /// coarse-to-fine schedule sets it during training.
    pub level_weights: Vec<f32>,
    /// Weight of each level in `dL/d position` only (empty: all 1), on top of
    /// `level_weights`: the straight-through coarse-to-fine schedule smooths the cameras'
    /// gradient without holding the field's own fit back.
    pub position_level_weights: Vec<f32>,
    /// Moving scenes: the space-time grid, and the offset of its first-layer weights
    /// (`motion dims x hidden`).
    pub motion: Option<SpaceTimeGrid>,
    motion_weight: Option<usize>,
}

/// When a moving field sees the samples of a call.
#[derive(Clone, Copy, Debug)]
enum Moments<'a> {
    /// Each its own (`n`).
    Each(&'a [f32]),
    /// All the same one.
    At(f32),
    /// Any: a moment drawn from each point's coordinates, so that density queries over
    /// many points (the occupancy grid's refreshes) see every moment.
    Any,
}

impl<'a> Moments<'a> {
    /// A forward's samples: their own moments, or moment 0 where they carry none.
    fn of(times: &'a [f32]) -> Self {
        if times.is_empty() {
            Moments::At(0.0)
        } else {
            Moments::Each(times)
        }
    }
}

/// The time-smoothness prior looks at every this-many-th sample of a batch: thousands of
/// pairs a step are enough for a prior, and each pair costs a space-time lookup forward and
/// two backward, so the sparser prior scored better at equal time than every fourth sample
/// (figures in `docs/benchmarks.md`).
pub const SMOOTH_STRIDE: usize = 16;

/// A moment in [0, 1) drawn from a unit-cube point's coordinates: the same point, the same
/// moment; points a jitter apart, unrelated ones.
pub(crate) fn moment_of_point(u: &[f32]) -> f32 {
    let bits = u[0].to_bits() ^ u[1].to_bits().rotate_left(11) ^ u[2].to_bits().rotate_left(22);
    let h = bits.wrapping_mul(0x9e37_79b1) ^ (bits >> 15);
    (h.wrapping_mul(0x85eb_ca6b) >> 8) as f32 / (1u32 << 24) as f32
}

/// Reused buffers of one thread (activations and their gradients).
#[derive(Default, Debug)]
pub struct FastWorkspace {
    unit: Vec<f32>,
    /// Moving scenes: `unit` with each sample's moment (`n x 4`), and its encoding.
    unit_time: Vec<f32>,
    enc_motion: Vec<f32>,
    d_enc_motion: Vec<f32>,
    /// The smoothness prior's points, the same a moment later, the latter's encoding, and
    /// the gradients of both.
    now: Vec<f32>,
    later: Vec<f32>,
    enc_later: Vec<f32>,
    d_smooth: Vec<f32>,
    /// Anti-aliased fields: each sample's weight of each level (`n x levels`).
    level_scale: Vec<f32>,
    enc: Vec<f32>,
    h: Vec<f32>,
    geo: Vec<f32>,
    colour_in: Vec<f32>,
    c1: Vec<f32>,
    c2: Vec<f32>,
    /// The samples an inference coloured ([`Field::infer_picked`]).
    picked: Vec<u32>,
    /// Densities of the last forward (one per sample).
    pub sigma: Vec<f32>,
    /// Colours of the last forward (three per sample).
    pub rgb: Vec<f32>,
    /// The mean appearance code, and each sample's code index, of the last forward.
    mean_code: Vec<f32>,
    code_index: Vec<u32>,
    d_logit: Vec<f32>,
    d_c2: Vec<f32>,
    d_c1: Vec<f32>,
    d_colour_in: Vec<f32>,
    d_geo: Vec<f32>,
    d_h: Vec<f32>,
    d_enc: Vec<f32>,
    /// Set to the samples to come: backward passes leave the hash grid's scatter for
    /// [`FastField::scatter_deferred`], keeping their points and encoding gradients here
    /// (level by level, room for that many samples).
    pub defer_grid: Option<usize>,
    /// The precision of the networks' products (training sets it; `f32` by default).
    pub products: Precision,
    deferred_unit: Vec<f32>,
    /// The waiting encoding gradients' planes while no share is encoded ahead; with one,
    /// they take the rows of `share_enc` its forwards have read.
    deferred_d_enc: Vec<f32>,
    /// A worker's share encoded ahead of its chunks ([`FastField::pre_encode`]): its points
    /// and their encodings level by level, the next chunk's first sample at `share_next`.
    share_unit: Vec<f32>,
    share_enc: Vec<f32>,
    share_next: usize,
}

impl FastWorkspace {
    /// Where the deferred encoding gradients wait, and how many samples a level's plane
    /// holds: the share's planes while one is encoded ahead (a chunk's gradients take the
    /// rows its forward has read, so the share's encodings and the gradients waiting cost
    /// the memory of one), else planes of their own with room for `room` samples.
    fn waiting_planes(&self, room: usize) -> (&[f32], usize) {
        if self.share_unit.is_empty() {
            (&self.deferred_d_enc, room)
        } else {
            (&self.share_enc, self.share_unit.len() / 3)
        }
    }

    /// How many waiting samples' gradients the planes can hold: with a share encoded
    /// ahead, only the rows its forwards have read.
    fn scatter_room(&self, room: usize) -> usize {
        if self.share_unit.is_empty() {
            room
        } else {
            self.share_next
        }
    }

    /// Keeps the last backward's `n` points and their encoding gradients (`e` a sample) for
    /// a deferred scatter, after those already waiting (`room` as in
    /// [`waiting_planes`](Self::waiting_planes)).
    fn keep_for_scatter(&mut self, n: usize, e: usize, room: usize) {
        let kept = self.deferred_unit.len() / 3;
        let (planes, room) = if self.share_unit.is_empty() {
            if kept == 0 {
                resize_reused(&mut self.deferred_d_enc, room * e, 0.0);
            }
            (&mut self.deferred_d_enc[..room * e], room)
        } else {
            (&mut self.share_enc[..], self.share_unit.len() / 3)
        };
        if kept == 0 {
            // The points never outgrow the planes' room (`Vec`'s doubling would).
            self.deferred_unit.reserve_exact(room * 3);
        }
        for (s, row) in self.d_enc[..n * e].chunks_exact(e).enumerate() {
            for (l, g) in row.chunks_exact(FEATURES).enumerate() {
                let at = (l * room + kept + s) * FEATURES;
                planes[at..at + FEATURES].copy_from_slice(g);
            }
        }
        self.deferred_unit.extend_from_slice(&self.unit[..n * 3]);
    }
}

/// `dz = dh * (h > 0)` in place.
fn relu_bwd(dh: &mut [f32], h: &[f32]) {
    for (d, &y) in dh.iter_mut().zip(h) {
        *d = if y > 0.0 { *d } else { 0.0 };
    }
}

/// Moves the colours of the picked samples, packed at the front of `rgb` (three values a
/// row), to their own rows (`picked` in increasing order), and zeroes the other rows. In
/// place from the back: a picked sample's row is never before its packed one.
fn spread_rows(rgb: &mut [f32], picked: &[u32]) {
    let mut end = rgb.len() / 3;
    for (r, &s) in picked.iter().enumerate().rev() {
        let s = s as usize;
        rgb[3 * (s + 1)..3 * end].fill(0.0);
        rgb.copy_within(3 * r..3 * r + 3, 3 * s);
        end = s;
    }
    rgb[..3 * end].fill(0.0);
}

/// The name of the per-photo appearance codes (`images x dims`) among the parameters.
pub const APPEARANCE_CODES: &str = "appearance.codes";

/// The mean of `codes` (rows of `dims` values) into `mean`: the look of
/// `Appearance::Mean`. Empty when there are no codes.
pub fn mean_code(codes: &[f32], dims: usize, mean: &mut Vec<f32>) {
    mean.clear();
    if dims == 0 {
        return;
    }
    mean.resize(dims, 0.0);
    let images = codes.len() / dims;
    for row in codes.chunks_exact(dims) {
        for (m, v) in mean.iter_mut().zip(row) {
            *m += v / images as f32;
        }
    }
}

impl FastField {
    pub fn new(config: FastFieldConfig) -> Self {
        let mut layout = ParamLayout::default();
        let grid = HashGrid::new(config.grid, "hash.", &mut layout);
        // Its tables right after the still grid's: hash tables update lazily, and the lazy
        // part of the parameter vector is its start.
        let motion = config
            .motion
            .map(|c| SpaceTimeGrid::new(c, "motion.", &mut layout));
        let (w, g) = (config.hidden, config.geo_features);
        let (images, dims) = (config.appearance_images, config.appearance_dims);
        let dims = if images > 0 { dims } else { 0 };
        let colour_in = SH_DIMS + g - 1 + dims;
        let weights = [
            layout.push("density.0.weight", &[grid.dims(), w]),
            layout.push("density.1.weight", &[w, g]),
            layout.push("colour.0.weight", &[colour_in, w]),
            layout.push("colour.1.weight", &[w, w]),
            layout.push("colour.2.weight", &[w, 3]),
        ];
        let motion_weight = motion
            .as_ref()
            .map(|m| layout.push("density.motion.weight", &[m.dims(), w]));
        // Last, so a model without codes has the same layout as before they existed.
        let codes = (dims > 0).then(|| layout.push(APPEARANCE_CODES, &[images, dims]));
        FastField {
            config,
            grid,
            layout,
            weights,
            codes,
            level_weights: Vec::new(),
            position_level_weights: Vec::new(),
            motion,
            motion_weight,
        }
    }

    /// Anti-aliased fields: each of `n` samples' weight of each level into `out`
    /// (`n x levels`), from their footprints (`n`, field units; empty: the reference
    /// footprint) and the coarse-to-fine schedule's level weights.
    fn level_scales(&self, footprints: &[f32], n: usize, out: &mut Vec<f32>) {
        let Some(aa) = self.config.antialias else {
            return;
        };
        let levels = &self.grid.levels;
        grow(out, n * levels.len());
        let to_unit = 0.5 / self.config.bound;
        let factors: Vec<f32> = levels.iter().map(|l| cell_factor(l.resolution)).collect();
        let schedule: Vec<f32> = (0..levels.len())
            .map(|l| self.level_weights.get(l).copied().unwrap_or(1.0))
            .collect();
        let sigma2: Vec<f32> = (0..n)
            .map(|s| {
                let sigma = footprints.get(s).copied().unwrap_or(aa.reference_footprint) * to_unit;
                sigma * sigma
            })
            .collect();
        fill_level_weights(&mut out[..n * levels.len()], &sigma2, &factors, &schedule);
    }

    /// Scales each level's features (`n x dims()`, in place) by its weight: the sample's
    /// own (`scales`, anti-aliased fields) or the level's (the coarse-to-fine schedule).
    fn weigh_levels(&self, values: &mut [f32], scales: &[f32]) {
        let f = crate::encoding::hash_grid::FEATURES;
        if self.config.antialias.is_some() {
            let levels = self.grid.levels.len();
            for (row, ws) in values
                .chunks_exact_mut(self.grid.dims())
                .zip(scales.chunks_exact(levels))
            {
                for (level, w) in row.chunks_exact_mut(f).zip(ws) {
                    level.iter_mut().for_each(|v| *v *= w);
                }
            }
            return;
        }
        if self.level_weights.is_empty() {
            return;
        }
        for row in values.chunks_exact_mut(self.grid.dims()) {
            for (level, w) in row.chunks_exact_mut(f).zip(&self.level_weights) {
                level.iter_mut().for_each(|v| *v *= w);
            }
        }
    }

    /// Values per appearance code (0 without codes).
    pub fn appearance_dims(&self) -> usize {
        if self.codes.is_some() {
            self.config.appearance_dims
        } else {
            0
        }
    }

    /// Where the space-time features' first-layer weights (`motion dims x hidden`) start
    /// in the parameter vector (moving fields).
    pub fn motion_weight_offset(&self) -> Option<usize> {
        self.motion_weight
    }

    /// Where the appearance codes (`images x dims`) start in the parameter vector.
    pub fn codes_offset(&self) -> Option<usize> {
        self.codes
    }

    /// The appearance codes, `images x dims` (empty without codes).
    pub fn codes<'a>(&self, params: &'a [f32]) -> &'a [f32] {
        match self.codes {
            Some(at) => {
                &params[at..][..self.config.appearance_images * self.config.appearance_dims]
            }
            None => &[],
        }
    }

    pub fn num_params(&self) -> usize {
        self.layout.total
    }

    /// The parameters of the two MLPs (everything after the hash tables).
    pub fn mlp_range(&self) -> std::ops::Range<usize> {
        let tables_end = match &self.motion {
            Some(m) => m.param_range().end,
            None => self.grid.param_range().end,
        };
        tables_end..self.layout.total
    }

    /// Offsets of the weight matrices in the parameter vector, in order: density 0, 1,
    /// colour 0, 1, 2 (each `inputs x outputs`, row-major).
    pub fn weight_offsets(&self) -> [usize; 5] {
        self.weights
    }

    pub fn colour_in_dims(&self) -> usize {
        SH_DIMS + self.config.geo_features - 1 + self.appearance_dims()
    }

    /// Glorot-uniform MLP weights, hash tables `U(-1e-4, 1e-4)`, appearance codes 0 (every
    /// photo starts with the mean look).
    pub fn init_params(&self, seed: u64) -> Vec<f32> {
        let mut rng = Rng::new(seed ^ 0xfa57);
        let mut p = self.layout.init_glorot(&mut rng);
        self.grid.init(&mut p, &mut rng);
        if let Some(m) = &self.motion {
            m.init(&mut p, &mut rng);
        }
        if let Some(at) = self.codes {
            let n = self.config.appearance_images * self.config.appearance_dims;
            p[at..at + n].iter_mut().for_each(|v| *v = 0.0);
        }
        // The weights of the harmonics the colour network is not fed start at 0; with
        // their inputs 0 they get no gradient, and they give the view direction none.
        let (used, width) = (self.view_harmonics(), self.config.hidden);
        p[self.weights[2] + used * width..][..(SH_DIMS - used) * width].fill(0.0);
        p
    }

    /// The view direction's spherical harmonics the colour network is fed (the first
    /// ones; see [`FastFieldConfig::view_harmonics`]).
    pub fn view_harmonics(&self) -> usize {
        self.config.view_harmonics.clamp(1, SH_DIMS)
    }

    /// Keeps in `ws` each sample's code index and the mean code, for the forward and its
    /// backward.
    fn gather_codes(&self, params: &[f32], appearance: &[u32], n: usize, ws: &mut FastWorkspace) {
        let dims = self.appearance_dims();
        if dims == 0 {
            return;
        }
        let images = self.config.appearance_images;
        mean_code(self.codes(params), dims, &mut ws.mean_code);
        ws.code_index.clear();
        ws.code_index
            .extend((0..n).map(|s| match appearance.get(s) {
                Some(&i) if (i as usize) < images => i,
                _ => crate::stage::MEAN_APPEARANCE,
            }));
    }

    fn weight<'a>(&self, params: &'a [f32], k: usize, rows: usize, cols: usize) -> MatRef<'a> {
        MatRef::new(&params[self.weights[k]..][..rows * cols], rows, cols)
    }

    /// Multiply-adds of one sample through both networks (the encoding not counted).
    pub fn macs_per_sample(&self) -> usize {
        let (w, g) = (self.config.hidden, self.config.geo_features);
        let motion = self.motion.as_ref().map_or(0, |m| m.dims());
        (self.grid.dims() + motion) * w + w * g + self.colour_in_dims() * w + w * w + w * 3
    }

    /// Moving scenes: `ws.unit` with each of the `n` samples' moment into `ws.unit_time`,
    /// and its space-time encoding into `ws.enc_motion`.
    fn encode_motion(&self, params: &[f32], moments: Moments, n: usize, ws: &mut FastWorkspace) {
        let Some(motion) = &self.motion else {
            return;
        };
        grow(&mut ws.unit_time, n * 4);
        grow(&mut ws.enc_motion, n * motion.dims());
        for (s, (u, out)) in ws
            .unit
            .chunks_exact(3)
            .zip(ws.unit_time.chunks_exact_mut(4))
            .take(n)
            .enumerate()
        {
            out[..3].copy_from_slice(u);
            out[3] = match moments {
                Moments::Each(times) => times[s],
                Moments::At(t) => t,
                Moments::Any => moment_of_point(u),
            };
        }
        motion.encode(params, &ws.unit_time[..n * 4], &mut ws.enc_motion);
    }

    /// World positions (packed `n x 3`) into the unit cube of the scene box.
    fn to_unit(&self, positions: &[f32], unit: &mut [f32]) {
        let b = self.config.bound;
        let inv = 0.5 / b;
        for (u, &p) in unit.iter_mut().zip(positions) {
            *u = (p + b) * inv;
        }
    }

    /// Density network only: leaves `ws.sigma` (and `ws.geo`) for `n` positions with their
    /// `footprints` (see [`FieldInput::footprints`]).
    fn eval_density(
        &self,
        params: &[f32],
        positions: &[f32],
        footprints: &[f32],
        moments: Moments,
        ws: &mut FastWorkspace,
    ) {
        let n = positions.len() / 3;
        let products = ws.products;
        let (w, g, e) = (
            self.config.hidden,
            self.config.geo_features,
            self.grid.dims(),
        );
        grow(&mut ws.unit, n * 3);
        grow(&mut ws.enc, n * e);
        grow(&mut ws.h, n * w);
        grow(&mut ws.geo, n * g);
        grow(&mut ws.sigma, n);
        self.to_unit(positions, &mut ws.unit[..n * 3]);
        let clock = step_clock::start(Stage::Encoding);
        if !self.take_pre_encoded(n, ws) {
            self.grid.encode(params, &ws.unit[..n * 3], &mut ws.enc);
        }
        clock.stop();
        let clock = step_clock::start(Stage::LevelWeights);
        self.level_scales(footprints, n, &mut ws.level_scale);
        self.weigh_levels(&mut ws.enc[..n * e], &ws.level_scale);
        clock.stop();
        let clock = step_clock::start(Stage::Encoding);
        self.encode_motion(params, moments, n, ws);
        clock.stop();
        let _clock = step_clock::start(Stage::Networks);
        let h = &mut ws.h[..n * w];
        matmul_in(
            products,
            h,
            MatRef::new(&ws.enc, n, e),
            self.weight(params, 0, e, w),
            false,
        );
        if let (Some(m), Some(at)) = (&self.motion, self.motion_weight) {
            let md = m.dims();
            matmul_in(
                products,
                h,
                MatRef::new(&ws.enc_motion, n, md),
                MatRef::new(&params[at..][..md * w], md, w),
                true,
            );
        }
        relu(h);
        matmul_in(
            products,
            &mut ws.geo,
            MatRef::new(h, n, w),
            self.weight(params, 1, w, g),
            false,
        );
        for (s, row) in ws.sigma[..n].iter_mut().zip(ws.geo.chunks_exact(g)) {
            *s = row[0].min(LOG_SIGMA_MAX).exp();
        }
    }

    /// Encodes the points at `positions` (a worker's whole share of a step, in the order its
    /// chunks will come) level by level, ahead of the forward passes, which then take their
    /// encodings from here: as in the backward ([`scatter_deferred`](Self::scatter_deferred)),
    /// one pass a level over the whole share keeps a fine level's table in the caches, where
    /// chunk by chunk it is fetched again for each. The encodings are the same, bit for bit.
    pub fn pre_encode(&self, params: &[f32], positions: &[f32], ws: &mut FastWorkspace) {
        let _clock = step_clock::start(Stage::Encoding);
        let n = positions.len() / 3;
        resize_reused(&mut ws.share_unit, n * 3, 0.0);
        self.to_unit(positions, &mut ws.share_unit);
        resize_reused(&mut ws.share_enc, n * self.grid.dims(), 0.0);
        self.grid
            .encode_by_level(params, &ws.share_unit, &mut ws.share_enc);
        ws.share_next = 0;
    }

    /// Forgets what [`pre_encode`](Self::pre_encode) left.
    pub fn end_pre_encoded(&self, ws: &mut FastWorkspace) {
        // The share's planes may hold gradients waiting for their scatter.
        assert!(ws.deferred_unit.is_empty(), "scatter before the share ends");
        ws.share_unit.clear();
        ws.share_next = 0;
    }

    /// Fills `ws.enc` for the `n` points in `ws.unit` from the share encoded ahead, if they
    /// are its next points (anything else is encoded as it comes); whether it did.
    fn take_pre_encoded(&self, n: usize, ws: &mut FastWorkspace) -> bool {
        let (room, next) = (ws.share_unit.len() / 3, ws.share_next);
        if next + n > room || ws.unit[..n * 3] != ws.share_unit[next * 3..(next + n) * 3] {
            return false;
        }
        let e = self.grid.dims();
        for l in 0..e / FEATURES {
            let plane = &ws.share_enc[(l * room + next) * FEATURES..][..n * FEATURES];
            for (s, f) in plane.chunks_exact(FEATURES).enumerate() {
                ws.enc[s * e + l * FEATURES..][..FEATURES].copy_from_slice(f);
            }
        }
        ws.share_next += n;
        true
    }

    /// Densities at `positions` into `out`, with the networks' products in `products`, in
    /// a workspace of the calling thread's own: for callers that evaluate from many threads
    /// (occupancy refreshes).
    pub fn density_into(
        &self,
        params: &[f32],
        positions: &[f32],
        products: Precision,
        out: &mut [f32],
    ) {
        thread_local! {
            static WS: std::cell::RefCell<FastWorkspace> = std::cell::RefCell::default();
        }
        WS.with(|ws| {
            let ws = &mut ws.borrow_mut();
            ws.products = products;
            self.eval_density(params, positions, &[], Moments::Any, ws);
            out.copy_from_slice(&ws.sigma[..out.len()]);
        })
    }

    /// Densities at `positions` into `out` at moment `time` of a moving scene (`None`: as
    /// [`Field::density`], any moment; still fields ignore it).
    pub fn density_at(
        &self,
        params: &[f32],
        positions: &[f32],
        time: Option<f32>,
        ws: &mut FastWorkspace,
        out: &mut [f32],
    ) {
        let moments = time.map_or(Moments::Any, Moments::At);
        self.eval_density(params, positions, &[], moments, ws);
        out.copy_from_slice(&ws.sigma[..out.len()]);
    }

    /// Density and colour of the `n` samples of `input` (positions, unit directions shared
    /// by `samples_per_dir` consecutive samples, appearance indices, footprints), into
    /// `ws.sigma` and `ws.rgb`.
    fn eval_samples(&self, params: &[f32], input: FieldInput, ws: &mut FastWorkspace) {
        self.eval_input_density(params, &input, ws);
        self.eval_colour(params, &input, 0..input.len(), ws);
    }

    /// The density pass of a forward over `input`'s samples (their footprints and moments).
    fn eval_input_density(&self, params: &[f32], input: &FieldInput, ws: &mut FastWorkspace) {
        self.eval_density(
            params,
            input.positions,
            input.footprints,
            Moments::of(input.times),
            ws,
        );
    }

    /// The colour network over the samples `rows` names (in increasing order), from the
    /// geometry features the density pass left in `ws`: row `r` of `ws.colour_in`, `c1`,
    /// `c2` and `rgb` holds the `r`th of them (all `n` samples in order for a forward,
    /// which its backward reads).
    fn eval_colour(
        &self,
        params: &[f32],
        input: &FieldInput,
        rows: impl ExactSizeIterator<Item = usize>,
        ws: &mut FastWorkspace,
    ) {
        let (n, m) = (input.len(), rows.len());
        let products = ws.products;
        let (w, g, ci) = (
            self.config.hidden,
            self.config.geo_features,
            self.colour_in_dims(),
        );
        let (dirs, spd) = (input.dirs, input.samples_per_dir);
        let dims = self.appearance_dims();
        let _clock = step_clock::start(Stage::Networks);
        self.gather_codes(params, input.appearance, n, ws);
        let codes = self.codes(params);
        let harmonics = self.view_harmonics();
        grow(&mut ws.colour_in, m * ci);
        grow(&mut ws.c1, m * w);
        grow(&mut ws.c2, m * w);
        grow(&mut ws.rgb, n.max(m) * 3);
        for (r, s) in rows.enumerate() {
            let row = &mut ws.colour_in[r * ci..][..ci];
            let d = &dirs[3 * (s / spd)..][..3];
            row[..SH_DIMS].copy_from_slice(&sh4([d[0], d[1], d[2]]));
            row[harmonics..SH_DIMS].fill(0.0);
            row[SH_DIMS..][..g - 1].copy_from_slice(&ws.geo[s * g + 1..][..g - 1]);
            if dims > 0 {
                let code = match ws.code_index[s] as usize {
                    i if i < self.config.appearance_images => &codes[i * dims..][..dims],
                    _ => &ws.mean_code[..],
                };
                row[SH_DIMS + g - 1..].copy_from_slice(code);
            }
        }
        let c1 = &mut ws.c1[..m * w];
        matmul_in(
            products,
            c1,
            MatRef::new(&ws.colour_in, m, ci),
            self.weight(params, 2, ci, w),
            false,
        );
        relu(c1);
        let c2 = &mut ws.c2[..m * w];
        matmul_in(
            products,
            c2,
            MatRef::new(c1, m, w),
            self.weight(params, 3, w, w),
            false,
        );
        relu(c2);
        let rgb = &mut ws.rgb[..m * 3];
        matmul_in(
            products,
            rgb,
            MatRef::new(c2, m, w),
            self.weight(params, 4, w, 3),
            false,
        );
        rgb.iter_mut().for_each(|v| *v = sigmoid(*v));
    }

    /// Backward of the forward that filled `ws` (over the same `n` samples): given
    /// `d_sigma` (`n`) and `d_rgb` (`n x 3`), accumulates parameter gradients into `grads`.
    fn eval_samples_bwd(
        &self,
        params: &[f32],
        ws: &mut FastWorkspace,
        d_sigma: &[f32],
        d_rgb: &[f32],
        grads: &mut Grads,
    ) {
        let n = d_sigma.len();
        let products = ws.products;
        let (w, g, ci, e) = (
            self.config.hidden,
            self.config.geo_features,
            self.colour_in_dims(),
            self.grid.dims(),
        );
        let networks = step_clock::start(Stage::NetworksBackward);
        grow(&mut ws.d_logit, n * 3);
        grow(&mut ws.d_c2, n * w);
        grow(&mut ws.d_c1, n * w);
        grow(&mut ws.d_h, n * w);
        grow(&mut ws.d_colour_in, n * ci);
        grow(&mut ws.d_geo, n * g);
        grow(&mut ws.d_enc, n * e);
        let gw = |k: usize| self.weights[k];
        let values = grads.values_mut();
        // Colour network.
        for ((dl, &y), &dy) in ws.d_logit[..n * 3].iter_mut().zip(&ws.rgb).zip(d_rgb) {
            *dl = dy * y * (1.0 - y);
        }
        let d_logit = MatRef::new(&ws.d_logit, n, 3);
        matmul_in(
            products,
            &mut values[gw(4)..][..w * 3],
            MatRef::new(&ws.c2, n, w).t(),
            d_logit,
            true,
        );
        let d_c2 = &mut ws.d_c2[..n * w];
        matmul_in(
            products,
            d_c2,
            d_logit,
            self.weight(params, 4, w, 3).t(),
            false,
        );
        relu_bwd(d_c2, &ws.c2);
        let d_c2 = MatRef::new(d_c2, n, w);
        matmul_in(
            products,
            &mut values[gw(3)..][..w * w],
            MatRef::new(&ws.c1, n, w).t(),
            d_c2,
            true,
        );
        let d_c1 = &mut ws.d_c1[..n * w];
        matmul_in(
            products,
            d_c1,
            d_c2,
            self.weight(params, 3, w, w).t(),
            false,
        );
        relu_bwd(d_c1, &ws.c1);
        let d_c1 = MatRef::new(d_c1, n, w);
        matmul_in(
            products,
            &mut values[gw(2)..][..ci * w],
            MatRef::new(&ws.colour_in, n, ci).t(),
            d_c1,
            true,
        );
        matmul_in(
            products,
            &mut ws.d_colour_in,
            d_c1,
            self.weight(params, 2, ci, w).t(),
            false,
        );
        // Density network: sigma = exp(min(o_0, max)), geo features come back from colour.
        for s in 0..n {
            let o0 = ws.geo[s * g];
            let row = &mut ws.d_geo[s * g..][..g];
            row[0] = if o0 < LOG_SIGMA_MAX {
                d_sigma[s] * ws.sigma[s]
            } else {
                0.0
            };
            row[1..].copy_from_slice(&ws.d_colour_in[s * ci + SH_DIMS..][..g - 1]);
        }
        // Appearance codes: each sample's gradient goes to its photo's code, or, for the
        // mean code, to every code in equal parts.
        if let Some(at) = self.codes {
            let (dims, images) = (self.appearance_dims(), self.config.appearance_images);
            let first = SH_DIMS + g - 1;
            for s in 0..n {
                let d = &ws.d_colour_in[s * ci + first..][..dims];
                match ws.code_index[s] as usize {
                    i if i < images => {
                        for (gv, dv) in values[at + i * dims..][..dims].iter_mut().zip(d) {
                            *gv += dv;
                        }
                    }
                    _ => {
                        for row in values[at..][..images * dims].chunks_exact_mut(dims) {
                            for (gv, dv) in row.iter_mut().zip(d) {
                                *gv += dv / images as f32;
                            }
                        }
                    }
                }
            }
        }
        let d_geo = MatRef::new(&ws.d_geo, n, g);
        matmul_in(
            products,
            &mut values[gw(1)..][..w * g],
            MatRef::new(&ws.h, n, w).t(),
            d_geo,
            true,
        );
        let d_h = &mut ws.d_h[..n * w];
        matmul_in(
            products,
            d_h,
            d_geo,
            self.weight(params, 1, w, g).t(),
            false,
        );
        relu_bwd(d_h, &ws.h);
        let d_h = MatRef::new(d_h, n, w);
        matmul_in(
            products,
            &mut values[gw(0)..][..e * w],
            MatRef::new(&ws.enc, n, e).t(),
            d_h,
            true,
        );
        matmul_in(
            products,
            &mut ws.d_enc,
            d_h,
            self.weight(params, 0, e, w).t(),
            false,
        );
        if let (Some(m), Some(at)) = (&self.motion, self.motion_weight) {
            let md = m.dims();
            matmul_in(
                products,
                &mut values[at..][..md * w],
                MatRef::new(&ws.enc_motion, n, md).t(),
                d_h,
                true,
            );
            grow(&mut ws.d_enc_motion, n * md);
            matmul_in(
                products,
                &mut ws.d_enc_motion,
                d_h,
                MatRef::new(&params[at..][..md * w], md, w).t(),
                false,
            );
        }
        networks.stop();
        let clock = step_clock::start(Stage::LevelWeights);
        self.weigh_levels(&mut ws.d_enc[..n * e], &ws.level_scale);
        clock.stop();
        let _clock = step_clock::start(Stage::EncodingBackward);
        grads.mark(self.mlp_range());
        let deferred = match ws.defer_grid {
            Some(room) => {
                // More samples came than there is room for: what waits goes first, in order.
                if ws.deferred_unit.len() / 3 + n > ws.scatter_room(room) {
                    self.scatter_waiting(ws, grads);
                }
                let fits = n <= ws.scatter_room(room);
                if fits {
                    ws.keep_for_scatter(n, e, room);
                }
                fits
            }
            None => false,
        };
        if !deferred {
            self.grid
                .encode_bwd(&ws.unit[..n * 3], &ws.d_enc[..n * e], grads);
        }
        if let Some(m) = &self.motion {
            m.encode_bwd(
                &ws.unit_time[..n * 4],
                &ws.d_enc_motion[..n * m.dims()],
                grads,
            );
        }
    }

    /// Moving fields: the prior that the scene changes smoothly in time, for the last
    /// forward's `n` samples (every [`SMOOTH_STRIDE`]-th): `weight` times the sum over them
    /// of `|m(x, t) - m(x, t + dt)|^2`, `m` the space-time grid's features and `dt` one
    /// cell of its finest time level (back from the last moment). Adds its gradient to
    /// `grads` and returns its value (0 for still fields).
    pub fn time_smoothness_bwd(
        &self,
        params: &[f32],
        ws: &mut FastWorkspace,
        n: usize,
        weight: f32,
        grads: &mut Grads,
    ) -> f64 {
        let Some(motion) = &self.motion else {
            return 0.0;
        };
        if weight == 0.0 || n == 0 {
            return 0.0;
        }
        let md = motion.dims();
        let k = n.div_ceil(SMOOTH_STRIDE);
        let dt = 1.0 / motion.config.max_time_resolution.max(1) as f32;
        grow(&mut ws.now, k * 4);
        grow(&mut ws.later, k * 4);
        grow(&mut ws.enc_later, k * md);
        grow(&mut ws.d_smooth, k * md);
        let sampled = ws.unit_time[..n * 4].chunks_exact(4).step_by(SMOOTH_STRIDE);
        for ((p, now), later) in sampled
            .zip(ws.now.chunks_exact_mut(4))
            .zip(ws.later.chunks_exact_mut(4))
        {
            now.copy_from_slice(p);
            later.copy_from_slice(p);
            later[3] = if p[3] + dt <= 1.0 {
                p[3] + dt
            } else {
                p[3] - dt
            };
        }
        motion.encode(params, &ws.later[..k * 4], &mut ws.enc_later);
        let scale = 2.0 * weight;
        let mut value = 0.0f64;
        for j in 0..k {
            let a = &ws.enc_motion[j * SMOOTH_STRIDE * md..][..md];
            let b = &ws.enc_later[j * md..][..md];
            for ((d, &x), &y) in ws.d_smooth[j * md..][..md].iter_mut().zip(a).zip(b) {
                value += f64::from((x - y) * (x - y));
                *d = scale * (x - y);
            }
        }
        motion.encode_bwd(&ws.now[..k * 4], &ws.d_smooth[..k * md], grads);
        ws.d_smooth[..k * md].iter_mut().for_each(|d| *d = -*d);
        motion.encode_bwd(&ws.later[..k * 4], &ws.d_smooth[..k * md], grads);
        value * f64::from(weight)
    }

    /// Scatters into the hash grid's gradients what the backward passes since
    /// [`FastWorkspace::defer_grid`] was set left there, level by level over all their
    /// samples at once, and forgets it. Chunk by chunk, a fine level's table (megabytes)
    /// is fetched into the caches again for every chunk's few thousand writes; over a
    /// worker's whole share it stays there while they all land. The sums are the same,
    /// bit for bit: an entry belongs to one level, and each level takes the samples in
    /// the same order.
    pub fn scatter_deferred(&self, ws: &mut FastWorkspace, grads: &mut Grads) {
        let _clock = step_clock::start(Stage::EncodingBackward);
        self.scatter_waiting(ws, grads);
    }

    /// [`scatter_deferred`](Self::scatter_deferred) inside a stage already clocked.
    fn scatter_waiting(&self, ws: &mut FastWorkspace, grads: &mut Grads) {
        if let (Some(room), false) = (ws.defer_grid, ws.deferred_unit.is_empty()) {
            // The planes hold `room` samples a level; the first of each are filled.
            let (planes, room) = ws.waiting_planes(room);
            self.grid
                .encode_bwd_by_level(&ws.deferred_unit, planes, room, grads);
        }
        ws.deferred_unit.clear();
    }

    /// [`Field::backward`], and also `dL/d position` (`n x 3`, field space) into
    /// `d_positions` and `dL/d direction` (one per sample, `n x 3`, of the unit view
    /// direction `dirs`) into `d_dirs`: camera refinement moves and turns rays.
    #[allow(clippy::too_many_arguments)]
    pub fn backward_with_positions(
        &self,
        params: &[f32],
        ws: &mut FastWorkspace,
        d_output: FieldGrad,
        grads: &mut Grads,
        dirs: &[f32],
        d_positions: &mut Vec<f32>,
        d_dirs: &mut Vec<f32>,
    ) {
        let n = d_output.d_sigma.len();
        d_positions.clear();
        d_positions.resize(n * 3, 0.0);
        d_dirs.clear();
        d_dirs.resize(n * 3, 0.0);
        if n == 0 {
            return;
        }
        self.eval_samples_bwd(params, ws, d_output.d_sigma, d_output.d_rgb, grads);
        let ci = self.colour_in_dims();
        for s in 0..n {
            let d = &dirs[s * 3..][..3];
            let g = &ws.d_colour_in[s * ci..][..SH_DIMS];
            d_dirs[s * 3..][..3].copy_from_slice(&sh4_bwd([d[0], d[1], d[2]], g));
        }
        let e = self.grid.dims();
        // The tables have their gradient: what remains of `d_enc` is the positions'.
        if !self.position_level_weights.is_empty() {
            let f = crate::encoding::hash_grid::FEATURES;
            for row in ws.d_enc[..n * e].chunks_exact_mut(e) {
                for (level, w) in row.chunks_exact_mut(f).zip(&self.position_level_weights) {
                    level.iter_mut().for_each(|v| *v *= w);
                }
            }
        }
        self.grid
            .encode_input_bwd(params, &ws.unit[..n * 3], &ws.d_enc[..n * e], d_positions);
        let to_world = 0.5 / self.config.bound;
        d_positions.iter_mut().for_each(|v| *v *= to_world);
    }
}

impl Field for FastField {
    type Context = FastWorkspace;

    fn num_params(&self) -> usize {
        self.layout.total
    }

    fn forward<'c>(
        &self,
        params: &[f32],
        input: FieldInput,
        ctx: &'c mut FastWorkspace,
    ) -> FieldOutput<'c> {
        let n = input.len();
        self.eval_samples(params, input, ctx);
        FieldOutput {
            sigma: &ctx.sigma[..n],
            rgb: &ctx.rgb[..n * 3],
        }
    }

    fn infer_picked<'c>(
        &self,
        params: &[f32],
        input: FieldInput,
        ctx: &'c mut FastWorkspace,
        pick: &mut dyn FnMut(&[f32], &mut Vec<u32>),
    ) -> FieldOutput<'c> {
        let n = input.len();
        self.eval_input_density(params, &input, ctx);
        let mut picked = std::mem::take(&mut ctx.picked);
        picked.clear();
        pick(&ctx.sigma[..n], &mut picked);
        debug_assert!(picked.windows(2).all(|p| p[0] < p[1]));
        debug_assert!(picked.last().is_none_or(|&s| (s as usize) < n));
        self.eval_colour(params, &input, picked.iter().map(|&s| s as usize), ctx);
        spread_rows(&mut ctx.rgb[..n * 3], &picked);
        ctx.picked = picked;
        FieldOutput {
            sigma: &ctx.sigma[..n],
            rgb: &ctx.rgb[..n * 3],
        }
    }

    fn backward(
        &self,
        params: &[f32],
        ctx: &mut FastWorkspace,
        d_output: FieldGrad,
        grads: &mut Grads,
    ) {
        if d_output.d_sigma.is_empty() {
            return;
        }
        self.eval_samples_bwd(params, ctx, d_output.d_sigma, d_output.d_rgb, grads);
    }

    fn density(&self, params: &[f32], positions: &[f32], ctx: &mut FastWorkspace, out: &mut [f32]) {
        self.eval_density(params, positions, &[], Moments::Any, ctx);
        out.copy_from_slice(&ctx.sigma[..out.len()]);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::nn::GradBuffer;

    fn input<'a>(positions: &'a [f32], dirs: &'a [f32]) -> FieldInput<'a> {
        FieldInput {
            positions,
            dirs,
            samples_per_dir: 1,
            appearance: &[],
            footprints: &[],
            variances: &[],
            times: &[],
        }
    }

    fn tiny() -> FastField {
        tiny_with_codes(0, 0)
    }

    fn tiny_with_codes(appearance_dims: usize, appearance_images: usize) -> FastField {
        FastField::new(FastFieldConfig {
            grid: HashGridConfig {
                levels: 3,
                log2_table_size: 6,
                base_resolution: 2,
                max_resolution: 8,
            },
            hidden: 8,
            geo_features: 4,
            bound: 1.5,
            appearance_dims,
            appearance_images,
            antialias: None,
            motion: None,
            view_harmonics: SH_DIMS,
        })
    }

    fn tiny_moving() -> FastField {
        let mut config = tiny().config;
        config.motion = Some(SpaceTimeConfig {
            levels: 2,
            log2_table_size: 7,
            base_resolution: 2,
            max_resolution: 6,
            base_time_resolution: 2,
            max_time_resolution: 5,
        });
        FastField::new(config)
    }

    fn tiny_antialiased(reference_footprint: f32) -> FastField {
        let mut field = tiny();
        field.config.antialias = Some(Antialias {
            reference_footprint,
        });
        field
    }

    #[test]
    fn backward_matches_finite_differences() {
        backward_matches_finite_differences_of(&tiny(), &[], &[]);
    }

    /// The space-time grid's tables and first-layer weights included.
    #[test]
    fn moving_backward_matches_finite_differences() {
        let field = tiny_moving();
        assert!(field
            .layout
            .tensors
            .iter()
            .any(|t| t.name == "density.motion.weight"));
        backward_matches_finite_differences_of(&field, &[], &[]);
    }

    /// The time-smoothness prior's gradient against central differences of its value, on
    /// samples at moments near the end too (the later moment is taken backwards there).
    #[test]
    fn time_smoothness_gradient_matches_finite_differences() {
        let field = tiny_moving();
        let mut rng = Rng::new(5);
        let params = random_params(&field, &mut rng);
        let n = 2 * SMOOTH_STRIDE + 1;
        let pos: Vec<f32> = (0..n * 3).map(|_| rng.range(-1.4, 1.4)).collect();
        let dirs = rng.unit_directions(n);
        let mut times: Vec<f32> = (0..n).map(|_| rng.uniform()).collect();
        // A paired sample near the last moment, whose pair looks back in time.
        times[SMOOTH_STRIDE] = 0.99;
        let weight = 0.3;
        let value = |p: &[f32], grads: &mut GradBuffer| -> f64 {
            let mut ws = FastWorkspace::default();
            let mut inp = input(&pos, &dirs);
            inp.times = &times;
            field.forward(p, inp, &mut ws);
            field.time_smoothness_bwd(p, &mut ws, n, weight, &mut grads.all())
        };
        let mut grads = GradBuffer::new(field.num_params());
        let v = value(&params, &mut grads);
        assert!(v > 0.0);
        let motion = field.motion.as_ref().expect("a moving field").param_range();
        let (mut err, mut norm, mut checked) = (0.0f64, 0.0f64, 0);
        for i in motion.clone() {
            let g = f64::from(grads.values[i]);
            if g == 0.0 {
                continue;
            }
            let h = 1e-3;
            let (mut a, mut b) = (params.clone(), params.clone());
            a[i] += h;
            b[i] -= h;
            let mut scratch = GradBuffer::new(field.num_params());
            let fd = (value(&a, &mut scratch) - value(&b, &mut scratch)) / (2.0 * h as f64);
            err += (fd - g).powi(2);
            norm += g * g;
            checked += 1;
        }
        assert!(checked > 20, "only {checked} parameters had gradients");
        let rel = (err / norm).sqrt();
        assert!(rel < 1e-2, "relative error {rel} over {checked} parameters");
        // The prior touches the space-time tables alone.
        let outside = (0..field.num_params())
            .filter(|i| !motion.contains(i))
            .any(|i| grads.values[i] != 0.0);
        assert!(!outside);
    }

    /// The occupancy grid's refreshes query points jittered inside cells: the moments
    /// drawn from them must cover [0, 1] evenly, or a limb that is there only at some
    /// moments would be left out of the grid and never marched.
    #[test]
    fn moments_drawn_from_points_cover_every_moment() {
        let mut rng = Rng::new(9);
        let mut deciles = [0usize; 10];
        let n = 4000;
        for _ in 0..n {
            // Points of neighbouring cells of a 128^3 grid, as a refresh draws them.
            let u = [0.5, 0.5, 0.5].map(|c: f32| c + rng.range(0.0, 3.0 / 128.0));
            let t = moment_of_point(&u);
            assert!((0.0..1.0).contains(&t), "{t}");
            deciles[(t * 10.0) as usize] += 1;
        }
        for (d, &count) in deciles.iter().enumerate() {
            let share = count as f64 / n as f64;
            assert!((0.07..0.13).contains(&share), "decile {d}: {share}");
        }
        assert_eq!(
            moment_of_point(&[0.1, 0.2, 0.3]),
            moment_of_point(&[0.1, 0.2, 0.3])
        );
    }

    #[test]
    fn a_moving_field_differs_between_moments_and_keeps_its_tables_lazy() {
        let field = tiny_moving();
        let motion = field.motion.as_ref().expect("a moving field");
        // The lazy (hash-table) part ends after both grids' tables.
        assert_eq!(field.mlp_range().start, motion.param_range().end);
        assert_eq!(motion.param_range().start, field.grid.param_range().end);
        let mut rng = Rng::new(3);
        let params = random_params(&field, &mut rng);
        let pos = [0.2, -0.3, 0.4, 0.2, -0.3, 0.4];
        let dirs = [0.0, 0.0, 1.0, 0.0, 0.0, 1.0];
        let mut ws = FastWorkspace::default();
        let mut inp = input(&pos, &dirs);
        inp.times = &[0.1, 0.9];
        let out = field.forward(&params, inp, &mut ws);
        assert!(
            (out.sigma[0] - out.sigma[1]).abs() > 1e-4,
            "{:?}",
            out.sigma
        );
        // Density queries at a moment see what the forward saw then.
        let mut sigma = [0.0; 2];
        field.density_at(
            &params,
            &pos,
            Some(0.9),
            &mut FastWorkspace::default(),
            &mut sigma,
        );
        assert!((sigma[1] - out.sigma[1]).abs() < 1e-5 * out.sigma[1].max(1.0));
    }

    /// The anti-aliased field's gradients, with footprints that weigh the
    /// levels anywhere from nearly 1 to nearly 0, and with the coarse-to-fine schedule.
    #[test]
    fn antialiased_backward_matches_finite_differences() {
        let mut field = tiny_antialiased(0.05);
        let footprints = [0.01, 0.05, 0.1, 0.2, 0.4, 0.02];
        let weights: Vec<f32> = field
            .grid
            .levels
            .iter()
            .map(|l| level_weight(footprints[4] * 0.5 / 1.5, l.resolution))
            .collect();
        assert!(weights[0] > 0.9 && weights[2] < 0.5, "{weights:?}");
        backward_matches_finite_differences_of(&field, &[], &footprints);
        field.level_weights = vec![1.0, 0.7, 0.2];
        backward_matches_finite_differences_of(&field, &[], &footprints);
        // No footprints: the reference footprint everywhere.
        backward_matches_finite_differences_of(&field, &[], &[]);
    }

    /// With footprints far below every cell, anti-aliasing changes nothing; density
    /// queries without footprints see the reference footprint.
    #[test]
    fn tiny_footprints_are_point_samples_and_density_uses_the_reference() {
        let plain = tiny();
        let params = plain.init_params(5);
        let pos = [0.1, 0.2, -0.3, 1.0, -1.2, 0.4];
        let dirs = [0.0, 0.0, 1.0, 1.0, 0.0, 0.0];
        let mut ws = FastWorkspace::default();
        let point = plain.forward(&params, input(&pos, &dirs), &mut ws);
        let (point_sigma, point_rgb) = (point.sigma.to_vec(), point.rgb.to_vec());
        let aa = tiny_antialiased(0.3);
        let mut inp = input(&pos, &dirs);
        inp.footprints = &[1e-6, 1e-6];
        let out = aa.forward(&params, inp, &mut ws);
        for (a, b) in out.sigma.iter().zip(&point_sigma) {
            assert!((a / b - 1.0).abs() < 1e-5, "{a} vs {b}");
        }
        for (a, b) in out.rgb.iter().zip(&point_rgb) {
            assert!((a - b).abs() < 1e-6);
        }
        let mut inp = input(&pos, &dirs);
        inp.footprints = &[0.3, 0.3];
        let wide = aa.forward(&params, inp, &mut ws).sigma.to_vec();
        let mut alone = [0.0; 2];
        aa.density(&params, &pos, &mut FastWorkspace::default(), &mut alone);
        assert_eq!(wide, alone.to_vec());
        assert_ne!(wide, point_sigma, "a wide footprint reads less detail");
    }

    /// The networks with bfloat16 products (8 significant bits per input, f32 sums) give
    /// the f32 field's outputs and gradients up to that rounding, on the default widths.
    #[test]
    fn bf16_products_give_the_f32_field_up_to_their_rounding() {
        let Some(bf16) = Precision::bf16() else {
            eprintln!("skipped: this CPU has no AVX-512 BF16");
            return;
        };
        let mut config = FastFieldConfig::default();
        config.grid.log2_table_size = 10;
        let field = FastField::new(config);
        let mut rng = Rng::new(4);
        let params: Vec<f32> = (0..field.num_params())
            .map(|_| rng.range(-0.3, 0.3))
            .collect();
        let n = 300;
        let pos: Vec<f32> = (0..n * 3).map(|_| rng.range(-1.4, 1.4)).collect();
        let dirs = rng.unit_directions(n);
        let d_sigma: Vec<f32> = (0..n).map(|_| rng.range(-1.0, 1.0)).collect();
        let d_rgb: Vec<f32> = (0..n * 3).map(|_| rng.range(-1.0, 1.0)).collect();
        let run = |products: Precision| {
            let mut ws = FastWorkspace {
                products,
                ..FastWorkspace::default()
            };
            let out = field.forward(&params, input(&pos, &dirs), &mut ws);
            let (sigma, rgb) = (out.sigma.to_vec(), out.rgb.to_vec());
            let mut grads = GradBuffer::new(field.num_params());
            let d = FieldGrad {
                d_sigma: &d_sigma,
                d_rgb: &d_rgb,
            };
            field.backward(&params, &mut ws, d, &mut grads.all());
            (sigma, rgb, grads.values)
        };
        let (sigma, rgb, grads) = run(Precision::F32);
        let (sigma_b, rgb_b, grads_b) = run(bf16);
        // Relative error of a whole vector: the rounding's 2^-9 per input, summed over
        // a layer's inputs in random directions, through four layers.
        let rel = |a: &[f32], b: &[f32]| {
            let err: f64 = a.iter().zip(b).map(|(x, y)| ((x - y) as f64).powi(2)).sum();
            let norm: f64 = a.iter().map(|x| (*x as f64).powi(2)).sum();
            (err / norm).sqrt()
        };
        let (e_sigma, e_rgb, e_grad) = (
            rel(&sigma, &sigma_b),
            rel(&rgb, &rgb_b),
            rel(&grads, &grads_b),
        );
        assert!(
            e_sigma < 2e-3 && e_rgb < 2e-3 && e_grad < 6e-2,
            "{e_sigma} {e_rgb} {e_grad}"
        );
        // And they are rounded: the same products in f32 would agree to 1e-6.
        assert!(e_sigma > 1e-5, "{e_sigma}");
    }

    /// The appearance codes' gradient, per photo and through the mean code.
    #[test]
    fn appearance_code_gradients_match_finite_differences() {
        let field = tiny_with_codes(4, 3);
        let mean = crate::stage::MEAN_APPEARANCE;
        backward_matches_finite_differences_of(&field, &[0, 2, mean, 1, mean, 0], &[]);
    }

    /// A field fed the view direction's first four harmonics: the colour network's
    /// weights for the other twelve start at 0 and get no gradient, so colours and the
    /// direction's gradient follow degrees 0 and 1 alone (against central differences of
    /// the loss in the direction); the parameters' gradients match finite differences.
    #[test]
    fn a_field_fed_four_harmonics_sees_degrees_0_and_1_alone() {
        let mut field = tiny();
        field.config.view_harmonics = 4;
        let w = field.config.hidden;
        let unused = field.weights[2] + 4 * w..field.weights[2] + SH_DIMS * w;
        let init = field.init_params(5);
        assert!(init[unused.clone()].iter().all(|&v| v == 0.0));
        assert!(init[field.weights[2]..][..4 * w].iter().any(|&v| v != 0.0));
        // Large weights elsewhere (every path carries signal), the unused ones as trained.
        let mut rng = Rng::new(4);
        let mut params = random_params(&field, &mut rng);
        params[unused.clone()].fill(0.0);
        let n = 5;
        let pos: Vec<f32> = (0..n * 3).map(|_| rng.range(-1.2, 1.2)).collect();
        let dirs = rng.unit_directions(n);
        let (a, b): (Vec<f32>, Vec<f32>) = (
            (0..n).map(|_| rng.range(-1.0, 1.0)).collect(),
            (0..n * 3).map(|_| rng.range(-1.0, 1.0)).collect(),
        );
        let loss = |dirs: &[f32]| -> f64 {
            let mut ws = FastWorkspace::default();
            let out = field.forward(&params, input(&pos, dirs), &mut ws);
            let ls: f64 = out
                .sigma
                .iter()
                .zip(&a)
                .map(|(s, a)| f64::from(s * a))
                .sum();
            let lc: f64 = out.rgb.iter().zip(&b).map(|(c, b)| f64::from(c * b)).sum();
            ls + lc
        };
        let (_, grads, _, d_dirs) = with_input_gradients(&field, &params, (&pos, &dirs), (&a, &b));
        assert!(grads[unused.clone()].iter().all(|&g| g == 0.0));
        for (k, &g) in d_dirs.iter().enumerate() {
            let h = 1e-3;
            let (mut p, mut m) = (dirs.clone(), dirs.clone());
            p[k] += h;
            m[k] -= h;
            let fd = (loss(&p) - loss(&m)) / (2.0 * f64::from(h));
            assert!(
                (fd - f64::from(g)).abs() < 2e-3,
                "direction {k}: {g} vs {fd}"
            );
        }
        assert!(
            d_dirs.iter().any(|&g| g.abs() > 1e-3),
            "no direction gradient"
        );
        // Whatever the unused weights hold, they are fed nothing: the same colours.
        let mut other = params.clone();
        for v in &mut other[unused] {
            *v = rng.range(-0.5, 0.5);
        }
        let colours = |p: &[f32]| {
            let mut ws = FastWorkspace::default();
            field.forward(p, input(&pos, &dirs), &mut ws).rgb.to_vec()
        };
        assert_eq!(colours(&params), colours(&other));
        backward_matches_finite_differences_of(&field, &[], &[]);
    }

    /// Codes colour only: density is the same whatever the photo, and a photo's code
    /// changes its colours and no other photo's.
    #[test]
    fn appearance_codes_change_colour_not_density() {
        let field = tiny_with_codes(4, 3);
        let mut params = field.init_params(3);
        let pos = [0.1, 0.2, -0.3, 1.0, -1.2, 0.4];
        let dirs = [0.0, 0.0, 1.0, 1.0, 0.0, 0.0];
        let run = |p: &[f32], looks: &[u32]| {
            let mut ws = FastWorkspace::default();
            let mut inp = input(&pos, &dirs);
            inp.appearance = looks;
            let out = field.forward(p, inp, &mut ws);
            (out.sigma.to_vec(), out.rgb.to_vec())
        };
        let before = run(&params, &[0, 1]);
        let codes = field.codes.expect("codes");
        params[codes..codes + 4].iter_mut().for_each(|v| *v = 3.0);
        let after = run(&params, &[0, 1]);
        assert_eq!(before.0, after.0, "density ignores the codes");
        assert_ne!(
            before.1[..3],
            after.1[..3],
            "photo 0's colour follows its code"
        );
        assert_eq!(before.1[3..], after.1[3..], "photo 1's does not");
        assert_eq!(field.codes(&params).len(), 12);
    }

    /// Forward passes over two chunks of a share encoded ahead give the forward of each
    /// chunk alone, bit for bit; points that are not the share's next are encoded as they
    /// come.
    #[test]
    fn a_share_encoded_ahead_gives_the_chunks_own_encodings() {
        let mut rng = Rng::new(9);
        let field = tiny();
        let params = random_params(&field, &mut rng);
        let chunks: Vec<(Vec<f32>, Vec<f32>)> = [7, 5]
            .iter()
            .map(|&n| {
                let pos: Vec<f32> = (0..n * 3).map(|_| rng.range(-1.4, 1.4)).collect();
                let dirs: Vec<f32> = (0..n).flat_map(|_| [0.0, 0.6, 0.8]).collect();
                (pos, dirs)
            })
            .collect();
        let forward = |ws: &mut FastWorkspace, (pos, dirs): &(Vec<f32>, Vec<f32>)| {
            let out = field.forward(&params, input(pos, dirs), ws);
            (out.sigma.to_vec(), out.rgb.to_vec())
        };
        let alone: Vec<_> = chunks
            .iter()
            .map(|c| forward(&mut FastWorkspace::default(), c))
            .collect();
        let mut ws = FastWorkspace::default();
        let share: Vec<f32> = chunks.iter().flat_map(|c| c.0.clone()).collect();
        field.pre_encode(&params, &share, &mut ws);
        // A chunk out of turn (the second first) is encoded as it comes.
        assert_eq!(forward(&mut ws, &chunks[1]), alone[1]);
        assert_eq!(ws.share_next, 0, "the share waits for its first chunk");
        for (c, want) in chunks.iter().zip(&alone) {
            assert_eq!(&forward(&mut ws, c), want);
        }
        assert_eq!(ws.share_next, 12, "both chunks came from the share");
        field.end_pre_encoded(&mut ws);
        assert_eq!(forward(&mut ws, &chunks[0]), alone[0]);
    }

    /// Parameters of `field` drawn uniformly from [-0.5, 0.5] (larger than the init's, so
    /// every path carries signal).
    fn random_params(field: &FastField, rng: &mut Rng) -> Vec<f32> {
        (0..field.num_params())
            .map(|_| rng.range(-0.5, 0.5))
            .collect()
    }

    /// A chunk of samples for the backward tests: points, directions, and the gradients
    /// of density and colour.
    type Chunk = (Vec<f32>, Vec<f32>, Vec<f32>, Vec<f32>);

    /// Chunks of `sizes` samples, drawn from `rng`.
    fn random_chunks(rng: &mut Rng, sizes: &[usize]) -> Vec<Chunk> {
        sizes
            .iter()
            .map(|&n| {
                let pos: Vec<f32> = (0..n * 3).map(|_| rng.range(-1.4, 1.4)).collect();
                let dirs: Vec<f32> = (0..n).flat_map(|_| [0.0, 0.6, 0.8]).collect();
                let a: Vec<f32> = (0..n).map(|_| rng.range(-1.0, 1.0)).collect();
                let b: Vec<f32> = (0..n * 3).map(|_| rng.range(-1.0, 1.0)).collect();
                (pos, dirs, a, b)
            })
            .collect()
    }

    /// The forward and backward of each chunk in turn, in `ws`, into `grads`.
    fn train_chunks(
        field: &FastField,
        params: &[f32],
        chunks: &[Chunk],
        ws: &mut FastWorkspace,
        grads: &mut GradBuffer,
    ) {
        for (pos, dirs, a, b) in chunks {
            field.forward(params, input(pos, dirs), ws);
            let d = FieldGrad {
                d_sigma: a,
                d_rgb: b,
            };
            field.backward(params, ws, d, &mut grads.all());
        }
    }

    /// Backward passes over two chunks with the grid's scatter deferred to one pass over
    /// both give the gradients of the passes scattered one by one, bit for bit.
    #[test]
    fn a_deferred_grid_scatter_is_the_immediate_one() {
        let mut rng = Rng::new(8);
        let field = tiny();
        let params = random_params(&field, &mut rng);
        let chunks = random_chunks(&mut rng, &[7, 7]);
        // Room for the 14 samples that come, for more (the planes are read part-filled), or
        // for fewer (what waits is scattered when a chunk does not fit).
        let run = |room: Option<usize>| {
            let mut ws = FastWorkspace {
                defer_grid: room,
                ..Default::default()
            };
            let mut grads = GradBuffer::new(field.num_params());
            train_chunks(&field, &params, &chunks, &mut ws, &mut grads);
            let before = grads.values.clone();
            field.scatter_deferred(&mut ws, &mut grads.all());
            let dirty = grads.dirty_fraction();
            (before, grads.values, dirty)
        };
        let (immediate, after_nothing, dirty) = run(None);
        assert_eq!(immediate, after_nothing, "nothing was deferred");
        for room in [14, 20, 10] {
            let (before, deferred, deferred_dirty) = run(Some(room));
            assert_ne!(
                before, deferred,
                "the tables' gradients waited (room {room})"
            );
            assert_eq!(deferred, immediate, "room {room}");
            assert_eq!(deferred_dirty, dirty, "room {room}");
        }
    }

    /// The same with the share encoded ahead, as training runs it: the gradients wait in
    /// the rows of the share's planes its forwards have read (no planes of their own), a
    /// chunk out of turn (a patch's rays) sends what waits to the tables first, and the
    /// sums are those of the immediate scatters, bit for bit.
    #[test]
    fn gradients_waiting_in_the_shares_planes_are_the_immediate_scatter() {
        let mut rng = Rng::new(12);
        let field = tiny();
        let params = random_params(&field, &mut rng);
        let chunks = random_chunks(&mut rng, &[7, 6, 5]);
        // The share holds the first and last chunks; the middle one comes out of turn.
        let share: Vec<f32> = [&chunks[0], &chunks[2]]
            .iter()
            .flat_map(|c| c.0.clone())
            .collect();
        let run = |ahead: bool| {
            let mut ws = FastWorkspace {
                defer_grid: ahead.then_some(12),
                ..Default::default()
            };
            if ahead {
                field.pre_encode(&params, &share, &mut ws);
            }
            let mut grads = GradBuffer::new(field.num_params());
            train_chunks(&field, &params, &chunks, &mut ws, &mut grads);
            field.scatter_deferred(&mut ws, &mut grads.all());
            assert!(ws.deferred_d_enc.is_empty(), "no planes of their own");
            let read = ws.share_next;
            field.end_pre_encoded(&mut ws);
            (grads.values, read)
        };
        let (immediate, _) = run(false);
        let (deferred, read) = run(true);
        assert_eq!(read, 12, "the share's chunks read their encodings from it");
        assert_eq!(deferred, immediate);
    }

    /// The straight-through schedule: weighting the levels of the position gradient
    /// leaves the forward and the tables' gradient as they are, and the position gradient
    /// is the weighted sum of each level's share (which add up to the full gradient).
    #[test]
    fn position_level_weights_act_on_the_position_gradient_only() {
        let mut rng = Rng::new(5);
        let base = tiny();
        let params = random_params(&base, &mut rng);
        let n = 5;
        let pos: Vec<f32> = (0..n * 3).map(|_| rng.range(-1.4, 1.4)).collect();
        let dirs: Vec<f32> = (0..n).flat_map(|_| [0.0, 0.6, 0.8]).collect();
        let a: Vec<f32> = (0..n).map(|_| rng.range(-1.0, 1.0)).collect();
        let b: Vec<f32> = (0..n * 3).map(|_| rng.range(-1.0, 1.0)).collect();
        let run = |weights: &[f32]| {
            let mut field = base.clone();
            field.position_level_weights = weights.to_vec();
            with_input_gradients(&field, &params, (&pos, &dirs), (&a, &b))
        };
        let full = run(&[]);
        let weights = [1.0, 0.5, 0.0];
        let weighted = run(&weights);
        assert_eq!(weighted.0, full.0, "the forward is unchanged");
        assert_eq!(
            weighted.1, full.1,
            "the tables' and MLPs' gradients are unchanged"
        );
        assert_eq!(weighted.3, full.3, "the direction gradient is unchanged");
        let shares: Vec<Vec<f32>> = (0..3)
            .map(|l| {
                let mut one = [0.0; 3];
                one[l] = 1.0;
                run(&one).2
            })
            .collect();
        let sum_of = |w: &[f32]| -> Vec<f32> {
            (0..n * 3)
                .map(|i| (0..3).map(|l| w[l] * shares[l][i]).sum())
                .collect()
        };
        let close = |x: &[f32], y: &[f32]| {
            x.iter()
                .zip(y)
                .all(|(p, q)| (p - q).abs() <= 1e-5 * (1.0 + q.abs()))
        };
        assert!(full.2.iter().any(|&g| g.abs() > 1e-3), "{:?}", full.2);
        assert!(close(&full.2, &sum_of(&[1.0; 3])), "the shares add up");
        assert!(close(&weighted.2, &sum_of(&weights)), "{:?}", weighted.2);
        assert!(!close(&weighted.2, &full.2), "the weights change it");
    }

    /// A forward's density and colours, every parameter's gradient, the positions' and
    /// the directions' gradients.
    type ForwardAndGradients = ((Vec<f32>, Vec<f32>), Vec<f32>, Vec<f32>, Vec<f32>);

    /// The forward's density and colours of the samples at `pos` looking along `dirs`,
    /// and the backward from `d_sigma` and `d_rgb`: every parameter's gradient and the
    /// positions' and directions' (`FastField::backward_with_positions`).
    fn with_input_gradients(
        field: &FastField,
        params: &[f32],
        (pos, dirs): (&[f32], &[f32]),
        (d_sigma, d_rgb): (&[f32], &[f32]),
    ) -> ForwardAndGradients {
        let mut ws = FastWorkspace::default();
        let out = field.forward(params, input(pos, dirs), &mut ws);
        let out = (out.sigma.to_vec(), out.rgb.to_vec());
        let mut grads = GradBuffer::new(field.num_params());
        let (mut d_pos, mut d_dirs) = (Vec::new(), Vec::new());
        let d = FieldGrad { d_sigma, d_rgb };
        field.backward_with_positions(
            params,
            &mut ws,
            d,
            &mut grads.all(),
            dirs,
            &mut d_pos,
            &mut d_dirs,
        );
        (out, grads.values, d_pos, d_dirs)
    }

    fn backward_matches_finite_differences_of(
        field: &FastField,
        looks: &[u32],
        footprints: &[f32],
    ) {
        let mut rng = Rng::new(11);
        let params = random_params(field, &mut rng);
        let n = 6;
        let pos: Vec<f32> = (0..n * 3).map(|_| rng.range(-1.4, 1.4)).collect();
        let dirs = rng.unit_directions(n);
        let a: Vec<f32> = (0..n).map(|_| rng.range(-1.0, 1.0)).collect();
        let b: Vec<f32> = (0..n * 3).map(|_| rng.range(-1.0, 1.0)).collect();
        // Moving fields: each sample at its own moment.
        let times: Vec<f32> = match field.motion {
            Some(_) => (0..n).map(|_| rng.uniform()).collect(),
            None => Vec::new(),
        };
        let loss = |p: &[f32]| -> f64 {
            let mut ws = FastWorkspace::default();
            let mut inp = input(&pos, &dirs);
            inp.appearance = looks;
            inp.footprints = footprints;
            inp.times = &times;
            let out = field.forward(p, inp, &mut ws);
            let ls: f64 = out.sigma.iter().zip(&a).map(|(s, a)| (s * a) as f64).sum();
            let lc: f64 = out.rgb.iter().zip(&b).map(|(c, b)| (c * b) as f64).sum();
            ls + lc
        };
        let mut ws = FastWorkspace::default();
        let mut inp = input(&pos, &dirs);
        inp.appearance = looks;
        inp.footprints = footprints;
        inp.times = &times;
        field.forward(&params, inp, &mut ws);
        let mut grads = GradBuffer::new(field.num_params());
        let d = FieldGrad {
            d_sigma: &a,
            d_rgb: &b,
        };
        field.backward(&params, &mut ws, d, &mut grads.all());
        let (mut err, mut norm, mut checked) = (0.0f64, 0.0f64, 0);
        for t in &field.layout.tensors {
            // Every code entry; every third of the rest.
            let stride = if t.name == "appearance.codes" { 1 } else { 3 };
            for i in t.range().step_by(stride) {
                let g = grads.values[i] as f64;
                if g == 0.0 {
                    continue;
                }
                let h = 1e-3;
                let (mut p1, mut p2) = (params.clone(), params.clone());
                p1[i] += h;
                p2[i] -= h;
                let fd = (loss(&p1) - loss(&p2)) / (2.0 * h as f64);
                err += (fd - g).powi(2);
                norm += g * g;
                checked += 1;
            }
        }
        let rel = (err / norm).sqrt();
        assert!(checked > 50, "only {checked} parameters had gradients");
        assert!(
            rel < 1e-2,
            "relative gradient error {rel} over {checked} parameters"
        );
    }

    /// Inference that colours only the picked samples gives them the forward's colours
    /// (appearance codes included), every sample the forward's density, and the other
    /// samples no colour; the picker sees every density.
    #[test]
    fn picked_samples_get_the_forwards_colours_and_the_rest_none() {
        let field = tiny_with_codes(2, 3);
        let mut params = field.init_params(4);
        let mut rng = crate::rng::Rng::new(3);
        params.iter_mut().for_each(|v| *v += rng.range(-0.5, 0.5));
        let n = 9;
        let pos: Vec<f32> = (0..3 * n).map(|_| rng.range(-1.2, 1.2)).collect();
        let dirs: Vec<f32> = (0..n)
            .flat_map(|k| [0.6, 0.0, 0.8].map(|v| v * (k as f32 - 4.0).signum().max(0.5)))
            .collect();
        let appearance: Vec<u32> = (0..n as u32).map(|k| k % 4).collect();
        let with_codes = FieldInput {
            appearance: &appearance,
            ..input(&pos, &dirs)
        };
        let mut ws = FastWorkspace::default();
        let full = field.forward(&params, with_codes, &mut ws);
        let (sigma, rgb) = (full.sigma.to_vec(), full.rgb.to_vec());
        for picks in [
            vec![],
            vec![0],
            vec![3, 4, 8],
            (0..n as u32).collect::<Vec<_>>(),
        ] {
            let mut seen = Vec::new();
            let mut ws = FastWorkspace::default();
            let out = field.infer_picked(&params, with_codes, &mut ws, &mut |s, picked| {
                seen = s.to_vec();
                picked.extend(&picks);
            });
            assert_eq!(seen, sigma);
            assert_eq!(out.sigma, &sigma[..]);
            for s in 0..n {
                let got = &out.rgb[3 * s..3 * s + 3];
                if picks.contains(&(s as u32)) {
                    assert_eq!(got, &rgb[3 * s..3 * s + 3], "sample {s} of {picks:?}");
                } else {
                    assert_eq!(got, &[0.0; 3], "sample {s} of {picks:?}");
                }
            }
        }
    }

    #[test]
    fn density_alone_matches_the_full_forward() {
        let field = tiny();
        let params = field.init_params(2);
        let pos = [0.1, 0.2, -0.3, 1.0, -1.2, 0.4];
        let dirs = [0.0, 0.0, 1.0, 1.0, 0.0, 0.0];
        let mut ws = FastWorkspace::default();
        let full = field
            .forward(&params, input(&pos, &dirs), &mut ws)
            .sigma
            .to_vec();
        let mut alone = [0.0; 2];
        field.density(&params, &pos, &mut FastWorkspace::default(), &mut alone);
        assert_eq!(full, alone.to_vec());
        // One direction shared by both samples gives the colour of each sample seen along it.
        let shared = FieldInput {
            positions: &pos,
            dirs: &dirs[..3],
            samples_per_dir: 2,
            appearance: &[],
            footprints: &[],
            variances: &[],
            times: &[],
        };
        let rgb = field.forward(&params, shared, &mut ws).rgb.to_vec();
        let per_sample = [0.0, 0.0, 1.0, 0.0, 0.0, 1.0];
        assert_eq!(
            rgb,
            field
                .forward(&params, input(&pos, &per_sample), &mut ws)
                .rgb
        );
        // Near-zero tables and zero-mean weights: density starts near exp(0) = 1.
        assert!(full.iter().all(|s| (0.5..2.0).contains(s)), "{full:?}");
    }
}
