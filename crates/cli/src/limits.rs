//! Ranges of the numbers the command line and scenario files take, checked where they are
//! parsed so that no huge, tiny or non-finite value reaches a `Duration` or a deadline.

use std::time::{Duration, Instant};

use canpos_host::control::show_num;

/// Longest time accepted for a duration, an event time or a replayed log span, s (about 31
/// years: far beyond any run, small enough that `Instant + Duration` cannot overflow).
pub const MAX_SECONDS: f64 = 1.0e9;

/// Slowest and fastest `replay --speed` (besides 0 = as fast as possible).
pub const SPEED_RANGE: (f64, f64) = (1.0e-3, 1.0e6);

/// Checks a time in seconds: finite, ≥ 0 (> 0 when `positive`) and ≤ [`MAX_SECONDS`].
pub fn check_seconds(v: f64, positive: bool) -> Result<f64, String> {
    if !v.is_finite() {
        return Err(format!("{v} is not a finite number of seconds"));
    }
    if positive && v <= 0.0 {
        return Err(format!("{} s must be > 0", show_num(v)));
    }
    if v < 0.0 {
        return Err(format!("{} s must not be negative", show_num(v)));
    }
    if v > MAX_SECONDS {
        return Err(format!(
            "{} s is longer than the limit of {MAX_SECONDS:e} s",
            show_num(v)
        ));
    }
    Ok(v)
}

/// clap value parser for a duration in seconds (0…[`MAX_SECONDS`]).
pub fn parse_seconds(s: &str) -> Result<f64, String> {
    let v: f64 = s
        .trim()
        .parse()
        .map_err(|_| format!("`{s}` is not a number of seconds"))?;
    check_seconds(v, false)
}

/// clap value parser for a duration in seconds that must be > 0.
pub fn parse_positive_seconds(s: &str) -> Result<f64, String> {
    let v: f64 = s
        .trim()
        .parse()
        .map_err(|_| format!("`{s}` is not a number of seconds"))?;
    check_seconds(v, true)
}

/// clap value parser for `replay --speed`: 0, or within [`SPEED_RANGE`].
pub fn parse_speed(s: &str) -> Result<f64, String> {
    let v: f64 = s
        .trim()
        .parse()
        .map_err(|_| format!("`{s}` is not a number"))?;
    let (lo, hi) = SPEED_RANGE;
    if v == 0.0 || (v.is_finite() && (lo..=hi).contains(&v)) {
        Ok(v)
    } else {
        Err(format!(
            "{} is out of range: 0 (as fast as possible) or {lo} … {hi:e}",
            show_num(v)
        ))
    }
}

/// `start + secs`, for a `secs` already checked by [`check_seconds`]; `None` if the clock
/// cannot represent it.
pub fn deadline(start: Instant, secs: f64) -> Option<Instant> {
    Duration::try_from_secs_f64(secs)
        .ok()
        .and_then(|d| start.checked_add(d))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn seconds() {
        assert_eq!(parse_seconds("2.5"), Ok(2.5));
        assert_eq!(parse_seconds("0"), Ok(0.0));
        for bad in ["1e300", "1e19", "-1", "NaN", "inf", "x"] {
            assert!(parse_seconds(bad).is_err(), "{bad}");
        }
        assert!(parse_positive_seconds("0").is_err());
        assert!(deadline(Instant::now(), MAX_SECONDS).is_some());
    }

    #[test]
    fn speed() {
        assert_eq!(parse_speed("0"), Ok(0.0));
        assert_eq!(parse_speed("2"), Ok(2.0));
        for bad in ["1e-300", "1e300", "-1", "NaN", "inf"] {
            assert!(parse_speed(bad).is_err(), "{bad}");
        }
    }
}
