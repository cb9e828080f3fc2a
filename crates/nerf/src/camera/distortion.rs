//! Lens distortion of real cameras, and its inverse for casting rays.
//!
//! Coordinates are normalised image coordinates: `x = (u - cx) / fx`, `y = (v - cy) / fy`
//! with `v` growing downwards (OpenCV / COLMAP convention, before the flip to OpenGL axes).
//!
//! * [`LensModel::Opencv`]: radial `1 + k1 r^2 + k2 r^4 + k3 r^6 + k4 r^8` and tangential
//!   `p1, p2` (COLMAP's SIMPLE_RADIAL, RADIAL and OPENCV are special cases; `k4` is zero in
//!   all of them).
//! * [`LensModel::Fisheye`]: OpenCV's equidistant model, `theta_d = theta (1 + k1 theta^2 +
//!   k2 theta^4 + k3 theta^6 + k4 theta^8)` (COLMAP's OPENCV_FISHEYE).
//!
//! Rays need the inverse (distorted pixel -> undistorted direction), which has no closed
//! form: a few Newton steps from the distorted point converge to well below a pixel for
//! any real lens.

use serde::{Deserialize, Serialize};

#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LensModel {
    #[default]
    Opencv,
    Fisheye,
}

/// Distortion coefficients; all zero is an ideal pinhole.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Distortion {
    pub model: LensModel,
    /// Radial coefficients k1..k4.
    pub k: [f32; 4],
    /// Tangential coefficients p1, p2 (OpenCV model only).
    pub p: [f32; 2],
}

const NEWTON_STEPS: usize = 12;

impl Distortion {
    pub fn is_pinhole(&self) -> bool {
        self.k == [0.0; 4] && self.p == [0.0; 2]
    }

    /// Undistorted normalised point -> distorted normalised point.
    pub fn distort(&self, x: f32, y: f32) -> (f32, f32) {
        let (xd, yd) = self.distort64(x as f64, y as f64);
        (xd as f32, yd as f32)
    }

    fn distort64(&self, x: f64, y: f64) -> (f64, f64) {
        let [k1, k2, k3, k4] = self.k.map(f64::from);
        let [p1, p2] = self.p.map(f64::from);
        let r2 = x * x + y * y;
        match self.model {
            LensModel::Opencv => {
                let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * (k3 + r2 * k4)));
                (
                    x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
                    y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y,
                )
            }
            LensModel::Fisheye => {
                let r = r2.sqrt();
                if r < 1e-12 {
                    return (x, y);
                }
                let theta = r.atan();
                let t2 = theta * theta;
                let theta_d = theta * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))));
                (x * theta_d / r, y * theta_d / r)
            }
        }
    }

    /// Distorted normalised point -> undistorted normalised point (Newton's method on
    /// `distort(p) = target`, with a numerical Jacobian).
    pub fn undistort(&self, xd: f32, yd: f32) -> (f32, f32) {
        if self.is_pinhole() {
            return (xd, yd);
        }
        let (tx, ty) = (xd as f64, yd as f64);
        let (mut x, mut y) = (tx, ty);
        let h = 1e-7;
        for _ in 0..NEWTON_STEPS {
            let (fx, fy) = self.distort64(x, y);
            let (ex, ey) = (fx - tx, fy - ty);
            if ex.abs() < 1e-12 && ey.abs() < 1e-12 {
                break;
            }
            let (ax, ay) = self.distort64(x + h, y);
            let (bx, by) = self.distort64(x, y + h);
            let (j00, j10, j01, j11) = ((ax - fx) / h, (ay - fy) / h, (bx - fx) / h, (by - fy) / h);
            let det = j00 * j11 - j01 * j10;
            if det.abs() < 1e-12 {
                break;
            }
            x -= (j11 * ex - j01 * ey) / det;
            y -= (-j10 * ex + j00 * ey) / det;
        }
        (x as f32, y as f32)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn round_trip(d: Distortion) {
        for i in -8..=8 {
            for j in -8..=8 {
                let (x, y) = (i as f32 * 0.08, j as f32 * 0.08);
                let (xd, yd) = d.distort(x, y);
                let (xu, yu) = d.undistort(xd, yd);
                assert!(
                    (xu - x).abs() < 1e-5 && (yu - y).abs() < 1e-5,
                    "{d:?}: ({x}, {y}) -> ({xd}, {yd}) -> ({xu}, {yu})"
                );
            }
        }
    }

    #[test]
    fn undistort_inverts_distort() {
        // The fox capture's lens (instant-ngp sample data), a stronger barrel lens, and a
        // fisheye.
        round_trip(Distortion {
            model: LensModel::Opencv,
            k: [0.0578, -0.0805, 0.0, 0.0],
            p: [-0.00098, 0.000156],
        });
        round_trip(Distortion {
            model: LensModel::Opencv,
            k: [-0.25, 0.08, -0.01, 0.0],
            p: [0.001, -0.002],
        });
        round_trip(Distortion {
            model: LensModel::Fisheye,
            k: [0.05, -0.01, 0.002, 0.0],
            p: [0.0; 2],
        });
    }

    #[test]
    fn radial_distortion_moves_points_outwards() {
        let d = Distortion {
            model: LensModel::Opencv,
            k: [0.1, 0.0, 0.0, 0.0],
            p: [0.0; 2],
        };
        let (xd, yd) = d.distort(0.5, 0.0);
        assert!((xd - 0.5 * (1.0 + 0.1 * 0.25)).abs() < 1e-7 && yd == 0.0);
        assert_eq!(Distortion::default().undistort(0.3, -0.2), (0.3, -0.2));
    }
}
