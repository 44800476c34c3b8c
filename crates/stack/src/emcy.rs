//! EMCY producer (CiA 301 §7.2.7): error codes, the error register (0x1001), the pre-defined
//! error field (0x1003) and the inhibit time (0x1015).

use crate::od::Abort;
use crate::wire::{Duration, Instant};

/// Error register bits (0x1001, CiA 301 Table 48; TH/E Table 6).
pub mod reg {
    /// Generic error (set whenever any error is active).
    pub const GENERIC: u8 = 0x01;
    /// Current.
    pub const CURRENT: u8 = 0x02;
    /// Voltage.
    pub const VOLTAGE: u8 = 0x04;
    /// Temperature.
    pub const TEMPERATURE: u8 = 0x08;
    /// Communication error (overrun, error state).
    pub const COMMUNICATION: u8 = 0x10;
    /// Device profile specific.
    pub const PROFILE: u8 = 0x20;
    /// Manufacturer specific.
    pub const MANUFACTURER: u8 = 0x80;
}

/// The CiA 301 EMCY error codes the stack and its applications raise.
pub mod code {
    /// Error reset or no error.
    pub const NO_ERROR: u16 = 0x0000;
    /// Main voltage.
    pub const MAIN_VOLTAGE: u16 = 0x3100;
    /// Temperature (ambient).
    pub const TEMPERATURE: u16 = 0x4200;
    /// Device hardware (transducer error, missing magnet).
    pub const HARDWARE: u16 = 0x5000;
    /// Device software / TMI: insufficient event timer.
    pub const SOFTWARE: u16 = 0x6000;
    /// Data set.
    pub const DATA_SET: u16 = 0x6300;
    /// Communication (generic).
    pub const COMMUNICATION: u16 = 0x8100;
    /// CAN overrun (objects lost).
    pub const CAN_OVERRUN: u16 = 0x8110;
    /// CAN in error passive mode.
    pub const ERROR_PASSIVE: u16 = 0x8120;
    /// Life guard error or heartbeat error.
    pub const LIFE_GUARD: u16 = 0x8130;
    /// Recovered from bus off.
    pub const BUS_OFF_RECOVERED: u16 = 0x8140;
    /// CAN-ID collision.
    pub const COB_COLLISION: u16 = 0x8150;
    /// PDO not processed due to length error.
    pub const PDO_LENGTH: u16 = 0x8210;
    /// Unexpected SYNC data length (CiA 301).
    pub const SYNC_LENGTH: u16 = 0x8240;
    /// PDO length exceeded (an RPDO longer than its mapping).
    pub const PDO_LENGTH_EXCEEDED: u16 = 0x8220;
    /// RPDO timeout (its deadline monitoring, the event timer 0x1400:5, expired).
    pub const RPDO_TIMEOUT: u16 = 0x8250;
}

pub use crate::config::HISTORY_LEN;
use crate::config::{EMCY_ACTIVE_LEN as ACTIVE_LEN, EMCY_PENDING_LEN as PENDING_LEN};
// The history and the pending frames are rings (indices masked), so that nothing is shifted:
// a shift compiles to a call of the general-purpose `memmove`, which a firmware would link
// only for this (its size in docs/FIRMWARE.md).
const _: () = assert!(HISTORY_LEN.is_power_of_two() && PENDING_LEN.is_power_of_two());

/// Bit 31 of the COB-ID EMCY (0x1014): the EMCY is not valid, nothing is sent on it.
const COB_ID_NOT_VALID: u32 = 0x8000_0000;

/// Whether a COB-ID EMCY value may name a restricted CAN-ID ([`crate::cob::restricted_id`]):
/// only while marked not valid, as nothing is then sent on it.
#[inline(always)]
pub(crate) fn cob_id_may_be_restricted(raw: u32) -> bool {
    raw & COB_ID_NOT_VALID != 0
}

/// Whether a write of `raw` over `cur` to the COB-ID EMCY is refused: the CAN-ID of a valid
/// EMCY may not change (CiA 301 7.5.2.17); a new CAN-ID goes in while it is marked not valid.
#[inline(always)]
pub(crate) fn cob_id_change_refused(cur: u32, raw: u32) -> bool {
    cur & COB_ID_NOT_VALID == 0 && raw & COB_ID_NOT_VALID == 0 && (cur ^ raw) & 0x7FF != 0
}

/// The EMCY producer's state.
#[derive(Clone, Debug)]
pub struct Emcy {
    /// The active errors, each its code in bits 0–15 and its error-register bits in 16–23:
    /// a word has no padding, so a new `Emcy` is all zero bytes (one `memclr`, not a loop).
    active: [u32; ACTIVE_LEN],
    // The counts and ring positions are bytes (every ring is far shorter than 256): less RAM
    // than `usize` (docs/FIRMWARE.md).
    n_active: u8,
    history: [u32; HISTORY_LEN],
    /// Where the newest history entry is.
    newest: u8,
    n_history: u8,
    /// The pending frames' payloads, little-endian words (see [`payload`]).
    pending: [u64; PENDING_LEN],
    /// Where the oldest pending frame is.
    first_pending: u8,
    n_pending: u8,
    inhibit: Duration,
    next_allowed: Instant,
    /// EMCYs that could not be queued (pending queue full).
    pub lost: u32,
    /// Bumped whenever the error register or the history may have changed, so the device
    /// mirrors them into 0x1001 / 0x1003 only then (not on every frame).
    generation: u32,
    /// See [`Emcy::set_reset_on_register_change`].
    on_register_change: bool,
}

impl Emcy {
    /// The active errors: code (bits 0–15) and error-register bits (16–23).
    #[inline]
    fn active_codes(&self) -> &[u32] {
        // `n_active` never exceeds the array: `min` costs less than a bounds check's panic.
        &self.active[..usize::from(self.n_active).min(ACTIVE_LEN)]
    }

    /// Where `code` is in the active list, `ACTIVE_LEN` if it is not active (one register,
    /// not an `Option`'s two). A firmware's raise, clear and `is_active` share one search.
    #[cfg_attr(not(feature = "inline-hot-paths"), inline(never))]
    fn find(&self, code: u16) -> usize {
        // Over indices, not a slice's `position`: a tighter loop.
        (0..usize::from(self.n_active).min(ACTIVE_LEN))
            .find(|&i| self.active[i] as u16 == code)
            .unwrap_or(ACTIVE_LEN)
    }
}

impl core::default::Default for Emcy {
    fn default() -> Self {
        Emcy {
            active: [0; ACTIVE_LEN],
            n_active: 0,
            history: [0; HISTORY_LEN],
            newest: 0,
            n_history: 0,
            pending: [0; PENDING_LEN],
            first_pending: 0,
            n_pending: 0,
            inhibit: Duration::ZERO,
            next_allowed: Instant::ZERO,
            lost: 0,
            generation: 0,
            on_register_change: false,
        }
    }
}

impl Emcy {
    /// The error register (0x1001) as the active errors make it.
    #[cfg_attr(feature = "inline-hot-paths", inline)]
    #[cfg_attr(not(feature = "inline-hot-paths"), inline(never))]
    pub fn register(&self) -> u8 {
        let mut r = 0;
        for &a in self.active_codes() {
            r |= (a >> 16) as u8 | reg::GENERIC;
        }
        r
    }

    /// A counter that changes whenever [`Emcy::register`] or the history may have changed.
    #[inline]
    pub fn generation(&self) -> u32 {
        self.generation
    }

    /// Whether an EMCY waits to be sent.
    #[inline]
    pub fn has_pending(&self) -> bool {
        self.n_pending > 0
    }

    /// Whether `code` is active.
    pub fn is_active(&self, code: u16) -> bool {
        self.find(code) < ACTIVE_LEN
    }

    /// Sets the inhibit time (0x1015, 100 µs units).
    pub fn set_inhibit(&mut self, units_100us: u16) {
        self.inhibit = Duration::from_micros(units_100us as u64 * 100);
    }

    /// An error appears: records it, adds it to the history and queues its EMCY (once per
    /// event: an error already active sends nothing).
    pub fn raise(&mut self, code: u16, reg_bits: u8, mfr: [u8; 5]) {
        if self.is_active(code) {
            return;
        }
        if usize::from(self.n_active) < ACTIVE_LEN {
            self.active[usize::from(self.n_active)] = u32::from(code) | u32::from(reg_bits) << 16;
            self.n_active += 1;
        }
        // `record` bumps the generation (the register's change with it).
        let p = payload(code, mfr);
        self.record(p);
        self.queue(p);
    }

    /// An error that stands while its EMCY cannot be sent yet (bus-off): active in the register
    /// (0x1001) at once, announced later with [`Emcy::event`] and cleared with [`Emcy::clear`]
    /// (CANopenNode reports "recovered from bus off" so: the error is set when the controller
    /// goes bus-off, its EMCY leaves when the bus is back).
    pub fn hold(&mut self, code: u16, reg_bits: u8) {
        if self.is_active(code) || usize::from(self.n_active) >= ACTIVE_LEN {
            return;
        }
        self.active[usize::from(self.n_active)] = u32::from(code) | u32::from(reg_bits) << 16;
        self.n_active += 1;
        self.generation = self.generation.wrapping_add(1);
    }

    /// A one-shot event (no lasting error condition): queued and recorded, register unchanged.
    // A firmware's events share one copy.
    #[cfg_attr(not(feature = "inline-hot-paths"), inline(never))]
    pub fn event(&mut self, code: u16, mfr: [u8; 5]) {
        let p = payload(code, mfr);
        self.record(p);
        self.queue(p);
    }

    /// An error goes away; when no error is left, EMCY 0x0000 with the register follows.
    pub fn clear(&mut self, code: u16) {
        let i = self.find(code);
        if i >= ACTIVE_LEN {
            return;
        }
        // The register before is the one after with the cleared error's bits: no pass over the
        // list before the removal, and none at all unless the rule needs it.
        let gone = (self.active[i % ACTIVE_LEN] >> 16) as u8 | reg::GENERIC;
        // The last error takes its place: the list's order tells nothing (the register is a
        // union, and a search finds a code anywhere), so nothing needs shifting.
        self.n_active -= 1;
        self.active[i % ACTIVE_LEN] = self.active[usize::from(self.n_active) % ACTIVE_LEN];
        self.generation = self.generation.wrapping_add(1);
        if self.n_active == 0 || (self.on_register_change && gone & !self.register() != 0) {
            self.queue(payload(code::NO_ERROR, [0; 5]));
        }
    }

    /// Sends 0x0000 also when an error clears while others stay, if the error register changed
    /// (the model's rule, [`crate::model::Features::emcy_on_register_change`]).
    pub fn set_reset_on_register_change(&mut self, on: bool) {
        self.on_register_change = on;
    }

    /// Queues an "error reset" EMCY (0x0000) with the current error register: after a
    /// one-shot event such as "recovered from bus-off" on models whose EMCYs go along with
    /// every change of the error state.
    pub fn reset_message(&mut self) {
        self.queue(payload(code::NO_ERROR, [0; 5]));
    }

    /// Sends the power-on EMCY "without reasonable data" (D14).
    pub fn power_on(&mut self) {
        self.queue(payload(code::NO_ERROR, [0; 5]));
    }

    /// Forgets active errors and pending frames (reset); the history survives until cleared.
    pub fn reset(&mut self) {
        self.n_active = 0;
        self.n_pending = 0;
        self.generation = self.generation.wrapping_add(1);
        self.next_allowed = Instant::ZERO;
    }

    /// Entry `i` (1-based, newest first) of 0x1003.
    pub fn history(&self, i: usize) -> Option<u32> {
        if i == 0 || i > usize::from(self.n_history) {
            None
        } else {
            Some(self.history[(usize::from(self.newest) + i - 1) % HISTORY_LEN])
        }
    }
    /// Entry `i` (1-based, newest first, at most [`HISTORY_LEN`]) of 0x1003, 0 past the last
    /// one: as [`Emcy::history`] with `unwrap_or(0)`, without its check, since the slots past
    /// the entries are zero (cleared with the history, filled newest first).
    #[inline]
    pub(crate) fn history_or_zero(&self, i: usize) -> u32 {
        self.history[(usize::from(self.newest) + i.wrapping_sub(1)) % HISTORY_LEN]
    }
    /// Number of history entries (0x1003/0).
    pub fn history_len(&self) -> usize {
        usize::from(self.n_history)
    }
    /// Whether 0x1003 sub `sub` may be read: sub-indices beyond the recorded errors hold no data
    /// (CiA 301; the conformance tool's EMCY-03 expects the read of 1003:01 to abort when the
    /// history is empty).
    #[inline(always)]
    pub(crate) fn history_readable(&self, sub: u8) -> Result<(), Abort> {
        if usize::from(sub) > self.history_len() {
            return Err(Abort::NoData);
        }
        Ok(())
    }
    /// Clears 0x1003.
    pub fn clear_history(&mut self) {
        self.n_history = 0;
        self.history = [0; HISTORY_LEN];
        self.generation = self.generation.wrapping_add(1);
    }

    // A firmware's raises share one copy.
    #[cfg_attr(not(feature = "inline-hot-paths"), inline(never))]
    fn record(&mut self, p: u64) {
        // Bits 16–31 hold the first two manufacturer bytes (EMCY bytes 3–4), so the history
        // entry matches the frame (conformance EMCY-06).
        let entry = p as u16 as u32 | ((p >> 24) as u16 as u32) << 16;
        let newest = (usize::from(self.newest) + HISTORY_LEN - 1) % HISTORY_LEN;
        self.newest = newest as u8;
        self.history[newest] = entry;
        self.n_history = (self.n_history + 1).min(HISTORY_LEN as u8);
        self.generation = self.generation.wrapping_add(1);
    }

    /// Queues the EMCY of payload `p` (see [`payload`]) with the current error register: every
    /// caller sends that, and reading it here spares each call site its own call.
    fn queue(&mut self, p: u64) {
        let register = self.register();
        if usize::from(self.n_pending) == PENDING_LEN {
            self.lost = self.lost.wrapping_add(1);
            return;
        }
        self.pending[usize::from(self.first_pending + self.n_pending) % PENDING_LEN] =
            p | u64::from(register) << 16;
        self.n_pending += 1;
    }

    /// When the next queued EMCY may go out, if one waits.
    #[inline]
    pub fn poll_timeout(&self) -> Option<Instant> {
        (self.n_pending > 0).then_some(self.next_allowed)
    }

    /// [`Emcy::poll_timeout`] in µs, `u64::MAX` for none (the node's timer table).
    #[inline]
    pub fn due_us(&self) -> u64 {
        if self.n_pending > 0 {
            self.next_allowed.0
        } else {
            u64::MAX
        }
    }

    /// Takes the next EMCY payload whose inhibit time has passed.
    pub fn poll(&mut self, now: Instant) -> Option<[u8; 8]> {
        if self.n_pending == 0 || now < self.next_allowed {
            return None;
        }
        // Always in range; the mask spares the bounds check.
        let f = self.pending[usize::from(self.first_pending) % PENDING_LEN];
        self.first_pending = ((usize::from(self.first_pending) + 1) % PENDING_LEN) as u8;
        self.n_pending -= 1;
        self.next_allowed = now + self.inhibit;
        Some(f.to_le_bytes())
    }
}

/// An EMCY's payload as a little-endian word, its error register (byte 2) left 0: the code
/// in bytes 0–1, the manufacturer bytes in 3–7. Passed in registers, not as a byte array on
/// the stack, and stored whole.
#[inline]
fn payload(code: u16, mfr: [u8; 5]) -> u64 {
    let c = code.to_le_bytes();
    u64::from_le_bytes([c[0], c[1], 0, mfr[0], mfr[1], mfr[2], mfr[3], mfr[4]])
}

#[cfg(test)]
mod tests {
    use super::*;

    /// CiA 301 7.5.2.17: a valid EMCY keeps its CAN-ID, a change goes through "not valid";
    /// only a COB-ID marked not valid may name a restricted CAN-ID.
    #[test]
    fn cob_id_rules() {
        let (valid, off) = (0x0000_0085, 0x8000_0085);
        assert!(cob_id_change_refused(valid, 0x86));
        assert!(!cob_id_change_refused(valid, valid));
        assert!(!cob_id_change_refused(valid, off), "marking it not valid");
        assert!(
            !cob_id_change_refused(valid, 0x8000_0086),
            "marking it not valid on another CAN-ID"
        );
        assert!(
            !cob_id_change_refused(off, 0x8000_0086),
            "moving it while not valid"
        );
        assert!(
            !cob_id_change_refused(off, 0x86),
            "valid again on a new CAN-ID"
        );
        assert!(cob_id_may_be_restricted(0x8000_0000));
        assert!(!cob_id_may_be_restricted(0x0000_0001));
    }

    /// 0x1003 sub-indices past the recorded errors abort with "no data".
    #[test]
    fn history_reads_past_the_entries_have_no_data() {
        let mut e = Emcy::default();
        assert_eq!(e.history_readable(0), Ok(()));
        assert_eq!(e.history_readable(1), Err(Abort::NoData));
        e.raise(code::HARDWARE, reg::MANUFACTURER, [0; 5]);
        assert_eq!(e.history_readable(1), Ok(()));
        assert_eq!(e.history_readable(2), Err(Abort::NoData));
    }

    #[test]
    fn register_history_and_clear() {
        let mut e = Emcy::default();
        e.raise(code::HARDWARE, reg::MANUFACTURER, [0; 5]);
        assert_eq!(
            e.register(),
            0x81,
            "D13: missing magnet gives register 0x81"
        );
        assert_eq!(e.poll(Instant(0)), Some([0x00, 0x50, 0x81, 0, 0, 0, 0, 0]));
        e.raise(code::HARDWARE, reg::MANUFACTURER, [0; 5]);
        assert_eq!(e.poll(Instant(0)), None, "once per event");
        e.clear(code::HARDWARE);
        assert_eq!(e.poll(Instant(0)), Some([0; 8]));
        assert_eq!(e.history(1), Some(0x5000));
    }

    /// CiA 301 §7.2.7: an EMCY is sent once per error event. More distinct errors than the
    /// active list holds are still sent and recorded; the list keeps the first eight.
    /// A held error is in the register at once, sends nothing, is held once however often, and
    /// its clearing sends the error reset; a full active list takes no more.
    #[test]
    fn a_held_error_marks_the_register_without_sending() {
        let mut e = Emcy::default();
        e.hold(code::BUS_OFF_RECOVERED, reg::COMMUNICATION);
        e.hold(code::BUS_OFF_RECOVERED, reg::COMMUNICATION);
        assert_eq!((e.register(), e.poll(Instant(0))), (0x11, None));
        e.event(code::BUS_OFF_RECOVERED, [0; 5]);
        assert_eq!(e.poll(Instant(0)).map(|f| f[2]), Some(0x11));
        e.clear(code::BUS_OFF_RECOVERED);
        assert_eq!(e.register(), 0, "held once");
        assert_eq!(e.poll(Instant(0)), Some([0; 8]));
        for c in 0..ACTIVE_LEN as u16 {
            e.raise(0x1000 + c, 0, [0; 5]);
        }
        e.hold(code::BUS_OFF_RECOVERED, reg::COMMUNICATION);
        assert!(!e.is_active(code::BUS_OFF_RECOVERED), "the list is full");
    }

    #[test]
    fn more_distinct_errors_than_the_active_list_holds_are_still_sent() {
        let mut e = Emcy::default();
        for k in 0..ACTIVE_LEN as u16 + 1 {
            e.raise(0xFF00 + k, reg::MANUFACTURER, [0; 5]);
            let f = e.poll(Instant(0)).expect("each error sends its EMCY");
            assert_eq!(u16::from_le_bytes([f[0], f[1]]), 0xFF00 + k);
        }
        assert_eq!(e.history(1), Some(0xFF08));
        assert_eq!(e.history_len(), HISTORY_LEN);
        assert!(e.is_active(0xFF07) && !e.is_active(0xFF08));
        for k in 0..ACTIVE_LEN as u16 {
            e.clear(0xFF00 + k);
        }
        assert_eq!(e.register(), 0);
        assert_eq!(e.poll(Instant(0)), Some([0; 8]), "no error left: 0x0000");
    }

    /// CiA 301 §7.5.2.2 (0x1001): bit 0, generic error, is set whenever any error is active,
    /// whether or not the error's own bits name it; the register is the union of the errors'.
    #[test]
    fn the_register_is_the_union_with_the_generic_bit() {
        let mut e = Emcy::default();
        e.raise(0x3100, reg::GENERIC | 0x04, [0; 5]);
        assert_eq!(e.register(), 0x05);
        e.raise(0x4200, 0x08, [0; 5]);
        assert_eq!(e.register(), 0x0D);
        e.clear(0x3100);
        assert_eq!(e.register(), 0x09);
    }

    /// With the rule "0x0000 on every change of the register", an error clearing while others
    /// stay sends 0x0000 exactly when the register loses bits; without it, only the last one
    /// clearing does.
    #[test]
    fn reset_on_register_change_sends_only_when_the_register_changes() {
        for on in [false, true] {
            let mut e = Emcy::default();
            e.set_reset_on_register_change(on);
            e.raise(0x3100, reg::VOLTAGE, [0; 5]);
            e.raise(0x4200, reg::TEMPERATURE, [0; 5]);
            e.raise(0x4210, reg::TEMPERATURE, [0; 5]);
            while e.poll(Instant(0)).is_some() {}
            e.clear(0x3100);
            let changed = on.then_some([0, 0, 0x09, 0, 0, 0, 0, 0]);
            assert_eq!(
                e.poll(Instant(0)),
                changed,
                "0x1001 0x0D -> 0x09, rule {on}"
            );
            e.clear(0x4200);
            assert_eq!(e.poll(Instant(0)), None, "0x1001 stays 0x09, rule {on}");
            e.clear(0x4210);
            assert_eq!(e.poll(Instant(0)), Some([0; 8]), "none left, rule {on}");
        }
    }

    /// CiA 301 §7.5.2.5 (0x1003): an entry holds the error code in bits 0–15 and the first two
    /// manufacturer bytes (EMCY bytes 3–4) in bits 16–31, as the frame has them.
    #[test]
    fn a_history_entry_holds_the_code_and_the_first_manufacturer_bytes() {
        let mut e = Emcy::default();
        e.raise(0x5000, reg::MANUFACTURER, [0x34, 0x12, 0x56, 0, 0]);
        assert_eq!(e.history(1), Some(0x1234_5000));
    }

    /// The pending queue is bounded: an EMCY that does not fit is counted as lost, the queued
    /// ones go out in order.
    /// The rings once they have wrapped: 0x1003 lists the last eight errors newest first, and
    /// the pending frames leave in the order they were queued, with the ninth counted as lost.
    #[test]
    fn history_and_pending_keep_their_order_after_wrapping() {
        let mut e = Emcy::default();
        for k in 0..10u16 {
            e.event(0x1000 + k, [0; 5]);
        }
        let hist: [u32; HISTORY_LEN] = core::array::from_fn(|i| e.history(i + 1).unwrap());
        assert_eq!(hist, core::array::from_fn(|i| 0x1009 - i as u32));
        assert_eq!(e.history(HISTORY_LEN + 1), None);
        // Ten queued, eight kept (the first eight), two lost; take three, queue four more.
        assert_eq!(e.lost, 2);
        let code = |f: [u8; 8]| u16::from_le_bytes([f[0], f[1]]);
        let first: [u16; 3] = core::array::from_fn(|_| code(e.poll(Instant(0)).unwrap()));
        assert_eq!(first, [0x1000, 0x1001, 0x1002]);
        for k in 0..3u16 {
            e.event(0x2000 + k, [0; 5]);
        }
        e.event(0x2003, [0; 5]);
        assert_eq!(e.lost, 3, "the fourth finds the queue full again");
        let rest: [u16; 8] = core::array::from_fn(|_| code(e.poll(Instant(0)).unwrap()));
        assert_eq!(
            rest,
            [0x1003, 0x1004, 0x1005, 0x1006, 0x1007, 0x2000, 0x2001, 0x2002]
        );
        assert_eq!(e.poll(Instant(0)), None);
    }

    #[test]
    fn a_full_pending_queue_counts_the_lost_emcy() {
        let mut e = Emcy::default();
        for k in 0..PENDING_LEN as u16 + 1 {
            e.event(0x1000 + k, [0; 5]);
        }
        assert_eq!(e.lost, 1);
        for k in 0..PENDING_LEN as u16 {
            assert_eq!(e.poll(Instant(0)).map(|f| f[0]), Some(k as u8));
        }
        assert_eq!(e.poll(Instant(0)), None);
    }

    /// An error that clears and comes back is a new event: a second EMCY.
    #[test]
    fn an_error_that_clears_and_returns_sends_again() {
        let mut e = Emcy::default();
        e.raise(code::HARDWARE, reg::MANUFACTURER, [0; 5]);
        e.clear(code::HARDWARE);
        e.raise(code::HARDWARE, reg::MANUFACTURER, [0; 5]);
        let sent: [Option<[u8; 8]>; 4] = core::array::from_fn(|_| e.poll(Instant(0)));
        assert_eq!(sent[0].map(|f| f[1]), Some(0x50));
        assert_eq!(sent[1], Some([0; 8]));
        assert_eq!(sent[2].map(|f| (f[1], f[2])), Some((0x50, 0x81)));
        assert_eq!(sent[3], None);
        assert_eq!((e.history(1), e.history(2)), (Some(0x5000), Some(0x5000)));
    }

    /// Reset forgets active errors and queued EMCYs; the history stays until cleared.
    #[test]
    fn reset_forgets_active_and_pending_keeps_history() {
        let mut e = Emcy::default();
        e.set_inhibit(100);
        e.raise(code::HARDWARE, reg::MANUFACTURER, [0; 5]);
        assert!(e.poll(Instant(0)).is_some());
        e.event(0x1234, [0; 5]);
        e.reset();
        assert_eq!((e.register(), e.poll_timeout()), (0, None));
        assert_eq!(e.poll(Instant(0)), None);
        e.event(0x1234, [0; 5]);
        assert_eq!(
            e.poll_timeout(),
            Some(Instant(0)),
            "inhibit restarts with the reset"
        );
        assert_eq!(e.history(2), Some(0x1234));
        e.clear_history();
        assert_eq!((e.history_len(), e.history(1)), (0, None));
    }

    /// `history_or_zero` reads the ring without checking the count: it answers as `history`
    /// with 0 for a missing entry, however full the history and after a clear.
    #[test]
    fn history_or_zero_answers_as_history() {
        let mut e = Emcy::default();
        let check = |e: &Emcy| {
            for i in 1..=HISTORY_LEN {
                assert_eq!(e.history_or_zero(i), e.history(i).unwrap_or(0), "entry {i}");
            }
        };
        check(&e);
        for round in 0..3u16 {
            for k in 0..11u16 {
                e.event(0x1000 + k, [k as u8, round as u8, 0, 0, 0]);
                check(&e);
                e.poll(Instant(0));
                if k == 4 {
                    e.reset();
                    check(&e);
                }
            }
            e.clear_history();
            check(&e);
            for k in 0..=round {
                e.raise(0x2000 + k, reg::MANUFACTURER, [1; 5]);
                check(&e);
            }
            e.clear_history();
            check(&e);
        }
    }

    #[test]
    fn inhibit_spaces_emcys() {
        let mut e = Emcy::default();
        e.set_inhibit(100); // 10 ms
        e.event(0x9080, [1, 0, 0, 0, 0]);
        e.event(0x9080, [1, 1, 0, 0, 0]);
        assert!(e.poll(Instant(0)).is_some());
        assert!(e.poll(Instant(9_999)).is_none());
        assert_eq!(e.poll_timeout(), Some(Instant(10_000)));
        assert!(e.poll(Instant(10_000)).is_some());
    }

    /// With the register-change rule, clearing an error whose register bit no other active error
    /// holds sends EMCY 0x0000, whatever its place in the list (here the second of two); one
    /// whose bit another error keeps sends nothing.
    #[test]
    fn clearing_the_only_error_of_a_register_bit_reports_the_change() {
        let mut e = Emcy::default();
        e.set_reset_on_register_change(true);
        e.raise(code::TEMPERATURE, reg::TEMPERATURE, [0; 5]);
        e.raise(0x3100, reg::VOLTAGE, [0; 5]);
        e.raise(0x3200, reg::VOLTAGE, [0; 5]);
        while e.poll(Instant(0)).is_some() {}
        e.clear(0x3200);
        assert!(e.poll(Instant(0)).is_none(), "voltage still held by 0x3100");
        e.clear(0x3100);
        let f = e
            .poll(Instant(0))
            .expect("EMCY 0x0000: the voltage bit is gone");
        assert_eq!(f[..3], [0x00, 0x00, reg::GENERIC | reg::TEMPERATURE]);
    }
}
