//! The runtime: drives one or many simulated sensors ([`canpos_stack::Node`] + [`canpos_sim::Sensor`])
//! on one bus, on absolute deadlines.
//!
//! # Design
//!
//! One thread per bus. Each turn of its loop:
//!
//! 1. drains received frames and hands each to every node;
//! 2. runs every measurement cycle that is due (motion → [`Sensor::cycle`](canpos_sim::Sensor::cycle) →
//!    [`Node::update_sample`](canpos_stack::Node::update_sample)); cycles are scheduled as `start + k × cycle`, never as
//!    "now + cycle", so they do not drift. The sensor publishes each measurement at the first
//!    cycle boundary after its pulse returned (one cycle later on every TH / E-Series stroke),
//!    and its temperature leaving the limits raises the core's over-temperature condition
//!    (EMCY 0x4200) by itself;
//! 3. polls every node ([`Node::poll`](canpos_stack::Node::poll): the timers that are due — TPDO event timers,
//!    heartbeat, SDO timeout, EMCY inhibit — then the frames it has to send) and routes what
//!    they send: to the transport **and** to the other nodes of this runtime (they share the
//!    bus; a transport never echoes a frame to its sender);
//! 4. answers control requests ([`crate::control`]);
//! 5. sleeps until the earliest of all deadlines, a received frame, or a control request.
//!
//! The sleep is a [`crossbeam_channel::Select`] over the transport's receive queue and the
//! control queue (so frames are handled at once), ended a little before the deadline
//! ([`EARLY_WAKE`]) and finished with `clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME)`: the
//! futex wait behind the channel is only as precise as the scheduler makes it, the absolute
//! sleep is the precise part. The thread's timer slack is set to 1 ns (`PR_SET_TIMERSLACK`),
//! without which Linux rounds every timed sleep up by 50 µs. [`Lateness`] records how late each
//! timed wake was.
//!
//! Time: the core's [`Instant`] is microseconds since the runtime was created
//! (`CLOCK_MONOTONIC`, via [`std::time::Instant`]).
//!
//! # Files
//!
//! This file holds the [`Runtime`] and its loop (power, turn, routing, watching the transport
//! and the controllers); `device.rs` the device wrapper (one simulated sensor: node, sensor,
//! faults, timing, its own controller); `clock.rs` the clock glue (advancing to a time, frames
//! in their order, stalls); `requests.rs` the control requests as the runtime carries them out;
//! `wait.rs` the precise waits and their [`Lateness`]. The children extend [`Runtime`] with
//! further `impl` blocks; none of them names this file's loop.

use std::io;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::Duration;

use canpos_stack::{Frame, Instant};
use crossbeam_channel::{Receiver, Sender};
use serde_json::{json, Value};

use crate::can::{BusState, Transport};
use crate::clock::{Driver, Horizon, SimClock};
use crate::control::request::{Fault, Request};
pub use crate::sys::{set_timer_slack_1ns, sleep_until, sleep_until_precise, SPIN_TAIL};
use crate::timing::DeviceTiming;

/// How long the CAN overrun EMCY (0x8110) stays active after the transport last lost a frame.
pub const OVERRUN_HOLD: Duration = Duration::from_secs(1);

/// How often the runtime looks at its sensors' own controllers (paced in-process buses), µs.
const CONTROLLER_POLL_US: u64 = 5_000;

/// The default state file of a unit: `<state_dir>/<model>-<serial>.bin`.
pub fn state_file(state_dir: &std::path::Path, model: &str, serial: u32) -> PathBuf {
    state_dir.join(format!("{model}-{serial}.bin"))
}

/// The default state directory: `$CANPOS_STATE_DIR`, else `$XDG_STATE_HOME/canpos`, else
/// `$HOME/.local/state/canpos`, else `./canpos-state`.
pub fn default_state_dir() -> PathBuf {
    if let Some(d) = std::env::var_os("CANPOS_STATE_DIR").filter(|d| !d.is_empty()) {
        return PathBuf::from(d);
    }
    if let Some(d) = std::env::var_os("XDG_STATE_HOME").filter(|d| !d.is_empty()) {
        return PathBuf::from(d).join("canpos");
    }
    if let Some(h) = std::env::var_os("HOME").filter(|d| !d.is_empty()) {
        return PathBuf::from(h).join(".local/state/canpos");
    }
    PathBuf::from("canpos-state")
}

/// A message to the runtime thread.
pub(crate) enum Msg {
    Request(Request, Sender<Value>),
    Stop,
}

/// Sends control requests to a running [`Runtime`]; cheap to clone, usable from any thread.
#[derive(Clone)]
pub struct ControlHandle {
    tx: Sender<Msg>,
}

impl ControlHandle {
    /// Sends `req` and waits for the answer (`{"ok":true,…}` or `{"ok":false,"error":…}`).
    pub fn request(&self, req: Request) -> Value {
        let (tx, rx) = crossbeam_channel::bounded(1);
        if self.tx.send(Msg::Request(req, tx)).is_err() {
            return json!({"ok": false, "error": "the runtime has stopped"});
        }
        rx.recv_timeout(Duration::from_secs(10)).unwrap_or_else(
            |_| json!({"ok": false, "error": "the runtime did not answer within 10 s"}),
        )
    }

    /// Asks the runtime to stop (returns at once).
    pub fn stop(&self) {
        let _ = self.tx.send(Msg::Stop);
    }
}

/// Drives simulated sensors on one transport. Build it, [`Runtime::add`] sensors, then
/// [`Runtime::run`] (blocking) or [`Runtime::spawn`].
pub struct Runtime {
    transport: Box<dyn Transport>,
    devices: Vec<SimDevice>,
    powered: Vec<bool>,
    /// The simulation clock: the bus's when the transport has one (an in-process bus), else
    /// a wall clock of the runtime's own (docs/CLOCK.md).
    clock: SimClock,
    /// This runtime's horizon on the bus's clock (`None`: the clock is the runtime's own).
    horizon: Option<Horizon>,
    /// The simulation time the runtime has processed every event up to.
    reached: Instant,
    /// A received frame stamped later than the time being processed, kept for its time.
    stash: Option<crate::can::RxFrame>,
    /// Frames were received since the transport was last looked at (receive filter).
    received: bool,
    /// When the sensors' own controllers are looked at next (every [`CONTROLLER_POLL_US`],
    /// not at every event: each look runs the bus and reads its counters).
    next_controller_look: Instant,
    /// How late (wall − simulation time) own events were processed (wall-driven clocks).
    events_late: Lateness,
    /// How late (wall − end of frame) received frames were handled (wall-driven clocks).
    frames_late: Lateness,
    bus_bitrate: Option<u16>,
    rx: Receiver<Msg>,
    tx: Sender<Msg>,
    lateness: Lateness,
    started: bool,
    /// Lost frames of the transport already reported.
    drops_seen: u64,
    /// While frames are being lost: when the overrun EMCY is cleared.
    overrun_until: Option<Instant>,
    /// Controller state last seen on the transport.
    bus_state: BusState,
    /// Install receive filters on transports that support them (SocketCAN).
    kernel_filter: bool,
    /// The COB-IDs last given to [`Transport::set_rx_filter`].
    filter: Option<Vec<u16>>,
    /// [`Transport::reconnections`] already acted on.
    reconnections_seen: u64,
}

/// A runtime running on its own thread.
pub struct RuntimeHandle {
    control: ControlHandle,
    thread: Option<JoinHandle<io::Result<Lateness>>>,
    stopped: Arc<AtomicBool>,
}

impl RuntimeHandle {
    /// Runs `body` on the runtime thread (with the runtime's priority); `body` gets the
    /// control messages that `tx` sends.
    pub(crate) fn spawn_loop(
        tx: Sender<Msg>,
        rx: Receiver<Msg>,
        body: impl FnOnce(Receiver<Msg>) -> io::Result<Lateness> + Send + 'static,
    ) -> io::Result<RuntimeHandle> {
        let stopped = Arc::new(AtomicBool::new(false));
        let flag = Arc::clone(&stopped);
        let thread = std::thread::Builder::new()
            .name("canpos-runtime".into())
            .spawn(move || {
                // Above the process's other threads when `--rt-priority` was given.
                if let Err(e) = crate::realtime::runtime_thread() {
                    tracing::warn!(error = %e, "runtime thread keeps the process's priority");
                }
                let r = body(rx);
                flag.store(true, Ordering::SeqCst);
                r
            })?;
        Ok(RuntimeHandle {
            control: ControlHandle { tx },
            thread: Some(thread),
            stopped,
        })
    }

    /// The control handle.
    pub fn control(&self) -> ControlHandle {
        self.control.clone()
    }

    /// Whether the runtime thread has ended (transport died or stopped).
    pub fn is_finished(&self) -> bool {
        self.stopped.load(Ordering::SeqCst) || self.thread.as_ref().is_none_or(|t| t.is_finished())
    }

    /// Stops the runtime and waits for its thread; returns the wake-up statistics.
    pub fn stop(mut self) -> io::Result<Lateness> {
        self.control.stop();
        self.join_inner()
    }

    /// Waits for the runtime thread to end on its own (transport closed, or a stop request
    /// through a [`ControlHandle`]).
    pub fn join(mut self) -> io::Result<Lateness> {
        self.join_inner()
    }

    fn join_inner(&mut self) -> io::Result<Lateness> {
        match self.thread.take() {
            Some(t) => t
                .join()
                .unwrap_or_else(|_| Err(io::Error::other("runtime thread panicked"))),
            None => Ok(Lateness::default()),
        }
    }
}

impl Drop for RuntimeHandle {
    fn drop(&mut self) {
        if self.thread.is_some() {
            self.control.stop();
            let _ = self.join_inner();
        }
    }
}

impl Runtime {
    /// A runtime on `transport`. `bus_bitrate_kbps` overrides the transport's own notion of the
    /// bus bit rate (a socketcand bus has none): nodes configured for another bit rate fall
    /// silent (SPEC §9).
    ///
    /// On a transport with a simulation clock (an in-process bus, a hub channel in this
    /// process) the runtime joins that clock as a timed participant; elsewhere it keeps a wall
    /// clock of its own (docs/CLOCK.md).
    pub fn new(mut transport: Box<dyn Transport>, bus_bitrate_kbps: Option<u32>) -> Runtime {
        let (tx, rx) = crossbeam_channel::bounded(64);
        let bus_bitrate = bus_bitrate_kbps
            .or_else(|| transport.bus_bitrate())
            .map(|b| b.min(u32::from(u16::MAX)) as u16);
        let horizon = transport.join_clock();
        // Holding nothing until it runs (power-on sets it to the runtime's time).
        if let Some(h) = &horizon {
            h.set(u64::MAX);
        }
        let clock = horizon
            .as_ref()
            .map_or_else(SimClock::wall, |h| h.clock().clone());
        let reached = Instant::from_micros(clock.limit() / 1000);
        Runtime {
            transport,
            devices: Vec::new(),
            powered: Vec::new(),
            clock,
            horizon,
            reached,
            stash: None,
            received: false,
            next_controller_look: reached,
            events_late: Lateness::default(),
            frames_late: Lateness::default(),
            bus_bitrate,
            rx,
            tx,
            lateness: Lateness::default(),
            started: false,
            drops_seen: 0,
            overrun_until: None,
            bus_state: BusState::ErrorActive,
            kernel_filter: true,
            filter: None,
            reconnections_seen: 0,
        }
    }

    /// Whether to restrict reception to the nodes' COB-IDs on transports that filter in the
    /// kernel (SocketCAN; on by default): NMT, SYNC, LSS, SDO, error control and remote frames.
    pub fn set_kernel_filter(&mut self, on: bool) {
        self.kernel_filter = on;
    }

    /// Adds a sensor (powered off until [`Runtime::power_on_all`] or the start of
    /// [`Runtime::run`]); returns its index for control requests.
    pub fn add(&mut self, setup: SensorSetup) -> usize {
        let now = self.now();
        let mut d = SimDevice::new(setup, now);
        d.hw.set_bus_bitrate(self.bus_bitrate);
        // On a paced in-process bus each sensor has its own controller, as on a real bus.
        d.port = self.transport.controller();
        self.devices.push(d);
        self.powered.push(false);
        self.devices.len() - 1
    }

    /// Number of sensors.
    pub fn len(&self) -> usize {
        self.devices.len()
    }

    /// True when no sensor was added.
    pub fn is_empty(&self) -> bool {
        self.devices.is_empty()
    }

    /// A handle to send control requests (also works before the runtime runs: they are
    /// answered once it does).
    pub fn control(&self) -> ControlHandle {
        ControlHandle {
            tx: self.tx.clone(),
        }
    }

    /// Powers every sensor on now: each sends its boot-up at once.
    pub fn power_on_all(&mut self) {
        let now = self.now().max(self.reached);
        self.reached = now;
        self.hold_at(now.micros() * 1000);
        for i in 0..self.devices.len() {
            self.power_on(i, now);
        }
        self.route(now);
        self.started = true;
        self.hold_next();
    }

    /// Powers sensor `i` on: at once, or after its boot delay ([`DeviceTiming::boot_delay`]).
    fn power_on(&mut self, i: usize, now: Instant) {
        let d = &mut self.devices[i];
        if !d.timing.boot_delay.is_zero() {
            let at = Instant::from_micros(now.micros() + d.timing.boot_delay.as_micros() as u64);
            d.power_on_at = Some(at);
            tracing::info!(sensor = %d.name, delay_ms = d.timing.boot_delay.as_millis() as u64,
                "powered on, booting");
            return;
        }
        self.power_on_now(i, now);
    }

    fn power_on_now(&mut self, i: usize, now: Instant) {
        let d = &mut self.devices[i];
        d.power_on_at = None;
        d.held.clear();
        d.rebooting = None;
        d.power_on_bootup = true;
        d.node.power_on(now);
        // The core starts without fault conditions; the next cycle raises it again if needed.
        d.temp_alarm = false;
        d.next_cycle = now;
        self.powered[i] = true;
        tracing::info!(sensor = %d.name, node_id = d.node.device().node_id(),
            bitrate_kbps = d.node.device().bitrate(), "powered on");
    }

    fn power_off(&mut self, i: usize) {
        let d = &mut self.devices[i];
        d.node.power_off();
        d.power_on_at = None;
        d.held.clear();
        d.rebooting = None;
        self.powered[i] = false;
    }

    /// Sets sensor `i`'s own timing; checked first, so a refused value changes nothing.
    pub fn set_timing(&mut self, i: usize, timing: DeviceTiming) -> Result<(), String> {
        timing.check()?;
        let d = self
            .devices
            .get_mut(i)
            .ok_or_else(|| format!("sensor {i} does not exist"))?;
        d.timing = timing;
        Ok(())
    }

    /// Runs until stopped through a [`ControlHandle`] or until the transport dies; returns the
    /// wake-up statistics.
    pub fn run(mut self) -> io::Result<Lateness> {
        set_timer_slack_1ns();
        if !self.started {
            self.power_on_all();
        }
        let result = self.run_loop();
        // How late the host ran the simulation (its frames kept their times): docs/CLOCK.md.
        tracing::info!(lateness = %self.lateness, events = self.events_late.count,
            events_late_max_us = self.events_late.max_us,
            events_late_over_1ms = self.events_late.over_1ms,
            frames_late_max_us = self.frames_late.max_us, "runtime stopped");
        result.map(|()| self.lateness)
    }

    /// Runs on a new thread.
    pub fn spawn(self) -> io::Result<RuntimeHandle> {
        let (tx, rx) = (self.tx.clone(), self.rx.clone());
        RuntimeHandle::spawn_loop(tx, rx, move |_| self.run())
    }

    fn run_loop(&mut self) -> io::Result<()> {
        // A stepped clock's runtime wakes when the clock is stepped.
        let stepped = (self.clock.driver() == Driver::Stepped).then(|| self.clock.subscribe());
        loop {
            self.advance(self.now())?;
            // Control requests.
            loop {
                match self.rx.try_recv() {
                    Ok(Msg::Stop) => return Ok(()),
                    Ok(Msg::Request(req, reply)) => {
                        // What was due before the request happens first: a measurement cycle
                        // that began before a magnet moved must not see the new position. The
                        // request is handled at the time that reached, never earlier.
                        let now = match self.advance(self.now()) {
                            Ok(now) => now,
                            Err(e) => {
                                let _ = reply
                                    .send(json!({"ok": false, "error": format!("transport: {e}")}));
                                return Err(e);
                            }
                        };
                        self.hold_at(now.micros() * 1000);
                        let answer = self.handle_request(req, now);
                        self.route(now);
                        self.hold_next();
                        let _ = reply.send(answer);
                    }
                    Err(_) => break,
                }
            }
            match &stepped {
                Some(steps) => {
                    if self.stash.is_none() {
                        wait_stepped(self.transport.receiver(), &self.rx, steps);
                    } else {
                        wait_stepped(&crossbeam_channel::never(), &self.rx, steps);
                    }
                }
                None => {
                    let deadline = self.deadline();
                    // A frame kept for its later time is due then, like a timer.
                    let deadline = match (&self.stash, deadline) {
                        (Some(rx), d) => {
                            let t = self.frame_time(rx);
                            Some(d.map_or(t, |d| d.min(t)))
                        }
                        (None, d) => d,
                    };
                    self.wait(deadline)?;
                }
            }
        }
    }

    /// The own events due at `now`: the transport's reports, power-on, the end of stalls,
    /// measurement cycles and node timers; what the nodes send goes out stamped `now`.
    fn turn(&mut self, now: Instant) {
        let received = std::mem::take(&mut self.received);
        self.watch_transport(now, received);
        for i in 0..self.devices.len() {
            let d = &mut self.devices[i];
            if d.power_on_at.is_some_and(|t| t <= now) {
                self.power_on_now(i, now);
            }
            let d = &mut self.devices[i];
            if d.stall_until.is_some_and(|t| t <= now) {
                d.stall_until = None;
                d.faults.retain(|f| *f != Fault::Stall);
                tracing::info!(sensor = %d.name, "stall over");
            }
        }
        for i in 0..self.devices.len() {
            if self.powered[i] {
                // The node's timers run in `route` (`Node::poll`), after every cycle's values.
                self.devices[i].run_cycles(now);
            } else {
                let d = &mut self.devices[i];
                while d.next_cycle <= now {
                    d.next_cycle = Instant::from_micros(d.next_cycle.micros() + d.cycle_us);
                }
            }
        }
        self.route(now);
    }

    /// Hands a frame to every node except `from`.
    fn deliver(&mut self, f: &Frame, from: Option<usize>, now: Instant) {
        for (i, d) in self.devices.iter_mut().enumerate() {
            if Some(i) != from && d.listening(now) {
                d.receive(f, now);
            }
        }
    }

    /// Runs the nodes' due timers and sends what they produce, to the transport and to the
    /// other local nodes, until no node has anything left (an answer may trigger another
    /// answer).
    fn route(&mut self, now: Instant) {
        let mut due = Vec::new();
        for _ in 0..1000 {
            let mut any = false;
            for i in 0..self.devices.len() {
                due.clear();
                self.devices[i].release(now, &mut due);
                while let Some(f) = self.devices[i].poll(now) {
                    if self.devices[i].bus_off {
                        self.devices[i].lost_bus_off += 1;
                        continue;
                    }
                    if let Some(f) = self.devices[i].hold(f, now) {
                        due.push(f);
                    }
                }
                self.devices[i].power_on_bootup = false;
                for f in due.drain(..) {
                    any = true;
                    self.devices[i].frames_sent += 1;
                    let port = match &mut self.devices[i].port {
                        Some(p) => p,
                        None => &mut self.transport,
                    };
                    if let Err(e) = port.send(&f) {
                        tracing::warn!(error = %e, "send failed");
                    }
                    self.deliver(&f, Some(i), now);
                }
            }
            if !any {
                return;
            }
        }
        tracing::warn!("frame routing did not settle after 1000 rounds");
    }

    fn deadline(&self) -> Option<Instant> {
        self.devices
            .iter()
            .zip(&self.powered)
            .flat_map(|(d, &p)| {
                let own = if p { d.deadline() } else { d.next_cycle };
                [Some(own), d.timing_deadline()]
            })
            .flatten()
            .chain(self.overrun_until)
            .chain(self.devices.iter().filter_map(|d| d.overflow_until))
            // Controller counters are looked at every few ms while sensors have their own.
            .chain(
                self.devices
                    .iter()
                    .any(|d| d.port.is_some())
                    .then_some(self.next_controller_look),
            )
            .min()
    }

    /// Reacts to what the transport reports about the bus: lost frames (CAN overrun EMCY
    /// 0x8110, cleared [`OVERRUN_HOLD`] after the last loss), the controller's error state
    /// (error passive 0x8120, recovered from bus-off 0x8140), and keeps its receive filter on
    /// the nodes' COB-IDs (re-checked after received frames, which may change them).
    fn watch_transport(&mut self, now: Instant, received: bool) {
        // The core reports these per model (EMCY codes and bytes, error register, TMI 0x1002);
        // lost frames are its "software buffer overflow" (0x8110), separate from the injectable
        // controller overrun (`can-overrun`), and error passive / bus-off are left alone while
        // the same fault is injected by hand.
        use canpos_encoder::Fault as Core;
        let dropped = self.transport.dropped();
        if dropped > self.drops_seen {
            tracing::warn!(
                lost = dropped - self.drops_seen,
                total = dropped,
                "CAN frames lost"
            );
            self.drops_seen = dropped;
            if self.overrun_until.is_none() {
                for d in &mut self.devices {
                    d.node.inject_fault(Core::CanBufferOverflow, true);
                }
            }
            self.overrun_until = Some(Instant::from_micros(
                now.micros() + OVERRUN_HOLD.as_micros() as u64,
            ));
        } else if self.overrun_until.is_some_and(|t| t <= now) {
            self.overrun_until = None;
            for d in &mut self.devices {
                d.node.inject_fault(Core::CanBufferOverflow, false);
            }
        }
        let reconnections = self.transport.reconnections();
        if reconnections != self.reconnections_seen {
            self.reconnections_seen = reconnections;
            // The bus is back after an outage (the server went away): the nodes boot again as
            // after a power cycle, and report the outage as their model reports the end of a
            // bus-off (EMCY 0x8140 on every model).
            tracing::warn!("bus back after an outage: the nodes boot again");
            for i in 0..self.devices.len() {
                if !(self.powered[i] || self.devices[i].power_on_at.is_some()) {
                    continue;
                }
                self.power_off(i);
                self.devices[i].sensor.power_cycle();
                self.power_on(i, now);
                if self.powered[i] {
                    let n = &mut self.devices[i].node;
                    n.inject_fault(Core::CanBusOff, true);
                    n.inject_fault(Core::CanBusOff, false);
                }
            }
            // The outage's bus-off ended with it; the fresh nodes start error-active.
            self.bus_state = self.transport.bus_state();
        }
        if now >= self.next_controller_look
            || self
                .devices
                .iter()
                .any(|d| d.overflow_until.is_some_and(|t| t <= now))
        {
            self.watch_controllers(now);
            self.next_controller_look = Instant::from_micros(now.micros() + CONTROLLER_POLL_US);
        }
        // Sensors with their own controllers report through them (above); the transport's
        // state is only asked for otherwise (on an in-process bus it runs the bus).
        let shared = self.devices.iter().all(|d| d.port.is_none());
        let state = if shared {
            self.transport.bus_state()
        } else {
            self.bus_state
        };
        if state != self.bus_state && shared {
            let old = std::mem::replace(&mut self.bus_state, state);
            tracing::warn!(from = ?old, to = ?state, "CAN controller state");
            for d in &mut self.devices {
                let passive = state == BusState::ErrorPassive;
                if (passive || old == BusState::ErrorPassive)
                    && !d.faults.contains(&Fault::ErrorPassive)
                {
                    d.node.inject_fault(Core::CanErrorPassive, passive);
                }
                // Leaving bus-off is the recovery the core reports (0x8140). The kernel keeps a
                // real controller off the bus; the runtime does not mute the node itself.
                if (state == BusState::BusOff || old == BusState::BusOff) && !d.bus_off {
                    d.node
                        .inject_fault(Core::CanBusOff, state == BusState::BusOff);
                }
            }
        }
        if self.kernel_filter && (received || self.filter.is_none()) {
            self.update_filter();
        }
    }

    /// Reacts to what each sensor's own controller reports (paced in-process buses): frames
    /// lost in its full transmit queue (the model's overflow reaction, held
    /// [`OVERRUN_HOLD`] after the last loss), collisions with a node sending the same
    /// identifier (CAN-ID collision), and its error state (error passive, bus-off, recovery).
    fn watch_controllers(&mut self, now: Instant) {
        use canpos_encoder::Fault as Core;
        // Sensors without their own controller share the transport's (one TCP connection to a
        // hub): its transmit-queue overflows, as the server reports them (issue 36 item 7).
        let shared_lost = self.transport.tx_overflows();
        for (i, d) in self.devices.iter_mut().enumerate() {
            let c = match &d.port {
                Some(p) => p.bus_stats().and_then(|s| s.controller),
                None => (shared_lost > 0).then(|| crate::bus::MemberStats {
                    lost_overflow: shared_lost,
                    ..Default::default()
                }),
            };
            let Some(c) = c else {
                continue;
            };
            let old = d.seen.unwrap_or_default();
            if c.lost_overflow > old.lost_overflow {
                if d.overflow_until.is_none() {
                    tracing::warn!(
                        sensor = i,
                        lost = c.lost_overflow - old.lost_overflow,
                        "transmit queue overflow: the bus cannot take this sensor's frames"
                    );
                    d.node.inject_fault(Core::TransmitOverflow, true);
                }
                d.overflow_until = Some(Instant::from_micros(
                    now.micros() + OVERRUN_HOLD.as_micros() as u64,
                ));
            } else if d.overflow_until.is_some_and(|t| t <= now) {
                d.overflow_until = None;
                d.node.inject_fault(Core::TransmitOverflow, false);
            }
            // One collision EMCY per OVERRUN_HOLD at most: a duplicate node collides at
            // every frame, and the report must not flood a bus that is already disturbed.
            if c.collisions > old.collisions && d.collision_quiet_until.is_none_or(|t| t <= now) {
                tracing::warn!(
                    sensor = i,
                    collisions = c.collisions,
                    "CAN-ID collision: another node sends this sensor's identifiers"
                );
                d.node.inject_fault(Core::CobIdCollision, true);
                d.collision_quiet_until = Some(Instant::from_micros(
                    now.micros() + OVERRUN_HOLD.as_micros() as u64,
                ));
            }
            if c.state != old.state {
                tracing::warn!(sensor = i, from = ?old.state, to = ?c.state, tec = c.tec, rec = c.rec,
                    "CAN controller state");
                let passive = c.state == BusState::ErrorPassive;
                if (passive || old.state == BusState::ErrorPassive)
                    && !d.faults.contains(&Fault::ErrorPassive)
                {
                    d.node.inject_fault(Core::CanErrorPassive, passive);
                }
                if (c.state == BusState::BusOff || old.state == BusState::BusOff) && !d.bus_off {
                    d.node
                        .inject_fault(Core::CanBusOff, c.state == BusState::BusOff);
                }
            }
            d.seen = Some(c);
        }
    }

    /// The standard COB-IDs the nodes listen to; remote frames always pass the filter.
    fn update_filter(&mut self) {
        let mut ids = vec![0x000, 0x7E5];
        for d in &mut self.devices {
            let id = u16::from(d.node.device().node_id());
            if (1..=127).contains(&id) {
                ids.extend([0x600 + id, 0x700 + id]);
            }
            let sync = d.node.read_object(0x1005, 0).unwrap_or(0x80);
            ids.push((sync & 0x7FF) as u16);
        }
        ids.sort_unstable();
        ids.dedup();
        if self.filter.as_ref() == Some(&ids) {
            return;
        }
        match self.transport.set_rx_filter(&ids) {
            Ok(true) => tracing::debug!(cob_ids = ?ids, "receive filter set"),
            Ok(false) => {}
            Err(e) => tracing::warn!(error = %e, "cannot set the receive filter"),
        }
        self.filter = Some(ids);
    }

    /// Sleeps until `deadline`, a received frame or a control message.
    fn wait(&mut self, deadline: Option<Instant>) -> io::Result<()> {
        let target = deadline.map(|d| self.to_std(d));
        if let Some(late) = wait_until(self.transport.receiver(), &self.rx, target) {
            self.lateness.record(late.as_micros() as u64);
        }
        Ok(())
    }
}

mod clock;
mod device;
mod requests;
mod wait;

use device::SimDevice;
pub use device::{HardwareStats, SensorSetup, SimHardware, AUTOBAUD_FRAMES, STORE_TIME};
use wait::wait_stepped;
pub(crate) use wait::wait_until;
pub use wait::{Lateness, EARLY_WAKE};

#[cfg(test)]
mod hardware_tests;
#[cfg(test)]
mod tests;
