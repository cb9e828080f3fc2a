//! Matrix products over row-major `f32` slices, via the `gemm-f32` crate, or with inputs
//! rounded to bfloat16 where the CPU has AVX-512 BF16 ([`Precision`]).
//!
//! Every layer is `Y = X W + b` with `X: n x in`, `W: in x out` (TensorFlow's kernel
//! layout, which the reference NeRF used). The backward needs `dX = dY W^T` and
//! `dW += X^T dY`; both are strided views of the same buffers, so no transpose is copied.
//! Each call is single-threaded: parallelism comes from independent ray chunks per thread.

use gemm_common::Parallelism;

use super::bf16_kernels::{pairs_product, rows_product, PackedRight, Rows};

/// A strided, read-only matrix view.
#[derive(Clone, Copy, Debug)]
pub struct MatRef<'a> {
    data: &'a [f32],
    rows: usize,
    cols: usize,
    row_stride: usize,
    col_stride: usize,
}

impl<'a> MatRef<'a> {
    /// `rows x cols`, row-major, densely packed. Panics if `data` is too short, as that
    /// is a bug in the caller rather than something a user can cause.
    pub fn new(data: &'a [f32], rows: usize, cols: usize) -> Self {
        assert!(
            data.len() >= rows * cols,
            "matrix {rows}x{cols} needs {} values, got {}",
            rows * cols,
            data.len()
        );
        MatRef {
            data,
            rows,
            cols,
            row_stride: cols,
            col_stride: 1,
        }
    }

    /// The transpose, as a view of the same memory.
    pub fn t(self) -> Self {
        MatRef {
            data: self.data,
            rows: self.cols,
            cols: self.rows,
            row_stride: self.col_stride,
            col_stride: self.row_stride,
        }
    }
}

/// How a product treats its inputs: as `f32`, or rounded to bfloat16 with `f32` sums
/// (mixed precision, as GPU trainers run their networks in half precision): twice the
/// multiply-adds per instruction, 8 significant bits per input. Only made for a CPU that
/// has the kernels, so a product never falls back unasked.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Precision {
    bf16: bool,
}

impl Precision {
    /// Inputs as they are.
    pub const F32: Precision = Precision { bf16: false };

    /// bfloat16 inputs, `f32` sums: `None` where the CPU lacks AVX-512 BF16.
    pub fn bf16() -> Option<Precision> {
        super::bf16_kernels::available().then_some(Precision { bf16: true })
    }

    pub fn is_bf16(self) -> bool {
        self.bf16
    }
}

/// [`matmul`] in `precision`. The bfloat16 kernels take `a` with contiguous rows (`X W`,
/// `dY W^T`) or `a` the transpose of such a matrix and `b` with contiguous rows (`X^T dY`);
/// other layouts are multiplied in `f32`.
pub fn matmul_in(precision: Precision, out: &mut [f32], a: MatRef, b: MatRef, accumulate: bool) {
    assert_eq!(a.cols, b.rows, "inner dimensions differ");
    let (m, n, k) = (a.rows, b.cols, a.cols);
    if precision.bf16 && m > 0 && n > 0 && k > 0 {
        if a.col_stride == 1 {
            let right = PackedRight::new(k, n, |r, c| b.data[r * b.row_stride + c * b.col_stride]);
            let rows = Rows {
                values: a.data,
                stride: a.row_stride,
                cols: k,
            };
            rows_product(out, rows, m, &right, accumulate);
            return;
        }
        if a.row_stride == 1 && b.col_stride == 1 {
            // a is x^T: x's rows are a's columns.
            let x = Rows {
                values: a.data,
                stride: a.col_stride,
                cols: m,
            };
            let y = Rows {
                values: b.data,
                stride: b.row_stride,
                cols: n,
            };
            pairs_product(out, x, y, k, accumulate);
            return;
        }
    }
    matmul(out, a, b, accumulate);
}

/// `out (m x n, row-major) = a b`, or `out += a b` when `accumulate`.
pub fn matmul(out: &mut [f32], a: MatRef, b: MatRef, accumulate: bool) {
    gemm_checked(out, a, b, accumulate, Parallelism::None);
}

/// Like [`matmul`] but lets `gemm-f32` split the one product over `threads` threads
/// (used by the benchmark to measure the library's peak).
pub fn matmul_parallel(out: &mut [f32], a: MatRef, b: MatRef, threads: usize) {
    gemm_checked(out, a, b, false, Parallelism::Rayon(threads));
}

fn gemm_checked(out: &mut [f32], a: MatRef, b: MatRef, accumulate: bool, parallelism: Parallelism) {
    assert_eq!(a.cols, b.rows, "inner dimensions differ");
    let (m, n, k) = (a.rows, b.cols, a.cols);
    assert!(out.len() >= m * n, "output too short");
    if m == 0 || n == 0 {
        return;
    }
    if k == 0 {
        if !accumulate {
            out[..m * n].fill(0.0);
        }
        return;
    }
    // The kernels prefer a column-major destination: ours is row-major, so (as the `gemm`
    // crate's front end does) compute the transpose, `out^T = b^T a^T`, which swaps the
    // operands and their strides. A single column is both layouts at once.
    let (rows, cols, out_cs, out_rs, lhs, rhs) = if n > 1 {
        (n, m, n as isize, 1, b.t(), a.t())
    } else {
        (m, n, 1, n as isize, a, b)
    };
    // SAFETY: the asserts above and in `MatRef::new` keep every index the strides reach
    // inside the slices: a's largest is (m-1)*rs + (k-1)*cs < rows*cols <= len, same for b,
    // and out is m*n dense. The output does not alias the inputs (it is `&mut`). All
    // strides are positive, which the kernels require.
    unsafe {
        gemm_f32::gemm::f32::get_gemm_fn()(
            rows,
            cols,
            k,
            out.as_mut_ptr(),
            out_cs,
            out_rs,
            accumulate,
            lhs.data.as_ptr(),
            lhs.col_stride as isize,
            lhs.row_stride as isize,
            rhs.data.as_ptr(),
            rhs.col_stride as isize,
            rhs.row_stride as isize,
            1.0,
            1.0,
            false,
            false,
            false,
            parallelism,
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn naive(a: &[f32], b: &[f32], m: usize, k: usize, n: usize) -> Vec<f32> {
        let mut c = vec![0.0; m * n];
        for i in 0..m {
            for j in 0..n {
                c[i * n + j] = (0..k).map(|p| a[i * k + p] * b[p * n + j]).sum();
            }
        }
        c
    }

    #[test]
    fn products_and_transposes_match_naive() {
        let (m, k, n) = (7, 5, 3);
        let a: Vec<f32> = (0..m * k).map(|i| (i as f32 * 0.37).sin()).collect();
        let b: Vec<f32> = (0..k * n).map(|i| (i as f32 * 0.11).cos()).collect();
        let want = naive(&a, &b, m, k, n);
        let mut c = vec![1.0; m * n];
        matmul(&mut c, MatRef::new(&a, m, k), MatRef::new(&b, k, n), false);
        for (x, y) in c.iter().zip(&want) {
            assert!((x - y).abs() < 1e-5);
        }
        // Accumulate adds on top.
        matmul(&mut c, MatRef::new(&a, m, k), MatRef::new(&b, k, n), true);
        for (x, y) in c.iter().zip(&want) {
            assert!((x - 2.0 * y).abs() < 1e-5);
        }
        // (b^T a^T) = (a b)^T
        let mut ct = vec![0.0; n * m];
        matmul(
            &mut ct,
            MatRef::new(&b, k, n).t(),
            MatRef::new(&a, m, k).t(),
            false,
        );
        for i in 0..m {
            for j in 0..n {
                assert!((ct[j * m + i] - want[i * n + j]).abs() < 1e-5);
            }
        }
    }

    /// Every layout the layers use (`X W`, `dY W^T`, `X^T dY`), at shapes that take each
    /// of the kernels' paths: one column, one row, inner size one, and sizes past a
    /// register tile, single-threaded and split over threads.
    #[test]
    fn every_layout_and_edge_shape_matches_naive() {
        for &(m, k, n) in &[(1, 4, 1), (9, 3, 1), (1, 6, 9), (5, 1, 4), (67, 33, 65)] {
            let a: Vec<f32> = (0..m * k).map(|i| (i as f32 * 0.29).sin()).collect();
            let b: Vec<f32> = (0..k * n).map(|i| (i as f32 * 0.17).cos()).collect();
            let want = naive(&a, &b, m, k, n);
            let (at, bt) = (transposed(&a, m, k), transposed(&b, k, n));
            let layouts = [
                (MatRef::new(&a, m, k), MatRef::new(&b, k, n)),
                (MatRef::new(&a, m, k), MatRef::new(&bt, n, k).t()),
                (MatRef::new(&at, k, m).t(), MatRef::new(&b, k, n)),
            ];
            for (la, lb) in layouts {
                let mut c = vec![f32::NAN; m * n];
                matmul(&mut c, la, lb, false);
                let mut p = vec![f32::NAN; m * n];
                matmul_parallel(&mut p, la, lb, 2);
                for ((x, y), w) in c.iter().zip(&p).zip(&want) {
                    let tol = 1e-4 * (1.0 + w.abs());
                    assert!((x - w).abs() < tol, "{m}x{k}x{n}: {x} vs {w}");
                    assert!((y - w).abs() < tol, "{m}x{k}x{n} parallel: {y} vs {w}");
                }
            }
        }
    }

    fn transposed(x: &[f32], rows: usize, cols: usize) -> Vec<f32> {
        (0..rows * cols)
            .map(|i| x[(i % rows) * cols + i / rows])
            .collect()
    }

    /// `a b` in `f64` over the inputs rounded to bfloat16: what the bfloat16 kernels must
    /// give up to the order of their `f32` sums.
    fn rounded_product(a: MatRef, b: MatRef) -> Vec<f32> {
        use super::super::bf16_kernels::round_to_bf16;
        let at = |m: MatRef, r: usize, c: usize| {
            round_to_bf16(m.data[r * m.row_stride + c * m.col_stride]) as f64
        };
        let mut c = vec![0.0; a.rows * b.cols];
        for i in 0..a.rows {
            for j in 0..b.cols {
                c[i * b.cols + j] =
                    (0..a.cols).map(|p| at(a, i, p) * at(b, p, j)).sum::<f64>() as f32;
            }
        }
        c
    }

    #[test]
    fn bf16_products_are_the_products_of_the_rounded_inputs() {
        let Some(bf16) = Precision::bf16() else {
            eprintln!("skipped: this CPU has no AVX-512 BF16");
            return;
        };
        let values = |len: usize, seed: f32| -> Vec<f32> {
            (0..len)
                .map(|i| ((i as f32 + seed) * 0.731).sin() * 2.0)
                .collect()
        };
        // (m, k, n): blocks of rows and their tails, odd inner sizes, 1 to 7 vectors of
        // columns; then the weight gradient's chunks of samples, an odd count among them.
        for (m, k, n) in [
            (37, 31, 64),
            (50, 64, 16),
            (13, 3, 64),
            (25, 64, 3),
            (40, 64, 31),
            (19, 33, 100),
            (7, 1, 1),
        ] {
            let (a, w) = (values(m * k, 0.5), values(k * n, 1.5));
            let (a, w) = (MatRef::new(&a, m, k), MatRef::new(&w, k, n));
            let wt_data: Vec<f32> = (0..n * k).map(|i| w.data[(i % k) * n + i / k]).collect();
            // b given as the transpose of an n x k matrix: a strided view, as W^T is.
            let wt = MatRef::new(&wt_data, n, k).t();
            for b in [w, wt] {
                let want = rounded_product(a, b);
                let mut got = vec![0.5; m * n];
                matmul_in(bf16, &mut got, a, b, false);
                let mut twice = got.clone();
                matmul_in(bf16, &mut twice, a, b, true);
                for ((g, t), w) in got.iter().zip(&twice).zip(&want) {
                    assert!(
                        (g - w).abs() <= 1e-5 * (1.0 + w.abs()),
                        "{m}x{k}x{n}: {g} vs {w}"
                    );
                    assert!((t - 2.0 * w).abs() <= 2e-5 * (1.0 + w.abs()));
                }
            }
        }
        for (m, k, n) in [(513, 31, 64), (300, 64, 16), (64, 64, 3), (9, 32, 70)] {
            let (x, y) = (values(m * k, 2.5), values(m * n, 3.5));
            let (xt, y) = (MatRef::new(&x, m, k).t(), MatRef::new(&y, m, n));
            let want = rounded_product(xt, y);
            let mut got = vec![0.25; k * n];
            matmul_in(bf16, &mut got, xt, y, true);
            for (g, w) in got.iter().zip(&want) {
                let w = w + 0.25;
                assert!(
                    (g - w).abs() <= 1e-4 * (1.0 + w.abs()),
                    "{m}x{k}x{n}: {g} vs {w}"
                );
            }
        }
    }

    #[test]
    fn bf16_rounding_keeps_eight_significant_bits() {
        use super::super::bf16_kernels::round_to_bf16;
        assert_eq!(round_to_bf16(1.0), 1.0);
        assert_eq!(round_to_bf16(1.0 + 1.0 / 256.0), 1.0); // halfway: to even
        assert_eq!(round_to_bf16(1.0 + 3.0 / 256.0), 1.0 + 4.0 / 256.0);
        assert_eq!(round_to_bf16(-2.5), -2.5);
        assert!(round_to_bf16(f32::NAN).is_nan());
    }
}
