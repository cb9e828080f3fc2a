//! Pose algebra for real captures: the similarity transforms that put a capture's cameras
//! into a canonical frame (centred, scaled, +Z up), and the average pose and focus point
//! those frames are built from.

use crate::camera::Pose;
use crate::math::{add, cross, dot, length, normalize_or_zero, scale, sub, V3};

/// `x -> s R x + t`, applied to camera positions (rotations only see `R`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Similarity {
    pub rotation: [[f32; 3]; 3],
    pub translation: V3,
    pub scale: f32,
}

impl Similarity {
    pub const IDENTITY: Similarity = Similarity {
        rotation: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        translation: [0.0; 3],
        scale: 1.0,
    };

    pub fn apply_point(&self, p: V3) -> V3 {
        add(scale(mat_vec(&self.rotation, p), self.scale), self.translation)
    }

    pub fn apply_pose(&self, pose: &Pose) -> Pose {
        let mut out = [[0.0; 4]; 3];
        let o = self.apply_point(origin(pose));
        for c in 0..3 {
            let axis = mat_vec(&self.rotation, column(pose, c));
            for r in 0..3 {
                out[r][c] = axis[r];
            }
        }
        for r in 0..3 {
            out[r][3] = o[r];
        }
        out
    }

    /// `self` after `first`.
    pub fn after(&self, first: &Similarity) -> Similarity {
        Similarity {
            rotation: mat_mul(&self.rotation, &first.rotation),
            translation: self.apply_point(first.translation),
            scale: self.scale * first.scale,
        }
    }
}

pub fn column(pose: &Pose, c: usize) -> V3 {
    [pose[0][c], pose[1][c], pose[2][c]]
}

pub fn origin(pose: &Pose) -> V3 {
    column(pose, 3)
}

fn mat_vec(m: &[[f32; 3]; 3], v: V3) -> V3 {
    [dot(m[0], v), dot(m[1], v), dot(m[2], v)]
}

fn mat_mul(a: &[[f32; 3]; 3], b: &[[f32; 3]; 3]) -> [[f32; 3]; 3] {
    let mut m = [[0.0; 3]; 3];
    for (r, row) in m.iter_mut().enumerate() {
        for (c, v) in row.iter_mut().enumerate() {
            *v = (0..3).map(|k| a[r][k] * b[k][c]).sum();
        }
    }
    m
}

fn mean(points: impl Iterator<Item = V3>) -> V3 {
    let (mut s, mut n) = ([0.0f32; 3], 0usize);
    for p in points {
        s = add(s, p);
        n += 1;
    }
    scale(s, 1.0 / n.max(1) as f32)
}

/// LLFF's average pose: mean position, mean viewing axis, mean up (re-orthogonalised).
pub fn average_pose(poses: &[Pose]) -> Pose {
    let centre = mean(poses.iter().map(origin));
    let z = normalize_or_zero(mean(poses.iter().map(|p| column(p, 2))));
    let up = mean(poses.iter().map(|p| column(p, 1)));
    let x = normalize_or_zero(cross(up, z));
    let y = cross(z, x);
    [
        [x[0], y[0], z[0], centre[0]],
        [x[1], y[1], z[1], centre[1]],
        [x[2], y[2], z[2], centre[2]],
    ]
}

/// The similarity that maps `pose`'s frame onto the world frame (its rigid inverse).
pub fn into_frame_of(pose: &Pose) -> Similarity {
    let mut rotation = [[0.0; 3]; 3];
    for (r, row) in rotation.iter_mut().enumerate() {
        *row = column(pose, r);
    }
    let t = mat_vec(&rotation, origin(pose));
    Similarity {
        rotation,
        translation: scale(t, -1.0),
        scale: 1.0,
    }
}

/// The point nearest (in least squares) to every camera's optical axis: what an
/// inward-facing capture looks at. Falls back to the mean position when the axes are
/// (nearly) parallel.
pub fn focus_point(poses: &[Pose]) -> V3 {
    let mut a = [[0.0f64; 3]; 3];
    let mut b = [0.0f64; 3];
    for p in poses {
        let d = normalize_or_zero(column(p, 2)).map(f64::from);
        let o = origin(p).map(f64::from);
        for r in 0..3 {
            for c in 0..3 {
                let m = if r == c { 1.0 } else { 0.0 } - d[r] * d[c];
                a[r][c] += m;
                b[r] += m * o[c];
            }
        }
    }
    let det = a[0][0] * (a[1][1] * a[2][2] - a[1][2] * a[2][1])
        - a[0][1] * (a[1][0] * a[2][2] - a[1][2] * a[2][0])
        + a[0][2] * (a[1][0] * a[2][1] - a[1][1] * a[2][0]);
    if det.abs() < 1e-6 * poses.len().pow(3) as f64 {
        return mean(poses.iter().map(origin));
    }
    let solve_col = |k: usize| {
        let mut m = a;
        for r in 0..3 {
            m[r][k] = b[r];
        }
        (m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
            - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
            + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0]))
            / det
    };
    [solve_col(0) as f32, solve_col(1) as f32, solve_col(2) as f32]
}

/// A rotation taking unit vector `from` onto `to` (Rodrigues).
pub(crate) fn rotation_between(from: V3, to: V3) -> [[f32; 3]; 3] {
    let v = cross(from, to);
    let c = dot(from, to);
    let s = length(v);
    if s < 1e-7 {
        if c > 0.0 {
            return Similarity::IDENTITY.rotation;
        }
        // Half turn about any axis perpendicular to `from`.
        let helper = if from[0].abs() < 0.9 { [1.0, 0.0, 0.0] } else { [0.0, 1.0, 0.0] };
        let k = normalize_or_zero(cross(from, helper));
        let mut m = [[0.0; 3]; 3];
        for (r, row) in m.iter_mut().enumerate() {
            for (col, x) in row.iter_mut().enumerate() {
                *x = 2.0 * k[r] * k[col] - if r == col { 1.0 } else { 0.0 };
            }
        }
        return m;
    }
    let k = scale(v, 1.0 / s);
    let kx = [[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]];
    let kx2 = mat_mul(&kx, &kx);
    let mut m = Similarity::IDENTITY.rotation;
    for r in 0..3 {
        for col in 0..3 {
            m[r][col] += s * kx[r][col] + (1.0 - c) * kx2[r][col];
        }
    }
    m
}

/// The frame of an inward-facing capture: the focus point moves to the origin, the
/// cameras' mean up vector becomes +Z (our orbits' up), and the scale puts the cameras at
/// root-mean-square distance `radius` from the origin.
pub fn inward_frame(poses: &[Pose], radius: f32) -> Similarity {
    let centre = focus_point(poses);
    let up = normalize_or_zero(mean(poses.iter().map(|p| column(p, 1))));
    let rotation = rotation_between(up, [0.0, 0.0, 1.0]);
    let rms = (poses
        .iter()
        .map(|p| {
            let d = sub(origin(p), centre);
            dot(d, d)
        })
        .sum::<f32>()
        / poses.len().max(1) as f32)
        .sqrt();
    let s = if rms > 0.0 { radius / rms } else { 1.0 };
    Similarity {
        rotation,
        translation: scale(mat_vec(&rotation, centre), -s),
        scale: s,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::{look_at, orbit};

    #[test]
    fn inward_frame_finds_centre_up_and_radius() {
        // Cameras on a 120-degree arc, looking at (1, 2, 3) with +Y up, 5 units away.
        let centre = [1.0, 2.0, 3.0];
        let poses: Vec<Pose> = (0..9)
            .map(|k| {
                let a = -1.0 + k as f32 * 0.25;
                let eye = add(centre, [5.0 * a.sin(), 1.0, 5.0 * a.cos()]);
                look_at(eye, centre, [0.0, 1.0, 0.0])
            })
            .collect();
        let f = focus_point(&poses);
        assert!(length(sub(f, centre)) < 1e-3, "focus {f:?}");
        let sim = inward_frame(&poses, 2.0);
        let moved: Vec<Pose> = poses.iter().map(|p| sim.apply_pose(p)).collect();
        let rms = (moved.iter().map(|p| dot(origin(p), origin(p))).sum::<f32>() / 9.0).sqrt();
        assert!((rms - 2.0).abs() < 1e-4, "radius {rms}");
        for p in &moved {
            // Up is +Z now, and every camera still looks at the (new) origin.
            assert!(dot(column(p, 1), [0.0, 0.0, 1.0]) > 0.97);
            let to_centre = normalize_or_zero(scale(origin(p), -1.0));
            assert!(dot(scale(column(p, 2), -1.0), to_centre) > 0.9999);
        }
    }

    #[test]
    fn average_pose_of_an_orbit_and_inverse() {
        let poses = orbit(8, 4.0, 0.3);
        let avg = average_pose(&poses);
        let o = origin(&avg);
        assert!(o[0].abs() < 1e-4 && o[1].abs() < 1e-4, "orbit centre {o:?}");
        let to = into_frame_of(&poses[3]);
        let p = to.apply_pose(&poses[3]);
        for r in 0..3 {
            for c in 0..4 {
                let want = if r == c { 1.0 } else { 0.0 };
                assert!((p[r][c] - want).abs() < 1e-5, "{p:?}");
            }
        }
        let both = to.after(&Similarity { scale: 2.0, ..Similarity::IDENTITY });
        let q = [0.3, -0.2, 0.5];
        let want = to.apply_point(scale(q, 2.0));
        assert!(length(sub(both.apply_point(q), want)) < 1e-5);
    }
}
