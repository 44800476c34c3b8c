//! The talk gate (a bit-rate switch, or a bus running another bit rate) and the bit-rate
//! simulation: frames heard or lost while the node's rate differs from the bus, TMI autobaud.

use super::*;

impl<A: Application, S: Storage> Node<A, S> {
    /// Tells the node the bit rate of the bus it is attached to (virtual buses).
    #[cfg(feature = "simulation")]
    pub fn set_bus_bitrate(&mut self, kbps: Option<u16>) {
        self.dev.bus_bitrate = kbps;
        self.epilogue();
    }
}

impl<A: Application, S: Storage> Device<A, S> {
    /// [`Node::poll_transmit`] once a frame was lost: counts it and the rest that are lost.
    /// `can_talk(now)` has just answered false and nothing changes its answer before the next
    /// entry point, so every frame still waiting is lost as well: dropped at once, not one by one.
    #[cold]
    #[inline(never)]
    pub(super) fn poll_transmit_lost(&mut self) -> Option<Frame> {
        debug_assert!(!self.can_talk(self.now));
        let lost = 1 + self.tx.len() as u32;
        self.stats.tx_wrong_bitrate = self.stats.tx_wrong_bitrate.wrapping_add(lost);
        self.tx.clear();
        None
    }

    /// Whether the node can receive at `now` (bit rate matches, not switching).
    pub(super) fn can_hear(&mut self, now: Instant) -> bool {
        if let Some(t) = self.silent_until {
            if now < t {
                return false;
            }
        }
        // Without the bus model (firmware), the controller hears only its own bit rate.
        #[cfg(not(feature = "simulation"))]
        return true;
        #[cfg(feature = "simulation")]
        match self.bus_bitrate {
            None => true,
            Some(bus) if self.bitrate == 0 => {
                // Autobaud (TMI): lock on after a few frames of continuous traffic (R19).
                self.autobaud_frames += 1;
                if self.autobaud_frames >= 4 {
                    self.bitrate = bus;
                    self.cfg.bitrate_kbps = bus;
                }
                false
            }
            Some(bus) => {
                if bus == self.bitrate {
                    true
                } else {
                    self.stats.rx_wrong_bitrate = self.stats.rx_wrong_bitrate.wrapping_add(1);
                    false
                }
            }
        }
    }

    #[inline(always)]
    pub(super) fn can_talk(&self, now: Instant) -> bool {
        debug_assert_eq!(self.talk_from, self.talk_from_now(), "update_talk missed");
        now.0 >= self.talk_from
    }

    /// What `talk_from` must be.
    fn talk_from_now(&self) -> u64 {
        #[cfg(feature = "simulation")]
        if self.bus_bitrate.is_some_and(|bus| bus != self.bitrate) {
            return u64::MAX;
        }
        self.silent_until.map_or(0, |t| t.0)
    }

    /// Recomputes `talk_from` from `bitrate`, `bus_bitrate` and `silent_until` (the node's
    /// epilogue).
    pub(crate) fn update_talk(&mut self) {
        self.talk_from = self.talk_from_now();
    }
}
