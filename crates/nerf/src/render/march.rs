//! Occupancy-grid ray marching (Instant-NGP's sampler): rays step through the scene box
//! with a fixed step (growing steps in contracted space), keeping samples only in occupied
//! cells, and the samples of many rays are packed into one [`PackedSamples`] batch for the
//! field. Not differentiable: sample positions are inputs of the field.
//!
//! Training packs whole rays ([`Marcher::pack_ray`]); the model differentiates through
//! compositing. Rendering ([`render_marched`], any [`Field`]) marches in rounds: every live
//! ray takes a few more steps, the round's samples are evaluated together, and rays stop
//! once their transmittance falls below [`MIN_TRANSMITTANCE`] (early termination), so
//! samples behind opaque surfaces are never evaluated; and only samples that weigh at least
//! [`MIN_WEIGHT`] in their pixel go through the colour network.
//!
//! Depths are reported along the camera's (unnormalised) ray direction, like the paper's
//! renderer, although marching itself works in metric units along unit directions.

use crate::math::{length, scale};
use crate::render::contraction;
use crate::render::occupancy::{ray_box, OccupancyGrid};
use crate::render::volume::{Accumulator, RayOutput};
use crate::stage::{Field, PackedSamples, RayBatch};

/// Rendering stops a ray once less than this much light gets through.
pub const MIN_TRANSMITTANCE: f32 = 1e-4;

/// Rendering colours only samples whose weight in their pixel is at least this: the field
/// evaluates every sample's density, but its colour network only where the colour shows.
pub const MIN_WEIGHT: f32 = 1e-4;

/// A ray's samples per rendering round at most. Most rays stop within a few samples of
/// the surface they meet, and a round's samples past that are wasted.
const ROUND_STEPS: usize = 4;

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

    /// The field-space footprint of ray `r`'s sample at metric depth `t` (world point
    /// `p`): the ray's radius there, shrunk as contraction shrinks space.
    #[inline]
    pub fn footprint(&self, rays: &RayBatch, r: usize, t: f32, p: [f32; 3]) -> f32 {
        let radius = rays.radius_at(r, t);
        match self.contract {
            None => radius,
            Some(half) => radius * contraction::footprint_scale(p, half),
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

impl Marcher {
    /// Marches ray `r` of `rays` from a random offset `jitter` in [0, 1) of the first step
    /// and appends its samples to `out` as one packed ray (positions in field space, unit
    /// view direction per sample). Returns the samples it added.
    pub fn pack_ray(
        &self,
        grid: &OccupancyGrid,
        rays: &RayBatch,
        r: usize,
        jitter: f32,
        out: &mut PackedSamples,
    ) -> usize {
        let (origin, dir) = (rays.origins[r], rays.dirs[r]);
        let norm = length(dir);
        let d = scale(dir, 1.0 / norm);
        let before = out.t.len();
        if let Some((t0, t1)) = self.span(grid, origin, d, norm) {
            let t = t0 + jitter * self.dt;
            self.march(
                grid,
                origin,
                d,
                t..t1,
                self.max_samples,
                &mut out.t,
                &mut out.dt,
            );
        }
        let view = rays.view_dirs[r];
        let view = scale(view, 1.0 / length(view));
        let added = out.t.len() - before;
        out.appearance
            .extend(std::iter::repeat_n(rays.appearance_of(r), added));
        if let Some(&time) = rays.times.get(r) {
            out.times.extend(std::iter::repeat_n(time, added));
        }
        let footprints = !rays.radii.is_empty();
        for &tt in &out.t[before..] {
            let p = [
                origin[0] + tt * d[0],
                origin[1] + tt * d[1],
                origin[2] + tt * d[2],
            ];
            out.positions.push(self.field_point(p));
            out.dirs.push(view);
            if footprints {
                out.footprints.push(self.footprint(rays, r, tt, p));
            }
        }
        out.end_ray();
        out.t.len() - before
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

/// Reused buffers of one rendering thread, with the field's context `C`.
#[derive(Default, Debug)]
pub struct MarchWorkspace<C> {
    pub field: C,
    round: PackedSamples,
    /// Per ray: state and how many samples it has taken; which rays still march.
    unit_rays: Vec<UnitRay>,
    pub taken: Vec<usize>,
    acc: Vec<Accumulator>,
    next_t: Vec<f32>,
    end_t: Vec<f32>,
    live: Vec<usize>,
    /// The rays of the current round, in packing order.
    round_rays: Vec<usize>,
}

/// Renders `rays` through `field` with early termination; a round evaluates at most about
/// `samples_per_round` samples, and colours only those whose weight is at least
/// `min_weight` ([`MIN_WEIGHT`]; 0 colours every sample).
#[allow(clippy::too_many_arguments)]
pub fn render_marched<F: Field>(
    field: &F,
    params: &[f32],
    marcher: &Marcher,
    grid: &OccupancyGrid,
    samples_per_round: usize,
    min_weight: f32,
    rays: &RayBatch,
    ws: &mut MarchWorkspace<F::Context>,
    out: &mut [RayOutput],
) {
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
        let (o, dir) = (rays.origins[k], rays.dirs[k]);
        let norm = length(dir);
        let d = scale(dir, 1.0 / norm);
        let view = rays.view_dirs[k];
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
    let footprints = !rays.radii.is_empty();
    while !ws.live.is_empty() {
        let per_ray = (samples_per_round / ws.live.len()).clamp(1, ROUND_STEPS);
        ws.round.clear();
        ws.round_rays.clear();
        let mut still = Vec::with_capacity(ws.live.len());
        for &k in &ws.live {
            let UnitRay {
                origin: o,
                dir: d,
                view_dir,
                ..
            } = ws.unit_rays[k];
            let start = ws.round.t.len();
            let budget = per_ray.min(marcher.max_samples - ws.taken[k]);
            ws.next_t[k] = marcher.march(
                grid,
                o,
                d,
                ws.next_t[k]..ws.end_t[k],
                budget,
                &mut ws.round.t,
                &mut ws.round.dt,
            );
            ws.taken[k] += ws.round.t.len() - start;
            if ws.round.t.len() > start {
                let added = ws.round.t.len() - start;
                ws.round
                    .appearance
                    .extend(std::iter::repeat_n(rays.appearance_of(k), added));
                if let Some(&time) = rays.times.get(k) {
                    ws.round.times.extend(std::iter::repeat_n(time, added));
                }
                for &tt in &ws.round.t[start..] {
                    let p = [o[0] + tt * d[0], o[1] + tt * d[1], o[2] + tt * d[2]];
                    ws.round.positions.push(marcher.field_point(p));
                    ws.round.dirs.push(view_dir);
                    if footprints {
                        ws.round.footprints.push(marcher.footprint(rays, k, tt, p));
                    }
                }
                ws.round.end_ray();
                ws.round_rays.push(k);
            }
        }
        if ws.round.is_empty() {
            break;
        }
        let (round, round_rays, acc) = (&ws.round, &ws.round_rays, &ws.acc);
        let mut pick = |sigma: &[f32], picked: &mut Vec<u32>| {
            for (i, &k) in round_rays.iter().enumerate() {
                let mut trans = acc[k].transmittance();
                for s in round.ray(i) {
                    let alpha = 1.0 - (-sigma[s] * round.dt[s]).exp();
                    if trans * alpha >= min_weight {
                        picked.push(s as u32);
                    }
                    trans *= 1.0 - alpha;
                }
            }
        };
        let f = field.infer_picked(params, round.field_input(), &mut ws.field, &mut pick);
        for (i, &k) in ws.round_rays.iter().enumerate() {
            let norm = ws.unit_rays[k].norm;
            let acc = &mut ws.acc[k];
            for s in ws.round.ray(i) {
                acc.add(
                    ws.round.t[s] / norm,
                    ws.round.dt[s],
                    f.sigma[s],
                    &f.rgb[s * 3..][..3],
                );
            }
            let done = acc.transmittance() < MIN_TRANSMITTANCE
                || ws.next_t[k] >= ws.end_t[k]
                || ws.taken[k] >= marcher.max_samples;
            if !done {
                still.push(k);
            }
        }
        ws.live = still;
    }
    for k in 0..r {
        out[k] = ws.acc[k].finish(rays.backgrounds[k]);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::Ray;

    /// A marched sample's footprint is its ray's cone radius times its
    /// distance (world rays), the radius itself (NDC cylinders), shrunk by contraction.
    #[test]
    fn samples_carry_their_pixel_footprints() {
        let grid = OccupancyGrid::new(16, 1.5);
        let mut rays = RayBatch::new(2.0, 6.0);
        let ray = Ray {
            origin: [0.0, -4.0, 0.0],
            dir: [0.0, 2.0, 0.0],
        };
        rays.push_with_radius(ray, [0.0, 1.0, 0.0], [1.0; 3], 0, 0.01);
        let marcher = Marcher {
            dt: 0.1,
            max_samples: 1000,
            near: 2.0,
            far: 6.0,
            contract: None,
        };
        let mut out = PackedSamples::default();
        out.clear();
        let n = marcher.pack_ray(&grid, &rays, 0, 0.5, &mut out);
        assert!(n > 10);
        assert_eq!(out.footprints.len(), n);
        for (f, t) in out.footprints.iter().zip(&out.t) {
            assert!((f - 0.01 * t).abs() < 1e-6, "{f} at {t}");
        }
        rays.cylinders = true;
        out.clear();
        marcher.pack_ray(&grid, &rays, 0, 0.5, &mut out);
        assert!(out.footprints.iter().all(|&f| f == 0.01));
        // Contracted: samples beyond the inner cube stand for more space, so their
        // footprint in the field shrinks.
        rays.cylinders = false;
        let contracted = Marcher {
            contract: Some(0.5),
            far: 40.0,
            ..marcher
        };
        out.clear();
        contracted.pack_ray(&grid, &rays, 0, 0.5, &mut out);
        let (first, last) = (out.footprints[0], out.footprints[out.len() - 1]);
        let t_first = out.t[0];
        assert!(
            (first
                - 0.01 * t_first * contraction::footprint_scale([0.0, -4.0 + t_first, 0.0], 0.5))
            .abs()
                < 1e-6
        );
        assert!(
            last < 0.01 * out.t[out.len() - 1],
            "contraction shrinks footprints"
        );
        // A batch without radii marches point samples.
        let mut points = RayBatch::new(2.0, 6.0);
        points.push(ray, [0.0, 1.0, 0.0], [1.0; 3], 0);
        out.clear();
        marcher.pack_ray(&grid, &points, 0, 0.5, &mut out);
        assert!(out.footprints.is_empty() && !out.t.is_empty());
    }
}
