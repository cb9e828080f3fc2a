//! Matrix products over row-major `f32` slices, via the `gemm` crate.
//!
//! Every layer is `Y = X W + b` with `X: n x in`, `W: in x out` (TensorFlow's kernel
//! layout, which the reference NeRF used). The backward needs `dX = dY W^T` and
//! `dW += X^T dY`; both are strided views of the same buffers, so no transpose is copied.
//! Each call is single-threaded: parallelism comes from independent ray chunks per thread.

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

/// `out (m x n, row-major) = a b`, or `out += a b` when `accumulate`.
pub fn matmul(out: &mut [f32], a: MatRef, b: MatRef, accumulate: bool) {
    gemm_checked(out, a, b, accumulate, gemm::Parallelism::None);
}

/// Like [`matmul`] but lets `gemm` split the one product over `threads` threads
/// (used by the benchmark to measure the library's peak).
pub fn matmul_parallel(out: &mut [f32], a: MatRef, b: MatRef, threads: usize) {
    gemm_checked(out, a, b, false, gemm::Parallelism::Rayon(threads));
}

fn gemm_checked(
    out: &mut [f32],
    a: MatRef,
    b: MatRef,
    accumulate: bool,
    parallelism: gemm::Parallelism,
) {
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
    // SAFETY: the asserts above and in `MatRef::new` keep every index the strides reach
    // inside the slices: a's largest is (m-1)*rs + (k-1)*cs < rows*cols <= len, same for b,
    // and out is m*n dense. The output does not alias the inputs (it is `&mut`).
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            out.as_mut_ptr(),
            1,
            n as isize,
            accumulate,
            a.data.as_ptr(),
            a.col_stride as isize,
            a.row_stride as isize,
            b.data.as_ptr(),
            b.col_stride as isize,
            b.row_stride as isize,
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
}
