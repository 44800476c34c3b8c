//! RPDOs (CiA 301 §7.2.2): communication parameters 0x1400+n, mapping 0x1600+n, synchronous
//! (0–240: applied at the next SYNC) and asynchronous (254 / 255: applied at once) reception,
//! the event timer as deadline monitoring (EMCY 0x8250) and the length checks (0x8210 /
//! 0x8220). The parameter rules are the TPDOs' (`pdo::check_param` and friends, with
//! `RX = true`); what a received value must pass and what it sets off is the node's one write
//! path (`node/access.rs`), shared with SDO downloads.
//!
//! Built with [`MAX_RPDOS`] RPDOs at most: 0 (a firmware of a device without RPDOs, set by
//! `CANPOS_MAX_RPDOS`) leaves none of this code in the build.

use crate::emcy::{self, Emcy};
use crate::od::{Abort, Dictionary};
use crate::pdo::{check_param, read_mapping, validate_param, Mapped, Rules, COB_INVALID, MAX_MAP};
use crate::wire::{Duration, Instant};

pub use crate::config::MAX_RPDOS;

/// No deadline.
const NEVER: u64 = u64::MAX;

/// How the last reception of an RPDO compared with its mapped length.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
enum Length {
    /// As mapped (or none received yet).
    #[default]
    Fits,
    /// Shorter than mapped: not processed (EMCY 0x8210).
    Short,
    /// Longer than mapped: processed with the first bytes (EMCY 0x8220).
    Long,
}

/// The length errors and their EMCY codes.
const LENGTH_ERRORS: [(Length, u16); 2] = [
    (Length::Short, emcy::code::PDO_LENGTH),
    (Length::Long, emcy::code::PDO_LENGTH_EXCEEDED),
];

/// One RPDO's cached configuration and reception state.
#[derive(Clone, Copy, Debug)]
pub struct Rpdo {
    cob: u32,
    /// `cob`'s 11-bit CAN-ID.
    id: u16,
    ttype: u8,
    /// Deadline monitoring period in µs (0x1400:5 in ms), 0 when off.
    timeout_us: u32,
    map: [Mapped; MAX_MAP],
    n_map: u8,
    len: u8,
    /// When the deadline monitoring expires, [`NEVER`] while it does not run: it starts with
    /// the first reception after (re)configuration or entering Operational.
    deadline: u64,
    /// A synchronous RPDO's data received since the last SYNC, applied at the next one.
    held: Option<[u8; 8]>,
    /// The deadline passed (EMCY 0x8250 raised) and no reception came since.
    timed_out: bool,
    length: Length,
}

impl Default for Rpdo {
    fn default() -> Self {
        Rpdo {
            cob: COB_INVALID,
            id: 0,
            ttype: 255,
            timeout_us: 0,
            map: [Mapped::default(); MAX_MAP],
            n_map: 0,
            len: 0,
            deadline: NEVER,
            held: None,
            timed_out: false,
            length: Length::Fits,
        }
    }
}

impl Rpdo {
    /// RPDO `n` as the dictionary configures it, with no data held, no deadline running and
    /// no error.
    fn read(od: &Dictionary, n: usize) -> Rpdo {
        let ci = comm_index(n);
        let cob = od.value(ci, 1).unwrap_or(COB_INVALID);
        let mut map = [Mapped::default(); MAX_MAP];
        let (n_map, len) = read_mapping::<true>(od, map_index(n), &mut map);
        Rpdo {
            cob,
            id: (cob & 0x7FF) as u16,
            ttype: od.value(ci, 2).unwrap_or(255) as u8,
            // The event timer is the deadline (UNSIGNED16 ms: the product stays in 32 bits).
            timeout_us: u32::from(od.value(ci, 5).unwrap_or(0) as u16) * 1000,
            map,
            n_map,
            len,
            deadline: NEVER,
            held: None,
            timed_out: false,
            length: Length::Fits,
        }
    }

    /// The mapped length in bytes.
    pub fn len(&self) -> usize {
        usize::from(self.len)
    }
    /// Whether nothing is mapped.
    pub fn is_empty(&self) -> bool {
        self.n_map == 0
    }
    /// Whether the RPDO is received: it exists (COB-ID bit 31 clear) and maps something.
    pub fn valid(&self) -> bool {
        self.cob & COB_INVALID == 0 && !self.is_empty()
    }
    /// The 11-bit CAN-ID it is received on.
    pub fn can_id(&self) -> u16 {
        self.id
    }
    /// The transmission type: 0–240 synchronous, 254 / 255 asynchronous.
    pub fn transmission_type(&self) -> u8 {
        self.ttype
    }
    /// Whether its deadline monitoring expired with no reception since (EMCY 0x8250).
    pub fn timed_out(&self) -> bool {
        self.timed_out
    }
    fn synchronous(&self) -> bool {
        self.ttype <= 240
    }
}

/// The values one RPDO's data gives its mapped objects: (slot, raw value) each, dummy entries
/// left out.
#[derive(Clone, Copy, Debug)]
pub struct Values {
    items: [(u8, u32); MAX_MAP],
    n: usize,
}

impl Values {
    /// The (slot, raw value) pairs in mapping order.
    pub fn iter(&self) -> impl Iterator<Item = (usize, u32)> + '_ {
        self.items[..self.n]
            .iter()
            .map(|&(slot, v)| (usize::from(slot), v))
    }
}

/// All RPDOs of a node.
#[derive(Clone, Debug)]
pub struct Rpdos {
    /// The earliest deadline in µs ([`NEVER`]: none).
    due: u64,
    /// In Operational: receptions are processed.
    active: bool,
    count: usize,
    pdos: [Rpdo; MAX_RPDOS],
}

impl Default for Rpdos {
    fn default() -> Self {
        // Nothing configured, nothing received, not in Operational.
        Rpdos {
            due: NEVER,
            active: false,
            count: 0,
            pdos: [Rpdo::default(); MAX_RPDOS],
        }
    }
}

/// Index of the communication parameter record of RPDO `n` (0-based).
pub const fn comm_index(n: usize) -> u16 {
    0x1400 + n as u16
}
/// Index of the mapping record of RPDO `n` (0-based).
pub const fn map_index(n: usize) -> u16 {
    0x1600 + n as u16
}

impl Rpdos {
    /// Re-reads every RPDO's configuration from the dictionary (a reset communication or
    /// node): their errors are forgotten with the EMCY service's active errors, which the
    /// reset clears too (an error kept here would be raised again by another RPDO's
    /// reception, or keep 0x8250 standing for good).
    pub fn configure_all(&mut self, count: usize, od: &Dictionary) {
        if MAX_RPDOS == 0 {
            return;
        }
        self.count = count.min(MAX_RPDOS);
        for (n, p) in self.pdos.iter_mut().enumerate() {
            *p = if n < self.count {
                Rpdo::read(od, n)
            } else {
                Rpdo::default()
            };
        }
        self.refresh_due();
    }

    /// Re-reads RPDO `n` (0-based) after a write to its parameters: held data is dropped and
    /// the deadline monitoring waits for the next reception. Its errors stay for that
    /// reception to end while it is valid; one no longer valid receives nothing, so they end
    /// now (the EMCY codes no RPDO holds any more are cleared).
    pub fn configure(&mut self, n: usize, od: &Dictionary, emcy: &mut Emcy) {
        if let Some(p) = self.pdos.get_mut(n) {
            let (timed_out, length) = (p.timed_out, p.length);
            *p = Rpdo::read(od, n);
            if p.valid() {
                p.timed_out = timed_out;
                p.length = length;
            }
        }
        self.refresh_due();
        for (kind, code) in LENGTH_ERRORS {
            if !self.pdos.iter().any(|p| p.length == kind) {
                emcy.clear(code);
            }
        }
        if !self.pdos.iter().any(|p| p.timed_out) {
            emcy.clear(emcy::code::RPDO_TIMEOUT);
        }
    }

    /// The rule of one RPDO parameter value on its own (`index` in 0x1400.. or 0x1600..): the
    /// TPDOs' rules ([`crate::pdo::Tpdos::check_value`]) with an RPDO's mappable objects.
    pub fn check_value(od: &Dictionary, index: u16, sub: u8, raw: u32) -> Result<(), Abort> {
        check_param::<true>(od, index, sub, raw)
    }

    /// Validates an SDO write to an RPDO parameter before it lands, as
    /// [`crate::pdo::Tpdos::validate`] does a TPDO's.
    pub fn validate(&self, od: &Dictionary, index: u16, sub: u8, raw: u32) -> Result<(), Abort> {
        let rules = Rules {
            count: self.count,
            event_gt_inhibit: false,
        };
        validate_param::<true>(rules, od, index, sub, raw)
    }

    /// Starts or stops reception (entering / leaving Operational). Leaving drops held data
    /// and stops the deadline monitoring; entering waits for a reception to start it.
    pub fn set_active(&mut self, active: bool) {
        if MAX_RPDOS == 0 || active == self.active {
            return;
        }
        self.active = active;
        for p in self.pdos.iter_mut() {
            p.deadline = NEVER;
            p.held = None;
        }
        self.refresh_due();
    }

    /// The RPDOs the device has (0 in a build without the service).
    #[inline(always)]
    pub fn count(&self) -> usize {
        if MAX_RPDOS == 0 {
            0
        } else {
            self.count
        }
    }

    /// Whether receptions are processed (Operational).
    pub fn active(&self) -> bool {
        self.active
    }

    /// The RPDO a data frame with CAN-ID `id` is for, while active.
    #[inline]
    pub fn find(&self, id: u16) -> Option<usize> {
        if MAX_RPDOS == 0 || !self.active {
            return None;
        }
        self.pdos
            .iter()
            .take(self.count)
            .position(|p| p.valid() && p.id == id)
    }

    /// RPDO `n` received `data`: the length checks, the deadline monitoring, and the data to
    /// apply now (an asynchronous RPDO's; a synchronous one's is held for the next SYNC).
    pub fn receive(
        &mut self,
        n: usize,
        data: &[u8],
        now: Instant,
        emcy: &mut Emcy,
    ) -> Option<[u8; 8]> {
        let p = self.pdos.get_mut(n)?;
        let len = usize::from(p.len);
        p.length = match data.len() {
            l if l < len => Length::Short,
            l if l > len => Length::Long,
            _ => Length::Fits,
        };
        self.report_length(emcy);
        let p = &mut self.pdos[n];
        if p.length == Length::Short {
            // Not processed: neither applied nor counted as a reception for the deadline.
            return None;
        }
        if p.timeout_us > 0 {
            p.deadline = (now + Duration::from_micros(u64::from(p.timeout_us))).0;
        }
        if core::mem::take(&mut p.timed_out) && !self.pdos.iter().any(|p| p.timed_out) {
            emcy.clear(emcy::code::RPDO_TIMEOUT);
        }
        self.refresh_due();
        let p = &mut self.pdos[n];
        // The whole frame (bytes past the mapping are never read: `values` takes the mapped
        // ones).
        let mut buf = [0u8; 8];
        let k = data.len().min(buf.len());
        buf[..k].copy_from_slice(&data[..k]);
        if p.synchronous() {
            p.held = Some(buf);
            return None;
        }
        Some(buf)
    }

    /// Raises or clears the two length errors: each stays while an RPDO's last reception had
    /// it (the error register's communication bit with it).
    fn report_length(&self, emcy: &mut Emcy) {
        for (kind, code) in LENGTH_ERRORS {
            if self.pdos.iter().any(|p| p.length == kind) {
                emcy.raise(code, emcy::reg::COMMUNICATION, [0; 5]);
            } else {
                emcy.clear(code);
            }
        }
    }

    /// At a SYNC: the data synchronous RPDO `n` received since the last one, taken.
    pub fn take_held(&mut self, n: usize) -> Option<[u8; 8]> {
        if !self.active {
            return None;
        }
        self.pdos.get_mut(n)?.held.take()
    }

    /// The values RPDO `n`'s `data` gives its mapped objects, in mapping order.
    pub fn values(&self, n: usize, data: [u8; 8]) -> Values {
        let mut out = Values {
            items: [(0, 0); MAX_MAP],
            n: 0,
        };
        let Some(p) = self.pdos.get(n) else {
            return out;
        };
        let acc = u64::from_le_bytes(data);
        for m in p.map.iter().take(usize::from(p.n_map)) {
            // A dummy entry (mask 0) only takes its bytes.
            if m.mask != 0 {
                out.items[out.n] = (m.slot, (acc >> (m.shift & 63)) as u32 & m.mask);
                out.n += 1;
            }
        }
        out
    }

    /// The deadlines that passed at `now`: each raises EMCY 0x8250 "RPDO timeout" once; the
    /// monitoring of that RPDO starts again with its next reception, which clears the error.
    pub fn handle_timeout(&mut self, now: Instant, emcy: &mut Emcy) {
        for p in self.pdos.iter_mut() {
            if now.0 >= p.deadline {
                p.deadline = NEVER;
                p.timed_out = true;
                emcy.raise(emcy::code::RPDO_TIMEOUT, emcy::reg::COMMUNICATION, [0; 5]);
            }
        }
        self.refresh_due();
    }

    fn refresh_due(&mut self) {
        self.due = self.pdos.iter().map(|p| p.deadline).min().unwrap_or(NEVER);
    }

    /// The earliest deadline in µs, `u64::MAX` for none.
    #[inline]
    pub(crate) fn due_us(&self) -> u64 {
        if MAX_RPDOS == 0 {
            return NEVER;
        }
        self.due
    }

    /// Read access to RPDO `n` (0-based).
    pub fn get(&self, n: usize) -> Option<&Rpdo> {
        self.pdos[..self.count].get(n)
    }
}
