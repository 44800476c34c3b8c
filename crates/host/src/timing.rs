//! A device's own timing, for testing a master's timeouts: how long its SDO answers take, how
//! long it needs to boot after power-on and after an NMT reset. The runtime applies it
//! ([`crate::runtime`]); the core stays timeless apart from the timers the profiles define.
//!
//! The three manuals state none of these times (docs/CONTROL.md, "Device timing"): by default
//! a canpos device answers as soon as it has processed a request and boots at once.

use std::time::Duration;

use serde::{Deserialize, Serialize};

/// Longest delay any timing value may take: longer than every SDO or boot timeout a master
/// uses, short enough that a typo (ms for µs) is caught.
pub const MAX_DELAY: Duration = Duration::from_secs(600);

/// Per-device delays. All zero by default.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct DeviceTiming {
    /// Added before every SDO response (server → client, 0x580 + node-id).
    pub sdo_delay: Duration,
    /// Up to this much more, uniformly at random per response (seeded per device, so a run is
    /// reproducible). Responses keep their order.
    pub sdo_jitter: Duration,
    /// From power-on to the boot-up message; the device is not on the bus meanwhile.
    pub boot_delay: Duration,
    /// From an NMT reset (node or communication) to the boot-up message; the device neither
    /// answers nor sends meanwhile.
    pub reset_boot_delay: Duration,
}

impl DeviceTiming {
    /// Checks every value against [`MAX_DELAY`].
    pub fn check(&self) -> Result<(), String> {
        for (name, v) in [
            ("sdo-delay", self.sdo_delay),
            ("sdo-jitter", self.sdo_jitter),
            ("boot-delay", self.boot_delay),
            ("reset-boot-delay", self.reset_boot_delay),
        ] {
            if v > MAX_DELAY {
                return Err(format!(
                    "{name} {} ms is out of range (0…{} ms)",
                    v.as_millis(),
                    MAX_DELAY.as_millis()
                ));
            }
        }
        Ok(())
    }

    /// Whether SDO responses are held at all.
    pub fn delays_sdo(&self) -> bool {
        !self.sdo_delay.is_zero() || !self.sdo_jitter.is_zero()
    }
}

/// Milliseconds as given on the command line, in a scenario or a control request: finite,
/// 0…[`MAX_DELAY`]. `what` names the value in the error.
pub fn millis(what: &str, ms: f64) -> Result<Duration, String> {
    if !ms.is_finite() || ms < 0.0 || ms > MAX_DELAY.as_secs_f64() * 1e3 {
        return Err(format!(
            "{what} {ms} ms is out of range (0…{} ms)",
            MAX_DELAY.as_millis()
        ));
    }
    Ok(Duration::from_secs_f64(ms / 1e3))
}

/// A small deterministic generator for the jitter (xorshift64*): reproducible per seed, no
/// dependency for a uniform number.
#[derive(Clone, Debug)]
pub struct Jitter(u64);

impl Jitter {
    /// A generator for one device.
    pub fn new(seed: u64) -> Jitter {
        // Never zero (xorshift's fixed point).
        Jitter(seed ^ 0x9E37_79B9_7F4A_7C15 | 1)
    }

    /// Uniform in `0..=max`.
    pub fn up_to(&mut self, max: Duration) -> Duration {
        if max.is_zero() {
            return Duration::ZERO;
        }
        let mut x = self.0;
        x ^= x >> 12;
        x ^= x << 25;
        x ^= x >> 27;
        self.0 = x;
        let r = x.wrapping_mul(0x2545_F491_4F6C_DD1D);
        let us = max.as_micros() as u64;
        Duration::from_micros(r % (us + 1))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ranges_are_checked() {
        assert!(millis("sdo-delay", 0.0).is_ok());
        assert_eq!(millis("x", 1.5).unwrap(), Duration::from_micros(1500));
        for bad in [-1.0, f64::NAN, f64::INFINITY, 600_001.0] {
            let e = millis("sdo-delay", bad).unwrap_err();
            assert!(e.contains("sdo-delay") && e.contains("out of range"), "{e}");
        }
        let t = DeviceTiming {
            boot_delay: MAX_DELAY + Duration::from_millis(1),
            ..Default::default()
        };
        assert!(t.check().unwrap_err().contains("boot-delay"));
        assert!(DeviceTiming::default().check().is_ok());
    }

    #[test]
    fn jitter_is_bounded_reproducible_and_spread() {
        let max = Duration::from_millis(10);
        let a: Vec<_> = {
            let mut j = Jitter::new(7);
            (0..1000).map(|_| j.up_to(max)).collect()
        };
        let mut j = Jitter::new(7);
        assert!(a.iter().all(|d| *d == j.up_to(max) && *d <= max));
        assert!(a.iter().any(|d| *d < Duration::from_millis(2)));
        assert!(a.iter().any(|d| *d > Duration::from_millis(8)));
        assert_eq!(Jitter::new(1).up_to(Duration::ZERO), Duration::ZERO);
    }
}
