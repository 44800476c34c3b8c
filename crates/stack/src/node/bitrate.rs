//! The talk gate (a bit-rate switch in progress) and the bit rate a controller detected
//! (autobaud). Which bit rate the bus runs is the CAN controller's business: a firmware's
//! hardware, a host's device wrapper.

use super::*;

impl<A: Application, S: Storage> Node<A, S> {
    /// The CAN controller detected the bus's bit rate, `kbps` (a controller in autobaud, TMI
    /// R19: it listens until it has received frames without error at one rate). A node waiting
    /// for it (active bit rate 0) takes it as its active bit rate, and a node with a node-id
    /// announces itself with its boot-up. Otherwise (a rate already active, powered off, a
    /// bit-rate switch in progress) nothing changes.
    pub fn bitrate_detected(&mut self, kbps: u16, now: Instant) {
        if !self.hears(now) || self.dev.bitrate != 0 || kbps == 0 {
            return;
        }
        let d = &mut self.dev;
        d.now = now;
        d.bitrate = kbps;
        d.cfg.set_bitrate_kbps(kbps);
        if d.node_id != UNCONFIGURED {
            d.tx.push_std(cob::ERRCTL + d.node_id as u16, [0; 8], 1);
        }
        self.epilogue();
    }

    /// Whether the node receives at `now`: powered, and no bit-rate switch in progress (CiA 305
    /// §5.8: deaf from "activate bit timing" to the end of the second switch delay).
    pub fn hears(&self, now: Instant) -> bool {
        self.dev.powered && self.dev.hears(now)
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
        self.stats.tx_silenced = self.stats.tx_silenced.wrapping_add(lost);
        self.tx.clear();
        None
    }

    /// Whether the node can receive at `now` (not switching its bit rate).
    pub(super) fn hears(&self, now: Instant) -> bool {
        self.silent_until.is_none_or(|t| now >= t)
    }

    #[inline(always)]
    pub(super) fn can_talk(&self, now: Instant) -> bool {
        debug_assert_eq!(self.talk_from, self.talk_from_now(), "update_talk missed");
        now.0 >= self.talk_from
    }

    /// What `talk_from` must be.
    fn talk_from_now(&self) -> u64 {
        self.silent_until.map_or(0, |t| t.0)
    }

    /// Recomputes `talk_from` from `silent_until` (the node's epilogue).
    pub(crate) fn update_talk(&mut self) {
        self.talk_from = self.talk_from_now();
    }
}
