//! Training rays: uniformly random pixels of the training views, as a [`RayBatch`] with
//! their target colours.
//!
//! Ray `k` of step `s` is a pure function of `(seed, s, k)` (see [`crate::rng`]): which
//! pixel, its background colour, and the random stream its samples are drawn from. So the
//! rays of a step do not depend on how many threads draw them, a resumed run draws what the
//! uninterrupted one would have, and another engine can draw the very same rays.

use crate::data::{Background, Dataset};
use crate::rng::Rng;
use crate::stage::RayBatch;

/// How a step draws its rays.
#[derive(Clone, Copy, Debug)]
pub struct PixelSampling {
    pub seed: u64,
    pub step: u64,
    /// Rays come from the central `crop` fraction of each image (1: everywhere).
    pub crop: f32,
    pub background: Background,
    /// Which appearance code colours the rays (`PerView` when training: each its own
    /// photo's; `Mean` when fitting cameras other than the training ones to a model).
    pub appearance: crate::stage::Appearance,
}

/// Training rays with what they are compared to, and each ray's random stream (which also
/// draws its samples' positions).
#[derive(Clone, Debug, Default)]
pub struct TrainingRays {
    pub rays: RayBatch,
    /// `n x 3`: the pixel's colour over the ray's background.
    pub targets: Vec<[f32; 3]>,
    pub rngs: Vec<Rng>,
}

impl TrainingRays {
    pub fn len(&self) -> usize {
        self.rays.len()
    }
    pub fn is_empty(&self) -> bool {
        self.rays.is_empty()
    }

    /// Replaces the batch with rays `range` of the step.
    pub fn draw(&mut self, data: &Dataset, how: &PixelSampling, range: std::ops::Range<u64>) {
        self.rays.clear();
        self.rays.near = data.near;
        self.rays.far = data.far;
        self.rays.appearance = how.appearance;
        self.rays.cylinders = data.space.cylinders();
        self.targets.clear();
        self.rngs.clear();
        for k in range {
            self.push(data, how, k);
        }
    }

    /// [`draw`](Self::draw) spread over the rayon threads in blocks: the same rays in the
    /// same order (each is a function of its index alone), for an engine whose host only
    /// draws rays while a device does the rest.
    pub fn draw_parallel(
        &mut self,
        data: &Dataset,
        how: &PixelSampling,
        range: std::ops::Range<u64>,
    ) {
        use rayon::prelude::*;
        const BLOCK: u64 = 256;
        let starts: Vec<u64> = (range.start..range.end).step_by(BLOCK as usize).collect();
        let blocks: Vec<TrainingRays> = starts
            .par_iter()
            .map(|&s| {
                let mut block = TrainingRays::default();
                block.draw(data, how, s..(s + BLOCK).min(range.end));
                block
            })
            .collect();
        self.draw(data, how, 0..0);
        for b in blocks {
            let r = &mut self.rays;
            r.origins.extend_from_slice(&b.rays.origins);
            r.dirs.extend_from_slice(&b.rays.dirs);
            r.view_dirs.extend_from_slice(&b.rays.view_dirs);
            r.backgrounds.extend_from_slice(&b.rays.backgrounds);
            r.pixels.extend_from_slice(&b.rays.pixels);
            r.radii.extend_from_slice(&b.rays.radii);
            r.times.extend_from_slice(&b.rays.times);
            self.targets.extend_from_slice(&b.targets);
            self.rngs.extend(b.rngs);
        }
    }

    /// Appends ray `k` of the step ([`PixelChoice::draw`]), warped into the scene's ray
    /// space.
    pub fn push(&mut self, data: &Dataset, how: &PixelSampling, k: u64) {
        let PixelChoice {
            view: v,
            pixel,
            background,
            rng,
        } = PixelChoice::draw(data, how, k);
        let view = &data.views[v];
        let w = view.image.width;
        let (x, y) = ((pixel % w) as f32 + 0.5, (pixel / w) as f32 + 0.5);
        let world = view.camera.ray_at(x, y);
        let (origin, dir) = data.space.warp(world.origin, world.dir);
        let radius = data
            .space
            .footprint_radius(view.camera.cone_radius(x, y), world.dir);
        self.rays.push_with_radius(
            crate::camera::Ray { origin, dir },
            world.dir,
            background,
            ((v as u64) << 32) | pixel as u64,
            radius,
        );
        if let Some(time) = view.time {
            self.rays.times.push(time);
        }
        self.targets
            .push(view.image.composite_pixel(pixel, background));
        self.rngs.push(rng);
    }
}

/// Which pixel ray `k` of a step sees, and its background: the random part of a training
/// ray (the rest follows from the view's camera and image, on the host in
/// [`TrainingRays::push`] or on a GPU from these indices).
#[derive(Clone, Debug)]
pub struct PixelChoice {
    pub view: usize,
    /// `row * width + column` in the view's image.
    pub pixel: usize,
    pub background: [f32; 3],
    /// The ray's random stream after these draws (its samples' positions come next).
    pub rng: Rng,
}

impl PixelChoice {
    /// Ray `k` of the step: a uniformly random training pixel of the views rays are drawn
    /// from (`Dataset::drawn_views`), inside the central `crop`
    /// fraction while warming up; among the pixels its mask keeps, if it has one).
    pub fn draw(data: &Dataset, how: &PixelSampling, k: u64) -> PixelChoice {
        let mut rng = Rng::for_stream(how.seed, how.step, k);
        let v = match &data.drawn_views {
            Some(drawn) => drawn[rng.below(drawn.len())],
            None => rng.below(data.views.len()),
        };
        let view = &data.views[v];
        let (w, h) = (view.image.width, view.image.height);
        let (cw, ch) = (
            ((w as f32 * how.crop) as usize).max(1),
            ((h as f32 * how.crop) as usize).max(1),
        );
        let (x0, y0) = ((w - cw) / 2, (h - ch) / 2);
        let pixel = match &view.kept_pixels {
            Some(kept) => kept[rng.below(kept.len())] as usize,
            None => {
                let i = x0 + rng.below(cw);
                let j = y0 + rng.below(ch);
                j * w + i
            }
        };
        let background = match how.background {
            Background::White => [1.0; 3],
            Background::Black => [0.0; 3],
            Background::Random => [rng.uniform(), rng.uniform(), rng.uniform()],
        };
        PixelChoice {
            view: v,
            pixel,
            background,
            rng,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::data::synth::{self, SynthOptions};
    use crate::data::Split;

    /// Drawn in parallel blocks, a step's rays are the sequential draw's, ray for ray.
    #[test]
    fn parallel_draw_is_the_sequential_draw() {
        let opts = SynthOptions {
            size: 8,
            supersample: 1,
            ..Default::default()
        };
        let data = synth::dataset(&opts, Split::Train, 3);
        let how = PixelSampling {
            seed: 5,
            step: 9,
            crop: 0.5,
            background: Background::Random,
            appearance: crate::stage::Appearance::PerView,
        };
        let (mut a, mut b) = (TrainingRays::default(), TrainingRays::default());
        a.draw(&data, &how, 3..1000);
        b.draw_parallel(&data, &how, 3..1000);
        assert_eq!(b.len(), 997);
        assert_eq!(a.rays.origins, b.rays.origins);
        assert_eq!(a.rays.dirs, b.rays.dirs);
        assert_eq!(a.rays.view_dirs, b.rays.view_dirs);
        assert_eq!(a.rays.backgrounds, b.rays.backgrounds);
        assert_eq!(a.rays.pixels, b.rays.pixels);
        assert_eq!(a.rays.radii, b.rays.radii);
        assert_eq!(a.rays.radii.len(), 997);
        assert_eq!(a.targets, b.targets);
        assert_eq!((a.rays.near, a.rays.far), (b.rays.near, b.rays.far));
        // The streams continue alike (the lattice jitter is their next draw).
        for (x, y) in a.rngs.iter().zip(&b.rngs) {
            assert_eq!(x.clone().uniform(), y.clone().uniform());
        }
    }

    /// Left-out cameras get no rays, at any scale of a multi-scale split; the rest keep
    /// theirs, and leaving none out draws exactly the rays of a split that never left any.
    #[test]
    fn left_out_cameras_get_no_rays() {
        let opts = SynthOptions {
            size: 8,
            supersample: 1,
            ..Default::default()
        };
        let mut data = synth::dataset(&opts, Split::Train, 4);
        data.add_scales(2).expect("scales");
        assert_eq!(data.views.len(), 8);
        let how = PixelSampling {
            seed: 1,
            step: 3,
            crop: 1.0,
            background: Background::White,
            appearance: crate::stage::Appearance::PerView,
        };
        let views = |data: &Dataset| -> Vec<usize> {
            (0..2000)
                .map(|k| PixelChoice::draw(data, &how, k).view)
                .collect()
        };
        let all = views(&data);
        data.leave_out(4, &[]);
        assert_eq!(views(&data), all);
        data.leave_out(4, &[1, 2]);
        let drawn = views(&data);
        assert!(drawn.iter().all(|v| ![1, 2, 5, 6].contains(v)), "{drawn:?}");
        for v in [0, 3, 4, 7] {
            assert!(drawn.contains(&v), "view {v} lost its rays");
        }
    }
}
