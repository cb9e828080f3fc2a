//! Training from few photos (at most [`FEW_VIEWS`]). With few photos, space that few of
//! them see can explain their pixels with anything at any depth, and a field fills it
//! with floaters that every other view then shows. Few-view training keeps the space that
//! fewer than half of the training photos frame empty: the occupancy grid never marks it,
//! so no sample is taken there in training or rendering. It keeps the space the scene's
//! surfaces hide from every photo empty too (`hidden_space`). And the colour network sees
//! only the view direction's first [`VIEW_HARMONICS`] spherical harmonics: with a
//! handful of photos, the finer ones let colour vary with the view enough to explain
//! each photo's pixels without the right geometry. Last, the hash tables' entries decay
//! towards zero ([`TABLE_DECAY`]): a few photos' pixels can be fitted exactly by fine
//! features that only they constrain, and every other view shows those as speckle and
//! ghosts; the decay keeps a feature only where the photos keep asking for it.

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::camera::ray_space::RaySpace;
use crate::camera::Camera;
use crate::render::occupancy::{cell_centre, OccupancyGrid};

/// Runs on at most this many training views get few-view training by default.
pub const FEW_VIEWS: usize = 16;

/// The view direction's spherical harmonics (degrees 0 and 1) the colour network of a
/// few-view run sees (`field::FastFieldConfig::view_harmonics`; 16 otherwise).
pub const VIEW_HARMONICS: usize = 4;

/// The L2 penalty on the hash tables' entries a step touches in a few-view run
/// (`FastModelConfig::table_decay`; none otherwise): on 8-view lego 1e-6 and 3e-6
/// measured alike and above the larger weights; 3e-6 also on the chair (figures in
/// `docs/benchmarks.md`).
pub const TABLE_DECAY: f32 = 3e-6;

/// Whether keeping unseen space empty applies to a scene marched in `space`, contracted
/// or not: only to bounded scenes in world space, whose grid cells are places the photos
/// can be asked about (a forward-facing capture's NDC cells and a contracted capture's
/// outer cells are not).
pub fn applies(space: RaySpace, contract: bool) -> bool {
    space == RaySpace::World && !contract
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct FewView {
    /// The training photos.
    pub photos: usize,
    /// Training steps between passes that find the space the scene hides from every
    /// training camera (`hidden_space`); 0: none, as in runs saved before there were any.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub hidden_every: u64,
}

fn is_zero(x: &u64) -> bool {
    *x == 0
}

impl FewView {
    /// Few-view training from `photos` photos, as a new run trains.
    pub fn new(photos: usize) -> Self {
        FewView {
            photos,
            hidden_every: super::hidden_space::EVERY,
        }
    }

    /// Whether the pass that finds hidden space runs after `steps_done` steps.
    pub fn hidden_pass_after(&self, steps_done: u64) -> bool {
        self.hidden_every > 0 && steps_done > 0 && steps_done.is_multiple_of(self.hidden_every)
    }

    /// How many photos must see a cell for it to hold anything: half of them, at least 2.
    pub fn min_views(&self) -> usize {
        self.photos.div_ceil(2).max(2)
    }
}

/// What few-view training knows of a run's cells: which enough training cameras frame
/// (fixed by the cameras) and which the scene hides from all of them (the last pass's
/// answer, saved with the checkpoint).
#[derive(Clone, Debug, Default)]
pub struct Visibility {
    pub cameras: Vec<Camera>,
    pub framed: Vec<bool>,
    pub hidden: Vec<bool>,
}

impl Visibility {
    /// The cells that may hold anything: framed and not hidden.
    pub fn possible(&self) -> Vec<bool> {
        let hidden = |i: usize| self.hidden.get(i).copied().unwrap_or(false);
        self.framed
            .iter()
            .enumerate()
            .map(|(i, &f)| f && !hidden(i))
            .collect()
    }

    /// Judges `grid`'s cells again (`hidden_space::hidden_cells`; `dt` is the marching
    /// step of its thickness) and returns the cells that may hold anything from now on.
    pub fn find_hidden(&mut self, grid: &OccupancyGrid, dt: f32) -> Vec<bool> {
        self.hidden = super::hidden_space::hidden_cells(&self.cameras, grid, dt, &self.hidden);
        self.possible()
    }
}

/// For each cell of a `resolution^3` grid over `[-bound, bound]^3` (x fastest), whether at
/// least `min_views` of `cameras` see its centre: in front of the camera and inside its
/// image, widened by the cell's own size there (`Camera::frames`).
pub fn seen_by(cameras: &[Camera], resolution: usize, bound: f32, min_views: usize) -> Vec<bool> {
    let cell = 2.0 * bound / resolution as f32;
    (0..resolution.pow(3))
        .into_par_iter()
        .map(|i| {
            let p = cell_centre(resolution, bound, i);
            cameras.iter().filter(|cam| cam.frames(p, cell)).count() >= min_views
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn half_of_the_photos_and_at_least_two_must_see_a_cell() {
        let min = |photos| FewView::new(photos).min_views();
        assert_eq!(
            [min(1), min(3), min(4), min(8), min(9), min(16)],
            [2, 2, 2, 4, 5, 8]
        );
    }
    use crate::camera::look_at;

    #[test]
    fn a_cell_is_seen_where_it_projects_into_enough_images() {
        // Two cameras on the x axis, facing the origin, with a narrow field of view.
        let left = Camera::from_fov_x(
            32,
            32,
            0.3,
            look_at([-4.0, 0.0, 0.0], [0.0; 3], [0.0, 0.0, 1.0]),
        );
        let right = Camera::from_fov_x(
            32,
            32,
            0.3,
            look_at([4.0, 0.0, 0.0], [0.0; 3], [0.0, 0.0, 1.0]),
        );
        let res = 16;
        let seen = seen_by(&[left.clone(), right], res, 1.5, 2);
        let at = |p: [f32; 3]| {
            let cell = 3.0 / res as f32;
            let c = p.map(|x| ((x + 1.5) / cell) as usize);
            seen[c[0] + res * (c[1] + res * c[2])]
        };
        assert!(at([0.0, 0.0, 0.0]), "the centre is in both views");
        assert!(
            !at([0.0, 1.4, 1.4]),
            "a corner is outside both narrow views"
        );
        // The centre's projection lands mid-image, where ray_at points.
        let r = left.ray_at(16.0, 16.0);
        assert!(r.dir[0] > 0.99 * crate::math::length(r.dir));
        // One view is not enough at two, but is at one.
        assert!(!seen_by(std::slice::from_ref(&left), res, 1.5, 2)
            .iter()
            .any(|&s| s));
        let one = seen_by(&[left], res, 1.5, 1);
        assert!(one.iter().any(|&s| s) && !one.iter().all(|&s| s));
    }

    #[test]
    fn a_point_behind_the_camera_or_off_the_image_is_not_seen() {
        let cam = Camera::from_fov_x(
            32,
            32,
            0.5,
            look_at([0.0, -4.0, 0.0], [0.0; 3], [0.0, 0.0, 1.0]),
        );
        assert!(cam.frames([0.0, 0.0, 0.0], 0.01));
        assert!(!cam.frames([0.0, -6.0, 0.0], 0.01), "behind");
        assert!(!cam.frames([3.0, 0.0, 0.0], 0.01), "off to the side");
    }
}
