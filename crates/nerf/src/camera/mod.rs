//! Pinhole cameras in the Blender / OpenGL convention and the rays they cast.
//!
//! A pose is camera-to-world: the camera looks down its own -Z axis, +Y is up, +X right.
//! Pixel (i, j) (column, row) has camera-space direction
//! `((i + 0.5 - cx) / fx, -(j + 0.5 - cy) / fy, -1)`, rotated into the world by the pose.
//! Real lenses are undistorted first (see [`crate::camera::distortion`]).
//! Directions are *not* normalised, so the marching parameter `t` is depth along -Z.
//!
//! Beside the pinhole model: [`distortion`] (real lenses), [`ray_space`] (where rays are
//! marched: world or NDC), and [`path`] (camera paths for videos).

pub mod distortion;
pub mod footprint;
pub mod path;
pub mod ray_space;

use crate::camera::distortion::Distortion;
use crate::math::{cross, normalize_or_zero, scale, sub, V3};

/// Camera-to-world transform: rotation columns are the camera's X, Y, Z axes in the world.
pub type Pose = [[f32; 4]; 3];

/// How far a pose's rotation may be from orthonormal (largest entry of `R^T R - I`) and
/// still be taken as a rotation. Real exports (Blender, COLMAP, instant-ngp, nerfstudio)
/// are orthonormal to about 1e-6; 1e-2 leaves room for matrices printed with few digits.
pub const ROTATION_TOLERANCE: f32 = 1e-2;
/// Camera positions beyond this distance from the origin are a broken export, not a scene.
pub const MAX_POSITION: f32 = 1e6;

/// Checks that a camera-to-world matrix is a rotation and a finite, sensible position.
pub fn check_pose(pose: &Pose) -> Result<(), String> {
    if pose.iter().flatten().any(|v| !v.is_finite()) {
        return Err("the pose has a non-finite entry".into());
    }
    let col = |c: usize| [pose[0][c], pose[1][c], pose[2][c]];
    let mut worst = 0.0f32;
    for a in 0..3 {
        for b in 0..3 {
            let d = crate::math::dot(col(a), col(b)) - if a == b { 1.0 } else { 0.0 };
            worst = worst.max(d.abs());
        }
    }
    let det = crate::math::dot(col(0), cross(col(1), col(2)));
    if worst > ROTATION_TOLERANCE || det < 0.0 {
        return Err(format!(
            "the pose's 3x3 part is not a rotation (columns off orthonormal by {worst:.3}, \
             determinant {det:.3}); camera-to-world matrices must be rotation + translation"
        ));
    }
    let distance = crate::math::length(col(3));
    if distance > MAX_POSITION {
        return Err(format!(
            "the camera sits {distance:e} units from the origin (more than {MAX_POSITION:e})"
        ));
    }
    Ok(())
}

/// The largest image side rendered, in pixels.
pub const MAX_IMAGE_SIDE: usize = 16384;

/// Refuses image sizes that cannot be rendered (zero) or would not fit in memory, saying
/// the limit and what the size would need (RGB, depth and opacity: 5 floats per pixel).
pub fn check_image_size(width: usize, height: usize) -> std::result::Result<(), String> {
    if width == 0 || height == 0 {
        return Err(format!("a {width}x{height} image has no pixels"));
    }
    if width > MAX_IMAGE_SIDE || height > MAX_IMAGE_SIDE {
        let bytes = width as f64 * height as f64 * 5.0 * 4.0;
        return Err(format!(
            "a {width}x{height} image is larger than the limit of {MAX_IMAGE_SIDE} pixels a \
             side (it would need {:.1} GiB for its buffers alone)",
            bytes / f64::from(1u32 << 30)
        ));
    }
    Ok(())
}

/// A camera-to-world pose from the rows of a 4x4 (or 3x4) matrix, checked (see
/// [`check_pose`]).
pub fn pose_from_rows(m: &[Vec<f32>]) -> Result<Pose, String> {
    let pose = pose_from_rows_unchecked(m)?;
    check_pose(&pose)?;
    Ok(pose)
}

/// Divides a uniform scale out of a pose's 3x3 part (some exporters multiply the rotation
/// by a scene's `scale_factor`): when its three columns are orthogonal and of one length
/// other than 1, returns that length and leaves a rotation. Anything else (reflections,
/// shears, columns of different lengths) is left for [`check_pose`] to refuse.
pub fn remove_uniform_scale(pose: &mut Pose) -> Option<f32> {
    let col = |p: &Pose, c: usize| [p[0][c], p[1][c], p[2][c]];
    let lengths = [0, 1, 2].map(|c| crate::math::length(col(pose, c)));
    let mean = lengths.iter().sum::<f32>() / 3.0;
    let uniform = lengths.iter().all(|l| (l - mean).abs() <= 1e-3 * mean);
    if !(uniform && mean.is_finite() && mean > 1e-6) || (mean - 1.0).abs() <= ROTATION_TOLERANCE {
        return None;
    }
    let mut scaled = *pose;
    for row in scaled.iter_mut() {
        for v in row.iter_mut().take(3) {
            *v /= mean;
        }
    }
    check_pose(&scaled).ok()?;
    *pose = scaled;
    Some(mean)
}

/// The rows of a 4x4 (or 3x4) matrix as a pose, its shape and finiteness checked but not
/// whether its 3x3 part is a rotation.
pub fn pose_from_rows_unchecked(m: &[Vec<f32>]) -> Result<Pose, String> {
    if !(m.len() == 4 || m.len() == 3) || m.iter().any(|row| row.len() != 4) {
        let shape: Vec<usize> = m.iter().map(|r| r.len()).collect();
        return Err(format!(
            "the matrix must be 4x4, got rows of lengths {shape:?}"
        ));
    }
    if m.iter().flatten().any(|v| !v.is_finite()) {
        return Err("the matrix has a non-finite entry".into());
    }
    let mut pose = [[0.0; 4]; 3];
    for (r, row) in pose.iter_mut().enumerate() {
        row.copy_from_slice(&m[r]);
    }
    Ok(pose)
}

/// One camera: image size, intrinsics and pose.
#[derive(Clone, Debug, PartialEq)]
pub struct Camera {
    pub width: usize,
    pub height: usize,
    pub fx: f32,
    pub fy: f32,
    pub cx: f32,
    pub cy: f32,
    pub c2w: Pose,
    /// Lens distortion of the image (none for synthetic scenes).
    pub distortion: Distortion,
}

/// A ray `o + t d`, with `d` unnormalised (see the module docs).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Ray {
    pub origin: V3,
    pub dir: V3,
}

impl Camera {
    /// A camera with square pixels and the principal point in the image centre, from the
    /// horizontal field of view (Blender's `camera_angle_x`): `f = 0.5 W / tan(0.5 fov)`.
    pub fn from_fov_x(width: usize, height: usize, fov_x: f32, c2w: Pose) -> Camera {
        let f = 0.5 * width as f32 / (0.5 * fov_x).tan();
        Camera {
            width,
            height,
            fx: f,
            fy: f,
            cx: 0.5 * width as f32,
            cy: 0.5 * height as f32,
            c2w,
            distortion: Distortion::default(),
        }
    }

    /// The same view at `1/factor` of the resolution (intrinsics scaled to match).
    pub fn downscaled(&self, factor: usize) -> Camera {
        let s = 1.0 / factor as f32;
        Camera {
            width: self.width / factor,
            height: self.height / factor,
            fx: self.fx * s,
            fy: self.fy * s,
            cx: self.cx * s,
            cy: self.cy * s,
            c2w: self.c2w,
            distortion: self.distortion,
        }
    }

    pub fn origin(&self) -> V3 {
        [self.c2w[0][3], self.c2w[1][3], self.c2w[2][3]]
    }

    /// The vertical field of view, in degrees.
    pub fn fov_y_degrees(&self) -> f32 {
        (2.0 * (0.5 * self.height as f32 / self.fy).atan()).to_degrees()
    }

    /// Where the world point `p` lands in the image, pinhole (lens distortion aside):
    /// `(x, y, depth)`, in pixels from the top-left corner and in units along the camera's
    /// axis; the inverse of [`ray_at`](Self::ray_at) for points in front of the camera
    /// (depth > 0; behind it the pixel is meaningless).
    pub fn project(&self, p: V3) -> (f32, f32, f32) {
        let m = &self.c2w;
        let rel = sub(p, self.origin());
        let axis = |c: usize| rel[0] * m[0][c] + rel[1] * m[1][c] + rel[2] * m[2][c];
        let depth = -axis(2);
        (
            self.fx * axis(0) / depth + self.cx,
            -self.fy * axis(1) / depth + self.cy,
            depth,
        )
    }

    /// Whether the point `p`, widened by `size` around it, lies in front of the camera
    /// and inside its image (pinhole projection; lens distortion is ignored, which only
    /// moves the border a little).
    pub fn frames(&self, p: V3, size: f32) -> bool {
        let (x, y, depth) = self.project(p);
        if depth <= 0.0 {
            return false;
        }
        let margin = self.fx.max(self.fy) * size / depth;
        x >= -margin
            && x <= self.width as f32 + margin
            && y >= -margin
            && y <= self.height as f32 + margin
    }

    /// The ray through the centre of pixel (column `i`, row `j`).
    #[inline]
    pub fn ray(&self, i: usize, j: usize) -> Ray {
        self.ray_at(i as f32 + 0.5, j as f32 + 0.5)
    }

    /// The ray through the continuous image point (x, y), in pixels from the top-left corner.
    #[inline]
    pub fn ray_at(&self, x: f32, y: f32) -> Ray {
        let (u, v) = self
            .distortion
            .undistort((x - self.cx) / self.fx, (y - self.cy) / self.fy);
        let d_cam = [u, -v, -1.0];
        let m = &self.c2w;
        let dir = [
            m[0][0] * d_cam[0] + m[0][1] * d_cam[1] + m[0][2] * d_cam[2],
            m[1][0] * d_cam[0] + m[1][1] * d_cam[1] + m[1][2] * d_cam[2],
            m[2][0] * d_cam[0] + m[2][1] * d_cam[1] + m[2][2] * d_cam[2],
        ];
        Ray {
            origin: self.origin(),
            dir,
        }
    }
}

/// A pose at `eye` looking at `target`, with `up` (world) pointing roughly up in the image.
pub fn look_at(eye: V3, target: V3, up: V3) -> Pose {
    let z = normalize_or_zero(sub(eye, target)); // camera looks down -Z
    let x = normalize_or_zero(cross(up, z));
    let y = cross(z, x);
    [
        [x[0], y[0], z[0], eye[0]],
        [x[1], y[1], z[1], eye[1]],
        [x[2], y[2], z[2], eye[2]],
    ]
}

/// A point on a sphere around the origin: azimuth around +Z, elevation above the XY plane
/// (both in radians), Blender's Z-up world.
pub fn spherical(radius: f32, azimuth: f32, elevation: f32) -> V3 {
    scale(
        [
            elevation.cos() * azimuth.cos(),
            elevation.cos() * azimuth.sin(),
            elevation.sin(),
        ],
        radius,
    )
}

/// `frames` poses on a circle around the origin at a fixed elevation, looking at the origin:
/// the paper's 360-degree videos.
pub fn orbit(frames: usize, radius: f32, elevation: f32) -> Vec<Pose> {
    (0..frames)
        .map(|k| {
            let az = std::f32::consts::TAU * k as f32 / frames as f32;
            look_at(spherical(radius, az, elevation), [0.0; 3], [0.0, 0.0, 1.0])
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::{dot, length};

    #[test]
    fn centre_ray_points_at_target() {
        let eye = [3.0, 1.0, 2.0];
        let cam = Camera::from_fov_x(100, 80, 0.7, look_at(eye, [0.0; 3], [0.0, 0.0, 1.0]));
        let r = cam.ray_at(50.0, 40.0);
        let to_target = normalize_or_zero(scale(eye, -1.0));
        assert!((dot(normalize_or_zero(r.dir), to_target) - 1.0).abs() < 1e-6);
        // Unnormalised: the centre ray has unit length (z component -1 in camera space).
        assert!((length(r.dir) - 1.0).abs() < 1e-6);
        assert_eq!(r.origin, eye);
    }

    #[test]
    fn projecting_a_point_on_a_pixels_ray_gives_back_the_pixel() {
        let cam = Camera::from_fov_x(
            100,
            80,
            0.7,
            look_at([3.0, 1.0, 2.0], [0.0; 3], [0.0, 0.0, 1.0]),
        );
        for (x, y) in [(50.0, 40.0), (3.5, 77.25), (99.0, 0.5)] {
            let r = cam.ray_at(x, y);
            let p = [0, 1, 2].map(|a| r.origin[a] + 2.5 * r.dir[a]);
            let (px, py, depth) = cam.project(p);
            assert!(
                (px - x).abs() < 1e-3 && (py - y).abs() < 1e-3,
                "{x},{y}: {px},{py}"
            );
            // The ray's direction has unit length along the axis (z = -1 in camera space).
            assert!((depth - 2.5).abs() < 1e-4, "{depth}");
        }
        assert!(cam.project([6.0, 2.0, 4.0]).2 < 0.0, "behind the camera");
    }

    #[test]
    fn image_up_is_world_up_and_right_is_right() {
        let cam = Camera::from_fov_x(
            100,
            100,
            0.7,
            look_at([0.0, -4.0, 0.0], [0.0; 3], [0.0, 0.0, 1.0]),
        );
        let top = cam.ray_at(50.0, 0.0).dir;
        let right = cam.ray_at(100.0, 50.0).dir;
        assert!(top[2] > 0.0, "row 0 looks up: {top:?}");
        assert!(
            right[0] > 0.0,
            "last column looks right (+X from -Y): {right:?}"
        );
    }

    #[test]
    fn focal_from_fov() {
        let cam = Camera::from_fov_x(
            800,
            800,
            0.6911112,
            look_at([0.0, 0.0, 4.0], [0.0; 3], [0.0, 1.0, 0.0]),
        );
        assert!((cam.fx - 1111.111).abs() < 0.01, "{}", cam.fx);
        let half = cam.downscaled(2);
        assert_eq!(half.width, 400);
        assert!((half.fx - 555.5555).abs() < 0.01);
        // The same world point maps to the same ray at both resolutions.
        let a = normalize_or_zero(cam.ray_at(200.0, 300.0).dir);
        let b = normalize_or_zero(half.ray_at(100.0, 150.0).dir);
        assert!((dot(a, b) - 1.0).abs() < 1e-6);
    }

    #[test]
    fn orbit_stays_on_circle() {
        for p in orbit(12, 4.0, 0.5) {
            let o = [p[0][3], p[1][3], p[2][3]];
            assert!((length(o) - 4.0).abs() < 1e-5);
            assert!((o[2] - 4.0 * 0.5f32.sin()).abs() < 1e-5);
        }
    }
}
