//! Loops compiled for the widest vectors the CPU has, chosen at run time.
//!
//! A plain loop of branch-free arithmetic vectorises in the baseline's vectors (SSE2 on
//! x86-64); [`in_width!`] compiles the same loop again for AVX2 and AVX-512 and picks by
//! [`Width`]. Each copy performs the same operations in the same order (Rust fuses no
//! multiply-add unless asked), so every width gives the same bits, which tests check by
//! running each width the CPU has.

/// A vector width the CPU running this process has. Only made by [`Width::widest`],
/// [`Width::available`] and [`Width::baseline`], so a width is always one the CPU runs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Width(Kind);

#[doc(hidden)]
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kind {
    Baseline,
    #[cfg(target_arch = "x86_64")]
    Avx2,
    #[cfg(target_arch = "x86_64")]
    Avx512,
}

impl Width {
    /// The target's baseline vectors, which every CPU of it has.
    pub fn baseline() -> Width {
        Width(Kind::Baseline)
    }

    /// The widest vectors this CPU has.
    pub fn widest() -> Width {
        #[cfg(target_arch = "x86_64")]
        {
            if std::arch::is_x86_feature_detected!("avx512f") {
                return Width(Kind::Avx512);
            }
            if std::arch::is_x86_feature_detected!("avx2") {
                return Width(Kind::Avx2);
            }
        }
        Width::baseline()
    }

    /// Every width this CPU has, the baseline first.
    pub fn available() -> Vec<Width> {
        #[cfg_attr(not(target_arch = "x86_64"), allow(unused_mut))]
        let mut widths = vec![Width::baseline()];
        #[cfg(target_arch = "x86_64")]
        {
            if std::arch::is_x86_feature_detected!("avx2") {
                widths.push(Width(Kind::Avx2));
            }
            if std::arch::is_x86_feature_detected!("avx512f") {
                widths.push(Width(Kind::Avx512));
            }
        }
        widths
    }

    #[doc(hidden)]
    pub fn kind(self) -> Kind {
        self.0
    }
}

/// `fn NAME(width: Width, ARGS)` running `BODY(ARGS)` (an `#[inline(always)]` function, so
/// that it compiles into each copy) in the vectors of `width`.
macro_rules! in_width {
    ($(#[$attr:meta])* $vis:vis fn $name:ident($($arg:ident: $ty:ty),* $(,)?) => $body:path) => {
        $(#[$attr])*
        $vis fn $name(width: $crate::simd::Width, $($arg: $ty),*) {
            #[cfg(target_arch = "x86_64")]
            #[target_feature(enable = "avx512f")]
            fn avx512($($arg: $ty),*) {
                $body($($arg),*)
            }
            #[cfg(target_arch = "x86_64")]
            #[target_feature(enable = "avx2")]
            fn avx2($($arg: $ty),*) {
                $body($($arg),*)
            }
            match width.kind() {
                // SAFETY: a `Width` is only made for features the CPU has.
                #[cfg(target_arch = "x86_64")]
                $crate::simd::Kind::Avx512 => unsafe { avx512($($arg),*) },
                // SAFETY: as above.
                #[cfg(target_arch = "x86_64")]
                $crate::simd::Kind::Avx2 => unsafe { avx2($($arg),*) },
                $crate::simd::Kind::Baseline => $body($($arg),*),
            }
        }
    };
}
pub(crate) use in_width;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_baseline_is_always_available_and_the_widest_among_them() {
        let all = Width::available();
        assert_eq!(all[0], Width::baseline());
        assert_eq!(all.last(), Some(&Width::widest()));
    }
}
