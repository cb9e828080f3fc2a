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
        add(
            scale(mat_vec(&self.rotation, p), self.scale),
            self.translation,
        )
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

    /// The similarity that undoes this one.
    pub fn inverse(&self) -> Similarity {
        let rt: [[f32; 3]; 3] =
            std::array::from_fn(|i| std::array::from_fn(|j| self.rotation[j][i]));
        let s = 1.0 / self.scale;
        Similarity {
            rotation: rt,
            translation: scale(mat_vec(&rt, self.translation), -s),
            scale: s,
        }
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
    [
        solve_col(0) as f32,
        solve_col(1) as f32,
        solve_col(2) as f32,
    ]
}

/// The rotation that turns the cameras' mean up vector to +Z (our orbits' up).
fn up_to_z(poses: &[Pose]) -> [[f32; 3]; 3] {
    let up = normalize_or_zero(mean(poses.iter().map(|p| column(p, 1))));
    rotation_between(up, [0.0, 0.0, 1.0])
}

/// nerfstudio's default placement: the cameras' mean up vector becomes +Z, their mean
/// position moves to the origin, and they are scaled to fit in `[-1, 1]^3`.
pub fn centred_frame(poses: &[Pose]) -> Similarity {
    let oriented = Similarity {
        rotation: up_to_z(poses),
        ..Similarity::IDENTITY
    };
    let centre = mean(poses.iter().map(|p| oriented.apply_point(origin(p))));
    let extent = poses
        .iter()
        .flat_map(|p| sub(oriented.apply_point(origin(p)), centre))
        .fold(0.0f32, |m, x| m.max(x.abs()));
    let s = if extent > 0.0 { 1.0 / extent } else { 1.0 };
    Similarity {
        rotation: oriented.rotation,
        translation: scale(centre, -s),
        scale: s,
    }
}

/// A rotation taking unit vector `from` onto `to` (Rodrigues).
fn rotation_between(from: V3, to: V3) -> [[f32; 3]; 3] {
    let v = cross(from, to);
    let c = dot(from, to);
    let s = length(v);
    if s < 1e-7 {
        if c > 0.0 {
            return Similarity::IDENTITY.rotation;
        }
        // Half turn about any axis perpendicular to `from`.
        let helper = if from[0].abs() < 0.9 {
            [1.0, 0.0, 0.0]
        } else {
            [0.0, 1.0, 0.0]
        };
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

/// Half-extent of the fast model's box for an inward-facing (360-degree) capture placed by
/// [`inward_frame`] with radius 1, in units of the cameras' radius; space is contracted
/// beyond half of it. The kept cube (1.5 radii) holds the cameras and what they look at,
/// and follows them: a box from the sparse points instead reaches, in a room, far beyond
/// what the photos see well, and trains worse. Every
/// reader of such a capture (LLFF `--spherify`, COLMAP, and `nerf capture`'s
/// `transforms.json`) uses this one box.
pub const INWARD_BOX: f32 = 3.0;

/// The frame of an inward-facing capture: the focus point moves to the origin, the
/// cameras' mean up vector becomes +Z (our orbits' up), and the scale puts the cameras at
/// root-mean-square distance `radius` from the origin.
pub fn inward_frame(poses: &[Pose], radius: f32) -> Similarity {
    let centre = focus_point(poses);
    let rotation = up_to_z(poses);
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

/// The similarity `x -> s R x + t` that best maps points `from` onto `to` (least squares;
/// Horn's closed form with quaternions), and the RMS distance left.
pub fn fit_similarity(from: &[V3], to: &[V3]) -> (Similarity, f32) {
    let n = from.len().min(to.len());
    let fit = CentredPairs::of(&from[..n], &to[..n]);
    let sim = fit.similarity(horn_rotation(fit.cross));
    let rms = (from[..n]
        .iter()
        .zip(&to[..n])
        .map(|(&a, &b)| {
            let d = sub(sim.apply_point(a), b);
            dot(d, d)
        })
        .sum::<f32>()
        / n.max(1) as f32)
        .sqrt();
    (sim, rms)
}

/// The similarity that best maps the cameras `from` onto `to`: its rotation the one that
/// best turns their orientations onto each other (Horn's least squares over every
/// camera's three axes: the chordal mean of the cameras' relative rotations), its scale
/// and translation those of the centres. Centres alone leave the rotation poorly
/// determined when they lie near a plane or a line against their own errors (a
/// forward-facing grid, whose centre errors can be a tenth of its spread); orientations
/// determine it for any layout.
pub fn fit_similarity_of_poses(from: &[Pose], to: &[Pose]) -> Similarity {
    let n = from.len().min(to.len());
    let centres = |poses: &[Pose]| poses[..n].iter().map(origin).collect::<Vec<_>>();
    let fit = CentredPairs::of(&centres(from), &centres(to));
    let mut axes = [[0.0f64; 3]; 3];
    for (a, b) in from[..n].iter().zip(&to[..n]) {
        for axis in 0..3 {
            let (u, v) = (column(a, axis), column(b, axis));
            for r in 0..3 {
                for c in 0..3 {
                    axes[r][c] += f64::from(u[r]) * f64::from(v[c]);
                }
            }
        }
    }
    fit.similarity(horn_rotation(axes))
}

/// Paired point sets about their centroids: the cross-covariance `sum a b^T` and the
/// spreads that Horn's method needs.
struct CentredPairs {
    centroid_from: V3,
    centroid_to: V3,
    cross: [[f64; 3]; 3],
    var_from: f64,
    var_to: f64,
}

impl CentredPairs {
    fn of(from: &[V3], to: &[V3]) -> CentredPairs {
        let centroid_from = mean(from.iter().copied());
        let centroid_to = mean(to.iter().copied());
        let mut cross = [[0.0f64; 3]; 3];
        let (mut var_from, mut var_to) = (0.0f64, 0.0f64);
        for (&a, &b) in from.iter().zip(to) {
            let a = sub(a, centroid_from).map(f64::from);
            let b = sub(b, centroid_to).map(f64::from);
            for r in 0..3 {
                for c in 0..3 {
                    cross[r][c] += a[r] * b[c];
                }
            }
            var_from += a.iter().map(|v| v * v).sum::<f64>();
            var_to += b.iter().map(|v| v * v).sum::<f64>();
        }
        CentredPairs {
            centroid_from,
            centroid_to,
            cross,
            var_from,
            var_to,
        }
    }

    /// With `rotation` found: Horn's symmetric scale, and the translation that maps the
    /// centroids onto each other.
    fn similarity(&self, rotation: [[f32; 3]; 3]) -> Similarity {
        let scale_ab = if self.var_from > 0.0 {
            (self.var_to / self.var_from).sqrt() as f32
        } else {
            1.0
        };
        let rotated = mat_vec(&rotation, self.centroid_from);
        Similarity {
            rotation,
            translation: sub(self.centroid_to, scale(rotated, scale_ab)),
            scale: scale_ab,
        }
    }
}

/// The rotation `R` that maximises `sum b . R a` for the cross-covariance `s = sum a b^T`
/// (Horn's quaternion method).
fn horn_rotation(s: [[f64; 3]; 3]) -> [[f32; 3]; 3] {
    let [[sxx, sxy, sxz], [syx, syy, syz], [szx, szy, szz]] = s;
    let m = [
        [sxx + syy + szz, syz - szy, szx - sxz, sxy - syx],
        [syz - szy, sxx - syy - szz, sxy + syx, szx + sxz],
        [szx - sxz, sxy + syx, -sxx + syy - szz, syz + szy],
        [sxy - syx, szx + sxz, syz + szy, -sxx - syy + szz],
    ];
    let [w, x, y, z] = top_eigenvector(m);
    [
        [
            w * w + x * x - y * y - z * z,
            2.0 * (x * y - w * z),
            2.0 * (x * z + w * y),
        ],
        [
            2.0 * (x * y + w * z),
            w * w - x * x + y * y - z * z,
            2.0 * (y * z - w * x),
        ],
        [
            2.0 * (x * z - w * y),
            2.0 * (y * z + w * x),
            w * w - x * x - y * y + z * z,
        ],
    ]
    .map(|row| row.map(|v| v as f32))
}

/// Unit eigenvector of the largest eigenvalue of a symmetric 4x4 matrix (cyclic Jacobi).
fn top_eigenvector(mut a: [[f64; 4]; 4]) -> [f64; 4] {
    let mut v = [[0.0f64; 4]; 4];
    for (i, row) in v.iter_mut().enumerate() {
        row[i] = 1.0;
    }
    for _sweep in 0..50 {
        let off: f64 = (0..4)
            .flat_map(|p| ((p + 1)..4).map(move |q| (p, q)))
            .map(|(p, q)| a[p][q] * a[p][q])
            .sum();
        if off < 1e-24 {
            break;
        }
        for p in 0..4 {
            for q in (p + 1)..4 {
                if a[p][q].abs() < 1e-300 {
                    continue;
                }
                let theta = (a[q][q] - a[p][p]) / (2.0 * a[p][q]);
                let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
                let t = if theta == 0.0 { 1.0 } else { t };
                let c = 1.0 / (t * t + 1.0).sqrt();
                let s = t * c;
                for k in 0..4 {
                    let (akp, akq) = (a[k][p], a[k][q]);
                    a[k][p] = c * akp - s * akq;
                    a[k][q] = s * akp + c * akq;
                }
                for k in 0..4 {
                    let (apk, aqk) = (a[p][k], a[q][k]);
                    a[p][k] = c * apk - s * aqk;
                    a[q][k] = s * apk + c * aqk;
                }
                for row in v.iter_mut() {
                    let (vp, vq) = (row[p], row[q]);
                    row[p] = c * vp - s * vq;
                    row[q] = s * vp + c * vq;
                }
            }
        }
    }
    let best = (0..4).fold(0, |b, i| if a[i][i] > a[b][b] { i } else { b });
    [v[0][best], v[1][best], v[2][best], v[3][best]]
}

/// The largest angle (degrees) between a camera's viewing direction and the cameras' mean
/// viewing direction: small for forward-facing captures, large for ones that circle the
/// object.
pub fn view_spread_degrees(poses: &[Pose]) -> f32 {
    let mean = normalize_or_zero(mean(poses.iter().map(|p| normalize_or_zero(column(p, 2)))));
    poses
        .iter()
        .map(|p| {
            dot(normalize_or_zero(column(p, 2)), mean)
                .clamp(-1.0, 1.0)
                .acos()
                .to_degrees()
        })
        .fold(0.0, f32::max)
}

/// Angle in degrees between the rotations of two poses.
pub fn rotation_error_degrees(a: &Pose, b: &Pose) -> f32 {
    // trace(Ra^T Rb) = 1 + 2 cos(angle).
    let trace: f32 = (0..3).map(|c| dot(column(a, c), column(b, c))).sum();
    ((trace - 1.0) * 0.5).clamp(-1.0, 1.0).acos().to_degrees()
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
    fn fit_similarity_recovers_a_known_transform() {
        let truth = Similarity {
            rotation: rotation_between(normalize_or_zero([0.3, -0.5, 0.8]), [0.0, 0.0, 1.0]),
            translation: [0.5, -2.0, 1.0],
            scale: 0.37,
        };
        let from: Vec<V3> = (0..12)
            .map(|k| {
                let a = k as f32 * 0.7;
                [3.0 * a.cos(), 2.0 * a.sin(), (k % 3) as f32 - 1.0]
            })
            .collect();
        let to: Vec<V3> = from.iter().map(|&p| truth.apply_point(p)).collect();
        let (fit, rms) = fit_similarity(&from, &to);
        assert!(rms < 1e-5, "rms {rms}");
        assert!((fit.scale - 0.37).abs() < 1e-5);
        for r in 0..3 {
            for c in 0..3 {
                assert!((fit.rotation[r][c] - truth.rotation[r][c]).abs() < 1e-5);
            }
        }
        let pose = look_at([1.0, 2.0, 3.0], [0.0; 3], [0.0, 0.0, 1.0]);
        let turned = Similarity {
            rotation: rotation_between([1.0, 0.0, 0.0], normalize_or_zero([1.0, 0.1, 0.0])),
            ..Similarity::IDENTITY
        }
        .apply_pose(&pose);
        let angle = rotation_error_degrees(&pose, &turned);
        assert!((angle - 0.1f32.atan().to_degrees()).abs() < 1e-2, "{angle}");
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
        let both = to.after(&Similarity {
            scale: 2.0,
            ..Similarity::IDENTITY
        });
        let q = [0.3, -0.2, 0.5];
        let want = to.apply_point(scale(q, 2.0));
        assert!(length(sub(both.apply_point(q), want)) < 1e-5);
    }
}
