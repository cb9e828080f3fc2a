//! Matrix products with bfloat16 inputs and `f32` sums, on CPUs with AVX-512 BF16.
//!
//! `vdpbf16ps` multiplies pairs of bfloat16 values and adds both products to an `f32`
//! lane, so it does twice the multiply-adds of an `f32` FMA per instruction: on a Zen 4
//! core the small networks' products run at about twice the `f32` peak. Inputs are
//! rounded to bfloat16 (8 significant bits) inside the kernels, a block of rows at a time
//! into a buffer that stays in L1; every sum stays in `f32`.
//!
//! Two shapes cover a layer's forward and backward:
//! - [`rows_product`]: `out = a b` with `a`'s rows contiguous (`X W` and `dY W^T`), the
//!   reduction running along `a`'s rows, paired two by two;
//! - [`pairs_product`]: `out = x^T y` (the weight gradient `X^T dY`), the reduction
//!   running over the samples, paired two rows at a time.

#[cfg(target_arch = "x86_64")]
use std::arch::x86_64::*;

/// Whether this CPU runs the kernels (AVX-512 F, BW and BF16).
pub fn available() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx512f")
            && std::arch::is_x86_feature_detected!("avx512bw")
            && std::arch::is_x86_feature_detected!("avx512bf16")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// Lanes of an `f32` vector.
const LANES: usize = 16;

fn round_up(v: usize, to: usize) -> usize {
    v.div_ceil(to) * to
}

/// `v` rounded to bfloat16 (nearest even, as the kernels round), back as an `f32`.
pub fn round_to_bf16(v: f32) -> f32 {
    f32::from_bits(bf16_bits(v) << 16)
}

/// bfloat16 of `v`, rounded to nearest even as the hardware's conversion rounds.
fn bf16_bits(v: f32) -> u32 {
    let bits = v.to_bits();
    if v.is_nan() {
        return (bits >> 16) | 0x40;
    }
    bits.wrapping_add(0x7fff + ((bits >> 16) & 1)) >> 16
}

/// The right operand of [`rows_product`] (`k x n`), rounded to bfloat16 and laid out as
/// pairs of rows: word `j * cols + c` holds rows `2j` and `2j + 1` of column `c` (the low
/// half the even row), zeros past `k` and `n`.
pub struct PackedRight {
    words: Vec<u32>,
    pairs: usize,
    /// Columns rounded up to a whole vector.
    cols: usize,
    n: usize,
}

impl PackedRight {
    /// Packs the `k x n` matrix whose element `(r, c)` is `at(r, c)`.
    pub fn new(k: usize, n: usize, at: impl Fn(usize, usize) -> f32) -> PackedRight {
        let (pairs, cols) = (k.div_ceil(2), round_up(n, LANES));
        let mut words = vec![0u32; pairs * cols];
        for j in 0..pairs {
            for c in 0..n {
                let lo = bf16_bits(at(2 * j, c));
                let hi = if 2 * j + 1 < k {
                    bf16_bits(at(2 * j + 1, c))
                } else {
                    0
                };
                words[j * cols + c] = lo | hi << 16;
            }
        }
        PackedRight {
            words,
            pairs,
            cols,
            n,
        }
    }
}

/// `out (m x n, dense) = a b`, or `+=` when `accumulate`: `a` is `m x k` with its rows at
/// stride `a_stride` (each row's `k` values contiguous), `b` packed. Panics if a slice is
/// shorter than the shapes need, or if the CPU lacks the kernels ([`available`]).
pub fn rows_product(
    out: &mut [f32],
    a: &[f32],
    a_stride: usize,
    m: usize,
    k: usize,
    b: &PackedRight,
    accumulate: bool,
) {
    let n = b.n;
    assert!(available(), "the CPU has no AVX-512 BF16");
    assert_eq!(b.pairs, k.div_ceil(2), "inner dimensions differ");
    assert!(out.len() >= m * n, "output too short");
    assert!(
        m == 0 || a.len() >= (m - 1) * a_stride + k,
        "left operand too short"
    );
    #[cfg(target_arch = "x86_64")]
    // SAFETY: the CPU has the features (asserted), and the asserts above keep every access
    // inside the slices.
    unsafe {
        x86::rows_product(out, a, a_stride, m, k, b, accumulate)
    }
}

/// `out (k x n, dense) = x^T y`, or `+=` when `accumulate`: `x` is `m x k` and `y` is
/// `m x n`, each with its rows at its stride (each row's values contiguous). Panics as
/// [`rows_product`] does.
#[allow(clippy::too_many_arguments)]
pub fn pairs_product(
    out: &mut [f32],
    x: &[f32],
    x_stride: usize,
    k: usize,
    y: &[f32],
    y_stride: usize,
    n: usize,
    m: usize,
    accumulate: bool,
) {
    assert!(available(), "the CPU has no AVX-512 BF16");
    assert!(out.len() >= k * n, "output too short");
    assert!(
        m == 0 || x.len() >= (m - 1) * x_stride + k,
        "left operand too short"
    );
    assert!(
        m == 0 || y.len() >= (m - 1) * y_stride + n,
        "right operand too short"
    );
    #[cfg(target_arch = "x86_64")]
    if n < 2 * LANES && k > n {
        // Few columns fill few lanes: the transpose `y^T x` runs `k` across them instead.
        let mut transposed = vec![0.0; n * k];
        // SAFETY: as in `rows_product`.
        unsafe { x86::pairs_product(&mut transposed, y, y_stride, n, x, x_stride, k, m, false) }
        for (r, row) in out.chunks_exact_mut(n).take(k).enumerate() {
            for (c, v) in row.iter_mut().enumerate() {
                let t = transposed[c * k + r];
                *v = if accumulate { *v + t } else { t };
            }
        }
    } else {
        // SAFETY: as in `rows_product`.
        unsafe { x86::pairs_product(out, x, x_stride, k, y, y_stride, n, m, accumulate) }
    }
}

#[cfg(target_arch = "x86_64")]
mod x86 {
    use super::*;

    /// Rows of the left operand (or of the weight gradient's output) a block holds: enough
    /// independent sums to cover the product's latency, few enough to stay in registers.
    fn block_rows(vectors: usize) -> usize {
        match vectors {
            4 => 6,
            3 => 8,
            _ => 12,
        }
    }

    /// Samples a weight gradient packs at a time (their pairs stay in L1 and L2).
    const CHUNK: usize = 256;

    /// Lanes `0..count` of a vector (all for `count >= 16`).
    fn mask(count: usize) -> __mmask16 {
        if count >= LANES {
            0xffff
        } else {
            ((1u32 << count) - 1) as __mmask16
        }
    }

    /// The bfloat16 pairs of `count <= 32` values at `p` (zeros past them), as 16 words.
    #[target_feature(enable = "avx512f,avx512bw,avx512bf16")]
    unsafe fn pairs_along(p: *const f32, count: usize) -> __m512i {
        // SAFETY: the caller guarantees the CPU features and the bounds.
        unsafe {
            let lo = _mm512_maskz_loadu_ps(mask(count), p);
            let hi = if count > LANES {
                _mm512_maskz_loadu_ps(mask(count - LANES), p.add(LANES))
            } else {
                _mm512_setzero_ps()
            };
            std::mem::transmute::<__m512bh, __m512i>(_mm512_cvtne2ps_pbh(hi, lo))
        }
    }

    /// The bfloat16 pairs of two rows' `count <= 16` values at `even` and `odd` (the low
    /// half from `even`), as 16 words.
    #[target_feature(enable = "avx512f,avx512bw,avx512bf16")]
    unsafe fn pairs_across(even: *const f32, odd: Option<*const f32>, count: usize) -> __m512i {
        // SAFETY: the caller guarantees the CPU features and the bounds.
        unsafe {
            const INTERLEAVE: [i16; 32] = {
                let mut idx = [0i16; 32];
                let mut l = 0;
                while l < 32 {
                    idx[l] = (l / 2 + (l % 2) * 16) as i16;
                    l += 1;
                }
                idx
            };
            let lo = _mm512_maskz_loadu_ps(mask(count), even);
            let hi = match odd {
                Some(p) => _mm512_maskz_loadu_ps(mask(count), p),
                None => _mm512_setzero_ps(),
            };
            let both = std::mem::transmute::<__m512bh, __m512i>(_mm512_cvtne2ps_pbh(hi, lo));
            let idx = _mm512_loadu_si512(INTERLEAVE.as_ptr() as *const _);
            _mm512_permutexvar_epi16(idx, both)
        }
    }

    #[target_feature(enable = "avx512f,avx512bw,avx512bf16")]
    unsafe fn dot(acc: __m512, a: __m512i, b: __m512i) -> __m512 {
        // SAFETY: the caller guarantees the CPU features and the bounds.
        unsafe {
            _mm512_dpbf16_ps(
                acc,
                std::mem::transmute::<__m512i, __m512bh>(a),
                std::mem::transmute::<__m512i, __m512bh>(b),
            )
        }
    }

    #[target_feature(enable = "avx512f,avx512bw,avx512bf16")]
    pub(super) unsafe fn rows_product(
        out: &mut [f32],
        a: &[f32],
        a_stride: usize,
        m: usize,
        k: usize,
        b: &PackedRight,
        accumulate: bool,
    ) {
        // SAFETY: the caller guarantees the CPU features and the bounds.
        unsafe {
            let n = b.n;
            // A block's rows as pairs, each row a whole number of vectors long.
            let row_words = round_up(b.pairs, LANES);
            let mut scratch = vec![0u32; 12 * row_words];
            let mut c0 = 0;
            while c0 < n {
                let vectors = (n - c0).div_ceil(LANES).min(4);
                let rows = block_rows(vectors);
                let mut r0 = 0;
                while r0 < m {
                    let block = rows.min(m - r0);
                    for r in 0..block {
                        let row = a.as_ptr().add((r0 + r) * a_stride);
                        for (w, at) in (0..k).step_by(2 * LANES).enumerate() {
                            let v = pairs_along(row.add(at), k - at);
                            _mm512_storeu_si512(
                                scratch.as_mut_ptr().add(r * row_words + w * LANES) as *mut _,
                                v,
                            );
                        }
                    }
                    let dst = out.as_mut_ptr().add(r0 * n + c0);
                    let args = (dst, n, n - c0, &scratch[..], row_words, b, c0, accumulate);
                    match (vectors, block == rows) {
                        (4, true) => rows_block::<4, 6>(args),
                        (3, true) => rows_block::<3, 8>(args),
                        (2, true) => rows_block::<2, 12>(args),
                        (1, true) => rows_block::<1, 12>(args),
                        _ => {
                            for r in 0..block {
                                let dst = out.as_mut_ptr().add((r0 + r) * n + c0);
                                let row = &scratch[r * row_words..];
                                let args = (dst, n, n - c0, row, row_words, b, c0, accumulate);
                                match vectors {
                                    4 => rows_block::<4, 1>(args),
                                    3 => rows_block::<3, 1>(args),
                                    2 => rows_block::<2, 1>(args),
                                    _ => rows_block::<1, 1>(args),
                                }
                            }
                        }
                    }
                    r0 += block;
                }
                c0 += 4 * LANES;
            }
        }
    }

    /// `(output at the block's first row and column, output row stride, columns left from
    /// there, the block's packed rows, their stride, b, b's first column, accumulate)`.
    type RowsArgs<'a> = (
        *mut f32,
        usize,
        usize,
        &'a [u32],
        usize,
        &'a PackedRight,
        usize,
        bool,
    );

    #[target_feature(enable = "avx512f,avx512bw,avx512bf16")]
    #[inline]
    unsafe fn rows_block<const V: usize, const R: usize>(args: RowsArgs) {
        // SAFETY: the caller guarantees the CPU features and the bounds.
        unsafe {
            let (dst, stride, cols_left, rows, row_words, b, c0, accumulate) = args;
            let mut acc = [[_mm512_setzero_ps(); V]; R];
            if accumulate {
                for (r, acc_r) in acc.iter_mut().enumerate() {
                    for (q, v) in acc_r.iter_mut().enumerate() {
                        let m = mask(cols_left.saturating_sub(q * LANES));
                        *v = _mm512_maskz_loadu_ps(m, dst.add(r * stride + q * LANES));
                    }
                }
            }
            let bw = b.words.as_ptr().add(c0);
            for j in 0..b.pairs {
                let mut bv = [_mm512_setzero_si512(); V];
                for (q, v) in bv.iter_mut().enumerate() {
                    *v = _mm512_loadu_si512(bw.add(j * b.cols + q * LANES) as *const _);
                }
                for (r, acc_r) in acc.iter_mut().enumerate() {
                    let av = _mm512_set1_epi32(*rows.get_unchecked(r * row_words + j) as i32);
                    for q in 0..V {
                        acc_r[q] = dot(acc_r[q], av, bv[q]);
                    }
                }
            }
            for (r, acc_r) in acc.iter().enumerate() {
                for (q, v) in acc_r.iter().enumerate() {
                    let m = mask(cols_left.saturating_sub(q * LANES));
                    _mm512_mask_storeu_ps(dst.add(r * stride + q * LANES), m, *v);
                }
            }
        }
    }

    #[target_feature(enable = "avx512f,avx512bw,avx512bf16")]
    #[allow(clippy::too_many_arguments)]
    pub(super) unsafe fn pairs_product(
        out: &mut [f32],
        x: &[f32],
        x_stride: usize,
        k: usize,
        y: &[f32],
        y_stride: usize,
        n: usize,
        m: usize,
        accumulate: bool,
    ) {
        // SAFETY: the caller guarantees the CPU features and the bounds.
        unsafe {
            // The sums, `k` rounded up to 16 rows (so that blocks of 4, 8 or 16 rows fill
            // it), `n` to whole vectors; and a chunk's pairs of x and y, the same widths.
            let (rows, cols) = (round_up(k, LANES), round_up(n, LANES));
            let mut sums = vec![0f32; rows * cols];
            let mut xp = vec![0u32; CHUNK / 2 * rows];
            let mut yp = vec![0u32; CHUNK / 2 * cols];
            for s0 in (0..m).step_by(CHUNK) {
                let pairs = (m - s0).min(CHUNK).div_ceil(2);
                for i in 0..pairs {
                    let even = s0 + 2 * i;
                    let odd = (even + 1 < m).then_some(even + 1);
                    for (packed, width, src, stride, len) in [
                        (&mut xp, rows, x, x_stride, k),
                        (&mut yp, cols, y, y_stride, n),
                    ] {
                        for c in (0..len).step_by(LANES) {
                            let v = pairs_across(
                                src.as_ptr().add(even * stride + c),
                                odd.map(|o| src.as_ptr().add(o * stride + c)),
                                len - c,
                            );
                            _mm512_storeu_si512(
                                packed.as_mut_ptr().add(i * width + c) as *mut _,
                                v,
                            );
                        }
                    }
                }
                for c0 in (0..cols).step_by(4 * LANES) {
                    let vectors = ((cols - c0) / LANES).min(4);
                    // Rows of sums a block holds (4, 8 or 16, dividing `rows`, a multiple of 16).
                    let height = match vectors {
                        4 | 3 => 4,
                        2 => 8,
                        _ => 16,
                    };
                    for r0 in (0..round_up(k, height)).step_by(height) {
                        let args = (&mut sums[..], cols, &xp[..], rows, &yp[..], pairs, r0, c0);
                        match vectors {
                            4 => pairs_block::<4, 4>(args),
                            3 => pairs_block::<3, 4>(args),
                            2 => pairs_block::<2, 8>(args),
                            _ => pairs_block::<1, 16>(args),
                        }
                    }
                }
            }
            for r in 0..k {
                let (dst, src) = (&mut out[r * n..][..n], &sums[r * cols..][..n]);
                if accumulate {
                    dst.iter_mut().zip(src).for_each(|(d, s)| *d += s);
                } else {
                    dst.copy_from_slice(src);
                }
            }
        }
    }

    /// `(the sums, their row stride, x's pairs, their row stride, y's pairs, pairs, the
    /// block's first row of sums, its first column)`.
    type PairsArgs<'a> = (
        &'a mut [f32],
        usize,
        &'a [u32],
        usize,
        &'a [u32],
        usize,
        usize,
        usize,
    );

    #[target_feature(enable = "avx512f,avx512bw,avx512bf16")]
    #[inline]
    unsafe fn pairs_block<const V: usize, const R: usize>(args: PairsArgs) {
        // SAFETY: the caller guarantees the CPU features and the bounds.
        unsafe {
            let (sums, cols, xp, rows, yp, pairs, r0, c0) = args;
            let base = sums.as_mut_ptr().add(r0 * cols + c0);
            let mut acc = [[_mm512_setzero_ps(); V]; R];
            for (r, acc_r) in acc.iter_mut().enumerate() {
                for (q, v) in acc_r.iter_mut().enumerate() {
                    *v = _mm512_loadu_ps(base.add(r * cols + q * LANES));
                }
            }
            for i in 0..pairs {
                let mut yv = [_mm512_setzero_si512(); V];
                for (q, v) in yv.iter_mut().enumerate() {
                    *v = _mm512_loadu_si512(yp.as_ptr().add(i * cols + c0 + q * LANES) as *const _);
                }
                for (r, acc_r) in acc.iter_mut().enumerate() {
                    let xv = _mm512_set1_epi32(*xp.get_unchecked(i * rows + r0 + r) as i32);
                    for q in 0..V {
                        acc_r[q] = dot(acc_r[q], xv, yv[q]);
                    }
                }
            }
            for (r, acc_r) in acc.iter().enumerate() {
                for (q, v) in acc_r.iter().enumerate() {
                    _mm512_storeu_ps(base.add(r * cols + q * LANES), *v);
                }
            }
        }
    }
}
