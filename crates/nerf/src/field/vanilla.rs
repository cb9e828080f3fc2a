//! The paper's radiance field: an 8 x 256 ReLU MLP over positionally encoded positions, with
//! the encoded input concatenated again after the 4th layer, a density head, a 256 feature,
//! and a 128-wide view branch that sees the encoded direction (NeRF, figure 7).
//!
//! Work mapping: one call evaluates `n` samples belonging to `r` rays of equal sample count
//! (`n = r * samples_per_ray`), one dense layer at a time, each a single-threaded GEMM over
//! the whole chunk; the caller runs chunks on different threads. Activations stay in a
//! [`VanillaWorkspace`] that is reused across calls, so training allocates nothing per step.
//!
//! Because a ray's direction is the same for all its samples, the direction's contribution
//! to the view layer is computed once per ray (`dir_proj`) and broadcast, and its weight
//! gradient is taken from per-ray sums: exactly the product with the concatenated input,
//! for about 3% less work.
//!
//! Weights are `in x out` row-major. A layer with a concatenated input stores one matrix
//! whose first rows multiply the hidden state and whose last rows multiply the encoding.

use serde::{Deserialize, Serialize};

use super::deformation::{Deformation, DeformationConfig, DeformationWorkspace};
use crate::encoding::FrequencyEncoding;
use crate::nn::activation::{col_sum_into, relu, sigmoid};
use crate::nn::dense::Dense;
use crate::nn::grow;
use crate::nn::linalg::{matmul, MatRef};
use crate::nn::trunk::Trunk;
use crate::nn::{Grads, ParamLayout};
use crate::stage::{Field, FieldGrad, FieldInput, FieldOutput};

/// The shape of one vanilla network.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct VanillaConfig {
    /// Hidden layers of the trunk (paper: 8).
    pub depth: usize,
    /// Width of the trunk (paper: 256).
    pub width: usize,
    /// The encoded position is concatenated to the output of this trunk layer (0-based;
    /// paper: 4, i.e. it enters the 6th layer). `None`: no skip.
    pub skip: Option<usize>,
    pub position_encoding: FrequencyEncoding,
    /// `None`: colour from the trunk alone (the "no view dependence" ablation).
    pub direction_encoding: Option<FrequencyEncoding>,
    /// Width of the view branch (paper: 128).
    pub view_width: usize,
    /// D-NeRF: a deformation carries each point, at the moment it is seen, into the
    /// canonical scene this network describes (`None`: a still scene).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub deformation: Option<DeformationConfig>,
}

impl VanillaConfig {
    pub fn paper() -> Self {
        VanillaConfig {
            depth: 8,
            width: 256,
            skip: Some(4),
            position_encoding: FrequencyEncoding {
                frequencies: 10,
                paper_form: false,
            },
            direction_encoding: Some(FrequencyEncoding {
                frequencies: 4,
                paper_form: false,
            }),
            view_width: 128,
            deformation: None,
        }
    }
}

/// Where each layer's weights sit in the flat parameter vector.
#[derive(Clone, Debug)]
pub struct VanillaNet {
    pub config: VanillaConfig,
    pub layout: ParamLayout,
    trunk: Trunk,
    heads: Heads,
    deformation: Option<Deformation>,
    /// FreeNeRF's frequency regularisation: each band of the position's encoding scaled by
    /// its visibility (`model::free_nerf`); empty: every band whole.
    pub band_mask: Vec<f32>,
}

#[derive(Clone, Debug)]
enum Heads {
    /// sigma from the trunk; colour from `feature` + encoded direction.
    ViewDependent {
        sigma: Dense,
        feature: Dense,
        view: Dense,
        rgb: Dense,
    },
    /// One layer to (r, g, b, sigma).
    Direct { output: Dense },
}

impl VanillaNet {
    /// Lays out the parameters under `prefix` (e.g. `"coarse."`).
    pub fn new(config: VanillaConfig, prefix: &str) -> Self {
        let mut layout = ParamLayout::default();
        let in_x = config.position_encoding.dims();
        let w = config.width;
        let trunk = Trunk::new(
            &mut layout,
            &format!("{prefix}pts_"),
            in_x,
            config.depth,
            w,
            config.skip,
        );
        let heads = match config.direction_encoding {
            Some(dir) => Heads::ViewDependent {
                sigma: Dense::push(&mut layout, &format!("{prefix}sigma"), w, 1),
                feature: Dense::push(&mut layout, &format!("{prefix}feature"), w, w),
                view: Dense::push(
                    &mut layout,
                    &format!("{prefix}view"),
                    w + dir.dims(),
                    config.view_width,
                ),
                rgb: Dense::push(&mut layout, &format!("{prefix}rgb"), config.view_width, 3),
            },
            None => Heads::Direct {
                output: Dense::push(&mut layout, &format!("{prefix}output"), w, 4),
            },
        };
        let deformation = config.deformation.clone().map(|d| {
            let prefix = format!("{prefix}time_");
            Deformation::new(d, config.position_encoding, &mut layout, &prefix)
        });
        VanillaNet {
            config,
            layout,
            trunk,
            heads,
            deformation,
            band_mask: Vec::new(),
        }
    }

    /// Scales each band of `n` encoded positions (`n x dims()`, in place) by
    /// [`Self::band_mask`]; the raw position (the reference form's first three values)
    /// passes whole.
    fn mask_bands(&self, encoded: &mut [f32]) {
        if self.band_mask.is_empty() {
            return;
        }
        let e = self.config.position_encoding;
        let first = e.dims() - 6 * e.frequencies;
        for row in encoded.chunks_exact_mut(e.dims()) {
            for (band, &m) in row[first..].chunks_exact_mut(6).zip(&self.band_mask) {
                band.iter_mut().for_each(|v| *v *= m);
            }
        }
    }

    pub fn num_params(&self) -> usize {
        self.layout.total
    }

    /// Finishes a fresh initialisation of this network's `params` (see
    /// [`Deformation::start_still`]).
    pub fn finish_init(&self, params: &mut [f32]) {
        if let Some(d) = &self.deformation {
            d.start_still(params);
        }
    }

    /// Multiply-adds of one forward evaluation of one sample (the per-ray direction term is
    /// counted per sample, as an unfused implementation would do it).
    pub fn macs_per_sample(&self) -> usize {
        let trunk = self.trunk.macs();
        let heads = match &self.heads {
            Heads::ViewDependent {
                sigma,
                feature,
                view,
                rgb,
            } => [sigma, feature, view, rgb].iter().map(|d| d.macs()).sum(),
            Heads::Direct { output } => output.macs(),
        };
        trunk
            + heads
            + self
                .deformation
                .as_ref()
                .map_or(0, Deformation::macs_per_sample)
    }

    /// Evaluates `n = dirs.len() / 3 * samples_per_ray` samples. `positions` is `n x 3`,
    /// `variances` `n x 3` covariance diagonals (mip-NeRF's frustums, encoded by the
    /// integrated encoding) or empty (points), `times` `n` moments or empty (all at 0, the
    /// canonical moment), `dirs` one unit direction per ray (`r x 3`). Fills `ws.sigma` (`n`,
    /// after ReLU) and `ws.rgb` (`n x 3`, after sigmoid) and keeps what
    /// [`Self::eval_rays_bwd`] needs.
    #[allow(clippy::too_many_arguments)]
    pub fn eval_rays(
        &self,
        params: &[f32],
        positions: &[f32],
        variances: &[f32],
        times: &[f32],
        dirs: &[f32],
        samples_per_ray: usize,
        ws: &mut VanillaWorkspace,
    ) {
        let rays = dirs.len() / 3;
        let n = rays * samples_per_ray;
        assert_eq!(
            positions.len(),
            n * 3,
            "positions must be rays x samples_per_ray x 3"
        );
        ws.resize(&self.config, n, rays);
        let cfg = &self.config;
        let (in_x, w) = (cfg.position_encoding.dims(), cfg.width);
        ws.times.clear();
        let positions = match &self.deformation {
            Some(d) if !times.is_empty() => {
                assert!(
                    variances.is_empty(),
                    "no integrated encoding with a deformation"
                );
                d.forward(params, positions, times, &mut ws.deform);
                ws.times.extend_from_slice(times);
                &ws.deform.moved[..n * 3]
            }
            _ => positions,
        };
        if variances.is_empty() {
            cfg.position_encoding
                .encode_all(positions, &mut ws.enc[..n * in_x]);
        } else {
            assert_eq!(variances.len(), n * 3, "variances must be n x 3");
            for ((p, v), o) in positions
                .chunks_exact(3)
                .zip(variances.chunks_exact(3))
                .zip(ws.enc.chunks_exact_mut(in_x))
            {
                cfg.position_encoding.encode_integrated(p, v, o);
            }
        }

        self.mask_bands(&mut ws.enc[..n * in_x]);
        self.trunk.forward(params, &ws.enc, n, &mut ws.hidden);
        let last = &ws.hidden[cfg.depth - 1][..n * w];
        match &self.heads {
            Heads::ViewDependent {
                sigma,
                feature,
                view,
                rgb,
            } => {
                // Density: one dot product per sample.
                let ws_sigma = &params[sigma.w..][..w];
                for (s, h) in ws.raw_sigma[..n].iter_mut().zip(last.chunks_exact(w)) {
                    *s = params[sigma.b] + dot(h, ws_sigma);
                }
                feature.fill_bias(params, &mut ws.feature[..n * w]);
                matmul(
                    &mut ws.feature[..n * w],
                    MatRef::new(last, n, w),
                    feature.weight(params, 0, w),
                    true,
                );
                // View branch: feature part per sample, direction part once per ray.
                let dir_enc = cfg
                    .direction_encoding
                    .expect("view-dependent heads have a direction encoding");
                let (in_d, vw) = (dir_enc.dims(), cfg.view_width);
                dir_enc.encode_all(dirs, &mut ws.dir_enc[..rays * in_d]);
                view.fill_bias(params, &mut ws.dir_proj[..rays * vw]);
                matmul(
                    &mut ws.dir_proj[..rays * vw],
                    MatRef::new(&ws.dir_enc, rays, in_d),
                    view.weight(params, w, in_d),
                    true,
                );
                for (r, rows) in ws.view_hidden[..n * vw]
                    .chunks_exact_mut(samples_per_ray * vw)
                    .enumerate()
                {
                    let proj = &ws.dir_proj[r * vw..][..vw];
                    for row in rows.chunks_exact_mut(vw) {
                        row.copy_from_slice(proj);
                    }
                }
                matmul(
                    &mut ws.view_hidden[..n * vw],
                    MatRef::new(&ws.feature, n, w),
                    view.weight(params, 0, w),
                    true,
                );
                relu(&mut ws.view_hidden[..n * vw]);
                let (wr, br) = (&params[rgb.w..][..vw * 3], &params[rgb.b..][..3]);
                for (h, out) in ws.view_hidden[..n * vw]
                    .chunks_exact(vw)
                    .zip(ws.rgb.chunks_exact_mut(3))
                {
                    for c in 0..3 {
                        let mut acc = br[c];
                        for (k, &hk) in h.iter().enumerate() {
                            acc += hk * wr[k * 3 + c];
                        }
                        out[c] = sigmoid(acc);
                    }
                }
            }
            Heads::Direct { output } => {
                let (wo, bo) = (&params[output.w..][..w * 4], &params[output.b..][..4]);
                for ((h, out), s) in last
                    .chunks_exact(w)
                    .zip(ws.rgb.chunks_exact_mut(3))
                    .zip(&mut ws.raw_sigma)
                {
                    let mut acc = [bo[0], bo[1], bo[2], bo[3]];
                    for (k, &hk) in h.iter().enumerate() {
                        for (c, a) in acc.iter_mut().enumerate() {
                            *a += hk * wo[k * 4 + c];
                        }
                    }
                    out.copy_from_slice(&[sigmoid(acc[0]), sigmoid(acc[1]), sigmoid(acc[2])]);
                    *s = acc[3];
                }
            }
        }
        for (s, &raw) in ws.sigma[..n].iter_mut().zip(&ws.raw_sigma) {
            *s = raw.max(0.0);
        }
    }

    /// Backward of the last [`Self::eval_rays`] on `ws`: given `d_sigma` (`n`) and `d_rgb`
    /// (`n x 3`), accumulates parameter gradients into `grads` (same layout as `params`).
    pub fn eval_rays_bwd(
        &self,
        params: &[f32],
        ws: &mut VanillaWorkspace,
        d_sigma: &[f32],
        d_rgb: &[f32],
        grads: &mut [f32],
    ) {
        let (n, rays) = (ws.n, ws.rays);
        let spr = n / rays.max(1);
        let cfg = &self.config;
        let (in_x, w) = (cfg.position_encoding.dims(), cfg.width);
        let last = &ws.hidden[cfg.depth - 1][..n * w];
        // `d_a` receives the gradient with respect to the last trunk layer's output.
        match &self.heads {
            Heads::ViewDependent {
                sigma,
                feature,
                view,
                rgb,
            } => {
                let dir_enc = cfg
                    .direction_encoding
                    .expect("view-dependent heads have a direction encoding");
                let (in_d, vw) = (dir_enc.dims(), cfg.view_width);
                // RGB layer (sigmoid): d_raw = d_rgb * rgb (1 - rgb).
                let wr = &params[rgb.w..][..vw * 3];
                let (gw, gb) = rgb.slices_mut(grads);
                for (s, (h, dh)) in ws.view_hidden[..n * vw]
                    .chunks_exact(vw)
                    .zip(ws.d_view.chunks_exact_mut(vw))
                    .enumerate()
                {
                    let mut d_raw = [0.0f32; 3];
                    for c in 0..3 {
                        let y = ws.rgb[s * 3 + c];
                        d_raw[c] = d_rgb[s * 3 + c] * y * (1.0 - y);
                        gb[c] += d_raw[c];
                    }
                    for k in 0..vw {
                        let g = &mut gw[k * 3..][..3];
                        g[0] += h[k] * d_raw[0];
                        g[1] += h[k] * d_raw[1];
                        g[2] += h[k] * d_raw[2];
                        // ReLU of the view layer folded in.
                        dh[k] = if h[k] > 0.0 {
                            wr[k * 3] * d_raw[0]
                                + wr[k * 3 + 1] * d_raw[1]
                                + wr[k * 3 + 2] * d_raw[2]
                        } else {
                            0.0
                        };
                    }
                }
                // View layer: feature rows per sample, direction rows from per-ray sums.
                let d_view = &ws.d_view[..n * vw];
                {
                    let (gw, gb) = view.slices_mut(grads);
                    col_sum_into(d_view, vw, gb);
                    matmul(
                        &mut gw[..w * vw],
                        MatRef::new(&ws.feature, n, w).t(),
                        MatRef::new(d_view, n, vw),
                        true,
                    );
                    for (r, rows) in d_view.chunks_exact(spr * vw).enumerate() {
                        let dp = &mut ws.d_dir_proj[r * vw..][..vw];
                        dp.fill(0.0);
                        for row in rows.chunks_exact(vw) {
                            for (a, b) in dp.iter_mut().zip(row) {
                                *a += b;
                            }
                        }
                    }
                    matmul(
                        &mut gw[w * vw..],
                        MatRef::new(&ws.dir_enc, rays, in_d).t(),
                        MatRef::new(&ws.d_dir_proj, rays, vw),
                        true,
                    );
                }
                let d_feat = &mut ws.d_a[..n * w];
                matmul(
                    d_feat,
                    MatRef::new(d_view, n, vw),
                    view.weight(params, 0, w).t(),
                    false,
                );
                // Feature layer (linear).
                {
                    let (gw, gb) = feature.slices_mut(grads);
                    col_sum_into(d_feat, w, gb);
                    matmul(
                        gw,
                        MatRef::new(last, n, w).t(),
                        MatRef::new(d_feat, n, w),
                        true,
                    );
                }
                let d_last = &mut ws.d_b[..n * w];
                matmul(
                    d_last,
                    MatRef::new(&ws.d_a, n, w),
                    feature.weight(params, 0, w).t(),
                    false,
                );
                // Density head (ReLU on the raw output).
                let w_sigma = &params[sigma.w..][..w];
                let (gw, gb) = sigma.slices_mut(grads);
                for s in 0..n {
                    let ds = if ws.raw_sigma[s] > 0.0 {
                        d_sigma[s]
                    } else {
                        0.0
                    };
                    if ds == 0.0 {
                        continue;
                    }
                    gb[0] += ds;
                    let h = &last[s * w..][..w];
                    let dh = &mut d_last[s * w..][..w];
                    for k in 0..w {
                        gw[k] += h[k] * ds;
                        dh[k] += w_sigma[k] * ds;
                    }
                }
                std::mem::swap(&mut ws.d_a, &mut ws.d_b);
            }
            Heads::Direct { output } => {
                let wo = &params[output.w..][..w * 4];
                let d_raw = &mut ws.d_view[..n * 4];
                for s in 0..n {
                    for c in 0..3 {
                        let y = ws.rgb[s * 3 + c];
                        d_raw[s * 4 + c] = d_rgb[s * 3 + c] * y * (1.0 - y);
                    }
                    d_raw[s * 4 + 3] = if ws.raw_sigma[s] > 0.0 {
                        d_sigma[s]
                    } else {
                        0.0
                    };
                }
                let (gw, gb) = output.slices_mut(grads);
                col_sum_into(d_raw, 4, gb);
                matmul(
                    gw,
                    MatRef::new(last, n, w).t(),
                    MatRef::new(d_raw, n, 4),
                    true,
                );
                matmul(
                    &mut ws.d_a[..n * w],
                    MatRef::new(d_raw, n, 4),
                    MatRef::new(wo, w, 4).t(),
                    false,
                );
            }
        }
        let deformation = self.deformation.as_ref().filter(|_| !ws.times.is_empty());
        self.trunk.backward(
            params,
            &ws.enc,
            &ws.hidden,
            n,
            &mut ws.d_a,
            &mut ws.d_b,
            grads,
            deformation.map(|_| &mut ws.d_enc[..n * in_x]),
        );
        if let Some(d) = deformation {
            // The trunk's input gradient is the masked encoding's.
            self.mask_bands(&mut ws.d_enc[..n * in_x]);
            let moved = &ws.deform.moved[..n * 3];
            for ((p, d_enc), d_p) in moved
                .chunks_exact(3)
                .zip(ws.d_enc.chunks_exact(in_x))
                .zip(ws.d_moved.chunks_exact_mut(3))
            {
                cfg.position_encoding.encode_bwd(p, d_enc, d_p);
            }
            d.backward(
                params,
                &ws.times,
                &ws.d_moved[..n * 3],
                &mut ws.deform,
                grads,
            );
        }
    }

    /// Densities at `positions` (`n x 3`) at moment `time` (`None`: the canonical one).
    pub fn density_at(
        &self,
        params: &[f32],
        positions: &[f32],
        time: Option<f32>,
        ws: &mut VanillaWorkspace,
        out: &mut [f32],
    ) {
        let n = out.len();
        ws.time_fill.clear();
        if let Some(t) = time {
            ws.time_fill.resize(n, t);
        }
        let times = std::mem::take(&mut ws.time_fill);
        // Density does not depend on the direction: one "ray" of all the points.
        self.eval_rays(params, positions, &[], &times, &[0.0, 0.0, 1.0], n, ws);
        ws.time_fill = times;
        out.copy_from_slice(&ws.sigma[..n]);
    }
}

#[inline]
fn dot(a: &[f32], b: &[f32]) -> f32 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

impl Field for VanillaNet {
    type Context = VanillaWorkspace;

    fn num_params(&self) -> usize {
        VanillaNet::num_params(self)
    }

    /// `input.samples_per_dir` is the samples per ray: all samples of a ray share its
    /// direction, whose share of the view layer is computed once per ray.
    fn forward<'c>(
        &self,
        params: &[f32],
        input: FieldInput,
        ctx: &'c mut VanillaWorkspace,
    ) -> FieldOutput<'c> {
        let n = input.len();
        self.eval_rays(
            params,
            input.positions,
            input.variances,
            input.times,
            input.dirs,
            input.samples_per_dir,
            ctx,
        );
        FieldOutput {
            sigma: &ctx.sigma[..n],
            rgb: &ctx.rgb[..n * 3],
        }
    }

    fn backward(
        &self,
        params: &[f32],
        ctx: &mut VanillaWorkspace,
        d_output: FieldGrad,
        grads: &mut Grads,
    ) {
        self.eval_rays_bwd(params, ctx, d_output.d_sigma, d_output.d_rgb, grads.dense());
    }

    fn density(
        &self,
        params: &[f32],
        positions: &[f32],
        ctx: &mut VanillaWorkspace,
        out: &mut [f32],
    ) {
        self.density_at(params, positions, None, ctx, out);
    }
}

/// Activations of one chunk, kept for the backward pass, plus scratch for it. Grows to the
/// largest chunk seen and is then reused.
#[derive(Default, Debug)]
pub struct VanillaWorkspace {
    n: usize,
    rays: usize,
    enc: Vec<f32>,
    hidden: Vec<Vec<f32>>,
    raw_sigma: Vec<f32>,
    feature: Vec<f32>,
    dir_enc: Vec<f32>,
    dir_proj: Vec<f32>,
    view_hidden: Vec<f32>,
    /// Density after ReLU, one per sample.
    pub sigma: Vec<f32>,
    /// Colour after sigmoid, three per sample.
    pub rgb: Vec<f32>,
    d_a: Vec<f32>,
    d_b: Vec<f32>,
    d_view: Vec<f32>,
    d_dir_proj: Vec<f32>,
    /// The deformation's activations and the moments it saw (empty: none ran).
    deform: DeformationWorkspace,
    times: Vec<f32>,
    time_fill: Vec<f32>,
    d_enc: Vec<f32>,
    d_moved: Vec<f32>,
}

impl VanillaWorkspace {
    fn resize(&mut self, cfg: &VanillaConfig, n: usize, rays: usize) {
        self.n = n;
        self.rays = rays;
        let (w, vw) = (cfg.width, cfg.view_width.max(4));
        let in_d = cfg.direction_encoding.map_or(0, |e| e.dims());
        grow(&mut self.enc, n * cfg.position_encoding.dims());
        self.hidden.resize_with(cfg.depth, Vec::new);
        for h in &mut self.hidden {
            grow(h, n * w);
        }
        for v in [&mut self.raw_sigma, &mut self.sigma] {
            grow(v, n);
        }
        grow(&mut self.rgb, n * 3);
        for v in [&mut self.feature, &mut self.d_a, &mut self.d_b] {
            grow(v, n * w);
        }
        grow(&mut self.dir_enc, rays * in_d);
        grow(&mut self.dir_proj, rays * vw);
        grow(&mut self.d_dir_proj, rays * vw);
        grow(&mut self.view_hidden, n * vw);
        grow(&mut self.d_view, n * vw);
        if cfg.deformation.is_some() {
            grow(&mut self.d_enc, n * cfg.position_encoding.dims());
            grow(&mut self.d_moved, n * 3);
        }
    }

    /// Bytes held, for memory reports.
    pub fn bytes(&self) -> usize {
        let vecs = [
            &self.enc,
            &self.raw_sigma,
            &self.feature,
            &self.dir_enc,
            &self.dir_proj,
            &self.view_hidden,
            &self.sigma,
            &self.rgb,
            &self.d_a,
            &self.d_b,
            &self.d_view,
            &self.d_dir_proj,
            &self.times,
            &self.time_fill,
            &self.d_enc,
            &self.d_moved,
        ];
        4 * (vecs.iter().map(|v| v.len()).sum::<usize>()
            + self.hidden.iter().map(|v| v.len()).sum::<usize>())
            + self.deform.bytes()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    fn tiny(view_dependent: bool) -> VanillaConfig {
        VanillaConfig {
            depth: 4,
            width: 8,
            skip: Some(1),
            position_encoding: FrequencyEncoding {
                frequencies: 2,
                paper_form: false,
            },
            direction_encoding: view_dependent.then_some(FrequencyEncoding {
                frequencies: 1,
                paper_form: false,
            }),
            view_width: 4,
            deformation: None,
        }
    }

    /// Loss `sum(a * sigma) + sum(b * rgb)` for fixed random a, b; checks every parameter's
    /// analytic gradient against central differences (in f64 accumulation of f32 outputs).
    fn check_gradients(cfg: VanillaConfig) {
        check_gradients_at(cfg, false);
    }

    /// As [`check_gradients`]; `moving`: every sample at its own moment (some at 0, where
    /// the deformation is off), so the deformation's gradients are checked too.
    fn check_gradients_at(cfg: VanillaConfig, moving: bool) {
        check_masked_gradients(cfg, moving, &[]);
    }

    /// As [`check_gradients_at`], with the position encoding's bands masked by `mask`.
    fn check_masked_gradients(cfg: VanillaConfig, moving: bool, mask: &[f32]) {
        let mut net = VanillaNet::new(cfg, "");
        net.band_mask = mask.to_vec();
        let mut rng = Rng::new(11);
        let mut params = net.layout.init_glorot(&mut rng);
        // Non-zero biases so ReLU kinks are generic.
        for t in &net.layout.tensors {
            if t.shape.len() == 1 {
                for v in &mut params[t.range()] {
                    *v = rng.range(-0.3, 0.3);
                }
            }
        }
        let (rays, spr) = (3, 4);
        let n = rays * spr;
        let pos: Vec<f32> = (0..n * 3).map(|_| rng.range(-1.0, 1.0)).collect();
        let dirs: Vec<f32> = (0..rays)
            .flat_map(|_| {
                crate::math::normalize_or_zero([
                    rng.range(-1.0, 1.0),
                    rng.range(-1.0, 1.0),
                    rng.range(-1.0, 1.0),
                ])
            })
            .collect();
        let a: Vec<f32> = (0..n).map(|_| rng.range(-1.0, 1.0)).collect();
        let b: Vec<f32> = (0..n * 3).map(|_| rng.range(-1.0, 1.0)).collect();
        let times: Vec<f32> = match moving {
            true => (0..n)
                .map(|i| if i % 5 == 0 { 0.0 } else { rng.range(0.0, 1.0) })
                .collect(),
            false => Vec::new(),
        };
        let mut ws = VanillaWorkspace::default();
        let loss = |p: &[f32], ws: &mut VanillaWorkspace| -> f64 {
            net.eval_rays(p, &pos, &[], &times, &dirs, spr, ws);
            let s: f64 = ws.sigma[..n]
                .iter()
                .zip(&a)
                .map(|(x, y)| (*x as f64) * (*y as f64))
                .sum();
            s + ws.rgb[..n * 3]
                .iter()
                .zip(&b)
                .map(|(x, y)| (*x as f64) * (*y as f64))
                .sum::<f64>()
        };
        loss(&params, &mut ws);
        let mut grads = vec![0.0; params.len()];
        net.eval_rays_bwd(&params, &mut ws, &a, &b, &mut grads);
        // Small step: a larger one lets some ReLU input cross zero and spoils the difference.
        let h = 1e-4f32;
        let (mut err2, mut norm2) = (0.0f64, 0.0f64);
        for i in 0..params.len() {
            let orig = params[i];
            params[i] = orig + h;
            let lp = loss(&params, &mut ws);
            params[i] = orig - h;
            let lm = loss(&params, &mut ws);
            params[i] = orig;
            let fd = (lp - lm) / (2.0 * h as f64);
            err2 += (fd - grads[i] as f64).powi(2);
            norm2 += fd * fd;
        }
        let rel = (err2 / norm2).sqrt();
        if moving {
            // The deformation's parameters follow the field's: they must have moved.
            let first = net
                .layout
                .tensors
                .iter()
                .find(|t| t.name.starts_with("time_"));
            let start = first.expect("a deformation's tensors").offset;
            assert!(
                grads[start..].iter().any(|g| *g != 0.0),
                "no deformation gradient"
            );
        }

        assert!(norm2 > 0.0 && rel < 1e-2, "relative gradient error {rel}");
    }

    #[test]
    fn gradients_view_dependent() {
        check_gradients(tiny(true));
    }

    /// The tiny view-dependent net with a tiny deformation.
    fn tiny_moving() -> VanillaConfig {
        VanillaConfig {
            deformation: Some(DeformationConfig {
                depth: 3,
                width: 6,
                skip: Some(0),
                time_frequencies: 2,
            }),
            ..tiny(true)
        }
    }

    #[test]
    fn gradients_through_a_deformation() {
        check_gradients_at(tiny_moving(), true);
    }

    /// FreeNeRF's mask scales the bands in the forward and, through a deformation, in the
    /// input's gradient (finite differences with a partial mask); the masked encoding is
    /// the raw position whole and each band times its visibility.
    #[test]
    fn gradients_with_masked_bands() {
        let cfg = tiny_moving();
        let bands = cfg.position_encoding.frequencies;
        assert!(bands >= 2, "the tiny net has {bands} bands");
        let mut mask = vec![0.0; bands];
        mask[0] = 1.0;
        mask[1] = 0.4;
        check_masked_gradients(cfg.clone(), true, &mask);
        // The masked encoding: the raw position whole, each band times its visibility.
        let mut net = VanillaNet::new(
            VanillaConfig {
                deformation: None,
                ..cfg
            },
            "",
        );
        net.band_mask = mask.clone();
        let e = net.config.position_encoding;
        let mut enc = vec![0.0; e.dims()];
        e.encode(&[0.3, -0.2, 0.7], &mut enc);
        let mut masked = enc.clone();
        net.mask_bands(&mut masked);
        let first = e.dims() - 6 * bands;
        assert_eq!(masked[..first], enc[..first]);
        for (k, &m) in mask.iter().enumerate() {
            for j in 0..6 {
                let at = first + 6 * k + j;
                assert_eq!(masked[at], enc[at] * m, "band {k}");
            }
        }
    }

    /// At moment 0 the deformation is off: the field is its canonical network alone, and
    /// at another moment it moves.
    #[test]
    fn the_canonical_moment_is_not_deformed() {
        let cfg = VanillaConfig {
            deformation: Some(DeformationConfig {
                depth: 2,
                width: 8,
                skip: None,
                time_frequencies: 2,
            }),
            ..tiny(false)
        };
        let net = VanillaNet::new(cfg, "");
        let params = net.layout.init_glorot(&mut Rng::new(3));
        let pos = [0.1, 0.2, 0.3, -0.4, 0.5, 0.0];
        let (mut ws, mut out) = (VanillaWorkspace::default(), [0.0f32; 2]);
        let dir = [0.0, 0.0, 1.0];
        net.eval_rays(&params, &pos, &[], &[], &dir, 2, &mut ws);
        let still = ws.rgb[..6].to_vec();
        net.eval_rays(&params, &pos, &[], &[0.0, 0.0], &dir, 2, &mut ws);
        assert_eq!(ws.rgb[..6], still[..]);
        net.eval_rays(&params, &pos, &[], &[0.7, 0.7], &dir, 2, &mut ws);
        assert_ne!(ws.rgb[..6], still[..]);
        net.density_at(&params, &pos, Some(0.0), &mut ws, &mut out);
        let canonical = out;
        net.density_at(&params, &pos, None, &mut ws, &mut out);
        assert_eq!(out, canonical);
    }

    #[test]
    fn gradients_without_view_dependence() {
        check_gradients(tiny(false));
    }

    #[test]
    fn paper_shape_and_flops() {
        let net = VanillaNet::new(VanillaConfig::paper(), "coarse.");
        // 63->256, 6 x 256->256, (256+63)->256, sigma 256->1, feature 256->256,
        // view (256+27)->128, rgb 128->3.
        let macs = 63 * 256 + 6 * 256 * 256 + 319 * 256 + 256 + 256 * 256 + 283 * 128 + 128 * 3;
        assert_eq!(net.macs_per_sample(), macs);
        assert_eq!(net.layout.tensors[0].name, "coarse.pts_0.weight");
        assert_eq!(net.layout.tensors[10].shape, vec![319, 256]);
        // 262,144 evaluations x 3 (forward + backward) x 2 flops per MAC: about 933 GFLOP.
        let gflop = 262_144.0 * 6.0 * macs as f64 / 1e9;
        assert!((gflop - 933.0).abs() < 1.0, "{gflop}");
    }

    #[test]
    fn direction_changes_colour_only_when_view_dependent() {
        for vd in [true, false] {
            let net = VanillaNet::new(tiny(vd), "");
            let params = net.layout.init_glorot(&mut Rng::new(2));
            let mut ws = VanillaWorkspace::default();
            let pos = [0.1, 0.2, 0.3];
            net.eval_rays(&params, &pos, &[], &[], &[1.0, 0.0, 0.0], 1, &mut ws);
            let c1 = ws.rgb[..3].to_vec();
            net.eval_rays(&params, &pos, &[], &[], &[0.0, 1.0, 0.0], 1, &mut ws);
            assert_eq!(c1 != ws.rgb[..3], vd);
        }
    }
}
