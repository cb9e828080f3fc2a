//! Patches of rays from poses between the training cameras, where no photo was taken:
//! what RegNeRF's depth smoothness (`render::depth_smoothness`) renders. They have no
//! colours to match, only depths to keep smooth.

use serde::{Deserialize, Serialize};

use crate::camera::path::pose_between;
use crate::camera::ray_space::RaySpace;
use crate::camera::Camera;
use crate::data::pixels::TrainingRays;
use crate::data::Dataset;
use crate::render::depth_smoothness::PATCH_SIDE;
use crate::rng::Rng;
use crate::stage::{Appearance, RayBatch};

/// RegNeRF's depth smoothness in a run (`--depth-smoothness W`).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct DepthSmoothness {
    /// The loss's weight against the mean squared error, per patch (its mean over a
    /// step's patches).
    pub weight: f32,
    /// Patches per training step.
    pub patches: usize,
    /// Pixels between a patch's neighbouring rays ([`stride_for`] the photos' width).
    pub stride: usize,
}

/// Patches per step by default: 64 rays. Four keep nearly all of sixteen's gain for a
/// fraction of their time (docs/benchmarks.md, "Fewer patches a step").
pub const PATCHES: usize = 4;

/// Random streams of patch rays start here, far from the photo rays' (`0, 1, ...`).
const PATCH_STREAMS: u64 = 1 << 62;

/// Patch `k`'s random stream `i`: 0 draws its camera and pixels, `1 + r` its ray `r`'s
/// samples; no two patches share one.
fn patch_stream(k: u64, i: usize) -> u64 {
    debug_assert!(i <= PATCH_SIDE * PATCH_SIDE);
    PATCH_STREAMS + (k << 8) + i as u64
}

/// The pixel step between a patch's rays for photos `width` pixels wide: a patch spans
/// about 1/40 of the photo (RegNeRF's 8-pixel patches on LLFF's 378-pixel-high photos
/// span 1/47), so it sees a piece of surface, not one pixel's noise, at any resolution.
pub fn stride_for(width: usize) -> usize {
    (width / (40 * (PATCH_SIDE - 1))).max(1)
}

/// Which patch: step `step`'s `k`th of a run seeded `seed`.
#[derive(Clone, Copy, Debug)]
pub struct PatchDraw {
    pub seed: u64,
    pub step: u64,
    pub k: u64,
}

/// The camera of a patch: a training camera moved a random way towards one of its two
/// nearest neighbours (the photos training rays are drawn from), and its random stream.
fn camera_between(data: &Dataset, draw: PatchDraw) -> (usize, Camera, Rng) {
    let mut rng = Rng::for_stream(draw.seed, draw.step, patch_stream(draw.k, 0));
    let drawn = data
        .drawn_views
        .clone()
        .unwrap_or_else(|| (0..data.views.len()).collect());
    let a = drawn[rng.below(drawn.len())];
    let centre = data.views[a].camera.origin();
    let mut others: Vec<(f32, usize)> = drawn
        .iter()
        .filter(|&&v| v != a)
        .map(|&v| {
            let d = crate::math::sub(data.views[v].camera.origin(), centre);
            (crate::math::dot(d, d), v)
        })
        .collect();
    others.sort_by(|x, y| x.0.total_cmp(&y.0));
    let b = match others.len() {
        0 => a,
        n => others[rng.below(n.min(2))].1,
    };
    let mut camera = data.views[a].camera.clone();
    let orbit = matches!(data.space, RaySpace::World);
    camera.c2w = pose_between(&camera.c2w, &data.views[b].camera.c2w, rng.uniform(), orbit);
    (a, camera, rng)
}

/// Replaces `out` with the patch's `PATCH_SIDE x PATCH_SIDE` rays, row by row, `stride`
/// pixels apart (targets black: nothing compares them with a photo).
pub fn draw_patch(data: &Dataset, draw: PatchDraw, stride: usize, out: &mut TrainingRays) {
    let (view, camera, mut rng) = camera_between(data, draw);
    let span = (PATCH_SIDE - 1) * stride + 1;
    let x0 = rng.below(camera.width.saturating_sub(span) + 1);
    let y0 = rng.below(camera.height.saturating_sub(span) + 1);
    out.rays.clear();
    out.rays.near = data.near;
    out.rays.far = data.far;
    out.rays.cylinders = data.space.cylinders();
    out.rays.appearance = Appearance::Mean;
    out.targets.clear();
    out.rngs.clear();
    for i in 0..PATCH_SIDE * PATCH_SIDE {
        let (x, y) = (
            x0 + (i % PATCH_SIDE) * stride,
            y0 + (i / PATCH_SIDE) * stride,
        );
        let (cx, cy) = (x as f32 + 0.5, y as f32 + 0.5);
        let world = camera.ray_at(cx, cy);
        let (origin, dir) = data.space.warp(world.origin, world.dir);
        let radius = data
            .space
            .footprint_radius(camera.cone_radius(cx, cy), world.dir);
        let pixel = ((view as u64) << 32) | (y * camera.width + x) as u64;
        out.rays.push_with_radius(
            crate::camera::Ray { origin, dir },
            world.dir,
            [0.0; 3],
            pixel,
            radius,
        );
        if let Some(time) = data.views[view].time {
            out.rays.times.push(time);
        }
        out.targets.push([0.0; 3]);
        out.rngs.push(Rng::for_stream(
            draw.seed,
            draw.step,
            patch_stream(draw.k, i + 1),
        ));
    }
}

/// Step `step`'s first `patches` patches of a run seeded `seed`, `stride` pixels between
/// rays, one after another in one batch: the patches the CPU engine renders one at a time
/// (the GPU engine renders them together).
pub fn draw_patches(
    data: &Dataset,
    (seed, step): (u64, u64),
    patches: usize,
    stride: usize,
) -> TrainingRays {
    let mut all = TrainingRays::default();
    let mut one = TrainingRays::default();
    for k in 0..patches as u64 {
        draw_patch(data, PatchDraw { seed, step, k }, stride, &mut one);
        if k == 0 {
            all.rays = RayBatch::new(one.rays.near, one.rays.far);
            all.rays.cylinders = one.rays.cylinders;
        }
        all.rays.extend(&one.rays);
        all.targets.extend_from_slice(&one.targets);
        all.rngs.extend_from_slice(&one.rngs);
    }
    all
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::data::synth::{self, SynthOptions};
    use crate::data::Split;

    #[test]
    fn patches_look_from_between_the_cameras_at_what_they_see() {
        let opts = SynthOptions {
            size: 64,
            supersample: 1,
            ..Default::default()
        };
        let data = synth::dataset(&opts, Split::Train, 8);
        let radius = crate::math::length(data.views[0].camera.origin());
        let mut again = TrainingRays::default();
        for k in 0..20 {
            let draw = PatchDraw {
                seed: 3,
                step: 7,
                k,
            };
            let mut rays = TrainingRays::default();
            draw_patch(&data, draw, 2, &mut rays);
            assert_eq!(rays.len(), PATCH_SIDE * PATCH_SIDE);
            // Drawn again, the same rays (a resumed run draws what it would have).
            draw_patch(&data, draw, 2, &mut again);
            assert_eq!(rays.rays.dirs, again.rays.dirs);
            let o = rays.rays.origins[0];
            let (_, camera, _) = camera_between(&data, draw);
            // On the cameras' sphere, not a photo's pose, looking at the object.
            assert!((crate::math::length(o) - radius).abs() < 1e-3 * radius);
            let ahead =
                crate::math::scale([camera.c2w[0][2], camera.c2w[1][2], camera.c2w[2][2]], -1.0);
            let to_centre = crate::math::normalize_or_zero(crate::math::scale(o, -1.0));
            assert!(crate::math::dot(ahead, to_centre) > 0.9);
            // Neighbouring rays two pixels apart.
            let (px, py) = (rays.rays.pixels[0] as u32 as usize, rays.rays.pixels[1]);
            assert_eq!(py as u32 as usize, px + 2);
            assert_eq!(rays.rays.appearance, Appearance::Mean);
        }
        // Every patch's camera and rays draw from streams of their own.
        let streams: std::collections::HashSet<u64> = (0..64)
            .flat_map(|k| (0..=PATCH_SIDE * PATCH_SIDE).map(move |i| patch_stream(k, i)))
            .collect();
        assert_eq!(streams.len(), 64 * (PATCH_SIDE * PATCH_SIDE + 1));
        assert_eq!(stride_for(400), 3);
        assert_eq!(stride_for(64), 1);
    }
}
