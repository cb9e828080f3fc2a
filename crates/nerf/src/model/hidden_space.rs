//! Few-view training's second rule: space that the scene's own surfaces hide from every
//! training camera stays empty. From all around, some camera looks under an object's base
//! or into a gap and clears what the first steps left there. From a handful of photos
//! taken from above, no photo's pixel passes through the density under a base plate, so
//! nothing removes it, and every new view from lower down shows it as a skirt of fog.
//!
//! A pass every few hundred steps looks from each occupied cell of the occupancy grid
//! towards each training camera that frames it, summing the grid's densities along the
//! way. A cell is hidden when every such camera sees it only through an opaque stretch
//! (optical depth above [`OPAQUE`]); the [`SURFACE_CELLS`] cells nearest it do not count,
//! so a surface is never hidden by its own thickness and only what lies deeper behind
//! one is. A hidden cell stays empty, and is judged again at every pass, so it comes back
//! as soon as a camera sees it (when what hid it has cleared).

use rayon::prelude::*;

use crate::camera::Camera;
use crate::math::{length, sub};
use crate::render::occupancy::{cell_centre, OccupancyGrid};

/// Training steps between passes in a new few-view run (the first pass ends the grid's
/// warm-up, `OccupancyConfig::warmup_steps`). Passes every 64 steps measured the same.
pub const EVERY: u64 = 256;

/// Optical depth past which a stretch hides what is behind it (transmittance `e^-4`,
/// under 2%).
pub const OPAQUE: f32 = 4.0;

/// Cells nearest a cell, along the way to a camera, that do not hide it: its own surface.
pub const SURFACE_CELLS: f32 = 3.0;

/// Which cells of `grid` (x fastest) the scene hides from every one of `cameras` that
/// frames them. The cells judged are the occupied ones and those `was_hidden` (the last
/// pass's answer, or empty); every other cell is not hidden. `dt` is the marching step
/// the grid's thickness (`sigma * dt` per cell) was measured over.
pub fn hidden_cells(
    cameras: &[Camera],
    grid: &OccupancyGrid,
    dt: f32,
    was_hidden: &[bool],
) -> Vec<bool> {
    let res = grid.resolution;
    let cell = 2.0 * grid.bound / res as f32;
    let occupied = grid.occupied_cells();
    let sight = Sight {
        grid,
        cell,
        // Optical depth of one cell's length per unit of thickness.
        per_thickness: cell / dt,
    };
    (0..res.pow(3))
        .into_par_iter()
        .map(|i| {
            let judged = occupied[i] || was_hidden.get(i).copied().unwrap_or(false);
            if !judged {
                return false;
            }
            let p = cell_centre(res, grid.bound, i);
            !cameras
                .iter()
                .any(|cam| cam.frames(p, cell) && sight.clear(p, cam.origin()))
        })
        .collect()
}

/// Lines of sight through an occupancy grid's densities.
struct Sight<'a> {
    grid: &'a OccupancyGrid,
    cell: f32,
    per_thickness: f32,
}

impl Sight<'_> {
    /// Whether the way from `p` to `eye` leaves the grid (or reaches `eye`) before its
    /// optical depth passes [`OPAQUE`], stepping one cell at a time from
    /// [`SURFACE_CELLS`] cells out.
    fn clear(&self, p: [f32; 3], eye: [f32; 3]) -> bool {
        let to = sub(eye, p);
        let distance = length(to);
        if distance <= 0.0 {
            return true;
        }
        let dir = to.map(|x| x / distance);
        let mut depth = 0.0;
        let mut t = SURFACE_CELLS * self.cell;
        while t < distance {
            let q = [0, 1, 2].map(|a| p[a] + dir[a] * t);
            let Some(i) = self.grid.cell_index(q) else {
                return true;
            };
            depth += self.grid.thickness[i] * self.per_thickness;
            if depth > OPAQUE {
                return false;
            }
            t += self.cell;
        }
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::look_at;

    const RES: usize = 32;
    const BOUND: f32 = 1.0;

    fn camera_at(eye: [f32; 3]) -> Camera {
        Camera::from_fov_x(64, 64, 1.2, look_at(eye, [0.0; 3], [0.0, 0.0, 1.0]))
    }

    fn cell_of(p: [f32; 3]) -> usize {
        let cell = 2.0 * BOUND / RES as f32;
        let c = p.map(|x| ((x + BOUND) / cell) as usize);
        c[0] + RES * (c[1] + RES * c[2])
    }

    /// A grid whose cells with `wall(centre)` are opaque (thickness 1 at `dt` = one cell)
    /// and all occupied, the others empty but for `also` (occupied, no thickness).
    fn grid_with(wall: impl Fn([f32; 3]) -> bool, also: &[[f32; 3]]) -> (OccupancyGrid, f32) {
        let cell = 2.0 * BOUND / RES as f32;
        let thickness: Vec<f32> = (0..RES.pow(3))
            .map(|i| {
                if wall(cell_centre(RES, BOUND, i)) {
                    1.0
                } else {
                    0.0
                }
            })
            .collect();
        let mut occupied: Vec<bool> = thickness.iter().map(|&t| t > 0.0).collect();
        for &p in also {
            occupied[cell_of(p)] = true;
        }
        (
            OccupancyGrid::from_parts(RES, BOUND, thickness, occupied),
            cell,
        )
    }

    /// A slab at z in [-0.1, 0.4] (eight cells thick).
    fn slab(p: [f32; 3]) -> bool {
        (-0.1..0.4).contains(&p[2]) && p[0].abs() < 0.9 && p[1].abs() < 0.9
    }

    #[test]
    fn space_under_a_slab_is_hidden_from_cameras_above_and_the_slab_is_not() {
        let under = [0.03, 0.03, -0.5];
        let (grid, dt) = grid_with(slab, &[under]);
        let above = [camera_at([0.2, 0.1, 4.0]), camera_at([3.0, 0.5, 3.0])];
        let hidden = hidden_cells(&above, &grid, dt, &[]);
        assert!(
            hidden[cell_of(under)],
            "under the slab, seen only through it"
        );
        assert!(
            !hidden[cell_of([0.03, 0.03, 0.35])] && !hidden[cell_of([0.03, 0.03, 0.28])],
            "the slab's top cells: their own surface does not hide them"
        );
        assert!(
            hidden[cell_of([0.03, 0.03, -0.07])],
            "its bottom cells, eight cells deep, are behind it"
        );
        assert!(
            !hidden[cell_of([0.5, 0.5, 0.7])],
            "an empty cell is not judged"
        );
        // A camera below sees under the slab.
        let below = [camera_at([0.2, 0.1, 4.0]), camera_at([0.1, 3.0, -3.0])];
        let hidden = hidden_cells(&below, &grid, dt, &[]);
        assert!(!hidden[cell_of(under)]);
    }

    #[test]
    fn a_camera_that_does_not_frame_a_cell_does_not_see_it() {
        let under = [0.03, 0.03, -0.5];
        let (grid, dt) = grid_with(slab, &[under]);
        // Below the slab, but facing away from it: it frames nothing of the grid.
        let away = Camera::from_fov_x(
            64,
            64,
            0.5,
            look_at([0.0, 3.0, -3.0], [0.0, 9.0, -9.0], [0.0, 0.0, 1.0]),
        );
        let cameras = [camera_at([0.2, 0.1, 4.0]), away];
        assert!(hidden_cells(&cameras, &grid, dt, &[])[cell_of(under)]);
    }

    #[test]
    fn thin_fog_does_not_hide_and_a_hidden_cell_is_judged_again() {
        let under = [0.03, 0.03, -0.5];
        let cameras = [camera_at([0.2, 0.1, 4.0])];
        // Fog of a fifth of the slab's density: optical depth 1.6 through its eight cells.
        let (mut grid, dt) = grid_with(slab, &[under]);
        for t in &mut grid.thickness {
            *t *= 0.2;
        }
        assert!(!hidden_cells(&cameras, &grid, dt, &[])[cell_of(under)]);
        // A cell the last pass hid is judged although no longer occupied: still hidden
        // behind the slab, and free again once the slab is gone.
        let (grid, dt) = grid_with(slab, &[]);
        let was = hidden_cells(&cameras, &grid_with(slab, &[under]).0, dt, &[]);
        assert!(was[cell_of(under)]);
        assert!(hidden_cells(&cameras, &grid, dt, &was)[cell_of(under)]);
        assert!(!hidden_cells(&cameras, &grid, dt, &[])[cell_of(under)]);
        let (open, dt) = grid_with(|_| false, &[]);
        assert!(!hidden_cells(&cameras, &open, dt, &was)[cell_of(under)]);
    }
}
