//! The device: every service wired to one object dictionary, driven by frames and time.
//!
//! [`Node`] is the sans-IO surface: `handle_frame`, `handle_timeout`, `poll_transmit`,
//! `poll_timeout`, `update_sample`. [`Device`] holds the state the services share; the SDO
//! server and the LSS slave sit beside it so they can borrow it mutably while they run.
//!
//! Each rule lives in its service's module (`emcy`, `errctl`, `storage`, `wire::cob`, …); the
//! node only wires them together. Its `impl`s are split by concern over this directory:
//!
//! | file | what |
//! | --- | --- |
//! | `mod.rs` | [`Node`], [`Device`], the entry points and the one epilogue |
//! | `route.rs` | which service a received frame is for; NMT commands |
//! | `timeout.rs` | the deadlines that passed; the TPDO-only fast path |
//! | `access.rs` | object access for the SDO server: lookup, write rules by hook, side effects |
//! | `persist.rs` | loading from the stored image; "save", "load" / "kill", the automatic store |
//! | `lss_glue.rs` | what the LSS slave asks of the device; object copies of node-id and bit rate |
//! | `services.rs` | hot object slots; the services' configuration; EMCY sending; PDO activity |
//! | `bitrate.rs` | the talk gate (a bit-rate switch) and the detected bit rate (autobaud) |

use crate::app::{AppCtx, AppView, Application, ModelOf};
use crate::emcy::{self, Emcy};
use crate::errbehav;
use crate::errctl::{self, ErrCtl, ErrCtlEvent};
use crate::hbcons::{self, HbConsumer};
use crate::lss::{self, LssSlave, UNCONFIGURED};
use crate::model::{Features, Model, UnitConfig};
use crate::nmt::{NmtCommand, NmtState};
use crate::od::{self, le_u32, Abort, DataType, Dictionary, Entry, Hook, Param, ParamSource};
use crate::pdo::Tpdos;
use crate::rpdo::Rpdos;
use crate::sdo::{ObjectAccess, SdoServer};
use crate::storage::{self, Scope, Storage, StorageError, IMAGE_MAX};
use crate::timers::{Timer, TimerTable, NEVER};
use crate::txq::TxQueue;
use crate::wire::{cob, Frame, Instant};

mod access;
mod bitrate;
mod lss_glue;
mod persist;
mod route;
mod services;
mod slots;
mod timeout;

use slots::HotSlots;

/// Counters a host may show.
#[derive(Clone, Copy, Debug, Default)]
pub struct Stats {
    /// Frames the node produced while it could not talk (a bit-rate switch, CiA 305 §5.8):
    /// lost, as on a real bus.
    pub tx_silenced: u32,
    /// "save" / "load" commands completed (wrapping): a frame whose handling changes it made
    /// the node queue the answer to a store (a simulated device holds that answer for the
    /// store time, D7).
    pub stores: u8,
    /// Resets of communication so far, power-on included (wrapping).
    pub resets: u8,
    /// The stored image failed its check at the last load.
    pub storage_corrupt: bool,
}

/// The state all services share: dictionary, NMT state, identity, queues, storage.
pub struct Device<A: Application, S: Storage> {
    pub(crate) model: &'static ModelOf<A>,
    pub(crate) cfg: A::Config,
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
    /// Bit-rate switch in progress (LSS activate): silent until then.
    pub(crate) silent_until: Option<Instant>,
    /// The node may send from this instant (µs) on: `silent_until`. Derived by the node's
    /// epilogue: sending is checked per frame, so one comparison.
    talk_from: u64,
    /// Node-id and bit rate the unit was built with: what a power-on falls back to when
    /// nothing is stored (`cfg` follows the active values, so it cannot serve).
    pub(crate) factory_lss: (u8, u16),
    /// Node-id and bit rate as stored by LSS (kept across "restore defaults").
    pub(crate) stored_lss: (Option<u8>, Option<u16>),
    pub(crate) tx: TxQueue,
    pub(crate) emcy: Emcy,
    pub(crate) errctl: ErrCtl,
    /// The heartbeat consumer (0x1016).
    pub(crate) hbc: HbConsumer,
    pub(crate) pdo: Tpdos,
    pub(crate) rpdo: Rpdos,
    pub(crate) app: A,
    pub(crate) storage: S,
    pub(crate) now: Instant,
    pub(crate) stats: Stats,
    /// Slots of the objects the per-frame paths touch.
    hot: HotSlots,
    /// The last `(index << 8 | sub, slot)` found: an SDO request looks its object up twice
    /// (size, then access), and masters poll the same object again and again.
    memo: (u32, usize),
    /// [`Emcy::generation`] last mirrored into 0x1001 / 0x1003.
    emcy_synced: u32,
}

/// A CANopen device: the CiA 301 / 305 services wired to one dictionary, running
/// application `A` and storing through `S`.
pub struct Node<A: Application, S: Storage> {
    sdo: SdoServer,
    lss: LssSlave,
    dev: Device<A, S>,
    /// The services' deadlines, written by [`Node::epilogue`] only.
    timers: TimerTable,
    /// [`Node::poll_timeout`] in µs ([`NEVER`]: none), from the epilogue: hosts ask after
    /// every frame, and an answer kept is free.
    deadline: u64,
    /// The earliest deadline of everything but the TPDOs (same encoding): while it is in the
    /// future a timer expiry can only concern TPDOs. (This and `fast_due` serve the host's
    /// timer fast path only, [`crate::config::INLINE_HOT_PATHS`]: a firmware takes the full
    /// path, for less flash, and only keeps the two fields; both figures are in
    /// docs/FIRMWARE.md, "Build options in figures".)
    other_due: u64,
    /// The timer fast path (only TPDO timers can be due) applies while `now < fast_due`:
    /// `other_due` while the node runs (powered, with a node-id, out of initialisation), else
    /// 0. (EMCY needs no term of its own: the epilogue flushes what was raised, and an EMCY
    /// held back by its inhibit time has its deadline in `other_due`.)
    fast_due: u64,
}

impl<A: Application + core::default::Default, S: Storage> Node<A, S> {
    /// A node of `model` running a new `A` with unit configuration `cfg`, powered off. Call
    /// [`Node::power_on`].
    #[inline(always)] // lets firmware build the node in its static, not in a stack temporary
    pub fn new(model: &'static ModelOf<A>, cfg: A::Config, storage: S) -> Self {
        Node::with_app(model, cfg, A::default(), storage)
    }
}

impl<A: Application, S: Storage> Node<A, S> {
    /// A node of the device `model` describes, running application `app`, powered off. Call
    /// [`Node::power_on`].
    #[inline(always)] // as `new`
    pub fn with_app(model: &'static ModelOf<A>, cfg: A::Config, app: A, storage: S) -> Self {
        // The unit's own dictionary (a device with one per configuration); none to pick where
        // the build fixes a description that has no variants.
        let model = match A::FIXED {
            Some(f) if f.variant.is_none() => model,
            _ => model.for_unit(&cfg),
        };
        let od = Dictionary::new(model);
        let hot = HotSlots::new(model);
        let f = A::features(model);
        Node {
            sdo: SdoServer::new(f.sdo_segmented, f.sdo_block),
            lss: LssSlave::default(),
            timers: TimerTable::default(),
            deadline: NEVER,
            other_due: NEVER,
            fast_due: 0,
            dev: Device {
                model,
                cfg,
                od,
                nmt: NmtState::Initialising,
                powered: false,
                node_id: cfg.node_id(),
                pending_node_id: cfg.node_id(),
                bitrate: cfg.bitrate_kbps(),
                pending_bitrate: cfg.bitrate_kbps(),
                silent_until: None,
                talk_from: 0,
                factory_lss: (cfg.node_id(), cfg.bitrate_kbps()),
                stored_lss: (None, None),
                tx: TxQueue::default(),
                emcy: Emcy::default(),
                errctl: ErrCtl::default(),
                hbc: HbConsumer::default(),
                pdo: Tpdos::default(),
                rpdo: Rpdos::default(),
                app,
                storage,
                now: Instant::ZERO,
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
            if crate::config::INLINE_HOT_PATHS {
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
        set(Timer::SdoTransfer, self.sdo.due_us());
        set(Timer::LssSwitch, self.lss.due_us());
        set(Timer::Silence, us(d.silent_until));
        set(Timer::ErrorControl, d.errctl.due_us());
        if crate::config::MAX_HB_CONSUMERS > 0 {
            set(Timer::HbConsumer, d.hbc.due_us());
        }
        set(Timer::Emcy, emcy);
        if crate::config::MAX_RPDOS > 0 {
            // (Else never armed: `clear` and the default leave it at `NEVER`.)
            set(Timer::Rpdo, d.rpdo.due_us());
        }
        debug_assert_eq!(other, self.timers.next());
        // The TPDOs keep their own schedule (the hot path reads it directly).
        self.deadline = other.min(d.pdo.due_us());
        // A node without a node-id stays in initialisation (`reset`), so one test says both.
        debug_assert!(d.node_id != UNCONFIGURED || d.nmt == NmtState::Initialising);
        if crate::config::INLINE_HOT_PATHS {
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
        d.stats.resets = d.stats.resets.wrapping_add(1);
        d.node_id = d.pending_node_id;
        d.bitrate = d.pending_bitrate;
        d.cfg.set_node_id(d.node_id);
        d.cfg.set_bitrate_kbps(d.bitrate);
        // The application forgets first: reset node then gives it its stored values back.
        if application {
            d.app.reset();
        }
        d.load_values(application);
        d.emcy.reset();
        d.errctl.reset();
        d.apply_comm_config(now);
        d.pdo.set_active(false, now);
        d.rpdo.set_active(false);
        if d.node_id == UNCONFIGURED {
            // CiA 305: no node-id, no NMT: wait in LSS for one, in LSS waiting for a master to
            // select (DS 305 V2), or in configuration by itself (DSP 305 V1.1 R7:
            // `Features::lss_unconfigured_configures`).
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
            // one out-of-line copy, for less flash (the config.rs list has both figures).
            if crate::config::INLINE_HOT_PATHS {
                self.epilogue_inline();
            } else {
                self.epilogue();
            }
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

    /// The device's own process wrote `raw` (little-endian, the type's bytes only) to
    /// `index`/`sub`: an input it read, as an application's cycle writes its live values. The
    /// value must suit the entry (its type, size and range: [`Abort`] as an SDO write would
    /// get), but access does not count (a read-only input is the process's to change), and
    /// only an object of the application area (0x2000 on) that no service or application rule
    /// owns ([`Hook::None`]) may be written so: [`Abort::UnsupportedAccess`] otherwise (the
    /// communication area's objects, 0x1001 among them, are the services'). A refused value
    /// changes nothing, and a constant ([`od::Access::Const`]) is refused as an SDO write of
    /// it is ([`Abort::ReadOnly`]). A changed
    /// value is a change-of-state event to the TPDOs that map it (the path of
    /// [`Node::update_sample`]). Returns whether the value changed; a node that is off takes
    /// nothing (`Ok(false)`).
    pub fn write_process_value(
        &mut self,
        index: u16,
        sub: u8,
        raw: u32,
        now: Instant,
    ) -> Result<bool, Abort> {
        let d = &mut self.dev;
        let slot = d.od.find(index, sub)?;
        let e = d.od.entry(slot);
        let Some(size) = e.ty.size() else {
            return Err(Abort::UnsupportedAccess);
        };
        if e.hook != Hook::None || e.index < 0x2000 {
            return Err(Abort::UnsupportedAccess);
        }
        // A constant never changes (its EDS `const`), whoever writes.
        if e.access == od::Access::Const {
            return Err(Abort::ReadOnly);
        }
        // Bits beyond the type's bytes would be sent by no PDO and read by no SDO.
        if size < 4 && raw >> (8 * size) != 0 {
            return Err(Abort::InvalidValue);
        }
        e.check(raw)?;
        if !d.powered {
            return Ok(false);
        }
        d.now = now;
        if d.od.get(slot) == raw {
            return Ok(false);
        }
        d.od.set(slot, raw);
        d.pdo.value_changed(slot, true);
        d.run_pdos(now);
        self.epilogue();
        Ok(true)
    }

    /// Handles every deadline that has passed at `now`.
    #[inline]
    pub fn handle_timeout(&mut self, now: Instant) {
        // Fast path for a producing node: while every other deadline is in the future, the
        // steps of the full path would all do nothing but the TPDOs'. (`fast_due` is 0
        // while powered off, unconfigured, initialising or with EMCY work.)
        // (A firmware takes the full path: the same steps, less flash.)
        if crate::config::INLINE_HOT_PATHS && now.0 < self.fast_due {
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
            if crate::config::INLINE_HOT_PATHS
                && now.0 < self.fast_due
                && self.dev.tx.is_empty()
                && self.dev.can_talk(now)
            {
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

    /// Takes the next frame to send. Frames produced during a bit-rate switch are lost, as on
    /// a real bus.
    #[inline]
    pub fn poll_transmit(&mut self) -> Option<Frame> {
        let d = &mut self.dev;
        let f = d.tx.pop()?;
        if d.can_talk(d.now) {
            return Some(f);
        }
        d.poll_transmit_lost()
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

    /// Injects (`active`) or removes a fault the application reports the way its device's
    /// manual says ([`Application::inject`]: its EMCY, error register and reactions).
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
    /// The model's features: constants where the application fixes its description
    /// ([`Application::FIXED`]: the plain firmware, a one-model sensor build).
    #[inline(always)]
    pub fn features(&self) -> &'static Features {
        A::features(self.model)
    }

    /// The product model.
    pub fn model(&self) -> &'static ModelOf<A> {
        self.model
    }

    /// The unit configuration (with the active node-id and bit rate).
    pub fn config(&self) -> &A::Config {
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

    /// Whether the node is powered.
    pub fn powered(&self) -> bool {
        self.powered
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

    /// Frames waiting in the transmit queue.
    pub fn queued(&self) -> usize {
        self.tx.len()
    }

    /// The EMCY producer.
    pub fn emcy(&self) -> &Emcy {
        &self.emcy
    }

    /// The TPDOs.
    pub fn tpdos(&self) -> &Tpdos {
        &self.pdo
    }

    /// The RPDOs.
    pub fn rpdos(&self) -> &Rpdos {
        &self.rpdo
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
}
