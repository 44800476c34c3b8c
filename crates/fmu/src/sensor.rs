//! The sensor FMU: one canpos unit – the CLI's [`Runtime`] with its [`SensorSetup`], the same
//! stack node and measurement model – on a stepped [`SimClock`] that only `fmi3DoStep` moves
//! (docs/CLOCK.md), its CAN controller an [`LsBusPort`] that turns frames into FMI-LS-BUS CAN
//! operations and back (docs/FMU.md).

use std::collections::VecDeque;
use std::io;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use canpos_host::can::{RxFrame, Transport};
use canpos_host::clock::{Horizon, SimClock};
use canpos_host::control::request::Request;
use canpos_host::crossbeam_channel::{self, Receiver, Sender, TrySendError};
use canpos_host::runtime::{state_file, SensorSetup};
use canpos_host::{FileStorage, Runtime};
use canpos_models::DeviceConfig;
use canpos_sim::motion::{Profile, Profiles};
use canpos_sim::SensorSpec;
use canpos_stack::{Frame, Instant};
use serde_json::Value as Json;

use crate::lsbus::{self, ArbitrationLostBehavior, CanStatus, Config, Op, TxBuffer};
use crate::model::{
    BusTerminal, Causality, Description, Discrete, FmuModel, StepResult, Value, VarType, Variable,
};
use crate::resource::Entries;

/// `maxSize` of `Rx_Data` / `Tx_Data`, bytes: 128 classic CAN frames of 8 bytes.
pub const BUS_DATA_MAX: usize = 128 * 24;
/// Frames the node may have waiting for the bus (its transmit queue); more are lost and
/// counted, as on a controller whose queue is full.
const OUTBOX_MAX: usize = 1024;
/// Frames received and not yet taken by the node (its receive queue); more are lost and
/// raise the CAN overrun EMCY (0x8110) as on a real controller.
const RX_QUEUE: usize = 256;
/// Frames sent and not yet confirmed, kept for a retransmission after Arbitration Lost.
const UNCONFIRMED_MAX: usize = 64;
/// The LS-BUS CAN MIME type of the terminal's binaries.
pub const CAN_MIME: &str = "application/org.fmi-standard.fmi-ls-bus.can; version=\"1.0.0\"";

// Value references (docs/FMU.md has the table).
const VR_NODE_ID: u32 = 1;
const VR_BITRATE: u32 = 2;
const VR_SERIAL: u32 = 3;
const VR_SEED: u32 = 4;
const VR_IDEAL: u32 = 5;
const VR_THERMAL: u32 = 6;
const VR_MAGNET: u32 = 100;
const VR_AMBIENT: u32 = 150;
const VR_FAULT: u32 = 160;
const VR_TRUE: u32 = 200;
const VR_REPORTED: u32 = 250;
const VR_NMT: u32 = 300;
const VR_ERROR_REGISTER: u32 = 301;
/// `CAN.Rx_Data`.
pub const VR_RX_DATA: u32 = 1000;
/// `CAN.Tx_Data`.
pub const VR_TX_DATA: u32 = 1001;
/// `CAN.Rx_Clock`.
pub const VR_RX_CLOCK: u32 = 1002;
/// `CAN.Tx_Clock`.
pub const VR_TX_CLOCK: u32 = 1003;

/// The fault switches, as Boolean inputs (the control interface's faults of the measurement).
const FAULTS: [(&str, &str); 6] = [
    ("missing_magnet", "missing-magnet"),
    ("extra_magnet", "extra-magnet"),
    ("magnets_too_close", "magnets-too-close"),
    ("sensor_error", "sensor-error"),
    ("supply_voltage", "supply-voltage"),
    ("over_temperature", "over-temperature"),
];

/// One sensor unit: a model with its default configuration, or an order code's.
#[derive(Debug, Clone)]
pub struct SensorUnit {
    /// The CANopen model.
    pub model: &'static canpos_models::Model,
    /// Unit configuration (node-id, bit rate, serial, stroke, channels, cycle).
    pub cfg: DeviceConfig,
    /// Technical data of the measurement model.
    pub spec: SensorSpec,
    /// The normalised order code, empty for a model's default unit.
    pub order_code: String,
}

fn sim_model(name: &str) -> Option<canpos_sim::Model> {
    canpos_sim::Model::ALL
        .into_iter()
        .find(|m| m.name() == name)
}

impl SensorUnit {
    /// A model's default unit (`th`, `e-series`, `tmi`), as `canpos run --model` makes it.
    pub fn for_model(name: &str) -> Result<SensorUnit, String> {
        let model = canpos_models::by_name(name).ok_or_else(|| {
            let known: Vec<_> = canpos_models::all().iter().map(|m| m.name).collect();
            format!("unknown model `{name}` (known: {})", known.join(", "))
        })?;
        let mut cfg = model.default_config;
        let sm = sim_model(name).ok_or_else(|| format!("no measurement model for `{name}`"))?;
        let spec = SensorSpec::for_model(sm, f64::from(cfg.stroke_mm), cfg.channels as usize)
            .map_err(|e| format!("{e:#}"))?;
        cfg.cycle_us = spec.cycle_time_us;
        Ok(SensorUnit {
            model,
            cfg,
            spec,
            order_code: String::new(),
        })
    }

    /// The unit an order code names, as `canpos run --order-code` makes it.
    pub fn for_order_code(code: &str) -> Result<SensorUnit, String> {
        let oc = canpos_sim::parse_order_code(code)
            .map_err(|e| format!("bad order code `{code}`: {e:#}"))?;
        let model = canpos_models::by_name(oc.model_name())
            .ok_or_else(|| format!("model `{}` is not in this build", oc.model_name()))?;
        let spec = oc.sensor_spec().map_err(|e| format!("{e:#}"))?;
        let mut cfg = model.default_config;
        cfg.stroke_mm = oc.stroke_mm.round() as u32;
        cfg.position_step_nm = oc.resolution_nm();
        cfg.channels = oc.magnets as u8;
        cfg.bitrate_kbps = oc.bit_rate_kbit as u16;
        cfg.cycle_us = spec.cycle_time_us;
        Ok(SensorUnit {
            model,
            cfg,
            spec,
            order_code: oc.normalized,
        })
    }

    pub(crate) fn from_entries(e: &Entries) -> Result<SensorUnit, String> {
        e.only(&["kind", "model", "order_code"])?;
        match (e.get("model"), e.get("order_code")) {
            (Some(_), Some(_)) => Err("give either `model` or `order_code`, not both".into()),
            (Some(m), None) => Self::for_model(m),
            (None, Some(c)) => Self::for_order_code(c),
            (None, None) => Err("a sensor needs `model` or `order_code`".into()),
        }
    }

    pub(crate) fn resource_entries(&self) -> Vec<(&'static str, String)> {
        let mut v = vec![("kind", "sensor".to_string())];
        if self.order_code.is_empty() {
            v.push(("model", self.model.name.to_string()));
        } else {
            v.push(("order_code", self.order_code.clone()));
        }
        v
    }

    fn channels(&self) -> usize {
        usize::from(self.cfg.channels.max(1))
    }

    /// Default magnet positions: one per channel, spread over the stroke (as `canpos run`).
    pub fn default_magnets(&self) -> Vec<f64> {
        let n = self.channels() as f64;
        (0..self.channels())
            .map(|k| self.spec.stroke_mm * (k as f64 + 1.0) / (n + 1.0))
            .collect()
    }

    /// The unit's name: `canpos_th`, or the order code.
    pub fn identifier(&self) -> String {
        if self.order_code.is_empty() {
            format!("canpos_{}", self.model.name.replace('-', "_"))
        } else {
            format!("canpos_{}", self.order_code.to_ascii_lowercase())
        }
    }

    /// The unit's EDS (its dictionary), for `documentation/`.
    pub fn eds(&self, file_name: &str) -> Result<String, String> {
        let info = canpos_stack::eds::EdsInfo {
            file_name,
            order_code: &self.order_code,
            ..Default::default()
        };
        let mut text = String::new();
        canpos_stack::eds::write_eds(&mut text, self.model, &self.cfg, &info)
            .map_err(|_| "formatting the EDS failed".to_string())?;
        Ok(text)
    }

    pub(crate) fn description(&self, token: String) -> Result<Description, String> {
        use Causality::*;
        let c = &self.cfg;
        let mut v = vec![
            Variable::time(),
            Variable::new("node_id", VR_NODE_ID, VarType::UInt8, Parameter,
                "CANopen node-id (1…127, 255 = unconfigured); the unit's 0x2000 until stored otherwise")
                .start(c.node_id.to_string()),
            Variable::new("bitrate", VR_BITRATE, VarType::UInt16, Parameter,
                "bit rate of the bus, kbit/s (the node falls silent on another bit rate than its own)")
                .start(c.bitrate_kbps.to_string()),
            Variable::new("serial_number", VR_SERIAL, VarType::UInt32, Parameter, "serial number (0x1018 sub 4)")
                .start(c.serial.to_string()),
            Variable::new("seed", VR_SEED, VarType::UInt64, Parameter, "seed of the unit's errors and noise")
                .start(c.serial.to_string()),
            Variable::new("ideal", VR_IDEAL, VarType::Boolean, Parameter, "no measurement errors at all")
                .start("false"),
            Variable::new("thermal_time_scale", VR_THERMAL, VarType::Float64, Parameter,
                "factor on the thermal time constants (0 < k ≤ 1e6)")
                .start("1"),
        ];
        for (i, mm) in self.default_magnets().into_iter().enumerate() {
            v.push(
                Variable::new(
                    format!("magnet_position[{}]", i + 1),
                    VR_MAGNET + i as u32,
                    VarType::Float64,
                    Input,
                    format!(
                        "position of magnet {} on the rod, mm from the zero point",
                        i + 1
                    ),
                )
                .start(format!("{mm}"))
                .unit("mm"),
            );
        }
        v.push(
            Variable::new(
                "ambient_temperature",
                VR_AMBIENT,
                VarType::Float64,
                Input,
                "ambient temperature, °C",
            )
            .start(format!("{}", canpos_sim::DEFAULT_AMBIENT_C))
            .unit("degC"),
        );
        for (i, (name, fault)) in FAULTS.iter().enumerate() {
            // The runtime refuses magnets-too-close on one channel (it needs two magnets).
            if *fault == "magnets-too-close" && self.channels() < 2 {
                continue;
            }
            v.push(
                Variable::new(
                    format!("fault_{name}"),
                    VR_FAULT + i as u32,
                    VarType::Boolean,
                    Input,
                    format!(
                        "the control interface's `{fault}` fault (channel 1, default parameter)"
                    ),
                )
                .start("false"),
            );
        }
        for i in 0..self.channels() {
            v.push(
                Variable::new(
                    format!("true_position[{}]", i + 1),
                    VR_TRUE + i as u32,
                    VarType::Float64,
                    Output,
                    format!(
                        "true position of magnet {} at the last measurement, mm",
                        i + 1
                    ),
                )
                .unit("mm"),
            );
        }
        for i in 0..self.channels() {
            v.push(
                Variable::new(
                    format!("reported_position[{}]", i + 1),
                    VR_REPORTED + i as u32,
                    VarType::Float64,
                    Output,
                    format!(
                        "position value 0x6020 sub {} in mm (NaN when unreadable)",
                        i + 1
                    ),
                )
                .unit("mm"),
            );
        }
        v.push(Variable::new("nmt_state", VR_NMT, VarType::UInt8, Output,
            "NMT state as in the heartbeat: 0 initialising, 4 stopped, 5 operational, 127 pre-operational"));
        v.push(Variable::new(
            "error_register",
            VR_ERROR_REGISTER,
            VarType::UInt8,
            Output,
            "error register 0x1001",
        ));
        v.extend(lsbus_variables("CAN", VR_RX_DATA));
        let id = self.identifier();
        let eds_name = format!("{id}.eds");
        let eds = self.eds(&eds_name)?;
        Ok(Description {
            model_name: if self.order_code.is_empty() {
                format!("canpos {} CANopen position sensor", self.model.name)
            } else {
                format!("canpos {} ({})", self.order_code, self.model.name)
            },
            model_identifier: id,
            description: format!(
                "canpos software twin of a {} CANopen position sensor on an FMI-LS-BUS CAN terminal",
                self.model.name
            ),
            token,
            variables: v,
            terminals: vec![BusTerminal { name: "CAN".into() }],
            is_bus_simulation: false,
            documentation: vec![(eds_name, eds)],
            step_size: 0.001,
        })
    }
}

/// The four variables of an LS-BUS CAN terminal named `prefix`, value references `vr0..vr0+3`
/// (`Rx_Data`, `Tx_Data`, `Rx_Clock`, `Tx_Clock`), as a node sees them.
pub fn lsbus_variables(prefix: &str, vr0: u32) -> Vec<Variable> {
    let data = |name: &str, vr: u32, causality, clock: u32, what: &str| {
        let mut v = Variable::new(
            format!("{prefix}.{name}"),
            vr,
            VarType::Binary,
            causality,
            what,
        );
        v.clocks = Some(clock);
        v.mime_type = Some(CAN_MIME);
        v.max_size = Some(BUS_DATA_MAX);
        if causality == Causality::Input {
            v.start = Some(String::new());
        }
        v
    };
    vec![
        data(
            "Rx_Data",
            vr0,
            Causality::Input,
            vr0 + 2,
            "LS-BUS CAN operations from the bus",
        ),
        data(
            "Tx_Data",
            vr0 + 1,
            Causality::Output,
            vr0 + 3,
            "LS-BUS CAN operations to the bus",
        ),
        Variable::new(
            format!("{prefix}.Rx_Clock"),
            vr0 + 2,
            VarType::Clock,
            Causality::Input,
            "ticks when Rx_Data holds operations",
        ),
        Variable::new(
            format!("{prefix}.Tx_Clock"),
            vr0 + 3,
            VarType::Clock,
            Causality::Output,
            "ticks when Tx_Data holds operations",
        ),
    ]
}

/// What the node sent and the bus has not taken yet, with the send times (ns).
#[derive(Default)]
struct Outbox {
    frames: VecDeque<(u64, Frame)>,
    lost: u64,
}

/// The sensor's CAN controller in the FMU: frames the runtime sends wait in the outbox for
/// `Tx_Data`; frames from `Rx_Data` arrive through the receive queue, stamped with the
/// simulation time they were on the bus.
pub struct LsBusPort {
    clock: SimClock,
    outbox: Arc<Mutex<Outbox>>,
    rx: Receiver<RxFrame>,
    rx_lost: Arc<AtomicU64>,
    kbps: u32,
    /// Frames its controller's transmit queue lost (see `UNCONFIRMED_MAX`).
    tx_lost: Arc<AtomicU64>,
}

impl Transport for LsBusPort {
    fn send(&mut self, frame: &Frame) -> io::Result<()> {
        // A participant's send time is its horizon: the clock's `now` (docs/CLOCK.md).
        let at = self.clock.now();
        let mut o = self.outbox.lock().unwrap_or_else(|p| p.into_inner());
        if o.frames.len() >= OUTBOX_MAX {
            o.lost += 1;
        } else {
            o.frames.push_back((at, *frame));
        }
        Ok(())
    }
    fn receiver(&self) -> &Receiver<RxFrame> {
        &self.rx
    }
    fn bus_bitrate(&self) -> Option<u32> {
        Some(self.kbps)
    }
    fn dropped(&self) -> u64 {
        self.rx_lost.load(Ordering::Relaxed)
    }
    // The runtime raises its sensor's transmit-overflow reaction on these (0x8110, the TMI's
    // 0x6000), as for a hub client's reported overflows (docs/BUS.md).
    fn tx_overflows(&self) -> u64 {
        self.tx_lost.load(Ordering::Relaxed)
    }
    fn join_clock(&mut self) -> Option<Horizon> {
        Some(self.clock.participant("fmu sensor"))
    }
    fn describe(&self) -> String {
        "fmi-ls-bus CAN terminal".into()
    }
}

/// The runtime and what the FMU holds of its controller.
struct Running {
    rt: Runtime,
    clock: SimClock,
    outbox: Arc<Mutex<Outbox>>,
    rx: Sender<RxFrame>,
    rx_lost: Arc<AtomicU64>,
    tx_lost: Arc<AtomicU64>,
    // The unit's state file lives here for the instance's life (removed with it).
    _dir: tempfile::TempDir,
}

#[derive(Debug, Clone, Copy)]
struct Params {
    node_id: u8,
    bitrate: u16,
    serial: u32,
    seed: u64,
    ideal: bool,
    thermal: f64,
}

/// The node's side of the bus as LS-BUS models it: its own error counters (ISO 11898-1
/// rules on the Bus Error and Confirm operations it is given) and its state.
#[derive(Debug)]
struct NodeBus {
    tec: u32,
    rec: u32,
    status: CanStatus,
    /// Bus-off since (ns): recovery after 128 × 11 recessive bits.
    bus_off_at: Option<u64>,
    unconfirmed: VecDeque<Frame>,
    configured: bool,
    /// The bus confirms frames (a Confirm came): only then are unconfirmed frames queued ones.
    confirms: bool,
}

/// A sensor FMU instance.
pub struct SensorFmu {
    unit: SensorUnit,
    desc: Description,
    params: Params,
    magnets: Vec<f64>,
    ambient: f64,
    faults: [bool; FAULTS.len()],
    applied_magnets: Vec<f64>,
    applied_ambient: f64,
    applied_faults: [bool; FAULTS.len()],
    run: Option<Running>,
    start: f64,
    /// Simulation time reached, µs since the start time.
    now_us: u64,
    rx_data: Vec<u8>,
    rx_clock: bool,
    tx: TxBuffer,
    tx_clock: bool,
    /// What `Tx_Data` shows (a copy taken when the clock ticked).
    tx_view: Vec<u8>,
    bus: NodeBus,
    state: Option<(u64, Json)>,
    log: Vec<String>,
}

impl SensorFmu {
    /// A new instance of `unit` (not yet running: that starts at the end of initialization).
    pub fn new(unit: SensorUnit, desc: Description) -> Result<SensorFmu, String> {
        let c = unit.cfg;
        let magnets = unit.default_magnets();
        Ok(SensorFmu {
            params: Params {
                node_id: c.node_id,
                bitrate: c.bitrate_kbps,
                serial: c.serial,
                seed: u64::from(c.serial),
                ideal: false,
                thermal: 1.0,
            },
            applied_magnets: magnets.clone(),
            magnets,
            ambient: canpos_sim::DEFAULT_AMBIENT_C,
            applied_ambient: canpos_sim::DEFAULT_AMBIENT_C,
            faults: [false; FAULTS.len()],
            applied_faults: [false; FAULTS.len()],
            unit,
            desc,
            run: None,
            start: 0.0,
            now_us: 0,
            rx_data: Vec::new(),
            rx_clock: false,
            tx: TxBuffer::new(BUS_DATA_MAX),
            tx_clock: false,
            tx_view: Vec::new(),
            bus: NodeBus {
                tec: 0,
                rec: 0,
                status: CanStatus::ErrorActive,
                bus_off_at: None,
                unconfirmed: VecDeque::new(),
                configured: false,
                confirms: false,
            },
            state: None,
            log: Vec::new(),
        })
    }

    fn build(&mut self) -> Result<Running, String> {
        let p = self.params;
        let clock = SimClock::stepped();
        let (tx, rx) = crossbeam_channel::bounded(RX_QUEUE);
        let outbox = Arc::new(Mutex::new(Outbox::default()));
        let rx_lost = Arc::new(AtomicU64::new(0));
        let tx_lost = Arc::new(AtomicU64::new(0));
        let port = LsBusPort {
            tx_lost: tx_lost.clone(),
            clock: clock.clone(),
            outbox: outbox.clone(),
            rx,
            rx_lost: rx_lost.clone(),
            kbps: u32::from(p.bitrate),
        };
        let mut rt = Runtime::new(Box::new(port), Some(u32::from(p.bitrate)));
        let dir = tempfile::Builder::new()
            .prefix("canpos-fmu-")
            .tempdir()
            .map_err(|e| format!("creating the unit's state directory: {e}"))?;
        let model = self.unit.model;
        let mut cfg = self.unit.cfg;
        cfg.node_id = p.node_id;
        cfg.bitrate_kbps = p.bitrate;
        cfg.serial = p.serial;
        let mut spec = self.unit.spec.clone();
        spec.thermal_time_constant_s *= p.thermal;
        spec.waveguide_time_constant_s *= p.thermal;
        let path = state_file(dir.path(), model.name, cfg.serial);
        let storage = FileStorage::open(&path)
            .map_err(|e| format!("opening {}: {e}", path.display()))?
            .for_model(model);
        rt.add(SensorSetup {
            name: format!("{}-{}", model.name, cfg.serial),
            model,
            cfg,
            spec,
            seed: p.seed,
            ideal: p.ideal,
            motion: Box::new(Profiles(
                self.magnets
                    .iter()
                    .map(|&pos_mm| Profile::Static { pos_mm })
                    .collect(),
            )),
            storage,
        });
        self.applied_magnets = self.magnets.clone();
        Ok(Running {
            rt,
            clock,
            outbox,
            rx: tx,
            rx_lost,
            tx_lost,
            _dir: dir,
        })
    }

    fn request(&mut self, req: Request) -> Result<(), String> {
        let Some(r) = self.run.as_mut() else {
            return Ok(());
        };
        let a = r.rt.request_now(req);
        self.state = None;
        if a["ok"] == Json::Bool(true) {
            Ok(())
        } else {
            Err(a["error"].as_str().unwrap_or("refused").to_string())
        }
    }

    /// Applies an input just set; if the runtime refuses it, `undo` puts the old value back,
    /// so a refused input changes nothing and does not block the inputs set after it.
    fn apply_or_undo(&mut self, undo: impl FnOnce(&mut Self)) -> Result<(), String> {
        if self.run.is_none() {
            return Ok(());
        }
        self.apply_inputs().inspect_err(|_| undo(self))
    }

    /// Hands the inputs that changed to the runtime, at the time reached.
    fn apply_inputs(&mut self) -> Result<(), String> {
        for i in 0..self.magnets.len() {
            if self.magnets[i].to_bits() != self.applied_magnets[i].to_bits() {
                self.request(Request::Magnet {
                    sensor: Some(0),
                    index: i,
                    mm: Some(self.magnets[i]),
                    velocity: None,
                })?;
                self.applied_magnets[i] = self.magnets[i];
            }
        }
        if self.ambient.to_bits() != self.applied_ambient.to_bits() {
            self.request(Request::Ambient {
                sensor: Some(0),
                celsius: self.ambient,
            })?;
            self.applied_ambient = self.ambient;
        }
        for (i, (_, fault)) in FAULTS.iter().enumerate() {
            if self.faults[i] != self.applied_faults[i] {
                self.request(Request::Fault {
                    sensor: Some(0),
                    name: fault.to_string(),
                    on: self.faults[i],
                    value: None,
                    channel: None,
                })?;
                self.applied_faults[i] = self.faults[i];
            }
        }
        Ok(())
    }

    fn state(&mut self) -> Option<&Json> {
        let now = self.now_us;
        if self.state.as_ref().is_none_or(|(t, _)| *t != now) {
            let r = self.run.as_mut()?;
            let s = r.rt.request_now(Request::State { sensor: Some(0) });
            self.state = Some((now, s));
        }
        self.state.as_ref().map(|(_, s)| s)
    }

    fn outbox_len(&self) -> usize {
        self.run.as_ref().map_or(0, |r| {
            r.outbox
                .lock()
                .unwrap_or_else(|p| p.into_inner())
                .frames
                .len()
        })
    }

    /// Moves what the node sent into `Tx_Data` (whole operations, as many as fit), with the
    /// LS-BUS configuration first; ticks `Tx_Clock` when there is anything.
    fn fill_tx(&mut self) {
        if !self.bus.configured {
            let bps = u32::from(self.params.bitrate) * 1000;
            let _ = self.tx.push(&Op::Configuration(Config::CanBaudrate(bps)));
            let _ = self.tx.push(&Op::Configuration(Config::ArbitrationLost(
                ArbitrationLostBehavior::BufferAndRetransmit,
            )));
            self.bus.configured = true;
        }
        if let Some(r) = self.run.as_ref() {
            let mut o = r.outbox.lock().unwrap_or_else(|p| p.into_inner());
            if o.lost > 0 {
                self.log.push(format!(
                    "{} frames lost: the node's transmit queue ({OUTBOX_MAX}) was full",
                    o.lost
                ));
                o.lost = 0;
            }
            while let Some((_, f)) = o.frames.front() {
                let op = transmit_op(f);
                if self.tx.push(&op).is_err() {
                    break;
                }
                if self.bus.unconfirmed.len() >= UNCONFIRMED_MAX {
                    // Its controller's queue (the bus simulation's 64 per node, docs/BUS.md)
                    // is full: the bus loses a frame, which the node learns as a transmit
                    // overflow (D34); the oldest unconfirmed one counts as gone.
                    self.bus.unconfirmed.pop_front();
                    // Without bus notifications (a direct connection, LS-BUS
                    // `BusNotifications`) nothing is ever confirmed: no loss to tell.
                    if self.bus.confirms {
                        r.tx_lost.fetch_add(1, Ordering::Relaxed);
                    }
                }
                self.bus.unconfirmed.push_back(*f);
                o.frames.pop_front();
            }
        }
        if !self.tx.is_empty() {
            self.tx_view.clear();
            self.tx_view.extend_from_slice(self.tx.bytes());
            self.tx_clock = true;
        }
    }

    /// Runs the runtime to `us` (µs since the start).
    fn advance(&mut self, us: u64) -> Result<(), String> {
        self.bus_off_recovery(us)?;
        let r = self.run.as_mut().ok_or("the instance is not initialized")?;
        r.rt.advance_to(Instant::from_micros(us))
            .map_err(|e| format!("the runtime stopped: {e}"))?;
        self.now_us = us;
        Ok(())
    }

    fn set_status(&mut self, s: CanStatus) -> Result<(), String> {
        if s == self.bus.status {
            return Ok(());
        }
        let old = self.bus.status;
        self.bus.status = s;
        let _ = self.tx.push(&Op::Status(s));
        // The node's own reaction, as the control interface's faults make it (EMCY 0x8120,
        // 0x8140, silence while bus-off).
        match (old, s) {
            (_, CanStatus::BusOff) => self.fault("bus-off", true)?,
            (CanStatus::BusOff, _) => self.fault("bus-off", false)?,
            _ => {}
        }
        let passive = s == CanStatus::ErrorPassive;
        if passive != (old == CanStatus::ErrorPassive) && s != CanStatus::BusOff {
            self.fault("error-passive", passive)?;
        }
        Ok(())
    }

    fn fault(&mut self, name: &str, on: bool) -> Result<(), String> {
        self.request(Request::Fault {
            sensor: Some(0),
            name: name.into(),
            on,
            value: None,
            channel: None,
        })
    }

    fn counters_changed(&mut self) -> Result<(), String> {
        let b = &self.bus;
        let s = if b.tec > 255 {
            CanStatus::BusOff
        } else if b.tec >= 128 || b.rec >= 128 {
            CanStatus::ErrorPassive
        } else {
            CanStatus::ErrorActive
        };
        if s == CanStatus::BusOff && self.bus.bus_off_at.is_none() {
            self.bus.bus_off_at = Some(self.now_us);
        }
        if self.bus.status != CanStatus::BusOff {
            self.set_status(s)?;
        }
        Ok(())
    }

    /// Bus-off ends after 128 occurrences of 11 recessive bits (ISO 11898-1); LS-BUS does not
    /// model it, so the node counts the bit times itself.
    fn bus_off_recovery(&mut self, us: u64) -> Result<(), String> {
        let Some(at) = self.bus.bus_off_at else {
            return Ok(());
        };
        let bit_ns = 1_000_000 / u64::from(self.params.bitrate.max(1));
        if us.saturating_mul(1000) >= at * 1000 + 128 * 11 * bit_ns {
            self.bus.bus_off_at = None;
            self.bus.tec = 0;
            self.bus.rec = 0;
            self.set_status(CanStatus::ErrorActive)?;
        }
        Ok(())
    }

    /// Takes the operations of `Rx_Data` (checked when they were set) at the time reached.
    fn take_rx(&mut self) -> Result<(), String> {
        let data = std::mem::take(&mut self.rx_data);
        let ops = lsbus::parse(&data).map_err(|e| e.to_string())?;
        let now_ns = self.now_us * 1000;
        for op in ops {
            match op {
                Op::Transmit {
                    id,
                    ide,
                    rtr,
                    data,
                    dlc,
                } => {
                    let frame = if rtr {
                        Frame::remote(id, ide, dlc as u8)
                    } else {
                        Frame::with_id(id, ide, data)
                    }
                    .map_err(|e| format!("CAN Transmit 0x{id:X}: {e:?}"))?;
                    if self.bus.status == CanStatus::BusOff {
                        continue;
                    }
                    self.bus.rec = self.bus.rec.saturating_sub(1);
                    let r = self.run.as_ref().ok_or("not initialized")?;
                    let rx = RxFrame {
                        frame,
                        timestamp: r.clock.system_time_of(now_ns),
                    };
                    match r.rx.try_send(rx) {
                        Ok(()) => {}
                        Err(TrySendError::Full(_)) => {
                            r.rx_lost.fetch_add(1, Ordering::Relaxed);
                        }
                        Err(TrySendError::Disconnected(_)) => {
                            return Err("the runtime's receive queue is gone".into())
                        }
                    }
                }
                Op::FdTransmit { id, .. } | Op::XlTransmit { id, .. } => {
                    // A classic CAN 2.0 controller: the frame is not for it (docs/FMU.md).
                    self.log.push(format!(
                        "CAN FD / XL Transmit 0x{id:X} ignored: this node is a classic CAN node"
                    ));
                }
                Op::Confirm { id } => {
                    self.bus.confirms = true;
                    if let Some(i) = self.bus.unconfirmed.iter().position(|f| f.id() == id) {
                        self.bus.unconfirmed.remove(i);
                    }
                    self.bus.tec = self.bus.tec.saturating_sub(1);
                    self.counters_changed()?;
                }
                Op::ArbitrationLost { id } => {
                    // Discarded by the bus: the controller sends it again, as a real one does.
                    if let Some(i) = self.bus.unconfirmed.iter().position(|f| f.id() == id) {
                        if let Some(f) = self.bus.unconfirmed.remove(i) {
                            if let Some(r) = self.run.as_ref() {
                                let mut o = r.outbox.lock().unwrap_or_else(|p| p.into_inner());
                                o.frames.push_front((now_ns, f));
                            }
                        }
                    }
                }
                Op::BusError { is_sender, .. } => {
                    if self.bus.status == CanStatus::BusOff {
                        continue;
                    }
                    if is_sender {
                        self.bus.tec += 8;
                    } else {
                        self.bus.rec = (self.bus.rec + 1).min(255);
                    }
                    self.counters_changed()?;
                }
                Op::Configuration(c) => {
                    self.log
                        .push(format!("Configuration {c:?} from the bus ignored: a node configures the bus, not the other way round"));
                }
                Op::Status(s) => {
                    self.log.push(format!(
                        "Status {s:?} from the bus ignored: a node reports its own"
                    ));
                }
                Op::Wakeup => {}
            }
        }
        Ok(())
    }

    fn nanos_of(&self, t: f64) -> Result<u64, String> {
        let d = t - self.start;
        if !(d.is_finite() && d >= -1e-9) {
            return Err(format!(
                "time {t} s is before the start time {} s",
                self.start
            ));
        }
        Ok((d.max(0.0) * 1e9).round() as u64)
    }
}

fn transmit_op(f: &Frame) -> Op<'_> {
    Op::Transmit {
        id: f.id(),
        ide: f.is_extended(),
        rtr: f.is_remote(),
        data: f.data(),
        dlc: u16::from(f.dlc()),
    }
}

impl FmuModel for SensorFmu {
    fn description(&self) -> &Description {
        &self.desc
    }

    fn enter_initialization(&mut self, start_time: f64) -> Result<(), String> {
        if !start_time.is_finite() {
            return Err(format!("start time {start_time} is not finite"));
        }
        self.start = start_time;
        Ok(())
    }

    fn exit_initialization(&mut self) -> Result<(), String> {
        let r = self.build()?;
        self.run = Some(r);
        self.apply_inputs()?;
        // Power on at the start time: the LS-BUS configuration and the boot-up leave in the
        // event that ends initialization (the importer reads Tx_Clock there).
        self.advance(0)?;
        self.fill_tx();
        Ok(())
    }

    fn get(&mut self, vr: u32) -> Result<Value<'_>, String> {
        let p = self.params;
        Ok(match vr {
            crate::model::VR_TIME => Value::Float64(self.start + self.now_us as f64 / 1e6),
            VR_NODE_ID => Value::UInt8(p.node_id),
            VR_BITRATE => Value::UInt16(p.bitrate),
            VR_SERIAL => Value::UInt32(p.serial),
            VR_SEED => Value::UInt64(p.seed),
            VR_IDEAL => Value::Boolean(p.ideal),
            VR_THERMAL => Value::Float64(p.thermal),
            VR_AMBIENT => Value::Float64(self.ambient),
            VR_RX_DATA => Value::Binary(&self.rx_data),
            VR_TX_DATA => Value::Binary(&self.tx_view),
            VR_RX_CLOCK => Value::Clock(self.rx_clock),
            VR_TX_CLOCK => {
                // An output clock reports each tick once (FMI 3.0 §2.2.8.3).
                let t = self.tx_clock;
                self.tx_clock = false;
                Value::Clock(t)
            }
            v if (VR_MAGNET..VR_MAGNET + 50).contains(&v) => {
                Value::Float64(self.magnets[(v - VR_MAGNET) as usize])
            }
            v if (VR_FAULT..VR_FAULT + 40).contains(&v) => {
                Value::Boolean(self.faults[(v - VR_FAULT) as usize])
            }
            v if (VR_TRUE..VR_TRUE + 50).contains(&v) => {
                let i = (v - VR_TRUE) as usize;
                let x = self
                    .state()
                    .and_then(|s| s["true_mm"][i].as_f64())
                    .unwrap_or(self.magnets[i]);
                Value::Float64(x)
            }
            v if (VR_REPORTED..VR_REPORTED + 50).contains(&v) => {
                let i = (v - VR_REPORTED) as usize;
                let x = self
                    .state()
                    .and_then(|s| s["reported_mm"][i].as_f64())
                    .unwrap_or(f64::NAN);
                Value::Float64(x)
            }
            VR_NMT => Value::UInt8(match self.state().and_then(|s| s["nmt"].as_str()) {
                Some("operational") => 5,
                Some("stopped") => 4,
                Some("pre-operational") => 127,
                _ => 0,
            }),
            VR_ERROR_REGISTER => Value::UInt8(
                self.state()
                    .and_then(|s| s["error_register"].as_u64())
                    .unwrap_or(0) as u8,
            ),
            _ => return Err(format!("no variable with value reference {vr}")),
        })
    }

    fn set(&mut self, vr: u32, v: Value<'_>) -> Result<(), String> {
        let p = &mut self.params;
        match (vr, v) {
            (VR_NODE_ID, Value::UInt8(n)) => {
                if !(1..=127).contains(&n) && n != 255 {
                    return Err(format!(
                        "node_id {n} is out of range (1…127, or 255 = unconfigured)"
                    ));
                }
                p.node_id = n;
            }
            (VR_BITRATE, Value::UInt16(b)) => {
                const RATES: [u16; 9] = [10, 20, 50, 125, 250, 500, 800, 1000, 100];
                if !RATES.contains(&b) {
                    return Err(format!(
                        "bitrate {b} kbit/s is not a CiA 301 bit rate (10, 20, 50, 100, 125, 250, 500, 800, 1000)"
                    ));
                }
                p.bitrate = b;
            }
            (VR_SERIAL, Value::UInt32(s)) => p.serial = s,
            (VR_SEED, Value::UInt64(s)) => p.seed = s,
            (VR_IDEAL, Value::Boolean(b)) => p.ideal = b,
            (VR_THERMAL, Value::Float64(k)) => {
                if !(k.is_finite() && k > 0.0 && k <= 1e6) {
                    return Err(format!(
                        "thermal_time_scale {k} must be a positive number, at most 1e6"
                    ));
                }
                p.thermal = k;
            }
            (VR_AMBIENT, Value::Float64(c)) => {
                if !(c.is_finite() && (-273.15..=1000.0).contains(&c)) {
                    return Err(format!("ambient temperature {c} °C is not plausible"));
                }
                let old = std::mem::replace(&mut self.ambient, c);
                self.apply_or_undo(|m| m.ambient = old)?;
            }
            (VR_RX_DATA, Value::Binary(b)) => {
                // Checked whole now: a malformed buffer is refused and changes nothing.
                lsbus::parse(b).map_err(|e| e.to_string())?;
                self.rx_data.clear();
                self.rx_data.extend_from_slice(b);
            }
            (VR_RX_CLOCK, Value::Clock(on)) => self.rx_clock = on,
            (v, Value::Float64(mm)) if (VR_MAGNET..VR_MAGNET + 50).contains(&v) => {
                if !canpos_sim::motion::in_range(mm) {
                    return Err(format!(
                        "magnet position {mm} mm is not a finite number within ±1e9 mm"
                    ));
                }
                let k = (v - VR_MAGNET) as usize;
                let old = std::mem::replace(&mut self.magnets[k], mm);
                self.apply_or_undo(|m| m.magnets[k] = old)?;
            }
            (v, Value::Boolean(on)) if (VR_FAULT..VR_FAULT + 40).contains(&v) => {
                let k = (v - VR_FAULT) as usize;
                let old = std::mem::replace(&mut self.faults[k], on);
                self.apply_or_undo(|m| m.faults[k] = old)?;
            }
            _ => return Err(format!("value reference {vr} cannot be set")),
        }
        Ok(())
    }

    fn do_step(&mut self, t: f64, h: f64, early: bool) -> Result<StepResult, String> {
        if !(h.is_finite() && h > 0.0) {
            return Err(format!("communication step size {h} is not positive"));
        }
        let at_us = self.nanos_of(t)? / 1000;
        if at_us.abs_diff(self.now_us) > 1 {
            return Err(format!(
                "doStep at {t} s, but the instance is at {} s",
                self.start + self.now_us as f64 / 1e6
            ));
        }
        let end_us = self.nanos_of(t + h)? / 1000;
        let mut stop = end_us;
        if early {
            // Stop at the first event that sent something: its frames leave at their time.
            for _ in 0..100_000 {
                let next = self.run.as_ref().and_then(|r| r.rt.next_event());
                let s = next
                    .map_or(end_us, |e| e.micros())
                    .clamp(self.now_us, end_us);
                self.advance(s)?;
                if self.outbox_len() > 0 || !self.bus.configured || s >= end_us {
                    stop = s;
                    break;
                }
            }
        }
        if stop == end_us {
            self.advance(end_us)?;
        }
        self.fill_tx();
        let event_needed = self.tx_clock;
        Ok(StepResult {
            event_needed,
            last_time: self.start + stop as f64 / 1e6,
            early_return: stop < end_us,
        })
    }

    fn update_discrete_states(&mut self) -> Result<Discrete, String> {
        if self.rx_clock {
            self.rx_clock = false;
            self.take_rx()?;
            // Frames on the bus now are taken now; what the node answers at once leaves in
            // this event (a Tx_Clock tick the importer reads after this call).
            self.advance(self.now_us)?;
            self.fill_tx();
        }
        Ok(Discrete {
            need_update: false,
            next_event_time: None,
        })
    }

    fn enter_step_mode(&mut self) -> Result<(), String> {
        self.tx.clear();
        self.tx_view.clear();
        self.tx_clock = false;
        self.rx_clock = false;
        Ok(())
    }

    fn take_log(&mut self) -> Vec<String> {
        std::mem::take(&mut self.log)
    }
}
