//! The control interface's requests ([`Request`], [`Fault`]): their JSON form, their checks
//! and their parsing from a line ([`parse_request`]). Plain data, below the runtime that
//! carries them out.

use std::fmt;
use std::str::FromStr;

use serde::{Deserialize, Serialize};
use serde_json::{json, Value};

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
    /// Sets an input of a device served from an EDS (docs/EDS_DEVICE.md) as its own process
    /// would: a read-only object of the device profile area 0x6000–0x9FFF, checked against
    /// its type and range; a TPDO that maps it sees a change-of-state event. Numbers are JSON
    /// numbers or text (`"0x6000"`, `"-5"`); a BOOLEAN object also takes `true` / `false`.
    SetInput {
        /// Sensor index (0: the one device of a `--eds` process).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        sensor: Option<usize>,
        /// Object index, e.g. `24576` or `"0x6000"`.
        index: Value,
        /// Sub-index (default 0).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        sub: Option<Value>,
        /// The new value, a whole number of the object's type.
        value: Value,
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
            Request::SetInput {
                index, sub, value, ..
            } => {
                let sub = sub.as_ref().map_or("0".to_string(), Value::to_string);
                write!(f, "set-input {index}/{sub} = {value}")
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
            | Request::SetInput { sensor, .. }
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
            Request::SetInput { .. } => self.input_target().map(|_| ()),
            Request::BusFault {
                kind, value, on, ..
            } => bus_disturbance(kind, *value, *on).map(|_| ()),
            Request::PowerCycle { .. } | Request::State { .. } | Request::ResetLateness { .. } => {
                Ok(())
            }
        }
    }
}

impl Request {
    /// Index, sub-index and value of a [`Request::SetInput`], each a whole number in its
    /// range (the value in that of an `i64`: the device checks it against the object's type).
    pub fn input_target(&self) -> Result<(u16, u8, i64), String> {
        let Request::SetInput {
            index, sub, value, ..
        } = self
        else {
            return Err("not a set-input request".into());
        };
        let index = whole("index", index)?;
        let index = u16::try_from(index)
            .map_err(|_| format!("index {index} is not an object index (0 … 0xFFFF)"))?;
        let sub = match sub {
            Some(s) => whole("sub", s)?,
            None => 0,
        };
        let sub =
            u8::try_from(sub).map_err(|_| format!("sub {sub} is not a sub-index (0 … 255)"))?;
        Ok((index, sub, whole("value", value)?))
    }
}

/// A whole number given as a JSON number, as text (decimal or `0x` hex, with an optional
/// `-`), or as `true` / `false` (1 / 0).
fn whole(what: &str, v: &Value) -> Result<i64, String> {
    let bad = || format!("{what} {v} is not a whole number (decimal or 0x hex)");
    match v {
        Value::Bool(b) => Ok(i64::from(*b)),
        Value::Number(n) => n.as_i64().ok_or_else(bad),
        Value::String(s) => {
            let t = s.trim();
            let (neg, body) = match t.strip_prefix('-') {
                Some(b) => (true, b),
                None => (false, t),
            };
            let n = match body.strip_prefix("0x").or_else(|| body.strip_prefix("0X")) {
                Some(h) if !h.is_empty() && h.bytes().all(|b| b.is_ascii_hexdigit()) => {
                    i64::from_str_radix(h, 16).ok()
                }
                Some(_) => None,
                None if !body.is_empty() && body.bytes().all(|b| b.is_ascii_digit()) => {
                    body.parse().ok()
                }
                None => None,
            }
            .ok_or_else(bad)?;
            Ok(if neg { -n } else { n })
        }
        _ => Err(bad()),
    }
}

/// The disturbance a [`Request::BusFault`] asks for, with its parameters checked.
pub fn bus_disturbance(
    kind: &str,
    value: Option<f64>,
    on: Option<bool>,
) -> Result<crate::can::Disturbance, String> {
    use crate::can::Disturbance;
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
pub const COMMANDS: [&str; 11] = [
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
    "set-input",
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
