//! TPDOs and the SYNC consumer (CiA 301 §7.2.2, §7.2.5): communication parameters 0x1800+n,
//! mapping 0x1A00+n, transmission types, inhibit and event timers, and the validation rules of
//! SPEC §5 for dynamic mapping.

use crate::config;
use crate::od::{Abort, Dictionary};
use crate::txq::TxQueue;
use crate::wire::{Duration, Frame, Instant};

pub use crate::config::{MAX_MAP, MAX_TPDOS};

/// COB-ID bit 31: PDO does not exist / is not valid.
pub const COB_INVALID: u32 = 0x8000_0000;
/// COB-ID bit 30: no RTR allowed on this PDO.
pub const COB_NO_RTR: u32 = 0x4000_0000;
/// COB-ID bit 29: 29-bit identifier (not supported).
pub const COB_EXTENDED: u32 = 0x2000_0000;
// The restricted CAN-IDs and the 29-bit COB-ID bits serve every service: in `wire::cob`.
pub use crate::wire::cob::{restricted_id, COB_ID_HIGH_BITS};

/// No deadline (timers are µs instants; `u64::MAX` is never reached).
const NEVER: u64 = u64::MAX;
/// `Tpdo::sync_count` while a TPDO waits for the SYNC of its start value (counts stay ≤ 240).
const SYNC_WAIT: u8 = u8::MAX;
/// `Tpdos::single` when zero or several TPDOs have timers.
const NO_SINGLE: u8 = u8::MAX;
const _: () = assert!(crate::od::MAX_ENTRIES <= 256);

#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct Mapped {
    /// Dictionary slot (every slot fits a `u8`: `MAX_ENTRIES` ≤ 256).
    pub(crate) slot: u8,
    /// Bit position of the entry in the frame's data read as a little-endian u64.
    pub(crate) shift: u8,
    /// The entry's bytes of the value (`bytes` of them, at most 4); 0 for an RPDO's dummy
    /// entry, whose bytes are skipped.
    pub(crate) mask: u32,
}

/// The side of a PDO: the few parameter rules in which TPDOs and RPDOs differ (their indices,
/// which objects they may map, dummy entries). Everything else is one code for both, with
/// the side as a `const RX: bool` parameter: a firmware without RPDOs links the TPDO copy only,
/// with no RPDO branch in it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Dir {
    /// A TPDO (0x1800… / 0x1A00…): maps readable objects.
    Tx,
    /// An RPDO (0x1400… / 0x1600…): maps writable objects and dummy entries.
    Rx,
}

impl Dir {
    /// The side a `const RX: bool` names.
    pub(crate) const fn of(rx: bool) -> Dir {
        if rx {
            Dir::Rx
        } else {
            Dir::Tx
        }
    }
    /// The communication parameter record of PDO 0 of this side.
    pub(crate) const fn comm_base(self) -> u16 {
        match self {
            Dir::Tx => 0x1800,
            Dir::Rx => 0x1400,
        }
    }
    /// The mapping record of PDO 0 of this side.
    pub(crate) const fn map_base(self) -> u16 {
        self.comm_base() + 0x200
    }
}

/// One TPDO's cached configuration and timers.
#[derive(Clone, Copy, Debug)]
pub struct Tpdo {
    cob: u32,
    /// `cob`'s 11-bit CAN-ID, kept with it (read for every frame).
    id: u16,
    ttype: u8,
    /// Inhibit time in µs (0x1800:3 is 16 bits of 100 µs: at most 6.6 s, so 32 bits hold it).
    inhibit_us: u32,
    /// Event timer period in µs, 0 when off (0x1800:5 is 16 bits of ms: at most 65.5 s).
    event_us: u32,
    map: [Mapped; MAX_MAP],
    n_map: u8,
    len: u8,
    /// Next event-timer expiry in µs, [`NEVER`] when the timer is off.
    next_event: u64,
    inhibit_until: Instant,
    pending: bool,
    sync_count: u8,
    /// SYNC start value (0x1800:6, 0 where the table has none): a cyclic synchronous TPDO
    /// starts counting at the SYNC whose counter equals it. While it waits for that SYNC
    /// (from every restart of the count), `sync_count` is [`SYNC_WAIT`].
    sync_start: u8,
    changed: bool,
    /// Event timer periods that passed without a transmission because the host was late.
    pub missed: u32,
}

impl core::default::Default for Tpdo {
    fn default() -> Self {
        Tpdo {
            cob: COB_INVALID,
            id: 0,
            ttype: 0,
            inhibit_us: 0,
            event_us: 0,
            map: [Mapped::default(); MAX_MAP],
            n_map: 0,
            len: 0,
            next_event: NEVER,
            inhibit_until: Instant::ZERO,
            pending: false,
            sync_count: 0,
            sync_start: 0,
            changed: false,
            missed: 0,
        }
    }
}

impl Tpdo {
    /// Whether the PDO exists (COB-ID bit 31 clear) and maps something.
    pub fn valid(&self) -> bool {
        self.cob & COB_INVALID == 0 && self.n_map > 0
    }
    /// The 11-bit CAN-ID.
    pub fn can_id(&self) -> u16 {
        self.id
    }
    /// The transmission type.
    pub fn transmission_type(&self) -> u8 {
        self.ttype
    }
    fn asynchronous(&self) -> bool {
        self.ttype >= 254
    }
    #[inline(always)]
    fn inhibit(&self) -> Duration {
        Duration::from_micros(u64::from(self.inhibit_us))
    }

    /// The SYNC count a (re)start begins with: [`SYNC_WAIT`] with a start value, else 0.
    #[inline(always)]
    fn first_count(&self) -> u8 {
        if config::SYNC_START && self.sync_start != 0 {
            SYNC_WAIT
        } else {
            0
        }
    }

    /// The timers of an asynchronous TPDO at `now`: the event timer on its absolute
    /// schedule, then the inhibit time. Returns the frame when it is to be sent now.
    #[cfg_attr(feature = "inline-hot-paths", inline(always))]
    #[cfg_attr(not(feature = "inline-hot-paths"), inline(never))]
    fn step(&mut self, od: &Dictionary, now: Instant) -> Option<Frame> {
        let t = self.next_event;
        // The event timer expired (it is `NEVER` while off).
        let fired = now.0 >= t;
        if fired {
            // Absolute schedule: the next period starts where this one was due.
            let per = u64::from(self.event_us);
            let mut next = t + per;
            // Divides only when late: an expiry on time costs a comparison.
            if next <= now.0 {
                // At least 1 µs, so that the division is defined whatever the period (the timer
                // only runs when it is not 0); floored here, where it is used.
                // `q` whole periods passed since `t` (all but the one due at `t` were missed)
                // and `r` µs of the current one: the next starts `per - r` µs on.
                let per = per.max(1);
                let (q, r) = crate::div::div_rem(now.0 - t, per);
                self.missed = self.missed.wrapping_add(q as u32);
                next = now.0 - r + per;
            }
            self.next_event = next;
        }
        if (fired || self.pending) && now >= self.inhibit_until {
            self.pending = false;
            self.changed = false;
            return Some(self.send(od, now));
        }
        if fired {
            // Held back by the inhibit time.
            self.pending = true;
        }
        None
    }

    /// The frame of this TPDO at `now`, which starts its inhibit time. Out of line without
    /// `inline-hot-paths`: SYNC, RTR and the timers share it.
    #[cfg_attr(feature = "inline-hot-paths", inline(always))]
    #[cfg_attr(not(feature = "inline-hot-paths"), inline(never))]
    fn send(&mut self, od: &Dictionary, now: Instant) -> Frame {
        self.inhibit_until = now + self.inhibit();
        // Assembled in one little-endian u64: no per-entry slice copies. `configure` keeps the
        // entries within 8 bytes in all (shift ≤ 56), each of at most 4 (values are 32-bit).
        let map = self.map.iter().take(self.n_map as usize);
        let value = |slot| od.get_u8(slot);
        let data = assemble_shifted(map, value);
        // `configure` keeps `len` ≤ 8; `can_id` is 11 bits.
        Frame::std_checked(self.can_id(), data, self.len)
    }

    /// The earliest instant at which [`Tpdo::step`] has work.
    #[inline(always)]
    fn own_due(&self) -> u64 {
        if self.pending {
            self.next_event.min(self.inhibit_until.0)
        } else {
            self.next_event
        }
    }
}

/// All TPDOs of a node.
#[derive(Clone, Debug)]
pub struct Tpdos {
    pdos: [Tpdo; MAX_TPDOS],
    count: usize,
    active: bool,
    /// Bit n: TPDO n is valid and asynchronous (254 / 255): the only ones with timers.
    timer_mask: u8,
    /// Bit n: TPDO n is valid and synchronous (0…240): the only ones a SYNC concerns. Both
    /// masks are derived in `refresh`, which every configuration change ends in.
    sync_mask: u8,
    /// The index of the only TPDO in `timer_mask` when there is exactly one (the usual
    /// configuration), else [`NO_SINGLE`]: the timer walk is then no walk. A host's shortcut
    /// only ([`crate::config::INLINE_HOT_PATHS`]; its figures are there): a firmware walks the
    /// one TPDO as any other.
    single: u8,
    /// The earliest deadline of any TPDO in µs (`u64::MAX`: none), kept up to date by every
    /// method that changes a timer, so that `poll_timeout` and an early `handle_timeout` cost
    /// a comparison instead of a walk over all TPDOs.
    due: u64,
}

impl Default for Tpdos {
    fn default() -> Self {
        Tpdos {
            pdos: [Tpdo::default(); MAX_TPDOS],
            count: 0,
            active: false,
            timer_mask: 0,
            sync_mask: 0,
            single: NO_SINGLE,
            due: NEVER,
        }
    }
}

/// Index of the communication parameter record of TPDO `n` (0-based).
pub const fn comm_index(n: usize) -> u16 {
    0x1800 + n as u16
}
/// Index of the mapping record of TPDO `n` (0-based).
pub const fn map_index(n: usize) -> u16 {
    0x1A00 + n as u16
}

impl Tpdos {
    /// Re-reads every TPDO's configuration from the dictionary (after reset or load).
    pub fn configure_all(&mut self, count: usize, od: &Dictionary) {
        self.count = count.min(MAX_TPDOS);
        for n in 0..self.count {
            self.configure(n, od);
        }
        self.refresh();
    }

    /// Recomputes `timer_mask`, `sync_mask` and `due` after a change of configuration.
    fn refresh(&mut self) {
        let (mut mask, mut sync) = (0u8, 0u8);
        let mut bit = 1u8;
        for p in self.pdos.iter().take(self.count) {
            if p.valid() {
                if p.asynchronous() {
                    mask |= bit;
                } else {
                    sync |= bit;
                }
            }
            bit <<= 1;
        }
        self.timer_mask = mask;
        self.sync_mask = sync;
        if config::INLINE_HOT_PATHS {
            self.single = if mask.is_power_of_two() {
                mask.trailing_zeros() as u8
            } else {
                NO_SINGLE
            };
        }
        self.refresh_due();
    }

    /// Recomputes `due` after a change of timers (validity unchanged).
    #[cfg_attr(feature = "inline-hot-paths", inline)]
    #[cfg_attr(not(feature = "inline-hot-paths"), inline(never))]
    fn refresh_due(&mut self) {
        let mut t = NEVER;
        let mut mask = self.timer_mask;
        while mask != 0 {
            // `timer_mask` has bits below `count` ≤ MAX_TPDOS only (a power of two).
            let p = &self.pdos[mask.trailing_zeros() as usize & (MAX_TPDOS - 1)];
            mask &= mask - 1;
            t = t.min(p.next_event);
            if p.pending {
                t = t.min(p.inhibit_until.0);
            }
        }
        // `NEVER` while inactive: stopping stops every timer, and nothing starts one then.
        debug_assert!(self.active || t == NEVER);
        self.due = t;
    }

    /// Re-reads TPDO `n` (0-based) after a write to its parameters. Timers restart.
    /// [`Tpdos::configure`] after a parameter of TPDO `n` changed: a running PDO restarts its
    /// timers from `now` with the new values.
    pub fn reconfigure(&mut self, n: usize, od: &Dictionary, now: Instant) {
        self.configure(n, od);
        if self.active {
            // As if production started again now.
            self.active = false;
            self.set_active(true, now);
        }
    }

    /// Reads TPDO `n`'s parameters from the dictionary.
    pub fn configure(&mut self, n: usize, od: &Dictionary) {
        let Some(p) = self.pdos.get_mut(n) else {
            return;
        };
        let ci = comm_index(n);
        p.cob = od.value(ci, 1).unwrap_or(COB_INVALID);
        p.id = (p.cob & 0x7FF) as u16;
        p.ttype = od.value(ci, 2).unwrap_or(254) as u8;
        // Both are UNSIGNED16 in the table (every write and load is checked against the type),
        // read as such: the products stay in 32 bits.
        p.inhibit_us = u32::from(od.value(ci, 3).unwrap_or(0) as u16) * 100;
        p.event_us = u32::from(od.value(ci, 5).unwrap_or(0) as u16) * 1000;
        if config::SYNC_START {
            p.sync_start = od.value(ci, 6).unwrap_or(0) as u8;
        }
        let (n_map, len) = read_mapping::<false>(od, map_index(n), &mut p.map);
        p.n_map = n_map;
        p.len = len;
        p.next_event = NEVER;
        p.pending = false;
        p.sync_count = p.first_count();
        self.refresh();
    }

    /// The rule of one TPDO parameter value on its own (`index` in 0x1800.. or 0x1A00..),
    /// whatever the PDO holds now: what an SDO write must pass and what a state file may load.
    /// Independent of the PDO count configured (a state file is loaded before it is).
    pub fn check_value(od: &Dictionary, index: u16, sub: u8, raw: u32) -> Result<(), Abort> {
        check_param::<false>(od, index, sub, raw)
    }

    /// Validates an SDO write to a TPDO parameter (`index` in 0x1800.. or 0x1A00..) before it
    /// lands: [`Tpdos::check_value`] and the rules that relate it to what the PDO holds now.
    pub fn validate(
        &self,
        od: &Dictionary,
        index: u16,
        sub: u8,
        raw: u32,
        event_gt_inhibit: bool,
    ) -> Result<(), Abort> {
        let rules = Rules {
            count: self.count,
            event_gt_inhibit,
        };
        validate_param::<false>(rules, od, index, sub, raw)
    }

    /// Starts or stops production (entering / leaving Operational, life guarding).
    pub fn set_active(&mut self, active: bool, now: Instant) {
        if !(active && self.active) {
            self.active = active;
            self.restart(now);
        }
        self.refresh_due();
    }

    /// Every TPDO's timers from `now`: started while active, stopped otherwise. The SYNC
    /// state restarts too (it is read only while active, and set again when production starts).
    fn restart(&mut self, now: Instant) {
        // The TPDOs in `timer_mask` are the valid asynchronous ones.
        let mut timers = if self.active { self.timer_mask } else { 0 };
        for p in self.pdos.iter_mut().take(self.count) {
            let timer = timers & 1 != 0;
            timers >>= 1;
            p.next_event = if timer && p.event_us > 0 {
                (now + Duration::from_micros(u64::from(p.event_us))).0
            } else {
                NEVER
            };
            p.pending = false;
            p.sync_count = p.first_count();
            p.changed = true;
        }
    }

    /// Whether PDOs are being produced.
    pub fn active(&self) -> bool {
        self.active
    }

    /// A mapped value changed. `event` marks application events (cam / work-area state
    /// changes) that trigger asynchronous TPDOs mapping `slot`.
    pub fn value_changed(&mut self, slot: usize, event: bool) {
        for p in self.pdos.iter_mut().take(self.count) {
            if !p.valid()
                || !p.map[..p.n_map as usize]
                    .iter()
                    .any(|m| usize::from(m.slot) == slot)
            {
                continue;
            }
            p.changed = true;
            if event && self.active && p.asynchronous() {
                // Sent by `handle_timeout` once the inhibit time allows.
                p.pending = true;
            }
        }
        self.refresh_due();
    }

    /// A SYNC arrived, with its counter when it carries one: produces synchronous TPDOs into
    /// `out`. A cyclic TPDO with a SYNC start value counts from the SYNC whose counter equals
    /// it (CiA 301 0x1800:6); a SYNC without a counter starts it at once (no counter to wait
    /// for: the producer's 0x1019 is 0).
    pub(crate) fn on_sync(
        &mut self,
        od: &Dictionary,
        now: Instant,
        counter: Option<u8>,
        out: &mut TxQueue,
    ) {
        if !self.active {
            return;
        }
        let mut mask = self.sync_mask;
        while mask != 0 {
            let n = mask.trailing_zeros() as usize;
            mask &= mask - 1;
            // `sync_mask` has bits below `count` ≤ MAX_TPDOS only.
            let p = &mut self.pdos[n & (MAX_TPDOS - 1)];
            let send = if p.ttype == 0 {
                core::mem::take(&mut p.changed)
            } else {
                if config::SYNC_START && p.sync_count == SYNC_WAIT {
                    if counter.is_some_and(|c| c != p.sync_start) {
                        continue;
                    }
                    // This SYNC is the first one counted.
                    p.sync_count = 0;
                }
                p.sync_count += 1;
                if p.sync_count >= p.ttype {
                    p.sync_count = 0;
                    true
                } else {
                    false
                }
            };
            if send {
                out.push(p.send(od, now));
            }
        }
        // Synchronous TPDOs have no timer of their own: the schedule is unchanged.
    }

    /// A remote request for CAN-ID `id`: answers a TPDO that allows RTR.
    // One caller (the node's frame router): inlined there, as it was before the router grew
    // the RPDO and heartbeat-consumer tests (out of line it cost the TH firmware 84 B).
    #[inline(always)]
    pub fn on_rtr(
        &mut self,
        id: u16,
        od: &Dictionary,
        now: Instant,
        mut out: impl FnMut(Frame),
    ) -> bool {
        if !self.active {
            return false;
        }
        for p in self.pdos.iter_mut().take(self.count) {
            if p.valid() && p.cob & COB_NO_RTR == 0 && p.can_id() == id {
                out(p.send(od, now));
                self.refresh_due();
                return true;
            }
        }
        false
    }

    /// The earliest deadline of any TPDO.
    #[inline]
    pub fn poll_timeout(&self) -> Option<Instant> {
        (self.due != u64::MAX).then_some(Instant(self.due))
    }

    /// [`Tpdos::poll_timeout`] in µs, `u64::MAX` for none.
    #[inline]
    pub(crate) fn due_us(&self) -> u64 {
        self.due
    }

    /// Produces the asynchronous TPDOs that are due at `now`, in TPDO order.
    #[inline]
    pub fn handle_timeout(&mut self, od: &Dictionary, now: Instant, out: &mut dyn FnMut(Frame)) {
        while let Some(f) = self.poll_due(od, now) {
            out(f);
        }
    }

    /// The first asynchronous TPDO due at `now` (in TPDO order), built; any other one due stays
    /// due (`due` ≤ `now`: the earliest deadline may then be reported early, never late) for
    /// the next call. Calling this until `None` is
    /// [`Tpdos::handle_timeout`]; a host loop calls it once per frame it can send, so a TPDO
    /// goes out without passing through a queue.
    #[inline(always)]
    pub fn poll_due(&mut self, od: &Dictionary, now: Instant) -> Option<Frame> {
        // Nothing is due before `due` (it is `NEVER` while inactive).
        if now.0 < self.due {
            return None;
        }
        self.scan_due(od, now)
    }

    /// [`Tpdos::poll_due`] for a caller that knows `due` has passed (the node's timer fast
    /// path): the walk over the timers, which also recomputes `due`. Out of line without the
    /// `inline-hot-paths` feature: the node calls it from two places, and [`Tpdo::step`] is
    /// called twice in it (docs/FIRMWARE.md, "Build options in figures").
    #[cfg_attr(feature = "inline-hot-paths", inline(always))]
    #[cfg_attr(not(feature = "inline-hot-paths"), inline(never))]
    pub(crate) fn scan_due(&mut self, od: &Dictionary, now: Instant) -> Option<Frame> {
        // `single` stays `NO_SINGLE` without the option: the walk below.
        if config::INLINE_HOT_PATHS {
            if let Some(p) = self.pdos.get_mut(usize::from(self.single)) {
                // One TPDO with a timer: its own deadlines are all there is.
                let f = p.step(od, now);
                self.due = p.own_due();
                return f;
            }
        }
        let mut due = NEVER;
        let mut f = None;
        let mut mask = self.timer_mask;
        while mask != 0 {
            if f.is_some() {
                // The TPDOs after a frame are looked at by the next call: until then
                // something may still be due now.
                due = now.0;
                break;
            }
            // `timer_mask` has bits below `count` ≤ MAX_TPDOS only (a power of two).
            let n = (mask.trailing_zeros() & (MAX_TPDOS as u32 - 1)) as usize;
            mask &= mask - 1;
            let p = &mut self.pdos[n];
            f = p.step(od, now);
            due = due.min(p.own_due());
        }
        // `due` is `NEVER` while inactive: no timer runs then.
        self.due = due;
        f
    }

    /// Read access to TPDO `n` (0-based).
    pub fn get(&self, n: usize) -> Option<&Tpdo> {
        self.pdos[..self.count].get(n)
    }
}

/// What [`validate_param`] needs to know of the PDOs of one side.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Rules {
    /// PDOs of this side the device has.
    pub(crate) count: usize,
    /// `Features::event_timer_above_inhibit` (TPDOs only).
    pub(crate) event_gt_inhibit: bool,
}

/// The rule of one PDO parameter value on its own (`index` in the communication or mapping
/// records of the side `RX` names), whatever the PDO holds now: what an SDO write must pass and what a state
/// file may load.
pub(crate) fn check_param<const RX: bool>(
    od: &Dictionary,
    index: u16,
    sub: u8,
    raw: u32,
) -> Result<(), Abort> {
    if index < Dir::of(RX).map_base() {
        match sub {
            // 29-bit CAN-IDs are not supported; a valid PDO may not use a restricted one.
            1 if raw & (COB_EXTENDED | COB_ID_HIGH_BITS) != 0
                || (raw & COB_INVALID == 0 && restricted_id(raw & 0x7FF)) =>
            {
                return Err(Abort::InvalidValue)
            }
            // D10: 241–253 are reserved.
            2 if (241..254).contains(&(raw as u8)) => return Err(Abort::InvalidValue),
            // SYNC start value: 0 (none) or a SYNC counter value 1…240.
            6 if config::SYNC_START && raw > 240 => return Err(Abort::InvalidValue),
            _ => {}
        }
        return Ok(());
    }
    if sub == 0 {
        // A mapping record's entries are subs 1…N without a gap (every model's are, tested):
        // `raw` counts no more of them than there are when sub `raw` exists.
        if raw > 0xFF || od.find(index, raw as u8).is_err() {
            return Err(Abort::MappingLength);
        }
    } else if raw != 0 {
        check_mappable::<RX>(od, raw)?;
    }
    Ok(())
}

/// Validates an SDO write to a PDO parameter before it lands: [`check_param`] and the rules
/// that relate it to what the PDO holds now.
pub(crate) fn validate_param<const RX: bool>(
    r: Rules,
    od: &Dictionary,
    index: u16,
    sub: u8,
    raw: u32,
) -> Result<(), Abort> {
    let (comm_base, map_base) = (Dir::of(RX).comm_base(), Dir::of(RX).map_base());
    let n = r.count as u16;
    let comm = (comm_base..comm_base + n).contains(&index);
    if !comm && !(map_base..map_base + n).contains(&index) {
        return Ok(());
    }
    // The manuals' procedure: set sub 0 to zero before changing entries (checked first).
    if !comm && sub != 0 && od.value(index, 0).unwrap_or(0) != 0 {
        return Err(Abort::UnsupportedAccess);
    }
    check_param::<RX>(od, index, sub, raw)?;
    if comm {
        match sub {
            1 => {
                let cur = od.value(index, 1).unwrap_or(COB_INVALID);
                let valid_now = cur & COB_INVALID == 0;
                let valid_new = raw & COB_INVALID == 0;
                // Changing the CAN-ID of a valid PDO is refused; toggling bits 31 / 30 is not.
                if valid_now && valid_new && (cur & 0x7FF) != (raw & 0x7FF) {
                    return Err(Abort::InvalidValue);
                }
            }
            3 | 5 if r.event_gt_inhibit => {
                // `Features::event_timer_above_inhibit`: the event timer must stay above the
                // inhibit time (0 excepted).
                let (inh, ev) = if sub == 3 {
                    (raw, od.value(index, 5).unwrap_or(0))
                } else {
                    (od.value(index, 3).unwrap_or(0), raw)
                };
                if ev != 0 && (ev as u64) * 10 <= inh as u64 {
                    return Err(Abort::InvalidValue);
                }
            }
            _ => {}
        }
    } else if sub == 0 {
        let mut bits = 0u32;
        // `check_param` kept `raw` to the entries there are: no overflow.
        for k in 1..raw + 1 {
            let e = od.value(index, k as u8).ok_or(Abort::MappingLength)?;
            if e == 0 {
                // An empty entry cannot be counted in.
                return Err(Abort::NotMappable);
            }
            check_mappable::<RX>(od, e)?;
            bits += e & 0xFF;
        }
        if bits > 64 {
            return Err(Abort::MappingLength);
        }
    }
    Ok(())
}

/// The mapping record `mi` as `map` entries, from sub 1 on, at most `MAX_MAP`: the number of
/// entries and the PDO's length in bytes. The first entry that cannot be mapped ends them (the
/// write rules keep a record from holding one).
pub(crate) fn read_mapping<const RX: bool>(
    od: &Dictionary,
    mi: u16,
    map: &mut [Mapped; MAX_MAP],
) -> (u8, u8) {
    let count = od.value(mi, 0).unwrap_or(0) as usize;
    let (mut n_map, mut len) = (0u8, 0u8);
    for m in map.iter_mut().take(count) {
        let Some(raw) = od.value(mi, n_map + 1) else {
            break;
        };
        // A dummy entry (RPDOs only) has no slot, and a mask of 0: its bytes are skipped.
        let dummy = RX && dummy_bits(raw).is_some();
        let slot = match od.find((raw >> 16) as u16, (raw >> 8) as u8) {
            Ok(slot) => slot,
            Err(_) if dummy => 0,
            Err(_) => break,
        };
        let bytes = ((raw & 0xFF) / 8) as u8;
        if len + bytes > 8 {
            break;
        }
        // Precomputed so that building a TPDO is one mask and one shift per entry.
        *m = Mapped {
            slot: slot as u8,
            shift: 8 * len,
            mask: if dummy { 0 } else { byte_mask(bytes) },
        };
        n_map += 1;
        len += bytes;
    }
    (n_map, len)
}

/// The bits of the data type a dummy mapping entry names (index 0x0002–0x0007, sub 0: the
/// CiA 301 integer types), `None` for any other entry.
fn dummy_bits(raw: u32) -> Option<u8> {
    // Index and sub-index (`raw >> 8`): the type's index, sub 0.
    let bits = match raw >> 8 {
        0x200 | 0x500 => 8,
        0x300 | 0x600 => 16,
        0x400 | 0x700 => 32,
        _ => return None,
    };
    Some(bits)
}

/// Whether mapping entry `raw` may be mapped into a PDO of the side `RX` names: an object that may be
/// mapped, readable for a TPDO and writable for an RPDO, of at most its type's bits in whole
/// bytes; for an RPDO also a dummy entry of exactly its type's bits.
fn check_mappable<const RX: bool>(od: &Dictionary, raw: u32) -> Result<(), Abort> {
    // Compared as the u8s they are (a byte table of the types' sizes, not a word table).
    let bits = raw as u8;
    if RX {
        if let Some(b) = dummy_bits(raw) {
            return if bits == b {
                Ok(())
            } else {
                Err(Abort::NotMappable)
            };
        }
    }
    let slot = od.find((raw >> 16) as u16, (raw >> 8) as u8)?;
    let e = od.entry(slot);
    // A TPDO reads its objects, an RPDO writes them.
    let allowed = if RX {
        e.access.writable()
    } else {
        e.access.readable()
    };
    if !e.pdo || !allowed || bits == 0 || !bits.is_multiple_of(8) || bits > e.ty.bits() {
        return Err(Abort::NotMappable);
    }
    Ok(())
}

/// A TPDO's data from its entries (as `configure` lays them out: in order, 8 bytes in all,
/// shift ≤ 64) and their values, in one little-endian u64: no per-entry copies.
#[inline(always)]
fn assemble_shifted<'a>(
    map: impl Iterator<Item = &'a Mapped>,
    value: impl Fn(u8) -> u32,
) -> [u8; 8] {
    let mut acc = 0u64;
    for m in map {
        acc |= u64::from(value(m.slot) & m.mask) << (m.shift & 63);
    }
    acc.to_le_bytes()
}

/// The low `bytes` bytes of a u32 (0 for none, all of them from 4 on): a checked shift
/// instead of a branch around the shift by 32.
#[inline(always)]
pub(crate) fn byte_mask(bytes: u8) -> u32 {
    1u32.checked_shl(8 * u32::from(bytes))
        .map_or(u32::MAX, |v| v - 1)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A TPDO's data is its entries' low bytes one after the other, for every layout
    /// `configure` makes of up to four entries of 0…8 bytes (empty ones and ones past 4 bytes
    /// included: a value has 4, the rest of such an entry is 0).
    #[test]
    fn tpdo_assembly_lays_the_entries_end_to_end() {
        let value = |slot: u8| 0x9E37_79B9u32.wrapping_mul(u32::from(slot) + 1) | 0x0101_0101;
        let mut layouts = 0;
        for code in 0..9u32.pow(4) {
            let (mut map, mut len) = ([Mapped::default(); 4], 0u8);
            let mut n = 0;
            for (k, m) in map.iter_mut().enumerate() {
                let bytes = (code / 9u32.pow(k as u32) % 9) as u8;
                if len + bytes > 8 {
                    break;
                }
                *m = Mapped {
                    slot: k as u8,
                    shift: 8 * len,
                    mask: byte_mask(bytes),
                };
                n += 1;
                len += bytes;
            }
            // Each entry's value bytes (at most 4) at its byte offset; the rest 0.
            let mut want = [0u8; 8];
            for m in &map[..n] {
                let (at, bytes) = (usize::from(m.shift / 8), (m.mask.count_ones() / 8) as usize);
                let le = value(m.slot).to_le_bytes();
                want[at..at + bytes].copy_from_slice(&le[..bytes]);
            }
            let got = assemble_shifted(map.iter().take(n), value);
            assert_eq!(got, want, "{:?}", &map[..n]);
            layouts += 1;
        }
        assert_eq!(layouts, 6561);
    }

    #[test]
    fn byte_mask_keeps_the_low_bytes() {
        // Every entry length `configure` admits (at most 8 bytes in all).
        for bytes in 0..=8u8 {
            let want = ((1u64 << (8 * bytes.min(4))) - 1) as u32;
            assert_eq!(byte_mask(bytes), want, "{bytes}");
        }
    }
}
