//! Real spherical harmonics up to degree 4 (bands l = 0..3, 16 values) of a unit direction:
//! the fast field's view-direction encoding. They are an orthonormal basis of smooth
//! functions on the sphere, so the colour network gets view dependence without learning an
//! encoding. The backward ([`sh4_bwd`]) carries a gradient to the direction, for camera
//! refinement (a camera's rotation turns its rays).

/// Values per direction.
pub const SH_DIMS: usize = 16;

/// The 16 basis functions at unit direction `d`.
#[inline]
pub fn sh4(d: [f32; 3]) -> [f32; SH_DIMS] {
    let [x, y, z] = d;
    let (xx, yy, zz) = (x * x, y * y, z * z);
    [
        0.282_094_8,
        -0.488_602_5 * y,
        0.488_602_5 * z,
        -0.488_602_5 * x,
        1.092_548_4 * x * y,
        -1.092_548_4 * y * z,
        0.946_174_7 * zz - 0.315_391_57,
        -1.092_548_4 * x * z,
        0.546_274_2 * (xx - yy),
        0.590_043_6 * y * (yy - 3.0 * xx),
        2.890_611_4 * x * y * z,
        0.457_045_8 * y * (1.0 - 5.0 * zz),
        0.373_176_33 * z * (5.0 * zz - 3.0),
        0.457_045_8 * x * (1.0 - 5.0 * zz),
        1.445_305_7 * z * (xx - yy),
        0.590_043_6 * x * (3.0 * yy - xx),
    ]
}

/// `dL/d d` (the direction taken as a free 3-vector) from `dL/d sh4(d)`.
#[inline]
pub fn sh4_bwd(d: [f32; 3], g: &[f32]) -> [f32; 3] {
    let [x, y, z] = d;
    let (xx, yy, zz) = (x * x, y * y, z * z);
    let (a, b, c, e) = (0.488_602_5, 1.092_548_4, 0.946_174_7, 0.546_274_2);
    let (f, h, i, j, k) = (
        0.590_043_6,
        0.457_045_8,
        0.373_176_33,
        1.445_305_7,
        2.890_611_4,
    );
    // Rows: the partial derivatives (d/dx, d/dy, d/dz) of each basis function.
    let rows: [[f32; 3]; SH_DIMS] = [
        [0.0, 0.0, 0.0],
        [0.0, -a, 0.0],
        [0.0, 0.0, a],
        [-a, 0.0, 0.0],
        [b * y, b * x, 0.0],
        [0.0, -b * z, -b * y],
        [0.0, 0.0, 2.0 * c * z],
        [-b * z, 0.0, -b * x],
        [2.0 * e * x, -2.0 * e * y, 0.0],
        [-6.0 * f * x * y, 3.0 * f * (yy - xx), 0.0],
        [k * y * z, k * x * z, k * x * y],
        [0.0, h * (1.0 - 5.0 * zz), -10.0 * h * y * z],
        [0.0, 0.0, i * (15.0 * zz - 3.0)],
        [h * (1.0 - 5.0 * zz), 0.0, -10.0 * h * x * z],
        [2.0 * j * x * z, -2.0 * j * y * z, j * (xx - yy)],
        [3.0 * f * (yy - xx), 6.0 * f * x * y, 0.0],
    ];
    let mut out = [0.0f32; 3];
    for (row, &gk) in rows.iter().zip(g) {
        for a in 0..3 {
            out[a] += gk * row[a];
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn backward_matches_finite_differences() {
        let d = [0.3f32, -0.5, 0.81];
        let g: Vec<f32> = (0..SH_DIMS)
            .map(|k| ((k * 7 % 5) as f32 - 2.0) * 0.3)
            .collect();
        let analytic = sh4_bwd(d, &g);
        for a in 0..3 {
            let h = 1e-3;
            let (mut lo, mut hi) = (d, d);
            lo[a] -= h;
            hi[a] += h;
            let f = |v: [f32; 3]| {
                sh4(v)
                    .iter()
                    .zip(&g)
                    .map(|(y, g)| (y * g) as f64)
                    .sum::<f64>()
            };
            let fd = (f(hi) - f(lo)) / (2.0 * h as f64);
            assert!(
                (fd - analytic[a] as f64).abs() < 1e-3,
                "axis {a}: {fd} vs {}",
                analytic[a]
            );
        }
    }

    /// The basis is orthonormal: integrating `Y_i Y_j` over the sphere (Fibonacci lattice
    /// quadrature) gives the identity.
    #[test]
    fn basis_is_orthonormal_on_the_sphere() {
        let n = 20_000;
        let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
        let mut gram = [[0f64; SH_DIMS]; SH_DIMS];
        for k in 0..n {
            let z = 1.0 - (2.0 * k as f64 + 1.0) / n as f64;
            let r = (1.0 - z * z).sqrt();
            let phi = golden * k as f64;
            let y = sh4([(r * phi.cos()) as f32, (r * phi.sin()) as f32, z as f32]);
            for i in 0..SH_DIMS {
                for j in 0..SH_DIMS {
                    gram[i][j] += y[i] as f64 * y[j] as f64 * 4.0 * std::f64::consts::PI / n as f64;
                }
            }
        }
        for i in 0..SH_DIMS {
            for j in 0..SH_DIMS {
                let want = if i == j { 1.0 } else { 0.0 };
                assert!(
                    (gram[i][j] - want).abs() < 2e-3,
                    "<Y{i}, Y{j}> = {}",
                    gram[i][j]
                );
            }
        }
    }
}
