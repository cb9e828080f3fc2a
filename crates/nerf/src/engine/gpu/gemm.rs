//! A tiled matrix product for the dense layers: `C = A B` over strided views, in 16 x 16
//! output tiles, each computed by one 16 x 16 workgroup that stages the matching 16 x 16
//! tiles of `A` and `B` in workgroup memory (every value read from global memory once per
//! tile instead of once per output). The reduction can be split into parts along `k`
//! (the third grid axis), each writing its own output, for weight gradients whose `k` is
//! the batch. An epilogue adds a bias, applies a ReLU, or zeroes where a mask is not
//! positive (the backward of the ReLU that made the mask).
//!
//! [`matmul`] launches the kernel its [`Path`] names: the 16 x 16 one and the blocked one
//! (4 x 4 outputs a thread) here, the wide one (`gemm_wide`) and the tensor-core one
//! (`gemm_cmma`) in their files.

use cubecl::prelude::*;
use cubecl::server::Handle;

use super::device::{Gpu, Path, WARP};
use super::gemm_cmma;
use super::gemm_epilogue::{store, Epi, Gemm, GemmLaunch};
use super::gemm_wide::{gemm_wide, Shape};

/// Output tile side (and workgroup side).
pub const TILE: usize = 16;

#[cube(launch_unchecked)]
fn gemm_tiled(a: &[f32], b: &[f32], bias: &[f32], mask: &[f32], c: &mut [f32], g: Gemm) {
    let tx = UNIT_POS_X as usize;
    let ty = UNIT_POS_Y as usize;
    let col = CUBE_POS_X as usize * 16 + tx;
    let row = CUBE_POS_Y as usize * 16 + ty;
    let part = CUBE_POS_Z as usize;
    let (m, n) = (g.m as usize, g.n as usize);
    let first = part * g.k_part as usize;
    let last = usize::min(first + g.k_part as usize, g.k as usize);
    let mut a_tile = Shared::<[f32]>::new_slice(256usize);
    let mut b_tile = Shared::<[f32]>::new_slice(256usize);
    let mut acc = 0.0f32;
    let mut l0 = first;
    while l0 < last {
        // Stage A(row, l0 + tx) and B(l0 + ty, col); zeros past the edges.
        let la = l0 + tx;
        let mut av = 0.0f32;
        if row < m && la < last {
            av = a[g.a_off as usize + row * g.a_si as usize + la * g.a_sl as usize];
        }
        a_tile[ty * 16 + tx] = av;
        let lb = l0 + ty;
        let mut bv = 0.0f32;
        if col < n && lb < last {
            bv = b[g.b_off as usize + lb * g.b_sl as usize + col * g.b_sj as usize];
        }
        b_tile[ty * 16 + tx] = bv;
        sync_cube();
        for kk in 0..16usize {
            acc += a_tile[ty * 16 + kk] * b_tile[kk * 16 + tx];
        }
        sync_cube();
        l0 += 16;
    }
    if row < m && col < n {
        let at = g.c_part as usize * part;
        let e = Epi::new(g.has_bias, g.bias_off, g.relu, g.has_mask, g.n);
        store(acc, row, col, at, bias, mask, c, e);
    }
}

/// Rows of `C` each thread of the blocked kernel computes, `TILE` apart (and columns, for
/// products with more than [`NARROW`] of them).
const PER_THREAD: usize = 4;
/// The blocked kernel's output tile height: `TILE * PER_THREAD` rows.
pub const BLOCK: usize = TILE * PER_THREAD;
/// Products with at most this many output columns take one column per thread.
pub const NARROW: usize = 2 * TILE;

/// `gemm_tiled` with each thread computing `PER_THREAD` rows (`ty + 16 i`) by `cols`
/// columns (`tx + 16 j`) of a 64 x `16 cols` tile: per value staged in workgroup memory,
/// several multiply-adds instead of one, which the tiled kernel's loop is bound by.
#[cube(launch_unchecked)]
fn gemm_blocked(
    a: &[f32],
    b: &[f32],
    bias: &[f32],
    mask: &[f32],
    c: &mut [f32],
    g: Gemm,
    #[comptime] cols: usize,
) {
    let tx = UNIT_POS_X as usize;
    let ty = UNIT_POS_Y as usize;
    let width = TILE * cols;
    let col0 = CUBE_POS_X as usize * width;
    let row0 = CUBE_POS_Y as usize * BLOCK;
    let part = CUBE_POS_Z as usize;
    let (m, n) = (g.m as usize, g.n as usize);
    let first = part * g.k_part as usize;
    let last = usize::min(first + g.k_part as usize, g.k as usize);
    // A's 64 rows by 16 reduced indices, B's 16 by `width` columns.
    let mut a_tile = Shared::<[f32]>::new_slice(BLOCK * TILE);
    let mut b_tile = Shared::<[f32]>::new_slice(TILE * width);
    let mut acc = Array::<f32>::new(PER_THREAD * cols);
    #[unroll]
    for q in 0..PER_THREAD * cols {
        acc[q] = 0.0;
    }
    let mut a_reg = Array::<f32>::new(PER_THREAD);
    let mut b_reg = Array::<f32>::new(cols);
    let mut l0 = first;
    while l0 < last {
        // Each thread stages `PER_THREAD` values of A and `cols` of B; zeros past the edges.
        let la = l0 + tx;
        #[unroll]
        for q in 0..PER_THREAD {
            let r = ty + TILE * q;
            let row = row0 + r;
            let mut av = 0.0f32;
            if row < m && la < last {
                av = a[g.a_off as usize + row * g.a_si as usize + la * g.a_sl as usize];
            }
            a_tile[r * TILE + tx] = av;
        }
        let lb = l0 + ty;
        #[unroll]
        for q in 0..cols {
            let cc = tx + TILE * q;
            let col = col0 + cc;
            let mut bv = 0.0f32;
            if col < n && lb < last {
                bv = b[g.b_off as usize + lb * g.b_sl as usize + col * g.b_sj as usize];
            }
            b_tile[ty * width + cc] = bv;
        }
        sync_cube();
        for kk in 0..TILE {
            #[unroll]
            for q in 0..PER_THREAD {
                a_reg[q] = a_tile[(ty + TILE * q) * TILE + kk];
            }
            #[unroll]
            for q in 0..cols {
                b_reg[q] = b_tile[kk * width + tx + TILE * q];
            }
            #[unroll]
            for i in 0..PER_THREAD {
                #[unroll]
                for j in 0..cols {
                    acc[i * cols + j] += a_reg[i] * b_reg[j];
                }
            }
        }
        sync_cube();
        l0 += TILE;
    }
    #[unroll]
    for i in 0..PER_THREAD {
        #[unroll]
        for j in 0..cols {
            let row = row0 + ty + TILE * i;
            let col = col0 + tx + TILE * j;
            if row < m && col < n {
                let at = g.c_part as usize * part;
                let e = Epi::new(g.has_bias, g.bias_off, g.relu, g.has_mask, g.n);
                store(acc[i * cols + j], row, col, at, bias, mask, c, e);
            }
        }
    }
}

/// A strided operand: element (outer index `i`, reduced index `l`) at
/// `buf[off + i outer + l reduce]`; `i` is `A`'s row or `B`'s column.
#[derive(Clone, Copy, Debug)]
pub struct View<'a> {
    pub buf: &'a Handle,
    /// Floats in `buf`.
    pub len: usize,
    pub off: usize,
    pub outer: usize,
    pub reduce: usize,
}

/// The epilogue of a product.
#[derive(Clone, Copy, Default)]
pub struct Epilogue<'a> {
    /// A bias vector: `(buffer, its length, offset)`.
    pub bias: Option<(&'a Handle, usize, usize)>,
    pub relu: bool,
    /// `(mask, its length)`, laid out as `C`.
    pub mask: Option<(&'a Handle, usize)>,
}

/// The kernel one product takes, with what it is compiled for.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Kernel {
    Tiled,
    Blocked {
        cols: usize,
    },
    Wide(Shape),
    Cmma {
        a_rows_unit: bool,
        b_cols_unit: bool,
    },
}

impl Kernel {
    /// `path`'s kernel for an `m x n` product: the wide and tensor-core kernels take
    /// products of more than [`NARROW`] columns, the blocked kernel the narrower ones,
    /// except on a `software` adapter, where the wide kernel takes them all: lavapipe
    /// loads a value lane by lane, so the wide kernel's many multiply-adds a load pay for
    /// the columns it computes past `n` (docs/benchmarks.md).
    /// `a_rows_unit`, `b_cols_unit`: `A`'s rows (`B`'s columns) are adjacent in memory.
    fn for_product(
        path: Path,
        (m, n): (usize, usize),
        a_rows_unit: bool,
        b_cols_unit: bool,
        software: bool,
    ) -> Kernel {
        let narrow = n <= NARROW;
        match path {
            Path::Plain | Path::Tiled => Kernel::Tiled,
            Path::Cmma if !narrow => Kernel::Cmma {
                a_rows_unit,
                b_cols_unit,
            },
            // Outputs a thread: 8 rows (columns) where the product has more than 64, else 4.
            Path::Wide if !narrow || software => Kernel::Wide(Shape {
                tm: if m > BLOCK { 8 } else { 4 },
                tn: if n > BLOCK { 8 } else { 4 },
                a_rows_unit,
                b_cols_unit,
            }),
            Path::Blocked | Path::Wide | Path::Cmma => Kernel::Blocked {
                cols: if narrow { 1 } else { PER_THREAD },
            },
        }
    }

    /// Workgroups across `n` and down `m`.
    fn grid(self, m: usize, n: usize) -> (usize, usize) {
        match self {
            Kernel::Tiled => (n.div_ceil(TILE), m.div_ceil(TILE)),
            Kernel::Blocked { cols } => (n.div_ceil(TILE * cols), m.div_ceil(BLOCK)),
            Kernel::Wide(s) => (n.div_ceil(TILE * s.tn), m.div_ceil(TILE * s.tm)),
            Kernel::Cmma { .. } => (n.div_ceil(gemm_cmma::TILE), m.div_ceil(gemm_cmma::TILE)),
        }
    }

    fn workgroup(self) -> CubeDim {
        match self {
            Kernel::Cmma { .. } => CubeDim::new_2d(WARP, gemm_cmma::WARPS as u32),
            _ => CubeDim::new_2d(TILE as u32, TILE as u32),
        }
    }
}

/// `C = A B` (`m x k` by `k x n`) into `c` (`parts x m x n` when the reduction is split
/// into `parts` of `k_part`), through `epilogue`, by the kernel of `path` ([`Kernel`];
/// `Plain` is the caller's own, and takes the 16 x 16 kernel here).
/// Returns false (launching nothing) when the grid would exceed 65535 tiles down `m`: the
/// caller takes its plain kernel then.
#[allow(clippy::too_many_arguments)]
pub fn matmul(
    gpu: &Gpu,
    (m, n, k): (usize, usize, usize),
    a: View,
    b: View,
    c: &Handle,
    k_part: usize,
    epilogue: Epilogue,
    path: Path,
) -> bool {
    let parts = k.div_ceil(k_part.max(1)).max(1);
    let kernel = Kernel::for_product(path, (m, n), a.outer == 1, b.outer == 1, gpu.software);
    let (gx, gy) = kernel.grid(m, n);
    if gy > 65535 || parts > 65535 || m == 0 || n == 0 {
        return m == 0 || n == 0;
    }
    let none = gpu.floats(1);
    let (bias, bias_len, bias_off) = epilogue.bias.map_or((&none, 1, 0), |b| b);
    let (mask, mask_len) = epilogue.mask.map_or((&none, 1), |m| m);
    let g = GemmLaunch::new(
        m as u32,
        n as u32,
        k as u32,
        a.off as u32,
        a.outer as u32,
        a.reduce as u32,
        b.off as u32,
        b.reduce as u32,
        b.outer as u32,
        (m * n) as u32,
        k_part.max(1) as u32,
        u32::from(epilogue.bias.is_some()),
        bias_off as u32,
        u32::from(epilogue.relu),
        u32::from(epilogue.mask.is_some()),
    );
    // SAFETY: the views' lengths are those of their buffers and every index the kernel
    // forms stays below them for the shapes given (the callers build the views from the
    // layer's shapes); rows and columns past `m` and `n` are never read or written.
    unsafe {
        let count = CubeCount::Static(gx as u32, gy as u32, parts as u32);
        let dim = kernel.workgroup();
        let args = (
            BufferArg::from_raw_parts(a.buf.clone(), a.len),
            BufferArg::from_raw_parts(b.buf.clone(), b.len),
            BufferArg::from_raw_parts(bias.clone(), bias_len),
            BufferArg::from_raw_parts(mask.clone(), mask_len),
            BufferArg::from_raw_parts(c.clone(), parts * m * n),
        );
        match kernel {
            Kernel::Cmma {
                a_rows_unit,
                b_cols_unit,
            } => gemm_cmma::gemm_cmma::launch_unchecked(
                &gpu.client,
                count,
                dim,
                args.0,
                args.1,
                args.2,
                args.3,
                args.4,
                g,
                a_rows_unit,
                b_cols_unit,
            ),
            Kernel::Wide(shape) => gemm_wide::launch_unchecked(
                &gpu.client,
                count,
                dim,
                args.0,
                args.1,
                args.2,
                args.3,
                args.4,
                g,
                shape,
            ),
            Kernel::Blocked { cols } => gemm_blocked::launch_unchecked(
                &gpu.client,
                count,
                dim,
                args.0,
                args.1,
                args.2,
                args.3,
                args.4,
                g,
                cols,
            ),
            Kernel::Tiled => gemm_tiled::launch_unchecked(
                &gpu.client,
                count,
                dim,
                args.0,
                args.1,
                args.2,
                args.3,
                args.4,
                g,
            ),
        }
    }
    true
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::gpu::device::{test_gpu, worst};
    use crate::rng::Rng;

    /// Narrow products take the blocked kernel on a hardware adapter and the wide one on a
    /// software adapter; wide products take the wide kernel on both.
    #[test]
    fn narrow_products_take_the_wide_kernel_on_a_software_adapter_only() {
        let wide = |tm, tn| {
            Kernel::Wide(Shape {
                tm,
                tn,
                a_rows_unit: false,
                b_cols_unit: true,
            })
        };
        let kernel =
            |n, software| Kernel::for_product(Path::Wide, (4096, n), false, true, software);
        assert_eq!(kernel(16, false), Kernel::Blocked { cols: 1 });
        assert_eq!(kernel(16, true), wide(8, 4));
        assert_eq!(kernel(64, false), wide(8, 4));
        assert_eq!(kernel(64, true), wide(8, 4));
        assert_eq!(kernel(128, false), wide(8, 8));
        // The other paths are what they name, on either adapter.
        let blocked = Kernel::for_product(Path::Blocked, (4096, 16), false, true, true);
        assert_eq!(blocked, Kernel::Blocked { cols: 1 });
    }

    /// Every kernel against a host product on shapes that end mid-tile, with the
    /// reduction split into parts, `A` transposed (as weight gradients read it), and each
    /// epilogue.
    #[test]
    fn both_kernels_match_a_host_product() {
        let Some(gpu) = test_gpu() else {
            return;
        };
        let mut paths = vec![Path::Tiled, Path::Blocked, Path::Wide];
        if gpu.tensor_cores {
            paths.push(Path::Cmma);
        } else {
            eprintln!(
                "{}: no f16 cooperative matrices, the tensor-core kernel is not tested",
                gpu.name
            );
        }
        let mut rng = Rng::new(11);
        // (m, n, k, k_part, A transposed, B transposed): the wide kernel's four tile
        // shapes and both staging orders of each operand among them.
        for (m, n, k, k_part, transposed, b_transposed) in [
            (200, 64, 31, 31, false, false),
            (130, 48, 64, 64, false, true),
            (70, 37, 150, 64, true, false),
            (150, 16, 64, 64, false, false),
            (90, 3, 33, 16, true, false),
            (300, 150, 70, 70, false, true),
            (60, 200, 90, 40, true, false),
            (257, 130, 48, 48, true, true),
        ] {
            let av: Vec<f32> = (0..m * k).map(|_| rng.range(-1.0, 1.0)).collect();
            let bv: Vec<f32> = (0..k * n).map(|_| rng.range(-1.0, 1.0)).collect();
            let bias: Vec<f32> = (0..n).map(|_| rng.range(-1.0, 1.0)).collect();
            let mask: Vec<f32> = (0..m * n).map(|_| rng.range(-1.0, 1.0)).collect();
            // A(i, l): row-major, or stored as its transpose (`k x m`).
            let (outer, reduce) = if transposed { (1, m) } else { (k, 1) };
            // B(l, j): row-major, or stored as its transpose (`n x k`).
            let (b_sl, b_sj) = if b_transposed { (1, k) } else { (n, 1) };
            let parts = k.div_ceil(k_part);
            let mut want = vec![0.0f32; parts * m * n];
            for p in 0..parts {
                for i in 0..m {
                    for j in 0..n {
                        let mut acc = 0.0;
                        for l in p * k_part..((p + 1) * k_part).min(k) {
                            acc += av[i * outer + l * reduce] * bv[l * b_sl + j * b_sj];
                        }
                        if parts == 1 {
                            acc = (acc + bias[j]).max(0.0);
                            if mask[i * n + j] <= 0.0 {
                                acc = 0.0;
                            }
                        }
                        want[p * m * n + i * n + j] = acc;
                    }
                }
            }
            let (a, b) = (gpu.upload(&av), gpu.upload(&bv));
            let (bias_h, mask_h) = (gpu.upload(&bias), gpu.upload(&mask));
            for path in paths.iter().copied() {
                let c = gpu.floats(parts * m * n);
                let epilogue = if parts == 1 {
                    Epilogue {
                        bias: Some((&bias_h, n, 0)),
                        relu: true,
                        mask: Some((&mask_h, m * n)),
                    }
                } else {
                    Epilogue::default()
                };
                let a_view = View {
                    buf: &a,
                    len: m * k,
                    off: 0,
                    outer,
                    reduce,
                };
                let b_view = View {
                    buf: &b,
                    len: k * n,
                    off: 0,
                    outer: b_sj,
                    reduce: b_sl,
                };
                let (mnk, part) = ((m, n, k), k_part);
                assert!(matmul(&gpu, mnk, a_view, b_view, &c, part, epilogue, path));
                let got = gpu.read(&c, parts * m * n).expect("read");
                let err = worst(&got, &want);
                eprintln!("{m}x{n}x{k} in {parts} parts, {path:?}: {err:.1e}");
                // Tensor cores multiply `f16` roundings of the operands (11 bits).
                let tolerance = if path == Path::Cmma { 3e-2 } else { 1e-4 };
                assert!(err < tolerance, "{m}x{n}x{k}, {path:?}: {err}");
            }
        }
    }
}
