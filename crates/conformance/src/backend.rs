//! The two ways the harness reaches a device: a [`VirtualDut`] (a `canpos_stack::Node` on a
//! virtual clock, deterministic and as fast as the CPU) and a [`SocketcandDut`] (a real-time
//! `canpos_host` runtime behind an in-process socketcand hub, reached over TCP like any tool).

use std::collections::VecDeque;
use std::time::Duration as StdDuration;

use canpos_encoder::{Fault, Sample};
use canpos_host::runtime::{Runtime, RuntimeHandle, SensorSetup, SimHardware};
use canpos_host::socketcand::{Client, Hub, HubHandle};
use canpos_host::Transport;
use canpos_models::{Model, SensorNode};
use canpos_stack::storage::RamStorage;
use canpos_stack::{Frame, Instant, Node};

/// A device under test as the harness sees it: frames in and out on a clock in µs.
pub trait Backend {
    /// The product model of the device.
    fn model(&self) -> &'static Model;
    /// Puts `f` on the bus.
    fn send(&mut self, f: &Frame);
    /// The harness clock (µs since the back end started).
    fn now_us(&mut self) -> u64;
    /// The next frame the device sends, waiting at most until `deadline_us`; `None` when the
    /// deadline passed (the clock then reads at least `deadline_us`).
    fn recv_until(&mut self, deadline_us: u64) -> Option<(u64, Frame)>;
    /// Power off and on again (stored data reload, boot-up). `false` when not supported.
    fn power_cycle(&mut self) -> bool;
    /// Feeds one measurement sample (moves the magnets). `false` when not supported.
    fn update_sample(&mut self, s: &Sample) -> bool;
    /// Injects or removes a sensor fault. `false` when not supported.
    fn inject_fault(&mut self, fault: Fault, active: bool) -> bool;
    /// Whether time runs on a virtual clock (cases may then wait for long windows for free).
    fn is_virtual(&self) -> bool;
}

/// A `Node` with RAM storage on a virtual clock: time only moves when the harness waits, and
/// then jumps from one node deadline to the next, so a 10 s window costs microseconds.
pub struct VirtualDut {
    node: SensorNode<RamStorage>,
    /// The store time of "save" / "load" (D7), as the host runtime's sensors have it.
    hw: SimHardware,
    now: u64,
    rx: VecDeque<(u64, Frame)>,
}

impl VirtualDut {
    /// A powered-on node of `model` with its default configuration (boot-up queued).
    pub fn new(model: &'static Model) -> VirtualDut {
        let mut node = Node::new(model, model.default_config, RamStorage::default());
        node.power_on(Instant::ZERO);
        let mut d = VirtualDut {
            node,
            hw: SimHardware::default(),
            now: 0,
            rx: VecDeque::new(),
        };
        d.drain();
        d
    }

    /// The node itself (white-box checks next to the black-box cases).
    pub fn node(&mut self) -> &mut SensorNode<RamStorage> {
        &mut self.node
    }

    fn drain(&mut self) {
        while let Some(f) = self.hw.poll(&mut self.node, Instant::from_micros(self.now)) {
            self.rx.push_back((self.now, f));
        }
    }
}

impl Backend for VirtualDut {
    fn model(&self) -> &'static Model {
        self.node.device().model()
    }
    fn send(&mut self, f: &Frame) {
        self.hw
            .receive(&mut self.node, f, Instant::from_micros(self.now));
        self.drain();
    }
    fn now_us(&mut self) -> u64 {
        self.now
    }
    fn recv_until(&mut self, deadline_us: u64) -> Option<(u64, Frame)> {
        // A bound on deadlines that fire without producing a frame, so a core bug cannot hang
        // the suite.
        let mut spins = 0u32;
        loop {
            if let Some(x) = self.rx.pop_front() {
                return Some(x);
            }
            let next = [self.node.poll_timeout(), self.hw.deadline()];
            match next.into_iter().flatten().min() {
                Some(t) if t.micros() <= deadline_us && spins < 1_000_000 => {
                    spins += 1;
                    self.now = self.now.max(t.micros());
                    self.node.handle_timeout(Instant::from_micros(self.now));
                    self.drain();
                }
                _ => {
                    self.now = self.now.max(deadline_us);
                    self.node.handle_timeout(Instant::from_micros(self.now));
                    self.drain();
                    return self.rx.pop_front();
                }
            }
        }
    }
    fn power_cycle(&mut self) -> bool {
        self.node.power_off();
        self.rx.clear();
        self.node.power_on(Instant::from_micros(self.now));
        self.drain();
        true
    }
    fn update_sample(&mut self, s: &Sample) -> bool {
        self.node.update_sample(s, Instant::from_micros(self.now));
        self.drain();
        true
    }
    fn inject_fault(&mut self, fault: Fault, active: bool) -> bool {
        self.node.inject_fault(fault, active);
        self.drain();
        true
    }
    fn is_virtual(&self) -> bool {
        true
    }
}

/// A real-time device: an in-process socketcand hub on a free loopback port, a
/// `canpos_host::runtime` sensor attached to it over TCP, and the harness as a second TCP
/// client. In-process rather than spawning the release binary so the suite needs no prior
/// `cargo build --release` and cannot leave processes behind.
pub struct SocketcandDut {
    model: &'static Model,
    client: Client,
    epoch: std::time::Instant,
    // Dropped in this order: the runtime stops before the hub goes away.
    _runtime: RuntimeHandle,
    _hub: HubHandle,
    _state: tempfile::TempDir,
}

/// A per-run state directory for the runtime's file storage, removed on drop.
impl SocketcandDut {
    /// Starts hub and device and waits for the device's boot-up message.
    pub fn start(model: &'static Model) -> std::io::Result<SocketcandDut> {
        let hub = Hub::bind("127.0.0.1:0")?.spawn()?;
        let addr = hub.local_addr();
        let client = Client::connect(addr, "can0")?;
        let dev_tx = Client::connect(addr, "can0")?;
        let cfg = model.default_config;
        let stroke = f64::from(cfg.stroke_mm);
        let spec = match model.name {
            "th" => canpos_sim::SensorSpec::th(stroke, 1),
            "e-series" => canpos_sim::SensorSpec::e_series(canpos_sim::Variant::Ep, stroke, 1),
            _ => canpos_sim::SensorSpec::tmi(stroke, 1),
        }
        .map_err(|e| std::io::Error::other(e.to_string()))?;
        // A private directory (random name, created exclusively), removed with the DUT.
        let state_dir = tempfile::Builder::new()
            .prefix(&format!("canpos-conformance-{}-", model.name))
            .tempdir()?;
        let state = state_dir.path().to_path_buf();
        let mut rt = Runtime::new(Box::new(dev_tx), None);
        rt.add(SensorSetup {
            name: format!("conformance-{}", model.name),
            model,
            cfg,
            spec,
            seed: 1,
            ideal: true,
            motion: Box::new(canpos_sim::motion::Profiles::new(vec![
                canpos_sim::motion::Profile::Static {
                    pos_mm: stroke / 2.0,
                },
            ])),
            storage: canpos_host::file_storage::FileStorage::new(state.join("dut.bin")),
        });
        let epoch = std::time::Instant::now();
        let runtime = rt.spawn()?;
        let mut d = SocketcandDut {
            model,
            client,
            epoch,
            _runtime: runtime,
            _hub: hub,
            _state: state_dir,
        };
        // The runtime may power on before the harness client's subscription is complete, so
        // the boot-up is not awaited; a reset node gives a defined start instead.
        let t = d.now_us() + 50_000;
        let _ = d.recv_until(t);
        Ok(d)
    }
}

impl Backend for SocketcandDut {
    fn model(&self) -> &'static Model {
        self.model
    }
    fn send(&mut self, f: &Frame) {
        self.client.send(f).expect("socketcand send");
    }
    fn now_us(&mut self) -> u64 {
        self.epoch.elapsed().as_micros() as u64
    }
    fn recv_until(&mut self, deadline_us: u64) -> Option<(u64, Frame)> {
        let deadline = self.epoch + StdDuration::from_micros(deadline_us);
        match self.client.recv_deadline(deadline) {
            // Stamped on arrival: the hub's timestamps are wall-clock, the harness clock is
            // monotonic; loopback latency is far below the tolerances checked.
            Ok(Some(rx)) => Some((self.now_us(), rx.frame)),
            _ => None,
        }
    }
    fn power_cycle(&mut self) -> bool {
        false
    }
    fn update_sample(&mut self, _s: &Sample) -> bool {
        false
    }
    fn inject_fault(&mut self, _fault: Fault, _active: bool) -> bool {
        false
    }
    fn is_virtual(&self) -> bool {
        false
    }
}
