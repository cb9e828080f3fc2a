//! The dense layers' product on tensor cores: CubeCL's cooperative matrices (`cmma`), `f16`
//! operands and `f32` sums, where the adapter offers them (Vulkan through SPIR-V, the
//! `spirv` feature). Four warps a workgroup share a 64 x 64 output tile, each computing 32
//! x 32 of it as 2 x 2 matrices of 16 x 16; `A` and `B` are staged 16 reduced indices at a
//! time into workgroup memory, rounded to `f16` on the way, and the sums go through
//! workgroup memory once more for the epilogue.
//!
//! On an H100 it measured no faster than the wide kernel compiled to SPIR-V
//! (docs/benchmarks.md), so it runs only when asked (`NERF_GPU_MATMUL=cmma`), for the
//! forward products: the tensor cores' throughput is there to take with larger tiles and
//! operands kept in `f16`, not in this kernel's staging.

use cubecl::prelude::*;
use half::f16;

use super::device::WARP;
use super::gemm_epilogue::{store, Epi, Gemm};

/// Output tile side; the reduced index is staged 16 at a time.
pub(super) const TILE: usize = 64;
const K: usize = 16;
/// Warps a workgroup.
pub(super) const WARPS: usize = 4;

/// A 16 x 16 matrix of sums, zeroed.
#[cube]
fn zero_sums() -> cmma::Matrix<f32> {
    cmma::Matrix::<f32>::from_value(
        cmma::MatrixIdent::Accumulator,
        16usize,
        16usize,
        16usize,
        cmma::MatrixLayout::Undefined,
        0.0,
    )
}

/// A 16 x 16 operand (`ident`: `A` or `B`) read row-major from workgroup memory, rows
/// `stride` apart.
#[cube]
fn operand(
    #[comptime] ident: cmma::MatrixIdent,
    tile: &[f16],
    #[comptime] stride: usize,
) -> cmma::Matrix<f16> {
    cmma::Matrix::<f16>::from_slice(
        ident,
        16usize,
        16usize,
        16usize,
        cmma::MatrixLayout::RowMajor,
        tile,
        stride as u32,
    )
}

/// `C = A B` through the epilogue, as `gemm_tiled`, in 64 x 64 tiles on tensor cores.
#[cube(launch_unchecked)]
#[allow(clippy::too_many_arguments)]
pub(super) fn gemm_cmma(
    a: &[f32],
    b: &[f32],
    bias: &[f32],
    mask: &[f32],
    c: &mut [f32],
    g: Gemm,
    #[comptime] a_rows_unit: bool,
    #[comptime] b_cols_unit: bool,
) {
    let lane = UNIT_POS_X as usize;
    let warp = UNIT_POS_Y as usize;
    let threads = WARP as usize * WARPS;
    let t = warp * WARP as usize + lane;
    let row0 = CUBE_POS_Y as usize * TILE;
    let col0 = CUBE_POS_X as usize * TILE;
    let part = CUBE_POS_Z as usize;
    let (m, n) = (g.m as usize, g.n as usize);
    let first = part * g.k_part as usize;
    let last = usize::min(first + g.k_part as usize, g.k as usize);
    // A's tile row-major (`[row][l]`), B's row-major (`[l][col]`), the sums row-major.
    let mut a_tile = Shared::<[f16]>::new_slice(TILE * K);
    let mut b_tile = Shared::<[f16]>::new_slice(K * TILE);
    let mut c_tile = Shared::<[f32]>::new_slice(TILE * TILE);
    // This warp's 32 x 32 corner of the tile.
    let wr = (warp / 2) * 32;
    let wc = (warp % 2) * 32;
    let acc00 = zero_sums();
    let acc01 = zero_sums();
    let acc10 = zero_sums();
    let acc11 = zero_sums();
    let mut l0 = first;
    while l0 < last {
        #[unroll]
        for q in 0..TILE * K / (WARP as usize * WARPS) {
            let idx = t + threads * q;
            let mut r = idx / K;
            let mut l = idx % K;
            if a_rows_unit {
                r = idx % TILE;
                l = idx / TILE;
            }
            let (row, la) = (row0 + r, l0 + l);
            let mut v = 0.0f32;
            if row < m && la < last {
                v = a[g.a_off as usize + row * g.a_si as usize + la * g.a_sl as usize];
            }
            a_tile[r * K + l] = f16::cast_from(v);
        }
        #[unroll]
        for q in 0..TILE * K / (WARP as usize * WARPS) {
            let idx = t + threads * q;
            let mut cc = idx / K;
            let mut l = idx % K;
            if b_cols_unit {
                cc = idx % TILE;
                l = idx / TILE;
            }
            let (col, lb) = (col0 + cc, l0 + l);
            let mut v = 0.0f32;
            if col < n && lb < last {
                v = b[g.b_off as usize + lb * g.b_sl as usize + col * g.b_sj as usize];
            }
            b_tile[l * TILE + cc] = f16::cast_from(v);
        }
        sync_cube();
        let a0 = operand(cmma::MatrixIdent::A, &a_tile[wr * K..(wr + 16) * K], K);
        let a1 = operand(
            cmma::MatrixIdent::A,
            &a_tile[(wr + 16) * K..(wr + 32) * K],
            K,
        );
        let b0 = operand(cmma::MatrixIdent::B, &b_tile[wc..K * TILE], TILE);
        let b1 = operand(cmma::MatrixIdent::B, &b_tile[wc + 16..K * TILE], TILE);
        cmma::execute(&a0, &b0, &acc00, &acc00);
        cmma::execute(&a0, &b1, &acc01, &acc01);
        cmma::execute(&a1, &b0, &acc10, &acc10);
        cmma::execute(&a1, &b1, &acc11, &acc11);
        sync_cube();
        l0 += K;
    }
    let at0 = wr * TILE + wc;
    let end = TILE * TILE;
    let stride = TILE as u32;
    let layout = cmma::MatrixLayout::RowMajor;
    cmma::store(&mut c_tile[at0..end], &acc00, stride, layout);
    cmma::store(&mut c_tile[at0 + 16..end], &acc01, stride, layout);
    cmma::store(&mut c_tile[at0 + 16 * TILE..end], &acc10, stride, layout);
    cmma::store(
        &mut c_tile[at0 + 16 * TILE + 16..end],
        &acc11,
        stride,
        layout,
    );
    sync_cube();
    let at = g.c_part as usize * part;
    #[unroll]
    for q in 0..TILE * TILE / (WARP as usize * WARPS) {
        let idx = t + threads * q;
        let (row, col) = (row0 + idx / TILE, col0 + idx % TILE);
        if row < m && col < n {
            let e = Epi::new(g.has_bias, g.bias_off, g.relu, g.has_mask, g.n);
            store(c_tile[idx], row, col, at, bias, mask, c, e);
        }
    }
}
