//! Real spherical harmonics up to degree 4 (bands l = 0..3, 16 values) of a unit direction:
//! the fast field's view-direction encoding. They are an orthonormal basis of smooth
//! functions on the sphere, so the colour network gets view dependence without learning an
//! encoding. Directions are not optimised, so there is no backward.

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

#[cfg(test)]
mod tests {
    use super::*;

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
