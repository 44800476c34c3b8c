//! 64-bit division without the compiler's 64-bit division routine on a 32-bit microcontroller.
//!
//! A `u64` or `i64` division on a 32-bit target calls compiler-builtins' `u64_div_rem` and its
//! `__aeabi_*divmod` wrappers, linked as soon as one place divides. The stack and the encoder
//! (which uses this module too: public, hidden from the docs) divide in 64 bits
//! only off their per-frame paths (a late timer's catch-up, a position in nm per measurement
//! cycle, derived parameters), so there one out-of-line shift-and-subtract loop, with its
//! 32-bit fast path, serves them all, in a fraction of that flash (docs/FIRMWARE.md, "Build
//! options in figures"). A 64-bit host divides natively, as before.

/// `(n / d, n % d)`. `d` must not be 0 (every caller divides by at least 1).
#[inline]
pub fn div_rem(n: u64, d: u64) -> (u64, u64) {
    debug_assert!(d != 0);
    #[cfg(target_pointer_width = "64")]
    {
        (n / d, n % d)
    }
    #[cfg(not(target_pointer_width = "64"))]
    {
        long_div(n, d)
    }
}

/// `n / d` for a `d` that is not 0.
#[inline]
pub fn div(n: u64, d: u64) -> u64 {
    div_rem(n, d).0
}

/// `n` divided by a positive `d`, rounded towards −∞ (`i64::div_euclid` for a positive
/// divisor).
#[inline]
pub fn div_floor(n: i64, d: u64) -> i64 {
    let (q, r) = div_rem(n.unsigned_abs(), d);
    if n >= 0 {
        q as i64
    } else {
        // −q, one further down when something was left over; `q ≤ 2^63`, so the negation
        // wraps only for i64::MIN itself, which it then is.
        (q + u64::from(r != 0)).wrapping_neg() as i64
    }
}

/// Binary long division, one quotient bit per step from the dividend's highest set bit (one
/// 32-bit division when both fit 32 bits).
/// Out of line: the one copy every 64-bit division of a 32-bit build shares (a 64-bit host
/// only tests it).
#[cfg(any(test, not(target_pointer_width = "64")))]
#[inline(never)]
pub(crate) fn long_div(n: u64, d: u64) -> (u64, u64) {
    if (n | d) >> 32 == 0 {
        // Both fit a register: the processor's own 32-bit division.
        let (n, d) = (n as u32, d as u32);
        return (u64::from(n / d), u64::from(n % d));
    }
    let (mut q, mut r) = (0u64, 0u64);
    let mut bit = 64 - n.leading_zeros();
    while bit > 0 {
        bit -= 1;
        // The bit shifted out of `r` counts too: `r < d` may exceed 2^63.
        let carry = r >> 63;
        r = (r << 1) + (n >> bit & 1);
        q <<= 1;
        if carry != 0 || r >= d {
            r = r.wrapping_sub(d);
            q |= 1;
        }
    }
    (q, r)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn edges() {
        for (n, d) in [
            (0, 1),
            (1, 1),
            (u64::MAX, 1),
            (u64::MAX, u64::MAX),
            (u64::MAX - 1, u64::MAX),
            (u64::MAX, 1 << 63),
            ((1 << 63) + 5, (1 << 63) + 1),
            (1 << 32, 3),
            (u64::MAX, 0xFFFF_FFFF),
            (12345, 1 << 40),
            // Both in 32 bits: the processor's division.
            (7, 2),
            (100, 7),
            (0xFFFF_FFFF, 3),
            // Low halves zero: the long way (the high halves decide the path).
            (1 << 40, 1 << 33),
            (3 << 32, 1 << 32),
        ] {
            assert_eq!(long_div(n, d), (n / d, n % d), "{n} / {d}");
            assert_eq!(div_rem(n, d), (n / d, n % d), "{n} / {d}");
        }
        assert_eq!(div_floor(-7, 2), -4);
        assert_eq!(div_floor(-8, 2), -4);
        assert_eq!(div_floor(7, 2), 3);
        assert_eq!(div_floor(i64::MIN, 1), i64::MIN);
        assert_eq!(div_floor(i64::MIN, 3), i64::MIN.div_euclid(3));
        assert_eq!(div_floor(i64::MAX, u64::MAX), 0);
        assert_eq!(div_floor(-1, u64::MAX), -1);
        assert_eq!(div(10, 3), 3);
    }

    proptest! {
        #[test]
        fn long_division_is_division(n: u64, d in 1u64..) {
            prop_assert_eq!(long_div(n, d), (n / d, n % d));
        }

        #[test]
        fn long_division_of_small_divisors(n: u64, d in 1u64..100_000) {
            prop_assert_eq!(long_div(n, d), (n / d, n % d));
        }

        #[test]
        fn long_division_in_32_bits(n in 0u64..1 << 32, d in 1u64..1 << 32) {
            prop_assert_eq!(long_div(n, d), (n / d, n % d));
        }

        #[test]
        fn floor_is_euclid(n: i64, d in 1i64..) {
            prop_assert_eq!(div_floor(n, d as u64), n.div_euclid(d));
        }
    }
}
