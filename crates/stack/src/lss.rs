//! LSS slave (CiA 305): commissioning node-id and bit rate on 0x7E5 / 0x7E4.
//!
//! The LSS slave runs beside the NMT state machine in one of two states, *waiting* and
//! *configuration*. Every request is an 8-byte frame on 0x7E5 whose byte 0 is the command
//! specifier; answers go out on 0x7E4, 8 bytes, byte 0 repeating the specifier.
//!
//! | cs | service | states | answer |
//! | --- | --- | --- | --- |
//! | 0x04 | switch state global (byte 1: 0 waiting, 1 configuration) | both | none |
//! | 0x40…0x43 | switch state selective (vendor, product, revision, serial) | waiting | 0x44 |
//! | 0x11 | configure node-id | configuration | 0x11 status |
//! | 0x13 | configure bit timing (table, index) | configuration | 0x13 status |
//! | 0x15 | activate bit timing (switch delay ms, LE) | configuration | none |
//! | 0x17 | store configuration | configuration | 0x17 status |
//! | 0x46…0x4B | identify remote slave (vendor, product, revision low/high, serial low/high) | both | 0x4F |
//! | 0x4C | identify non-configured remote slave | both | 0x50 |
//! | 0x51 | fastscan (DS 305 V2 models only) | waiting, non-configured | 0x4F |
//! | 0x5A…0x5E | inquire vendor, product, revision, serial, node-id | configuration | value |
//!
//! Anything else (unknown specifiers, DLC ≠ 8, services outside their state) is ignored without
//! an answer, as CiA 305 requires of a slave: the master relies on the silence.
//!
//! The rules the seeds leave open follow CiA 305 as implemented by CANopenNode (OD.md G14):
//! 32-bit values are little-endian in bytes 1…4, the switch delay is 16 bit LE in bytes 1…2 and
//! covers two periods (before and after the switch), the bit-timing table is the CiA table 0.

use crate::wire::{Duration, Instant};

/// Node-id of a node that has none (CiA 305).
pub const UNCONFIGURED: u8 = 0xFF;

pub use crate::wire::lss::{
    cs, Identify, Inquire, LssRequest, LssResponse, Part, Status, FASTSCAN_CONFIRM,
    MODE_CONFIGURATION, MODE_WAITING, STATUS_MANUFACTURER, STATUS_OK, STATUS_REFUSED,
    STATUS_STORAGE_ERROR,
};

/// Status byte: service done.
const OK: u8 = STATUS_OK;
/// Status byte of configure node-id / bit timing: value out of range / not supported.
const REFUSED: u8 = STATUS_REFUSED;
/// Status byte of store configuration: storage media access error.
const STORAGE_ERROR: u8 = STATUS_STORAGE_ERROR;

/// Marks the reserved entry of [`BIT_TIMING_TABLE`].
const RESERVED: u16 = u16::MAX;

/// The CiA 305 bit-timing table 0 in kbit/s, by index (5 is reserved, 9 is automatic
/// bit-rate detection, which canpos represents as 0).
const BIT_TIMING_TABLE: [u16; 10] = [1000, 800, 500, 250, 125, RESERVED, 50, 20, 10, 0];

/// The bit rate in kbit/s of CiA 305 table-0 entry `index` (0 = automatic detection), `None`
/// for a reserved or unknown index. Whether a model accepts it is a separate question (D9).
pub fn bit_timing_kbps(index: u8) -> Option<u16> {
    BIT_TIMING_TABLE
        .get(index as usize)
        .copied()
        .filter(|&k| k != RESERVED)
}

/// Progress through a multi-frame LSS sequence (switch selective, identify remote slave): how
/// many frames arrived in order, and whether all of them matched so far.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
struct Sequence {
    step: u8,
    matched: bool,
    /// The low bound of the range being received (identify remote slave).
    low: u32,
}

impl Sequence {
    /// Frame `step` of a sequence whose frames are `0..=last` arrived, `matched` or not. True
    /// once frame `last` completes it in order with every frame matched; the sequence then starts
    /// over. A frame out of order starts it over too; frame 0 always (re)starts it, so a master
    /// can retry at any point.
    #[inline(never)] // both LSS sequences share one copy
    fn advance(&mut self, step: u8, matched: bool, last: u8) -> bool {
        if step != 0 && self.step != step {
            *self = Sequence::default();
            return false;
        }
        // `low` is left as it is: only a low-bound frame in order sets what a later one reads.
        self.matched = matched && (step == 0 || self.matched);
        self.step = step + 1;
        if step != last {
            return false;
        }
        let all = self.matched;
        *self = Sequence::default();
        all
    }
}

/// An "activate bit timing" in progress. CiA 305: the slave stops sending and receiving, waits
/// the switch delay, switches its bit rate, waits the delay again, then goes on at the new rate
/// (the node stays silent until [`Request::ActivateBitRate`]'s `silent_until`).
///
/// A flag rather than an `Option`: the default (none pending) is all zeros, which a node reset
/// writes in place.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
struct BitSwitch {
    /// A switch is pending.
    pending: bool,
    /// End of the first delay: the new bit rate becomes active.
    switch_at: Instant,
    /// The bit rate to switch to (kbit/s).
    kbps: u16,
}

/// What the LSS slave needs to know of the node. Asked per frame, and the LSS address only by
/// the services that compare it (an inquiry of the node-id needs no dictionary search).
pub trait LssNode {
    /// The LSS address: 0x1018 sub 1…4 (vendor-id, product code, revision, serial).
    fn address(&self) -> [u32; 4];
    /// Part `i` (0 vendor-id … 3 serial number) of [`LssNode::address`], all a service
    /// compares or reports at a time; a node can look up just that one.
    fn address_part(&self, i: u8) -> u32 {
        self.address()[i as usize]
    }
    /// Active node-id ([`UNCONFIGURED`] = none).
    fn node_id(&self) -> u8;
    /// Node-id and bit rate (kbit/s) that the next reset activates.
    fn pending(&self) -> (u8, u16);
    /// The model answers fastscan (DS 305 V2).
    fn fastscan(&self) -> bool;
    /// CiA 305 table-0 bit-timing indices the model accepts (D9).
    fn bit_timing(&self) -> &'static [u8];

    /// A node takes part in fastscan / answers "identify non-configured" only while it has
    /// neither an active nor a pending node-id: one that already got a pending id will enter
    /// NMT with it.
    fn unconfigured(&self) -> bool {
        self.node_id() == UNCONFIGURED && self.pending().0 == UNCONFIGURED
    }
}

/// A change of node state an LSS request asks for. The slave changes only its own state; the
/// node carries these out and hands the outcome to [`confirm`] for the answer.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Request {
    /// Configure node-id: the id the next reset communication activates.
    ConfigureNodeId(u8),
    /// Configure bit timing: the bit rate (kbit/s, 0 = automatic) the next reset activates.
    ConfigureBitRate(u16),
    /// Activate bit timing: silent (deaf and mute) until `silent_until`; the new bit rate
    /// comes from [`LssSlave::handle_timeout`] halfway.
    ActivateBitRate {
        /// End of both switch delays.
        silent_until: Instant,
    },
    /// Store configuration: keep the pending node-id and bit rate.
    StoreConfiguration,
}

/// What one LSS frame produced.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
// A word-sized tag puts an answer on a word boundary: written and read as two aligned words
// (a byte tag leaves it at offset 1).
#[repr(u32)]
pub enum Output {
    /// No answer (CiA 305 slaves stay silent on what is not for them).
    Silent,
    /// This answer on 0x7E4.
    Answer([u8; 8]),
    /// A request for the node; its outcome gives the answer ([`confirm`]).
    Do(Request),
}

/// The answer to a [`Request`] the node carried out (`ok`) or could not.
pub fn confirm(r: Request, ok: bool) -> Option<[u8; 8]> {
    match r {
        // Only values the slave accepted become requests.
        Request::ConfigureNodeId(_) => Some(answer(cs::CONFIGURE_NODE_ID, OK)),
        Request::ConfigureBitRate(_) => Some(answer(cs::CONFIGURE_BIT_TIMING, OK)),
        Request::ActivateBitRate { .. } => None,
        Request::StoreConfiguration => Some(answer(
            cs::STORE_CONFIGURATION,
            if ok { OK } else { STORAGE_ERROR },
        )),
    }
}

/// LSS slave state (waiting / configuration) beside the NMT state machine.
#[derive(Clone, Debug, Default)]
pub struct LssSlave {
    configuration: bool,
    selective: Sequence,
    identify: Sequence,
    /// Which LSS address part (0 vendor … 3 serial) fastscan is checking.
    fastscan_pos: u8,
    switch: BitSwitch,
}

impl LssSlave {
    /// Whether the slave is in LSS configuration state.
    #[inline]
    pub fn in_configuration(&self) -> bool {
        self.configuration
    }

    /// Enters configuration state (TMI R7: a node without a valid node-id goes there by
    /// itself).
    pub fn force_configuration(&mut self) {
        self.configuration = true;
    }

    /// Handles one frame on 0x7E5.
    #[cfg_attr(not(feature = "inline-hot-paths"), inline(never))]
    pub fn handle(&mut self, data: &[u8], now: Instant, node: &impl LssNode) -> Output {
        // CiA 305 frames are always 8 bytes; anything else is not LSS and gets no answer.
        let Ok(d) = <&[u8; 8]>::try_from(data) else {
            return Output::Silent;
        };
        let value = u32::from_le_bytes([d[1], d[2], d[3], d[4]]);
        let answer_if = |a: Option<[u8; 8]>| a.map_or(Output::Silent, Output::Answer);
        match d[0] {
            cs::SWITCH_GLOBAL => {
                match d[1] {
                    0 => {
                        self.configuration = false;
                        // Leaving configuration ends any half-done selection.
                        self.selective = Sequence::default();
                    }
                    1 => self.configuration = true,
                    _ => {}
                }
                Output::Silent
            }
            // Selection only makes sense for slaves still waiting (CiA 305 state table);
            // a slave already in configuration ignores it, as CANopenNode does.
            c @ cs::SWITCH_SEL_VENDOR..=cs::SWITCH_SEL_SERIAL if !self.configuration => {
                let part = c - cs::SWITCH_SEL_VENDOR;
                let matched = value == address_part(node, part);
                if self.selective.advance(part, matched, 3) {
                    self.configuration = true;
                    return Output::Answer(answer(cs::SWITCH_SEL_RESPONSE, 0));
                }
                Output::Silent
            }
            c @ cs::IDENTIFY_VENDOR..=cs::IDENTIFY_SERIAL_HIGH => {
                answer_if(self.identify(c, value, node))
            }
            cs::IDENTIFY_NON_CONFIGURED => answer_if(
                node.unconfigured()
                    .then(|| answer(cs::IDENTIFY_NON_CONFIGURED_SLAVE, 0)),
            ),
            cs::FASTSCAN => answer_if(self.fastscan(d, value, node)),
            _ if !self.configuration => Output::Silent,
            // From here on: services of the configuration state only.
            cs::CONFIGURE_NODE_ID => {
                let id = d[1];
                if (1..=127).contains(&id) || id == UNCONFIGURED {
                    // Takes effect at the next reset communication (or, for a node that has
                    // none yet, when it is switched back to waiting: node.rs `after_lss`).
                    Output::Do(Request::ConfigureNodeId(id))
                } else {
                    Output::Answer(answer(cs::CONFIGURE_NODE_ID, REFUSED))
                }
            }
            cs::CONFIGURE_BIT_TIMING => {
                let (table, index) = (d[1], d[2]);
                match bit_timing_kbps(index) {
                    Some(kbps) if table == 0 && node.bit_timing().contains(&index) => {
                        Output::Do(Request::ConfigureBitRate(kbps))
                    }
                    _ => Output::Answer(answer(cs::CONFIGURE_BIT_TIMING, REFUSED)),
                }
            }
            cs::ACTIVATE_BIT_TIMING => {
                let delay = Duration::from_millis(u16::from_le_bytes([d[1], d[2]]) as u64);
                let switch_at = now + delay;
                self.switch = BitSwitch {
                    pending: true,
                    switch_at,
                    kbps: node.pending().1,
                };
                Output::Do(Request::ActivateBitRate {
                    silent_until: switch_at + delay,
                })
            }
            cs::STORE_CONFIGURATION => Output::Do(Request::StoreConfiguration),
            c @ cs::INQUIRE_VENDOR..=cs::INQUIRE_SERIAL => {
                let v = address_part(node, c - cs::INQUIRE_VENDOR).to_le_bytes();
                Output::Answer([c, v[0], v[1], v[2], v[3], 0, 0, 0])
            }
            // The manuals' example answers `5E 7F` for a node running as 127: the active
            // node-id, not a pending one (0xFF while the node has none).
            cs::INQUIRE_NODE_ID => Output::Answer(answer(cs::INQUIRE_NODE_ID, node.node_id())),
            _ => Output::Silent,
        }
    }

    /// Identify remote slave (0x46…0x4B): answers 0x4F after the sixth frame if vendor and
    /// product equal the slave's and revision and serial lie within the bounds (inclusive).
    /// Valid in both LSS states (CiA 305), so a master can look for slaves at any time.
    fn identify(&mut self, c: u8, value: u32, node: &impl LssNode) -> Option<[u8; 8]> {
        let step = c - cs::IDENTIFY_VENDOR;
        // Steps 2 and 4 are the low bounds of revision and serial, kept until their high bounds
        // (3, 5) arrive; vendor and product (0, 1) are a range of one value.
        let bound = step == 2 || step == 4;
        if bound {
            // A frame out of order clears it again in `advance`.
            self.identify.low = value;
        }
        let low = if step < 2 { value } else { self.identify.low };
        let matched = bound || (low..=value).contains(&address_part(node, step.div_ceil(2)));
        self.identify
            .advance(step, matched, 5)
            .then(|| answer(cs::IDENTIFY_SLAVE, 0))
    }

    /// Fastscan (CiA 305 V2): byte 5 `bitChecked`, byte 6 `lssSub`, byte 7 `lssNext`. Only
    /// non-configured slaves in waiting state take part, so that configured nodes and a slave
    /// already found (now in configuration) stay out of the next scan.
    fn fastscan(&mut self, d: &[u8; 8], id_number: u32, node: &impl LssNode) -> Option<[u8; 8]> {
        if !node.fastscan() || self.configuration || !node.unconfigured() {
            return None;
        }
        let (bit_checked, sub, next) = (d[5], d[6], d[7]);
        if bit_checked == FASTSCAN_CONFIRM {
            // Reset: every participant answers and starts again with the vendor-id.
            self.fastscan_pos = 0;
            return Some(answer(cs::IDENTIFY_SLAVE, 0));
        }
        // `fastscan_pos` is at most 3 (it is 0 or a checked `next`), so `sub` is too.
        if bit_checked > 31 || next > 3 || sub != self.fastscan_pos {
            return None;
        }
        // Bits bit_checked…31 are compared; the lower ones are still unknown to the master.
        let mask = u32::MAX << bit_checked;
        if address_part(node, sub) & mask != id_number & mask {
            return None;
        }
        self.fastscan_pos = next;
        if bit_checked == 0 && next < sub {
            // All 128 bits confirmed (lssNext wraps back): this slave is the one found.
            self.configuration = true;
            self.fastscan_pos = 0;
        }
        Some(answer(cs::IDENTIFY_SLAVE, 0))
    }

    /// Deadline of a pending bit-rate switch.
    #[inline]
    pub fn poll_timeout(&self) -> Option<Instant> {
        self.switch.pending.then_some(self.switch.switch_at)
    }

    /// [`LssSlave::poll_timeout`] in µs, `u64::MAX` for none (the node's timer table).
    #[inline]
    pub fn due_us(&self) -> u64 {
        if self.switch.pending {
            self.switch.switch_at.0
        } else {
            u64::MAX
        }
    }

    /// Advances a pending bit-rate switch: the bit rate to make active now, once the first
    /// switch delay is over.
    pub fn handle_timeout(&mut self, now: Instant) -> Option<u16> {
        let s = self.switch;
        if !s.pending || now < s.switch_at {
            return None;
        }
        self.switch.pending = false;
        Some(s.kbps)
    }
}

/// [`LssNode::address_part`]: one call for the four services that compare or report a part.
#[cfg_attr(not(feature = "inline-hot-paths"), inline(never))]
fn address_part(node: &impl LssNode, i: u8) -> u32 {
    node.address_part(i)
}

/// An LSS answer frame: specifier, status / byte 1, zeros.
const fn answer(c: u8, status: u8) -> [u8; 8] {
    [c, status, 0, 0, 0, 0, 0, 0]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn table_zero() {
        assert_eq!(bit_timing_kbps(0), Some(1000));
        assert_eq!(bit_timing_kbps(4), Some(125));
        assert_eq!(bit_timing_kbps(5), None);
        assert_eq!(bit_timing_kbps(8), Some(10));
        assert_eq!(bit_timing_kbps(9), Some(0));
        assert_eq!(bit_timing_kbps(10), None);
        assert_eq!(bit_timing_kbps(0xFF), None);
    }

    /// A node with node-id 5 and 250 kbit/s pending.
    struct Unit;

    impl LssNode for Unit {
        fn address(&self) -> [u32; 4] {
            [1, 2, 3, 4]
        }
        fn node_id(&self) -> u8 {
            5
        }
        fn pending(&self) -> (u8, u16) {
            (5, 250)
        }
        fn fastscan(&self) -> bool {
            true
        }
        fn bit_timing(&self) -> &'static [u8] {
            &[3]
        }
    }

    #[test]
    fn activate_bit_timing_is_due_after_the_first_switch_delay() {
        // CiA 305: the new bit rate becomes active one switch delay after the request (and
        // the node stays silent one more); the slave's deadline says when.
        let mut s = LssSlave::default();
        assert_eq!((s.poll_timeout(), s.due_us()), (None, u64::MAX));
        let t0 = Instant::from_micros(1_000);
        s.handle(&[cs::SWITCH_GLOBAL, 1, 0, 0, 0, 0, 0, 0], t0, &Unit);
        let out = s.handle(&[cs::ACTIVATE_BIT_TIMING, 10, 0, 0, 0, 0, 0, 0], t0, &Unit);
        assert_eq!(
            out,
            Output::Do(Request::ActivateBitRate {
                silent_until: Instant::from_micros(21_000)
            })
        );
        let due = Instant::from_micros(11_000);
        assert_eq!((s.poll_timeout(), s.due_us()), (Some(due), 11_000));
        assert_eq!(s.handle_timeout(Instant::from_micros(10_999)), None);
        assert_eq!(s.poll_timeout(), Some(due), "still pending");
        assert_eq!(s.handle_timeout(due), Some(250));
        assert_eq!((s.poll_timeout(), s.due_us()), (None, u64::MAX));
    }

    /// A node that gives only its whole address answers the inquiry of each part from it (the
    /// default `LssNode::address_part`).
    #[test]
    fn inquiries_read_the_default_address_part() {
        let mut s = LssSlave::default();
        let t0 = Instant::ZERO;
        s.handle(&[cs::SWITCH_GLOBAL, 1, 0, 0, 0, 0, 0, 0], t0, &Unit);
        for (c, v) in (cs::INQUIRE_VENDOR..=cs::INQUIRE_SERIAL).zip(1u8..) {
            let out = s.handle(&[c, 0, 0, 0, 0, 0, 0, 0], t0, &Unit);
            assert_eq!(out, Output::Answer([c, v, 0, 0, 0, 0, 0, 0]), "{c:#x}");
        }
    }

    /// The slave reads the frames [`LssRequest::emit`] writes and answers with the bytes
    /// [`LssResponse::emit`] writes: one vocabulary for both ends.
    #[test]
    fn slave_speaks_the_wire_types() {
        let mut s = LssSlave::default();
        let t0 = Instant::ZERO;
        let mut ask = |r: LssRequest| s.handle(&r.emit(), t0, &Unit);
        let mode = MODE_CONFIGURATION;
        assert_eq!(ask(LssRequest::SwitchGlobal { mode }), Output::Silent);
        for (part, value) in Part::ALL.into_iter().zip(1u32..) {
            let answer = LssResponse::Identity { part, value }.emit();
            let asked = ask(LssRequest::Inquire(Inquire::Identity(part)));
            assert_eq!(asked, Output::Answer(answer), "{part:?}");
        }
        let node_id = LssResponse::NodeId(5).emit();
        assert_eq!(
            ask(LssRequest::Inquire(Inquire::NodeId)),
            Output::Answer(node_id)
        );
        assert_eq!(
            ask(LssRequest::ConfigureNodeId { node_id: 9 }),
            Output::Do(Request::ConfigureNodeId(9))
        );
        let refused = Status {
            code: STATUS_REFUSED,
            spec: 0,
        };
        assert_eq!(
            ask(LssRequest::ConfigureNodeId { node_id: 200 }),
            Output::Answer(LssResponse::ConfigureNodeId(refused).emit())
        );
        assert_eq!(
            ask(LssRequest::ConfigureBitTiming { table: 0, index: 2 }),
            Output::Answer(LssResponse::ConfigureBitTiming(refused).emit())
        );
        assert_eq!(
            ask(LssRequest::ConfigureBitTiming { table: 0, index: 3 }),
            Output::Do(Request::ConfigureBitRate(250))
        );
        let stored = confirm(Request::StoreConfiguration, false).map(|a| LssResponse::parse(&a));
        let error = Status {
            code: STATUS_STORAGE_ERROR,
            spec: 0,
        };
        assert_eq!(stored, Some(Some(LssResponse::StoreConfiguration(error))));
        // Waiting again: selected by its address, the slave answers switch selective.
        let waiting = MODE_WAITING;
        assert_eq!(
            ask(LssRequest::SwitchGlobal { mode: waiting }),
            Output::Silent
        );
        let mut last = Output::Silent;
        for (part, value) in Part::ALL.into_iter().zip(1u32..) {
            last = ask(LssRequest::SwitchSelective { part, value });
        }
        assert_eq!(last, Output::Answer(LssResponse::SwitchSelective.emit()));
    }

    #[test]
    fn sequence_restarts_and_rejects_out_of_order() {
        let mut s = Sequence::default();
        assert!(!s.advance(1, true, 3));
        assert_eq!(s.step, 0);
        assert!(!s.advance(0, true, 3));
        assert!(!s.advance(1, false, 3));
        assert!(!s.matched);
        assert!(!s.advance(0, true, 3));
        assert!(s.matched && s.step == 1);
        assert!(!s.advance(2, true, 3));
        assert_eq!(s.step, 0);
    }

    #[test]
    fn sequence_completes_only_in_order_and_all_matched() {
        let mut s = Sequence::default();
        for step in 0..3 {
            assert!(!s.advance(step, true, 3));
        }
        assert!(s.advance(3, true, 3));
        assert_eq!(s, Sequence::default(), "starts over once complete");
        for step in 0..3 {
            assert!(!s.advance(step, step != 1, 3));
        }
        assert!(!s.advance(3, true, 3), "one frame did not match");
        assert_eq!(s, Sequence::default());
        for step in [0, 1, 3] {
            assert!(!s.advance(step, true, 3), "frame 2 missing");
        }
    }
}
