//! Error control (CiA 301 §7.2.8.3): boot-up, heartbeat producer (0x1017) and node guarding with
//! life guarding (0x100C × 0x100D, D11).

use crate::nmt::NmtState;
use crate::wire::{cob, Duration, Instant};

/// Whether a guarding COB-ID (0x100E) value may name a restricted CAN-ID
/// ([`crate::cob::restricted_id`]): only the pre-defined 0x700 + node-id, since guarding answers
/// on its COB-ID's CAN-ID and has no "not valid" bit.
#[inline(always)]
pub(crate) fn guarding_cob_id_may_be_restricted(raw: u32, node_id: u8) -> bool {
    raw & 0x7FF == u32::from(cob::ERRCTL) + u32::from(node_id)
}

/// Whether a SYNC (0x1005) or guarding (0x100E) COB-ID `raw` lands on `other_can_id`, the
/// other one's CAN-ID: the two may not share one (D22), as a zero-length data frame counts as a
/// guard request (socketcand has no RTR, D11), so every SYNC would be answered as one.
#[inline(always)]
pub(crate) fn sync_guarding_clash(raw: u32, other_can_id: u32) -> bool {
    raw & 0x7FF == other_can_id
}

/// Heartbeat and node-guarding state of the slave.
// "Off" and "none" are zero, not `Option`s: cheaper tests and stores, and the default (a
// reset) is all zero bytes.
#[derive(Clone, Debug, Default)]
pub struct ErrCtl {
    /// The heartbeat period (0x1017), zero for off (a period is at least 1 ms).
    heartbeat: Duration,
    /// When the next heartbeat is due; meaningless while the heartbeat is off.
    next_heartbeat: Instant,
    toggle: bool,
    /// Guard time × life time factor (0x100C × 0x100D), zero for none (either is zero).
    life_time: Duration,
    /// Deadline of the next expected guard request, once guarding has started; zero for none
    /// (a deadline is a non-zero life time after some instant, and the add saturates, so it is
    /// never zero).
    guard_deadline: Instant,
    /// A life-guarding event happened and no guard request has come since.
    pub life_guard_lost: bool,
    /// CAN-ID on which guard requests are answered (0x100E; pre-defined 0x700 + node-id).
    guarding_id: u16,
}

/// What a timer expiry produced.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ErrCtlEvent {
    /// Send a heartbeat with this state byte.
    Heartbeat(u8),
    /// The life time elapsed without a guard request (EMCY 0x8130, PDOs stop).
    LifeGuardingLost,
}

impl ErrCtl {
    /// Applies 0x1017 (ms, 0 = off): the first heartbeat follows one period after `now`.
    // A firmware's reset and 0x1017 writes share one copy.
    #[cfg_attr(not(feature = "inline-hot-paths"), inline(never))]
    pub fn set_heartbeat(&mut self, ms: u16, now: Instant) {
        let p = Duration::from_millis(ms as u64);
        self.heartbeat = p;
        self.next_heartbeat = now + p;
    }

    /// Applies 0x100C (ms) and 0x100D: life guarding is armed once both are non-zero and a guard
    /// request has arrived.
    pub fn set_guarding(&mut self, guard_ms: u16, factor: u8, now: Instant) {
        // Zero exactly when either is.
        let l = Duration::from_millis(guard_ms as u64 * factor as u64);
        self.life_time = l;
        self.guard_deadline = if l != Duration::ZERO && self.guard_deadline != Instant::ZERO {
            now + l
        } else {
            Instant::ZERO
        };
        if l == Duration::ZERO {
            self.life_guard_lost = false;
        }
    }

    /// Sets the CAN-ID of the guarding protocol (0x100E).
    pub fn set_guarding_id(&mut self, id: u16) {
        self.guarding_id = id;
    }

    /// The CAN-ID on which guard requests are answered.
    #[inline]
    pub fn guarding_id(&self) -> u16 {
        self.guarding_id
    }

    /// Clears the toggle and guarding state (reset communication).
    pub fn reset(&mut self) {
        *self = ErrCtl::default();
    }

    /// A guard request arrived: returns the reply byte (state | toggle) and re-arms life guarding.
    pub fn guard_request(&mut self, state: NmtState, now: Instant) -> u8 {
        let b = state.code() | if self.toggle { 0x80 } else { 0 };
        self.toggle = !self.toggle;
        let l = self.life_time;
        if l != Duration::ZERO {
            self.guard_deadline = now + l;
        }
        self.life_guard_lost = false;
        b
    }

    /// The next deadline of this service in µs, `u64::MAX` for none (the node's timer table).
    #[inline]
    pub fn due_us(&self) -> u64 {
        let hb = if self.heartbeat == Duration::ZERO {
            u64::MAX
        } else {
            self.next_heartbeat.0
        };
        let guard = if self.guard_deadline == Instant::ZERO {
            u64::MAX
        } else {
            self.guard_deadline.0
        };
        hb.min(guard)
    }

    /// Handles expired timers; call until it returns `None`. `guarding`: the device has node
    /// guarding (without it life guarding is never armed; a constant drops its code).
    #[inline]
    pub fn handle_timeout(
        &mut self,
        now: Instant,
        state: NmtState,
        guarding: bool,
    ) -> Option<ErrCtlEvent> {
        let (t, p) = (self.next_heartbeat, self.heartbeat);
        if p != Duration::ZERO && now >= t {
            // Absolute schedule: no drift; skip whole periods if the host was late.
            // `now >= t`: no saturating subtraction needed. On time, 0 whole periods behind:
            // one division per heartbeat rather than a test for lateness first (its flash cost
            // in docs/FIRMWARE.md, "Build options in figures").
            let behind = crate::div::div(now.0 - t.0, p.micros());
            self.next_heartbeat = t + Duration(p.micros() * (behind + 1));
            return Some(ErrCtlEvent::Heartbeat(state.code()));
        }
        let d = self.guard_deadline;
        if guarding && d != Instant::ZERO && now >= d {
            self.guard_deadline = Instant::ZERO;
            self.life_guard_lost = true;
            return Some(ErrCtlEvent::LifeGuardingLost);
        }
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// D22: SYNC and guarding never on one CAN-ID (whatever the COB-ID's flag bits); guarding
    /// may keep its own pre-defined 0x700 + node-id although it is restricted.
    #[test]
    fn sync_and_guarding_can_ids() {
        assert!(sync_guarding_clash(0x0000_0705, 0x705));
        assert!(sync_guarding_clash(0x8000_0705, 0x705));
        assert!(!sync_guarding_clash(0x0000_0706, 0x705));
        assert!(guarding_cob_id_may_be_restricted(0x705, 5));
        assert!(!guarding_cob_id_may_be_restricted(0x706, 5));
        assert!(!guarding_cob_id_may_be_restricted(0x77F, 5));
    }

    /// A heartbeat served exactly one period late goes out once, and the schedule stays on its
    /// grid: the next one is due a period later, not at once again.
    #[test]
    fn a_heartbeat_one_period_late_is_sent_once_and_the_grid_kept() {
        let mut e = ErrCtl::default();
        e.set_heartbeat(100, Instant::ZERO);
        let at = Instant::from_millis(200);
        let s = NmtState::PreOperational;
        assert_eq!(
            e.handle_timeout(at, s, false),
            Some(ErrCtlEvent::Heartbeat(0x7F))
        );
        assert_eq!(e.handle_timeout(at, s, false), None, "once at 200 ms");
        assert_eq!(e.due_us(), 300_000);
    }

    /// Only switching guarding off (a zero guard time or factor) forgets a lost life guarding; a
    /// new non-zero life time is no guard request.
    #[test]
    fn only_guarding_off_forgets_a_lost_life_guarding() {
        let mut e = ErrCtl::default();
        let s = NmtState::Operational;
        e.set_guarding(100, 3, Instant::ZERO);
        e.guard_request(s, Instant::ZERO);
        let at = Instant::from_millis(300);
        assert_eq!(
            e.handle_timeout(at, s, true),
            Some(ErrCtlEvent::LifeGuardingLost)
        );
        e.set_guarding(200, 3, at);
        assert!(e.life_guard_lost, "still lost");
        e.set_guarding(0, 3, at);
        assert!(!e.life_guard_lost, "guarding off");
    }
}
