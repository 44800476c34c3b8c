use core::ops::{Add, AddAssign, Sub};

/// A point on the caller's monotonic clock, in microseconds. The core never reads a clock: the
/// host (or a test's virtual clock) passes `Instant`s in.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct Instant(pub(crate) u64);

/// A span of time in microseconds.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct Duration(pub(crate) u64);

impl Instant {
    /// Time zero of the clock.
    pub const ZERO: Instant = Instant(0);
    /// From microseconds.
    pub const fn from_micros(us: u64) -> Self {
        Instant(us)
    }
    /// From milliseconds.
    pub const fn from_millis(ms: u64) -> Self {
        Instant(ms * 1000)
    }
    /// Microseconds since the clock's zero.
    pub const fn micros(self) -> u64 {
        self.0
    }
    /// `self - earlier`, zero if `earlier` is later.
    pub const fn saturating_since(self, earlier: Instant) -> Duration {
        Duration(self.0.saturating_sub(earlier.0))
    }
}

impl Duration {
    /// Zero length.
    pub const ZERO: Duration = Duration(0);
    /// From microseconds.
    pub const fn from_micros(us: u64) -> Self {
        Duration(us)
    }
    /// From milliseconds.
    pub const fn from_millis(ms: u64) -> Self {
        Duration(ms * 1000)
    }
    /// Length in microseconds.
    pub const fn micros(self) -> u64 {
        self.0
    }
}

impl Add<Duration> for Instant {
    type Output = Instant;
    // A saturating 64-bit add takes several instructions on a 32-bit MCU: a firmware's many
    // call sites share one copy (config.rs lists what that saves).
    #[cfg_attr(not(feature = "inline-hot-paths"), inline(never))]
    fn add(self, d: Duration) -> Instant {
        Instant(self.0.saturating_add(d.0))
    }
}

impl AddAssign<Duration> for Instant {
    fn add_assign(&mut self, d: Duration) {
        *self = *self + d;
    }
}

impl Sub<Instant> for Instant {
    type Output = Duration;
    fn sub(self, o: Instant) -> Duration {
        Duration(self.0.saturating_sub(o.0))
    }
}
