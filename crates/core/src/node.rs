//! The device: every service wired to one object dictionary, driven by frames and time.
//!
//! [`Node`] is the sans-IO surface: `handle_frame`, `handle_timeout`, `poll_transmit`,
//! `poll_timeout`, `update_sample`. [`Device`] holds the state the services share; the SDO
//! server and the LSS slave sit beside it so they can borrow it mutably while they run.

use crate::app::{self, AppCtx, AppView, Application};
use crate::emcy::{self, Emcy};
use crate::encoder::Encoder;
use crate::errctl::{ErrCtl, ErrCtlEvent};
use crate::lss::{self, LssSlave};
use crate::models::{DeviceConfig, Features, Model};
use crate::nmt::{NmtCommand, NmtState};
use crate::od::{
    self, le_u32, Abort, DataType, DefaultValue, Dictionary, Entry, Hook, Param, ParamSource,
};
use crate::pdo::{self, Tpdos};
use crate::sdo::{ObjectAccess, SdoServer};
use crate::storage::{self, Scope, Storage, StorageError, IMAGE_MAX};
use crate::timers::{Timer, TimerTable, NEVER};
use crate::txq::TxQueue;
use crate::wire::{cob, Duration, Frame, Instant};

/// Node-id of a node that has none (CiA 305).
pub const UNCONFIGURED: u8 = 0xFF;
/// "save" signature (0x1010).
pub const SIG_SAVE: u32 = 0x6576_6173;
/// "load" signature (0x1011).
pub const SIG_LOAD: u32 = 0x6461_6F6C;
/// "kill" as ASCII bytes on the wire (D23).
pub const SIG_KILL_ASCII: u32 = 0x6C6C_696B;
/// "kill" as the TMI manual prints it (D23).
pub const SIG_KILL_MANUAL: u32 = 0x6B69_6C6C;
/// The bit rate in kbit/s (0 = autobaud) that an object copy of it holds (TMI 0x2001: kbit/s,
/// 0xFFFF = autobaud, D16).
fn kbps_of_object(raw: u32) -> u16 {
    if raw == 0xFFFF {
        0
    } else {
        raw as u16
    }
}

/// [`kbps_of_object`] the other way round.
fn object_of_kbps(kbps: u16) -> u32 {
    if kbps == 0 {
        0xFFFF
    } else {
        kbps as u32
    }
}

/// A stored node-id if it is one a node may have (1…127, or 0xFF = unconfigured).
fn stored_node_id(v: u32) -> Option<u8> {
    ((1..=127).contains(&v) || v == u32::from(UNCONFIGURED)).then_some(v as u8)
}

/// A change of the stored image ([`Device::change_stored`]).
#[derive(Clone, Copy, PartialEq, Eq)]
enum Change {
    /// "save" (0x1010) of a scope, or the automatic store ([`Scope::Auto`]).
    Save(Scope),
    /// "load" (0x1011) of a scope, or "kill": forgets what was stored for it (the LSS
    /// configuration and records of entries outside the scope stay, records this model has no
    /// entry for go); defaults apply at the next reset (D7).
    Forget(Scope),
    /// LSS "store configuration".
    Lss,
}

/// The slot and entry of this model's object that a stored record's `key` names, if any (an
/// LSS or bookkeeping key names none). Out of line: every reading and writing of the image
/// looks its records up through it.
#[inline(never)]
fn stored_entry(od: &Dictionary, key: u32) -> Option<(usize, &'static Entry)> {
    if !storage::is_object_key(key) {
        return None;
    }
    // Firmware searches by the key itself: no index and sub-index to split it into, no abort
    // to work out for a key the table lacks.
    #[cfg(not(feature = "inline-hot-paths"))]
    let slot = od::search_entries(od.entries(), key).ok()?;
    #[cfg(feature = "inline-hot-paths")]
    let slot = od.find((key >> 8) as u16, key as u8).ok()?;
    Some((slot, od.entries().get(slot)?))
}

/// A stored value of `e` as it applies under node-id `node` (D15): a COB-ID whose CAN-ID was the
/// pre-defined one (`base + node-id`) for the node-id it was saved under moves to this node's,
/// keeping its other bits; any other value stays as stored. Images without the saved node-id
/// (written before it was recorded) keep the earlier rule: a CAN-ID in the pre-defined range
/// of another node-id follows.
fn follow_node_id(e: &Entry, v: u32, saved: Option<u8>, node: u8) -> u32 {
    let DefaultValue::NodeId(base) = e.default else {
        return v;
    };
    // The default's flag bits (e.g. "not valid") are no part of the CAN-ID.
    let base = base & 0x7FF;
    let id = v & 0x7FF;
    let ours = base + node as u32;
    let follows = match saved {
        Some(old) => id == base + old as u32,
        None => id > base && id <= base + 0x7F,
    };
    if follows && node != UNCONFIGURED && id != ours {
        (v & !0x7FF) | ours
    } else {
        v
    }
}

/// Minimum time a store takes before the SDO answer (D7).
pub const STORE_TIME: Duration = Duration::from_millis(20);

/// Counters a host may show.
#[derive(Clone, Copy, Debug, Default)]
pub struct Stats {
    /// Frames received while the node's bit rate differed from the bus.
    pub rx_wrong_bitrate: u32,
    /// Frames dropped at transmit while the node's bit rate differed from the bus.
    pub tx_wrong_bitrate: u32,
    /// The stored image failed its check at the last load.
    pub storage_corrupt: bool,
}

/// The state all services share: dictionary, NMT state, identity, queues, storage.
pub struct Device<A: Application, S: Storage> {
    pub(crate) model: &'static Model,
    pub(crate) cfg: DeviceConfig,
    pub(crate) od: Dictionary,
    pub(crate) nmt: NmtState,
    pub(crate) powered: bool,
    /// Active node-id (1…127 or [`UNCONFIGURED`]).
    pub(crate) node_id: u8,
    /// Node-id that becomes active at the next reset communication.
    pub(crate) pending_node_id: u8,
    /// Active bit rate in kbit/s (0 = autobaud, not yet detected).
    pub(crate) bitrate: u16,
    /// Bit rate that becomes active at the next reset / activation.
    pub(crate) pending_bitrate: u16,
    /// Bit rate of the bus the node is attached to, if known.
    #[cfg(feature = "simulation")]
    pub(crate) bus_bitrate: Option<u16>,
    /// Bit-rate switch in progress (LSS activate): silent until then.
    pub(crate) silent_until: Option<Instant>,
    /// The node may send from this instant (µs) on: `silent_until`, or never while the bus
    /// runs another bit rate. Derived from the three fields above by the node's epilogue:
    /// sending is checked per frame, so one comparison.
    talk_from: u64,
    /// Node-id and bit rate the unit was built with: what a power-on falls back to when
    /// nothing is stored (`cfg` follows the active values, so it cannot serve).
    pub(crate) factory_lss: (u8, u16),
    #[cfg(feature = "simulation")]
    autobaud_frames: u8,
    /// Node-id and bit rate as stored by LSS (kept across "restore defaults").
    pub(crate) stored_lss: (Option<u8>, Option<u16>),
    pub(crate) tx: TxQueue,
    pub(crate) emcy: Emcy,
    pub(crate) errctl: ErrCtl,
    pub(crate) pdo: Tpdos,
    pub(crate) app: A,
    pub(crate) storage: S,
    pub(crate) now: Instant,
    /// A store completed: the SDO answer waits until this instant (D7).
    #[cfg(feature = "simulation")]
    pub(crate) sdo_hold_until: Option<Instant>,
    pub(crate) stats: Stats,
    /// Slots of the objects the per-frame paths touch.
    hot: HotSlots,
    /// The last `(index << 8 | sub, slot)` found: an SDO request looks its object up twice
    /// (size, then access), and masters poll the same object again and again.
    memo: (u32, usize),
    /// [`Emcy::generation`] last mirrored into 0x1001 / 0x1003.
    emcy_synced: u32,
}

/// No such object in this model's table.
const NO_SLOT: u16 = u16::MAX;

/// Slots of the objects that per-frame paths read or write, found once per node: the model
/// table is static, so a slot never moves, and a frame then costs no dictionary search.
#[derive(Clone, Copy, Debug)]
struct HotSlots {
    /// 0x1005 COB-ID SYNC.
    sync: u16,
    /// 0x1014 COB-ID EMCY.
    emcy_cob: u16,
    /// 0x1001 error register.
    err_reg: u16,
    /// 0x1003 sub 0.
    hist: u16,
    /// How many of 0x1003 sub 1…8 the table has: they follow sub 0 in the slots.
    hist_subs: u8,
}

impl HotSlots {
    /// From the model's table (not the dictionary, which would then have to be in memory
    /// before the node it is part of: in firmware, a 0.8 KB stack temporary).
    fn new(model: &Model) -> Self {
        // Out of line: six lookups share it (this runs once per node).
        #[inline(never)]
        fn find(model: &Model, index: u16, sub: u8) -> u16 {
            model
                .search(od::key(index, sub))
                .map_or(NO_SLOT, |s| s as u16)
        }
        let slot = |index: u16, sub: u8| find(model, index, sub);
        let hist = slot(0x1003, 0);
        let hist_subs = (1..=emcy::HISTORY_LEN as u16)
            .take_while(|&i| hist != NO_SLOT && slot(0x1003, i as u8) == hist + i)
            .count() as u8;
        HotSlots {
            sync: slot(0x1005, 0),
            emcy_cob: slot(0x1014, 0),
            err_reg: slot(0x1001, 0),
            hist,
            hist_subs,
        }
    }
}

impl Dictionary {
    /// Value of a slot from [`HotSlots`], `None` when the model lacks the object.
    #[inline]
    fn hot(&self, slot: u16) -> Option<u32> {
        (slot != NO_SLOT).then(|| self.get(slot as usize))
    }

    /// Sets a slot from [`HotSlots`] if the model has the object.
    #[inline]
    fn set_hot(&mut self, slot: u16, raw: u32) {
        if slot != NO_SLOT {
            self.set(slot as usize, raw);
        }
    }
}

/// A CANopen position sensor node.
pub struct Node<A: Application, S: Storage> {
    sdo: SdoServer,
    #[cfg(feature = "simulation")]
    held_sdo: Option<(Instant, [u8; 8])>,
    lss: LssSlave,
    dev: Device<A, S>,
    /// The services' deadlines, written by [`Node::epilogue`] only.
    timers: TimerTable,
    /// [`Node::poll_timeout`] in µs ([`NEVER`]: none), from the epilogue: hosts ask after
    /// every frame, and an answer kept is free.
    deadline: u64,
    /// The earliest deadline of everything but the TPDOs (same encoding): while it is in the
    /// future a timer expiry can only concern TPDOs. (This and `fast_due` serve the host's
    /// timer fast path only: a firmware takes the full path, for less flash.)
    #[cfg(feature = "inline-hot-paths")]
    other_due: u64,
    /// The timer fast path (only TPDO timers can be due) applies while `now < fast_due`:
    /// `other_due` while the node runs (powered, with a node-id, out of initialisation), else
    /// 0. (EMCY needs no term of its own: the epilogue flushes what was raised, and an EMCY
    /// held back by its inhibit time has its deadline in `other_due`.)
    #[cfg(feature = "inline-hot-paths")]
    fast_due: u64,
}

struct Params<'a> {
    model: &'static Model,
    cfg: &'a DeviceConfig,
}

impl ParamSource for Params<'_> {
    fn param(&self, p: Param) -> u32 {
        (self.model.param)(self.cfg, p)
    }
}

impl<S: Storage> Node<Encoder, S> {
    /// A sensor of `model` (the CiA 406 application) with unit configuration `cfg`, powered
    /// off. Call [`Node::power_on`].
    #[inline(always)] // lets firmware build the node in its static, not in a stack temporary
    pub fn new(model: &'static Model, cfg: DeviceConfig, storage: S) -> Self {
        Node::with_app(model, cfg, Encoder::default(), storage)
    }
}

impl<A: Application, S: Storage> Node<A, S> {
    /// A node of the device `model` describes, running application `app`, powered off. Call
    /// [`Node::power_on`].
    #[inline(always)] // as `new`
    pub fn with_app(model: &'static Model, cfg: DeviceConfig, app: A, storage: S) -> Self {
        // The unit's own dictionary (the one-channel TMI's has channel 1 only).
        let model = crate::models::for_unit(model, &cfg);
        let od = Dictionary::new(model);
        let hot = HotSlots::new(model);
        let f = app::features::<A>(model);
        Node {
            sdo: SdoServer::new(f.sdo_segmented, f.sdo_block),
            #[cfg(feature = "simulation")]
            held_sdo: None,
            lss: LssSlave::default(),
            timers: TimerTable::default(),
            deadline: NEVER,
            #[cfg(feature = "inline-hot-paths")]
            other_due: NEVER,
            #[cfg(feature = "inline-hot-paths")]
            fast_due: 0,
            dev: Device {
                model,
                cfg,
                od,
                nmt: NmtState::Initialising,
                powered: false,
                node_id: cfg.node_id,
                pending_node_id: cfg.node_id,
                bitrate: cfg.bitrate_kbps,
                pending_bitrate: cfg.bitrate_kbps,
                #[cfg(feature = "simulation")]
                bus_bitrate: None,
                silent_until: None,
                talk_from: 0,
                factory_lss: (cfg.node_id, cfg.bitrate_kbps),
                #[cfg(feature = "simulation")]
                autobaud_frames: 0,
                stored_lss: (None, None),
                tx: TxQueue::default(),
                emcy: Emcy::default(),
                errctl: ErrCtl::default(),
                pdo: Tpdos::default(),
                app,
                storage,
                now: Instant::ZERO,
                #[cfg(feature = "simulation")]
                sdo_hold_until: None,
                stats: Stats::default(),
                hot,
                memo: (u32::MAX, 0),
                emcy_synced: 0,
            },
        }
    }

    /// Power-on (or a power cycle): loads stored data, boots, sends the boot-up message and the
    /// power-on EMCY. A node without a valid node-id stays silent in LSS.
    pub fn power_on(&mut self, now: Instant) {
        self.dev.now = now;
        self.dev.powered = true;
        self.dev.tx.clear();
        self.sdo.reset();
        #[cfg(feature = "simulation")]
        {
            self.held_sdo = None;
        }
        self.lss = LssSlave::default();
        // A bit-rate switch cut short by the power cycle must not keep the node deaf.
        self.dev.silent_until = None;
        self.dev.emcy = Emcy::default();
        let on_change = self.dev.features().emcy_on_register_change;
        self.dev.emcy.set_reset_on_register_change(on_change);
        self.dev.app.power_on();
        self.dev.stored_lss = (None, None);
        self.dev.stats.storage_corrupt = false;
        // Stored LSS values override the factory configuration.
        let (lss, corrupt) = self.dev.stored_lss_config();
        self.dev.stored_lss = lss;
        self.dev.stats.storage_corrupt = corrupt;
        // Unstored LSS changes (even ones a reset activated) are gone after a power cycle.
        let (factory_id, factory_kbps) = self.dev.factory_lss;
        self.dev.pending_node_id = self.dev.stored_lss.0.unwrap_or(factory_id);
        self.dev.pending_bitrate = self.dev.stored_lss.1.unwrap_or(factory_kbps);
        self.dev.bitrate = self.dev.pending_bitrate;
        self.reset(true, now);
        if corrupt {
            self.dev.report_corrupt_storage();
        }
        self.epilogue();
    }

    /// [`Node::epilogue_inline`] out of line: every entry point, and in a firmware build (without
    /// `inline-hot-paths`) the per-frame one too.
    #[inline(never)]
    fn epilogue(&mut self) {
        self.epilogue_inline();
    }

    /// The end of every `&mut` entry point: what was raised goes out as EMCY, the talk gate
    /// follows the bit rates, and the timer table and the deadlines derived from it are
    /// written again from the services' own `poll_timeout`s. Nothing else keeps them. A host
    /// (`inline-hot-paths`) inlines it in [`Node::handle_frame`], where a request's answer waits
    /// for it.
    #[inline(always)]
    fn epilogue_inline(&mut self) {
        let d = &mut self.dev;
        if !d.powered {
            self.timers.clear();
            self.deadline = NEVER;
            #[cfg(feature = "inline-hot-paths")]
            {
                self.other_due = NEVER;
                self.fast_due = 0;
            }
            return;
        }
        d.flush_emcy();
        d.update_talk();
        let us = |t: Option<Instant>| t.map_or(NEVER, |t| t.0);
        // Armed exactly when `flush_emcy` sends (else a deadline would stay due with nothing
        // to serve it, and a host would spin).
        let emcy = if d.emcy_served() {
            d.emcy.due_us()
        } else {
            NEVER
        };
        // Every entry is written, so the earliest is the earliest of these (taken as they go:
        // a host reads them from registers, not back from the table).
        let t = &mut self.timers;
        let mut other = NEVER;
        let mut set = |timer, us: u64| {
            t.set_us(timer, us);
            other = other.min(us);
        };
        #[cfg(feature = "simulation")]
        set(Timer::HeldSdo, us(self.held_sdo.map(|(t, _)| t)));
        set(Timer::SdoTransfer, self.sdo.due_us());
        set(Timer::LssSwitch, self.lss.due_us());
        set(Timer::Silence, us(d.silent_until));
        set(Timer::ErrorControl, d.errctl.due_us());
        set(Timer::Emcy, emcy);
        debug_assert_eq!(other, self.timers.next());
        // The TPDOs keep their own schedule (the hot path reads it directly).
        self.deadline = other.min(d.pdo.due_us());
        // A node without a node-id stays in initialisation (`reset`), so one test says both.
        debug_assert!(d.node_id != UNCONFIGURED || d.nmt == NmtState::Initialising);
        #[cfg(feature = "inline-hot-paths")]
        {
            self.other_due = other;
            let runs = d.nmt != NmtState::Initialising;
            self.fast_due = if runs { other } else { 0 };
        }
    }

    /// Power off: the node neither sends nor receives until [`Node::power_on`].
    pub fn power_off(&mut self) {
        self.dev.powered = false;
        self.dev.tx.clear();
        self.epilogue();
    }

    /// NMT reset node (`application == true`) or reset communication.
    fn reset(&mut self, application: bool, now: Instant) {
        let d = &mut self.dev;
        d.now = now;
        self.sdo.reset();
        #[cfg(feature = "simulation")]
        {
            self.held_sdo = None;
            d.sdo_hold_until = None;
        }
        d.node_id = d.pending_node_id;
        d.bitrate = d.pending_bitrate;
        d.cfg.node_id = d.node_id;
        d.cfg.bitrate_kbps = d.bitrate;
        // The application forgets first: reset node then gives it its stored values back.
        if application {
            d.app.reset();
        }
        d.load_values(application);
        d.emcy.reset();
        d.errctl.reset();
        d.apply_comm_config(now);
        d.pdo.set_active(false, now);
        if d.node_id == UNCONFIGURED {
            // CiA 305: no node-id, no NMT: wait in LSS for one, in LSS waiting for a master to
            // select (DS 305 V2), or in configuration by itself (TMI R7).
            d.nmt = NmtState::Initialising;
            if d.features().lss_unconfigured_configures {
                self.lss.force_configuration();
            }
            return;
        }
        d.nmt = NmtState::PreOperational;
        d.tx.push_std(cob::ERRCTL + d.node_id as u16, [0; 8], 1);
        if d.features().power_on_emcy {
            d.emcy.power_on();
        }
    }

    /// Handles one received frame at `now`.
    #[inline]
    pub fn handle_frame(&mut self, f: &Frame, now: Instant) {
        if !self.dev.powered {
            return;
        }
        if self.handle_frame_inner(f, now) {
            // A host inlines it where a request's answer waits for it; a firmware shares the
            // one out-of-line copy (about 0.4 KB of flash less).
            #[cfg(feature = "inline-hot-paths")]
            self.epilogue_inline();
            #[cfg(not(feature = "inline-hot-paths"))]
            self.epilogue();
        }
    }

    /// Returns whether the frame concerned the node (only then can a deadline have changed).
    fn handle_frame_inner(&mut self, f: &Frame, now: Instant) -> bool {
        self.dev.now = now;
        let autobaud = self.dev.bitrate == 0;
        if !self.dev.can_hear(now) {
            // Autobaud just locked: the node joins the bus and announces itself (R19).
            let d = &mut self.dev;
            if autobaud && d.bitrate != 0 && d.node_id != UNCONFIGURED {
                d.tx.push_std(cob::ERRCTL + d.node_id as u16, [0; 8], 1);
            }
            return true;
        }
        let Some(id) = f.std_id() else { return false };
        // Most traffic on a busy bus is other nodes' PDOs: recognise it before anything else.
        if self.dev.ignores(id, f.is_remote()) {
            return false;
        }
        let d = &mut self.dev;
        if id == cob::LSS_RX {
            let reply = match self.lss.handle(f.data(), now, &*d) {
                lss::Output::Silent => None,
                lss::Output::Answer(a) => Some(a),
                lss::Output::Do(r) => {
                    let ok = d.lss_request(r);
                    if let Some(kbps) = self.lss.handle_timeout(now) {
                        // A switch delay of 0: the new bit rate is active at once.
                        d.activate_bitrate(kbps);
                    }
                    lss::confirm(r, ok)
                }
            };
            if let Some(r) = reply {
                d.tx.push(Frame::std8(cob::LSS_TX, r));
            }
            self.after_lss(now);
            return true;
        }
        if d.node_id == UNCONFIGURED {
            return true;
        }
        let node = d.node_id as u16;
        if id == cob::NMT {
            if f.is_remote() {
                return true;
            }
            if let Some(c) = NmtCommand::parse(f.data(), d.node_id) {
                self.nmt_command(c, now);
            }
            return true;
        }
        if id == cob::SDO_RX + node && !f.is_remote() {
            if d.nmt.sdo_allowed() {
                // Read only where a request needs them (the expedited fast path does not).
                let model = d.model;
                let t = move || app::features::<A>(model).sdo_transfers();
                if let Some(r) = self.sdo.handle_as(f.data(), now, d, t) {
                    // A simulated store holds its answer (D7).
                    #[cfg(feature = "simulation")]
                    let r = match d.sdo_hold_until.take() {
                        Some(t) => {
                            self.held_sdo = Some((t, r));
                            None
                        }
                        None => Some(r),
                    };
                    #[cfg(not(feature = "simulation"))]
                    let r = Some(r);
                    if let Some(r) = r {
                        d.tx.push_std(cob::SDO_TX + node, r, 8);
                    }
                }
                // Block-upload segments (a whole block answers one request).
                while let Some(s) = self.sdo.poll_transmit_as(t) {
                    d.tx.push_std(cob::SDO_TX + node, s, 8);
                }
            }
            return true;
        }
        let sync_id = d.od.hot(d.hot.sync).unwrap_or(0x80);
        let sync = sync_id & 0x8000_0000 == 0 && id as u32 == sync_id & 0x7FF && !f.is_remote();
        // A SYNC is never taken for a guard request (the write rules keep the two CAN-IDs
        // apart; this keeps it so whatever else changes).
        if id == d.errctl.guarding_id() && !sync {
            // Node guarding: an RTR, or on socketcand (no RTR) a zero-length data frame (D11, D22).
            if d.features().node_guarding && (f.is_remote() || f.dlc() == 0) {
                let b = d.errctl.guard_request(d.nmt, now);
                d.tx.push_std(id, [b, 0, 0, 0, 0, 0, 0, 0], 1);
                d.update_pdo_activity(now);
            }
            return true;
        }
        if !d.nmt.sdo_allowed() {
            return true;
        }
        if sync {
            if f.dlc() <= 1 {
                let Device { pdo, od, tx, .. } = d;
                pdo.on_sync(od, now, tx);
            } else if d.features().sync_length_emcy {
                // CiA 301 "unexpected SYNC data length" (conformance EMCY-04 without an RPDO).
                // DLC 1 stays accepted: without 0x1019 the counter byte is simply ignored.
                // The TMI's own EMCY table has no such code, so it ignores the frame.
                d.emcy.event(emcy::code::SYNC_LENGTH, [0; 5]);
            }
            return true;
        }
        // What is left `ignores` let through as a remote request on a model with RTR-triggered
        // TPDOs.
        let Device { pdo, od, tx, .. } = d;
        pdo.on_rtr(id, od, now, &mut |fr| {
            tx.push(fr);
        });
        true
    }

    fn nmt_command(&mut self, c: NmtCommand, now: Instant) {
        let d = &mut self.dev;
        match c {
            NmtCommand::Start => {
                if d.app.refuses_start(&mut d.emcy) {
                    // E.g. the TMI lock-out: stays pre-operational, the EMCY repeats (§1.14).
                    return;
                }
                d.nmt = NmtState::Operational;
            }
            NmtCommand::Stop => {
                d.nmt = NmtState::Stopped;
                // No SDO in Stopped: an unfinished transfer ends silently (no timeout abort).
                self.sdo.reset();
            }
            NmtCommand::EnterPreOperational => d.nmt = NmtState::PreOperational,
            NmtCommand::ResetNode => return self.reset(true, now),
            NmtCommand::ResetCommunication => return self.reset(false, now),
        }
        d.update_pdo_activity(now);
    }

    #[cfg_attr(not(feature = "inline-hot-paths"), inline(never))] // one copy for both callers
    fn after_lss(&mut self, now: Instant) {
        // A node that was unconfigured enters NMT once it has a node-id and LSS is waiting.
        let d = &self.dev;
        if d.node_id == UNCONFIGURED
            && d.pending_node_id != UNCONFIGURED
            && !self.lss.in_configuration()
        {
            self.reset(false, now);
        }
    }

    /// Feeds one process cycle's sample (a measurement) to the application.
    pub fn update_sample(&mut self, s: &A::Sample, now: Instant) {
        if !self.dev.powered {
            return;
        }
        self.dev.now = now;
        let d = &mut self.dev;
        let forced_preop = {
            let (app, mut cx) = d.app_ctx(now);
            app.cycle(s, &mut cx)
        };
        if d.app.take_auto_dirty() {
            // Values the device keeps by itself (TH 0x2901 life extremes, D19). A failing
            // medium only loses this update; the next change tries again.
            let _ = d.store(Scope::Auto);
        }
        if forced_preop && d.nmt == NmtState::Operational {
            d.nmt = NmtState::PreOperational;
            d.update_pdo_activity(now);
        }
        d.flush_emcy();
        d.run_pdos(now);
        self.epilogue();
    }

    /// Handles every deadline that has passed at `now`.
    #[inline]
    pub fn handle_timeout(&mut self, now: Instant) {
        // Fast path for a producing node: while every other deadline is in the future, the
        // steps of the full path would all do nothing but the TPDOs'. (`fast_due` is 0
        // while powered off, unconfigured, initialising or with EMCY work.)
        // (A firmware takes the full path: the same steps, less flash.)
        #[cfg(feature = "inline-hot-paths")]
        if now.0 < self.fast_due {
            self.dev.run_pdos(now);
            self.after_tpdo_timers(now);
            return;
        }
        if !self.dev.powered {
            return;
        }
        self.dev.now = now;
        self.handle_timeout_slow(now);
    }

    #[inline(never)]
    fn handle_timeout_slow(&mut self, now: Instant) {
        self.handle_timeout_full(now);
        self.epilogue();
    }

    fn handle_timeout_full(&mut self, now: Instant) {
        // The table says which services have a deadline that passed (the epilogue of the
        // entry point before wrote it); the others have nothing to do.
        let due = |t| self.timers.due(t, now.0);
        let (transfer, switch, silence) = (
            due(Timer::SdoTransfer),
            due(Timer::LssSwitch),
            due(Timer::Silence),
        );
        #[cfg(feature = "simulation")]
        if let Some((_, r)) = self.held_sdo.take_if(|_| due(Timer::HeldSdo)) {
            // A node stopped during the store time no longer serves SDO.
            if self.dev.nmt.sdo_allowed() {
                let id = cob::SDO_TX + self.dev.node_id as u16;
                self.dev.tx.push_std(id, r, 8);
            }
        }
        if transfer {
            if let Some(r) = self.sdo.handle_timeout(now) {
                let id = cob::SDO_TX + self.dev.node_id as u16;
                self.dev.tx.push_std(id, r, 8);
            }
        }
        if switch {
            if let Some(kbps) = self.lss.handle_timeout(now) {
                self.dev.activate_bitrate(kbps);
            }
        }
        if silence {
            // The bit-rate switch is over: the node talks again.
            self.dev.silent_until = None;
        }
        self.after_lss(now);
        let d = &mut self.dev;
        // (A node without a node-id is initialising: one test says both.)
        if d.nmt == NmtState::Initialising {
            return;
        }
        let guarding = d.features().node_guarding;
        while let Some(ev) = d.errctl.handle_timeout(now, d.nmt, guarding) {
            match ev {
                ErrCtlEvent::Heartbeat(b) => {
                    let id = cob::ERRCTL + d.node_id as u16;
                    d.tx.push_std(id, [b, 0, 0, 0, 0, 0, 0, 0], 1);
                }
                ErrCtlEvent::LifeGuardingLost => {
                    d.emcy
                        .raise(emcy::code::LIFE_GUARD, emcy::reg::COMMUNICATION, [0; 5]);
                    d.update_pdo_activity(now);
                }
            }
        }
        d.run_pdos(now);
    }

    /// The rest of the timer fast path once the TPDOs ran: the node's clock and deadline
    /// (TPDOs change neither the other deadlines nor the EMCY state).
    #[cfg(feature = "inline-hot-paths")]
    #[inline(always)]
    fn after_tpdo_timers(&mut self, now: Instant) {
        let d = &mut self.dev;
        d.now = now;
        // Nothing for the EMCY service to do (see `fast_due`).
        debug_assert!(d.emcy.generation() == d.emcy_synced, "EMCY not mirrored");
        // (A stopped node keeps its EMCYs until it leaves Stopped.)
        debug_assert!(
            !d.emcy.has_pending()
                || !d.emcy_served()
                || d.emcy.poll_timeout().is_some_and(|t| now < t),
            "EMCY due: {:?} at {now:?}, nmt {:?}",
            d.emcy.poll_timeout(),
            d.nmt
        );
        // The epilogue for the one schedule that can have changed.
        self.deadline = self.other_due.min(d.pdo.due_us());
    }

    /// One step of a host loop: runs the timers due at `now` (as [`Node::handle_timeout`])
    /// and takes the next frame to send (as [`Node::poll_transmit`]). Call it until it
    /// returns `None`; then wait for a frame or [`Node::poll_timeout`].
    ///
    /// A producing node spends its time here. When nothing is queued and only TPDO timers
    /// are due, the first due TPDO goes straight to the caller instead of through the transmit
    /// queue; another one due at the same time comes from the next call: same frames, same
    /// order.
    #[inline(always)]
    pub fn poll(&mut self, now: Instant) -> Option<Frame> {
        if now.0 >= self.deadline {
            // The host's fast path (a firmware takes the full one).
            #[cfg(feature = "inline-hot-paths")]
            if now.0 < self.fast_due && self.dev.tx.is_empty() && self.dev.can_talk(now) {
                // `now ≥ deadline` and `now < other_due`: the TPDOs' `due` has passed.
                let Device { pdo, od, .. } = &mut self.dev;
                let first = pdo.scan_due(od, now);
                self.after_tpdo_timers(now);
                if first.is_some() {
                    return first;
                }
                return self.poll_transmit();
            }
            self.handle_timeout(now);
        }
        self.poll_transmit()
    }

    /// The next instant at which [`Node::handle_timeout`] has work.
    pub fn poll_timeout(&self) -> Option<Instant> {
        // Kept current by every method that changes a deadline (0 while powered off).
        (self.deadline != u64::MAX).then_some(Instant(self.deadline))
    }

    /// Takes the next frame to send. Frames produced while the node's bit rate differs from the
    /// bus (or during a bit-rate switch) are lost, as on a real bus.
    #[inline]
    pub fn poll_transmit(&mut self) -> Option<Frame> {
        let d = &mut self.dev;
        let f = d.tx.pop()?;
        if d.can_talk(d.now) {
            return Some(f);
        }
        d.poll_transmit_lost()
    }

    /// Tells the node the bit rate of the bus it is attached to (virtual buses).
    #[cfg(feature = "simulation")]
    pub fn set_bus_bitrate(&mut self, kbps: Option<u16>) {
        self.dev.bus_bitrate = kbps;
        self.epilogue();
    }

    /// The SDO server (read-only view: counters, transfer in progress).
    pub fn sdo_server(&self) -> &SdoServer {
        &self.sdo
    }

    /// The device state (read-only view for hosts and tests).
    pub fn device(&self) -> &Device<A, S> {
        &self.dev
    }

    /// Mutable access to the storage backend (hosts: fault injection, inspection).
    pub fn storage_mut(&mut self) -> &mut S {
        &mut self.dev.storage
    }

    /// Mutable access to the application (fault injection, presets from a control interface).
    pub fn app_mut(&mut self) -> &mut A {
        &mut self.dev.app
    }

    /// Injects (`active`) or removes a fault the CiA 406 application reports the way the
    /// model's manual says (EMCY code and bytes, error register, alarms, TMI 0x1002 bits and
    /// lock-out).
    pub fn inject_fault(&mut self, fault: A::Fault, active: bool) {
        if !self.dev.powered {
            return;
        }
        let d = &mut self.dev;
        let now = d.now;
        let forced_preop = {
            let (app, mut cx) = d.app_ctx(now);
            app.inject(fault, active, &mut cx)
        };
        if forced_preop && d.nmt == NmtState::Operational {
            d.nmt = NmtState::PreOperational;
            d.update_pdo_activity(now);
        }
        d.flush_emcy();
        d.run_pdos(now);
        self.epilogue();
    }

    /// Raises (or with `active == false` clears) a device error from outside the CANopen
    /// services: supply voltage, temperature, CAN controller states (fault injection, or the
    /// real hardware's monitors on an MCU). What is raised here stays until it is cleared
    /// here, also a code the application raises for reasons of its own (the sensor's 0x5000):
    /// the application clears only what it raised. Both share the code's one active entry, so
    /// clearing it here while the application still has a reason ends it until the
    /// application's next cycle raises it again.
    pub fn set_error(&mut self, code: u16, reg_bits: u8, mfr: [u8; 5], active: bool) {
        let d = &mut self.dev;
        if active {
            d.emcy.raise(code, reg_bits, mfr);
        } else {
            d.emcy.clear(code);
        }
        self.epilogue();
    }

    /// Reads an object as an SDO client would see it, bypassing the bus (hosts, tests).
    pub fn read_object(&mut self, index: u16, sub: u8) -> Result<u32, Abort> {
        let mut b = [0u8; 4];
        let n = ObjectAccess::read(&mut self.dev, index, sub, 0, &mut b)?;
        Ok(le_u32(&b[..n]))
    }
}

impl<A: Application, S: Storage> Device<A, S> {
    /// The model's features: constants where the application fixes them
    /// ([`Application::FEATURES`]) or in a one-model build whose application runs only product
    /// models ([`crate::models::features_of`]; 0.7 KB of the TH firmware).
    #[inline(always)]
    pub fn features(&self) -> &'static Features {
        app::features::<A>(self.model)
    }

    /// The product model.
    pub fn model(&self) -> &'static Model {
        self.model
    }
    /// The unit configuration (with the active node-id and bit rate).
    pub fn config(&self) -> &DeviceConfig {
        &self.cfg
    }
    /// The object dictionary.
    pub fn od(&self) -> &Dictionary {
        &self.od
    }
    /// The NMT state.
    pub fn nmt_state(&self) -> NmtState {
        self.nmt
    }
    /// Active node-id ([`UNCONFIGURED`] = none).
    pub fn node_id(&self) -> u8 {
        self.node_id
    }
    /// Active bit rate in kbit/s (0 = autobaud not yet locked).
    pub fn bitrate(&self) -> u16 {
        self.bitrate
    }
    /// Counters.
    pub fn stats(&self) -> Stats {
        self.stats
    }
    /// The EMCY producer.
    pub fn emcy(&self) -> &Emcy {
        &self.emcy
    }
    /// The TPDOs.
    pub fn tpdos(&self) -> &Tpdos {
        &self.pdo
    }
    /// The application.
    pub fn app(&self) -> &A {
        &self.app
    }
    /// The LSS address (0x1018/1…4).
    pub fn lss_address(&self) -> [u32; 4] {
        [1, 2, 3, 4].map(|s| self.od.value(0x1018, s).unwrap_or(0))
    }
    /// Node-id and bit rate that the next reset activates.
    pub fn pending(&self) -> (u8, u16) {
        (self.pending_node_id, self.pending_bitrate)
    }

    /// Whether a standard frame `id` is none of the node's business: not LSS, NMT, its SDO or
    /// error control, SYNC, nor (where the model allows) a remote request. Mirrors the checks of
    /// `Node::handle_frame_inner` that would end in doing nothing.
    #[inline]
    fn ignores(&self, id: u16, remote: bool) -> bool {
        if id == cob::LSS_RX {
            return false;
        }
        if self.node_id == UNCONFIGURED {
            return true;
        }
        let node = self.node_id as u16;
        if id == cob::NMT || id == cob::SDO_RX + node || id == self.errctl.guarding_id() {
            return false;
        }
        if !self.nmt.sdo_allowed() {
            return true;
        }
        let sync_id = self.od.hot(self.hot.sync).unwrap_or(0x80);
        let is_sync = sync_id & 0x8000_0000 == 0 && id as u32 == sync_id & 0x7FF && !remote;
        !(is_sync || remote && self.features().tpdo_rtr)
    }

    /// [`Node::poll_transmit`] once a frame was lost: counts it and the rest that are lost.
    /// `can_talk(now)` has just answered false and nothing changes its answer before the next
    /// entry point, so every frame still waiting is lost as well: dropped at once, not one by one.
    #[cold]
    #[inline(never)]
    fn poll_transmit_lost(&mut self) -> Option<Frame> {
        debug_assert!(!self.can_talk(self.now));
        let lost = 1 + self.tx.len() as u32;
        self.stats.tx_wrong_bitrate = self.stats.tx_wrong_bitrate.wrapping_add(lost);
        self.tx.clear();
        None
    }

    /// Whether the node can receive at `now` (bit rate matches, not switching).
    fn can_hear(&mut self, now: Instant) -> bool {
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
    fn can_talk(&self, now: Instant) -> bool {
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

    /// Carries out what an LSS request asks; returns whether it succeeded. Configure node-id /
    /// bit timing set the pending value and the objects that copy it (TMI 0x2000 / 0x2001), so
    /// that every copy says the same.
    #[cfg_attr(not(feature = "inline-hot-paths"), inline(never))] // rare: out of the frame path
    fn lss_request(&mut self, r: lss::Request) -> bool {
        let (hook, raw) = match r {
            lss::Request::ConfigureNodeId(id) => {
                self.pending_node_id = id;
                if id == UNCONFIGURED {
                    return true;
                }
                (Hook::PendingNodeId, id as u32)
            }
            lss::Request::ConfigureBitRate(kbps) => {
                self.pending_bitrate = kbps;
                (Hook::PendingBitRate, object_of_kbps(kbps))
            }
            lss::Request::ActivateBitRate { silent_until } => {
                // Deaf and mute for both switch delays; checked on every frame.
                self.silent_until = Some(silent_until);
                return true;
            }
            lss::Request::StoreConfiguration => return self.store_lss().is_ok(),
        };
        self.set_hooked(hook, raw);
        true
    }

    /// Sets every entry with `hook` (rare paths only: it scans the table).
    fn set_hooked(&mut self, hook: Hook, raw: u32) {
        // The table is 'static: walked directly, not looked up slot by slot.
        for (slot, e) in self.od.entries().iter().enumerate() {
            if e.hook == hook {
                self.od.set(slot, raw);
            }
        }
    }

    /// Makes `kbps` the active bit rate now (LSS activate bit timing).
    pub(crate) fn activate_bitrate(&mut self, kbps: u16) {
        self.bitrate = kbps;
        self.cfg.bitrate_kbps = kbps;
        #[cfg(feature = "simulation")]
        {
            self.autobaud_frames = 0;
        }
    }

    /// Reloads values: the entries a reset communication covers always, every other one on
    /// reset node. Defaults first, then whatever the stored image holds for them (D6); stored
    /// COB-IDs that were pre-defined for the node-id they were saved under follow the active
    /// one (D15).
    #[inline(never)] // as `stored_lss_config`: the caller's frame stays small
    fn load_values(&mut self, application: bool) {
        let p = Params {
            model: self.model,
            cfg: &self.cfg,
        };
        let node = self.node_id;
        let reloads = |e: &Entry| application || e.reset_by_comm();
        for (slot, e) in self.od.entries().iter().enumerate() {
            if reloads(e) {
                self.od.set(slot, crate::od::resolve_default(e, &p, node));
            }
        }
        let mut buf = [0u8; IMAGE_MAX];
        let tag = self.features().tag;
        let Ok(recs) = storage::load_image(&mut self.storage, tag, &mut buf) else {
            return;
        };
        let saved_node = recs
            .clone()
            .find(|&(k, _)| k == storage::KEY_SAVED_NODE_ID)
            .and_then(|(_, v)| stored_node_id(v));
        for (k, v) in recs {
            let Some((slot, e)) = stored_entry(&self.od, k) else {
                if let Some(n) = storage::app_record(k).filter(|_| application) {
                    self.app.load_stored(n, v);
                }
                continue;
            };
            if e.group != crate::od::Group::Volatile && reloads(e) {
                let v = follow_node_id(e, v, saved_node, node);
                // A checksummed image can still hold what no write would have been let in (a
                // hand-edited or foreign file; found by fuzzing): that object keeps its default.
                // The rule is a write's, less what relates the value to the one it replaces.
                if e.accepts(v) && self.value_allowed(e, v).is_ok() {
                    self.od.set(slot, v);
                }
            }
        }
        // The write rule that relates guarding to SYNC (`validate`), once both are loaded:
        // guarding on SYNC's CAN-ID keeps its default (0x700 + node-id, which SYNC cannot have).
        // 0x100E:0 by its record key: slot and entry in one look-up.
        if let Some((g, e)) = stored_entry(&self.od, 0x0010_0E00) {
            if self.od.get(g) & 0x7FF == self.sync_can_id() {
                self.od.set(g, crate::od::resolve_default(e, &p, node));
            }
        }
    }

    /// The CAN-ID of the SYNC COB-ID (0x1005), whatever its bit 31.
    fn sync_can_id(&self) -> u32 {
        self.od.hot(self.hot.sync).unwrap_or(0x80) & 0x7FF
    }

    /// The node-id and bit rate stored by LSS or in their object copies (TMI 0x2000 / 0x2001,
    /// R17, R19: written there and saved with "save", they apply at power-up too; LSS "store
    /// configuration" keeps both copies equal, so an object copy is the newer one), and
    /// whether the image failed its check.
    // Out of line: its image buffer is then gone before `power_on` calls `reset`, which loads
    // the image again (two buffers on the stack at once are too many for firmware).
    #[inline(never)]
    fn stored_lss_config(&mut self) -> ((Option<u8>, Option<u16>), bool) {
        let mut buf = [0u8; IMAGE_MAX];
        let tag = self.features().tag;
        let recs = match storage::load_image(&mut self.storage, tag, &mut buf) {
            Ok(recs) => recs,
            Err(StorageError::Empty) => return ((None, None), false),
            Err(_) => return ((None, None), true),
        };
        // The last node-id and bit rate of each source: [LSS node-id, LSS bit rate, object
        // node-id, object bit rate].
        let mut last = [None; 4];
        for (k, v) in recs {
            let at = match k {
                storage::KEY_LSS_NODE_ID => 0,
                storage::KEY_LSS_BITRATE => 1,
                _ => match stored_entry(&self.od, k).map(|(_, e)| e.hook) {
                    Some(Hook::PendingNodeId) => 2,
                    Some(Hook::PendingBitRate) => 3,
                    _ => continue,
                },
            };
            // A checksummed image can still hold an impossible node-id (a hand-edited or
            // foreign file; found by fuzzing): ignore it rather than talk on COB-IDs of node 0
            // or 200.
            if at & 1 == 0 && stored_node_id(v).is_none() {
                continue;
            }
            last[at] = Some(v);
        }
        let [lss_id, lss_kbps, obj_id, obj_kbps] = last;
        let id = obj_id.or(lss_id).map(|v| v as u8);
        let kbps = obj_kbps.map(kbps_of_object).or(lss_kbps.map(|v| v as u16));
        ((id, kbps), false)
    }

    /// The application and the context it runs in (disjoint borrows of the device).
    fn app_ctx(&mut self, now: Instant) -> (&mut A, AppCtx<'_>) {
        let cx = AppCtx {
            od: &mut self.od,
            emcy: &mut self.emcy,
            pdo: &mut self.pdo,
            model: self.model,
            cfg: &self.cfg,
            nmt: self.nmt,
            bitrate_kbps: self.bitrate,
            now,
        };
        (&mut self.app, cx)
    }

    /// Hands guard time, life time factor and the guarding COB-ID (0x100E where the model has
    /// it, else the pre-defined 0x700 + node-id) to the error-control service.
    /// Without the feature (a constant where the build fixes the features) life guarding is
    /// never armed, and its code is not linked.
    fn apply_guarding(&mut self, now: Instant) {
        if self.features().node_guarding {
            let gt = self.od.value(0x100C, 0).unwrap_or(0) as u16;
            let lf = self.od.value(0x100D, 0).unwrap_or(0) as u8;
            self.errctl.set_guarding(gt, lf, now);
        }
        let id = self
            .od
            .value(0x100E, 0)
            .map_or(cob::ERRCTL + self.node_id as u16, |v| (v & 0x7FF) as u16);
        self.errctl.set_guarding_id(id);
    }

    /// Pushes the cached service configuration from the dictionary after a reload.
    fn apply_comm_config(&mut self, now: Instant) {
        self.pdo
            .configure_all(self.features().tpdos as usize, &self.od);
        let hb = self.od.value(0x1017, 0).unwrap_or(0) as u16;
        self.errctl.set_heartbeat(hb, now);
        self.apply_guarding(now);
        self.emcy
            .set_inhibit(self.od.value(0x1015, 0).unwrap_or(0) as u16);
        self.sync_error_register();
    }

    fn sync_error_register(&mut self) {
        let h = self.hot;
        let r = self.emcy.register();
        self.od.set_hot(h.err_reg, r as u32);
        let n = self.emcy.history_len();
        self.od.set_hot(h.hist, n as u32);
        // Half-open: an inclusive range's iterator compiles to more code.
        for i in 1..usize::from(h.hist_subs) + 1 {
            let v = self.emcy.history_or_zero(i);
            self.od.set(usize::from(h.hist) + i, v);
        }
        self.emcy_synced = self.emcy.generation();
    }

    /// Moves EMCYs whose inhibit time allows into the transmit queue and mirrors the error
    /// register and history into the dictionary.
    #[inline]
    fn flush_emcy(&mut self) {
        // Runs after every frame and timer: on a host the usual "nothing to do" stays inline; a
        // firmware calls straight through (`flush_emcy_slow` checks the same), a test fewer at
        // every call site.
        #[cfg(feature = "inline-hot-paths")]
        if self.emcy.generation() == self.emcy_synced && !self.emcy.has_pending() {
            return;
        }
        self.flush_emcy_slow();
    }

    /// Whether EMCYs go out now: in pre-operational and operational only. A stopped node keeps
    /// them until it leaves Stopped, one without a node-id (initialising) until it has one.
    /// The one rule for both sending and the EMCY deadline.
    #[inline]
    fn emcy_served(&self) -> bool {
        self.nmt.sdo_allowed()
    }

    // Out of line: `flush_emcy` is inlined at every entry point's end.
    #[inline(never)]
    fn flush_emcy_slow(&mut self) {
        // Nothing else writes 0x1001 / 0x1003 between resets, so an unchanged EMCY state needs
        // no mirroring (this runs after every frame).
        if self.emcy.generation() != self.emcy_synced {
            self.sync_error_register();
        }
        // No separate "nothing waits" test: `poll` makes it (reading the COB-ID first is cheap).
        if !self.emcy_served() {
            return;
        }
        let cobid = self
            .od
            .hot(self.hot.emcy_cob)
            .unwrap_or(0x80 + self.node_id as u32);
        while let Some(p) = self.emcy.poll(self.now) {
            if cobid & 0x8000_0000 == 0 {
                self.tx.push_std((cobid & 0x7FF) as u16, p, 8);
            }
        }
    }

    fn run_pdos(&mut self, now: Instant) {
        let Device { pdo, od, tx, .. } = self;
        pdo.handle_timeout(od, now, &mut |f| {
            tx.push(f);
        });
    }

    /// PDOs run in Operational unless life guarding was lost (D11).
    fn update_pdo_activity(&mut self, now: Instant) {
        let guarding = self.features().node_guarding;
        let lost = guarding && self.errctl.life_guard_lost;
        let on = self.nmt == NmtState::Operational && !lost;
        self.pdo.set_active(on, now);
        // Also a 0x8130 raised from outside (`Node::set_error`), on every model.
        if !lost && self.emcy.is_active(emcy::code::LIFE_GUARD) {
            self.emcy.clear(emcy::code::LIFE_GUARD);
            self.flush_emcy();
        }
    }

    /// At power-on, the stored image failed its check: the application's reaction, else EMCY
    /// 0x6300. Sent by the epilogue that ends [`Node::power_on`] right after.
    fn report_corrupt_storage(&mut self) {
        let now = self.now;
        let (app, mut cx) = self.app_ctx(now);
        if !app.storage_corrupt(&mut cx) {
            self.emcy.raise(emcy::code::DATA_SET, 0, [0; 5]);
        }
    }

    /// "save" (0x1010) of `scope`, or the automatic store of the values the device keeps by
    /// itself: the covered entries' current values replace what was stored for them; the
    /// rest of the image stays. A "save" records the active node-id with them (D15); the
    /// automatic store keeps the one recorded.
    pub(crate) fn store(&mut self, scope: Scope) -> Result<(), Abort> {
        self.change_stored(Change::Save(scope))
            .map_err(|_| Abort::CannotStore)
    }

    /// LSS "store configuration": keeps the pending node-id and bit rate, in the LSS records
    /// and in the objects that hold copies of them (TMI 0x2000 / 0x2001), so that every copy
    /// says the same after the next power-on.
    pub(crate) fn store_lss(&mut self) -> Result<(), StorageError> {
        self.change_stored(Change::Lss)?;
        self.stored_lss = (Some(self.pending_node_id), Some(self.pending_bitrate));
        Ok(())
    }

    /// Every change of the stored image: the records `change` covers are dropped and the
    /// values it stores written in their place; the rest of the image stays. One rule and one
    /// writer for all of them, as they differ only in which records those are.
    // Out of line: the image buffer of `change_image`, inlined here, is on the stack only
    // while a change runs.
    #[inline(never)]
    fn change_stored(&mut self, change: Change) -> Result<(), StorageError> {
        let od = &self.od;
        let (id, kbps) = (self.pending_node_id, self.pending_bitrate);
        let replaced = |k: u32| match (stored_entry(od, k), change) {
            (Some((_, e)), Change::Save(scope) | Change::Forget(scope)) => scope.covers(e),
            (Some((_, e)), Change::Lss) => {
                matches!(e.hook, Hook::PendingNodeId | Hook::PendingBitRate)
            }
            // A "save" replaces the saved node-id (the automatic store, of no COB-ID, keeps
            // it: D15); a "load" forgets the records of objects this model does not have too.
            (None, Change::Save(scope)) => {
                scope != Scope::Auto && k == storage::KEY_SAVED_NODE_ID
                    || scope.covers_app_values() && storage::app_record(k).is_some()
            }
            (None, Change::Forget(scope)) => {
                storage::is_object_key(k)
                    || scope.covers_app_values() && storage::app_record(k).is_some()
            }
            (None, Change::Lss) => k == storage::KEY_LSS_NODE_ID || k == storage::KEY_LSS_BITRATE,
        };
        // The value `change` stores for `e` in `slot`, if any.
        let value = |slot: usize, e: &Entry| match change {
            Change::Save(scope) => scope.covers(e).then(|| od.get(slot)),
            Change::Forget(_) => None,
            Change::Lss => match e.hook {
                Hook::PendingNodeId => Some(id as u32),
                Hook::PendingBitRate => Some(object_of_kbps(kbps)),
                _ => None,
            },
        };
        let node = self.node_id as u32;
        let app = &self.app;
        let put = &mut |w: &mut storage::ImageWriter<'_>| {
            (change != Change::Lss
                || w.push(storage::KEY_LSS_NODE_ID, id as u32)
                    && w.push(storage::KEY_LSS_BITRATE, kbps as u32))
                // Slots counted up to MAX_ENTRIES, which no table exceeds: no bounds check.
                && (0..od::MAX_ENTRIES)
                    .zip(od.entries())
                    .all(|(slot, e)| value(slot, e).is_none_or(|v| w.push(e.key(), v)))
                && match change {
                    Change::Save(scope) if scope != Scope::Auto => {
                        w.push(storage::KEY_SAVED_NODE_ID, node)
                            && (!scope.covers_app_values()
                                || (0..storage::APP_RECORDS).all(|k| {
                                    app.stored_value(k)
                                        .is_none_or(|v| w.push(storage::app_key(k), v))
                                }))
                    }
                    _ => true,
                }
        };
        let tag = self.features().tag;
        storage::change_image(&mut self.storage, tag, &replaced, put)
    }

    /// The rule of an entry's hook for a value of its own, on this node-id, whatever the object
    /// holds now: an SDO write must pass it, and a value from the state file that fails it is
    /// not loaded. For COB-IDs of services this node produces or answers on it keeps them off
    /// 29-bit and CiA 301 restricted CAN-IDs (else a write or a state file could make the node
    /// talk on the NMT or SYNC identifier). Out of line in firmware: writes and loads share it.
    #[cfg_attr(feature = "inline-hot-paths", inline)]
    #[cfg_attr(not(feature = "inline-hot-paths"), inline(never))]
    fn value_allowed(&self, e: &Entry, raw: u32) -> Result<(), Abort> {
        // Bit 30 (SYNC: generate; EMCY: reserved), 29-bit ids and bits 11–28 are refused, and
        // so are the CiA 301 restricted CAN-IDs (conformance OTH-10) but for an EMCY COB-ID
        // marked not valid and guarding's pre-defined 0x700 + node-id (guarding answers on the
        // COB-ID's CAN-ID: it has no "not valid" bit).
        let id = raw & 0x7FF;
        let may_be_restricted = match e.hook {
            Hook::SyncCobId => false,
            Hook::EmcyCobId => raw & 0x8000_0000 != 0,
            Hook::GuardingCobId => id == 0x700 + self.node_id as u32,
            Hook::TpdoComm | Hook::TpdoMap => {
                return Tpdos::check_value(&self.od, e.index, e.sub, raw)
            }
            // The others check nothing beyond the table.
            _ => return Ok(()),
        };
        if raw & (0x6000_0000 | pdo::COB_ID_HIGH_BITS) != 0
            || !may_be_restricted && pdo::restricted_id(id)
        {
            return Err(Abort::InvalidValue);
        }
        Ok(())
    }

    /// The rule of an entry's hook for an SDO write of `raw` over `cur` that passed the
    /// table's checks: [`Device::value_allowed`] and what relates the new value to the current
    /// one (a state file's values are loaded without the latter).
    #[inline]
    fn validate(&mut self, e: &Entry, cur: u32, raw: u32) -> Result<(), Abort> {
        if e.hook.checked_by_service() {
            return self.validate_service(e, raw);
        }
        // One call for every other hook (`value_allowed` is a match of its own).
        self.value_allowed(e, raw)?;
        let clash = match e.hook {
            // The CAN-ID of a valid EMCY may not change (CiA 301 7.5.2.17).
            Hook::EmcyCobId => {
                cur & 0x8000_0000 == 0 && raw & 0x8000_0000 == 0 && (cur ^ raw) & 0x7FF != 0
            }
            // Guarding and SYNC may not share a CAN-ID: a zero-length data frame counts as a
            // guard request (D22), so every SYNC would be answered as one.
            Hook::SyncCobId => raw & 0x7FF == u32::from(self.errctl.guarding_id()),
            Hook::GuardingCobId => raw & 0x7FF == self.sync_can_id(),
            // The others (`Hook::None` among them) check nothing beyond their own value (or
            // act instead of storing).
            _ => false,
        };
        if clash {
            return Err(Abort::InvalidValue);
        }
        Ok(())
    }

    /// [`Device::validate`] for the PDO parameters and the application's objects.
    #[inline(never)]
    fn validate_service(&mut self, e: &Entry, raw: u32) -> Result<(), Abort> {
        match e.hook {
            Hook::TpdoComm | Hook::TpdoMap => {
                let strict = self.features().event_timer_above_inhibit;
                self.pdo.validate(&self.od, e.index, e.sub, raw, strict)
            }
            hook => match hook.app_number() {
                Some(h) => {
                    let cx = AppView {
                        od: &self.od,
                        model: self.model,
                        cfg: &self.cfg,
                    };
                    self.app.validate(h, e.sub, raw, &cx)
                }
                None => Ok(()),
            },
        }
    }

    /// The side effects of an entry's hook once a write has landed.
    #[inline]
    fn written(&mut self, e: &Entry, raw: u32) {
        // Most objects have none: no call for them.
        if e.hook.acts_when_written() {
            self.written_slow(e, raw);
        }
    }

    #[inline(never)]
    fn written_slow(&mut self, e: &Entry, raw: u32) {
        let now = self.now;
        match e.hook {
            Hook::ErrorHistory => {
                self.emcy.clear_history();
                self.sync_error_register();
            }
            Hook::Guarding | Hook::GuardingCobId => self.apply_guarding(now),
            Hook::EmcyInhibit => self.emcy.set_inhibit(raw as u16),
            Hook::Heartbeat => self.errctl.set_heartbeat(raw as u16, now),
            Hook::TpdoComm | Hook::TpdoMap => {
                let n = (e.index & 0x1FF) as usize;
                self.pdo.reconfigure(n, &self.od, now);
                if e.hook == Hook::TpdoComm {
                    let (app, mut cx) = self.app_ctx(now);
                    app.tpdo_comm_written(n, e.sub, raw, &mut cx);
                }
            }
            Hook::PendingNodeId => self.pending_node_id = raw as u8,
            Hook::PendingBitRate => self.pending_bitrate = kbps_of_object(raw),
            hook => {
                if let Some(h) = hook.app_number() {
                    let (app, mut cx) = self.app_ctx(now);
                    app.written(h, e.sub, raw, &mut cx);
                }
            }
        }
    }

    // Out of line: its image buffers would give every write a 4 KiB stack frame.
    #[inline(never)]
    fn storage_command(&mut self, e: &Entry, raw: u32) -> Result<(), Abort> {
        let f = self.features();
        let scope = Scope::of_sub(e.sub);
        // "save" stores; "load", and "kill" where the model has it, forget.
        let change = if e.hook == Hook::StoreParameters {
            let kill = f.kill_signature && (raw == SIG_KILL_ASCII || raw == SIG_KILL_MANUAL);
            if raw != SIG_SAVE && !kill {
                return Err(Abort::CannotStore);
            }
            if f.store_preop_only && self.nmt != NmtState::PreOperational {
                return Err(Abort::WrongState);
            }
            if kill {
                Change::Forget(scope)
            } else {
                Change::Save(scope)
            }
        } else {
            if raw != SIG_LOAD {
                return Err(Abort::CannotStore);
            }
            Change::Forget(scope)
        };
        self.change_stored(change).map_err(|_| Abort::CannotStore)?;
        // D7: the answer leaves no earlier than the store time after the request arrived.
        #[cfg(feature = "simulation")]
        {
            self.sdo_hold_until = Some(self.now + STORE_TIME);
        }
        Ok(())
    }
}

impl<A: Application, S: Storage> Device<A, S> {
    /// [`Dictionary::find`] with a one-entry memo (the table never changes, so a found slot
    /// stays right).
    #[cfg_attr(feature = "inline-hot-paths", inline)]
    #[cfg_attr(not(feature = "inline-hot-paths"), inline(never))]
    fn find(&mut self, index: u16, sub: u8) -> Result<usize, Abort> {
        let key = od::key(index, sub);
        if self.memo.0 == key {
            return Ok(self.memo.1);
        }
        let slot = self.od.find(index, sub)?;
        self.memo = (key, slot);
        Ok(slot)
    }
}

impl<A: Application, S: Storage> Device<A, S> {
    /// The slot of `index`/`sub` if it may be read now (the two steps of every upload; one
    /// shared copy in firmware).
    #[cfg_attr(feature = "inline-hot-paths", inline(always))] // a host: on the SDO fast paths
    #[cfg_attr(not(feature = "inline-hot-paths"), inline(never))]
    fn find_readable(&mut self, index: u16, sub: u8) -> Result<usize, Abort> {
        let slot = self.find(index, sub)?;
        self.readable(slot)?;
        Ok(slot)
    }

    /// The slot of `index`/`sub` if it may be written (every download's first step).
    #[cfg_attr(feature = "inline-hot-paths", inline(always))] // a host: on the SDO fast paths
    #[cfg_attr(not(feature = "inline-hot-paths"), inline(never))]
    fn find_writable(&mut self, index: u16, sub: u8) -> Result<usize, Abort> {
        let slot = self.find(index, sub)?;
        if !self.od.entry(slot).access.writable() {
            return Err(Abort::ReadOnly);
        }
        Ok(slot)
    }

    /// Whether `slot` may be read now: readable, and (0x1003) within the recorded errors,
    /// since sub-indices beyond them hold no data (CiA 301; the conformance tool's EMCY-03
    /// expects the read of 1003:01 to abort when the history is empty).
    #[inline]
    fn readable(&self, slot: usize) -> Result<(), Abort> {
        let e = self.od.entry(slot);
        if !e.access.readable() {
            return Err(Abort::WriteOnly);
        }
        if e.hook == Hook::ErrorHistory && e.sub as usize > self.emcy.history_len() {
            return Err(Abort::NoData);
        }
        Ok(())
    }
}

impl<A: Application, S: Storage> lss::LssNode for Device<A, S> {
    fn address(&self) -> [u32; 4] {
        self.lss_address()
    }
    fn address_part(&self, i: u8) -> u32 {
        // One dictionary search rather than the four of `lss_address`.
        self.od.value(0x1018, i + 1).unwrap_or(0)
    }
    fn node_id(&self) -> u8 {
        self.node_id
    }
    fn pending(&self) -> (u8, u16) {
        (self.pending_node_id, self.pending_bitrate)
    }
    fn fastscan(&self) -> bool {
        self.features().lss_fastscan
    }
    fn bit_timing(&self) -> &'static [u8] {
        self.features().lss_bit_timing
    }
}

impl<A: Application, S: Storage> ObjectAccess for Device<A, S> {
    fn upload_size(&mut self, index: u16, sub: u8) -> Result<usize, Abort> {
        let slot = self.find_readable(index, sub)?;
        Ok(self.od.size_of(slot))
    }

    fn read(&mut self, index: u16, sub: u8, offset: usize, buf: &mut [u8]) -> Result<usize, Abort> {
        let slot = self.find_readable(index, sub)?;
        // Values the application derives from others are current when read.
        if let Some(h) = self.od.entry(slot).hook.app_number() {
            self.app.refresh(h, &mut self.od, self.nmt);
        }
        Ok(self.od.read_at(slot, offset, buf))
    }

    fn download_size(&mut self, index: u16, sub: u8) -> Result<Option<usize>, Abort> {
        let slot = self.find_writable(index, sub)?;
        Ok(self.od.entry(slot).ty.size())
    }

    fn write(&mut self, index: u16, sub: u8, data: &[u8]) -> Result<(), Abort> {
        let slot = self.find_writable(index, sub)?;
        self.write_slot(slot, data.len(), le_u32(data))
    }

    #[inline]
    fn write_expedited(
        &mut self,
        index: u16,
        sub: u8,
        size: Option<u32>,
        data: &[u8; 4],
    ) -> Result<(), Abort> {
        // `download_size` and `write` with one lookup: the same checks in the same order.
        let slot = self.find_writable(index, sub)?;
        let e = self.od.entry(slot);
        let len = match size {
            Some(n) => n as usize,
            None => e.ty.size().unwrap_or(4),
        }
        .min(4);
        // `le_u32` of the first `len` bytes.
        let raw = u32::from_le_bytes(*data) & (u64::from(u32::MAX) >> (32 - 8 * len as u32)) as u32;
        self.write_slot(slot, len, raw)
    }
}

impl<A: Application, S: Storage> Device<A, S> {
    /// The checks and side effects of a write of `len` bytes (`raw`, little-endian) to a
    /// writable object.
    #[inline]
    fn write_slot(&mut self, slot: usize, len: usize, raw: u32) -> Result<(), Abort> {
        let e = self.od.entry(slot);
        let Some(size) = e.ty.size() else {
            return Err(Abort::UnsupportedAccess);
        };
        if len > size {
            return Err(Abort::LengthTooHigh);
        }
        if len < size {
            return Err(Abort::LengthTooLow);
        }
        if matches!(e.hook, Hook::StoreParameters | Hook::RestoreDefaults) {
            return self.storage_command(e, raw);
        }
        if e.ty == DataType::Boolean && raw > 1 {
            return Err(Abort::InvalidValue);
        }
        e.check(raw)?;
        self.validate(e, self.od.get(slot), raw)?;
        self.od.set(slot, raw);
        self.written(e, raw);
        Ok(())
    }
}
