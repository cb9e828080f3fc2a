//! Where a scene's cameras aim, against the box the fast model covers: what tells a file
//! read in the wrong convention (every camera looking away from the scene) or placed around
//! another centre (every camera looking past the box) from one read right.

use crate::camera::Camera;
use crate::math::V3;

/// Points spread through the box `[-bound, bound]^3`: a 5x5x5 lattice, its corners included.
fn box_points(bound: f32) -> impl Iterator<Item = V3> {
    const N: usize = 5;
    let at = move |k: usize| bound * (2.0 * k as f32 / (N - 1) as f32 - 1.0);
    (0..N * N * N).map(move |i| [at(i % N), at(i / N % N), at(i / (N * N))])
}

/// Whether any part of the box lies in the camera's view, no farther than `far` along its
/// axis (lens distortion aside: what matters is where the camera points). A camera inside
/// the box (or on its surface) sees it, whichever way it looks: an inside-out capture of a
/// room has its box around the cameras.
pub fn sees_box(camera: &Camera, bound: f32, far: f32) -> bool {
    if camera.origin().iter().all(|x| x.abs() <= 1.01 * bound) {
        return true;
    }
    box_points(bound).any(|p| {
        let (u, v, depth) = camera.project(p);
        depth > 0.0
            && depth <= far
            && (0.0..=camera.width as f32).contains(&u)
            && (0.0..=camera.height as f32).contains(&v)
    })
}

/// How many of `cameras` see no part of the box (see [`sees_box`]).
pub fn cameras_blind_to_box(cameras: &[Camera], bound: f32, far: f32) -> usize {
    cameras.iter().filter(|c| !sees_box(c, bound, far)).count()
}

/// Whether the ray through the image centre crosses the box no farther than `far` (a
/// camera inside the box counts).
pub fn central_ray_hits_box(camera: &Camera, bound: f32, far: f32) -> bool {
    let ray = camera.ray_at(camera.cx, camera.cy);
    let (mut t0, mut t1) = (0.0f32, far);
    for a in 0..3 {
        let (o, d) = (ray.origin[a], ray.dir[a]);
        if d.abs() < 1e-12 {
            if o.abs() > bound {
                return false;
            }
            continue;
        }
        let (ta, tb) = ((-bound - o) / d, (bound - o) / d);
        t0 = t0.max(ta.min(tb));
        t1 = t1.min(ta.max(tb));
    }
    t0 <= t1
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::look_at;
    use crate::math::{add, scale};

    fn camera(eye: V3, target: V3) -> Camera {
        Camera::from_fov_x(64, 64, 0.8, look_at(eye, target, [0.0, 0.0, 1.0]))
    }

    /// Eight cameras on a circle of `radius` at height `z`, each looking at `target(eye)`.
    fn ring(radius: f32, z: f32, target: impl Fn(V3) -> V3) -> Vec<Camera> {
        (0..8)
            .map(|k| {
                let a = k as f32 * std::f32::consts::TAU / 8.0;
                let eye = [radius * a.cos(), radius * a.sin(), z];
                camera(eye, target(eye))
            })
            .collect()
    }

    #[test]
    fn four_shapes_of_capture() {
        // Inward: a ring around the box, looking at its centre.
        let inward = ring(4.0, 1.0, |_| [0.0; 3]);
        assert_eq!(cameras_blind_to_box(&inward, 1.5, 6.0), 0);
        // Forward-facing: a small grid of cameras looking the same way at the box.
        let forward: Vec<Camera> = (0..9)
            .map(|k| {
                let eye = [(k % 3) as f32 * 0.3 - 0.3, -4.0, (k / 3) as f32 * 0.3];
                camera(eye, add(eye, [0.0, 4.0, 0.0]))
            })
            .collect();
        assert_eq!(cameras_blind_to_box(&forward, 1.5, 6.0), 0);
        // Inside-out: a room around the cameras, each looking outwards.
        let room = ring(0.3, 0.0, |eye| scale(eye, 10.0));
        assert_eq!(cameras_blind_to_box(&room, 3.0, 6.0), 0);
        // Away: a ring around the box, every camera facing outwards.
        let away = ring(4.0, 1.0, |eye| scale(eye, 2.0));
        assert_eq!(cameras_blind_to_box(&away, 1.5, 6.0), 8);
        // Straight up, from above the box.
        let up = ring(1.0, 5.0, |eye| add(eye, [0.01, 0.0, 5.0]));
        assert_eq!(cameras_blind_to_box(&up, 1.5, 20.0), 8);
    }

    #[test]
    fn central_rays_find_the_box_or_miss_it() {
        let inward = ring(4.0, 1.0, |_| [0.0; 3]);
        assert!(inward.iter().all(|c| central_ray_hits_box(c, 1.5, 6.0)));
        // Circling a point 5 units off the origin: the rays miss the default box.
        let off = ring(4.0, 1.0, |_| [0.0; 3])
            .into_iter()
            .map(|mut c| {
                c.c2w[0][3] += 5.0;
                c
            })
            .collect::<Vec<_>>();
        let hits = off
            .iter()
            .filter(|c| central_ray_hits_box(c, 1.5, 6.0))
            .count();
        assert!(hits <= 2, "{hits} of 8 hit");
    }
}
