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

#[cfg(test)]
mod tests {
    use super::erf;

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
}
