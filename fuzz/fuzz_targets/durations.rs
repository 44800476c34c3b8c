//! Duration, time and speed parsing of the command line (`--duration`, `--speed`, scenario
//! `duration` / `at`).
//!
//! Invariants: no panic; an accepted duration is finite, within 0 … MAX_SECONDS and gives a
//! deadline; an accepted speed is 0 or within SPEED_RANGE, and any log offset within the limit
//! divided by it is either refused or gives a deadline.
#![no_main]

use std::time::Instant;

use canpos_cli::limits::{
    check_seconds, deadline, parse_positive_seconds, parse_seconds, parse_speed, MAX_SECONDS,
    SPEED_RANGE,
};

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let Ok(s) = std::str::from_utf8(data) else {
        return;
    };
    let now = Instant::now();
    for v in [parse_seconds(s), parse_positive_seconds(s)]
        .into_iter()
        .flatten()
    {
        assert!(
            v.is_finite() && (0.0..=MAX_SECONDS).contains(&v),
            "{s:?} → {v}"
        );
        assert!(deadline(now, v).is_some(), "{s:?} → {v} has no deadline");
    }
    if let Ok(speed) = parse_speed(s) {
        let (lo, hi) = SPEED_RANGE;
        assert!(
            speed == 0.0 || (lo..=hi).contains(&speed),
            "{s:?} → {speed}"
        );
        if speed > 0.0 {
            // The longest and a short log span at this speed: refused, or a real deadline.
            for span in [MAX_SECONDS, 1.0, 1e-6] {
                if let Ok(secs) = check_seconds(span / speed, false) {
                    assert!(deadline(now, secs).is_some());
                }
            }
        }
    }
    // The raw number, as a scenario file gives it.
    if let Ok(v) = s.trim().parse::<f64>() {
        if let Ok(v) = check_seconds(v, false) {
            assert!(deadline(now, v).is_some());
        }
    }
});
