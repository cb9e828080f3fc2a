//! Pixel footprints (mip-NeRF, Barron et al. 2021): a pixel sees a cone, not a line. Its
//! radius is taken as the standard deviation of a disc as wide as the pixel, `2 / sqrt(12)`
//! of the pixel's width (mip-NeRF's choice: the variance of a uniform distribution over the
//! pixel), per unit of distance along the ray. Anti-aliased fields read no detail finer
//! than a sample's footprint, so a model trained or viewed at several distances neither
//! blurs close up nor aliases far away.

use super::ray_space::RaySpace;
use super::Camera;
use crate::math::{length, normalize_or_zero, sub};

/// The footprint radius of a pixel of width 1: `2 / sqrt(12)`.
pub const PIXEL_RADIUS: f32 = 0.577_350_26;

impl Camera {
    /// The footprint radius, per unit of distance along the ray, of the pixel centred at
    /// image point `(x, y)`: from the angles to its neighbours' rays, so lens distortion
    /// (which stretches pixels towards the edges) is included.
    pub fn cone_radius(&self, x: f32, y: f32) -> f32 {
        let unit = |x: f32, y: f32| normalize_or_zero(self.ray_at(x, y).dir);
        let here = unit(x, y);
        let across = length(sub(unit(x + 1.0, y), here));
        let down = length(sub(unit(x, y + 1.0), here));
        PIXEL_RADIUS * (across * down).sqrt()
    }
}

impl RaySpace {
    /// A pixel's footprint in this space, given its world cone radius `cone` (see
    /// [`Camera::cone_radius`]) and world ray direction `dir`: world rays keep the cone
    /// (radius per unit distance); in NDC a pixel covers the same `x, y` at every depth,
    /// so the radius there is constant: `sqrt(ax ay) cone |d| / |d_z|`.
    pub fn footprint_radius(&self, cone: f32, dir: [f32; 3]) -> f32 {
        match self {
            RaySpace::World => cone,
            RaySpace::Ndc(ndc) => {
                (ndc.ax * ndc.ay).sqrt() * cone * length(dir) / dir[2].abs().max(1e-6)
            }
        }
    }

    /// Whether footprints in this space are constant along rays (see
    /// [`RayBatch::cylinders`](crate::stage::RayBatch::cylinders)).
    pub fn cylinders(&self) -> bool {
        matches!(self, RaySpace::Ndc(_))
    }
}

/// The typical footprint (field units) of training samples near the scene's centre: the
/// median over `cameras` of the central pixel's radius at the camera's distance from the
/// origin (at least `min_distance`), or its NDC radius. Anti-aliased fields use it where
/// samples carry no footprint (occupancy refreshes, meshes).
pub fn reference_footprint(cameras: &[Camera], space: &RaySpace, min_distance: f32) -> f32 {
    let mut radii: Vec<f32> = cameras
        .iter()
        .map(|c| {
            let centre = c.ray_at(c.cx, c.cy);
            let cone = c.cone_radius(c.cx, c.cy);
            match space {
                RaySpace::World => cone * length(c.origin()).max(min_distance),
                RaySpace::Ndc(_) => space.footprint_radius(cone, centre.dir),
            }
        })
        .filter(|r| r.is_finite())
        .collect();
    if radii.is_empty() {
        return 0.0;
    }
    radii.sort_by(f32::total_cmp);
    radii[radii.len() / 2]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::look_at;

    /// At the centre of a pinhole camera the cone is one pixel of `1 / f` radians, times
    /// `2 / sqrt(12)`; halving the resolution doubles it.
    #[test]
    fn centre_pixel_cone_is_pixel_angle_times_the_disc_factor() {
        let cam = Camera::from_fov_x(
            400,
            300,
            0.69,
            look_at([0.0, -4.0, 1.0], [0.0; 3], [0.0, 0.0, 1.0]),
        );
        let r = cam.cone_radius(200.0, 150.0);
        let expected = PIXEL_RADIUS / cam.fx;
        assert!((r / expected - 1.0).abs() < 1e-3, "{r} vs {expected}");
        let half = cam.downscaled(2);
        let r2 = half.cone_radius(100.0, 75.0);
        assert!((r2 / (2.0 * r) - 1.0).abs() < 1e-3, "{r2} vs 2 x {r}");
        // Towards a corner pixels subtend smaller angles (they are seen obliquely).
        assert!(cam.cone_radius(1.0, 1.0) < r);
    }

    /// An NDC footprint equals the world footprint's width in NDC units at the ray's depth.
    #[test]
    fn ndc_radius_is_the_world_cone_seen_in_ndc() {
        use crate::camera::ray_space::Ndc;
        let ndc = Ndc {
            ax: 2.0 * 500.0 / 400.0,
            ay: 2.0 * 500.0 / 300.0,
            near: 1.0,
        };
        let space = RaySpace::Ndc(ndc);
        let (cone, dir) = (0.001, [0.1, -0.05, -1.0]);
        let r = space.footprint_radius(cone, dir);
        // A world point at depth z: moving sideways by the cone's radius at that distance
        // moves NDC x by ax * radius / |z|.
        let z = 3.0;
        let s = z * length(dir) / dir[2].abs();
        let world = cone * s;
        let expected = (ndc.ax * ndc.ay).sqrt() * world / z;
        assert!((r / expected - 1.0).abs() < 1e-4, "{r} vs {expected}");
        assert!(space.cylinders() && !RaySpace::World.cylinders());
    }
}
