//! The node's deadlines, one entry per service timer (after quinn-proto's `TimerTable`).
//!
//! Nothing sets an entry where the service's state changes: the node's epilogue, which ends
//! every `&mut` entry point, asks each service for its `poll_timeout` and writes the whole table
//! again. A service therefore cannot leave a stale deadline behind. The TPDOs' event and inhibit
//! timers are not in the table: the PDO service keeps their schedule itself (`Tpdos::due_us`),
//! which the timer hot path reads directly.

/// One service timer.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(u8)]
pub(crate) enum Timer {
    /// A segmented / block SDO transfer's timeout.
    SdoTransfer,
    /// LSS activate bit timing: the switch.
    LssSwitch,
    /// The end of a bit-rate switch's silence.
    Silence,
    /// Heartbeat and life guarding.
    ErrorControl,
    /// An EMCY held back by its inhibit time.
    Emcy,
    /// An RPDO's deadline monitoring (its event timer).
    Rpdo,
}

// A build without RPDOs has no entry for them (never set nor read there).
const COUNT: usize = if crate::config::MAX_RPDOS > 0 {
    Timer::Rpdo as usize + 1
} else {
    Timer::Rpdo as usize
};

/// No deadline.
pub(crate) const NEVER: u64 = u64::MAX;

/// Deadlines in µs ([`NEVER`] = none), by [`Timer`].
#[derive(Clone, Copy, Debug)]
pub(crate) struct TimerTable {
    at: [u64; COUNT],
}

impl Default for TimerTable {
    fn default() -> Self {
        TimerTable { at: [NEVER; COUNT] }
    }
}

impl TimerTable {
    /// Sets `t` in µs.
    #[inline(always)]
    pub(crate) fn set_us(&mut self, t: Timer, at: u64) {
        self.at[t as usize] = at;
    }

    /// Disarms every timer.
    pub(crate) fn clear(&mut self) {
        *self = TimerTable::default();
    }

    /// Whether `t` is due at `now` (µs).
    #[inline(always)]
    pub(crate) fn due(&self, t: Timer, now: u64) -> bool {
        now >= self.at[t as usize]
    }

    /// The earliest deadline.
    pub(crate) fn next(&self) -> u64 {
        self.at.iter().copied().min().unwrap_or(NEVER)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn earliest_and_disarm() {
        let mut t = TimerTable::default();
        assert_eq!(t.next(), NEVER);
        t.set_us(Timer::Emcy, 50);
        t.set_us(Timer::SdoTransfer, 70);
        assert_eq!(t.next(), 50);
        assert!(t.due(Timer::Emcy, 50) && !t.due(Timer::Emcy, 49));
        assert!(!t.due(Timer::LssSwitch, u64::MAX - 1));
        t.set_us(Timer::Emcy, NEVER);
        assert_eq!(t.next(), 70);
        t.clear();
        assert_eq!(t.next(), NEVER);
    }
}
