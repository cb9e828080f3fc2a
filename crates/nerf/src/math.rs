//! Tiny 3-vector helpers over `[f32; 3]`; enough for cameras and the scene generator.

pub type V3 = [f32; 3];

#[inline]
pub fn add(a: V3, b: V3) -> V3 {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}
#[inline]
pub fn sub(a: V3, b: V3) -> V3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
#[inline]
pub fn scale(a: V3, s: f32) -> V3 {
    [a[0] * s, a[1] * s, a[2] * s]
}
#[inline]
pub fn mul(a: V3, b: V3) -> V3 {
    [a[0] * b[0], a[1] * b[1], a[2] * b[2]]
}
#[inline]
pub fn dot(a: V3, b: V3) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
#[inline]
pub fn cross(a: V3, b: V3) -> V3 {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}
#[inline]
pub fn length(a: V3) -> f32 {
    dot(a, a).sqrt()
}
/// Unit vector along `a`; the zero vector stays zero rather than becoming NaN.
#[inline]
pub fn normalize_or_zero(a: V3) -> V3 {
    let l = length(a);
    if l > 0.0 {
        scale(a, 1.0 / l)
    } else {
        [0.0; 3]
    }
}

/// The error function, to 1.5e-7 (Abramowitz & Stegun 7.1.26); odd, 1 at infinity.
#[inline]
pub fn erf(x: f32) -> f32 {
    let a = x.abs();
    if a.is_infinite() {
        return x.signum();
    }
    let t = 1.0 / (1.0 + 0.327_591_1 * a);
    let poly = t
        * (0.254_829_6
            + t * (-0.284_496_74 + t * (1.421_413_7 + t * (-1.453_152 + t * 1.061_405_4))));
    (1.0 - poly * (-a * a).exp()).copysign(x)
}

/// `exp(y)` for `y <= 0`, to about 2e-7 relative (inputs under -87 give about 1.6e-38).
/// Branch-free arithmetic with no library call, so a loop over it vectorises, which the
/// library's `exp` (a call per value) does not.
#[inline(always)]
pub fn exp_nonpositive(y: f32) -> f32 {
    // y = k ln 2 + r with |r| <= ln 2 / 2, so exp(y) = 2^k exp(r).
    const ROUND: f32 = 12_582_912.0; // 1.5 * 2^23: adding it rounds to an integer.
    const LN2_HI: f32 = 0.693_145_75;
    const LN2_LO: f32 = 1.428_606_8e-6;
    let y = y.max(-87.0);
    let rounded = y * std::f32::consts::LOG2_E + ROUND;
    let k = rounded - ROUND;
    // `ROUND + k` lies in [2^23, 2^24), where one unit is one step of the bits: the bits
    // are ROUND's plus k (a cast `k as i32` saturates and would not vectorise).
    let biased = rounded
        .to_bits()
        .wrapping_sub(ROUND.to_bits())
        .wrapping_add(127);
    let r = (y - k * LN2_HI) - k * LN2_LO;
    let p = 1.0
        + r * (1.0
            + r * (0.5
                + r * (1.0 / 6.0 + r * (1.0 / 24.0 + r * (1.0 / 120.0 + r * (1.0 / 720.0))))));
    p * f32::from_bits(biased << 23)
}

/// `erf(1 / sqrt(x))` for `x >= 0` (1 at 0), as [`erf`] computes it but branch-free, for
/// loops that should vectorise.
#[inline(always)]
pub fn erf_of_inv_sqrt(x: f32) -> f32 {
    let a = x.sqrt().recip();
    let t = 1.0 / (1.0 + 0.327_591_1 * a);
    let poly = t
        * (0.254_829_6
            + t * (-0.284_496_74 + t * (1.421_413_7 + t * (-1.453_152 + t * 1.061_405_4))));
    1.0 - poly * exp_nonpositive(-x.recip())
}

#[cfg(test)]
mod tests {
    use super::{erf, erf_of_inv_sqrt, exp_nonpositive};

    /// Against values from the series `2/sqrt(pi) sum (-1)^k x^(2k+1) / (k! (2k+1))`.
    #[test]
    fn erf_matches_its_series() {
        for &x in &[0.0f64, 0.1, 0.5, 1.0, 1.7, 2.5] {
            let mut sum = 0.0;
            let mut term = x; // (-1)^k x^(2k+1) / k!
            for k in 0..60 {
                sum += term / (2 * k + 1) as f64;
                term *= -x * x / (k + 1) as f64;
            }
            let exact = 2.0 / std::f64::consts::PI.sqrt() * sum;
            let got = erf(x as f32) as f64;
            assert!(
                (got - exact).abs() < 3e-7,
                "erf({x}) = {got}, series {exact}"
            );
            assert!((erf(-x as f32) as f64 + exact).abs() < 3e-7);
        }
        assert_eq!(erf(f32::INFINITY), 1.0);
        assert!((erf(10.0) - 1.0).abs() < 1e-7);
    }

    #[test]
    fn branch_free_exp_matches_the_library() {
        let mut y = 0.0f32;
        while y > -90.0 {
            let (got, want) = (exp_nonpositive(y), y.exp());
            assert!(
                (got - want).abs() <= 3e-7 * want + 1e-37,
                "exp({y}) = {got}, library {want}"
            );
            y -= 0.013_7;
        }
        assert_eq!(exp_nonpositive(0.0), 1.0);
        assert!(exp_nonpositive(f32::NEG_INFINITY) < 1e-37);
    }

    #[test]
    fn branch_free_erf_matches_erf() {
        assert_eq!(erf_of_inv_sqrt(0.0), 1.0);
        let mut x = 1e-6f32;
        while x < 1e6 {
            let (got, want) = (erf_of_inv_sqrt(x), erf(x.sqrt().recip()));
            assert!((got - want).abs() < 3e-7, "x = {x}: {got} vs {want}");
            x *= 1.07;
        }
    }
}
