//! The view direction's spherical harmonics on the GPU, shared by the fast field's layer
//! path (`field`) and its one-kernel inference (`fused`).

use cubecl::prelude::*;

/// The 16 spherical harmonics of the unit direction `(x, y, z)`, as
/// `encoding::spherical_harmonics::sh4`.
#[cube]
pub fn sh4(x: f32, y: f32, z: f32) -> Array<f32> {
    let xx = x * x;
    let yy = y * y;
    let zz = z * z;
    let mut sh = Array::<f32>::new(16usize);
    sh[0] = 0.282_094_8f32;
    sh[1] = 0.0f32 - 0.488_602_5f32 * y;
    sh[2] = 0.488_602_5f32 * z;
    sh[3] = 0.0f32 - 0.488_602_5f32 * x;
    sh[4] = 1.092_548_4f32 * x * y;
    sh[5] = 0.0f32 - 1.092_548_4f32 * y * z;
    sh[6] = 0.946_174_7f32 * zz - 0.315_391_57f32;
    sh[7] = 0.0f32 - 1.092_548_4f32 * x * z;
    sh[8] = 0.546_274_2f32 * (xx - yy);
    sh[9] = 0.590_043_6f32 * y * (yy - 3.0f32 * xx);
    sh[10] = 2.890_611_4f32 * x * y * z;
    sh[11] = 0.457_045_8f32 * y * (1.0f32 - 5.0f32 * zz);
    sh[12] = 0.373_176_33f32 * z * (5.0f32 * zz - 3.0f32);
    sh[13] = 0.457_045_8f32 * x * (1.0f32 - 5.0f32 * zz);
    sh[14] = 1.445_305_7f32 * z * (xx - yy);
    sh[15] = 0.590_043_6f32 * x * (3.0f32 * yy - xx);
    sh
}

/// The `k`-th of [`sh4`]'s harmonics alone, for kernels that give each output its own
/// thread (neighbouring threads then write neighbouring values).
#[cube]
pub fn sh4_at(k: usize, x: f32, y: f32, z: f32) -> f32 {
    let xx = x * x;
    let yy = y * y;
    let zz = z * z;
    let mut v = 0.282_094_8f32;
    if k == 1 {
        v = 0.0f32 - 0.488_602_5f32 * y;
    } else if k == 2 {
        v = 0.488_602_5f32 * z;
    } else if k == 3 {
        v = 0.0f32 - 0.488_602_5f32 * x;
    } else if k == 4 {
        v = 1.092_548_4f32 * x * y;
    } else if k == 5 {
        v = 0.0f32 - 1.092_548_4f32 * y * z;
    } else if k == 6 {
        v = 0.946_174_7f32 * zz - 0.315_391_57f32;
    } else if k == 7 {
        v = 0.0f32 - 1.092_548_4f32 * x * z;
    } else if k == 8 {
        v = 0.546_274_2f32 * (xx - yy);
    } else if k == 9 {
        v = 0.590_043_6f32 * y * (yy - 3.0f32 * xx);
    } else if k == 10 {
        v = 2.890_611_4f32 * x * y * z;
    } else if k == 11 {
        v = 0.457_045_8f32 * y * (1.0f32 - 5.0f32 * zz);
    } else if k == 12 {
        v = 0.373_176_33f32 * z * (5.0f32 * zz - 3.0f32);
    } else if k == 13 {
        v = 0.457_045_8f32 * x * (1.0f32 - 5.0f32 * zz);
    } else if k == 14 {
        v = 1.445_305_7f32 * z * (xx - yy);
    } else if k == 15 {
        v = 0.590_043_6f32 * x * (3.0f32 * yy - xx);
    }
    v
}
