//! A canpos [`Transport`] on a SIL Kit CAN network: one participant with one CAN controller
//! (`silkit://HOST:PORT/NETWORK`, docs/SILKIT.md).
//!
//! **Time modes.** [`TimeMode::Wall`]: no lifecycle and no time synchronisation; frames carry
//! the wall-clock time they were received at (SIL Kit's own timestamp is undefined then).
//! [`TimeMode::Sync`]: a coordinated lifecycle (a system controller starts and stops it) and a
//! time-synchronisation service stepping by a fixed step. The simulation time is SIL Kit's:
//! the transport's [`SimClock`] is stepped to each step's start, a runtime on the transport
//! ([`Transport::join_clock`]) processes every event up to it before the step completes, and
//! frames from the others are handed over at the first step after their SIL Kit timestamp
//! (all of them have arrived by then; one stamped with the current step may not have). So the
//! same scenario gives the same frames at the same simulated times, run after run (D36).
//!
//! **Faults.** A frame SIL Kit hands over that classic CAN cannot carry (more than 8 bytes,
//! CAN FD or XL) is dropped and counted, with a WARN; a frame canpos is asked to send always
//! fits (canpos frames are classic). The lifecycle stopping or aborting ends the transport
//! with that reason; see [`super`] for the registry.

use std::collections::VecDeque;
use std::ffi::{c_void, CStr, CString};
use std::io;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, Weak};
use std::time::{Duration, SystemTime};

use canpos_stack::Frame;
use crossbeam_channel::{Receiver, Sender};

use super::rejoin::{self, Joined, Link, Watch};
use super::sys::{self, Api};
use super::{check_name, Error, Participant, RegistryUri};
use crate::can::{RxFrame, Transport};
use crate::clock::{Horizon, SimClock, Slot};

/// Frames received and not yet taken by the transport's user; more are dropped and counted
/// ([`Transport::dropped`]), as a controller's receive FIFO loses them.
pub const RX_QUEUE: usize = 4096;
/// Frames of later steps held in synchronised mode; more are dropped and counted.
pub const HELD_MAX: usize = 65_536;
/// How long a participant stays after its last send before it leaves (its frames are written
/// to the peers by SIL Kit's own thread).
pub const LINGER: Duration = Duration::from_millis(100);
/// How long a synchronised participant waits for the simulation to start before it says so.
pub const START_WAIT_WARN: Duration = Duration::from_secs(5);
/// The step of synchronised mode when none is given: 1 ms (a TMI's fastest TPDO period).
pub const DEFAULT_STEP: Duration = Duration::from_millis(1);

/// How the participant's time runs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TimeMode {
    /// The wall clock; no lifecycle (what a rig with hardware in the loop runs).
    Wall,
    /// SIL Kit's simulation time in steps of this length, under a system controller.
    Sync {
        /// The step.
        step: Duration,
    },
}

/// Where and as whom to join.
#[derive(Clone, Debug)]
pub struct Options {
    /// The registry.
    pub registry: RegistryUri,
    /// The CAN network's name.
    pub network: String,
    /// The participant's name (unique in the simulation).
    pub participant: String,
    /// The time mode.
    pub time: TimeMode,
    /// The bit rate the controller announces (kbit/s), if known.
    pub bitrate_kbps: Option<u32>,
}

/// State the SIL Kit handlers share with the transport (they run on SIL Kit's threads).
struct Shared {
    api: &'static Api,
    participant: String,
    /// `None` once the transport ended (the receiver then reports disconnected).
    tx: Mutex<Option<Sender<RxFrame>>>,
    dead: Mutex<Option<String>>,
    dropped: AtomicU64,
    not_classic: AtomicU64,
    sync: Option<SyncState>,
    /// The lifecycle service (synchronised mode), as an address.
    lifecycle: std::sync::atomic::AtomicUsize,
    /// The transport is being dropped: its lifecycle must not be started any more.
    left: AtomicBool,
    /// The registry's departures, for the watcher thread (`rejoin`).
    watch: Arc<Watch>,
}

/// Synchronised mode: frames held for their step, the clock, the runtime's horizon.
struct SyncState {
    clock: SimClock,
    held: Mutex<VecDeque<(u64, Frame)>>,
    /// The horizon of the runtime that joined the clock, if one did.
    runtime: Mutex<Option<Weak<Slot>>>,
    /// The runtime has held a finite horizon once (it started).
    runtime_started: AtomicBool,
    /// Step starts for the stepper thread; `None` ends it.
    steps: Sender<Option<u64>>,
    /// Frames sent before the first step (a sensor's boot-up at power-on), sent at its start
    /// in their order; `None` from then on.
    early: Mutex<Option<Vec<Frame>>>,
}

impl Shared {
    /// Ends the transport (its receiver reports disconnected, `why` as the reason); `loud`:
    /// a WARN, for what the user did not ask for.
    fn end_with(&self, why: String, loud: bool) {
        let mut dead = self.dead.lock().unwrap_or_else(|e| e.into_inner());
        if dead.is_none() {
            if loud {
                tracing::warn!(participant = %self.participant, "SIL Kit: {why}");
            } else {
                tracing::info!(participant = %self.participant, "SIL Kit: {why}");
            }
            *dead = Some(why);
        }
        drop(dead);
        self.tx.lock().unwrap_or_else(|e| e.into_inner()).take();
    }

    fn end(&self, why: String) {
        self.end_with(why, true);
    }

    fn deliver(&self, rx: RxFrame) {
        if let Some(tx) = &*self.tx.lock().unwrap_or_else(|e| e.into_inner()) {
            if tx.try_send(rx).is_err() {
                self.dropped.fetch_add(1, Ordering::Relaxed);
            }
        }
    }
}

/// The classic CAN frame of a SIL Kit frame; `None` for one classic CAN cannot carry.
///
/// # Safety
/// `f.data` points to `f.data.size` bytes (or is null with size 0).
unsafe fn classic_frame(f: &sys::CanFrame) -> Option<Frame> {
    if f.flags & (sys::CAN_FLAG_FDF | sys::CAN_FLAG_XLF) != 0 || f.data.size > 8 || f.dlc > 8 {
        return None;
    }
    let ext = f.flags & sys::CAN_FLAG_IDE != 0;
    if f.flags & sys::CAN_FLAG_RTR != 0 {
        return Frame::remote(f.id, ext, f.dlc as u8).ok();
    }
    let data = if f.data.size == 0 || f.data.data.is_null() {
        &[][..]
    } else {
        // SAFETY: the caller's guarantee; size ≤ 8.
        unsafe { std::slice::from_raw_parts(f.data.data, f.data.size) }
    };
    Frame::with_id(f.id, ext, data).ok()
}

unsafe extern "C" fn on_frame(
    ctx: *mut c_void,
    _c: *mut sys::CanController,
    ev: *mut sys::CanFrameEvent,
) {
    // SAFETY: `ctx` is the `Shared` the transport keeps alive until the participant is gone;
    // `ev` and its frame are valid during the call (Can.h).
    let (shared, ev) = unsafe { (&*(ctx as *const Shared), &*ev) };
    if ev.frame.is_null() {
        return;
    }
    // SAFETY: as above.
    let Some(frame) = (unsafe { classic_frame(&*ev.frame) }) else {
        let n = shared.not_classic.fetch_add(1, Ordering::Relaxed) + 1;
        if n.is_power_of_two() {
            tracing::warn!(participant = %shared.participant, count = n,
                "SIL Kit: a frame classic CAN cannot carry (CAN FD / XL or more than 8 bytes) was dropped");
        }
        return;
    };
    match &shared.sync {
        None => shared.deliver(RxFrame::now(frame)),
        Some(s) => {
            let mut held = s.held.lock().unwrap_or_else(|e| e.into_inner());
            if held.len() < HELD_MAX {
                held.push_back((ev.timestamp, frame));
            } else {
                shared.dropped.fetch_add(1, Ordering::Relaxed);
            }
        }
    }
}

unsafe extern "C" fn on_step(
    ctx: *mut c_void,
    _t: *mut sys::TimeSyncService,
    now: sys::NanosecondsTime,
    _duration: sys::NanosecondsTime,
) {
    // SAFETY: as in `on_frame`.
    let shared = unsafe { &*(ctx as *const Shared) };
    if let Some(s) = &shared.sync {
        // The stepper thread completes the step; SIL Kit's thread must not wait here.
        let _ = s.steps.send(Some(now));
    }
}

unsafe extern "C" fn on_comm_ready(ctx: *mut c_void, _l: *mut sys::LifecycleService) {
    // SAFETY: as in `on_frame`; the controller pointer is stored before the lifecycle starts.
    let ctl = unsafe { &*(ctx as *const ControllerCtx) };
    // SAFETY: a live controller of a live participant.
    let rc = unsafe { (ctl.api.can_controller_start)(ctl.controller) };
    if let Err(e) = ctl.api.check("SilKit_CanController_Start", rc) {
        ctl.shared.end(e.to_string());
    }
}

unsafe extern "C" fn on_stop(ctx: *mut c_void, _l: *mut sys::LifecycleService) {
    // SAFETY: as in `on_frame`.
    let shared = unsafe { &*(ctx as *const Shared) };
    if shared.left.load(Ordering::SeqCst) {
        // Our own `SilKit_LifecycleService_Stop` (the transport is dropped), not the system
        // controller's.
        shared.end_with("the participant left".into(), false);
    } else {
        shared.end("the system controller stopped the simulation".into());
    }
}

unsafe extern "C" fn on_disconnected(
    ctx: *mut c_void,
    _m: *mut sys::SystemMonitor,
    info: *const sys::ParticipantConnectionInformation,
) {
    // SAFETY: as in `on_frame`; `info` and its name are valid during the call (Orchestration.h).
    let shared = unsafe { &*(ctx as *const Shared) };
    // SAFETY: as above; the name is NUL-terminated or null.
    let name = unsafe { info.as_ref() }
        .filter(|i| !i.participant_name.is_null())
        .map(|i| {
            unsafe { CStr::from_ptr(i.participant_name) }
                .to_string_lossy()
                .into_owned()
        })
        .unwrap_or_else(|| "?".into());
    // Named in the log: SIL Kit reports the Error state this may cause before this handler.
    tracing::info!(participant = %shared.participant, "SIL Kit: participant `{name}` disconnected");
    // SAFETY: as above.
    if unsafe { rejoin::is_registry(info) } {
        shared.watch.registry_lost();
    }
}

unsafe extern "C" fn on_system_state(ctx: *mut c_void, _m: *mut sys::SystemMonitor, state: i16) {
    // SAFETY: as in `on_frame`.
    let shared = unsafe { &*(ctx as *const Shared) };
    if state != sys::SYSTEM_STATE_ERROR || shared.left.load(Ordering::SeqCst) {
        return;
    }
    // SIL Kit's time stops in the Error state and only a restart of every participant and
    // the system controller leaves it: waiting would hang the process (docs/SILKIT.md).
    shared.end(
        "the simulation fell into SIL Kit's Error state (a participant or the system controller \
         left without stopping it): restart the participants and the system controller"
            .into(),
    );
}

unsafe extern "C" fn on_abort(ctx: *mut c_void, _l: *mut sys::LifecycleService, last: i16) {
    // SAFETY: as in `on_frame`.
    let shared = unsafe { &*(ctx as *const Shared) };
    shared.end(format!(
        "the simulation was aborted (participant state {last})"
    ));
}

/// What the communication-ready handler needs.
struct ControllerCtx {
    api: &'static Api,
    controller: *mut sys::CanController,
    shared: Arc<Shared>,
}

/// A SIL Kit CAN controller as a canpos transport.
pub struct SilkitCan {
    // Dropped first: SIL Kit calls no handler after the participant is destroyed.
    link: Arc<Link>,
    /// Watches the registry (`rejoin`); stopped and joined before the participant leaves.
    watcher: Option<std::thread::JoinHandle<()>>,
    lifecycle: *mut sys::LifecycleService,
    shared: Arc<Shared>,
    _ctl_ctx: Option<Box<ControllerCtx>>,
    rx: Receiver<RxFrame>,
    stepper: Option<std::thread::JoinHandle<()>>,
    started: AtomicBool,
    /// When the last frame was handed to SIL Kit (see [`LINGER`]).
    last_send: Mutex<Option<std::time::Instant>>,
    describe: String,
    name: String,
}

// SAFETY: the raw handles are used only through SIL Kit's thread-safe C API, and live as long
// as the participant in `link`.
unsafe impl Send for SilkitCan {}

impl SilkitCan {
    /// Joins `opts.registry` as `opts.participant` with one CAN controller on `opts.network`.
    /// In wall-clock mode the controller is started at once; in synchronised mode the
    /// lifecycle starts at the first use (so a runtime joins the clock before the first step).
    pub fn open(api: &'static Api, opts: &Options) -> Result<SilkitCan, Error> {
        check_name("network name", &opts.network).map_err(Error::BadArgument)?;
        let (tx, rx) = crossbeam_channel::bounded(RX_QUEUE);
        let (steps_tx, steps_rx) = crossbeam_channel::unbounded();
        let sync = match opts.time {
            TimeMode::Wall => None,
            TimeMode::Sync { .. } => Some(SyncState {
                clock: SimClock::stepped(),
                held: Mutex::new(VecDeque::new()),
                runtime: Mutex::new(None),
                runtime_started: AtomicBool::new(false),
                steps: steps_tx,
                early: Mutex::new(Some(Vec::new())),
            }),
        };
        let shared = Arc::new(Shared {
            api,
            participant: opts.participant.clone(),
            tx: Mutex::new(Some(tx)),
            dead: Mutex::new(None),
            dropped: AtomicU64::new(0),
            not_classic: AtomicU64::new(0),
            sync,
            lifecycle: std::sync::atomic::AtomicUsize::new(0),
            left: AtomicBool::new(false),
            watch: Arc::new(Watch::default()),
        });
        let ctx = Arc::as_ptr(&shared) as *mut c_void;
        let mut joined = join(api, opts, ctx)?;
        let (participant, controller) = (joined.participant.raw(), joined.controller);
        let mut lifecycle = std::ptr::null_mut();
        let mut ctl_ctx = None;
        let mut stepper = None;
        match opts.time {
            TimeMode::Wall => {
                start_wall(api, &mut joined, &shared.watch)?;
            }
            TimeMode::Sync { step } => {
                let cfg = sys::LifecycleConfiguration {
                    header: sys::StructHeader::new(sys::LIFECYCLE_CONFIGURATION_ID),
                    operation_mode: sys::OPERATION_MODE_COORDINATED,
                };
                // SAFETY: live participant, a valid configuration, out-pointer.
                api.check("SilKit_LifecycleService_Create", unsafe {
                    (api.lifecycle_service_create)(&mut lifecycle, participant, &cfg)
                })?;
                shared.lifecycle.store(lifecycle as usize, Ordering::SeqCst);
                let cc = Box::new(ControllerCtx {
                    api,
                    controller,
                    shared: Arc::clone(&shared),
                });
                let cc_ptr = &*cc as *const ControllerCtx as *mut c_void;
                ctl_ctx = Some(cc);
                let mut time_sync = std::ptr::null_mut();
                let step_ns = u64::try_from(step.as_nanos()).unwrap_or(u64::MAX).max(1);
                // SAFETY: live services; the contexts outlive the participant.
                unsafe {
                    api.check(
                        "SilKit_LifecycleService_SetCommunicationReadyHandler",
                        (api.lifecycle_service_set_communication_ready_handler)(
                            lifecycle,
                            cc_ptr,
                            on_comm_ready,
                        ),
                    )?;
                    api.check(
                        "SilKit_LifecycleService_SetStopHandler",
                        (api.lifecycle_service_set_stop_handler)(lifecycle, ctx, on_stop),
                    )?;
                    api.check(
                        "SilKit_LifecycleService_SetAbortHandler",
                        (api.lifecycle_service_set_abort_handler)(lifecycle, ctx, on_abort),
                    )?;
                    // A participant or the system controller that vanishes puts the
                    // simulation in SIL Kit's Error state, where time stops: watched, so
                    // that the transport ends with that reason instead of waiting forever.
                    let mut monitor = std::ptr::null_mut();
                    api.check(
                        "SilKit_SystemMonitor_Create",
                        (api.system_monitor_create)(&mut monitor, participant),
                    )?;
                    api.check(
                        "SilKit_SystemMonitor_SetParticipantDisconnectedHandler",
                        (api.system_monitor_set_participant_disconnected_handler)(
                            monitor,
                            ctx,
                            on_disconnected,
                        ),
                    )?;
                    let mut id = 0;
                    api.check(
                        "SilKit_SystemMonitor_AddSystemStateHandler",
                        (api.system_monitor_add_system_state_handler)(
                            monitor,
                            ctx,
                            on_system_state,
                            &mut id,
                        ),
                    )?;
                    api.check(
                        "SilKit_TimeSyncService_Create",
                        (api.time_sync_service_create)(&mut time_sync, lifecycle),
                    )?;
                    api.check(
                        "SilKit_TimeSyncService_SetSimulationStepHandlerAsync",
                        (api.time_sync_service_set_simulation_step_handler_async)(
                            time_sync, ctx, on_step, step_ns,
                        ),
                    )?;
                }
                let weak = Arc::downgrade(&shared);
                let ts = time_sync as usize;
                let cs = controller as usize;
                stepper = Some(
                    std::thread::Builder::new()
                        .name("canpos-silkit-step".into())
                        .spawn(move || stepper_loop(weak, steps_rx, ts, cs))
                        .map_err(|e| Error::BadArgument(format!("cannot start a thread: {e}")))?,
                );
            }
        }
        let link = Arc::new(Link::new(joined));
        let watcher = spawn_watcher(api, opts, &shared, &link)?;
        Ok(SilkitCan {
            describe: describe(opts),
            name: opts.participant.clone(),
            link,
            watcher: Some(watcher),
            lifecycle,
            shared,
            _ctl_ctx: ctl_ctx,
            rx,
            stepper,
            started: AtomicBool::new(matches!(opts.time, TimeMode::Wall)),
            last_send: Mutex::new(None),
        })
    }

    /// Starts the coordinated lifecycle (synchronised mode), once: at the first use of the
    /// transport (a tool's or a runtime's first send or wait for a frame).
    fn start(&self) {
        if self.started.swap(true, Ordering::SeqCst) {
            return;
        }
        let mut gate = lock(&GATE);
        if gate.held {
            gate.pending.push(Arc::downgrade(&self.shared));
            return;
        }
        drop(gate);
        start_lifecycle(&self.shared);
    }

    /// Frames dropped because classic CAN cannot carry them.
    pub fn not_classic(&self) -> u64 {
        self.shared.not_classic.load(Ordering::Relaxed)
    }

    /// The participant's name.
    pub fn participant(&self) -> &str {
        &self.name
    }

    /// Frames sent while the transport was between two participants (rejoining a registry
    /// that came back, `rejoin`).
    pub fn lost_rejoining(&self) -> u64 {
        self.link.lost()
    }
}

/// Joins `opts.registry` as `opts.participant` with the CAN controller `CAN1` on
/// `opts.network`, its frames handed to `ctx` (the transport's `Shared`, which outlives the
/// participant), not started.
fn join(api: &'static Api, opts: &Options, ctx: *mut c_void) -> Result<Joined, Error> {
    let participant = Participant::join(api, &opts.participant, &opts.registry)?;
    let cname = CString::new("CAN1").expect("no NUL");
    let cnet =
        CString::new(opts.network.as_str()).map_err(|e| Error::BadArgument(e.to_string()))?;
    let mut controller = std::ptr::null_mut();
    // SAFETY: live participant, NUL-terminated strings, out-pointer.
    api.check("SilKit_CanController_Create", unsafe {
        (api.can_controller_create)(
            &mut controller,
            participant.raw(),
            cname.as_ptr(),
            cnet.as_ptr(),
        )
    })?;
    let mut id = 0;
    // SAFETY: `ctx` outlives the participant (field order of `SilkitCan`).
    api.check("SilKit_CanController_AddFrameHandler", unsafe {
        (api.can_controller_add_frame_handler)(
            controller,
            ctx,
            on_frame,
            sys::DIRECTION_RECEIVE,
            &mut id,
        )
    })?;
    if let Some(kbps) = opts.bitrate_kbps {
        // SAFETY: live controller.
        api.check("SilKit_CanController_SetBaudRate", unsafe {
            (api.can_controller_set_baud_rate)(controller, kbps.saturating_mul(1000), 0, 0)
        })?;
    }
    Ok(Joined {
        participant,
        connections: None,
        controller,
    })
}

/// The participant's system monitor. SIL Kit allows one a participant (a second
/// `SilKit_SystemMonitor_Create` fails): every handler of a participant goes on this one.
fn system_monitor(
    api: &'static Api,
    participant: &Participant,
) -> Result<*mut sys::SystemMonitor, Error> {
    let mut monitor = std::ptr::null_mut();
    // SAFETY: a live participant, an out-pointer.
    api.check("SilKit_SystemMonitor_Create", unsafe {
        (api.system_monitor_create)(&mut monitor, participant.raw())
    })?;
    Ok(monitor)
}

/// Wall-clock mode: the registry watched for its departure, the controller started, then
/// nothing sent before SIL Kit's discovery has settled: a frame sent on SIL Kit's trivial bus
/// while the others already route through a simulator is lost (D54). A rejoin waits the same.
fn start_wall(api: &'static Api, j: &mut Joined, watch: &Watch) -> Result<(), Error> {
    let created = std::time::Instant::now();
    let monitor = system_monitor(api, &j.participant)?;
    rejoin::watch_registry(api, monitor, watch)?;
    // SAFETY: live controller.
    api.check("SilKit_CanController_Start", unsafe {
        (api.can_controller_start)(j.controller)
    })?;
    j.connections = super::discovery::watch_connections(&j.participant, monitor)
        .map_err(|e| tracing::debug!("SIL Kit: participant connections not watched: {e}"))
        .ok();
    let settled = super::discovery::settle(
        j.participant.silkit_log(),
        j.connections.as_deref(),
        "CAN1",
        created,
    );
    tracing::debug!(participant = %j.participant.name(), ?settled,
        waited_ms = created.elapsed().as_millis() as u64, "SIL Kit: discovery settled");
    Ok(())
}

/// The thread that watches the registry (`rejoin`): in wall-clock mode it rejoins a registry
/// that came back, in synchronised mode it ends the transport then.
fn spawn_watcher(
    api: &'static Api,
    opts: &Options,
    shared: &Arc<Shared>,
    link: &Arc<Link>,
) -> Result<std::thread::JoinHandle<()>, Error> {
    let on_return = match opts.time {
        TimeMode::Wall => {
            let weak = Arc::downgrade(shared);
            let opts = opts.clone();
            rejoin::OnReturn::Rejoin {
                link: Arc::clone(link),
                leave: Box::new(move |old: Joined| {
                    // As a transport that is dropped: stopped, and a linger (see `Drop`).
                    // SAFETY: a live controller of a live participant.
                    let _ = unsafe { (api.can_controller_stop)(old.controller) };
                    std::thread::sleep(LINGER);
                    drop(old);
                }),
                join: Box::new(move || {
                    let sh = weak
                        .upgrade()
                        .ok_or_else(|| Error::BadArgument("the transport ended".into()))?;
                    let mut j = join(api, &opts, Arc::as_ptr(&sh) as *mut c_void)?;
                    start_wall(api, &mut j, &sh.watch)?;
                    Ok(j)
                }),
            }
        }
        TimeMode::Sync { .. } => {
            let weak = Arc::downgrade(shared);
            rejoin::OnReturn::End(Box::new(move |why| {
                if let Some(sh) = weak.upgrade() {
                    sh.end(why);
                }
            }))
        }
    };
    let watch = Arc::clone(&shared.watch);
    let registry = opts.registry.clone();
    let name = opts.participant.clone();
    std::thread::Builder::new()
        .name("canpos-silkit-registry".into())
        .spawn(move || rejoin::watcher(watch, registry, name, on_return))
        .map_err(|e| Error::BadArgument(format!("cannot start a thread: {e}")))
}

/// What the banner shows: the URL (IPv6 hosts in brackets, so it can be copied) and the name.
fn describe(opts: &Options) -> String {
    format!("{}/{} as {}", opts.registry, opts.network, opts.participant)
}

/// Lifecycle starts held back until [`release_starts`] (see [`hold_starts`]).
struct Gate {
    held: bool,
    pending: Vec<Weak<Shared>>,
}

static GATE: Mutex<Gate> = Mutex::new(Gate {
    held: false,
    pending: Vec::new(),
});

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// Holds back the start of synchronised participants' lifecycles in this process until
/// [`release_starts`]: `canpos run --time sync` sets its sensors' start-up NMT state (a control
/// request) before SIL Kit's time begins, so that it takes effect at time 0 in every run, not
/// at whatever step the request happened to reach the runtime.
pub fn hold_starts() {
    lock(&GATE).held = true;
}

/// Starts the lifecycles held back by [`hold_starts`] (and no longer holds new ones).
pub fn release_starts() {
    let mut gate = lock(&GATE);
    gate.held = false;
    for w in std::mem::take(&mut gate.pending) {
        if let Some(sh) = w.upgrade() {
            // Under the gate's lock: a transport that is dropping marks itself left under it
            // first, before its participant is destroyed.
            if !sh.left.load(Ordering::SeqCst) {
                start_lifecycle(&sh);
            }
        }
    }
}

fn start_lifecycle(sh: &Shared) {
    let lifecycle = sh.lifecycle.load(Ordering::SeqCst) as *mut sys::LifecycleService;
    if lifecycle.is_null() {
        return;
    }
    // SAFETY: a live lifecycle service (its participant is not destroyed: `left` is false).
    let rc = unsafe { (sh.api.lifecycle_service_start_lifecycle)(lifecycle) };
    if let Err(e) = sh.api.check("SilKit_LifecycleService_StartLifecycle", rc) {
        sh.end(e.to_string());
    }
}

/// Synchronised mode: for each step `now`, hands over the frames stamped before it, moves the
/// clock to it, waits until the runtime (if one joined) has processed everything up to it,
/// and completes the step.
fn stepper_loop(
    shared: Weak<Shared>,
    steps: Receiver<Option<u64>>,
    time_sync: usize,
    controller: usize,
) {
    let time_sync = time_sync as *mut sys::TimeSyncService;
    // SIL Kit's time begins only when a system controller starts the simulation: until then
    // the participant waits, as it should, but says so once (a forgotten system controller or
    // a participant name it does not require looks like a hang otherwise).
    let first = match steps.recv_timeout(START_WAIT_WARN) {
        Ok(first) => first,
        Err(crossbeam_channel::RecvTimeoutError::Timeout) => {
            if let Some(sh) = shared.upgrade() {
                tracing::warn!(participant = %sh.participant,
                    "SIL Kit: waiting for a system controller to start the simulation (e.g. \
                     `sil-kit-system-controller -u silkit://HOST:PORT {} …`, naming every \
                     synchronised participant; docs/SILKIT.md)", sh.participant);
            }
            steps.recv().ok().flatten()
        }
        Err(crossbeam_channel::RecvTimeoutError::Disconnected) => None,
    };
    let mut next = first;
    while let Some(now) = next.take() {
        let Some(sh) = shared.upgrade() else { return };
        let Some(s) = &sh.sync else { return };
        {
            let mut held = s.held.lock().unwrap_or_else(|e| e.into_inner());
            // By timestamp, then as arbitration orders frames sent at once (lowest identifier
            // first; the data for the same identifier): not by arrival, which varies.
            let mut due: Vec<(u64, Frame)> = Vec::new();
            held.retain(|&(t, f)| {
                if t < now {
                    due.push((t, f));
                    false
                } else {
                    true
                }
            });
            drop(held);
            due.sort_by_key(|&(t, f)| {
                (t, f.is_extended(), f.id(), f.is_remote(), *f.raw(), f.dlc())
            });
            let runtime = s
                .runtime
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .is_some();
            for (t, frame) in due {
                let timestamp = if runtime {
                    s.clock.system_time_of(t)
                } else {
                    SystemTime::UNIX_EPOCH + Duration::from_nanos(t)
                };
                sh.deliver(RxFrame { frame, timestamp });
            }
        }
        let early = s.early.lock().unwrap_or_else(|e| e.into_inner()).take();
        for f in early.into_iter().flatten() {
            let stamp = super::netsim::context_of_time(now);
            if let Err(e) = send_frame(sh.api, controller as *mut sys::CanController, &f, stamp) {
                tracing::warn!(participant = %sh.participant, "SIL Kit: {e}");
            }
        }
        let _ = s.clock.step_to(now);
        wait_for_runtime(&sh, s, now);
        tracing::trace!(now, "SIL Kit: step complete");
        // SAFETY: the service lives as long as the participant, which `sh` outlives only
        // through the transport (dropped after the participant): checked by the upgrade.
        let rc = unsafe { (sh.api.time_sync_service_complete_simulation_step)(time_sync) };
        if let Err(e) = sh
            .api
            .check("SilKit_TimeSyncService_CompleteSimulationStep", rc)
        {
            sh.end(e.to_string());
            return;
        }
        drop(sh);
        next = steps.recv().ok().flatten();
    }
}

/// Until the runtime on the clock has taken every frame handed over and processed every event
/// up to `now` (its horizon is past `now`), or is gone. Polled: the runtime's thread tells
/// nobody when it is done.
fn wait_for_runtime(sh: &Shared, s: &SyncState, now: u64) {
    let Some(slot) = s.runtime.lock().unwrap_or_else(|e| e.into_inner()).clone() else {
        return;
    };
    let mut spins = 0u32;
    loop {
        let Some(slot) = slot.upgrade() else { return };
        if sh.tx.lock().unwrap_or_else(|e| e.into_inner()).is_none() {
            return;
        }
        let at = slot.at();
        let queue_empty = sh
            .tx
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .as_ref()
            .is_none_or(|tx| tx.is_empty());
        if at != u64::MAX {
            s.runtime_started.store(true, Ordering::Relaxed);
        }
        if s.runtime_started.load(Ordering::Relaxed) && at > now && queue_empty {
            return;
        }
        spins += 1;
        if spins < 100 {
            std::thread::yield_now();
        } else {
            std::thread::sleep(Duration::from_micros(50));
        }
    }
}

/// Sends a classic frame on `controller`, with `context` as its user context (in synchronised
/// mode its simulated time, for a network simulator: `netsim::context_of_time`, D40).
fn send_frame(
    api: &'static Api,
    controller: *mut sys::CanController,
    frame: &Frame,
    context: u64,
) -> Result<(), Error> {
    let data = frame.data();
    let mut flags = 0;
    if frame.is_extended() {
        flags |= sys::CAN_FLAG_IDE;
    }
    if frame.is_remote() {
        flags |= sys::CAN_FLAG_RTR;
    }
    let mut f = sys::CanFrame {
        header: sys::StructHeader::new(sys::CAN_FRAME_ID),
        id: frame.id(),
        flags,
        dlc: u16::from(frame.dlc()),
        sdt: 0,
        vcid: 0,
        af: 0,
        data: sys::ByteVector {
            data: data.as_ptr(),
            size: if frame.is_remote() { 0 } else { data.len() },
        },
    };
    // SAFETY: a live controller; SIL Kit copies the frame before returning.
    let rc = unsafe { (api.can_controller_send_frame)(controller, &mut f, context as *mut c_void) };
    api.check("SilKit_CanController_SendFrame", rc)
}

impl Transport for SilkitCan {
    fn send(&mut self, frame: &Frame) -> io::Result<()> {
        self.start();
        if let Some(why) = &*self.shared.dead.lock().unwrap_or_else(|e| e.into_inner()) {
            return Err(io::Error::new(
                io::ErrorKind::ConnectionAborted,
                why.clone(),
            ));
        }
        if let Some(s) = &self.shared.sync {
            if let Some(early) = &mut *s.early.lock().unwrap_or_else(|e| e.into_inner()) {
                if early.len() < RX_QUEUE {
                    early.push(*frame);
                } else {
                    self.shared.dropped.fetch_add(1, Ordering::Relaxed);
                }
                return Ok(());
            }
        }
        if let Some(s) = &self.shared.sync {
            tracing::trace!(id = frame.id(), limit = s.clock.limit(), "SIL Kit: send");
        }
        *self.last_send.lock().unwrap_or_else(|e| e.into_inner()) = Some(std::time::Instant::now());
        // Synchronised: stamped with the step's time (D40), so canpos bus netsim enters it into
        // the bus at that simulated time, not at whichever of its steps it arrived in.
        let stamp = self
            .shared
            .sync
            .as_ref()
            .map_or(0, |s| super::netsim::context_of_time(s.clock.limit()));
        let api = self.shared.api;
        self.link
            .with_controller(|c| send_frame(api, c, frame, stamp))
            .map_err(|e| io::Error::other(e.to_string()))
    }

    fn receiver(&self) -> &Receiver<RxFrame> {
        self.start();
        &self.rx
    }

    fn recv_timeout(&mut self, timeout: Option<Duration>) -> io::Result<Option<RxFrame>> {
        self.start();
        let r = match timeout {
            None => self
                .rx
                .recv()
                .map_err(|_| crossbeam_channel::RecvTimeoutError::Disconnected),
            Some(t) => self.rx.recv_timeout(t),
        };
        match r {
            Ok(f) => Ok(Some(f)),
            Err(crossbeam_channel::RecvTimeoutError::Timeout) => Ok(None),
            Err(crossbeam_channel::RecvTimeoutError::Disconnected) => Err(self.dead_error()),
        }
    }

    fn dead_error(&self) -> io::Error {
        let why = self
            .shared
            .dead
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .clone()
            .unwrap_or_else(|| "SIL Kit transport closed".into());
        io::Error::new(io::ErrorKind::ConnectionAborted, why)
    }

    fn dropped(&self) -> u64 {
        self.shared.dropped.load(Ordering::Relaxed)
    }

    fn join_clock(&mut self) -> Option<Horizon> {
        let s = self.shared.sync.as_ref()?;
        let h = s.clock.participant(&self.describe);
        *s.runtime.lock().unwrap_or_else(|e| e.into_inner()) = Some(h.slot());
        // The lifecycle starts at the runtime's first send or wait, after its power-on: the
        // horizon is still at the clock's time here (the runtime holds nothing until it runs),
        // which the stepper must not take for a runtime that started.
        Some(h)
    }

    fn describe(&self) -> String {
        self.describe.clone()
    }
}

impl Drop for SilkitCan {
    fn drop(&mut self) {
        self.shared.left.store(true, Ordering::SeqCst);
        drop(lock(&GATE));
        // No rejoin from here on: the watcher ends (a rejoin under way finishes first).
        self.shared.watch.stop();
        if let Some(t) = self.watcher.take() {
            let _ = t.join();
        }
        let started = self.started.load(Ordering::SeqCst);
        if started {
            // Stopped before leaving, and a linger for a network simulator to take note: SIL
            // Kit 5.0.3's simulator crashes on a send it queued for a controller that left
            // (it frees its target when the controller leaves), and a stopped controller is
            // sent nothing (docs/BENCHMARKS.md "SIL Kit: canpos bus netsim at scale").
            let api = self.shared.api;
            // SAFETY: a live controller; an error (not started) is of no consequence.
            let _ = self.link.with_controller(|c| {
                let _ = unsafe { (api.can_controller_stop)(c) };
                Ok(())
            });
            std::thread::sleep(LINGER);
        }
        if started && !self.lifecycle.is_null() {
            let reason = CString::new("canpos participant leaves").expect("no NUL");
            // SAFETY: a live lifecycle service; an error (not running) is of no consequence.
            let _ = unsafe {
                (self.shared.api.lifecycle_service_stop)(self.lifecycle, reason.as_ptr())
            };
        }
        // SIL Kit writes frames to its peers on its own thread: destroying the participant
        // right after a send loses them (a one-shot `canpos nmt` did, 5 of 12 times).
        if let Some(t) = *self.last_send.lock().unwrap_or_else(|e| e.into_inner()) {
            std::thread::sleep(LINGER.saturating_sub(t.elapsed()));
        }
        // Ends a wait for the runtime, and the receiver.
        self.shared.end_with("the participant left".into(), false);
        if let (Some(s), Some(t)) = (&self.shared.sync, self.stepper.take()) {
            // The stepper completes no step once the participant is destroyed (when the field
            // drops, after this body): it ends here, before.
            let _ = s.steps.send(None);
            let _ = t.join();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_description_is_a_url_that_can_be_copied() {
        let mut o = Options {
            registry: RegistryUri {
                host: "::1".into(),
                port: 8501,
            },
            network: "can0".into(),
            participant: "th-11".into(),
            time: TimeMode::Wall,
            bitrate_kbps: None,
        };
        assert_eq!(describe(&o), "silkit://[::1]:8501/can0 as th-11");
        o.registry.host = "127.0.0.1".into();
        assert_eq!(describe(&o), "silkit://127.0.0.1:8501/can0 as th-11");
    }
}
