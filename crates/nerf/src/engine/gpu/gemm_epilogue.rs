//! What every kernel of the dense layers' products shares: a product's shape, strides
//! and epilogue as launch arguments ([`Gemm`]), and the epilogue that writes each sum
//! (a bias, a ReLU, a mask).

use cubecl::prelude::*;

/// Strides and epilogue of one product, in the order the kernel reads them.
#[derive(CubeType, CubeLaunch, Clone, Copy)]
pub struct Gemm {
    pub(super) m: u32,
    pub(super) n: u32,
    pub(super) k: u32,
    /// `A(i, l) = a[a_off + i a_si + l a_sl]`.
    pub(super) a_off: u32,
    pub(super) a_si: u32,
    pub(super) a_sl: u32,
    /// `B(l, j) = b[b_off + l b_sl + j b_sj]`.
    pub(super) b_off: u32,
    pub(super) b_sl: u32,
    pub(super) b_sj: u32,
    /// `C(i, j) = c[c_off + part c_part + i n + j]`; part `p` sums `l` in
    /// `[p k_part, (p + 1) k_part)`.
    pub(super) c_part: u32,
    pub(super) k_part: u32,
    /// Epilogue: 1 adds `bias[bias_off + j]`; 1 applies a ReLU; 1 zeroes `C(i, j)` where
    /// `mask[i n + j] <= 0`.
    pub(super) has_bias: u32,
    pub(super) bias_off: u32,
    pub(super) relu: u32,
    pub(super) has_mask: u32,
}

/// The epilogue's flags and the output's width, as [`store`] reads them.
#[derive(CubeType, Clone, Copy)]
pub(super) struct Epi {
    pub(super) has_bias: u32,
    pub(super) bias_off: u32,
    pub(super) relu: u32,
    pub(super) has_mask: u32,
    pub(super) n: u32,
}

#[cube]
impl Epi {
    pub(super) fn new(has_bias: u32, bias_off: u32, relu: u32, has_mask: u32, n: u32) -> Epi {
        Epi {
            has_bias,
            bias_off,
            relu,
            has_mask,
            n,
        }
    }
}

/// Writes the sum `v` of `C(row, col)` through the epilogue `e` into `c` from `at`.
#[cube]
#[allow(clippy::too_many_arguments)]
pub(super) fn store(
    v: f32,
    row: usize,
    col: usize,
    at: usize,
    bias: &[f32],
    mask: &[f32],
    c: &mut [f32],
    e: Epi,
) {
    let n = e.n as usize;
    let mut v = v;
    if e.has_bias == 1 {
        v += bias[e.bias_off as usize + col];
    }
    if e.relu == 1 {
        v = f32::max(v, 0.0);
    }
    if e.has_mask == 1 && mask[row * n + col] <= 0.0 {
        v = 0.0;
    }
    c[at + row * n + col] = v;
}
