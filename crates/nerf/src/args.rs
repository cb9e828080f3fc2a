//! Parsers of the command line's numbers, shared by every command: a NaN, an infinity or a
//! value outside its range is refused by clap with the reason, before any work starts.

fn number(s: &str) -> Result<f64, String> {
    let v: f64 = s.trim().parse().map_err(|e| format!("{s:?}: {e}"))?;
    if v.is_finite() {
        Ok(v)
    } else {
        Err(format!("{s} is not a finite number"))
    }
}

/// Any finite number.
pub fn finite(s: &str) -> Result<f32, String> {
    number(s).map(|v| v as f32)
}

/// A finite number above zero.
pub fn positive(s: &str) -> Result<f32, String> {
    positive_f64(s).map(|v| v as f32)
}

/// A finite number above zero, in double precision (durations).
pub fn positive_f64(s: &str) -> Result<f64, String> {
    match number(s)? {
        v if v > 0.0 => Ok(v),
        v => Err(format!("{v} must be above 0")),
    }
}

/// A finite number from 0 to 1.
pub fn fraction(s: &str) -> Result<f32, String> {
    match number(s)? {
        v if (0.0..=1.0).contains(&v) => Ok(v as f32),
        v => Err(format!("{v} must be between 0 and 1")),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nan_infinity_and_out_of_range_are_refused() {
        for bad in ["NaN", "inf", "-inf", "x", ""] {
            assert!(finite(bad).is_err(), "{bad}");
            assert!(positive(bad).is_err(), "{bad}");
            assert!(fraction(bad).is_err(), "{bad}");
        }
        assert_eq!(finite("-2.5"), Ok(-2.5));
        assert!(positive("0").is_err() && positive("-1").is_err());
        assert_eq!(positive("24"), Ok(24.0));
        assert!(fraction("1.5").is_err() && fraction("-0.1").is_err());
        assert_eq!(fraction("0.95"), Ok(0.95));
    }
}
