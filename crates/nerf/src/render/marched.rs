//! The fast field's renderer: rays march through the occupancy grid with a fixed step, the
//! samples of many rays are packed into one batch for the field, and each ray is
//! composited by the shared quadrature of [`volume`](crate::render::volume).
//!
//! Training packs whole rays ([`MarchBatch`]) and differentiates through compositing.
//! Rendering marches in rounds: every live ray takes a few more steps, the batch is
//! evaluated, and rays stop once their transmittance falls below [`MIN_TRANSMITTANCE`]
//! (early termination), so samples behind opaque surfaces are never evaluated.
//!
//! Depths are reported along the camera's (unnormalised) ray direction, like the paper's
//! renderer, although marching itself works in metric units along unit directions.

use crate::field::{FastField, FastWorkspace};
use crate::math::{length, scale};
use crate::model::FastModel;
use crate::nn::GradBuffer;
use crate::render::contraction;
use crate::render::occupancy::{ray_box, OccupancyGrid};
use crate::render::pipeline::Rays;
use crate::render::volume::{composite, composite_bwd, Accumulator, RayOutput};

/// Rendering stops a ray once less than this much light gets through.
pub const MIN_TRANSMITTANCE: f32 = 1e-4;

/// Where and how finely rays are marched.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Marcher {
    /// Step length (metric; in contracted space when `contract` is set).
    pub dt: f32,
    /// Samples per ray at most.
    pub max_samples: usize,
    pub near: f32,
    pub far: f32,
    /// Contract space outside the cube of this half-extent (see `contraction`).
    pub contract: Option<f32>,
}

impl Marcher {
    /// The metric span to march of a ray with unit direction `d` whose camera direction
    /// has length `norm` (near and far are along the camera direction): inside the box, or
    /// all of `near..far` when space is contracted.
    pub fn span(
        &self,
        grid: &OccupancyGrid,
        o: [f32; 3],
        d: [f32; 3],
        norm: f32,
    ) -> Option<(f32, f32)> {
        let (near, far) = (self.near * norm, self.far * norm);
        match self.contract {
            None => ray_box(o, d, grid.bound, near, far),
            Some(_) => (far > near).then_some((near, far)),
        }
    }

    /// Marches over `span`, appending sample depths in occupied cells and their step
    /// lengths, at most `max` of them; returns the depth to continue from.
    #[allow(clippy::too_many_arguments)]
    pub fn march(
        &self,
        grid: &OccupancyGrid,
        o: [f32; 3],
        d: [f32; 3],
        span: std::ops::Range<f32>,
        max: usize,
        t: &mut Vec<f32>,
        dt: &mut Vec<f32>,
    ) -> f32 {
        match self.contract {
            None => {
                let next = grid.march(o, d, span, self.dt, max, t);
                dt.resize(t.len(), self.dt);
                next
            }
            Some(r) => march_contracted(grid, o, d, span, self.dt, r, max, t, dt),
        }
    }

    /// Where the field sees a world point.
    #[inline]
    pub fn field_point(&self, p: [f32; 3]) -> [f32; 3] {
        match self.contract {
            None => p,
            Some(r) => contraction::contract(p, r),
        }
    }
}

/// Marching through contracted space: steps grow with distance so each covers about `dt`
/// of the contracted grid; no cell skipping (the ray is curved in grid space).
#[allow(clippy::too_many_arguments)]
fn march_contracted(
    grid: &OccupancyGrid,
    o: [f32; 3],
    d: [f32; 3],
    span: std::ops::Range<f32>,
    dt: f32,
    r: f32,
    max: usize,
    t_out: &mut Vec<f32>,
    dt_out: &mut Vec<f32>,
) -> f32 {
    let (mut t, end) = (span.start, span.end);
    let mut added = 0;
    while t < end && added < max {
        let p = [o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2]];
        if contraction::beyond(p, r) {
            return f32::INFINITY;
        }
        let step = contraction::world_step(p, r, dt);
        if grid.is_occupied(contraction::contract(p, r)) {
            t_out.push(t);
            dt_out.push(step);
            added += 1;
        }
        t += step;
    }
    t
}

/// Rays and their marched samples, packed for one evaluation of the field.
#[derive(Default, Debug)]
pub struct MarchBatch {
    /// Per ray: origin, unit marching and viewing directions, background, target colour.
    origins: Vec<[f32; 3]>,
    dirs: Vec<[f32; 3]>,
    view_dirs: Vec<[f32; 3]>,
    backgrounds: Vec<[f32; 3]>,
    targets: Vec<[f32; 3]>,
    /// Samples of ray `k` are `starts[k]..starts[k + 1]`; each has a depth and a step
    /// length.
    starts: Vec<usize>,
    t: Vec<f32>,
    dt: Vec<f32>,
}

impl MarchBatch {
    pub fn clear(&mut self) {
        self.origins.clear();
        self.dirs.clear();
        self.view_dirs.clear();
        self.backgrounds.clear();
        self.targets.clear();
        self.t.clear();
        self.dt.clear();
        self.starts.clear();
    }

    pub fn rays(&self) -> usize {
        self.origins.len()
    }
    pub fn samples(&self) -> usize {
        self.t.len()
    }

    /// Marches a camera ray (`dir` unnormalised) from a random offset `jitter` in [0, 1) of
    /// the first step and packs it with its target colour; colour is conditioned on
    /// `view_dir` (see `Rays::view_dirs`). Returns the samples it added.
    #[allow(clippy::too_many_arguments)]
    pub fn push(
        &mut self,
        grid: &OccupancyGrid,
        marcher: &Marcher,
        origin: [f32; 3],
        dir: [f32; 3],
        view_dir: [f32; 3],
        background: [f32; 3],
        target: [f32; 3],
        jitter: f32,
    ) -> usize {
        if self.starts.is_empty() {
            self.starts.push(0);
        }
        let norm = length(dir);
        let d = scale(dir, 1.0 / norm);
        let before = self.t.len();
        if let Some((t0, t1)) = marcher.span(grid, origin, d, norm) {
            let t = t0 + jitter * marcher.dt;
            marcher.march(
                grid,
                origin,
                d,
                t..t1,
                marcher.max_samples,
                &mut self.t,
                &mut self.dt,
            );
        }
        self.origins.push(origin);
        self.dirs.push(d);
        self.view_dirs.push(scale(view_dir, 1.0 / length(view_dir)));
        self.backgrounds.push(background);
        self.targets.push(target);
        self.starts.push(self.t.len());
        self.t.len() - before
    }
}

/// A camera ray with its direction normalised; `norm` converts metric depth back to depth
/// along the camera's direction.
#[derive(Clone, Copy, Debug)]
struct UnitRay {
    origin: [f32; 3],
    dir: [f32; 3],
    view_dir: [f32; 3],
    norm: f32,
}

/// Reused buffers of one thread.
#[derive(Default, Debug)]
pub struct MarchWorkspace {
    pub field: FastWorkspace,
    positions: Vec<f32>,
    dirs: Vec<f32>,
    weights: Vec<f32>,
    d_sigma: Vec<f32>,
    d_rgb: Vec<f32>,
    /// Rendering: per-ray state and which rays are still marching.
    unit_rays: Vec<UnitRay>,
    taken: Vec<usize>,
    acc: Vec<Accumulator>,
    next_t: Vec<f32>,
    end_t: Vec<f32>,
    live: Vec<usize>,
    round_rays: Vec<(usize, usize, usize)>,
    t: Vec<f32>,
    dt: Vec<f32>,
}

/// One ray's part of a packed batch: origin, unit marching direction, unit viewing
/// direction, and its samples' range in `t`.
type PackedRay = ([f32; 3], [f32; 3], [f32; 3], std::ops::Range<usize>);

/// Lays out sample positions and viewing directions of `t` for the field.
fn pack_samples(
    marcher: &Marcher,
    positions: &mut Vec<f32>,
    dirs: &mut Vec<f32>,
    t: &[f32],
    rays: impl Iterator<Item = PackedRay>,
) {
    positions.clear();
    dirs.clear();
    for (o, d, view, range) in rays {
        for &tt in &t[range] {
            let p = [o[0] + tt * d[0], o[1] + tt * d[1], o[2] + tt * d[2]];
            positions.extend_from_slice(&marcher.field_point(p));
            dirs.extend_from_slice(&view);
        }
    }
}

/// Forward and backward of a packed batch against its targets. The loss is the sum of
/// squared errors times `loss_scale`; gradients go into `grads`. Returns the batch's sum of
/// squared errors (unscaled).
pub fn train_batch(
    field: &FastField,
    params: &[f32],
    marcher: &Marcher,
    batch: &MarchBatch,
    loss_scale: f32,
    ws: &mut MarchWorkspace,
    grads: &mut GradBuffer,
) -> f64 {
    let n = batch.samples();
    let rays = batch.rays();
    pack_samples(
        marcher,
        &mut ws.positions,
        &mut ws.dirs,
        &batch.t,
        (0..rays).map(|k| {
            (
                batch.origins[k],
                batch.dirs[k],
                batch.view_dirs[k],
                batch.starts[k]..batch.starts[k + 1],
            )
        }),
    );
    ws.weights.resize(n, 0.0);
    ws.d_sigma.resize(n, 0.0);
    ws.d_rgb.resize(n * 3, 0.0);
    if n > 0 {
        field.forward(params, &ws.positions, &ws.dirs, &mut ws.field);
    }
    let mut sse = 0.0f64;
    for k in 0..rays {
        let r = batch.starts[k]..batch.starts[k + 1];
        let (sigma, rgb) = (
            &ws.field.sigma[r.clone()],
            &ws.field.rgb[r.start * 3..r.end * 3],
        );
        let out = composite(
            &batch.t[r.clone()],
            &batch.dt[r.clone()],
            sigma,
            rgb,
            batch.backgrounds[k],
            &mut ws.weights[r.clone()],
        );
        let mut d_out = [0.0f32; 3];
        for c in 0..3 {
            let e = out.rgb[c] - batch.targets[k][c];
            sse += (e * e) as f64;
            d_out[c] = 2.0 * e * loss_scale;
        }
        composite_bwd(
            &batch.dt[r.clone()],
            sigma,
            rgb,
            batch.backgrounds[k],
            out.rgb,
            d_out,
            &mut ws.d_sigma[r.clone()],
            &mut ws.d_rgb[r.start * 3..r.end * 3],
        );
    }
    if n > 0 {
        field.backward(
            params,
            &mut ws.field,
            &ws.d_sigma[..n],
            &ws.d_rgb[..n * 3],
            grads,
        );
    }
    sse
}

/// Renders a chunk of rays with early termination; a round evaluates at most the model's
/// `batch_samples` samples.
pub fn render_chunk(
    model: &FastModel,
    params: &[f32],
    rays: &Rays,
    ws: &mut MarchWorkspace,
    out: &mut [RayOutput],
) {
    let (field, grid) = (&model.field, &model.grid);
    let marcher = &model.marcher(rays.near, rays.far);
    let samples_per_round = model.config.batch_samples;
    let r = rays.len();
    ws.acc.clear();
    ws.acc.resize(r, Accumulator::default());
    ws.next_t.clear();
    ws.end_t.clear();
    ws.live.clear();
    ws.unit_rays.clear();
    ws.taken.clear();
    ws.taken.resize(r, 0);
    for k in 0..r {
        let o = [
            rays.origins[3 * k],
            rays.origins[3 * k + 1],
            rays.origins[3 * k + 2],
        ];
        let dir = [rays.dirs[3 * k], rays.dirs[3 * k + 1], rays.dirs[3 * k + 2]];
        let norm = length(dir);
        let d = scale(dir, 1.0 / norm);
        let view = rays.view_dir(k);
        ws.unit_rays.push(UnitRay {
            origin: o,
            dir: d,
            view_dir: scale(view, 1.0 / length(view)),
            norm,
        });
        match marcher.span(grid, o, d, norm) {
            Some((t0, t1)) => {
                ws.next_t.push(t0 + 0.5 * marcher.dt);
                ws.end_t.push(t1);
                ws.live.push(k);
            }
            None => {
                ws.next_t.push(0.0);
                ws.end_t.push(0.0);
            }
        }
    }
    while !ws.live.is_empty() {
        let per_ray = (samples_per_round / ws.live.len()).clamp(1, 64);
        ws.t.clear();
        ws.dt.clear();
        ws.round_rays.clear();
        let mut still = Vec::with_capacity(ws.live.len());
        for &k in &ws.live {
            let UnitRay {
                origin: o, dir: d, ..
            } = ws.unit_rays[k];
            let start = ws.t.len();
            let budget = per_ray.min(marcher.max_samples - ws.taken[k]);
            ws.next_t[k] = marcher.march(
                grid,
                o,
                d,
                ws.next_t[k]..ws.end_t[k],
                budget,
                &mut ws.t,
                &mut ws.dt,
            );
            ws.taken[k] += ws.t.len() - start;
            if ws.t.len() > start {
                ws.round_rays.push((k, start, ws.t.len()));
            }
        }
        if ws.t.is_empty() {
            break;
        }
        let t = std::mem::take(&mut ws.t);
        let round = std::mem::take(&mut ws.round_rays);
        pack_samples(
            marcher,
            &mut ws.positions,
            &mut ws.dirs,
            &t,
            round.iter().map(|&(k, s, e)| {
                let u = ws.unit_rays[k];
                (u.origin, u.dir, u.view_dir, s..e)
            }),
        );
        field.forward(params, &ws.positions, &ws.dirs, &mut ws.field);
        for &(k, s, e) in &round {
            let norm = ws.unit_rays[k].norm;
            let acc = &mut ws.acc[k];
            for i in s..e {
                acc.add(
                    t[i] / norm,
                    ws.dt[i],
                    ws.field.sigma[i],
                    &ws.field.rgb[i * 3..][..3],
                );
            }
            let done = acc.transmittance() < MIN_TRANSMITTANCE
                || ws.next_t[k] >= ws.end_t[k]
                || ws.taken[k] >= marcher.max_samples;
            if !done {
                still.push(k);
            }
        }
        ws.t = t;
        ws.round_rays = round;
        ws.live = still;
    }
    for k in 0..r {
        let bg = [
            rays.backgrounds[3 * k],
            rays.backgrounds[3 * k + 1],
            rays.backgrounds[3 * k + 2],
        ];
        out[k] = ws.acc[k].finish(bg);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::encoding::HashGridConfig;
    use crate::field::FastFieldConfig;
    use crate::model::FastModelConfig;

    fn dense_model() -> (FastModel, Vec<f32>) {
        let config = FastModelConfig {
            field: FastFieldConfig {
                grid: HashGridConfig {
                    levels: 4,
                    log2_table_size: 10,
                    base_resolution: 4,
                    max_resolution: 32,
                },
                ..FastFieldConfig::default()
            },
            ..FastModelConfig::default()
        };
        let model = FastModel::new(config);
        let mut params = model.field.init_params(5);
        // Positive, varying table values and a positive log-density weight: an opaque,
        // textured fog filling the box.
        let mut rng = crate::rng::Rng::new(8);
        for v in &mut params[model.field.grid.param_range()] {
            *v = rng.range(0.5, 1.5);
        }
        for t in &model.field.layout.tensors {
            if t.name == "density.0.weight" {
                params[t.range()].iter_mut().for_each(|w| *w = w.abs());
            }
            if t.name == "density.1.weight" {
                for row in params[t.range()].chunks_exact_mut(t.shape[1]) {
                    row[0] = 0.5;
                }
            }
        }
        (model, params)
    }

    /// Renders packed rays, then packs them for training on the renderer's lattice (jitter
    /// 0.5) with the rendered colours as targets and runs the training pass.
    struct RenderThenTrain {
        out: Vec<RayOutput>,
        /// The renderer's workspace, reused by training (which leaves the renderer's per-ray
        /// step counts `taken` as they were).
        ws: MarchWorkspace,
        marcher: Marcher,
        batch: MarchBatch,
        /// Training loss against the rendered colours.
        sse: f64,
    }

    fn render_then_train(
        model: &FastModel,
        params: &[f32],
        (origins, dirs, bgs): (&[f32], &[f32], &[f32]),
        (near, far): (f32, f32),
    ) -> RenderThenTrain {
        let n = origins.len() / 3;
        let rays = Rays {
            origins,
            dirs,
            view_dirs: None,
            backgrounds: bgs,
            near,
            far,
        };
        let mut ws = MarchWorkspace::default();
        let mut out = vec![RayOutput::default(); n];
        render_chunk(model, params, &rays, &mut ws, &mut out);
        let marcher = model.marcher(near, far);
        let mut batch = MarchBatch::default();
        for k in 0..n {
            let v = |b: &[f32]| [b[3 * k], b[3 * k + 1], b[3 * k + 2]];
            batch.push(
                &model.grid,
                &marcher,
                v(origins),
                v(dirs),
                v(dirs),
                v(bgs),
                out[k].rgb,
                0.5,
            );
        }
        let mut grads = GradBuffer::new(model.field.num_params());
        let sse = train_batch(
            &model.field,
            params,
            &marcher,
            &batch,
            1.0,
            &mut ws,
            &mut grads,
        );
        RenderThenTrain {
            out,
            ws,
            marcher,
            batch,
            sse,
        }
    }

    /// Rendering (in rounds, stopping opaque rays) and training (all samples, composited at
    /// once) see the same colour for the same lattice, and rendering stops early.
    #[test]
    fn rendering_agrees_with_training_and_terminates_early() {
        let (model, params) = dense_model();
        let origins: Vec<f32> = (0..6).flat_map(|_| [0.0, -4.0, 0.3]).collect();
        let dirs: Vec<f32> = (0..6)
            .flat_map(|k| [0.05 * k as f32 - 0.1, 1.0, 0.02 * k as f32])
            .collect();
        let bgs: Vec<f32> = (0..6).flat_map(|k| [0.1 * k as f32, 0.5, 1.0]).collect();
        let RenderThenTrain {
            out,
            ws,
            batch,
            sse,
            ..
        } = render_then_train(&model, &params, (&origins, &dirs, &bgs), (2.0, 6.0));
        assert!(out.iter().all(|o| o.opacity > 0.999), "{out:?}");
        // The box is about 590 steps deep; an opaque fog ends each ray within a few rounds.
        assert!(
            ws.taken.iter().all(|&n| n > 0 && n <= 128),
            "{:?}",
            ws.taken
        );
        assert!(batch.samples() > 6 * 500, "training marches whole rays");
        assert!(sse < 1e-9, "render and training disagree: sse {sse}");
    }

    /// With contraction, rays run on past the box with growing steps, and rendering and
    /// training still see the same colour.
    #[test]
    fn contracted_rays_march_beyond_the_box_and_agree() {
        let (mut model, mut params) = dense_model();
        model.config.contract = true;
        // A thin fog (sigma about 1): light reaches the contracted shell.
        for t in &model.field.layout.tensors {
            if t.name == "density.1.weight" {
                for row in params[t.range()].chunks_exact_mut(t.shape[1]) {
                    row[0] = 0.0;
                }
            }
        }
        let origins: Vec<f32> = (0..4).flat_map(|_| [0.0, -1.0, 0.2]).collect();
        let dirs: Vec<f32> = (0..4)
            .flat_map(|k| [0.1 * k as f32 - 0.15, 1.0, 0.05])
            .collect();
        let bgs: Vec<f32> = (0..4).flat_map(|_| [0.2, 0.4, 0.6]).collect();
        let RenderThenTrain {
            out,
            marcher,
            batch,
            sse,
            ..
        } = render_then_train(&model, &params, (&origins, &dirs, &bgs), (0.05, 1e4));
        let r = marcher.contract.expect("contracted");
        // Samples reach far past the inner cube, with steps that grow with distance.
        let far_t = batch.t.iter().copied().fold(0.0f32, f32::max);
        let max_dt = batch.dt.iter().copied().fold(0.0f32, f32::max);
        assert!(far_t > 20.0 * r, "last sample at {far_t}, inner cube {r}");
        assert!(max_dt > 100.0 * marcher.dt, "{max_dt} vs {}", marcher.dt);
        assert!(batch.samples() < 4 * marcher.max_samples);
        assert!(sse < 1e-9, "render and training disagree: sse {sse}");
        assert!(out.iter().all(|o| o.opacity > 0.5), "{out:?}");
    }
}
