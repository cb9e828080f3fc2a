//! The paper's two-pass renderer for a chunk of rays: stratified samples through the coarse
//! network, importance samples from its weights, then the fine network on the sorted union.
//!
//! Work mapping: a chunk of `r` rays is processed by one thread start to finish, in its own
//! [`ChunkWorkspace`]; in training the coarse pass runs forward and backward before the fine
//! pass runs, so both share one set of activation buffers. Every ray carries its own
//! [`Rng`] stream, so results do not depend on how rays are grouped into chunks.

use crate::field::{VanillaNet, VanillaWorkspace};
use crate::math::{length, scale};
use crate::model::VanillaModel;
use crate::render::sampling::{merge_sorted, sample_pdf, stratified};
use crate::render::volume::{composite, composite_bwd, depth_deltas, RayOutput};
use crate::rng::Rng;

/// A chunk of rays: packed `r x 3` origins, (unnormalised) directions and background colours.
#[derive(Clone, Copy, Debug)]
pub struct Rays<'a> {
    pub origins: &'a [f32],
    pub dirs: &'a [f32],
    /// The directions colour depends on, when they differ from `dirs`: NDC rays are
    /// marched along warped directions but seen from their world directions (as in the
    /// paper's code).
    pub view_dirs: Option<&'a [f32]>,
    pub backgrounds: &'a [f32],
    pub near: f32,
    pub far: f32,
}

impl Rays<'_> {
    pub fn len(&self) -> usize {
        self.origins.len() / 3
    }
    pub fn is_empty(&self) -> bool {
        self.origins.is_empty()
    }
    fn dir(&self, r: usize) -> [f32; 3] {
        [self.dirs[r * 3], self.dirs[r * 3 + 1], self.dirs[r * 3 + 2]]
    }
    /// The (unnormalised) direction of ray `r` that colour is conditioned on.
    pub fn view_dir(&self, r: usize) -> [f32; 3] {
        let d = self.view_dirs.unwrap_or(self.dirs);
        [d[r * 3], d[r * 3 + 1], d[r * 3 + 2]]
    }
    fn bg(&self, r: usize) -> [f32; 3] {
        [
            self.backgrounds[r * 3],
            self.backgrounds[r * 3 + 1],
            self.backgrounds[r * 3 + 2],
        ]
    }
}

/// Reused buffers of one thread.
#[derive(Default, Debug)]
pub struct ChunkWorkspace {
    net: VanillaWorkspace,
    unit_dirs: Vec<f32>,
    positions: Vec<f32>,
    t_coarse: Vec<f32>,
    t_fine: Vec<f32>,
    t_new: Vec<f32>,
    deltas: Vec<f32>,
    weights: Vec<f32>,
    cdf: Vec<f32>,
    d_sigma: Vec<f32>,
    d_rgb: Vec<f32>,
    outputs: Vec<RayOutput>,
}

/// Squared-error sums of one chunk, per pass.
#[derive(Clone, Copy, Debug, Default)]
pub struct ChunkLoss {
    pub coarse_sse: f64,
    pub fine_sse: f64,
}

fn prepare(ws: &mut ChunkWorkspace, rays: &Rays) {
    let r = rays.len();
    ws.unit_dirs.clear();
    for k in 0..r {
        let d = rays.view_dir(k);
        ws.unit_dirs.extend_from_slice(&scale(d, 1.0 / length(d)));
    }
    ws.outputs.resize(r, RayOutput::default());
}

fn coarse_samples(ws: &mut ChunkWorkspace, rays: &Rays, n: usize, mut rngs: Option<&mut [Rng]>) {
    ws.t_coarse.resize(rays.len() * n, 0.0);
    for (k, t) in ws.t_coarse.chunks_exact_mut(n).enumerate() {
        stratified(
            rays.near,
            rays.far,
            rngs.as_deref_mut().map(|g| &mut g[k]),
            t,
        );
    }
}

/// Draws the importance samples from the coarse weights (in `ws.weights`) and merges them with
/// the coarse samples into `ws.t_fine`.
fn fine_samples(
    ws: &mut ChunkWorkspace,
    r: usize,
    n_c: usize,
    n_f: usize,
    mut rngs: Option<&mut [Rng]>,
) {
    ws.t_fine.resize(r * (n_c + n_f), 0.0);
    ws.t_new.resize(n_f, 0.0);
    for k in 0..r {
        let tc = &ws.t_coarse[k * n_c..][..n_c];
        sample_pdf(
            tc,
            &ws.weights[k * n_c..][..n_c],
            rngs.as_deref_mut().map(|g| &mut g[k]),
            &mut ws.t_new,
            &mut ws.cdf,
        );
        ws.t_new.sort_unstable_by(f32::total_cmp);
        merge_sorted(
            tc,
            &ws.t_new,
            &mut ws.t_fine[k * (n_c + n_f)..][..n_c + n_f],
        );
    }
}

/// Evaluates `net` at depths `t` (`r x spr`) and composites each ray into `ws.outputs`,
/// leaving the weights in `ws.weights` and activations in `ws.net`.
fn pass_forward(
    net: &VanillaNet,
    params: &[f32],
    rays: &Rays,
    t: &[f32],
    spr: usize,
    ws: &mut ChunkWorkspace,
) {
    let r = rays.len();
    ws.positions.resize(r * spr * 3, 0.0);
    for k in 0..r {
        let (o, d) = (&rays.origins[k * 3..][..3], rays.dir(k));
        for (s, p) in ws.positions[k * spr * 3..][..spr * 3]
            .chunks_exact_mut(3)
            .enumerate()
        {
            let tt = t[k * spr + s];
            p.copy_from_slice(&[o[0] + tt * d[0], o[1] + tt * d[1], o[2] + tt * d[2]]);
        }
    }
    net.forward(params, &ws.positions, &ws.unit_dirs, spr, &mut ws.net);
    ws.weights.resize(r * spr, 0.0);
    ws.deltas.resize(r * spr, 0.0);
    for k in 0..r {
        let deltas = &mut ws.deltas[k * spr..][..spr];
        depth_deltas(&t[k * spr..][..spr], length(rays.dir(k)), deltas);
        ws.outputs[k] = composite(
            &t[k * spr..][..spr],
            deltas,
            &ws.net.sigma[k * spr..][..spr],
            &ws.net.rgb[k * spr * 3..][..spr * 3],
            rays.bg(k),
            &mut ws.weights[k * spr..][..spr],
        );
    }
}

/// Loss on the last pass, its backward through compositing and the network. Returns the
/// pass's sum of squared errors.
#[allow(clippy::too_many_arguments)]
fn pass_backward(
    net: &VanillaNet,
    params: &[f32],
    rays: &Rays,
    spr: usize,
    targets: &[f32],
    loss_scale: f32,
    ws: &mut ChunkWorkspace,
    grads: &mut [f32],
) -> f64 {
    let r = rays.len();
    ws.d_sigma.resize(r * spr, 0.0);
    ws.d_rgb.resize(r * spr * 3, 0.0);
    let mut sse = 0.0f64;
    for k in 0..r {
        let out = ws.outputs[k];
        let mut d_out = [0.0f32; 3];
        for c in 0..3 {
            let e = out.rgb[c] - targets[k * 3 + c];
            sse += (e * e) as f64;
            d_out[c] = 2.0 * e * loss_scale;
        }
        composite_bwd(
            &ws.deltas[k * spr..][..spr],
            &ws.net.sigma[k * spr..][..spr],
            &ws.net.rgb[k * spr * 3..][..spr * 3],
            rays.bg(k),
            out.rgb,
            d_out,
            &mut ws.d_sigma[k * spr..][..spr],
            &mut ws.d_rgb[k * spr * 3..][..spr * 3],
        );
    }
    net.backward(params, &mut ws.net, &ws.d_sigma, &ws.d_rgb, grads);
    sse
}

/// What a training chunk is compared with: colours (`r x 3`) and the factor that turns the
/// sum of squared errors into this chunk's share of the loss.
#[derive(Clone, Copy, Debug)]
pub struct Targets<'a> {
    pub rgb: &'a [f32],
    pub loss_scale: f32,
}

/// One training chunk: forward and backward of both passes against `targets` (`r x 3`).
/// The loss is `loss_scale * sum of squared errors` per pass (so `1 / (3 * batch)` gives the
/// batch MSE); gradients are accumulated into `grads` (layout of `model.layout`).
pub fn train_chunk(
    model: &VanillaModel,
    params: &[f32],
    rays: &Rays,
    targets: Targets,
    rngs: &mut [Rng],
    ws: &mut ChunkWorkspace,
    grads: &mut [f32],
) -> ChunkLoss {
    let Targets {
        rgb: targets,
        loss_scale,
    } = targets;
    let r = rays.len();
    let (n_c, n_f) = (model.config.n_coarse, model.config.n_fine);
    let (p_coarse, p_fine) = model.split(params);
    let (g_coarse, g_fine) = model.split_mut(grads);
    prepare(ws, rays);
    coarse_samples(ws, rays, n_c, Some(rngs));
    let t = std::mem::take(&mut ws.t_coarse);
    pass_forward(&model.coarse, p_coarse, rays, &t, n_c, ws);
    let coarse_sse = pass_backward(
        &model.coarse,
        p_coarse,
        rays,
        n_c,
        targets,
        loss_scale,
        ws,
        g_coarse,
    );
    ws.t_coarse = t;
    let mut fine_sse = 0.0;
    if let Some(fine) = &model.fine {
        fine_samples(ws, r, n_c, n_f, Some(rngs));
        let t = std::mem::take(&mut ws.t_fine);
        pass_forward(fine, p_fine, rays, &t, n_c + n_f, ws);
        fine_sse = pass_backward(
            fine,
            p_fine,
            rays,
            n_c + n_f,
            targets,
            loss_scale,
            ws,
            g_fine,
        );
        ws.t_fine = t;
    }
    ChunkLoss {
        coarse_sse,
        fine_sse,
    }
}

/// Renders a chunk for evaluation: bin-midpoint coarse samples, evenly spaced importance
/// samples, the fine network's result (the coarse one without a fine network).
pub fn render_chunk(
    model: &VanillaModel,
    params: &[f32],
    rays: &Rays,
    ws: &mut ChunkWorkspace,
    out: &mut [RayOutput],
) {
    let r = rays.len();
    let (n_c, n_f) = (model.config.n_coarse, model.config.n_fine);
    let (p_coarse, p_fine) = model.split(params);
    prepare(ws, rays);
    coarse_samples(ws, rays, n_c, None);
    let t = std::mem::take(&mut ws.t_coarse);
    pass_forward(&model.coarse, p_coarse, rays, &t, n_c, ws);
    ws.t_coarse = t;
    if let Some(fine) = &model.fine {
        fine_samples(ws, r, n_c, n_f, None);
        let t = std::mem::take(&mut ws.t_fine);
        pass_forward(fine, p_fine, rays, &t, n_c + n_f, ws);
        ws.t_fine = t;
    }
    out[..r].copy_from_slice(&ws.outputs[..r]);
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tiny_model() -> VanillaModel {
        let (mut config, _) = crate::presets::build("demo").expect("preset");
        config.net.width = 16;
        config.net.view_width = 8;
        config.n_coarse = 8;
        config.n_fine = 8;
        VanillaModel::new(config)
    }

    fn rays(n: usize) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
        let mut rng = Rng::new(9);
        let origins = (0..n).flat_map(|_| [0.0, -4.0, 0.5]).collect();
        let dirs = (0..n)
            .flat_map(|_| [rng.range(-0.3, 0.3), 1.0, rng.range(-0.3, 0.3)])
            .collect();
        let bgs = (0..n)
            .flat_map(|_| [rng.uniform(), rng.uniform(), rng.uniform()])
            .collect();
        (origins, dirs, bgs)
    }

    /// Chunking is an implementation detail: one chunk of 8 rays and two of 4 give the same
    /// loss and gradients, in training and in rendering.
    #[test]
    fn results_do_not_depend_on_chunking() {
        let model = tiny_model();
        let params = model.init_params(3);
        let (o, d, b) = rays(8);
        let targets: Vec<f32> = (0..24).map(|i| (i % 5) as f32 * 0.2).collect();
        let rngs: Vec<Rng> = (0..8).map(|r| Rng::for_stream(1, 2, r)).collect();
        let run = |ranges: &[std::ops::Range<usize>]| {
            let mut grads = vec![0.0; params.len()];
            let mut ws = ChunkWorkspace::default();
            let mut sse = 0.0;
            let mut rendered = vec![RayOutput::default(); 8];
            for r in ranges {
                let sub = |v: &[f32]| v[r.start * 3..r.end * 3].to_vec();
                let (so, sd, sb) = (sub(&o), sub(&d), sub(&b));
                let rays = Rays {
                    origins: &so,
                    dirs: &sd,
                    view_dirs: None,
                    backgrounds: &sb,
                    near: 2.0,
                    far: 6.0,
                };
                let mut g = rngs[r.clone()].to_vec();
                let t = Targets {
                    rgb: &targets[r.start * 3..r.end * 3],
                    loss_scale: 1.0 / 24.0,
                };
                let l = train_chunk(&model, &params, &rays, t, &mut g, &mut ws, &mut grads);
                sse += l.coarse_sse + l.fine_sse;
                render_chunk(&model, &params, &rays, &mut ws, &mut rendered[r.clone()]);
            }
            (sse, grads, rendered)
        };
        let (sse_a, grads_a, out_a) = run(std::slice::from_ref(&(0..8)));
        let (sse_b, grads_b, out_b) = run(&[0..4, 4..8]);
        assert!(
            (sse_a - sse_b).abs() < 1e-6 * sse_a.max(1.0),
            "{sse_a} vs {sse_b}"
        );
        let norm: f32 = grads_a.iter().map(|g| g * g).sum::<f32>().sqrt();
        let diff: f32 = grads_a
            .iter()
            .zip(&grads_b)
            .map(|(x, y)| (x - y) * (x - y))
            .sum::<f32>()
            .sqrt();
        assert!(
            norm > 0.0 && diff <= 1e-5 * norm,
            "gradient differs by {diff} (norm {norm})"
        );
        for (x, y) in out_a.iter().zip(&out_b) {
            for c in 0..3 {
                assert!((x.rgb[c] - y.rgb[c]).abs() < 1e-6);
            }
        }
    }
}
