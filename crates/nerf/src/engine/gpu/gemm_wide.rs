//! The dense layers' product for wide layers: each thread of a 16 x 16 workgroup computes
//! up to 8 x 8 outputs of a tile of up to 128 x 128, reading its operands from workgroup
//! memory four at a time (`vec4`). The blocked kernel (`gemm`) computes 4 x 4 outputs a
//! thread and issues a shared-memory load for every two multiply-adds; here a step of the
//! reduction loads four `vec4`s for 64 multiply-adds, and each value staged from global
//! memory feeds up to 128 outputs instead of 64.
//!
//! Layout: a thread owns rows `4 (ty + 16 g) + e` and columns `4 (tx + 16 h) + f`, so each
//! of its `vec4` reads is one aligned load, the rows a warp reads are two broadcasts and
//! its columns one contiguous run. The tiles are stored with the reduced index outermost
//! (`A` transposed), each row padded by one `vec4` so that the staging writes, which walk
//! the reduced index, spread over the banks.

use cubecl::prelude::*;

use super::gemm_epilogue::{store, Epi, Gemm};

type V4 = Vector<f32, Const<4>>;

/// Output tile side (and workgroup side) in threads; the reduced index is staged 16 at a
/// time.
const SIDE: usize = 16;

/// The staging and tile geometry of one launch, fixed when the kernel is compiled.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub(super) struct Shape {
    /// Outputs a thread down and across (4 or 8 each): `16 tm x 16 tn` a workgroup.
    pub tm: usize,
    pub tn: usize,
    /// `A`'s rows are adjacent in memory (`a_si == 1`, a transposed operand), so staging
    /// walks rows first to read memory in order; `b_cols_unit` likewise for `B`'s columns.
    pub a_rows_unit: bool,
    pub b_cols_unit: bool,
}

/// One operand as staging reads it: element (outer index `i`, reduced index `l`) at
/// `off + i outer + l reduce`, the tile's outer indices from `first`, `len` in all (`A`'s
/// rows, `B`'s columns).
#[derive(CubeType, Clone, Copy)]
struct Operand {
    off: usize,
    outer: usize,
    reduce: usize,
    first: usize,
    len: usize,
}

#[cube]
impl Operand {
    fn new(off: u32, outer: u32, reduce: u32, first: usize, len: u32) -> Operand {
        Operand {
            off: off as usize,
            outer: outer as usize,
            reduce: reduce as usize,
            first,
            len: len as usize,
        }
    }
}

/// The `idx`-th vec4 of an operand's tile at `l0` (four adjacent outer indices at one
/// reduced index; zeros past the edges) and its index in the tile, `groups` vec4s a row.
/// `outer_unit`: adjacent outer indices are adjacent in memory, so consecutive threads
/// take consecutive groups.
#[cube]
fn fetch(
    buf: &[f32],
    o: &Operand,
    idx: usize,
    l0: usize,
    last: usize,
    #[comptime] groups: usize,
    #[comptime] outer_unit: bool,
) -> (V4, usize) {
    let mut group = idx / SIDE;
    let mut l = idx % SIDE;
    if outer_unit {
        group = idx % groups;
        l = idx / groups;
    }
    let reduced = l0 + l;
    let mut v = V4::broadcast(0.0);
    #[unroll]
    for e in 0..4 {
        let i = o.first + 4 * group + e;
        if i < o.len && reduced < last {
            v.insert(e, buf[o.off + i * o.outer + reduced * o.reduce]);
        }
    }
    (v, l * (groups + 1) + group)
}

/// `C = A B` through the epilogue, as `gemm_tiled`, with `16 tm` rows by `16 tn` columns a
/// workgroup.
#[cube(launch_unchecked)]
#[allow(clippy::too_many_arguments)]
pub(super) fn gemm_wide(
    a: &[f32],
    b: &[f32],
    bias: &[f32],
    mask: &[f32],
    c: &mut [f32],
    g: Gemm,
    #[comptime] s: Shape,
) {
    let (tm, tn) = (s.tm, s.tn);
    let tx = UNIT_POS_X as usize;
    let ty = UNIT_POS_Y as usize;
    let t = ty * SIDE + tx;
    // The padded row length of each tile, in vec4s.
    let a_stride = SIDE * tm / 4 + 1;
    let b_stride = SIDE * tn / 4 + 1;
    let row0 = CUBE_POS_Y as usize * SIDE * tm;
    let col0 = CUBE_POS_X as usize * SIDE * tn;
    let part = CUBE_POS_Z as usize;
    let first = part * g.k_part as usize;
    let last = usize::min(first + g.k_part as usize, g.k as usize);
    let mut a_tile = Shared::<[V4]>::new_slice(SIDE * (SIDE * tm / 4 + 1));
    let mut b_tile = Shared::<[V4]>::new_slice(SIDE * (SIDE * tn / 4 + 1));
    let mut acc = Array::<f32>::new(tm * tn);
    #[unroll]
    for q in 0..tm * tn {
        acc[q] = 0.0;
    }
    let mut a_reg = Array::<f32>::new(tm);
    let mut b_reg = Array::<f32>::new(tn);
    let a_op = Operand::new(g.a_off, g.a_si, g.a_sl, row0, g.m);
    let b_op = Operand::new(g.b_off, g.b_sj, g.b_sl, col0, g.n);
    let mut l0 = first;
    while l0 < last {
        #[unroll]
        for q in 0..tm / 4 {
            let idx = t + SIDE * SIDE * q;
            let (v, at) = fetch(a, &a_op, idx, l0, last, SIDE * tm / 4, s.a_rows_unit);
            a_tile[at] = v;
        }
        #[unroll]
        for q in 0..tn / 4 {
            let idx = t + SIDE * SIDE * q;
            let (v, at) = fetch(b, &b_op, idx, l0, last, SIDE * tn / 4, s.b_cols_unit);
            b_tile[at] = v;
        }
        sync_cube();
        for kk in 0..SIDE {
            #[unroll]
            for gq in 0..tm / 4 {
                let v = a_tile[kk * a_stride + ty + SIDE * gq];
                #[unroll]
                for e in 0..4 {
                    a_reg[gq * 4 + e] = v.extract(e);
                }
            }
            #[unroll]
            for hq in 0..tn / 4 {
                let v = b_tile[kk * b_stride + tx + SIDE * hq];
                #[unroll]
                for f in 0..4 {
                    b_reg[hq * 4 + f] = v.extract(f);
                }
            }
            #[unroll]
            for i in 0..tm {
                #[unroll]
                for j in 0..tn {
                    acc[i * tn + j] += a_reg[i] * b_reg[j];
                }
            }
        }
        sync_cube();
        l0 += SIDE;
    }
    let at = g.c_part as usize * part;
    #[unroll]
    for i in 0..tm {
        #[unroll]
        for j in 0..tn {
            let row = row0 + 4 * (ty + SIDE * (i / 4)) + i % 4;
            let col = col0 + 4 * (tx + SIDE * (j / 4)) + j % 4;
            if row < g.m as usize && col < g.n as usize {
                let e = Epi::new(g.has_bias, g.bias_off, g.relu, g.has_mask, g.n);
                store(acc[i * tn + j], row, col, at, bias, mask, c, e);
            }
        }
    }
}
