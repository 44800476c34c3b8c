//! The device: every service wired to one object dictionary, driven by frames and time.
//!
//! [`Node`] is the sans-IO surface: `handle_frame`, `handle_timeout`, `poll_transmit`,
//! `poll_timeout`, `update_sample`. [`Device`] holds the state the services share; the SDO
//! server and the LSS slave sit beside it so they can borrow it mutably while they run.

use crate::emcy::{self, Emcy};
use crate::encoder::{AppCtx, Encoder, Sample};
use crate::errctl::{ErrCtl, ErrCtlEvent};
use crate::lss::LssSlave;
use crate::models::{DeviceConfig, Model};
use crate::nmt::{NmtCommand, NmtState};
use crate::od::{le_u32, Abort, DataType, Dictionary, Group, Param, ParamSource};
use crate::pdo::{self, Tpdos};
use crate::sdo::{ObjectAccess, SdoServer};
use crate::storage::{self, Storage, StorageError, IMAGE_MAX};
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
/// [`Device::store`] selector for the values the device stores by itself ([`Group::Auto`]).
const STORE_AUTO: u8 = 0xFE;
/// Storage record key of TMI object 0x2000 (node-id).
const KEY_TMI_NODE_ID: u32 = 0x2000 << 8;
/// Storage record key of TMI object 0x2001 (bit rate, kbit/s, 0xFFFF = autobaud).
const KEY_TMI_BITRATE: u32 = 0x2001 << 8;

/// TMI 0x2001 value → bit rate in kbit/s (0 = autobaud, D16).
fn tmi_kbps(raw: u32) -> u16 {
    if raw == 0xFFFF {
        0
    } else {
        raw as u16
    }
}

/// A stored node-id if it is one a node may have (1…127, or 0xFF = unconfigured).
fn stored_node_id(v: u32) -> Option<u8> {
    ((1..=127).contains(&v) || v == u32::from(UNCONFIGURED)).then_some(v as u8)
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
pub struct Device<S: Storage> {
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
    pub(crate) bus_bitrate: Option<u16>,
    /// Bit-rate switch in progress (LSS activate): silent until then.
    pub(crate) silent_until: Option<Instant>,
    /// The node may send from this instant (µs) on: `silent_until`, or never while the bus
    /// runs another bit rate. Derived from the three fields above by `update_talk`, which
    /// every change of them calls: sending is checked per frame, so one comparison.
    talk_from: u64,
    /// Node-id and bit rate the unit was built with: what a power-on falls back to when
    /// nothing is stored (`cfg` follows the active values, so it cannot serve).
    pub(crate) factory_lss: (u8, u16),
    autobaud_frames: u8,
    /// Node-id and bit rate as stored by LSS (kept across "restore defaults").
    pub(crate) stored_lss: (Option<u8>, Option<u16>),
    pub(crate) tx: TxQueue,
    pub(crate) emcy: Emcy,
    pub(crate) errctl: ErrCtl,
    pub(crate) pdo: Tpdos,
    pub(crate) encoder: Encoder,
    pub(crate) storage: S,
    pub(crate) now: Instant,
    /// A store completed: the SDO answer waits until this instant (D7).
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
    /// 0x1003 sub 0…8.
    hist: [u16; 1 + emcy::HISTORY_LEN],
}

impl HotSlots {
    fn new(od: &Dictionary) -> Self {
        let slot = |index: u16, sub: u8| od.find(index, sub).map_or(NO_SLOT, |s| s as u16);
        let mut hist = [NO_SLOT; 1 + emcy::HISTORY_LEN];
        for (i, h) in hist.iter_mut().enumerate() {
            *h = slot(0x1003, i as u8);
        }
        HotSlots {
            sync: slot(0x1005, 0),
            emcy_cob: slot(0x1014, 0),
            err_reg: slot(0x1001, 0),
            hist,
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
pub struct Node<S: Storage> {
    sdo: SdoServer,
    held_sdo: Option<(Instant, [u8; 8])>,
    lss: LssSlave,
    dev: Device<S>,
    /// [`Node::poll_timeout`] in µs (`u64::MAX`: none), recomputed at the end of every method
    /// that can change a deadline: hosts ask after every frame, and a cached answer is free.
    deadline: u64,
    /// The earliest deadline of everything but the TPDOs (same encoding): while it is in the
    /// future a timer expiry can only concern TPDOs.
    other_due: u64,
    /// `u64::MAX` while powered with a node-id and out of initialisation, else 0. Set where
    /// those change: `reset` and `power_off`.
    timer_gate: u64,
    /// The timer fast path (only TPDO timers can be due) applies while `now < fast_due`:
    /// `other_due & timer_gate`, kept by `update_fast_due`. (EMCY needs no term of its own:
    /// every entry point flushes what it raised, and an EMCY held back by its inhibit time
    /// has its deadline in `other_due`.)
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

impl<S: Storage> Node<S> {
    /// A node of `model` with unit configuration `cfg`, powered off. Call [`Node::power_on`].
    pub fn new(model: &'static Model, cfg: DeviceConfig, storage: S) -> Self {
        let od = Dictionary::new(model.entries);
        let hot = HotSlots::new(&od);
        Node {
            sdo: SdoServer::new(model.features.sdo_segmented, model.features.sdo_block),
            held_sdo: None,
            lss: LssSlave::default(),
            deadline: u64::MAX,
            other_due: u64::MAX,
            timer_gate: 0,
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
                bus_bitrate: None,
                silent_until: None,
                talk_from: 0,
                factory_lss: (cfg.node_id, cfg.bitrate_kbps),
                autobaud_frames: 0,
                stored_lss: (None, None),
                tx: TxQueue::default(),
                emcy: Emcy::default(),
                errctl: ErrCtl::default(),
                pdo: Tpdos::default(),
                encoder: Encoder::default(),
                storage,
                now: Instant::ZERO,
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
        self.held_sdo = None;
        self.lss = LssSlave::default();
        // A bit-rate switch cut short by the power cycle must not keep the node deaf.
        self.dev.silent_until = None;
        self.dev.update_talk();
        self.dev.emcy = Emcy::default();
        self.dev.encoder = Encoder::default();
        self.dev.stored_lss = (None, None);
        self.dev.stats.storage_corrupt = false;
        // Stored LSS values override the factory configuration.
        let mut buf = [0u8; IMAGE_MAX];
        let corrupt = match self.dev.storage.load(&mut buf) {
            Ok(n) => match storage::parse_image(&buf[..n], self.dev.model.features.tag) {
                Ok(recs) => {
                    let mut obj = (None, None);
                    for (k, v) in recs {
                        match k {
                            // A checksummed image can still hold an impossible node-id (a
                            // hand-edited or foreign file; found by fuzzing): ignore it rather
                            // than talk on COB-IDs of node 0 or 200.
                            storage::KEY_LSS_NODE_ID => {
                                self.dev.stored_lss.0 = stored_node_id(v).or(self.dev.stored_lss.0)
                            }
                            storage::KEY_LSS_BITRATE => self.dev.stored_lss.1 = Some(v as u16),
                            KEY_TMI_NODE_ID => obj.0 = stored_node_id(v).or(obj.0),
                            KEY_TMI_BITRATE => obj.1 = Some(tmi_kbps(v)),
                            _ => {}
                        }
                    }
                    // TMI (R17, R19): node-id / bit rate written to 0x2000 / 0x2001 and saved
                    // with "save" apply at power-up too; LSS "store configuration" keeps both
                    // copies equal, so the object copy is the newer one.
                    if self.dev.model.features.tmi_emcy {
                        self.dev.stored_lss.0 = obj.0.or(self.dev.stored_lss.0);
                        self.dev.stored_lss.1 = obj.1.or(self.dev.stored_lss.1);
                    }
                    false
                }
                Err(_) => true,
            },
            Err(StorageError::Empty) => false,
            Err(_) => true,
        };
        self.dev.stats.storage_corrupt = corrupt;
        // Unstored LSS changes (even ones a reset activated) are gone after a power cycle.
        let (factory_id, factory_kbps) = self.dev.factory_lss;
        self.dev.pending_node_id = self.dev.stored_lss.0.unwrap_or(factory_id);
        self.dev.pending_bitrate = self.dev.stored_lss.1.unwrap_or(factory_kbps);
        self.dev.bitrate = self.dev.pending_bitrate;
        self.dev.update_talk();
        self.reset(true, now);
        if corrupt {
            self.dev.report_corrupt_storage();
        }
        self.refresh_deadline();
    }

    /// Recomputes the cached deadlines (see `deadline`, `other_due`).
    fn refresh_deadline(&mut self) {
        let d = &self.dev;
        if !d.powered {
            self.deadline = u64::MAX;
            self.other_due = u64::MAX;
            self.update_fast_due();
            return;
        }
        let mut t = u64::MAX;
        let mut take = |c: Option<Instant>| {
            if let Some(c) = c {
                t = t.min(c.0);
            }
        };
        take(self.held_sdo.map(|(t, _)| t));
        take(self.sdo.poll_timeout());
        take(self.lss.poll_timeout());
        take(d.errctl.poll_timeout());
        if d.nmt != NmtState::Stopped {
            take(d.emcy.poll_timeout());
        }
        self.other_due = t;
        self.deadline = t.min(d.pdo.due_us());
        self.update_fast_due();
    }

    /// Recomputes `fast_due` from `other_due` and `timer_gate`; every method that changes
    /// one of them ends here (the fast path itself changes neither).
    #[inline(always)]
    fn update_fast_due(&mut self) {
        self.fast_due = self.other_due & self.timer_gate;
    }

    /// Power off: the node neither sends nor receives until [`Node::power_on`].
    pub fn power_off(&mut self) {
        self.dev.powered = false;
        self.timer_gate = 0;
        self.dev.tx.clear();
        self.refresh_deadline();
    }

    /// NMT reset node (`application == true`) or reset communication.
    fn reset(&mut self, application: bool, now: Instant) {
        self.reset_inner(application, now);
        // Node-id and NMT state (initialising or not) change nowhere else.
        let d = &self.dev;
        self.timer_gate = if d.node_id != UNCONFIGURED && d.nmt != NmtState::Initialising {
            u64::MAX
        } else {
            0
        };
        self.update_fast_due();
    }

    fn reset_inner(&mut self, application: bool, now: Instant) {
        let d = &mut self.dev;
        d.now = now;
        self.sdo.reset();
        self.held_sdo = None;
        d.sdo_hold_until = None;
        d.node_id = d.pending_node_id;
        d.bitrate = d.pending_bitrate;
        d.update_talk();
        d.cfg.node_id = d.node_id;
        d.cfg.bitrate_kbps = d.bitrate;
        d.load_values(application);
        d.emcy.reset();
        d.errctl.reset();
        if application {
            d.encoder.reset();
        }
        d.apply_comm_config(now);
        d.pdo.set_active(false, now);
        if d.node_id == UNCONFIGURED {
            // CiA 305: no node-id, no NMT: wait in LSS for one.
            d.nmt = NmtState::Initialising;
            self.lss.force_configuration();
            return;
        }
        d.nmt = NmtState::PreOperational;
        d.tx.push(Frame::std_len(cob::ERRCTL + d.node_id as u16, [0; 8], 1));
        if !d.model.features.tmi_emcy {
            d.emcy.power_on();
        }
        d.flush_emcy();
    }

    /// Handles one received frame at `now`.
    #[inline]
    pub fn handle_frame(&mut self, f: &Frame, now: Instant) {
        if !self.dev.powered {
            return;
        }
        if self.handle_frame_inner(f, now) {
            self.refresh_deadline();
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
                d.tx.push(Frame::std_len(cob::ERRCTL + d.node_id as u16, [0; 8], 1));
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
            if let Some(r) = self.lss.handle(f.data(), now, d) {
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
                if let Some(r) = self.sdo.handle(f.data(), now, d) {
                    match d.sdo_hold_until.take() {
                        Some(t) => self.held_sdo = Some((t, r)),
                        None => {
                            d.tx.push(Frame::std8(cob::SDO_TX + node, r));
                        }
                    }
                }
                // Block-upload segments (a whole block answers one request).
                while let Some(s) = self.sdo.poll_transmit() {
                    d.tx.push(Frame::std8(cob::SDO_TX + node, s));
                }
                d.flush_emcy();
            }
            return true;
        }
        if id == cob::ERRCTL + node {
            // Node guarding: an RTR, or on socketcand (no RTR) a zero-length data frame (D11, D22).
            if d.model.features.node_guarding && (f.is_remote() || f.dlc() == 0) {
                let b = d.errctl.guard_request(d.nmt, now);
                d.tx.push(Frame::std_len(
                    cob::ERRCTL + node,
                    [b, 0, 0, 0, 0, 0, 0, 0],
                    1,
                ));
                d.update_pdo_activity(now);
            }
            return true;
        }
        if !d.nmt.sdo_allowed() {
            return true;
        }
        let sync_id = d.od.hot(d.hot.sync).unwrap_or(0x80);
        if sync_id & 0x8000_0000 == 0 && id as u32 == sync_id & 0x7FF && !f.is_remote() {
            if f.dlc() <= 1 {
                let Device { pdo, od, tx, .. } = d;
                pdo.on_sync(od, now, &mut |fr| {
                    tx.push(fr);
                });
            } else if !d.model.features.tmi_emcy {
                // CiA 301 "unexpected SYNC data length" (conformance EMCY-04 without an RPDO).
                // DLC 1 stays accepted: without 0x1019 the counter byte is simply ignored.
                // The TMI's own EMCY table has no such code, so it ignores the frame.
                d.emcy.event(emcy::code::SYNC_LENGTH, [0; 5]);
                d.flush_emcy();
            }
            return true;
        }
        if f.is_remote() && d.model.features.tpdo_rtr {
            let Device { pdo, od, tx, .. } = d;
            pdo.on_rtr(id, od, now, &mut |fr| {
                tx.push(fr);
            });
        }
        true
    }

    fn nmt_command(&mut self, c: NmtCommand, now: Instant) {
        let d = &mut self.dev;
        match c {
            NmtCommand::Start => {
                if d.encoder.lockout() {
                    // TMI lock-out: stays pre-operational and repeats the EMCY (§3.12).
                    d.encoder.repeat_lockout_emcy(&mut d.emcy);
                    d.flush_emcy();
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

    /// Feeds one measurement cycle's sample to the CiA 406 application.
    pub fn update_sample(&mut self, s: &Sample, now: Instant) {
        if !self.dev.powered {
            return;
        }
        self.dev.now = now;
        let d = &mut self.dev;
        let forced_preop = {
            let (encoder, mut cx) = d.app(now);
            encoder.cycle(s, &mut cx)
        };
        if d.encoder.take_auto_dirty() {
            // Values the device keeps by itself (TH 0x2901 life extremes, D19). A failing
            // medium only loses this update; the next change tries again.
            let _ = d.store(STORE_AUTO);
        }
        if forced_preop && d.nmt == NmtState::Operational {
            d.nmt = NmtState::PreOperational;
            d.update_pdo_activity(now);
        }
        d.flush_emcy();
        d.run_pdos(now);
        self.refresh_deadline();
    }

    /// Handles every deadline that has passed at `now`.
    #[inline]
    pub fn handle_timeout(&mut self, now: Instant) {
        // Fast path for a producing node: while every other deadline is in the future, the
        // steps of the full path would all do nothing but the TPDOs'. (`fast_due` is 0
        // while powered off, unconfigured, initialising or with EMCY work.)
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
        self.refresh_deadline();
    }

    fn handle_timeout_full(&mut self, now: Instant) {
        if let Some((t, r)) = self.held_sdo {
            if now >= t {
                self.held_sdo = None;
                // A node stopped during the store time no longer serves SDO.
                if self.dev.nmt.sdo_allowed() {
                    let id = cob::SDO_TX + self.dev.node_id as u16;
                    self.dev.tx.push(Frame::std8(id, r));
                }
            }
        }
        if let Some(r) = self.sdo.handle_timeout(now) {
            let id = cob::SDO_TX + self.dev.node_id as u16;
            self.dev.tx.push(Frame::std8(id, r));
        }
        self.lss.handle_timeout(now, &mut self.dev);
        self.after_lss(now);
        let d = &mut self.dev;
        if d.node_id == UNCONFIGURED || d.nmt == NmtState::Initialising {
            return;
        }
        while let Some(ev) = d.errctl.handle_timeout(now, d.nmt) {
            match ev {
                ErrCtlEvent::Heartbeat(b) => {
                    d.tx.push(Frame::std_len(
                        cob::ERRCTL + d.node_id as u16,
                        [b, 0, 0, 0, 0, 0, 0, 0],
                        1,
                    ));
                }
                ErrCtlEvent::LifeGuardingLost => {
                    d.emcy
                        .raise(emcy::code::LIFE_GUARD, emcy::reg::COMMUNICATION, [0; 5]);
                    d.update_pdo_activity(now);
                }
            }
        }
        d.run_pdos(now);
        d.flush_emcy();
    }

    /// The rest of the timer fast path once the TPDOs ran: the node's clock and deadline
    /// (TPDOs change neither the other deadlines nor the EMCY state).
    #[inline(always)]
    fn after_tpdo_timers(&mut self, now: Instant) {
        let d = &mut self.dev;
        d.now = now;
        // Nothing for the EMCY service to do (see `fast_due`).
        debug_assert!(d.emcy.generation() == d.emcy_synced, "EMCY not mirrored");
        // (A stopped node keeps its EMCYs until it leaves Stopped.)
        debug_assert!(
            !d.emcy.has_pending()
                || d.nmt == NmtState::Stopped
                || d.emcy.poll_timeout().is_some_and(|t| now < t),
            "EMCY due: {:?} at {now:?}, nmt {:?}",
            d.emcy.poll_timeout(),
            d.nmt
        );
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
            if now.0 < self.fast_due && self.dev.tx.is_empty() && self.dev.can_talk(now) {
                // `now ≥ deadline` and `now < other_due`: the TPDOs' `due` has passed.
                let Device { pdo, od, .. } = &mut self.dev;
                let first = pdo.scan_due(od, now);
                self.after_tpdo_timers(now);
                if first.is_some() {
                    return first;
                }
            } else {
                self.handle_timeout(now);
            }
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
    pub fn set_bus_bitrate(&mut self, kbps: Option<u16>) {
        self.dev.bus_bitrate = kbps;
        self.dev.update_talk();
    }

    /// The SDO server (read-only view: counters, transfer in progress).
    pub fn sdo_server(&self) -> &SdoServer {
        &self.sdo
    }

    /// The device state (read-only view for hosts and tests).
    pub fn device(&self) -> &Device<S> {
        &self.dev
    }

    /// Mutable access to the storage backend (hosts: fault injection, inspection).
    pub fn storage_mut(&mut self) -> &mut S {
        &mut self.dev.storage
    }

    /// Mutable access to the CiA 406 application (fault injection, presets from a control
    /// interface).
    pub fn encoder_mut(&mut self) -> &mut Encoder {
        &mut self.dev.encoder
    }

    /// Injects (`active`) or removes a fault the CiA 406 application reports the way the
    /// model's manual says (EMCY code and bytes, error register, alarms, TMI 0x1002 bits and
    /// lock-out).
    pub fn inject_fault(&mut self, fault: crate::encoder::Fault, active: bool) {
        if !self.dev.powered {
            return;
        }
        let d = &mut self.dev;
        let now = d.now;
        let forced_preop = {
            let (encoder, mut cx) = d.app(now);
            encoder.inject(fault, active, &mut cx)
        };
        if forced_preop && d.nmt == NmtState::Operational {
            d.nmt = NmtState::PreOperational;
            d.update_pdo_activity(now);
        }
        d.flush_emcy();
        d.run_pdos(now);
        self.refresh_deadline();
    }

    /// Raises (or with `active == false` clears) a device error from outside the CANopen
    /// services: supply voltage, temperature, CAN controller states (fault injection, or the
    /// real hardware's monitors on an MCU).
    pub fn set_error(&mut self, code: u16, reg_bits: u8, mfr: [u8; 5], active: bool) {
        let d = &mut self.dev;
        if active {
            d.emcy.raise(code, reg_bits, mfr);
        } else {
            d.emcy.clear(code);
        }
        d.flush_emcy();
        self.refresh_deadline();
    }

    /// Reads an object as an SDO client would see it, bypassing the bus (hosts, tests).
    pub fn read_object(&mut self, index: u16, sub: u8) -> Result<u32, Abort> {
        let mut b = [0u8; 4];
        let n = ObjectAccess::read(&mut self.dev, index, sub, 0, &mut b)?;
        Ok(le_u32(&b[..n]))
    }
}

impl<S: Storage> Device<S> {
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
    /// The CiA 406 application.
    pub fn encoder(&self) -> &Encoder {
        &self.encoder
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
        if id == cob::NMT || id == cob::SDO_RX + node || id == cob::ERRCTL + node {
            return false;
        }
        if !self.nmt.sdo_allowed() {
            return true;
        }
        let sync_id = self.od.hot(self.hot.sync).unwrap_or(0x80);
        let is_sync = sync_id & 0x8000_0000 == 0 && id as u32 == sync_id & 0x7FF && !remote;
        !(is_sync || remote && self.model.features.tpdo_rtr)
    }

    /// [`Node::poll_transmit`] once a frame was lost: counts it and the rest that are lost.
    #[cold]
    #[inline(never)]
    fn poll_transmit_lost(&mut self) -> Option<Frame> {
        self.stats.tx_wrong_bitrate = self.stats.tx_wrong_bitrate.wrapping_add(1);
        while let Some(f) = self.tx.pop() {
            if self.can_talk(self.now) {
                return Some(f);
            }
            self.stats.tx_wrong_bitrate = self.stats.tx_wrong_bitrate.wrapping_add(1);
        }
        None
    }

    /// Whether the node can receive at `now` (bit rate matches, not switching).
    fn can_hear(&mut self, now: Instant) -> bool {
        if let Some(t) = self.silent_until {
            if now < t {
                return false;
            }
        }
        match self.bus_bitrate {
            None => true,
            Some(bus) if self.bitrate == 0 => {
                // Autobaud (TMI): lock on after a few frames of continuous traffic (R19).
                self.autobaud_frames += 1;
                if self.autobaud_frames >= 4 {
                    self.bitrate = bus;
                    self.update_talk();
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
        match self.bus_bitrate {
            Some(bus) if bus != self.bitrate => u64::MAX,
            _ => self.silent_until.map_or(0, |t| t.0),
        }
    }

    /// Recomputes `talk_from` after a change of `bitrate`, `bus_bitrate` or `silent_until`.
    pub(crate) fn update_talk(&mut self) {
        self.talk_from = self.talk_from_now();
    }

    /// Sets the pending node-id (LSS configure node-id, TMI 0x2000).
    pub(crate) fn set_pending_node_id(&mut self, id: u8) {
        self.pending_node_id = id;
    }

    /// Sets the pending bit rate (LSS configure bit timing, TMI 0x2001).
    pub(crate) fn set_pending_bitrate(&mut self, kbps: u16) {
        self.pending_bitrate = kbps;
    }

    /// Makes `kbps` the active bit rate now (LSS activate bit timing).
    pub(crate) fn activate_bitrate(&mut self, kbps: u16) {
        self.bitrate = kbps;
        self.cfg.bitrate_kbps = kbps;
        self.autobaud_frames = 0;
        self.update_talk();
    }

    /// Reloads values: communication objects always, application objects on reset node.
    /// Defaults first, then whatever the stored image holds for those ranges (D6).
    fn load_values(&mut self, application: bool) {
        let p = Params {
            model: self.model,
            cfg: &self.cfg,
        };
        let node = self.node_id;
        self.od.load_defaults(0x1000, 0x1FFF, &p, node);
        if application {
            self.od.load_defaults(0x2000, 0xFFFF, &p, node);
        }
        let mut buf = [0u8; IMAGE_MAX];
        let Ok(n) = self.storage.load(&mut buf) else {
            return;
        };
        let Ok(recs) = storage::parse_image(&buf[..n], self.model.features.tag) else {
            return;
        };
        for (k, v) in recs {
            let index = (k >> 8) as u16;
            if k > 0x00FF_FFFF || (!application && index >= 0x2000) {
                continue;
            }
            if let Ok(slot) = self.od.find(index, k as u8) {
                if self.od.entry(slot).group != Group::Volatile {
                    self.od.set(slot, v);
                }
            }
        }
        // D15: stored TPDO COB-IDs that were the default for another node-id follow this one.
        for n in 0..self.model.features.tpdos as usize {
            if let Ok(slot) = self.od.find(pdo::comm_index(n), 1) {
                let v = self.od.get(slot);
                let base = 0x180 + 0x100 * n as u32;
                let id = v & 0x7FF;
                if id > base && id <= base + 0x7F && id != base + node as u32 {
                    self.od.set(slot, (v & !0x7FF) | (base + node as u32));
                }
            }
        }
        if let Some(v) = self.od.hot(self.hot.emcy_cob) {
            let slot = self.hot.emcy_cob as usize;
            let id = v & 0x7FF;
            if id > 0x80 && id <= 0xFF && id != 0x80 + node as u32 {
                self.od.set(slot, (v & !0x7FF) | (0x80 + node as u32));
            }
        }
    }

    /// The encoder and the context it runs in (disjoint borrows of the device).
    fn app(&mut self, now: Instant) -> (&mut Encoder, AppCtx<'_>) {
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
        (&mut self.encoder, cx)
    }

    /// Pushes the cached service configuration from the dictionary after a reload.
    fn apply_comm_config(&mut self, now: Instant) {
        self.pdo
            .configure_all(self.model.features.tpdos as usize, &self.od);
        let hb = self.od.value(0x1017, 0).unwrap_or(0) as u16;
        self.errctl.set_heartbeat(hb, now);
        let gt = self.od.value(0x100C, 0).unwrap_or(0) as u16;
        let lf = self.od.value(0x100D, 0).unwrap_or(0) as u8;
        self.errctl.set_guarding(gt, lf, now);
        self.emcy
            .set_inhibit(self.od.value(0x1015, 0).unwrap_or(0) as u16);
        self.sync_error_register();
    }

    fn sync_error_register(&mut self) {
        let h = self.hot;
        let r = self.emcy.register();
        self.od.set_hot(h.err_reg, r as u32);
        let n = self.emcy.history_len();
        self.od.set_hot(h.hist[0], n as u32);
        for i in 1..=emcy::HISTORY_LEN {
            self.od
                .set_hot(h.hist[i], self.emcy.history(i).unwrap_or(0));
        }
        self.emcy_synced = self.emcy.generation();
    }

    /// Moves EMCYs whose inhibit time allows into the transmit queue and mirrors the error
    /// register and history into the dictionary.
    #[inline]
    fn flush_emcy(&mut self) {
        // Runs after every frame and timer: the usual "nothing to do" stays inline.
        if self.emcy.generation() != self.emcy_synced || self.emcy.has_pending() {
            self.flush_emcy_slow();
        }
    }

    fn flush_emcy_slow(&mut self) {
        // Nothing else writes 0x1001 / 0x1003 between resets, so an unchanged EMCY state needs
        // no mirroring (this runs after every frame).
        if self.emcy.generation() != self.emcy_synced {
            self.sync_error_register();
        }
        if !self.emcy.has_pending() || self.nmt == NmtState::Stopped || self.node_id == UNCONFIGURED
        {
            return;
        }
        let cobid = self
            .od
            .hot(self.hot.emcy_cob)
            .unwrap_or(0x80 + self.node_id as u32);
        while let Some(p) = self.emcy.poll(self.now) {
            if cobid & 0x8000_0000 == 0 {
                self.tx.push(Frame::std8((cobid & 0x7FF) as u16, p));
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
        let on = self.nmt == NmtState::Operational && !self.errctl.life_guard_lost;
        self.pdo.set_active(on, now);
        if !self.errctl.life_guard_lost && self.emcy.is_active(emcy::code::LIFE_GUARD) {
            self.emcy.clear(emcy::code::LIFE_GUARD);
            self.flush_emcy();
        }
    }

    fn report_corrupt_storage(&mut self) {
        self.encoder.storage_corrupt(&mut self.emcy, self.model);
        if !self.encoder.handles_storage_corrupt(self.model) {
            self.emcy.raise(emcy::code::DATA_SET, 0, [0; 5]);
        }
        self.flush_emcy();
    }

    /// Writes the stored image: `groups` selects what "save" covers (0x1010 sub 1 all, 2 comm,
    /// 3 application); the rest keeps what was stored before.
    pub(crate) fn store(&mut self, sub: u8) -> Result<(), Abort> {
        let mut old = [0u8; IMAGE_MAX];
        let old_len = self.storage.load(&mut old).unwrap_or(0);
        let mut buf = [0u8; IMAGE_MAX];
        let mut w = storage::ImageWriter::new(&mut buf, self.model.features.tag);
        let covers = |index: u16, group: Group| match sub {
            STORE_AUTO => group == Group::Auto,
            2 => group == Group::Comm || (group != Group::Volatile && index < 0x2000),
            3 => index >= 0x2000 && group != Group::Volatile,
            _ => group != Group::Volatile,
        };
        for (slot, e) in self.od.entries().iter().enumerate() {
            if covers(e.index, e.group) {
                w.push(e.key(), self.od.get(slot));
            }
        }
        if let Ok(recs) = storage::parse_image(&old[..old_len], self.model.features.tag) {
            for (k, v) in recs {
                let keep = k > 0x00FF_FFFF
                    || self.od.find((k >> 8) as u16, k as u8).is_ok_and(|s| {
                        let e = self.od.entry(s);
                        !covers(e.index, e.group)
                    });
                if keep {
                    w.push(k, v);
                }
            }
        }
        let n = w.finish();
        self.storage.save(&buf[..n]).map_err(|_| Abort::CannotStore)
    }

    /// "load" / "kill": forgets the stored parameters of the selected groups (the LSS
    /// configuration stays); defaults apply at the next reset (D7).
    pub(crate) fn forget(&mut self, sub: u8) -> Result<(), Abort> {
        let mut old = [0u8; IMAGE_MAX];
        let old_len = match self.storage.load(&mut old) {
            Ok(n) => n,
            Err(StorageError::Empty) => return Ok(()),
            Err(StorageError::Corrupt) => 0,
            Err(StorageError::Io) => return Err(Abort::CannotStore),
        };
        let mut buf = [0u8; IMAGE_MAX];
        let mut w = storage::ImageWriter::new(&mut buf, self.model.features.tag);
        if let Ok(recs) = storage::parse_image(&old[..old_len], self.model.features.tag) {
            for (k, v) in recs {
                let index = (k >> 8) as u16;
                let keep = match sub {
                    2 => k > 0x00FF_FFFF || index >= 0x2000,
                    3 => k > 0x00FF_FFFF || index < 0x2000,
                    _ => k > 0x00FF_FFFF,
                };
                if keep {
                    w.push(k, v);
                }
            }
        }
        let n = w.finish();
        self.storage.save(&buf[..n]).map_err(|_| Abort::CannotStore)
    }

    /// LSS "store configuration": keeps the pending node-id and bit rate.
    pub(crate) fn store_lss(&mut self) -> Result<(), StorageError> {
        let mut old = [0u8; IMAGE_MAX];
        let old_len = self.storage.load(&mut old).unwrap_or(0);
        let mut buf = [0u8; IMAGE_MAX];
        let mut w = storage::ImageWriter::new(&mut buf, self.model.features.tag);
        w.push(storage::KEY_LSS_NODE_ID, self.pending_node_id as u32);
        w.push(storage::KEY_LSS_BITRATE, self.pending_bitrate as u32);
        let tmi = self.model.features.tmi_emcy;
        if tmi {
            w.push(KEY_TMI_NODE_ID, self.pending_node_id as u32);
            let kbps = if self.pending_bitrate == 0 {
                0xFFFF
            } else {
                self.pending_bitrate as u32
            };
            w.push(KEY_TMI_BITRATE, kbps);
        }
        if let Ok(recs) = storage::parse_image(&old[..old_len], self.model.features.tag) {
            for (k, v) in recs {
                let replaced = k == storage::KEY_LSS_NODE_ID
                    || k == storage::KEY_LSS_BITRATE
                    || (tmi && (k == KEY_TMI_NODE_ID || k == KEY_TMI_BITRATE));
                if !replaced {
                    w.push(k, v);
                }
            }
        }
        let n = w.finish();
        self.storage.save(&buf[..n])?;
        self.stored_lss = (Some(self.pending_node_id), Some(self.pending_bitrate));
        Ok(())
    }

    /// 0x1003 sub-indices beyond the number of recorded errors hold no data (CiA 301; the
    /// conformance tool's EMCY-03 expects the read of 1003:01 to abort when the history is
    /// empty).
    fn history_has(&self, index: u16, sub: u8) -> Result<(), Abort> {
        if index == 0x1003 && sub as usize > self.emcy.history_len() {
            return Err(Abort::NoData);
        }
        Ok(())
    }

    /// Service-level rules for a write that passed the table's checks.
    #[inline]
    fn validate(&mut self, index: u16, sub: u8, raw: u32) -> Result<(), Abort> {
        match index {
            0x1005 => {
                // SYNC consumer only: bit 30 (generate) and 29-bit ids are refused, and so are
                // the CiA 301 restricted CAN-IDs (conformance OTH-10).
                if raw & 0x6000_0000 != 0 || pdo::restricted_id(raw & 0x7FF) {
                    return Err(Abort::InvalidValue);
                }
                Ok(())
            }
            0x1014 => {
                if raw & 0x2000_0000 != 0 {
                    return Err(Abort::InvalidValue);
                }
                // A valid EMCY COB-ID may not be a restricted CAN-ID (conformance OTH-10).
                if raw & 0x8000_0000 == 0 && pdo::restricted_id(raw & 0x7FF) {
                    return Err(Abort::InvalidValue);
                }
                let cur = self.od.hot(self.hot.emcy_cob).unwrap_or(0);
                if cur & 0x8000_0000 == 0 && raw & 0x8000_0000 == 0 && (cur ^ raw) & 0x7FF != 0 {
                    return Err(Abort::InvalidValue);
                }
                Ok(())
            }
            0x1800..=0x1BFF | 0x2000..=0x9FFF => self.validate_service(index, sub, raw),
            _ => Ok(()),
        }
    }

    /// [`Device::validate`] for the PDO parameters and the application's objects.
    #[inline(never)]
    fn validate_service(&mut self, index: u16, sub: u8, raw: u32) -> Result<(), Abort> {
        match index {
            0x1800..=0x1BFF => {
                let tmi = self.model.features.tmi_emcy;
                self.pdo.validate(&self.od, index, sub, raw, tmi)
            }
            0x2000..=0x9FFF => {
                let cx = crate::encoder::AppView {
                    od: &self.od,
                    model: self.model,
                    cfg: &self.cfg,
                };
                self.encoder.validate(index, sub, raw, &cx)
            }
            _ => Ok(()),
        }
    }

    /// Side effects once a write has landed.
    #[inline]
    fn written(&mut self, index: u16, sub: u8, raw: u32) {
        // Most communication objects have none: no call for them.
        if matches!(
            index,
            0x1003 | 0x100C | 0x100D | 0x1015 | 0x1017 | 0x1800..=0x1803 | 0x1A00..=0x1A03
        ) || index >= 0x2000
        {
            self.written_slow(index, sub, raw);
        }
    }

    #[inline(never)]
    fn written_slow(&mut self, index: u16, sub: u8, raw: u32) {
        let now = self.now;
        match index {
            0x1003 => {
                self.emcy.clear_history();
                self.sync_error_register();
            }
            0x100C | 0x100D => {
                let gt = self.od.value(0x100C, 0).unwrap_or(0) as u16;
                let lf = self.od.value(0x100D, 0).unwrap_or(0) as u8;
                self.errctl.set_guarding(gt, lf, now);
            }
            0x1015 => self.emcy.set_inhibit(raw as u16),
            0x1017 => self.errctl.set_heartbeat(raw as u16, now),
            0x1800..=0x1803 | 0x1A00..=0x1A03 => {
                let n = (index & 0x3) as usize;
                self.pdo.configure(n, &self.od);
                if index == 0x1800 && sub == 5 {
                    // D12: 0x6200 and TPDO1's event timer are one value.
                    self.od.set_value(0x6200, 0, raw);
                }
                let on = self.pdo.active();
                if on {
                    self.pdo.set_active(false, now);
                    self.pdo.set_active(true, now);
                }
            }
            0x6200 => {
                self.od.set_value(0x1800, 5, raw);
                self.pdo.configure(0, &self.od);
                if self.pdo.active() {
                    self.pdo.set_active(false, now);
                    self.pdo.set_active(true, now);
                }
            }
            0x2000 if self.model.features.tmi_emcy => self.pending_node_id = raw as u8,
            0x2001 if self.model.features.tmi_emcy => {
                self.pending_bitrate = tmi_kbps(raw);
            }
            _ => {
                if index >= 0x2000 {
                    let (encoder, mut cx) = self.app(now);
                    encoder.written(index, sub, raw, &mut cx);
                }
            }
        }
    }

    // Out of line: its image buffers would give every write a 4 KiB stack frame.
    #[inline(never)]
    fn storage_command(&mut self, index: u16, sub: u8, raw: u32) -> Result<(), Abort> {
        let f = self.model.features;
        if index == 0x1010 {
            let kill = f.kill_signature && (raw == SIG_KILL_ASCII || raw == SIG_KILL_MANUAL);
            if raw != SIG_SAVE && !kill {
                return Err(Abort::CannotStore);
            }
            if f.store_preop_only && self.nmt != NmtState::PreOperational {
                return Err(Abort::WrongState);
            }
            if kill {
                self.forget(sub)?;
            } else {
                self.store(sub)?;
            }
        } else {
            if raw != SIG_LOAD {
                return Err(Abort::CannotStore);
            }
            self.forget(sub)?;
        }
        self.sdo_hold_until = Some(self.now + STORE_TIME);
        Ok(())
    }
}

impl<S: Storage> Device<S> {
    /// [`Dictionary::find`] with a one-entry memo (the table never changes, so a found slot
    /// stays right).
    #[inline]
    fn find(&mut self, index: u16, sub: u8) -> Result<usize, Abort> {
        let key = (index as u32) << 8 | sub as u32;
        if self.memo.0 == key {
            return Ok(self.memo.1);
        }
        let slot = self.od.find(index, sub)?;
        self.memo = (key, slot);
        Ok(slot)
    }
}

impl<S: Storage> ObjectAccess for Device<S> {
    fn upload_size(&mut self, index: u16, sub: u8) -> Result<usize, Abort> {
        let slot = self.find(index, sub)?;
        if !self.od.entry(slot).access.readable() {
            return Err(Abort::WriteOnly);
        }
        self.history_has(index, sub)?;
        Ok(self.od.size_of(slot))
    }

    fn read(&mut self, index: u16, sub: u8, offset: usize, buf: &mut [u8]) -> Result<usize, Abort> {
        let slot = self.find(index, sub)?;
        if !self.od.entry(slot).access.readable() {
            return Err(Abort::WriteOnly);
        }
        self.history_has(index, sub)?;
        // Values derived from others (0x6500, 0x6509, TMI 0x1002) are current when read.
        self.encoder.refresh(index, &mut self.od, self.nmt);
        Ok(self.od.read_at(slot, offset, buf))
    }

    fn download_size(&mut self, index: u16, sub: u8) -> Result<Option<usize>, Abort> {
        let slot = self.find(index, sub)?;
        let e = self.od.entry(slot);
        if !e.access.writable() {
            return Err(Abort::ReadOnly);
        }
        Ok(e.ty.size())
    }

    fn write(&mut self, index: u16, sub: u8, data: &[u8]) -> Result<(), Abort> {
        let slot = self.find(index, sub)?;
        if !self.od.entry(slot).access.writable() {
            return Err(Abort::ReadOnly);
        }
        self.write_slot(slot, index, sub, data.len(), le_u32(data))
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
        let slot = self.find(index, sub)?;
        let e = self.od.entry(slot);
        if !e.access.writable() {
            return Err(Abort::ReadOnly);
        }
        let len = match size {
            Some(n) => n as usize,
            None => e.ty.size().unwrap_or(4),
        }
        .min(4);
        // `le_u32` of the first `len` bytes.
        let raw = u32::from_le_bytes(*data) & (u64::from(u32::MAX) >> (32 - 8 * len as u32)) as u32;
        self.write_slot(slot, index, sub, len, raw)
    }
}

impl<S: Storage> Device<S> {
    /// The checks and side effects of a write of `len` bytes (`raw`, little-endian) to a
    /// writable object.
    #[inline]
    fn write_slot(
        &mut self,
        slot: usize,
        index: u16,
        sub: u8,
        len: usize,
        raw: u32,
    ) -> Result<(), Abort> {
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
        if matches!(index, 0x1010 | 0x1011) {
            return self.storage_command(index, sub, raw);
        }
        if e.ty == DataType::Boolean && raw > 1 {
            return Err(Abort::InvalidValue);
        }
        if !e.accepts(raw) {
            return Err(if e.above_range(raw) {
                Abort::ValueTooHigh
            } else if e.below_range(raw) {
                Abort::ValueTooLow
            } else {
                Abort::InvalidValue
            });
        }
        self.validate(index, sub, raw)?;
        self.od.set(slot, raw);
        self.written(index, sub, raw);
        Ok(())
    }
}
