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

/// `out (m x n, dense) = a b`, or `+=` when `accumulate`, for `a` of `m` rows of `k` and
/// `b` packed. Panics if a slice is shorter than the shapes need, or if the CPU lacks the
/// kernels ([`available`]).
pub fn rows_product(out: &mut [f32], a: Rows, m: usize, b: &PackedRight, accumulate: bool) {
    assert!(available(), "the CPU has no AVX-512 BF16");
    assert_eq!(b.pairs, a.cols.div_ceil(2), "inner dimensions differ");
    assert!(out.len() >= m * b.n, "output too short");
    a.assert_holds(m, "left operand");
    #[cfg(target_arch = "x86_64")]
    // SAFETY: the CPU has the features (asserted), and the asserts above keep every access
    // inside the slices.
    unsafe {
        x86::rows_product(out, a, m, b, accumulate)
    }
}

/// Rows of a matrix: row `r`'s `cols` values from `values[r * stride]`, contiguous.
#[derive(Clone, Copy)]
pub struct Rows<'a> {
    pub values: &'a [f32],
    pub stride: usize,
    pub cols: usize,
}

impl Rows<'_> {
    /// Panics unless `count` rows fit in the values.
    fn assert_holds(self, count: usize, what: &str) {
        assert!(
            count == 0 || self.values.len() >= (count - 1) * self.stride + self.cols,
            "{what} too short"
        );
    }
}

/// `out (k x n, dense) = x^T y`, or `+=` when `accumulate`, for `x` of `m` rows of `k`
/// and `y` of `m` rows of `n`. Panics as [`rows_product`] does.
pub fn pairs_product(out: &mut [f32], x: Rows, y: Rows, m: usize, accumulate: bool) {
    let (k, n) = (x.cols, y.cols);
    assert!(available(), "the CPU has no AVX-512 BF16");
    assert!(out.len() >= k * n, "output too short");
    x.assert_holds(m, "left operand");
    y.assert_holds(m, "right operand");
    #[cfg(target_arch = "x86_64")]
    if n < 2 * LANES && k > n {
        // Few columns fill few lanes: the transpose `y^T x` runs `k` across them instead.
        let mut transposed = vec![0.0; n * k];
        // SAFETY: as in `rows_product`.
        unsafe { x86::pairs_product(&mut transposed, y, x, m, false) }
        for (r, row) in out.chunks_exact_mut(n).take(k).enumerate() {
            for (c, v) in row.iter_mut().enumerate() {
                let t = transposed[c * k + r];
                *v = if accumulate { *v + t } else { t };
            }
        }
    } else {
        // SAFETY: as in `rows_product`.
        unsafe { x86::pairs_product(out, x, y, m, accumulate) }
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
        a: Rows,
        m: usize,
        b: &PackedRight,
        accumulate: bool,
    ) {
        // SAFETY: the caller guarantees the CPU features and the bounds.
        unsafe {
            let (n, k) = (b.n, a.cols);
            // A block's rows as pairs, each row a whole number of vectors long.
            let row_words = round_up(b.pairs, LANES);
            let mut scratch = vec![0u32; 12 * row_words];
            let out_ptr = out.as_mut_ptr();
            let mut c0 = 0;
            while c0 < n {
                let vectors = (n - c0).div_ceil(LANES).min(4);
                let rows = block_rows(vectors);
                let mut r0 = 0;
                while r0 < m {
                    let block = rows.min(m - r0);
                    for r in 0..block {
                        let row = a.values.as_ptr().add((r0 + r) * a.stride);
                        for (w, at) in (0..k).step_by(2 * LANES).enumerate() {
                            let v = pairs_along(row.add(at), k - at);
                            _mm512_storeu_si512(
                                scratch.as_mut_ptr().add(r * row_words + w * LANES) as *mut _,
                                v,
                            );
                        }
                    }
                    let tile = |r: usize| Tile {
                        at: out_ptr.add((r0 + r) * n + c0),
                        stride: n,
                        cols: n - c0,
                        accumulate,
                    };
                    let operands = |r: usize| Operands {
                        left: scratch.as_ptr().add(r * row_words),
                        left_row: row_words,
                        left_step: 1,
                        right: b.words.as_ptr().add(c0),
                        right_step: b.cols,
                        steps: b.pairs,
                    };
                    match (vectors, block == rows) {
                        (4, true) => block_of::<4, 6>(tile(0), operands(0)),
                        (3, true) => block_of::<3, 8>(tile(0), operands(0)),
                        (2, true) => block_of::<2, 12>(tile(0), operands(0)),
                        (1, true) => block_of::<1, 12>(tile(0), operands(0)),
                        _ => {
                            for r in 0..block {
                                let (t, o) = (tile(r), operands(r));
                                match vectors {
                                    4 => block_of::<4, 1>(t, o),
                                    3 => block_of::<3, 1>(t, o),
                                    2 => block_of::<2, 1>(t, o),
                                    _ => block_of::<1, 1>(t, o),
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

    #[target_feature(enable = "avx512f,avx512bw,avx512bf16")]
    pub(super) unsafe fn pairs_product(
        out: &mut [f32],
        x: Rows,
        y: Rows,
        m: usize,
        accumulate: bool,
    ) {
        // SAFETY: the caller guarantees the CPU features and the bounds.
        unsafe {
            let (k, n) = (x.cols, y.cols);
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
                    for (packed, width, src) in [(&mut xp, rows, x), (&mut yp, cols, y)] {
                        let at =
                            |row: usize, c: usize| src.values.as_ptr().add(row * src.stride + c);
                        for c in (0..src.cols).step_by(LANES) {
                            let v = pairs_across(at(even, c), odd.map(|o| at(o, c)), src.cols - c);
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
                        let tile = Tile {
                            at: sums.as_mut_ptr().add(r0 * cols + c0),
                            stride: cols,
                            cols: cols - c0,
                            accumulate: true,
                        };
                        let operands = Operands {
                            left: xp.as_ptr().add(r0),
                            left_row: 1,
                            left_step: rows,
                            right: yp.as_ptr().add(c0),
                            right_step: cols,
                            steps: pairs,
                        };
                        match vectors {
                            4 => block_of::<4, 4>(tile, operands),
                            3 => block_of::<3, 4>(tile, operands),
                            2 => block_of::<2, 8>(tile, operands),
                            _ => block_of::<1, 16>(tile, operands),
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

    /// A block of outputs: `R` rows of `V` vectors from `at`, rows `stride` apart, of which
    /// `cols` columns are real (the rest neither read nor written); with `accumulate` the
    /// sums start from what is there, else from zero.
    #[derive(Clone, Copy)]
    struct Tile {
        at: *mut f32,
        stride: usize,
        cols: usize,
        accumulate: bool,
    }

    /// The packed operands of a block's sums over `steps` pairs: the left word of the
    /// block's row `r` at step `i` is at `left + r * left_row + i * left_step`, the right
    /// vectors of step `i` from `right + i * right_step`.
    #[derive(Clone, Copy)]
    struct Operands {
        left: *const u32,
        left_row: usize,
        left_step: usize,
        right: *const u32,
        right_step: usize,
        steps: usize,
    }

    /// `tile (+)= left right` over the operands' steps: each step one broadcast of a row's
    /// pair against `V` vectors of pairs, `R x V` independent sums.
    #[target_feature(enable = "avx512f,avx512bw,avx512bf16")]
    #[inline]
    unsafe fn block_of<const V: usize, const R: usize>(tile: Tile, o: Operands) {
        // SAFETY: the caller guarantees the CPU features and the bounds.
        unsafe {
            let masks: [__mmask16; V] =
                std::array::from_fn(|q| mask(tile.cols.saturating_sub(q * LANES)));
            let mut acc = [[_mm512_setzero_ps(); V]; R];
            if tile.accumulate {
                for (r, acc_r) in acc.iter_mut().enumerate() {
                    for (q, v) in acc_r.iter_mut().enumerate() {
                        let at = tile.at.add(r * tile.stride + q * LANES);
                        *v = _mm512_maskz_loadu_ps(masks[q], at);
                    }
                }
            }
            for i in 0..o.steps {
                let right = o.right.add(i * o.right_step);
                let mut rv = [_mm512_setzero_si512(); V];
                for (q, v) in rv.iter_mut().enumerate() {
                    *v = _mm512_loadu_si512(right.add(q * LANES) as *const _);
                }
                for (r, acc_r) in acc.iter_mut().enumerate() {
                    let left = *o.left.add(r * o.left_row + i * o.left_step);
                    let lv = _mm512_set1_epi32(left as i32);
                    for q in 0..V {
                        acc_r[q] = dot(acc_r[q], lv, rv[q]);
                    }
                }
            }
            for (r, acc_r) in acc.iter().enumerate() {
                for (q, v) in acc_r.iter().enumerate() {
                    let at = tile.at.add(r * tile.stride + q * LANES);
                    _mm512_mask_storeu_ps(at, masks[q], *v);
                }
            }
        }
    }
}
