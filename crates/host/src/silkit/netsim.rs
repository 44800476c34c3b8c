//! canpos as the CAN network simulator of Vector SIL Kit (issue 32 item 3, docs/SILKIT.md
//! "canpos as the network simulator").
//!
//! SIL Kit's open core models no bus: without a network simulator every frame is confirmed as
//! transmitted at once. Its experimental NetworkSimulator C API lets one participant take over
//! a network: SIL Kit hands it every controller of the network (a descriptor), their mode
//! requests, bit rates and frame requests, and the simulator tells the controllers what
//! happened through an event producer. Here each simulated network is a
//! [`crate::bus::controllers::Network`] on canpos's bus timeline: bit time with stuffing,
//! arbitration, end-of-frame times, acknowledgement only of the frame that won the bus, error
//! counters and bus-off (docs/BUS.md).
//!
//! The C API is bound by hand (`extern "C"` declarations of the few functions used and
//! `#[repr(C)]` structs, every one starting with SIL Kit's versioned struct header) next to
//! [`sys`]'s, resolved from the library [`sys::api`] loaded at run time, so canpos builds and
//! tests without SIL Kit.
//!
//! SIL Kit 5.0.3 crashes the process that simulates when a controller leaves while a send to
//! it is queued (D57); `canpos bus netsim` therefore runs a [`Simulator`] in a worker process
//! it restarts. A [`Simulator`] in another program has no such guard.
//!
//! Time: in synchronised mode the bus time is SIL Kit's simulation time, advanced by the
//! participant's simulation steps; otherwise the simulator's monotonic clock since it started
//! (a driver thread runs the bus). See [`TimeMode`].

use std::collections::BTreeMap;
use std::ffi::{c_char, c_void, CString};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use super::sys::{
    self, Api, ByteVector, CanErrorStateChangeEvent, CanFrame, CanFrameEvent,
    CanFrameTransmitEvent, CanStateChangeEvent, LifecycleConfiguration, ReturnCode, StructHeader,
};
use super::RegistryUri;

use crate::bus::controllers::{
    BusState, ControllerMode, Descriptor, MemberStats, NetCounters, NetEvent, Network, RawFrame,
    TxStatus,
};
use crate::bus::Nanos;

/// The struct ids of the events the simulator produces and the tables it hands SIL Kit
/// (InterfaceIdentifiers.h of SIL Kit 5.0; [`sys`] has those canpos's participants use).
pub mod ids {
    use super::sys::{struct_id, SERVICE_CAN, SERVICE_NETWORK_SIMULATION};
    /// `SilKit_CanFrameTransmitEvent` v2 (with `canId`).
    pub const CAN_FRAME_TRANSMIT_EVENT: u64 = struct_id(SERVICE_CAN, 2, 2);
    /// `SilKit_CanFrameEvent` v1.
    pub const CAN_FRAME_EVENT: u64 = struct_id(SERVICE_CAN, 3, 1);
    /// `SilKit_CanStateChangeEvent` v1.
    pub const CAN_STATE_CHANGE_EVENT: u64 = struct_id(SERVICE_CAN, 4, 1);
    /// `SilKit_CanErrorStateChangeEvent` v1.
    pub const CAN_ERROR_STATE_CHANGE_EVENT: u64 = struct_id(SERVICE_CAN, 5, 1);
    /// `SilKit_Experimental_EventReceivers` v1.
    pub const EVENT_RECEIVERS: u64 = struct_id(SERVICE_NETWORK_SIMULATION, 1, 1);
    /// `SilKit_Experimental_SimulatedNetworkFunctions` v1.
    pub const SIMULATED_NETWORK_FUNCTIONS: u64 = struct_id(SERVICE_NETWORK_SIMULATION, 2, 1);
    /// `SilKit_Experimental_SimulatedCanControllerFunctions` v1.
    pub const SIMULATED_CAN_CONTROLLER_FUNCTIONS: u64 = struct_id(SERVICE_NETWORK_SIMULATION, 3, 1);
}

/// `SilKit_Experimental_EventReceivers`.
#[repr(C)]
struct EventReceivers {
    header: StructHeader,
    num: usize,
    descriptors: *const u64,
}

/// `SilKit_Experimental_NetSim_CanFrameRequest`.
#[repr(C)]
struct CanFrameRequest {
    header: StructHeader,
    frame: *mut CanFrame,
    user_context: *mut c_void,
}

/// `SilKit_Experimental_NetSim_CanConfigureBaudrate`.
#[repr(C)]
struct CanConfigureBaudrate {
    header: StructHeader,
    rate: u32,
    fd_rate: u32,
    xl_rate: u32,
}

/// `SilKit_Experimental_NetSim_CanControllerMode`.
#[repr(C)]
struct CanControllerModeMsg {
    header: StructHeader,
    flags: i32,
    state: i32,
}
const MODE_RESET_ERROR_HANDLING: i32 = 1;
const MODE_CANCEL_TRANSMIT_REQUESTS: i32 = 2;

/// `SilKit_Experimental_SimulatedNetworkFunctions`.
#[repr(C)]
struct SimulatedNetworkFunctions {
    header: StructHeader,
    provide: unsafe extern "C" fn(*mut *mut c_void, *mut *const c_void, u64, *mut c_void),
    removed: unsafe extern "C" fn(u64, *mut c_void),
    set_event_producer: unsafe extern "C" fn(*mut c_void, *mut c_void),
}

/// `SilKit_Experimental_SimulatedCanControllerFunctions`.
#[repr(C)]
struct SimulatedCanControllerFunctions {
    header: StructHeader,
    on_set_baudrate: unsafe extern "C" fn(*mut c_void, *const CanConfigureBaudrate),
    on_frame_request: unsafe extern "C" fn(*mut c_void, *const CanFrameRequest),
    on_set_controller_mode: unsafe extern "C" fn(*mut c_void, *const CanControllerModeMsg),
}

/// `SilKit_TimeSyncService_SimulationStepHandler_t` with an untyped service.
type StepHandler = unsafe extern "C" fn(*mut c_void, *mut c_void, u64, u64);

/// The experimental NetworkSimulator functions (NetworkSimulator.h, EventProducer.h) and the
/// synchronous step handler, resolved from the library [`sys::api`] loaded.
struct NetsimFns {
    create: unsafe extern "C" fn(*mut *mut c_void, *mut sys::Participant) -> ReturnCode,
    simulate_network: unsafe extern "C" fn(
        *mut c_void,
        *const c_char,
        u32,
        *mut c_void,
        *const SimulatedNetworkFunctions,
    ) -> ReturnCode,
    start: unsafe extern "C" fn(*mut c_void) -> ReturnCode,
    produce:
        unsafe extern "C" fn(*mut c_void, *mut StructHeader, *const EventReceivers) -> ReturnCode,
    set_step_handler: unsafe extern "C" fn(
        *mut sys::TimeSyncService,
        *mut c_void,
        StepHandler,
        u64,
    ) -> ReturnCode,
}

impl NetsimFns {
    fn resolve(api: &Api) -> Result<NetsimFns, sys::Error> {
        // SAFETY: each type is the C declaration of that function in SIL Kit 5's headers
        // (sys::api refused other majors).
        unsafe {
            Ok(NetsimFns {
                create: api.symbol(b"SilKit_Experimental_NetworkSimulator_Create\0")?,
                simulate_network: api
                    .symbol(b"SilKit_Experimental_NetworkSimulator_SimulateNetwork\0")?,
                start: api.symbol(b"SilKit_Experimental_NetworkSimulator_Start\0")?,
                produce: api.symbol(b"SilKit_Experimental_CanEventProducer_Produce\0")?,
                set_step_handler: api
                    .symbol(b"SilKit_TimeSyncService_SetSimulationStepHandler\0")?,
            })
        }
    }
}

/// The top byte of a frame request's user context that marks it as a simulation time stamp
/// (D40): `0xC0` is never the top byte of a user-space pointer (x86-64 and AArch64 user
/// addresses are below 2^48), so a context from another SIL Kit participant is never taken
/// for a time.
pub const TIME_CONTEXT_TAG: u64 = 0xC0 << 56;
const TIME_MASK: u64 = (1 << 56) - 1;

/// The user context with which a canpos participant in synchronised mode sends a frame at
/// simulation time `t` ns (`t` < 2^56 ns, 2.28 years), so that the simulator enters it into
/// the bus at that time (D40).
pub fn context_of_time(t: Nanos) -> u64 {
    TIME_CONTEXT_TAG | (t & TIME_MASK)
}

/// The simulation time stamped in a user context by [`context_of_time`], if it is one.
pub fn time_of_context(context: u64) -> Option<Nanos> {
    (context & !TIME_MASK == TIME_CONTEXT_TAG).then_some(context & TIME_MASK)
}

/// How the simulator keeps time.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TimeMode {
    /// The simulator's monotonic clock since it started (a rig with hardware in the loop; the
    /// participants are not synchronised).
    Wall,
    /// SIL Kit's simulation time: the simulator is a synchronised participant with simulation
    /// steps of this many ns; its lifecycle coordinated (a system controller starts and stops
    /// it) or autonomous.
    Sync {
        /// Step, ns.
        step: Nanos,
        /// Coordinated lifecycle.
        coordinated: bool,
    },
}

/// One network to simulate.
#[derive(Clone, Debug)]
pub struct NetworkSpec {
    /// SIL Kit network name.
    pub name: String,
    /// Bit rate, kbit/s (CiA 301).
    pub kbps: u32,
}

/// A frame request waiting for its time (synchronised mode).
#[derive(Debug)]
struct Waiting {
    at: Nanos,
    seq: u64,
    desc: Descriptor,
    id: u32,
    flags: u32,
    dlc: u16,
    len: u8,
    data: [u8; 8],
    /// The request was longer than 8 bytes (judged when submitted).
    too_long: usize,
    context: u64,
}

struct NetState {
    name: CString,
    net: Network,
    producer: *mut c_void,
    waiting: Vec<Waiting>,
}

struct Shared {
    nets: Vec<NetState>,
    /// Controller contexts handed to SIL Kit (kept until the participant is gone).
    // Boxed: SIL Kit holds their addresses, which must not move when the Vec grows.
    #[allow(clippy::vec_box)]
    ctrl_ctx: Vec<Box<CtrlCtx>>,
    seq: u64,
    /// Synchronised mode: the simulation step's time; wall mode: unused.
    sync_now: Option<Nanos>,
    stopped: bool,
}

struct Core {
    api: &'static Api,
    fns: NetsimFns,
    mode: TimeMode,
    start: Instant,
    /// Added to bus times in what SIL Kit's controllers are told: 0 in synchronised mode (bus
    /// time is simulation time); in wall mode the Unix time of `start`, so a receiver reads
    /// wall-clock end-of-frame times (D41).
    epoch: Nanos,
    shared: Mutex<Shared>,
    wake: Condvar,
}

// SAFETY: the raw pointers in Shared (event producers) are SIL Kit objects that SIL Kit lets
// any thread use; every access goes through the mutex.
unsafe impl Send for Core {}
// SAFETY: as above.
unsafe impl Sync for Core {}

struct NetCtx {
    core: *const Core,
    index: usize,
}

struct CtrlCtx {
    core: *const Core,
    index: usize,
    desc: Descriptor,
}

static NETWORK_FUNCTIONS: SimulatedNetworkFunctions = SimulatedNetworkFunctions {
    header: StructHeader::new(ids::SIMULATED_NETWORK_FUNCTIONS),
    provide: on_provide,
    removed: on_removed,
    set_event_producer: on_set_event_producer,
};

static CAN_CONTROLLER_FUNCTIONS: SimulatedCanControllerFunctions =
    SimulatedCanControllerFunctions {
        header: StructHeader::new(ids::SIMULATED_CAN_CONTROLLER_FUNCTIONS),
        on_set_baudrate,
        on_frame_request,
        on_set_controller_mode,
    };

impl Core {
    fn lock(&self) -> MutexGuard<'_, Shared> {
        // A panic in a callback must not take the simulator down with poisoned state errors.
        self.shared.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// The bus time of a request or mode change arriving now.
    fn now(&self, s: &Shared) -> Nanos {
        match self.mode {
            TimeMode::Wall => self.start.elapsed().as_nanos() as Nanos,
            TimeMode::Sync { .. } => s.sync_now.unwrap_or(0),
        }
    }

    /// Sends what a network's controllers are told.
    fn produce(&self, net: &NetState, events: &[NetEvent]) {
        if net.producer.is_null() {
            return;
        }
        for e in events {
            match e {
                NetEvent::Frame {
                    senders,
                    receivers,
                    frame,
                    at,
                } => {
                    let data = frame.data();
                    let mut flags_v = 0;
                    if frame.is_extended() {
                        flags_v |= sys::CAN_FLAG_IDE;
                    }
                    if frame.is_remote() {
                        flags_v |= sys::CAN_FLAG_RTR;
                    }
                    let mut cf = CanFrame {
                        header: StructHeader::new(sys::CAN_FRAME_ID),
                        id: frame.id(),
                        flags: flags_v,
                        dlc: u16::from(frame.dlc()),
                        sdt: 0,
                        vcid: 0,
                        af: 0,
                        data: ByteVector {
                            data: data.as_ptr(),
                            size: data.len(),
                        },
                    };
                    if !receivers.is_empty() {
                        let mut ev = CanFrameEvent {
                            header: StructHeader::new(ids::CAN_FRAME_EVENT),
                            timestamp: *at + self.epoch,
                            frame: &mut cf,
                            direction: 2,
                            user_context: std::ptr::null_mut(),
                        };
                        self.produce_one(net, &mut ev.header, receivers);
                    }
                    for &(d, context) in senders {
                        // As SIL Kit's own bus does: the sender gets its frame back as sent,
                        // then the acknowledgement.
                        let mut ev = CanFrameEvent {
                            header: StructHeader::new(ids::CAN_FRAME_EVENT),
                            timestamp: *at + self.epoch,
                            frame: &mut cf,
                            direction: 1,
                            user_context: context as *mut c_void,
                        };
                        self.produce_one(net, &mut ev.header, &[d]);
                        self.transmit(net, d, context, frame.id(), 1, *at + self.epoch);
                    }
                }
                NetEvent::NotSent {
                    to,
                    context,
                    id,
                    status,
                    at,
                } => {
                    let s = match status {
                        TxStatus::Transmitted => 1,
                        TxStatus::Canceled => 2,
                        TxStatus::QueueFull => 4,
                    };
                    self.transmit(net, *to, *context, *id, s, *at + self.epoch);
                }
                NetEvent::Status {
                    to,
                    mode,
                    error,
                    at,
                } => {
                    // SIL Kit's CAN event producer sends a controller status with both states,
                    // taking the one not in the event from the last event it produced for any
                    // controller of the network. So the mode goes first to no receiver (it only
                    // sets that memory), then the error state to the controller: one status
                    // with both of this controller's states.
                    let mut st = CanStateChangeEvent {
                        header: StructHeader::new(ids::CAN_STATE_CHANGE_EVENT),
                        timestamp: *at + self.epoch,
                        state: *mode as i32,
                    };
                    self.produce_one(net, &mut st.header, &[]);
                    let mut er = CanErrorStateChangeEvent {
                        header: StructHeader::new(ids::CAN_ERROR_STATE_CHANGE_EVENT),
                        timestamp: *at + self.epoch,
                        error_state: match error {
                            None => 0,
                            Some(BusState::ErrorActive) => 1,
                            Some(BusState::ErrorPassive) => 2,
                            Some(BusState::BusOff) => 3,
                        },
                    };
                    self.produce_one(net, &mut er.header, &[*to]);
                }
            }
        }
    }

    fn transmit(
        &self,
        net: &NetState,
        to: Descriptor,
        context: u64,
        id: u32,
        status: i32,
        at: Nanos,
    ) {
        let mut ev = CanFrameTransmitEvent {
            header: StructHeader::new(ids::CAN_FRAME_TRANSMIT_EVENT),
            user_context: context as *mut c_void,
            timestamp: at,
            status,
            can_id: id,
        };
        self.produce_one(net, &mut ev.header, &[to]);
    }

    fn produce_one(&self, net: &NetState, msg: &mut StructHeader, to: &[Descriptor]) {
        let receivers = EventReceivers {
            header: StructHeader::new(ids::EVENT_RECEIVERS),
            num: to.len(),
            descriptors: if to.is_empty() {
                [0u64].as_ptr()
            } else {
                to.as_ptr()
            },
        };
        // SAFETY: the producer is the one SIL Kit gave for this network; the message and the
        // receivers live across the call, which copies them.
        let rc = unsafe { (self.fns.produce)(net.producer, msg, &receivers) };
        if let Err(e) = self
            .api
            .check("SilKit_Experimental_CanEventProducer_Produce", rc)
        {
            tracing::warn!(network = ?net.name, "{e}");
        }
    }

    /// Synchronised mode: enters the requests stamped before `t` in time order, runs the bus
    /// to just before `t` and tells the controllers.
    fn step(&self, t: Nanos) {
        if self.mode == TimeMode::Wall {
            // Steps come back to back on SIL Kit's I/O thread (this participant is alone in
            // its time synchronisation); pausing here until the next event, at most a step,
            // paces them to the wall clock. Frame requests are handled between steps.
            let (_, next) = self.run_to_now();
            let now = self.start.elapsed().as_nanos() as Nanos;
            let wait = next.map_or(WALL_STEP, |n| n.saturating_sub(now).min(WALL_STEP));
            if wait > 0 {
                std::thread::sleep(Duration::from_nanos(wait));
            }
            return;
        }
        let mut s = self.lock();
        s.sync_now = Some(t);
        let Shared { nets, .. } = &mut *s;
        let mut out = Vec::new();
        for ns in nets.iter_mut() {
            out.clear();
            ns.waiting.sort_by_key(|w| (w.at, w.seq));
            let ready = ns.waiting.partition_point(|w| w.at < t);
            let batch: Vec<Waiting> = ns.waiting.drain(..ready).collect();
            for w in batch {
                // Just before its time: the requests stamped with one time all take part in
                // the arbitration at that time (advancing to it would start the first alone).
                ns.net.advance_to(w.at.saturating_sub(1), &mut out);
                submit(&mut ns.net, &w, &mut out);
            }
            ns.net.advance_to(t.saturating_sub(1), &mut out);
            // A frame that started before `t` is settled: report it now, at its end of frame,
            // though that is after `t`. A receiver then has every frame that ended before its
            // step when SIL Kit grants the step, provided the step is shorter than the
            // shortest frame (D40); requests stamped up to that end only queue for the next
            // arbitration.
            if let Some((start, end)) = ns.net.settled_frame() {
                if start < t {
                    ns.net.advance_to(end, &mut out);
                }
            }
            self.produce(ns, &out);
        }
    }

    /// Wall mode: runs every network to now and tells the controllers; returns when the next
    /// thing falls due.
    fn run_to_now(&self) -> (bool, Option<Nanos>) {
        let mut s = self.lock();
        let now = self.now(&s);
        let mut out = Vec::new();
        let mut next: Option<Nanos> = None;
        for ns in s.nets.iter_mut() {
            out.clear();
            ns.net.advance_to(now, &mut out);
            self.produce(ns, &out);
            if let Some(t) = ns.net.next_event() {
                next = Some(next.map_or(t, |n: Nanos| n.min(t)));
            }
        }
        (s.stopped, next)
    }
}

fn submit(net: &mut Network, w: &Waiting, out: &mut Vec<NetEvent>) {
    let mut long = [0u8; 9];
    let data: &[u8] = if w.too_long > 8 {
        // Only the length matters to the judgement: 9 bytes stand for any longer field.
        &long[..]
    } else {
        long[..usize::from(w.len)].copy_from_slice(&w.data[..usize::from(w.len)]);
        &long[..usize::from(w.len)]
    };
    let raw = RawFrame {
        id: w.id,
        extended: w.flags & sys::CAN_FLAG_IDE != 0,
        remote: w.flags & sys::CAN_FLAG_RTR != 0,
        fd_or_xl: w.flags & (sys::CAN_FLAG_FDF | sys::CAN_FLAG_XLF) != 0,
        dlc: w.dlc,
        data,
    };
    net.request(w.desc, &raw, w.context, w.at, out);
}

/// Runs `f` on the core behind a callback context, catching a panic (unwinding into C++ is
/// undefined behaviour).
fn guarded(what: &str, f: impl FnOnce()) {
    if std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)).is_err() {
        tracing::error!("netsim: panic in SIL Kit callback {what} (ignored)");
    }
}

unsafe extern "C" fn on_provide(
    out_ctrl: *mut *mut c_void,
    out_fns: *mut *const c_void,
    desc: u64,
    net: *mut c_void,
) {
    guarded("ProvideSimulatedController", || {
        // SAFETY: `net` is the NetCtx this module registered; the Core outlives the participant.
        let nctx = unsafe { &*(net as *const NetCtx) };
        let core = unsafe { &*nctx.core };
        let mut s = core.lock();
        let known = s.nets[nctx.index].net.attach(desc);
        if !known {
            tracing::warn!(
                network = ?s.nets[nctx.index].name,
                descriptor = desc,
                "controller refused (network full or descriptor known): its frames are dropped"
            );
        } else {
            tracing::info!(network = ?s.nets[nctx.index].name, descriptor = desc, "controller joined");
        }
        let ctx = Box::new(CtrlCtx {
            core: nctx.core,
            index: nctx.index,
            desc,
        });
        let p = &*ctx as *const CtrlCtx as *mut c_void;
        // Bounded: the network holds at most MAX_CONTROLLERS; a refused one costs its box.
        s.ctrl_ctx.push(ctx);
        // SAFETY: SIL Kit passes valid out pointers.
        unsafe {
            *out_ctrl = p;
            *out_fns = &CAN_CONTROLLER_FUNCTIONS as *const _ as *const c_void;
        }
    });
}

unsafe extern "C" fn on_removed(desc: u64, net: *mut c_void) {
    guarded("SimulatedControllerRemoved", || {
        // SAFETY: as in on_provide.
        let nctx = unsafe { &*(net as *const NetCtx) };
        let core = unsafe { &*nctx.core };
        let mut s = core.lock();
        let ns = &mut s.nets[nctx.index];
        ns.net.detach(desc);
        ns.waiting.retain(|w| w.desc != desc);
        tracing::info!(network = ?ns.name, descriptor = desc, "controller left");
    });
}

unsafe extern "C" fn on_set_event_producer(producer: *mut c_void, net: *mut c_void) {
    guarded("SetEventProducer", || {
        // SAFETY: as in on_provide.
        let nctx = unsafe { &*(net as *const NetCtx) };
        let core = unsafe { &*nctx.core };
        core.lock().nets[nctx.index].producer = producer;
    });
}

unsafe extern "C" fn on_set_baudrate(ctrl: *mut c_void, msg: *const CanConfigureBaudrate) {
    guarded("OnSetBaudrate", || {
        // SAFETY: `ctrl` is a CtrlCtx of this module, `msg` valid for the call.
        let c = unsafe { &*(ctrl as *const CtrlCtx) };
        let core = unsafe { &*c.core };
        let rate = unsafe { (*msg).rate };
        let mut s = core.lock();
        let now = core.now(&s);
        let ns = &mut s.nets[c.index];
        if rate != 0 && rate != ns.net.bitrate_kbps() * 1000 {
            tracing::warn!(network = ?ns.name, descriptor = c.desc, rate,
                "controller set another bit rate than the network's: cut off");
        }
        ns.net.set_bitrate(c.desc, rate, now);
        core.wake.notify_all();
    });
}

unsafe extern "C" fn on_set_controller_mode(ctrl: *mut c_void, msg: *const CanControllerModeMsg) {
    guarded("OnSetControllerMode", || {
        // SAFETY: as in on_set_baudrate.
        let c = unsafe { &*(ctrl as *const CtrlCtx) };
        let core = unsafe { &*c.core };
        let (flags_v, state) = unsafe { ((*msg).flags, (*msg).state) };
        let Some(mode) = ControllerMode::from_raw(state) else {
            tracing::warn!(
                descriptor = c.desc,
                state,
                "unknown controller mode ignored"
            );
            return;
        };
        let mut s = core.lock();
        let now = core.now(&s);
        let ns = &mut s.nets[c.index];
        let mut out = Vec::new();
        if core.mode == TimeMode::Wall {
            ns.net.advance_to(now, &mut out);
        }
        ns.net.set_mode(
            c.desc,
            mode,
            flags_v & MODE_RESET_ERROR_HANDLING != 0,
            flags_v & MODE_CANCEL_TRANSMIT_REQUESTS != 0,
            now,
            &mut out,
        );
        core.produce(ns, &out);
        core.wake.notify_all();
    });
}

unsafe extern "C" fn on_frame_request(ctrl: *mut c_void, msg: *const CanFrameRequest) {
    guarded("OnFrameRequest", || {
        // SAFETY: as in on_set_baudrate; the frame and its data are valid for the call and
        // copied here.
        let c = unsafe { &*(ctrl as *const CtrlCtx) };
        let core = unsafe { &*c.core };
        let req = unsafe { &*msg };
        if req.frame.is_null() {
            return;
        }
        let f = unsafe { &*req.frame };
        let n = f.data.size;
        let mut data = [0u8; 8];
        if n <= 8 && n > 0 && !f.data.data.is_null() {
            data[..n].copy_from_slice(unsafe { std::slice::from_raw_parts(f.data.data, n) });
        }
        let context = req.user_context as u64;
        let mut s = core.lock();
        let now = core.now(&s);
        let seq = s.seq;
        s.seq += 1;
        let ns = &mut s.nets[c.index];
        let at = match core.mode {
            TimeMode::Wall => now,
            // A canpos participant stamps its frames with its simulation time (D40); another
            // participant's frame enters the bus at the simulator's next step.
            TimeMode::Sync { .. } => time_of_context(context).unwrap_or(now),
        };
        let w = Waiting {
            at,
            seq,
            desc: c.desc,
            id: f.id,
            flags: f.flags,
            dlc: f.dlc,
            len: n.min(8) as u8,
            data,
            too_long: if n > 8 { n } else { 0 },
            context,
        };
        let mut out = Vec::new();
        match core.mode {
            TimeMode::Wall => {
                ns.net.advance_to(now, &mut out);
                submit(&mut ns.net, &w, &mut out);
                core.produce(ns, &out);
                core.wake.notify_all();
            }
            TimeMode::Sync { .. } => {
                // Bounded like a controller's queue: a flood beyond it is refused at once.
                if ns.waiting.iter().filter(|x| x.desc == c.desc).count()
                    >= 4 * crate::bus::DEFAULT_TX_DEPTH
                {
                    out.push(NetEvent::NotSent {
                        to: c.desc,
                        context,
                        id: f.id,
                        status: TxStatus::QueueFull,
                        at: now,
                    });
                    core.produce(ns, &out);
                } else {
                    ns.waiting.push(w);
                }
            }
        }
    });
}

unsafe extern "C" fn on_step(ctx: *mut c_void, _ts: *mut c_void, now: u64, _duration: u64) {
    guarded("SimulationStep", || {
        // SAFETY: `ctx` is the Core, alive while the participant is.
        let core = unsafe { &*(ctx as *const Core) };
        core.step(now);
    });
}

unsafe extern "C" fn on_stop(ctx: *mut c_void, _lc: *mut sys::LifecycleService) {
    guarded("Stop", || {
        // SAFETY: as in on_step.
        let core = unsafe { &*(ctx as *const Core) };
        core.lock().stopped = true;
        core.wake.notify_all();
    });
}

/// A network's figures.
#[derive(Clone, Debug)]
pub struct NetworkReport {
    /// Its name.
    pub name: String,
    /// Bus time reached, ns.
    pub reached: Nanos,
    /// Counters.
    pub counters: NetCounters,
    /// Load over the last second (fraction) and frames/s.
    pub load: (f64, f64),
    /// Each controller: descriptor, mode, bus counters.
    pub controllers: Vec<(Descriptor, ControllerMode, Option<MemberStats>)>,
    /// Controllers that left, with their last mode and counters.
    pub departed: Vec<(Descriptor, ControllerMode, Option<MemberStats>)>,
}

/// The simulation step in wall mode: how often the bus is run to the wall clock and what
/// happened on it is told (the times told are exact; delivery lags by up to a step).
pub const WALL_STEP: Nanos = 500_000;

/// Joins the registry as `name` with canpos's participant configuration (D35).
fn join(
    api: &'static Api,
    name: &str,
    registry: &RegistryUri,
) -> Result<*mut sys::Participant, sys::Error> {
    super::check_name("participant name", name).map_err(sys::Error::BadArgument)?;
    let config = super::PARTICIPANT_CONFIGURATION;
    let cname = CString::new(name).map_err(|e| sys::Error::BadArgument(e.to_string()))?;
    let curi =
        CString::new(registry.to_string()).map_err(|e| sys::Error::BadArgument(e.to_string()))?;
    let ccfg = CString::new(config).expect("no NUL");
    let mut cfg = std::ptr::null_mut();
    // SAFETY: out-pointer and a NUL-terminated string.
    api.check("SilKit_ParticipantConfiguration_FromString", unsafe {
        (api.participant_configuration_from_string)(&mut cfg, ccfg.as_ptr())
    })?;
    let mut raw = std::ptr::null_mut();
    // SAFETY: valid configuration, NUL-terminated strings, out-pointer.
    let rc = unsafe { (api.participant_create)(&mut raw, cfg, cname.as_ptr(), curi.as_ptr()) };
    // SAFETY: the participant keeps its own copy of the configuration.
    unsafe { (api.participant_configuration_destroy)(cfg) };
    api.check("SilKit_Participant_Create", rc)
        .map_err(|e| match e {
            sys::Error::Call { code, message, .. } => sys::Error::Call {
                call: "SilKit_Participant_Create",
                code,
                code_name: sys::return_code_name(code),
                message: format!("participant `{name}` at {registry}: {message}"),
            },
            e => e,
        })?;
    Ok(raw)
}

/// The running simulator: one SIL Kit participant simulating its networks.
pub struct Simulator {
    core: Arc<Core>,
    participant: *mut sys::Participant,
    lifecycle: *mut sys::LifecycleService,
    // Boxed: SIL Kit holds their addresses.
    #[allow(clippy::vec_box)]
    _nets: Vec<Box<NetCtx>>,
}

// SAFETY: SIL Kit's handles may be used from any thread (its C API is thread-safe).
unsafe impl Send for Simulator {}

impl Simulator {
    /// Joins the registry at `registry` as `participant_name` and takes over `networks` as
    /// their CAN network simulator.
    pub fn start(
        api: &'static Api,
        registry: &RegistryUri,
        participant_name: &str,
        networks: &[NetworkSpec],
        mode: TimeMode,
    ) -> Result<Simulator, String> {
        if networks.is_empty() {
            return Err("no network to simulate".into());
        }
        let fns = NetsimFns::resolve(api).map_err(|e| e.to_string())?;
        let mut names = BTreeMap::new();
        let mut nets = Vec::new();
        for n in networks {
            super::check_name("network name", &n.name)?;
            if names.insert(n.name.clone(), ()).is_some() {
                return Err(format!("network {} given twice", n.name));
            }
            nets.push(NetState {
                name: CString::new(n.name.clone()).expect("checked: printable ASCII"),
                net: Network::new(n.kbps)?,
                producer: std::ptr::null_mut(),
                waiting: Vec::new(),
            });
        }
        let core = Arc::new(Core {
            api,
            fns,
            mode,
            start: Instant::now(),
            epoch: match mode {
                TimeMode::Wall => std::time::SystemTime::now()
                    .duration_since(std::time::UNIX_EPOCH)
                    .map_or(0, |d| d.as_nanos() as Nanos),
                TimeMode::Sync { .. } => 0,
            },
            shared: Mutex::new(Shared {
                nets,
                ctrl_ctx: Vec::new(),
                seq: 0,
                sync_now: None,
                stopped: false,
            }),
            wake: Condvar::new(),
        });
        let raw = join(api, participant_name, registry).map_err(|e| e.to_string())?;
        let mut sim = Simulator {
            core: core.clone(),
            participant: raw,
            lifecycle: std::ptr::null_mut(),
            _nets: Vec::new(),
        };
        let err = |e: sys::Error| e.to_string();
        let core_ptr = Arc::as_ptr(&core) as *mut c_void;
        let f = &core.fns;
        // SAFETY: handles from SIL Kit; contexts (Core, NetCtx) live as long as `sim`, which
        // destroys the participant (and so every callback) before dropping them.
        unsafe {
            let lc_conf = LifecycleConfiguration {
                header: StructHeader::new(sys::LIFECYCLE_CONFIGURATION_ID),
                operation_mode: match mode {
                    TimeMode::Sync {
                        coordinated: true, ..
                    } => sys::OPERATION_MODE_COORDINATED,
                    _ => sys::OPERATION_MODE_AUTONOMOUS,
                },
            };
            let mut lc = std::ptr::null_mut();
            api.check(
                "SilKit_LifecycleService_Create",
                (api.lifecycle_service_create)(&mut lc, raw, &lc_conf),
            )
            .map_err(err)?;
            sim.lifecycle = lc;
            api.check(
                "SilKit_LifecycleService_SetStopHandler",
                (api.lifecycle_service_set_stop_handler)(lc, core_ptr, on_stop),
            )
            .map_err(err)?;
            // Both modes step on SIL Kit's I/O thread, where its discovery and frame-request
            // callbacks run too, so producing never races SIL Kit's table of controllers (D41).
            // SIL Kit copies the event (Produce returns with nothing of canpos's kept) but
            // posts every targeted send with a raw pointer to its per-controller target, freed
            // when that controller leaves: a controller leaving while sends for it are queued
            // crashes SIL Kit 5.0.3 whatever thread produced them, and a removal already queued
            // on this thread runs before sends produced now (D57: `canpos bus netsim` restarts
            // the process that runs this). Wall mode paces its steps itself.
            {
                let step = match mode {
                    TimeMode::Sync { step, .. } => step,
                    TimeMode::Wall => WALL_STEP,
                };
                let mut ts = std::ptr::null_mut();
                api.check(
                    "SilKit_TimeSyncService_Create",
                    (api.time_sync_service_create)(&mut ts, lc),
                )
                .map_err(err)?;
                api.check(
                    "SilKit_TimeSyncService_SetSimulationStepHandler",
                    (f.set_step_handler)(ts, core_ptr, on_step, step),
                )
                .map_err(err)?;
            }
            let mut netsim = std::ptr::null_mut();
            api.check(
                "SilKit_Experimental_NetworkSimulator_Create",
                (f.create)(&mut netsim, raw),
            )
            .map_err(err)?;
            let nnets = core.lock().nets.len();
            for index in 0..nnets {
                let nctx = Box::new(NetCtx {
                    core: Arc::as_ptr(&core),
                    index,
                });
                let np = &*nctx as *const NetCtx as *mut c_void;
                sim._nets.push(nctx);
                let net_name = core.lock().nets[index].name.clone();
                api.check(
                    "SilKit_Experimental_NetworkSimulator_SimulateNetwork",
                    (f.simulate_network)(
                        netsim,
                        net_name.as_ptr(),
                        1, // SilKit_NetworkType_CAN
                        np,
                        &NETWORK_FUNCTIONS,
                    ),
                )
                .map_err(err)?;
            }
            api.check(
                "SilKit_Experimental_NetworkSimulator_Start",
                (f.start)(netsim),
            )
            .map_err(err)?;
            api.check(
                "SilKit_LifecycleService_StartLifecycle",
                (api.lifecycle_service_start_lifecycle)(lc),
            )
            .map_err(err)?;
        }
        Ok(sim)
    }

    /// Whether SIL Kit stopped the participant (a system controller's stop, or an error).
    pub fn is_stopped(&self) -> bool {
        self.core.lock().stopped
    }

    /// Each network's figures.
    pub fn report(&self) -> Vec<NetworkReport> {
        let mut s = self.core.lock();
        s.nets
            .iter_mut()
            .map(|ns| NetworkReport {
                name: ns.name.to_string_lossy().into_owned(),
                reached: ns.net.reached(),
                counters: ns.net.counters(),
                load: ns.net.load(),
                controllers: ns.net.controllers(),
                departed: ns.net.departed().to_vec(),
            })
            .collect()
    }
}

impl Drop for Simulator {
    fn drop(&mut self) {
        let api = self.core.api;
        if !self.lifecycle.is_null() {
            let reason = c"canpos bus netsim stops";
            // SAFETY: a live lifecycle handle.
            let _ = unsafe { (api.lifecycle_service_stop)(self.lifecycle, reason.as_ptr()) };
            // A graceful end (the others are told the simulator left, not that it vanished):
            // wait for the lifecycle to complete, at most 5 s; the wait goes on in its thread
            // if SIL Kit hangs, and the participant is destroyed regardless.
            let (tx, rx) = std::sync::mpsc::channel();
            let lc = self.lifecycle as usize;
            let _ = std::thread::Builder::new()
                .name("netsim-stop".into())
                .spawn(move || {
                    let mut state = 0i16;
                    // SAFETY: the handle stays valid until the participant is destroyed,
                    // which waits for this answer or its timeout.
                    let _ = unsafe {
                        (api.lifecycle_service_wait_for_lifecycle_to_complete)(
                            lc as *mut sys::LifecycleService,
                            &mut state,
                        )
                    };
                    let _ = tx.send(state);
                });
            let _ = rx.recv_timeout(Duration::from_secs(5));
        }
        {
            self.core.lock().stopped = true;
            self.core.wake.notify_all();
        }
        // Destroyed before the contexts (`_nets`, the core) its callbacks use.
        // SAFETY: created by `join`, destroyed once.
        let rc = unsafe { (api.participant_destroy)(self.participant) };
        if let Err(e) = api.check("SilKit_Participant_Destroy", rc) {
            tracing::warn!("leaving SIL Kit: {e}");
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn struct_ids_are_silkit_5s() {
        // SK_ID_MAKE(Can, SilKit_CanFrameTransmitEvent): 'S' 'K', service 1, type 2, version 2.
        assert_eq!(ids::CAN_FRAME_TRANSMIT_EVENT, 0x534B_0102_0200_0000);
        assert_eq!(ids::SIMULATED_NETWORK_FUNCTIONS, 0x534B_0802_0100_0000);
        assert_eq!(
            ids::SIMULATED_CAN_CONTROLLER_FUNCTIONS,
            0x534B_0803_0100_0000
        );
        assert_eq!(ids::EVENT_RECEIVERS, 0x534B_0801_0100_0000);
    }

    #[test]
    fn layouts_match_the_c_headers() {
        // pack(8) on x86-64: the sizes and offsets gcc gives for NetworkSimulator.h /
        // EventProducer.h.
        assert_eq!(std::mem::size_of::<EventReceivers>(), 48);
        assert_eq!(std::mem::offset_of!(CanFrameRequest, user_context), 40);
        assert_eq!(std::mem::offset_of!(CanConfigureBaudrate, xl_rate), 40);
        assert_eq!(std::mem::offset_of!(CanControllerModeMsg, state), 36);
        assert_eq!(std::mem::size_of::<SimulatedNetworkFunctions>(), 56);
        assert_eq!(std::mem::size_of::<SimulatedCanControllerFunctions>(), 56);
    }

    #[test]
    fn time_contexts_round_trip_and_pointers_are_not_times() {
        assert_eq!(time_of_context(context_of_time(0)), Some(0));
        assert_eq!(
            time_of_context(context_of_time(123_456_789)),
            Some(123_456_789)
        );
        assert_eq!(time_of_context(0), None);
        assert_eq!(time_of_context(0x7fff_1234_5678), None);
        assert_eq!(time_of_context(u64::MAX), None);
    }
}
