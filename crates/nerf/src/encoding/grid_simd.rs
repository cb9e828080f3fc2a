//! The hash grids' inner loops for eight samples at once (AVX2), one vector lane per
//! sample: a cell's corners (table indices and trilinear weights, [`corners8`]) and the
//! weighted sum of the corners' features ([`interpolate8`]). Their tests, against the
//! scalar loops, sit with the grids; other CPUs run those scalar loops.
//!
//! The numbers are those of the scalar loops to the bit: the same operations in the same
//! order (no fused multiply-adds, the weights multiplied x, then y, then z, the corners
//! summed in order), so a machine without AVX2 trains the same run. Only finite coordinates are promised that;
//! a NaN coordinate clamps to the cube's face here and stays NaN in the scalar path, and
//! both are garbage the engine's finiteness checks catch upstream.

/// What [`corners8`] needs of a hash-grid level.
#[derive(Clone, Copy)]
pub(crate) struct LevelShape {
    /// Cells per axis.
    pub resolution: u32,
    /// Table entries (a power of two when hashed).
    pub entries: usize,
    /// Vertices indexed densely rather than hashed.
    pub dense: bool,
    /// The spatial hash's multipliers of y and z.
    pub primes: [u32; 2],
}

/// Samples per call: the lanes of one AVX2 vector of `f32`.
pub(crate) const LANES: usize = 8;

/// Whether this CPU runs the loops (checked once; the standard library caches it).
#[inline]
pub(crate) fn available() -> bool {
    std::is_x86_feature_detected!("avx2")
}

/// The corners of [`LANES`] points (`points`: packed `x, y, z`) in a level of `shape`
/// (the scalar `Level::corners` of the hash grid, eight at a time): `idx[k][first + j]`
/// and `w[k][first + j]` receive corner `k`'s table index and weight of point `j`.
///
/// # Safety
/// The CPU must have AVX2 ([`available`]).
#[target_feature(enable = "avx2")]
pub(crate) unsafe fn corners8<const G: usize>(
    level: LevelShape,
    points: &[f32; 3 * LANES],
    idx: &mut [[u32; G]; 8],
    w: &mut [[f32; G]; 8],
    first: usize,
) {
    use std::arch::x86_64::*;
    let n = level.resolution;
    let cells = _mm256_set1_ps(n as f32);
    let last = _mm256_set1_epi32((n - 1) as i32);
    let (zero, one) = (_mm256_setzero_ps(), _mm256_set1_ps(1.0));
    let mut cell = [_mm256_setzero_si256(); 3];
    let mut frac = [zero; 3];
    let mut rest = [zero; 3];
    for a in 0..3 {
        let coords: [f32; LANES] = std::array::from_fn(|j| points[3 * j + a]);
        // SAFETY: `coords` holds LANES floats.
        let u = unsafe { _mm256_loadu_ps(coords.as_ptr()) };
        let p = _mm256_mul_ps(_mm256_min_ps(_mm256_max_ps(u, zero), one), cells);
        // `p` lies in [0, n], so truncation is the scalar `as u32`.
        let c = _mm256_min_epu32(_mm256_cvttps_epi32(p), last);
        cell[a] = c;
        frac[a] = _mm256_sub_ps(p, _mm256_cvtepi32_ps(c));
        rest[a] = _mm256_sub_ps(one, frac[a]);
    }
    let step = _mm256_set1_epi32(1);
    let mask = _mm256_set1_epi32((level.entries - 1) as i32);
    let side = _mm256_set1_epi32((n + 1) as i32);
    let (prime_y, prime_z) = (
        _mm256_set1_epi32(level.primes[0] as i32),
        _mm256_set1_epi32(level.primes[1] as i32),
    );
    for k in 0..8 {
        let b = [k & 1, (k >> 1) & 1, (k >> 2) & 1];
        let at: [__m256i; 3] = std::array::from_fn(|a| {
            if b[a] == 1 {
                _mm256_add_epi32(cell[a], step)
            } else {
                cell[a]
            }
        });
        let index = if level.dense {
            let yz = _mm256_add_epi32(at[1], _mm256_mullo_epi32(side, at[2]));
            _mm256_add_epi32(at[0], _mm256_mullo_epi32(side, yz))
        } else {
            let hashed = _mm256_xor_si256(
                _mm256_xor_si256(at[0], _mm256_mullo_epi32(at[1], prime_y)),
                _mm256_mullo_epi32(at[2], prime_z),
            );
            _mm256_and_si256(hashed, mask)
        };
        let pick = |a: usize| if b[a] == 1 { frac[a] } else { rest[a] };
        let weight = _mm256_mul_ps(_mm256_mul_ps(pick(0), pick(1)), pick(2));
        let (idx, w) = (
            &mut idx[k][first..first + LANES],
            &mut w[k][first..first + LANES],
        );
        // SAFETY: `idx` and `w` hold LANES values each; unaligned stores.
        unsafe {
            _mm256_storeu_si256(idx.as_mut_ptr().cast::<__m256i>(), index);
            _mm256_storeu_ps(w.as_mut_ptr(), weight);
        }
    }
}

/// The features of [`LANES`] samples, `Σ_k w[k][j] * table[idx[k][j]]` for each of the two
/// features (`C` corners; `idx` and `w` corner-major, the group's samples `first..first +
/// LANES`), returned as the two features' lanes.
///
/// # Safety
/// The CPU must have AVX2 ([`available`]), and every `idx[k][first + j]` must index an
/// entry of `table` (`2 * idx + 1 < table.len()`).
#[target_feature(enable = "avx2")]
pub(crate) unsafe fn interpolate8<const C: usize, const G: usize>(
    table: &[f32],
    idx: &[[u32; G]; C],
    w: &[[f32; G]; C],
    first: usize,
) -> [[f32; LANES]; 2] {
    use std::arch::x86_64::*;
    // Each entry's two features as one 64-bit element: the gather of samples
    // 0, 1, 4, 5 and that of 2, 3, 6, 7 interleave back into the lanes in order.
    let order = _mm256_setr_epi32(0, 1, 4, 5, 2, 3, 6, 7);
    let base = table.as_ptr().cast::<f64>();
    let mut f = [_mm256_setzero_ps(); 2];
    for k in 0..C {
        // SAFETY: `first + LANES <= G` (the caller's group), unaligned loads.
        let (at, weight) = unsafe {
            (
                _mm256_loadu_si256(idx[k][first..first + LANES].as_ptr().cast::<__m256i>()),
                _mm256_loadu_ps(w[k][first..first + LANES].as_ptr()),
            )
        };
        let at = _mm256_permutevar8x32_epi32(at, order);
        // SAFETY: the caller promises every index inside `table`; an entry is 8 bytes.
        let (low, high) = unsafe {
            (
                _mm256_i32gather_pd::<8>(base, _mm256_castsi256_si128(at)),
                _mm256_i32gather_pd::<8>(base, _mm256_extracti128_si256::<1>(at)),
            )
        };
        let (low, high) = (_mm256_castpd_ps(low), _mm256_castpd_ps(high));
        let first_feature = _mm256_shuffle_ps::<0b10_00_10_00>(low, high);
        let second_feature = _mm256_shuffle_ps::<0b11_01_11_01>(low, high);
        f[0] = _mm256_add_ps(f[0], _mm256_mul_ps(weight, first_feature));
        f[1] = _mm256_add_ps(f[1], _mm256_mul_ps(weight, second_feature));
    }
    let mut out = [[0f32; LANES]; 2];
    // SAFETY: `out[i]` holds LANES floats.
    unsafe {
        _mm256_storeu_ps(out[0].as_mut_ptr(), f[0]);
        _mm256_storeu_ps(out[1].as_mut_ptr(), f[1]);
    }
    out
}
