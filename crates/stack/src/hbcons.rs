//! Heartbeat consumer (CiA 301 §7.2.8.3.2.2, object 0x1016 "consumer heartbeat time").
//!
//! Each sub-index 1…n is `(node-id << 16) | time_ms`: the node whose heartbeat (0x700 +
//! node-id) is expected at least every `time_ms`. A zero time, or a node-id 0 or above 127,
//! leaves the entry unused. Monitoring of a node starts with the first heartbeat received from
//! it, not with the configuration; a heartbeat that then fails to come within the time is a
//! heartbeat event (the node raises EMCY 0x8130 and reacts as 0x1029 sub 1 says). D27 in
//! docs/DECISIONS.md has what the stack decided beyond the standard: the states it monitors
//! in, and the boot-up of a consumed node.
//!
//! Sized by [`MAX_HB_CONSUMERS`]; with 0 the service is compiled out (every method a constant).

use crate::config::MAX_HB_CONSUMERS;
use crate::od::{Abort, Dictionary};
use crate::timers::NEVER;
use crate::wire::{Duration, Instant};

/// The consumer heartbeat time object.
pub const INDEX: u16 = 0x1016;

/// Bits 31–24 of an entry: reserved, 0 (CiA 301).
const RESERVED: u32 = 0xFF00_0000;

/// The node-id an entry `raw` watches, `None` for an unused entry (zero time, node-id 0 or
/// above 127).
#[inline]
pub const fn watched(raw: u32) -> Option<u8> {
    let node = (raw >> 16) as u8;
    if raw & 0xFFFF == 0 || node == 0 || node > 127 {
        None
    } else {
        Some(node)
    }
}

/// The rule of an entry's value alone: the reserved bits are 0 (abort 0x06090030 otherwise).
pub fn value_allowed(raw: u32) -> Result<(), Abort> {
    if raw & RESERVED != 0 {
        return Err(Abort::InvalidValue);
    }
    Ok(())
}

/// The rule of a write of `raw` to sub-index `sub` against the other entries in `od`: a node-id
/// already watched by another entry with a non-zero time is refused with 0x06040043 (general
/// parameter incompatibility, CiA 301), and nothing changes.
pub fn check(od: &Dictionary, sub: u8, raw: u32) -> Result<(), Abort> {
    let Some(node) = watched(raw) else {
        return Ok(());
    };
    for other in 1..=MAX_HB_CONSUMERS as u8 {
        let Some(v) = od.value(INDEX, other) else {
            break;
        };
        if other != sub && watched(v) == Some(node) {
            return Err(Abort::ParamIncompatible);
        }
    }
    Ok(())
}

/// Where a consumer entry stands.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
enum Watch {
    /// Unused (no node-id or no time).
    #[default]
    Unused,
    /// Configured; no heartbeat received yet (or since a boot-up, or since the node left
    /// pre-operational / operational): not monitored.
    Waiting,
    /// Heartbeats come; the next one is due at the entry's deadline.
    Active,
}

/// One 0x1016 entry.
#[derive(Clone, Copy, Debug, Default)]
struct Entry {
    node: u8,
    watch: Watch,
    /// The heartbeat was missed and none has come since: the node's error stands.
    lost: bool,
    /// The consumer time in ms (a `u16` as in the object: 16 B an entry, not 24).
    time_ms: u16,
    deadline: Instant,
}

/// The heartbeat consumer: the entries of 0x1016 and which node-ids they watch.
#[derive(Clone, Debug, Default)]
pub struct HbConsumer {
    entries: [Entry; MAX_HB_CONSUMERS],
    /// The watched node-ids, one bit each (bit n of word n / 32): a received frame's one test.
    nodes: [u32; 4],
    /// The earliest deadline of an active entry in µs, [`NEVER`] for none.
    next: u64,
}

impl HbConsumer {
    /// Takes every entry from `od` (reset communication, a load): nothing is monitored until
    /// each node's first heartbeat. A node-id a stored image names twice is watched by its first
    /// entry only (an SDO write cannot make the second one).
    pub fn load(&mut self, od: &Dictionary) {
        *self = HbConsumer {
            next: NEVER,
            ..HbConsumer::default()
        };
        for sub in 1..=MAX_HB_CONSUMERS as u8 {
            let Some(raw) = od.value(INDEX, sub) else {
                break;
            };
            self.set(sub, raw);
        }
    }

    /// Sub-index `sub` (1…) now holds `raw` (a write that passed [`check`]): the entry waits
    /// for its node's first heartbeat, and an error it had ends. Returns whether one did.
    pub fn set(&mut self, sub: u8, raw: u32) -> bool {
        let Some(e) = self.entries.get_mut(usize::from(sub).wrapping_sub(1)) else {
            return false;
        };
        let was_lost = e.lost;
        let old = e.node;
        *e = Entry::default();
        if old != 0 {
            Self::mark(&mut self.nodes, old, false);
        }
        if let Some(node) = watched(raw) {
            if !self.watches(node) {
                let e = &mut self.entries[usize::from(sub) - 1];
                e.node = node;
                e.watch = Watch::Waiting;
                e.time_ms = raw as u16;
                Self::mark(&mut self.nodes, node, true);
            }
        }
        self.refresh_next();
        was_lost
    }

    fn mark(nodes: &mut [u32; 4], node: u8, on: bool) {
        let (w, b) = (usize::from(node >> 5), 1u32 << (node & 31));
        if on {
            nodes[w] |= b;
        } else {
            nodes[w] &= !b;
        }
    }

    /// Whether an entry watches `node` (1…127).
    #[inline]
    fn watches(&self, node: u8) -> bool {
        self.nodes[usize::from(node >> 5) & 3] >> (node & 31) & 1 != 0
    }

    /// Whether a frame with CAN-ID `id` is a watched node's heartbeat (the receive path's
    /// test: a constant `false` when the service is compiled out).
    #[inline(always)]
    pub fn consumes(&self, id: u16) -> bool {
        if MAX_HB_CONSUMERS == 0 {
            return false;
        }
        // Node-ids 1…127, then its bit. Below 0x701 first: most frames that get this far
        // (other nodes' PDOs) leave after that one compare.
        if id < 0x701 {
            return false;
        }
        id <= 0x77F && self.watches(id as u8 & 0x7F)
    }

    /// A heartbeat of `node` arrived with state byte `state` at `now` (the node is
    /// pre-operational or operational). A heartbeat starts or continues monitoring; a boot-up
    /// (state 0) stops it until the node's next heartbeat (D27). Either ends the node's error:
    /// returns whether it did.
    pub fn received(&mut self, node: u8, state: u8, now: Instant) -> bool {
        let mut ended = false;
        for e in self.entries.iter_mut() {
            if e.node == node && e.watch != Watch::Unused {
                ended = e.lost;
                e.lost = false;
                if state & 0x7F == 0 {
                    e.watch = Watch::Waiting;
                } else {
                    e.watch = Watch::Active;
                    e.deadline = now + Duration::from_millis(u64::from(e.time_ms));
                }
            }
        }
        self.refresh_next();
        ended
    }

    /// The node left pre-operational and operational: no entry is monitored until its node's
    /// next heartbeat (errors that stand stay).
    pub fn pause(&mut self) {
        for e in self.entries.iter_mut() {
            if e.watch == Watch::Active {
                e.watch = Watch::Waiting;
            }
        }
        self.next = NEVER;
    }

    /// The next missed heartbeat at `now`: its node-id, the entry no longer monitored until
    /// that node's next heartbeat. Call until `None`.
    pub fn handle_timeout(&mut self, now: Instant) -> Option<u8> {
        if now.0 < self.next {
            return None;
        }
        let mut hit = None;
        for e in self.entries.iter_mut() {
            if e.watch == Watch::Active && now >= e.deadline {
                e.watch = Watch::Waiting;
                e.lost = true;
                hit = Some(e.node);
                break;
            }
        }
        self.refresh_next();
        hit
    }

    /// Whether a watched node's heartbeat was missed and has not come since.
    pub fn any_lost(&self) -> bool {
        self.entries.iter().any(|e| e.lost)
    }

    /// The next deadline in µs, `u64::MAX` for none (the node's timer table).
    #[inline]
    pub fn due_us(&self) -> u64 {
        if MAX_HB_CONSUMERS == 0 {
            return NEVER;
        }
        self.next
    }

    fn refresh_next(&mut self) {
        self.next = self
            .entries
            .iter()
            .filter(|e| e.watch == Watch::Active)
            .map(|e| e.deadline.0)
            .min()
            .unwrap_or(NEVER);
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use crate::model::{CommConfig, Features, Model, Table};
    use crate::od::cia301;
    use crate::od::{Access, DataType, DefaultValue, Entry as OdEntry, Group, Range};
    use std::boxed::Box;
    use std::vec::Vec;

    const fn raw(node: u8, ms: u16) -> u32 {
        (node as u32) << 16 | ms as u32
    }

    /// A dictionary with 0x1016 sub 0…n holding `values`.
    fn od_with(values: &[u32]) -> Dictionary {
        let mut t: Vec<OdEntry> = Vec::new();
        let e = |sub: u8, v: u32, ty: DataType| OdEntry {
            index: INDEX,
            sub,
            #[cfg(feature = "names")]
            name: "",
            ty,
            access: Access::Rw,
            pdo: false,
            default: DefaultValue::Const(v),
            range: &Range::Any,
            group: Group::Comm,
            hook: cia301::hook_of(INDEX, sub),
        };
        t.push(e(0, values.len() as u32, DataType::Unsigned8));
        for (i, &v) in values.iter().enumerate() {
            t.push(e(i as u8 + 1, v, DataType::Unsigned32));
        }
        let entries: &'static [OdEntry] = Box::leak(t.into_boxed_slice());
        let keys: &'static [u32] = Box::leak(entries.iter().map(OdEntry::key).collect());
        let model: &'static Model = Box::leak(Box::new(Model {
            table: Table {
                name: "t",
                product: "",
                vendor: "",
                entries,
                keys,
                features: FEATURES,
            },
            profile: (),
            param: |_, _| 0,
            derive: |c| c,
            variant: None,
            default_config: CommConfig {
                node_id: 1,
                bitrate_kbps: 125,
                serial: 0,
            },
        }));
        // (A node loads the defaults at its reset; these tests set them.)
        let mut od = Dictionary::new(model);
        for (i, e) in entries.iter().enumerate() {
            if let DefaultValue::Const(v) = e.default {
                od.set(i, v);
            }
        }
        od
    }

    const FEATURES: Features = Features {
        tag: 0,
        tpdos: 0,
        rpdos: 0,
        sdo_segmented: false,
        sdo_block: false,
        node_guarding: false,
        tpdo_rtr: false,
        lss_fastscan: false,
        lss_bit_timing: &[],
        bitrates: &[],
        store_preop_only: false,
        kill_signature: false,
        power_on_emcy: false,
        sync_length_emcy: false,
        emcy_on_register_change: false,
        event_timer_above_inhibit: false,
        lss_unconfigured_configures: false,
    };

    fn ms(n: u64) -> Instant {
        Instant::from_millis(n)
    }

    /// A table with no entries (or only unused ones) has no deadline: not even one at 0, which
    /// would wake a host at once after every reset.
    #[test]
    fn no_entries_no_deadline() {
        for v in [&[][..], &[0, raw(0, 5)][..]] {
            let mut c = HbConsumer::default();
            c.load(&od_with(v));
            assert_eq!(c.due_us(), NEVER);
            assert!(!c.consumes(0x700));
        }
    }

    #[test]
    fn an_entry_is_unused_without_a_node_id_1_to_127_or_a_time() {
        assert_eq!(watched(raw(5, 100)), Some(5));
        assert_eq!(watched(raw(127, 1)), Some(127));
        assert_eq!(watched(raw(0, 100)), None);
        assert_eq!(watched(raw(128, 100)), None);
        assert_eq!(watched(raw(5, 0)), None);
        assert_eq!(value_allowed(raw(5, 100)), Ok(()));
        assert_eq!(value_allowed(0x0100_0000), Err(Abort::InvalidValue));
        assert_eq!(value_allowed(0x8005_0064), Err(Abort::InvalidValue));
    }

    /// CiA 301: a node-id already watched with a non-zero time is refused (0x06040043) in any
    /// sub-index but its own; unused entries never clash. Generated over every pair of entries
    /// of a table of four.
    #[test]
    fn cia301_a_node_id_watched_twice_is_refused() {
        for held in 1..=4u8 {
            for sub in 1..=4u8 {
                let mut v = [raw(9, 0), raw(0, 50), raw(130, 50), 0];
                v[usize::from(held) - 1] = raw(7, 100);
                let od = od_with(&v);
                let want = if sub == held {
                    Ok(())
                } else {
                    Err(Abort::ParamIncompatible)
                };
                assert_eq!(check(&od, sub, raw(7, 200)), want, "held {held} sub {sub}");
                // Unused values never clash, nor does another node-id.
                assert_eq!(check(&od, sub, raw(7, 0)), Ok(()));
                assert_eq!(check(&od, sub, raw(8, 200)), Ok(()));
                // An entry with the node-id but a zero time watches nothing.
                assert_eq!(check(&od, sub, raw(9, 10)), Ok(()));
            }
        }
    }

    /// CiA 301: monitoring starts with the first heartbeat, not with the configuration; then a
    /// heartbeat missed for the consumer time is an event, once, until the next heartbeat.
    #[test]
    fn cia301_monitoring_starts_with_the_first_heartbeat() {
        for time in [1u16, 100, 0xFFFF] {
            let mut c = HbConsumer::default();
            c.load(&od_with(&[raw(5, time)]));
            assert_eq!(c.due_us(), NEVER, "nothing before the first heartbeat");
            assert_eq!(c.handle_timeout(ms(1_000_000)), None);
            assert!(c.consumes(0x705) && !c.consumes(0x706) && !c.consumes(0x605));
            let t0 = ms(1_000_000);
            assert!(!c.received(5, 0x05, t0));
            let due = t0 + Duration::from_millis(u64::from(time));
            assert_eq!(c.due_us(), due.0);
            assert_eq!(c.handle_timeout(Instant(due.0 - 1)), None);
            assert!(!c.any_lost());
            // Handled on time, or late (a host that slept past the deadline).
            let at = if time == 100 {
                due + Duration::from_millis(1)
            } else {
                due
            };
            assert_eq!(c.handle_timeout(at), Some(5));
            assert!(c.any_lost());
            assert_eq!(c.handle_timeout(ms(3_000_000)), None, "one event");
            assert_eq!(c.due_us(), NEVER);
            // The next heartbeat ends the error and monitors again.
            assert!(c.received(5, 0x7F, ms(3_000_000)));
            assert!(!c.any_lost());
            assert_eq!(c.due_us(), ms(3_000_000).0 + u64::from(time) * 1000);
        }
    }

    /// Each heartbeat restarts the node's time; entries run on their own times.
    #[test]
    fn each_heartbeat_restarts_its_entry_only() {
        let mut c = HbConsumer::default();
        c.load(&od_with(&[raw(3, 100), 0, raw(4, 30)]));
        assert!(!c.consumes(0x700), "an unused entry watches nothing");
        c.received(3, 0x05, ms(0));
        c.received(4, 0x05, ms(0));
        assert_eq!(c.due_us(), ms(30).0);
        c.received(4, 0x05, ms(20));
        assert_eq!(c.due_us(), ms(50).0);
        c.received(3, 0x05, ms(40));
        assert_eq!(c.handle_timeout(ms(50)), Some(4));
        assert_eq!(c.handle_timeout(ms(139)), None);
        assert_eq!(c.handle_timeout(ms(140)), Some(3));
        assert_eq!(c.handle_timeout(ms(140)), None);
    }

    /// D27: a consumed node's boot-up ends monitoring (its heartbeat may be off after its
    /// reset) and its error; its next heartbeat starts monitoring again.
    #[test]
    fn a_boot_up_stops_monitoring_until_the_next_heartbeat() {
        let mut c = HbConsumer::default();
        c.load(&od_with(&[raw(6, 10)]));
        c.received(6, 0x7F, ms(0));
        assert_eq!(c.handle_timeout(ms(10)), Some(6));
        assert!(c.received(6, 0x00, ms(20)), "the boot-up ends the error");
        assert!(!c.any_lost());
        assert_eq!(c.due_us(), NEVER);
        assert_eq!(c.handle_timeout(ms(1000)), None);
        c.received(6, 0x7F, ms(1000));
        assert!(!c.received(6, 0x00, ms(1005)), "no error to end");
        assert_eq!(c.handle_timeout(ms(2000)), None);
    }

    /// A write reconfigures its entry: waiting again, its error gone; a node-id freed by one
    /// entry may be taken by another.
    #[test]
    fn a_write_restarts_its_entry() {
        let mut c = HbConsumer::default();
        c.load(&od_with(&[raw(6, 10), 0]));
        c.received(6, 0x05, ms(0));
        assert_eq!(c.handle_timeout(ms(10)), Some(6));
        assert!(c.set(1, raw(6, 20)), "its error ended");
        assert!(!c.any_lost());
        assert_eq!(c.due_us(), NEVER);
        assert!(!c.set(1, 0));
        assert!(!c.consumes(0x706));
        assert!(!c.set(2, raw(6, 20)));
        assert!(c.consumes(0x706));
        let beyond = MAX_HB_CONSUMERS as u8 + 1;
        assert!(
            !c.set(0, raw(9, 1)) && !c.set(beyond, raw(9, 1)),
            "no such entry"
        );
        assert!(!c.consumes(0x709));
    }

    /// A stored image with a node-id twice (an SDO write cannot make one): the first watches.
    #[test]
    fn a_loaded_duplicate_watches_once() {
        let mut c = HbConsumer::default();
        c.load(&od_with(&[raw(6, 10), raw(6, 50)]));
        c.received(6, 0x05, ms(0));
        assert_eq!(c.due_us(), ms(10).0);
        assert_eq!(c.handle_timeout(ms(10)), Some(6));
        assert_eq!(c.handle_timeout(ms(50)), None);
    }

    #[test]
    fn pause_stops_monitoring_and_keeps_errors() {
        let mut c = HbConsumer::default();
        c.load(&od_with(&[raw(1, 10), raw(2, 10), raw(3, 10)]));
        c.received(1, 0x05, ms(0));
        c.received(2, 0x05, ms(5));
        c.received(3, 0x05, ms(5));
        assert_eq!(c.handle_timeout(ms(10)), Some(1));
        c.pause();
        assert_eq!(c.due_us(), NEVER);
        assert_eq!(c.handle_timeout(ms(100)), None);
        assert!(c.any_lost());
        // Node 3 was monitored at the pause: no longer, until its own next heartbeat.
        c.received(2, 0x05, ms(200));
        assert_eq!(c.due_us(), ms(210).0);
        assert_eq!(c.handle_timeout(ms(210)), Some(2));
        assert_eq!(c.handle_timeout(ms(210)), None);
    }

    /// The bitmap: every node-id 1…127 in its own bit, whatever the entry.
    #[test]
    fn consumes_exactly_the_watched_node_ids() {
        for node in 1..=127u8 {
            let mut c = HbConsumer::default();
            c.load(&od_with(&[0, raw(node, 1)]));
            for id in 0x680..0x800u16 {
                assert_eq!(
                    c.consumes(id),
                    id == 0x700 + u16::from(node),
                    "{node} {id:#x}"
                );
            }
        }
    }
}
