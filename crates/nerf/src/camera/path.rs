//! Camera paths for videos, besides [`orbit`](crate::camera::orbit): an LLFF-style
//! `spiral` around the average training camera, a smooth path `interpolate`d through the
//! training cameras, and nerfstudio's `camera_path.json` files.
//!
//! Poses are camera-to-world in OpenGL axes (x right, y up, looking down -z), as in the
//! Blender format.

use std::path::Path;

use serde::Deserialize;

use crate::camera::{look_at, Camera, Pose};
use crate::error::{NerfError, Result};
use crate::math::{add, cross, normalize_or_zero, scale, sub, V3};

fn column(p: &Pose, c: usize) -> V3 {
    [p[0][c], p[1][c], p[2][c]]
}

fn from_columns(x: V3, y: V3, z: V3, t: V3) -> Pose {
    std::array::from_fn(|r| [x[r], y[r], z[r], t[r]])
}

/// A spiral in front of the average training camera (the LLFF videos): `rotations` turns,
/// radii from the spread of the camera positions, always looking at the point `focus`
/// distance ahead of the average camera.
pub fn spiral(poses: &[Pose], frames: usize, rotations: f32) -> Vec<Pose> {
    let n = poses.len().max(1) as f32;
    let mean = |c: usize| {
        poses
            .iter()
            .fold([0.0; 3], |acc, p| add(acc, scale(column(p, c), 1.0 / n)))
    };
    let (centre, back, up) = (
        mean(3),
        normalize_or_zero(mean(2)),
        normalize_or_zero(mean(1)),
    );
    let right = normalize_or_zero(cross(up, back));
    let up = cross(back, right);
    // Radii: the 90th percentile of the cameras' offsets along the average axes.
    let radius = |axis: V3| {
        let mut d: Vec<f32> = poses
            .iter()
            .map(|p| crate::math::dot(sub(column(p, 3), centre), axis).abs())
            .collect();
        d.sort_by(f32::total_cmp);
        d.get((d.len().saturating_sub(1) as f32 * 0.9) as usize)
            .copied()
            .unwrap_or(0.0)
            .max(0.05)
    };
    let (rx, ry, rz) = (radius(right), radius(up), radius(back));
    // Look at the scene centre's depth along the viewing axis (objects sit at the origin).
    let focus = crate::math::dot(centre, back).abs().max(0.5);
    let target = sub(centre, scale(back, focus));
    (0..frames)
        .map(|k| {
            let theta = std::f32::consts::TAU * rotations * k as f32 / frames.max(1) as f32;
            let offset = add(
                add(scale(right, rx * theta.cos()), scale(up, -ry * theta.sin())),
                scale(back, -rz * 0.5 * (theta * 0.5).sin()),
            );
            look_at(add(centre, offset), target, up)
        })
        .collect()
}

/// Unit quaternion `[w, x, y, z]` of a pose's rotation.
fn quaternion(p: &Pose) -> [f32; 4] {
    let m = |r: usize, c: usize| p[r][c];
    let trace = m(0, 0) + m(1, 1) + m(2, 2);
    let q = if trace > 0.0 {
        let s = (trace + 1.0).sqrt() * 2.0;
        [
            0.25 * s,
            (m(2, 1) - m(1, 2)) / s,
            (m(0, 2) - m(2, 0)) / s,
            (m(1, 0) - m(0, 1)) / s,
        ]
    } else if m(0, 0) > m(1, 1) && m(0, 0) > m(2, 2) {
        let s = (1.0 + m(0, 0) - m(1, 1) - m(2, 2)).sqrt() * 2.0;
        [
            (m(2, 1) - m(1, 2)) / s,
            0.25 * s,
            (m(0, 1) + m(1, 0)) / s,
            (m(0, 2) + m(2, 0)) / s,
        ]
    } else if m(1, 1) > m(2, 2) {
        let s = (1.0 + m(1, 1) - m(0, 0) - m(2, 2)).sqrt() * 2.0;
        [
            (m(0, 2) - m(2, 0)) / s,
            (m(0, 1) + m(1, 0)) / s,
            0.25 * s,
            (m(1, 2) + m(2, 1)) / s,
        ]
    } else {
        let s = (1.0 + m(2, 2) - m(0, 0) - m(1, 1)).sqrt() * 2.0;
        [
            (m(1, 0) - m(0, 1)) / s,
            (m(0, 2) + m(2, 0)) / s,
            (m(1, 2) + m(2, 1)) / s,
            0.25 * s,
        ]
    };
    let l = q.iter().map(|v| v * v).sum::<f32>().sqrt();
    q.map(|v| v / l)
}

fn rotation(q: [f32; 4]) -> [V3; 3] {
    let [w, x, y, z] = q;
    let x_axis = [
        1.0 - 2.0 * (y * y + z * z),
        2.0 * (x * y + w * z),
        2.0 * (x * z - w * y),
    ];
    let y_axis = [
        2.0 * (x * y - w * z),
        1.0 - 2.0 * (x * x + z * z),
        2.0 * (y * z + w * x),
    ];
    let z_axis = [
        2.0 * (x * z + w * y),
        2.0 * (y * z - w * x),
        1.0 - 2.0 * (x * x + y * y),
    ];
    [x_axis, y_axis, z_axis]
}

fn slerp(a: [f32; 4], mut b: [f32; 4], t: f32) -> [f32; 4] {
    let mut dot: f32 = a.iter().zip(&b).map(|(x, y)| x * y).sum();
    if dot < 0.0 {
        b = b.map(|v| -v);
        dot = -dot;
    }
    let (wa, wb) = if dot > 0.9995 {
        (1.0 - t, t)
    } else {
        let theta = dot.clamp(-1.0, 1.0).acos();
        let s = theta.sin();
        (((1.0 - t) * theta).sin() / s, (t * theta).sin() / s)
    };
    let q: [f32; 4] = std::array::from_fn(|i| wa * a[i] + wb * b[i]);
    let l = q.iter().map(|v| v * v).sum::<f32>().sqrt();
    q.map(|v| v / l)
}

/// The pose a fraction `t` of the way from `a` to `b`: rotations by slerp, positions
/// along the straight line between them, or, with `orbit`, at the interpolated distance
/// from the world origin along the interpolated direction (cameras around an object: the
/// straight line would cut inside their sphere, closer than any photo was taken).
pub fn pose_between(a: &Pose, b: &Pose, t: f32, orbit: bool) -> Pose {
    let (pa, pb) = (column(a, 3), column(b, 3));
    let line = add(scale(pa, 1.0 - t), scale(pb, t));
    let pos = if orbit {
        let radius = (1.0 - t) * crate::math::length(pa) + t * crate::math::length(pb);
        scale(normalize_or_zero(line), radius)
    } else {
        line
    };
    let [x, y, z] = rotation(slerp(quaternion(a), quaternion(b), t));
    from_columns(x, y, z, pos)
}

/// A closed, smooth path through `keys` training cameras (taken evenly from `poses` and
/// ordered by azimuth around the up axis so the loop does not zigzag): positions by
/// Catmull-Rom splines, which pass through every key, rotations by slerp.
pub fn interpolate(poses: &[Pose], keys: usize, frames: usize) -> Vec<Pose> {
    if poses.is_empty() || frames == 0 {
        return Vec::new();
    }
    let step = (poses.len() as f32 / keys.clamp(2, poses.len()) as f32).max(1.0);
    let mut key: Vec<Pose> = (0..keys.clamp(2, poses.len()))
        .map(|k| poses[((k as f32 * step) as usize).min(poses.len() - 1)])
        .collect();
    key.sort_by(|a, b| {
        let az = |p: &Pose| p[1][3].atan2(p[0][3]);
        az(a).total_cmp(&az(b))
    });
    through_keyframes(&key, frames, true)
}

/// `frames` poses along a smooth path through `keys` in their order: positions by
/// Catmull-Rom splines (through every key), rotations by slerp; `closed` returns to the
/// first key (the frames then span the loop, the last one short of the start), an open
/// path ends on the last key. Frame `f` sits at path parameter [`path_parameter`].
pub fn through_keyframes(keys: &[Pose], frames: usize, closed: bool) -> Vec<Pose> {
    let n = keys.len();
    if n == 0 || frames == 0 {
        return Vec::new();
    }
    // Neighbours past an open path's ends repeat the end key.
    let key = |i: isize| -> &Pose {
        if closed {
            &keys[i.rem_euclid(n as isize) as usize]
        } else {
            &keys[i.clamp(0, n as isize - 1) as usize]
        }
    };
    (0..frames)
        .map(|f| {
            let (i, t) = path_parameter(f, frames, n, closed);
            let i = i as isize;
            let p = |k: isize| column(key(i + k), 3);
            let (p0, p1, p2, p3) = (p(-1), p(0), p(1), p(2));
            let pos: V3 = std::array::from_fn(|c| {
                0.5 * (2.0 * p1[c]
                    + (p2[c] - p0[c]) * t
                    + (2.0 * p0[c] - 5.0 * p1[c] + 4.0 * p2[c] - p3[c]) * t * t
                    + (3.0 * p1[c] - p0[c] - 3.0 * p2[c] + p3[c]) * t * t * t)
            });
            let q = slerp(quaternion(key(i)), quaternion(key(i + 1)), t);
            let [x, y, z] = rotation(q);
            from_columns(x, y, z, pos)
        })
        .collect()
}

/// Which segment frame `f` of `frames` falls in on a path through `keys` keys, and how
/// far along it (0..1): what [`through_keyframes`] uses, for interpolating anything else
/// that keyframes carry (a field of view).
pub fn path_parameter(f: usize, frames: usize, keys: usize, closed: bool) -> (usize, f32) {
    let segments = if closed { keys } else { keys.saturating_sub(1) };
    if segments == 0 {
        return (0, 0.0);
    }
    let u = if closed || frames < 2 {
        f as f32 / frames as f32 * segments as f32
    } else {
        f as f32 / (frames - 1) as f32 * segments as f32
    };
    let i = (u.floor() as usize).min(segments - 1);
    (i, (u - i as f32).clamp(0.0, 1.0))
}

#[derive(Deserialize)]
struct PathFile {
    render_width: Option<usize>,
    render_height: Option<usize>,
    /// nerfstudio: `perspective`, `fisheye` or `equirectangular`.
    camera_type: Option<String>,
    camera_path: Option<Vec<PathFrame>>,
}

#[derive(Deserialize)]
struct PathFrame {
    /// Camera-to-world: row-major 16 values, or nested 4x4 (or 3x4) rows.
    camera_to_world: Matrix,
    /// Vertical field of view in degrees.
    fov: f32,
    aspect: Option<f32>,
    camera_type: Option<String>,
    /// Moving scenes: the moment in [0, 1] the frame shows.
    time: Option<f32>,
}

#[derive(Deserialize)]
#[serde(untagged)]
enum Matrix {
    Flat(Vec<f32>),
    Nested(Vec<Vec<f32>>),
}

impl Matrix {
    fn pose(&self) -> std::result::Result<Pose, String> {
        let rows: Vec<Vec<f32>> = match self {
            Matrix::Flat(v) if v.len() == 16 || v.len() == 12 => {
                v.chunks(4).map(<[f32]>::to_vec).collect()
            }
            Matrix::Flat(v) => {
                return Err(format!(
                    "camera_to_world has {} values, expected 16",
                    v.len()
                ))
            }
            Matrix::Nested(rows) => rows.clone(),
        };
        super::pose_from_rows(&rows).map_err(|m| m.replace("the matrix", "camera_to_world"))
    }
}

/// The moments of a camera path's frames (each frame's optional `time`, in [0, 1]: paths
/// through a moving scene), one per frame of [`load_camera_path`].
pub fn load_camera_path_times(path: &Path) -> Result<Vec<Option<f32>>> {
    let file: PathFile = crate::io::read_json(path)?;
    let frames = file.camera_path.unwrap_or_default();
    for (k, f) in frames.iter().enumerate() {
        if let Some(t) = f.time.filter(|t| !(0.0..=1.0).contains(t)) {
            return Err(NerfError::Format {
                path: path.to_path_buf(),
                message: format!("camera_path[{k}].time {t} is not a moment in [0, 1]"),
            });
        }
    }
    Ok(frames.iter().map(|f| f.time).collect())
}

/// The cameras of a nerfstudio `camera_path.json` (its per-frame `camera_path` list: a
/// 4x4 `camera_to_world`, flat row-major or nested, vertical `fov` in degrees, `aspect`),
/// at the file's `render_width` x `render_height` (a frame's `aspect` is used only when the
/// file gives no size); `size` overrides the height, keeping the aspect. Only perspective
/// paths are rendered: fisheye and equirectangular ones are refused by name.
pub fn load_camera_path(path: &Path, size: Option<usize>) -> Result<Vec<Camera>> {
    let file: PathFile = crate::io::read_json(path)?;
    let bad = |m: String| NerfError::Format {
        path: path.to_path_buf(),
        message: m,
    };
    let frames = file.camera_path.as_ref().ok_or_else(|| {
        bad("no `camera_path` list (export the path from the viewer first)".into())
    })?;
    if frames.is_empty() {
        return Err(bad(
            "the `camera_path` list is empty: no frames to render".into()
        ));
    }
    let file_aspect = match (file.render_width, file.render_height) {
        (Some(w), Some(h)) if w > 0 && h > 0 => Some(w as f32 / h as f32),
        (Some(_), Some(_)) => {
            return Err(bad("render_width and render_height must be positive".into()))
        }
        _ => None,
    };
    let height = size.or(file.render_height).unwrap_or(400).max(1);
    frames
        .iter()
        .enumerate()
        .map(|(k, f)| {
            let kind = f.camera_type.as_deref().or(file.camera_type.as_deref());
            if let Some(kind) = kind.filter(|t| !t.eq_ignore_ascii_case("perspective")) {
                return Err(bad(format!(
                    "camera_path[{k}] is a {kind} camera; only perspective paths are \
                     rendered (set the camera type to perspective in the viewer and export again)"
                )));
            }
            let pose = f
                .camera_to_world
                .pose()
                .map_err(|m| bad(format!("camera_path[{k}]: {m}")))?;
            if !(f.fov > 0.0 && f.fov < 180.0) {
                return Err(bad(format!(
                    "camera_path[{k}].fov {} is not in (0, 180)",
                    f.fov
                )));
            }
            let aspect = file_aspect.or(f.aspect).unwrap_or(1.0);
            if !(aspect.is_finite() && aspect > 0.0) {
                return Err(bad(format!(
                    "camera_path[{k}].aspect {aspect} must be a positive number"
                )));
            }
            let width = (height as f64 * aspect as f64).round().max(1.0);
            let width = if width > usize::MAX as f64 {
                usize::MAX
            } else {
                width as usize
            };
            super::check_image_size(width, height)
                .map_err(|m| bad(format!("camera_path[{k}]: {m}")))?;
            let fov_x = 2.0 * (aspect * (f.fov.to_radians() / 2.0).tan()).atan();
            Ok(Camera::from_fov_x(width, height, fov_x, pose))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::orbit;
    use crate::math::length;

    /// The largest distance between consecutive positions of a path.
    fn largest_step(poses: &[Pose]) -> f32 {
        poses
            .windows(2)
            .map(|w| length(sub(column(&w[1], 3), column(&w[0], 3))))
            .fold(0.0, f32::max)
    }

    /// An open path starts on its first key, ends on its last and passes through the
    /// ones between, in the order given.
    #[test]
    fn open_paths_run_through_their_keys_in_order() {
        let keys: Vec<Pose> = [
            [3.0, 0.0, 1.0],
            [0.0, 3.0, 1.5],
            [-3.0, 0.0, 1.0],
            [0.0, -3.0, 0.5],
        ]
        .iter()
        .map(|&eye| crate::camera::look_at(eye, [0.0; 3], [0.0, 0.0, 1.0]))
        .collect();
        let frames = through_keyframes(&keys, 7, false);
        assert_eq!(frames.len(), 7);
        for (f, k) in [(0, 0), (2, 1), (4, 2), (6, 3)] {
            for r in 0..3 {
                for c in 0..4 {
                    assert!(
                        (frames[f][r][c] - keys[k][r][c]).abs() < 1e-4,
                        "frame {f} vs key {k}: {:?} {:?}",
                        frames[f],
                        keys[k]
                    );
                }
            }
        }
        assert_eq!(path_parameter(6, 7, 4, false), (2, 1.0));
        assert_eq!(path_parameter(3, 8, 4, true), (1, 0.5));
    }

    #[test]
    fn poses_between_two_cameras_run_from_one_to_the_other() {
        let a = look_at([4.0, 0.0, 1.0], [0.0; 3], [0.0, 0.0, 1.0]);
        let b = look_at([0.0, 4.0, 1.0], [0.0; 3], [0.0, 0.0, 1.0]);
        let close = |p: &Pose, q: &Pose| {
            p.iter()
                .flatten()
                .zip(q.iter().flatten())
                .all(|(x, y)| (x - y).abs() < 1e-5)
        };
        for orbit in [false, true] {
            assert!(close(&pose_between(&a, &b, 0.0, orbit), &a));
            assert!(close(&pose_between(&a, &b, 1.0, orbit), &b));
        }
        // Halfway around the orbit: as far out as both, and still facing the centre.
        let half = pose_between(&a, &b, 0.5, true);
        let radius = crate::math::length(column(&a, 3));
        assert!((crate::math::length(column(&half, 3)) - radius).abs() < 1e-4);
        let towards = normalize_or_zero(scale(column(&half, 3), -1.0));
        let looking = scale(column(&half, 2), -1.0);
        assert!(crate::math::dot(towards, looking) > 0.99);
        // On the straight line it is inside the orbit.
        let line = pose_between(&a, &b, 0.5, false);
        assert!(crate::math::length(column(&line, 3)) < radius - 0.5);
    }

    #[test]
    fn quaternions_round_trip_rotations() {
        for p in orbit(7, 4.0, 0.5) {
            let [x, y, z] = rotation(quaternion(&p));
            for (a, c) in [x, y, z].iter().zip(0..3) {
                let want = column(&p, c);
                assert!(length(sub(*a, want)) < 1e-4, "{a:?} vs {want:?}");
            }
        }
    }

    #[test]
    fn interpolation_passes_through_its_keys_smoothly() {
        let poses = orbit(12, 4.0, 0.4);
        let path = interpolate(&poses, 6, 60);
        assert_eq!(path.len(), 60);
        // Every 10th frame is a key camera (pose and position).
        let keys: Vec<V3> = (0..6).map(|k| column(&poses[2 * k], 3)).collect();
        for f in (0..60).step_by(10) {
            let p = column(&path[f], 3);
            assert!(
                keys.iter().any(|k| length(sub(*k, p)) < 1e-4),
                "frame {f} at {p:?}"
            );
        }
        // Small steps: about the circumference over 60 frames.
        let circumference = std::f32::consts::TAU * 4.0 * 0.4f32.cos();
        assert!(largest_step(&path) < 2.0 * circumference / 60.0);
    }

    #[test]
    fn spiral_stays_near_the_cameras_and_faces_the_scene() {
        let poses: Vec<Pose> = (0..9)
            .map(|k| {
                let x = (k % 3) as f32 * 0.3 - 0.3;
                let y = (k / 3) as f32 * 0.2 - 0.2;
                look_at([x, -4.0, y], [0.0; 3], [0.0, 0.0, 1.0])
            })
            .collect();
        let path = spiral(&poses, 40, 2.0);
        for p in &path {
            let pos = column(p, 3);
            assert!(length(sub(pos, [0.0, -4.0, 0.0])) < 1.0, "{pos:?}");
            // Looking along -z of the camera: towards +y, where the scene is.
            assert!(column(p, 2)[1] < -0.9);
        }
        assert!(largest_step(&path) < 0.2);
    }

    #[test]
    fn nerfstudio_camera_path_loads_and_bad_files_name_the_problem() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("camera_path.json");
        let pose = look_at([0.0, -4.0, 1.0], [0.0; 3], [0.0, 0.0, 1.0]);
        let flat: Vec<f32> = pose
            .iter()
            .flat_map(|r| r.iter().copied())
            .chain([0.0, 0.0, 0.0, 1.0])
            .collect();
        let json = serde_json::json!({
            "render_width": 64, "render_height": 48, "fps": 24,
            "camera_path": [{"camera_to_world": flat, "fov": 50.0, "aspect": 4.0 / 3.0}]
        });
        std::fs::write(&path, json.to_string()).expect("write");
        let cams = load_camera_path(&path, None).expect("load");
        assert_eq!((cams.len(), cams[0].width, cams[0].height), (1, 64, 48));
        assert_eq!(cams[0].c2w, pose);
        // Vertical fov 50 degrees: fy = 24 / tan(25 deg).
        assert!((cams[0].fy - 24.0 / 25f32.to_radians().tan()).abs() < 1e-2);
        std::fs::write(
            &path,
            r#"{"camera_path": [{"camera_to_world": [1, 2], "fov": 50}]}"#,
        )
        .expect("write");
        let err = load_camera_path(&path, None).expect_err("short matrix");
        assert!(
            err.to_string().contains("camera_to_world has 2 values"),
            "{err}"
        );
        assert!(err.to_string().contains("camera_path.json"), "{err}");
    }
}
