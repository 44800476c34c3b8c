//! The control interface (SPEC §12): a loopback TCP server speaking JSON lines, so a test
//! harness in any language can move magnets, inject faults, power-cycle and read the true and
//! reported state. The protocol is documented in `docs/CONTROL.md`.
//!
//! One request per line, one answer line per request:
//!
//! ```text
//! → {"cmd":"magnet","index":0,"mm":250.0}
//! ← {"ok":true}
//! → {"cmd":"fault","name":"nonsense","on":true}
//! ← {"ok":false,"error":"unknown fault `nonsense`; known: missing-magnet, …"}
//! ```

use std::fmt;
use std::io::{self, BufRead, BufReader, Write};
use std::net::{SocketAddr, TcpListener, TcpStream, ToSocketAddrs};
use std::str::FromStr;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::Duration;

use serde::{Deserialize, Serialize};
use serde_json::{json, Value};

use crate::runtime::ControlHandle;

/// Longest request line accepted (a request is a few dozen bytes). A longer line is answered
/// with one error and skipped up to its newline: no part of it is ever run as a request.
pub const MAX_LINE: usize = 64 * 1024;

/// Most control connections served at once; one more is answered with an error and closed.
/// Clients are test harnesses (a handful); the cap keeps a runaway client from using up
/// threads.
pub const MAX_CONNECTIONS: usize = 32;

/// Lowest temperature accepted anywhere (absolute zero), °C.
pub const MIN_CELSIUS: f64 = -273.15;
/// Highest temperature accepted, °C (far above any sensor's rating, so over-temperature tests
/// fit; beyond it a value is a typo).
pub const MAX_CELSIUS: f64 = 1000.0;
/// Supply voltages accepted by the `supply-voltage` fault, V (either polarity).
pub const MAX_SUPPLY_V: f64 = 1000.0;

/// A control request. `sensor` selects the sensor of a multi-sensor runtime (0-based, default
/// 0). A key a request does not know is refused with its name (`deny_unknown_fields` on every
/// variant): a misspelt `velocty` must not turn a move into a jump.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "cmd", rename_all = "kebab-case", deny_unknown_fields)]
pub enum Request {
    /// Moves magnet `index` (0-based) to `mm`; `null` takes it off the rod. `velocity` (mm/s)
    /// limits the speed of the move (jump when absent).
    Magnet {
        /// Sensor index.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        sensor: Option<usize>,
        /// Magnet index (0 = the first magnet of the motion source).
        #[serde(default)]
        index: usize,
        /// Target position in mm from the zero point; `None` removes the magnet.
        mm: Option<f64>,
        /// Speed limit of the move, mm/s.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        velocity: Option<f64>,
    },
    /// Starts a motion profile (the `--motion` syntax, without `csv:`) from now on.
    Motion {
        /// Sensor index.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        sensor: Option<usize>,
        /// The spec, e.g. `sine:center=500,amp=200,period=4`.
        spec: String,
    },
    /// Turns a fault on or off (see [`Fault`]).
    Fault {
        /// Sensor index.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        sensor: Option<usize>,
        /// Fault name, e.g. `missing-magnet`.
        name: String,
        /// On or off.
        on: bool,
        /// Fault parameter: extra magnet position (mm), supply voltage (V), temperature (°C).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        value: Option<f64>,
        /// Channel (0-based) for missing-magnet / magnets-too-close; default 0.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        channel: Option<usize>,
    },
    /// Power off and on again: stored data are reloaded, boot-up is sent.
    PowerCycle {
        /// Sensor index.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        sensor: Option<usize>,
    },
    /// Sets the ambient temperature (°C) of the thermal model.
    Ambient {
        /// Sensor index.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        sensor: Option<usize>,
        /// Ambient temperature, °C.
        celsius: f64,
    },
    /// Reads the state: NMT state, node-id, bit rate, true and reported positions, velocity,
    /// error register, active faults.
    State {
        /// Sensor index.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        sensor: Option<usize>,
    },
    /// Disturbs the bus (paced virtual buses; docs/BUS.md): `corrupt` with `value` corrupted
    /// frames per million (0 stops), `stuck-dominant` with `value` ms from now, `transceiver`
    /// of `sensor` with `on`. Out of range: an error, and nothing changes.
    BusFault {
        /// Sensor index (whose bus; whose transceiver).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        sensor: Option<usize>,
        /// `corrupt`, `stuck-dominant` or `transceiver`.
        kind: String,
        /// The parameter of `corrupt` and `stuck-dominant`.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        value: Option<f64>,
        /// Failed (`true`) or working again, for `transceiver`.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        on: Option<bool>,
    },
    /// Restarts the runtime's wake-up lateness statistics (`wake_lateness_us` of the state),
    /// so a measurement covers a chosen window, not the start-up. All sensors of a runtime
    /// share the statistics; `sensor` is taken as on every request (and must name one), so a
    /// client that adds it to every request is served. A struct variant, not a unit variant:
    /// serde lets an internally tagged unit variant take any fields, and a field this request
    /// does not know must be refused like every other's.
    ResetLateness {
        /// Sensor index (checked; the statistics are the runtime's).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        sensor: Option<usize>,
    },
    /// Hands the sensor an NMT command as if a master had sent it, without putting a frame on
    /// the bus (a scenario's `nmt = "operational"`, or a timed NMT event).
    Nmt {
        /// Sensor index.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        sensor: Option<usize>,
        /// `start`, `stop`, `preop`, `reset` or `reset-comm`.
        command: String,
    },
    /// Sets the device's own timing ([`crate::timing::DeviceTiming`]); the values not given
    /// stay. Answers the timing now in force.
    Timing {
        /// Sensor index.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        sensor: Option<usize>,
        /// Delay before every SDO response, ms.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        sdo_delay_ms: Option<f64>,
        /// Random extra delay of SDO responses, up to this many ms.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        sdo_jitter_ms: Option<f64>,
        /// Power-on to boot-up, ms.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        boot_delay_ms: Option<f64>,
        /// NMT reset to boot-up, ms.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        reset_boot_delay_ms: Option<f64>,
    },
}

/// The NMT commands of [`Request::Nmt`] and their command specifiers (CiA 301).
pub const NMT_COMMANDS: [(&str, u8); 5] = [
    ("start", 0x01),
    ("stop", 0x02),
    ("preop", 0x80),
    ("reset", 0x81),
    ("reset-comm", 0x82),
];

/// The command specifier of an NMT command name ([`NMT_COMMANDS`]).
pub fn nmt_command(name: &str) -> Result<u8, String> {
    NMT_COMMANDS
        .iter()
        .find(|(n, _)| n.eq_ignore_ascii_case(name.trim()))
        .map(|(_, cs)| *cs)
        .ok_or_else(|| {
            let known: Vec<_> = NMT_COMMANDS.iter().map(|(n, _)| *n).collect();
            format!("unknown NMT command `{name}`; known: {}", known.join(", "))
        })
}

/// Readable one-line form for logs, e.g. `sensor 1: fault missing-magnet on (channel 0)`.
impl fmt::Display for Request {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if let Some(s) = self.sensor() {
            write!(f, "sensor {s}: ")?;
        }
        match self {
            Request::Magnet {
                index,
                mm,
                velocity,
                ..
            } => {
                match mm {
                    Some(mm) => write!(f, "magnet {index} to {mm} mm")?,
                    None => write!(f, "magnet {index} off the rod")?,
                }
                if let Some(v) = velocity {
                    write!(f, " at {v} mm/s")?;
                }
                Ok(())
            }
            Request::Motion { spec, .. } => write!(f, "motion {spec}"),
            Request::Fault {
                name,
                on,
                value,
                channel,
                ..
            } => {
                write!(f, "fault {name} {}", if *on { "on" } else { "off" })?;
                if let Some(v) = value {
                    write!(f, " value {v}")?;
                }
                if let Some(c) = channel {
                    write!(f, " channel {c}")?;
                }
                Ok(())
            }
            Request::PowerCycle { .. } => f.write_str("power-cycle"),
            Request::Ambient { celsius, .. } => write!(f, "ambient {celsius} °C"),
            Request::State { .. } => f.write_str("state"),
            Request::ResetLateness { .. } => f.write_str("reset-lateness"),
            Request::Nmt { command, .. } => write!(f, "nmt {command}"),
            Request::Timing {
                sdo_delay_ms,
                sdo_jitter_ms,
                boot_delay_ms,
                reset_boot_delay_ms,
                ..
            } => {
                f.write_str("timing")?;
                for (k, v) in [
                    ("sdo_delay_ms", sdo_delay_ms),
                    ("sdo_jitter_ms", sdo_jitter_ms),
                    ("boot_delay_ms", boot_delay_ms),
                    ("reset_boot_delay_ms", reset_boot_delay_ms),
                ] {
                    if let Some(v) = v {
                        write!(f, " {k}={v}")?;
                    }
                }
                Ok(())
            }
            Request::BusFault {
                kind, value, on, ..
            } => {
                write!(f, "bus-fault {kind}")?;
                if let Some(v) = value {
                    write!(f, " {v}")?;
                }
                if let Some(on) = on {
                    write!(f, " {}", if *on { "on" } else { "off" })?;
                }
                Ok(())
            }
        }
    }
}

impl Request {
    /// The sensor it addresses (`None` = sensor 0).
    pub fn sensor(&self) -> Option<usize> {
        match self {
            Request::Magnet { sensor, .. }
            | Request::Motion { sensor, .. }
            | Request::Fault { sensor, .. }
            | Request::PowerCycle { sensor }
            | Request::Ambient { sensor, .. }
            | Request::State { sensor }
            | Request::Nmt { sensor, .. }
            | Request::Timing { sensor, .. }
            | Request::BusFault { sensor, .. }
            | Request::ResetLateness { sensor } => *sensor,
        }
    }

    /// Checks the values that need no device to judge: numbers finite and physically
    /// possible, fault names known, motion specs well-formed. The runtime checks the rest
    /// (sensor, magnet and channel indices) before it changes anything.
    pub fn validate(&self) -> Result<(), String> {
        match self {
            Request::Magnet { mm, velocity, .. } => {
                if let Some(mm) = mm {
                    if !canpos_sim::motion::in_range(*mm) {
                        return Err(format!(
                            "magnet position {} mm is not a finite number within ±{:e} mm",
                            show_num(*mm),
                            canpos_sim::motion::MAX_MAGNITUDE
                        ));
                    }
                }
                if let Some(v) = velocity {
                    if !(canpos_sim::motion::in_range(*v) && *v > 0.0) {
                        return Err(format!(
                            "velocity {} mm/s must be > 0 and at most {:e}",
                            show_num(*v),
                            canpos_sim::motion::MAX_MAGNITUDE
                        ));
                    }
                }
                Ok(())
            }
            Request::Motion { spec, .. } => {
                match canpos_sim::motion::MotionSpec::parse(spec).map_err(|e| e.to_string())? {
                    canpos_sim::motion::MotionSpec::Profiles(_) => Ok(()),
                    canpos_sim::motion::MotionSpec::Csv(_) => Err(
                        "a CSV trajectory can only be given at start (--motion csv:FILE)".into(),
                    ),
                }
            }
            Request::Fault {
                name, value, on, ..
            } => {
                let fault: Fault = name.parse()?;
                if fault == Fault::Stall && *on && value.is_none() {
                    return Err("stall needs its duration: value = seconds".into());
                }
                let Some(v) = value else { return Ok(()) };
                if !v.is_finite() {
                    return Err(format!("fault value {v} is not a finite number"));
                }
                match fault {
                    Fault::OverTemperature => check_celsius(*v),
                    Fault::SupplyVoltage if v.abs() > MAX_SUPPLY_V => Err(format!(
                        "supply voltage {} V is out of range (±{MAX_SUPPLY_V} V)",
                        show_num(*v)
                    )),
                    Fault::ExtraMagnet if !canpos_sim::motion::in_range(*v) => Err(format!(
                        "extra magnet position {} mm is beyond ±{:e} mm",
                        show_num(*v),
                        canpos_sim::motion::MAX_MAGNITUDE
                    )),
                    Fault::SupplyVoltage | Fault::ExtraMagnet => Ok(()),
                    Fault::Stall => crate::timing::millis("stall", v * 1e3).and_then(|d| {
                        if d.is_zero() {
                            Err("stall needs a duration > 0 s".into())
                        } else {
                            Ok(())
                        }
                    }),
                    _ if *on => Err(format!("fault `{fault}` takes no value")),
                    _ => Ok(()),
                }
            }
            Request::Ambient { celsius, .. } => check_celsius(*celsius),
            Request::Timing {
                sdo_delay_ms,
                sdo_jitter_ms,
                boot_delay_ms,
                reset_boot_delay_ms,
                ..
            } => {
                for (what, v) in [
                    ("sdo_delay_ms", sdo_delay_ms),
                    ("sdo_jitter_ms", sdo_jitter_ms),
                    ("boot_delay_ms", boot_delay_ms),
                    ("reset_boot_delay_ms", reset_boot_delay_ms),
                ] {
                    if let Some(v) = v {
                        crate::timing::millis(what, *v)?;
                    }
                }
                Ok(())
            }
            Request::Nmt { command, .. } => nmt_command(command).map(|_| ()),
            Request::BusFault {
                kind, value, on, ..
            } => bus_disturbance(kind, *value, *on).map(|_| ()),
            Request::PowerCycle { .. } | Request::State { .. } | Request::ResetLateness { .. } => {
                Ok(())
            }
        }
    }
}

/// The disturbance a [`Request::BusFault`] asks for, with its parameters checked.
pub fn bus_disturbance(
    kind: &str,
    value: Option<f64>,
    on: Option<bool>,
) -> Result<crate::transport::Disturbance, String> {
    use crate::transport::Disturbance;
    match kind {
        "corrupt" => {
            let v = value.ok_or(
                "bus fault `corrupt` needs a value: corrupted frames per million (0 … 1000000)",
            )?;
            if !(0.0..=1_000_000.0).contains(&v) || v.fract() != 0.0 {
                return Err(format!(
                    "corrupted frames per million must be a whole number 0 … 1000000, not {}",
                    show_num(v)
                ));
            }
            Ok(Disturbance::CorruptedFrames {
                per_million: v as u32,
            })
        }
        "stuck-dominant" => {
            let v = value
                .ok_or("bus fault `stuck-dominant` needs a value: milliseconds (0.001 … 60000)")?;
            if !(0.001..=60_000.0).contains(&v) {
                return Err(format!(
                    "stuck-dominant interval must be 0.001 … 60000 ms, not {}",
                    show_num(v)
                ));
            }
            Ok(Disturbance::StuckDominant {
                duration: std::time::Duration::from_secs_f64(v / 1000.0),
            })
        }
        "transceiver" => Ok(Disturbance::TransceiverFailed(
            on.ok_or("bus fault `transceiver` needs on (failed) or off (working)")?,
        )),
        other => Err(format!(
            "unknown bus fault `{other}` (corrupt, stuck-dominant, transceiver)"
        )),
    }
}

/// A number for a message: plain when moderate, in exponent form when huge or tiny (`1e300`,
/// not three hundred digits).
pub fn show_num(v: f64) -> String {
    let a = v.abs();
    if a != 0.0 && a.is_finite() && !(1e-3..1e9).contains(&a) {
        format!("{v:e}")
    } else {
        format!("{v}")
    }
}

fn check_celsius(t: f64) -> Result<(), String> {
    if t.is_finite() && (MIN_CELSIUS..=MAX_CELSIUS).contains(&t) {
        Ok(())
    } else {
        Err(format!(
            "temperature {} °C is out of range ({MIN_CELSIUS} … {MAX_CELSIUS} °C)",
            show_num(t)
        ))
    }
}

/// The faults the control interface can inject (SPEC §11).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Fault {
    /// A channel reports no magnet (sim) → the core's EMCY 0x5000, register 0x81.
    MissingMagnet,
    /// One more magnet on the rod (sim; `value` = position in mm, default 90 % of the stroke).
    ExtraMagnet,
    /// Two magnets closer than the minimum distance (sim) → as missing magnet.
    MagnetsTooClose,
    /// Transducer error: no position at all (sim) → EMCY 0x5000, register 0x81.
    SensorError,
    /// Supply voltage out of range (sim `value` V, default 2 V under the minimum) → EMCY 0x3100,
    /// register 0x05.
    SupplyVoltage,
    /// Over-temperature (sim `value` °C, default 10 °C over the maximum) → EMCY 0x4200,
    /// register 0x09.
    OverTemperature,
    /// Corrupts the state file; the next power cycle starts on defaults with EMCY 0x6300.
    StorageCorrupt,
    /// CAN error passive → EMCY 0x8120, register 0x11.
    ErrorPassive,
    /// Bus-off: the node neither sends nor receives; `off` = recovery → EMCY 0x8140 then 0x0000.
    BusOff,
    /// CAN overrun → EMCY 0x8110, register 0x11.
    CanOverrun,
    /// A communication error of no more specific kind → EMCY 0x8100, register 0x11 (TH,
    /// E-Series; the TMI's table has no such code).
    Communication,
    /// PDOs not processed because of their length (a condition: `off` clears it) → EMCY 0x8210
    /// (TH, E-Series; not in the TMI's table).
    PdoLength,
    /// TMI system-data errors (002 §1.14, 0x5000 with sub-codes). All but
    /// `unexpected-system-data` lock the sensor out of operational until a power cycle (the
    /// start is refused with a repeated EMCY; 0x1002 bits 8–14). On TH / E-Series they report
    /// as a sensor error.
    WrongMapping,
    /// See [`Fault::WrongMapping`]: wrong vendor-id (0x5000 1/3/1).
    WrongVendorId,
    /// See [`Fault::WrongMapping`]: wrong scale (0x5000 1/3/2).
    WrongScale,
    /// See [`Fault::WrongMapping`]: wrong resolution (0x5000 1/4/0).
    WrongResolution,
    /// See [`Fault::WrongMapping`]: unexpected system data (0x5000 1/5/0, pre-operational once).
    UnexpectedSystemData,
    /// See [`Fault::WrongMapping`]: no system data (0x5000 1/6/0).
    NoSystemData,
    /// See [`Fault::WrongMapping`]: invalid serial number in EEPROM (0x5000 2/1/0).
    InvalidSerial,
    /// `on` powers the sensor off, `off` powers it on again.
    PowerCycle,
    /// The device answers nothing for `value` seconds: it takes no frame from the bus (SDO,
    /// NMT, guarding, LSS, SYNC), while what its own timers send (heartbeat, event-timer
    /// TPDOs) goes on. `off` ends it early.
    Stall,
}

impl Fault {
    /// Every fault.
    pub const ALL: [Fault; 21] = [
        Fault::MissingMagnet,
        Fault::ExtraMagnet,
        Fault::MagnetsTooClose,
        Fault::SensorError,
        Fault::SupplyVoltage,
        Fault::OverTemperature,
        Fault::StorageCorrupt,
        Fault::ErrorPassive,
        Fault::BusOff,
        Fault::CanOverrun,
        Fault::Communication,
        Fault::PdoLength,
        Fault::WrongMapping,
        Fault::WrongVendorId,
        Fault::WrongScale,
        Fault::WrongResolution,
        Fault::UnexpectedSystemData,
        Fault::NoSystemData,
        Fault::InvalidSerial,
        Fault::PowerCycle,
        Fault::Stall,
    ];

    /// The name used on the wire and the command line.
    pub fn name(self) -> &'static str {
        match self {
            Fault::MissingMagnet => "missing-magnet",
            Fault::ExtraMagnet => "extra-magnet",
            Fault::MagnetsTooClose => "magnets-too-close",
            Fault::SensorError => "sensor-error",
            Fault::SupplyVoltage => "supply-voltage",
            Fault::OverTemperature => "over-temperature",
            Fault::StorageCorrupt => "storage-corrupt",
            Fault::ErrorPassive => "error-passive",
            Fault::BusOff => "bus-off",
            Fault::CanOverrun => "can-overrun",
            Fault::Communication => "communication",
            Fault::PdoLength => "pdo-length",
            Fault::WrongMapping => "wrong-mapping",
            Fault::WrongVendorId => "wrong-vendor-id",
            Fault::WrongScale => "wrong-scale",
            Fault::WrongResolution => "wrong-resolution",
            Fault::UnexpectedSystemData => "unexpected-system-data",
            Fault::NoSystemData => "no-system-data",
            Fault::InvalidSerial => "invalid-serial",
            Fault::PowerCycle => "power-cycle",
            Fault::Stall => "stall",
        }
    }
}

impl fmt::Display for Fault {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for Fault {
    type Err = String;
    fn from_str(s: &str) -> Result<Fault, String> {
        Fault::ALL
            .into_iter()
            .find(|f| f.name().eq_ignore_ascii_case(s.trim()))
            .ok_or_else(|| {
                let known: Vec<_> = Fault::ALL.iter().map(|f| f.name()).collect();
                format!("unknown fault `{s}`; known: {}", known.join(", "))
            })
    }
}

/// The `cmd` names of [`Request`], for messages.
pub const COMMANDS: [&str; 10] = [
    "magnet",
    "motion",
    "fault",
    "power-cycle",
    "ambient",
    "state",
    "bus-fault",
    "reset-lateness",
    "nmt",
    "timing",
];

/// Parses one request line into a request, or the error answer to send back. A key the
/// request does not know is refused with its name and the request's own keys, e.g. ``unknown
/// field `velocty` in a `magnet` request, expected one of `sensor`, `index`, `mm`,
/// `velocity` ``; nothing of a refused line runs.
pub fn parse_request(line: &str) -> Result<Request, Value> {
    // serde would also take an array, its fields by position (`["magnet",null,0,250]`): a form
    // nobody documents, with no names to check.
    if !line.trim_start().starts_with('{') {
        return Err(json!({"ok": false, "error": format!(
            "bad request: a request is one JSON object, e.g. {{\"cmd\":\"state\"}} (cmds: {})",
            COMMANDS.join(", ")
        )}));
    }
    serde_json::from_str::<Request>(line).map_err(|e| {
        let msg = e.to_string();
        let error = match msg.strip_prefix("unknown field ") {
            // Only on this error path: which request it was, read again for the message.
            Some(rest) => {
                #[derive(Deserialize)]
                struct Cmd {
                    cmd: String,
                }
                match serde_json::from_str::<Cmd>(line) {
                    Ok(Cmd { cmd }) => format!("unknown field {}", with_cmd(rest, &cmd)),
                    Err(_) => msg,
                }
            }
            None => format!(
                "bad request: {msg}; expected e.g. {{\"cmd\":\"state\"}} (cmds: {})",
                COMMANDS.join(", ")
            ),
        };
        json!({"ok": false, "error": error})
    })
}

/// Puts ``in a `cmd` request`` after the field's name in the rest of serde's ``unknown field
/// `x`, expected …`` (or ``…, there are no fields``) after `unknown field `.
fn with_cmd(rest: &str, cmd: &str) -> String {
    // The last of these marks: the name itself may hold any character.
    let end = ["`, expected ", "`, there are no fields"]
        .iter()
        .filter_map(|m| rest.rfind(m))
        .max();
    match end {
        Some(end) => {
            let (name, tail) = rest.split_at(end + 1);
            let tail = tail.replace("there are no fields", "it takes no fields");
            format!("{name} in a `{cmd}` request{tail}")
        }
        None => format!("{rest} (in a `{cmd}` request)"),
    }
}

/// A running control server.
pub struct ControlServer {
    addr: SocketAddr,
    _thread: JoinHandle<()>,
}

impl ControlServer {
    /// The address it listens on.
    pub fn local_addr(&self) -> SocketAddr {
        self.addr
    }
}

/// How long a control connection may stay without a complete request before it is closed
/// (and how long an answer may wait for its client to take it). Clients keep a connection
/// only while they use it, or reconnect: the dashboard and `canpos ctl` connect per request,
/// the Python client reconnects when it finds its connection closed.
pub const IDLE_TIMEOUT: Duration = Duration::from_secs(30);

/// Longest answer line [`call`] reads (a `state` answer is a few KiB): a server that sends
/// an endless line gets an error, not all of the client's memory.
pub const MAX_ANSWER: usize = 1024 * 1024;

/// Limits of a control server ([`serve_with`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ServeOptions {
    /// A connection is closed, without a word, when no complete request line arrives within
    /// this time after it opened or after its last answer; it is also closed when an answer
    /// cannot be handed to the socket within this time (its client does not read). Default
    /// [`IDLE_TIMEOUT`]; at least 1 ms is used.
    pub idle_timeout: Duration,
    /// Connections served at once; one more gets one error line and is closed. Default
    /// [`MAX_CONNECTIONS`].
    pub max_connections: usize,
}

impl Default for ServeOptions {
    fn default() -> Self {
        ServeOptions {
            idle_timeout: IDLE_TIMEOUT,
            max_connections: MAX_CONNECTIONS,
        }
    }
}

/// Serves the control interface on `addr`, answering through `handle`, with the default
/// [`ServeOptions`]. Each connection gets a thread (clients are test harnesses: few). Warns
/// when `addr` is not loopback: the interface has no authentication.
pub fn serve(addr: impl ToSocketAddrs, handle: ControlHandle) -> io::Result<ControlServer> {
    serve_on(TcpListener::bind(addr)?, handle)
}

/// [`serve`] on a listener bound earlier: a host binds before its sensors boot, so that a
/// client that saw the boot-up can connect at once (connections wait in the backlog until
/// the runtime is up).
pub fn serve_on(listener: TcpListener, handle: ControlHandle) -> io::Result<ControlServer> {
    serve_with(listener, handle, ServeOptions::default())
}

/// [`serve_on`] with other limits (a short idle timeout in a test, say).
///
/// What a connection can hold: one request line (at most [`MAX_LINE`] bytes) and one answer
/// at a time. Answers are written straight to the socket, never queued here: a client that
/// sends requests and never reads fills the kernel's socket buffers, then the server stops
/// reading its requests (TCP holds the client back), and after `idle_timeout` without
/// progress the connection is closed. So every connection costs at most a line, an answer and
/// its thread, for at most `idle_timeout` past its last request.
pub fn serve_with(
    listener: TcpListener,
    handle: ControlHandle,
    options: ServeOptions,
) -> io::Result<ControlServer> {
    let addr = listener.local_addr()?;
    crate::warn_if_exposed(addr, "the control interface");
    let open = Arc::new(AtomicUsize::new(0));
    let thread = std::thread::Builder::new()
        .name("canpos-control".into())
        .spawn(move || {
            for conn in listener.incoming() {
                let stream = match conn {
                    Ok(s) => s,
                    Err(e) => {
                        // Out of descriptors, say: retrying at once would spin; the connection
                        // waits in the backlog meanwhile.
                        tracing::warn!(error = %e, "control interface: accept failed");
                        std::thread::sleep(Duration::from_millis(100));
                        continue;
                    }
                };
                if open.fetch_add(1, Ordering::SeqCst) >= options.max_connections {
                    open.fetch_sub(1, Ordering::SeqCst);
                    refuse(stream, options.max_connections);
                    continue;
                }
                let h = handle.clone();
                let count = Arc::clone(&open);
                let spawned = std::thread::Builder::new()
                    .name("canpos-control-conn".into())
                    .spawn(move || {
                        match serve_conn(stream, h, options.idle_timeout) {
                            Ok(End::Closed) => {}
                            Ok(End::Idle) => tracing::debug!(
                                timeout_s = options.idle_timeout.as_secs_f64(),
                                "control connection closed: idle"
                            ),
                            Ok(End::NotReading) => tracing::warn!(
                                timeout_s = options.idle_timeout.as_secs_f64(),
                                "control connection closed: its client takes no answers"
                            ),
                            Err(e) => tracing::debug!(error = %e, "control connection ended"),
                        }
                        count.fetch_sub(1, Ordering::SeqCst);
                    });
                if spawned.is_err() {
                    open.fetch_sub(1, Ordering::SeqCst);
                }
            }
        })?;
    Ok(ControlServer {
        addr,
        _thread: thread,
    })
}

/// Answers a connection beyond the limit with one error line and closes it, at once: the
/// accept loop never waits on that client (a fresh socket's buffer takes the line whole).
fn refuse(stream: TcpStream, max: usize) {
    let line = format!(
        "{}\n",
        json!({"ok": false, "error": format!("too many control connections (at most {max}); idle ones are closed after their timeout, try again")})
    );
    let _ = stream.set_nonblocking(true);
    let _ = (&stream).write_all(line.as_bytes());
    let _ = stream.shutdown(std::net::Shutdown::Write);
}

/// One line read by [`read_line_limited`].
#[derive(Debug, PartialEq, Eq)]
pub enum Line {
    /// A complete line (without its newline; the last line may lack one).
    Text(Vec<u8>),
    /// A line longer than the limit; it was read up to and including its newline and dropped.
    TooLong,
    /// End of the stream.
    Eof,
}

/// Reads one line of at most `limit` bytes. A longer line is consumed up to its newline (or
/// the end of the stream) without keeping more than `limit` bytes, and reported as
/// [`Line::TooLong`]: the caller answers it once and no tail of it becomes a request.
pub fn read_line_limited(r: &mut impl BufRead, limit: usize) -> io::Result<Line> {
    let mut line = Vec::new();
    let mut too_long = false;
    loop {
        let buf = match r.fill_buf() {
            Ok(b) => b,
            Err(e) if e.kind() == io::ErrorKind::Interrupted => continue,
            Err(e) => return Err(e),
        };
        if buf.is_empty() {
            return Ok(match (too_long, line.is_empty()) {
                (true, _) => Line::TooLong,
                (false, true) => Line::Eof,
                (false, false) => Line::Text(line),
            });
        }
        let (chunk, done) = match buf.iter().position(|&b| b == b'\n') {
            Some(i) => (&buf[..i], Some(i + 1)),
            None => (buf, None),
        };
        if !too_long {
            if line.len() + chunk.len() > limit {
                too_long = true;
                line = Vec::new();
            } else {
                line.extend_from_slice(chunk);
            }
        }
        let used = done.unwrap_or(buf.len());
        r.consume(used);
        if done.is_some() {
            return Ok(if too_long {
                Line::TooLong
            } else {
                Line::Text(line)
            });
        }
    }
}

/// Answers one request line: parsed here, checked and applied by the runtime.
pub fn answer_line(line: &str, handle: &ControlHandle) -> Value {
    match parse_request(line) {
        Ok(req) => handle.request(req),
        Err(e) => e,
    }
}

/// How a connection ended without an error.
enum End {
    /// The client closed it.
    Closed,
    /// No request within the idle timeout.
    Idle,
    /// An answer not taken within the idle timeout: the client does not read.
    NotReading,
}

/// A connection's reading side with a deadline for the whole of the next request line: a
/// client that sends nothing, or a byte now and then, is closed all the same.
struct Deadline {
    stream: TcpStream,
    at: std::time::Instant,
}

impl io::Read for Deadline {
    fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        let left = self.at.saturating_duration_since(std::time::Instant::now());
        if left.is_zero() {
            return Err(io::ErrorKind::TimedOut.into());
        }
        self.stream.set_read_timeout(Some(left))?;
        self.stream.read(buf)
    }
}

/// Now plus `d`, or a year from now when `d` is beyond what the clock can add.
fn deadline_after(d: Duration) -> std::time::Instant {
    let now = std::time::Instant::now();
    now.checked_add(d)
        .unwrap_or_else(|| now + Duration::from_secs(365 * 24 * 3600))
}

fn serve_conn(stream: TcpStream, handle: ControlHandle, idle: Duration) -> io::Result<End> {
    // A socket timeout of zero is refused by the OS (and would mean none).
    let idle = idle.max(Duration::from_millis(1));
    stream.set_nodelay(true)?;
    // An answer the client does not take within the idle time ends the connection.
    stream.set_write_timeout(Some(idle))?;
    let mut out = stream.try_clone()?;
    let mut reader = BufReader::new(Deadline {
        stream,
        at: deadline_after(idle),
    });
    loop {
        let line = match read_line_limited(&mut reader, MAX_LINE) {
            Ok(l) => l,
            Err(e)
                if matches!(
                    e.kind(),
                    io::ErrorKind::TimedOut | io::ErrorKind::WouldBlock
                ) =>
            {
                return Ok(End::Idle)
            }
            Err(e) => return Err(e),
        };
        let answer = match line {
            Line::Eof => return Ok(End::Closed),
            Line::TooLong => json!({
                "ok": false,
                "error": format!("request line longer than {MAX_LINE} bytes; discarded up to its newline")
            }),
            Line::Text(bytes) => match std::str::from_utf8(&bytes) {
                Err(_) => json!({"ok": false, "error": "request line is not UTF-8"}),
                Ok(text) => {
                    let text = text.trim();
                    if text.is_empty() {
                        continue;
                    }
                    answer_line(text, &handle)
                }
            },
        };
        let mut s = answer.to_string();
        s.push('\n');
        match out.write_all(s.as_bytes()) {
            Err(e)
                if matches!(
                    e.kind(),
                    io::ErrorKind::TimedOut | io::ErrorKind::WouldBlock
                ) =>
            {
                return Ok(End::NotReading)
            }
            r => r?,
        }
        reader.get_mut().at = deadline_after(idle);
    }
}

/// Client side: sends one request and returns the answer (used by `canpos ctl`).
pub fn call(addr: impl ToSocketAddrs, req: &Request, timeout: Duration) -> io::Result<Value> {
    let mut last = None;
    for a in addr.to_socket_addrs()? {
        match TcpStream::connect_timeout(&a, timeout) {
            Ok(mut s) => {
                s.set_write_timeout(Some(timeout))?;
                let mut line = serde_json::to_string(req).map_err(io::Error::other)?;
                line.push('\n');
                s.write_all(line.as_bytes())?;
                // The whole answer within `timeout`, not each read: a server that trickles
                // bytes cannot hold the caller longer.
                let mut r = BufReader::new(Deadline {
                    stream: s,
                    at: deadline_after(timeout),
                });
                let reply = match read_line_limited(&mut r, MAX_ANSWER)? {
                    Line::Text(t) => t,
                    Line::TooLong => {
                        return Err(io::Error::new(
                            io::ErrorKind::InvalidData,
                            format!("answer longer than {MAX_ANSWER} bytes"),
                        ))
                    }
                    Line::Eof => {
                        return Err(io::Error::new(
                            io::ErrorKind::UnexpectedEof,
                            "the control interface closed the connection without an answer",
                        ))
                    }
                };
                return serde_json::from_slice(&reply).map_err(|e| {
                    io::Error::new(io::ErrorKind::InvalidData, format!("bad answer: {e}"))
                });
            }
            Err(e) => last = Some(e),
        }
    }
    Err(last.unwrap_or_else(|| io::Error::new(io::ErrorKind::NotFound, "no address")))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bus_faults_are_checked_before_anything_changes() {
        use crate::transport::Disturbance;
        assert_eq!(
            bus_disturbance("corrupt", Some(500.0), None),
            Ok(Disturbance::CorruptedFrames { per_million: 500 })
        );
        for (kind, value, on) in [
            ("corrupt", Some(1_000_001.0), None),
            ("corrupt", Some(-1.0), None),
            ("corrupt", Some(0.5), None),
            ("corrupt", Some(f64::NAN), None),
            ("corrupt", None, None),
            ("stuck-dominant", Some(0.0), None),
            ("stuck-dominant", Some(60_001.0), None),
            ("stuck-dominant", Some(f64::INFINITY), None),
            ("transceiver", None, None),
            ("lightning", Some(1.0), None),
        ] {
            let r = Request::BusFault {
                sensor: None,
                kind: kind.into(),
                value,
                on,
            };
            assert!(r.validate().is_err(), "{kind} {value:?}");
        }
        // On the runtime's bus: a paced bus refuses nothing valid, and a refusal changes nothing.
        let bus = crate::mem::MemBus::new();
        let port = bus.attach();
        assert!(crate::transport::Transport::disturb(
            &port,
            Disturbance::StuckDominant {
                duration: std::time::Duration::from_millis(1000)
            }
        )
        .is_ok());
        assert!(
            crate::transport::Transport::disturb(
                &port,
                Disturbance::StuckDominant {
                    duration: std::time::Duration::from_millis(1000)
                }
            )
            .is_err(),
            "one interval at a time"
        );
    }

    #[test]
    fn parses_documented_requests() {
        assert_eq!(
            parse_request(r#"{"cmd":"magnet","index":0,"mm":250.0}"#).unwrap(),
            Request::Magnet {
                sensor: None,
                index: 0,
                mm: Some(250.0),
                velocity: None
            }
        );
        assert!(matches!(
            parse_request(r#"{"cmd":"motion","spec":"sine:center=500,amp=200,period=4"}"#),
            Ok(Request::Motion { .. })
        ));
        assert!(matches!(
            parse_request(r#"{"cmd":"fault","name":"missing-magnet","on":true}"#),
            Ok(Request::Fault { on: true, .. })
        ));
        assert_eq!(
            parse_request(r#"{"cmd":"power-cycle"}"#).unwrap(),
            Request::PowerCycle { sensor: None }
        );
        assert_eq!(
            parse_request(r#"{"cmd":"state","sensor":1}"#).unwrap(),
            Request::State { sensor: Some(1) }
        );
        let e = parse_request(r#"{"cmd":"fly"}"#).unwrap_err();
        assert_eq!(e["ok"], false);
        assert!(e["error"].as_str().unwrap().contains("fly"), "{e}");
    }

    #[test]
    fn over_long_line_is_dropped_whole() {
        let mut input = vec![b'x'; 100];
        input.extend_from_slice(b"{\"cmd\":\"power-cycle\"}\n{\"cmd\":\"state\"}\n");
        // A tiny buffer so that the long line arrives in many pieces.
        let mut r = BufReader::with_capacity(7, &input[..]);
        assert_eq!(read_line_limited(&mut r, 64).unwrap(), Line::TooLong);
        assert_eq!(
            read_line_limited(&mut r, 64).unwrap(),
            Line::Text(b"{\"cmd\":\"state\"}".to_vec())
        );
        assert_eq!(read_line_limited(&mut r, 64).unwrap(), Line::Eof);
        // Exactly the limit is fine; a last line without newline counts.
        let mut r = BufReader::with_capacity(3, &b"abcd\nabcde"[..]);
        assert_eq!(
            read_line_limited(&mut r, 4).unwrap(),
            Line::Text(b"abcd".to_vec())
        );
        assert_eq!(read_line_limited(&mut r, 4).unwrap(), Line::TooLong);
        assert_eq!(read_line_limited(&mut r, 4).unwrap(), Line::Eof);
    }

    #[test]
    fn absurd_values_are_refused() {
        let bad = [
            r#"{"cmd":"magnet","index":0,"mm":1e300}"#,
            r#"{"cmd":"magnet","index":0,"mm":-1e300}"#,
            r#"{"cmd":"magnet","index":0,"mm":10,"velocity":-1}"#,
            r#"{"cmd":"ambient","celsius":-300}"#,
            r#"{"cmd":"ambient","celsius":1e300}"#,
            r#"{"cmd":"fault","name":"over-temperature","on":true,"value":-300}"#,
            r#"{"cmd":"fault","name":"supply-voltage","on":true,"value":1e300}"#,
            r#"{"cmd":"fault","name":"extra-magnet","on":true,"value":1e300}"#,
            r#"{"cmd":"fault","name":"bus-off","on":true,"value":3}"#,
            r#"{"cmd":"fault","name":"nonsense","on":true}"#,
            r#"{"cmd":"motion","spec":"static:1e300"}"#,
            r#"{"cmd":"motion","spec":"sine:center=1,amp=1,period=1e-300"}"#,
            r#"{"cmd":"motion","spec":"csv:x.csv"}"#,
        ];
        for line in bad {
            let req = parse_request(line).unwrap();
            assert!(req.validate().is_err(), "{line} accepted");
        }
        let good = [
            r#"{"cmd":"magnet","index":0,"mm":-20,"velocity":100}"#,
            r#"{"cmd":"ambient","celsius":-40}"#,
            r#"{"cmd":"fault","name":"over-temperature","on":true,"value":120}"#,
            r#"{"cmd":"fault","name":"supply-voltage","on":true,"value":9}"#,
            r#"{"cmd":"fault","name":"bus-off","on":false}"#,
            r#"{"cmd":"motion","spec":"sine:center=500,amp=200,period=4"}"#,
        ];
        for line in good {
            let req = parse_request(line).unwrap();
            assert_eq!(req.validate(), Ok(()), "{line}");
        }
    }

    /// A one-channel TH on an in-process bus, running, and its control handle.
    fn runtime(dir: &std::path::Path) -> (crate::RuntimeHandle, ControlHandle) {
        use crate::runtime::{state_file, SensorSetup};
        use canpos_sim::motion::{Profile, Profiles};
        let model = canpos_core::models::by_name("th").unwrap();
        let cfg = model.default_config;
        let setup = SensorSetup {
            name: "th-control".into(),
            model,
            cfg,
            spec: canpos_sim::SensorSpec::th(f64::from(cfg.stroke_mm), 1).unwrap(),
            seed: 1,
            ideal: true,
            motion: Box::new(Profiles(vec![Profile::Static { pos_mm: 250.0 }])),
            storage: crate::FileStorage::new(state_file(dir, "th", cfg.serial)),
        };
        let bus = crate::mem::MemBus::new();
        let mut rt = crate::runtime::Runtime::new(Box::new(bus.attach()), None);
        rt.add(setup);
        let h = rt.spawn().unwrap();
        let c = h.control();
        (h, c)
    }

    /// Every variant with every optional field given: what `canpos ctl`, a scenario and the
    /// dashboard send (they serialize these).
    fn every_request() -> Vec<Request> {
        vec![
            Request::Magnet {
                sensor: Some(0),
                index: 0,
                mm: Some(1.0),
                velocity: Some(2.0),
            },
            Request::Motion {
                sensor: Some(0),
                spec: "static:1".into(),
            },
            Request::Fault {
                sensor: Some(0),
                name: "stall".into(),
                on: true,
                value: Some(1.0),
                channel: Some(0),
            },
            Request::PowerCycle { sensor: Some(0) },
            Request::Ambient {
                sensor: Some(0),
                celsius: 20.0,
            },
            Request::State { sensor: Some(0) },
            Request::BusFault {
                sensor: Some(0),
                kind: "transceiver".into(),
                value: Some(1.0),
                on: Some(true),
            },
            Request::ResetLateness { sensor: Some(0) },
            Request::Nmt {
                sensor: Some(0),
                command: "start".into(),
            },
            Request::Timing {
                sensor: Some(0),
                sdo_delay_ms: Some(1.0),
                sdo_jitter_ms: Some(1.0),
                boot_delay_ms: Some(1.0),
                reset_boot_delay_ms: Some(1.0),
            },
        ]
    }

    /// Issue 35 item 9: `{"cmd":"magnet","index":0,"mm":700,"velocty":100}` answered ok and
    /// the magnet jumped. Every request with an unknown key is refused with the key's name.
    #[test]
    fn unknown_fields_are_refused_with_their_name() {
        let e = parse_request(r#"{"cmd":"magnet","index":0,"mm":700,"velocty":100}"#).unwrap_err();
        assert_eq!(e["ok"], false);
        assert_eq!(
            e["error"],
            "unknown field `velocty` in a `magnet` request, expected one of `sensor`, `index`, `mm`, `velocity`"
        );
        let reqs = every_request();
        assert_eq!(reqs.len(), COMMANDS.len(), "a request missing here");
        for req in reqs {
            let mut v = serde_json::to_value(&req).unwrap();
            let cmd = v["cmd"].as_str().unwrap().to_string();
            assert!(COMMANDS.contains(&cmd.as_str()), "{cmd} not in COMMANDS");
            // Serialized as the tools send it, it parses back the same.
            assert_eq!(parse_request(&v.to_string()).unwrap(), req, "{v}");
            // The key last, first, or a near miss of a real one (a unit variant used to take
            // anything).
            for key in ["velocty", "Sensor", "a`b, expected x"] {
                v[key] = json!(1);
                let e = parse_request(&v.to_string()).unwrap_err();
                let msg = e["error"].as_str().unwrap();
                assert!(
                    msg.starts_with(&format!("unknown field `{key}` in a `{cmd}` request")),
                    "{v}: {msg}"
                );
                v.as_object_mut().unwrap().remove(key);
            }
        }
        assert_eq!(
            parse_request(r#"{"cmd":"reset-lateness","x":1}"#).unwrap_err()["error"],
            "unknown field `x` in a `reset-lateness` request, expected `sensor`"
        );
        // docs/CONTROL.md: every request may carry `"sensor": N` (the Python client adds it to
        // each one), `reset-lateness` included.
        for req in every_request() {
            let mut v = serde_json::to_value(&req).unwrap();
            v["sensor"] = json!(1);
            assert!(parse_request(&v.to_string()).is_ok(), "{v}");
        }
        // Still refused with the cmd's name when the cmd comes last.
        let e = parse_request(r#"{"velocty":1,"cmd":"state"}"#).unwrap_err();
        assert!(
            e["error"]
                .as_str()
                .unwrap()
                .starts_with("unknown field `velocty` in a `state` request"),
            "{e}"
        );
        // Fields by position, with no names to check, are no request either.
        for line in [
            r#"["state"]"#,
            r#"["magnet",null,0,250.0,null]"#,
            " [\"reset-lateness\"]",
        ] {
            let e = parse_request(line).unwrap_err();
            assert!(
                e["error"].as_str().unwrap().contains("one JSON object"),
                "{line}: {e}"
            );
        }
    }

    /// Each request of docs/CONTROL.md's table parses as written there, and the table shows
    /// every command.
    #[test]
    fn the_documented_requests_parse() {
        let doc = include_str!("../../../docs/CONTROL.md");
        let mut seen = std::collections::BTreeSet::new();
        for row in doc.lines().filter(|l| l.starts_with("| `{\"cmd\":")) {
            let line = &row[3..row[3..].find('`').unwrap() + 3];
            let req =
                parse_request(line).unwrap_or_else(|e| panic!("docs/CONTROL.md: {line}: {e}"));
            let v = serde_json::to_value(&req).unwrap();
            seen.insert(v["cmd"].as_str().unwrap().to_string());
        }
        for cmd in COMMANDS {
            assert!(
                seen.contains(cmd),
                "docs/CONTROL.md's table shows no `{cmd}`"
            );
        }
    }

    /// The misspelt key of the issue, on a running sensor: refused, and the magnet stays.
    #[test]
    fn a_misspelt_key_moves_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let (h, c) = runtime(dir.path());
        let before = c.request(Request::State { sensor: None });
        assert_eq!(before["true_mm"], json!([250.0]), "{before}");
        let a = answer_line(r#"{"cmd":"magnet","index":0,"mm":700,"velocty":100}"#, &c);
        assert_eq!(a["ok"], false, "{a}");
        assert!(a["error"].as_str().unwrap().contains("`velocty`"), "{a}");
        // A request accepted after the refused one: once it shows, the refused one would
        // have shown too.
        let a = answer_line(r#"{"cmd":"ambient","celsius":21}"#, &c);
        assert_eq!(a["ok"], true, "{a}");
        let st = c.request(Request::State { sensor: None });
        assert_eq!(
            (&st["true_mm"], &st["ambient_c"]),
            (&json!([250.0]), &json!(21.0))
        );
        h.stop().unwrap();
    }

    /// Connects and sends `state`; the answer line (or the error that ended the read).
    fn ask_state(addr: SocketAddr, timeout: Duration) -> io::Result<Value> {
        call(addr, &Request::State { sensor: None }, timeout)
    }

    /// A control server on a free loopback port that closes connections idle for `idle`.
    fn serve_idle(c: ControlHandle, idle: Duration) -> ControlServer {
        serve_with(
            TcpListener::bind("127.0.0.1:0").unwrap(),
            c,
            ServeOptions {
                idle_timeout: idle,
                ..ServeOptions::default()
            },
        )
        .unwrap()
    }

    /// Issue 35 item 6: 32 idle connections used to lock the control interface out for good.
    /// Now a refused client hears so at once, idle connections are closed after the timeout,
    /// and a new client is answered within it.
    #[test]
    fn idle_connections_are_closed_and_a_new_client_gets_in() {
        let dir = tempfile::tempdir().unwrap();
        let (h, c) = runtime(dir.path());
        let idle = Duration::from_secs(2);
        let srv = serve_idle(c, idle);
        let addr = srv.local_addr();
        // 32 clients that ask once (so each is surely being served) and then say nothing.
        let mut quiet = Vec::new();
        for _ in 0..MAX_CONNECTIONS {
            let mut s = TcpStream::connect(addr).unwrap();
            s.write_all(b"{\"cmd\":\"state\"}\n").unwrap();
            let mut r = BufReader::new(s.try_clone().unwrap());
            let mut line = String::new();
            r.read_line(&mut line).unwrap();
            assert!(line.contains("\"ok\":true"), "{line}");
            quiet.push(r);
        }
        let start = std::time::Instant::now();
        // One more is refused with a reason, promptly (not after its own timeout).
        let a = ask_state(addr, Duration::from_secs(10)).unwrap();
        if start.elapsed() < idle {
            assert_eq!(a["ok"], false, "{a}");
            assert!(a["error"].as_str().unwrap().contains("too many"), "{a}");
        }
        // A client that tries again is answered once the idle ones are gone.
        let bound = idle + Duration::from_secs(20);
        let answered = loop {
            let a = ask_state(addr, Duration::from_secs(10)).unwrap();
            if a["ok"] == true {
                break start.elapsed();
            }
            assert!(
                start.elapsed() < bound,
                "still locked out after {bound:?}: {a}"
            );
            std::thread::sleep(Duration::from_millis(50));
        };
        assert!(answered < bound, "{answered:?}");
        // The idle ones were closed by the server: each reads the end of the stream.
        for r in &mut quiet {
            r.get_ref().set_read_timeout(Some(bound)).unwrap();
            let mut line = String::new();
            assert_eq!(r.read_line(&mut line).unwrap(), 0, "{line}");
        }
        h.stop().unwrap();
    }

    /// A client that sends requests and reads no answer: the server stops taking its requests
    /// once the socket buffers are full (no answers pile up in memory) and closes it after the
    /// timeout, while others are served.
    #[test]
    fn a_client_that_never_reads_is_held_back_and_closed() {
        let dir = tempfile::tempdir().unwrap();
        let (h, c) = runtime(dir.path());
        let idle = Duration::from_secs(1);
        let srv = serve_idle(c, idle);
        let addr = srv.local_addr();
        let mut s = TcpStream::connect(addr).unwrap();
        s.set_write_timeout(Some(Duration::from_millis(500)))
            .unwrap();
        // Each `state` answer is ~100 times its request. The socket buffers hold some MiB of
        // requests and answers; a server that took every request would take all 64 MiB (and
        // owe GiBs of answers).
        let chunk = b"{\"cmd\":\"state\"}\n".repeat(4096);
        let mut sent = 0usize;
        let start = std::time::Instant::now();
        let held_back = loop {
            match s.write(&chunk) {
                Ok(n) => sent += n,
                Err(e)
                    if matches!(
                        e.kind(),
                        io::ErrorKind::WouldBlock | io::ErrorKind::TimedOut
                    ) =>
                {
                    break true
                }
                // Closed by the server (after it stopped reading): held back too.
                Err(_) => break true,
            }
            if sent > 64 << 20 || start.elapsed() > Duration::from_secs(60) {
                break false;
            }
        };
        assert!(
            held_back,
            "the server took {sent} bytes of requests nobody reads answers to"
        );
        // Another client is served meanwhile, and the stuck one is closed after the timeout.
        assert_eq!(
            ask_state(addr, Duration::from_secs(10)).unwrap()["ok"],
            true
        );
        // Closed by the server: with requests of ours unread there, it resets the connection,
        // and our next write fails (reading instead would free the server to go on).
        let end = std::time::Instant::now() + Duration::from_secs(30);
        let closed = loop {
            match s.write(b"\n") {
                Err(e)
                    if !matches!(
                        e.kind(),
                        io::ErrorKind::WouldBlock | io::ErrorKind::TimedOut
                    ) =>
                {
                    break true
                }
                _ if std::time::Instant::now() > end => break false,
                _ => {}
            }
        };
        assert!(closed, "the stuck connection stays open");
        h.stop().unwrap();
    }

    #[test]
    fn fault_names_round_trip() {
        for f in Fault::ALL {
            assert_eq!(f.name().parse::<Fault>().unwrap(), f);
        }
        let e = "bogus".parse::<Fault>().unwrap_err();
        assert!(e.contains("missing-magnet"), "{e}");
    }
}
