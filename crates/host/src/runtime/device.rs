//! The device wrapper: one simulated sensor inside the runtime ([`SimDevice`]: its node, its
//! sensor and motion, its injected faults, its timing, its own controller) and what builds it
//! ([`SensorSetup`]).

use std::time::Duration;

use canpos_models::{DeviceConfig, Model, SensorNode};
use canpos_sim::motion::{LiveHandle, LiveMotion, Motion};
use canpos_sim::{Sensor, SensorSpec};
use canpos_stack::storage::Storage;
use canpos_stack::{Application, Frame, Instant, Node};
use serde_json::{json, Value};

use crate::can::Transport;
use crate::control::request::Fault;
use crate::file_storage::FileStorage;
use crate::timing::{DeviceTiming, Jitter};

/// Minimum time a store takes before its SDO answer leaves (D7): what a firmware's flash takes
/// by itself.
pub const STORE_TIME: canpos_stack::Duration = canpos_stack::Duration::from_millis(20);

/// Frames a controller in autobaud hears before it has the bus's bit rate (TMI R19:
/// "continuous traffic of 4–5 messages").
pub const AUTOBAUD_FRAMES: u8 = 4;

/// What [`SimHardware`] counted.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct HardwareStats {
    /// Frames received while the node's bit rate differed from the bus.
    pub rx_wrong_bitrate: u32,
    /// Frames the node produced and that never reached the bus: while its bit rate differed
    /// from the bus, and during a bit-rate switch (the core's [`canpos_stack::Stats::tx_silenced`]).
    pub tx_wrong_bitrate: u32,
}

/// What a firmware's hardware does by itself and a simulated node needs done around it: the
/// CAN controller on a bus of a given bit rate (frames lost both ways while the node's rate
/// differs; autobaud detecting the bus's rate after [`AUTOBAUD_FRAMES`] frames) and the store
/// time of "save" / "load" (D7: their SDO answer waits [`STORE_TIME`] after the request).
///
/// The node goes through it both ways: [`SimHardware::receive`] for every frame from the bus,
/// [`SimHardware::poll`] in place of [`Node::poll`], and the host wakes for
/// [`SimHardware::deadline`] too. It reads only what the node reports (its active bit rate, its
/// store and reset counts, its queue length): no CANopen frame is decoded here.
#[derive(Debug, Default)]
pub struct SimHardware {
    /// The bus's bit rate in kbit/s (`None`: unknown, the node's own).
    bus_kbps: Option<u16>,
    /// Frames heard while the node waits for its bit rate (autobaud).
    autobaud_frames: u8,
    rx_wrong_bitrate: u32,
    tx_wrong_bitrate: u32,
    /// The store answer is the frame the node sends after this many more, and the store's
    /// request arrived then; with the node's reset count then.
    store_answer: Option<(usize, Instant, u8)>,
    /// A store's answer waiting out the store time: when it is due, the frame, the node's reset
    /// count when it was held (a reset drops it, as it drops a transfer in progress).
    held: Option<(Instant, Frame, u8)>,
    /// The held answer, due: it goes out after this many more of the node's frames.
    release: Option<(usize, Frame)>,
}

impl SimHardware {
    /// On a bus of `kbps` kbit/s (`None`: unknown).
    pub fn new(kbps: Option<u16>) -> SimHardware {
        SimHardware {
            bus_kbps: kbps,
            ..SimHardware::default()
        }
    }

    /// The bus the node is attached to now runs `kbps` kbit/s (`None`: unknown).
    pub fn set_bus_bitrate(&mut self, kbps: Option<u16>) {
        self.bus_kbps = kbps;
    }

    /// The bus's bit rate in kbit/s, if known.
    pub fn bus_bitrate(&self) -> Option<u16> {
        self.bus_kbps
    }

    /// What was counted, with the frames the node lost during a bit-rate switch.
    pub fn stats<A: Application, S: Storage>(&self, node: &Node<A, S>) -> HardwareStats {
        HardwareStats {
            rx_wrong_bitrate: self.rx_wrong_bitrate,
            tx_wrong_bitrate: self
                .tx_wrong_bitrate
                .wrapping_add(node.device().stats().tx_silenced),
        }
    }

    /// Whether the node and the bus run different bit rates now.
    fn mismatch<A: Application, S: Storage>(&self, node: &Node<A, S>) -> bool {
        self.bus_kbps
            .is_some_and(|bus| bus != node.device().bitrate())
    }

    /// A frame from the bus at `now`. A node that hears (powered, not switching its bit rate)
    /// at another bit rate than the bus's does not get it; one in autobaud counts it towards
    /// detecting the bus's rate.
    pub fn receive<A: Application, S: Storage>(
        &mut self,
        node: &mut Node<A, S>,
        f: &Frame,
        now: Instant,
    ) {
        if let Some(bus) = self.bus_kbps.filter(|_| node.hears(now)) {
            if node.device().bitrate() == 0 {
                self.autobaud_frames = self.autobaud_frames.saturating_add(1);
                if self.autobaud_frames >= AUTOBAUD_FRAMES {
                    node.bitrate_detected(bus, now);
                }
                return;
            }
            // A new autobaud (after a reset to it) starts counting afresh.
            self.autobaud_frames = 0;
            if bus != node.device().bitrate() {
                self.rx_wrong_bitrate = self.rx_wrong_bitrate.wrapping_add(1);
                return;
            }
        }
        let before = node.device().stats();
        let ahead = node.device().queued();
        node.handle_frame(f, now);
        let after = node.device().stats();
        if after.stores != before.stores {
            // The answer is the first frame this one queued (`Stats::stores`).
            self.store_answer = Some((ahead, now, after.resets));
        }
    }

    /// The next frame for the bus at `now`, in place of [`Node::poll`]: a store's answer waits
    /// out the store time; what the node sends while its bit rate differs from the bus's is
    /// lost and counted.
    pub fn poll<A: Application, S: Storage>(
        &mut self,
        node: &mut Node<A, S>,
        now: Instant,
    ) -> Option<Frame> {
        if self.release.is_none() {
            if let Some((_, f, resets)) = self.held.take_if(|(due, _, _)| *due <= now) {
                let d = node.device();
                // A node powered off sends nothing until its power-on, which resets it; a reset
                // forgets the answer as it forgets a transfer; a stopped node serves no SDO.
                let serves = d.stats().resets == resets && d.nmt_state().sdo_allowed();
                if d.powered() && serves {
                    // Out where the node's own timer would have queued it: behind what waits.
                    self.release = Some((d.queued(), f));
                }
            }
        }
        loop {
            let f = match self.release {
                Some((0, f)) => {
                    self.release = None;
                    // Queued by the node it would have been lost during a bit-rate switch.
                    if !node.hears(now) || self.mismatch(node) {
                        self.tx_wrong_bitrate = self.tx_wrong_bitrate.wrapping_add(1);
                        continue;
                    }
                    return Some(f);
                }
                _ => match node.poll(now) {
                    Some(f) => {
                        if let Some((n, _)) = &mut self.release {
                            *n -= 1;
                        }
                        f
                    }
                    None => {
                        // Whatever was queued is out, or was lost with the queue.
                        self.store_answer = None;
                        if self.release.take().is_some() {
                            self.tx_wrong_bitrate = self.tx_wrong_bitrate.wrapping_add(1);
                        }
                        return None;
                    }
                },
            };
            if let Some((n, at, resets)) = self.store_answer {
                if n == 0 {
                    self.store_answer = None;
                    self.held = Some((at + STORE_TIME, f, resets));
                    continue;
                }
                self.store_answer = Some((n - 1, at, resets));
            }
            if self.mismatch(node) {
                self.tx_wrong_bitrate = self.tx_wrong_bitrate.wrapping_add(1);
                continue;
            }
            return Some(f);
        }
    }

    /// When [`SimHardware::poll`] has a held answer to send.
    pub fn deadline(&self) -> Option<Instant> {
        self.held.map(|(due, _, _)| due)
    }
}

/// Everything needed to build one simulated sensor.
pub struct SensorSetup {
    /// Label for logs and the control interface (e.g. `th-17143876`).
    pub name: String,
    /// The CANopen model.
    pub model: &'static Model,
    /// Unit configuration (node-id, bit rate, serial, stroke, steps, channels, cycle).
    pub cfg: DeviceConfig,
    /// Technical data for the measurement model.
    pub spec: SensorSpec,
    /// Seed of the unit's errors and noise.
    pub seed: u64,
    /// No measurement errors at all.
    pub ideal: bool,
    /// Where the magnets are (static positions, a profile, a CSV trajectory).
    pub motion: Box<dyn Motion>,
    /// Non-volatile storage of the node.
    pub storage: FileStorage,
}

/// One simulated sensor inside the runtime.
pub(super) struct SimDevice {
    pub(super) name: String,
    pub(super) node: SensorNode<FileStorage>,
    /// Its CAN controller's bit rate and autobaud, its flash's store time: every frame in and
    /// out of `node` goes through it.
    pub(super) hw: SimHardware,
    pub(super) sensor: Sensor,
    pub(super) motion: LiveMotion,
    pub(super) live: LiveHandle,
    pub(super) cycle_us: u64,
    /// Next measurement cycle (absolute).
    pub(super) next_cycle: Instant,
    /// Time origin of the motion source.
    pub(super) t0: Instant,
    pub(super) faults: Vec<Fault>,
    /// Bus-off: the CAN controller neither sends nor receives.
    pub(super) bus_off: bool,
    /// Frames the node produced while in (injected) bus-off: never sent, counted here.
    pub(super) lost_bus_off: u64,
    pub(super) last_true: Vec<Option<f64>>,
    pub(super) frames_sent: u64,
    /// The temperature condition as last told to the core.
    pub(super) temp_alarm: bool,
    /// SDO response delay, boot delays ([`DeviceTiming`]).
    pub(super) timing: DeviceTiming,
    pub(super) jitter: Jitter,
    /// SDO responses waiting out their delay, with when each is due (in order).
    pub(super) held: std::collections::VecDeque<(Instant, Frame)>,
    /// Powered, booting: the node starts (and sends its boot-up) then.
    pub(super) power_on_at: Option<Instant>,
    /// Rebooting after an NMT reset: deaf and silent until then, then this boot-up.
    pub(super) rebooting: Option<(Instant, Frame)>,
    /// The boot-up the node sends next comes from power-on (whose delay has passed).
    pub(super) power_on_bootup: bool,
    /// `stall` fault: the node takes no frames until then.
    pub(super) stall_until: Option<Instant>,
    /// Its own CAN controller on a paced bus (transmit queue, error counters); `None`: the
    /// runtime's transport is the controller of all its sensors.
    pub(super) port: Option<Box<dyn Transport>>,
    /// The controller's counters as last seen.
    pub(super) seen: Option<crate::bus::MemberStats>,
    /// While its transmit queue overflows: when the overflow reaction ends.
    pub(super) overflow_until: Option<Instant>,
    /// Measurement cycles never run because the runtime was stopped longer than the clock's
    /// stall bound ([`crate::clock::STALL_BOUND`]); shorter stalls skip none.
    pub(super) cycles_skipped: u64,
    /// No further collision report before then.
    pub(super) collision_quiet_until: Option<Instant>,
}

impl SimDevice {
    pub(super) fn new(s: SensorSetup, now: Instant) -> SimDevice {
        let cycle_us = u64::from(s.cfg.cycle_us.max(100));
        let motion = LiveMotion::new(s.motion);
        let live = motion.handle();
        SimDevice {
            name: s.name,
            node: Node::new(s.model, s.cfg, s.storage),
            hw: SimHardware::default(),
            sensor: Sensor::new(s.spec, s.seed, s.ideal),
            motion,
            live,
            cycle_us,
            next_cycle: now,
            t0: now,
            faults: Vec::new(),
            bus_off: false,
            lost_bus_off: 0,
            last_true: Vec::new(),
            frames_sent: 0,
            temp_alarm: false,
            timing: DeviceTiming::default(),
            jitter: Jitter::new(s.seed),
            held: std::collections::VecDeque::new(),
            power_on_at: None,
            rebooting: None,
            power_on_bootup: false,
            stall_until: None,
            port: None,
            seen: None,
            overflow_until: None,
            collision_quiet_until: None,
            cycles_skipped: 0,
        }
    }

    /// Whether the node takes frames from the bus now (not rebooting, not stalled).
    pub(super) fn listening(&self, now: Instant) -> bool {
        !self.bus_off && self.rebooting.is_none() && self.stall_until.is_none_or(|t| t <= now)
    }

    /// A frame from the bus at `now` (see [`SimHardware::receive`]).
    pub(super) fn receive(&mut self, f: &Frame, now: Instant) {
        self.hw.receive(&mut self.node, f, now);
    }

    /// The node's next frame at `now` (see [`SimHardware::poll`]).
    pub(super) fn poll(&mut self, now: Instant) -> Option<Frame> {
        self.hw.poll(&mut self.node, now)
    }

    /// Applies the device timing to a frame the node wants to send: an SDO response waits
    /// for its delay, a boot-up after an NMT reset for the reset boot delay (the node is
    /// silent meanwhile). Returns the frame if it goes out now.
    pub(super) fn hold(&mut self, f: Frame, now: Instant) -> Option<Frame> {
        let id = u16::from(self.node.device().node_id());
        let std = if f.is_remote() { None } else { f.std_id() };
        if std == Some(0x700 + id) && f.data() == [0] {
            if self.power_on_bootup || self.timing.reset_boot_delay.is_zero() {
                return Some(f);
            }
            let due = Instant::from_micros(
                now.micros() + self.timing.reset_boot_delay.as_micros() as u64,
            );
            // Whatever the node had in flight before the reset is gone with it.
            self.held.clear();
            self.rebooting = Some((due, f));
            tracing::debug!(sensor = %self.name, ?due, "rebooting after reset");
            return None;
        }
        if self.rebooting.is_some() {
            return None;
        }
        if self.timing.delays_sdo() && std == Some(0x580 + id) {
            let wait = self.timing.sdo_delay + self.jitter.up_to(self.timing.sdo_jitter);
            let mut due = now.micros() + wait.as_micros() as u64;
            // Responses keep their order whatever the jitter drew.
            if let Some((last, _)) = self.held.back() {
                due = due.max(last.micros());
            }
            self.held.push_back((Instant::from_micros(due), f));
            return None;
        }
        Some(f)
    }

    /// Held frames whose time has come, in order.
    pub(super) fn release(&mut self, now: Instant, out: &mut Vec<Frame>) {
        if let Some((due, f)) = self.rebooting {
            if due <= now {
                self.rebooting = None;
                out.push(f);
            }
        }
        while self.held.front().is_some_and(|(due, _)| *due <= now) {
            if let Some((_, f)) = self.held.pop_front() {
                out.push(f);
            }
        }
    }

    /// The earliest time a held frame, a reboot or a stall ends.
    pub(super) fn timing_deadline(&self) -> Option<Instant> {
        [
            self.held.front().map(|(t, _)| *t),
            self.hw.deadline(),
            self.rebooting.map(|(t, _)| t),
            self.power_on_at,
            self.stall_until,
        ]
        .into_iter()
        .flatten()
        .min()
    }

    /// Runs the measurement cycles due at `now` (only called while powered). The runtime calls
    /// it at each cycle's own time, in order, however late the host is (docs/CLOCK.md).
    pub(super) fn run_cycles(&mut self, now: Instant) {
        while self.next_cycle <= now {
            let at = self.next_cycle;
            let t_s = at.micros().saturating_sub(self.t0.micros()) as f64 / 1e6;
            self.last_true = self.motion.positions_mm(t_s);
            // Motion values are validated where they are parsed; a non-finite position here
            // would still be a bug, and the measurement must not see it.
            for p in &mut self.last_true {
                if p.is_some_and(|v| !v.is_finite()) {
                    *p = None;
                }
            }
            // Nothing is published before the first measurement's pulse has returned.
            if let Some(sample) = self.sensor.cycle(t_s, &self.last_true) {
                self.node.update_sample(&sample, at);
            }
            self.sync_temperature();
            self.next_cycle = Instant::from_micros(at.micros() + self.cycle_us);
        }
    }

    /// Skips the cycles before `now` (the runtime was stopped past the stall bound); returns
    /// how many.
    pub(super) fn skip_cycles(&mut self, now: Instant) -> u64 {
        if self.next_cycle >= now {
            return 0;
        }
        let missed = (now.micros() - self.next_cycle.micros()) / self.cycle_us;
        self.next_cycle = Instant::from_micros(self.next_cycle.micros() + missed * self.cycle_us);
        self.cycles_skipped += missed;
        missed
    }

    /// Tells the core about the temperature condition when it changes: the sensor's own
    /// temperature outside its limits, or the injected over-temperature fault.
    pub(super) fn sync_temperature(&mut self) {
        let want =
            self.sensor.temperature_out_of_range() || self.faults.contains(&Fault::OverTemperature);
        if want != self.temp_alarm {
            self.temp_alarm = want;
            self.node
                .inject_fault(canpos_encoder::Fault::OverTemperature, want);
        }
    }

    pub(super) fn deadline(&self) -> Instant {
        match self.node.poll_timeout() {
            Some(t) if t < self.next_cycle => t,
            _ => self.next_cycle,
        }
    }
}

/// The `timing` part of a control answer, in ms.
pub(super) fn timing_json(t: &DeviceTiming) -> Value {
    let ms = |d: Duration| d.as_secs_f64() * 1e3;
    json!({
        "sdo_delay_ms": ms(t.sdo_delay),
        "sdo_jitter_ms": ms(t.sdo_jitter),
        "boot_delay_ms": ms(t.boot_delay),
        "reset_boot_delay_ms": ms(t.reset_boot_delay),
    })
}
